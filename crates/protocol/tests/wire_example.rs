//! The worked example of `docs/protocol.md` (section 8). The page quotes these exact
//! bytes; this test rebuilds them with the library, checks that the page still contains
//! every block, and checks that a client reading them gets the states the page says, so
//! the page cannot drift from the code.

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

/// The body of an unsealed frame or the ciphertext of a sealed one.
fn body(datagram: &[u8]) -> &[u8] {
    &datagram[HEADER_LEN..datagram.len() - TAG_LEN]
}

fn pos(x: f32, y: f32, z: f32) -> QuantPos {
    QuantPos::from_f32([x, y, z])
}

/// The player's own object: id 7, a sphere.
const OWN: u64 = 7;
/// Another object: id 2^40, a capsule.
const OTHER: u64 = 1 << 40;

/// Every datagram of the example in the order they are sent, sealed, and the two
/// updates also as the packer left them (before sealing).
struct Example {
    action: Vec<u8>,
    update1_plain: Vec<u8>,
    update1: Vec<u8>,
    keep_alive: Vec<u8>,
    update2_plain: Vec<u8>,
    update2: Vec<u8>,
    keep_alive2: Vec<u8>,
    update3_plain: Vec<u8>,
    update3: Vec<u8>,
}

/// Packs one tick's update for the player (`own` pinned, `others` after) and returns it
/// unsealed and sealed with the server's next sequence number.
fn update(server: &mut ServerSession, header: UpdateHeader, own: DeltaRecord, others: &[DeltaRecord]) -> [Vec<u8>; 2] {
    let (mut batch, mut ends) = (DatagramBatch::new(), Vec::new());
    assert_eq!(pack_deltas(&header, Some(&own), others, 1, &mut batch, &mut ends), others.len());
    assert_eq!(batch.len(), 1, "the example's updates fit one datagram");
    let plain = batch.get(0).expect("one datagram").to_vec();
    server.sealer.seal_batch(&mut batch).expect("seal");
    [plain, batch.get(0).expect("one datagram").to_vec()]
}

/// Builds the example with the library, as a server and a client would.
fn example() -> Example {
    let keys = example_keys();
    let mut client = ClientSession::new(&keys);
    let mut server = ServerSession::new(&keys);

    // 8.1: the client's first Action (forward + jump, frame 42, sequence 0): it has
    // opened nothing yet, so its acknowledgement is "none".
    let mut action = Vec::new();
    let input =
        PlayerInput { mask: ActionMask::new(ActionMask::FORWARD | ActionMask::JUMP).unwrap(), client_frame: 42 };
    assert_eq!(client.seal(&ClientMessage::Action { input, acks: None }, &mut action), Ok(0));

    // 8.2: tick 1000, origin (100, 20, -50) units. The client holds nothing, so both
    // records are absolute: the own sphere at (101, 20.5, -50) is 64 steps away (Near),
    // the capsule at (1000, 0, 0) is 900 units away, beyond the i16 offset (Far).
    let origin = pos(100.0, 20.0, -50.0);
    let h1 = UpdateHeader { tick: 1000, dilation_permille: 1000, origin };
    let own1 = DeltaRecord::choose(OWN, ShapeKind::Sphere, pos(101.0, 20.5, -50.0), 1000, None, None);
    let other1 = DeltaRecord::choose(OTHER, ShapeKind::Capsule, pos(1000.0, 0.0, 0.0), 1000, None, None);
    let [update1_plain, update1] = update(&mut server, h1, own1, &[other1]);

    // 8.3: the client opened the update (server sequence 0) and every record resolved:
    // its next datagram, a KeepAlive (sequence 1), acknowledges it.
    let mut acks = AckTracker::default();
    acks.record(0);
    let mut keep_alive = Vec::new();
    assert_eq!(client.seal(&ClientMessage::KeepAlive { acks: acks.field() }, &mut keep_alive), Ok(1));

    // 8.4: tick 1003. The server holds the acknowledgement, so tick 1000's states are
    // baselines 3 ticks back: the sphere moved (+0.25, 0, -0.5) units (Delta), the
    // capsule did not (Same).
    let h2 = UpdateHeader { tick: 1003, ..h1 };
    let base = |r: &DeltaRecord| match r.state {
        RecordState::Absolute { pos, .. } => Some(Baseline { tick: 1000, pos }),
        _ => None,
    };
    let own2 = DeltaRecord::choose(OWN, ShapeKind::Sphere, pos(101.25, 20.5, -50.5), 1003, base(&own1), None);
    let other2 = DeltaRecord::choose(OTHER, ShapeKind::Capsule, pos(1000.0, 0.0, 0.0), 1003, base(&other1), None);
    assert_eq!(own2.state, RecordState::Delta { back: 3, d: [16, 0, -32] });
    assert_eq!(other2.state, RecordState::Same { back: 3 });
    let [update2_plain, update2] = update(&mut server, h2, own2, &[other2]);

    // 8.5: the client acknowledges both updates (server sequences 0 and 1) in its next
    // KeepAlive (sequence 2).
    acks.record(1);
    let mut keep_alive2 = Vec::new();
    assert_eq!(client.seal(&ClientMessage::KeepAlive { acks: acks.field() }, &mut keep_alive2), Ok(2));

    // 8.6: tick 1006. The sphere kept going: its state of tick 1003 moved on by its move
    // since tick 1000 is (6496, 1312, -3264); it is one step further on x (Predicted,
    // back 3, prior 3). The capsule is still where it was at tick 1003 (Same).
    let h3 = UpdateHeader { tick: 1006, ..h1 };
    let acked = |tick, pos| Some(Baseline { tick, pos });
    let own3 = DeltaRecord::choose(
        OWN,
        ShapeKind::Sphere,
        QuantPos::new(6497, 1312, -3264),
        1006,
        acked(1003, QuantPos::new(6480, 1312, -3232)),
        acked(1000, QuantPos::new(6464, 1312, -3200)),
    );
    let other3 = DeltaRecord::choose(
        OTHER,
        ShapeKind::Capsule,
        pos(1000.0, 0.0, 0.0),
        1006,
        acked(1003, pos(1000.0, 0.0, 0.0)),
        None,
    );
    assert_eq!(own3.state, RecordState::Predicted { back: 3, prior: 3, d: [1, 0, 0] });
    assert_eq!(other3.state, RecordState::Same { back: 3 });
    let [update3_plain, update3] = update(&mut server, h3, own3, &[other3]);

    Example { action, update1_plain, update1, keep_alive, update2_plain, update2, keep_alive2, update3_plain, update3 }
}

