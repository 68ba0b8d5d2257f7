//! The incremental upload: a device copy made right after a step is brought up to date
//! with the world's record of what changed since ([`Changes`]), not with the whole world.
//!
//! A zone keeps its world from tick to tick and edits it once a tick
//! ([`myriad_core::Dynamics::apply_sorted`]): a few objects leave, a few arrive, a few
//! ghosts' states are overwritten, and the rest shift by a few slots. Then:
//!
//! 1. the host packs the runs of kept slots and every state it wrote into one staging
//!    buffer ([`pack`]), sent in one copy;
//! 2. when slots moved, `k_patch_gather` (`kernels/patch.cu`) copies each kept object's
//!    nine arrays from its old slot into a spare set of arrays of the new length, which
//!    then becomes the current set (the old one is kept as the next tick's spare: no
//!    allocation in the steady state);
//! 3. `k_patch_scatter` writes the staged states into their slots;
//! 4. the actions, when any was set, travel whole (one byte an object).
//!
//! What crosses the bus is 12 bytes a run and 52 a written state (plus the actions), so
//! it follows the objects that crossed a boundary, not the zone's size. The record is
//! checked first ([`applicable`]); one that does not fit the device copy is not applied
//! and the caller uploads everything instead.

use myriad_core::world::Changes;
use myriad_core::{Dynamics, World};
use myriad_physics::PhysicsError;

use super::Resident;
use super::sync::{Objects, send, size_derived};
use crate::device::{DevBuf, Gpu};
use crate::launch::{KPatchGather, KPatchScatter};

/// Words (u32) a run takes in the staging buffer: to, from, len.
pub(crate) const RUN_WORDS: usize = 3;
/// Words a written state takes: its slot, pos, prev, half (3 each), radius, id, and one
/// word of four bytes (shape, kind, action, flags).
pub(crate) const STATE_WORDS: usize = 13;

/// The persistent per-object arrays a second time: the gather's destination.
pub(super) struct Spare {
    pos: DevBuf<f32>,
    prev: DevBuf<f32>,
    half: DevBuf<f32>,
    radius: DevBuf<f32>,
    shape: DevBuf<u8>,
    kind: DevBuf<u8>,
    id: DevBuf<u32>,
    action: DevBuf<u8>,
    flags: DevBuf<u8>,
}

/// The incremental upload's state: the spare arrays and the staging buffers, kept from
/// tick to tick.
pub(super) struct Patch {
    spare: Spare,
    /// The staged words on the device.
    staging: DevBuf<u32>,
    /// The staged words on the host, reused.
    words: Vec<u32>,
}

impl Patch {
    /// Nothing allocated yet.
    pub fn new() -> Patch {
        Patch {
            spare: Spare {
                pos: DevBuf::empty(),
                prev: DevBuf::empty(),
                half: DevBuf::empty(),
                radius: DevBuf::empty(),
                shape: DevBuf::empty(),
                kind: DevBuf::empty(),
                id: DevBuf::empty(),
                action: DevBuf::empty(),
                flags: DevBuf::empty(),
            },
            staging: DevBuf::empty(),
            words: Vec::new(),
        }
    }
}

impl Spare {
    /// Room for `n` objects, grown with the same headroom as the current arrays.
    fn ensure(&mut self, gpu: &Gpu, n: usize) -> Result<(), PhysicsError> {
        for b in [&mut self.pos, &mut self.prev, &mut self.half] {
            b.ensure(gpu, n * 12, 1.25)?;
        }
        self.radius.ensure(gpu, n * 4, 1.25)?;
        self.id.ensure(gpu, n * 4, 1.25)?;
        for b in [&mut self.shape, &mut self.kind, &mut self.action, &mut self.flags] {
            b.ensure(gpu, n, 1.25)?;
        }
        Ok(())
    }

    /// Makes these arrays the current ones and the current ones the spare.
    fn swap_with(&mut self, o: &mut Objects) {
        use std::mem::swap;
        swap(&mut self.pos, &mut o.pos);
        swap(&mut self.prev, &mut o.prev);
        swap(&mut self.half, &mut o.half);
        swap(&mut self.radius, &mut o.radius);
        swap(&mut self.shape, &mut o.shape);
        swap(&mut self.kind, &mut o.kind);
        swap(&mut self.id, &mut o.id);
        swap(&mut self.action, &mut o.action);
        swap(&mut self.flags, &mut o.flags);
    }
}

/// Whether `c` describes a change from `old_n` objects to `new_n` that the kernels can
/// apply: runs ascending by their new slot, apart, inside both lengths; written slots
/// ascending, unique, inside; and every slot no run covers written. The world's
/// record promises all of it; the check costs little next to the upload it saves and
/// keeps a wrong record from leaving stale slots on the device (the caller uploads
/// everything instead).
pub(crate) fn applicable(c: &Changes, old_n: usize, new_n: usize) -> bool {
    let w = &c.written;
    let written_in =
        |a: usize, b: usize| w.partition_point(|&s| (s as usize) < b) - w.partition_point(|&s| (s as usize) < a);
    if !w.windows(2).all(|p| p[0] < p[1]) || w.last().is_some_and(|&s| s as usize >= new_n) {
        return false;
    }
    let Some(runs) = &c.moved else { return old_n == new_n };
    let mut next = 0usize;
    for r in runs {
        let (to, from, len) = (r.to as usize, r.from as usize, r.len as usize);
        if to < next || to + len > new_n || from + len > old_n {
            return false;
        }
        // The gap before the run holds new objects only.
        if written_in(next, to) != to - next {
            return false;
        }
        next = to + len;
    }
    written_in(next, new_n) == new_n - next
}

