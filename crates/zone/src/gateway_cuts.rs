//! What a gateway knows of its cluster's zone cuts, for its operators' map
//! ([`myriad_physics::Backend::zone_cuts`]): nothing is routed by them (intents go to
//! every zone, subscriptions are world cells), so they are only shown.
//!
//! A gateway starts from the layout every zone starts with (the cluster's zone count
//! over the world's bounds, [`ZoneLayout::for_count`]), and hears, read-only, what the
//! supervisor tells the zones: its starts (`myriad.c.control`, each with the cuts the
//! run starts from: the checkpoint's after a rollback) and its cut moves
//! (`myriad.c.cuts`, each with the tick it applies at). Both are signed; one that does
//! not fit the layout (another shape, moved edges, cuts not finite and ascending) is
//! refused and counted. The cuts shown for the zones' world of run `r` at tick `t` are
//! those of the newest move of `r` applied at or before `t`, else those `r` started
//! from, else the first layout.
//!
//! A gateway started after a move learns it from the supervisor's reminder of the run's
//! last applied move (every [`crate::rebalance::announce::REMIND_S`]). One started after
//! a rollback with no move since shows the first layout until the next move: starts are
//! not repeated, the zones' heartbeats carry only a digest of their cuts, and the gateway
//! may not hear heartbeats.

use std::collections::BTreeMap;

use myriad_core::Aabb;
use myriad_physics::ZoneCuts;

use crate::layout::ZoneLayout;
use crate::rebalance::{CutMove, Cuts};

/// Cut moves kept (older runs' and ticks' go first).
const MOVES_KEPT: usize = 64;
/// Starts kept (older runs' go first).
const STARTS_KEPT: usize = 8;

/// Why a start or cut move was refused (the gateway's `rejected` reason).
pub(crate) const REFUSED: &str = "cuts";

/// A gateway's record of the cuts (see the module docs).
#[derive(Debug)]
pub(crate) struct CutsBook {
    /// The layout every cluster of this many zones starts with, over this world; its
    /// reach and max step are 0: the gateway checks the cuts' shape and edges, the zones
    /// the rest (a gateway only draws them).
    first: ZoneLayout,
    /// The cuts each run started from, by run.
    starts: BTreeMap<u64, (u64, Cuts)>,
    /// The cut moves heard, by (run, apply_at).
    moves: BTreeMap<(u64, u64), Cuts>,
}

impl CutsBook {
    /// The book of a cluster of `zones` zones over `bounds`.
    pub(crate) fn new(bounds: &Aabb, zones: usize) -> Result<CutsBook, crate::ZoneError> {
        let k = u16::try_from(zones).map_err(|_| crate::ZoneError::Layout(format!("{zones} zones")))?;
        let first = ZoneLayout::for_count(bounds, k, 0.0, 0.0)?;
        Ok(CutsBook { first, starts: BTreeMap::new(), moves: BTreeMap::new() })
    }

    /// Whether `cuts` fit the cluster's layout: its shape and edges, finite and
    /// ascending ([`ZoneLayout::with_cuts`]).
    fn fits(&self, (xs, zs): &Cuts) -> bool {
        self.first.with_cuts(xs, zs).is_ok()
    }

