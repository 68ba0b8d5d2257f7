//! Property tests on arbitrary worlds, lists (invalid slots, duplicates and broken
//! offsets included), configurations and links that lose datagrams and
//! acknowledgements, over several ticks of a moving world: the build never fails for
//! matching lengths, stays within `max_datagrams`, puts the own object in every
//! datagram once and sends only objects in view, every datagram opens and decodes, and
//! every record resolves at a client that acknowledges only the datagrams whose every
//! record resolved.

use std::collections::HashSet;

use myriad_interest::*;
use myriad_protocol::{
    AckTracker, Baselines, ClientSession, MAX_DATAGRAM, ServerMessage, ServerSession, SessionKeys, ShapeKind,
};
use proptest::prelude::*;

fn keys(i: u64) -> SessionKeys {
    SessionKeys { session_id: i, client_to_server: [1; 32], server_to_client: [2; 32] }
}

/// The client half: opens, resolves, acknowledges what resolved whole.
struct Client {
    session: ClientSession,
    baselines: Baselines,
    acks: AckTracker,
}

/// Replication settings, sane and odd: any of them may change what is sent, none may
/// break a datagram or name a state the client lacks. The budget stays a number of
/// bytes, 0 or more: a negative or NaN `budget_bytes_per_tick` makes `Replica::build`
/// panic (`budget.clamp(0.0, budget_bytes_per_tick)`, whose bounds are then out of
/// order); the server's configuration refuses such a `send_budget_kbps` first.
fn replication() -> impl Strategy<Value = ReplicationConfig> {
    (
        prop_oneof![Just(0.0f32), 0.0f32..100.0, 100.0f32..5000.0, Just(1e9)],
        prop_oneof![Just(f32::NAN), -10.0f32..200.0],
        prop_oneof![Just(f32::NAN), -2.0f32..40.0],
        prop_oneof![Just(f32::NAN), -2.0f32..40.0],
        prop_oneof![Just(f32::NAN), -10.0f32..400.0],
        prop_oneof![Just(f32::NAN), -2.0f32..40.0],
        0u64..10,
        prop_oneof![Just(f32::NAN), -2.0f32..40.0],
    )
        .prop_map(|c| ReplicationConfig {
            budget_bytes_per_tick: c.0,
            near: c.1,
            near_bound_ticks: c.2,
            far_bound_ticks: c.3,
            far: c.4,
            refresh_ticks: c.5,
            resend_ticks: c.6,
            max_wait_ticks: c.7,
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn datagrams_decode_resolve_and_keep_the_rules(
        positions in prop::collection::vec((-2000.0f32..2000.0, -50.0f32..50.0, -2000.0f32..2000.0), 1..400),
        lists in prop::collection::vec(prop::collection::vec(0u32..450, 0..350), 1..5),
        broken in prop::option::of((0usize..5, 0u32..800)),
        own in prop::collection::vec(0u32..450, 5),
        max_datagrams in 0usize..4,
        replication in replication(),
        ticks in 1u64..12,
        moving in 0u64..4,
        loss in prop::collection::vec(any::<bool>(), 64),
        ack_loss in prop::collection::vec(any::<bool>(), 16),
    ) {
        let n = positions.len();
        let ids: Vec<u64> = (0..n as u64).map(|i| i.wrapping_mul(0x9e37_79b9_7f4a_7c15)).collect();
        let kinds: Vec<ShapeKind> = (0..n).map(|i| [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule][i % 3]).collect();
        let mut pos: Vec<[f32; 3]> = positions.iter().map(|&(x, y, z)| [x, y, z]).collect();
        let mut offsets = vec![0u32];
        let mut objects = Vec::new();
        for l in &lists {
            objects.extend_from_slice(l);
            offsets.push(objects.len() as u32);
        }
        // A broken offset: out of order or past the end (that list is skipped).
        if let Some((i, v)) = broken {
            let i = i.min(offsets.len() - 1);
            offsets[i] = v;
        }
        let config = InterestConfig { max_datagrams, replication };
        let manager = InterestManager::new(config);
        let mut subs: Vec<Subscriber> = (0..lists.len())
            .map(|i| Subscriber::new(own[i], pos.get(own[i] as usize).copied().unwrap_or([0.0; 3]), ServerSession::new(&keys(i as u64)).sealer))
            .collect();
        let mut clients: Vec<Client> = (0..lists.len())
            .map(|i| Client { session: ClientSession::new(&keys(i as u64)), baselines: Baselines::default(), acks: AckTracker::default() })
            .collect();
        for tick in 1..=ticks {
            // Objects move a little, every `moving`-th one jumps far.
            for (i, p) in pos.iter_mut().enumerate() {
                let step = ((i as u64 * 7 + tick) % 5) as f32 * 0.3 - 0.6;
                p[0] += step;
                p[2] -= step * 0.5;
                if moving > 0 && (i as u64 + tick).is_multiple_of(moving * 3) {
                    p[1] += 700.0;
                }
            }
            let report = manager
                .build(TickInfo { tick, dilation_permille: 1000 }, &SoaObjects { ids: &ids, kinds: &kinds, positions: &pos }, AoiLists { offsets: &offsets, objects: &objects }, &mut subs)
                .unwrap();
            prop_assert_eq!(report.subscribers, lists.len());
            for (i, s) in subs.iter_mut().enumerate() {
                let client = &mut clients[i];
                prop_assert!(s.datagrams().len() <= max_datagrams.max(1));
                prop_assert_eq!(s.report().datagrams, s.datagrams().len());
                let own_id = ids.get(own[i] as usize).copied();
                let view: HashSet<u64> = offsets
                    .get(i..i + 2)
                    .and_then(|o| objects.get(o[0] as usize..o[1] as usize))
                    .unwrap_or(&[])
                    .iter()
                    .filter_map(|&s| ids.get(s as usize).copied())
                    .collect();
                let mut records = 0;
                for (j, d) in s.datagrams().iter().enumerate() {
                    prop_assert!(d.len() <= MAX_DATAGRAM);
                    // Each datagram decodes (the replay window would refuse a second
                    // open, so lost ones are opened on a twin session).
                    let lost = loss[(tick as usize * 3 + i * 5 + j) % loss.len()];
                    let mut d = d.to_vec();
                    let opened = if lost {
                        ClientSession::new(&keys(i as u64)).open(&mut d)
                    } else {
                        client.session.open(&mut d)
                    }
                    .unwrap();
                    let ServerMessage::StateUpdate(u) = opened.message else {
                        return Err(TestCaseError::fail("not a state update"));
                    };
                    prop_assert_eq!(u.header.tick, tick);
                    records += u.records.len();
                    // Ids strictly increasing: none twice in a datagram.
                    prop_assert!(u.records.windows(2).all(|w| w[0].id < w[1].id));
                    // Every datagram alone tells the player where it is.
                    if let Some(own_id) = own_id {
                        prop_assert_eq!(u.records.iter().filter(|r| r.id == own_id).count(), 1);
                    }
                    for r in &u.records {
                        prop_assert!(Some(r.id) == own_id || view.contains(&r.id), "object {} not in view", r.id);
                    }
                    if lost {
                        continue;
                    }
                    // Every record resolves: the server wrote deltas only against states
                    // the client acknowledged.
                    let mut states = Vec::new();
                    let failed = client.baselines.resolve_update(&u, &mut states);
                    prop_assert_eq!(failed, 0, "tick {}: {:?}", tick, u.records);
                    client.acks.record(opened.header.sequence);
                }
                prop_assert_eq!(records, s.report().records);
                if !ack_loss[(tick as usize + i) % ack_loss.len()]
                    && let Some(field) = client.acks.field()
                {
                    s.acknowledge(field);
                }
            }
        }
    }
}
