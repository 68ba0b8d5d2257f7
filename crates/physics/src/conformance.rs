//! Behaviour every backend must show, written once: the worlds and checks that the CPU
//! backends' tests (`tests/backends.rs`) and the CUDA backends' (`crates/cuda/tests`)
//! both run, so a new backend is held to exactly the same contract.
//!
//! Each check takes the backends under test and, where it compares results, a reference
//! backend whose world the others must reproduce bit for bit. A check panics with a
//! message naming the backend when the contract is broken: these are test helpers.

use myriad_core::rng::hash3;
use myriad_core::{Aabb, Action, ObjectKind, Placement, ScenarioSpec, Shape, Vec3, World};

use crate::{AoiResults, Backend, StepReport, TickConstants};

/// A small, crowded world: contacts of every pair kind happen from the first tick, at an
/// origin far from zero (so nothing relies on a world that starts at the origin).
pub fn crowded(seed: u64, placement: Placement) -> World {
    let mut spec = ScenarioSpec::custom(seed);
    spec.name = "test".into();
    spec.dynamic = 1_500;
    spec.users = 150;
    spec.static_objects = 150;
    spec.world_size = 96.0;
    spec.origin = Vec3::new(-2_000.0, 40.0, 7_000.0);
    spec.terrain_samples = 97;
    spec.max_height = 6.0;
    spec.placement = placement;
    spec.build().expect("the crowded test world builds")
}

/// The world of the pinned golden hash (`tests/golden.rs`): 900 dynamic objects,
/// 120 static objects, an 80-unit map at an odd origin.
pub fn golden_world() -> World {
    let mut spec = ScenarioSpec::custom(2024);
    spec.dynamic = 900;
    spec.users = 90;
    spec.static_objects = 120;
    spec.world_size = 80.0;
    spec.origin = Vec3::new(123.5, -7.0, -4096.0);
    spec.terrain_samples = 81;
    spec.max_height = 5.0;
    spec.build().expect("the golden test world builds")
}

/// Steps `ticks` times with the default constants.
pub fn run(backend: &mut dyn Backend, world: &mut World, ticks: usize) -> Vec<StepReport> {
    let k = TickConstants::default();
    (0..ticks).map(|_| backend.step(world, &k).expect("a step succeeds")).collect()
}

/// 150 ticks of a crowded world: every backend ends with the reference's world, bit for
/// bit, having found the same pairs and contacts tick by tick.
pub fn same_world_bit_for_bit(reference: &mut dyn Backend, others: &mut [Box<dyn Backend>]) {
    let start = crowded(11, Placement::Uniform);
    let mut want = start.clone();
    let want_reports = run(reference, &mut want, 150);
    assert_ne!(want.state_hash(), start.state_hash(), "the world must have moved");
    let contacts: u64 = want_reports.iter().map(|r| r.dynamic_contacts + r.static_contacts).sum();
    assert!(contacts > 1_000, "the test needs collisions, had {contacts}");
    for b in others {
        let mut w = start.clone();
        let reports = run(b.as_mut(), &mut w, 150);
        assert_eq!(w.state_hash(), want.state_hash(), "{} differs from {}", b.kind(), reference.kind());
        for (t, (a, c)) in reports.iter().zip(&want_reports).enumerate() {
            assert_eq!(
                (a.static_pairs, a.dynamic_pairs, a.static_contacts, a.dynamic_contacts),
                (c.static_pairs, c.dynamic_pairs, c.static_contacts, c.dynamic_contacts),
                "{} tick {t}",
                b.kind()
            );
        }
    }
}

