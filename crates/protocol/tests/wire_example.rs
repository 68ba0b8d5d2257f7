//! The worked example of `docs/protocol.md`. The page quotes these exact bytes; this
//! test rebuilds them and checks that the page still contains them, so the page cannot
//! drift from the code.

use myriad_protocol::*;

const DOC: &str = include_str!("../../../docs/protocol.md");

fn example_keys() -> SessionKeys {
    let mut client_to_server = [0u8; 32];
    let mut server_to_client = [0u8; 32];
    for i in 0..32 {
        client_to_server[i] = i as u8;
        server_to_client[i] = 0x80 + i as u8;
    }
    SessionKeys { session_id: 0x0102_0304_0506_0708, client_to_server, server_to_client }
}

fn hex(bytes: &[u8]) -> String {
    // 16 bytes per line, space separated, as on the page.
    bytes
        .chunks(16)
        .map(|c| c.iter().map(|b| format!("{b:02x}")).collect::<Vec<_>>().join(" "))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The client's first packet: an Action (forward + jump) for frame 42, sequence 0.
fn action_packet() -> Vec<u8> {
    let mut client = ClientSession::new(&example_keys());
    let mut out = Vec::new();
    let msg = ClientMessage::Action(PlayerInput {
        mask: ActionMask::new(ActionMask::FORWARD | ActionMask::JUMP).expect("valid mask"),
        client_frame: 42,
    });
    client.seal(&msg, &mut out).expect("seal");
    out
}

/// The server's first packet: tick 1000, real time, origin (100, 20, -50) units, one
/// compact record (id 7, sphere at (101, 20.5, -50)) and one extended record (id 2^40,
/// capsule at (1000, 0, 0): 900 units away, beyond the i16 offset range).
fn update_packet() -> (Vec<u8>, Vec<u8>) {
    let header = UpdateHeader { tick: 1000, dilation_permille: 1000, origin: QuantPos::from_f32([100.0, 20.0, -50.0]) };
    let records = [
        StateRecord { id: 7, kind: ShapeKind::Sphere, pos: QuantPos::from_f32([101.0, 20.5, -50.0]) },
        StateRecord { id: 1 << 40, kind: ShapeKind::Capsule, pos: QuantPos::from_f32([1000.0, 0.0, 0.0]) },
    ];
    let mut batch = DatagramBatch::new();
    assert_eq!(pack_updates(&header, &records, 1, &mut batch), 2);
    let plain = batch.get(0).expect("one datagram").to_vec();
    let mut server = ServerSession::new(&example_keys());
    server.sealer.seal_batch(&mut batch).expect("seal");
    let sealed = batch.get(0).expect("one datagram").to_vec();
    // And the client decodes it back.
    let mut client = ClientSession::new(&example_keys());
    let mut d = sealed.clone();
    let ServerMessage::StateUpdate(u) = client.open(&mut d).expect("open").message else {
        panic!("not a state update");
    };
    assert_eq!(u.records, records);
    (plain, sealed)
}

const ACTION_SEALED: &str = "\
01 01 08 07 06 05 04 03 02 01 00 00 00 00 00 00\n\
00 00 09 92 42 31 ad b0 3e 93 38 e1 86 3e 25 db\n\
86 72 79 b9 76 e0 98";
const UPDATE_PLAIN: &str = "\
01 81 00 00 00 00 00 00 00 00 00 00 00 00 00 00\n\
00 00 e8 03 00 00 00 00 00 00 e8 03 00 19 00 00\n\
00 05 00 00 80 f3 ff ff 07 00 00 00 00 00 00 00\n\
02 00 00 00 00 00 40 00 20 00 00 00 0b 00 00 00\n\
00 00 00 00 00 01 00 00 00 fa 00 00 00 00 00 00\n\
00 00 00 00 00 00 00 00 00 00 00 00 00 00 00 00\n\
00 00 00 00";
const UPDATE_SEALED: &str = "\
01 81 08 07 06 05 04 03 02 01 00 00 00 00 00 00\n\
00 00 69 ac 3f 97 66 a7 1a 00 97 15 fd 7c e3 32\n\
dc c1 b7 87 7a ae 5e a2 6e 79 44 41 3c be b0 b6\n\
23 e3 01 2b 3a ab a9 3d cb b2 09 10 d4 cf 7c 77\n\
b8 67 fb dc 5f d8 62 f5 65 1d fc da b0 a9 9b 4b\n\
4c 2d 19 81 f4 c2 73 b2 05 62 fd 1c 4e be cc 39\n\
9c 44 d5 ec";

#[test]
fn documented_bytes_match() {
    let action = hex(&action_packet());
    let (plain, sealed) = update_packet();
    let (plain, sealed) = (hex(&plain), hex(&sealed));
    assert_eq!(action, ACTION_SEALED);
    assert_eq!(plain, UPDATE_PLAIN);
    assert_eq!(sealed, UPDATE_SEALED);
    for block in [ACTION_SEALED, UPDATE_PLAIN, UPDATE_SEALED] {
        assert!(DOC.contains(block), "docs/protocol.md lacks:\n{block}");
    }
}
