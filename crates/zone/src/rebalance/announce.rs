//! Cut moves in a live cluster, the supervisor's side: deciding from the zones'
//! heartbeats, announcing, sending again until every zone holds the move, and noticing a
//! zone that steps on other cuts than announced.
//!
//! Every zone's heartbeat carries its step time, its owned objects, the digest of the
//! cuts it stepped with and the move it holds ([`crate::wire::Load`]). The
//! [`Announcer`] looks at the latest heartbeats of the epoch a few times a second:
//! - **Deciding.** With no move outstanding, [`StepTimePolicy`] (from the step times) or
//!   the test's [`ForcedMove`]s propose cuts; the move is announced for `apply_at` = the
//!   highest tick any zone reported + `lead` ticks, once [`CutMove::validate`] accepts
//!   it for the cuts in force, and refused (counted, logged) otherwise. One move is
//!   outstanding at a time: the next is decided only after every zone applied the last.
//! - **Delivering.** NATS delivers at most once, so the move is sent again (every
//!   `resend`) until every zone's heartbeat says it holds it or has applied it.
//! - **Reminding.** After that, with nothing outstanding, the epoch's last applied move
//!   is sent again every [`REMIND_S`]: zones recognise it as a repeat (their
//!   [`crate::rebalance::live::CutBook`] keeps the last applied), and a gateway that
//!   started after it was delivered learns the cuts in force (`gateway_cuts.rs`).
//! - **Checking.** A zone's heartbeat of tick `t` must name the cuts announced for tick
//!   `t - 1` (those it stepped with). One that does not missed a move (it came too late,
//!   or was refused) or took one nobody announced: [`Announcement::Diverged`], and the
//!   supervisor rolls the cluster back to the newest checkpoint whose zones all hold the
//!   same cuts ([`crate::supervisor`]); the move is dropped there (a rollback restarts
//!   from the checkpoint's cuts, and the policy decides again). So zones never go on
//!   with different cuts unseen; the lead only makes a rollback rare.
//!
//! Not [`crate::rebalance::Coordinator`]: it waits for every zone's report of one tick
//! and makes the zones wait for its answer, which a live cluster's zones must not do for
//! the supervisor; the announcer decides from whatever heartbeats it has and announces
//! far enough ahead instead.
//!
//! Forced moves (tests, `myriad cluster --rebalance-force`) are announced as soon as
//! nothing is outstanding, each for its own `at + lead`, so a test knows the tick a
//! cut moves at; one whose tick the zones have passed before it could be announced is
//! refused.

use std::sync::Arc;

use crate::error::ZoneError;
use crate::layout::{ZoneId, ZoneLayout};
use crate::rebalance::live::cuts_digest;
use crate::rebalance::{CutMove, Cuts, ForcedMove, StepTimeOptions, StepTimePolicy};
use crate::wire::{Load, ZoneState};

/// Seconds between reminders of the last applied move.
pub const REMIND_S: f64 = 2.0;

/// Who decides the moves of a live cluster.
#[derive(Clone, Debug, PartialEq)]
pub enum LivePolicy {
    /// [`StepTimePolicy`]: from the step times the zones report.
    StepTime(StepTimeOptions),
    /// Exactly these moves, each applied at `at + lead` (tests; an operator's forced
    /// move).
    Forced(Vec<ForcedMove>),
}

/// How the supervisor moves a live cluster's cuts.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveOptions {
    /// Ticks between the highest tick any zone reported and a move's `apply_at`: more
    /// than the zones step between two heartbeats and a delivery (30 = 1 s at 30 Hz).
    pub lead: u64,
    /// Seconds between sends of a move not yet held by every zone.
    pub resend_s: f64,
    /// Who decides.
    pub policy: LivePolicy,
}

impl LiveOptions {
    /// Options with `lead` ticks and `policy`, sent again every 0.2 s.
    pub fn new(lead: u64, policy: LivePolicy) -> LiveOptions {
        LiveOptions { lead, resend_s: 0.2, policy }
    }
}

/// What a zone's latest heartbeat of the current epoch said.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ZoneBeat {
    /// The tick it is at (the next it steps).
    pub tick: u64,
    /// What it is doing.
    pub state: ZoneState,
    /// Its load and cuts.
    pub load: Load,
}

