//! Interest selection, packing and sealing on the device (`kernels/interest.cu`), in
//! datagram protocol version 1, which the server no longer sends (it awaits its port to
//! version 2; the server does not use it): the AOI lists stay on the device, a kernel
//! picks each player's records by version 1's rule (the K nearest, then the stalest),
//! another packs them into version 1's state update bodies, and a third frames and seals each datagram with
//! ChaCha20-Poly1305 (`kernels/aead.cuh`) under sequence numbers leased from the player's
//! sealer, as the host's `Sealer` would. The host receives only finished datagrams.
//!
//! Each player's staleness (the tick each object in view was last sent) lives on the
//! device too, in one open-addressing table per player, double-buffered: a selection
//! reads the tables of the previous selection (found through each player's index in it)
//! and writes new ones, and marks what was packed as sent this tick.
//!
//! The players are served in chunks, so that the host sends one chunk while the device
//! builds the next: [`DeviceInterest::queue`] queues every chunk's kernels at once, each
//! chunk ending with an event, and its datagrams reach the host through stores into
//! mapped host memory (no copy whose size the host would first have to read back);
//! [`DeviceInterest::chunks`] waits for chunks (`chunks.rs`) and
//! [`DeviceInterest::finish`] ends the tick.
//!
//! The session keys travel to the device in page-locked memory for the tick and are
//! wiped there and on the device when it ends.
//!
//! This is not physics: a [`DeviceInterest`] is a capability of a CUDA backend
//! ([`CudaBackend::device_interest`](crate::CudaBackend::device_interest), or the factory's
//! [`CreatedBackend::device_interest`](crate::CreatedBackend)) that shares the device and
//! the world's copy there with the backend (each call locks it; the backend and its
//! interest run one after the other on the tick's thread, so the lock is uncontended).

mod chunks;

use std::ops::Range;
use std::sync::atomic::AtomicU8;
use std::sync::{Arc, Mutex};

use cudarc::driver::safe::CudaContext;

use myriad_core::{Aabb, World};
use myriad_physics::PhysicsError;
use myriad_protocol::{MAX_BODY, MAX_DATAGRAM, SealLease};
use rayon::prelude::*;

use crate::backend::{Resident, lock};
use crate::device::{DevBuf, Event, Pinned};
use crate::launch::{KInterestPack, KInterestSeal, KInterestSelect, KInterestStamp, Kernel};
use chunks::CHUNK_QUEUED;
pub use chunks::{InterestChunks, Payload, Payloads};

/// The most records one selected group can hold (`SEL_SORT` in the kernel): the
/// kernel sorts each group in shared memory.
pub const MAX_SELECTED: usize = 1024;

/// The most update datagrams a player the device packs (`MAX_PACK_DATAGRAMS` in the
/// kernel): [`MAX_SELECTED`] records at 113 a datagram.
pub const MAX_PACK_DATAGRAMS: usize = 9;

/// Players (one warp each) per block of `k_interest_pack`.
const PACK_WARPS: usize = 4;

/// Threads per block (one player) of `k_interest_select` (`SEL_THREADS` in the kernel).
const SELECT_THREADS: u32 = 256;

/// Datagrams (one warp each) per block of `k_interest_seal`.
const SEAL_WARPS: usize = 4;

/// Bytes from one datagram to the next in the host's copy (`DATAGRAM_STRIDE` in the
/// kernel), a multiple of 16: the datagrams travel as 16-byte words.
pub const DATAGRAM_STRIDE: usize = MAX_DATAGRAM;
const _: () = assert!(DATAGRAM_STRIDE.is_multiple_of(16));

/// Words of one player's entry in the lease table: key (8), session id (2), first
/// sequence number (2).
const LEASE_WORDS: usize = 12;

/// `prev` entry of a player absent from the previous selection.
pub const NO_PREVIOUS: u32 = u32::MAX;

/// What [`DeviceInterest::queue`] needs, one entry per player in each
/// slice.
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
    /// The sequence numbers (at least `max_datagrams`) and key each player's datagrams
    /// are sealed with (`None`: the player gets no datagram).
    pub leases: &'a [Option<SealLease>],
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
struct InterestState {
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
    /// Records packed per player, for the stamp.
    packed: DevBuf<u32>,
    host_info: Pinned,
    host_lens: Pinned,
    /// The sealed datagrams, written by `k_interest_seal`.
    host_out: Pinned,
    /// The lease table (keys, session ids, first numbers), for the tick only.
    host_leases: Pinned,
    /// The query's own objects, centres and previous indices, on their way to the device.
    host_own: Pinned,
    host_centres: Pinned,
    host_prev: Pinned,
    leases: DevBuf<u32>,
    /// This tick's chunks of players, and one event each: recorded after the chunk's
    /// downloads.
    chunks: Vec<Range<usize>>,
    chunk_done: Vec<Event>,
    chunk_state: Vec<AtomicU8>,
    /// (players, max datagrams) of the queued tick.
    queued: (usize, usize),
    /// The tick whose selection wrote `tables[current]`, if one did and nothing failed
    /// since: only then may a selection read them.
    tables_tick: Option<u64>,
}

