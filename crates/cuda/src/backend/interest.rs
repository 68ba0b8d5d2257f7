//! Interest selection on the device (`kernels/interest.cu`): the AOI lists stay on the
//! device, a kernel picks each player's records by the host interest manager's rule, and
//! the host downloads only the picked slots (at most the budget a player) instead of
//! every list.
//!
//! Each player's staleness (the tick each object in view was last sent) lives on the
//! device too, in one open-addressing table per player, double-buffered: a selection
//! reads the tables of the previous selection (found through each player's index in it)
//! and writes new ones; [`CudaBackend::stamp_interest`] then marks what the host packed.

use myriad_core::{Aabb, World};
use myriad_physics::PhysicsError;

use super::CudaBackend;
use crate::device::{DevBuf, Pinned};
use crate::launch::{KInterestCompact, KInterestCounts, KInterestSelect, KInterestStamp};

/// The most records one selected group can hold (`SEL_SORT` in the kernel): the
/// kernel sorts each group in shared memory.
pub const MAX_SELECTED: usize = 1024;

/// `prev` entry of a player absent from the previous selection.
pub const NO_PREVIOUS: u32 = u32::MAX;

/// What [`CudaBackend::select_interest`] needs, one entry per player in each slice.
#[derive(Debug, Clone, Copy)]
pub struct InterestQuery<'a> {
    /// The tick being built (staleness keys are ticks).
    pub tick: u64,
    /// Each player's area of interest.
    pub boxes: &'a [Aabb],
    /// Slot of each player's own object (an invalid slot: no own object).
    pub own: &'a [u32],
    /// Centre of each player's updates (the origin records are quantized against).
    pub centres: &'a [[f32; 3]],
    /// Each player's index in the previous selection, or [`NO_PREVIOUS`]: its staleness
    /// is read from there.
    pub prev: &'a [u32],
    /// Most update datagrams a player.
    pub max_datagrams: u32,
    /// `K`: records for the nearest objects when over budget.
    pub near_slots: u32,
    /// `R`: records for the stalest objects when over budget.
    pub rotation_slots: u32,
    /// Most slots chosen for one player (at least `K + R`, and at least what fits its
    /// datagrams without an own object; at most [`MAX_SELECTED`]).
    pub capacity: u32,
}

/// One player's selection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Selected<'a> {
    /// The slots to pack, in order.
    pub slots: &'a [u32],
    /// Objects in view, own excluded.
    pub in_view: u32,
    /// Whether the view was over budget (the slots are then the nearest group, then the
    /// stalest group).
    pub over_budget: bool,
}

/// The selections of one [`CudaBackend::select_interest`], in pinned host memory: player
/// `i`'s slots are `slots[offsets[i]..offsets[i + 1]]`.
#[derive(Debug, Clone, Copy)]
pub struct Selections<'a> {
    meta: &'a [u32],
    offsets: &'a [u32],
    slots: &'a [u32],
}

impl<'a> Selections<'a> {
    /// Number of players.
    pub fn len(&self) -> usize {
        self.meta.len() / 4
    }

    /// Whether there is no player.
    pub fn is_empty(&self) -> bool {
        self.meta.is_empty()
    }

    /// Player `i`'s selection.
    pub fn get(&self, i: usize) -> Option<Selected<'a>> {
        let m = self.meta.get(4 * i..4 * i + 4)?;
        let (start, end) = (*self.offsets.get(i)? as usize, *self.offsets.get(i + 1)? as usize);
        let slots = self.slots.get(start..end)?;
        Some(Selected { slots, in_view: m[1], over_budget: m[2] != 0 })
    }
}

/// One generation of staleness tables.
struct Tables {
    /// Each player's table starts at twice its list's offset (`nq + 1` entries).
    offsets: DevBuf<u32>,
    /// Object id plus one (0: empty).
    ids: DevBuf<u64>,
    /// The tick the object was last sent.
    keys: DevBuf<u64>,
    /// Whether the player kept a table (it was over budget).
    kept: DevBuf<u8>,
}

impl Tables {
    fn new() -> Tables {
        Tables { offsets: DevBuf::empty(), ids: DevBuf::empty(), keys: DevBuf::empty(), kept: DevBuf::empty() }
    }
}

/// The device state of interest selection.
pub(super) struct InterestState {
    tables: [Tables; 2],
    /// Index of the tables the last successful selection wrote.
    current: usize,
    own: DevBuf<u32>,
    centres: DevBuf<f32>,
    prev: DevBuf<u32>,
    dist: DevBuf<u32>,
    ids: DevBuf<u32>,
    flags: DevBuf<u8>,
    keys: DevBuf<u64>,
    meta: DevBuf<u32>,
    sel: DevBuf<u32>,
    /// Each player's start in `compact` (`nq + 1`).
    offsets: DevBuf<u32>,
    /// The selections one after the other, for the download.
    compact: DevBuf<u32>,
    packed: DevBuf<u32>,
    host_meta: Pinned,
    host_offsets: Pinned,
    host_sel: Pinned,
    /// (players, capacity, tick) of the last successful selection, for the stamp.
    last: Option<(usize, usize, u64)>,
    /// The tick whose selection wrote `tables[current]`, if one did and nothing failed
    /// since: only then may a selection read them.
    tables_tick: Option<u64>,
}

