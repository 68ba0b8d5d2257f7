//! The device: context, stream, module and kernels, plus thin owners of device and pinned
//! host memory. Raw driver calls are used (through cudarc's `result` layer) so that
//! launches carry no per-launch bookkeeping; every call's status is checked. Kernels are
//! launched through the typed argument structs of the `launch` module, which build the
//! raw argument slots of `Gpu::launch_raw` in the kernel's order.

use std::cell::RefCell;
use std::collections::{BTreeMap, HashMap};
use std::ffi::{CString, c_void};
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytemuck::Pod;
use cudarc::driver::result;
use cudarc::driver::safe::CudaContext;
use cudarc::driver::sys::{self, CUdeviceptr, CUevent, CUfunction, CUmodule, CUstream};
use myriad_physics::PhysicsError;

use crate::compile;
use crate::launch::DevPtr;

/// A driver error as a [`PhysicsError`] naming the stage it happened in.
pub(crate) fn dev_err(stage: &'static str) -> impl Fn(result::DriverError) -> PhysicsError {
    move |e| PhysicsError::Device { stage, message: format!("{e:?}") }
}

/// Whether a CUDA driver library can be loaded.
pub fn driver_present() -> bool {
    // SAFETY: only tries to open the library; no driver function is called.
    unsafe { sys::is_culib_present() }
}

/// What [`probe`] found.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    /// The device's name.
    pub name: String,
    /// Compute capability as `major * 10 + minor` (90 for Hopper).
    pub arch: u32,
}

/// Checks for a driver, NVRTC and a device, in that order, without ever panicking: the
/// error says which is missing.
pub fn probe() -> Result<(Arc<CudaContext>, DeviceInfo), String> {
    probe_on(0)
}

/// [`probe`] for device `ordinal` (a zone per GPU picks its own).
pub fn probe_on(ordinal: usize) -> Result<(Arc<CudaContext>, DeviceInfo), String> {
    if !driver_present() {
        return Err("no CUDA driver library (libcuda.so) was found".into());
    }
    if !compile::nvrtc_present() {
        return Err("no NVRTC library (libnvrtc.so) was found".into());
    }
    let ctx = CudaContext::new(ordinal).map_err(|e| format!("no usable CUDA device {ordinal}: {e:?}"))?;
    let name = ctx.name().map_err(|e| format!("reading the device name: {e:?}"))?;
    let (major, minor) = ctx.compute_capability().map_err(|e| format!("reading the compute capability: {e:?}"))?;
    Ok((ctx, DeviceInfo { name, arch: (major * 10 + minor) as u32 }))
}

/// The profile's table: each name's launches (or spans), total, mean and median time,
/// largest total first.
fn profile_rows(samples: &BTreeMap<&'static str, Vec<f64>>) -> String {
    let mut rows: Vec<(&str, usize, f64, f64)> = samples
        .iter()
        .filter(|(_, ms)| !ms.is_empty())
        .map(|(&name, ms)| {
            let mut sorted = ms.clone();
            sorted.sort_by(f64::total_cmp);
            (name, ms.len(), ms.iter().sum::<f64>(), sorted[sorted.len() / 2])
        })
        .collect();
    rows.sort_by(|a, b| b.2.total_cmp(&a.2));
    let mut s =
        String::from("| kernel | launches | total ms | mean us | median us |\n| --- | ---: | ---: | ---: | ---: |\n");
    for (name, count, total, median) in rows {
        s.push_str(&format!(
            "| {name} | {count} | {total:.3} | {:.2} | {:.2} |\n",
            total * 1e3 / count as f64,
            median * 1e3
        ));
    }
    s
}

/// What the device gives one kernel, as the driver reports it for the block size it was
/// launched with: whether its registers or shared memory, not the work, bound how many
/// of its warps run at once.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Resources {
    /// Threads a block, at the kernel's first launch.
    block: u32,
    /// Registers a thread.
    registers: i32,
    /// Local memory a thread (registers spilled, arrays the compiler could not keep in
    /// registers).
    local_bytes: i32,
    /// Static shared memory a block.
    shared_bytes: i32,
    /// Blocks of `block` threads a multiprocessor runs at once at most.
    blocks_per_sm: i32,
}

