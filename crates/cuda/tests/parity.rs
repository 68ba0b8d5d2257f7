//! CPU ↔ GPU parity over hundreds of ticks on crowded, clustered and duplicate-heavy
//! worlds (state hashes compared every 25 ticks, so a divergence is located), and
//! broad-phase pair sets against brute force on random, duplicate-heavy and clustered
//! inputs. The hashes are printed (run with `--nocapture`) for the results page.

mod common;

use common::{crowded, cuda_backend, cuda_backends};
use myriad_core::{ObjectKind, Placement, Shape, Vec3, World};
use myriad_physics::{BackendKind, TickConstants, create_cpu_backend};

fn duplicate_heavy(seed: u64) -> World {
    let mut w = crowded(seed, Placement::Uniform);
    let c = w.bounds.center();
    let y = w.terrain.height_at(c.x, c.z) + 4.0;
    // Four piles of 250 objects each at one point: duplicate Morton codes by the hundred.
    for pile in 0..4 {
        let spot = Vec3::new(c.x + 12.0 * pile as f32 - 18.0, y, c.z);
        for i in 0..250 {
            let shape = match i % 3 {
                0 => Shape::Sphere { radius: 0.5 },
                1 => Shape::Box { half: Vec3::splat(0.5) },
                _ => Shape::Capsule { radius: 0.4, half_height: 0.5 },
            };
            w.dynamics.spawn(shape, spot, ObjectKind::Npc).unwrap();
        }
    }
    w
}

fn worlds() -> Vec<(&'static str, World)> {
    vec![
        ("crowded", crowded(21, Placement::Uniform)),
        ("clustered", crowded(22, Placement::Clustered { hotspots: 3, fraction: 0.9, spread: 4.0 })),
        ("duplicate-heavy", duplicate_heavy(23)),
    ]
}

#[test]
fn gpu_state_hash_equals_cpu_over_hundreds_of_ticks() {
    let Some(mut gpus) = cuda_backends("gpu_state_hash_equals_cpu_over_hundreds_of_ticks") else { return };
    let k = TickConstants::default();
    const TICKS: usize = 300;
    for (name, start) in worlds() {
        let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
        let mut want = start.clone();
        let mut got: Vec<World> = gpus.iter().map(|_| start.clone()).collect();
        let mut contacts = 0u64;
        for t in 1..=TICKS {
            let r = cpu.step(&mut want, &k).unwrap();
            contacts += r.static_contacts + r.dynamic_contacts;
            for (b, w) in gpus.iter_mut().zip(&mut got) {
                let g = b.step(w, &k).unwrap();
                assert_eq!(
                    (g.static_pairs, g.dynamic_pairs, g.static_contacts, g.dynamic_contacts),
                    (r.static_pairs, r.dynamic_pairs, r.static_contacts, r.dynamic_contacts),
                    "{name}: {} tick {t}",
                    b.kind()
                );
            }
            if t % 25 == 0 || t == TICKS {
                for (b, w) in gpus.iter().zip(&got) {
                    assert_eq!(w.state_hash(), want.state_hash(), "{name}: {} diverged by tick {t}", b.kind());
                }
            }
        }
        assert!(contacts > 10_000, "{name}: needs collisions, had {contacts}");
        println!(
            "parity {name}: {} objects, {TICKS} ticks, {contacts} contacts, hash cpu {:016x} = cuda-naive {:016x} = cuda {:016x}",
            want.dynamics.len(),
            want.state_hash(),
            got[0].state_hash(),
            got[1].state_hash()
        );
    }
}

/// Every overlapping pair by brute force, in the canonical forms.
fn brute_pairs(w: &World) -> (Vec<u64>, Vec<u64>) {
    let d = &w.dynamics;
    let st = &w.statics;
    let mut s = Vec::new();
    let mut dy = Vec::new();
    for i in 0..d.len() {
        let a = d.aabb(i);
        for p in 0..st.prim_count() {
            if a.overlaps(&st.aabb(p)) {
                s.push((i as u64) << 32 | p as u64);
            }
        }
        for j in i + 1..d.len() {
            if a.overlaps(&d.aabb(j)) {
                dy.push((i as u64) << 32 | j as u64);
            }
        }
    }
    (s, dy)
}

