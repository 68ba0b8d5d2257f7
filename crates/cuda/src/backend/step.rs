//! One tick: sync, boxes and tree, broad phase, narrow phase, forces, then the download
//! of the new actions into the `World` (the positions, previous positions and flags stay
//! on the device, `held`), with the stage times from the events.

use std::time::Instant;

use myriad_core::World;
use myriad_physics::{PhysicsError, Stage, StepReport, TickConstants};

use super::broad::write_pass;
use super::held::Arrays;
use super::sync::{flat3_mut, par_copy};
use super::{Resident, Synced};

impl Resident {
    /// One step, or `None` (world untouched) when a pair list did not fit: the buffers are
    /// then grown to the exact totals and the device state is marked for re-upload.
    /// `sent` adds up the bytes uploaded by this try and any before it in the same step.
    pub(super) fn try_step(
        &mut self,
        world: &mut World,
        k: &TickConstants,
        sent: &mut u64,
    ) -> Result<Option<StepReport>, PhysicsError> {
        let wall = Instant::now();
        self.gpu.bind()?;
        let mut report = StepReport::default();
        self.gpu.record(self.events[0].raw)?;
        *sent += self.sync_world(world, Some(k))?;
        self.gpu.profile_host("host: physics, uploads", wall);
        let launching = Instant::now();
        report.upload_bytes = *sent;
        let n = self.n;
        if n == 0 {
            // The backend's step is the single owner of the world's tick counter: no
            // other code advances it.
            world.tick += 1;
            report.stage_ms[Stage::Upload as usize] = wall.elapsed().as_secs_f64() * 1e3;
            return Ok(Some(report));
        }
        let ev = |s: &Self, i: usize| s.gpu.record(s.events[i].raw);
        ev(self, 1)?;
        self.build_dynamic(world)?;
        ev(self, 2)?;

        let (sc, dc) = (self.obj.static_counts.ptr(), self.obj.dynamic_counts.ptr());
        let (qs_static, qs_dynamic) = self.count_pairs(|s| ev(s, 3))?;
        ev(self, 4)?;
        // No wait for the totals here: the write passes fill what fits, and the totals
        // come back with the state at the end of the step.
        self.static_pairs.ensure(&self.gpu, 4 * n, 1.0)?;
        self.dynamic_pairs.ensure(&self.gpu, 4 * n, 1.0)?;
        ev(self, 5)?;
        write_pass(&self.gpu, qs_static, false, self.static_targets(), sc, &self.static_pairs)?;
        ev(self, 6)?;
        write_pass(&self.gpu, qs_dynamic, true, self.dynamic_targets(), dc, &self.dynamic_pairs)?;
        ev(self, 7)?;
        let caps = [self.static_pairs.capacity(), self.dynamic_pairs.capacity()];

        self.counters.ensure(&self.gpu, 16, 1.0)?;
        self.gpu.zero(self.counters.ptr(), 2)?;
        self.narrow_static(caps[0])?;
        ev(self, 8)?;
        self.narrow_dynamic(caps[1])?;
        ev(self, 9)?;
        self.forces(world, k)?;
        ev(self, 10)?;
        let o = &self.obj;
        let h = &mut self.host;
        let gpu = &self.gpu;
        // The positions, previous positions and flags stay on the device, copied there
        // for the world to fetch if it ever reads them (`held`); when every copy is still
        // referred to, they come back with the actions.
        let held = self.held.fill(gpu, n, Arrays { pos: &o.pos, prev: &o.prev, flags: &o.flags })?;
        h.action.ensure(gpu, n)?;
        if held.is_none() {
            h.pos.ensure(gpu, n * 12)?;
            h.prev.ensure(gpu, n * 12)?;
            h.flags.ensure(gpu, n)?;
        }
        // The small totals first, then the state array by array, each followed by an
        // event: the host checks the totals as soon as they land (and, when nothing is
        // held, copies each array into the World while the next one is still crossing
        // the bus).
        h.small.ensure(gpu, 64)?;
        let mut down = gpu.download_async(&mut h.small, 0, self.counters.ptr(), 2)?;
        down += gpu.download_async(&mut h.small, 2, sc.add(n), 1)?;
        down += gpu.download_async(&mut h.small, 3, dc.add(n), 1)?;
        gpu.record(self.events[12].raw)?;
        if held.is_none() {
            down += gpu.download_async(&mut h.pos, 0, o.pos.ptr(), 3 * n)?;
        }
        gpu.record(self.events[13].raw)?;
        if held.is_none() {
            down += gpu.download_async(&mut h.prev, 0, o.prev.ptr(), 3 * n)?;
        }
        gpu.record(self.events[14].raw)?;
        down += gpu.download_async(&mut h.action, 0, o.action.ptr(), n)?;
        if held.is_none() {
            down += gpu.download_async(&mut h.flags, 0, o.flags.ptr(), n)?;
        }
        gpu.record(self.events[11].raw)?;
        gpu.profile_host("host: physics, launches", launching);
        let waiting = Instant::now();
        self.events[12].wait()?;
        gpu.profile_host("host: physics, waiting for the step", waiting);
        let copying = Instant::now();

        let small = h.small.slice::<u32>(4);
        let (contacts, totals) = ([small[0], small[1]], [small[2], small[3]]);
        if totals[0] > caps[0] || totals[1] > caps[1] {
            // Some list did not fit: grow to the exact totals and redo from the world,
            // which this step has not touched.
            gpu.sync()?;
            gpu.collect_profile()?;
            self.static_pairs.ensure(gpu, totals[0] as usize * 4, 1.0)?;
            self.dynamic_pairs.ensure(gpu, totals[1] as usize * 4, 1.0)?;
            self.synced = None;
            return Ok(None);
        }
        report.static_pairs = totals[0] as u64;
        report.dynamic_pairs = totals[1] as u64 / 2;
        report.static_contacts = contacts[0] as u64;
        report.dynamic_contacts = contacts[1] as u64;
        report.download_bytes = down;
        if let Some(held) = held {
            // Everything has landed before the world is written, and the world takes this
            // step's held copy only then: a step that fails leaves the world as it was,
            // holding its own last step's copy.
            gpu.sync()?;
            let action = world.dynamics.state_mut_holding(held);
            par_copy(action, h.action.slice::<u8>(n));
            gpu.profile_host("host: physics, the new state into the world", copying);
        } else {
            let st = world.dynamics.state_mut();
            self.events[13].wait()?;
            par_copy(flat3_mut(st.pos), h.pos.slice::<f32>(3 * n));
            self.events[14].wait()?;
            par_copy(flat3_mut(st.prev), h.prev.slice::<f32>(3 * n));
            gpu.sync()?;
            par_copy(st.action, h.action.slice::<u8>(n));
            par_copy(st.flags, h.flags.slice::<u8>(n));
        }
        gpu.collect_profile()?;
        // The backend's step is the single owner of the world's tick counter: no other
        // code advances it, so every backend moves it exactly once per step.
        world.tick += 1;
        self.synced = Some(Synced::of(world));
        self.boxes_fresh = None;

        let e = &self.events;
        let t = |a: usize, b: usize| e[a].ms_to(&e[b]);
        let ms = &mut report.stage_ms;
        ms[Stage::BuildDynamicBvh as usize] = t(1, 2)?;
        ms[Stage::BroadStatic as usize] = t(2, 3)? + t(5, 6)?;
        ms[Stage::BroadDynamic as usize] = t(3, 4)? + t(6, 7)?;
        ms[Stage::NarrowStatic as usize] = t(7, 8)?;
        ms[Stage::NarrowDynamic as usize] = t(8, 9)?;
        ms[Stage::Forces as usize] = t(9, 10)?;
        let device: f64 = ms.iter().sum();
        let wall_ms = wall.elapsed().as_secs_f64() * 1e3;
        ms[Stage::Upload as usize] = t(0, 1)? + t(10, 11)? + (wall_ms - device - t(0, 1)? - t(10, 11)?).max(0.0);
        Ok(Some(report))
    }
}
