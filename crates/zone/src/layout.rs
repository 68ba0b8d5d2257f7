//! Where zones are: a grid of rectangles over the world's x–z extent, with boundaries
//! kept as data (two sorted lists of cuts), so that a later step can move them.
//!
//! Distances are per axis (Chebyshev) in x–z, because that is how bounding boxes
//! overlap: an object whose centre lies in zone `Z` can only touch an object whose centre
//! is within `2 × max half extent` of `Z` on both axes. Height never matters.

use myriad_core::{Aabb, Vec3};

use crate::error::ZoneError;

/// A zone's index in its layout (row-major over the grid).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ZoneId(pub u16);

/// A rectangle of the x–z plane, `[min, max)` on both axes (the last row and column are
/// closed: the world's far edge belongs to them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    /// Smallest x.
    pub min_x: f32,
    /// Smallest z.
    pub min_z: f32,
    /// Largest x.
    pub max_x: f32,
    /// Largest z.
    pub max_z: f32,
}

impl Rect {
    /// Per-axis distance from a point to the rectangle (0 inside).
    pub fn distance(&self, x: f32, z: f32) -> f32 {
        let dx = (self.min_x - x).max(x - self.max_x).max(0.0);
        let dz = (self.min_z - z).max(z - self.max_z).max(0.0);
        dx.max(dz)
    }

    /// Per-axis distance between two rectangles (0 when they touch or overlap).
    pub fn distance_to(&self, o: &Rect) -> f32 {
        let dx = (self.min_x - o.max_x).max(o.min_x - self.max_x).max(0.0);
        let dz = (self.min_z - o.max_z).max(o.min_z - self.max_z).max(0.0);
        dx.max(dz)
    }
}

/// How the world is cut into zones, and how far zones see into each other.
#[derive(Clone, Debug, PartialEq)]
pub struct ZoneLayout {
    /// Cuts along x, ascending: column `c` spans `xs[c]..xs[c + 1]`.
    xs: Vec<f32>,
    /// Cuts along z, ascending: row `r` spans `zs[r]..zs[r + 1]`.
    zs: Vec<f32>,
    reach: f32,
    max_step: f32,
    neighbours: Vec<Vec<ZoneId>>,
}

impl ZoneLayout {
    /// `cols × rows` equal zones over `bounds`.
    ///
    /// `reach` is how far (per axis) a zone must see past its edge: at least twice the
    /// largest half extent of any dynamic object, so that every pair one of its objects
    /// can be in is found. `max_step` is the farthest an object may move in one tick; an
    /// object that moves farther is an error at the next exchange, never a silent loss.
    pub fn grid(bounds: &Aabb, cols: u16, rows: u16, reach: f32, max_step: f32) -> Result<ZoneLayout, ZoneError> {
        if cols == 0 || rows == 0 || cols as u32 * rows as u32 > u16::MAX as u32 {
            return Err(ZoneError::Layout(format!("a {cols} × {rows} grid")));
        }
        let cut = |lo: f32, hi: f32, n: u16| -> Vec<f32> {
            // In f64 so that the cuts do not depend on accumulated rounding.
            (0..=n).map(|i| (lo as f64 + (hi as f64 - lo as f64) * i as f64 / n as f64) as f32).collect()
        };
        ZoneLayout::from_cuts(
            cut(bounds.min.x, bounds.max.x, cols),
            cut(bounds.min.z, bounds.max.z, rows),
            reach,
            max_step,
        )
    }

    /// `k` zones in the squarest grid with `k` cells (`2` is 2 × 1, `4` is 2 × 2, `9` is
    /// 3 × 3, a prime is `k × 1`).
    pub fn for_count(bounds: &Aabb, k: u16, reach: f32, max_step: f32) -> Result<ZoneLayout, ZoneError> {
        // In u32: the square of a u16 overflows.
        let rows =
            (1..=k).filter(|&r| k.is_multiple_of(r) && u32::from(r) * u32::from(r) <= u32::from(k)).max().unwrap_or(1);
        ZoneLayout::grid(bounds, k / rows.max(1), rows, reach, max_step)
    }

