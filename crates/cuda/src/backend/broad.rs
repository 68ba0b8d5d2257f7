//! The broad phase (`kernels/broad.cu`): a count pass gives each query the number of
//! targets its box overlaps, a scan turns the counts into ranges, and a write pass fills
//! each range with the query's sorted targets. Targets come from a tree walk (`cuda`) or
//! from testing every target (`cuda-naive`). The same passes serve the step's static
//! and dynamic pairs, [`CudaBackend::broad_pairs`](super::CudaBackend::broad_pairs) and the area-of-interest queries.

use myriad_core::World;
use myriad_physics::PhysicsError;

use super::Resident;
use super::tree::Tree;
use crate::device::{DevBuf, Gpu, Pinned};
use crate::launch::{DevPtr, KNaiveCount, KNaiveWrite, KTreeCount, KTreeWrite};

/// Targets kept per object by the count pass: most objects have fewer contacts.
pub(super) const SLOTS: u32 = 8;

/// Where the candidates of a query come from.
#[derive(Clone, Copy)]
pub(super) enum Targets<'a> {
    /// Walk a tree over `boxes`.
    Tree(&'a Tree, DevPtr<f32>),
    /// Test all `n` boxes.
    All(usize, DevPtr<f32>),
}

/// Query boxes: `n` boxes at `boxes`, visited in the order `order` (null: in index
/// order). A tree count pass keeps each query's first `slots` targets at `scratch`
/// (`slots` a query), so the write pass walks the tree again only for queries with more.
/// The write pass sorts each range on its thread (the canonical order of the step's
/// short lists of contacts).
#[derive(Clone, Copy)]
pub(super) struct Queries {
    pub n: usize,
    pub boxes: DevPtr<f32>,
    pub order: DevPtr<u32>,
    pub scratch: DevPtr<u32>,
    pub slots: u32,
}

impl Queries {
    /// `n` boxes at `boxes`, in index order, with no kept targets.
    pub fn plain(n: usize, boxes: DevPtr<f32>) -> Queries {
        Queries { n, boxes, order: DevPtr::NULL, scratch: DevPtr::NULL, slots: 0 }
    }
}

/// The count pass: `counts[q]` = targets overlapping query box `q`; `counts[nq]` = 0.
pub(super) fn count_pass(
    gpu: &Gpu,
    qs: Queries,
    exclude_self: bool,
    t: Targets,
    counts: DevPtr<u32>,
) -> Result<(), PhysicsError> {
    let nq = qs.n;
    gpu.zero(counts.add(nq), 1)?;
    let exclude_self = exclude_self as u32;
    match t {
        Targets::Tree(tree, tboxes) => gpu.launch(
            nq,
            KTreeCount {
                nq: nq as u32,
                qboxes: qs.boxes,
                qorder: qs.order,
                exclude_self,
                nodes: tree.nodes.ptr(),
                order: tree.order.ptr(),
                nleaves: tree.leaves as u32,
                tboxes,
                counts,
                scratch: qs.scratch,
                slots: qs.slots,
            },
        ),
        Targets::All(nt, tboxes) => {
            gpu.launch(nq, KNaiveCount { nq: nq as u32, qboxes: qs.boxes, exclude_self, nt: nt as u32, tboxes, counts })
        }
    }
}

/// The write pass: each query's sorted targets at `out[offsets[q]..offsets[q + 1]]`,
/// for the queries whose range ends within `out`'s capacity.
pub(super) fn write_pass(
    gpu: &Gpu,
    qs: Queries,
    exclude_self: bool,
    t: Targets,
    offsets: DevPtr<u32>,
    out: &DevBuf<u32>,
) -> Result<(), PhysicsError> {
    let nq = qs.n;
    let exclude_self = exclude_self as u32;
    let cap = out.capacity();
    let out = out.ptr();
    match t {
        Targets::Tree(tree, tboxes) => gpu.launch(
            nq,
            KTreeWrite {
                nq: nq as u32,
                qboxes: qs.boxes,
                qorder: qs.order,
                exclude_self,
                nodes: tree.nodes.ptr(),
                order: tree.order.ptr(),
                nleaves: tree.leaves as u32,
                tboxes,
                offsets,
                out,
                cap,
                scratch: qs.scratch,
                slots: qs.slots,
            },
        ),
        Targets::All(nt, tboxes) => gpu.launch(
            nq,
            KNaiveWrite { nq: nq as u32, qboxes: qs.boxes, exclude_self, nt: nt as u32, tboxes, offsets, out, cap },
        ),
    }
}

