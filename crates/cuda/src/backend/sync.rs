//! The device copies of the world, what the host downloads into, and the upload of
//! whatever the host changed since the device last saw the world.

use bytemuck::Pod;
use myriad_core::{Vec3, World};
use myriad_physics::lbvh::morton::MortonFrame;
use myriad_physics::{BackendKind, PhysicsError, TickConstants};
use rayon::prelude::*;

use super::broad::SLOTS;
use super::tree::Leaves;
use super::{Resident, Synced};
use crate::device::{DevBuf, Gpu, Pinned};
use crate::launch::KBoxes;
use crate::params::DeviceParams;

/// The most objects (or primitives) a tree can hold: leaf indices carry a flag in their
/// top bit.
const LEAF_LIMIT: usize = (1 << 31) - 1;

/// Per-object device state.
/// Vectors are packed floats (x, y, z), boxes six floats (min, max); enums are one byte.
pub(crate) struct Objects {
    /// Positions, the state the kernels advance.
    pub pos: DevBuf<f32>,
    /// Positions one tick earlier (velocity is `pos - prev`).
    pub prev: DevBuf<f32>,
    /// Half extents of each shape's box.
    pub half: DevBuf<f32>,
    /// Sphere and capsule radii.
    pub radius: DevBuf<f32>,
    /// `ShapeKind` discriminants.
    pub shape: DevBuf<u8>,
    /// `ObjectKind` discriminants (NPC or user).
    pub kind: DevBuf<u8>,
    /// Object ids (they seed the NPCs' random numbers).
    pub id: DevBuf<u32>,
    /// Action bits (held directions, jump).
    pub action: DevBuf<u8>,
    /// Flag bits (on terrain, supported).
    pub flags: DevBuf<u8>,
    /// Boxes at the current positions, built each step.
    pub boxes: DevBuf<f32>,
    /// The narrow phase's summed responses, read by the forces.
    pub acc: DevBuf<f32>,
    /// Whether a contact supports the object from below.
    pub sup: DevBuf<u8>,
    /// Static pair counts, then (after the scan) each object's range start; `n + 1`.
    pub static_counts: DevBuf<u32>,
    /// As `static_counts`, for the dynamic pairs.
    pub dynamic_counts: DevBuf<u32>,
    /// The count passes' kept targets, `SLOTS` an object.
    pub static_keep: DevBuf<u32>,
    /// As `static_keep`, for the dynamic pairs.
    pub dynamic_keep: DevBuf<u32>,
}

impl Objects {
    /// Nothing allocated yet: the first sync sizes every buffer.
    pub fn new() -> Objects {
        Objects {
            pos: DevBuf::empty(),
            prev: DevBuf::empty(),
            half: DevBuf::empty(),
            radius: DevBuf::empty(),
            shape: DevBuf::empty(),
            kind: DevBuf::empty(),
            id: DevBuf::empty(),
            action: DevBuf::empty(),
            flags: DevBuf::empty(),
            boxes: DevBuf::empty(),
            acc: DevBuf::empty(),
            sup: DevBuf::empty(),
            static_counts: DevBuf::empty(),
            dynamic_counts: DevBuf::empty(),
            static_keep: DevBuf::empty(),
            dynamic_keep: DevBuf::empty(),
        }
    }
}

/// Static primitives on the device.
pub(super) struct Prims {
    /// Centres, packed floats.
    pub pos: DevBuf<f32>,
    /// Half extents, packed floats.
    pub half: DevBuf<f32>,
    /// Radii.
    pub radius: DevBuf<f32>,
    /// `ShapeKind` discriminants.
    pub shape: DevBuf<u8>,
    /// Boxes, built when the statics are uploaded.
    pub boxes: DevBuf<f32>,
    /// How many primitives are on the device.
    pub count: usize,
}

impl Prims {
    /// No primitives yet.
    pub fn new() -> Prims {
        Prims {
            pos: DevBuf::empty(),
            half: DevBuf::empty(),
            radius: DevBuf::empty(),
            shape: DevBuf::empty(),
            boxes: DevBuf::empty(),
            count: 0,
        }
    }
}

