//! A zone's side of the supervisor's cut moves ([`crate::rebalance::live`]): taking them
//! from the fabric, saying what the heartbeat reports of them, and applying a replay's.

use std::sync::Arc;

use super::Zone;
use crate::rebalance::live::{CutRefused, layout_digest};
use crate::rebalance::{CutMove, Cuts};
use crate::wire::{Message, decode};

impl Zone {
    /// The cuts the zone's objects were stepped to this tick with (its last step's, or
    /// those it started with): what a checkpoint of this tick records.
    pub fn stepped_cuts(&self) -> Cuts {
        let (xs, zs) = self.stepped_with.cuts();
        (xs.to_vec(), zs.to_vec())
    }

    /// [`crate::rebalance::live::cuts_digest`] of [`Zone::stepped_cuts`], for the
    /// heartbeat.
    pub fn stepped_digest(&self) -> u64 {
        layout_digest(&self.stepped_with)
    }

    /// The tick of the cut move held for a coming tick (0: none), for the heartbeat.
    pub fn pending_cut_move(&self) -> u64 {
        self.cuts.pending()
    }

    /// Applies a cut move a replay logged at this tick (the live zone applied it before
    /// stepping this tick): whether it could. A move for another tick, or one invalid
    /// for the layout, is refused.
    pub fn apply_logged_cut(&mut self, bytes: &[u8]) -> bool {
        let t = self.tick();
        let cut = match decode(&self.cfg.key, bytes) {
            Ok(Message::CutMove { cut, .. }) if cut.apply_at == t => cut,
            _ => return false,
        };
        match cut.validate(&self.layout) {
            Ok(layout) => self.set_layout(Arc::new(layout)).is_ok(),
            Err(_) => false,
        }
    }

    /// Files a supervisor's cut move in the book, or counts why not.
    pub(super) fn take_cut_move(&mut self, run: u64, cut: CutMove, bytes: &[u8], t: u64) {
        let taken = if run != self.cfg.run {
            Err(CutRefused::Run { got: run, epoch: self.cfg.run })
        } else {
            self.cuts.offer(cut, bytes, t, &self.layout)
        };
        match taken {
            Ok(fresh) => {
                self.stats.messages.1 += 1;
                if fresh {
                    tracing::info!(zone = self.cfg.id.0, tick = t, apply_at = self.cuts.pending(), "cut move held");
                }
            }
            Err(refused) => {
                tracing::warn!(zone = self.cfg.id.0, tick = t, %refused, "cut move refused");
                self.stats.cut_moves_refused += 1;
                self.reject(refused.label(), t);
            }
        }
    }
}
