//! Area-of-interest queries on the device: count and write passes with the query boxes
//! as queries and the dynamic objects as targets, over a grid of columns for `cuda`
//! (`grid`) and every object for `cuda-naive` (the broad phase's passes).

use myriad_core::{Aabb, World};
use myriad_physics::lbvh::morton::MortonFrame;
use myriad_physics::{AoiResults, PhysicsError};
use rayon::prelude::*;
use std::time::Instant;

use super::Resident;
use super::broad::{Queries, count_pass, write_pass};
use super::grid::Frame;
use crate::launch::KSortRanges;

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
        let total = self.aoi_on_device(world, boxes)?;
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
    /// lists: the lists' offsets (`nq + 1`) are in `aoi_counts`, their slots in
    /// `aoi_out`, each list sorted by slot, and only the total comes back to the host.
    /// With no box or no object nothing is launched and the device buffers are not
    /// written. `cuda` answers from a grid of columns (`grid`), `cuda-naive` by testing
    /// every object; both give every object whose box overlaps, as the CPU does.
    pub(crate) fn aoi_on_device(&mut self, world: &World, boxes: &[Aabb]) -> Result<usize, PhysicsError> {
        let started = Instant::now();
        self.gpu.bind()?;
        self.sync_world(world, None)?;
        let nq = boxes.len();
        if nq == 0 || self.n == 0 {
            return Ok(0);
        }
        // The boxes of the last step (or query) serve as long as no one moved an object.
        let generation = world.dynamics.generation();
        if self.boxes_fresh != Some(generation) {
            self.build_boxes()?;
            self.boxes_fresh = Some(generation);
        }
        let gpu = &self.gpu;
        gpu.profile_host("host: AOI query, the world's copy and boxes", started);
        let started = Instant::now();
        self.aoi_boxes.ensure(gpu, nq * 24, 1.25)?;
        self.aoi_counts.ensure(gpu, (nq + 1) * 4, 1.25)?;
        if self.aoi_order.ensure(gpu, nq * 4, 1.25)? {
            self.order_age = None;
        }
        // Into page-locked memory on the pool, then up on the stream: the stream has
        // passed the copy before the next query writes here (every query waits for its
        // total, and the lists' readers wait for their kernels).
        let h = &mut self.host;
        h.aoi_boxes.ensure(gpu, nq * 24)?;
        h.aoi_boxes.slice_mut::<[f32; 6]>(nq).par_iter_mut().zip(boxes.par_iter()).for_each(|(f, b)| {
            *f = [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z];
        });
        gpu.upload_async(&self.aoi_boxes, &h.aoi_boxes, 6 * nq)?;
        let counts = self.aoi_counts.ptr();
        // `cuda-naive` tests the boxes in index order; the grid's warps take them in
        // `query_order`.
        let qs = Queries::plain(nq, self.aoi_boxes.ptr());
        let ordered = Queries { order: self.aoi_order.ptr(), ..qs };
        let naive = self.naive();
        if naive {
            count_pass(gpu, qs, false, self.dynamic_targets(), counts)?;
        } else {
            // Which warp answers which box changes no list, so the order is kept while
            // the boxes are as many, and made again now and then as players move.
            let age = match self.order_age {
                Some((len, age)) if len == nq && age < ORDER_KEPT => age + 1,
                _ => {
                    let h = &mut self.host;
                    h.aoi_order.ensure(gpu, nq * 4)?;
                    h.aoi_order.slice_mut::<u32>(nq).copy_from_slice(&query_order(boxes));
                    gpu.upload_async(&self.aoi_order, &h.aoi_order, nq)?;
                    0
                }
            };
            self.order_age = Some((nq, age));
            let frame = Frame::new(&world.bounds, boxes);
            gpu.profile_host("host: AOI query, boxes and order up", started);
            self.grid.build(gpu, &mut self.scan, self.n, self.obj.boxes.ptr(), frame)?;
            self.grid.count(gpu, ordered, counts)?;
        }
        self.scan.exclusive(gpu, counts, nq + 1)?;
        self.host.small.ensure(gpu, 4)?;
        gpu.download_async(&mut self.host.small, 0, counts.add(nq), 1)?;
        gpu.sync()?;
        let total = self.host.small.slice::<u32>(1)[0] as usize;
        self.aoi_out.ensure(gpu, total * 4, 1.25)?;
        if naive {
            // Testing every object in order gives each list sorted.
            write_pass(gpu, qs, false, self.dynamic_targets(), counts, &self.aoi_out)?;
        } else {
            // The grid writes each list in its columns' order; a block a list sorts it.
            self.grid.write(gpu, ordered, counts, &self.aoi_out)?;
            // 512 threads: a list of 2,500 (AOI 100, scenario 3) is 2,048 comparisons a
            // step of its sorting network, 4 a thread.
            gpu.launch_grid(
                nq as u32,
                512,
                KSortRanges { nq: nq as u32, offsets: counts, objects: self.aoi_out.ptr() },
            )?;
        }
        Ok(total)
    }
}

/// Queries that keep the order of the boxes before it is made again.
const ORDER_KEPT: u32 = 30;

/// The boxes' indices in the Morton order of their centres (ties by index): the order in
/// which the grid's warps take them. Players' boxes come in session order, scattered over
/// the map: taken in this order, warps running at once read the same columns, which the
/// cache then holds. Only which warp answers a box changes, not any list.
fn query_order(boxes: &[Aabb]) -> Vec<u32> {
    let bounds = boxes.iter().fold(Aabb::EMPTY, |acc, b| acc.union(&Aabb::new(b.center(), b.center())));
    let frame = MortonFrame::new(&bounds);
    let mut keyed: Vec<(u64, u32)> =
        boxes.iter().enumerate().map(|(i, b)| (frame.code(b.center()), i as u32)).collect();
    // 10,000 players' keys: on the pool, a few times faster than on one core. The keys
    // are unique (ties broken by index), so the order is the same either way.
    keyed.par_sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

#[cfg(test)]
mod tests {
    use myriad_core::Vec3;

    use super::*;

    #[test]
    fn the_query_order_is_a_permutation_that_keeps_neighbours_together() {
        let at = |x: f32, z: f32| Aabb::new(Vec3::new(x - 1.0, 0.0, z - 1.0), Vec3::new(x + 1.0, 2.0, z + 1.0));
        // Two clusters, interleaved in the input.
        let boxes: Vec<Aabb> =
            (0..8).map(|i| if i % 2 == 0 { at(i as f32, 0.0) } else { at(900.0 + i as f32, 900.0) }).collect();
        let order = query_order(&boxes);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..8).collect::<Vec<u32>>());
        let first: Vec<u32> = order[..4].iter().map(|i| i % 2).collect();
        assert!(first.iter().all(|&c| c == first[0]), "one cluster first: {order:?}");
        assert!(query_order(&[]).is_empty());
        // Identical centres: by index.
        assert_eq!(query_order(&[at(5.0, 5.0), at(5.0, 5.0), at(5.0, 5.0)]), vec![0, 1, 2]);
    }
}