/// The Action's body in clear: mask, frame 42, acknowledgement "none".
fn action_body() -> Vec<u8> {
    let mut b = vec![0x11, 42, 0, 0, 0];
    AckField::encode(None, &mut b);
    b
}

/// The KeepAlive's body in clear: an acknowledgement of server sequence 0 alone.
fn keep_alive_body() -> Vec<u8> {
    let mut b = Vec::new();
    AckField::encode(AckField::new(0, 0), &mut b);
    b
}

/// The second KeepAlive's body in clear: server sequences 1 and 0.
fn keep_alive2_body() -> Vec<u8> {
    let mut b = Vec::new();
    AckField::encode(AckField::new(1, 1), &mut b);
    b
}

/// What the page quotes, in page order: (what, exact bytes).
fn blocks(e: &Example) -> Vec<(&'static str, String)> {
    vec![
        ("8.1 action body", hex(&action_body())),
        ("8.1 sealed action", hex(&e.action)),
        ("8.2 update 1 before sealing", hex(&e.update1_plain)),
        ("8.2 sealed update 1", hex(&e.update1)),
        ("8.3 keep-alive body", hex(&keep_alive_body())),
        ("8.3 sealed keep-alive", hex(&e.keep_alive)),
        ("8.4 update 2 before sealing", hex(&e.update2_plain)),
        ("8.4 sealed update 2", hex(&e.update2)),
        ("8.5 keep-alive body", hex(&keep_alive2_body())),
        ("8.5 sealed keep-alive", hex(&e.keep_alive2)),
        ("8.6 update 3 before sealing", hex(&e.update3_plain)),
        ("8.6 sealed update 3", hex(&e.update3)),
    ]
}

#[test]
fn documented_bytes_match() {
    let e = example();
    if std::env::var_os("PRINT_EXAMPLE").is_some() {
        for (what, block) in blocks(&e) {
            println!("{what}:\n{block}\n");
        }
    }
    for (what, block) in blocks(&e) {
        assert!(DOC.contains(&format!("```text\n{block}\n```")), "docs/protocol.md lacks {what}:\n{block}");
    }
    // The header lines the page annotates: version 3 in every datagram.
    for d in [&e.action, &e.update1, &e.keep_alive, &e.update2, &e.keep_alive2, &e.update3] {
        assert_eq!(d[0], 3);
    }
    // The sizes the page states.
    assert_eq!(
        [e.action.len(), e.update1.len(), e.keep_alive.len(), e.update2.len(), e.update3.len()],
        [55, 18 + 24 + 29 + 16, 50, 18 + 24 + 16 + 16, 18 + 24 + 15 + 16]
    );
}

