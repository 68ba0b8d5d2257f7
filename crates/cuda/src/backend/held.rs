//! The previous positions and flags a step leaves on the device until the host reads
//! them (`myriad_core::HeldState`): a GPU server tick never does, and a step that does
//! not bring them back moves 13 bytes an object less across the bus.
//!
//! A step copies them, on the device, into a [`Held`] that no world refers to any more
//! and hands the world that `Held`; the next step's kernels overwrite only the working
//! arrays, so a world whose step failed half-way, or a second world stepped by the same
//! backend, still fetches the values of its own last step. The backend keeps a few
//! (`HELD_MAX`); when every one is referred to, a step brings the arrays back as before.

use std::sync::{Arc, Mutex};

use cudarc::driver::result;
use cudarc::driver::safe::CudaContext;
use myriad_core::{HeldState, Vec3};
use myriad_physics::PhysicsError;

use super::sync::{flat3_mut, par_copy};
use crate::device::{DevBuf, Event, Gpu, Pinned, dev_err};

/// The most [`Held`]s a backend keeps: one for the world's last step, one for the step
/// under way, one for a second world (a test, a clone being compared).
pub(super) const HELD_MAX: usize = 3;

/// One step's previous positions and flags, copied on the device.
pub(super) struct Held {
    /// Previous positions, packed floats.
    prev: DevBuf<f32>,
    /// Flag bits.
    flags: DevBuf<u8>,
    /// Objects the copies hold.
    n: usize,
    /// Recorded on the backend's stream after the copies.
    ready: Event,
    /// Page-locked memory a fetch reads back through (made by the first fetch).
    staging: Mutex<Pinned>,
    ctx: Arc<CudaContext>,
}

impl Held {
    fn new(gpu: &Gpu) -> Result<Held, PhysicsError> {
        Ok(Held {
            prev: DevBuf::empty(),
            flags: DevBuf::empty(),
            n: 0,
            ready: Event::new(gpu)?,
            staging: Mutex::new(Pinned::empty()),
            ctx: gpu.ctx.clone(),
        })
    }

    /// Copies `n` objects' previous positions and flags from `prev` and `flags` (the
    /// step's working arrays) into this, on `gpu`'s stream.
    fn copy_from(&mut self, gpu: &Gpu, n: usize, prev: &DevBuf<f32>, flags: &DevBuf<u8>) -> Result<(), PhysicsError> {
        self.prev.ensure(gpu, n * 12, 1.25)?;
        self.flags.ensure(gpu, n, 1.25)?;
        gpu.copy(self.prev.ptr(), prev.ptr(), 3 * n)?;
        gpu.copy(self.flags.ptr(), flags.ptr(), n)?;
        gpu.record(self.ready.raw)?;
        self.n = n;
        Ok(())
    }

    fn read_back(&self, prev: &mut [Vec3], flags: &mut [u8]) -> Result<(), PhysicsError> {
        let n = self.n;
        assert!(prev.len() == n && flags.len() == n, "held for {n} objects, read back into {}", prev.len());
        self.ctx.bind_to_thread().map_err(dev_err("bind"))?;
        self.ready.wait()?;
        let mut staging = self.staging.lock().unwrap_or_else(|p| p.into_inner());
        staging.ensure_in(&self.ctx, 13 * n)?;
        let (p, f) = staging.slice_mut::<u8>(13 * n).split_at_mut(12 * n);
        // Synchronous copies on the default stream, which the backend's (non-blocking)
        // stream does not wait for: the tick goes on while a reader fetches.
        // SAFETY: each source holds at least as many bytes as its destination (the
        // buffers were sized for `n` objects when this was filled).
        unsafe {
            result::memcpy_dtoh_sync(p, self.prev.ptr().raw()).map_err(dev_err("read back"))?;
            result::memcpy_dtoh_sync(f, self.flags.ptr().raw()).map_err(dev_err("read back"))?;
        }
        par_copy(flat3_mut(prev), bytemuck::cast_slice(p));
        par_copy(flags, f);
        Ok(())
    }
}

impl HeldState for Held {
    fn fetch(&self, prev: &mut [Vec3], flags: &mut [u8]) {
        if let Err(e) = self.read_back(prev, flags) {
            panic!("the previous positions and flags of {} objects are lost on the device: {e}", self.n);
        }
    }
}

/// The backend's [`Held`]s.
#[derive(Default)]
pub(super) struct HeldPool {
    held: Vec<Arc<Held>>,
}

impl HeldPool {
    /// A `Held` no world refers to, filled with this step's `n` previous positions and
    /// flags (copied on the device), or `None` when all [`HELD_MAX`] are referred to.
    pub fn fill(
        &mut self,
        gpu: &Gpu,
        n: usize,
        prev: &DevBuf<f32>,
        flags: &DevBuf<u8>,
    ) -> Result<Option<Arc<Held>>, PhysicsError> {
        let free = match self.held.iter().position(|h| Arc::strong_count(h) == 1) {
            Some(i) => i,
            None if self.held.len() < HELD_MAX => {
                self.held.push(Arc::new(Held::new(gpu)?));
                self.held.len() - 1
            }
            None => return Ok(None),
        };
        let held = Arc::get_mut(&mut self.held[free]).expect("a held no world refers to has one owner");
        held.copy_from(gpu, n, prev, flags)?;
        Ok(Some(self.held[free].clone()))
    }
}
