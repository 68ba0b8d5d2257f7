//! The narrow phase (`kernels/physics.cu`): one thread per object tests its pairs (the
//! ranges the broad phase wrote) and sums the responses into `acc` in the CPU's order,
//! static pairs first, then dynamic pairs; `counters` gets the contact counts.

use myriad_physics::PhysicsError;

use super::Resident;
use crate::launch::{KNarrowDynamic, KNarrowStatic};

impl Resident {
    /// `k_narrow_static` over the static pair list, of which the first `cap` entries
    /// were written (a range past `cap` is left out, and the step is redone).
    pub(super) fn narrow_static(&self, cap: u32) -> Result<(), PhysicsError> {
        let (o, p) = (&self.obj, &self.prims);
        self.gpu.launch(
            self.n,
            KNarrowStatic {
                n: self.n as u32,
                kp: self.params.ptr(),
                pos: o.pos.ptr(),
                prev: o.prev.ptr(),
                half: o.half.ptr(),
                radius: o.radius.ptr(),
                shape: o.shape.ptr(),
                spos: p.pos.ptr(),
                shalf: p.half.ptr(),
                sradius: p.radius.ptr(),
                sshape: p.shape.ptr(),
                offsets: o.static_counts.ptr(),
                prims: self.static_pairs.ptr(),
                cap,
                acc: o.acc.ptr(),
                sup: o.sup.ptr(),
                counters: self.counters.ptr(),
            },
        )
    }

    /// `k_narrow_dynamic` over the dynamic pair list (first `cap` entries written).
    pub(super) fn narrow_dynamic(&self, cap: u32) -> Result<(), PhysicsError> {
        let o = &self.obj;
        self.gpu.launch(
            self.n,
            KNarrowDynamic {
                n: self.n as u32,
                kp: self.params.ptr(),
                pos: o.pos.ptr(),
                prev: o.prev.ptr(),
                half: o.half.ptr(),
                radius: o.radius.ptr(),
                shape: o.shape.ptr(),
                offsets: o.dynamic_counts.ptr(),
                others: self.dynamic_pairs.ptr(),
                cap,
                acc: o.acc.ptr(),
                sup: o.sup.ptr(),
                counters: self.counters.ptr(),
            },
        )
    }
}
