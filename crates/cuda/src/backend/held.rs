//! The positions, previous positions and flags a step leaves on the device until the host
//! reads them (`myriad_core::HeldState`): a GPU server tick reads only its players'
//! positions ([`Held`]'s gather), and a step that brings back only the actions moves 25
//! bytes an object less across the bus.
//!
//! A step copies them, on the device, into a [`Held`] that no world refers to any more
//! and hands the world that `Held`; the next step's kernels overwrite only the working
//! arrays, so a world whose step failed half-way, or a second world stepped by the same
//! backend, still fetches the values of its own last step. The backend keeps a few
//! (`HELD_MAX`); when every one is referred to, a step brings the arrays back as before.

use std::sync::{Arc, Mutex, Weak};

use cudarc::driver::result;
use cudarc::driver::safe::CudaContext;
use myriad_core::{HeldState, Vec3};
use myriad_physics::PhysicsError;

use super::sync::{flat3_mut, par_copy};
use super::{Resident, lock};
use crate::device::{DevBuf, Event, Gpu, Pinned, dev_err};
use crate::launch::{DevPtr, KGatherPositions};

/// The most [`Held`]s a backend keeps: one for the world's last step, one for the step
/// under way, one for a second world (a test, a clone being compared).
pub(super) const HELD_MAX: usize = 3;

/// One step's positions, previous positions and flags, copied on the device.
pub(super) struct Held {
    /// Positions, packed floats.
    pos: DevBuf<f32>,
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
    /// The backend that made this, whose stream and kernels gather some positions; gone
    /// when the backend was dropped (a gather then reads every position back).
    resident: Weak<Mutex<Resident>>,
    ctx: Arc<CudaContext>,
}

impl Held {
    fn new(gpu: &Gpu, resident: Weak<Mutex<Resident>>) -> Result<Held, PhysicsError> {
        Ok(Held {
            pos: DevBuf::empty(),
            prev: DevBuf::empty(),
            flags: DevBuf::empty(),
            n: 0,
            ready: Event::new(gpu)?,
            staging: Mutex::new(Pinned::empty()),
            resident,
            ctx: gpu.ctx.clone(),
        })
    }

    /// Copies `n` objects' state from `from` (the step's working arrays) into this, on
    /// `gpu`'s stream.
    fn copy_from(&mut self, gpu: &Gpu, n: usize, from: Arrays<'_>) -> Result<(), PhysicsError> {
        self.pos.ensure(gpu, n * 12, 1.25)?;
        self.prev.ensure(gpu, n * 12, 1.25)?;
        self.flags.ensure(gpu, n, 1.25)?;
        gpu.copy(self.pos.ptr(), from.pos.ptr(), 3 * n)?;
        gpu.copy(self.prev.ptr(), from.prev.ptr(), 3 * n)?;
        gpu.copy(self.flags.ptr(), from.flags.ptr(), n)?;
        gpu.record(self.ready.raw)?;
        self.n = n;
        Ok(())
    }

    /// Runs `read` on `bytes` bytes of this copy's page-locked staging memory, once the
    /// copies have landed, with the context current.
    fn staged<R>(
        &self,
        bytes: usize,
        read: impl FnOnce(&mut [u8]) -> Result<R, PhysicsError>,
    ) -> Result<R, PhysicsError> {
        self.ctx.bind_to_thread().map_err(dev_err("bind"))?;
        self.ready.wait()?;
        let mut staging = self.staging.lock().unwrap_or_else(|p| p.into_inner());
        staging.ensure_in(&self.ctx, bytes)?;
        read(staging.slice_mut::<u8>(bytes))
    }

    fn read_back(&self, pos: &mut [Vec3], prev: &mut [Vec3], flags: &mut [u8]) -> Result<(), PhysicsError> {
        let n = self.n;
        assert!(
            pos.len() == n && prev.len() == n && flags.len() == n,
            "held for {n} objects, read back into {}",
            prev.len()
        );
        self.staged(25 * n, |staging| {
            let (p, rest) = staging.split_at_mut(12 * n);
            let (q, f) = rest.split_at_mut(12 * n);
            copy_back(p, &self.pos)?;
            copy_back(q, &self.prev)?;
            copy_back(f, &self.flags)?;
            par_copy(flat3_mut(pos), bytemuck::cast_slice(p));
            par_copy(flat3_mut(prev), bytemuck::cast_slice(q));
            par_copy(flags, f);
            Ok(())
        })
    }

