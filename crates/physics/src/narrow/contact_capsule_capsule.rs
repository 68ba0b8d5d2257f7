//! Capsule–capsule.

use super::Contact;
use super::segment::{Swept, segment_segment};
use myriad_core::Vec3;

/// Two vertical capsules (centres `ac`, `bc`; radii `ar`, `br`; segment half lengths
/// `ahh`, `bhh`). The segments are parallel: the closest points are at one height when
/// the y ranges overlap (the middle of the shared range) and at the facing ends
/// otherwise, and the test becomes sphere–sphere between them. Coaxial capsules are
/// separated by lifting `b` above `a`.
#[inline]
pub fn contact_capsule_capsule(ac: Vec3, ar: f32, ahh: f32, bc: Vec3, br: f32, bhh: f32) -> Option<Contact> {
    let a = Swept { c: ac, y0: ac.y - ahh, y1: ac.y + ahh, r: ar };
    let b = Swept { c: bc, y0: bc.y - bhh, y1: bc.y + bhh, r: br };
    segment_segment(a, b)
}
