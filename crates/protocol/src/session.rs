//! Session keys, sealing and opening.
//!
//! The TLS login hands both sides a session id and two random 32-byte keys, one per
//! direction. Each datagram is sealed with ChaCha20-Poly1305:
//!
//! * key: the sending direction's key;
//! * nonce (12 bytes): direction byte (0 client to server, 1 server to client), three
//!   zero bytes, then the 64-bit sequence number little-endian;
//! * associated data: the 18-byte header, so version, kind, session id and sequence
//!   cannot be altered;
//! * tag: the 16 bytes after the ciphertext.
//!
//! A [`Sealer`] numbers its packets 0, 1, 2, … so a (key, nonce) pair is never reused.
//! An [`Opener`] runs the checks in cost order and commits the sequence number to its
//! [`ReplayWindow`] only after the tag verified and the body decoded. The checks
//! ([`Opener::verify`], `&self`) and the commit ([`Opener::commit`], `&mut self`) are
//! separate steps, so a receiver can verify many datagrams on several threads and
//! commit them in order on one.
//!
//! # Nonce ownership
//!
//! ChaCha20-Poly1305 breaks if one (key, nonce) pair seals two different datagrams, so
//! **every sequence number of a session's direction has at most one owner, and an owner
//! uses each of its numbers at most once**:
//!
//! * The login creates one [`Sealer`] per session and direction; it owns every sequence
//!   number from 0 up to, but not including, `u64::MAX` (which is never used, and which
//!   an [`Opener`] rejects).
//! * A sealer owns the range `[next_sequence, end_sequence)` and uses it in order.
//! * [`Sealer::lease`] moves the first `count` numbers of that range to a [`SealLease`]
//!   and advances the sealer past them, so the sealer can never use them again. A lease
//!   can be sent to another thread, and either becomes a bounded [`Sealer`]
//!   ([`SealLease::into_sealer`]), which refuses to seal past the lease's end with
//!   [`SealError::LeaseExhausted`], or hands its key and range to a device that seals
//!   by itself ([`SealLease::key_bytes`], [`SealLease::first_sequence`],
//!   [`SealLease::end_sequence`]); such a device takes over the same obligation.
//! * Neither [`Sealer`] nor [`SealLease`] is `Clone`: ownership of a range moves, it is
//!   never copied. Dropping a lease (or a leased sealer) abandons its unused numbers;
//!   they are simply never sent, which the receiver's replay window does not mind.
//!
//! Because the parent advances past a lease, datagrams sealed elsewhere carry sequence
//! numbers that interleave with the parent's in time but not in value; the receiver's
//! [`ReplayWindow`] accepts them in any order within its width.

use crate::aead::Aead;

use crate::batch::DatagramBatch;
use crate::error::{DecodeError, OpenError, SealError};
use crate::header::{Direction, HEADER_LEN, Header, MAX_DATAGRAM, MIN_DATAGRAM, PacketKind, peek_header};
use crate::message::{ClientMessage, ServerMessage, encode_client, encode_server};
use crate::replay::ReplayWindow;

/// What the login service hands to both ends of a session.
#[derive(Clone, PartialEq, Eq)]
pub struct SessionKeys {
    /// The session id every datagram carries.
    pub session_id: u64,
    /// Key of client-to-server datagrams.
    pub client_to_server: [u8; 32],
    /// Key of server-to-client datagrams.
    pub server_to_client: [u8; 32],
}

impl Drop for SessionKeys {
    // Wipe the keys when the last copy goes, so they do not linger in freed memory.
    fn drop(&mut self) {
        use zeroize::Zeroize;
        self.client_to_server.zeroize();
        self.server_to_client.zeroize();
    }
}

impl std::fmt::Debug for SessionKeys {
    // Keys never reach logs.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionKeys").field("session_id", &self.session_id).finish_non_exhaustive()
    }
}

/// 32 bytes of key material: wiped when dropped, never printed.
struct SecretKey([u8; 32]);

impl Drop for SecretKey {
    fn drop(&mut self) {
        use zeroize::Zeroize;
        self.0.zeroize();
    }
}

