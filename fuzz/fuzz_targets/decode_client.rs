//! Raw decoding of client message bodies: the first byte picks the packet kind, the
//! rest is the body. Decoding must never panic, and whatever decodes must re-encode to
//! the same bytes (one encoding per message).
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{ClientMessage, PacketKind};

fuzz_target!(|data: &[u8]| {
    let Some((&kind, body)) = data.split_first() else { return };
    let Some(kind) = PacketKind::from_byte(kind) else { return };
    if let Ok(msg) = ClientMessage::decode_body(kind, body) {
        let mut again = Vec::new();
        msg.encode_body(&mut again);
        assert_eq!(again, body);
        assert_eq!(msg.kind(), kind);
    }
});
