//! Message bodies for both directions, and their framing into unsealed datagrams.
//!
//! Every body is a fixed little-endian structure whose length is implied by the packet
//! kind, except the state update, whose length follows from its records. Decoding
//! rejects trailing bytes, so each message has exactly one valid length.
//!
//! | kind | body |
//! | --- | --- |
//! | `Action` (0x01) | `u8` mask (bits 0..=4 only), `u32` client frame, 16-byte acknowledgement |
//! | `ClientKeepAlive` (0x03) | 16-byte acknowledgement |
//! | `Ready` (0x02), `ClientDisconnect` (0x04), `ServerKeepAlive` (0x82) | empty |
//! | `ServerDisconnect` (0x83) | `u8` reason |
//! | `ServerInfo` (0x84) | `u16` tick rate in Hz, `u16` time dilation in 1/1000 |
//! | `StateUpdate` (0x81) | a delta update, see [`crate::delta`] |
//!
//! The acknowledgement ([`AckField`], [`crate::ack`]) names the server datagrams the
//! client opened, so the server can send objects relative to states the client holds.

use crate::ack::AckField;
use crate::delta::DeltaUpdate;
use crate::error::{DecodeError, EncodeError};
use crate::header::{HEADER_LEN, MAX_BODY, PROTOCOL_VERSION, PacketKind, TAG_LEN};
use crate::wire::Reader;

/// The five input bits of an action: which movement keys are held this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct ActionMask(u8);

impl ActionMask {
    /// Move forward (bit 0).
    pub const FORWARD: u8 = 1 << 0;
    /// Move back (bit 1).
    pub const BACK: u8 = 1 << 1;
    /// Strafe right (bit 2).
    pub const RIGHT: u8 = 1 << 2;
    /// Strafe left (bit 3).
    pub const LEFT: u8 = 1 << 3;
    /// Jump (bit 4).
    pub const JUMP: u8 = 1 << 4;
    /// All valid bits.
    pub const VALID: u8 = 0x1f;

    /// Wraps a mask, or returns `None` if a bit above bit 4 is set.
    pub const fn new(bits: u8) -> Option<Self> {
        if bits & !Self::VALID == 0 { Some(Self(bits)) } else { None }
    }

    /// The raw bits.
    pub const fn bits(self) -> u8 {
        self.0
    }

    /// Whether every bit of `flag` is set.
    pub const fn contains(self, flag: u8) -> bool {
        self.0 & flag == flag
    }
}

/// A player's input for one client frame. The server keeps the latest (by frame) and
/// applies it during the next tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PlayerInput {
    /// Keys held.
    pub mask: ActionMask,
    /// The client's frame counter, so the server can ignore actions that arrive out of
    /// order.
    pub client_frame: u32,
}

/// Messages a client sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ClientMessage {
    /// Input for one frame, with the client's acknowledgement of the server datagrams
    /// it opened (`None`: none yet).
    Action {
        /// The keys held and the frame.
        input: PlayerInput,
        /// Which server datagrams the client opened.
        acks: Option<AckField>,
    },
    /// The client has loaded the world and wants state updates.
    Ready,
    /// Keeps the session alive while the client has nothing else to send, and
    /// acknowledges as an action does.
    KeepAlive {
        /// Which server datagrams the client opened.
        acks: Option<AckField>,
    },
    /// The client leaves; the server frees the session.
    Disconnect,
}

impl ClientMessage {
    /// The packet kind this message travels as.
    pub const fn kind(&self) -> PacketKind {
        match self {
            Self::Action { .. } => PacketKind::Action,
            Self::Ready => PacketKind::Ready,
            Self::KeepAlive { .. } => PacketKind::ClientKeepAlive,
            Self::Disconnect => PacketKind::ClientDisconnect,
        }
    }

    /// Appends the body (not the header) to `out`.
    pub fn encode_body(&self, out: &mut Vec<u8>) {
        match self {
            Self::Action { input, acks } => {
                out.push(input.mask.bits());
                out.extend_from_slice(&input.client_frame.to_le_bytes());
                AckField::encode(*acks, out);
            }
            Self::KeepAlive { acks } => AckField::encode(*acks, out),
            Self::Ready | Self::Disconnect => {}
        }
    }

    /// The acknowledgement this message carries, if it carries one.
    pub fn acks(&self) -> Option<AckField> {
        match self {
            Self::Action { acks, .. } | Self::KeepAlive { acks } => *acks,
            Self::Ready | Self::Disconnect => None,
        }
    }

    /// Decodes the body of a packet of kind `kind`.
    pub fn decode_body(kind: PacketKind, body: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(body);
        let msg = match kind {
            PacketKind::Action => {
                let bits = r.u8()?;
                let mask = ActionMask::new(bits).ok_or(DecodeError::BadActionMask(bits))?;
                let input = PlayerInput { mask, client_frame: r.u32()? };
                Self::Action { input, acks: AckField::read(&mut r)? }
            }
            PacketKind::Ready => Self::Ready,
            PacketKind::ClientKeepAlive => Self::KeepAlive { acks: AckField::read(&mut r)? },
            PacketKind::ClientDisconnect => Self::Disconnect,
            other => return Err(DecodeError::WrongDirection(other)),
        };
        r.finish()?;
        Ok(msg)
    }
}