#[test]
fn pair_sets_equal_brute_force() {
    for kind in [BackendKind::CudaNaive, BackendKind::Cuda] {
        let Some(mut b) = cuda_backend("pair_sets_equal_brute_force", kind) else { return };
        let k = TickConstants::default();
        for (name, mut w) in worlds() {
            for round in 0..3 {
                let (s, d) = b.broad_pairs(&w).unwrap();
                let (ws, wd) = brute_pairs(&w);
                assert!(!wd.is_empty() && !ws.is_empty(), "{name}: the test needs pairs");
                assert_eq!(s, ws, "{kind} {name} round {round}: static pairs");
                assert_eq!(d, wd, "{kind} {name} round {round}: dynamic pairs");
                for _ in 0..20 {
                    myriad_physics::Backend::step(&mut b, &mut w, &k).unwrap();
                }
            }
        }
    }
}

/// Steps the CPU and each CUDA backend one tick at a time from the same state (the GPU
/// world is reset to the CPU's before each tick) and, at the first tick where any object
/// differs, prints the differing objects with their state and candidate pairs. A
/// diagnostic for the hash comparisons above; it fails exactly when they would.
#[test]
fn first_divergence_is_reported_per_object() {
    let Some(mut gpus) = cuda_backends("first_divergence_is_reported_per_object") else { return };
    let k = TickConstants::default();
    for (name, start) in worlds() {
        for b in gpus.iter_mut() {
            let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
            let mut want = start.clone();
            for t in 0..60 {
                let before = want.clone();
                let mut got = want.clone();
                cpu.step(&mut want, &k).unwrap();
                b.step(&mut got, &k).unwrap();
                if got.state_hash() == want.state_hash() {
                    continue;
                }
                let (d, g) = (&want.dynamics, &got.dynamics);
                let bd = &before.dynamics;
                let mut shown = 0;
                for s in 0..d.len() {
                    let same = d.positions()[s].to_array().map(f32::to_bits)
                        == g.positions()[s].to_array().map(f32::to_bits)
                        && d.prev_positions()[s].to_array().map(f32::to_bits)
                            == g.prev_positions()[s].to_array().map(f32::to_bits)
                        && d.actions()[s] == g.actions()[s]
                        && d.flags()[s] == g.flags()[s];
                    if same {
                        continue;
                    }
                    let bb = bd.aabb(s);
                    let statics: Vec<usize> =
                        (0..before.statics.prim_count()).filter(|&p| before.statics.aabb(p).overlaps(&bb)).collect();
                    let others: Vec<usize> = (0..bd.len()).filter(|&o| o != s && bd.aabb(o).overlaps(&bb)).collect();
                    println!(
                        "{name} {} tick {t} slot {s} {:?} {:?}: before pos {:?} prev {:?} action {} flags {}; \
                         cpu pos {:?} prev {:?} a {} f {}; gpu pos {:?} prev {:?} a {} f {}; statics {statics:?} others {others:?}",
                        b.kind(),
                        bd.kinds()[s],
                        bd.shapes()[s],
                        bd.positions()[s],
                        bd.prev_positions()[s],
                        bd.actions()[s],
                        bd.flags()[s],
                        d.positions()[s],
                        d.prev_positions()[s],
                        d.actions()[s],
                        d.flags()[s],
                        g.positions()[s],
                        g.prev_positions()[s],
                        g.actions()[s],
                        g.flags()[s],
                    );
                    shown += 1;
                    if shown == 6 {
                        break;
                    }
                }
                panic!("{name}: {} differs from cpu at tick {t}", b.kind());
            }
        }
    }
}