/// Pinned host buffers for what comes back each step.
pub(super) struct Host {
    /// New positions.
    pub pos: Pinned,
    /// New previous positions.
    pub prev: Pinned,
    /// New actions.
    pub action: Pinned,
    /// New flags.
    pub flags: Pinned,
    /// The contact counts and pair totals: read first, to decide whether to redo.
    pub small: Pinned,
    /// AOI range starts, one per query plus the total.
    pub aoi_offsets: Pinned,
    /// AOI results, the objects of every query.
    pub aoi_objects: Pinned,
    /// The AOI query boxes, six floats each, on their way up.
    pub aoi_boxes: Pinned,
    /// The order the grid's warps take the boxes in, on its way up.
    pub aoi_order: Pinned,
    /// The slots of a gather of some positions (`held`), read by its kernel in place.
    pub gather_slots: Pinned,
    /// The gathered positions, written by the kernel in place.
    pub gather_pos: Pinned,
}

/// The vectors as packed floats (x, y, z, x, ...), without copying (glam's `Vec3` is
/// `#[repr(C)]` of three `f32` and `Pod`).
pub(super) fn flat3(v: &[Vec3]) -> &[f32] {
    bytemuck::cast_slice(v)
}

/// [`flat3`] for writing.
pub(super) fn flat3_mut(v: &mut [Vec3]) -> &mut [f32] {
    bytemuck::cast_slice_mut(v)
}

/// `dst.copy_from_slice(src)`, on rayon's pool for large arrays: copying the state out
/// of pinned memory into the `World` is the largest host cost of a step, and one core's
/// memcpy bandwidth is a fraction of what the machine has.
pub(super) fn par_copy<T: Copy + Send + Sync>(dst: &mut [T], src: &[T]) {
    const CHUNK: usize = 1 << 16;
    if dst.len() < 4 * CHUNK {
        dst.copy_from_slice(src);
    } else {
        dst.par_chunks_mut(CHUNK).zip(src.par_chunks(CHUNK)).for_each(|(d, s)| d.copy_from_slice(s));
    }
}

/// [`Gpu::upload`], adding the bytes sent to `sent`.
pub(super) fn send<T: Pod>(gpu: &Gpu, dst: &DevBuf<T>, src: &[T], sent: &mut u64) -> Result<(), PhysicsError> {
    gpu.upload(dst, src)?;
    *sent += std::mem::size_of_val(src) as u64;
    Ok(())
}

/// Sizes the per-step buffers (boxes, responses, pair counts and kept targets, support
/// bits) for `n` objects; their contents are rebuilt by every step.
pub(super) fn size_derived(gpu: &Gpu, o: &mut Objects, n: usize) -> Result<(), PhysicsError> {
    for b in [&mut o.boxes, &mut o.acc] {
        b.ensure(gpu, n * 24, 1.25)?;
    }
    for b in [&mut o.static_counts, &mut o.dynamic_counts] {
        b.ensure(gpu, (n + 1) * 4, 1.25)?;
    }
    for b in [&mut o.static_keep, &mut o.dynamic_keep] {
        b.ensure(gpu, n * SLOTS as usize * 4, 1.25)?;
    }
    o.sup.ensure(gpu, n, 1.25)?;
    Ok(())
}

