//! Fixed-point positions: 1/64 unit per step in an `i32`, i.e. about ±33.5 million
//! units at 0.015625-unit resolution. Beyond ±2^24 units an `f32` position is already
//! coarser than one step, so the fixed-point range is not the limiting factor.

/// Fixed-point steps per world unit.
pub const POS_SCALE: f32 = 64.0;

/// A position in fixed point, 1/64 unit per step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct QuantPos {
    /// X in 1/64 units.
    pub x: i32,
    /// Y in 1/64 units.
    pub y: i32,
    /// Z in 1/64 units.
    pub z: i32,
}

impl QuantPos {
    /// Builds a position from its three fixed-point components.
    pub const fn new(x: i32, y: i32, z: i32) -> Self {
        Self { x, y, z }
    }

    /// Rounds a world position to the nearest step. Values beyond the `i32` range
    /// saturate and NaN becomes 0 (Rust's float-to-int casts are saturating), so no
    /// input can panic or wrap.
    #[inline]
    pub fn from_f32(p: [f32; 3]) -> Self {
        #[inline]
        fn q(v: f32) -> i32 {
            // Same result as `(v * 64.0).round() as i32` (half away from zero), but
            // without the `roundf` library call, which showed up at 6% of an interest
            // tick: in f64, `v * 64` and `± 0.5` are exact, and the cast truncates.
            let s = f64::from(v) * f64::from(POS_SCALE);
            (s + 0.5f64.copysign(s)) as i32
        }
        Self::new(q(p[0]), q(p[1]), q(p[2]))
    }

    /// Converts back to world units.
    #[inline]
    pub fn to_f32(self) -> [f32; 3] {
        [self.x as f32 / POS_SCALE, self.y as f32 / POS_SCALE, self.z as f32 / POS_SCALE]
    }

    /// `self - origin`, if every component fits an `i16` (±512 units).
    #[inline]
    pub fn offset_from(self, origin: QuantPos) -> Option<[i16; 3]> {
        #[inline]
        fn d(a: i32, b: i32) -> Option<i16> {
            i16::try_from(i64::from(a) - i64::from(b)).ok()
        }
        Some([d(self.x, origin.x)?, d(self.y, origin.y)?, d(self.z, origin.z)?])
    }

    /// `origin + offset`, saturating at the `i32` range (only a hostile packet can get
    /// there; saturating keeps the decoder total).
    #[inline]
    pub fn add_offset(origin: QuantPos, offset: [i16; 3]) -> Self {
        Self::new(
            origin.x.saturating_add(i32::from(offset[0])),
            origin.y.saturating_add(i32::from(offset[1])),
            origin.z.saturating_add(i32::from(offset[2])),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantization_resolution_and_saturation() {
        let q = QuantPos::from_f32([1.0, -0.5, 1.0 / 64.0]);
        assert_eq!(q, QuantPos::new(64, -32, 1));
        assert_eq!(q.to_f32(), [1.0, -0.5, 1.0 / 64.0]);
        let s = QuantPos::from_f32([f32::NAN, f32::INFINITY, -1e30]);
        assert_eq!(s, QuantPos::new(0, i32::MAX, i32::MIN));
        // Half a step rounds away from zero: error is at most 1/128 unit.
        let p = [123.456f32, -98.765, 0.0078];
        let back = QuantPos::from_f32(p).to_f32();
        for (b, v) in back.iter().zip(p) {
            assert!((b - v).abs() <= 1.0 / 128.0 + 1e-4);
        }
    }

    #[test]
    fn rounding_matches_f32_round() {
        let mut x = 0x1234_5678u32;
        for _ in 0..200_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let v = f32::from_bits(x);
            let want = (v * POS_SCALE).round() as i32;
            assert_eq!(QuantPos::from_f32([v, 0.0, 0.0]).x, want, "{v}");
        }
        for v in [0.5 / 64.0, -0.5 / 64.0, 1.5 / 64.0, 0.49999997 / 64.0, 1e-40, -0.0] {
            assert_eq!(QuantPos::from_f32([v, 0.0, 0.0]).x, (v * POS_SCALE).round() as i32, "{v}");
        }
    }

    #[test]
    fn offsets_fit_i16_or_not() {
        let o = QuantPos::new(1000, 0, -5);
        assert_eq!(QuantPos::new(1000 + 32767, -32768, -5).offset_from(o), Some([32767, -32768, 0]));
        assert_eq!(QuantPos::new(1000 + 32768, 0, 0).offset_from(o), None);
        assert_eq!(QuantPos::new(i32::MIN, 0, 0).offset_from(QuantPos::new(i32::MAX, 0, 0)), None);
        assert_eq!(QuantPos::add_offset(QuantPos::new(i32::MAX, 0, 0), [5, 0, 0]).x, i32::MAX);
    }
}
