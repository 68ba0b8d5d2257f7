//! Our broad phase and Rapier's find the same pairs on identical boxes: the precondition
//! of the timing comparison in `benches/rapier.rs`. Both are also checked against brute
//! force, and our standalone broad phase against the `cpu` backend's own pair counts.
//!
//! The lattice set is made of the boundary cases: boxes sharing a centre (duplicate Morton
//! codes), and neighbours whose faces, edges or corners touch exactly (closed intervals
//! on both sides make those pairs).

#[path = "../common/rapier_side.rs"]
mod rapier_side;

use myriad_core::{Aabb, PhysicsConfig, ScenarioSpec};
use myriad_peers::{AabbSet, Lattice, OurBroadPhase, PairDiff, Pairs, unpack};
use myriad_physics::{BackendKind, TickConstants, create_cpu_backend};
use rapier_side::{RapierBroad, Skin};

fn assert_same(what: &str, expected: &Pairs, got: &Pairs) {
    for (kind, e, g) in [("dynamic", &expected.dynamic, &got.dynamic), ("static", &expected.statics, &got.statics)] {
        let d = PairDiff::of(e, g);
        assert!(
            d.is_empty(),
            "{what}, {kind} pairs: {} missing (first {:?}), {} extra (first {:?}) of {} expected",
            d.only_first.len(),
            d.only_first.first().map(|p| unpack(*p)),
            d.only_second.len(),
            d.only_second.first().map(|p| unpack(*p)),
            e.len()
        );
    }
}

fn ours(set: &AabbSet, bp: &mut OurBroadPhase) -> Pairs {
    let mut out = Pairs::default();
    bp.pairs(set, &mut out);
    out
}

fn rapier_pairs(r: &RapierBroad) -> Pairs {
    let (pairs, static_static) = r.pairs();
    assert_eq!(static_static, 0, "Rapier reported static-static pairs: the groups are wrong");
    pairs
}

/// Whether two boxes touch without their interiors overlapping on some axis.
fn touching(a: &Aabb, b: &Aabb) -> bool {
    a.overlaps(b) && (0..3).any(|i| a.max[i] == b.min[i] || b.max[i] == a.min[i])
}

#[test]
fn duplicates_and_touching_boxes_give_the_same_pairs_on_both_sides() {
    let mut set = Lattice { dynamic: 3_000, statics: 600, side: 14, seed: 7 }.build("lattice");
    let brute = Pairs::brute_force(&set.dynamic_aabbs(), &set.static_aabbs());
    let boxes = set.dynamic_aabbs();
    let touching_pairs = brute.dynamic.iter().filter(|p| {
        let (a, b) = unpack(**p);
        touching(&boxes[a as usize], &boxes[b as usize])
    });
    assert!(touching_pairs.count() > 1_000, "the set must exercise touching boxes");

    let mut bp = OurBroadPhase::default();
    bp.build_statics(&set);
    assert_same("ours, full build", &brute, &ours(&set, &mut bp));

    let mut rapier = RapierBroad::new(&set, Skin::Exact);
    rapier.check_aabbs(&set).unwrap();
    rapier.update_all();
    rapier.apply_events();
    assert_same("Rapier, full build", &brute, &rapier_pairs(&rapier));

    // Incremental: some boxes hop one lattice step (faces stay on the half-grid, so new
    // touching pairs appear and old ones end), the rest stay put.
    for tick in 0..3 {
        let mut centres = set.dynamic_centres.clone();
        for (i, c) in centres.iter_mut().enumerate() {
            if (i + tick) % 3 == 0 {
                c[i % 3] += if i % 2 == 0 { 1.0 } else { -1.0 };
            }
        }
        set.set_dynamic_centres(&centres);
        let brute = Pairs::brute_force(&set.dynamic_aabbs(), &set.static_aabbs());
        assert_same(&format!("ours, tick {tick}"), &brute, &ours(&set, &mut bp));
        assert!(rapier.move_dynamics(&set.dynamic_centres) > 0);
        rapier.update_moved();
        rapier.apply_events();
        assert_same(&format!("Rapier, tick {tick}"), &brute, &rapier_pairs(&rapier));
    }
}

#[test]
fn scenario_pairs_are_equal_and_match_the_backend() {
    let mut world = ScenarioSpec::custom(3).counts(3_000, 100, 600).map_size(96.0, 65).build().unwrap();
    let mut set = AabbSet::from_world("small", &world);

    let mut bp = OurBroadPhase::default();
    bp.build_statics(&set);
    let ours0 = ours(&set, &mut bp);
    assert!(ours0.dynamic.len() > 100 && ours0.statics.len() > 100, "a dense enough world: {ours0:?}");
    assert_same("ours vs brute force", &Pairs::brute_force(&set.dynamic_aabbs(), &set.static_aabbs()), &ours0);

    // The backend's first step finds its pairs before anything moves: the same boxes.
    let mut backend = create_cpu_backend(BackendKind::Cpu).unwrap();
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    let report = backend.step(&mut world, &k).unwrap();
    assert_eq!(
        (report.dynamic_pairs, report.static_pairs),
        (ours0.dynamic.len() as u64, ours0.statics.len() as u64),
        "the standalone broad phase must be the backend's"
    );

    let mut rapier = RapierBroad::new(&set, Skin::Exact);
    rapier.check_aabbs(&set).unwrap();
    rapier.update_all();
    rapier.apply_events();
    assert_same("Rapier, full build", &ours0, &rapier_pairs(&rapier));

    // Rapier as shipped pads its boxes: it finds at least our pairs.
    let mut loose = RapierBroad::new(&set, Skin::Default);
    loose.update_all();
    loose.apply_events();
    let padded = rapier_pairs(&loose);
    assert!(PairDiff::of(&ours0.dynamic, &padded.dynamic).only_first.is_empty());
    assert!(PairDiff::of(&ours0.statics, &padded.statics).only_first.is_empty());

    // Incremental, with the world's own motion.
    for tick in 0..4 {
        backend.step(&mut world, &k).unwrap();
        set.set_dynamic_centres(world.dynamics.positions());
        let expected = ours(&set, &mut bp);
        rapier.move_dynamics(&set.dynamic_centres);
        rapier.update_moved();
        rapier.apply_events();
        assert_same(&format!("Rapier, tick {tick}"), &expected, &rapier_pairs(&rapier));
    }
}
