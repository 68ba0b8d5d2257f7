//! Compiling the kernels with NVRTC, and the on-disk CUBIN cache.
//!
//! The kernels are CUDA C++ sources embedded in the binary (`kernels/*.cu`, `*.cuh`). At
//! start-up they are compiled for the device's architecture straight to a CUBIN
//! (`-arch=sm_XX`), which the driver loads in a fraction of a millisecond, where PTX
//! would cost a JIT compile of ~80 ms. The CUBIN is cached on disk, keyed by a hash of
//! the source, the options, the architecture and the NVRTC version, so a server start
//! usually pays neither cost.
//!
//! Options: `--fmad=false` (Rust never contracts `a * b + c` into a fused multiply–add,
//! so the kernels must not either), `-prec-div=true -prec-sqrt=true` (IEEE division and
//! square root, as on the CPU) and `-ftz=false` (keep subnormals).

use std::ffi::{CStr, CString, c_char, c_int};
use std::path::PathBuf;

use cudarc::nvrtc::sys as nvrtc;

/// The kernel sources, in the order they are concatenated into one program.
pub const SOURCES: [(&str, &str); 8] = [
    ("scan.cu", include_str!("../kernels/scan.cu")),
    ("lbvh.cu", include_str!("../kernels/lbvh.cu")),
    ("broad.cu", include_str!("../kernels/broad.cu")),
    ("grid.cu", include_str!("../kernels/grid.cu")),
    ("physics.cu", include_str!("../kernels/physics.cu")),
    ("patch.cu", include_str!("../kernels/patch.cu")),
    ("replica.cu", include_str!("../kernels/replica.cu")),
    ("pack.cu", include_str!("../kernels/pack.cu")),
];

/// Headers the sources include, handed to NVRTC by name.
pub const HEADERS: [(&str, &str); 4] = [
    ("common.cuh", include_str!("../kernels/common.cuh")),
    ("narrow.cuh", include_str!("../kernels/narrow.cuh")),
    ("replica.cuh", include_str!("../kernels/replica.cuh")),
    ("pack.cuh", include_str!("../kernels/pack.cuh")),
];

/// Every kernel entry point the backends load, with its number of parameters (each
/// launch's argument count is checked against it at run time; the argument structs of
/// the `launch` module are checked against the sources' signatures by a unit test).
pub const KERNELS: [(&str, usize); 30] = [
    ("k_scan_blocks", 3),
    ("k_scan_sums", 2),
    ("k_scan_add", 3),
    ("k_boxes_morton", 12),
    ("k_radix_counts", 3),
    ("k_radix_pass", 9),
    ("k_emit", 5),
    ("k_refit", 7),
    ("k_tree_count", 11),
    ("k_tree_write", 13),
    ("k_sort_ranges", 3),
    ("k_grid_keys", 9),
    ("k_grid_scatter", 6),
    ("k_grid_pass", 14),
    ("k_naive_count", 6),
    ("k_naive_write", 8),
    ("k_boxes", 4),
    ("k_narrow_static", 17),
    ("k_narrow_dynamic", 13),
    ("k_forces", 16),
    ("k_patch_gather", 21),
    ("k_patch_scatter", 12),
    ("k_gather_positions", 4),
    ("k_replica_objects", 5),
    ("k_replica_due", 22),
    ("k_replica_rank", 5),
    ("k_replica_take", 15),
    ("k_replica_pack", 13),
    ("k_replica_commit", 13),
    ("k_replica_carry", 5),
];

/// The parameter count of each `extern "C" __global__` function in the sources, read
/// from the text (for checking [`KERNELS`]).
pub fn declared_kernels() -> Vec<(String, usize)> {
    kernel_declarations()
        .into_iter()
        .map(|(name, params)| (name.to_string(), params.split(',').filter(|p| !p.trim().is_empty()).count()))
        .collect()
}

/// Every `extern "C" __global__` function of the sources as its name and the text of
/// its parameter list, in the sources' order (for [`declared_kernels`] and the launch
/// structs' check).
pub fn kernel_declarations() -> Vec<(&'static str, &'static str)> {
    const HEAD: &str = "extern \"C\" __global__ void ";
    let mut out = Vec::new();
    for (_, text) in SOURCES {
        let mut rest = text;
        while let Some(at) = rest.find(HEAD) {
            rest = &rest[at + HEAD.len()..];
            let Some(open) = rest.find('(') else { break };
            let Some(close) = rest.find(')') else { break };
            out.push((rest[..open].trim(), &rest[open + 1..close]));
            rest = &rest[close..];
        }
    }
    out
}

