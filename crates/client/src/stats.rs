//! Counters of one client session, and rates between two snapshots.

/// Cumulative counters of a client (over reconnects).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ClientStats {
    /// Datagrams received that passed authentication.
    pub datagrams: u64,
    /// Bytes of those datagrams.
    pub bytes: u64,
    /// State-update datagrams among them.
    pub updates: u64,
    /// State records received and resolved (applied to the mirror).
    pub records: u64,
    /// Delta records skipped because the client did not hold their baseline (the object
    /// is only delayed: the datagram is not acknowledged, so the server sends it again
    /// relative to a state the client holds).
    pub unresolved: u64,
    /// Datagrams dropped: not authentic, replayed or malformed.
    pub rejected: u64,
    /// State updates whose body did not decode (after authentication: a server bug).
    pub decode_errors: u64,
    /// Highest tick seen in a state update.
    pub last_tick: u64,
    /// Datagrams the server numbered but we never received (gaps in sequence numbers,
    /// summed over sessions).
    pub lost: u64,
    /// Datagrams sent.
    pub sent: u64,
    /// Logins after the first.
    pub reconnects: u64,
    /// Datagrams sent again because an answer was missing: Readies resent and keep-alive
    /// probes to a silent server (docs/protocol.md §7a).
    pub resent: u64,
}

impl ClientStats {
    /// Share of the server's datagrams lost, 0..=1.
    pub fn loss(&self) -> f64 {
        let total = self.datagrams + self.lost;
        if total == 0 { 0.0 } else { self.lost as f64 / total as f64 }
    }

    /// Rates per second between an earlier snapshot and this one.
    pub fn rates_since(&self, earlier: &ClientStats, seconds: f64) -> Rates {
        let s = seconds.max(1e-9);
        Rates {
            updates_per_s: (self.updates - earlier.updates) as f64 / s,
            bytes_per_s: (self.bytes - earlier.bytes) as f64 / s,
            records_per_s: (self.records - earlier.records) as f64 / s,
        }
    }
}

/// Rates between two [`ClientStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Rates {
    /// State-update datagrams per second.
    pub updates_per_s: f64,
    /// Bytes per second.
    pub bytes_per_s: f64,
    /// Records per second.
    pub records_per_s: f64,
}

/// Tracks sequence numbers of one session to count gaps.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SequenceTracker {
    highest: Option<u64>,
}

impl SequenceTracker {
    /// Records an accepted sequence number; returns how many numbers it skipped (a
    /// datagram arriving late after being counted as lost is not un-counted: the replay
    /// window accepts it, and loss is an estimate).
    pub(crate) fn record(&mut self, seq: u64) -> u64 {
        match self.highest {
            None => {
                self.highest = Some(seq);
                seq
            }
            Some(h) if seq > h => {
                self.highest = Some(seq);
                seq - h - 1
            }
            Some(_) => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_count_as_loss() {
        let mut t = SequenceTracker::default();
        assert_eq!(t.record(0), 0);
        assert_eq!(t.record(1), 0);
        assert_eq!(t.record(4), 2);
        assert_eq!(t.record(3), 0);
        let s = ClientStats { datagrams: 8, lost: 2, ..Default::default() };
        assert!((s.loss() - 0.2).abs() < 1e-9);
    }
}
