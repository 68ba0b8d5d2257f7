//! Sphere–sphere.

use super::{Contact, FALLBACK_NORMAL, dot};
use myriad_core::Vec3;

/// Spheres at `ca` (radius `ra`) and `cb` (radius `rb`) overlap when their centres are
/// closer than the sum of the radii; the normal is the unit centre difference.
#[inline]
pub fn contact_sphere_sphere(ca: Vec3, ra: f32, cb: Vec3, rb: f32) -> Option<Contact> {
    let d = cb - ca;
    let dist2 = dot(d, d);
    let r = ra + rb;
    if dist2 >= r * r {
        return None;
    }
    let dist = dist2.sqrt();
    let normal = if dist > 0.0 { Vec3::new(d.x / dist, d.y / dist, d.z / dist) } else { FALLBACK_NORMAL };
    Some(Contact { normal, depth: r - dist })
}
