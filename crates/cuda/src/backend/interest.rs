//! Interest selection and packing on the device (`kernels/interest.cu`): the AOI lists
//! stay on the device, a kernel picks each player's records by the host interest
//! manager's rule, another packs them into state update bodies byte for byte as the
//! host's `pack_updates_pinned` would, and the host downloads only the finished bodies,
//! to frame and seal them.
//!
//! Each player's staleness (the tick each object in view was last sent) lives on the
//! device too, in one open-addressing table per player, double-buffered: a selection
//! reads the tables of the previous selection (found through each player's index in it)
//! and writes new ones, and marks what was packed as sent this tick.

use myriad_core::{Aabb, World};
use myriad_physics::PhysicsError;
use myriad_protocol::MAX_BODY;

use super::CudaBackend;
use crate::device::{DevBuf, Pinned};
use crate::launch::{KInterestBodies, KInterestPack, KInterestSelect, KInterestStamp};

/// The most records one selected group can hold (`SEL_SORT` in the kernel): the
/// kernel sorts each group in shared memory.
pub const MAX_SELECTED: usize = 1024;

/// The most update datagrams a player the device packs (`MAX_PACK_DATAGRAMS` in the
/// kernel): [`MAX_SELECTED`] records at 113 a datagram.
pub const MAX_PACK_DATAGRAMS: usize = 9;

/// Players (one warp each) per block of `k_interest_pack`.
const PACK_WARPS: usize = 4;

/// `prev` entry of a player absent from the previous selection.
pub const NO_PREVIOUS: u32 = u32::MAX;

/// What [`CudaBackend::interest_updates`] needs, one entry per player in each slice.
#[derive(Debug, Clone, Copy)]
pub struct InterestQuery<'a> {
    /// The tick being built (staleness keys are ticks; the updates carry it).
    pub tick: u64,
    /// Time dilation in 1/1000, carried by the updates.
    pub dilation_permille: u16,
    /// Each player's area of interest.
    pub boxes: &'a [Aabb],
    /// Slot of each player's own object (an invalid slot: no own object).
    pub own: &'a [u32],
    /// Centre of each player's updates (the origin records are quantized against).
    pub centres: &'a [[f32; 3]],
    /// Each player's index in the previous selection, or [`NO_PREVIOUS`]: its staleness
    /// is read from there.
    pub prev: &'a [u32],
    /// Most update datagrams a player (1 to [`MAX_PACK_DATAGRAMS`]).
    pub max_datagrams: u32,
    /// `K`: records for the nearest objects when over budget.
    pub near_slots: u32,
    /// `R`: records for the stalest objects when over budget.
    pub rotation_slots: u32,
    /// Most slots chosen for one player (at least `K + R`, and at least what fits its
    /// datagrams without an own object; at most [`MAX_SELECTED`]).
    pub capacity: u32,
}

/// One player's updates, as packed on the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Payload<'a> {
    /// Objects in view, own excluded.
    pub in_view: u32,
    /// Whether the view was over budget (the records are then the nearest, then the
    /// stalest).
    pub over_budget: bool,
    /// Whether the player's own object is pinned at the start of every datagram.
    pub pinned: bool,
    /// Records of other objects packed.
    pub packed: u32,
    lens: &'a [u32],
    bytes: &'a [u8],
}

impl<'a> Payload<'a> {
    /// The state update bodies, one a datagram, in order (frame and seal each with
    /// `myriad_protocol::push_update_body` and a sealer).
    pub fn bodies(&self) -> impl Iterator<Item = &'a [u8]> + use<'a> {
        let bytes = self.bytes;
        self.lens.iter().scan(0usize, move |at, &len| {
            let body = bytes.get(*at..*at + len as usize)?;
            *at += len as usize;
            Some(body)
        })
    }
}

/// The updates of one [`CudaBackend::interest_updates`], in pinned host memory.
#[derive(Debug, Clone, Copy)]
pub struct Payloads<'a> {
    /// Per player: in view, flags (over budget, pinned << 1), packed, datagrams.
    info: &'a [u32],
    /// Per player, `max_datagrams` body lengths.
    lens: &'a [u32],
    /// Each player's start in `bytes` (`players + 1`).
    offsets: &'a [u32],
    bytes: &'a [u8],
    max_datagrams: usize,
}

