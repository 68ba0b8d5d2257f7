//! Acknowledgements: which server datagrams a client received.
//!
//! A client reports, in its actions and keep-alives, the newest server sequence number
//! it opened and a 64-bit field of the 64 numbers before it (bit `i` set: sequence
//! `newest - 1 - i` was opened). The server turns them into the baselines its deltas are
//! relative to ([`crate::delta`]): a state the client acknowledged is one it holds.
//!
//! Acknowledgements are idempotent and travel in every client datagram, so a lost one is
//! repeated by the next; 65 sequence numbers are about one second of updates at 30 ticks
//! a second and two datagrams a tick.
//!
//! ```
//! use myriad_protocol::{AckField, AckTracker};
//!
//! let mut acks = AckTracker::default();
//! assert_eq!(acks.field(), None);
//! for sequence in [3, 5, 4, 9] {
//!     acks.record(sequence);
//! }
//! let field = acks.field().unwrap();
//! assert_eq!(field.newest(), 9);
//! assert_eq!(field.acknowledged().collect::<Vec<_>>(), [9, 5, 4, 3]);
//! assert!(field.contains(4) && !field.contains(6));
//! ```

use crate::error::DecodeError;
use crate::wire::Reader;

/// Encoded length of an optional [`AckField`]: newest (u64) and the field (u64).
pub const ACK_LEN: usize = 16;

/// Sequence numbers below the newest an [`AckField`] covers.
pub const ACK_BITS: u64 = 64;

/// What "nothing received yet" is encoded as: the newest sequence `u64::MAX`, which no
/// datagram ever carries (`docs/protocol.md`, section 3), with an empty field.
const NONE: u64 = u64::MAX;

/// The newest server sequence number a client opened and which of the 64 before it it
/// opened too.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct AckField {
    newest: u64,
    bits: u64,
}

impl AckField {
    /// A field for `newest` and the 64 numbers before it (`bits`, bit `i` for
    /// `newest - 1 - i`). `None` if `newest` is `u64::MAX` (never a sequence number) or
    /// a bit names a number below 0.
    pub fn new(newest: u64, bits: u64) -> Option<Self> {
        let valid = if newest >= ACK_BITS { u64::MAX } else { (1u64 << newest) - 1 };
        (newest != NONE && bits & !valid == 0).then_some(Self { newest, bits })
    }

    /// The newest sequence number acknowledged.
    pub fn newest(&self) -> u64 {
        self.newest
    }

    /// The field of the 64 numbers below [`Self::newest`].
    pub fn bits(&self) -> u64 {
        self.bits
    }

    /// Whether `sequence` is acknowledged.
    pub fn contains(&self, sequence: u64) -> bool {
        match self.newest.checked_sub(sequence) {
            Some(0) => true,
            Some(back @ 1..=ACK_BITS) => self.bits >> (back - 1) & 1 == 1,
            _ => false,
        }
    }

