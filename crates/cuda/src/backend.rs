//! The two CUDA backends, over one device-resident pipeline.
//!
//! # How it works
//! World state lives on the device between steps; a step uploads only what the host
//! changed (detected through the world's generation counters: everything after spawns or
//! despawns, positions, actions and flags after teleports or new actions, the statics
//! when they change) and downloads the new state into pinned buffers. Per tick:
//!
//! 1. `build_dynamic_bvh`: object boxes; for `cuda` also Morton codes, the radix sort,
//!    Karras emission and the refit (`kernels/lbvh.cu`).
//! 2. `broad_static`, `broad_dynamic`: each object counts the static primitives and the
//!    other objects its box overlaps (tree walk for `cuda`, every target for
//!    `cuda-naive`); an exclusive scan gives each object its exact range; the host reads
//!    the two totals and grows the pair buffers to them (so no pair is ever dropped);
//!    a second pass writes and sorts each range (`kernels/broad.cu`).
//! 3. `narrow_static`, `narrow_dynamic`, `forces`: one thread per object sums its
//!    responses in the CPU's order and integrates (`kernels/physics.cu`).
//!
//! The two backends differ only in how step 2 finds candidates.
//!
//! # Performance note
//! Stage times come from CUDA events; the host's own time in a step (launch calls, the
//! mid-step read of the pair totals, copying the state into the `World`) is added to
//! `upload`, so the stages sum to the wall-clock time of the step.

use std::time::Instant;

use cudarc::driver::sys::CUdeviceptr;
use myriad_core::{Aabb, Vec3, World};
use myriad_physics::integrate::NpcTurn;
use myriad_physics::lbvh::morton::MortonFrame;
use myriad_physics::{AoiResults, Backend, BackendKind, PhysicsError, Stage, StepReport, TickConstants};
use rayon::prelude::*;

use crate::device::{Arg, DevBuf, Event, Gpu, Pinned};
use crate::params::DeviceParams;

const LEAF_LIMIT: usize = (1 << 31) - 1;
/// Passes of 8 bits over the 63-bit Morton codes.
const RADIX_PASSES: u32 = 8;
const RADIX_TILE: usize = 2048;
const SCAN_BLOCK: usize = 1024;
/// Up to this length one block scans the whole array in one launch (4 items a thread),
/// saving two launches. Not more: each thread reads its items one after the other, and at
/// 32 items a thread (the 32k-entry radix histogram of 260k keys) this one launch took
/// 52 us on an H200 where the three launches of the block-parallel scan took 12.6 us.
const SCAN_ONE_BLOCK: usize = 4 * 1024;
const NODE_BYTES: usize = 64;
const EVENTS: usize = 15;

/// Exclusive scans of u32 arrays on the device.
struct Scan {
    sums: DevBuf,
}

impl Scan {
    /// Replaces `data[0..len]` by its exclusive prefix sum.
    fn exclusive(&mut self, gpu: &Gpu, data: CUdeviceptr, len: usize) -> Result<(), PhysicsError> {
        if len == 0 {
            return Ok(());
        }
        if len <= SCAN_ONE_BLOCK {
            return gpu.launch_grid("k_scan_sums", 1, SCAN_BLOCK as u32, &[Arg::P(data), Arg::U(len as u32)]);
        }
        let blocks = len.div_ceil(SCAN_BLOCK);
        self.sums.ensure(gpu, blocks * 4, 1.5)?;
        let (d, l, s) = (Arg::P(data), Arg::U(len as u32), Arg::P(self.sums.ptr));
        gpu.launch_grid("k_scan_blocks", blocks as u32, SCAN_BLOCK as u32, &[d, l, s])?;
        gpu.launch_grid("k_scan_sums", 1, SCAN_BLOCK as u32, &[s, Arg::U(blocks as u32)])?;
        gpu.launch_grid("k_scan_add", blocks as u32, SCAN_BLOCK as u32, &[d, l, s])
    }
}

/// A linear BVH on the device (`kernels/lbvh.cu`).
struct Tree {
    keys: DevBuf,
    keys_tmp: DevBuf,
    /// `order[leaf]`: the object (or primitive) in that leaf.
    order: DevBuf,
    order_tmp: DevBuf,
    nodes: DevBuf,
    node_parent: DevBuf,
    leaf_parent: DevBuf,
    arrivals: DevBuf,
    hist: DevBuf,
    leaves: usize,
}

impl Tree {
    fn new() -> Tree {
        let e = DevBuf::empty;
        Tree {
            keys: e(),
            keys_tmp: e(),
            order: e(),
            order_tmp: e(),
            nodes: e(),
            node_parent: e(),
            leaf_parent: e(),
            arrivals: e(),
            hist: e(),
            leaves: 0,
        }
    }