/// The resources table: each kernel's block, registers, local and shared memory, and
/// the warps a multiprocessor runs at once at most (of 64 on sm_80 and sm_90).
fn resource_rows(rows: &[(&str, Resources)]) -> String {
    let mut s = String::from(
        "| kernel | block | registers a thread | local bytes a thread | shared bytes a block | warps a multiprocessor |\n\
         | --- | ---: | ---: | ---: | ---: | ---: |\n",
    );
    for (name, r) in rows {
        let warps = r.blocks_per_sm * r.block.div_ceil(32) as i32;
        s.push_str(&format!(
            "| {name} | {} | {} | {} | {} | {warps} |\n",
            r.block, r.registers, r.local_bytes, r.shared_bytes
        ));
    }
    s
}

/// A kernel argument.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Arg {
    /// A device pointer.
    P(CUdeviceptr),
    /// A 32-bit integer.
    U(u32),
    /// A 64-bit integer.
    L(u64),
    /// A float.
    F(f32),
}

/// Context, stream and loaded kernels.
pub(crate) struct Gpu {
    pub ctx: Arc<CudaContext>,
    pub info: DeviceInfo,
    pub stream: CUstream,
    module: CUmodule,
    kernels: HashMap<&'static str, (CUfunction, usize)>,
    /// Per-kernel timing, when `MYRIAD_CUDA_PROFILE=1`.
    profile: Option<RefCell<Profile>>,
}

/// Per-kernel device times: an event pair around every launch, folded into each name's
/// samples after each synchronization. Costs two event records per launch, so it is off
/// by default. Spans of host time between launches (named `host: ...`) join the same
/// samples. The table gives the median beside the mean: a run's first launches also
/// pay for allocating and first touching its buffers.
#[derive(Default)]
struct Profile {
    pending: Vec<(&'static str, Event, Event)>,
    spare: Vec<Event>,
    /// Milliseconds of each launch or span, by name.
    samples: BTreeMap<&'static str, Vec<f64>>,
    /// Each kernel's block size at its first launch (for the resources table).
    blocks: BTreeMap<&'static str, u32>,
}

// SAFETY: the stream, module and function handles belong to the context held in `ctx`;
// driver handles may be used from any thread once that context is current, which every
// entry point ensures with `bind`. The backend owning a `Gpu` is used by one thread at a
// time (`&mut self`).
unsafe impl Send for Gpu {}

impl Gpu {
    /// Probes device `ordinal`, loads (or compiles) the kernels and creates a stream.
    pub fn new(ordinal: usize) -> Result<Gpu, String> {
        let (ctx, info) = probe_on(ordinal)?;
        ctx.bind_to_thread().map_err(|e| format!("binding the context: {e:?}"))?;
        let cubin = compile::cached_cubin(info.arch).map_err(|e| format!("compiling the kernels: {e}"))?;
        // SAFETY: the context is current; `cubin` is a complete CUBIN image that stays
        // alive during the call.
        let module = unsafe { result::module::load_data(cubin.as_ptr() as *const c_void) }
            .map_err(|e| format!("loading the kernels for sm_{}: {e:?}", info.arch))?;
        let mut kernels = HashMap::new();
        for (name, arity) in compile::KERNELS {
            let c = CString::new(name).map_err(|e| e.to_string())?;
            // SAFETY: `module` was loaded above and is live.
            let f = unsafe { result::module::get_function(module, c) }
                .map_err(|e| format!("kernel {name} missing from the module: {e:?}"))?;
            kernels.insert(name, (f, arity));
        }
        let stream = result::stream::create(result::stream::StreamKind::NonBlocking)
            .map_err(|e| format!("creating a stream: {e:?}"))?;
        let profile = std::env::var("MYRIAD_CUDA_PROFILE").is_ok_and(|v| v == "1").then(RefCell::default);
        Ok(Gpu { ctx, info, stream, module, kernels, profile })
    }