impl InterestState {
    fn new() -> InterestState {
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
            packed: DevBuf::empty(),
            host_info: Pinned::empty(),
            host_lens: Pinned::empty(),
            host_out: Pinned::empty(),
            host_leases: Pinned::empty(),
            host_own: Pinned::empty(),
            host_centres: Pinned::empty(),
            host_prev: Pinned::empty(),
            leases: DevBuf::empty(),
            chunks: Vec::new(),
            chunk_done: Vec::new(),
            chunk_state: Vec::new(),
            queued: (0, 1),
            tables_tick: None,
        }
    }
}

/// Interest selection, packing and sealing on a CUDA backend's device (module docs).
pub struct DeviceInterest {
    state: InterestState,
    /// The device's context, bound by the threads that wait for chunks.
    ctx: Arc<CudaContext>,
    /// Last: the device state it shares with the backend, which the buffers above belong
    /// to (fields drop in order).
    resident: Arc<Mutex<Resident>>,
}

impl std::fmt::Debug for DeviceInterest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DeviceInterest").field("chunks", &self.state.chunks).finish_non_exhaustive()
    }
}

impl DeviceInterest {
    /// Interest state of its own over `resident`, the backend's device state.
    pub(crate) fn new(resident: Arc<Mutex<Resident>>) -> DeviceInterest {
        let ctx = lock(&resident).gpu.ctx.clone();
        DeviceInterest { state: InterestState::new(), ctx, resident }
    }

    /// Queues the selection, packing and sealing of each player's state updates for this
    /// tick on the device (see the module docs and `kernels/interest.cu`), in chunks of
    /// `chunk` players (at least one); returns the number of chunks. Wait for them through
    /// [`chunks`](Self::chunks), in any order, then call [`finish`](Self::finish) (also
    /// after an error). The AOI lists and the selections never leave the device.
    ///
    /// Every `prev` index must refer to the previous complete build; after an error,
    /// pass [`NO_PREVIOUS`] for everyone.
    pub fn queue(&mut self, world: &World, q: &InterestQuery<'_>, chunk: usize) -> Result<usize, PhysicsError> {
        let s = &mut self.state;
        let mut resident = lock(&self.resident);
        let d = &mut *resident;
        s.chunks.clear();
        let r = s.queue(d, world, q, chunk.max(1));
        if r.is_err() {
            s.chunks.clear();
            s.failed(d);
        }
        r.map(|()| s.chunks.len())
    }

    /// The players the device selects at once (one block each, on every multiprocessor):
    /// chunks of a multiple of this keep the device busy to the end of each chunk.
    pub fn wave(&self) -> Result<usize, PhysicsError> {
        let d = lock(&self.resident);
        d.gpu.bind()?;
        d.gpu.wave(KInterestSelect::NAME, SELECT_THREADS)
    }

    /// The queued tick's chunks, to wait for and read, from any number of threads.
    pub fn chunks(&self) -> InterestChunks<'_> {
        let s = &self.state;
        InterestChunks {
            chunks: &s.chunks,
            done: &s.chunk_done,
            state: &s.chunk_state,
            info: &s.host_info,
            lens: &s.host_lens,
            out: &s.host_out,
            max_datagrams: s.queued.1,
            ctx: &self.ctx,
        }
    }

    /// Ends the queued tick: waits for the device, wipes the keys, and, when every
    /// chunk was taken (`complete`), makes the staleness tables it wrote the next tick's;
    /// otherwise the next tick starts afresh.
    pub fn finish(&mut self, tick: u64, complete: bool) -> Result<(), PhysicsError> {
        let s = &mut self.state;
        let mut resident = lock(&self.resident);
        let d = &mut *resident;
        let done = d.gpu.bind().and_then(|()| s.wipe_keys(d));
        if complete && done.is_ok() && !s.chunks.is_empty() && d.n > 0 {
            s.current = 1 - s.current;
            s.tables_tick = Some(tick);
        } else if !complete || done.is_err() {
            s.failed(d);
        }
        s.chunks.clear();
        done.and_then(|()| d.gpu.collect_profile())
    }
}

