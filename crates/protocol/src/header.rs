//! The 18-byte clear-text header that starts every datagram, and the size limits.
//!
//! ```text
//! offset  size  field
//!      0     1  protocol version (PROTOCOL_VERSION)
//!      1     1  packet kind (PacketKind); bit 7 set = server to client
//!      2     8  session id, u64 little-endian
//!     10     8  sequence number, u64 little-endian
//!     18     n  body, encrypted
//!   18+n    16  Poly1305 tag
//! ```
//!
//! [`peek_header`] runs every check that needs no key, so a server can drop garbage
//! before it looks a session up or spends any time on cryptography.

use crate::error::DecodeError;
use crate::wire::Reader;

/// Version byte of this format. A packet with any other value is dropped.
pub const PROTOCOL_VERSION: u8 = 3;
/// Length of the clear-text header.
pub const HEADER_LEN: usize = 18;
/// Length of the Poly1305 authentication tag that ends every datagram.
pub const TAG_LEN: usize = 16;
/// Largest datagram (UDP payload) either side sends or accepts. 1200 bytes fit the
/// IPv6 minimum MTU of 1280 with the IP and UDP headers, so no path fragments them.
pub const MAX_DATAGRAM: usize = 1200;
/// Smallest valid datagram: a header, an empty body and a tag.
pub const MIN_DATAGRAM: usize = HEADER_LEN + TAG_LEN;
/// Largest body (plaintext) a datagram can carry.
pub const MAX_BODY: usize = MAX_DATAGRAM - MIN_DATAGRAM;

/// Which way a packet travels. Part of the nonce, so a packet can never be reflected
/// back to its sender as valid even if both directions shared a key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Direction {
    /// Client to server.
    ClientToServer,
    /// Server to client.
    ServerToClient,
}

impl Direction {
    /// The byte this direction contributes to the nonce (0 or 1).
    pub const fn nonce_byte(self) -> u8 {
        match self {
            Self::ClientToServer => 0,
            Self::ServerToClient => 1,
        }
    }
}

/// The kind of a packet, from the header's second byte.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum PacketKind {
    /// Client to server: the player's input for one frame.
    Action = 0x01,
    /// Client to server: the client has loaded and wants state updates.
    Ready = 0x02,
    /// Client to server: nothing to say, the session is alive.
    ClientKeepAlive = 0x03,
    /// Client to server: the client leaves.
    ClientDisconnect = 0x04,
    /// Server to client: positions of objects in the player's area of interest.
    StateUpdate = 0x81,
    /// Server to client: nothing to say, the session is alive.
    ServerKeepAlive = 0x82,
    /// Server to client: the server ends the session, with a reason.
    ServerDisconnect = 0x83,
    /// Server to client: tick rate and time dilation.
    ServerInfo = 0x84,
}

impl PacketKind {
    /// Every kind, in byte order.
    pub const ALL: [PacketKind; 8] = [
        Self::Action,
        Self::Ready,
        Self::ClientKeepAlive,
        Self::ClientDisconnect,
        Self::StateUpdate,
        Self::ServerKeepAlive,
        Self::ServerDisconnect,
        Self::ServerInfo,
    ];

    /// Parses the kind byte.
    pub const fn from_byte(byte: u8) -> Option<Self> {
        Some(match byte {
            0x01 => Self::Action,
            0x02 => Self::Ready,
            0x03 => Self::ClientKeepAlive,
            0x04 => Self::ClientDisconnect,
            0x81 => Self::StateUpdate,
            0x82 => Self::ServerKeepAlive,
            0x83 => Self::ServerDisconnect,
            0x84 => Self::ServerInfo,
            _ => return None,
        })
    }

    /// The direction this kind travels in (bit 7 of the byte).
    pub const fn direction(self) -> Direction {
        if (self as u8) & 0x80 == 0 { Direction::ClientToServer } else { Direction::ServerToClient }
    }
}

/// A parsed header.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Header {
    /// The packet kind.
    pub kind: PacketKind,
    /// The session the packet belongs to (handed out by the login service).
    pub session_id: u64,
    /// The sender's sequence number, unique per session and direction.
    pub sequence: u64,
}

