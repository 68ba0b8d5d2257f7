//! The checks every backend must pass ([`myriad_physics::conformance`]), on `cuda-naive`
//! and `cuda`, whose worlds must equal the `cpu` backend's bit for bit.
//!
//! Without a GPU these skip (saying so); with `MYRIAD_REQUIRE_CUDA=1` they fail instead.

mod common;

use common::cuda_backends;
use myriad_physics::conformance;
use myriad_physics::{BackendKind, create_cpu_backend};

#[test]
fn every_backend_produces_the_same_world_bit_for_bit() {
    let Some(mut gpus) = cuda_backends("every_backend_produces_the_same_world_bit_for_bit") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::same_world_bit_for_bit(cpu.as_mut(), &mut gpus);
}

/// Actions set between steps (only they travel to the device then), teleports, spawns
/// and removals: the CUDA backends see each and keep the CPU's world.
#[test]
fn host_changes_between_steps_are_seen() {
    let Some(mut gpus) = cuda_backends("host_changes_between_steps_are_seen") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::host_changes_between_steps_are_seen(cpu.as_mut(), &mut gpus);
}

#[test]
fn stacked_duplicates_agree_and_separate() {
    let Some(mut gpus) = cuda_backends("stacked_duplicates_agree_and_separate") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::stacked_duplicates_agree_and_separate(cpu.as_mut(), &mut gpus);
}

#[test]
fn physics_stays_sane_over_hundreds_of_ticks() {
    let Some(mut gpus) = cuda_backends("physics_stays_sane_over_hundreds_of_ticks") else { return };
    conformance::physics_stays_sane(&mut gpus);
}

#[test]
fn resting_objects_stay_at_rest() {
    let Some(mut gpus) = cuda_backends("resting_objects_stay_at_rest") else { return };
    conformance::resting_objects_stay_at_rest(&mut gpus);
}

#[test]
fn overlapping_objects_are_pushed_apart() {
    let Some(mut gpus) = cuda_backends("overlapping_objects_are_pushed_apart") else { return };
    conformance::overlapping_objects_are_pushed_apart(&mut gpus);
}

#[test]
fn area_of_interest_matches_brute_force() {
    let Some(mut gpus) = cuda_backends("area_of_interest_matches_brute_force") else { return };
    conformance::area_of_interest_matches_brute_force(&mut gpus);
}

/// The golden world of `crates/physics/tests/golden.rs` (whose pinned hash the CPU
/// backends must give): the CUDA backends must give the CPU's hash.
#[test]
fn golden_scenario_matches_the_cpu() {
    let Some(mut gpus) = cuda_backends("golden_scenario_matches_the_cpu") else { return };
    let want = conformance::golden_hash(create_cpu_backend(BackendKind::Cpu).unwrap().as_mut());
    for b in &mut gpus {
        let got = conformance::golden_hash(b.as_mut());
        assert_eq!(got, want, "{}: {got:#018x}", b.kind());
        println!("golden scenario, 120 ticks: {} {got:#018x} = cpu", b.kind());
    }
}

/// Moved from one world to the next, the CUDA backends keep no device copy of the first
/// (their copies are keyed on the worlds' stamps, not on addresses a dropped world hands
/// on).
#[test]
fn a_moved_backend_answers_for_its_new_world() {
    let Some(mut gpus) = cuda_backends("a_moved_backend_answers_for_its_new_world") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::a_moved_backend_answers_for_its_new_world(cpu.as_mut(), &mut gpus);
}

/// Worlds stepped in turn keep their own positions, previous positions and flags, which each step
/// leaves on the device until the host reads them: three worlds (one more than the
/// backend keeps copies for while the others are unread), a clone, readers on several
/// threads.
#[test]
fn worlds_stepped_in_turn_keep_their_own_state() {
    let Some(mut gpus) = cuda_backends("worlds_stepped_in_turn_keep_their_own_state") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::worlds_stepped_in_turn_keep_their_own_state(cpu.as_mut(), &mut gpus);
}

