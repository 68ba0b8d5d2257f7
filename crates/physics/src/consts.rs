//! Per-tick constants derived from [`PhysicsConfig`].

use myriad_core::PhysicsConfig;
use serde::{Deserialize, Serialize};

/// Everything a step multiplies by, computed once per tick on the host (in `f64`, then
/// rounded to `f32`) so that every backend, CPU or GPU, uses the very same values.
///
/// Velocities inside a step are in units per tick (Verlet: `pos - prev`) and
/// accelerations in units per tick².
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[repr(C)]
pub struct TickConstants {
    /// Gravity times dt², subtracted from the vertical velocity each tick.
    pub gravity_dt2: f32,
    /// `1 - air_drag`: velocity kept each tick.
    pub air_keep: f32,
    /// `1 - ground_friction`: horizontal velocity kept each tick on the ground.
    pub ground_keep: f32,
    /// Horizontal acceleration from a held direction, per tick², chosen so that friction
    /// and drag balance it at `move_speed`.
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
}

impl TickConstants {
    /// Constants for one tick of `1 / tick_rate` seconds scaled by `time_scale` (the
    /// time-dilation factor; 1 for real time).
    pub fn new(config: &PhysicsConfig, time_scale: f32) -> TickConstants {
        let dt = time_scale as f64 / config.tick_rate as f64;
        let air_keep = 1.0 - config.air_drag as f64;
        let ground_keep = 1.0 - config.ground_friction as f64;
        // Steady state on the ground: v = v·k + a  ⇒  a = v·(1 − k), with k the product of
        // the two keeps and v the top speed in units per tick.
        let k = air_keep * ground_keep;
        TickConstants {
            gravity_dt2: (config.gravity as f64 * dt * dt) as f32,
            air_keep: air_keep as f32,
            ground_keep: ground_keep as f32,
            move_accel: (config.move_speed as f64 * dt * (1.0 - k)) as f32,
            jump_velocity: (config.jump_speed as f64 * dt) as f32,
            one_plus_e: 1.0 + config.restitution,
            ground_tolerance: config.ground_tolerance,
            support_min_y: 0.7,
            npc_period: config.npc_action_period,
        }
    }
}

impl Default for TickConstants {
    fn default() -> Self {
        TickConstants::new(&PhysicsConfig::default(), 1.0)
    }
}
