//! Property tests on arbitrary worlds, lists (invalid slots and broken offsets
//! included) and configurations: the build never fails for matching lengths, respects
//! the budget, puts the own object first, sends only objects in view, and every
//! datagram opens.

use myriad_interest::*;
use myriad_protocol::{ClientSession, MAX_DATAGRAM, ServerMessage, ServerSession, SessionKeys, ShapeKind};
use proptest::prelude::*;

fn keys(i: u64) -> SessionKeys {
    SessionKeys { session_id: i, client_to_server: [1; 32], server_to_client: [2; 32] }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn builds_respect_budget_and_view(
        positions in prop::collection::vec((-2000.0f32..2000.0, -50.0f32..50.0, -2000.0f32..2000.0), 1..400),
        lists in prop::collection::vec(prop::collection::vec(0u32..450, 0..350), 1..5),
        own in prop::collection::vec(0u32..450, 5),
        max_datagrams in 0usize..4,
        near_share in prop_oneof![Just(f32::NAN), -1.0f32..2.0],
        ticks in 1u64..4,
    ) {
        let n = positions.len();
        let ids: Vec<u64> = (0..n as u64).map(|i| i.wrapping_mul(0x9e37_79b9_7f4a_7c15)).collect();
        let kinds: Vec<ShapeKind> = (0..n).map(|i| [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule][i % 3]).collect();
        let pos: Vec<[f32; 3]> = positions.iter().map(|&(x, y, z)| [x, y, z]).collect();
        let soa = SoaObjects { ids: &ids, kinds: &kinds, positions: &pos };
        let mut offsets = vec![0u32];
        let mut objects = Vec::new();
        for l in &lists {
            objects.extend_from_slice(l);
            offsets.push(objects.len() as u32);
        }
        let config = InterestConfig { max_datagrams, near_share };
        let manager = InterestManager::new(config);
        let mut subs: Vec<Subscriber> = (0..lists.len())
            .map(|i| Subscriber::new(own[i], [0.0, 0.0, 0.0], ServerSession::new(&keys(i as u64)).sealer))
            .collect();
        let mut clients: Vec<ClientSession> = (0..lists.len()).map(|i| ClientSession::new(&keys(i as u64))).collect();
        for tick in 0..ticks {
            let report = manager
                .build(TickInfo { tick, dilation_permille: 1000 }, &soa, AoiLists { offsets: &offsets, objects: &objects }, &mut subs)
                .unwrap();
            prop_assert_eq!(report.subscribers, lists.len());
            for (i, s) in subs.iter().enumerate() {
                prop_assert!(s.datagrams().len() <= max_datagrams.max(1));
                let own_id = ids.get(own[i] as usize).copied();
                let mut records = Vec::new();
                for d in s.datagrams().iter() {
                    prop_assert!(d.len() <= MAX_DATAGRAM);
                    let mut d = d.to_vec();
                    match clients[i].open(&mut d).unwrap().message {
                        ServerMessage::StateUpdate(u) => {
                            // Every datagram alone tells the player where it is.
                            if let Some(own_id) = own_id {
                                prop_assert_eq!(u.records.first().map(|r| r.id), Some(own_id));
                            }
                            records.extend(u.records)
                        }
                        other => prop_assert!(false, "unexpected {:?}", other),
                    }
                }
                prop_assert_eq!(records.len(), s.report().records);
                let view: Vec<u64> = lists[i].iter().filter_map(|&s| ids.get(s as usize).copied()).collect();
                let others: Vec<u64> = records.iter().map(|r| r.id).filter(|&id| Some(id) != own_id).collect();
                for id in &others {
                    prop_assert!(view.contains(id));
                }
                // Nothing is left out while there is room for it.
                let distinct = {
                    let mut v = view.clone();
                    v.retain(|&id| Some(id) != own_id);
                    v.sort_unstable();
                    v.dedup();
                    v.len()
                };
                // Over budget, the datagrams are all used unless everything was sent
                // (possible when duplicate slots inflated the estimate).
                if s.report().over_budget {
                    prop_assert!(s.datagrams().len() == max_datagrams.max(1) || others.len() == distinct);
                } else {
                    prop_assert!(others.len() >= distinct);
                }
            }
        }
    }
}