    /// A layout from explicit cuts (each list ascending, at least two values). Fails when
    /// a zone is narrower than `reach + max_step`: zones would then see past their
    /// neighbours.
    pub fn from_cuts(xs: Vec<f32>, zs: Vec<f32>, reach: f32, max_step: f32) -> Result<ZoneLayout, ZoneError> {
        let ascending =
            |v: &[f32]| v.len() >= 2 && v.iter().all(|c| c.is_finite()) && v.windows(2).all(|w| w[0] < w[1]);
        if !ascending(&xs) || !ascending(&zs) {
            return Err(ZoneError::Layout("cuts must be finite and ascending, at least two per axis".into()));
        }
        if !(reach.is_finite() && reach >= 0.0 && max_step.is_finite() && max_step >= 0.0) {
            return Err(ZoneError::Layout(format!("reach {reach} and max step {max_step}")));
        }
        let margin = reach + max_step;
        let narrowest = xs.windows(2).chain(zs.windows(2)).map(|w| w[1] - w[0]).fold(f32::INFINITY, f32::min);
        if (xs.len() > 2 || zs.len() > 2) && narrowest <= margin {
            return Err(ZoneError::Layout(format!(
                "a zone {narrowest} wide is not wider than reach + max step = {margin}: use fewer zones"
            )));
        }
        let mut layout = ZoneLayout { xs, zs, reach, max_step, neighbours: Vec::new() };
        let n = layout.len();
        layout.neighbours = (0..n)
            .map(|a| {
                let ra = layout.region(ZoneId(a as u16));
                (0..n)
                    .filter(|&b| b != a && ra.distance_to(&layout.region(ZoneId(b as u16))) <= margin)
                    .map(|b| ZoneId(b as u16))
                    .collect()
            })
            .collect();
        Ok(layout)
    }

    /// The cuts along x and along z, ascending; the first and last of each are the
    /// world's edges.
    pub fn cuts(&self) -> (&[f32], &[f32]) {
        (&self.xs, &self.zs)
    }

    /// This layout with its inner cuts moved to `xs` and `zs` (whole lists, edges
    /// included): same shape, reach and max step. Refuses lists of another length,
    /// edges that moved (the world's bounds do not change), cuts that are not finite
    /// and ascending, and a zone not wider than `reach + max step`, as
    /// [`ZoneLayout::from_cuts`] does.
    pub fn with_cuts(&self, xs: &[f32], zs: &[f32]) -> Result<ZoneLayout, ZoneError> {
        if xs.len() != self.xs.len() || zs.len() != self.zs.len() {
            return Err(ZoneError::Layout(format!(
                "{} x cuts and {} z cuts for a layout of {} and {}",
                xs.len(),
                zs.len(),
                self.xs.len(),
                self.zs.len()
            )));
        }
        // Bit comparisons: an edge is the world's bound, exactly, or the move is refused.
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits();
        let edges = |new: &[f32], old: &[f32]| same(new[0], old[0]) && same(new[new.len() - 1], old[old.len() - 1]);
        if !edges(xs, &self.xs) || !edges(zs, &self.zs) {
            return Err(ZoneError::Layout("the outer cuts are the world's bounds and do not move".into()));
        }
        let moved = ZoneLayout::from_cuts(xs.to_vec(), zs.to_vec(), self.reach, self.max_step)?;
        // Zones wider than the margin make neighbours a matter of the grid alone (two
        // zones apart are a whole zone apart): a move never changes who exchanges with
        // whom, which zones switching at one tick rely on.
        if moved.neighbours != self.neighbours {
            return Err(ZoneError::Layout("a cut move that changes the zones' neighbours".into()));
        }
        Ok(moved)
    }

    /// The smallest width a zone may have: wider than this is required
    /// ([`ZoneLayout::from_cuts`]).
    pub fn margin(&self) -> f32 {
        self.reach + self.max_step
    }

    /// Number of zones.
    pub fn len(&self) -> usize {
        (self.xs.len() - 1) * (self.zs.len() - 1)
    }

    /// Whether there are none (never: a layout has at least one zone).
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Every zone, in order.
    pub fn zones(&self) -> impl Iterator<Item = ZoneId> + use<> {
        (0..self.len() as u16).map(ZoneId)
    }

    /// Columns and rows of the grid.
    pub fn shape(&self) -> (usize, usize) {
        (self.xs.len() - 1, self.zs.len() - 1)
    }

    /// How far past its edge a zone sees (ghosts, static scenery).
    pub fn reach(&self) -> f32 {
        self.reach
    }

