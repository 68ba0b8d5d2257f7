//! Shared helpers of the GPU tests: which CUDA backends can run here, and the worlds of
//! `crates/physics/tests/backends.rs`.

#![allow(dead_code)]

use myriad_core::{Placement, ScenarioSpec, Vec3, World};
use myriad_cuda::CudaBackend;
use myriad_physics::{Backend, BackendKind, StepReport, TickConstants};

/// Whether the run must fail instead of skipping when no GPU is usable.
pub fn cuda_required() -> bool {
    std::env::var("MYRIAD_REQUIRE_CUDA").is_ok_and(|v| v == "1")
}

/// The CUDA backends, or `None` (after saying why) when this machine cannot run them.
/// With `MYRIAD_REQUIRE_CUDA=1` a missing GPU fails the test instead.
pub fn cuda_backends(test: &str) -> Option<Vec<Box<dyn Backend>>> {
    let mut out: Vec<Box<dyn Backend>> = Vec::new();
    for kind in [BackendKind::CudaNaive, BackendKind::Cuda] {
        match CudaBackend::new(kind) {
            Ok(b) => out.push(Box::new(b)),
            Err(e) => {
                assert!(!cuda_required(), "MYRIAD_REQUIRE_CUDA=1 but {kind} is unavailable: {e}");
                eprintln!("skipping {test}: {e}");
                return None;
            }
        }
    }
    Some(out)
}

/// One CUDA backend of `kind`, or `None` as for [`cuda_backends`].
pub fn cuda_backend(test: &str, kind: BackendKind) -> Option<CudaBackend> {
    match CudaBackend::new(kind) {
        Ok(b) => Some(b),
        Err(e) => {
            assert!(!cuda_required(), "MYRIAD_REQUIRE_CUDA=1 but {kind} is unavailable: {e}");
            eprintln!("skipping {test}: {e}");
            None
        }
    }
}

/// A small, crowded world: contacts of every pair kind happen from the first tick (the
/// world of `crates/physics/tests/backends.rs`).
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
    spec.build().unwrap()
}

/// Steps `ticks` times with the default constants.
pub fn run(backend: &mut dyn Backend, world: &mut World, ticks: usize) -> Vec<StepReport> {
    let k = TickConstants::default();
    (0..ticks).map(|_| backend.step(world, &k).unwrap()).collect()
}
