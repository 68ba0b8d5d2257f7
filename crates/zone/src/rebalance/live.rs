//! Cut moves in a live cluster, the zone's side: which moves a zone takes from the
//! fabric, and when it follows them.
//!
//! The supervisor publishes a signed [`Message::CutMove`](crate::wire::Message::CutMove)
//! on `myriad.<cluster>.cuts` (only its NATS user may: [`crate::fabric_auth`]) for an
//! `apply_at` some ticks ahead of the zones (`--rebalance-lead-ticks`). A zone keeps it
//! in its [`CutBook`] and follows it just before stepping `apply_at`
//! ([`crate::Zone::set_layout`]), so hand-offs happen at that tick's exchange as in
//! `myriad sim --rebalance`. It refuses, counts and otherwise ignores ([`CutRefused`]):
//! a move of another epoch, one whose `apply_at` it has already stepped (`late`), one
//! that conflicts with a move it holds, and one [`CutMove::validate`] refuses for the
//! layout it would move from. A refusal never stops the tick.
//!
//! A refused or lost move must not leave zones on different cuts unnoticed: every
//! heartbeat carries the digest of the cuts its zone stepped with ([`cuts_digest`]) and
//! the move it holds, the supervisor sends a move again until every zone holds it, and
//! a zone seen past `apply_at` on other cuts than announced is a fault that rolls the
//! cluster back ([`crate::rebalance::announce`]).

use std::sync::Arc;

use crate::layout::ZoneLayout;
use crate::rebalance::CutMove;

/// A digest of cuts (FNV-1a over the counts and the bits of every cut): what a heartbeat
/// says of the cuts a zone follows, so the supervisor can compare them with its own.
pub fn cuts_digest(xs: &[f32], zs: &[f32]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for b in bytes {
            h ^= *b as u64;
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    for cuts in [xs, zs] {
        eat(&(cuts.len() as u32).to_le_bytes());
        cuts.iter().for_each(|c| eat(&c.to_bits().to_le_bytes()));
    }
    h
}

/// The digest of a layout's cuts.
pub fn layout_digest(layout: &ZoneLayout) -> u64 {
    let (xs, zs) = layout.cuts();
    cuts_digest(xs, zs)
}

/// Why a zone did not take a cut move (counted as `myriad_zone_rejected_total{reason}`
/// with [`CutRefused::label`], and in [`crate::ZoneStats::cut_moves_refused`]).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CutRefused {
    /// Of another epoch (an old move, replayed, or one of a rollback's past).
    #[error("a cut move of epoch {got}, this is epoch {epoch}")]
    Run {
        /// The move's epoch.
        got: u64,
        /// The zone's.
        epoch: u64,
    },
    /// For a tick the zone has already stepped, or is stepping.
    #[error("a cut move for tick {apply_at} arrived at tick {tick}")]
    Late {
        /// When it was to apply.
        apply_at: u64,
        /// The zone's tick when it arrived.
        tick: u64,
    },
    /// Another move is held for that tick or a later one not yet applied: moves come one
    /// at a time.
    #[error("a cut move for tick {apply_at} while the one for tick {held} is held")]
    Conflict {
        /// The move's tick.
        apply_at: u64,
        /// The tick of the move held.
        held: u64,
    },
    /// The cuts cannot follow the layout they would move from ([`CutMove::validate`]).
    #[error("an invalid cut move: {0}")]
    Invalid(String),
}

impl CutRefused {
    /// A short stable name, for metrics labels.
    pub fn label(&self) -> &'static str {
        match self {
            CutRefused::Run { .. } => "cut_run",
            CutRefused::Late { .. } => "cut_late",
            CutRefused::Conflict { .. } => "cut_conflict",
            CutRefused::Invalid(_) => "cut_invalid",
        }
    }
}

/// A move a zone holds: the move, the layout it makes, and the signed message (logged
/// for a replay when it is applied).
#[derive(Clone, Debug)]
pub struct HeldMove {
    /// The move.
    pub cut: CutMove,
    /// The layout it makes of the one before it.
    pub layout: Arc<ZoneLayout>,
    /// The message as it arrived.
    pub bytes: Vec<u8>,
}

/// The cut move a zone holds until its tick, and the last it applied (so that the
/// supervisor's repeats of either are recognised, not refused).
#[derive(Debug, Default)]
pub struct CutBook {
    held: Option<HeldMove>,
    /// (apply_at, digest of the cuts) of the last move applied.
    applied: Option<(u64, u64)>,
}

