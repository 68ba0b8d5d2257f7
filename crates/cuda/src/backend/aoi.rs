//! Area-of-interest queries on the device: the broad phase's count and write passes
//! with the query boxes as queries and the dynamic objects as targets.

use myriad_core::{Aabb, World};
use myriad_physics::{AoiResults, PhysicsError};

use super::CudaBackend;
use super::broad::{Queries, count_pass, write_pass};
use crate::launch::KTreeGather;

impl CudaBackend {
    /// The objects overlapping each box of `boxes`, as CSR lists in `out`.
    pub(super) fn query_impl(
        &mut self,
        world: &World,
        boxes: &[Aabb],
        out: &mut AoiResults,
    ) -> Result<(), PhysicsError> {
        out.clear();
        let nq = boxes.len();
        let total = self.aoi_on_device(world, boxes, true)?.total;
        if nq == 0 || self.n == 0 {
            out.offsets.resize(nq + 1, 0);
            return Ok(());
        }
        let gpu = &self.gpu;
        let h = &mut self.host;
        h.aoi_offsets.ensure(gpu, (nq + 1) * 4)?;
        h.aoi_objects.ensure(gpu, total * 4)?;
        gpu.download_async(&mut h.aoi_offsets, 0, self.aoi_counts.ptr(), nq + 1)?;
        gpu.download_async(&mut h.aoi_objects, 0, self.aoi_out.ptr(), total)?;
        gpu.sync()?;
        gpu.collect_profile()?;
        out.offsets.extend_from_slice(h.aoi_offsets.slice::<u32>(nq + 1));
        out.objects.extend_from_slice(h.aoi_objects.slice::<u32>(total));
        Ok(())
    }

    /// Answers the queries into device memory: the lists' range starts (`nq + 1`) are in
    /// `aoi_counts`, their slots in `aoi_out`, and only a total comes back to the host.
    /// With `sorted`, each list is sorted by slot and fills its range (CSR). Without, a
    /// list is in the order the tree walk found it, and may be written by one walk into
    /// ranges of a fixed stride sized from the previous call (then `lens` is set and
    /// `aoi_lens` holds each list's length); a list longer than its range makes the
    /// query run again as count and write passes, so no target is ever dropped. With no
    /// box or no object nothing is launched and the device buffers are not written.
    pub(super) fn aoi_on_device(
        &mut self,
        world: &World,
        boxes: &[Aabb],
        sorted: bool,
    ) -> Result<AoiOnDevice, PhysicsError> {
        self.gpu.bind()?;
        self.sync_world(world, None)?;
        let nq = boxes.len();
        if nq == 0 || self.n == 0 {
            return Ok(AoiOnDevice { total: 0, lens: false });
        }
        // The boxes of the last step (or query) serve as long as no one moved an object.
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
        if !sorted
            && !self.naive()
            && let Some(total) = self.aoi_one_walk(nq)?
        {
            return Ok(AoiOnDevice { total, lens: true });
        }
        let gpu = &self.gpu;
        let qs = Queries { sorted, ..Queries::plain(nq, self.aoi_boxes.ptr()) };
        count_pass(gpu, qs, false, self.dynamic_targets(), self.aoi_counts.ptr())?;
        self.scan.exclusive(gpu, self.aoi_counts.ptr(), nq + 1)?;
        self.host.small.ensure(gpu, 4)?;
        gpu.download_async(&mut self.host.small, 0, self.aoi_counts.ptr().add(nq), 1)?;
        gpu.sync()?;
        let total = self.host.small.slice::<u32>(1)[0] as usize;
        self.aoi_out.ensure(gpu, total * 4, 1.25)?;
        write_pass(gpu, qs, false, self.dynamic_targets(), self.aoi_counts.ptr(), &self.aoi_out)?;
        let walk = &mut self.aoi_walk;
        walk.total = total;
        walk.pause = walk.pause.saturating_sub(1);
        if walk.stride.is_none() && walk.pause == 0 {
            // A first guess: the mean list; the next walk measures the longest.
            walk.stride = Some(stride_for(total.div_ceil(nq)));
        }
        Ok(AoiOnDevice { total, lens: false })
    }

    /// The one-walk query into strided ranges, if the stride guess exists, its output
    /// stays within [`WALK_ROOM`] times the last exact total, and no list outgrew it: the
    /// slots in all ranges.
    fn aoi_one_walk(&mut self, nq: usize) -> Result<Option<usize>, PhysicsError> {
        let Some(stride) = self.aoi_walk.stride else { return Ok(None) };
        let slots = nq * stride as usize;
        if slots > WALK_ROOM * self.aoi_walk.total + (1 << 16) || slots >= u32::MAX as usize {
            // Lists too uneven for one stride (a crowd in a few views): count and write
            // for a while before trying again.
            self.aoi_walk.stride = None;
            self.aoi_walk.pause = WALK_PAUSE;
            return Ok(None);
        }
        let gpu = &self.gpu;
        self.aoi_out.ensure(gpu, slots * 4, 1.25)?;
        self.aoi_lens.ensure(gpu, nq * 4, 1.25)?;
        self.aoi_most.ensure(gpu, 4, 1.0)?;
        gpu.zero(self.aoi_most.ptr(), 1)?;
        gpu.launch(
            nq,
            KTreeGather {
                nq: nq as u32,
                qboxes: self.aoi_boxes.ptr(),
                nodes: self.dyn_tree.nodes.ptr(),
                order: self.dyn_tree.order.ptr(),
                nleaves: self.dyn_tree.leaves as u32,
                tboxes: self.obj.boxes.ptr(),
                stride,
                offsets: self.aoi_counts.ptr(),
                lens: self.aoi_lens.ptr(),
                out: self.aoi_out.ptr(),
                most: self.aoi_most.ptr(),
            },
        )?;
        self.host.small.ensure(gpu, 4)?;
        gpu.download_async(&mut self.host.small, 0, self.aoi_most.ptr(), 1)?;
        gpu.sync()?;
        let most = self.host.small.slice::<u32>(1)[0] as usize;
        self.aoi_walk.stride = Some(stride_for(most));
        if most > stride as usize {
            return Ok(None);
        }
        Ok(Some(slots))
    }
}

/// Where [`CudaBackend::aoi_on_device`] left its lists.
#[derive(Debug, Clone, Copy)]
pub(super) struct AoiOnDevice {
    /// Slots in all ranges.
    pub total: usize,
    /// Whether `aoi_lens` holds the lists' lengths (strided ranges).
    pub lens: bool,
}

/// The one-walk query's sizing, kept between calls.
#[derive(Debug, Default)]
pub(super) struct AoiWalk {
    /// Slots a query for the next walk (`None`: none yet, or the last was too large).
    pub stride: Option<u32>,
    /// The last exact total (the walk may use at most about [`WALK_ROOM`] times that).
    pub total: usize,
    /// Exact queries to run before the next guess.
    pub pause: u32,
}

/// Most slots of the one-walk query, as a multiple of the exact total: every slot also
/// costs the interest selection's scratch and staleness tables (about 50 bytes).
const WALK_ROOM: usize = 3;

/// Exact queries after a stride was refused, before the next guess.
const WALK_PAUSE: u32 = 64;

/// A stride with room for a quarter more than `most` (lists change little from one tick
/// to the next), in whole cache lines of slots.
fn stride_for(most: usize) -> u32 {
    let want = (most + most / 4).max(32);
    want.div_ceil(32).saturating_mul(32).min(u32::MAX as usize / 2) as u32
}
