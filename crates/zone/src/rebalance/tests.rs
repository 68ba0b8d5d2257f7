use std::sync::Arc;

use myriad_core::{Aabb, Vec3};

use super::*;

fn bounds() -> Aabb {
    Aabb::new(Vec3::ZERO, Vec3::new(400.0, 50.0, 400.0))
}

/// Reports of `layout`'s zones for objects at `points`, each owned by its zone.
fn reports(layout: &ZoneLayout, tick: u64, points: &[Vec3]) -> Vec<LoadReport> {
    layout
        .zones()
        .map(|z| {
            let mine = points.iter().copied().filter(|p| layout.zone_at(*p) == z);
            LoadReport::of(z, tick, mine, &bounds(), 256)
        })
        .collect()
}

/// `n` points spread evenly over x in `[x0, x1)` (z in the middle of the map).
fn band(n: usize, x0: f32, x1: f32) -> Vec<Vec3> {
    (0..n).map(|i| Vec3::new(x0 + (x1 - x0) * i as f32 / n as f32, 0.0, 100.0 + (i % 200) as f32)).collect()
}

#[test]
fn histograms_bin_and_split_counts() {
    let mut h = Histogram::new(0.0, 100.0, 10);
    for v in [-5.0, 0.0, 9.99, 10.0, 55.0, 100.0, 250.0, f32::NAN] {
        h.add(v);
    }
    assert_eq!(h.counts(), &[4, 1, 0, 0, 0, 1, 0, 0, 0, 2], "edges and outsiders go to the edge bins");
    assert_eq!(h.total(), 8);
    let mut even = Histogram::new(0.0, 100.0, 100);
    (0..1000).for_each(|i| even.add(i as f32 / 10.0));
    assert!((even.quantile(0.5).unwrap() - 50.0).abs() < 1.0);
    assert_eq!(Histogram::new(0.0, 1.0, 4).quantile(0.5), None);
    assert!(h.merge(&Histogram::new(0.0, 100.0, 11)).is_err());
}

#[test]
fn a_balanced_world_keeps_its_cuts() {
    let l = ZoneLayout::for_count(&bounds(), 4, 1.5, 2.0).unwrap();
    let mut p = CountPolicy::new(CountOptions::default(), &l);
    let points: Vec<Vec3> = (0..4000).map(|i| Vec3::new((i % 64) as f32 * 6.2, 0.0, (i / 64) as f32 * 6.3)).collect();
    assert_eq!(p.decide(0, &l, &reports(&l, 0, &points)).unwrap(), None);
}

#[test]
fn cuts_move_toward_the_crowd_at_most_max_move_and_rest() {
    let l = ZoneLayout::for_count(&bounds(), 2, 1.5, 2.0).unwrap();
    let mut p = CountPolicy::new(CountOptions::default(), &l);
    // 3,000 objects in x 20..100, 1,000 over the rest: the balanced cut is near 73.
    let mut points = band(3000, 20.0, 100.0);
    points.extend(band(1000, 100.0, 400.0));
    let (xs, zs) = p.decide(0, &l, &reports(&l, 0, &points)).unwrap().expect("unbalanced");
    assert_eq!(xs, vec![0.0, 180.0, 400.0], "a tenth of the zone width (20) toward the crowd");
    assert_eq!(zs, l.cuts().1, "one row: nothing to balance");
    let l = Arc::new(l.with_cuts(&xs, &zs).unwrap());
    // Within the cool-down (60 ticks) the cut rests.
    assert_eq!(p.decide(30, &l, &reports(&l, 30, &points)).unwrap(), None);
    let mut l = l;
    let mut tick = 60;
    while let Some((xs, zs)) = p.decide(tick, &l, &reports(&l, tick, &points)).unwrap() {
        l = Arc::new(l.with_cuts(&xs, &zs).unwrap());
        tick += 60;
        assert!(tick < 10_000);
    }
    // It stops once the columns are within the threshold (1.3 × the mean).
    let cut = l.cuts().0[1];
    let left = points.iter().filter(|p| p.x < cut).count() as f64;
    assert!(left <= 1.3 * 2000.0 && (70.0..=140.0).contains(&cut), "cut {cut}, {left} left of it");
}

#[test]
fn cuts_never_come_closer_than_the_margin() {
    // Three columns 20 wide with a margin of 13.5: everyone in the first 5 units.
    let b = Aabb::new(Vec3::ZERO, Vec3::new(60.0, 50.0, 20.0));
    let mut l = Arc::new(ZoneLayout::for_count(&b, 3, 11.5, 2.0).unwrap());
    let opts = CountOptions { cooldown: 0, max_move: Some(50.0), ..CountOptions::default() };
    let mut p = CountPolicy::new(opts, &l);
    let points: Vec<Vec3> = (0..900).map(|i| Vec3::new((i % 50) as f32 * 0.1, 0.0, 5.0)).collect();
    for t in 0..20 {
        let r: Vec<LoadReport> = l
            .zones()
            .map(|z| LoadReport::of(z, t, points.iter().copied().filter(|p| l.zone_at(*p) == z), &b, 64))
            .collect();
        if let Some((xs, zs)) = p.decide(t, &l, &r).unwrap() {
            l = Arc::new(l.with_cuts(&xs, &zs).expect("clamped to a valid layout"));
        }
    }
    let xs = l.cuts().0;
    assert!(xs.windows(2).all(|w| w[1] - w[0] > l.margin()), "{xs:?}");
    assert!(xs[1] < 20.0, "the first cut moved toward the crowd: {xs:?}");
}

