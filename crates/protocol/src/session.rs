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
//! [`ReplayWindow`] only after the tag verified and the body decoded.

use chacha20poly1305::aead::array::Array;
use chacha20poly1305::{AeadInOut, ChaCha20Poly1305, KeyInit};

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

fn nonce(direction: Direction, sequence: u64) -> Array<u8, chacha20poly1305::consts::U12> {
    let mut n = [0u8; 12];
    n[0] = direction.nonce_byte();
    n[4..].copy_from_slice(&sequence.to_le_bytes());
    Array::from(n)
}

/// Seals outgoing datagrams of one session and direction.
///
/// Deliberately not `Clone`: two copies would hand out the same sequence numbers and so
/// reuse nonces under one key, which breaks ChaCha20-Poly1305.
pub struct Sealer {
    cipher: ChaCha20Poly1305,
    session_id: u64,
    direction: Direction,
    next_sequence: u64,
}

impl std::fmt::Debug for Sealer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sealer")
            .field("session_id", &self.session_id)
            .field("direction", &self.direction)
            .field("next_sequence", &self.next_sequence)
            .finish_non_exhaustive()
    }
}

impl Sealer {
    /// A sealer for `direction` with `key`, starting at sequence 0.
    pub fn new(session_id: u64, direction: Direction, key: &[u8; 32]) -> Self {
        Self { cipher: ChaCha20Poly1305::new(&Array::from(*key)), session_id, direction, next_sequence: 0 }
    }

    /// The sequence number the next datagram gets.
    pub fn next_sequence(&self) -> u64 {
        self.next_sequence
    }

    /// Seals an unsealed frame in place: `datagram` is [`HEADER_LEN`] bytes whose
    /// second byte is the packet kind (as written by [`encode_client`],
    /// [`encode_server`] or [`crate::pack_updates`]), the plaintext body, and
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
        // u64::MAX is never used, so the counter cannot wrap to a used nonce.
        if self.next_sequence == u64::MAX {
            return Err(SealError::SequenceExhausted);
        }
        let sequence = self.next_sequence;
        let (head, rest) = datagram.split_at_mut(HEADER_LEN);
        let (body, tag_space) = rest.split_at_mut(len - MIN_DATAGRAM);
        let header: &mut [u8; HEADER_LEN] = head.try_into().map_err(|_| SealError::BadLength(len))?;
        Header { kind, session_id: self.session_id, sequence }.write(header);
        let tag = self
            .cipher
            .encrypt_inout_detached(&nonce(self.direction, sequence), header, body.into())
            // Only fails for bodies of 256 GiB and more.
            .map_err(|_| SealError::BadLength(len))?;
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

/// A datagram that passed every check.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Opened<T> {
    /// Its header.
    pub header: Header,
    /// What the decoder made of its body.
    pub message: T,
}

/// Opens incoming datagrams of one session and direction, rejecting replays.
///
/// Not `Clone`: two copies would each accept the same packet once.
pub struct Opener {
    cipher: ChaCha20Poly1305,
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
        Self { cipher: ChaCha20Poly1305::new(&Array::from(*key)), session_id, direction, window: ReplayWindow::new() }
    }

    /// The replay window (read only).
    pub fn window(&self) -> &ReplayWindow {
        &self.window
    }

    /// Checks, decrypts in place and decodes `datagram` with `decode(kind, body)`.
    ///
    /// Order: length, version, kind and direction, session id, replay window (all
    /// without cryptography), then the tag, then `decode`; the sequence number is
    /// recorded only when all passed. On any error the opener is unchanged. If the tag
    /// verified, `datagram`'s body now holds plaintext; otherwise it is untouched.
    pub fn open_with<T>(
        &mut self,
        datagram: &mut [u8],
        decode: impl FnOnce(PacketKind, &[u8]) -> Result<T, DecodeError>,
    ) -> Result<Opened<T>, OpenError> {
        let header = peek_header(datagram, self.direction)?;
        if header.session_id != self.session_id {
            return Err(OpenError::WrongSession { expected: self.session_id, got: header.session_id });
        }
        self.window.check(header.sequence)?;
        let len = datagram.len();
        let (head, rest) = datagram.split_at_mut(HEADER_LEN);
        let (body, tag) = rest.split_at_mut(len - MIN_DATAGRAM);
        let tag = Array::try_from(&*tag).map_err(|_| OpenError::Authentication)?;
        self.cipher
            .decrypt_inout_detached(&nonce(self.direction, header.sequence), head, body.into(), &tag)
            .map_err(|_| OpenError::Authentication)?;
        let message = decode(header.kind, body)?;
        self.window.commit(header.sequence)?;
        Ok(Opened { header, message })
    }
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
    /// large for one datagram (use [`crate::pack_updates`] and [`Sealer::seal_batch`]).
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