impl InterestState {
    pub fn new() -> InterestState {
        InterestState {
            tables: [Tables::new(), Tables::new()],
            current: 0,
            own: DevBuf::empty(),
            centres: DevBuf::empty(),
            prev: DevBuf::empty(),
            dist: DevBuf::empty(),
            ids: DevBuf::empty(),
            flags: DevBuf::empty(),
            keys: DevBuf::empty(),
            meta: DevBuf::empty(),
            sel: DevBuf::empty(),
            offsets: DevBuf::empty(),
            compact: DevBuf::empty(),
            packed: DevBuf::empty(),
            host_meta: Pinned::empty(),
            host_offsets: Pinned::empty(),
            host_sel: Pinned::empty(),
            last: None,
            tables_tick: None,
        }
    }
}

impl CudaBackend {
    /// Selects each player's records for this tick on the device (see the module docs
    /// and `kernels/interest.cu`). The AOI lists never leave the device; what comes back
    /// is at most `capacity` slots a player.
    ///
    /// Every `prev` index must refer to the previous successful selection; after an
    /// error, pass [`NO_PREVIOUS`] for everyone.
    pub fn select_interest(&mut self, world: &World, q: &InterestQuery<'_>) -> Result<Selections<'_>, PhysicsError> {
        let r = self.select_impl(world, q);
        if r.is_err() {
            self.synced = None;
            self.n = usize::MAX;
            self.interest.last = None;
            self.interest.tables_tick = None;
        }
        r?;
        let s = &self.interest;
        let (nq, _, _) = s.last.unwrap_or((0, 0, 0));
        let offsets = if nq == 0 { &[][..] } else { s.host_offsets.slice::<u32>(nq + 1) };
        let total = offsets.last().map_or(0, |&t| t as usize);
        Ok(Selections { meta: s.host_meta.slice::<u32>(nq * 4), offsets, slots: s.host_sel.slice::<u32>(total) })
    }

    fn select_impl(&mut self, world: &World, q: &InterestQuery<'_>) -> Result<(), PhysicsError> {
        let nq = q.boxes.len();
        let cap = q.capacity as usize;
        if q.own.len() != nq || q.centres.len() != nq || q.prev.len() != nq {
            return Err(PhysicsError::Device { stage: "interest", message: "query slices differ in length".into() });
        }
        if cap == 0 || cap > MAX_SELECTED || q.near_slots as usize > cap || q.rotation_slots as usize > cap {
            return Err(PhysicsError::Device {
                stage: "interest",
                message: format!("a budget of {cap} records is outside 1..={MAX_SELECTED}"),
            });
        }
        self.interest.last = None;
        // Unsorted lists: the selection does not depend on their order.
        let (total, parts) = self.aoi_on_device(world, q.boxes, false)?;
        let gpu = &self.gpu;
        let s = &mut self.interest;
        s.host_meta.ensure(gpu, nq * 16)?;
        s.host_offsets.ensure(gpu, (nq + 1) * 4)?;
        if nq == 0 {
            s.last = Some((0, cap, q.tick));
            return Ok(());
        }
        s.meta.ensure(gpu, nq * 16, 1.25)?;
        if self.n == 0 {
            // No object at all: nothing to select and no staleness to keep.
            s.offsets.ensure(gpu, (nq + 1) * 4, 1.25)?;
            gpu.zero(s.meta.ptr(), nq * 4)?;
            gpu.zero(s.offsets.ptr(), nq + 1)?;
            gpu.download_async(&mut s.host_meta, 0, s.meta.ptr(), nq * 4)?;
            gpu.download_async(&mut s.host_offsets, 0, s.offsets.ptr(), nq + 1)?;
            gpu.sync()?;
            s.last = Some((nq, cap, q.tick));
            s.tables_tick = None;
            return Ok(());
        }
        let next = 1 - s.current;
        let total = total.max(1);
        s.own.ensure(gpu, nq * 4, 1.25)?;
        s.centres.ensure(gpu, nq * 12, 1.25)?;
        s.prev.ensure(gpu, nq * 4, 1.25)?;
        s.dist.ensure(gpu, total * 4, 1.25)?;
        s.ids.ensure(gpu, total * 4, 1.25)?;
        s.flags.ensure(gpu, total, 1.25)?;
        s.keys.ensure(gpu, total * 8, 1.25)?;
        s.sel.ensure(gpu, nq * cap * 4, 1.25)?;
        s.offsets.ensure(gpu, (nq + 1) * 4, 1.25)?;
        let t = &mut s.tables[next];
        t.offsets.ensure(gpu, (nq + 1) * 4, 1.25)?;
        t.ids.ensure(gpu, 2 * total * 8, 1.25)?;
        t.keys.ensure(gpu, 2 * total * 8, 1.25)?;
        t.kept.ensure(gpu, nq, 1.25)?;
        gpu.zero(t.ids.ptr(), 2 * total)?;
        gpu.upload(&s.own, q.own)?;
        gpu.upload(&s.centres, q.centres.as_flattened())?;
        // Staleness is read only from the tables of the previous tick's selection (a
        // player missing a tick starts afresh, as on the host).
        if q.tick.checked_sub(1).is_some_and(|t| s.tables_tick == Some(t)) {
            gpu.upload(&s.prev, q.prev)?;
        } else {
            gpu.upload(&s.prev, &vec![NO_PREVIOUS; nq])?;
        }
        let (p, t) = (&s.tables[s.current], &s.tables[next]);
        gpu.launch_grid(
            nq as u32,
            256,
            KInterestSelect {
                nq: nq as u32,
                offsets: self.aoi_counts.ptr(),
                parts: parts as u32,
                objects: self.aoi_out.ptr(),
                n: self.n as u32,
                pos: self.obj.pos.ptr(),
                ids: self.obj.id.ptr(),
                own: s.own.ptr(),
                centres: s.centres.ptr(),
                prev_index: s.prev.ptr(),
                prev_toff: p.offsets.ptr(),
                prev_tid: p.ids.ptr(),
                prev_tkey: p.keys.ptr(),
                prev_rot: p.kept.ptr(),
                next_toff: t.offsets.ptr(),
                next_tid: t.ids.ptr(),
                next_tkey: t.keys.ptr(),
                next_rot: t.kept.ptr(),
                cdist: s.dist.ptr(),
                cid: s.ids.ptr(),
                cflag: s.flags.ptr(),
                ckey: s.keys.ptr(),
                tick: q.tick,
                max_datagrams: q.max_datagrams,
                near_slots: q.near_slots,
                rotation_slots: q.rotation_slots,
                cap: q.capacity,
                meta: s.meta.ptr(),
                sel: s.sel.ptr(),
            },
        )?;
        // What was chosen, packed: the counts' scan gives each player its start.
        gpu.launch(
            nq + 1,
            KInterestCounts { nq: nq as u32, meta: s.meta.ptr(), cap: q.capacity, counts: s.offsets.ptr() },
        )?;
        self.scan.exclusive(gpu, s.offsets.ptr(), nq + 1)?;
        gpu.download_async(&mut s.host_meta, 0, s.meta.ptr(), nq * 4)?;
        gpu.download_async(&mut s.host_offsets, 0, s.offsets.ptr(), nq + 1)?;
        gpu.sync()?;
        let total = s.host_offsets.slice::<u32>(nq + 1)[nq] as usize;
        s.compact.ensure(gpu, total.max(1) * 4, 1.25)?;
        s.host_sel.ensure(gpu, total.max(1) * 4)?;
        gpu.launch_grid(
            nq as u32,
            256,
            KInterestCompact {
                nq: nq as u32,
                meta: s.meta.ptr(),
                sel: s.sel.ptr(),
                cap: q.capacity,
                offsets: s.offsets.ptr(),
                out: s.compact.ptr(),
            },
        )?;
        gpu.download_async(&mut s.host_sel, 0, s.compact.ptr(), total)?;
        gpu.sync()?;
        gpu.collect_profile()?;
        s.current = next;
        s.last = Some((nq, cap, q.tick));
        s.tables_tick = Some(q.tick);
        Ok(())
    }

    /// Marks, in the tables of the last selection, the first `packed[i]` selected records
    /// of each over-budget player `i` as sent at its tick: what the host actually packed
    /// (a budget with extended records can take fewer than were selected). Queued on the
    /// stream; nothing waits for it.
    pub fn stamp_interest(&mut self, packed: &[u32]) -> Result<(), PhysicsError> {
        let Some((nq, cap, tick)) = self.interest.last else { return Ok(()) };
        if packed.len() != nq {
            return Err(PhysicsError::Device {
                stage: "interest",
                message: format!("{} packed counts for {nq} players", packed.len()),
            });
        }
        if nq == 0 {
            return Ok(());
        }
        let gpu = &self.gpu;
        let s = &mut self.interest;
        s.packed.ensure(gpu, nq * 4, 1.25)?;
        gpu.upload(&s.packed, packed)?;
        let t = &s.tables[s.current];
        gpu.launch_grid(
            nq as u32,
            256,
            KInterestStamp {
                nq: nq as u32,
                meta: s.meta.ptr(),
                sel: s.sel.ptr(),
                cap: cap as u32,
                packed: s.packed.ptr(),
                ids: self.obj.id.ptr(),
                toff: t.offsets.ptr(),
                tid: t.ids.ptr(),
                tkey: t.keys.ptr(),
                tick,
            },
        )
    }
}