    /// Writes the boxes of the `n` objects at `pos ± half` into `boxes` and builds the
    /// tree over them.
    #[allow(clippy::too_many_arguments)]
    fn build(
        &mut self,
        gpu: &Gpu,
        n: usize,
        pos: CUdeviceptr,
        half: CUdeviceptr,
        boxes: CUdeviceptr,
        frame: &MortonFrame,
    ) -> Result<(), PhysicsError> {
        self.leaves = n;
        if n == 0 {
            return Ok(());
        }
        for b in [&mut self.keys, &mut self.keys_tmp] {
            b.ensure(gpu, n * 8, 1.25)?;
        }
        for b in
            [&mut self.order, &mut self.order_tmp, &mut self.leaf_parent, &mut self.node_parent, &mut self.arrivals]
        {
            b.ensure(gpu, n * 4, 1.25)?;
        }
        self.nodes.ensure(gpu, n * NODE_BYTES, 1.25)?;
        let (m, s) = (frame.min, frame.scale);
        gpu.launch(
            "k_boxes_morton",
            n,
            &[
                Arg::U(n as u32),
                Arg::P(pos),
                Arg::P(half),
                Arg::P(boxes),
                Arg::P(self.keys.ptr),
                Arg::P(self.order.ptr),
                Arg::F(m.x),
                Arg::F(m.y),
                Arg::F(m.z),
                Arg::F(s.x),
                Arg::F(s.y),
                Arg::F(s.z),
            ],
        )?;
        // One-sweep radix sort: the digit counts of all passes, then one launch a pass.
        // `hist` holds the 8 x 256 counts, the 8 tile counters and 8 x 256 status words
        // a tile, all zeroed at once.
        let tiles = n.div_ceil(RADIX_TILE);
        let words = RADIX_PASSES as usize * (256 + 1 + 256 * tiles);
        self.hist.ensure(gpu, words * 4, 1.25)?;
        gpu.zero(self.hist.ptr, words * 4)?;
        let counters = self.hist.ptr + 4 * 256 * RADIX_PASSES as u64;
        let status = counters + 4 * RADIX_PASSES as u64;
        let nn = Arg::U(n as u32);
        let blocks = n.div_ceil(256).min(1024);
        gpu.launch_grid("k_radix_counts", blocks as u32, 256, &[Arg::P(self.keys.ptr), nn, Arg::P(self.hist.ptr)])?;
        for pass in 0..RADIX_PASSES {
            gpu.launch_grid(
                "k_radix_pass",
                tiles as u32,
                256,
                &[
                    Arg::P(self.keys.ptr),
                    Arg::P(self.order.ptr),
                    Arg::P(self.keys_tmp.ptr),
                    Arg::P(self.order_tmp.ptr),
                    nn,
                    Arg::U(pass),
                    Arg::P(self.hist.ptr),
                    Arg::P(status + 4 * (pass as u64) * 256 * tiles as u64),
                    Arg::P(counters + 4 * pass as u64),
                ],
            )?;
            std::mem::swap(&mut self.keys, &mut self.keys_tmp);
            std::mem::swap(&mut self.order, &mut self.order_tmp);
        }
        if n >= 2 {
            gpu.launch(
                "k_emit",
                n - 1,
                &[
                    Arg::P(self.keys.ptr),
                    Arg::U(n as u32),
                    Arg::P(self.nodes.ptr),
                    Arg::P(self.node_parent.ptr),
                    Arg::P(self.leaf_parent.ptr),
                ],
            )?;
            gpu.zero(self.arrivals.ptr, (n - 1) * 4)?;
            gpu.launch(
                "k_refit",
                n,
                &[
                    Arg::U(n as u32),
                    Arg::P(self.order.ptr),
                    Arg::P(boxes),
                    Arg::P(self.nodes.ptr),
                    Arg::P(self.node_parent.ptr),
                    Arg::P(self.leaf_parent.ptr),
                    Arg::P(self.arrivals.ptr),
                ],
            )?;
        }
        Ok(())
    }
}

/// Where the candidates of a query come from.
#[derive(Clone, Copy)]
enum Targets<'a> {
    /// Walk a tree over `boxes`.
    Tree(&'a Tree, CUdeviceptr),
    /// Test all `n` boxes.
    All(usize, CUdeviceptr),
}

/// Query boxes: `n` boxes at `boxes`, visited in the order `order` (0: in index order).
/// A tree count pass keeps each query's first `slots` targets at `scratch` (`slots` a
/// query), so the write pass walks the tree again only for queries with more.
#[derive(Clone, Copy)]
struct Queries {
    n: usize,
    boxes: CUdeviceptr,
    order: CUdeviceptr,
    scratch: CUdeviceptr,
    slots: u32,
}

/// Targets kept per object by the count pass: most objects have fewer contacts.
const SLOTS: u32 = 8;

