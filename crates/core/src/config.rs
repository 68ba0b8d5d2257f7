//! Physics parameters shared by every backend.

use serde::{Deserialize, Serialize};

/// The physical constants of a world. Backends turn them into per-tick constants once
/// (see `myriad_physics::TickConstants`), so every backend multiplies by the very same
/// `f32` values.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhysicsConfig {
    /// Simulation steps per second; one step advances time by `1 / tick_rate` seconds
    /// (times the time-dilation factor, when the server applies one).
    pub tick_rate: f32,
    /// Downward acceleration in units/s².
    pub gravity: f32,
    /// Fraction of horizontal velocity lost per tick while standing on something.
    pub ground_friction: f32,
    /// Fraction of velocity lost per tick to the air, always.
    pub air_drag: f32,
    /// Top walking speed in units/s: the acceleration from the action mask is chosen so
    /// that ground friction balances it at this speed.
    pub move_speed: f32,
    /// Upward speed given by a jump, in units/s.
    pub jump_speed: f32,
    /// Share of the approaching normal velocity a collision gives back (0 = no bounce).
    pub restitution: f32,
    /// NPCs pick a new random action every this many ticks (each with its own phase).
    pub npc_action_period: u32,
    /// Distance above the terrain within which an object still counts as standing on it.
    pub ground_tolerance: f32,
}

impl Default for PhysicsConfig {
    fn default() -> Self {
        PhysicsConfig {
            tick_rate: 30.0,
            gravity: 9.81,
            ground_friction: 0.2,
            air_drag: 0.002,
            move_speed: 5.0,
            jump_speed: 5.0,
            restitution: 0.2,
            npc_action_period: 60,
            ground_tolerance: 0.05,
        }
    }
}

impl PhysicsConfig {
    /// Checks every parameter, naming the first bad one.
    pub fn validate(&self) -> Result<(), crate::CoreError> {
        let check = |what: &'static str, v: f32, ok: bool| {
            if v.is_finite() && ok { Ok(()) } else { Err(crate::CoreError::invalid(what, format!("{v}"))) }
        };
        check("tick_rate", self.tick_rate, self.tick_rate > 0.0)?;
        check("gravity", self.gravity, true)?;
        check(
            "ground_friction",
            self.ground_friction,
            (0.0..1.0).contains(&self.ground_friction) && self.ground_friction > 0.0,
        )?;
        check("air_drag", self.air_drag, (0.0..1.0).contains(&self.air_drag))?;
        check("move_speed", self.move_speed, self.move_speed >= 0.0)?;
        check("jump_speed", self.jump_speed, self.jump_speed >= 0.0)?;
        check("restitution", self.restitution, (0.0..=1.0).contains(&self.restitution))?;
        check("ground_tolerance", self.ground_tolerance, self.ground_tolerance >= 0.0)?;
        if self.npc_action_period == 0 {
            return Err(crate::CoreError::invalid("npc_action_period", "must be at least 1"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_bad_values_are_named() {
        PhysicsConfig::default().validate().unwrap();
        let bad = PhysicsConfig { ground_friction: 1.5, ..Default::default() };
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("ground_friction"), "{err}");
        let bad = PhysicsConfig { tick_rate: f32::NAN, ..Default::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("tick_rate"));
    }
}