impl Resident {
    /// The static primitives as targets.
    pub(super) fn static_targets(&self) -> Targets<'_> {
        if self.naive() {
            Targets::All(self.prims.count, self.prims.boxes.ptr())
        } else {
            Targets::Tree(&self.static_tree, self.prims.boxes.ptr())
        }
    }

    /// The dynamic objects as targets.
    pub(super) fn dynamic_targets(&self) -> Targets<'_> {
        if self.naive() {
            Targets::All(self.n, self.obj.boxes.ptr())
        } else {
            Targets::Tree(&self.dyn_tree, self.obj.boxes.ptr())
        }
    }

    /// The dynamic objects as queries, in the dynamic tree's leaf order for `cuda`, with
    /// `scratch` for the count pass's kept targets.
    pub(super) fn object_queries(&self, scratch: &DevBuf<u32>) -> Queries {
        if self.naive() {
            return Queries::plain(self.n, self.obj.boxes.ptr());
        }
        Queries {
            n: self.n,
            boxes: self.obj.boxes.ptr(),
            order: self.dyn_tree.order.ptr(),
            scratch: scratch.ptr(),
            slots: SLOTS,
        }
    }

    /// The count passes and scans of a step's static and dynamic pairs: afterwards
    /// `static_counts` and `dynamic_counts` hold each object's range start, and their
    /// entry `n` the total. Returns the two query sets for the write passes.
    pub(super) fn count_pairs(
        &mut self,
        mut after_static: impl FnMut(&Self) -> Result<(), PhysicsError>,
    ) -> Result<(Queries, Queries), PhysicsError> {
        let n = self.n;
        let (sc, dc) = (self.obj.static_counts.ptr(), self.obj.dynamic_counts.ptr());
        let (qs_static, qs_dynamic) =
            (self.object_queries(&self.obj.static_keep), self.object_queries(&self.obj.dynamic_keep));
        count_pass(&self.gpu, qs_static, false, self.static_targets(), sc)?;
        self.scan.exclusive(&self.gpu, sc, n + 1)?;
        after_static(self)?;
        count_pass(&self.gpu, qs_dynamic, true, self.dynamic_targets(), dc)?;
        self.scan.exclusive(&self.gpu, dc, n + 1)?;
        Ok((qs_static, qs_dynamic))
    }

    pub(super) fn broad_pairs_impl(&mut self, world: &World) -> Result<(Vec<u64>, Vec<u64>), PhysicsError> {
        self.gpu.bind()?;
        self.sync_world(world, None)?;
        let n = self.n;
        if n == 0 {
            return Ok((Vec::new(), Vec::new()));
        }
        self.build_dynamic(world)?;
        self.boxes_fresh = Some(world.dynamics.generation());
        let (sc, dc) = (self.obj.static_counts.ptr(), self.obj.dynamic_counts.ptr());
        let (qs_static, qs_dynamic) = self.count_pairs(|_| Ok(()))?;
        let mut lists = Vec::new();
        for (counts, exclude_self) in [(sc, false), (dc, true)] {
            let mut offsets = Pinned::empty();
            offsets.ensure(&self.gpu, (n + 1) * 4)?;
            self.gpu.download_async(&mut offsets, 0, counts, n + 1)?;
            self.gpu.sync()?;
            let offsets: Vec<u32> = offsets.slice::<u32>(n + 1).to_vec();
            let total = offsets[n] as usize;
            let mut out = DevBuf::<u32>::empty();
            out.ensure(&self.gpu, total * 4, 1.0)?;
            let targets = if exclude_self { self.dynamic_targets() } else { self.static_targets() };
            let qs = if exclude_self { qs_dynamic } else { qs_static };
            write_pass(&self.gpu, qs, exclude_self, targets, counts, &out)?;
            let mut host = Pinned::empty();
            host.ensure(&self.gpu, total * 4)?;
            self.gpu.download_async(&mut host, 0, out.ptr(), total)?;
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
}