    /// Makes the context current on the calling thread.
    pub fn bind(&self) -> Result<(), PhysicsError> {
        self.ctx.bind_to_thread().map_err(dev_err("bind"))
    }

    /// Launches kernel `name` on `grid` blocks of `block` threads with raw argument
    /// slots. Only the typed launches of [`crate::launch`] call this: they build `args`
    /// from a kernel's argument struct, so the slots are in the kernel's order.
    pub(crate) fn launch_raw(
        &self,
        name: &'static str,
        grid: u32,
        block: u32,
        args: &[Arg],
    ) -> Result<(), PhysicsError> {
        if grid == 0 {
            return Ok(());
        }
        let (f, arity) =
            *self.kernels.get(name).ok_or(PhysicsError::Device { stage: name, message: "unknown kernel".into() })?;
        if args.len() != arity {
            return Err(PhysicsError::Device {
                stage: name,
                message: format!("{} arguments for {arity} parameters", args.len()),
            });
        }
        // Each argument lives in an 8-byte slot; the driver reads as many bytes as the
        // kernel's parameter has (4 for u32/f32, little-endian low bytes).
        let mut store: Vec<u64> = args
            .iter()
            .map(|a| match *a {
                Arg::P(p) => p,
                Arg::U(v) => v as u64,
                Arg::L(v) => v,
                Arg::F(v) => v.to_bits() as u64,
            })
            .collect();
        let mut ptrs: Vec<*mut c_void> = store.iter_mut().map(|s| s as *mut u64 as *mut c_void).collect();
        let timing = match &self.profile {
            Some(p) => {
                let mut p = p.borrow_mut();
                p.blocks.entry(name).or_insert(block);
                let start = match p.spare.pop() {
                    Some(e) => e,
                    None => Event::new(self)?,
                };
                let end = match p.spare.pop() {
                    Some(e) => e,
                    None => Event::new(self)?,
                };
                self.record(start.raw)?;
                Some((start, end))
            }
            None => None,
        };
        // SAFETY: `f` comes from the loaded module; the argument slots match the kernel's
        // parameter list (built from the kernel's argument struct, whose fields are
        // checked against the C++ signature by `launch`'s tests) and live
        // until the launch call returns (the driver copies them).
        unsafe { result::launch_kernel(f, (grid, 1, 1), (block, 1, 1), 0, self.stream, &mut ptrs) }
            .map_err(dev_err(name))?;
        if let (Some((start, end)), Some(p)) = (timing, &self.profile) {
            self.record(end.raw)?;
            p.borrow_mut().pending.push((name, start, end));
        }
        Ok(())
    }

    /// Folds the kernel times recorded since the last call into the totals (after a
    /// synchronize; nothing to do unless profiling).
    pub fn collect_profile(&self) -> Result<(), PhysicsError> {
        let Some(p) = &self.profile else { return Ok(()) };
        let mut p = p.borrow_mut();
        let pending = std::mem::take(&mut p.pending);
        for (name, start, end) in pending {
            let ms = start.ms_to(&end)?;
            p.samples.entry(name).or_default().push(ms);
            p.spare.push(start);
            p.spare.push(end);
        }
        Ok(())
    }

    /// Adds the host time since `since` under `name` to the profile (when profiling): the
    /// host's own work and waits between launches, beside the kernels' device times.
    pub fn profile_host(&self, name: &'static str, since: Instant) {
        self.profile_span(name, since.elapsed());
    }

    /// Adds `took` under `name` to the profile, when profiling: a host span timed by
    /// its caller.
    pub fn profile_span(&self, name: &'static str, took: Duration) {
        if let Some(p) = &self.profile {
            p.borrow_mut().samples.entry(name).or_default().push(took.as_secs_f64() * 1e3);
        }
    }

