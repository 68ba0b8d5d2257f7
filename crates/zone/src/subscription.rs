//! States by interest, the shared part: the grid of cells subscriptions are made of, the
//! set of cells a gateway subscribes to, and how a gateway computes it from its players.
//!
//! A gateway's players see the objects whose boxes overlap their AOI boxes. A zone
//! sends a gateway the objects whose *centres* lie in the cells it subscribed to
//! ([`crate::views`]), and the gateway shows the newest view it has whole, some ticks
//! after it subscribed. So the cells must cover, for every player, its AOI box grown by
//! a **margin**: the farthest the player can move before the subscription takes effect
//! (`lag ticks × max step`), plus the largest half extent of an object (an object whose
//! box reaches into the AOI box has its centre at most that far outside it). Coarse
//! cells and a cell that stays subscribed for a while after it is last needed
//! (`linger`) make the subscription change rarely.
//!
//! The grid starts at the world's lower x and z bounds; a point outside the bounds
//! belongs to the nearest edge cell, as a point outside the cuts belongs to an edge zone.

use myriad_core::{Aabb, Vec3};

use crate::error::ZoneError;
use crate::wire::{MAX_CELLS, cell_bytes};

/// A grid of square cells over the world's x–z extent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellGrid {
    min_x: f32,
    min_z: f32,
    cell: f32,
    cols: u16,
    rows: u16,
}

impl CellGrid {
    /// Cells of side `cell` over `bounds` (enough to cover them), at most [`MAX_CELLS`].
    pub fn new(bounds: &Aabb, cell: f32) -> Result<CellGrid, ZoneError> {
        if !(cell.is_finite() && cell > 0.0) {
            return Err(ZoneError::Layout(format!("a cell side of {cell} (> 0)")));
        }
        let count = |extent: f32| ((extent / cell).ceil() as u64).max(1);
        let (cols, rows) = (count(bounds.max.x - bounds.min.x), count(bounds.max.z - bounds.min.z));
        if cols > u64::from(u16::MAX) || rows > u64::from(u16::MAX) || cols * rows > MAX_CELLS {
            return Err(ZoneError::Layout(format!(
                "{cols} × {rows} cells of side {cell}: at most {MAX_CELLS} (use larger cells)"
            )));
        }
        Ok(CellGrid { min_x: bounds.min.x, min_z: bounds.min.z, cell, cols: cols as u16, rows: rows as u16 })
    }

    /// The cell side.
    pub fn cell(&self) -> f32 {
        self.cell
    }

    /// Columns (along x) and rows (along z).
    pub fn shape(&self) -> (u16, u16) {
        (self.cols, self.rows)
    }

    /// Cells in all.
    pub fn len(&self) -> usize {
        usize::from(self.cols) * usize::from(self.rows)
    }

    /// Whether the grid has no cells (never: a grid has at least one).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn col(&self, x: f32) -> u16 {
        // `as` saturates (NaN to 0), so any float lands in the grid.
        (((x - self.min_x) / self.cell).floor().max(0.0) as u32).min(u32::from(self.cols) - 1) as u16
    }

    fn row(&self, z: f32) -> u16 {
        (((z - self.min_z) / self.cell).floor().max(0.0) as u32).min(u32::from(self.rows) - 1) as u16
    }

    /// The cell holding `p`'s centre (x and z; edge cells take what lies outside).
    pub fn cell_of(&self, p: Vec3) -> u32 {
        u32::from(self.row(p.z)) * u32::from(self.cols) + u32::from(self.col(p.x))
    }

    /// Adds to `set` every cell that meets the square of half side `half` around `p`.
    pub fn cover(&self, set: &mut CellSet, p: Vec3, half: f32) {
        let (c0, c1) = (self.col(p.x - half), self.col(p.x + half));
        let (r0, r1) = (self.row(p.z - half), self.row(p.z + half));
        for r in r0..=r1 {
            for c in c0..=c1 {
                set.insert(u32::from(r) * u32::from(self.cols) + u32::from(c));
            }
        }
    }
}

/// A set of cells of one grid, as bits.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CellSet {
    words: Vec<u64>,
    len: u32,
}

impl CellSet {
    /// An empty set of `cells` cells.
    pub fn new(cells: usize) -> CellSet {
        CellSet { words: vec![0; cells.div_ceil(64)], len: cells as u32 }
    }

    /// Whether `cell` is in.
    #[inline]
    pub fn contains(&self, cell: u32) -> bool {
        cell < self.len && self.words[(cell / 64) as usize] & (1 << (cell % 64)) != 0
    }

    /// Puts `cell` in (one outside the grid is ignored).
    pub fn insert(&mut self, cell: u32) {
        if cell < self.len {
            self.words[(cell / 64) as usize] |= 1 << (cell % 64);
        }
    }

