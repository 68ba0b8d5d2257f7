//! The grid of columns the `cuda` backend answers area-of-interest queries with
//! (`kernels/grid.cu`): the dynamic objects counting-sorted by the column of their box's
//! low corner, then a warp a query box testing the objects of the columns it can reach.
//! A tree walk a thread a box kept a few warps an SM busy for milliseconds when ten
//! thousand players each asked for thousands of objects; the lists are the same.

use myriad_core::Aabb;
use myriad_physics::PhysicsError;

use super::broad::Queries;
use super::scan::Scan;
use crate::device::{DevBuf, Gpu};
use crate::launch::{DevPtr, KGridKeys, KGridPass, KGridScatter};

/// Columns along each axis at most: 2,048² columns are 16 MiB of counts.
const MAX_COLUMNS: f32 = 2048.0;
/// Columns across the narrowest query box: finer columns waste less of each row the
/// warp reads (the box's edges fall within one column), coarser ones make fewer rows.
const COLUMNS_PER_BOX: f32 = 6.0;
/// Threads a block of the warp-a-query kernels.
const BLOCK: u32 = 256;

/// Where the columns are: column `(x, z)` covers `origin + [x, x + 1) / inv` (the edge
/// columns also everything beyond), `g` columns along each axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Frame {
    pub ox: f32,
    pub oz: f32,
    pub inv: f32,
    pub g: u32,
}

impl Frame {
    /// One column holding everything: where the bounds give no grid, and before the
    /// first build.
    const WHOLE: Frame = Frame { ox: 0.0, oz: 0.0, inv: 0.0, g: 1 };

    /// Columns over the world's `bounds`, about [`COLUMNS_PER_BOX`] across the narrowest
    /// of `queries` (fewer where that would exceed [`MAX_COLUMNS`]). Degenerate or
    /// non-finite bounds get one column: the lists are right, only slower.
    pub fn new(bounds: &Aabb, queries: &[Aabb]) -> Frame {
        let extent = (bounds.max.x - bounds.min.x).max(bounds.max.z - bounds.min.z);
        if !(extent.is_finite() && extent > 0.0 && bounds.min.x.is_finite() && bounds.min.z.is_finite()) {
            return Frame::WHOLE;
        }
        let narrowest = queries
            .iter()
            .map(|b| (b.max.x - b.min.x).min(b.max.z - b.min.z))
            .filter(|e| e.is_finite() && *e > 0.0)
            .fold(f32::INFINITY, f32::min);
        let mut cell = (narrowest / COLUMNS_PER_BOX).max(extent / MAX_COLUMNS);
        if !cell.is_finite() {
            cell = extent / MAX_COLUMNS;
        }
        let g = (extent / cell).ceil().clamp(1.0, MAX_COLUMNS) as u32;
        Frame { ox: bounds.min.x, oz: bounds.min.z, inv: 1.0 / cell, g }
    }

    /// Columns in all.
    fn cells(&self) -> usize {
        self.g as usize * self.g as usize
    }
}

/// The grid's device buffers, rebuilt for each query (a few passes over the objects,
/// against thousands of boxes answered from it).
pub(super) struct Grid {
    frame: Frame,
    keys: DevBuf<u32>,
    /// Each column's end in `slots` once built (`k_grid_scatter`).
    cells: DevBuf<u32>,
    boxes: DevBuf<f32>,
    slots: DevBuf<u32>,
    /// The widest object's width, as float bits.
    wmax: DevBuf<u32>,
}

impl Grid {
    /// An empty grid; the first build allocates.
    pub fn new() -> Grid {
        Grid {
            frame: Frame::WHOLE,
            keys: DevBuf::empty(),
            cells: DevBuf::empty(),
            boxes: DevBuf::empty(),
            slots: DevBuf::empty(),
            wmax: DevBuf::empty(),
        }
    }

    /// Sorts the `n` objects whose boxes are at `boxes` into `frame`'s columns.
    pub fn build(
        &mut self,
        gpu: &Gpu,
        scan: &mut Scan,
        n: usize,
        boxes: DevPtr<f32>,
        frame: Frame,
    ) -> Result<(), PhysicsError> {
        self.frame = frame;
        let cells = frame.cells() + 1;
        self.keys.ensure(gpu, n * 4, 1.25)?;
        self.slots.ensure(gpu, n * 4, 1.25)?;
        self.boxes.ensure(gpu, n * 24, 1.25)?;
        self.cells.ensure(gpu, cells * 4, 1.25)?;
        self.wmax.ensure(gpu, 4, 1.0)?;
        gpu.zero(self.cells.ptr(), cells)?;
        gpu.zero(self.wmax.ptr(), 1)?;
        let Frame { ox, oz, inv, g } = frame;
        gpu.launch(
            n,
            KGridKeys {
                n: n as u32,
                boxes,
                ox,
                oz,
                inv,
                g,
                keys: self.keys.ptr(),
                cells: self.cells.ptr(),
                wmax: self.wmax.ptr(),
            },
        )?;
        scan.exclusive(gpu, self.cells.ptr(), cells)?;
        gpu.launch(
            n,
            KGridScatter {
                n: n as u32,
                keys: self.keys.ptr(),
                cells: self.cells.ptr(),
                boxes,
                gboxes: self.boxes.ptr(),
                gslots: self.slots.ptr(),
            },
        )
    }

