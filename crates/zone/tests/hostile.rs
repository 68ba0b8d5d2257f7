//! Bad input on the fabric: every real message is accompanied by malformed, truncated,
//! altered, replayed, delayed (out-of-order), misaddressed and forged ones. The zones
//! reject and count each kind and still end in one process's state hash.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use myriad_core::ActionScript;
use myriad_physics::TickConstants;
use myriad_zone::wire::{Message, decode, encode_border};
use myriad_zone::{ClusterKey, Fabric, MemoryFabric, RunOptions, ZoneError, ZoneId, ZoneLayout, pair_reach, run_zoned};

mod common;
use common::{clustered, cpu, single};

/// Forwards every message and adds hostile ones around it.
struct Hostile {
    inner: MemoryFabric,
    key: ClusterKey,
    zones: u16,
    /// Real messages held back, delivered again three sends later.
    delayed: VecDeque<(ZoneId, Vec<u8>)>,
    sent: u64,
}

impl Fabric for Hostile {
    fn send(&mut self, to: ZoneId, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.sent += 1;
        let stranger_key = ClusterKey::new(b"not the cluster's key at all!!").unwrap();
        let Ok(Message::Border(m)) = decode(&self.key, &bytes) else { panic!("a real border message") };
        let hostile = [
            bytes[..bytes.len() / 2].to_vec(), // truncated
            bytes.iter().enumerate().map(|(i, b)| if i == 40 { b ^ 1 } else { *b }).collect(), // altered
            vec![0x4d, 0x5a, 1, 1, 0, 0, 0],   // garbage
            bytes.clone(),                     // replayed
            encode_border(&stranger_key, &m).unwrap(), // forged
            encode_border(&self.key, &myriad_zone::wire::Border { tick: m.tick + 3, ..m.clone() }).unwrap(), // early
            encode_border(&self.key, &myriad_zone::wire::Border { run: m.run ^ 1, ..m.clone() }).unwrap(), // other run
            encode_border(&self.key, &myriad_zone::wire::Border { to: ZoneId((to.0 + 1) % self.zones), ..m.clone() })
                .unwrap(), // misrouted
        ];
        self.inner.send(to, bytes.clone())?;
        for h in hostile {
            self.inner.send(to, h)?;
        }
        // Out of order: an old real message arrives again, ticks later.
        self.delayed.push_back((to, bytes));
        if self.delayed.len() > 3 {
            let (to, old) = self.delayed.pop_front().expect("held");
            self.inner.send(to, old)?;
        }
        Ok(())
    }
    fn publish_states(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.inner.publish_states(bytes)
    }
    fn send_view(&mut self, gateway: u16, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.inner.send_view(gateway, bytes)
    }
    fn recv(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        self.inner.recv(deadline)
    }
    fn max_message(&self) -> usize {
        self.inner.max_message()
    }
    fn bytes(&self) -> (u64, u64) {
        self.inner.bytes()
    }
}

#[test]
fn hostile_messages_are_rejected_counted_and_never_applied() {
    let world = clustered(8, 4_000, 400, 1_500);
    let script = ActionScript::walkers(&world, 400, 120, 5);
    let k = TickConstants::default();
    let layout = ZoneLayout::for_count(&world.bounds, 4, pair_reach(&world), 2.0).unwrap();
    let opts = RunOptions::new(120, Duration::from_secs(60));
    let fabrics = MemoryFabric::mesh(4)
        .into_iter()
        .map(|inner| {
            Box::new(Hostile { inner, key: opts.key.clone(), zones: 4, delayed: VecDeque::new(), sent: 0 })
                as Box<dyn Fabric>
        })
        .collect();
    let run = run_zoned(&world, layout, &script, &k, &cpu, fabrics, &opts).unwrap();
    assert_eq!(run.state_hash, single(&world, 120, &script), "nothing hostile was applied");
    let mut rejected = std::collections::BTreeMap::new();
    for s in &run.stats {
        for (r, n) in &s.rejected {
            *rejected.entry(*r).or_insert(0) += n;
        }
    }
    eprintln!("rejected: {rejected:?}");
    for reason in ["truncated", "tag", "early", "run", "misrouted", "stale"] {
        assert!(rejected.get(reason).copied().unwrap_or(0) > 0, "{reason} counted: {rejected:?}");
    }
    // A replay is caught as `replayed` while its tick is open, as `stale` after.
    assert!(rejected.get("replayed").copied().unwrap_or(0) + rejected["stale"] > 0);
}