    /// The farthest an object may move in one tick.
    pub fn max_step(&self) -> f32 {
        self.max_step
    }

    /// The zone's rectangle.
    pub fn region(&self, z: ZoneId) -> Rect {
        let cols = self.xs.len() - 1;
        let (c, r) = (z.0 as usize % cols, z.0 as usize / cols);
        Rect { min_x: self.xs[c], max_x: self.xs[c + 1], min_z: self.zs[r], max_z: self.zs[r + 1] }
    }

    /// The zone that owns a point: the cell whose half-open span holds it, points outside
    /// the cuts going to the nearest edge cell.
    pub fn zone_at(&self, p: Vec3) -> ZoneId {
        let cols = self.xs.len() - 1;
        ZoneId((cell(&self.zs, p.z) * cols + cell(&self.xs, p.x)) as u16)
    }

    /// The zones that must know of an object centred at `p`: its owner and every zone
    /// whose cells meet the square of half side `reach` around it. This is the one
    /// definition of "sees" (ghosts sent, ghosts kept).
    pub fn seers(&self, p: Vec3) -> impl Iterator<Item = ZoneId> + '_ {
        let cols = self.xs.len() - 1;
        let (c0, c1) = (cell(&self.xs, p.x - self.reach), cell(&self.xs, p.x + self.reach));
        let (r0, r1) = (cell(&self.zs, p.z - self.reach), cell(&self.zs, p.z + self.reach));
        (r0..=r1).flat_map(move |r| (c0..=c1).map(move |c| ZoneId((r * cols + c) as u16)))
    }

    /// Whether zone `z` must know of an object centred at `p` (see [`ZoneLayout::seers`]).
    pub fn sees(&self, z: ZoneId, p: Vec3) -> bool {
        let cols = self.xs.len() - 1;
        let (c, r) = (z.0 as usize % cols, z.0 as usize / cols);
        let within =
            |cuts: &[f32], i: usize, v: f32| cell(cuts, v - self.reach) <= i && i <= cell(cuts, v + self.reach);
        within(&self.xs, c, p.x) && within(&self.zs, r, p.z)
    }

    /// The zones whose regions lie within `reach + max_step` of `z`'s: the only ones it
    /// exchanges with, and the only ones it waits for.
    pub fn neighbours(&self, z: ZoneId) -> &[ZoneId] {
        &self.neighbours[z.0 as usize]
    }
}