/// What the supervisor must do or report after a look at the heartbeats.
#[derive(Clone, Debug, PartialEq)]
pub enum Announcement {
    /// Publish this move on the cuts subject (`first`: newly decided, else a repeat).
    Send {
        /// The move.
        cut: CutMove,
        /// Whether it was just decided.
        first: bool,
    },
    /// Every zone stepped past the move's tick on its cuts.
    Applied(CutMove),
    /// A proposed move was not announced (invalid for the cuts in force, or a forced
    /// move whose tick the zones had passed).
    Refused {
        /// The tick it was decided at.
        decided_at: u64,
        /// Why.
        reason: String,
    },
    /// A zone steps on other cuts than announced: the cluster must roll back.
    Diverged(String),
}

/// The move announced and not yet applied by every zone.
#[derive(Clone, Debug)]
struct Outstanding {
    cut: CutMove,
    digest: u64,
    /// When it was last sent (seconds).
    sent_at: f64,
    /// Whether it was a forced move (announced again after a rollback to before it).
    forced: bool,
}

/// Counts of a run's cut moves, for the summary and the metrics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MoveCounts {
    /// Moves announced.
    pub announced: u64,
    /// Moves every zone applied.
    pub applied: u64,
    /// Moves proposed and not announced.
    pub refused: u64,
}

/// The supervisor's rebalancing (see the module docs).
pub struct Announcer {
    opts: LiveOptions,
    /// The cuts of the last move announced (or the epoch's start).
    layout: Arc<ZoneLayout>,
    /// This epoch's cuts by the first tick stepped with them: (apply_at, digest), the
    /// start's first (apply_at 0).
    history: Vec<(u64, u64)>,
    policy: Option<StepTimePolicy>,
    /// Forced moves not announced yet, by decision tick.
    forced: Vec<ForcedMove>,
    outstanding: Option<Outstanding>,
    /// This epoch's last applied move and when it was last sent.
    applied: Option<(CutMove, f64)>,
    counts: MoveCounts,
    /// The run's last tick: a move for it or later would never apply.
    end: u64,
}

impl Announcer {
    /// An announcer for zones that start on `layout` and stop at tick `end`.
    pub fn new(opts: LiveOptions, layout: Arc<ZoneLayout>, end: u64) -> Result<Announcer, ZoneError> {
        if opts.lead == 0 || !(opts.resend_s.is_finite() && opts.resend_s > 0.0) {
            return Err(ZoneError::Layout(format!("a lead of {} ticks, sent every {} s", opts.lead, opts.resend_s)));
        }
        let (policy, mut forced) = match &opts.policy {
            LivePolicy::StepTime(o) => (Some(StepTimePolicy::new(o.clone(), &layout)), Vec::new()),
            LivePolicy::Forced(f) => (None, f.clone()),
        };
        forced.sort_by_key(|f| f.at);
        let (xs, zs) = layout.cuts();
        let history = vec![(0, cuts_digest(xs, zs))];
        let counts = MoveCounts::default();
        Ok(Announcer { opts, layout, history, policy, forced, outstanding: None, applied: None, counts, end })
    }

    /// The counts so far.
    pub fn counts(&self) -> MoveCounts {
        self.counts
    }

    /// The cuts of the last move announced.
    pub fn cuts(&self) -> Cuts {
        let (xs, zs) = self.layout.cuts();
        (xs.to_vec(), zs.to_vec())
    }

    /// An epoch starts at `tick` on `cuts` (its checkpoint's): a move outstanding is
    /// dropped (a forced one is announced again when its tick is still to come), and
    /// forced moves whose tick has passed with it.
    pub fn restart(&mut self, tick: u64, cuts: &Cuts) -> Result<(), ZoneError> {
        self.layout = Arc::new(self.layout.with_cuts(&cuts.0, &cuts.1)?);
        self.history = vec![(0, cuts_digest(&cuts.0, &cuts.1))];
        self.applied = None;
        if let Some(o) = self.outstanding.take() {
            tracing::warn!(apply_at = o.cut.apply_at, tick, "a rollback dropped the cut move outstanding");
            if o.forced {
                let CutMove { decided_at: at, xs, zs, .. } = o.cut;
                self.forced.insert(0, ForcedMove { at, xs, zs });
            }
        }
        let lead = self.opts.lead;
        self.forced.retain(|f| f.at + lead > tick);
        Ok(())
    }

    /// The digest of the cuts announced for stepping tick `t`.
    fn expected(&self, t: u64) -> u64 {
        let after_start = self.history.iter().skip(1).rfind(|(a, _)| *a <= t);
        after_start.unwrap_or(&self.history[0]).1
    }