impl Header {
    /// Writes the header into the first [`HEADER_LEN`] bytes of `out`.
    pub fn write(&self, out: &mut [u8; HEADER_LEN]) {
        out[0] = PROTOCOL_VERSION;
        out[1] = self.kind as u8;
        out[2..10].copy_from_slice(&self.session_id.to_le_bytes());
        out[10..18].copy_from_slice(&self.sequence.to_le_bytes());
    }
}

/// Checks a received datagram without any key: its length, version, kind (which must
/// travel in `direction`) and sequence number (never `u64::MAX`), and returns its
/// header.
///
/// The server calls this first and drops the datagram on error; only then does it look
/// up the session named by [`Header::session_id`].
pub fn peek_header(datagram: &[u8], direction: Direction) -> Result<Header, DecodeError> {
    if datagram.len() < MIN_DATAGRAM {
        return Err(DecodeError::Truncated { needed: MIN_DATAGRAM, got: datagram.len() });
    }
    if datagram.len() > MAX_DATAGRAM {
        return Err(DecodeError::TooLong { len: datagram.len(), max: MAX_DATAGRAM });
    }
    let mut r = Reader::new(datagram);
    let version = r.u8()?;
    if version != PROTOCOL_VERSION {
        return Err(DecodeError::BadVersion(version));
    }
    let kind_byte = r.u8()?;
    let kind = PacketKind::from_byte(kind_byte).ok_or(DecodeError::UnknownKind(kind_byte))?;
    if kind.direction() != direction {
        return Err(DecodeError::WrongDirection(kind));
    }
    let session_id = r.u64()?;
    let sequence = r.u64()?;
    // No sender ever uses u64::MAX (its sealer stops one short). Accepting it would
    // push the receiver's replay window to the top, after which every later datagram of
    // the session looks replayed; so it is rejected here, before any cryptography.
    if sequence == u64::MAX {
        return Err(DecodeError::ReservedSequence);
    }
    Ok(Header { kind, session_id, sequence })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kind_bytes_round_trip() {
        for kind in PacketKind::ALL {
            assert_eq!(PacketKind::from_byte(kind as u8), Some(kind));
        }
        let assigned = (0..=255u8).filter(|&b| PacketKind::from_byte(b).is_some()).count();
        assert_eq!(assigned, PacketKind::ALL.len());
    }

    #[test]
    fn peek_rejects_cheap_failures() {
        let mut d = [0u8; MIN_DATAGRAM];
        Header { kind: PacketKind::Ready, session_id: 7, sequence: 9 }
            .write((&mut d[..HEADER_LEN]).try_into().unwrap());
        let h = peek_header(&d, Direction::ClientToServer).unwrap();
        assert_eq!((h.kind, h.session_id, h.sequence), (PacketKind::Ready, 7, 9));
        assert_eq!(peek_header(&d, Direction::ServerToClient), Err(DecodeError::WrongDirection(PacketKind::Ready)));
        assert!(matches!(
            peek_header(&d[..MIN_DATAGRAM - 1], Direction::ClientToServer),
            Err(DecodeError::Truncated { .. })
        ));
        assert!(matches!(
            peek_header(&[1u8; MAX_DATAGRAM + 1], Direction::ClientToServer),
            Err(DecodeError::TooLong { .. })
        ));
        // Version 1 (a client from before acknowledgements and deltas) and the next one.
        for version in [1, 2, PROTOCOL_VERSION + 1] {
            d[0] = version;
            assert_eq!(peek_header(&d, Direction::ClientToServer), Err(DecodeError::BadVersion(version)));
        }
        d[0] = PROTOCOL_VERSION;
        d[1] = 0x7f;
        assert_eq!(peek_header(&d, Direction::ClientToServer), Err(DecodeError::UnknownKind(0x7f)));
        d[1] = PacketKind::Ready as u8;
        d[10..18].copy_from_slice(&u64::MAX.to_le_bytes());
        assert_eq!(peek_header(&d, Direction::ClientToServer), Err(DecodeError::ReservedSequence));
        d[10..18].copy_from_slice(&(u64::MAX - 1).to_le_bytes());
        assert_eq!(peek_header(&d, Direction::ClientToServer).map(|h| h.sequence), Ok(u64::MAX - 1));
    }
}