/// A server's pattern: between steps the host sets actions (every tick, on a third of
/// the users), and now and then teleports an object or spawns and removes one. Every
/// backend must see each change and end with the reference's world, bit for bit —
/// including a backend that copies only the actions when nothing else changed.
pub fn host_changes_between_steps_are_seen(reference: &mut dyn Backend, others: &mut [Box<dyn Backend>]) {
    let start = crowded(21, Placement::Uniform);
    let k = TickConstants::default();
    let drive = |b: &mut dyn Backend| {
        let mut w = start.clone();
        let ids: Vec<_> = w.dynamics.ids().to_vec();
        for t in 0..90u64 {
            for (i, id) in ids.iter().enumerate().filter(|(i, _)| (*i as u64 + t).is_multiple_of(3)) {
                let bits = (hash3(7, i as u64, t / 10) & 0x1f) as u8;
                w.dynamics.set_action(*id, Action::from_bits_truncate(bits));
            }
            if t % 25 == 7 {
                let id = ids[(t as usize * 13) % ids.len()];
                let c = w.bounds.center();
                w.dynamics.teleport(id, Vec3::new(c.x, c.y + 5.0, c.z));
            }
            if t == 40 {
                let extra = w.dynamics.spawn(Shape::Sphere { radius: 0.5 }, w.bounds.center(), ObjectKind::User);
                let extra = extra.expect("spawn");
                b.step(&mut w, &k).expect("a step succeeds");
                w.dynamics.despawn(extra);
            }
            b.step(&mut w, &k).expect("a step succeeds");
        }
        w
    };
    let want = drive(reference);
    for b in others {
        let got = drive(b.as_mut());
        assert_eq!(got.state_hash(), want.state_hash(), "{} misses host changes between steps", b.kind());
    }
}

/// Steps that refit the dynamic tree instead of building it end in the reference's world.
/// For refit counts 0, 1, 3 and 8, a crowded world stepped 30 ticks (objects falling and
/// pushing each other, so a refit tree's nodes loosen), with new actions every tick, a
/// spawn at tick 11 and a teleport at tick 19, equals `reference`'s after every tick. A
/// backend that keeps a dynamic tree ([`Backend::tree_age`]) must build it on schedule:
/// after `refits` refits, and at once after the spawn (the objects changed) and the
/// teleport (an object far from its leaf's place), but not after new actions.
pub fn refit_steps_agree(reference: &mut dyn Backend, others: &mut [Box<dyn Backend>]) {
    let k = TickConstants::default();
    let edit = |w: &mut World, tick: u32| {
        let ids: Vec<_> = w.dynamics.ids().to_vec();
        for (i, id) in ids.iter().enumerate().filter(|(i, _)| (*i as u32 + tick).is_multiple_of(4)) {
            let bits = (hash3(3, i as u64, u64::from(tick) / 5) & 0x1f) as u8;
            w.dynamics.set_action(*id, Action::from_bits_truncate(bits));
        }
        let c = w.bounds.center();
        match tick {
            11 => {
                let at = c + Vec3::new(3.0, 6.0, -2.0);
                w.dynamics.spawn(Shape::Sphere { radius: 0.5 }, at, ObjectKind::Npc).expect("spawn");
                true
            }
            19 => {
                assert!(w.dynamics.teleport(ids[5], Vec3::new(c.x - 20.0, c.y + 8.0, c.z + 15.0)));
                true
            }
            _ => false,
        }
    };
    for b in others {
        let name = b.kind();
        for refits in [0, 1, 3, 8] {
            b.set_tree_refits(refits);
            let mut want = crowded(7, Placement::Uniform);
            let mut got = want.clone();
            let mut age: Option<u32> = None;
            for tick in 0..30u32 {
                edit(&mut want, tick);
                let rebuild = edit(&mut got, tick);
                reference.step(&mut want, &k).expect("a step succeeds");
                b.step(&mut got, &k).expect("a step succeeds");
                assert_eq!(got.state_hash(), want.state_hash(), "{name}, refits {refits}: tick {tick}");
                age = match age {
                    Some(a) if a < refits && !rebuild => Some(a + 1),
                    _ => Some(0),
                };
                if let Some(got_age) = b.tree_age() {
                    assert_eq!(Some(got_age), age, "{name}, refits {refits}: the tree's age after tick {tick}");
                }
            }
        }
    }
}

/// 300 objects spawned at one point (duplicate Morton codes, coincident centres): every
/// backend gives the reference's world and the pile spreads out.
pub fn stacked_duplicates_agree_and_separate(reference: &mut dyn Backend, others: &mut [Box<dyn Backend>]) {
    let mut base = crowded(13, Placement::Uniform);
    let spot = base.dynamics.positions()[0] + Vec3::new(0.0, 3.0, 0.0);
    for i in 0..300 {
        let shape = match i % 3 {
            0 => Shape::Sphere { radius: 0.5 },
            1 => Shape::Box { half: Vec3::splat(0.5) },
            _ => Shape::Capsule { radius: 0.4, half_height: 0.5 },
        };
        base.dynamics.spawn(shape, spot, ObjectKind::Npc).expect("spawn");
    }
    let spread_out = |w: &World, who: &dyn Backend| {
        // No two of the spawned objects share a position any more.
        let n = w.dynamics.len();
        let mut pts: Vec<[u32; 3]> =
            w.dynamics.positions()[n - 300..].iter().map(|p| p.to_array().map(f32::to_bits)).collect();
        pts.sort_unstable();
        pts.dedup();
        assert_eq!(pts.len(), 300, "{}", who.kind());
    };
    let mut want = base.clone();
    run(reference, &mut want, 60);
    spread_out(&want, reference);
    for b in others {
        let mut w = base.clone();
        run(b.as_mut(), &mut w, 60);
        assert_eq!(w.state_hash(), want.state_hash(), "{}", b.kind());
        spread_out(&w, b.as_ref());
    }
}

