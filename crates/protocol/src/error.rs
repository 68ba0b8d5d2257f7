//! Typed errors. [`OpenError`] separates a malformed packet (cheap checks or body
//! decoding failed), a forged or corrupted one (tag check failed) and a replayed one,
//! so the server can count them apart; none of them changes any state.

use crate::header::PacketKind;
use thiserror::Error;

/// A packet or body that does not follow the wire format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum DecodeError {
    /// Fewer bytes than the format needs.
    #[error("truncated: needed {needed} bytes, got {got}")]
    Truncated {
        /// Bytes the decoder needed at the point it stopped.
        needed: usize,
        /// Bytes that were available.
        got: usize,
    },
    /// More bytes than any valid datagram can hold.
    #[error("datagram of {len} bytes exceeds the {max}-byte limit")]
    TooLong {
        /// Length received.
        len: usize,
        /// Largest valid length.
        max: usize,
    },
    /// Bytes left over after a complete body.
    #[error("{extra} trailing bytes after the body")]
    TrailingBytes {
        /// Number of unread bytes.
        extra: usize,
    },
    /// The header's protocol version is not ours.
    #[error("unsupported protocol version {0}")]
    BadVersion(u8),
    /// The header's packet kind byte is not assigned.
    #[error("unknown packet kind 0x{0:02x}")]
    UnknownKind(u8),
    /// A known packet kind that travels the other way.
    #[error("packet kind {0:?} is not valid in this direction")]
    WrongDirection(PacketKind),
    /// The header's sequence number is `u64::MAX`, which no sender ever uses.
    #[error("sequence number u64::MAX is never used")]
    ReservedSequence,
    /// An action mask with bits above bit 4.
    #[error("action mask 0x{0:02x} has bits above bit 4")]
    BadActionMask(u8),
    /// An unassigned disconnect reason code.
    #[error("unknown disconnect reason {0}")]
    BadDisconnectReason(u8),
    /// An unassigned shape kind in a state record or shape.
    #[error("unknown shape kind {0}")]
    BadShapeKind(u8),
    /// Reserved bits of an extended record are not zero.
    #[error("reserved bits set in a record's word or form byte 0x{0:08x}")]
    ReservedBits(u32),
    /// An object id that overflows 64 bits once the packet's id base is added.
    #[error("object id overflows u64")]
    IdOverflow,
    /// A state update declaring more records than its body holds.
    #[error("record count {count} does not match the body")]
    RecordCount {
        /// The declared count.
        count: u16,
    },
    /// A delta record naming a baseline 0 or more than 63 ticks back.
    #[error("delta record with baseline {0} ticks back (1 to 63 allowed)")]
    BadBack(u8),
    /// An id code (exp-Golomb) whose value exceeds `u64::MAX`.
    #[error("malformed id code")]
    BadIdCode,
    /// A predicted delta record whose prior state is 0 ticks before its baseline, or
    /// more than 63 ticks before its update together with its back.
    #[error("predicted record with back {back} and prior {prior} (prior ≥ 1, back + prior ≤ 63)")]
    BadPrior {
        /// Ticks from the baseline to the update.
        back: u8,
        /// Ticks from the prior state to the baseline.
        prior: u8,
    },
    /// An acknowledgement naming sequence numbers that cannot exist.
    #[error("acknowledgement of newest {newest} with field 0x{bits:016x} names no datagram")]
    BadAck {
        /// The newest sequence number acknowledged.
        newest: u64,
        /// The field of the ones before it.
        bits: u64,
    },
}

/// Why a received datagram was rejected by the replay window.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum ReplayError {
    /// This sequence number was already accepted.
    #[error("sequence {0} already received")]
    Duplicate(u64),
    /// This sequence number is older than the window remembers.
    #[error("sequence {0} is older than the replay window")]
    TooOld(u64),
}

/// Coarse class of an [`OpenError`], for counters and logs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorClass {
    /// The packet does not follow the format, or belongs to another session.
    Malformed,
    /// The tag did not verify: forged, corrupted or sealed with another key.
    Authentication,
    /// A sequence number seen before, or too old to tell.
    Replayed,
}

/// Why [`Opener::open_with`](crate::Opener::open_with) rejected a datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum OpenError {
    /// The header or the (authentic) body does not follow the format.
    #[error("malformed packet: {0}")]
    Malformed(#[from] DecodeError),
    /// The header names another session than the opener's.
    #[error("packet for session {got}, expected {expected}")]
    WrongSession {
        /// This opener's session id.
        expected: u64,
        /// The id in the header.
        got: u64,
    },
    /// The Poly1305 tag did not verify.
    #[error("authentication failed")]
    Authentication,
    /// The sequence number was replayed or is too old.
    #[error("replayed packet: {0}")]
    Replayed(#[from] ReplayError),
}

impl OpenError {
    /// The coarse class of this error.
    pub fn class(&self) -> ErrorClass {
        match self {
            Self::Malformed(_) | Self::WrongSession { .. } => ErrorClass::Malformed,
            Self::Authentication => ErrorClass::Authentication,
            Self::Replayed(_) => ErrorClass::Replayed,
        }
    }
}

/// Why a datagram could not be sealed. These are caller bugs or an exhausted session,
/// never caused by the peer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum SealError {
    /// The buffer is shorter than header plus tag, or longer than [`crate::MAX_DATAGRAM`].
    #[error("datagram buffer of {0} bytes has an invalid length")]
    BadLength(usize),
    /// The kind byte in the buffer is unknown or belongs to the other direction.
    #[error("packet kind byte 0x{0:02x} cannot be sealed by this side")]
    BadKind(u8),
    /// The message does not fit one datagram.
    #[error(transparent)]
    Encode(#[from] EncodeError),
    /// All 2^64 - 1 sequence numbers of this key were used: a new login is needed.
    #[error("sequence numbers exhausted; the session must be re-keyed")]
    SequenceExhausted,
    /// A sealer made from a [`SealLease`](crate::SealLease) used every sequence number of
    /// its lease; lease a new range from the session's sealer.
    #[error("sequence numbers of the lease exhausted")]
    LeaseExhausted,
    /// [`Sealer::lease`](crate::Sealer::lease) asked for more sequence numbers than the
    /// sealer has left.
    #[error("lease of {requested} sequence numbers requested, {available} left")]
    LeaseTooLarge {
        /// Numbers asked for.
        requested: u64,
        /// Numbers the sealer still owns.
        available: u64,
    },
    /// [`Sealer::return_unused`](crate::Sealer::return_unused) was given a lease that is
    /// not this sealer's latest (another session's, or one the sealer has moved past
    /// since), or more numbers used than the lease holds: nothing is returned.
    #[error("the lease cannot be returned to this sealer")]
    LeaseNotReturnable,
}

/// A message that cannot be encoded into one datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum EncodeError {
    /// The body would exceed [`crate::MAX_BODY`]; state updates this large must go
    /// through [`crate::pack_deltas`], which splits them.
    #[error("body of {len} bytes exceeds the {max}-byte limit")]
    TooLarge {
        /// Body length the message needs.
        len: usize,
        /// Largest body length.
        max: usize,
    },
    /// A delta update whose record ids are not strictly increasing.
    #[error("delta update records must have strictly increasing ids")]
    Unordered,
    /// A delta record no datagram can carry: a back or prior out of range, or a delta
    /// wider than the widest class (`DeltaRecord::choose` makes none).
    #[error("a delta record's back, prior or delta is out of range")]
    OutOfRange,
}