    /// Forgets the samples gathered so far (the launches still pending are kept): a
    /// measurement that starts after its warm-up profiles only what it measures.
    pub fn restart_profile(&self) {
        if let Some(p) = &self.profile {
            p.borrow_mut().samples.clear();
        }
    }

    /// The per-kernel table (launches, total, mean and median time), then each launched
    /// kernel's resources (registers, local and shared memory, warps a multiprocessor
    /// runs at once), when profiling.
    pub fn profile_table(&self) -> Option<String> {
        let p = self.profile.as_ref()?.borrow();
        let rows: Vec<(&str, Resources)> =
            p.blocks.iter().filter_map(|(&name, &block)| Some((name, self.resources(name, block)?))).collect();
        Some(format!("{}\n{}", profile_rows(&p.samples), resource_rows(&rows)))
    }

    /// What the driver reports of kernel `name` launched with `block` threads a block;
    /// `None` when it cannot say (the table leaves the kernel out).
    fn resources(&self, name: &str, block: u32) -> Option<Resources> {
        use sys::CUfunction_attribute_enum as A;
        let &(f, _) = self.kernels.get(name)?;
        self.ctx.bind_to_thread().ok()?;
        // SAFETY: `f` belongs to the module this value loaded, which is still loaded;
        // the context is current.
        let attribute = |a: A| unsafe { result::function::get_function_attribute(f, a) }.ok();
        Some(Resources {
            block,
            registers: attribute(A::CU_FUNC_ATTRIBUTE_NUM_REGS)?,
            local_bytes: attribute(A::CU_FUNC_ATTRIBUTE_LOCAL_SIZE_BYTES)?,
            shared_bytes: attribute(A::CU_FUNC_ATTRIBUTE_SHARED_SIZE_BYTES)?,
            // SAFETY: as above; no dynamic shared memory (no launch asks for any).
            blocks_per_sm: unsafe { result::occupancy::max_active_block_per_multiprocessor(f, block as i32, 0) }
                .ok()?,
        })
    }

    /// Waits for everything queued on the stream.
    pub fn sync(&self) -> Result<(), PhysicsError> {
        // SAFETY: the stream is live.
        unsafe { result::stream::synchronize(self.stream) }.map_err(dev_err("synchronize"))
    }

    /// Copies `items` items from `src` to `dst` on the device, asynchronously.
    pub fn copy<T>(&self, dst: DevPtr<T>, src: DevPtr<T>, items: usize) -> Result<(), PhysicsError> {
        let bytes = items * std::mem::size_of::<T>();
        if bytes == 0 {
            return Ok(());
        }
        // SAFETY: both point to at least `items` items of device memory (callers pass
        // buffers and a count within both), and the two do not overlap.
        unsafe { result::memcpy_dtod_async(dst.raw(), src.raw(), bytes, self.stream) }.map_err(dev_err("copy"))
    }

    /// Fills `items` items at `dst` with zero bytes, asynchronously.
    pub fn zero<T>(&self, dst: DevPtr<T>, items: usize) -> Result<(), PhysicsError> {
        let bytes = items * std::mem::size_of::<T>();
        if bytes == 0 {
            return Ok(());
        }
        // SAFETY: `dst` points to at least `items` items of device memory (callers pass a
        // buffer and a count within it).
        unsafe { result::memset_d8_async(dst.raw(), 0, bytes, self.stream) }.map_err(dev_err("memset"))
    }

    /// Copies a host slice to device memory, ordered on the stream; the call returns once
    /// the source may be reused.
    pub fn upload<T: Pod>(&self, dst: &DevBuf<T>, src: &[T]) -> Result<(), PhysicsError> {
        let bytes = std::mem::size_of_val(src);
        if bytes == 0 {
            return Ok(());
        }
        if bytes > dst.bytes {
            return Err(PhysicsError::Device { stage: "upload", message: format!("{bytes} bytes into {}", dst.bytes) });
        }
        // SAFETY: the destination holds at least `bytes` bytes (checked). The copy is
        // ordered on this backend's stream: a plain cuMemcpyHtoD runs on the legacy
        // stream and, from pageable memory, may return before its DMA lands, so kernels
        // queued on this (non-blocking) stream could read the buffer first. Waiting for
        // the stream keeps `src` alive until the copy is done; uploads happen only when
        // the host changed the world, so the wait is rare.
        unsafe {
            result::memcpy_htod_async(dst.ptr().raw(), src, self.stream).map_err(dev_err("upload"))?;
            result::stream::synchronize(self.stream).map_err(dev_err("upload"))
        }
    }