impl<'a> Payloads<'a> {
    /// Number of players.
    pub fn len(&self) -> usize {
        self.info.len() / 4
    }

    /// Whether there is no player.
    pub fn is_empty(&self) -> bool {
        self.info.is_empty()
    }

    /// Player `i`'s updates; `None` past the end or if the device's counts disagree
    /// (its lengths do not add up to its share of the bytes).
    pub fn get(&self, i: usize) -> Option<Payload<'a>> {
        let m = self.info.get(4 * i..4 * i + 4)?;
        let datagrams = (m[3] as usize).min(self.max_datagrams);
        let lens = self.lens.get(i * self.max_datagrams..i * self.max_datagrams + datagrams)?;
        let (start, end) = (*self.offsets.get(i)? as usize, *self.offsets.get(i + 1)? as usize);
        let bytes = self.bytes.get(start..end)?;
        if lens.iter().map(|&l| l as usize).sum::<usize>() != bytes.len() {
            return None;
        }
        Some(Payload { in_view: m[0], over_budget: m[1] & 1 != 0, pinned: m[1] & 2 != 0, packed: m[2], lens, bytes })
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
    /// Each player's `max_datagrams` bodies of `MAX_BODY` bytes, and their lengths.
    bodies: DevBuf<u8>,
    lens: DevBuf<u32>,
    /// What the host needs of each player besides the bytes (see [`Payloads`]).
    info: DevBuf<u32>,
    /// Each player's bytes, then by the scan its start in `out` (`nq + 1`).
    offsets: DevBuf<u32>,
    /// The bodies one after the other, for the download.
    out: DevBuf<u8>,
    /// Records packed per player, for the stamp.
    packed: DevBuf<u32>,
    host_info: Pinned,
    host_lens: Pinned,
    host_offsets: Pinned,
    host_out: Pinned,
    /// (players, max datagrams) of the last successful build.
    last: Option<(usize, usize)>,
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
            bodies: DevBuf::empty(),
            lens: DevBuf::empty(),
            info: DevBuf::empty(),
            offsets: DevBuf::empty(),
            out: DevBuf::empty(),
            packed: DevBuf::empty(),
            host_info: Pinned::empty(),
            host_lens: Pinned::empty(),
            host_offsets: Pinned::empty(),
            host_out: Pinned::empty(),
            last: None,
            tables_tick: None,
        }
    }
}

