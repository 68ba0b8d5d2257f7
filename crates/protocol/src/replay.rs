//! Sliding replay window over 64-bit sequence numbers.
//!
//! The window remembers the highest sequence accepted and, as a ring of
//! [`REPLAY_WINDOW`] bits indexed by `sequence % REPLAY_WINDOW`, which of the
//! `REPLAY_WINDOW` sequences up to it were accepted. A sequence is acceptable when it is
//! newer than the highest, or within the window and not yet seen. [`ReplayWindow::check`]
//! never changes the window; [`ReplayWindow::commit`] is called only once the packet's
//! tag verified and its body decoded, so forged packets cannot move the window.

use crate::error::ReplayError;

/// Number of sequence numbers the window remembers below the highest one accepted.
/// 1024 packets is over 8 seconds of 120 Hz traffic, far more reordering than UDP shows.
pub const REPLAY_WINDOW: u64 = 1024;

const WORDS: usize = (REPLAY_WINDOW / 64) as usize;

/// Per-session, per-direction record of the sequence numbers already accepted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReplayWindow {
    /// Highest sequence accepted; meaningless while `started` is false.
    newest: u64,
    /// Whether any sequence was accepted yet.
    started: bool,
    /// Ring of seen bits, bit `seq % REPLAY_WINDOW`.
    bits: [u64; WORDS],
}

impl Default for ReplayWindow {
    fn default() -> Self {
        Self::new()
    }
}

impl ReplayWindow {
    /// An empty window that accepts any sequence number.
    pub const fn new() -> Self {
        Self { newest: 0, started: false, bits: [0; WORDS] }
    }

    /// The highest sequence accepted so far, if any.
    pub fn newest(&self) -> Option<u64> {
        self.started.then_some(self.newest)
    }

    #[inline]
    fn slot(seq: u64) -> (usize, u64) {
        let bit = seq % REPLAY_WINDOW;
        ((bit / 64) as usize, 1u64 << (bit % 64))
    }

    /// Whether `seq` would be accepted. Changes nothing.
    #[inline]
    pub fn check(&self, seq: u64) -> Result<(), ReplayError> {
        if !self.started || seq > self.newest {
            return Ok(());
        }
        if self.newest - seq >= REPLAY_WINDOW {
            return Err(ReplayError::TooOld(seq));
        }
        let (word, mask) = Self::slot(seq);
        if self.bits[word] & mask != 0 { Err(ReplayError::Duplicate(seq)) } else { Ok(()) }
    }

    /// Records `seq` as accepted; call only after [`check`](Self::check) passed and the
    /// packet authenticated. Returns the same error as `check` and changes nothing if
    /// `seq` is not acceptable.
    pub fn commit(&mut self, seq: u64) -> Result<(), ReplayError> {
        self.check(seq)?;
        if !self.started {
            self.started = true;
            self.newest = seq;
            self.bits = [0; WORDS];
        } else if seq > self.newest {
            let advance = seq - self.newest;
            if advance >= REPLAY_WINDOW {
                self.bits = [0; WORDS];
            } else {
                // Forget the slots the window slides past: they now stand for the
                // newly reachable sequences newest+1 ..= seq.
                for s in self.newest + 1..=seq {
                    let (word, mask) = Self::slot(s);
                    self.bits[word] &= !mask;
                }
            }
            self.newest = seq;
        }
        let (word, mask) = Self::slot(seq);
        self.bits[word] |= mask;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn duplicates_and_old_packets() {
        let mut w = ReplayWindow::new();
        assert_eq!(w.newest(), None);
        w.commit(5).unwrap();
        assert_eq!(w.check(5), Err(ReplayError::Duplicate(5)));
        assert_eq!(w.check(4), Ok(()));
        w.commit(5 + REPLAY_WINDOW).unwrap();
        assert_eq!(w.check(5), Err(ReplayError::TooOld(5)));
        assert_eq!(w.check(6), Ok(()));
        assert_eq!(w.check(5 + REPLAY_WINDOW), Err(ReplayError::Duplicate(5 + REPLAY_WINDOW)));
        assert_eq!(w.commit(5), Err(ReplayError::TooOld(5)));
        w.commit(u64::MAX).unwrap();
        assert_eq!(w.check(u64::MAX), Err(ReplayError::Duplicate(u64::MAX)));
        assert_eq!(w.check(u64::MAX - REPLAY_WINDOW), Err(ReplayError::TooOld(u64::MAX - REPLAY_WINDOW)));
        assert_eq!(w.check(u64::MAX - REPLAY_WINDOW + 1), Ok(()));
    }
}
