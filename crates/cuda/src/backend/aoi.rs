//! Area-of-interest queries on the device: the broad phase's count and write passes
//! with the query boxes as queries and the dynamic objects as targets.

use myriad_core::{Aabb, World};
use myriad_physics::{AoiResults, PhysicsError};

use super::Resident;
use super::broad::{Queries, count_pass, write_pass};
use crate::launch::{DevPtr, KAoiCells};

impl Resident {
    /// The objects overlapping each box of `boxes`, as CSR lists in `out`.
    pub(super) fn query_impl(
        &mut self,
        world: &World,
        boxes: &[Aabb],
        out: &mut AoiResults,
    ) -> Result<(), PhysicsError> {
        out.clear();
        let nq = boxes.len();
        let (total, _) = self.aoi_on_device(world, boxes, true)?;
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

    /// Answers the queries into device memory and returns the number of slots in all
    /// lists and how many consecutive lists make one query's (`parts`): the lists'
    /// offsets (`nq * parts + 1`) are in `aoi_counts`, their slots in `aoi_out`, and only
    /// the total comes back to the host. With `sorted`, each query has one list, sorted by
    /// slot. Without, on a tree, each query is walked as `SPLIT`² cells (`k_aoi_cells`), each list in the walk's order. With no box or no object nothing is
    /// launched and the device buffers are not written.
    pub(crate) fn aoi_on_device(
        &mut self,
        world: &World,
        boxes: &[Aabb],
        sorted: bool,
    ) -> Result<(usize, usize), PhysicsError> {
        self.gpu.bind()?;
        self.sync_world(world, None)?;
        let nq = boxes.len();
        if nq == 0 || self.n == 0 {
            return Ok((0, 1));
        }
        // The boxes of the last step (or query) serve as long as no one moved an object.
        let generation = world.dynamics.generation();
        if self.boxes_fresh != Some(generation) {
            self.build_dynamic(world)?;
            self.boxes_fresh = Some(generation);
        }
        let parts = if sorted || self.naive() { 1 } else { SPLIT * SPLIT };
        let lists = nq * parts;
        let gpu = &self.gpu;
        self.aoi_boxes.ensure(gpu, nq * 24, 1.25)?;
        self.aoi_counts.ensure(gpu, (lists + 1) * 4, 1.25)?;
        let flat: Vec<f32> = boxes.iter().flat_map(|b| [b.min.to_array(), b.max.to_array()]).flatten().collect();
        gpu.upload(&self.aoi_boxes, &flat)?;
        let qs = Queries::plain(nq, self.aoi_boxes.ptr());
        let tree = &self.dyn_tree;
        let counts = self.aoi_counts.ptr();
        let cells = KAoiCells {
            nq: nq as u32,
            split: SPLIT as u32,
            qboxes: qs.boxes,
            nodes: tree.nodes.ptr(),
            order: tree.order.ptr(),
            nleaves: tree.leaves as u32,
            tboxes: self.obj.boxes.ptr(),
            ranges: counts,
            out: DevPtr::NULL,
            cap: 0,
        };
        if parts == 1 {
            count_pass(gpu, qs, false, self.dynamic_targets(), counts)?;
        } else {
            gpu.zero(counts.add(lists), 1)?;
            gpu.launch(lists, cells)?;
        }
        self.scan.exclusive(gpu, counts, lists + 1)?;
        self.host.small.ensure(gpu, 4)?;
        gpu.download_async(&mut self.host.small, 0, counts.add(lists), 1)?;
        gpu.sync()?;
        let total = self.host.small.slice::<u32>(1)[0] as usize;
        self.aoi_out.ensure(gpu, total * 4, 1.25)?;
        if parts == 1 {
            let qs = Queries { sorted, ..qs };
            write_pass(gpu, qs, false, self.dynamic_targets(), counts, &self.aoi_out)?;
        } else {
            gpu.launch(lists, KAoiCells { out: self.aoi_out.ptr(), cap: self.aoi_out.capacity(), ..cells })?;
        }
        Ok((total, parts))
    }
}

/// Cells per axis (x and z) an AOI box is split into on the unsorted path.
const SPLIT: usize = 4;
