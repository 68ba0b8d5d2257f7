//! The backend tests of `crates/physics/tests/backends.rs`, on `cuda-naive` and `cuda`,
//! each compared with the CPU backend where the original compares backends.
//!
//! Without a GPU these skip (saying so); with `MYRIAD_REQUIRE_CUDA=1` they fail instead.

mod common;

use common::{crowded, cuda_backends, run};
use myriad_core::{Aabb, ObjectKind, Placement, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::{AoiResults, Backend, BackendKind, TickConstants, create_backend};

#[test]
fn every_backend_produces_the_same_world_bit_for_bit() {
    let Some(gpus) = cuda_backends("every_backend_produces_the_same_world_bit_for_bit") else { return };
    let start = crowded(11, Placement::Uniform);
    let mut cpu = create_backend(BackendKind::Cpu).unwrap();
    let mut want = start.clone();
    let want_reports = run(cpu.as_mut(), &mut want, 150);
    let contacts: u64 = want_reports.iter().map(|r| r.dynamic_contacts + r.static_contacts).sum();
    assert!(contacts > 1_000, "the test needs collisions, had {contacts}");
    for mut b in gpus {
        let mut w = start.clone();
        let reports = run(b.as_mut(), &mut w, 150);
        assert_eq!(w.state_hash(), want.state_hash(), "{}", b.kind());
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

#[test]
fn stacked_duplicates_agree_and_separate() {
    let Some(gpus) = cuda_backends("stacked_duplicates_agree_and_separate") else { return };
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
    let mut cpu = create_backend(BackendKind::Cpu).unwrap();
    let mut want = base.clone();
    run(cpu.as_mut(), &mut want, 60);
    for mut b in gpus {
        let mut w = base.clone();
        run(b.as_mut(), &mut w, 60);
        assert_eq!(w.state_hash(), want.state_hash(), "{}", b.kind());
        let n = w.dynamics.len();
        let mut pts: Vec<[u32; 3]> =
            w.dynamics.positions()[n - 300..].iter().map(|p| p.to_array().map(f32::to_bits)).collect();
        pts.sort_unstable();
        pts.dedup();
        assert_eq!(pts.len(), 300, "{}", b.kind());
    }
}

#[test]
fn physics_stays_sane_over_hundreds_of_ticks() {
    let Some(gpus) = cuda_backends("physics_stays_sane_over_hundreds_of_ticks") else { return };
    for mut b in gpus {
        let mut w = crowded(14, Placement::Uniform);
        run(b.as_mut(), &mut w, 300);
        let d = &w.dynamics;
        for s in 0..d.len() {
            let p = d.positions()[s];
            assert!(p.is_finite() && d.prev_positions()[s].is_finite(), "slot {s}: {p}");
            let bb = d.aabb(s);
            assert!(w.bounds.contains_point(bb.min) && w.bounds.contains_point(bb.max), "slot {s} outside: {bb:?}");
            let floor = w.terrain.height_at(p.x, p.z) + d.half_extents()[s].y;
            assert!(p.y >= floor, "slot {s} under the terrain: {} < {floor}", p.y);
        }
    }
}

#[test]
fn resting_objects_stay_at_rest() {
    let Some(gpus) = cuda_backends("resting_objects_stay_at_rest") else { return };
    for mut b in gpus {
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
                w.dynamics.spawn(shape, Vec3::new(x, y, z), ObjectKind::User).unwrap();
            }
        }
        run(b.as_mut(), &mut w, 60);
        let settled: Vec<Vec3> = w.dynamics.positions().to_vec();
        run(b.as_mut(), &mut w, 200);
        for (s, (a, now)) in settled.iter().zip(w.dynamics.positions()).enumerate() {
            assert!((*a - *now).length() < 1e-3, "{}: slot {s} moved from {a} to {now}", b.kind());
        }
    }
}

#[test]
fn overlapping_objects_are_pushed_apart() {
    let Some(gpus) = cuda_backends("overlapping_objects_are_pushed_apart") else { return };
    for mut b in gpus {
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
    let Some(gpus) = cuda_backends("area_of_interest_matches_brute_force") else { return };
    for mut b in gpus {
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
        check(&w, b.as_mut());
        run(b.as_mut(), &mut w, 10);
        check(&w, b.as_mut());
        w.dynamics.spawn(Shape::Sphere { radius: 1.0 }, c, ObjectKind::User).unwrap();
        let first = w.dynamics.ids()[0];
        w.dynamics.despawn(first);
        check(&w, b.as_mut());
        // An empty batch and a world change between steps (teleport) keep answers exact.
        let mut out = AoiResults::default();
        b.query_aoi(&w, &[], &mut out).unwrap();
        assert!(out.is_empty());
        let id = w.dynamics.ids()[5];
        w.dynamics.teleport(id, c);
        check(&w, b.as_mut());
    }
}

/// The scenario of `crates/physics/tests/golden.rs` (whose pinned hash the CPU backends
/// must give): the CUDA backends must give the CPU's hash.
#[test]
fn golden_scenario_matches_the_cpu() {
    let Some(gpus) = cuda_backends("golden_scenario_matches_the_cpu") else { return };
    let mut spec = ScenarioSpec::custom(2024);
    spec.dynamic = 900;
    spec.users = 90;
    spec.static_objects = 120;
    spec.world_size = 80.0;
    spec.origin = Vec3::new(123.5, -7.0, -4096.0);
    spec.terrain_samples = 81;
    spec.max_height = 5.0;
    let start = spec.build().unwrap();
    let k = TickConstants::default();
    let mut want = start.clone();
    let mut cpu = create_backend(BackendKind::Cpu).unwrap();
    for _ in 0..120 {
        cpu.step(&mut want, &k).unwrap();
    }
    for mut b in gpus {
        let mut w = start.clone();
        for _ in 0..120 {
            b.step(&mut w, &k).unwrap();
        }
        assert_eq!(w.state_hash(), want.state_hash(), "{}: {:#018x}", b.kind(), w.state_hash());
        println!("golden scenario, 120 ticks: {} {:#018x} = cpu", b.kind(), w.state_hash());
    }
}
