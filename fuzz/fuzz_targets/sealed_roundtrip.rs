//! Open-of-sealed-packet with authentic tags, so the fuzzer reaches the decoders behind
//! the cryptography: the input is a kind byte, a byte position and a body. The body is
//! framed and sealed with the right key; opening must succeed exactly when the body
//! decodes, and the same datagram with one bit flipped (at the chosen position) must be
//! rejected without changing the opener. The same datagram claiming sequence `u64::MAX`
//! must be rejected as malformed before any cryptography.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{
    ClientMessage, ClientSession, DecodeError, Direction, HEADER_LEN, MAX_BODY, OpenError, PacketKind, Sealer,
    ServerMessage, ServerSession, SessionKeys, TAG_LEN,
};

fuzz_target!(|data: &[u8]| {
    let [kind, flip_hi, flip_lo, body @ ..] = data else { return };
    let Some(kind) = PacketKind::from_byte(*kind) else { return };
    if body.len() > MAX_BODY {
        return;
    }
    let keys = SessionKeys { session_id: 77, client_to_server: [3; 32], server_to_client: [4; 32] };
    let (dir, key) = match kind.direction() {
        Direction::ClientToServer => (Direction::ClientToServer, keys.client_to_server),
        Direction::ServerToClient => (Direction::ServerToClient, keys.server_to_client),
    };
    let mut sealer = Sealer::new(keys.session_id, dir, &key);
    let mut frame = vec![0u8; HEADER_LEN];
    frame[1] = kind as u8;
    frame.extend_from_slice(body);
    frame.extend_from_slice(&[0; TAG_LEN]);
    sealer.seal_in_place(&mut frame).expect("valid frame seals");

    let flip = usize::from(u16::from_le_bytes([*flip_lo, *flip_hi])) % (frame.len() * 8);
    let mut damaged = frame.clone();
    damaged[flip / 8] ^= 1 << (flip % 8);
    let mut top = frame.clone();
    top[10..18].copy_from_slice(&u64::MAX.to_le_bytes());
    let reserved = Err(OpenError::Malformed(DecodeError::ReservedSequence));

    match dir {
        Direction::ClientToServer => {
            let mut s = ServerSession::new(&keys);
            assert!(s.open(&mut damaged).is_err());
            assert_eq!(s.open(&mut top).map(|_| ()), reserved);
            assert_eq!(s.opener.window().newest(), None);
            let expect = ClientMessage::decode_body(kind, body);
            let got = s.open(&mut frame).map(|o| o.message);
            assert_eq!(got.ok(), expect.ok());
        }
        Direction::ServerToClient => {
            let mut c = ClientSession::new(&keys);
            assert!(c.open(&mut damaged).is_err());
            assert_eq!(c.open(&mut top).map(|_| ()), reserved);
            assert_eq!(c.opener.window().newest(), None);
            let expect = ServerMessage::decode_body(kind, body);
            let got = c.open(&mut frame).map(|o| o.message);
            assert_eq!(got.ok(), expect.ok());
        }
    }
});