    /// Queues a copy of the first `count` items of pinned host memory `src` to device
    /// memory, ordered on the stream: `src` must not change until the stream has passed
    /// the copy (an event or a synchronize).
    pub fn upload_async<T: Pod>(&self, dst: &DevBuf<T>, src: &Pinned, count: usize) -> Result<(), PhysicsError> {
        let bytes = count * std::mem::size_of::<T>();
        if bytes == 0 {
            return Ok(());
        }
        if bytes > dst.bytes || bytes > src.bytes {
            return Err(PhysicsError::Device {
                stage: "upload",
                message: format!("{bytes} bytes from {} into {}", src.bytes, dst.bytes),
            });
        }
        // SAFETY: both buffers hold at least `bytes` bytes (checked); `src` is pinned
        // memory owned by the caller, which keeps it unchanged until the copy is done.
        unsafe { sys::cuMemcpyHtoDAsync_v2(dst.ptr().raw(), src.ptr, bytes, self.stream).result() }
            .map_err(dev_err("upload"))
    }

    /// Queues a copy of `count` items of type `T` from device memory into pinned host
    /// memory, starting at item `at` of the host buffer; returns the bytes queued.
    pub fn download_async<T: Pod>(
        &self,
        dst: &mut Pinned,
        at: usize,
        src: DevPtr<T>,
        count: usize,
    ) -> Result<u64, PhysicsError> {
        let size = std::mem::size_of::<T>();
        let bytes = count * size;
        if bytes == 0 {
            return Ok(0);
        }
        if (at + count) * size > dst.bytes {
            return Err(PhysicsError::Device {
                stage: "download",
                message: format!("{bytes} bytes into {}", dst.bytes),
            });
        }
        // SAFETY: `dst` is pinned memory of at least `bytes` bytes that stays allocated
        // until the caller synchronizes the stream (it is owned by the backend).
        unsafe {
            sys::cuMemcpyDtoHAsync_v2((dst.ptr as *mut u8).add(at * size) as *mut c_void, src.raw(), bytes, self.stream)
                .result()
        }
        .map_err(dev_err("download"))?;
        Ok(bytes as u64)
    }

    /// Records `event` on the stream.
    pub fn record(&self, event: CUevent) -> Result<(), PhysicsError> {
        // SAFETY: both handles are live.
        unsafe { result::event::record(event, self.stream) }.map_err(dev_err("event"))
    }
}

impl Drop for Gpu {
    fn drop(&mut self) {
        if let Some(p) = self.profile.take() {
            // Events first, while the context is alive.
            drop(p);
        }
        if self.ctx.bind_to_thread().is_ok() {
            // SAFETY: the handles were created by this value and are not used after.
            unsafe {
                let _ = result::stream::synchronize(self.stream);
                let _ = result::stream::destroy(self.stream);
                let _ = result::module::unload(self.module);
            }
        }
    }
}

/// Device memory holding items of `T`, reallocated (contents dropped) when a larger size
/// is needed. The item type fixes the type of the pointers it hands out ([`DevPtr<T>`]),
/// so a buffer cannot be passed where a kernel expects another item type.
pub(crate) struct DevBuf<T> {
    ptr: DevPtr<T>,
    bytes: usize,
    ctx: Option<Arc<CudaContext>>,
}

impl<T> DevBuf<T> {
    /// An empty buffer.
    pub fn empty() -> DevBuf<T> {
        DevBuf { ptr: DevPtr::NULL, bytes: 0, ctx: None }
    }

