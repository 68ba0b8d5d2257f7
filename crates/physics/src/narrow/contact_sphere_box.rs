//! Sphere–box.

use super::Contact;
use super::segment::segment_box;
use myriad_core::Vec3;

/// A sphere at `c` of radius `r` against a box centred at `bc` with half extents `bh`;
/// the normal points from the sphere to the box.
///
/// Outside the box the closest point of the box to the centre decides: the normal runs
/// from the centre to it and the depth is the radius minus its distance. With the centre
/// inside, the sphere leaves through the nearest face (ties in the order −x, +x, −y, +y,
/// −z, +z) and the depth is the radius plus the distance to that face.
#[inline]
pub fn contact_sphere_box(c: Vec3, r: f32, bc: Vec3, bh: Vec3) -> Option<Contact> {
    segment_box(c, c.y, c.y, r, bc, bh)
}
