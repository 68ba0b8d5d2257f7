//! Forces and integration (`k_forces` in `kernels/physics.cu`): NPC decisions, actions,
//! the contact responses summed by the narrow phase, terrain, and the position update.

use myriad_core::World;
use myriad_physics::integrate::NpcTurn;
use myriad_physics::{PhysicsError, TickConstants};

use super::Resident;
use crate::launch::KForces;

impl Resident {
    /// `k_forces` for the tick `world.tick` (not yet advanced: the step advances it after
    /// the state comes back).
    pub(super) fn forces(&self, world: &World, k: &TickConstants) -> Result<(), PhysicsError> {
        let o = &self.obj;
        let turn = NpcTurn::at(world.tick, k.npc_period);
        self.gpu.launch(
            self.n,
            KForces {
                n: self.n as u32,
                kp: self.params.ptr(),
                seed: world.seed,
                tick: world.tick,
                period: turn.period,
                turn_phase: turn.phase,
                pos: o.pos.ptr(),
                prev: o.prev.ptr(),
                half: o.half.ptr(),
                kind: o.kind.ptr(),
                id: o.id.ptr(),
                action: o.action.ptr(),
                flags: o.flags.ptr(),
                acc: o.acc.ptr(),
                sup: o.sup.ptr(),
                samples: self.samples.ptr(),
            },
        )
    }
}
