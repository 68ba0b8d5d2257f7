use super::*;
use myriad_core::{Aabb, Vec3};

fn layout() -> Arc<ZoneLayout> {
    let b = Aabb::new(Vec3::ZERO, Vec3::new(400.0, 50.0, 400.0));
    Arc::new(ZoneLayout::for_count(&b, 2, 1.5, 2.0).unwrap())
}

/// A heartbeat of a running zone at `tick` on cuts `cuts`, holding the move of `pending`.
fn beat(tick: u64, cuts: u64, pending: u64, step_us: u32) -> Option<ZoneBeat> {
    Some(ZoneBeat { tick, state: ZoneState::Running, load: Load { step_us, owned: 100, cuts, pending } })
}

fn forced(at: u64, x: f32) -> ForcedMove {
    ForcedMove { at, xs: vec![0.0, x, 400.0], zs: vec![0.0, 400.0] }
}

#[test]
fn a_forced_move_is_sent_until_held_and_applied_by_every_zone() {
    let l = layout();
    let old = cuts_digest(l.cuts().0, l.cuts().1);
    let new = cuts_digest(&[0.0, 230.0, 400.0], &[0.0, 400.0]);
    let mut a = Announcer::new(LiveOptions::new(30, LivePolicy::Forced(vec![forced(60, 230.0)])), l, 10_000).unwrap();
    // Not before every zone is heard in the epoch.
    assert_eq!(a.observe(0.0, &[beat(5, old, 0, 1), None]), vec![]);
    let out = a.observe(0.1, &[beat(5, old, 0, 1), beat(6, old, 0, 1)]);
    let [Announcement::Send { cut, first: true }] = &out[..] else { panic!("{out:?}") };
    assert_eq!((cut.decided_at, cut.apply_at), (60, 90));
    // Zone 1 does not hold it yet: sent again, but no sooner than `resend_s`.
    assert_eq!(a.observe(0.2, &[beat(20, old, 90, 1), beat(20, old, 0, 1)]), vec![]);
    let again = a.observe(0.35, &[beat(25, old, 90, 1), beat(25, old, 0, 1)]);
    assert!(matches!(&again[..], [Announcement::Send { first: false, .. }]), "{again:?}");
    // Both hold it: quiet until both stepped past tick 90 on the new cuts.
    assert_eq!(a.observe(1.0, &[beat(40, old, 90, 1), beat(41, old, 90, 1)]), vec![]);
    assert_eq!(a.observe(2.0, &[beat(91, new, 0, 1), beat(90, old, 90, 1)]), vec![]);
    let out = a.observe(2.1, &[beat(95, new, 0, 1), beat(94, new, 0, 1)]);
    assert!(matches!(&out[..], [Announcement::Applied(c)] if c.apply_at == 90), "{out:?}");
    assert_eq!(a.counts(), MoveCounts { announced: 1, applied: 1, refused: 0 });
    assert_eq!(a.cuts().0, vec![0.0, 230.0, 400.0]);
    // Then a reminder of it every REMIND_S (for gateways that started after it), and
    // none after a rollback, whose start carries the cuts.
    let beats = [beat(120, new, 0, 1), beat(121, new, 0, 1)];
    assert_eq!(a.observe(2.1 + REMIND_S - 0.1, &beats), vec![]);
    // (A little past: 2.1 + 2.0 - 2.1 is under 2.0 in f64.)
    let out = a.observe(2.1 + REMIND_S + 0.01, &beats);
    assert!(matches!(&out[..], [Announcement::Send { cut, first: false }] if cut.apply_at == 90), "{out:?}");
    assert_eq!(a.observe(2.1 + REMIND_S + 0.5, &beats), vec![]);
    a.restart(100, &(vec![0.0, 230.0, 400.0], vec![0.0, 400.0])).unwrap();
    assert_eq!(a.observe(2.1 + 3.0 * REMIND_S, &[beat(101, new, 0, 1), beat(101, new, 0, 1)]), vec![]);
    assert_eq!(a.counts(), MoveCounts { announced: 1, applied: 1, refused: 0 });
}