/// The count pass: `counts[q]` = targets overlapping query box `q`; `counts[nq]` = 0.
fn count_pass(gpu: &Gpu, qs: Queries, exclude_self: bool, t: Targets, counts: CUdeviceptr) -> Result<(), PhysicsError> {
    let nq = qs.n;
    gpu.zero(counts + 4 * nq as u64, 4)?;
    let (q, qb, ex) = (Arg::U(nq as u32), Arg::P(qs.boxes), Arg::U(exclude_self as u32));
    match t {
        Targets::Tree(tree, tb) => gpu.launch(
            "k_tree_count",
            nq,
            &[
                q,
                qb,
                Arg::P(qs.order),
                ex,
                Arg::P(tree.nodes.ptr),
                Arg::P(tree.order.ptr),
                Arg::U(tree.leaves as u32),
                Arg::P(tb),
                Arg::P(counts),
                Arg::P(qs.scratch),
                Arg::U(qs.slots),
            ],
        ),
        Targets::All(nt, tb) => {
            gpu.launch("k_naive_count", nq, &[q, qb, ex, Arg::U(nt as u32), Arg::P(tb), Arg::P(counts)])
        }
    }
}

/// The write pass: each query's sorted targets at `out[offsets[q]..offsets[q + 1]]`,
/// for the queries whose range ends within `out`'s capacity.
fn write_pass(
    gpu: &Gpu,
    qs: Queries,
    exclude_self: bool,
    t: Targets,
    offsets: CUdeviceptr,
    out: &DevBuf,
) -> Result<(), PhysicsError> {
    let nq = qs.n;
    let (q, qb, ex) = (Arg::U(nq as u32), Arg::P(qs.boxes), Arg::U(exclude_self as u32));
    let cap = Arg::U(out.capacity::<u32>());
    let out = out.ptr;
    match t {
        Targets::Tree(tree, tb) => gpu.launch(
            "k_tree_write",
            nq,
            &[
                q,
                qb,
                Arg::P(qs.order),
                ex,
                Arg::P(tree.nodes.ptr),
                Arg::P(tree.order.ptr),
                Arg::U(tree.leaves as u32),
                Arg::P(tb),
                Arg::P(offsets),
                Arg::P(out),
                cap,
                Arg::P(qs.scratch),
                Arg::U(qs.slots),
            ],
        ),
        Targets::All(nt, tb) => gpu.launch(
            "k_naive_write",
            nq,
            &[q, qb, ex, Arg::U(nt as u32), Arg::P(tb), Arg::P(offsets), Arg::P(out), cap],
        ),
    }
}

/// Per-object device state.
struct Objects {
    pos: DevBuf,
    prev: DevBuf,
    half: DevBuf,
    radius: DevBuf,
    shape: DevBuf,
    kind: DevBuf,
    id: DevBuf,
    action: DevBuf,
    flags: DevBuf,
    boxes: DevBuf,
    acc: DevBuf,
    sup: DevBuf,
    static_counts: DevBuf,
    dynamic_counts: DevBuf,
    /// The count passes' kept targets, `SLOTS` an object.
    static_keep: DevBuf,
    dynamic_keep: DevBuf,
}

/// Static primitives on the device.
struct Prims {
    pos: DevBuf,
    half: DevBuf,
    radius: DevBuf,
    shape: DevBuf,
    boxes: DevBuf,
    count: usize,
}

/// Pinned host buffers for what comes back each step.
struct Host {
    pos: Pinned,
    prev: Pinned,
    action: Pinned,
    flags: Pinned,
    small: Pinned,
    aoi_offsets: Pinned,
    aoi_objects: Pinned,
}

// glam's Vec3 is `#[repr(C)] { x, y, z }` of f32: three packed floats.
const _: () = assert!(std::mem::size_of::<Vec3>() == 12 && std::mem::align_of::<Vec3>() == 4);

/// The vectors as packed floats (x, y, z, x, ...), without copying.
fn flat3(v: &[Vec3]) -> &[f32] {
    // SAFETY: Vec3 is repr(C) of three f32 with no padding (asserted above), so the
    // slice's memory is exactly `3 * len` initialised, aligned f32 values.
    unsafe { std::slice::from_raw_parts(v.as_ptr() as *const f32, v.len() * 3) }
}

/// `dst.copy_from_slice(src)`, on rayon's pool for large arrays: copying the state out
/// of pinned memory into the `World` is the largest host cost of a step, and one core's
/// memcpy bandwidth is a fraction of what the machine has.
fn par_copy<T: Copy + Send + Sync>(dst: &mut [T], src: &[T]) {
    const CHUNK: usize = 1 << 16;
    if dst.len() < 4 * CHUNK {
        dst.copy_from_slice(src);
    } else {
        dst.par_chunks_mut(CHUNK).zip(src.par_chunks(CHUNK)).for_each(|(d, s)| d.copy_from_slice(s));
    }
}

/// [`flat3`] for writing.
fn flat3_mut(v: &mut [Vec3]) -> &mut [f32] {
    // SAFETY: as in `flat3`; the borrow is unique.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr() as *mut f32, v.len() * 3) }
}