/// Why the kernels could not be compiled.
#[derive(Debug, thiserror::Error)]
pub enum CompileError {
    /// No NVRTC library could be loaded.
    #[error("the NVRTC library (libnvrtc.so) was not found")]
    NoNvrtc,
    /// NVRTC refused the program; the log says why.
    #[error("NVRTC failed ({status}):\n{log}")]
    Failed {
        /// NVRTC's status.
        status: String,
        /// The compiler's log.
        log: String,
    },
}

/// The whole program: every source file, with `#line` markers so errors name the file.
pub fn program_source() -> String {
    let mut s = String::new();
    for (name, text) in SOURCES {
        s.push_str(&format!("#line 1 \"{name}\"\n"));
        s.push_str(text);
        s.push('\n');
    }
    s
}

/// The compiler options for an architecture such as 90 (sm_90), plus `-I` for each
/// include directory.
pub fn options(arch: u32, include_dirs: &[PathBuf]) -> Vec<String> {
    let mut o: Vec<String> = vec![
        format!("-arch=sm_{arch}"),
        "--fmad=false".into(),
        "-prec-div=true".into(),
        "-prec-sqrt=true".into(),
        "-ftz=false".into(),
        "-std=c++17".into(),
        "-default-device".into(),
    ];
    o.extend(include_dirs.iter().map(|d| format!("-I{}", d.display())));
    o
}

/// Whether the NVRTC library can be loaded (takes ~140 ms the first time: it is large).
pub fn nvrtc_present() -> bool {
    // SAFETY: only tries to open the library; no NVRTC function is called.
    unsafe { nvrtc::is_culib_present() }
}

/// NVRTC's version as (major, minor).
pub fn nvrtc_version() -> Result<(i32, i32), CompileError> {
    if !nvrtc_present() {
        return Err(CompileError::NoNvrtc);
    }
    let (mut major, mut minor) = (0, 0);
    // SAFETY: the library is present (checked above); both pointers are valid.
    let r = unsafe { nvrtc::nvrtcVersion(&mut major, &mut minor) };
    check(r, None)?;
    Ok((major, minor))
}

fn status_name(r: nvrtc::nvrtcResult) -> String {
    // SAFETY: nvrtcGetErrorString returns a static string for any result code.
    unsafe {
        let p = nvrtc::nvrtcGetErrorString(r);
        if p.is_null() { format!("{r:?}") } else { CStr::from_ptr(p).to_string_lossy().into_owned() }
    }
}

fn check(r: nvrtc::nvrtcResult, log: Option<String>) -> Result<(), CompileError> {
    if r == nvrtc::nvrtcResult::NVRTC_SUCCESS {
        Ok(())
    } else {
        Err(CompileError::Failed { status: status_name(r), log: log.unwrap_or_default() })
    }
}

/// Compiles the program for `sm_{arch}` and returns the CUBIN. Needs NVRTC, not a GPU.
pub fn compile_cubin(arch: u32, include_dirs: &[PathBuf]) -> Result<Vec<u8>, CompileError> {
    compile_source(&program_source(), arch, include_dirs)
}

/// Compiles `source` (which may `#include` the kernels' [`HEADERS`] by name) for
/// `sm_{arch}` with the kernels' options and returns the CUBIN. Needs NVRTC, not a GPU.
/// Tests use it to check host-side layouts against the headers at compile time.
pub fn compile_source(source: &str, arch: u32, include_dirs: &[PathBuf]) -> Result<Vec<u8>, CompileError> {
    if !nvrtc_present() {
        return Err(CompileError::NoNvrtc);
    }
    let bad = |what: &str| CompileError::Failed { status: format!("{what} contains a NUL byte"), log: String::new() };
    let src = CString::new(source).map_err(|_| bad("the source"))?;
    let name = CString::new("myriad_kernels.cu").map_err(|_| bad("the name"))?;
    let header_text: Vec<CString> =
        HEADERS.iter().map(|(_, t)| CString::new(*t)).collect::<Result<_, _>>().map_err(|_| bad("a header"))?;
    let header_names: Vec<CString> =
        HEADERS.iter().map(|(n, _)| CString::new(*n)).collect::<Result<_, _>>().map_err(|_| bad("a header name"))?;
    let text_ptrs: Vec<*const c_char> = header_text.iter().map(|c| c.as_ptr()).collect();
    let name_ptrs: Vec<*const c_char> = header_names.iter().map(|c| c.as_ptr()).collect();
    let opts: Vec<CString> = options(arch, include_dirs)
        .into_iter()
        .map(CString::new)
        .collect::<Result<_, _>>()
        .map_err(|_| bad("an option"))?;
    let opt_ptrs: Vec<*const c_char> = opts.iter().map(|c| c.as_ptr()).collect();

    let mut prog: nvrtc::nvrtcProgram = std::ptr::null_mut();
    // SAFETY: every pointer refers to a NUL-terminated string that outlives the calls;
    // the arrays have the lengths passed; `prog` is destroyed below on every path.
    unsafe {
        check(
            nvrtc::nvrtcCreateProgram(
                &mut prog,
                src.as_ptr(),
                name.as_ptr(),
                HEADERS.len() as c_int,
                text_ptrs.as_ptr(),
                name_ptrs.as_ptr(),
            ),
            None,
        )?;
        let result = (|| {
            let r = nvrtc::nvrtcCompileProgram(prog, opt_ptrs.len() as c_int, opt_ptrs.as_ptr());
            if r != nvrtc::nvrtcResult::NVRTC_SUCCESS {
                return Err(CompileError::Failed { status: status_name(r), log: program_log(prog) });
            }
            let mut size = 0usize;
            check(nvrtc::nvrtcGetCUBINSize(prog, &mut size), None)?;
            let mut cubin = vec![0u8; size];
            check(nvrtc::nvrtcGetCUBIN(prog, cubin.as_mut_ptr() as *mut c_char), None)?;
            Ok(cubin)
        })();
        nvrtc::nvrtcDestroyProgram(&mut prog);
        result
    }
}

