//! Behaviour every backend must show ([`myriad_physics::conformance`]), on the CPU
//! backends: `cpu` is held to `cpu-naive`'s world bit for bit. The CUDA crate's tests run
//! the same checks on its backends against `cpu`.

use myriad_core::Placement;
use myriad_physics::conformance::{self, crowded, run};
use myriad_physics::{Backend, BackendKind, create_cpu_backend};

fn backends() -> Vec<Box<dyn Backend>> {
    BackendKind::ALL.into_iter().map(|k| create_cpu_backend(k).unwrap()).collect()
}

/// `cpu-naive` as the reference, `cpu` under test.
fn reference_and_others() -> (Box<dyn Backend>, Vec<Box<dyn Backend>>) {
    (create_cpu_backend(BackendKind::CpuNaive).unwrap(), vec![create_cpu_backend(BackendKind::Cpu).unwrap()])
}

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(f)
}

#[test]
fn every_backend_produces_the_same_world_bit_for_bit() {
    let (mut reference, mut others) = reference_and_others();
    conformance::same_world_bit_for_bit(reference.as_mut(), &mut others);
}

/// `cpu` refitting its dynamic tree for 0, 1, 3 and 8 steps in a row gives `cpu-naive`'s
/// world, and builds its tree on schedule.
#[test]
fn steps_that_refit_the_tree_end_in_the_reference_world() {
    let (mut reference, mut others) = reference_and_others();
    conformance::refit_steps_agree(reference.as_mut(), &mut others);
    assert!(others[0].tree_age().is_some(), "cpu keeps a dynamic tree");
}

#[test]
fn host_changes_between_steps_are_seen() {
    let (mut reference, mut others) = reference_and_others();
    conformance::host_changes_between_steps_are_seen(reference.as_mut(), &mut others);
}

#[test]
fn results_do_not_depend_on_thread_count_or_run() {
    let start = crowded(12, Placement::Clustered { hotspots: 3, fraction: 0.9, spread: 4.0 });
    let hash = |threads: usize| {
        in_pool(threads, || {
            let mut b = create_cpu_backend(BackendKind::Cpu).unwrap();
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
    let (mut reference, mut others) = reference_and_others();
    conformance::stacked_duplicates_agree_and_separate(reference.as_mut(), &mut others);
}

#[test]
fn physics_stays_sane_over_hundreds_of_ticks() {
    conformance::physics_stays_sane(&mut backends());
}

#[test]
fn resting_objects_stay_at_rest() {
    conformance::resting_objects_stay_at_rest(&mut backends());
}

#[test]
fn overlapping_objects_are_pushed_apart() {
    conformance::overlapping_objects_are_pushed_apart(&mut backends());
}

#[test]
fn area_of_interest_matches_brute_force() {
    conformance::area_of_interest_matches_brute_force(&mut backends());
}

#[test]
fn a_moved_backend_answers_for_its_new_world() {
    let mut reference = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::a_moved_backend_answers_for_its_new_world(reference.as_mut(), &mut backends());
}

#[test]
fn worlds_stepped_in_turn_keep_their_own_state() {
    let mut reference = create_cpu_backend(BackendKind::Cpu).unwrap();
    conformance::worlds_stepped_in_turn_keep_their_own_state(reference.as_mut(), &mut backends());
}
