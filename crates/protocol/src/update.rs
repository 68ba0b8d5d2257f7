//! The types a state update carries, shared by its encoding ([`crate::delta`]) and by
//! whoever reads it: an object's shape kind, its resolved state, and the fields every
//! datagram of one player's update in one tick shares.

use crate::error::DecodeError;
use crate::quant::QuantPos;
use crate::wire::Reader;

/// The three shapes a dynamic object can have.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[repr(u8)]
pub enum ShapeKind {
    /// A sphere.
    #[default]
    Sphere = 0,
    /// An axis-aligned box.
    Box = 1,
    /// A vertical capsule.
    Capsule = 2,
}

impl ShapeKind {
    /// Parses the two-bit kind code; 3 is not a kind.
    pub const fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Self::Sphere),
            1 => Some(Self::Box),
            2 => Some(Self::Capsule),
            _ => None,
        }
    }
}

/// One object's state in an update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct StateRecord {
    /// The object's id.
    pub id: u64,
    /// Its shape.
    pub kind: ShapeKind,
    /// Its position, quantized.
    pub pos: QuantPos,
}

/// The fields shared by every datagram of one player's update in one tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct UpdateHeader {
    /// The server tick the positions belong to.
    pub tick: u64,
    /// Time dilation in 1/1000 (1000 = real time).
    pub dilation_permille: u16,
    /// The point record positions are relative to (the player's AOI centre).
    pub origin: QuantPos,
}

/// Writes the 22 bytes an update header starts with: tick, dilation, origin.
pub(crate) fn write_header_fields(h: &UpdateHeader, out: &mut [u8]) {
    out[0..8].copy_from_slice(&h.tick.to_le_bytes());
    out[8..10].copy_from_slice(&h.dilation_permille.to_le_bytes());
    out[10..14].copy_from_slice(&h.origin.x.to_le_bytes());
    out[14..18].copy_from_slice(&h.origin.y.to_le_bytes());
    out[18..22].copy_from_slice(&h.origin.z.to_le_bytes());
}

/// Reads what [`write_header_fields`] wrote.
pub(crate) fn read_header_fields(r: &mut Reader<'_>) -> Result<UpdateHeader, DecodeError> {
    Ok(UpdateHeader {
        tick: r.u64()?,
        dilation_permille: r.u16()?,
        origin: QuantPos::new(r.i32()?, r.i32()?, r.i32()?),
    })
}