/// The bodies the page quotes decode to what it says, and the sealed datagrams open to
/// them: the page's prose and the bytes agree.
#[test]
fn the_example_reads_as_the_page_says() {
    let e = example();
    let keys = example_keys();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);

    let mut d = e.action.clone();
    let opened = server.open(&mut d).expect("the action opens");
    assert_eq!(opened.header.sequence, 0);
    assert_eq!(opened.message.acks(), None);
    let ClientMessage::Action { input, .. } = opened.message else { panic!("not an action") };
    assert_eq!((input.client_frame, input.mask.bits()), (42, 0x11));
    // Opening decrypts in place: the body is the one the page shows in clear.
    assert_eq!(body(&d), action_body());
    assert_eq!(action_body()[5..], [0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0, 0, 0, 0, 0, 0, 0, 0]);

    let mut d = e.keep_alive.clone();
    let opened = server.open(&mut d).expect("the keep-alive opens");
    assert_eq!(opened.header.sequence, 1);
    let acks = opened.message.acks().expect("an acknowledgement");
    assert_eq!((acks.newest(), acks.bits()), (0, 0));
    assert!(acks.contains(0) && !acks.contains(1));
    assert_eq!(body(&d), keep_alive_body());
    assert_eq!(keep_alive_body(), [0; 16]);

    // The client resolves both updates against what it holds.
    let mut baselines = Baselines::default();
    let mut states = Vec::new();
    let updates =
        [(&e.update1, &e.update1_plain, 0), (&e.update2, &e.update2_plain, 1), (&e.update3, &e.update3_plain, 2)];
    for (sealed, plain, seq) in updates {
        let mut d = sealed.clone();
        let opened = client.open(&mut d).expect("the update opens");
        assert_eq!(opened.header.sequence, seq);
        let ServerMessage::StateUpdate(u) = opened.message else { panic!("not a state update") };
        assert_eq!(DeltaUpdate::decode_body(body(plain)).as_ref(), Ok(&u), "the plain body is what was sealed");
        assert_eq!(baselines.resolve_update(&u, &mut states), 0, "every record resolves");
    }
    let rec = |id, kind, p| StateRecord { id, kind, pos: p };
    assert_eq!(
        states,
        [
            rec(OWN, ShapeKind::Sphere, QuantPos::new(6464, 1312, -3200)),
            rec(OTHER, ShapeKind::Capsule, QuantPos::new(64_000, 0, 0)),
            rec(OWN, ShapeKind::Sphere, QuantPos::new(6480, 1312, -3232)),
            rec(OTHER, ShapeKind::Capsule, QuantPos::new(64_000, 0, 0)),
            rec(OWN, ShapeKind::Sphere, QuantPos::new(6497, 1312, -3264)),
            rec(OTHER, ShapeKind::Capsule, QuantPos::new(64_000, 0, 0)),
        ]
    );

    // A client that missed the first update cannot resolve the second: it skips both
    // records and does not acknowledge the datagram.
    let mut fresh = Baselines::default();
    let u = DeltaUpdate::decode_body(body(&e.update2_plain)).unwrap();
    let mut none = Vec::new();
    assert_eq!(fresh.resolve_update(&u, &mut none), 2);
    assert!(none.is_empty());
    // One that holds the sphere's state of tick 1003 but not its prior of tick 1000
    // skips the Predicted record (and resolves the capsule's Same).
    let mut partial = Baselines::default();
    let sphere = |pos| DeltaRecord { id: OWN, state: RecordState::Absolute { kind: ShapeKind::Sphere, pos } };
    let capsule = DeltaRecord {
        id: OTHER,
        state: RecordState::Absolute { kind: ShapeKind::Capsule, pos: QuantPos::new(64_000, 0, 0) },
    };
    partial.resolve(1003, &sphere(QuantPos::new(6480, 1312, -3232))).unwrap();
    partial.resolve(1003, &capsule).unwrap();
    let u = DeltaUpdate::decode_body(body(&e.update3_plain)).unwrap();
    assert_eq!(partial.resolve_update(&u, &mut none), 1);
    assert_eq!(none, [rec(OTHER, ShapeKind::Capsule, QuantPos::new(64_000, 0, 0))]);
}