/// A CUDA backend: `cuda` (LBVH) or `cuda-naive` (all pairs).
pub struct CudaBackend {
    kind: BackendKind,
    n: usize,
    /// (generation, layout generation, address of the id vector, tick, seed) of the
    /// dynamics the device holds. The address, tick and seed tell two worlds with equal
    /// generation counters apart (a backend moved from one world to another).
    synced: Option<(u64, u64, usize, u64, u64)>,
    /// (generation, primitive count, address of the positions) of the statics on the
    /// device.
    statics_key: Option<(u64, usize, usize)>,
    /// (address, length) of the terrain samples uploaded.
    terrain_key: Option<(usize, usize)>,
    params_key: Option<DeviceParams>,
    /// The dynamics generation the dynamic boxes (and tree) were built at.
    boxes_fresh: Option<u64>,
    obj: Objects,
    prims: Prims,
    dyn_tree: Tree,
    static_tree: Tree,
    scan: Scan,
    static_pairs: DevBuf,
    dynamic_pairs: DevBuf,
    aoi_boxes: DevBuf,
    aoi_counts: DevBuf,
    aoi_out: DevBuf,
    params: DevBuf,
    counters: DevBuf,
    samples: DevBuf,
    host: Host,
    events: Vec<Event>,
    // Last: the context must outlive every buffer above (fields drop in order).
    gpu: Gpu,
}

impl CudaBackend {
    /// Probes the machine and sets up a backend of `kind` (`Cuda` or `CudaNaive`). Fails
    /// with [`PhysicsError::Unavailable`] saying why when there is no driver, NVRTC or
    /// device, or the kernels do not load.
    pub fn new(kind: BackendKind) -> Result<CudaBackend, PhysicsError> {
        let name = kind.name();
        if !matches!(kind, BackendKind::Cuda | BackendKind::CudaNaive) {
            return Err(PhysicsError::Unavailable { backend: name, reason: "not a CUDA backend kind".into() });
        }
        let gpu = Gpu::new().map_err(|reason| PhysicsError::Unavailable { backend: name, reason })?;
        let events = (0..EVENTS).map(|_| Event::new(&gpu)).collect::<Result<Vec<_>, _>>()?;
        let e = DevBuf::empty;
        let p = Pinned::empty;
        Ok(CudaBackend {
            kind,
            n: 0,
            synced: None,
            statics_key: None,
            terrain_key: None,
            params_key: None,
            boxes_fresh: None,
            obj: Objects {
                pos: e(),
                prev: e(),
                half: e(),
                radius: e(),
                shape: e(),
                kind: e(),
                id: e(),
                action: e(),
                flags: e(),
                boxes: e(),
                acc: e(),
                sup: e(),
                static_counts: e(),
                dynamic_counts: e(),
                static_keep: e(),
                dynamic_keep: e(),
            },
            prims: Prims { pos: e(), half: e(), radius: e(), shape: e(), boxes: e(), count: 0 },
            dyn_tree: Tree::new(),
            static_tree: Tree::new(),
            scan: Scan { sums: e() },
            static_pairs: e(),
            dynamic_pairs: e(),
            aoi_boxes: e(),
            aoi_counts: e(),
            aoi_out: e(),
            params: e(),
            counters: e(),
            samples: e(),
            host: Host { pos: p(), prev: p(), action: p(), flags: p(), small: p(), aoi_offsets: p(), aoi_objects: p() },
            events,
            gpu,
        })
    }

    fn naive(&self) -> bool {
        self.kind == BackendKind::CudaNaive
    }