    /// The positions of `slots` (each below `n`, checked by the world) into `out`: a
    /// gather on the backend's stream, or, when the backend is gone, every position
    /// read back and picked on the host. It locks the backend's state, so nothing that
    /// holds that lock (a step, the device replicas) may read positions this way; none
    /// does: they read the device's arrays.
    fn gather(&self, slots: &[u32], out: &mut [Vec3]) -> Result<(), PhysicsError> {
        if let Some(resident) = self.resident.upgrade() {
            // The copies were queued on this same stream: the gather runs after them.
            return lock(&resident).gather_positions(self.pos.ptr(), slots, out);
        }
        self.staged(12 * self.n, |staging| {
            copy_back(staging, &self.pos)?;
            let pos: &[Vec3] = bytemuck::cast_slice(staging);
            for (o, &s) in out.iter_mut().zip(slots) {
                *o = pos[s as usize];
            }
            Ok(())
        })
    }
}

/// Copies the first `dst.len()` bytes of `src` into `dst`: a synchronous copy on the
/// default stream, which the backend's (non-blocking) stream does not wait for, so the
/// tick goes on while a reader fetches. Every caller passes a buffer sized for the `n`
/// objects the copy holds, and at most that many bytes of it.
fn copy_back<T>(dst: &mut [u8], src: &DevBuf<T>) -> Result<(), PhysicsError> {
    // SAFETY: `src` holds at least `dst.len()` bytes (see above).
    unsafe { result::memcpy_dtoh_sync(dst, src.ptr().raw()) }.map_err(dev_err("read back"))
}

impl HeldState for Held {
    fn fetch(&self, pos: &mut [Vec3], prev: &mut [Vec3], flags: &mut [u8]) {
        if let Err(e) = self.read_back(pos, prev, flags) {
            panic!("the positions, previous positions and flags of {} objects are lost on the device: {e}", self.n);
        }
    }

    fn positions_at(&self, slots: &[u32], out: &mut [Vec3]) {
        if let Err(e) = self.gather(slots, out) {
            panic!("the positions of {} objects are lost on the device: {e}", self.n);
        }
    }
}

/// The working arrays a [`Held`] copies.
pub(super) struct Arrays<'a> {
    /// Positions, packed floats.
    pub pos: &'a DevBuf<f32>,
    /// Previous positions, packed floats.
    pub prev: &'a DevBuf<f32>,
    /// Flag bits.
    pub flags: &'a DevBuf<u8>,
}

/// The backend's [`Held`]s.
#[derive(Default)]
pub(super) struct HeldPool {
    held: Vec<Arc<Held>>,
    /// The backend's own state, which each `Held` gathers through.
    resident: Weak<Mutex<Resident>>,
}

impl HeldPool {
    /// A pool whose `Held`s gather through `resident`.
    pub fn new(resident: Weak<Mutex<Resident>>) -> HeldPool {
        HeldPool { held: Vec::new(), resident }
    }

    /// A `Held` no world refers to, filled with this step's `n` positions, previous
    /// positions and flags (copied on the device), or `None` when all [`HELD_MAX`] are
    /// referred to.
    pub fn fill(&mut self, gpu: &Gpu, n: usize, from: Arrays<'_>) -> Result<Option<Arc<Held>>, PhysicsError> {
        let free = match self.held.iter().position(|h| Arc::strong_count(h) == 1) {
            Some(i) => i,
            None if self.held.len() < HELD_MAX => {
                self.held.push(Arc::new(Held::new(gpu, self.resident.clone())?));
                self.held.len() - 1
            }
            None => return Ok(None),
        };
        let held = Arc::get_mut(&mut self.held[free]).expect("a held no world refers to has one owner");
        held.copy_from(gpu, n, from)?;
        Ok(Some(self.held[free].clone()))
    }
}

impl Resident {
    /// The positions of `slots` in the device array `pos` into `out`: the slots go up and
    /// the positions come back through mapped page-locked memory, one launch between.
    fn gather_positions(&mut self, pos: DevPtr<f32>, slots: &[u32], out: &mut [Vec3]) -> Result<(), PhysicsError> {
        let m = slots.len();
        if m == 0 {
            return Ok(());
        }
        self.gpu.bind()?;
        let (up, down) = (&mut self.host.gather_slots, &mut self.host.gather_pos);
        up.ensure(&self.gpu, 4 * m)?;
        down.ensure(&self.gpu, 12 * m)?;
        up.slice_mut::<u32>(m).copy_from_slice(slots);
        let kernel = KGatherPositions { m: m as u32, slots: up.device_ptr()?, pos, out: down.device_ptr()? };
        self.gpu.launch(m, kernel)?;
        self.gpu.sync()?;
        self.gpu.collect_profile()?;
        out.copy_from_slice(bytemuck::cast_slice(down.slice::<f32>(3 * m)));
        Ok(())
    }
}