impl std::fmt::Debug for SecretKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SecretKey(..)")
    }
}

/// Seals outgoing datagrams of one session and direction.
///
/// Deliberately not `Clone`: two copies would hand out the same sequence numbers and so
/// reuse nonces under one key, which breaks ChaCha20-Poly1305. To seal on another thread
/// or device, [`lease`](Self::lease) a range of sequence numbers instead (see the
/// module docs on nonce ownership).
pub struct Sealer {
    cipher: Aead,
    /// Kept only to hand out leases.
    key: SecretKey,
    session_id: u64,
    direction: Direction,
    next_sequence: u64,
    /// First sequence number this sealer does not own: `u64::MAX` for a session's own
    /// sealer, the lease's end for a leased one.
    end_sequence: u64,
    /// Whether this sealer was made from a [`SealLease`]; only changes which error an
    /// exhausted range reports.
    leased: bool,
}

impl std::fmt::Debug for Sealer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sealer")
            .field("session_id", &self.session_id)
            .field("direction", &self.direction)
            .field("next_sequence", &self.next_sequence)
            .field("end_sequence", &self.end_sequence)
            .field("leased", &self.leased)
            .finish_non_exhaustive()
    }
}

impl Sealer {
    /// A sealer for `direction` with `key`, starting at sequence 0 and owning every
    /// sequence number below `u64::MAX`.
    pub fn new(session_id: u64, direction: Direction, key: &[u8; 32]) -> Self {
        Self::with_range(session_id, direction, SecretKey(*key), 0, u64::MAX, false)
    }

    fn with_range(
        session_id: u64,
        direction: Direction,
        key: SecretKey,
        next_sequence: u64,
        end_sequence: u64,
        leased: bool,
    ) -> Self {
        let cipher = Aead::new(&key.0);
        Self { cipher, key, session_id, direction, next_sequence, end_sequence, leased }
    }

    /// The sequence number the next datagram gets.
    pub fn next_sequence(&self) -> u64 {
        self.next_sequence
    }

    /// The first sequence number this sealer may not use: `u64::MAX` for a session's
    /// own sealer, the lease's end for one made by [`SealLease::into_sealer`].
    pub fn end_sequence(&self) -> u64 {
        self.end_sequence
    }

    /// How many datagrams this sealer can still seal.
    pub fn remaining(&self) -> u64 {
        self.end_sequence - self.next_sequence
    }

    /// Reserves the next `count` sequence numbers, `[next_sequence, next_sequence +
    /// count)`, for sealing elsewhere, and advances this sealer past them: it never uses
    /// them again. The lease carries a copy of the key, so another thread
    /// ([`SealLease::into_sealer`]) or a device can seal with them.
    ///
    /// A lease never reaches past this sealer's own end (so never reaches `u64::MAX`).
    /// Fails with [`SealError::LeaseTooLarge`], changing nothing, if fewer than `count`
    /// numbers remain. A lease of 0 numbers is valid and seals nothing.
    pub fn lease(&mut self, count: u64) -> Result<SealLease, SealError> {
        let available = self.remaining();
        if count > available {
            return Err(SealError::LeaseTooLarge { requested: count, available });
        }
        let first = self.next_sequence;
        let end = first + count;
        self.next_sequence = end;
        Ok(SealLease {
            key: SecretKey(self.key.0),
            session_id: self.session_id,
            direction: self.direction,
            first_sequence: first,
            end_sequence: end,
        })
    }

    /// Takes back the unused tail of `lease`, the sealer's latest: its first `used`
    /// numbers were used (or may have been), the rest never were, so this sealer may use
    /// them. Keeps a session's numbers dense when a device seals fewer datagrams than it
    /// was leased numbers for. Fails with [`SealError::LeaseNotReturnable`], changing
    /// nothing, when the lease is another session's or direction's, when this sealer has
    /// sealed or leased since, or when `used` exceeds the lease.
    ///
    /// ```
    /// use myriad_protocol::{Direction, Sealer};
    ///
    /// let mut sealer = Sealer::new(7, Direction::ServerToClient, &[9; 32]);
    /// let lease = sealer.lease(4).unwrap(); // numbers 0..4
    /// sealer.return_unused(lease, 1).unwrap(); // only 0 was used
    /// assert_eq!(sealer.next_sequence(), 1);
    /// ```
    pub fn return_unused(&mut self, lease: SealLease, used: u64) -> Result<(), SealError> {
        let ours = lease.session_id == self.session_id
            && lease.direction == self.direction
            && lease.end_sequence == self.next_sequence
            && used <= lease.len();
        if !ours {
            return Err(SealError::LeaseNotReturnable);
        }
        self.next_sequence = lease.first_sequence + used;
        Ok(())
    }