    /// `counts[q]` = the objects box `q` of `qs` overlaps (warps taking the boxes in
    /// `qs.order`); `counts[qs.n]` = 0, for the scan.
    pub fn count(&self, gpu: &Gpu, qs: Queries, counts: DevPtr<u32>) -> Result<(), PhysicsError> {
        gpu.zero(counts.add(qs.n), 1)?;
        self.pass(gpu, qs, counts, None)
    }

    /// Each box's objects at `out[offsets[q] .. offsets[q + 1]]`, unsorted, for the
    /// boxes whose range ends within `out`'s capacity.
    pub fn write(&self, gpu: &Gpu, qs: Queries, offsets: DevPtr<u32>, out: &DevBuf<u32>) -> Result<(), PhysicsError> {
        self.pass(gpu, qs, offsets, Some(out))
    }

    /// `k_grid_pass`: counting into `counts` without `out`, else writing into `out` at
    /// the offsets `counts` holds.
    fn pass(&self, gpu: &Gpu, qs: Queries, counts: DevPtr<u32>, out: Option<&DevBuf<u32>>) -> Result<(), PhysicsError> {
        let Frame { ox, oz, inv, g } = self.frame;
        gpu.launch_grid(
            warp_blocks(qs.n),
            BLOCK,
            KGridPass {
                nq: qs.n as u32,
                qboxes: qs.boxes,
                qorder: qs.order,
                ox,
                oz,
                inv,
                g,
                cells: self.cells.ptr(),
                gboxes: self.boxes.ptr(),
                gslots: self.slots.ptr(),
                wmax: self.wmax.ptr(),
                counts,
                out: out.map_or(DevPtr::NULL, DevBuf::ptr),
                cap: out.map_or(0, DevBuf::capacity),
            },
        )
    }
}

/// Blocks of [`BLOCK`] threads for a warp a query.
fn warp_blocks(nq: usize) -> u32 {
    (nq * 32).div_ceil(BLOCK as usize) as u32
}

#[cfg(test)]
mod tests {
    use myriad_core::Vec3;

    use super::*;

    fn square(x: f32, z: f32, edge: f32) -> Aabb {
        Aabb::new(Vec3::new(x, 0.0, z), Vec3::new(x + edge, 10.0, z + edge))
    }

    #[test]
    fn columns_follow_the_narrowest_box_within_the_cap() {
        let world = Aabb::new(Vec3::new(-512.0, -10.0, -512.0), Vec3::new(512.0, 100.0, 512.0));
        let f = Frame::new(&world, &[square(0.0, 0.0, 100.0), square(5.0, 5.0, 60.0)]);
        assert_eq!((f.ox, f.oz), (-512.0, -512.0));
        assert_eq!(f.inv, 0.1, "60 / 6 units a column");
        assert_eq!(f.g, 103);
        // Tiny boxes: no more than the cap.
        let f = Frame::new(&world, &[square(0.0, 0.0, 0.01)]);
        assert_eq!(f.g, 2048);
        // No usable box: the cap's columns.
        let f = Frame::new(&world, &[Aabb::new(Vec3::splat(f32::NAN), Vec3::splat(f32::NAN))]);
        assert_eq!(f.g, 2048);
        assert_eq!(Frame::new(&world, &[]).g, 2048);
    }

    #[test]
    fn degenerate_worlds_get_one_column() {
        for world in [
            Aabb::new(Vec3::ZERO, Vec3::ZERO),
            Aabb::new(Vec3::splat(f32::NEG_INFINITY), Vec3::splat(f32::INFINITY)),
            Aabb::new(Vec3::splat(f32::NAN), Vec3::splat(1.0)),
        ] {
            let f = Frame::new(&world, &[square(0.0, 0.0, 10.0)]);
            assert_eq!((f.g, f.inv), (1, 0.0), "{world:?}");
        }
    }

    #[test]
    fn warps_cover_every_query() {
        assert_eq!(warp_blocks(0), 0);
        assert_eq!(warp_blocks(1), 1);
        assert_eq!(warp_blocks(8), 1);
        assert_eq!(warp_blocks(9), 2);
        assert_eq!(warp_blocks(10_000), 1250);
    }
}