/// 300 ticks of a crowded world: positions finite, everything inside the bounds and
/// on or above the terrain.
pub fn physics_stays_sane(backends: &mut [Box<dyn Backend>]) {
    for b in backends {
        let mut w = crowded(14, Placement::Uniform);
        run(b.as_mut(), &mut w, 300);
        let d = &w.dynamics;
        for s in 0..d.len() {
            let p = d.positions()[s];
            assert!(p.is_finite() && d.prev_positions()[s].is_finite(), "{} slot {s}: {p}", b.kind());
            let bb = d.aabb(s);
            assert!(
                w.bounds.contains_point(bb.min) && w.bounds.contains_point(bb.max),
                "{} slot {s} outside: {bb:?}",
                b.kind()
            );
            // The floor is enforced on the centre (height + half extent), exactly.
            let floor = w.terrain.height_at(p.x, p.z) + d.half_extents()[s].y;
            assert!(p.y >= floor, "{} slot {s} under the terrain: {} < {floor}", b.kind(), p.y);
        }
    }
}

/// A sparse grid of users holding no action falls, settles and then does not creep.
pub fn resting_objects_stay_at_rest(backends: &mut [Box<dyn Backend>]) {
    for b in backends {
        let mut w = crowded(15, Placement::Uniform);
        let ids: Vec<_> = w.dynamics.ids().to_vec();
        for id in ids {
            w.dynamics.despawn(id);
        }
        for i in 0..10 {
            for j in 0..10 {
                let (x, z) = (w.bounds.min.x + 8.0 + 8.0 * i as f32, w.bounds.min.z + 8.0 + 8.0 * j as f32);
                let shape = [
                    Shape::Sphere { radius: 0.5 },
                    Shape::Box { half: Vec3::splat(0.5) },
                    Shape::Capsule { radius: 0.4, half_height: 0.5 },
                ][(i + j) % 3];
                let y = w.terrain.height_at(x, z) + shape.half_extents().y + 0.3;
                w.dynamics.spawn(shape, Vec3::new(x, y, z), ObjectKind::User).expect("spawn");
            }
        }
        run(b.as_mut(), &mut w, 60); // fall and settle
        let settled: Vec<Vec3> = w.dynamics.positions().to_vec();
        run(b.as_mut(), &mut w, 200);
        for (s, (a, now)) in settled.iter().zip(w.dynamics.positions()).enumerate() {
            // Statics may hold some of them up; either way nothing creeps.
            assert!((*a - *now).length() < 1e-3, "{}: slot {s} moved from {a} to {now}", b.kind());
        }
    }
}

/// A sphere and a box spawned overlapping are pushed a full contact apart.
pub fn overlapping_objects_are_pushed_apart(backends: &mut [Box<dyn Backend>]) {
    for b in backends {
        let mut w = crowded(16, Placement::Uniform);
        let ids: Vec<_> = w.dynamics.ids().to_vec();
        for id in ids {
            w.dynamics.despawn(id);
        }
        let c = w.bounds.center();
        let y = w.terrain.height_at(c.x, c.z) + 0.5;
        let a = w.dynamics.spawn(Shape::Sphere { radius: 0.5 }, Vec3::new(c.x, y, c.z), ObjectKind::User).expect("a");
        let bx = w
            .dynamics
            .spawn(Shape::Box { half: Vec3::splat(0.5) }, Vec3::new(c.x + 0.6, y, c.z), ObjectKind::User)
            .expect("b");
        run(b.as_mut(), &mut w, 30);
        let pa = w.dynamics.positions()[w.dynamics.slot(a).expect("a lives")];
        let pb = w.dynamics.positions()[w.dynamics.slot(bx).expect("b lives")];
        assert!(pb.x - pa.x >= 0.99, "{}: still overlapping, {pa} {pb}", b.kind());
    }
}