    /// Seals an unsealed frame in place: `datagram` is [`HEADER_LEN`] bytes whose
    /// second byte is the packet kind (as written by [`encode_client`],
    /// [`encode_server`] or [`crate::pack_deltas`]), the plaintext body, and
    /// [`TAG_LEN`](crate::TAG_LEN) bytes of tag space. Fills in the header, encrypts the body and writes
    /// the tag. Returns the sequence number used.
    pub fn seal_in_place(&mut self, datagram: &mut [u8]) -> Result<u64, SealError> {
        let len = datagram.len();
        if !(MIN_DATAGRAM..=MAX_DATAGRAM).contains(&len) {
            return Err(SealError::BadLength(len));
        }
        let kind_byte = datagram[1];
        let kind = PacketKind::from_byte(kind_byte)
            .filter(|k| k.direction() == self.direction)
            .ok_or(SealError::BadKind(kind_byte))?;
        // The end is at most u64::MAX, which is never used, so the counter cannot wrap
        // to a used nonce; a leased sealer stops at its lease's end.
        if self.next_sequence >= self.end_sequence {
            return Err(if self.leased { SealError::LeaseExhausted } else { SealError::SequenceExhausted });
        }
        let sequence = self.next_sequence;
        let (head, rest) = datagram.split_at_mut(HEADER_LEN);
        let (body, tag_space) = rest.split_at_mut(len - MIN_DATAGRAM);
        let header: &mut [u8; HEADER_LEN] = head.try_into().map_err(|_| SealError::BadLength(len))?;
        Header { kind, session_id: self.session_id, sequence }.write(header);
        let tag = self.cipher.seal(self.direction, sequence, header, body);
        tag_space.copy_from_slice(&tag);
        self.next_sequence += 1;
        Ok(sequence)
    }

    /// Appends `msg` to `out` as one sealed server datagram (this sealer must seal
    /// server-to-client). Appends nothing on error.
    pub fn seal_server_message(&mut self, msg: &ServerMessage, out: &mut Vec<u8>) -> Result<u64, SealError> {
        let start = out.len();
        encode_server(msg, out)?;
        self.seal_tail(out, start)
    }

    /// Appends `msg` to `out` as one sealed client datagram (this sealer must seal
    /// client-to-server). Appends nothing on error.
    pub fn seal_client_message(&mut self, msg: &ClientMessage, out: &mut Vec<u8>) -> Result<u64, SealError> {
        let start = out.len();
        encode_client(msg, out);
        self.seal_tail(out, start)
    }

    fn seal_tail(&mut self, out: &mut Vec<u8>, start: usize) -> Result<u64, SealError> {
        let result = self.seal_in_place(&mut out[start..]);
        if result.is_err() {
            out.truncate(start);
        }
        result
    }

    /// Seals every datagram of `batch` in place (see [`seal_in_place`](Self::seal_in_place)).
    pub fn seal_batch(&mut self, batch: &mut DatagramBatch) -> Result<(), SealError> {
        batch.try_for_each_mut(|d| self.seal_in_place(d).map(|_| ()))
    }
}

