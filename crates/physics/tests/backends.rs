//! Behaviour every backend must show, written once and run on each (see `for_each_backend`).
//!
//! GPU backends (a later crate) reuse these scenarios through their own test suite; the
//! determinism tests here pin the contract they must meet: same world in, same bits out.

use myriad_core::{Aabb, ObjectKind, Placement, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::{AoiResults, Backend, BackendKind, StepReport, TickConstants, create_backend};

fn backends() -> Vec<Box<dyn Backend>> {
    BackendKind::ALL.into_iter().map(|k| create_backend(k).unwrap()).collect()
}

/// A small, crowded world: contacts of every pair kind happen from the first tick.
fn crowded(seed: u64, placement: Placement) -> World {
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
    spec.build().unwrap()
}

fn run(backend: &mut dyn Backend, world: &mut World, ticks: usize) -> Vec<StepReport> {
    let k = TickConstants::default();
    (0..ticks).map(|_| backend.step(world, &k).unwrap()).collect()
}

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(f)
}

#[test]
fn every_backend_produces_the_same_world_bit_for_bit() {
    let start = crowded(11, Placement::Uniform);
    let mut hashes = Vec::new();
    let mut reports = Vec::new();
    for mut b in backends() {
        let mut w = start.clone();
        let r = run(b.as_mut(), &mut w, 150);
        hashes.push((b.kind(), w.state_hash()));
        reports.push(r);
    }
    let first = hashes[0].1;
    assert!(hashes.iter().all(|h| h.1 == first), "{hashes:x?}");
    assert_ne!(first, start.state_hash(), "the world must have moved");
    // The same pairs and contacts were found, tick by tick.
    for r in &reports[1..] {
        for (a, b) in r.iter().zip(&reports[0]) {
            assert_eq!(
                (a.static_pairs, a.dynamic_pairs, a.static_contacts, a.dynamic_contacts),
                (b.static_pairs, b.dynamic_pairs, b.static_contacts, b.dynamic_contacts)
            );
        }
    }
    let contacts: u64 = reports[0].iter().map(|r| r.dynamic_contacts + r.static_contacts).sum();
    assert!(contacts > 1_000, "the test needs collisions, had {contacts}");
}

#[test]
fn results_do_not_depend_on_thread_count_or_run() {
    let start = crowded(12, Placement::Clustered { hotspots: 3, fraction: 0.9, spread: 4.0 });
    let hash = |threads: usize| {
        in_pool(threads, || {
            let mut b = create_backend(BackendKind::Cpu).unwrap();
            let mut w = start.clone();
            let reports = run(b.as_mut(), &mut w, 120);
            (w.state_hash(), reports.iter().map(|r| r.dynamic_contacts).sum::<u64>())
        })
    };
    let (one, contacts) = hash(1);
    assert!(contacts > 10_000, "a crowd collides a lot, had {contacts}");
    assert_eq!(hash(1).0, one, "same run twice");
    assert_eq!(hash(2).0, one);
    assert_eq!(hash(5).0, one);
}

#[test]
fn stacked_duplicates_agree_and_separate() {
    // Objects spawned at the very same spot: duplicate Morton codes, coincident centres.
    let mut base = crowded(13, Placement::Uniform);
    let spot = base.dynamics.positions()[0] + Vec3::new(0.0, 3.0, 0.0);
    for i in 0..300 {
        let shape = match i % 3 {
            0 => Shape::Sphere { radius: 0.5 },
            1 => Shape::Box { half: Vec3::splat(0.5) },
            _ => Shape::Capsule { radius: 0.4, half_height: 0.5 },
        };
        base.dynamics.spawn(shape, spot, ObjectKind::Npc).unwrap();
    }
    let mut hashes = Vec::new();
    for mut b in backends() {
        let mut w = base.clone();
        run(b.as_mut(), &mut w, 60);
        hashes.push(w.state_hash());
        // The pile spread out: no two of the spawned objects share a position any more.
        let n = w.dynamics.len();
        let mut pts: Vec<[u32; 3]> =
            w.dynamics.positions()[n - 300..].iter().map(|p| p.to_array().map(f32::to_bits)).collect();
        pts.sort_unstable();
        pts.dedup();
        assert_eq!(pts.len(), 300, "{}", b.kind());
    }
    assert!(hashes.windows(2).all(|h| h[0] == h[1]));
}

