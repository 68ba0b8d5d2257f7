//! Raw decoding of server message bodies (delta state updates included): the first byte
//! picks the packet kind, the rest is the body. Decoding must never panic; the zero-copy
//! view must agree with the owned decoders; what decodes must survive an encode/decode
//! round trip, re-encoding to the same bytes except for the form of absolute records.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{DeltaUpdate, DeltaUpdateView, PacketKind, RecordState, ServerMessage};

fuzz_target!(|data: &[u8]| {
    let Some((&kind, body)) = data.split_first() else { return };
    let Some(kind) = PacketKind::from_byte(kind) else { return };
    let decoded = ServerMessage::decode_body(kind, body);
    if kind == PacketKind::StateUpdate {
        // The view, the owned update and the message decoder accept the same bodies,
        // for the same reason, and read the same records.
        let view = DeltaUpdateView::parse(body);
        let owned = DeltaUpdate::decode_body(body);
        assert_eq!(view.as_ref().err(), decoded.as_ref().err());
        assert_eq!(owned.clone().map(ServerMessage::StateUpdate), decoded);
        if let (Ok(view), Ok(update)) = (view, &owned) {
            assert_eq!(view.header(), update.header);
            assert_eq!(view.len(), update.records.len());
            assert_eq!(view.is_empty(), update.records.is_empty());
            assert!(view.records().eq(update.records.iter().copied()));
            assert!(update.records.windows(2).all(|w| w[0].id < w[1].id), "ids strictly increase");
        }
    }
    let Ok(msg) = decoded else { return };
    let mut again = Vec::new();
    // A decoded body fitted one datagram, so its canonical encoding does too.
    msg.encode_body(&mut again).expect("re-encode");
    assert_eq!(ServerMessage::decode_body(kind, &again).as_ref(), Ok(&msg));
    // The canonical encoding is a fixed point.
    let mut third = Vec::new();
    ServerMessage::decode_body(kind, &again).expect("decodes").encode_body(&mut third).expect("re-encode");
    assert_eq!(third, again);
    // Every field has one encoding (varints included), except that an absolute record
    // is written `Near` whenever the origin reaches it: a body may carry it `Far` (or a
    // `Near` offset that saturates), which re-encodes shorter or differently. Without
    // absolute records, the bytes come back exactly.
    let absolute = match &msg {
        ServerMessage::StateUpdate(u) => u.records.iter().any(|r| matches!(r.state, RecordState::Absolute { .. })),
        _ => false,
    };
    if absolute {
        assert!(again.len() <= body.len());
    } else {
        assert_eq!(again, body);
    }
});