impl Resident {
    /// Uploads whatever the host changed since the device last saw the world; returns
    /// the bytes sent. A device copy made right after the last step, of a world whose
    /// every change since is recorded, gets only those changes (`patch`); otherwise
    /// what the generation counters say changed travels whole.
    pub(super) fn sync_world(&mut self, world: &World, k: Option<&TickConstants>) -> Result<u64, PhysicsError> {
        let d = &world.dynamics;
        let n = d.len();
        if n > LEAF_LIMIT {
            return Err(PhysicsError::TooManyObjects { count: n, max: LEAF_LIMIT });
        }
        let now = Synced::of(world);
        let mut sent = 0u64;
        let patched = match d.changes() {
            Some(c) if self.synced != Some(now) || self.n != n => self.patch(world, c)?,
            _ => None,
        };
        let gpu = &self.gpu;
        let o = &mut self.obj;
        if let Some(bytes) = patched {
            sent += bytes;
        } else {
            if self.synced.map(|s| (s.layout, s.identity)) != Some((now.layout, now.identity)) || self.n != n {
                // Objects came or went: slots changed meaning, upload everything.
                for b in [&mut o.pos, &mut o.prev, &mut o.half] {
                    b.ensure(gpu, n * 12, 1.25)?;
                }
                o.radius.ensure(gpu, n * 4, 1.25)?;
                o.id.ensure(gpu, n * 4, 1.25)?;
                for b in [&mut o.shape, &mut o.kind, &mut o.action, &mut o.flags] {
                    b.ensure(gpu, n, 1.25)?;
                }
                size_derived(gpu, o, n)?;
                send(gpu, &o.half, flat3(d.half_extents()), &mut sent)?;
                send(gpu, &o.radius, d.radii(), &mut sent)?;
                send(gpu, &o.shape, &d.shapes().iter().map(|s| *s as u8).collect::<Vec<u8>>(), &mut sent)?;
                send(gpu, &o.kind, &d.kinds().iter().map(|s| *s as u8).collect::<Vec<u8>>(), &mut sent)?;
                send(gpu, &o.id, &d.ids().iter().map(|i| i.0).collect::<Vec<u32>>(), &mut sent)?;
                self.n = n;
                self.synced = None;
            }
            match self.synced {
                Some(s) if s.generation == now.generation => {}
                // Every change since the last sync was a `set_action` (a server's
                // players): only the actions travel, not the whole state.
                Some(s) if now.generation - s.generation == now.action_generation - s.action_generation => {
                    send(gpu, &o.action, d.actions(), &mut sent)?;
                }
                _ => {
                    send(gpu, &o.pos, flat3(d.positions()), &mut sent)?;
                    send(gpu, &o.prev, flat3(d.prev_positions()), &mut sent)?;
                    send(gpu, &o.action, d.actions(), &mut sent)?;
                    send(gpu, &o.flags, d.flags(), &mut sent)?;
                    self.boxes_fresh = None;
                    // Positions set from outside the physics (teleports) may put objects
                    // far from where the tree placed them, and after objects came or went
                    // (or `invalidate`) its leaves mean other objects: build it afresh.
                    self.tree_age = None;
                }
            }
        }
        self.synced = Some(now);

        let st = &world.statics;
        let key = (st.stamp(), st.generation());
        if self.statics_key != Some(key) {
            let m = st.prim_count();
            let p = &mut self.prims;
            for b in [&mut p.pos, &mut p.half] {
                b.ensure(gpu, m * 12, 1.25)?;
            }
            p.boxes.ensure(gpu, m * 24, 1.25)?;
            p.radius.ensure(gpu, m * 4, 1.25)?;
            p.shape.ensure(gpu, m, 1.25)?;
            send(gpu, &p.pos, flat3(st.positions()), &mut sent)?;
            send(gpu, &p.half, flat3(st.half_extents()), &mut sent)?;
            send(gpu, &p.radius, st.radii(), &mut sent)?;
            send(gpu, &p.shape, &st.shapes().iter().map(|s| *s as u8).collect::<Vec<u8>>(), &mut sent)?;
            p.count = m;
            if self.kind == BackendKind::CudaNaive {
                gpu.launch(m, KBoxes { n: m as u32, pos: p.pos.ptr(), half: p.half.ptr(), boxes: p.boxes.ptr() })?;
            } else {
                let frame = MortonFrame::new(&world.bounds);
                let leaves = Leaves { n: m, pos: p.pos.ptr(), half: p.half.ptr(), boxes: p.boxes.ptr() };
                self.static_tree.build(gpu, leaves, &frame)?;
            }
            self.statics_key = Some(key);
        }

        let samples = world.terrain.samples();
        let tkey = world.terrain.stamp();
        if self.terrain_key != Some(tkey) {
            self.samples.ensure(gpu, samples.len() * 2, 1.0)?;
            send(gpu, &self.samples, samples, &mut sent)?;
            self.terrain_key = Some(tkey);
        }
        if let Some(k) = k {
            let params = DeviceParams::new(world, k);
            if self.params_key != Some(params) {
                self.params.ensure(gpu, std::mem::size_of::<DeviceParams>(), 1.0)?;
                send(gpu, &self.params, std::slice::from_ref(&params), &mut sent)?;
                self.params_key = Some(params);
            }
        }
        Ok(sent)
    }
}
