//! Box–capsule.

use super::Contact;
use super::segment::segment_box;
use myriad_core::Vec3;

/// A box at `bc` with half extents `bh` against a vertical capsule at `cc` (radius `cr`,
/// segment half length `chh`); the normal points from the box to the capsule.
///
/// The segment's point nearest the box is its nearer end when their y ranges are
/// disjoint and the middle of the shared range otherwise; a sphere of the capsule's
/// radius there is tested against the box. When the segment passes through the box the
/// capsule leaves by the shortest of the six axis moves.
#[inline]
pub fn contact_box_capsule(bc: Vec3, bh: Vec3, cc: Vec3, cr: f32, chh: f32) -> Option<Contact> {
    segment_box(cc, cc.y - chh, cc.y + chh, cr, bc, bh).map(Contact::flipped)
}
