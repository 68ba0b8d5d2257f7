//! The login exchange carried over TLS (docs/protocol.md, section 10), free of I/O.
//!
//! The TLS stream carries *frames*: `u32` length (little-endian, counting the kind byte
//! and the payload), `u8` kind, payload. The client sends one [`LoginRequest`]; the
//! server answers with one [`LoginResponse`] (accepted or refused) and, when the request
//! asked for it and the login was accepted, one [`MapData`] frame with the terrain and
//! the static scenery. Then the server closes the stream; everything else travels over
//! the sealed UDP session whose keys the accepted response carries.
//!
//! Readers first check the length prefix against a bound chosen by the receiver
//! ([`MAX_REQUEST_FRAME`] on the server, [`MAX_RESPONSE_FRAME`] on the client), so a
//! peer cannot make the other side allocate more than that.

use crate::error::DecodeError;
use crate::session::SessionKeys;
use crate::update::ShapeKind;
use crate::wire::Reader;

/// Version byte at the start of every login request this crate sends. Versions 2 to 5
/// add nothing to the request; they tell the server which refusal reasons the client
/// understands ([`RefusalReason::Busy`] from version 2, [`RefusalReason::Disabled`] and
/// [`RefusalReason::Banned`] from version 3, [`RefusalReason::OutdatedClient`] from
/// version 4) and which datagram protocol it speaks: 2 (acknowledgements and delta
/// updates) from version 4, 3 (bit-packed and predicted records,
/// [`crate::PROTOCOL_VERSION`]) from version 5.
pub const LOGIN_VERSION: u8 = 5;
/// Oldest login request version a server admits: older clients speak datagram protocol
/// 1 or 2, which this server no longer sends, and are refused
/// [`RefusalReason::OutdatedClient`] (which clients before version 4 read as
/// [`RefusalReason::BadRequest`]).
pub const MIN_SERVED_LOGIN_VERSION: u8 = 5;
/// Oldest login request version that decodes (version 1: no `Busy` refusal), so that a
/// server can tell an outdated client why it is refused.
pub const MIN_LOGIN_VERSION: u8 = 1;
/// Bytes of the length prefix of a frame.
pub const FRAME_PREFIX_LEN: usize = 4;
/// Largest request frame a server accepts (kind + payload): a version, two short strings
/// and a flag byte fit easily.
pub const MAX_REQUEST_FRAME: usize = 256;
/// Largest response frame a client accepts: a 4096×4096 heightmap plus a million static
/// primitives.
pub const MAX_RESPONSE_FRAME: usize = 64 << 20;
/// Longest username in bytes (the reference's login packet field).
pub const MAX_USERNAME: usize = 32;
/// Longest password in bytes (the reference's login packet field).
pub const MAX_PASSWORD: usize = 64;

/// Frame kinds of the login exchange.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum LoginFrameKind {
    /// Client → server: [`LoginRequest`].
    Request = 0x01,
    /// Server → client: [`LoginAccepted`].
    Accepted = 0x81,
    /// Server → client: [`LoginRefused`].
    Refused = 0x82,
    /// Server → client: [`MapData`].
    MapData = 0x83,
}

impl LoginFrameKind {
    fn from_byte(b: u8) -> Option<Self> {
        match b {
            0x01 => Some(Self::Request),
            0x81 => Some(Self::Accepted),
            0x82 => Some(Self::Refused),
            0x83 => Some(Self::MapData),
            _ => None,
        }
    }
}

/// Checks a frame's length prefix against the receiver's bound; returns the number of
/// bytes (kind + payload) to read next.
pub fn frame_len(prefix: [u8; FRAME_PREFIX_LEN], max: usize) -> Result<usize, DecodeError> {
    let len = u32::from_le_bytes(prefix) as usize;
    if len == 0 {
        return Err(DecodeError::Truncated { needed: 1, got: 0 });
    }
    if len > max {
        return Err(DecodeError::TooLong { len, max });
    }
    Ok(len)
}

fn begin_frame(kind: LoginFrameKind, out: &mut Vec<u8>) -> usize {
    let start = out.len();
    out.extend_from_slice(&[0; FRAME_PREFIX_LEN]);
    out.push(kind as u8);
    start
}