/// AOI answers equal brute force before any step (build), after steps (refit), after
/// the object set changed (rebuild), for an empty batch, after a teleport between steps,
/// and with objects and boxes where a spatial index's edges are: objects far outside the
/// world's bounds on every side, one object much wider than the rest, boxes reaching
/// past the bounds, a box as thin as an object, and a box turned inside out (which
/// overlaps nothing).
pub fn area_of_interest_matches_brute_force(backends: &mut [Box<dyn Backend>]) {
    for b in backends {
        let mut w = crowded(17, Placement::Clustered { hotspots: 2, fraction: 0.5, spread: 6.0 });
        let c = w.bounds.center();
        let mut queries: Vec<Aabb> = (0..40)
            .map(|i| {
                let centre = c + Vec3::new((i % 7) as f32 * 9.0 - 30.0, 0.0, (i % 5) as f32 * 11.0 - 25.0);
                Aabb::from_center_half(centre, Vec3::new(8.0 + i as f32, 100.0, 6.0))
            })
            .collect();
        let far = [Vec3::new(500.0, 0.0, 3.0), Vec3::new(-700.0, 5.0, -2.0), Vec3::new(1.0, 0.0, 900.0)];
        queries.extend(far.iter().map(|&d| Aabb::from_center_half(c + d, Vec3::new(4.0, 100.0, 4.0))));
        queries.push(Aabb::from_center_half(c, Vec3::splat(2_000.0)));
        queries.push(Aabb::from_center_half(c + Vec3::new(-47.0, 0.0, 0.0), Vec3::new(0.25, 100.0, 60.0)));
        queries.push(Aabb::new(c + Vec3::splat(5.0), c - Vec3::splat(5.0)));
        let check = |w: &World, b: &mut dyn Backend| {
            let mut out = AoiResults::default();
            b.query_aoi(w, &queries, &mut out).expect("AOI query");
            assert_eq!(out.len(), queries.len());
            let mut total = 0;
            for (q, bx) in queries.iter().enumerate() {
                let want: Vec<u32> =
                    (0..w.dynamics.len() as u32).filter(|&s| w.dynamics.aabb(s as usize).overlaps(bx)).collect();
                assert_eq!(out.get(q), want.as_slice(), "{} query {q}", b.kind());
                total += want.len();
            }
            assert!(total > 500, "queries must see objects, saw {total}");
        };
        check(&w, b.as_mut());
        run(b.as_mut(), &mut w, 10);
        check(&w, b.as_mut());
        w.dynamics.spawn(Shape::Sphere { radius: 1.0 }, c, ObjectKind::User).expect("spawn");
        let first = w.dynamics.ids()[0];
        w.dynamics.despawn(first);
        check(&w, b.as_mut());
        let mut out = AoiResults::default();
        b.query_aoi(&w, &[], &mut out).expect("empty AOI batch");
        assert!(out.is_empty(), "{}", b.kind());
        let id = w.dynamics.ids()[5];
        w.dynamics.teleport(id, c);
        check(&w, b.as_mut());
        for (k, &d) in far.iter().enumerate() {
            let id = w.dynamics.ids()[10 + k];
            assert!(w.dynamics.teleport(id, c + d));
        }
        let wide = Shape::Box { half: Vec3::new(30.0, 1.0, 25.0) };
        w.dynamics.spawn(wide, c + Vec3::new(-60.0, 0.0, 40.0), ObjectKind::Npc).expect("spawn");
        check(&w, b.as_mut());
        for q in &queries[40..43] {
            let mut out = AoiResults::default();
            b.query_aoi(&w, std::slice::from_ref(q), &mut out).expect("AOI query");
            assert_eq!(out.get(0).len(), 1, "{}: the far object at {q:?}", b.kind());
        }
    }
}