    /// Cells in the set.
    pub fn count(&self) -> usize {
        self.words.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// The cells in the set, ascending (a word at a time: empty stretches cost little).
    pub fn iter(&self) -> impl Iterator<Item = u32> + '_ {
        self.words.iter().enumerate().flat_map(|(i, &w)| {
            let mut w = w;
            std::iter::from_fn(move || {
                (w != 0).then(|| {
                    let bit = w.trailing_zeros();
                    w &= w - 1;
                    i as u32 * 64 + bit
                })
            })
        })
    }

    /// The wire form ([`crate::wire::Subscription::cells`]) for a grid of `cols × rows`.
    pub fn to_bytes(&self, cols: u16, rows: u16) -> Vec<u8> {
        let mut out: Vec<u8> = self.words.iter().flat_map(|w| w.to_le_bytes()).collect();
        out.truncate(cell_bytes(cols, rows));
        out
    }

    /// From the wire form (whose length and unused bits the decoder checked).
    pub fn from_bytes(bytes: &[u8], cells: usize) -> CellSet {
        let mut set = CellSet::new(cells);
        for (i, chunk) in bytes.chunks(8).enumerate() {
            let mut w = [0u8; 8];
            w[..chunk.len()].copy_from_slice(chunk);
            set.words[i] = u64::from_le_bytes(w);
        }
        set
    }
}

/// How a gateway turns its players into cells.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InterestConfig {
    /// Half the side of a player's AOI box (the server's `aoi_size` / 2).
    pub aoi_half: f32,
    /// The cells' side.
    pub cell: f32,
    /// How far past the AOI box the cells must reach (see the module docs:
    /// [`InterestConfig::margin_for`]).
    pub margin: f32,
    /// Ticks a cell stays subscribed after it was last needed.
    pub linger: u64,
}

impl InterestConfig {
    /// The margin for views that reach the gateway up to `lag_ticks` after the positions
    /// they were asked for, objects that move at most `max_step` a tick, and objects of
    /// at most `max_half_extent` (horizontally).
    pub fn margin_for(lag_ticks: u64, max_step: f32, max_half_extent: f32) -> f32 {
        lag_ticks as f32 * max_step + max_half_extent
    }

    /// The cell side a gateway uses unless told: an eighth of the AOI's side, grown
    /// where the world's x–z extent would need more than [`MAX_CELLS`] of them. Smaller
    /// cells hug the players' AOI boxes closer: with 100 players spread over scenario 2's
    /// map, AOI 100, lag 4, a gateway takes 157 kB a tick with cells of 12.5 against 167
    /// kB with cells of 25 and 197 kB with cells of 100 (lag 8), for the same 51 kB sent
    /// to its players; cells of 8 took 4 % less again at lag 2, where the subscription's
    /// bits grow with the square (`docs/zones.md`, "Packed views").
    pub fn default_cell(aoi_size: f32, bounds: &Aabb) -> f32 {
        let mut cell = if aoi_size.is_finite() && aoi_size > 0.0 { aoi_size / 8.0 } else { 1.0 };
        // A quarter larger until the grid fits (a few steps even for huge worlds).
        while CellGrid::new(bounds, cell).is_err() && cell < f32::MAX / 2.0 {
            cell *= 1.25;
        }
        cell
    }
}

/// A gateway's subscription as it changes: the cells it needs now and those it keeps for
/// a while ([`InterestConfig::linger`]).
#[derive(Clone, Debug)]
pub struct Interest {
    cfg: InterestConfig,
    grid: Option<CellGrid>,
    /// Per cell, the last tick it was needed (0: never).
    needed_at: Vec<u64>,
    /// What is subscribed, and its version.
    cells: CellSet,
    version: u64,
}

impl Interest {
    /// A gateway's interest by `cfg` (the grid comes with the world's bounds).
    pub fn new(cfg: InterestConfig) -> Interest {
        Interest { cfg, grid: None, needed_at: Vec::new(), cells: CellSet::default(), version: 0 }
    }

    /// The grid, once [`Interest::update`] has seen the world.
    pub fn grid(&self) -> Option<&CellGrid> {
        self.grid.as_ref()
    }

    /// The subscribed cells and their version.
    pub fn cells(&self) -> (&CellSet, u64) {
        (&self.cells, self.version)
    }