fn end_frame(start: usize, out: &mut [u8]) {
    let len = (out.len() - start - FRAME_PREFIX_LEN) as u32;
    out[start..start + FRAME_PREFIX_LEN].copy_from_slice(&len.to_le_bytes());
}

fn put_str(out: &mut Vec<u8>, s: &str) {
    // Callers bound the length first; u8 lengths are enough for every string here.
    out.push(s.len() as u8);
    out.extend_from_slice(s.as_bytes());
}

fn put_f32s(out: &mut Vec<u8>, v: &[f32]) {
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

fn get_str(r: &mut Reader<'_>, max: usize) -> Result<String, DecodeError> {
    let len = r.u8()? as usize;
    if len > max {
        return Err(DecodeError::TooLong { len, max });
    }
    let mut bytes = Vec::with_capacity(len);
    for _ in 0..len {
        bytes.push(r.u8()?);
    }
    // Invalid UTF-8 is reported as a malformed kind byte would be: the frame is garbage.
    String::from_utf8(bytes).map_err(|_| DecodeError::UnknownKind(0))
}

fn get_f32(r: &mut Reader<'_>) -> Result<f32, DecodeError> {
    Ok(f32::from_bits(r.u32()?))
}

fn get_vec3(r: &mut Reader<'_>) -> Result<[f32; 3], DecodeError> {
    Ok([get_f32(r)?, get_f32(r)?, get_f32(r)?])
}

fn expect_kind(body: &[u8], want: LoginFrameKind) -> Result<Reader<'_>, DecodeError> {
    let mut r = Reader::new(body);
    let kind = r.u8()?;
    if LoginFrameKind::from_byte(kind) != Some(want) {
        return Err(DecodeError::UnknownKind(kind));
    }
    Ok(r)
}

/// What a client sends to log in. The password is never printed by `Debug`.
#[derive(Clone, PartialEq, Eq)]
pub struct LoginRequest {
    /// Account name, 1 to [`MAX_USERNAME`] bytes.
    pub username: String,
    /// Password, at most [`MAX_PASSWORD`] bytes.
    pub password: String,
    /// Whether the client wants the terrain and static objects ([`MapData`]).
    pub want_map: bool,
    /// The request's version ([`MIN_LOGIN_VERSION`] to [`LOGIN_VERSION`]); it says which
    /// refusal reasons the client understands ([`RefusalReason::understood_by`]).
    pub version: u8,
}

impl LoginRequest {
    /// A request of the current version ([`LOGIN_VERSION`]).
    pub fn new(username: impl Into<String>, password: impl Into<String>, want_map: bool) -> Self {
        LoginRequest { username: username.into(), password: password.into(), want_map, version: LOGIN_VERSION }
    }
}

impl std::fmt::Debug for LoginRequest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LoginRequest")
            .field("username", &self.username)
            .field("want_map", &self.want_map)
            .field("version", &self.version)
            .finish()
    }
}

impl LoginRequest {
    /// Appends the request as one frame. Fails if a field is too long.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), DecodeError> {
        if self.username.is_empty() || self.username.len() > MAX_USERNAME {
            return Err(DecodeError::TooLong { len: self.username.len(), max: MAX_USERNAME });
        }
        if self.password.len() > MAX_PASSWORD {
            return Err(DecodeError::TooLong { len: self.password.len(), max: MAX_PASSWORD });
        }
        if !(MIN_LOGIN_VERSION..=LOGIN_VERSION).contains(&self.version) {
            return Err(DecodeError::BadVersion(self.version));
        }
        let start = begin_frame(LoginFrameKind::Request, out);
        out.push(self.version);
        put_str(out, &self.username);
        put_str(out, &self.password);
        out.push(u8::from(self.want_map));
        end_frame(start, out);
        Ok(())
    }

    /// Decodes a frame body (kind byte and payload, without the length prefix).
    pub fn decode(body: &[u8]) -> Result<Self, DecodeError> {
        let mut r = expect_kind(body, LoginFrameKind::Request)?;
        let version = r.u8()?;
        if !(MIN_LOGIN_VERSION..=LOGIN_VERSION).contains(&version) {
            return Err(DecodeError::BadVersion(version));
        }
        let username = get_str(&mut r, MAX_USERNAME)?;
        if username.is_empty() {
            return Err(DecodeError::Truncated { needed: 1, got: 0 });
        }
        let password = get_str(&mut r, MAX_PASSWORD)?;
        let want_map = match r.u8()? {
            0 => false,
            1 => true,
            other => return Err(DecodeError::ReservedBits(other as u32)),
        };
        r.finish()?;
        Ok(Self { username, password, want_map, version })
    }
}

