//! The `cpu` backend's area-of-interest query: a uniform grid over x–z.
//!
//! Why not the dynamic tree: an AOI box of a server holds hundreds to thousands of
//! objects, and a tree walk pays a node visit (two box tests and a stack push) for every
//! one of them, then the answer must be sorted. Here the objects are binned by the
//! centre of their box into square cells, in cell order; a query visits the cells its
//! box can reach and takes a cell whole when the union of the cell's boxes lies inside
//! the query, skips it when the union misses it, and tests the cell's boxes one by one
//! only on the query's rim. Boxes are copied into cell order, so every test reads memory
//! in sequence. (At scenario 2's AOI of 100 units on two cores, the tree query took
//! 54 ms a tick for 5,000 players.)
//!
//! The answers are exactly the tree's: the same closed-interval test
//! ([`Aabb::overlaps`]) decides every object that is not taken with its whole cell, and
//! a cell is taken whole only when every box in it lies inside the query, which implies
//! that test. Boxes that are not finite, not ordered (`min > max`) or larger than a cell
//! are not binned: every query tests them (they are rare, and a NaN box overlaps nothing).

use myriad_core::Aabb;
use rayon::prelude::*;

/// Cells per query edge the grid aims for: a query then spans about this many cells and
/// most of the cells it visits lie wholly inside it.
const CELLS_PER_QUERY: f32 = 6.0;

/// Queries answered per rayon task.
const QUERIES_PER_TASK: usize = 32;