    /// Recomputes the cells at gateway tick `tick` (from 1) from the players' positions
    /// and any extra AOI boxes (those the server last queried): returns whether they
    /// changed (the version then grows).
    pub fn update(
        &mut self,
        bounds: &Aabb,
        tick: u64,
        players: impl Iterator<Item = Vec3>,
        boxes: &[Aabb],
    ) -> Result<bool, ZoneError> {
        let grid = match self.grid {
            Some(g) => g,
            None => {
                let g = CellGrid::new(bounds, self.cfg.cell)?;
                self.needed_at = vec![0; g.len()];
                self.cells = CellSet::new(g.len());
                *self.grid.insert(g)
            }
        };
        let mut now = CellSet::new(grid.len());
        let reach = self.cfg.aoi_half + self.cfg.margin;
        for p in players {
            grid.cover(&mut now, p, reach);
        }
        for b in boxes {
            let c = (b.min + b.max) * 0.5;
            let half = ((b.max.x - b.min.x).max(b.max.z - b.min.z)) * 0.5;
            grid.cover(&mut now, c, half + self.cfg.margin);
        }
        for c in now.iter() {
            self.needed_at[c as usize] = tick;
        }
        let mut next = CellSet::new(grid.len());
        for (c, &at) in self.needed_at.iter().enumerate() {
            if at > 0 && tick.saturating_sub(at) <= self.cfg.linger {
                next.insert(c as u32);
            }
        }
        let changed = next != self.cells;
        if changed {
            self.cells = next;
            self.version += 1;
        }
        Ok(changed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds(side: f32) -> Aabb {
        Aabb::new(Vec3::ZERO, Vec3::new(side, 50.0, side))
    }

    #[test]
    fn cells_cover_the_world_and_clamp_what_lies_outside() {
        let g = CellGrid::new(&bounds(100.0), 30.0).unwrap();
        assert_eq!(g.shape(), (4, 4));
        assert_eq!(g.cell_of(Vec3::new(0.0, 0.0, 0.0)), 0);
        assert_eq!(g.cell_of(Vec3::new(99.9, 0.0, 0.0)), 3);
        assert_eq!(g.cell_of(Vec3::new(-5.0, 0.0, 200.0)), 12, "outside: the nearest edge cell");
        assert_eq!(g.cell_of(Vec3::new(f32::NAN, 0.0, 31.0)), 4);
        assert!(CellGrid::new(&bounds(100.0), 0.0).is_err());
        assert!(CellGrid::new(&bounds(100_000.0), 1.0).is_err(), "too many cells");
    }

    #[test]
    fn a_set_round_trips_through_its_wire_form() {
        let g = CellGrid::new(&bounds(100.0), 10.0).unwrap();
        let mut s = CellSet::new(g.len());
        g.cover(&mut s, Vec3::new(55.0, 0.0, 55.0), 6.0);
        assert_eq!(s.iter().collect::<Vec<_>>(), [44, 45, 46, 54, 55, 56, 64, 65, 66]);
        assert_eq!(s.count(), 9);
        let (cols, rows) = g.shape();
        let bytes = s.to_bytes(cols, rows);
        assert_eq!(bytes.len(), 13);
        assert_eq!(CellSet::from_bytes(&bytes, g.len()), s);
        assert!(s.contains(66) && !s.contains(67) && !s.contains(1000));
    }

    #[test]
    fn cells_linger_and_the_version_grows_only_on_change() {
        let cfg = InterestConfig { aoi_half: 5.0, cell: 10.0, margin: 2.0, linger: 3 };
        let mut i = Interest::new(cfg);
        let b = bounds(100.0);
        let at = |x: f32| std::iter::once(Vec3::new(x, 0.0, 5.0));
        assert!(i.update(&b, 1, at(15.0), &[]).unwrap());
        assert_eq!(i.cells().0.iter().collect::<Vec<_>>(), [0, 1, 2, 10, 11, 12]);
        assert!(!i.update(&b, 2, at(15.0), &[]).unwrap(), "the same cells: no new version");
        assert!(i.update(&b, 3, at(45.0), &[]).unwrap(), "new cells at once");
        assert_eq!(i.cells().1, 2);
        assert!(i.cells().0.contains(0), "old cells linger");
        assert!(!i.update(&b, 5, at(45.0), &[]).unwrap());
        assert!(i.update(&b, 6, at(45.0), &[]).unwrap(), "then go");
        assert!(!i.cells().0.contains(0) && i.cells().0.contains(3));
    }

    #[test]
    fn the_default_cell_is_an_eighth_of_the_aoi_unless_the_world_needs_fewer_cells() {
        let map = |side: f32| Aabb::new(Vec3::ZERO, Vec3::new(side, 50.0, side));
        assert_eq!(InterestConfig::default_cell(100.0, &map(1024.0)), 12.5);
        let long = Aabb::new(Vec3::ZERO, Vec3::new(1.0e7, 50.0, 1.0));
        for world in [map(1024.0), map(100_000.0), map(1.0e6), long] {
            let cell = InterestConfig::default_cell(100.0, &world);
            let grid = CellGrid::new(&world, cell);
            assert!(grid.is_ok(), "{world:?}: cell {cell}: {grid:?}");
        }
        assert!(InterestConfig::default_cell(100.0, &map(100_000.0)) > 12.5);
    }
}