    /// Uploads whatever the host changed since the device last saw the world.
    fn sync_world(&mut self, world: &World, k: Option<&TickConstants>) -> Result<(), PhysicsError> {
        let gpu = &self.gpu;
        let d = &world.dynamics;
        let n = d.len();
        if n > LEAF_LIMIT {
            return Err(PhysicsError::TooManyObjects { count: n, max: LEAF_LIMIT });
        }
        let (generation, layout) = (d.generation(), d.layout_generation());
        let identity = (d.ids().as_ptr() as usize, world.tick, world.seed);
        let o = &mut self.obj;
        if self.synced.map(|s| (s.1, s.2, s.3, s.4)) != Some((layout, identity.0, identity.1, identity.2))
            || self.n != n
        {
            // Objects came or went: slots changed meaning, upload everything.
            for b in [&mut o.pos, &mut o.prev, &mut o.half] {
                b.ensure(gpu, n * 12, 1.25)?;
            }
            for b in [&mut o.boxes, &mut o.acc] {
                b.ensure(gpu, n * 24, 1.25)?;
            }
            for b in [&mut o.radius, &mut o.id] {
                b.ensure(gpu, n * 4, 1.25)?;
            }
            for b in [&mut o.static_counts, &mut o.dynamic_counts] {
                b.ensure(gpu, (n + 1) * 4, 1.25)?;
            }
            for b in [&mut o.static_keep, &mut o.dynamic_keep] {
                b.ensure(gpu, n * SLOTS as usize * 4, 1.25)?;
            }
            for b in [&mut o.shape, &mut o.kind, &mut o.action, &mut o.flags, &mut o.sup] {
                b.ensure(gpu, n, 1.25)?;
            }
            gpu.upload(&o.half, flat3(d.half_extents()))?;
            gpu.upload(&o.radius, d.radii())?;
            gpu.upload(&o.shape, &d.shapes().iter().map(|s| *s as u8).collect::<Vec<u8>>())?;
            gpu.upload(&o.kind, &d.kinds().iter().map(|s| *s as u8).collect::<Vec<u8>>())?;
            gpu.upload(&o.id, &d.ids().iter().map(|i| i.0).collect::<Vec<u32>>())?;
            self.n = n;
            self.synced = None;
        }
        if self.synced.map(|s| s.0) != Some(generation) {
            gpu.upload(&o.pos, flat3(d.positions()))?;
            gpu.upload(&o.prev, flat3(d.prev_positions()))?;
            gpu.upload(&o.action, d.actions())?;
            gpu.upload(&o.flags, d.flags())?;
            self.boxes_fresh = None;
        }
        self.synced = Some((generation, layout, identity.0, identity.1, identity.2));

        let st = &world.statics;
        let key = (st.generation(), st.prim_count(), st.positions().as_ptr() as usize);
        if self.statics_key != Some(key) {
            let m = st.prim_count();
            let p = &mut self.prims;
            for b in [&mut p.pos, &mut p.half] {
                b.ensure(gpu, m * 12, 1.25)?;
            }
            p.boxes.ensure(gpu, m * 24, 1.25)?;
            p.radius.ensure(gpu, m * 4, 1.25)?;
            p.shape.ensure(gpu, m, 1.25)?;
            gpu.upload(&p.pos, flat3(st.positions()))?;
            gpu.upload(&p.half, flat3(st.half_extents()))?;
            gpu.upload(&p.radius, st.radii())?;
            gpu.upload(&p.shape, &st.shapes().iter().map(|s| *s as u8).collect::<Vec<u8>>())?;
            p.count = m;
            if self.kind == BackendKind::CudaNaive {
                gpu.launch(
                    "k_boxes",
                    m,
                    &[Arg::U(m as u32), Arg::P(p.pos.ptr), Arg::P(p.half.ptr), Arg::P(p.boxes.ptr)],
                )?;
            } else {
                let frame = MortonFrame::new(&world.bounds);
                self.static_tree.build(gpu, m, p.pos.ptr, p.half.ptr, p.boxes.ptr, &frame)?;
            }
            self.statics_key = Some(key);
        }

        let samples = world.terrain.samples();
        let tkey = (samples.as_ptr() as usize, samples.len());
        if self.terrain_key != Some(tkey) {
            self.samples.ensure(gpu, samples.len() * 2, 1.0)?;
            gpu.upload(&self.samples, samples)?;
            self.terrain_key = Some(tkey);
        }
        if let Some(k) = k {
            let params = DeviceParams::new(world, k);
            if self.params_key != Some(params) {
                self.params.ensure(gpu, 23 * 4, 1.0)?;
                gpu.upload(&self.params, &params.words())?;
                self.params_key = Some(params);
            }
        }
        Ok(())
    }

    /// Dynamic boxes (and, for `cuda`, the dynamic tree) at the device's positions.
    fn build_dynamic(&mut self, world: &World) -> Result<(), PhysicsError> {
        let n = self.n;
        let o = &self.obj;
        if self.naive() {
            self.gpu.launch(
                "k_boxes",
                n,
                &[Arg::U(n as u32), Arg::P(o.pos.ptr), Arg::P(o.half.ptr), Arg::P(o.boxes.ptr)],
            )
        } else {
            let frame = MortonFrame::new(&world.bounds);
            self.dyn_tree.build(&self.gpu, n, o.pos.ptr, o.half.ptr, o.boxes.ptr, &frame)
        }
    }

