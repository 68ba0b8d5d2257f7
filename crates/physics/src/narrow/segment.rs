//! The two workhorses of the narrow phase: a vertical segment swept by a sphere (a
//! capsule; a sphere is the case of a zero-length segment) against a box, and against
//! another such segment.
//!
//! The closest points are found with interval arithmetic along y. When they coincide (a
//! segment passes through the box, or two segments share their axis) no direction is
//! defined by them, and the shapes are separated along the cheapest way out instead:
//! each of the six directions for a box, straight up for two coaxial segments.

use super::{Contact, FALLBACK_NORMAL, contact_sphere_sphere, dot};
use myriad_core::Vec3;

/// The height on segment `[s0, s1]` closest to the range `[b0, b1]`: the nearer end when
/// the ranges are disjoint, the middle of the shared range otherwise.
#[inline]
fn closest_height(s0: f32, s1: f32, b0: f32, b1: f32) -> f32 {
    if s0 > b1 {
        s0
    } else if s1 < b0 {
        s1
    } else {
        (s0.max(b0) + s1.min(b1)) * 0.5
    }
}

/// The vertical segment at `(c.x, [s0, s1], c.z)` swept by radius `r`, against the box at
/// `bc` with half extents `bh`. The normal points from the segment's body to the box.
#[inline]
pub(crate) fn segment_box(c: Vec3, s0: f32, s1: f32, r: f32, bc: Vec3, bh: Vec3) -> Option<Contact> {
    let lo = bc - bh;
    let hi = bc + bh;
    let p = Vec3::new(c.x, closest_height(s0, s1, lo.y, hi.y), c.z);
    let q = Vec3::new(p.x.max(lo.x).min(hi.x), p.y.max(lo.y).min(hi.y), p.z.max(lo.z).min(hi.z));
    let d = q - p;
    let dist2 = dot(d, d);
    if dist2 > 0.0 {
        if dist2 >= r * r {
            return None;
        }
        let dist = dist2.sqrt();
        let normal = Vec3::new(d.x / dist, d.y / dist, d.z / dist);
        return Some(Contact { normal, depth: r - dist });
    }
    // The segment passes through the box: leave by the shortest of six moves. Each entry
    // is (distance the body must travel, normal from body to box); ties go to the first.
    let ways = [
        ((p.x - lo.x) + r, Vec3::X),     // move −x
        ((hi.x - p.x) + r, Vec3::NEG_X), // move +x
        ((s1 - lo.y) + r, Vec3::Y),      // move −y until the top end clears the bottom face
        ((hi.y - s0) + r, Vec3::NEG_Y),  // move +y until the bottom end clears the top face
        ((p.z - lo.z) + r, Vec3::Z),
        ((hi.z - p.z) + r, Vec3::NEG_Z),
    ];
    let mut best = ways[0];
    for w in &ways[1..] {
        if w.0 < best.0 {
            best = *w;
        }
    }
    Some(Contact { normal: best.1, depth: best.0 })
}

/// A vertical segment from `(c.x, y0, c.z)` to `(c.x, y1, c.z)` swept by radius `r`
/// (`c.y` is not used).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Swept {
    pub c: Vec3,
    pub y0: f32,
    pub y1: f32,
    pub r: f32,
}

/// Two swept vertical segments; the normal points from `a` to `b`.
#[inline]
pub(crate) fn segment_segment(a: Swept, b: Swept) -> Option<Contact> {
    let (ya, yb) = if a.y0 > b.y1 {
        (a.y0, b.y1)
    } else if a.y1 < b.y0 {
        (a.y1, b.y0)
    } else {
        let m = (a.y0.max(b.y0) + a.y1.min(b.y1)) * 0.5;
        (m, m)
    };
    let pa = Vec3::new(a.c.x, ya, a.c.z);
    let pb = Vec3::new(b.c.x, yb, b.c.z);
    let c = contact_sphere_sphere(pa, a.r, pb, b.r)?;
    if pa == pb {
        // Shared axis and overlapping ranges: lift b until its bottom end clears a's top.
        return Some(Contact { normal: FALLBACK_NORMAL, depth: (a.y1 - b.y0) + (a.r + b.r) });
    }
    Some(c)
}
