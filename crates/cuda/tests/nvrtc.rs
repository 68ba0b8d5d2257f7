//! Compiles every kernel with NVRTC. Needs the NVRTC library only, not a GPU, so CI runs
//! it on CPU-only machines (with NVRTC from PyPI on LD_LIBRARY_PATH). Skips with a
//! message when NVRTC is not found, unless `MYRIAD_REQUIRE_CUDA=1`.

use myriad_cuda::compile;

#[test]
fn every_kernel_compiles_for_each_target_architecture() {
    if !compile::nvrtc_present() {
        assert!(
            std::env::var("MYRIAD_REQUIRE_CUDA").as_deref() != Ok("1"),
            "MYRIAD_REQUIRE_CUDA=1 but NVRTC was not found"
        );
        eprintln!("skipping: the NVRTC library (libnvrtc.so) was not found; set LD_LIBRARY_PATH to include it");
        return;
    }
    let (major, minor) = compile::nvrtc_version().unwrap();
    eprintln!("NVRTC {major}.{minor}");
    // Hopper (the lent machines), Ampere and Ada.
    for arch in [90, 80, 89] {
        let cubin = compile::compile_cubin(arch, &[]).unwrap_or_else(|e| panic!("sm_{arch}: {e}"));
        // An ELF image: the driver loads it without a JIT step.
        assert_eq!(&cubin[..4], b"\x7fELF", "sm_{arch}: not a CUBIN");
    }
}

#[test]
fn a_broken_kernel_reports_the_compiler_log() {
    if !compile::nvrtc_present() {
        eprintln!("skipping: the NVRTC library was not found");
        return;
    }
    // The options are right and the sources are fine, so an unknown architecture is
    // what fails here; the error must carry NVRTC's status.
    let err = compile::compile_cubin(1, &[]).unwrap_err().to_string();
    assert!(err.contains("NVRTC"), "{err}");
}

#[test]
fn the_launch_table_matches_the_kernel_sources() {
    let mut declared = compile::declared_kernels();
    declared.sort();
    let mut table: Vec<(String, usize)> = compile::KERNELS.iter().map(|(n, a)| (n.to_string(), *a)).collect();
    table.sort();
    assert_eq!(declared, table);
}

#[test]
fn cache_keys_depend_on_the_architecture() {
    assert_ne!(compile::cache_key(90), compile::cache_key(80));
    assert_eq!(compile::cache_key(90), compile::cache_key(90));
    assert!(compile::program_source().contains("k_forces"));
}