/// A range of one session's sequence numbers, with its key, reserved by
/// [`Sealer::lease`] for sealing on another thread or device.
///
/// The parent sealer has already moved past `[first_sequence, end_sequence)`, so
/// whoever holds the lease is the only one that may seal with those numbers, each at
/// most once. Not `Clone`, for the same reason as [`Sealer`]. The key is wiped when the
/// lease drops and never appears in `Debug` output.
///
/// ```
/// use myriad_protocol::{Direction, SealError, Sealer, ServerMessage};
///
/// let mut sealer = Sealer::new(7, Direction::ServerToClient, &[9; 32]);
/// let lease = sealer.lease(100).unwrap(); // numbers 0..100
/// assert_eq!(sealer.next_sequence(), 100); // the parent skips them
/// let worker = std::thread::spawn(move || {
///     let mut leased = lease.into_sealer();
///     let mut out = Vec::new();
///     for _ in 0..100 {
///         leased.seal_server_message(&ServerMessage::KeepAlive, &mut out).unwrap();
///     }
///     assert_eq!(leased.seal_server_message(&ServerMessage::KeepAlive, &mut out), Err(SealError::LeaseExhausted));
///     out
/// });
/// assert_eq!(worker.join().unwrap().len(), 100 * 34);
/// ```
///
/// A lease cannot be copied:
///
/// ```compile_fail
/// # use myriad_protocol::{Direction, Sealer};
/// let lease = Sealer::new(7, Direction::ServerToClient, &[9; 32]).lease(1).unwrap();
/// let twice = lease.clone();
/// ```
pub struct SealLease {
    key: SecretKey,
    session_id: u64,
    direction: Direction,
    first_sequence: u64,
    end_sequence: u64,
}

impl std::fmt::Debug for SealLease {
    // The key never reaches logs.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SealLease")
            .field("session_id", &self.session_id)
            .field("direction", &self.direction)
            .field("first_sequence", &self.first_sequence)
            .field("end_sequence", &self.end_sequence)
            .finish_non_exhaustive()
    }
}

impl SealLease {
    /// The session every datagram sealed under this lease must name.
    pub fn session_id(&self) -> u64 {
        self.session_id
    }

    /// The direction the datagrams travel in (part of the nonce).
    pub fn direction(&self) -> Direction {
        self.direction
    }

    /// The first sequence number of the lease.
    pub fn first_sequence(&self) -> u64 {
        self.first_sequence
    }

    /// The first sequence number after the lease (exclusive end); never above
    /// `u64::MAX`, so `u64::MAX` itself is never in a lease.
    pub fn end_sequence(&self) -> u64 {
        self.end_sequence
    }

    /// How many sequence numbers the lease holds.
    pub fn len(&self) -> u64 {
        self.end_sequence - self.first_sequence
    }

    /// Whether the lease holds no sequence number at all.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The direction's ChaCha20-Poly1305 key, for a device that seals by itself.
    ///
    /// **Secret.** Copy it only into memory the device wipes after use, never log it, and
    /// seal with it only under nonces whose sequence lies in
    /// `[first_sequence, end_sequence)`, each at most once. The lease's own copy is wiped
    /// when it drops.
    pub fn key_bytes(&self) -> &[u8; 32] {
        &self.key.0
    }

    /// A sealer that starts at [`first_sequence`](Self::first_sequence) and refuses,
    /// with [`SealError::LeaseExhausted`], to seal at or past
    /// [`end_sequence`](Self::end_sequence).
    pub fn into_sealer(self) -> Sealer {
        let Self { key, session_id, direction, first_sequence, end_sequence } = self;
        Sealer::with_range(session_id, direction, key, first_sequence, end_sequence, true)
    }
}

/// A datagram that passed every check.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Opened<T> {
    /// Its header.
    pub header: Header,
    /// What the decoder made of its body.
    pub message: T,
}

/// A datagram that passed every check of [`Opener::verify`] (header, session, replay
/// window as it was then, tag, body) but is not yet recorded in the replay window.
///
/// Only [`Opener::commit`] turns it into an [`Opened`]: until then its sequence number
/// is still free, so another copy of the same datagram may verify too, and the commit
/// accepts only the first. Not `Clone`, and it can only be made by `verify`.
#[derive(Debug, PartialEq, Eq)]
#[must_use = "a verified datagram counts only once committed"]
pub struct Verified<T> {
    header: Header,
    message: T,
}

impl<T> Verified<T> {
    /// Its header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// Its sequence number, which [`Opener::commit`] records.
    pub fn sequence(&self) -> u64 {
        self.header.sequence
    }