    /// The buffer's address (null while empty).
    pub fn ptr(&self) -> DevPtr<T> {
        self.ptr
    }

    /// How many items of `T` fit (at most `u32::MAX`).
    pub fn capacity(&self) -> u32 {
        (self.bytes / std::mem::size_of::<T>()).min(u32::MAX as usize) as u32
    }

    /// Makes room for `bytes` bytes, reallocating with `headroom` (e.g. 1.25) when it has
    /// to grow. Returns whether it reallocated (the contents are then undefined).
    /// The size stays in bytes (not items) so that allocations are exactly those of
    /// the call sites' byte counts.
    pub fn ensure(&mut self, gpu: &Gpu, bytes: usize, headroom: f64) -> Result<bool, PhysicsError> {
        if bytes <= self.bytes && self.ptr.raw() != 0 {
            return Ok(false);
        }
        self.free();
        let want = ((bytes.max(64) as f64) * headroom) as usize;
        // SAFETY: the context is current (callers bind before any work).
        let ptr = unsafe { result::malloc_sync(want) }.map_err(dev_err("allocate"))?;
        self.ptr = DevPtr::from_raw(ptr);
        self.bytes = want;
        self.ctx = Some(gpu.ctx.clone());
        Ok(true)
    }

    /// Makes room for `bytes` bytes like [`ensure`](Self::ensure), but keeps the first
    /// `keep` bytes of the contents when it reallocates (copied on the device; waits for
    /// the stream, so it is for growth that happens rarely).
    pub fn grow_keeping(&mut self, gpu: &Gpu, bytes: usize, headroom: f64, keep: usize) -> Result<(), PhysicsError> {
        if bytes <= self.bytes && self.ptr.raw() != 0 {
            return Ok(());
        }
        let mut grown = DevBuf::<T>::empty();
        grown.ensure(gpu, bytes, headroom)?;
        let keep = keep.min(self.bytes);
        if keep > 0 {
            // SAFETY: both buffers hold at least `keep` bytes; the stream is waited for
            // before the old buffer is freed (on replacement below).
            unsafe {
                result::memcpy_dtod_async(grown.ptr.raw(), self.ptr.raw(), keep, gpu.stream)
                    .map_err(dev_err("copy"))?;
            }
            gpu.sync()?;
        }
        *self = grown;
        Ok(())
    }

    fn free(&mut self) {
        if self.ptr.raw() != 0
            && let Some(ctx) = &self.ctx
            && ctx.bind_to_thread().is_ok()
        {
            // SAFETY: `ptr` was allocated by `malloc_sync` in this context and is not
            // used after this point.
            unsafe {
                let _ = result::memory_free(self.ptr.raw());
            }
        }
        self.ptr = DevPtr::NULL;
        self.bytes = 0;
    }
}

impl<T> Drop for DevBuf<T> {
    fn drop(&mut self) {
        self.free();
    }
}

/// Page-locked host memory: the device copies it by DMA, asynchronously.
pub(crate) struct Pinned {
    ptr: *mut c_void,
    bytes: usize,
    ctx: Option<Arc<CudaContext>>,
}

// SAFETY: the buffer is plain memory owned by this value; it is only accessed through
// `&self`/`&mut self`.
unsafe impl Send for Pinned {}
// SAFETY: through `&self` the host only reads (`slice`, `range`, `device_ptr`); writes
// need `&mut self`. The device's writes are ordered by the caller, which reads a range
// only after waiting for the work that writes it.
unsafe impl Sync for Pinned {}

impl Pinned {
    /// An empty buffer.
    pub fn empty() -> Pinned {
        Pinned { ptr: std::ptr::null_mut(), bytes: 0, ctx: None }
    }

    /// Makes room for `bytes` bytes (contents dropped when it grows).
    pub fn ensure(&mut self, gpu: &Gpu, bytes: usize) -> Result<(), PhysicsError> {
        self.ensure_in(&gpu.ctx, bytes)
    }