/// A collision shape in compact form (kind, half extents, radius), as the world model
/// keeps it: a capsule's segment half length is `half[1] - radius`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShapeDesc {
    /// Sphere, box or capsule.
    pub kind: ShapeKind,
    /// Half extents of the bounding box.
    pub half: [f32; 3],
    /// Radius (spheres and capsules; 0 for boxes).
    pub radius: f32,
}

impl ShapeDesc {
    fn put(&self, out: &mut Vec<u8>) {
        out.push(self.kind as u8);
        put_f32s(out, &self.half);
        put_f32s(out, &[self.radius]);
    }

    fn get(r: &mut Reader<'_>) -> Result<Self, DecodeError> {
        let code = r.u8()?;
        let kind = ShapeKind::from_code(code).ok_or(DecodeError::BadShapeKind(code))?;
        Ok(Self { kind, half: get_vec3(r)?, radius: get_f32(r)? })
    }
}

/// The map the player is on: enough to place the terrain and to know what
/// [`MapData`] will contain.
#[derive(Debug, Clone, PartialEq)]
pub struct MapDescription {
    /// The store's map id.
    pub map_id: i64,
    /// The map's name.
    pub name: String,
    /// Minimum corner of the world.
    pub bounds_min: [f32; 3],
    /// Maximum corner of the world.
    pub bounds_max: [f32; 3],
    /// Heightmap samples along x (the terrain spans the bounds along x and z).
    pub terrain_width: u32,
    /// Heightmap samples along z.
    pub terrain_depth: u32,
    /// Height of the sample value 65535 above the world's floor.
    pub max_height: f32,
    /// Number of static primitives on the map.
    pub static_primitives: u32,
}

/// A successful login: the UDP session's keys and the player's object.
#[derive(Debug, Clone, PartialEq)]
pub struct LoginAccepted {
    /// Session id and the two direction keys (never printed by `Debug`).
    pub keys: SessionKeys,
    /// The server's UDP port (same host as the login service).
    pub udp_port: u16,
    /// The player's object id in state updates.
    pub entity_id: u64,
    /// The player's position.
    pub position: [f32; 3],
    /// The player's shape.
    pub shape: ShapeDesc,
    /// Ticks per second.
    pub tick_rate_hz: u16,
    /// Current time dilation in thousandths (1000 = real time).
    pub dilation_permille: u16,
    /// Current server tick.
    pub tick: u64,
    /// The map.
    pub map: MapDescription,
}

impl LoginAccepted {
    /// Appends the response as one frame.
    pub fn encode(&self, out: &mut Vec<u8>) {
        let start = begin_frame(LoginFrameKind::Accepted, out);
        out.extend_from_slice(&self.keys.session_id.to_le_bytes());
        out.extend_from_slice(&self.keys.client_to_server);
        out.extend_from_slice(&self.keys.server_to_client);
        out.extend_from_slice(&self.udp_port.to_le_bytes());
        out.extend_from_slice(&self.entity_id.to_le_bytes());
        put_f32s(out, &self.position);
        self.shape.put(out);
        out.extend_from_slice(&self.tick_rate_hz.to_le_bytes());
        out.extend_from_slice(&self.dilation_permille.to_le_bytes());
        out.extend_from_slice(&self.tick.to_le_bytes());
        let m = &self.map;
        out.extend_from_slice(&m.map_id.to_le_bytes());
        // Map names are at most 64 bytes in the store; truncate defensively on a char boundary.
        let mut name = m.name.as_str();
        while name.len() > 255 {
            let mut cut = 255;
            while !name.is_char_boundary(cut) {
                cut -= 1;
            }
            name = &name[..cut];
        }
        put_str(out, name);
        put_f32s(out, &m.bounds_min);
        put_f32s(out, &m.bounds_max);
        out.extend_from_slice(&m.terrain_width.to_le_bytes());
        out.extend_from_slice(&m.terrain_depth.to_le_bytes());
        put_f32s(out, &[m.max_height]);
        out.extend_from_slice(&m.static_primitives.to_le_bytes());
        end_frame(start, out);
    }