    /// Its message, verified but not committed: reading it changes nothing.
    pub fn message(&self) -> &T {
        &self.message
    }
}

/// Opens incoming datagrams of one session and direction, rejecting replays.
///
/// Opening is two steps, so that the cryptography of many datagrams can run on several
/// threads while the replay window stays in one place: [`verify`](Self::verify) takes
/// `&self` (an `Opener` is `Sync`) and checks everything without changing anything,
/// and [`commit`](Self::commit) takes `&mut self`, re-checks the window and records the
/// sequence number. [`open_with`](Self::open_with) is the two in a row.
///
/// Not `Clone`: two copies would each accept the same packet once.
pub struct Opener {
    cipher: Aead,
    session_id: u64,
    direction: Direction,
    window: ReplayWindow,
}

impl std::fmt::Debug for Opener {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Opener")
            .field("session_id", &self.session_id)
            .field("direction", &self.direction)
            .field("window", &self.window.newest())
            .finish_non_exhaustive()
    }
}

impl Opener {
    /// An opener for datagrams travelling in `direction`, sealed with `key`.
    pub fn new(session_id: u64, direction: Direction, key: &[u8; 32]) -> Self {
        Self { cipher: Aead::new(key), session_id, direction, window: ReplayWindow::new() }
    }

    /// The replay window (read only).
    pub fn window(&self) -> &ReplayWindow {
        &self.window
    }

    /// Checks, decrypts in place and decodes `datagram` with `decode(kind, body)`, and
    /// records its sequence number: [`verify`](Self::verify) then
    /// [`commit`](Self::commit).
    ///
    /// On any error the opener is unchanged. If the tag verified, `datagram`'s body now
    /// holds plaintext; a datagram rejected before the tag check is untouched, and one
    /// whose tag failed has an unspecified body (it is garbage either way).
    pub fn open_with<T>(
        &mut self,
        datagram: &mut [u8],
        decode: impl FnOnce(PacketKind, &[u8]) -> Result<T, DecodeError>,
    ) -> Result<Opened<T>, OpenError> {
        let verified = self.verify(datagram, decode)?;
        self.commit(verified)
    }

    /// Checks, decrypts in place and decodes `datagram` with `decode(kind, body)`,
    /// without recording anything: the replay window does not move, so this takes
    /// `&self` and may run for many datagrams at once on several threads.
    ///
    /// Order: length, version, kind and direction, sequence not `u64::MAX`, session id,
    /// replay window as it is now (all without cryptography), then the tag, then
    /// `decode`. Bytes are as for [`open_with`](Self::open_with).
    ///
    /// The window may move between `verify` and [`commit`](Self::commit). A caller
    /// that verifies several datagrams before committing them, and needs the error
    /// `open_with` would have given in their order, re-checks
    /// [`window`](Self::window) with the header's sequence number before reporting a
    /// tag or body error: sequentially, a datagram an earlier one made a replay fails
    /// at the window, before its tag is looked at.
    pub fn verify<T>(
        &self,
        datagram: &mut [u8],
        decode: impl FnOnce(PacketKind, &[u8]) -> Result<T, DecodeError>,
    ) -> Result<Verified<T>, OpenError> {
        let header = peek_header(datagram, self.direction)?;
        if header.session_id != self.session_id {
            return Err(OpenError::WrongSession { expected: self.session_id, got: header.session_id });
        }
        self.window.check(header.sequence)?;
        let len = datagram.len();
        let (head, rest) = datagram.split_at_mut(HEADER_LEN);
        let (body, tag) = rest.split_at_mut(len - MIN_DATAGRAM);
        // On failure the body may be partly decrypted: the caller drops the datagram.
        self.cipher.open(self.direction, header.sequence, head, body, tag).map_err(|_| OpenError::Authentication)?;
        let message = decode(header.kind, body)?;
        Ok(Verified { header, message })
    }