    /// [`Pinned::ensure`] in context `ctx`, which is current on this thread.
    pub fn ensure_in(&mut self, ctx: &Arc<CudaContext>, bytes: usize) -> Result<(), PhysicsError> {
        if bytes <= self.bytes && !self.ptr.is_null() {
            return Ok(());
        }
        self.free();
        let want = bytes.max(64) * 5 / 4;
        // SAFETY: the context is current. Mapped into the device's address space, so that
        // kernels may store into it ([`Pinned::device_ptr`]).
        let ptr =
            unsafe { result::malloc_host(want, sys::CU_MEMHOSTALLOC_DEVICEMAP) }.map_err(dev_err("pinned allocate"))?;
        // Zero it so that reading any part of it is defined.
        // SAFETY: `ptr` points to `want` writable bytes.
        unsafe { std::ptr::write_bytes(ptr as *mut u8, 0, want) };
        self.ptr = ptr;
        self.bytes = want;
        self.ctx = Some(ctx.clone());
        Ok(())
    }

    /// The buffer's address for kernels (null while empty): a kernel's stores to it land
    /// in this host memory, visible to the host once the stream has passed the kernel
    /// (an event or a synchronize).
    pub fn device_ptr<T>(&self) -> Result<DevPtr<T>, PhysicsError> {
        if self.ptr.is_null() {
            return Ok(DevPtr::NULL);
        }
        let mut dptr: CUdeviceptr = 0;
        // SAFETY: `ptr` was allocated by `malloc_host` with `CU_MEMHOSTALLOC_DEVICEMAP`
        // in the current context and is live; `dptr` is a valid place to write.
        unsafe { sys::cuMemHostGetDevicePointer_v2(&mut dptr, self.ptr, 0).result() }.map_err(dev_err("pinned map"))?;
        Ok(DevPtr::from_raw(dptr))
    }

    /// Items `at..at + count` as `T`, and no byte outside them: the device may still be
    /// writing other parts of the buffer. Panics when the buffer holds fewer.
    pub fn range<T: Pod>(&self, at: usize, count: usize) -> &[T] {
        let size = std::mem::size_of::<T>();
        assert!((at + count) * size <= self.bytes, "pinned buffer too small");
        if count == 0 {
            return &[];
        }
        // SAFETY: the bytes are within the allocation (asserted) and initialised (zeroed
        // at allocation); the caller has waited for the device's writes to this range.
        // The offset keeps `T`'s alignment: the allocation is page aligned and `at` counts
        // whole items.
        let raw = unsafe { std::slice::from_raw_parts((self.ptr as *const u8).add(at * size), count * size) };
        bytemuck::cast_slice(raw)
    }

    /// The first `count` items as `T`. `T: Pod` (plain data: any bit pattern is a valid
    /// value, no padding) is what makes reading the bytes the device wrote as `T` sound.
    /// Panics when the buffer holds fewer than `count` items.
    pub fn slice<T: Pod>(&self, count: usize) -> &[T] {
        let bytes = count * std::mem::size_of::<T>();
        assert!(bytes <= self.bytes, "pinned buffer too small");
        if bytes == 0 {
            return &[];
        }
        // SAFETY: `ptr` points to `self.bytes >= bytes` bytes (asserted) that were
        // zeroed at allocation, so all of them are initialised; the borrow of `self`
        // keeps the buffer alive and unchanged (writes need `&mut self`).
        let raw = unsafe { std::slice::from_raw_parts(self.ptr as *const u8, bytes) };
        // The driver's pinned allocations are page aligned, so the cast cannot fail.
        bytemuck::cast_slice(raw)
    }

    /// The first `count` items as `T`, to write. Panics like [`slice`](Self::slice).
    pub fn slice_mut<T: Pod>(&mut self, count: usize) -> &mut [T] {
        let bytes = count * std::mem::size_of::<T>();
        assert!(bytes <= self.bytes, "pinned buffer too small");
        if bytes == 0 {
            return &mut [];
        }
        // SAFETY: as in `slice`; `&mut self` makes this the only view of the bytes.
        let raw = unsafe { std::slice::from_raw_parts_mut(self.ptr as *mut u8, bytes) };
        bytemuck::cast_slice_mut(raw)
    }

