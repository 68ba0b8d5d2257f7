//! Narrow phase: exact contact tests for the six pairs of primitive shapes.
//!
//! Files are named `contact_[shape1]_[shape2].rs` (after parry). Each function takes the
//! two shapes at their positions and returns a [`Contact`] when they overlap: a unit
//! `normal` pointing **from the first shape to the second** and a penetration `depth`
//! (> 0), so moving the second shape by `normal * depth` (or the first by the opposite)
//! separates them. [`contact`] dispatches on the kinds and flips the normal when it calls
//! a function with its arguments swapped; a flip is an exact negation.
//!
//! Because capsules are vertical and boxes axis-aligned, every test is exact: the closest
//! points between a vertical segment and a box or another vertical segment reduce to
//! interval arithmetic along y and a clamp in x–z.
//!
//! Determinism: these functions use only `+ - * /`, `sqrt`, `min`, `max` and comparisons in
//! a fixed order, with no fused multiply–add. The CUDA kernels mirror them operation for
//! operation; change both together.

mod contact_box_box;
mod contact_box_capsule;
mod contact_capsule_capsule;
mod contact_sphere_box;
mod contact_sphere_capsule;
mod contact_sphere_sphere;
mod segment;

pub use contact_box_box::contact_box_box;
pub use contact_box_capsule::contact_box_capsule;
pub use contact_capsule_capsule::contact_capsule_capsule;
pub use contact_sphere_box::contact_sphere_box;
pub use contact_sphere_capsule::contact_sphere_capsule;
pub use contact_sphere_sphere::contact_sphere_sphere;

use myriad_core::{ShapeKind, Vec3};

/// The result of an overlap test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Contact {
    /// Unit normal from the first shape towards the second.
    pub normal: Vec3,
    /// How far the shapes overlap along the normal (> 0).
    pub depth: f32,
}

impl Contact {
    /// The same contact seen from the other shape.
    #[inline]
    pub fn flipped(self) -> Contact {
        Contact { normal: -self.normal, depth: self.depth }
    }
}

/// A primitive at a position, in the compact form of `myriad_core::shape`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Body {
    /// Which primitive.
    pub kind: ShapeKind,
    /// Centre.
    pub pos: Vec3,
    /// Half extents of the bounding box.
    pub half: Vec3,
    /// Radius (spheres and capsules).
    pub radius: f32,
}

impl Body {
    /// Half length of a capsule's core segment.
    #[inline]
    fn half_height(&self) -> f32 {
        self.half.y - self.radius
    }
}

/// The direction used when two centres coincide and no direction is defined: up, which
/// also lifts the object resting on top in the common stacking case.
pub const FALLBACK_NORMAL: Vec3 = Vec3::Y;

/// `a · b` evaluated as `(a.x * b.x + a.y * b.y) + a.z * b.z`, the order the kernels use.
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f32 {
    a.x * b.x + a.y * b.y + a.z * b.z
}

/// Exact contact between any two primitives; the normal points from `a` to `b`.
#[inline]
pub fn contact(a: &Body, b: &Body) -> Option<Contact> {
    use ShapeKind::*;
    match (a.kind, b.kind) {
        (Sphere, Sphere) => contact_sphere_sphere(a.pos, a.radius, b.pos, b.radius),
        (Sphere, Box) => contact_sphere_box(a.pos, a.radius, b.pos, b.half),
        (Box, Sphere) => contact_sphere_box(b.pos, b.radius, a.pos, a.half).map(Contact::flipped),
        (Sphere, Capsule) => contact_sphere_capsule(a.pos, a.radius, b.pos, b.radius, b.half_height()),
        (Capsule, Sphere) => {
            contact_sphere_capsule(b.pos, b.radius, a.pos, a.radius, a.half_height()).map(Contact::flipped)
        }
        (Box, Box) => contact_box_box(a.pos, a.half, b.pos, b.half),
        (Box, Capsule) => contact_box_capsule(a.pos, a.half, b.pos, b.radius, b.half_height()),
        (Capsule, Box) => contact_box_capsule(b.pos, b.half, a.pos, a.radius, a.half_height()).map(Contact::flipped),
        (Capsule, Capsule) => {
            contact_capsule_capsule(a.pos, a.radius, a.half_height(), b.pos, b.radius, b.half_height())
        }
    }
}

#[cfg(test)]
mod tests;
