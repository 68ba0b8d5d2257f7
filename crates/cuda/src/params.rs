//! The parameter block the kernels read (`struct Params` in `kernels/common.cuh`).

use myriad_core::World;
use myriad_physics::TickConstants;

/// Per-tick constants, world bounds and terrain sampling constants, laid out exactly as
/// the kernels' `Params` (23 four-byte fields, no padding).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub(crate) struct DeviceParams {
    pub gravity_dt2: f32,
    pub air_keep: f32,
    pub ground_keep: f32,
    pub move_accel: f32,
    pub jump_velocity: f32,
    pub one_plus_e: f32,
    pub ground_tolerance: f32,
    pub support_min_y: f32,
    pub npc_period: u32,
    pub bmin: [f32; 3],
    pub bmax: [f32; 3],
    pub t_width: u32,
    pub t_depth: u32,
    pub origin_x: f32,
    pub origin_z: f32,
    pub inv_cell_x: f32,
    pub inv_cell_z: f32,
    pub height_scale: f32,
    pub base_y: f32,
}

impl DeviceParams {
    /// The block for `world` under constants `k`.
    pub fn new(world: &World, k: &TickConstants) -> DeviceParams {
        let t = &world.terrain;
        let at = t.placement();
        let (inv_cell_x, inv_cell_z, height_scale) = t.sampling_constants();
        DeviceParams {
            gravity_dt2: k.gravity_dt2,
            air_keep: k.air_keep,
            ground_keep: k.ground_keep,
            move_accel: k.move_accel,
            jump_velocity: k.jump_velocity,
            one_plus_e: k.one_plus_e,
            ground_tolerance: k.ground_tolerance,
            support_min_y: k.support_min_y,
            npc_period: k.npc_period,
            bmin: world.bounds.min.to_array(),
            bmax: world.bounds.max.to_array(),
            t_width: t.width(),
            t_depth: t.depth(),
            origin_x: at.origin_x,
            origin_z: at.origin_z,
            inv_cell_x,
            inv_cell_z,
            height_scale,
            base_y: at.base_y,
        }
    }

    /// The block as 4-byte words, for the upload.
    pub fn words(&self) -> [u32; 23] {
        let f = |v: f32| v.to_bits();
        [
            f(self.gravity_dt2),
            f(self.air_keep),
            f(self.ground_keep),
            f(self.move_accel),
            f(self.jump_velocity),
            f(self.one_plus_e),
            f(self.ground_tolerance),
            f(self.support_min_y),
            self.npc_period,
            f(self.bmin[0]),
            f(self.bmin[1]),
            f(self.bmin[2]),
            f(self.bmax[0]),
            f(self.bmax[1]),
            f(self.bmax[2]),
            self.t_width,
            self.t_depth,
            f(self.origin_x),
            f(self.origin_z),
            f(self.inv_cell_x),
            f(self.inv_cell_z),
            f(self.height_scale),
            f(self.base_y),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_is_23_packed_words() {
        assert_eq!(std::mem::size_of::<DeviceParams>(), 23 * 4);
    }
}