impl InterestState {
    /// After a failure: the device copy and the staleness tables start afresh.
    fn failed(&mut self, d: &mut Resident) {
        d.invalidate();
        self.tables_tick = None;
    }

    /// Waits for the stream, then zeroes the lease table on the host and on the device.
    fn wipe_keys(&mut self, d: &Resident) -> Result<(), PhysicsError> {
        let s = self;
        let words = s.queued.0 * LEASE_WORDS;
        // The stream may still read the host table (an error left work queued).
        let synced = d.gpu.sync();
        if s.host_leases.capacity_bytes() >= words * 4 {
            s.host_leases.slice_mut::<u32>(words).fill(0);
        }
        synced?;
        if s.leases.capacity() as usize >= words {
            d.gpu.zero(s.leases.ptr(), words)?;
        }
        Ok(())
    }

    fn queue(
        &mut self,
        d: &mut Resident,
        world: &World,
        q: &InterestQuery<'_>,
        chunk: usize,
    ) -> Result<(), PhysicsError> {
        let nq = q.boxes.len();
        let cap = q.capacity as usize;
        let mdg = q.max_datagrams as usize;
        let fail = |message: String| Err(PhysicsError::Device { stage: "interest", message });
        if q.own.len() != nq || q.centres.len() != nq || q.prev.len() != nq || q.leases.len() != nq {
            return fail("query slices differ in length".into());
        }
        if cap == 0 || cap > MAX_SELECTED || q.near_slots as usize > cap || q.rotation_slots as usize > cap {
            return fail(format!("a budget of {cap} records is outside 1..={MAX_SELECTED}"));
        }
        if !(1..=MAX_PACK_DATAGRAMS).contains(&mdg) {
            return fail(format!("{mdg} datagrams a player is outside 1..={MAX_PACK_DATAGRAMS}"));
        }
        if q.leases.iter().flatten().any(|l| l.len() < mdg as u64) {
            return fail(format!("a lease of fewer than {mdg} sequence numbers"));
        }
        // Unsorted lists: the selection does not depend on their order.
        let (total, parts) = d.aoi_on_device(world, q.boxes, false)?;
        let gpu = &d.gpu;
        let s = self;
        s.queued = (nq, mdg);
        if nq == 0 {
            return Ok(());
        }
        s.chunks.extend((0..nq).step_by(chunk).map(|a| a..(a + chunk).min(nq)));
        while s.chunk_done.len() < s.chunks.len() {
            s.chunk_done.push(Event::new(gpu)?);
        }
        s.chunk_state.clear();
        s.chunk_state.resize_with(s.chunks.len(), || AtomicU8::new(CHUNK_QUEUED));
        s.host_info.ensure(gpu, nq * 16)?;
        s.host_lens.ensure(gpu, nq * mdg * 4)?;
        s.host_out.ensure(gpu, nq * mdg * DATAGRAM_STRIDE)?;
        if d.n == 0 {
            // No object at all: no update and no staleness to keep.
            s.host_info.slice_mut::<u32>(nq * 4).fill(0);
            s.host_lens.slice_mut::<u32>(nq * mdg).fill(0);
            s.tables_tick = None;
            for done in &s.chunk_done[..s.chunks.len()] {
                gpu.record(done.raw)?;
            }
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
        s.packed.ensure(gpu, nq * 4, 1.25)?;
        s.leases.ensure(gpu, nq * LEASE_WORDS * 4, 1.25)?;
        s.host_leases.ensure(gpu, nq * LEASE_WORDS * 4)?;
        let t = &mut s.tables[next];
        t.offsets.ensure(gpu, (nq + 1) * 4, 1.25)?;
        t.ids.ensure(gpu, 2 * total * 8, 1.25)?;
        t.keys.ensure(gpu, 2 * total * 8, 1.25)?;
        t.kept.ensure(gpu, nq, 1.25)?;
        gpu.zero(t.ids.ptr(), 2 * total)?;
        // The per-player inputs go through page-locked memory, copied in stream order with
        // no wait (the host rewrites them only after the tick's end has waited for the
        // stream).
        s.host_own.ensure(gpu, nq * 4)?;
        s.host_centres.ensure(gpu, nq * 12)?;
        s.host_prev.ensure(gpu, nq * 4)?;
        s.host_own.slice_mut::<u32>(nq).copy_from_slice(q.own);
        s.host_centres.slice_mut::<f32>(nq * 3).copy_from_slice(q.centres.as_flattened());
        // Staleness is read only from the tables of the previous tick's selection (a
        // player missing a tick starts afresh, as on the host).
        if q.tick.checked_sub(1).is_some_and(|t| s.tables_tick == Some(t)) {
            s.host_prev.slice_mut::<u32>(nq).copy_from_slice(q.prev);
        } else {
            s.host_prev.slice_mut::<u32>(nq).fill(NO_PREVIOUS);
        }
        gpu.upload_async(&s.own, &s.host_own, nq)?;
        gpu.upload_async(&s.centres, &s.host_centres, nq * 3)?;
        gpu.upload_async(&s.prev, &s.host_prev, nq)?;
        // The lease table, copied from page-locked memory in stream order (the host
        // table is wiped once the tick is done).
        // In parallel: an entry a player, thousands of them, each a key's worth of copying.
        s.host_leases
            .slice_mut::<u32>(nq * LEASE_WORDS)
            .par_chunks_exact_mut(LEASE_WORDS)
            .zip(q.leases)
            .for_each(|(entry, lease)| lease_entry(lease.as_ref(), entry));
        gpu.upload_async(&s.leases, &s.host_leases, nq * LEASE_WORDS)?;
        let out = s.host_out.device_ptr::<u8>()?;
        let (p, t) = (&s.tables[s.current], &s.tables[next]);
        for (players, done) in s.chunks.iter().zip(&s.chunk_done) {
            let (first, end, m) = (players.start as u32, players.end as u32, players.len());
            gpu.launch_grid(
                m as u32,
                SELECT_THREADS,
                KInterestSelect {
                    first,
                    nq: end,
                    offsets: d.aoi_counts.ptr(),
                    parts: parts as u32,
                    objects: d.aoi_out.ptr(),
                    n: d.n as u32,
                    pos: d.obj.pos.ptr(),
                    ids: d.obj.id.ptr(),
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
                m.div_ceil(PACK_WARPS) as u32,
                32 * PACK_WARPS as u32,
                KInterestPack {
                    first,
                    nq: end,
                    meta: s.meta.ptr(),
                    sel: s.sel.ptr(),
                    cap: q.capacity,
                    n: d.n as u32,
                    pos: d.obj.pos.ptr(),
                    ids: d.obj.id.ptr(),
                    shapes: d.obj.shape.ptr(),
                    own: s.own.ptr(),
                    centres: s.centres.ptr(),
                    tick: q.tick,
                    dilation: u32::from(q.dilation_permille),
                    max_datagrams: q.max_datagrams,
                    bodies: s.bodies.ptr(),
                    lens: s.lens.ptr(),
                    info: s.info.ptr(),
                    packed: s.packed.ptr(),
                },
            )?;
            // What was packed is what was sent: the new tables' keys of those become `tick`.
            gpu.launch_grid(
                m as u32,
                256,
                KInterestStamp {
                    first,
                    nq: end,
                    meta: s.meta.ptr(),
                    sel: s.sel.ptr(),
                    cap: q.capacity,
                    packed: s.packed.ptr(),
                    ids: d.obj.id.ptr(),
                    toff: t.offsets.ptr(),
                    tid: t.ids.ptr(),
                    tkey: t.keys.ptr(),
                    tick: q.tick,
                },
            )?;
            gpu.launch_grid(
                (m * mdg).div_ceil(SEAL_WARPS) as u32,
                32 * SEAL_WARPS as u32,
                KInterestSeal {
                    first,
                    nq: end,
                    max_datagrams: q.max_datagrams,
                    bodies: s.bodies.ptr(),
                    lens: s.lens.ptr(),
                    info: s.info.ptr(),
                    leases: s.leases.ptr(),
                    out,
                },
            )?;
            let a = players.start;
            gpu.download_async(&mut s.host_info, 4 * a, s.info.ptr().add(4 * a), 4 * m)?;
            gpu.download_async(&mut s.host_lens, a * mdg, s.lens.ptr().add(a * mdg), m * mdg)?;
            gpu.record(done.raw)?;
        }
        Ok(())
    }
}

/// One player's entry of the lease table: the key, the session id and the first
/// sequence number as little-endian words; without a lease, a first number of
/// `u64::MAX` (the kernel seals nothing for it).
fn lease_entry(lease: Option<&SealLease>, entry: &mut [u32]) {
    let Some(lease) = lease else {
        entry.fill(0);
        entry[10] = u32::MAX;
        entry[11] = u32::MAX;
        return;
    };
    for (w, b) in entry[..8].iter_mut().zip(lease.key_bytes().chunks_exact(4)) {
        *w = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    }
    let id = lease.session_id();
    let first = lease.first_sequence();
    entry[8..].copy_from_slice(&[id as u32, (id >> 32) as u32, first as u32, (first >> 32) as u32]);
}
