//! The three primitive shapes.
//!
//! Every backend stores a shape in one compact form: a [`ShapeKind`], the half extents of
//! its bounding box and a radius. For a sphere the half extents are `(r, r, r)`; for a box
//! the radius is 0; for a vertical capsule of radius `r` whose core segment has half
//! length `h`, the half extents are `(r, h + r, r)`. The bounding box of any shape at
//! position `p` is therefore `p ± half`, and the half length of a capsule's segment is
//! `half.y - radius`.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Which primitive a shape is. The discriminants are part of the wire and GPU formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[repr(u8)]
pub enum ShapeKind {
    /// A sphere.
    Sphere = 0,
    /// An axis-aligned box.
    Box = 1,
    /// A capsule whose axis is vertical (along y).
    Capsule = 2,
}

impl ShapeKind {
    /// Every kind, in discriminant order.
    pub const ALL: [ShapeKind; 3] = [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule];

    /// The kind with this discriminant.
    pub fn from_u8(v: u8) -> Option<ShapeKind> {
        Self::ALL.get(v as usize).copied()
    }

    /// A lower-case name (`sphere`, `box`, `capsule`).
    pub fn name(self) -> &'static str {
        match self {
            ShapeKind::Sphere => "sphere",
            ShapeKind::Box => "box",
            ShapeKind::Capsule => "capsule",
        }
    }
}

/// A shape with its parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Shape {
    /// A sphere of the given radius.
    Sphere {
        /// Radius.
        radius: f32,
    },
    /// An axis-aligned box with the given half extents.
    Box {
        /// Half the size on each axis.
        half: Vec3,
    },
    /// A vertical capsule: a segment of length `2 * half_height` along y, swept by a
    /// sphere of `radius`. Its total height is `2 * (half_height + radius)`.
    Capsule {
        /// Radius of the swept sphere.
        radius: f32,
        /// Half the length of the core segment (0 makes it a sphere).
        half_height: f32,
    },
}

impl Shape {
    /// The kind of this shape.
    pub fn kind(&self) -> ShapeKind {
        match self {
            Shape::Sphere { .. } => ShapeKind::Sphere,
            Shape::Box { .. } => ShapeKind::Box,
            Shape::Capsule { .. } => ShapeKind::Capsule,
        }
    }

    /// The half extents of the bounding box centred on the shape's position.
    pub fn half_extents(&self) -> Vec3 {
        match *self {
            Shape::Sphere { radius } => Vec3::splat(radius),
            Shape::Box { half } => half,
            Shape::Capsule { radius, half_height } => Vec3::new(radius, half_height + radius, radius),
        }
    }

    /// The radius (0 for a box).
    pub fn radius(&self) -> f32 {
        match *self {
            Shape::Sphere { radius } | Shape::Capsule { radius, .. } => radius,
            Shape::Box { .. } => 0.0,
        }
    }

    /// Rebuilds a shape from the compact form (kind, half extents, radius).
    pub fn from_compact(kind: ShapeKind, half: Vec3, radius: f32) -> Shape {
        match kind {
            ShapeKind::Sphere => Shape::Sphere { radius },
            ShapeKind::Box => Shape::Box { half },
            ShapeKind::Capsule => Shape::Capsule { radius, half_height: half.y - radius },
        }
    }

    /// Whether every parameter is finite and positive (a capsule's segment may be 0).
    pub fn is_valid(&self) -> bool {
        match *self {
            Shape::Sphere { radius } => radius.is_finite() && radius > 0.0,
            Shape::Box { half } => half.is_finite() && half.cmpgt(Vec3::ZERO).all(),
            Shape::Capsule { radius, half_height } => {
                radius.is_finite() && radius > 0.0 && half_height.is_finite() && half_height >= 0.0
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compact_form_round_trips() {
        for s in [
            Shape::Sphere { radius: 0.5 },
            Shape::Box { half: Vec3::new(1.0, 2.0, 3.0) },
            Shape::Capsule { radius: 0.25, half_height: 0.75 },
        ] {
            assert_eq!(Shape::from_compact(s.kind(), s.half_extents(), s.radius()), s);
            assert!(s.is_valid());
        }
        assert_eq!(Shape::Capsule { radius: 0.5, half_height: 1.0 }.half_extents(), Vec3::new(0.5, 1.5, 0.5));
        assert!(!Shape::Sphere { radius: f32::NAN }.is_valid());
        assert!(Shape::Capsule { radius: 1.0, half_height: 0.0 }.is_valid());
    }

    #[test]
    fn kinds_round_trip_through_u8() {
        for k in ShapeKind::ALL {
            assert_eq!(ShapeKind::from_u8(k as u8), Some(k));
        }
        assert_eq!(ShapeKind::from_u8(3), None);
    }
}