    /// The acknowledged sequence numbers, newest first.
    pub fn acknowledged(&self) -> impl Iterator<Item = u64> + '_ {
        std::iter::once(self.newest)
            .chain((0..ACK_BITS).filter(|i| self.bits >> i & 1 == 1).map(|i| self.newest - 1 - i))
    }

    /// Both fields in one: what either acknowledges within 64 numbers of the newer one's
    /// newest (older numbers of the older field are dropped; they were acknowledged
    /// long ago or are too old to matter).
    pub fn merge(self, other: Self) -> Self {
        let (hi, lo) = if self.newest >= other.newest { (self, other) } else { (other, self) };
        let shift = hi.newest - lo.newest;
        let mut bits = hi.bits;
        if (1..=ACK_BITS).contains(&shift) {
            // `lo.newest` itself is bit `shift - 1`; its field follows it.
            bits |= 1 << (shift - 1);
            bits |= lo.bits.checked_shl(shift as u32).unwrap_or(0);
        } else if shift == 0 {
            bits |= lo.bits;
        }
        Self { newest: hi.newest, bits }
    }

    /// Appends the 16-byte encoding of `field` (`None`: nothing received yet).
    pub fn encode(field: Option<Self>, out: &mut Vec<u8>) {
        let (newest, bits) = field.map_or((NONE, 0), |f| (f.newest, f.bits));
        out.extend_from_slice(&newest.to_le_bytes());
        out.extend_from_slice(&bits.to_le_bytes());
    }

    /// Decodes exactly the 16 bytes of [`Self::encode`]'s output.
    pub fn decode(bytes: &[u8]) -> Result<Option<Self>, DecodeError> {
        let mut r = Reader::new(bytes);
        let field = Self::read(&mut r)?;
        r.finish()?;
        Ok(field)
    }

    /// Reads the 16-byte encoding: `u64::MAX` with an empty field is "nothing received";
    /// `u64::MAX` with bits, or bits below sequence 0, are malformed.
    pub(crate) fn read(r: &mut Reader<'_>) -> Result<Option<Self>, DecodeError> {
        let (newest, bits) = (r.u64()?, r.u64()?);
        match (newest, bits) {
            (NONE, 0) => Ok(None),
            _ => Self::new(newest, bits).map(Some).ok_or(DecodeError::BadAck { newest, bits }),
        }
    }
}

/// A client's record of the server sequence numbers it opened, for its next
/// acknowledgement.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AckTracker {
    field: Option<AckField>,
}

impl AckTracker {
    /// Notes that the server datagram with `sequence` was opened (older than the field
    /// reaches: ignored; `u64::MAX`: never a sequence, ignored).
    pub fn record(&mut self, sequence: u64) {
        if let Some(one) = AckField::new(sequence, 0) {
            self.field = Some(self.field.map_or(one, |f| f.merge(one)));
        }
    }

    /// What to acknowledge now (`None` until something was opened).
    pub fn field(&self) -> Option<AckField> {
        self.field
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn out_of(n: usize) -> Vec<u8> {
        let mut out = Vec::new();
        AckField::encode(None, &mut out);
        out.resize(n, 0);
        out
    }

    #[test]
    fn encoding_round_trips_and_rejects_impossible_fields() {
        for field in [None, AckField::new(0, 0), AckField::new(70, u64::MAX), AckField::new(3, 0b101)] {
            let mut out = Vec::new();
            AckField::encode(field, &mut out);
            assert_eq!(out.len(), ACK_LEN);
            assert_eq!(AckField::decode(&out).unwrap(), field);
        }
        assert_eq!(AckField::new(3, 0b1000), None, "sequence -1 named");
        assert_eq!(AckField::new(u64::MAX, 0), None);
        let mut bad = u64::MAX.to_le_bytes().to_vec();
        bad.extend_from_slice(&1u64.to_le_bytes());
        assert!(matches!(AckField::decode(&bad), Err(DecodeError::BadAck { .. })));
        assert!(matches!(AckField::decode(&out_of(17)), Err(DecodeError::TrailingBytes { extra: 1 })));
    }

    proptest! {
        /// The tracker acknowledges exactly the recorded numbers within 64 of the newest,
        /// whatever the order they arrive in.
        #[test]
        fn tracker_acknowledges_what_was_recorded(seqs in proptest::collection::vec(0u64..300, 1..80)) {
            let mut t = AckTracker::default();
            for &s in &seqs {
                t.record(s);
            }
            let f = t.field().unwrap();
            let newest = *seqs.iter().max().unwrap();
            prop_assert_eq!(f.newest(), newest);
            for s in 0..310 {
                let expect = seqs.contains(&s) && newest - s.min(newest) <= ACK_BITS;
                prop_assert_eq!(f.contains(s), expect, "sequence {}", s);
            }
            let listed: Vec<u64> = f.acknowledged().collect();
            prop_assert!(listed.windows(2).all(|w| w[0] > w[1]));
            prop_assert!(listed.iter().all(|&s| f.contains(s)));
        }
    }
}