#[test]
fn cut_moves_are_checked() {
    let l = ZoneLayout::for_count(&bounds(), 4, 1.5, 2.0).unwrap();
    let ok = CutMove { decided_at: 30, apply_at: 32, xs: vec![0.0, 150.0, 400.0], zs: vec![0.0, 210.0, 400.0] };
    let moved = ok.validate(&l).unwrap();
    assert_eq!(moved.zone_at(Vec3::new(160.0, 0.0, 205.0)), crate::ZoneId(1));
    for (bad, why) in [
        (CutMove { apply_at: 30, ..ok.clone() }, "later"),
        (CutMove { xs: vec![1.0, 150.0, 400.0], ..ok.clone() }, "bounds"),
        (CutMove { xs: vec![0.0, 398.0, 400.0], ..ok.clone() }, "fewer zones"),
        (CutMove { zs: vec![0.0, 100.0, 200.0, 400.0], ..ok.clone() }, "cuts"),
        (CutMove { xs: vec![0.0, f32::NAN, 400.0], ..ok.clone() }, "finite"),
        // Past where the next zone's far cut was: objects would jump a zone.
        (CutMove { xs: vec![0.0, 150.0, 250.0, 400.0], zs: vec![0.0, 400.0], ..ok.clone() }, "cuts for a layout"),
    ] {
        let e = bad.validate(&l).unwrap_err().to_string();
        assert!(e.contains(why), "{bad:?}: {e}");
    }
    let three = ZoneLayout::for_count(&bounds(), 3, 1.5, 2.0).unwrap();
    let far = CutMove { decided_at: 0, apply_at: 1, xs: vec![0.0, 270.0, 300.0, 400.0], zs: vec![0.0, 400.0] };
    assert!(three.with_cuts(&far.xs, &far.zs).is_ok(), "a valid layout");
    let e = far.validate(&three).unwrap_err().to_string();
    assert!(e.contains("not their owners' neighbours"), "{e}");
    let near = CutMove { xs: vec![0.0, 262.0, 300.0, 400.0], ..far };
    assert!(near.validate(&three).is_ok(), "more than the margin (3.5) short of the old 266.7");
}

#[test]
fn the_coordinator_answers_once_every_zone_reported() {
    let l = Arc::new(ZoneLayout::for_count(&bounds(), 2, 1.5, 2.0).unwrap());
    let mut points = band(3000, 20.0, 100.0);
    points.extend(band(1000, 100.0, 400.0));
    let mut c = Coordinator::new(RebalanceOptions::default(), l.clone(), 100).unwrap();
    let mut r = reports(&l, 0, &points);
    let second = r.pop().unwrap();
    assert!(c.offer(r.pop().unwrap()).unwrap().is_none(), "one of two");
    let d = c.offer(second).unwrap().expect("a decision");
    assert_eq!((d.decided_at, d.apply_at), (0, 2));
    assert!(d.layout.is_some());
    // Reports that cannot be: a zone twice, a tick that reports nothing, a zone not in
    // the layout.
    let r = reports(&l, 30, &points);
    c.offer(r[0].clone()).unwrap();
    assert!(c.offer(r[0].clone()).is_err());
    assert!(c.offer(LoadReport { tick: 31, ..r[1].clone() }).is_err());
    assert!(c.offer(LoadReport { zone: crate::ZoneId(7), ..r[1].clone() }).is_err());
    // The last decision must apply before the end (tick 100): 90 + 2 < 100 decides,
    // nothing after.
    let log = c.finish();
    assert_eq!(log.moves.len(), 1);
    assert_eq!(log.samples.len(), 1);
    assert!(RebalanceOptions { delay: 30, ..RebalanceOptions::default() }.validate().is_err());
    assert!(RebalanceOptions { delay: 0, ..RebalanceOptions::default() }.validate().is_err());
    assert!(RebalanceOptions::default().decides(90, 100) && !RebalanceOptions::default().decides(90, 92));
}

#[test]
fn forced_moves_that_are_invalid_are_refused_and_logged() {
    let l = Arc::new(ZoneLayout::for_count(&bounds(), 2, 1.5, 2.0).unwrap());
    let policy = Policy::Forced(vec![
        ForcedMove { at: 0, xs: vec![0.0, 1.0, 400.0], zs: vec![0.0, 400.0] },
        ForcedMove { at: 30, xs: vec![0.0, 250.0, 400.0], zs: vec![0.0, 400.0] },
    ]);
    let mut c = Coordinator::new(RebalanceOptions { policy, ..RebalanceOptions::default() }, l.clone(), 100).unwrap();
    let mut decisions = Vec::new();
    for t in [0, 30] {
        for r in reports(&l, t, &band(10, 0.0, 400.0)) {
            decisions.extend(c.offer(r).unwrap());
        }
    }
    assert!(decisions[0].layout.is_none() && decisions[1].layout.is_some());
    assert_eq!(c.layout().cuts().0, &[0.0, 250.0, 400.0]);
    let log = c.finish();
    assert_eq!((log.moves.len(), log.refused.len()), (1, 1));
    assert!(log.refused[0].1.contains("fewer zones"));
}