/// # Safety
/// `prog` must be a live program.
unsafe fn program_log(prog: nvrtc::nvrtcProgram) -> String {
    let mut size = 0usize;
    // SAFETY: `prog` is live (caller); the buffer has the size NVRTC asked for.
    unsafe {
        if nvrtc::nvrtcGetProgramLogSize(prog, &mut size) != nvrtc::nvrtcResult::NVRTC_SUCCESS || size == 0 {
            return String::new();
        }
        let mut buf = vec![0u8; size];
        if nvrtc::nvrtcGetProgramLog(prog, buf.as_mut_ptr() as *mut c_char) != nvrtc::nvrtcResult::NVRTC_SUCCESS {
            return String::new();
        }
        String::from_utf8_lossy(&buf).trim_end_matches('\0').to_string()
    }
}

/// The cache directory: `$MYRIAD_CUBIN_CACHE`, else `$XDG_CACHE_HOME/myriad/cubin`, else
/// `$HOME/.cache/myriad/cubin`.
pub fn cache_dir() -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("MYRIAD_CUBIN_CACHE") {
        return Some(PathBuf::from(d));
    }
    if let Some(d) = std::env::var_os("XDG_CACHE_HOME") {
        return Some(PathBuf::from(d).join("myriad/cubin"));
    }
    std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/myriad/cubin"))
}

/// The cache key: a hash of the source, headers, options, architecture and NVRTC version.
pub fn cache_key(arch: u32) -> String {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(program_source().as_bytes());
    for (n, t) in HEADERS {
        h.update(n.as_bytes());
        h.update(t.as_bytes());
    }
    for o in options(arch, &[]) {
        h.update(o.as_bytes());
        h.update(&[0]);
    }
    if let Ok((a, b)) = nvrtc_version() {
        h.update(&a.to_le_bytes());
        h.update(&b.to_le_bytes());
    }
    format!("myriad-sm{arch}-{:016x}", h.digest())
}

/// The CUBIN for `sm_{arch}`: from the cache when present, else compiled and stored.
/// Cache failures are logged and otherwise ignored (the compile still works).
pub fn cached_cubin(arch: u32) -> Result<Vec<u8>, CompileError> {
    let key = cache_key(arch);
    let path = cache_dir().map(|d| d.join(format!("{key}.cubin")));
    if let Some(p) = &path
        && let Ok(bytes) = std::fs::read(p)
        && !bytes.is_empty()
    {
        tracing::debug!("CUBIN from cache {}", p.display());
        return Ok(bytes);
    }
    let started = std::time::Instant::now();
    let cubin = compile_cubin(arch, &[])?;
    tracing::info!("compiled the CUDA kernels for sm_{arch} in {:.0} ms", started.elapsed().as_secs_f64() * 1e3);
    if let Some(p) = &path {
        let tmp = p.with_extension(format!("tmp{}", std::process::id()));
        let stored = p
            .parent()
            .map_or(Ok(()), std::fs::create_dir_all)
            .and_then(|_| std::fs::write(&tmp, &cubin))
            .and_then(|_| std::fs::rename(&tmp, p));
        if let Err(e) = stored {
            tracing::warn!("could not cache the CUBIN at {}: {e}", p.display());
        }
    }
    Ok(cubin)
}
