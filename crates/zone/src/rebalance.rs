//! Boundaries that follow the load: when to move the cuts of a [`ZoneLayout`], where to,
//! and how every zone learns of it.
//!
//! A move is a [`CutMove`]: decided at tick `t` from the zones' reports of `t`, applied
//! by every zone at an announced later tick (before stepping it, with
//! [`crate::Zone::set_layout`]). The objects between an old cut and its new place are
//! then handed over at that tick's exchange like any object that crossed a boundary, so
//! a run whose cuts move still ends in one process's state hash.
//!
//! Two policies decide, both pure over their inputs:
//! - [`CountPolicy`] (for `myriad sim --zones K --rebalance`): from the objects each
//!   zone owns and a histogram of their x and z, so a run is reproducible;
//! - [`StepTimePolicy`] (for a live cluster): from measured step times, which no two
//!   runs share.
//!
//! In a live cluster the supervisor decides ([`announce`]) and publishes each move on
//! the fabric; the zones take it and follow it at its tick ([`live`]).
//!
//! A grid's cuts are global per axis (one x cut bounds every zone of its two columns),
//! so both policies balance columns and rows, not single zones. Neither ever makes a
//! zone as narrow as `reach + max step` ([`ZoneLayout::with_cuts`] refuses it), which
//! also keeps every zone's neighbours what they were.

pub mod announce;
mod coordinator;
pub mod live;
mod step_time;

pub use coordinator::{Coordinator, Decision, ForcedMove, LoadSample, Policy, RebalanceLog, RebalanceOptions};
pub use step_time::{StepTimeOptions, StepTimePolicy};

use std::time::Duration;

use myriad_core::Vec3;

use crate::error::ZoneError;
use crate::layout::{ZoneId, ZoneLayout};

/// Cuts along x and along z, edges included (as [`ZoneLayout::cuts`] gives them).
pub type Cuts = (Vec<f32>, Vec<f32>);

/// A decided move of the cuts: every zone follows `xs` and `zs` from tick `apply_at` on.
#[derive(Clone, Debug, PartialEq)]
pub struct CutMove {
    /// The tick whose reports decided it.
    pub decided_at: u64,
    /// The tick every zone steps with the new cuts first.
    pub apply_at: u64,
    /// The new cuts along x (edges included).
    pub xs: Vec<f32>,
    /// The new cuts along z (edges included).
    pub zs: Vec<f32>,
}

impl CutMove {
    /// The layout this move makes of `layout`, or why it cannot be applied: it must be
    /// announced for a later tick than it was decided at, keep the grid's shape and the
    /// world's edges, and leave every zone wider than `reach + max step`
    /// ([`ZoneLayout::with_cuts`]).
    pub fn validate(&self, layout: &ZoneLayout) -> Result<ZoneLayout, ZoneError> {
        if self.apply_at <= self.decided_at {
            return Err(ZoneError::Layout(format!(
                "a cut move decided at tick {} for tick {}: it must apply later",
                self.decided_at, self.apply_at
            )));
        }
        let moved = layout.with_cuts(&self.xs, &self.zs)?;
        let (xs, zs) = layout.cuts();
        let margin = layout.margin();
        if !within_neighbours(xs, &self.xs, margin) || !within_neighbours(zs, &self.zs, margin) {
            return Err(ZoneError::Layout(format!(
                "a cut moved to within reach + max step = {margin} of where its neighbouring cut was: objects would \
                 pass to zones that are not their owners' neighbours"
            )));
        }
        Ok(moved)
    }
}

/// Whether every inner cut of `new` lies more than `margin` inside the span of `old`'s
/// cuts on either side of it. Then an object (at most `max step` outside its owner's old
/// region) is owned and seen, under the new cuts, only by its owner's column (row) and
/// the ones next to it: its owner's neighbours, the only zones it exchanges with.
fn within_neighbours(old: &[f32], new: &[f32], margin: f32) -> bool {
    let m = margin as f64;
    (1..old.len() - 1).all(|j| new[j] as f64 - old[j - 1] as f64 > m && (old[j + 1] as f64 - new[j] as f64) > m)
}

/// Counts of values in fixed bins over `[lo, hi]` (values outside go to the edge bins).
#[derive(Clone, Debug, PartialEq)]
pub struct Histogram {
    lo: f32,
    hi: f32,
    counts: Vec<u32>,
}

impl Histogram {
    /// `bins` empty bins (at least one) over `[lo, hi]`.
    pub fn new(lo: f32, hi: f32, bins: usize) -> Histogram {
        Histogram { lo, hi, counts: vec![0; bins.max(1)] }
    }

    /// The bin of `v`: in f64, so that the same value lands in the same bin everywhere.
    fn bin(&self, v: f32) -> usize {
        let n = self.counts.len();
        let f = (v as f64 - self.lo as f64) / (self.hi as f64 - self.lo as f64);
        if f.is_nan() || f <= 0.0 { 0 } else { ((f * n as f64) as usize).min(n - 1) }
    }

