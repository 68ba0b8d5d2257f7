//! `auto` and the CUDA kinds without a GPU: no panic, a clear reason, a CPU fallback.

use myriad_cuda::{CudaBackend, create_backend};
use myriad_physics::{BackendKind, PhysicsError};

#[test]
fn auto_picks_cuda_when_usable_and_cpu_otherwise() {
    let usable = CudaBackend::new(BackendKind::Cuda).is_ok();
    let created = create_backend(BackendKind::Auto).unwrap();
    let b = &created.backend;
    let want = if usable { BackendKind::Cuda } else { BackendKind::Cpu };
    assert_eq!(b.kind(), want, "{}", b.description());
    // The device replicas comes with a CUDA backend, and only with one.
    assert_eq!(created.device_replicas.is_some(), usable);
    if std::env::var("MYRIAD_REQUIRE_CUDA").is_ok_and(|v| v == "1") {
        assert!(usable, "MYRIAD_REQUIRE_CUDA=1 but cuda is unavailable");
    }
}

#[test]
fn cuda_kinds_fail_cleanly_without_a_device() {
    for kind in [BackendKind::Cuda, BackendKind::CudaNaive] {
        match create_backend(kind) {
            Ok(b) => {
                assert_eq!(b.backend.kind(), kind);
                assert!(b.device_replicas.is_some(), "{kind} without its device replicas");
            }
            Err(PhysicsError::Unavailable { backend, reason }) => {
                assert_eq!(backend, kind.name());
                assert!(!reason.is_empty());
                eprintln!("{kind} unavailable here: {reason}");
            }
            Err(e) => panic!("{kind}: unexpected error {e}"),
        }
    }
    // The CPU kinds go through unchanged, and the names parse.
    let cpu = create_backend(BackendKind::Cpu).unwrap();
    assert_eq!(cpu.backend.kind(), BackendKind::Cpu);
    assert!(cpu.device_replicas.is_none());
    for name in ["cuda", "cuda-naive", "auto"] {
        assert_eq!(name.parse::<BackendKind>().unwrap().name(), name);
    }
}