    /// One look at the latest heartbeat of this epoch of every zone (`None`: not heard
    /// in it yet) at `now` (seconds, ascending).
    pub fn observe(&mut self, now: f64, beats: &[Option<ZoneBeat>]) -> Vec<Announcement> {
        let mut out = Vec::new();
        let stepping = |b: &ZoneBeat| b.state != ZoneState::Waiting;
        // Every zone on the cuts announced for the tick it last stepped.
        for (z, b) in beats.iter().enumerate() {
            let Some(b) = b.filter(stepping) else { continue };
            let want = self.expected(b.tick.saturating_sub(1));
            if b.tick > 0 && b.load.cuts != want {
                let missed = self.history.iter().skip(1).rfind(|(a, _)| *a < b.tick).map(|(a, _)| *a);
                out.push(Announcement::Diverged(format!(
                    "zone {z} at tick {} on cuts other than announced{}",
                    b.tick,
                    missed.map(|a| format!(" (the move of tick {a})")).unwrap_or_default()
                )));
                return out;
            }
        }
        if let Some(o) = &mut self.outstanding {
            let (a, d) = (o.cut.apply_at, o.digest);
            let applied = beats.iter().all(|b| b.is_some_and(|b| b.tick > a && b.load.cuts == d));
            if applied {
                self.counts.applied += 1;
                out.push(Announcement::Applied(o.cut.clone()));
                self.applied = Some((o.cut.clone(), now));
                self.outstanding = None;
            } else {
                let held = beats.iter().all(|b| b.is_some_and(|b| b.load.pending == a || b.tick > a));
                if !held && now - o.sent_at >= self.opts.resend_s {
                    o.sent_at = now;
                    out.push(Announcement::Send { cut: o.cut.clone(), first: false });
                }
                return out;
            }
        }
        if let Some((cut, sent_at)) = &mut self.applied
            && now - *sent_at >= REMIND_S
        {
            *sent_at = now;
            out.push(Announcement::Send { cut: cut.clone(), first: false });
        }
        // Decide only on a full view of zones that step.
        let Some(view) = beats.iter().map(|b| b.filter(stepping)).collect::<Option<Vec<ZoneBeat>>>() else {
            return out;
        };
        let top = view.iter().map(|b| b.tick).max().unwrap_or(0);
        let forced = self.policy.is_none();
        let proposal = match &mut self.policy {
            Some(p) => {
                let step_ms: Vec<f64> = view.iter().map(|b| b.load.step_us as f64 / 1e3).collect();
                p.observe(now, &self.layout, &step_ms).map(|(xs, zs)| (top, top + self.opts.lead, xs, zs))
            }
            None => self.forced.first().cloned().map(|f| {
                self.forced.remove(0);
                (f.at, f.at + self.opts.lead, f.xs, f.zs)
            }),
        };
        let Some((decided_at, apply_at, xs, zs)) = proposal else { return out };
        let cut = CutMove { decided_at, apply_at, xs, zs };
        let checked = if apply_at <= top + 1 {
            Err(format!("the zones reached tick {top}, too late to announce a move for tick {apply_at}"))
        } else if apply_at >= self.end {
            Err(format!("tick {apply_at} is past the run's last tick, {}", self.end))
        } else {
            cut.validate(&self.layout).map_err(|e| e.to_string())
        };
        match checked {
            Ok(layout) => {
                let digest = cuts_digest(&cut.xs, &cut.zs);
                self.layout = Arc::new(layout);
                self.history.push((apply_at, digest));
                self.outstanding = Some(Outstanding { cut: cut.clone(), digest, sent_at: now, forced });
                self.counts.announced += 1;
                out.push(Announcement::Send { cut, first: true });
            }
            Err(reason) => {
                self.counts.refused += 1;
                out.push(Announcement::Refused { decided_at, reason });
            }
        }
        out
    }

    /// Publishes each zone's load reported in `beats` as gauges
    /// (`myriad_supervisor_zone_step_seconds`, `myriad_supervisor_zone_owned_objects`)
    /// and the move counts (`myriad_supervisor_cut_moves_total{outcome}`).
    pub fn export(&self, beats: &[Option<ZoneBeat>]) {
        for (z, b) in beats.iter().enumerate() {
            let Some(b) = b else { continue };
            let z = ZoneId(z as u16).0.to_string();
            metrics::gauge!("myriad_supervisor_zone_step_seconds", "zone" => z.clone())
                .set(b.load.step_us as f64 / 1e6);
            metrics::gauge!("myriad_supervisor_zone_owned_objects", "zone" => z).set(b.load.owned as f64);
        }
        let c = self.counts;
        for (outcome, n) in [("announced", c.announced), ("applied", c.applied), ("refused", c.refused)] {
            metrics::counter!("myriad_supervisor_cut_moves_total", "outcome" => outcome).absolute(n);
        }
    }
}

#[cfg(test)]
#[path = "announce_tests.rs"]
mod tests;
