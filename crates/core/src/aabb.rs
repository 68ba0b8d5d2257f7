//! Axis-aligned bounding boxes.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// An axis-aligned box given by its minimum and maximum corners (inclusive).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    /// The corner with the smallest coordinates.
    pub min: Vec3,
    /// The corner with the largest coordinates.
    pub max: Vec3,
}

impl Aabb {
    /// An "empty" box: the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb { min: Vec3::splat(f32::INFINITY), max: Vec3::splat(f32::NEG_INFINITY) };

    /// A box from its corners.
    pub const fn new(min: Vec3, max: Vec3) -> Aabb {
        Aabb { min, max }
    }

    /// The box centred on `centre` with half extents `half`.
    ///
    /// Every backend computes object boxes with exactly this expression, so that the
    /// broad phases agree bit for bit.
    #[inline]
    pub fn from_center_half(centre: Vec3, half: Vec3) -> Aabb {
        Aabb { min: centre - half, max: centre + half }
    }

    /// Whether the two boxes overlap or touch (closed intervals on every axis).
    ///
    /// Touching counts as overlapping so that the broad phase never misses a pair the
    /// narrow phase would report.
    #[inline]
    pub fn overlaps(&self, other: &Aabb) -> bool {
        // `&` rather than `&&`: six cheap comparisons without branches beat early exits
        // that the branch predictor cannot guess in a tree traversal.
        (self.min.x <= other.max.x)
            & (other.min.x <= self.max.x)
            & (self.min.y <= other.max.y)
            & (other.min.y <= self.max.y)
            & (self.min.z <= other.max.z)
            & (other.min.z <= self.max.z)
    }

    /// The smallest box containing both.
    #[inline]
    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb { min: self.min.min(other.min), max: self.max.max(other.max) }
    }

    /// The centre point.
    #[inline]
    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// The size on each axis.
    #[inline]
    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }

    /// Whether `p` lies inside or on the boundary.
    #[inline]
    pub fn contains_point(&self, p: Vec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }

    /// Whether the box has finite corners with `min <= max` on every axis.
    pub fn is_valid(&self) -> bool {
        self.min.is_finite() && self.max.is_finite() && self.min.cmple(self.max).all()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn touching_boxes_overlap_and_separated_ones_do_not() {
        let a = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let touching = Aabb::new(Vec3::new(1.0, 0.0, 0.0), Vec3::new(2.0, 1.0, 1.0));
        let apart = Aabb::new(Vec3::new(1.01, 0.0, 0.0), Vec3::new(2.0, 1.0, 1.0));
        assert!(a.overlaps(&touching) && touching.overlaps(&a));
        assert!(!a.overlaps(&apart) && !apart.overlaps(&a));
    }

    #[test]
    fn union_with_empty_is_identity() {
        let a = Aabb::new(Vec3::new(-3.0, 2.0, 1.0), Vec3::new(4.0, 5.0, 6.0));
        assert_eq!(Aabb::EMPTY.union(&a), a);
        assert!(!Aabb::EMPTY.is_valid());
        assert!(a.is_valid());
    }
}