    /// Counts `v`.
    pub fn add(&mut self, v: f32) {
        let b = self.bin(v);
        self.counts[b] += 1;
    }

    /// Adds another histogram of the same bins.
    pub fn merge(&mut self, other: &Histogram) -> Result<(), ZoneError> {
        if other.counts.len() != self.counts.len() || other.lo != self.lo || other.hi != self.hi {
            return Err(ZoneError::Layout("histograms of different bins".into()));
        }
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        Ok(())
    }

    /// The counts, bin by bin.
    pub fn counts(&self) -> &[u32] {
        &self.counts
    }

    /// All values counted.
    pub fn total(&self) -> u64 {
        self.counts.iter().map(|&c| c as u64).sum()
    }

    /// The width of a bin.
    pub fn bin_width(&self) -> f64 {
        (self.hi as f64 - self.lo as f64) / self.counts.len() as f64
    }

    /// The value below which a share `q` (0..=1) of the counts lie, spreading each bin's
    /// count evenly over the bin; `None` when empty.
    pub fn quantile(&self, q: f64) -> Option<f64> {
        let total = self.total();
        if total == 0 {
            return None;
        }
        let want = q.clamp(0.0, 1.0) * total as f64;
        let w = self.bin_width();
        let mut below = 0.0f64;
        for (b, &c) in self.counts.iter().enumerate() {
            let c = c as f64;
            if c > 0.0 && below + c >= want {
                return Some(self.lo as f64 + (b as f64 + (want - below) / c) * w);
            }
            below += c;
        }
        Some(self.hi as f64)
    }
}

/// What one zone reports at a tick: its load, for the coordinator's decision.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadReport {
    /// The zone.
    pub zone: ZoneId,
    /// The tick reached (before stepping it).
    pub tick: u64,
    /// Objects it owns.
    pub owned: usize,
    /// Its owned objects' x.
    pub xs: Histogram,
    /// Its owned objects' z.
    pub zs: Histogram,
    /// Physics time since its previous report (measured: never used by [`CountPolicy`]).
    pub physics: Duration,
    /// Whole step time (physics and the zone's own work) since its previous report.
    pub step: Duration,
    /// Ticks stepped since its previous report.
    pub ticks: u64,
}

impl LoadReport {
    /// The report of zone `zone` at `tick` whose owned objects are at `positions`, with
    /// `bins` bins per axis over the x–z extent of `bounds`.
    pub fn of(
        zone: ZoneId,
        tick: u64,
        positions: impl Iterator<Item = Vec3>,
        bounds: &myriad_core::Aabb,
        bins: usize,
    ) -> LoadReport {
        let mut xs = Histogram::new(bounds.min.x, bounds.max.x, bins);
        let mut zs = Histogram::new(bounds.min.z, bounds.max.z, bins);
        let mut owned = 0;
        for p in positions {
            xs.add(p.x);
            zs.add(p.z);
            owned += 1;
        }
        LoadReport { zone, tick, owned, xs, zs, physics: Duration::ZERO, step: Duration::ZERO, ticks: 0 }
    }
}

/// The knobs of [`CountPolicy`].
#[derive(Clone, Debug, PartialEq)]
pub struct CountOptions {
    /// Move the cuts of an axis only when its most loaded column (row) holds more than
    /// this many times the mean.
    pub threshold: f64,
    /// The farthest one cut moves in one decision, in units; `None`: a tenth of the
    /// initial zone width along that axis.
    pub max_move: Option<f32>,
    /// A cut that moved does not move again within this many ticks.
    pub cooldown: u64,
}

impl Default for CountOptions {
    fn default() -> CountOptions {
        CountOptions { threshold: 1.3, max_move: None, cooldown: 60 }
    }
}

/// The deterministic policy: balance the objects per column and per row (see the module
/// docs). Its inputs are object counts and positions only, so two runs of one world
/// decide the same moves at the same ticks.
#[derive(Clone, Debug)]
pub struct CountPolicy {
    opts: CountOptions,
    /// Per axis, the farthest a cut moves at once.
    max_move: [f64; 2],
    /// Per axis, the tick each cut (edges included, never moved) last moved at.
    moved_at: [Vec<Option<u64>>; 2],
}

impl CountPolicy {
    /// A policy for `layout`'s grid.
    pub fn new(opts: CountOptions, layout: &ZoneLayout) -> CountPolicy {
        let (xs, zs) = layout.cuts();
        let (cols, rows) = layout.shape();
        let tenth = |cuts: &[f32], n: usize| (cuts[n] as f64 - cuts[0] as f64) / n as f64 / 10.0;
        let max_move = match opts.max_move {
            Some(m) => [m as f64, m as f64],
            None => [tenth(xs, cols), tenth(zs, rows)],
        };
        CountPolicy { opts, max_move, moved_at: [vec![None; xs.len()], vec![None; zs.len()]] }
    }

