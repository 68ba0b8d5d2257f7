//! Raw decoding of server message bodies (state updates included): the first byte
//! picks the packet kind, the rest is the body. Decoding must never panic; what decodes
//! must survive an encode/decode round trip, and the zero-copy view must agree with the
//! owned decoder.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{PacketKind, ServerMessage, StateUpdateView};

fuzz_target!(|data: &[u8]| {
    let Some((&kind, body)) = data.split_first() else { return };
    let Some(kind) = PacketKind::from_byte(kind) else { return };
    let decoded = ServerMessage::decode_body(kind, body);
    if kind == PacketKind::StateUpdate {
        let view = StateUpdateView::parse(body);
        assert_eq!(view.is_ok(), decoded.is_ok());
        if let (Ok(view), Ok(ServerMessage::StateUpdate(update))) = (view, &decoded) {
            assert!(view.records().eq(update.records.iter().copied()));
        }
    }
    if let Ok(msg) = decoded {
        let mut again = Vec::new();
        // A decoded body fitted one datagram, so its canonical encoding does too.
        msg.encode_body(&mut again).expect("re-encode");
        assert_eq!(ServerMessage::decode_body(kind, &again), Ok(msg));
    }
});
