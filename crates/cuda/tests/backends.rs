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

/// Worlds stepped in turn keep their own previous positions and flags, which each step
/// leaves on the device until the host reads them: three worlds (one more than the
/// backend keeps copies for while the others are unread), a clone, readers on several
/// threads.
#[test]
fn worlds_stepped_in_turn_keep_their_own_state() {
    let Some(mut gpus) = cuda_backends("worlds_stepped_in_turn_keep_their_own_state") else { return };
    let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::worlds_stepped_in_turn_keep_their_own_state(cpu.as_mut(), &mut gpus);
}