#[test]
fn a_zone_past_the_tick_on_the_old_cuts_is_a_divergence_and_a_rollback_announces_a_forced_move_again() {
    let l = layout();
    let old = cuts_digest(l.cuts().0, l.cuts().1);
    let moves = vec![forced(60, 230.0), forced(600, 250.0)];
    let mut a = Announcer::new(LiveOptions::new(30, LivePolicy::Forced(moves)), l, 10_000).unwrap();
    assert_eq!(a.observe(0.0, &[beat(5, old, 0, 1), beat(5, old, 0, 1)]).len(), 1);
    // Zone 1 stepped tick 90 without the move (it came too late, or was refused).
    let out = a.observe(0.5, &[beat(92, cuts_digest(&[0.0, 230.0, 400.0], &[0.0, 400.0]), 0, 1), beat(91, old, 0, 1)]);
    assert!(
        matches!(&out[..], [Announcement::Diverged(m)] if m.contains("zone 1") && m.contains("tick 90")),
        "{out:?}"
    );
    // A zone on cuts nobody announced is caught the same way.
    let out = a.observe(0.6, &[beat(50, 12345, 0, 1), beat(50, old, 90, 1)]);
    assert!(matches!(&out[..], [Announcement::Diverged(_)]), "{out:?}");
    // The rollback to tick 60 restarts on the checkpoint's (old) cuts: the forced move,
    // whose tick is still to come, is announced again; then the next one, for its tick.
    a.restart(60, &(vec![0.0, 200.0, 400.0], vec![0.0, 400.0])).unwrap();
    let out = a.observe(0.9, &[beat(61, old, 0, 1), beat(61, old, 0, 1)]);
    assert!(matches!(&out[..], [Announcement::Send { cut, first: true }] if cut.apply_at == 90), "{out:?}");
    let new = cuts_digest(&[0.0, 230.0, 400.0], &[0.0, 400.0]);
    // Applied; the next forced move follows at once.
    let out = a.observe(0.95, &[beat(91, new, 0, 1), beat(91, new, 0, 1)]);
    assert!(
        matches!(&out[..], [Announcement::Applied(_), Announcement::Send { cut, .. }] if cut.apply_at == 630),
        "{out:?}"
    );
    // A rollback to after the first move's tick keeps it (the checkpoint's cuts hold it)
    // and announces the second again.
    a.restart(120, &(vec![0.0, 230.0, 400.0], vec![0.0, 400.0])).unwrap();
    let out = a.observe(1.0, &[beat(121, new, 0, 1), beat(121, new, 0, 1)]);
    assert!(matches!(&out[..], [Announcement::Send { cut, first: true }] if cut.apply_at == 630), "{out:?}");
}

#[test]
fn moves_the_zones_passed_or_that_break_the_layout_are_refused() {
    let l = layout();
    let old = cuts_digest(l.cuts().0, l.cuts().1);
    // Tick 60 + 30 is passed; a zone 2 units wide is narrower than reach + max step.
    let moves = vec![forced(60, 230.0), forced(100, 2.0)];
    let mut a = Announcer::new(LiveOptions::new(30, LivePolicy::Forced(moves)), l.clone(), 10_000).unwrap();
    let out = a.observe(0.0, &[beat(95, old, 0, 1), beat(95, old, 0, 1)]);
    assert!(matches!(&out[..], [Announcement::Refused { decided_at: 60, reason }] if reason.contains("too late")));
    let out = a.observe(0.1, &[beat(96, old, 0, 1), beat(96, old, 0, 1)]);
    assert!(matches!(&out[..], [Announcement::Refused { decided_at: 100, .. }]), "{out:?}");
    assert_eq!(a.counts(), MoveCounts { announced: 0, applied: 0, refused: 2 });
    assert!(Announcer::new(LiveOptions::new(0, LivePolicy::Forced(vec![])), l, 10_000).is_err(), "a lead of 0");
}

#[test]
fn a_slow_zone_moves_the_cut_toward_it_from_its_step_times() {
    let l = layout();
    let old = cuts_digest(l.cuts().0, l.cuts().1);
    let opts = StepTimeOptions { sustain_s: 1.0, ..StepTimeOptions::default() };
    let mut a = Announcer::new(LiveOptions::new(30, LivePolicy::StepTime(opts)), l, 10_000).unwrap();
    // Zone 0 takes 30 ms a tick, zone 1 10 ms: over 1.15 × the mean for a second.
    assert_eq!(a.observe(0.0, &[beat(10, old, 0, 30_000), beat(10, old, 0, 10_000)]), vec![]);
    let out = a.observe(1.0, &[beat(40, old, 0, 30_000), beat(41, old, 0, 10_000)]);
    let [Announcement::Send { cut, first: true }] = &out[..] else { panic!("{out:?}") };
    assert_eq!((cut.decided_at, cut.apply_at), (41, 71), "the highest tick reported + the lead");
    assert!(cut.xs[1] < 200.0, "zone 0 shrinks: {:?}", cut.xs);
}