/// Why the server ends a session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum DisconnectReason {
    /// The server is shutting down.
    Shutdown = 0,
    /// The session sent nothing for too long.
    Timeout = 1,
    /// An operator removed the player (the admin API's kick, or its account was disabled
    /// or deleted). The player may log in again, unless the account no longer allows it.
    Kicked = 2,
    /// The same account logged in again elsewhere; this session is replaced.
    Replaced = 3,
    /// The server is full.
    ServerFull = 4,
    /// The session broke the protocol (for example, too many malformed packets).
    ProtocolViolation = 5,
    /// An operator banned the account: its logins are refused (login refusal `Banned`)
    /// until the ban ends or is lifted.
    Banned = 6,
}

impl DisconnectReason {
    /// Every reason, in code order.
    pub const ALL: [DisconnectReason; 7] = [
        Self::Shutdown,
        Self::Timeout,
        Self::Kicked,
        Self::Replaced,
        Self::ServerFull,
        Self::ProtocolViolation,
        Self::Banned,
    ];

    /// Parses a reason code.
    pub const fn from_code(code: u8) -> Option<Self> {
        Some(match code {
            0 => Self::Shutdown,
            1 => Self::Timeout,
            2 => Self::Kicked,
            3 => Self::Replaced,
            4 => Self::ServerFull,
            5 => Self::ProtocolViolation,
            6 => Self::Banned,
            _ => return None,
        })
    }
}

/// Simulation parameters the client needs to interpolate correctly.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ServerInfo {
    /// Ticks per second of wall-clock time.
    pub tick_rate_hz: u16,
    /// Simulated time per wall-clock time, in 1/1000 (1000 = real time, 500 = the
    /// world runs at half speed because the server is overloaded).
    pub dilation_permille: u16,
}

/// Messages the server sends.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum ServerMessage {
    /// Positions of objects in the player's area of interest, relative to states the
    /// client acknowledged where it can.
    StateUpdate(DeltaUpdate),
    /// Keeps the session alive while the server has nothing else to send.
    KeepAlive,
    /// The server ends the session.
    Disconnect(DisconnectReason),
    /// Tick rate and time dilation.
    ServerInfo(ServerInfo),
}

impl ServerMessage {
    /// The packet kind this message travels as.
    pub const fn kind(&self) -> PacketKind {
        match self {
            Self::StateUpdate(_) => PacketKind::StateUpdate,
            Self::KeepAlive => PacketKind::ServerKeepAlive,
            Self::Disconnect(_) => PacketKind::ServerDisconnect,
            Self::ServerInfo(_) => PacketKind::ServerInfo,
        }
    }

    /// Appends the body (not the header) to `out`. Fails only for a state update too
    /// large for one datagram.
    pub fn encode_body(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        match self {
            Self::StateUpdate(u) => u.encode_body(out)?,
            Self::KeepAlive => {}
            Self::Disconnect(reason) => out.push(*reason as u8),
            Self::ServerInfo(info) => {
                out.extend_from_slice(&info.tick_rate_hz.to_le_bytes());
                out.extend_from_slice(&info.dilation_permille.to_le_bytes());
            }
        }
        Ok(())
    }

    /// Decodes the body of a packet of kind `kind`.
    pub fn decode_body(kind: PacketKind, body: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(body);
        let msg = match kind {
            PacketKind::StateUpdate => {
                return DeltaUpdate::decode_body(body).map(Self::StateUpdate);
            }
            PacketKind::ServerKeepAlive => Self::KeepAlive,
            PacketKind::ServerDisconnect => {
                let code = r.u8()?;
                Self::Disconnect(DisconnectReason::from_code(code).ok_or(DecodeError::BadDisconnectReason(code))?)
            }
            PacketKind::ServerInfo => {
                Self::ServerInfo(ServerInfo { tick_rate_hz: r.u16()?, dilation_permille: r.u16()? })
            }
            other => return Err(DecodeError::WrongDirection(other)),
        };
        r.finish()?;
        Ok(msg)
    }
}

/// Appends an unsealed datagram frame to `out`: [`HEADER_LEN`] header bytes with only
/// the version and kind filled in, the body, and [`TAG_LEN`] zero bytes for the tag.
/// [`Sealer::seal_in_place`](crate::Sealer::seal_in_place) completes it.
fn frame(
    kind: PacketKind,
    out: &mut Vec<u8>,
    body: impl FnOnce(&mut Vec<u8>) -> Result<(), EncodeError>,
) -> Result<(), EncodeError> {
    let start = out.len();
    out.extend_from_slice(&[0u8; HEADER_LEN]);
    out[start] = PROTOCOL_VERSION;
    out[start + 1] = kind as u8;
    if let Err(e) = body(out) {
        out.truncate(start);
        return Err(e);
    }
    let len = out.len() - start - HEADER_LEN;
    if len > MAX_BODY {
        out.truncate(start);
        return Err(EncodeError::TooLarge { len, max: MAX_BODY });
    }
    out.extend_from_slice(&[0u8; TAG_LEN]);
    Ok(())
}

