//! What a client keeps to resolve delta records ([`Baselines`]), and the prediction a
//! `Predicted` record is relative to ([`predict`]).

use std::collections::VecDeque;

use crate::delta::{DeltaRecord, DeltaUpdate, MAX_BACK, RecordState};
use crate::quant::QuantPos;
use crate::update::{ShapeKind, StateRecord};

/// Where a `Predicted` record's baseline at `base`, `back` ticks before its update, is
/// expected to be: moved on along its move from `prior`, the state `prior_ticks` before
/// the baseline. Per axis `base + round((base - prior) × back / prior_ticks)`, rounding
/// to nearest and halves up (`floor((2n + p) / 2p)`), in 64-bit integers: exact on
/// every machine. The result may lie outside the `i32` range; the record's delta is
/// added to it before the position is saturated.
pub fn predict(base: QuantPos, prior: QuantPos, back: u8, prior_ticks: u8) -> [i64; 3] {
    let p = i64::from(prior_ticks.max(1));
    let axis = |b: i32, a: i32| {
        let n = (i64::from(b) - i64::from(a)) * i64::from(back);
        i64::from(b) + (2 * n + p).div_euclid(2 * p)
    };
    [axis(base.x, prior.x), axis(base.y, prior.y), axis(base.z, prior.z)]
}

/// The object's kind and its state `back` ticks before `tick`, from its history. A
/// record naming a tick before 0 has no baseline: it must not fall back on tick 0's
/// state (only a broken server sends one).
fn state_at(history: Option<&History>, id: u64, tick: u64, back: u64) -> Result<(ShapeKind, QuantPos), ResolveError> {
    let at = tick.checked_sub(back);
    let state = at.zip(history).and_then(|(at, h)| Some((h.kind, h.at(at)?)));
    state.ok_or(ResolveError::MissingBaseline { id, tick: at.unwrap_or(0) })
}

/// `from + d`, saturated at the `i32` range.
fn moved(from: [i64; 3], d: [i16; 3]) -> QuantPos {
    let at = |a: i64, d: i16| (a + i64::from(d)).clamp(i32::MIN.into(), i32::MAX.into()) as i32;
    QuantPos::new(at(from[0], d[0]), at(from[1], d[1]), at(from[2], d[2]))
}

/// Why a record could not be applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ResolveError {
    /// The record is relative to a state the client does not hold (it came too late, or
    /// the client restarted); the object's state is kept as it was.
    #[error("no state of object {id} at tick {tick} to apply a delta to")]
    MissingBaseline {
        /// The object.
        id: u64,
        /// The baseline's tick (0 for a record naming a tick before 0).
        tick: u64,
    },
}

/// What a client keeps to resolve delta records: every state it received of each object
/// in the last [`MAX_BACK`] ticks before the newest tick it saw.
#[derive(Debug, Clone, Default)]
pub struct Baselines {
    objects: foldhash::HashMap<u64, History>,
    newest: u64,
    pruned_at: u64,
}

#[derive(Debug, Clone)]
struct History {
    kind: ShapeKind,
    /// The newest state, equal to the back of `states` while that is not empty: most
    /// records name it, and reading it here does not touch the deque's memory, which
    /// for thousands of objects is a cache miss at nearly every record.
    last: (u64, QuantPos),
    /// `(tick, position)`, ticks increasing.
    states: VecDeque<(u64, QuantPos)>,
}

impl History {
    /// The state of `tick`. Searched from the newest: a record's baseline is the newest
    /// state the client acknowledged, nearly always one of the last few kept.
    fn at(&self, tick: u64) -> Option<QuantPos> {
        if !self.states.is_empty() && self.last.0 == tick {
            return Some(self.last.1);
        }
        self.states.iter().rev().take_while(|s| s.0 >= tick).find(|s| s.0 == tick).map(|s| s.1)
    }
}

impl Baselines {
    /// Resolves `record` of the update of tick `tick` into the object's state, and keeps
    /// that state as a baseline for later records.
    pub fn resolve(&mut self, tick: u64, record: &DeltaRecord) -> Result<StateRecord, ResolveError> {
        let id = record.id;
        let (kind, pos) = match record.state {
            RecordState::Absolute { kind, pos } => (kind, pos),
            RecordState::Delta { back, .. } | RecordState::Same { back } | RecordState::Predicted { back, .. } => {
                // One lookup of the object's history for both states a prediction needs.
                let history = self.objects.get(&id);
                let (kind, base) = state_at(history, id, tick, u64::from(back))?;
                match record.state {
                    RecordState::Delta { d, .. } => (kind, moved([base.x, base.y, base.z].map(i64::from), d)),
                    RecordState::Predicted { back, prior, d } => {
                        let (_, before) = state_at(history, id, tick, u64::from(back) + u64::from(prior))?;
                        (kind, moved(predict(base, before, back, prior), d))
                    }
                    _ => (kind, base),
                }
            }
        };
        self.remember(tick, StateRecord { id, kind, pos });
        Ok(StateRecord { id, kind, pos })
    }

    /// Resolves every record of `update` into `out` (appended, in the update's order) and
    /// returns how many could not be: a client acknowledges the datagram only when none
    /// failed, so the server never takes a state the client lacks for a baseline.
    pub fn resolve_update(&mut self, update: &DeltaUpdate, out: &mut Vec<StateRecord>) -> usize {
        self.resolve_records(update.header.tick, update.records.iter().copied(), out)
    }

    /// [`Self::resolve_update`] for the records of the update of tick `tick` as they come
    /// (a [`DeltaUpdateView`](crate::DeltaUpdateView)'s, without collecting them first).
    pub fn resolve_records(
        &mut self,
        tick: u64,
        records: impl IntoIterator<Item = DeltaRecord>,
        out: &mut Vec<StateRecord>,
    ) -> usize {
        let mut unresolved = 0;
        for r in records {
            match self.resolve(tick, &r) {
                Ok(state) => out.push(state),
                Err(_) => unresolved += 1,
            }
        }
        unresolved
    }

    /// Keeps `state` of tick `tick`.
    fn remember(&mut self, tick: u64, state: StateRecord) {
        self.newest = self.newest.max(tick);
        let floor = self.newest.saturating_sub(MAX_BACK);
        let h = self.objects.entry(state.id).or_insert_with(|| History {
            kind: state.kind,
            last: (tick, state.pos),
            states: VecDeque::new(),
        });
        h.kind = state.kind;
        if h.states.is_empty() || tick > h.last.0 {
            // Updates mostly come in order: the newest goes at the back.
            h.states.push_back((tick, state.pos));
        } else {
            // Where it goes, from the newest.
            match h.states.iter().rposition(|s| s.0 <= tick) {
                Some(i) if h.states[i].0 == tick => h.states[i].1 = state.pos,
                Some(i) => h.states.insert(i + 1, (tick, state.pos)),
                None => h.states.push_front((tick, state.pos)),
            }
        }
        while h.states.front().is_some_and(|s| s.0 < floor) {
            h.states.pop_front();
        }
        if let Some(&newest) = h.states.back() {
            h.last = newest;
        }
        // Now and then, forget objects with nothing left in the window. (Saturating: a
        // tick near `u64::MAX`, which only a broken server sends, must not overflow.)
        if self.newest >= self.pruned_at.saturating_add(MAX_BACK) {
            self.pruned_at = self.newest;
            self.objects.retain(|_, h| {
                while h.states.front().is_some_and(|s| s.0 < floor) {
                    h.states.pop_front();
                }
                !h.states.is_empty()
            });
        }
    }
}
