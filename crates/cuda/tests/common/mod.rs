//! Shared helpers of the GPU tests: which CUDA backends can run here, and the worlds of
//! [`myriad_physics::conformance`].

#![allow(dead_code, unused_imports)]

use myriad_cuda::CudaBackend;
use myriad_physics::{Backend, BackendKind};

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

/// The shared test worlds (the same as the CPU backends' tests).
pub use myriad_physics::conformance::{crowded, run};
