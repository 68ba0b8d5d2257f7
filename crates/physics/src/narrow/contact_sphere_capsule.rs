//! Sphere–capsule.

use super::Contact;
use super::segment::{Swept, segment_segment};
use myriad_core::Vec3;

/// A sphere at `c` of radius `r` against a vertical capsule at `cc` with radius `cr` and
/// segment half length `chh`: the centre's height clamped to the segment gives the
/// closest point, and the test becomes sphere–sphere there. A centre on the capsule's
/// axis lifts the capsule clear of the sphere.
#[inline]
pub fn contact_sphere_capsule(c: Vec3, r: f32, cc: Vec3, cr: f32, chh: f32) -> Option<Contact> {
    segment_segment(Swept { c, y0: c.y, y1: c.y, r }, Swept { c: cc, y0: cc.y - chh, y1: cc.y + chh, r: cr })
}