thread_local! {
    /// [`sort_slots`]'s scratch.
    static SCRATCH: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Lists shorter than this are sorted by comparison; longer ones by radix.
const RADIX_MIN: usize = 64;

/// Sorts `slots`, values below `n`, ascending: an LSD radix sort on bytes, as many
/// passes as `n` needs bytes (two up to 65,536 objects), whose steps do not branch on
/// the data. A comparison sort (and a bitmap scan after it) was half of the query's time
/// at AOI 100 in scenario 2; this one is about a sixth. Short lists are sorted in place.
fn sort_slots(slots: &mut [u32], n: usize, scratch: &mut Vec<u32>) {
    if slots.len() < RADIX_MIN {
        slots.sort_unstable();
        return;
    }
    let bits = u32::BITS - (n.max(2) as u32 - 1).leading_zeros();
    let passes = bits.div_ceil(8) as usize;
    let mut counts = [[0u32; 256]; 4];
    for &s in slots.iter() {
        for (p, count) in counts.iter_mut().enumerate().take(passes) {
            count[(s >> (8 * p)) as usize & 255] += 1;
        }
    }
    scratch.clear();
    scratch.resize(slots.len(), 0);
    let (mut from, mut to) = (&mut *slots, scratch.as_mut_slice());
    for (p, count) in counts.iter_mut().enumerate().take(passes) {
        let mut sum = 0;
        for c in count.iter_mut() {
            (*c, sum) = (sum, sum + *c);
        }
        for &s in from.iter() {
            let c = &mut count[(s >> (8 * p)) as usize & 255];
            to[*c as usize] = s;
            *c += 1;
        }
        std::mem::swap(&mut from, &mut to);
    }
    // After an odd number of passes the sorted list is in the scratch.
    if passes % 2 == 1 {
        slots.copy_from_slice(scratch);
    }
}

/// An object every query tests: its box and slot.
#[derive(Clone, Copy)]
struct Entry {
    aabb: Aabb,
    slot: u32,
}

/// The grid: objects binned by cell, rebuilt whenever the objects or the cell size change.
#[derive(Default)]
pub(crate) struct AoiGrid {
    /// (`Dynamics::stamp`, `Dynamics::generation`, cell size bits) the grid was built for.
    key: Option<(u64, u64, u32)>,
    /// Edge of a cell.
    cell: f32,
    /// Lower x and z of cell (0, 0).
    origin: [f32; 2],
    /// Cells along x and z.
    dims: [usize; 2],
    /// Answer buffers of [`query_all`](Self::query_all)'s tasks, kept for the next
    /// query: at AOI 100 they hold a hundred megabytes a tick, and fresh ones cost the
    /// kernel a zeroed page per 4 KiB touched (a sixth of scenario 3's CPU time).
    spare: std::sync::Mutex<Vec<(Vec<u32>, Vec<u32>)>>,
    /// `starts[c]..starts[c + 1]` are cell `c`'s entries (cell `c` is `iz * nx + ix`).
    starts: Vec<u32>,
    /// Slots of the binned objects in cell order, ascending within a cell (a cell wholly
    /// inside a query is copied from here).
    slots: Vec<u32>,
    /// Their boxes, in the same order (tested on a query's rim).
    boxes: Vec<Aabb>,
    /// The union of each cell's boxes ([`Aabb::EMPTY`] for an empty cell).
    bounds: Vec<Aabb>,
    /// Objects every query tests (see the module docs), ascending.
    outliers: Vec<Entry>,
    /// The largest half extent on x or z of a binned box (at most a cell).
    margin: f32,
    /// Each slot's cell (`u32::MAX`: not binned), kept for its memory.
    cells: Vec<u32>,
    /// The objects' boxes by slot, kept for their memory.
    aabbs: Vec<Aabb>,
}

/// A power of two near `x` (so that small changes of the query sizes keep the grid).
fn power_of_two_near(x: f32) -> f32 {
    if x.is_finite() && x > f32::MIN_POSITIVE { 2f32.powi(x.log2().round() as i32) } else { 1.0 }
}

/// The cell size the queries ask for: their median x–z edge over [`CELLS_PER_QUERY`].
fn cell_for(queries: &[Aabb]) -> f32 {
    let mut edges: Vec<f32> = queries
        .iter()
        .step_by(queries.len().div_ceil(64).max(1))
        .map(|q| (q.max.x - q.min.x).max(q.max.z - q.min.z))
        .filter(|e| e.is_finite() && *e > 0.0)
        .collect();
    if edges.is_empty() {
        return 1.0;
    }
    let mid = edges.len() / 2;
    let (_, median, _) = edges.select_nth_unstable_by(mid, f32::total_cmp);
    power_of_two_near(*median / CELLS_PER_QUERY)
}

/// Whether `b` is binned when the queries ask for cells of edge `cell` (the grid's cells
/// are that or larger).
fn binnable(b: &Aabb, cell: f32) -> bool {
    b.min.is_finite()
        && b.max.is_finite()
        && b.min.cmple(b.max).all()
        && (b.max.x - b.min.x) * 0.5 <= cell
        && (b.max.z - b.min.z) * 0.5 <= cell
        && (b.min.x + b.max.x).is_finite()
        && (b.min.z + b.max.z).is_finite()
}

impl AoiGrid {
    /// Makes the grid answer for the objects if it does not already: `fresh` is their
    /// (stamp, generation), `fill` writes their boxes by slot, and the cell size comes
    /// from `queries`.
    pub(crate) fn prepare(&mut self, fresh: (u64, u64), fill: impl FnOnce(&mut Vec<Aabb>), queries: &[Aabb]) {
        let want = cell_for(queries);
        if self.key == Some((fresh.0, fresh.1, want.to_bits())) {
            return;
        }
        let mut aabbs = std::mem::take(&mut self.aabbs);
        fill(&mut aabbs);
        self.build(&aabbs, want);
        self.aabbs = aabbs;
        self.key = Some((fresh.0, fresh.1, want.to_bits()));
    }

    /// Bins `aabbs` in cells of edge `cell` (or larger: at most about two cells an
    /// object, so that a sparse world does not cost memory).
    fn build(&mut self, aabbs: &[Aabb], want: f32) {
        let binnable = |b: &Aabb| binnable(b, want);
        let centre = |b: &Aabb| [(b.min.x + b.max.x) * 0.5, (b.min.z + b.max.z) * 0.5];
        let (lo, hi) = aabbs
            .par_iter()
            .filter(|b| binnable(b))
            .map(|b| {
                let c = centre(b);
                (c, c)
            })
            .reduce(
                || ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]),
                |(l1, h1), (l2, h2)| ([l1[0].min(l2[0]), l1[1].min(l2[1])], [h1[0].max(h2[0]), h1[1].max(h2[1])]),
            );
        let max_cells = (2 * aabbs.len()).clamp(4096, 1 << 31) as f64;
        let mut cell = want;
        let span = |lo: f32, hi: f32, cell: f32| {
            if hi >= lo { ((f64::from(hi) - f64::from(lo)) / f64::from(cell)).floor() + 1.0 } else { 1.0 }
        };
        while span(lo[0], hi[0], cell) * span(lo[1], hi[1], cell) > max_cells {
            cell *= 2.0;
        }
        self.cell = cell;
        self.origin = if hi[0] >= lo[0] { lo } else { [0.0; 2] };
        self.dims = [span(lo[0], hi[0], cell) as usize, span(lo[1], hi[1], cell) as usize];
        let cells = self.dims[0] * self.dims[1];
        let inv = 1.0 / cell;

        // A counting sort by cell: stable, so slots ascend within a cell.
        let (origin, dims) = (self.origin, self.dims);
        self.cells.clear();
        self.cells.par_extend(aabbs.par_iter().map(|b| {
            if !binnable(b) {
                return u32::MAX;
            }
            let c = centre(b);
            let ix = (((c[0] - origin[0]) * inv) as usize).min(dims[0] - 1);
            let iz = (((c[1] - origin[1]) * inv) as usize).min(dims[1] - 1);
            (iz * dims[0] + ix) as u32
        }));
        self.starts.clear();
        self.starts.resize(cells + 1, 0);
        for &c in self.cells.iter().filter(|&&c| c != u32::MAX) {
            self.starts[c as usize + 1] += 1;
        }
        for c in 0..cells {
            self.starts[c + 1] += self.starts[c];
        }
        let binned = self.starts[cells] as usize;
        self.slots.clear();
        self.slots.resize(binned, 0);
        let mut next = self.starts[..cells].to_vec();
        for (slot, &c) in self.cells.iter().enumerate().filter(|(_, c)| **c != u32::MAX) {
            let at = &mut next[c as usize];
            self.slots[*at as usize] = slot as u32;
            *at += 1;
        }
        self.boxes.clear();
        self.boxes.par_extend(self.slots.par_iter().map(|&s| aabbs[s as usize]));
        let (starts, boxes) = (&self.starts, &self.boxes);
        self.bounds.clear();
        self.bounds.par_extend(
            (0..cells)
                .into_par_iter()
                .map(|c| boxes[starts[c] as usize..starts[c + 1] as usize].iter().fold(Aabb::EMPTY, |u, b| u.union(b))),
        );
        self.margin = boxes
            .par_iter()
            .map(|b| ((b.max.x - b.min.x) * 0.5).max((b.max.z - b.min.z) * 0.5))
            .reduce(|| 0.0, f32::max);
        self.outliers.clear();
        self.outliers.extend(
            self.cells
                .iter()
                .zip(aabbs)
                .enumerate()
                .filter(|(_, (c, _))| **c == u32::MAX)
                .map(|(slot, (_, b))| Entry { aabb: *b, slot: slot as u32 }),
        );
    }

    /// Cells `lo..=hi` along one axis that can hold a box overlapping `[min, max]`
    /// (binned by centre, at most `margin` from its box's edge), one more each side for
    /// rounding; `None` when there are none.
    fn axis_range(&self, axis: usize, min: f32, max: f32) -> Option<(usize, usize)> {
        let inv = 1.0 / self.cell;
        let lo = ((min - self.margin - self.origin[axis]) * inv).floor() - 1.0;
        let hi = ((max + self.margin - self.origin[axis]) * inv).floor() + 1.0;
        let last = (self.dims[axis] - 1) as f32;
        // NaN compares false: a NaN bound gives no cells (the query overlaps nothing).
        if !(hi >= 0.0 && lo <= last) {
            return None;
        }
        Some((lo.max(0.0) as usize, hi.min(last) as usize))
    }

    /// Appends the slots of the objects whose boxes overlap `q` to `out`, ascending.
    fn query(&self, q: &Aabb, out: &mut Vec<u32>) {
        let start = out.len();
        let inside = |b: &Aabb| q.min.cmple(b.min).all() && b.max.cmple(q.max).all();
        if !self.slots.is_empty()
            && let (Some((x0, x1)), Some((z0, z1))) =
                (self.axis_range(0, q.min.x, q.max.x), self.axis_range(1, q.min.z, q.max.z))
        {
            let nx = self.dims[0];
            for iz in z0..=z1 {
                for c in iz * nx + x0..=iz * nx + x1 {
                    let b = &self.bounds[c];
                    if !b.overlaps(q) {
                        continue;
                    }
                    let run = self.starts[c] as usize..self.starts[c + 1] as usize;
                    if inside(b) {
                        out.extend_from_slice(&self.slots[run]);
                    } else {
                        let slots = &self.slots[run.clone()];
                        out.extend(self.boxes[run].iter().zip(slots).filter(|(b, _)| b.overlaps(q)).map(|(_, &s)| s));
                    }
                }
            }
        }
        out.extend(self.outliers.iter().filter(|e| e.aabb.overlaps(q)).map(|e| e.slot));
        SCRATCH.with_borrow_mut(|scratch| sort_slots(&mut out[start..], self.aabbs.len(), scratch));
    }

    /// Answers every query into `offsets` (one more than the queries) and `objects`, in
    /// parallel over queries.
    pub(crate) fn query_all(&self, queries: &[Aabb], offsets: &mut Vec<u32>, objects: &mut Vec<u32>) {
        let spare = || self.spare.lock().unwrap_or_else(std::sync::PoisonError::into_inner).pop();
        let parts: Vec<(Vec<u32>, Vec<u32>)> = queries
            .par_chunks(QUERIES_PER_TASK)
            .map(|chunk| {
                let (mut slots, mut ends) = spare().unwrap_or_default();
                slots.clear();
                ends.clear();
                for q in chunk {
                    self.query(q, &mut slots);
                    ends.push(slots.len() as u32);
                }
                (slots, ends)
            })
            .collect();
        offsets.clear();
        offsets.reserve(queries.len() + 1);
        offsets.push(0);
        let mut base = 0u32;
        for (slots, ends) in &parts {
            offsets.extend(ends.iter().map(|e| base + e));
            base += slots.len() as u32;
        }
        // Laid out in parallel: at AOI 100 the lists are tens of megabytes.
        objects.clear();
        objects.par_extend(rayon::iter::repeat_n(0, base as usize));
        let mut rest = objects.as_mut_slice();
        let mut dests = Vec::with_capacity(parts.len());
        for (slots, _) in &parts {
            let (dest, tail) = std::mem::take(&mut rest).split_at_mut(slots.len());
            dests.push(dest);
            rest = tail;
        }
        dests.into_par_iter().zip(&parts).for_each(|(dest, (slots, _))| dest.copy_from_slice(slots));
        self.spare.lock().unwrap_or_else(std::sync::PoisonError::into_inner).extend(parts);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::Vec3;

    /// xorshift64: a small deterministic generator for the cases.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn f(&mut self, lo: f32, hi: f32) -> f32 {
            lo + (self.next() >> 40) as f32 / (1u64 << 24) as f32 * (hi - lo)
        }
    }

    fn brute(aabbs: &[Aabb], q: &Aabb) -> Vec<u32> {
        (0..aabbs.len() as u32).filter(|&s| aabbs[s as usize].overlaps(q)).collect()
    }

    fn check(aabbs: &[Aabb], queries: &[Aabb], what: &str) {
        let mut grid = AoiGrid::default();
        grid.prepare((1, 1), |v| v.extend_from_slice(aabbs), queries);
        let (mut offsets, mut objects) = (Vec::new(), Vec::new());
        grid.query_all(queries, &mut offsets, &mut objects);
        assert_eq!(offsets.len(), queries.len() + 1, "{what}");
        for (i, q) in queries.iter().enumerate() {
            let got = &objects[offsets[i] as usize..offsets[i + 1] as usize];
            assert_eq!(got, brute(aabbs, q).as_slice(), "{what}: query {i} {q:?}");
        }
    }

    #[test]
    fn answers_equal_brute_force_on_random_worlds() {
        let mut r = Rng(0x9e37_79b9_7f4a_7c15);
        for round in 0..30 {
            let n = [0, 1, 7, 300, 3000][round % 5];
            let world = r.f(10.0, 2000.0);
            let mut aabbs: Vec<Aabb> = (0..n)
                .map(|_| {
                    let c = Vec3::new(r.f(0.0, world), r.f(-5.0, 40.0), r.f(0.0, world));
                    let h = Vec3::new(r.f(0.1, 3.0), r.f(0.1, 3.0), r.f(0.1, 3.0));
                    Aabb::from_center_half(c, h)
                })
                .collect();
            // Piles on one spot, exactly touching boxes, and a few odd ones.
            if n > 10 {
                let pile = Aabb::from_center_half(Vec3::new(world / 2.0, 0.0, world / 2.0), Vec3::ONE);
                aabbs[..n / 10].fill(pile);
                aabbs[1] = Aabb::new(Vec3::splat(f32::NAN), Vec3::splat(f32::NAN));
                aabbs[2] = Aabb::new(Vec3::splat(f32::NEG_INFINITY), Vec3::splat(f32::INFINITY));
                aabbs[3] = Aabb::from_center_half(Vec3::new(world / 3.0, 0.0, 0.0), Vec3::splat(world / 4.0));
                aabbs[4] = Aabb::new(Vec3::ONE, Vec3::ZERO);
                aabbs[5] = Aabb::from_center_half(Vec3::new(1e30, 0.0, -1e30), Vec3::ONE);
            }
            let edge = r.f(1.0, 300.0);
            let mut queries: Vec<Aabb> = (0..60)
                .map(|_| {
                    let c = Vec3::new(r.f(-50.0, world + 50.0), r.f(-5.0, 40.0), r.f(-50.0, world + 50.0));
                    Aabb::from_center_half(c, Vec3::new(edge / 2.0, r.f(1.0, 100.0), edge / 2.0))
                })
                .collect();
            // Queries that touch a box exactly, cover everything, are points, are NaN.
            if n > 10 {
                let b = aabbs[20];
                queries.push(Aabb::new(b.max, b.max + Vec3::ONE));
                queries.push(Aabb::new(b.min - Vec3::ONE, b.min));
            }
            queries.push(Aabb::new(Vec3::splat(f32::NEG_INFINITY), Vec3::splat(f32::INFINITY)));
            queries.push(Aabb::new(Vec3::splat(world / 2.0), Vec3::splat(world / 2.0)));
            queries.push(Aabb::new(Vec3::new(f32::NAN, 0.0, 0.0), Vec3::splat(world)));
            queries.push(Aabb::new(Vec3::splat(-1e9), Vec3::splat(-1e8)));
            check(&aabbs, &queries, &format!("round {round}, {n} objects"));
        }
    }

    #[test]
    fn slots_sort_either_way() {
        let mut r = Rng(7);
        let mut scratch = Vec::new();
        for n in [1usize, 63, 64, 65, 1000, 70_000, 1 << 24, u32::MAX as usize] {
            for len in [0, 1, 2, n / 20, n / 2, n] {
                let mut slots: Vec<u32> = (0..len.min(100_000)).map(|_| (r.next() % n as u64) as u32).collect();
                let mut want = slots.clone();
                want.sort_unstable();
                sort_slots(&mut slots, n, &mut scratch);
                assert_eq!(slots, want, "{len} of {n}");
            }
        }
    }

    #[test]
    fn a_new_generation_or_cell_size_rebuilds() {
        let a = vec![Aabb::from_center_half(Vec3::splat(5.0), Vec3::ONE)];
        let b = vec![Aabb::from_center_half(Vec3::splat(50.0), Vec3::ONE)];
        let q = [Aabb::new(Vec3::ZERO, Vec3::splat(10.0))];
        let mut grid = AoiGrid::default();
        let (mut offsets, mut objects) = (Vec::new(), Vec::new());
        grid.prepare((1, 1), |v| *v = a.clone(), &q);
        grid.query_all(&q, &mut offsets, &mut objects);
        assert_eq!(objects, [0]);
        // Same key: kept (the closure is not called).
        grid.prepare((1, 1), |_| unreachable!("the grid is fresh"), &q);
        grid.prepare((1, 2), |v| *v = b.clone(), &q);
        grid.query_all(&q, &mut offsets, &mut objects);
        assert!(objects.is_empty());
        let wide = [Aabb::new(Vec3::ZERO, Vec3::splat(100.0))];
        grid.prepare((1, 2), |v| *v = b.clone(), &wide);
        grid.query_all(&wide, &mut offsets, &mut objects);
        assert_eq!(objects, [0]);
    }
}