    fn decode_payload(r: &mut Reader<'_>) -> Result<Self, DecodeError> {
        let session_id = r.u64()?;
        let client_to_server = r.take::<32>()?;
        let server_to_client = r.take::<32>()?;
        let keys = SessionKeys { session_id, client_to_server, server_to_client };
        let udp_port = r.u16()?;
        let entity_id = r.u64()?;
        let position = get_vec3(r)?;
        let shape = ShapeDesc::get(r)?;
        let tick_rate_hz = r.u16()?;
        let dilation_permille = r.u16()?;
        let tick = r.u64()?;
        let map_id = r.u64()? as i64;
        let name = get_str(r, 255)?;
        let map = MapDescription {
            map_id,
            name,
            bounds_min: get_vec3(r)?,
            bounds_max: get_vec3(r)?,
            terrain_width: r.u32()?,
            terrain_depth: r.u32()?,
            max_height: get_f32(r)?,
            static_primitives: r.u32()?,
        };
        r.finish()?;
        Ok(Self { keys, udp_port, entity_id, position, shape, tick_rate_hz, dilation_permille, tick, map })
    }
}

/// Why a login was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum RefusalReason {
    /// Unknown user or wrong password (the two are not told apart).
    WrongCredentials = 1,
    /// Too many failed attempts from this address or for this account; retry later.
    RateLimited = 2,
    /// The server already has its maximum number of players.
    ServerFull = 3,
    /// The request was malformed.
    BadRequest = 4,
    /// The account database is unavailable; retry later.
    Unavailable = 5,
    /// The server is shutting down.
    ShuttingDown = 6,
    /// Too many password checks are waiting; retry after the hint (login version 2).
    Busy = 7,
    /// The account is disabled by an operator (login version 3). Told only after a
    /// correct password.
    Disabled = 8,
    /// The account is banned (login version 3); the retry hint is the time left of a
    /// timed ban in milliseconds (saturated at `u32::MAX`), 0 for a ban without end.
    /// Told only after a correct password.
    Banned = 9,
    /// The client speaks an older datagram protocol than the server (login version 5;
    /// an older client is told [`RefusalReason::BadRequest`], the nearest reason it
    /// knows). Told before the credentials are checked.
    OutdatedClient = 10,
}

impl RefusalReason {
    fn from_byte(b: u8) -> Option<Self> {
        Some(match b {
            1 => Self::WrongCredentials,
            2 => Self::RateLimited,
            3 => Self::ServerFull,
            4 => Self::BadRequest,
            5 => Self::Unavailable,
            6 => Self::ShuttingDown,
            7 => Self::Busy,
            8 => Self::Disabled,
            9 => Self::Banned,
            10 => Self::OutdatedClient,
            _ => return None,
        })
    }

    /// This reason as a client of login version `version` understands it: a version-1
    /// client does not know [`RefusalReason::Busy`] and gets
    /// [`RefusalReason::Unavailable`] (which it already retries) instead; a client before
    /// version 3 does not know [`RefusalReason::Disabled`] or [`RefusalReason::Banned`]
    /// and gets [`RefusalReason::WrongCredentials`], the refusal it does not retry; a
    /// client before version 4 does not know [`RefusalReason::OutdatedClient`] and gets
    /// [`RefusalReason::BadRequest`].
    pub fn understood_by(self, version: u8) -> RefusalReason {
        match self {
            Self::Busy if version < 2 => Self::Unavailable,
            Self::Disabled | Self::Banned if version < 3 => Self::WrongCredentials,
            Self::OutdatedClient if version < 4 => Self::BadRequest,
            other => other,
        }
    }
}