    fn static_targets(&self) -> Targets<'_> {
        if self.naive() {
            Targets::All(self.prims.count, self.prims.boxes.ptr)
        } else {
            Targets::Tree(&self.static_tree, self.prims.boxes.ptr)
        }
    }

    fn dynamic_targets(&self) -> Targets<'_> {
        if self.naive() {
            Targets::All(self.n, self.obj.boxes.ptr)
        } else {
            Targets::Tree(&self.dyn_tree, self.obj.boxes.ptr)
        }
    }

    /// The dynamic objects as queries, in the dynamic tree's leaf order for `cuda`, with
    /// `scratch` for the count pass's kept targets.
    fn object_queries(&self, scratch: &DevBuf) -> Queries {
        if self.naive() {
            return Queries { n: self.n, boxes: self.obj.boxes.ptr, order: 0, scratch: 0, slots: 0 };
        }
        Queries {
            n: self.n,
            boxes: self.obj.boxes.ptr,
            order: self.dyn_tree.order.ptr,
            scratch: scratch.ptr,
            slots: SLOTS,
        }
    }

    fn step_impl(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        // A step whose pair lists outgrew their buffers is redone once with buffers of
        // the exact size (the world is only written after a complete step).
        match self.try_step(world, k)? {
            Some(report) => Ok(report),
            None => self.try_step(world, k)?.ok_or(PhysicsError::Device {
                stage: "broad phase",
                message: "pair buffers still too small after growing them to the exact count".into(),
            }),
        }
    }

    /// One step, or `None` (world untouched) when a pair list did not fit: the buffers are
    /// then grown to the exact totals and the device state is marked for re-upload.
    fn try_step(&mut self, world: &mut World, k: &TickConstants) -> Result<Option<StepReport>, PhysicsError> {
        let wall = Instant::now();
        self.gpu.bind()?;
        let mut report = StepReport::default();
        self.gpu.record(self.events[0].raw)?;
        self.sync_world(world, Some(k))?;
        let n = self.n;
        if n == 0 {
            world.tick += 1;
            report.stage_ms[Stage::Upload as usize] = wall.elapsed().as_secs_f64() * 1e3;
            return Ok(Some(report));
        }
        let ev = |s: &Self, i: usize| s.gpu.record(s.events[i].raw);
        ev(self, 1)?;
        self.build_dynamic(world)?;
        ev(self, 2)?;

        let (sc, dc) = (self.obj.static_counts.ptr, self.obj.dynamic_counts.ptr);
        let (qs_static, qs_dynamic) =
            (self.object_queries(&self.obj.static_keep), self.object_queries(&self.obj.dynamic_keep));
        count_pass(&self.gpu, qs_static, false, self.static_targets(), sc)?;
        self.scan.exclusive(&self.gpu, sc, n + 1)?;
        ev(self, 3)?;
        count_pass(&self.gpu, qs_dynamic, true, self.dynamic_targets(), dc)?;
        self.scan.exclusive(&self.gpu, dc, n + 1)?;
        ev(self, 4)?;
        // No wait for the totals here: the write passes fill what fits, and the totals
        // come back with the state at the end of the step.
        self.static_pairs.ensure(&self.gpu, 4 * n, 1.0)?;
        self.dynamic_pairs.ensure(&self.gpu, 4 * n, 1.0)?;
        ev(self, 5)?;
        write_pass(&self.gpu, qs_static, false, self.static_targets(), sc, &self.static_pairs)?;
        ev(self, 6)?;
        write_pass(&self.gpu, qs_dynamic, true, self.dynamic_targets(), dc, &self.dynamic_pairs)?;
        ev(self, 7)?;
        let caps = [self.static_pairs.capacity::<u32>(), self.dynamic_pairs.capacity::<u32>()];

        self.counters.ensure(&self.gpu, 16, 1.0)?;
        self.gpu.zero(self.counters.ptr, 8)?;
        let o = &self.obj;
        let p = &self.prims;
        let (nn, kp) = (Arg::U(n as u32), Arg::P(self.params.ptr));
        let (pos, prev, half, radius, shape) =
            (Arg::P(o.pos.ptr), Arg::P(o.prev.ptr), Arg::P(o.half.ptr), Arg::P(o.radius.ptr), Arg::P(o.shape.ptr));
        let (acc, sup, counters) = (Arg::P(o.acc.ptr), Arg::P(o.sup.ptr), Arg::P(self.counters.ptr));
        self.gpu.launch(
            "k_narrow_static",
            n,
            &[
                nn,
                kp,
                pos,
                prev,
                half,
                radius,
                shape,
                Arg::P(p.pos.ptr),
                Arg::P(p.half.ptr),
                Arg::P(p.radius.ptr),
                Arg::P(p.shape.ptr),
                Arg::P(sc),
                Arg::P(self.static_pairs.ptr),
                Arg::U(caps[0]),
                acc,
                sup,
                counters,
            ],
        )?;
        ev(self, 8)?;
        self.gpu.launch(
            "k_narrow_dynamic",
            n,
            &[
                nn,
                kp,
                pos,
                prev,
                half,
                radius,
                shape,
                Arg::P(dc),
                Arg::P(self.dynamic_pairs.ptr),
                Arg::U(caps[1]),
                acc,
                sup,
                counters,
            ],
        )?;
        ev(self, 9)?;
        let turn = NpcTurn::at(world.tick, k.npc_period);
        self.gpu.launch(
            "k_forces",
            n,
            &[
                nn,
                kp,
                Arg::L(world.seed),
                Arg::L(world.tick),
                Arg::U(turn.period),
                Arg::U(turn.phase),
                pos,
                prev,
                half,
                Arg::P(o.kind.ptr),
                Arg::P(o.id.ptr),
                Arg::P(o.action.ptr),
                Arg::P(o.flags.ptr),
                acc,
                sup,
                Arg::P(self.samples.ptr),
            ],
        )?;
        ev(self, 10)?;
        let h = &mut self.host;
        let gpu = &self.gpu;
        h.pos.ensure(gpu, n * 12)?;
        h.prev.ensure(gpu, n * 12)?;
        h.action.ensure(gpu, n)?;
        h.flags.ensure(gpu, n)?;
        // The small totals first, then the state array by array, each followed by an
        // event: the host checks the totals as soon as they land and copies each array
        // into the World while the next one is still crossing the bus.
        h.small.ensure(gpu, 64)?;
        gpu.download_async::<u32>(&mut h.small, 0, self.counters.ptr, 2)?;
        gpu.download_async::<u32>(&mut h.small, 2, sc + 4 * n as u64, 1)?;
        gpu.download_async::<u32>(&mut h.small, 3, dc + 4 * n as u64, 1)?;
        gpu.record(self.events[12].raw)?;
        gpu.download_async::<f32>(&mut h.pos, 0, o.pos.ptr, 3 * n)?;
        gpu.record(self.events[13].raw)?;
        gpu.download_async::<f32>(&mut h.prev, 0, o.prev.ptr, 3 * n)?;
        gpu.record(self.events[14].raw)?;
        gpu.download_async::<u8>(&mut h.action, 0, o.action.ptr, n)?;
        gpu.download_async::<u8>(&mut h.flags, 0, o.flags.ptr, n)?;
        gpu.record(self.events[11].raw)?;
        self.events[12].wait()?;

        let small = h.small.slice::<u32>(4);
        let (contacts, totals) = ([small[0], small[1]], [small[2], small[3]]);
        if totals[0] > caps[0] || totals[1] > caps[1] {
            // Some list did not fit: grow to the exact totals and redo from the world,
            // which this step has not touched.
            gpu.sync()?;
            gpu.collect_profile()?;
            self.static_pairs.ensure(gpu, totals[0] as usize * 4, 1.0)?;
            self.dynamic_pairs.ensure(gpu, totals[1] as usize * 4, 1.0)?;
            self.synced = None;
            return Ok(None);
        }
        report.static_pairs = totals[0] as u64;
        report.dynamic_pairs = totals[1] as u64 / 2;
        report.static_contacts = contacts[0] as u64;
        report.dynamic_contacts = contacts[1] as u64;
        {
            let st = world.dynamics.state_mut();
            self.events[13].wait()?;
            par_copy(flat3_mut(st.pos), h.pos.slice::<f32>(3 * n));
            self.events[14].wait()?;
            par_copy(flat3_mut(st.prev), h.prev.slice::<f32>(3 * n));
            gpu.sync()?;
            par_copy(st.action, h.action.slice::<u8>(n));
            par_copy(st.flags, h.flags.slice::<u8>(n));
        }
        gpu.collect_profile()?;
        world.tick += 1;
        let d = &world.dynamics;
        self.synced = Some((d.generation(), d.layout_generation(), d.ids().as_ptr() as usize, world.tick, world.seed));
        self.boxes_fresh = None;

        let e = &self.events;
        let t = |a: usize, b: usize| e[a].ms_to(&e[b]);
        let ms = &mut report.stage_ms;
        ms[Stage::BuildDynamicBvh as usize] = t(1, 2)?;
        ms[Stage::BroadStatic as usize] = t(2, 3)? + t(5, 6)?;
        ms[Stage::BroadDynamic as usize] = t(3, 4)? + t(6, 7)?;
        ms[Stage::NarrowStatic as usize] = t(7, 8)?;
        ms[Stage::NarrowDynamic as usize] = t(8, 9)?;
        ms[Stage::Forces as usize] = t(9, 10)?;
        let device: f64 = ms.iter().sum();
        let wall_ms = wall.elapsed().as_secs_f64() * 1e3;
        ms[Stage::Upload as usize] = t(0, 1)? + t(10, 11)? + (wall_ms - device - t(0, 1)? - t(10, 11)?).max(0.0);
        Ok(Some(report))
    }

    /// The candidate pairs of the world as it is, without stepping: static pairs as
    /// `object << 32 | primitive` sorted by (object, primitive), dynamic pairs as
    /// `a << 32 | b` with `a < b`, sorted. For checking the broad phase against the CPU.
    pub fn broad_pairs(&mut self, world: &World) -> Result<(Vec<u64>, Vec<u64>), PhysicsError> {
        let r = self.broad_pairs_impl(world);
        if r.is_err() {
            self.synced = None;
            self.n = usize::MAX;
        }
        r
    }

    fn broad_pairs_impl(&mut self, world: &World) -> Result<(Vec<u64>, Vec<u64>), PhysicsError> {
        self.gpu.bind()?;
        self.sync_world(world, None)?;
        let n = self.n;
        if n == 0 {
            return Ok((Vec::new(), Vec::new()));
        }
        self.build_dynamic(world)?;
        self.boxes_fresh = Some(world.dynamics.generation());
        let (sc, dc) = (self.obj.static_counts.ptr, self.obj.dynamic_counts.ptr);
        let (qs_static, qs_dynamic) =
            (self.object_queries(&self.obj.static_keep), self.object_queries(&self.obj.dynamic_keep));
        count_pass(&self.gpu, qs_static, false, self.static_targets(), sc)?;
        self.scan.exclusive(&self.gpu, sc, n + 1)?;
        count_pass(&self.gpu, qs_dynamic, true, self.dynamic_targets(), dc)?;
        self.scan.exclusive(&self.gpu, dc, n + 1)?;
        let mut lists = Vec::new();
        for (counts, exclude_self) in [(sc, false), (dc, true)] {
            let mut offsets = Pinned::empty();
            offsets.ensure(&self.gpu, (n + 1) * 4)?;
            self.gpu.download_async::<u32>(&mut offsets, 0, counts, n + 1)?;
            self.gpu.sync()?;
            let offsets: Vec<u32> = offsets.slice::<u32>(n + 1).to_vec();
            let total = offsets[n] as usize;
            let mut out = DevBuf::empty();
            out.ensure(&self.gpu, total * 4, 1.0)?;
            let targets = if exclude_self { self.dynamic_targets() } else { self.static_targets() };
            let qs = if exclude_self { qs_dynamic } else { qs_static };
            write_pass(&self.gpu, qs, exclude_self, targets, counts, &out)?;
            let mut host = Pinned::empty();
            host.ensure(&self.gpu, total * 4)?;
            self.gpu.download_async::<u32>(&mut host, 0, out.ptr, total)?;
            self.gpu.sync()?;
            let items = host.slice::<u32>(total);
            let mut pairs = Vec::with_capacity(total);
            for obj in 0..n {
                for &t in &items[offsets[obj] as usize..offsets[obj + 1] as usize] {
                    if !exclude_self || (t as usize) > obj {
                        pairs.push((obj as u64) << 32 | t as u64);
                    }
                }
            }
            lists.push(pairs);
        }
        let dynamic = lists.pop().unwrap_or_default();
        let statics = lists.pop().unwrap_or_default();
        Ok((statics, dynamic))
    }

    fn query_impl(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        self.gpu.bind()?;
        self.sync_world(world, None)?;
        out.clear();
        let nq = boxes.len();
        if nq == 0 {
            out.offsets.push(0);
            return Ok(());
        }
        if self.n == 0 {
            out.offsets.resize(nq + 1, 0);
            return Ok(());
        }
        let generation = world.dynamics.generation();
        if self.boxes_fresh != Some(generation) {
            self.build_dynamic(world)?;
            self.boxes_fresh = Some(generation);
        }
        let gpu = &self.gpu;
        self.aoi_boxes.ensure(gpu, nq * 24, 1.25)?;
        self.aoi_counts.ensure(gpu, (nq + 1) * 4, 1.25)?;
        let flat: Vec<f32> = boxes.iter().flat_map(|b| [b.min.to_array(), b.max.to_array()]).flatten().collect();
        gpu.upload(&self.aoi_boxes, &flat)?;
        let qs = Queries { n: nq, boxes: self.aoi_boxes.ptr, order: 0, scratch: 0, slots: 0 };
        count_pass(gpu, qs, false, self.dynamic_targets(), self.aoi_counts.ptr)?;
        self.scan.exclusive(gpu, self.aoi_counts.ptr, nq + 1)?;
        self.host.aoi_offsets.ensure(gpu, (nq + 1) * 4)?;
        gpu.download_async::<u32>(&mut self.host.aoi_offsets, 0, self.aoi_counts.ptr, nq + 1)?;
        gpu.sync()?;
        let total = self.host.aoi_offsets.slice::<u32>(nq + 1)[nq] as usize;
        self.aoi_out.ensure(gpu, total * 4, 1.25)?;
        write_pass(gpu, qs, false, self.dynamic_targets(), self.aoi_counts.ptr, &self.aoi_out)?;
        let h = &mut self.host;
        h.aoi_objects.ensure(gpu, total * 4)?;
        gpu.download_async::<u32>(&mut h.aoi_objects, 0, self.aoi_out.ptr, total)?;
        gpu.sync()?;
        gpu.collect_profile()?;
        out.offsets.extend_from_slice(h.aoi_offsets.slice::<u32>(nq + 1));
        out.objects.extend_from_slice(h.aoi_objects.slice::<u32>(total));
        Ok(())
    }
}

impl Drop for CudaBackend {
    fn drop(&mut self) {
        if let Some(table) = self.gpu.profile_table() {
            eprintln!("per-kernel device time, {} ({} objects):\n{table}", self.description(), self.n);
        }
    }
}

impl Backend for CudaBackend {
    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }

    fn kind(&self) -> BackendKind {
        self.kind
    }

    fn description(&self) -> String {
        let how = if self.naive() { "all pairs" } else { "LBVH, device-resident" };
        format!("{} ({}, sm_{}, {how})", self.kind, self.gpu.info.name, self.gpu.info.arch)
    }

    fn step(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        let r = self.step_impl(world, k);
        if r.is_err() {
            // The device copy may be half updated: make the next call upload everything.
            self.synced = None;
            self.n = usize::MAX;
        }
        r
    }

    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        let r = self.query_impl(world, boxes, out);
        if r.is_err() {
            self.synced = None;
            self.n = usize::MAX;
        }
        r
    }
}
