//! `auto` and the CUDA kinds without a GPU: no panic, a clear reason, a CPU fallback.

use myriad_cuda::{CudaBackend, create_backend};
use myriad_physics::{BackendKind, PhysicsError};

#[test]
fn auto_picks_cuda_when_usable_and_cpu_otherwise() {
    let usable = CudaBackend::new(BackendKind::Cuda).is_ok();
    let b = create_backend(BackendKind::Auto).unwrap();
    let want = if usable { BackendKind::Cuda } else { BackendKind::Cpu };
    assert_eq!(b.kind(), want, "{}", b.description());
    if std::env::var("MYRIAD_REQUIRE_CUDA").is_ok_and(|v| v == "1") {
        assert!(usable, "MYRIAD_REQUIRE_CUDA=1 but cuda is unavailable");
    }
}

#[test]
fn cuda_kinds_fail_cleanly_without_a_device() {
    for kind in [BackendKind::Cuda, BackendKind::CudaNaive] {
        match create_backend(kind) {
            Ok(b) => assert_eq!(b.kind(), kind),
            Err(PhysicsError::Unavailable { backend, reason }) => {
                assert_eq!(backend, kind.name());
                assert!(!reason.is_empty());
                eprintln!("{kind} unavailable here: {reason}");
            }
            Err(e) => panic!("{kind}: unexpected error {e}"),
        }
    }
    // The CPU kinds go through unchanged, and the names parse.
    assert_eq!(create_backend(BackendKind::Cpu).unwrap().kind(), BackendKind::Cpu);
    for name in ["cuda", "cuda-naive", "auto"] {
        assert_eq!(name.parse::<BackendKind>().unwrap().name(), name);
    }
}