    fn free(&mut self) {
        if !self.ptr.is_null()
            && let Some(ctx) = &self.ctx
            && ctx.bind_to_thread().is_ok()
        {
            // SAFETY: allocated by `malloc_host`, not used after this point.
            unsafe {
                let _ = result::free_host(self.ptr);
            }
        }
        self.ptr = std::ptr::null_mut();
        self.bytes = 0;
    }
}

impl Drop for Pinned {
    fn drop(&mut self) {
        self.free();
    }
}

/// A CUDA event, for timing stages on the device.
pub(crate) struct Event {
    pub raw: CUevent,
    ctx: Arc<CudaContext>,
}

// SAFETY: as for `Gpu`: the handle belongs to the held context.
unsafe impl Send for Event {}
// SAFETY: the driver's event calls are thread-safe; several threads may wait for one
// event at once.
unsafe impl Sync for Event {}

impl Event {
    /// A new event in `gpu`'s context.
    pub fn new(gpu: &Gpu) -> Result<Event, PhysicsError> {
        let raw = result::event::create(sys::CUevent_flags::CU_EVENT_DEFAULT).map_err(dev_err("event"))?;
        Ok(Event { raw, ctx: gpu.ctx.clone() })
    }

    /// Blocks until the work recorded before this event is done.
    pub fn wait(&self) -> Result<(), PhysicsError> {
        // SAFETY: the event is live.
        unsafe { result::event::synchronize(self.raw) }.map_err(dev_err("event wait"))
    }

    /// Milliseconds from `self` to `end` (both recorded and complete).
    pub fn ms_to(&self, end: &Event) -> Result<f64, PhysicsError> {
        // SAFETY: both events are live and were recorded.
        unsafe { result::event::elapsed(self.raw, end.raw) }.map(f64::from).map_err(dev_err("event timing"))
    }
}

impl Drop for Event {
    fn drop(&mut self) {
        if self.ctx.bind_to_thread().is_ok() {
            // SAFETY: created by `new`, not used after.
            unsafe {
                let _ = result::event::destroy(self.raw);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_profile_table_gives_each_name_its_median_beside_its_mean() {
        let mut samples = BTreeMap::new();
        // A first launch that paid for its buffers, then the steady state.
        samples.insert("k_slow_start", vec![100.0, 1.0, 1.0, 2.0, 1.0]);
        samples.insert("host: span", vec![0.5, 0.5]);
        samples.insert("never", vec![]);
        let table = profile_rows(&samples);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines[0], "| kernel | launches | total ms | mean us | median us |");
        assert_eq!(lines[2], "| k_slow_start | 5 | 105.000 | 21000.00 | 1000.00 |");
        assert_eq!(lines[3], "| host: span | 2 | 1.000 | 500.00 | 500.00 |");
        assert_eq!(lines.len(), 4, "a name with no sample has no row: {table}");
    }

    #[test]
    fn the_resources_table_gives_each_kernels_warps_a_multiprocessor() {
        let due = Resources { block: 128, registers: 96, local_bytes: 0, shared_bytes: 2048, blocks_per_sm: 5 };
        // A block of 48 threads still takes two warps.
        let odd = Resources { block: 48, registers: 32, local_bytes: 24, shared_bytes: 0, blocks_per_sm: 32 };
        let table = resource_rows(&[("k_replica_due", due), ("k_odd", odd)]);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(
            lines[0],
            "| kernel | block | registers a thread | local bytes a thread | shared bytes a block | warps a multiprocessor |"
        );
        assert_eq!(lines[2], "| k_replica_due | 128 | 96 | 0 | 2048 | 20 |");
        assert_eq!(lines[3], "| k_odd | 48 | 32 | 24 | 0 | 64 |");
        assert_eq!(lines.len(), 4);
    }
}