impl CudaBackend {
    /// Selects and packs each player's state updates for this tick on the device (see
    /// the module docs and `kernels/interest.cu`). The AOI lists and the selections never
    /// leave the device; what comes back is the finished bodies.
    ///
    /// Every `prev` index must refer to the previous successful build; after an error,
    /// pass [`NO_PREVIOUS`] for everyone.
    pub fn interest_updates(&mut self, world: &World, q: &InterestQuery<'_>) -> Result<Payloads<'_>, PhysicsError> {
        let r = self.updates_impl(world, q);
        if r.is_err() {
            self.synced = None;
            self.n = usize::MAX;
            self.interest.last = None;
            self.interest.tables_tick = None;
        }
        r?;
        let s = &self.interest;
        let (nq, mdg) = s.last.unwrap_or((0, 1));
        let offsets = if nq == 0 { &[][..] } else { s.host_offsets.slice::<u32>(nq + 1) };
        let total = offsets.last().map_or(0, |&t| t as usize);
        Ok(Payloads {
            info: s.host_info.slice::<u32>(nq * 4),
            lens: s.host_lens.slice::<u32>(nq * mdg),
            offsets,
            bytes: s.host_out.slice::<u8>(total),
            max_datagrams: mdg,
        })
    }

    fn updates_impl(&mut self, world: &World, q: &InterestQuery<'_>) -> Result<(), PhysicsError> {
        let nq = q.boxes.len();
        let cap = q.capacity as usize;
        let mdg = q.max_datagrams as usize;
        let fail = |message: String| Err(PhysicsError::Device { stage: "interest", message });
        if q.own.len() != nq || q.centres.len() != nq || q.prev.len() != nq {
            return fail("query slices differ in length".into());
        }
        if cap == 0 || cap > MAX_SELECTED || q.near_slots as usize > cap || q.rotation_slots as usize > cap {
            return fail(format!("a budget of {cap} records is outside 1..={MAX_SELECTED}"));
        }
        if !(1..=MAX_PACK_DATAGRAMS).contains(&mdg) {
            return fail(format!("{mdg} datagrams a player is outside 1..={MAX_PACK_DATAGRAMS}"));
        }
        self.interest.last = None;
        // Unsorted lists: the selection does not depend on their order.
        let (total, parts) = self.aoi_on_device(world, q.boxes, false)?;
        let gpu = &self.gpu;
        let s = &mut self.interest;
        s.host_info.ensure(gpu, nq * 16)?;
        s.host_lens.ensure(gpu, nq * mdg * 4)?;
        s.host_offsets.ensure(gpu, (nq + 1) * 4)?;
        if nq == 0 {
            s.last = Some((0, mdg));
            return Ok(());
        }
        if self.n == 0 {
            // No object at all: no update and no staleness to keep.
            s.host_info.slice_mut::<u32>(nq * 4).fill(0);
            s.host_lens.slice_mut::<u32>(nq * mdg).fill(0);
            s.host_offsets.slice_mut::<u32>(nq + 1).fill(0);
            s.last = Some((nq, mdg));
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
        s.meta.ensure(gpu, nq * 16, 1.25)?;
        s.sel.ensure(gpu, nq * cap * 4, 1.25)?;
        s.bodies.ensure(gpu, nq * mdg * MAX_BODY, 1.25)?;
        s.lens.ensure(gpu, nq * mdg * 4, 1.25)?;
        s.info.ensure(gpu, nq * 16, 1.25)?;
        s.offsets.ensure(gpu, (nq + 1) * 4, 1.25)?;
        s.packed.ensure(gpu, nq * 4, 1.25)?;
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
        gpu.launch_grid(
            nq.div_ceil(PACK_WARPS) as u32,
            32 * PACK_WARPS as u32,
            KInterestPack {
                nq: nq as u32,
                meta: s.meta.ptr(),
                sel: s.sel.ptr(),
                cap: q.capacity,
                n: self.n as u32,
                pos: self.obj.pos.ptr(),
                ids: self.obj.id.ptr(),
                shapes: self.obj.shape.ptr(),
                own: s.own.ptr(),
                centres: s.centres.ptr(),
                tick: q.tick,
                dilation: u32::from(q.dilation_permille),
                max_datagrams: q.max_datagrams,
                bodies: s.bodies.ptr(),
                lens: s.lens.ptr(),
                info: s.info.ptr(),
                totals: s.offsets.ptr(),
                packed: s.packed.ptr(),
            },
        )?;
        // What was packed is what was sent: the new tables' keys of those become `tick`.
        gpu.launch_grid(
            nq as u32,
            256,
            KInterestStamp {
                nq: nq as u32,
                meta: s.meta.ptr(),
                sel: s.sel.ptr(),
                cap: q.capacity,
                packed: s.packed.ptr(),
                ids: self.obj.id.ptr(),
                toff: t.offsets.ptr(),
                tid: t.ids.ptr(),
                tkey: t.keys.ptr(),
                tick: q.tick,
            },
        )?;
        // The players' byte counts' scan gives each its start in the download.
        self.scan.exclusive(gpu, s.offsets.ptr(), nq + 1)?;
        gpu.download_async(&mut s.host_info, 0, s.info.ptr(), nq * 4)?;
        gpu.download_async(&mut s.host_lens, 0, s.lens.ptr(), nq * mdg)?;
        gpu.download_async(&mut s.host_offsets, 0, s.offsets.ptr(), nq + 1)?;
        gpu.sync()?;
        let bytes = s.host_offsets.slice::<u32>(nq + 1)[nq] as usize;
        s.out.ensure(gpu, bytes.max(1), 1.25)?;
        s.host_out.ensure(gpu, bytes.max(1))?;
        gpu.launch_grid(
            nq as u32,
            256,
            KInterestBodies {
                nq: nq as u32,
                max_datagrams: q.max_datagrams,
                bodies: s.bodies.ptr(),
                lens: s.lens.ptr(),
                offsets: s.offsets.ptr(),
                out: s.out.ptr(),
            },
        )?;
        gpu.download_async(&mut s.host_out, 0, s.out.ptr(), bytes)?;
        gpu.sync()?;
        gpu.collect_profile()?;
        s.current = next;
        s.last = Some((nq, mdg));
        s.tables_tick = Some(q.tick);
        Ok(())
    }
}