/// The cell of `v` along one axis: cuts belong to the cell above them; values outside
/// the cuts go to the edge cells. Comparisons only, so the answer is exact.
fn cell(cuts: &[f32], v: f32) -> usize {
    cuts[1..cuts.len() - 1].iter().take_while(|&&c| c <= v).count()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds() -> Aabb {
        Aabb::new(Vec3::new(-30.0, 0.0, 0.0), Vec3::new(60.0, 50.0, 90.0))
    }

    #[test]
    fn grids_are_square_as_can_be() {
        for (k, shape) in
            [(1, (1, 1)), (2, (2, 1)), (4, (2, 2)), (6, (3, 2)), (9, (3, 3)), (7, (7, 1)), (400, (20, 20))]
        {
            assert_eq!(ZoneLayout::for_count(&bounds(), k, 0.5, 0.5).unwrap().shape(), shape, "{k}");
        }
    }

    #[test]
    fn every_point_has_one_owner_inside_its_region() {
        let l = ZoneLayout::for_count(&bounds(), 9, 2.0, 1.0).unwrap();
        for x in (-40..70).map(|v| v as f32 * 1.0 + 0.5).chain([-30.0, 0.0, 60.0]) {
            for z in (-5..95).map(|v| v as f32).chain([30.0, 60.0]) {
                let p = Vec3::new(x, 7.0, z);
                let owner = l.zone_at(p);
                let inside = (-30.0..=60.0).contains(&x) && (0.0..=90.0).contains(&z);
                if inside {
                    assert_eq!(l.region(owner).distance(x, z), 0.0, "{p}");
                }
                assert!(l.sees(owner, p) || !inside);
            }
        }
        assert_eq!(l.zone_at(Vec3::new(0.0, 0.0, 30.0)), ZoneId(4), "cuts belong to the upper cell");
        // Near a corner where four zones meet, all four see the point; far inside, one.
        let corner: Vec<_> = l.seers(Vec3::new(1.0, 0.0, 31.0)).collect();
        assert_eq!(corner, [ZoneId(0), ZoneId(1), ZoneId(3), ZoneId(4)]);
        assert_eq!(l.seers(Vec3::new(15.0, 0.0, 45.0)).collect::<Vec<_>>(), [ZoneId(4)]);
        for z in l.zones() {
            assert_eq!(l.sees(z, Vec3::new(1.0, 0.0, 31.0)), corner.contains(&z));
        }
    }

    #[test]
    fn neighbours_of_a_three_by_three_grid() {
        let l = ZoneLayout::for_count(&bounds(), 9, 2.0, 1.0).unwrap();
        assert_eq!(l.neighbours(ZoneId(4)).len(), 8, "the centre meets all");
        assert_eq!(l.neighbours(ZoneId(0)), &[ZoneId(1), ZoneId(3), ZoneId(4)], "a corner meets three");
        assert_eq!(l.neighbours(ZoneId(1)).len(), 5);
        for z in l.zones() {
            for n in l.neighbours(z) {
                assert!(l.neighbours(*n).contains(&z), "symmetric");
            }
        }
    }

    #[test]
    fn with_cuts_moves_inner_cuts_only() {
        let l = ZoneLayout::for_count(&bounds(), 4, 2.0, 1.0).unwrap();
        let (xs, zs) = (l.cuts().0.to_vec(), l.cuts().1.to_vec());
        assert_eq!((xs.as_slice(), zs.as_slice()), (&[-30.0, 15.0, 60.0][..], &[0.0, 45.0, 90.0][..]));
        let m = l.with_cuts(&[-30.0, 10.0, 60.0], &zs).unwrap();
        assert_eq!((m.reach(), m.max_step(), m.shape()), (2.0, 1.0, (2, 2)));
        assert_eq!(m.zone_at(Vec3::new(12.0, 0.0, 1.0)), ZoneId(1), "12 is now right of the cut");
        assert_eq!(l.zone_at(Vec3::new(12.0, 0.0, 1.0)), ZoneId(0));
        for (bad_x, bad_z, why) in [
            (vec![-31.0, 10.0, 60.0], zs.clone(), "outer cuts"),
            (vec![-30.0, 10.0, 60.5], zs.clone(), "outer cuts"),
            (vec![-30.0, 10.0, 30.0, 60.0], zs.clone(), "cuts for a layout"),
            (vec![-30.0, 60.0], zs.clone(), "cuts for a layout"),
            (vec![-30.0, f32::NAN, 60.0], zs.clone(), "finite"),
            (vec![-30.0, f32::INFINITY, 60.0], zs.clone(), "finite"),
            (vec![-30.0, 70.0, 60.0], zs.clone(), "ascending"),
            (vec![-30.0, -30.0, 60.0], zs.clone(), "ascending"),
            (xs.clone(), vec![0.0, 3.0, 90.0], "fewer zones"),
            (vec![-30.0, 57.5, 60.0], zs.clone(), "fewer zones"),
        ] {
            let e = l.with_cuts(&bad_x, &bad_z).unwrap_err().to_string();
            assert!(e.contains(why), "{bad_x:?} {bad_z:?}: {e}");
        }
        // A zone exactly as wide as the margin (3) is refused, a hair wider is not.
        assert!(l.with_cuts(&[-30.0, 57.0, 60.0], &zs).is_err());
        assert!(l.with_cuts(&[-30.0, 56.99, 60.0], &zs).is_ok());
    }

    #[test]
    fn refuses_zones_narrower_than_the_margin_and_bad_cuts() {
        assert!(ZoneLayout::for_count(&bounds(), 9, 25.0, 6.0).is_err());
        assert!(ZoneLayout::for_count(&bounds(), 1, 500.0, 6.0).is_ok(), "one zone has no neighbour to see");
        assert!(ZoneLayout::from_cuts(vec![0.0, 0.0], vec![0.0, 1.0], 0.0, 0.0).is_err());
        assert!(ZoneLayout::from_cuts(vec![0.0, f32::NAN], vec![0.0, 1.0], 0.0, 0.0).is_err());
        assert!(ZoneLayout::from_cuts(vec![0.0, 1.0], vec![0.0, 1.0], -1.0, 0.0).is_err());
        assert!(ZoneLayout::grid(&bounds(), 0, 1, 1.0, 1.0).is_err());
    }
}
