//! Box–box.

use super::Contact;
use myriad_core::Vec3;

/// Boxes at `ac` and `bc` with half extents `ah` and `bh` overlap when they overlap on all
/// three axes; the normal is the axis of least overlap, pointing from `a` towards `b`
/// (towards +axis when the centres coincide on it), the depth that overlap. Ties go to
/// the first axis in the order x, y, z.
#[inline]
pub fn contact_box_box(ac: Vec3, ah: Vec3, bc: Vec3, bh: Vec3) -> Option<Contact> {
    let d = bc - ac;
    let ox = (ah.x + bh.x) - d.x.abs();
    let oy = (ah.y + bh.y) - d.y.abs();
    let oz = (ah.z + bh.z) - d.z.abs();
    if ox <= 0.0 || oy <= 0.0 || oz <= 0.0 {
        return None;
    }
    let sign = |v: f32| if v < 0.0 { -1.0 } else { 1.0 };
    let (normal, depth) = if ox <= oy && ox <= oz {
        (Vec3::new(sign(d.x), 0.0, 0.0), ox)
    } else if oy <= oz {
        (Vec3::new(0.0, sign(d.y), 0.0), oy)
    } else {
        (Vec3::new(0.0, 0.0, sign(d.z)), oz)
    };
    Some(Contact { normal, depth })
}