impl std::fmt::Display for RefusalReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::WrongCredentials => "wrong username or password",
            Self::RateLimited => "too many failed logins, retry later",
            Self::ServerFull => "the server is full",
            Self::BadRequest => "malformed login request",
            Self::Unavailable => "the account database is unavailable",
            Self::ShuttingDown => "the server is shutting down",
            Self::Busy => "the server is busy checking other logins, retry later",
            Self::Disabled => "the account is disabled",
            Self::Banned => "the account is banned",
            Self::OutdatedClient => "the client is too old for this server (an older datagram protocol); update it",
        })
    }
}

/// A refused login.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoginRefused {
    /// Why.
    pub reason: RefusalReason,
    /// When a retry may succeed, in milliseconds (0 = no hint).
    pub retry_after_ms: u32,
}

impl LoginRefused {
    /// Appends the response as one frame.
    pub fn encode(&self, out: &mut Vec<u8>) {
        let start = begin_frame(LoginFrameKind::Refused, out);
        out.push(self.reason as u8);
        out.extend_from_slice(&self.retry_after_ms.to_le_bytes());
        end_frame(start, out);
    }

    fn decode_payload(r: &mut Reader<'_>) -> Result<Self, DecodeError> {
        let b = r.u8()?;
        let reason = RefusalReason::from_byte(b).ok_or(DecodeError::BadDisconnectReason(b))?;
        let retry_after_ms = r.u32()?;
        r.finish()?;
        Ok(Self { reason, retry_after_ms })
    }
}

/// The server's answer to a [`LoginRequest`].
#[derive(Debug, Clone, PartialEq)]
pub enum LoginResponse {
    /// Logged in.
    Accepted(Box<LoginAccepted>),
    /// Refused.
    Refused(LoginRefused),
}

impl LoginResponse {
    /// Appends the response as one frame.
    pub fn encode(&self, out: &mut Vec<u8>) {
        match self {
            Self::Accepted(a) => a.encode(out),
            Self::Refused(r) => r.encode(out),
        }
    }

    /// Decodes a frame body (kind byte and payload, without the length prefix).
    pub fn decode(body: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(body);
        match LoginFrameKind::from_byte(r.u8()?) {
            Some(LoginFrameKind::Accepted) => Ok(Self::Accepted(Box::new(LoginAccepted::decode_payload(&mut r)?))),
            Some(LoginFrameKind::Refused) => Ok(Self::Refused(LoginRefused::decode_payload(&mut r)?)),
            _ => Err(DecodeError::UnknownKind(body[0])),
        }
    }
}

/// One primitive of the static scenery.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticPrimitive {
    /// Its shape.
    pub shape: ShapeDesc,
    /// Its centre.
    pub position: [f32; 3],
}

/// The terrain samples and the static scenery of a map.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MapData {
    /// Samples along x.
    pub terrain_width: u32,
    /// Samples along z.
    pub terrain_depth: u32,
    /// `width × depth` samples, row-major by z; 65535 is the map's `max_height`.
    pub samples: Vec<u16>,
    /// Every static primitive.
    pub statics: Vec<StaticPrimitive>,
}

