//! Collision response: what each contact does to the two objects, and the deterministic
//! gather that sums those effects per object.
//!
//! A contact between `a` and `b` (normal from `a` to `b`) moves `b` by `+dx` and `a` by
//! `-dx`, and changes their velocities by `+dv` and `-dv`; against a static primitive the
//! dynamic object plays `b` and takes the whole response, between two dynamic objects
//! each takes half (docs/design.md, physics). Pairs already moving apart are skipped.
//!
//! Velocities are implicit in Verlet integration (`pos - prev`), so a response is applied
//! as `pos += dx; prev += dx - dv`: the position is corrected without the correction
//! turning into speed, and the velocity changes by exactly `dv`.
//!
//! **Determinism.** Float addition is not associative, so the order in which an object's
//! corrections are summed is fixed: first its static contacts by ascending primitive
//! index, then its dynamic contacts by ascending index of the other object. Every backend
//! sums in this order (the GPU gathers per object over sorted pair lists), never with
//! atomics.

use crate::consts::TickConstants;
use crate::narrow::{Contact, dot};
use myriad_core::Vec3;

/// The effect of one contact, as applied to its second object (`b`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Response {
    /// Position correction.
    pub dx: Vec3,
    /// Velocity change (units per tick).
    pub dv: Vec3,
    /// The contact normal's y component (whether it holds `b` up, or `a` when negative).
    pub normal_y: f32,
}

/// The response to `contact` between bodies moving with velocities `va` and `vb`, where
/// `b` takes the fraction `share` (1 against a static, 0.5 between dynamics). `None` when
/// they already move apart along the normal.
#[inline]
pub fn respond(contact: &Contact, va: Vec3, vb: Vec3, share: f32, k: &TickConstants) -> Option<Response> {
    let n = contact.normal;
    let vrel = vb - va;
    let vn = dot(vrel, n);
    if vn > 0.0 {
        return None;
    }
    let s = contact.depth * share;
    // Only the approaching part of the velocity is removed (and a share given back):
    // vn ≤ 0, so j ≥ 0 pushes b along +n.
    let j = -(k.one_plus_e * vn) * share;
    Some(Response { dx: n * s, dv: n * j, normal_y: n.y })
}

/// The sum of an object's responses, built in the canonical order.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Accum {
    /// Summed position correction.
    pub dx: Vec3,
    /// Summed velocity change.
    pub dv: Vec3,
    /// Some contact pushed this object upwards.
    pub supported: bool,
}

impl Accum {
    /// Adds a response in which this object is `b`.
    #[inline]
    pub fn add_as_b(&mut self, r: &Response, k: &TickConstants) {
        self.dx += r.dx;
        self.dv += r.dv;
        self.supported |= r.normal_y > k.support_min_y;
    }

    /// Adds a response in which this object is `a` (opposite sign).
    #[inline]
    pub fn add_as_a(&mut self, r: &Response, k: &TickConstants) {
        self.dx -= r.dx;
        self.dv -= r.dv;
        self.supported |= -r.normal_y > k.support_min_y;
    }

    /// Applies the sum to one object's Verlet state.
    #[inline]
    pub fn apply(&self, pos: &mut Vec3, prev: &mut Vec3) {
        *pos += self.dx;
        *prev += self.dx - self.dv;
    }
}
