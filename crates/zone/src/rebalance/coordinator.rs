//! The coordinator of a rebalancing run: it gathers every zone's [`LoadReport`] of a
//! tick, decides (one policy, one place), and answers every zone with the same
//! [`Decision`], which the zones apply at the announced tick. No threads here: the
//! caller carries reports and decisions ([`crate::run_zoned`] over channels).

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::error::ZoneError;
use crate::layout::ZoneLayout;
use crate::rebalance::{CountOptions, CountPolicy, CutMove, LoadReport};

/// How a zoned run watches and moves its cuts.
#[derive(Clone, Debug, PartialEq)]
pub struct RebalanceOptions {
    /// Zones report every this many ticks (ticks that are multiples of it).
    pub every: u64,
    /// A move decided at tick `t` applies at `t + delay` (at least 1, less than
    /// `every`, so that a decision is applied before the next reports).
    pub delay: u64,
    /// Histogram bins per axis over the world's extent.
    pub bins: usize,
    /// Who decides.
    pub policy: Policy,
}

impl Default for RebalanceOptions {
    fn default() -> RebalanceOptions {
        RebalanceOptions { every: 30, delay: 2, bins: 256, policy: Policy::Counts(CountOptions::default()) }
    }
}

impl RebalanceOptions {
    /// Refuses options a run cannot follow.
    pub fn validate(&self) -> Result<(), ZoneError> {
        if self.every < 2 || self.delay == 0 || self.delay >= self.every || self.bins == 0 {
            return Err(ZoneError::Layout(format!(
                "rebalancing every {} ticks with a delay of {} and {} bins: need every >= 2, 1 <= delay < every, \
                 bins >= 1",
                self.every, self.delay, self.bins
            )));
        }
        if let Policy::Counts(c) = &self.policy
            && !(c.threshold.is_finite() && c.threshold >= 1.0 && c.max_move.is_none_or(|m| m.is_finite() && m > 0.0))
        {
            return Err(ZoneError::Layout(format!("a count policy of {c:?}")));
        }
        Ok(())
    }

    /// Whether zones report at tick `t`.
    pub fn reports_at(&self, t: u64) -> bool {
        t.is_multiple_of(self.every)
    }

    /// Whether the reports of `t` are answered with a decision that zones wait for, in
    /// a run that ends at tick `end` (a move must apply before the end).
    pub fn decides(&self, t: u64, end: u64) -> bool {
        self.reports_at(t) && t + self.delay < end && !matches!(self.policy, Policy::Watch)
    }
}

/// Who decides the moves.
#[derive(Clone, Debug, PartialEq)]
pub enum Policy {
    /// Never move: gather the load figures only (the fixed cuts' baseline).
    Watch,
    /// [`CountPolicy`]: reproducible, from object counts.
    Counts(CountOptions),
    /// Exactly these moves (tests): each at its decision tick, refused (and logged) when
    /// invalid for the layout of that moment.
    Forced(Vec<ForcedMove>),
}

/// A move a test imposes: at the decision of tick `at`, go to these cuts.
#[derive(Clone, Debug, PartialEq)]
pub struct ForcedMove {
    /// The decision tick (a multiple of [`RebalanceOptions::every`]).
    pub at: u64,
    /// The cuts along x.
    pub xs: Vec<f32>,
    /// The cuts along z.
    pub zs: Vec<f32>,
}

/// What every zone hears after the reports of a tick.
#[derive(Clone, Debug)]
pub struct Decision {
    /// The tick decided at.
    pub decided_at: u64,
    /// The tick the zones apply it at.
    pub apply_at: u64,
    /// The new layout, or `None`: keep the cuts.
    pub layout: Option<Arc<ZoneLayout>>,
}

/// The zones' load at one report tick.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadSample {
    /// The tick.
    pub tick: u64,
    /// Objects each zone owned.
    pub owned: Vec<usize>,
    /// Each zone's physics time a tick since the previous sample, in ms (measured).
    pub physics_ms: Vec<f64>,
    /// Each zone's whole step a tick since the previous sample, in ms (measured).
    pub step_ms: Vec<f64>,
    /// Ticks since the previous sample.
    pub ticks: u64,
}