    /// Takes the supervisor's start of `run` from `tick` on `cuts`; `Err` when they do
    /// not fit the layout.
    pub(crate) fn start(&mut self, run: u64, tick: u64, cuts: Cuts) -> Result<(), &'static str> {
        if !self.fits(&cuts) {
            return Err(REFUSED);
        }
        self.starts.insert(run, (tick, cuts));
        while self.starts.len() > STARTS_KEPT {
            self.starts.pop_first();
        }
        Ok(())
    }

    /// Takes a cut move of `run`: `Ok(true)` when it is new (the supervisor sends a
    /// move again until every zone holds it), `Err` when it does not fit the layout or
    /// applies no later than it was decided.
    pub(crate) fn cut_move(&mut self, run: u64, cut: CutMove) -> Result<bool, &'static str> {
        let cuts = (cut.xs, cut.zs);
        if cut.apply_at <= cut.decided_at || !self.fits(&cuts) {
            return Err(REFUSED);
        }
        let fresh = self.moves.insert((run, cut.apply_at), cuts.clone()).is_none_or(|was| was != cuts);
        while self.moves.len() > MOVES_KEPT {
            self.moves.pop_first();
        }
        Ok(fresh)
    }

    /// The cuts of the zones' world of `run` at `tick` (`None`: no world taken yet).
    pub(crate) fn in_force(&self, run: u64, tick: Option<u64>) -> ZoneCuts {
        let (since_tick, (xs, zs)) = tick
            .and_then(|t| self.moves.range((run, 0)..=(run, t)).next_back().map(|((_, at), c)| (*at, c)))
            .or_else(|| self.starts.get(&run).map(|(at, c)| (*at, c)))
            .map_or_else(
                || {
                    let (xs, zs) = self.first.cuts();
                    (0, (xs.to_vec(), zs.to_vec()))
                },
                |(at, (xs, zs))| (at, (xs.clone(), zs.clone())),
            );
        ZoneCuts { xs, zs, run, zone_tick: tick, since_tick }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::Vec3;

    fn book() -> CutsBook {
        CutsBook::new(&Aabb::new(Vec3::ZERO, Vec3::new(1024.0, 50.0, 512.0)), 4).unwrap()
    }

    fn mv(decided_at: u64, apply_at: u64, x: f32) -> CutMove {
        CutMove { decided_at, apply_at, xs: vec![0.0, x, 1024.0], zs: vec![0.0, 256.0, 512.0] }
    }

    #[test]
    fn the_first_layout_until_a_move_applies_then_the_move() {
        let mut b = book();
        let first = b.in_force(1, Some(10));
        assert_eq!((first.xs, first.zs, first.since_tick), (vec![0.0, 512.0, 1024.0], vec![0.0, 256.0, 512.0], 0));
        assert_eq!(b.cut_move(1, mv(60, 90, 530.0)), Ok(true));
        assert_eq!(b.cut_move(1, mv(60, 90, 530.0)), Ok(false), "a repeat is no news");
        assert_eq!(b.in_force(1, Some(89)).xs[1], 512.0, "held, not in force yet");
        let moved = b.in_force(1, Some(90));
        assert_eq!((moved.xs[1], moved.since_tick, moved.run, moved.zone_tick), (530.0, 90, 1, Some(90)));
        assert_eq!(b.in_force(1, None).xs[1], 512.0, "no world taken: the first layout");
        assert_eq!(b.cut_move(1, mv(200, 230, 500.0)), Ok(true));
        assert_eq!(b.in_force(1, Some(229)).xs[1], 530.0);
        assert_eq!(b.in_force(1, Some(5000)).xs[1], 500.0);
    }

    #[test]
    fn a_rollback_follows_the_start_of_the_new_run() {
        let mut b = book();
        b.cut_move(1, mv(60, 90, 530.0)).unwrap();
        b.cut_move(1, mv(200, 230, 500.0)).unwrap();
        // Rolled back to tick 150's checkpoint (on the first move's cuts): the second
        // move of run 1 is not in force in run 2.
        b.start(2, 150, (vec![0.0, 530.0, 1024.0], vec![0.0, 256.0, 512.0])).unwrap();
        let c = b.in_force(2, Some(240));
        assert_eq!((c.xs[1], c.since_tick), (530.0, 150));
        b.cut_move(2, mv(240, 270, 500.0)).unwrap();
        assert_eq!(b.in_force(2, Some(270)).xs[1], 500.0);
        assert_eq!(b.in_force(3, Some(270)).xs[1], 512.0, "a run whose start was not heard: the first layout");
    }

    #[test]
    fn cuts_that_do_not_fit_the_layout_are_refused_and_change_nothing() {
        let mut b = book();
        let bad = [
            mv(60, 90, 2000.0),
            mv(60, 90, f32::NAN),
            mv(90, 90, 530.0),
            CutMove { decided_at: 1, apply_at: 2, xs: vec![0.0, 1024.0], zs: vec![0.0, 256.0, 512.0] },
            CutMove { decided_at: 1, apply_at: 2, xs: vec![-5.0, 512.0, 1024.0], zs: vec![0.0, 256.0, 512.0] },
        ];
        for m in bad {
            assert_eq!(b.cut_move(1, m.clone()), Err(REFUSED), "{m:?}");
        }
        assert_eq!(b.start(2, 30, (vec![0.0, 512.0], vec![0.0, 512.0])), Err(REFUSED));
        assert_eq!(b.in_force(1, Some(1000)), book().in_force(1, Some(1000)));
        assert_eq!(b.in_force(2, Some(1000)).since_tick, 0);
    }

    /// A link that hands the gateway the given messages, then nothing.
    struct Scripted(std::collections::VecDeque<Vec<u8>>);

    impl crate::fabric::GatewayLink for Scripted {
        fn send_intents(&mut self, _: Vec<u8>) -> Result<(), crate::ZoneError> {
            Ok(())
        }
        fn send_subscription(&mut self, _: Vec<u8>) -> Result<(), crate::ZoneError> {
            Ok(())
        }
        fn recv_states(&mut self, _: std::time::Instant) -> Result<Option<Vec<u8>>, crate::ZoneError> {
            Ok(self.0.pop_front())
        }
    }

    #[test]
    fn a_gateway_takes_signed_starts_and_moves_and_counts_the_rest() {
        use crate::wire::{ClusterKey, Message, encode_control, encode_cut_move};
        use myriad_physics::Backend;
        let key = ClusterKey::random();
        let mut spec = myriad_core::ScenarioSpec::custom(3);
        (spec.dynamic, spec.users, spec.static_objects, spec.world_size, spec.terrain_samples) = (0, 0, 0, 64.0, 9);
        let mut world = spec.build().unwrap();
        let b = world.bounds;
        let (x0, x1) = (b.min.x, b.max.x);
        let zs = vec![b.min.z, b.max.z];
        let start = (vec![x0, (x0 + x1) / 2.0, x1], zs.clone());
        let moved = CutMove { decided_at: 10, apply_at: 40, xs: vec![x0, x0 + (x1 - x0) * 0.4, x1], zs: zs.clone() };
        let misfit = CutMove { decided_at: 10, apply_at: 40, xs: vec![x0, x1 + 1.0, x1 + 2.0], zs: zs.clone() };
        let messages = [
            encode_control(&key, &Message::Start { run: 1, tick: 0, cuts: start }).unwrap(),
            encode_cut_move(&key, 1, &moved).unwrap(),
            encode_cut_move(&key, 1, &moved).unwrap(),
            encode_cut_move(&key, 1, &misfit).unwrap(),
            encode_cut_move(&ClusterKey::random(), 1, &moved).unwrap(),
            encode_control(&key, &Message::Halt { run: 2 }).unwrap(),
        ];
        let cfg = crate::GatewayConfig {
            gateway: 0,
            key,
            zones: 2,
            wait: std::time::Duration::ZERO,
            refresh: 30,
            interest: None,
        };
        let link = Scripted(messages.into_iter().collect());
        let mut g = crate::ZonesBackend::new(cfg, Box::new(link)).unwrap();
        g.prepare(&mut world);
        assert_eq!(g.zone_cuts(), None, "nothing known before the first step");
        g.step(&mut world, &myriad_physics::TickConstants::default()).unwrap();
        let stats = g.stats();
        assert_eq!(stats.cut_news, 2, "the start and the move, once: {stats:?}");
        assert_eq!((stats.rejected.get(REFUSED), stats.rejected.get("tag")), (Some(&1), Some(&1)), "{stats:?}");
        assert_eq!(stats.rejected.values().sum::<u64>(), 2, "a halt is no refusal: {stats:?}");
        // No world of the zones taken yet: the layout every cluster starts with.
        let cuts = g.zone_cuts().unwrap();
        assert_eq!((cuts.xs, cuts.zs, cuts.zone_tick), (vec![x0, (x0 + x1) / 2.0, x1], zs, None));
    }

    #[test]
    fn the_book_stays_bounded() {
        let mut b = book();
        for t in 0..200u64 {
            b.cut_move(1, mv(t * 10, t * 10 + 5, 500.0 + (t % 20) as f32)).unwrap();
            b.start(t, t, (vec![0.0, 512.0, 1024.0], vec![0.0, 256.0, 512.0])).unwrap();
        }
        assert_eq!((b.moves.len(), b.starts.len()), (MOVES_KEPT, STARTS_KEPT));
        assert_eq!(b.in_force(1, Some(1995)).xs[1], 500.0 + 19.0, "the newest kept");
    }
}