    /// The cuts to move to after the reports of `tick` (one per zone of `layout`), or
    /// `None` to keep them.
    pub fn decide(
        &mut self,
        tick: u64,
        layout: &ZoneLayout,
        reports: &[LoadReport],
    ) -> Result<Option<Cuts>, ZoneError> {
        if reports.len() != layout.len() {
            return Err(ZoneError::Layout(format!("{} reports for {} zones", reports.len(), layout.len())));
        }
        let (cols, rows) = layout.shape();
        let (mut loads_x, mut loads_z) = (vec![0u64; cols], vec![0u64; rows]);
        let (mut hist_x, mut hist_z) = (reports[0].xs.clone(), reports[0].zs.clone());
        for (i, r) in reports.iter().enumerate() {
            if i > 0 {
                hist_x.merge(&r.xs)?;
                hist_z.merge(&r.zs)?;
            }
            let z = r.zone.0 as usize;
            loads_x[z % cols] += r.owned as u64;
            loads_z[z / cols] += r.owned as u64;
        }
        let (xs, zs) = layout.cuts();
        let min_width = safe_width(layout.margin());
        let mut out = [xs.to_vec(), zs.to_vec()];
        let mut moved = false;
        for (axis, (cuts, loads, hist)) in [(xs, &loads_x, &hist_x), (zs, &loads_z, &hist_z)].into_iter().enumerate() {
            let frozen: Vec<bool> =
                self.moved_at[axis].iter().map(|m| m.is_some_and(|at| tick < at + self.opts.cooldown)).collect();
            let step = AxisStep { threshold: self.opts.threshold, max_move: self.max_move[axis], min_width };
            if let Some(new) = balance_axis(cuts, loads, hist, &frozen, &step) {
                for (i, (a, b)) in new.iter().zip(cuts).enumerate() {
                    if a != b {
                        self.moved_at[axis][i] = Some(tick);
                    }
                }
                out[axis] = new;
                moved = true;
            }
        }
        let [xs, zs] = out;
        Ok(moved.then_some((xs, zs)))
    }
}

/// A width a little over `margin`, so that a zone of it passes the layout's strict
/// "wider than the margin" after f32 rounding.
fn safe_width(margin: f32) -> f64 {
    margin as f64 * 1.001 + 0.01
}

/// How one axis may move.
struct AxisStep {
    threshold: f64,
    max_move: f64,
    min_width: f64,
}

/// New cuts for one axis, or `None` when they stay: only when the most loaded span holds
/// more than `threshold` × the mean; each inner cut not `frozen` moves toward the place
/// that splits the histogram's counts evenly, at most `max_move`, and never closer than
/// `min_width` to its neighbours. `None` also when no cut can move that far.
fn balance_axis(cuts: &[f32], loads: &[u64], hist: &Histogram, frozen: &[bool], s: &AxisStep) -> Option<Vec<f32>> {
    let n = cuts.len() - 1;
    let total: u64 = loads.iter().sum();
    if n < 2 || total == 0 {
        return None;
    }
    let mean = total as f64 / n as f64;
    let most = *loads.iter().max().expect("at least two spans") as f64;
    if most <= s.threshold * mean {
        return None;
    }
    let mut new: Vec<f64> = cuts.iter().map(|&c| c as f64).collect();
    // A bin's width of dead band: the histogram cannot place a cut more finely.
    let dead = hist.bin_width();
    for i in 1..n {
        if frozen[i] {
            continue;
        }
        let Some(target) = hist.quantile(i as f64 / n as f64) else { continue };
        let d = target - new[i];
        if d.abs() <= dead {
            continue;
        }
        new[i] += d.clamp(-s.max_move, s.max_move);
    }
    // Keep every span wider than the margin: clamp each moving cut above its (final)
    // lower neighbour and below the next cut that stays, leaving room for the spans in
    // between. Frozen cuts, cuts that stay and the edges do not move.
    let stays: Vec<bool> = (0..=n).map(|i| i == 0 || i == n || new[i] == cuts[i] as f64).collect();
    for i in 1..n {
        if stays[i] {
            continue;
        }
        let j = (i + 1..=n).find(|&j| stays[j]).expect("the edge stays");
        // Also within the old neighbouring cuts' margin ([`CutMove::validate`]).
        let lo = (new[i - 1] + s.min_width).max(cuts[i - 1] as f64 + s.min_width);
        let hi = (new[j] - (j - i) as f64 * s.min_width).min(cuts[i + 1] as f64 - s.min_width);
        if lo > hi {
            return None;
        }
        new[i] = new[i].clamp(lo, hi);
    }
    let out: Vec<f32> = new.iter().map(|&c| c as f32).collect();
    let ok = out.windows(2).all(|w| (w[1] as f64 - w[0] as f64) >= s.min_width);
    (ok && out != cuts).then_some(out)
}

#[cfg(test)]
mod tests;