#[test]
fn physics_stays_sane_over_hundreds_of_ticks() {
    for mut b in backends() {
        let mut w = crowded(14, Placement::Uniform);
        run(b.as_mut(), &mut w, 300);
        let d = &w.dynamics;
        for s in 0..d.len() {
            let p = d.positions()[s];
            assert!(p.is_finite() && d.prev_positions()[s].is_finite(), "slot {s}: {p}");
            let bb = d.aabb(s);
            assert!(w.bounds.contains_point(bb.min) && w.bounds.contains_point(bb.max), "slot {s} outside: {bb:?}");
            // The floor is enforced on the centre (height + half extent), exactly.
            let floor = w.terrain.height_at(p.x, p.z) + d.half_extents()[s].y;
            assert!(p.y >= floor, "slot {s} under the terrain: {} < {floor}", p.y);
        }
    }
}

#[test]
fn resting_objects_stay_at_rest() {
    for mut b in backends() {
        let mut w = crowded(15, Placement::Uniform);
        // Keep a sparse grid of users (who hold no action) and drop everything else.
        let ids: Vec<_> = w.dynamics.ids().to_vec();
        for id in ids {
            w.dynamics.despawn(id);
        }
        let mut spawned = Vec::new();
        for i in 0..10 {
            for j in 0..10 {
                let (x, z) = (w.bounds.min.x + 8.0 + 8.0 * i as f32, w.bounds.min.z + 8.0 + 8.0 * j as f32);
                let shape = [
                    Shape::Sphere { radius: 0.5 },
                    Shape::Box { half: Vec3::splat(0.5) },
                    Shape::Capsule { radius: 0.4, half_height: 0.5 },
                ][(i + j) % 3];
                let y = w.terrain.height_at(x, z) + shape.half_extents().y + 0.3;
                spawned.push(w.dynamics.spawn(shape, Vec3::new(x, y, z), ObjectKind::User).unwrap());
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

#[test]
fn overlapping_objects_are_pushed_apart() {
    for mut b in backends() {
        let mut w = crowded(16, Placement::Uniform);
        let ids: Vec<_> = w.dynamics.ids().to_vec();
        for id in ids {
            w.dynamics.despawn(id);
        }
        let c = w.bounds.center();
        let y = w.terrain.height_at(c.x, c.z) + 0.5;
        let a = w.dynamics.spawn(Shape::Sphere { radius: 0.5 }, Vec3::new(c.x, y, c.z), ObjectKind::User).unwrap();
        let bb = w
            .dynamics
            .spawn(Shape::Box { half: Vec3::splat(0.5) }, Vec3::new(c.x + 0.6, y, c.z), ObjectKind::User)
            .unwrap();
        run(b.as_mut(), &mut w, 30);
        let pa = w.dynamics.positions()[w.dynamics.slot(a).unwrap()];
        let pb = w.dynamics.positions()[w.dynamics.slot(bb).unwrap()];
        assert!(pb.x - pa.x >= 0.99, "{}: still overlapping, {pa} {pb}", b.kind());
    }
}

#[test]
fn area_of_interest_matches_brute_force() {
    for mut b in backends() {
        let mut w = crowded(17, Placement::Clustered { hotspots: 2, fraction: 0.5, spread: 6.0 });
        let c = w.bounds.center();
        let queries: Vec<Aabb> = (0..40)
            .map(|i| {
                let centre = c + Vec3::new((i % 7) as f32 * 9.0 - 30.0, 0.0, (i % 5) as f32 * 11.0 - 25.0);
                Aabb::from_center_half(centre, Vec3::new(8.0 + i as f32, 100.0, 6.0))
            })
            .collect();
        let check = |w: &World, b: &mut dyn Backend| {
            let mut out = AoiResults::default();
            b.query_aoi(w, &queries, &mut out).unwrap();
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
        check(&w, b.as_mut()); // before any step: builds
        run(b.as_mut(), &mut w, 10);
        check(&w, b.as_mut()); // after steps: refits
        w.dynamics.spawn(Shape::Sphere { radius: 1.0 }, c, ObjectKind::User).unwrap();
        let first = w.dynamics.ids()[0];
        w.dynamics.despawn(first);
        check(&w, b.as_mut()); // after the set changed: rebuilds
    }
}