/// Packs the staging words of `c` from `d` into `out` (cleared first): the runs
/// (`RUN_WORDS` each: to, from, len), then the written states as sections of `w =
/// c.written.len()` items: slots `[0, w)`, pos `[w, 4w)`, prev `[4w, 7w)`, half
/// `[7w, 10w)`, radius bits `[10w, 11w)`, id `[11w, 12w)`, bytes `[12w, 13w)` (shape |
/// kind << 8 | action << 16 | flags << 24), the layout `k_patch_scatter` reads. Returns
/// how many runs lead. `c` must be [`applicable`] to `d`.
pub(crate) fn pack(c: &Changes, d: &Dynamics, out: &mut Vec<u32>) -> usize {
    let runs = c.moved.as_deref().unwrap_or_default();
    let w = c.written.len();
    out.clear();
    out.resize(RUN_WORDS * runs.len() + STATE_WORDS * w, 0);
    let (head, states) = out.split_at_mut(RUN_WORDS * runs.len());
    for (dst, r) in head.chunks_exact_mut(RUN_WORDS).zip(runs) {
        dst.copy_from_slice(&[r.to, r.from, r.len]);
    }
    let (slots, rest) = states.split_at_mut(w);
    let (pos, rest) = rest.split_at_mut(3 * w);
    let (prev, rest) = rest.split_at_mut(3 * w);
    let (half, rest) = rest.split_at_mut(3 * w);
    let (radius, rest) = rest.split_at_mut(w);
    let (id, bytes) = rest.split_at_mut(w);
    let bits = |v: myriad_core::Vec3| v.to_array().map(f32::to_bits);
    for (k, &slot) in c.written.iter().enumerate() {
        let s = slot as usize;
        slots[k] = slot;
        pos[3 * k..3 * k + 3].copy_from_slice(&bits(d.positions()[s]));
        prev[3 * k..3 * k + 3].copy_from_slice(&bits(d.prev_positions()[s]));
        half[3 * k..3 * k + 3].copy_from_slice(&bits(d.half_extents()[s]));
        radius[k] = d.radii()[s].to_bits();
        id[k] = d.ids()[s].0;
        bytes[k] = u32::from_le_bytes([d.shapes()[s] as u8, d.kinds()[s] as u8, d.actions()[s], d.flags()[s]]);
    }
    runs.len()
}

impl Resident {
    /// Applies the world's record of changes to the device copy, when that copy was made
    /// exactly at the record's base and the record fits it; returns the bytes sent, or
    /// `None` (nothing done) when the caller must upload everything.
    pub(super) fn patch(&mut self, world: &World, c: &Changes) -> Result<Option<u64>, PhysicsError> {
        let d = &world.dynamics;
        let n = d.len();
        let at_base = self
            .synced
            .is_some_and(|s| (s.generation, s.layout, s.identity) == (c.base_generation, c.base_layout, d.stamp()));
        if !at_base || self.n != c.base_len || !applicable(c, self.n, n) {
            return Ok(None);
        }
        let gpu = &self.gpu;
        let p = &mut self.patch;
        let runs = pack(c, d, &mut p.words);
        let mut sent = 0u64;
        if !p.words.is_empty() {
            p.staging.ensure(gpu, p.words.len() * 4, 1.25)?;
            send(gpu, &p.staging, &p.words, &mut sent)?;
        }
        let o = &mut self.obj;
        if c.moved.is_some() {
            p.spare.ensure(gpu, n)?;
            let s = &p.spare;
            gpu.launch(
                n,
                KPatchGather {
                    n: n as u32,
                    runs: p.staging.ptr(),
                    nruns: runs as u32,
                    pos: o.pos.ptr(),
                    prev: o.prev.ptr(),
                    half: o.half.ptr(),
                    radius: o.radius.ptr(),
                    shape: o.shape.ptr(),
                    kind: o.kind.ptr(),
                    id: o.id.ptr(),
                    action: o.action.ptr(),
                    flags: o.flags.ptr(),
                    out_pos: s.pos.ptr(),
                    out_prev: s.prev.ptr(),
                    out_half: s.half.ptr(),
                    out_radius: s.radius.ptr(),
                    out_shape: s.shape.ptr(),
                    out_kind: s.kind.ptr(),
                    out_id: s.id.ptr(),
                    out_action: s.action.ptr(),
                    out_flags: s.flags.ptr(),
                },
            )?;
            p.spare.swap_with(o);
            size_derived(gpu, o, n)?;
            self.n = n;
        }
        let w = c.written.len();
        gpu.launch(
            w,
            KPatchScatter {
                w: w as u32,
                staged: p.staging.ptr().add(RUN_WORDS * runs),
                n: n as u32,
                pos: o.pos.ptr(),
                prev: o.prev.ptr(),
                half: o.half.ptr(),
                radius: o.radius.ptr(),
                shape: o.shape.ptr(),
                kind: o.kind.ptr(),
                id: o.id.ptr(),
                action: o.action.ptr(),
                flags: o.flags.ptr(),
            },
        )?;
        if c.actions {
            send(gpu, &o.action, d.actions(), &mut sent)?;
        }
        // Boxes follow positions and slots: stale unless only actions changed (as on
        // the full path). So does the tree: moved slots mean other objects in its leaves,
        // and written states put objects anywhere.
        if c.moved.is_some() || w > 0 {
            self.boxes_fresh = None;
            self.tree_age = None;
        }
        Ok(Some(sent))
    }
}

#[cfg(test)]
#[path = "patch_tests.rs"]
mod tests;
