//! 64-bit Morton codes over arbitrary world bounds.

use myriad_core::{Aabb, Vec3};

/// Bits per axis: 3 × 21 = 63 bits of a `u64`.
pub const BITS_PER_AXIS: u32 = 21;

/// Spreads the low 21 bits of `v` so that bit `i` lands at bit `3i`.
#[inline]
pub fn expand_bits(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | x << 32) & 0x001f_0000_0000_ffff;
    x = (x | x << 16) & 0x001f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// The quantisation of world coordinates to Morton grid cells: `cell = (p - min) * scale`,
/// clamped to `[0, 2^21 - 1]` per axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MortonFrame {
    /// The world's minimum corner.
    pub min: Vec3,
    /// Grid cells per unit on each axis.
    pub scale: Vec3,
}

impl MortonFrame {
    /// A frame spanning `bounds` (any size and origin; a degenerate axis gets scale 0).
    pub fn new(bounds: &Aabb) -> MortonFrame {
        let cells = ((1u32 << BITS_PER_AXIS) - 1) as f32;
        let size = bounds.size();
        let s = |e: f32| if e > 0.0 { cells / e } else { 0.0 };
        MortonFrame { min: bounds.min, scale: Vec3::new(s(size.x), s(size.y), s(size.z)) }
    }

    /// The Morton code of point `p` (points outside the bounds clamp to the edge).
    #[inline]
    pub fn code(&self, p: Vec3) -> u64 {
        let max = ((1u32 << BITS_PER_AXIS) - 1) as f32;
        let q = |v: f32, min: f32, scale: f32| ((v - min) * scale).clamp(0.0, max) as u64;
        let x = q(p.x, self.min.x, self.scale.x);
        let y = q(p.y, self.min.y, self.scale.y);
        let z = q(p.z, self.min.z, self.scale.z);
        expand_bits(x) << 2 | expand_bits(y) << 1 | expand_bits(z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interleaves_bits() {
        assert_eq!(expand_bits(0b1), 0b1);
        assert_eq!(expand_bits(0b11), 0b1001);
        assert_eq!(expand_bits(0x1f_ffff).count_ones(), 21);
        let frame = MortonFrame::new(&Aabb::new(Vec3::splat(-1000.0), Vec3::splat(3000.0)));
        assert_eq!(frame.code(Vec3::splat(-1000.0)), 0);
        assert_eq!(frame.code(Vec3::splat(1e9)), (1u64 << 63) - 1, "outside clamps");
        assert!(frame.code(Vec3::new(0.0, 0.0, 0.0)) < frame.code(Vec3::new(2000.0, 2000.0, 2000.0)));
    }
}