impl CutBook {
    /// Takes a move that arrived while the zone is at tick `tick` (its borders of `tick`
    /// may be sent already, so only a later tick is in time) and follows `current`:
    /// `Ok(true)` when held, `Ok(false)` when it repeats the move held or the last one
    /// applied (the supervisor sends a move until every zone holds it).
    pub fn offer(&mut self, cut: CutMove, bytes: &[u8], tick: u64, current: &ZoneLayout) -> Result<bool, CutRefused> {
        let digest = cuts_digest(&cut.xs, &cut.zs);
        let same = |apply_at: u64, d: u64| apply_at == cut.apply_at && d == digest;
        if let Some(h) = &self.held {
            if same(h.cut.apply_at, cuts_digest(&h.cut.xs, &h.cut.zs)) {
                return Ok(false);
            }
            return Err(CutRefused::Conflict { apply_at: cut.apply_at, held: h.cut.apply_at });
        }
        if self.applied.is_some_and(|(a, d)| same(a, d)) {
            return Ok(false);
        }
        if cut.apply_at <= tick {
            return Err(CutRefused::Late { apply_at: cut.apply_at, tick });
        }
        let layout = cut.validate(current).map_err(|e| CutRefused::Invalid(e.to_string()))?;
        self.held = Some(HeldMove { cut, layout: Arc::new(layout), bytes: bytes.to_vec() });
        Ok(true)
    }

    /// The move to apply before stepping `tick`, if one is held for it (taken from the
    /// book: it counts as applied).
    pub fn due(&mut self, tick: u64) -> Option<HeldMove> {
        if self.held.as_ref().is_none_or(|h| h.cut.apply_at != tick) {
            return None;
        }
        let h = self.held.take().expect("held");
        self.applied = Some((h.cut.apply_at, cuts_digest(&h.cut.xs, &h.cut.zs)));
        Some(h)
    }

    /// The tick of the move held (0: none), for the heartbeat.
    pub fn pending(&self) -> u64 {
        self.held.as_ref().map_or(0, |h| h.cut.apply_at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::{Aabb, Vec3};

    fn layout() -> ZoneLayout {
        let b = Aabb::new(Vec3::ZERO, Vec3::new(400.0, 50.0, 400.0));
        ZoneLayout::for_count(&b, 4, 1.5, 2.0).unwrap()
    }

    fn cut(apply_at: u64, x: f32) -> CutMove {
        CutMove { decided_at: 10, apply_at, xs: vec![0.0, x, 400.0], zs: vec![0.0, 200.0, 400.0] }
    }

    #[test]
    fn a_move_is_held_until_its_tick_and_repeats_are_recognised() {
        let l = layout();
        let mut book = CutBook::default();
        assert_eq!(book.offer(cut(40, 220.0), b"m", 12, &l), Ok(true));
        assert_eq!(book.pending(), 40);
        assert_eq!(book.offer(cut(40, 220.0), b"m", 13, &l), Ok(false), "a repeat");
        assert!(matches!(book.offer(cut(40, 210.0), b"m", 13, &l), Err(CutRefused::Conflict { .. })));
        assert!(matches!(book.offer(cut(50, 210.0), b"m", 13, &l), Err(CutRefused::Conflict { .. })));
        assert!(book.due(39).is_none());
        let h = book.due(40).expect("due");
        assert_eq!(h.layout.cuts().0, &[0.0, 220.0, 400.0]);
        assert_eq!(book.pending(), 0);
        assert_eq!(book.offer(cut(40, 220.0), b"m", 41, &l), Ok(false), "a repeat after it applied");
        assert_eq!(
            book.offer(cut(30, 240.0), b"m", 41, &l),
            Err(CutRefused::Late { apply_at: 30, tick: 41 }),
            "too late"
        );
        assert_eq!(book.offer(cut(41, 240.0), b"m", 41, &l).unwrap_err().label(), "cut_late", "being stepped");
        let invalid = book.offer(cut(60, 399.0), b"m", 41, &l).unwrap_err();
        assert_eq!(invalid.label(), "cut_invalid", "{invalid}");
        assert_eq!(book.pending(), 0, "nothing refused is held");
    }

    #[test]
    fn digests_tell_cuts_apart() {
        let (xs, zs) = (vec![0.0, 210.0, 400.0], vec![0.0, 200.0, 400.0]);
        assert_eq!(layout_digest(&layout().with_cuts(&xs, &zs).unwrap()), cuts_digest(&xs, &zs));
        assert_ne!(cuts_digest(&xs, &zs), cuts_digest(&xs, &[0.0, 201.0, 400.0]));
        assert_ne!(cuts_digest(&[0.0, 1.0], &[2.0, 3.0]), cuts_digest(&[0.0, 1.0, 2.0], &[3.0]), "counts count");
        assert_ne!(cuts_digest(&[0.0, 1.0], &[0.0, 1.0]), cuts_digest(&[-0.0, 1.0], &[0.0, 1.0]), "bits, not values");
    }
}