/// A backend moved from one world to the next answers for the new one: the first world
/// is used, then dropped, and the second, built the same way from another seed, has the
/// same generation counters and often the addresses the first one had. Caches keyed on
/// either would answer from the first world; the worlds' stamps tell them apart. The AOI
/// answer and one step are compared with `reference`'s, which sees only the second.
pub fn a_moved_backend_answers_for_its_new_world(reference: &mut dyn Backend, others: &mut [Box<dyn Backend>]) {
    let build = |seed| {
        let mut spec = ScenarioSpec::custom(seed);
        spec.dynamic = 800;
        spec.users = 20;
        spec.static_objects = 200;
        spec.world_size = 128.0;
        spec.terrain_samples = 65;
        spec.build().expect("the moved-backend world")
    };
    let k = TickConstants::default();
    let mut want_world = build(2);
    let first = build(1);
    assert_eq!(first.dynamics.generation(), want_world.dynamics.generation());
    assert_eq!(first.statics.generation(), want_world.statics.generation());
    assert_ne!(first.state_hash(), want_world.state_hash());
    drop(first);
    // Boxes across the map, from the ground up.
    let (lo, hi) = (want_world.bounds.min, want_world.bounds.max);
    let boxes: Vec<Aabb> = (0..16)
        .map(|i| {
            let t = (i as f32 + 0.5) / 16.0;
            Aabb::from_center_half(lo + (hi - lo) * Vec3::new(t, 0.5, 1.0 - t), (hi - lo) * 0.2)
        })
        .collect();
    let mut want = AoiResults::default();
    reference.query_aoi(&want_world, &boxes, &mut want).expect("AOI query");
    assert!(want.objects.len() > 100, "the boxes must see objects");
    reference.step(&mut want_world, &k).expect("step");
    for b in others {
        {
            let mut first = build(1);
            let mut on_first = AoiResults::default();
            b.query_aoi(&first, &boxes, &mut on_first).expect("AOI query");
            assert_ne!(on_first, want, "{}: the worlds must differ where the boxes look", b.kind());
            b.step(&mut first, &k).expect("step");
        }
        let mut world = build(2);
        let mut got = AoiResults::default();
        b.query_aoi(&world, &boxes, &mut got).expect("AOI query");
        assert_eq!(got, want, "{}: AOI answered from the first world", b.kind());
        b.step(&mut world, &k).expect("step");
        assert_eq!(world.state_hash(), want_world.state_hash(), "{}: stepped on the first world's state", b.kind());
    }
}

/// Worlds stepped in turn by one backend, read only at the end, each end as if stepped
/// alone: a backend that leaves a step's state where it computed it (the CUDA backends
/// keep the positions, previous positions and flags on the device until the host reads them) must
/// not hand one world another's, nor an older step's, whether the worlds are three (more
/// than such a backend keeps copies for), a clone taken mid-run, or a world read between
/// steps on several threads at once.
pub fn worlds_stepped_in_turn_keep_their_own_state(reference: &mut dyn Backend, others: &mut [Box<dyn Backend>]) {
    let k = TickConstants::default();
    let build = |seed| crowded(seed, Placement::Uniform);
    let mut want: Vec<World> = (1..=3).map(build).collect();
    for w in &mut want {
        run(reference, w, 12);
    }
    let want_clone = {
        let mut w = build(1);
        run(reference, &mut w, 6);
        w.state_hash()
    };
    for b in others {
        let mut worlds: Vec<World> = (1..=3).map(build).collect();
        let mut clone = None;
        for tick in 0..12 {
            for (i, w) in worlds.iter_mut().enumerate() {
                // Two worlds every tick, the third every other: the backend's copies are
                // taken in varying order.
                if i < 2 || tick % 2 == 0 {
                    b.step(w, &k).expect("step");
                }
            }
            if tick == 5 {
                clone = Some(worlds[0].clone());
                // Read on several threads at once between steps.
                let d = &worlds[1].dynamics;
                std::thread::scope(|s| {
                    for _ in 0..4 {
                        s.spawn(|| assert!(d.prev_positions().iter().all(|p| p.is_finite())));
                    }
                });
            }
        }
        // The third world missed six steps: make them up, alone.
        for _ in 0..6 {
            b.step(&mut worlds[2], &k).expect("step");
        }
        assert_eq!(clone.expect("cloned").state_hash(), want_clone, "{}: a clone taken after 6 steps", b.kind());
        for (i, (got, want)) in worlds.iter().zip(&want).enumerate() {
            assert_eq!(got.state_hash(), want.state_hash(), "{}: world {i} stepped in turn with others", b.kind());
        }
    }
}

/// The golden world stepped 120 times: its state hash (which `tests/golden.rs` pins).
pub fn golden_hash(backend: &mut dyn Backend) -> u64 {
    let mut w = golden_world();
    run(backend, &mut w, 120);
    w.state_hash()
}