    /// Records the sequence number of `verified`, which this opener verified, and hands
    /// back the opened datagram.
    ///
    /// The window is checked again, as it is now: of two copies of one datagram
    /// verified before either was committed, the second to commit is refused as
    /// [`OpenError::Replayed`]. A datagram verified by an opener of another session or
    /// direction is refused as [`OpenError::WrongSession`] or malformed: its tag was
    /// never checked under this opener's key. On error the opener is unchanged.
    pub fn commit<T>(&mut self, verified: Verified<T>) -> Result<Opened<T>, OpenError> {
        let Verified { header, message } = verified;
        if header.session_id != self.session_id {
            return Err(OpenError::WrongSession { expected: self.session_id, got: header.session_id });
        }
        if header.kind.direction() != self.direction {
            return Err(OpenError::Malformed(DecodeError::WrongDirection(header.kind)));
        }
        self.window.commit(header.sequence)?;
        Ok(Opened { header, message })
    }
}

/// Seals a body-less client datagram of `kind` at any `sequence`, `u64::MAX` included,
/// with the session's client-to-server key: what a buggy or malicious client holding
/// the key could send. It bypasses the nonce-ownership rules (module docs), so it exists
/// only for tests and attack tools (cargo feature `forge`).
#[cfg(any(test, feature = "forge"))]
pub fn forge_sealed(keys: &SessionKeys, kind: PacketKind, sequence: u64) -> Vec<u8> {
    let mut d = vec![0u8; MIN_DATAGRAM];
    let (head, tag_space) = d.split_at_mut(HEADER_LEN);
    let head: &mut [u8; HEADER_LEN] = head.try_into().expect("the header's length");
    Header { kind, session_id: keys.session_id, sequence }.write(head);
    let tag = Aead::new(&keys.client_to_server).seal(Direction::ClientToServer, sequence, head, &mut []);
    tag_space.copy_from_slice(&tag);
    d
}

/// The server's end of a session: seals server-to-client, opens client-to-server.
#[derive(Debug)]
pub struct ServerSession {
    /// Seals what the server sends.
    pub sealer: Sealer,
    /// Opens what the client sends.
    pub opener: Opener,
}

impl ServerSession {
    /// Both halves from the login's keys.
    pub fn new(keys: &SessionKeys) -> Self {
        Self {
            sealer: Sealer::new(keys.session_id, Direction::ServerToClient, &keys.server_to_client),
            opener: Opener::new(keys.session_id, Direction::ClientToServer, &keys.client_to_server),
        }
    }

    /// Appends `msg` to `out` as one sealed datagram. Fails for a state update too
    /// large for one datagram (use [`crate::pack_deltas`] and [`Sealer::seal_batch`]).
    pub fn seal(&mut self, msg: &ServerMessage, out: &mut Vec<u8>) -> Result<u64, SealError> {
        self.sealer.seal_server_message(msg, out)
    }

    /// Opens and decodes a client datagram.
    pub fn open(&mut self, datagram: &mut [u8]) -> Result<Opened<ClientMessage>, OpenError> {
        self.opener.open_with(datagram, ClientMessage::decode_body)
    }
}

/// The client's end of a session: seals client-to-server, opens server-to-client.
#[derive(Debug)]
pub struct ClientSession {
    /// Seals what the client sends.
    pub sealer: Sealer,
    /// Opens what the server sends.
    pub opener: Opener,
}

impl ClientSession {
    /// Both halves from the login's keys.
    pub fn new(keys: &SessionKeys) -> Self {
        Self {
            sealer: Sealer::new(keys.session_id, Direction::ClientToServer, &keys.client_to_server),
            opener: Opener::new(keys.session_id, Direction::ServerToClient, &keys.server_to_client),
        }
    }

    /// Appends `msg` to `out` as one sealed datagram.
    pub fn seal(&mut self, msg: &ClientMessage, out: &mut Vec<u8>) -> Result<u64, SealError> {
        self.sealer.seal_client_message(msg, out)
    }

    /// Opens and decodes a server datagram.
    pub fn open(&mut self, datagram: &mut [u8]) -> Result<Opened<ServerMessage>, OpenError> {
        self.opener.open_with(datagram, ServerMessage::decode_body)
    }
}

#[cfg(test)]
mod tests;