impl MapData {
    /// Appends the map as one frame. Fails if it exceeds [`MAX_RESPONSE_FRAME`] or the
    /// sample count does not match the size.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), DecodeError> {
        let n = self.terrain_width as usize * self.terrain_depth as usize;
        if self.samples.len() != n {
            return Err(DecodeError::RecordCount { count: u16::MAX });
        }
        let size = 1 + 12 + 2 * n + self.statics.len() * 29;
        if size > MAX_RESPONSE_FRAME {
            return Err(DecodeError::TooLong { len: size, max: MAX_RESPONSE_FRAME });
        }
        out.reserve(size + FRAME_PREFIX_LEN);
        let start = begin_frame(LoginFrameKind::MapData, out);
        out.extend_from_slice(&self.terrain_width.to_le_bytes());
        out.extend_from_slice(&self.terrain_depth.to_le_bytes());
        for s in &self.samples {
            out.extend_from_slice(&s.to_le_bytes());
        }
        out.extend_from_slice(&(self.statics.len() as u32).to_le_bytes());
        for p in &self.statics {
            p.shape.put(out);
            put_f32s(out, &p.position);
        }
        end_frame(start, out);
        Ok(())
    }

    /// Decodes a frame body (kind byte and payload, without the length prefix).
    pub fn decode(body: &[u8]) -> Result<Self, DecodeError> {
        let mut r = expect_kind(body, LoginFrameKind::MapData)?;
        let terrain_width = r.u32()?;
        let terrain_depth = r.u32()?;
        let n = terrain_width as usize * terrain_depth as usize;
        // Check against what is left before allocating, so a lying size cannot allocate.
        if n.saturating_mul(2) > r.remaining() {
            return Err(DecodeError::Truncated { needed: n.saturating_mul(2), got: r.remaining() });
        }
        let mut samples = Vec::with_capacity(n);
        for _ in 0..n {
            samples.push(r.u16()?);
        }
        let count = r.u32()? as usize;
        if count.saturating_mul(29) != r.remaining() {
            return Err(DecodeError::RecordCount { count: u16::try_from(count).unwrap_or(u16::MAX) });
        }
        let mut statics = Vec::with_capacity(count);
        for _ in 0..count {
            let shape = ShapeDesc::get(&mut r)?;
            statics.push(StaticPrimitive { shape, position: get_vec3(&mut r)? });
        }
        r.finish()?;
        Ok(Self { terrain_width, terrain_depth, samples, statics })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(frame: &[u8]) -> &[u8] {
        let len = frame_len(frame[..4].try_into().unwrap(), MAX_RESPONSE_FRAME).unwrap();
        assert_eq!(len, frame.len() - 4);
        &frame[4..]
    }

    fn accepted() -> LoginAccepted {
        LoginAccepted {
            keys: SessionKeys { session_id: 77, client_to_server: [1; 32], server_to_client: [2; 32] },
            udp_port: 7777,
            entity_id: 1 << 33,
            position: [1.5, -2.0, 3.25],
            shape: ShapeDesc { kind: ShapeKind::Capsule, half: [0.5, 1.0, 0.5], radius: 0.5 },
            tick_rate_hz: 30,
            dilation_permille: 1000,
            tick: 12345,
            map: MapDescription {
                map_id: 3,
                name: "scenario-1".into(),
                bounds_min: [0.0; 3],
                bounds_max: [1024.0, 192.0, 1024.0],
                terrain_width: 3,
                terrain_depth: 2,
                max_height: 128.0,
                static_primitives: 1,
            },
        }
    }

    #[test]
    fn request_round_trip_and_debug_hides_password() {
        let req = LoginRequest::new("user7", "password7", true);
        let mut out = Vec::new();
        req.encode(&mut out).unwrap();
        assert_eq!(LoginRequest::decode(body(&out)).unwrap(), req);
        assert!(!format!("{req:?}").contains("password7"));
        assert!(out.len() - 4 <= MAX_REQUEST_FRAME);
    }

    #[test]
    fn request_rejects_bad_fields() {
        let long = LoginRequest::new("u".repeat(33), "", false);
        assert!(long.encode(&mut Vec::new()).is_err());
        let mut out = Vec::new();
        LoginRequest::new("a", "b", false).encode(&mut out).unwrap();
        let mut bad = out[4..].to_vec();
        *bad.last_mut().unwrap() = 2;
        assert!(LoginRequest::decode(&bad).is_err());
        bad[1] = 9;
        assert_eq!(LoginRequest::decode(&bad), Err(DecodeError::BadVersion(9)));
        let mut trailing = out[4..].to_vec();
        trailing.push(0);
        assert!(matches!(LoginRequest::decode(&trailing), Err(DecodeError::TrailingBytes { .. })));
    }

    #[test]
    fn version_1_requests_still_decode_and_never_see_busy() {
        // A version-1 client (before `Busy` existed) sends exactly this; the server must
        // still read it, and must not answer it with a reason code it cannot decode.
        let mut v1 = LoginRequest::new("user7", "pw", false);
        v1.version = 1;
        let mut out = Vec::new();
        v1.encode(&mut out).unwrap();
        assert_eq!(out[5], 1, "the version byte follows the frame prefix and kind");
        assert_eq!(LoginRequest::decode(body(&out)).unwrap(), v1);
        assert_eq!(RefusalReason::Busy.understood_by(1), RefusalReason::Unavailable);
        assert_eq!(RefusalReason::Busy.understood_by(LOGIN_VERSION), RefusalReason::Busy);
        assert_eq!(RefusalReason::RateLimited.understood_by(1), RefusalReason::RateLimited);
        let mut bad = out[4..].to_vec();
        bad[1] = LOGIN_VERSION + 1;
        assert_eq!(LoginRequest::decode(&bad), Err(DecodeError::BadVersion(LOGIN_VERSION + 1)));
        // Version 3's reasons reach older clients as the refusal they do not retry.
        for old in [1, 2] {
            assert_eq!(RefusalReason::Disabled.understood_by(old), RefusalReason::WrongCredentials);
            assert_eq!(RefusalReason::Banned.understood_by(old), RefusalReason::WrongCredentials);
        }
        assert_eq!(RefusalReason::Banned.understood_by(3), RefusalReason::Banned);
        assert_eq!(RefusalReason::Disabled.understood_by(3), RefusalReason::Disabled);
        for old in 1..4 {
            assert_eq!(RefusalReason::OutdatedClient.understood_by(old), RefusalReason::BadRequest);
        }
        // A client of login version 4 (datagram protocol 2) knows the reason it is told.
        const { assert!(4 < MIN_SERVED_LOGIN_VERSION) };
        assert_eq!(RefusalReason::OutdatedClient.understood_by(4), RefusalReason::OutdatedClient);
        assert_eq!(RefusalReason::OutdatedClient.understood_by(LOGIN_VERSION), RefusalReason::OutdatedClient);
        // Busy has its own code, 7, with the retry hint.
        let mut out = Vec::new();
        LoginRefused { reason: RefusalReason::Busy, retry_after_ms: 250 }.encode(&mut out);
        assert_eq!(&out[4..], &[0x82, 7, 250, 0, 0, 0]);
    }

    #[test]
    fn responses_round_trip() {
        for resp in [
            LoginResponse::Accepted(Box::new(accepted())),
            LoginResponse::Refused(LoginRefused { reason: RefusalReason::RateLimited, retry_after_ms: 500 }),
            LoginResponse::Refused(LoginRefused { reason: RefusalReason::Busy, retry_after_ms: 250 }),
            LoginResponse::Refused(LoginRefused { reason: RefusalReason::Disabled, retry_after_ms: 0 }),
            LoginResponse::Refused(LoginRefused { reason: RefusalReason::Banned, retry_after_ms: 60_000 }),
        ] {
            let mut out = Vec::new();
            resp.encode(&mut out);
            assert_eq!(LoginResponse::decode(body(&out)).unwrap(), resp);
        }
    }

    #[test]
    fn map_round_trip_and_lying_sizes() {
        let map = MapData {
            terrain_width: 3,
            terrain_depth: 2,
            samples: vec![0, 1, 2, 3, 4, 65535],
            statics: vec![StaticPrimitive {
                shape: ShapeDesc { kind: ShapeKind::Box, half: [1.0, 2.0, 3.0], radius: 0.0 },
                position: [10.0, 0.0, -4.0],
            }],
        };
        let mut out = Vec::new();
        map.encode(&mut out).unwrap();
        assert_eq!(MapData::decode(body(&out)).unwrap(), map);
        let mut lying = out[4..].to_vec();
        lying[1..5].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(MapData::decode(&lying).is_err());
    }

    #[test]
    fn frame_length_is_bounded() {
        assert!(frame_len(1000u32.to_le_bytes(), MAX_REQUEST_FRAME).is_err());
        assert!(frame_len(0u32.to_le_bytes(), MAX_REQUEST_FRAME).is_err());
        assert_eq!(frame_len(10u32.to_le_bytes(), MAX_REQUEST_FRAME), Ok(10));
    }

    #[test]
    fn truncated_input_never_panics() {
        let mut out = Vec::new();
        LoginResponse::Accepted(Box::new(accepted())).encode(&mut out);
        for cut in 0..out.len() - 4 {
            let _ = LoginResponse::decode(&out[4..4 + cut]);
            let _ = LoginRequest::decode(&out[4..4 + cut]);
            let _ = MapData::decode(&out[4..4 + cut]);
        }
    }
}