/// Appends `msg` as an unsealed datagram frame (see [`crate::Sealer::seal_in_place`]).
pub fn encode_client(msg: &ClientMessage, out: &mut Vec<u8>) {
    // Client bodies are at most 21 bytes, so framing cannot fail.
    let _ = frame(msg.kind(), out, |o| {
        msg.encode_body(o);
        Ok(())
    });
}

/// Appends `msg` as an unsealed datagram frame (see [`crate::Sealer::seal_in_place`]).
/// Fails, appending nothing, for a state update too large for one datagram.
pub fn encode_server(msg: &ServerMessage, out: &mut Vec<u8>) -> Result<(), EncodeError> {
    frame(msg.kind(), out, |o| msg.encode_body(o))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn action_mask_rejects_high_bits() {
        assert!(ActionMask::new(0x1f).is_some());
        for bits in 0x20..=0xffu8 {
            assert!(ActionMask::new(bits).is_none());
            assert_eq!(
                ClientMessage::decode_body(PacketKind::Action, &[bits; 21]),
                Err(DecodeError::BadActionMask(bits))
            );
        }
        let m = ActionMask::new(ActionMask::FORWARD | ActionMask::JUMP).unwrap();
        assert!(m.contains(ActionMask::JUMP) && !m.contains(ActionMask::LEFT));
    }

    #[test]
    fn bodies_have_exact_lengths() {
        assert_eq!(ClientMessage::decode_body(PacketKind::Ready, &[0]), Err(DecodeError::TrailingBytes { extra: 1 }));
        assert!(matches!(
            ClientMessage::decode_body(PacketKind::Action, &[1, 0, 0]),
            Err(DecodeError::Truncated { .. })
        ));
        assert_eq!(
            ServerMessage::decode_body(PacketKind::ServerDisconnect, &[99]),
            Err(DecodeError::BadDisconnectReason(99))
        );
        assert_eq!(
            ServerMessage::decode_body(PacketKind::Ready, &[]),
            Err(DecodeError::WrongDirection(PacketKind::Ready))
        );
    }

    #[test]
    fn actions_and_keep_alives_carry_acknowledgements() {
        let acks = AckField::new(70, 0b101);
        let input = PlayerInput { mask: ActionMask::new(ActionMask::LEFT).unwrap(), client_frame: 7 };
        for msg in [
            ClientMessage::Action { input, acks },
            ClientMessage::Action { input, acks: None },
            ClientMessage::KeepAlive { acks },
            ClientMessage::KeepAlive { acks: None },
        ] {
            let mut body = Vec::new();
            msg.encode_body(&mut body);
            assert_eq!(ClientMessage::decode_body(msg.kind(), &body), Ok(msg));
            assert_eq!(msg.acks(), ClientMessage::decode_body(msg.kind(), &body).unwrap().acks());
            // One byte short or long is malformed: every body has one length.
            assert!(ClientMessage::decode_body(msg.kind(), &body[..body.len() - 1]).is_err());
            body.push(0);
            assert_eq!(ClientMessage::decode_body(msg.kind(), &body), Err(DecodeError::TrailingBytes { extra: 1 }));
        }
        // An acknowledgement naming sequence numbers below 0 is refused.
        let mut body = 2u64.to_le_bytes().to_vec();
        body.extend_from_slice(&0b100u64.to_le_bytes());
        assert!(matches!(
            ClientMessage::decode_body(PacketKind::ClientKeepAlive, &body),
            Err(DecodeError::BadAck { newest: 2, bits: 0b100 })
        ));
    }

    #[test]
    fn every_disconnect_reason_round_trips_and_the_next_code_is_malformed() {
        for (code, reason) in DisconnectReason::ALL.iter().enumerate() {
            assert_eq!(*reason as u8, code as u8, "ALL is in code order");
            let mut body = Vec::new();
            ServerMessage::Disconnect(*reason).encode_body(&mut body).unwrap();
            assert_eq!(body, [code as u8]);
            assert_eq!(
                ServerMessage::decode_body(PacketKind::ServerDisconnect, &body),
                Ok(ServerMessage::Disconnect(*reason))
            );
        }
        assert_eq!(
            ServerMessage::decode_body(PacketKind::ServerDisconnect, &[DisconnectReason::ALL.len() as u8]),
            Err(DecodeError::BadDisconnectReason(DisconnectReason::ALL.len() as u8))
        );
        assert_eq!(
            ServerMessage::decode_body(PacketKind::ServerDisconnect, &[6]),
            Ok(ServerMessage::Disconnect(DisconnectReason::Banned))
        );
    }

    #[test]
    fn frame_layout() {
        let mut out = vec![0xee];
        encode_client(&ClientMessage::KeepAlive { acks: None }, &mut out);
        assert_eq!(out.len(), 1 + HEADER_LEN + crate::ACK_LEN + TAG_LEN);
        assert_eq!(&out[1..3], &[PROTOCOL_VERSION, PacketKind::ClientKeepAlive as u8]);
    }
}
