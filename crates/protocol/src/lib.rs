//! Wire format of Myriad, free of I/O.
//!
//! This crate turns messages into sealed UDP datagrams and back, in memory only, so every
//! rule of the protocol can be unit-tested, property-tested, fuzzed and benchmarked
//! without a socket. `docs/protocol.md` describes the same format byte by byte.
//!
//! # How it works
//!
//! * Every datagram is `header (18 bytes) | ciphertext body | tag (16 bytes)`
//!   ([`header`]). The header is sent in clear but authenticated as associated data.
//! * A [`Sealer`] encrypts with ChaCha20-Poly1305 under one direction's key and a
//!   nonce made of the direction and a strictly increasing 64-bit sequence number
//!   ([`session`]).
//! * An [`Opener`] checks the cheap things first (length, version, packet kind,
//!   session id, replay window), then the tag, then decodes the body, and only then
//!   marks the sequence number as seen in its [`ReplayWindow`]: a packet that fails any
//!   check changes no state.
//! * Bodies are plain little-endian structures ([`message`]). The client acknowledges
//!   the server datagrams it opened in every action and keep-alive ([`ack`]); state
//!   updates carry each object relative to a state the client acknowledged (or
//!   predicted along its move since the one before), bit-packed, in 2 to 6 bytes when
//!   it moved little, or absolute when there is none ([`delta`]).
//!   [`pack_deltas`] fills as few datagrams as possible without allocating per record,
//!   and a client's [`Baselines`] resolves what it receives, skipping (never
//!   misapplying) a record whose baseline it lacks.
//!
//! This is version 3 of the datagram protocol ([`PROTOCOL_VERSION`]); clients of
//! versions 1 and 2 are refused at login ([`login::RefusalReason::OutdatedClient`]).
//!
//! # API boundary
//!
//! No sockets, threads or clocks here: callers hand in byte buffers and get byte
//! buffers back. The transport lives in `myriad-net`, the choice of what to send in
//! `myriad-interest`.

pub mod ack;
mod aead;
mod baselines;
pub mod batch;
mod bits;
pub mod delta;
pub mod error;
pub mod header;
pub mod login;
pub mod message;
pub mod quant;
mod receiver;
pub mod replay;
pub mod session;
pub mod update;

mod wire;

pub use ack::{ACK_LEN, AckField, AckTracker};
pub use batch::DatagramBatch;
pub use delta::{
    Baseline, Baselines, BodyLengthError, DELTA_HEADER_LEN, DeltaRecord, DeltaUpdate, DeltaUpdateView, MAX_BACK,
    RecordState, ResolveError, frame_delta_body, pack_deltas, predict,
};
pub use error::{DecodeError, EncodeError, ErrorClass, OpenError, ReplayError, SealError};
pub use header::{
    Direction, HEADER_LEN, Header, MAX_BODY, MAX_DATAGRAM, MIN_DATAGRAM, PROTOCOL_VERSION, PacketKind, TAG_LEN,
    peek_header,
};
pub use message::{
    ActionMask, ClientMessage, DisconnectReason, PlayerInput, ServerInfo, ServerMessage, encode_client, encode_server,
};
pub use quant::{POS_SCALE, QuantPos};
pub use receiver::UpdateReceiver;
pub use replay::{REPLAY_WINDOW, ReplayWindow};
pub use session::{ClientSession, Opened, Opener, SealLease, Sealer, ServerSession, SessionKeys, Verified};
pub use update::{ShapeKind, StateRecord, UpdateHeader};