/// What the coordinator saw and did in a run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RebalanceLog {
    /// The moves, in order.
    pub moves: Vec<CutMove>,
    /// Moves refused (decision tick, reason): nothing of them was applied.
    pub refused: Vec<(u64, String)>,
    /// The load at every report tick.
    pub samples: Vec<LoadSample>,
    /// The cuts at the end, along x and z.
    pub cuts: (Vec<f32>, Vec<f32>),
}

/// Gathers reports and decides (see the module docs).
pub struct Coordinator {
    opts: RebalanceOptions,
    end: u64,
    layout: Arc<ZoneLayout>,
    counts: Option<CountPolicy>,
    pending: BTreeMap<u64, Vec<Option<LoadReport>>>,
    log: RebalanceLog,
}

impl Coordinator {
    /// A coordinator for zones that start with `layout` and stop at tick `end`.
    pub fn new(opts: RebalanceOptions, layout: Arc<ZoneLayout>, end: u64) -> Result<Coordinator, ZoneError> {
        opts.validate()?;
        let counts = match &opts.policy {
            Policy::Counts(c) => Some(CountPolicy::new(c.clone(), &layout)),
            _ => None,
        };
        Ok(Coordinator { opts, end, layout, counts, pending: BTreeMap::new(), log: RebalanceLog::default() })
    }

    /// Takes one zone's report. When it completes its tick, the sample is logged and, on
    /// a deciding tick ([`RebalanceOptions::decides`]), the decision every zone must hear
    /// is returned. A report of a zone or tick that cannot be is an error.
    pub fn offer(&mut self, r: LoadReport) -> Result<Option<Decision>, ZoneError> {
        let n = self.layout.len();
        let z = r.zone.0 as usize;
        if z >= n || !self.opts.reports_at(r.tick) {
            return Err(ZoneError::Layout(format!("a load report of zone {z} at tick {}", r.tick)));
        }
        let t = r.tick;
        let slot = &mut self.pending.entry(t).or_insert_with(|| vec![None; n])[z];
        if slot.is_some() {
            return Err(ZoneError::Layout(format!("two load reports of zone {z} at tick {t}")));
        }
        *slot = Some(r);
        if self.pending[&t].iter().any(Option::is_none) {
            return Ok(None);
        }
        let reports: Vec<LoadReport> = self.pending.remove(&t).expect("complete").into_iter().flatten().collect();
        let per_tick = |d: std::time::Duration, ticks: u64| d.as_secs_f64() * 1e3 / ticks.max(1) as f64;
        self.log.samples.push(LoadSample {
            tick: t,
            owned: reports.iter().map(|r| r.owned).collect(),
            physics_ms: reports.iter().map(|r| per_tick(r.physics, r.ticks)).collect(),
            step_ms: reports.iter().map(|r| per_tick(r.step, r.ticks)).collect(),
            ticks: reports.iter().map(|r| r.ticks).max().unwrap_or(0),
        });
        if !self.opts.decides(t, self.end) {
            return Ok(None);
        }
        let apply_at = t + self.opts.delay;
        let proposal = match &self.opts.policy {
            Policy::Watch => None,
            Policy::Counts(_) => self.counts.as_mut().expect("count policy").decide(t, &self.layout, &reports)?,
            Policy::Forced(moves) => moves.iter().find(|m| m.at == t).map(|m| (m.xs.clone(), m.zs.clone())),
        };
        let layout = proposal.and_then(|(xs, zs)| {
            let m = CutMove { decided_at: t, apply_at, xs, zs };
            match m.validate(&self.layout) {
                Ok(l) => {
                    self.log.moves.push(m);
                    Some(Arc::new(l))
                }
                Err(e) => {
                    tracing::debug!(tick = t, error = %e, "cut move refused");
                    self.log.refused.push((t, e.to_string()));
                    None
                }
            }
        });
        if let Some(l) = &layout {
            self.layout = l.clone();
        }
        Ok(Some(Decision { decided_at: t, apply_at, layout }))
    }

    /// The layout of the last decision.
    pub fn layout(&self) -> &Arc<ZoneLayout> {
        &self.layout
    }

    /// The log, with the final cuts.
    pub fn finish(mut self) -> RebalanceLog {
        let (xs, zs) = self.layout.cuts();
        self.log.cuts = (xs.to_vec(), zs.to_vec());
        self.log
    }
}