/// A step leaves the positions, previous positions and flags on the device while the
/// backend has a copy no world refers to (1 byte an object comes back, the action, not
/// 26), and brings them back when every copy is referred to; the worlds keep the CPU's
/// state either way. Without this the conformance checks above would also pass if no
/// step held anything.
#[test]
fn a_step_leaves_the_previous_state_on_the_device_while_a_copy_is_free() {
    let Some(mut gpus) = cuda_backends("a_step_leaves_the_previous_state_on_the_device_while_a_copy_is_free") else {
        return;
    };
    let k = myriad_physics::TickConstants::default();
    let build = |seed| conformance::crowded(seed, myriad_core::Placement::Uniform);
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    // (world, whether its step finds a free copy). Nothing reads a world between these
    // steps (a read fetches the held arrays and frees the copy), except the backend
    // itself: a step of another world than the last uploads that world whole, reading
    // (so freeing) its own copy first. Worlds 0, 1 and 2 take the backend's three
    // copies; world 3 finds none and brings everything back; world 0, uploaded, frees
    // its copy and takes it again; world 3 again finds none; world 0 again takes its
    // own; stepped twice in a row (nothing uploaded) it still refers to that copy and
    // finds none free, and frees it by taking the full arrays; a third time in a row it
    // takes it again.
    let unread = [(0, true), (1, true), (2, true), (3, false), (0, true), (3, false), (0, true), (0, false), (0, true)];
    for b in &mut gpus {
        let name = b.kind();
        let mut want: Vec<_> = (1..=4).map(build).collect();
        let mut got: Vec<_> = (1..=4).map(build).collect();
        {
            let mut step = |i: usize, held: bool, when: &str| {
                cpu.step(&mut want[i], &k).unwrap();
                let report = b.step(&mut got[i], &k).unwrap();
                let per_object = if held { 1 } else { 26 };
                let n = got[i].dynamics.len() as u64;
                assert_eq!(report.download_bytes, 16 + per_object * n, "{name}, {when} (world {i}): held {held}");
            };
            for (turn, (i, held)) in unread.into_iter().enumerate() {
                step(i, held, &format!("turn {turn}"));
            }
        }
        let check = |got: &[myriad_core::World], want: &[myriad_core::World], when: &str| {
            for (i, (g, w)) in got.iter().zip(want).enumerate() {
                assert_eq!(g.state_hash(), w.state_hash(), "{name}: world {i} {when}");
            }
        };
        // Reading every world fetched what it held: every copy is free again.
        check(&got, &want, "after the unread turns");
        for i in [1, 2, 3] {
            cpu.step(&mut want[i], &k).unwrap();
            let report = b.step(&mut got[i], &k).unwrap();
            assert_eq!(report.download_bytes, 16 + got[i].dynamics.len() as u64, "{name}: world {i} after reads");
        }
        check(&got, &want, "at the end");
        println!("{name}: held steps download 1 byte an object, full ones 26; every world = cpu");
    }
}

/// Some positions of a world whose step left them on the device come from a gather (the
/// world's state stays held) and equal the CPU's, in the order asked, repeats included;
/// with the backend dropped they still do (the world's copy reads every position back).
#[test]
fn some_positions_are_gathered_on_the_device_and_equal_the_cpus() {
    let Some(gpus) = cuda_backends("some_positions_are_gathered_on_the_device_and_equal_the_cpus") else { return };
    let k = myriad_physics::TickConstants::default();
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    for mut b in gpus {
        let name = b.kind();
        let mut want = conformance::crowded(11, myriad_core::Placement::Uniform);
        let mut got = want.clone();
        for _ in 0..3 {
            cpu.step(&mut want, &k).unwrap();
            b.step(&mut got, &k).unwrap();
        }
        let n = got.dynamics.len() as u32;
        let slots: Vec<u32> = (0..n).rev().step_by(7).chain([0, 0, n - 1]).collect();
        let expect: Vec<_> = slots.iter().map(|&s| want.dynamics.positions()[s as usize]).collect();
        let mut out = Vec::new();
        assert!(got.dynamics.state_held(), "{name}: the step left the state on the device");
        got.dynamics.positions_at(&slots, &mut out);
        assert_eq!(out, expect, "{name}: gathered");
        assert!(got.dynamics.state_held(), "{name}: a gather fetches nothing else");
        got.dynamics.positions_at(&[], &mut out);
        assert!(out.is_empty());
        drop(b);
        got.dynamics.positions_at(&slots, &mut out);
        assert_eq!(out, expect, "{name}: read back without the backend");
        assert!(got.dynamics.state_held());
        assert_eq!(got.state_hash(), want.state_hash(), "{name}");
        assert!(!got.dynamics.state_held(), "the hash read everything");
        println!("{name}: {} positions gathered = cpu, with and without the backend", slots.len());
    }
}

/// Steps that refit the dynamic tree end in the CPU's world, and `cuda` builds its
/// tree on schedule (`cuda-naive` has none).
#[test]
fn steps_that_refit_the_tree_end_in_the_cpus_world() {
    let Some(mut gpus) = cuda_backends("steps_that_refit_the_tree_end_in_the_cpus_world") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::refit_steps_agree(cpu.as_mut(), &mut gpus);
    assert!(gpus[1].tree_age().is_some(), "cuda keeps a dynamic tree");
    assert!(gpus[0].tree_age().is_none(), "cuda-naive keeps none");
}
