//! The parameter block the kernels read (`struct Params` in `kernels/common.cuh`).
//!
//! The block is uploaded as raw bytes, so this struct and the C++ one must agree field
//! for field: same order, same offsets, same size. `tests/nvrtc.rs` checks every field's
//! offset and size against the header with NVRTC, so a reordered or retyped field on
//! either side fails there.

use bytemuck::{Pod, Zeroable};
use myriad_core::World;
use myriad_physics::TickConstants;

/// Per-tick constants, world bounds and terrain sampling constants, laid out exactly as
/// the kernels' `Params` (23 four-byte fields, no padding). `Pod` lets the upload take
/// the block's bytes without an unsafe cast; deriving it also proves there is no padding.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct DeviceParams {
    /// Gravity times dt² (`TickConstants::gravity_dt2`).
    pub gravity_dt2: f32,
    /// Velocity kept each tick, `1 - air_drag`.
    pub air_keep: f32,
    /// Horizontal velocity kept each tick on the ground, `1 - ground_friction`.
    pub ground_keep: f32,
    /// Horizontal acceleration from a held direction, per tick².
    pub move_accel: f32,
    /// Vertical velocity a jump sets, per tick.
    pub jump_velocity: f32,
    /// `1 + restitution`.
    pub one_plus_e: f32,
    /// How far above the terrain an object still stands on it.
    pub ground_tolerance: f32,
    /// A contact normal with a y component above this supports the object above.
    pub support_min_y: f32,
    /// NPC action period in ticks.
    pub npc_period: u32,
    /// The world bounds' minimum corner.
    pub bmin: [f32; 3],
    /// The world bounds' maximum corner.
    pub bmax: [f32; 3],
    /// Terrain samples along x.
    pub t_width: u32,
    /// Terrain samples along z.
    pub t_depth: u32,
    /// The terrain's x origin in world units.
    pub origin_x: f32,
    /// The terrain's z origin in world units.
    pub origin_z: f32,
    /// Terrain sampling constant `inv_cell_x` (`Terrain::sampling_constants`).
    pub inv_cell_x: f32,
    /// Terrain sampling constant `inv_cell_z`.
    pub inv_cell_z: f32,
    /// Terrain sampling constant `height_scale` (height per sample unit).
    pub height_scale: f32,
    /// The terrain's base height (`TerrainPlacement::base_y`).
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
}

#[cfg(test)]
mod tests {
    use super::*;

    // The field offsets are checked against the C++ header in `tests/nvrtc.rs`.
    #[test]
    fn block_is_23_packed_words() {
        assert_eq!(std::mem::size_of::<DeviceParams>(), 23 * 4);
    }
}
