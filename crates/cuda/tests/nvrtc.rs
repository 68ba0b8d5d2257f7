//! Compiles every kernel with NVRTC. Needs the NVRTC library only, not a GPU, so CI runs
//! it on CPU-only machines (with NVRTC from PyPI on LD_LIBRARY_PATH). Skips with a
//! message when NVRTC is not found, unless `MYRIAD_REQUIRE_NVRTC=1` (CI) or
//! `MYRIAD_REQUIRE_CUDA=1` (the GPU machine) makes that a failure.

use myriad_cuda::compile;

/// Whether NVRTC is here; when it is not, fails the test under `MYRIAD_REQUIRE_CUDA=1` or
/// `MYRIAD_REQUIRE_NVRTC=1`, or says that it skips (`unchecked`: what goes unchecked).
fn nvrtc(unchecked: &str) -> bool {
    if compile::nvrtc_present() {
        return true;
    }
    let var =
        if myriad_testenv::required("MYRIAD_REQUIRE_CUDA") { "MYRIAD_REQUIRE_CUDA" } else { "MYRIAD_REQUIRE_NVRTC" };
    myriad_testenv::missing(
        var,
        format!("the NVRTC library (libnvrtc.so) was not found, so {unchecked}; set LD_LIBRARY_PATH to include it"),
    );
    false
}

#[test]
fn every_kernel_compiles_for_each_target_architecture() {
    if !nvrtc("no kernel was compiled") {
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
    if !nvrtc("the compiler's error report was not checked") {
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

/// The host's parameter block must match the kernels' `struct Params` byte for byte: it
/// is uploaded as raw bytes. NVRTC compiles a program that includes the kernels' header
/// and asserts, at compile time, every field's offset, size and C type, and the struct's
/// size, with the numbers taken from `DeviceParams` here. A field reordered, retyped,
/// added or removed on either side fails the compile, and the log names the field.
#[test]
fn the_params_block_matches_the_kernel_header_field_by_field() {
    use myriad_cuda::params::DeviceParams;
    use std::mem::{offset_of, size_of, size_of_val};

    let z: DeviceParams = bytemuck::Zeroable::zeroed();
    // (name, offset, size, C type) of every field, in declaration order.
    macro_rules! fields {
        ($($f:ident: $c:literal),* $(,)?) => {
            vec![$((stringify!($f), offset_of!(DeviceParams, $f), size_of_val(&z.$f), $c)),*]
        };
    }
    let fields = fields![
        gravity_dt2: "float",
        air_keep: "float",
        ground_keep: "float",
        move_accel: "float",
        jump_velocity: "float",
        one_plus_e: "float",
        ground_tolerance: "float",
        support_min_y: "float",
        npc_period: "u32",
        bmin: "float[3]",
        bmax: "float[3]",
        t_width: "u32",
        t_depth: "u32",
        origin_x: "float",
        origin_z: "float",
        inv_cell_x: "float",
        inv_cell_z: "float",
        height_scale: "float",
        base_y: "float",
    ];
    // The list above must cover the whole struct, or a field added on the Rust side
    // alone would go unchecked.
    assert_eq!(fields.iter().map(|f| f.2).sum::<usize>(), size_of::<DeviceParams>(), "a field is missing above");

    // NVRTC has no <cstddef> (so no `offsetof`) without extra headers, and no
    // `__builtin_offsetof`; `__INTADDR__` is the constant-address builtin of its front
    // end (EDG), the one EDG's own `offsetof` is built on.
    let mut src = String::from(
        "#include \"common.cuh\"\n\
         #define OFFSET_OF(T, m) ((unsigned long long)__INTADDR__(&(((T*)0)->m)))\n\
         template <class A, class B> struct same_type { static const bool value = false; };\n\
         template <class A> struct same_type<A, A> { static const bool value = true; };\n",
    );
    for (name, offset, size, c_type) in &fields {
        src.push_str(&format!(
            "static_assert(OFFSET_OF(Params, {name}) == {offset}, \"Params::{name}: offset differs from DeviceParams ({offset})\");\n\
             static_assert(sizeof(Params::{name}) == {size}, \"Params::{name}: size differs from DeviceParams ({size})\");\n\
             static_assert(same_type<decltype(Params::{name}), {c_type}>::value, \"Params::{name}: not {c_type}\");\n"
        ));
    }
    let size = size_of::<DeviceParams>();
    src.push_str(&format!(
        "static_assert(sizeof(Params) == {size}, \"sizeof(Params) differs from DeviceParams ({size})\");\n"
    ));

    if !nvrtc("the Params layout was checked only on the Rust side") {
        return;
    }
    if let Err(e) = compile::compile_source(&src, 90, &[]) {
        panic!("DeviceParams and the kernels' Params disagree:\n{e}\n--- generated source ---\n{src}");
    }
}
