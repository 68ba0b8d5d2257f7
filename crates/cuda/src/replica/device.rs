//! [`DeviceReplicas`]: every player's replica in device memory, and a build's steps.
//!
//! A build: [`DeviceReplicas::select`] answers the AOI boxes on the device (the lists
//! stay there), carries the tracks of players left out of the build, and runs
//! `k_replica_due` (a warp a player: the objects due), `k_replica_rank` (a block a
//! player: sorted by urgency), `k_replica_take` (a warp a player: the budget) and
//! `k_replica_pack` (a warp a player: the chosen records packed into delta update
//! bodies in mapped host memory), for the players in chunks, an event after each;
//! [`DeviceReplicas::ready`] waits for a chunk, whose players the host frames and seals
//! ([`Choices`], then `Subscriber::seal_packed`) while the device chooses for the next,
//! and hands back what sealing did for every player with [`DeviceReplicas::commit`],
//! which queues `k_replica_commit` and does not wait.
//!
//! Players are known by a key (the session id): each has a *home*, an index into the
//! device arrays of what persists besides its tracks (own object's track, credit,
//! flights). Tracks live in one of two buffers, at the player's AOI list offset of the
//! build that wrote them; the next build writes the other. A player left out of a
//! build keeps its tracks (copied after this build's lists); one left out of
//! [`FORGET_BUILDS`] builds in a row is forgotten and starts afresh if it comes back.
//! After any failure every player starts afresh (the device state is not trusted).

use std::ops::Range;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use myriad_core::{Aabb, World};
use myriad_interest::{ReplicationConfig, TickInfo};
use myriad_physics::PhysicsError;
use myriad_protocol::AckField;

use super::device_config;
use super::homes::{Homes, Placed, Twice};
use super::layout::*;
use crate::backend::{Resident, lock};
use crate::device::{DevBuf, Event, Pinned};
use crate::launch::{
    KReplicaCarry, KReplicaCommit, KReplicaDue, KReplicaObjects, KReplicaPack, KReplicaRank, KReplicaTake,
};

/// Flights a player keeps at most (`R_FLIGHTS` in the kernels; the host replica's
/// `MAX_FLIGHTS`).
pub const FLIGHTS: usize = myriad_interest::replica::MAX_FLIGHTS;

/// States in a player's flights at most (`R_STATES`; `MAX_FLIGHT_STATES`).
pub const STATES: usize = myriad_interest::replica::MAX_FLIGHT_STATES;

/// Bytes between two delta update bodies in the packing's output (`R_BODY_STRIDE` in
/// `kernels/pack.cuh`): the largest body, rounded up so that every body starts 8-aligned.
pub const BODY_STRIDE: usize = 1168;

/// Builds a player may miss in a row before its replica is forgotten.
pub const FORGET_BUILDS: u64 = 2 * myriad_protocol::MAX_BACK;

/// Players (one warp each) per block of `k_replica_due`, `k_replica_take` and
/// `k_replica_commit`; `k_replica_due` keeps a filter per warp in shared memory for
/// `DUE_WARPS` of them.
const PLAYERS_PER_BLOCK: u32 = 4;
const _: () = assert!(PLAYERS_PER_BLOCK == 4, "DUE_WARPS in kernels/replica.cu");

/// Players (one warp each) per block of `k_replica_pack`, each with a body and a
/// histogram in shared memory.
const PACK_WARPS: u32 = 4;
const _: () = assert!(PACK_WARPS == 4, "PACK_WARPS in kernels/pack.cu");

/// Threads per block of `k_replica_rank` (one block a player).
const RANK_BLOCK: u32 = 256;

/// Threads per block of `k_replica_carry` (one a player left out).
const CARRY_BLOCK: u32 = 32;
/// Threads a block of `k_replica_objects` (an object each).
const OBJECTS_BLOCK: u32 = 256;

/// One player of a build.
#[derive(Debug, Clone, Copy)]
pub struct ReplicaPlayer {
    /// A key that stays with the player (its session id).
    pub key: u64,
    /// Slot of its own object (out of range: none).
    pub own: u32,
    /// Centre of its AOI box and origin of its updates.
    pub centre: [f32; 3],
    /// Acknowledgements that arrived since its last build.
    pub acks: Option<AckField>,
}

/// A build between its [`select`](DeviceReplicas::select) and its
/// [`commit`](DeviceReplicas::commit).
#[derive(Debug, Clone, Copy)]
struct Pending {
    players: usize,
    max_datagrams: usize,
    tick: u64,
    /// Tracks in the buffer this build writes (lists and carried).
    used: usize,
    /// Whether the world had no object (the lists are `no_lists`).
    no_objects: bool,
    /// Chunks in all (their ends are `State::chunk_ends`).
    chunks: usize,
    /// Chunks [`DeviceReplicas::ready`] has answered so far.
    ready: usize,
}

struct State {
    /// Each player's home, by session key.
    home_of: Homes,
    /// Homes the device arrays hold.
    capacity: usize,
    builds: u64,
    /// Whether the device state may be read (false: everyone starts afresh).
    valid: bool,
    /// The tracks buffer the last build wrote, and how many tracks it holds.
    current: usize,
    used: usize,
    pending: Option<Pending>,
    /// One event a chunk, recorded after its packing, and one before the first
    /// chunk's kernels: the device's time for the choice.
    chunk_done: Vec<Event>,
    chunks_start: Option<Event>,
    /// Where each chunk of the pending build ends (players).
    chunk_ends: Vec<usize>,
    /// The device's time from the first chunk's kernels to the last chunk's packing,
    /// of the last build whose chunks were all taken.
    choice_ms: Option<f64>,
    /// The last build's placement (its vectors reused).
    placed: Placed,
    /// Scratch: (home, offset) pairs for `k_replica_carry`.
    carry_pairs: Vec<u32>,
    homes: DevBuf<RHome>,
    flights: DevBuf<RFlight>,
    states: DevBuf<RState>,
    tracks: [DevBuf<RTrack>; 2],
    /// At last build's track offsets: the build whose candidate took each old track
    /// (builds count from 1; zeroed when allocated).
    taken: DevBuf<u64>,
    /// The world's objects gathered for this build (`k_replica_objects`).
    objs: DevBuf<RObj>,
    cands: DevBuf<RCand>,
    un: DevBuf<RKey>,
    orph: DevBuf<RKey>,
    moved: DevBuf<RMoved>,
    wanted: DevBuf<RDue>,
    /// The objects due sorted by urgency (`k_replica_rank`).
    ranked: DevBuf<RDue>,
    chosen: DevBuf<RChosen>,
    /// Per player: candidates and objects due (`k_replica_due`).
    counts: DevBuf<u32>,
    players: DevBuf<RPlayer>,
    config: DevBuf<RConfig>,
    /// Per player: `k_replica_take`'s counts, for `k_replica_pack`.
    infos: DevBuf<RInfo>,
    /// Per player and datagram: where its records end (read by `k_replica_commit`).
    ends: DevBuf<u32>,
    commits: DevBuf<RCommit>,
    carry: DevBuf<u32>,
    /// All-zero list offsets, for a build with no object in the world.
    no_lists: DevBuf<u32>,
    host_players: Pinned,
    host_config: Pinned,
    host_carry: Pinned,
    host_commits: Pinned,
    /// Written by `k_replica_due` and `k_replica_take` through the mapping.
    host_info: Pinned,
    /// Written by `k_replica_pack` through the mapping: per player its `RPacked`, per
    /// datagram its body's length, and the bodies.
    host_packed: Pinned,
    host_lens: Pinned,
    host_bodies: Pinned,
}

/// Every player's replica on a CUDA backend's device; see the module docs.
pub struct DeviceReplicas {
    state: State,
    /// Last: the device state it shares with the backend (fields drop in order).
    resident: Arc<Mutex<Resident>>,
}

impl std::fmt::Debug for DeviceReplicas {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DeviceReplicas")
            .field("players", &self.state.home_of.len())
            .field("builds", &self.state.builds)
            .finish_non_exhaustive()
    }
}

/// What a build chose and packed for each player, read from the host's mapped memory.
#[derive(Clone, Copy)]
pub struct Choices<'a> {
    info: &'a [RInfo],
    packed: &'a [RPacked],
    lens: &'a [u32],
    bodies: &'a Pinned,
    max_datagrams: usize,
}

impl<'a> Choices<'a> {
    /// Player `i`'s counts and own record.
    pub fn info(&self, i: usize) -> &'a RInfo {
        &self.info[i]
    }

    /// What packing player `i`'s records did.
    pub fn packed(&self, i: usize) -> &'a RPacked {
        &self.packed[i]
    }

    /// Player `i`'s delta update bodies, in order (a length past a body's room is cut
    /// to it, and the framing refuses it).
    pub fn bodies(&self, i: usize) -> impl ExactSizeIterator<Item = &'a [u8]> + 'a {
        let (bodies, m) = (self.bodies, self.max_datagrams);
        let lens = &self.lens[i * m..(i + 1) * m];
        let n = (self.packed[i].datagrams as usize).min(m);
        lens[..n].iter().enumerate().map(move |(d, &len)| {
            let at = (i * m + d) * BODY_STRIDE;
            bodies.range::<u8>(at, (len as usize).min(BODY_STRIDE))
        })
    }
}

impl DeviceReplicas {
    /// Replicas of their own over `resident`, the backend's device state.
    pub(crate) fn new(resident: Arc<Mutex<Resident>>) -> DeviceReplicas {
        DeviceReplicas { state: State::new(), resident }
    }

    /// Queues the choosing half of a build for `players` (boxes `boxes`, one each), in
    /// chunks of players of the sizes `chunks` says, in order (each at least one player,
    /// together every player; none when there are no players): see the module docs.
    /// Take each chunk's players with [`ready`](Self::ready) and read what was chosen
    /// for them with [`choices`](Self::choices), then call
    /// [`commit`](Self::commit) with what packing and sealing did for every player. A
    /// failure leaves every player to start afresh at the next build.
    #[allow(clippy::too_many_arguments)]
    pub fn select(
        &mut self,
        world: &World,
        boxes: &[Aabb],
        players: &[ReplicaPlayer],
        config: &ReplicationConfig,
        max_datagrams: usize,
        tick: TickInfo,
        chunks: &[usize],
    ) -> Result<(), PhysicsError> {
        let mut resident = lock(&self.resident);
        let s = &mut self.state;
        let r = s.select(&mut resident, world, boxes, players, config, max_datagrams, tick, chunks);
        if r.is_err() {
            s.failed();
        }
        r
    }

    /// Waits for the next chunk of the last [`select`](Self::select)'s players (in
    /// order) and returns their indices, or `None` when every chunk has been taken. A
    /// failure (a list out of order: a device fault) leaves every player to start
    /// afresh, and the build is not committed.
    pub fn ready(&mut self) -> Result<Option<Range<usize>>, PhysicsError> {
        let resident = lock(&self.resident);
        let s = &mut self.state;
        let r = s.ready(&resident);
        if r.is_err() {
            s.failed();
        }
        r
    }

    /// Adds the host time since `since` under `name` to the device's profile, when
    /// profiling (`MYRIAD_CUDA_PROFILE`): for the host work of a build that happens
    /// outside this type (packing and sealing what it chose).
    pub fn profile_host(&self, name: &'static str, since: Instant) {
        self.profile_span(name, since.elapsed());
    }

    /// Forgets what the device's profile gathered so far (`Gpu::restart_profile`), when
    /// profiling: for a measurement that starts after its warm-up.
    pub fn restart_profile(&self) {
        lock(&self.resident).gpu.restart_profile();
    }

    /// Adds `took` under `name` to the device's profile, when profiling: a span of the
    /// tick's host work timed elsewhere (the receive's phases).
    pub fn profile_span(&self, name: &'static str, took: Duration) {
        lock(&self.resident).gpu.profile_span(name, took);
    }

    /// The device's time (ms) from the first chunk's kernels to the last chunk's packing
    /// in the last build whose every chunk [`ready`](Self::ready) answered: what the
    /// host's sealing and sending overlap. `None` before that.
    pub fn choice_ms(&self) -> Option<f64> {
        self.state.choice_ms
    }

    /// The last [`select`](Self::select)'s choices.
    pub fn choices(&self) -> Choices<'_> {
        let s = &self.state;
        let (players, m) = s.pending.map_or((0, 1), |p| (p.players, p.max_datagrams));
        Choices {
            info: s.host_info.slice::<RInfo>(players),
            packed: s.host_packed.slice::<RPacked>(players),
            lens: s.host_lens.slice::<u32>(players * m),
            bodies: &s.host_bodies,
            max_datagrams: m,
        }
    }

    /// Ends the build: `commits[i]` is what sealing player `i`'s datagrams did (where
    /// each datagram's records end stayed on the device).
    pub fn commit(&mut self, commits: &[RCommit]) -> Result<(), PhysicsError> {
        let mut resident = lock(&self.resident);
        let s = &mut self.state;
        let r = s.commit(&mut resident, commits);
        if r.is_err() {
            s.failed();
        }
        r
    }
}

impl State {
    fn new() -> State {
        State {
            home_of: Homes::default(),
            capacity: 0,
            builds: 0,
            valid: false,
            current: 0,
            used: 0,
            pending: None,
            chunk_done: Vec::new(),
            chunks_start: None,
            chunk_ends: Vec::new(),
            choice_ms: None,
            placed: Placed::default(),
            carry_pairs: Vec::new(),
            homes: DevBuf::empty(),
            flights: DevBuf::empty(),
            states: DevBuf::empty(),
            tracks: [DevBuf::empty(), DevBuf::empty()],
            taken: DevBuf::empty(),
            objs: DevBuf::empty(),
            cands: DevBuf::empty(),
            un: DevBuf::empty(),
            orph: DevBuf::empty(),
            moved: DevBuf::empty(),
            wanted: DevBuf::empty(),
            ranked: DevBuf::empty(),
            chosen: DevBuf::empty(),
            counts: DevBuf::empty(),
            players: DevBuf::empty(),
            config: DevBuf::empty(),
            infos: DevBuf::empty(),
            ends: DevBuf::empty(),
            commits: DevBuf::empty(),
            carry: DevBuf::empty(),
            no_lists: DevBuf::empty(),
            host_players: Pinned::empty(),
            host_config: Pinned::empty(),
            host_carry: Pinned::empty(),
            host_commits: Pinned::empty(),
            host_info: Pinned::empty(),
            host_packed: Pinned::empty(),
            host_lens: Pinned::empty(),
            host_bodies: Pinned::empty(),
        }
    }

    /// The players of the pending build's chunk `c`.
    fn chunk_range(&self, c: usize) -> Range<usize> {
        let first = if c == 0 { 0 } else { self.chunk_ends[c - 1] };
        first..self.chunk_ends[c]
    }

    /// After a failure: nothing on the device is trusted; every player starts afresh.
    fn failed(&mut self) {
        self.valid = false;
        self.pending = None;
        self.home_of.clear();
        self.used = 0;
    }

    /// This build's homes: each player's and whether it starts afresh; the players left
    /// out are carried or forgotten.
    fn place(&mut self, players: &[ReplicaPlayer], out: &mut Placed) -> Result<(), PhysicsError> {
        if !self.valid || self.pending.is_some() {
            // A build that never committed, or a failure: start afresh.
            self.failed();
        }
        self.builds += 1;
        self.home_of.place(players.iter().map(|p| p.key), self.builds, FORGET_BUILDS, out).map_err(|Twice(key)| {
            PhysicsError::Device { stage: "replica", message: format!("player {key} twice in one build") }
        })
    }

    #[allow(clippy::too_many_arguments)]
    fn select(
        &mut self,
        d: &mut Resident,
        world: &World,
        boxes: &[Aabb],
        players: &[ReplicaPlayer],
        config: &ReplicationConfig,
        max_datagrams: usize,
        at: TickInfo,
        chunks: &[usize],
    ) -> Result<(), PhysicsError> {
        let nq = players.len();
        let tick = at.tick;
        if boxes.len() != nq {
            return Err(PhysicsError::Device {
                stage: "replica",
                message: format!("{} boxes for {nq} players", boxes.len()),
            });
        }
        if chunks.iter().sum::<usize>() != nq || chunks.contains(&0) {
            return Err(PhysicsError::Device {
                stage: "replica",
                message: format!("chunks of {chunks:?} players for {nq} players"),
            });
        }
        // The placement's vectors are reused; a build that fails drops them (the next
        // allocates afresh).
        let started = Instant::now();
        let mut placement = std::mem::take(&mut self.placed);
        self.place(players, &mut placement)?;
        let Placed { homes: placed, carried } = &mut placement;
        let carry = &mut self.carry_pairs;
        let cfg = device_config(config, max_datagrams);
        let mdg = cfg.max_datagrams as usize;
        d.gpu.profile_host("host: replica homes", started);
        let started = Instant::now();
        let total = d.aoi_on_device(world, boxes)?;
        d.gpu.profile_host("host: AOI query (to its total)", started);
        let started = Instant::now();
        let gpu = &d.gpu;
        let (old, new) = (self.current, 1 - self.current);
        // Carried tracks go after this build's lists.
        let mut used = total;
        carry.clear();
        for &(home, tracks) in carried.iter() {
            carry.extend([home, used as u32]);
            used += tracks as usize;
        }
        if used > u32::MAX as usize {
            return Err(PhysicsError::Device { stage: "replica", message: format!("{used} tracks") });
        }
        // Homes: the arrays grow keeping what they hold.
        let homes_needed = self.home_of.span().max(1);
        if homes_needed > self.capacity {
            let keep = self.capacity;
            let want = homes_needed.next_power_of_two().max(64);
            self.homes.grow_keeping(gpu, want * size_of::<RHome>(), 1.0, keep * size_of::<RHome>())?;
            self.flights.grow_keeping(
                gpu,
                want * FLIGHTS * size_of::<RFlight>(),
                1.0,
                keep * FLIGHTS * size_of::<RFlight>(),
            )?;
            self.states.grow_keeping(
                gpu,
                want * STATES * size_of::<RState>(),
                1.0,
                keep * STATES * size_of::<RState>(),
            )?;
            self.capacity = want;
        }
        let items = total.max(1);
        self.tracks[new].ensure(gpu, used.max(1) * size_of::<RTrack>(), 1.25)?;
        // The old buffer must exist for the kernels' pointer even when nothing is in it.
        self.tracks[old].ensure(gpu, size_of::<RTrack>(), 1.0)?;
        self.objs.ensure(gpu, d.n.max(1) * size_of::<RObj>(), 1.25)?;
        self.cands.ensure(gpu, items * size_of::<RCand>(), 1.25)?;
        self.un.ensure(gpu, items * size_of::<RKey>(), 1.25)?;
        self.orph.ensure(gpu, self.used.max(1) * size_of::<RKey>(), 1.25)?;
        if self.taken.ensure(gpu, self.used.max(1) * 8, 1.25)? {
            // Stale memory could hold any number, this build's too: no build is 0.
            gpu.zero(self.taken.ptr(), self.taken.capacity() as usize)?;
        }
        self.moved.ensure(gpu, items * size_of::<RMoved>(), 1.25)?;
        self.wanted.ensure(gpu, items * size_of::<RDue>(), 1.25)?;
        self.ranked.ensure(gpu, items * size_of::<RDue>(), 1.25)?;
        self.chosen.ensure(gpu, items * size_of::<RChosen>(), 1.25)?;
        self.counts.ensure(gpu, nq.max(1) * 2 * 4, 1.25)?;
        self.players.ensure(gpu, nq.max(1) * size_of::<RPlayer>(), 1.25)?;
        self.config.ensure(gpu, size_of::<RConfig>(), 1.0)?;
        self.carry.ensure(gpu, carry.len().max(1) * 4, 1.25)?;
        self.host_players.ensure(gpu, nq.max(1) * size_of::<RPlayer>())?;
        self.host_config.ensure(gpu, size_of::<RConfig>())?;
        self.host_carry.ensure(gpu, carry.len().max(1) * 4)?;
        self.infos.ensure(gpu, nq.max(1) * size_of::<RInfo>(), 1.25)?;
        self.ends.ensure(gpu, (nq * mdg).max(1) * 4, 1.25)?;
        self.host_info.ensure(gpu, nq.max(1) * size_of::<RInfo>())?;
        self.host_packed.ensure(gpu, nq.max(1) * size_of::<RPacked>())?;
        self.host_lens.ensure(gpu, (nq * mdg).max(1) * 4)?;
        self.host_bodies.ensure(gpu, (nq * mdg).max(1) * BODY_STRIDE)?;
        for ((dst, p), &(home, reset)) in
            self.host_players.slice_mut::<RPlayer>(nq).iter_mut().zip(players).zip(placed.iter())
        {
            *dst = RPlayer {
                ack_newest: p.acks.map_or(0, |a| a.newest()),
                ack_bits: p.acks.map_or(0, |a| a.bits()),
                centre: p.centre,
                home,
                reset: u32::from(reset),
                own_slot: p.own,
                has_acks: u32::from(p.acks.is_some()),
                pad: 0,
            };
        }
        self.host_config.slice_mut::<RConfig>(1)[0] = cfg;
        self.host_carry.slice_mut::<u32>(carry.len()).copy_from_slice(carry);
        gpu.upload_async(&self.players, &self.host_players, nq)?;
        gpu.upload_async(&self.config, &self.host_config, 1)?;
        gpu.upload_async(&self.carry, &self.host_carry, carry.len())?;
        let offsets = if d.n == 0 || nq == 0 {
            // No list was written: every player's is empty.
            self.no_lists.ensure(gpu, (nq + 1) * 4, 1.25)?;
            gpu.zero(self.no_lists.ptr(), nq + 1)?;
            self.no_lists.ptr()
        } else {
            d.aoi_counts.ptr()
        };
        if !carried.is_empty() {
            gpu.launch_grid(
                (carried.len() as u32).div_ceil(CARRY_BLOCK),
                CARRY_BLOCK,
                KReplicaCarry {
                    count: carried.len() as u32,
                    carry: self.carry.ptr(),
                    old_tracks: self.tracks[old].ptr(),
                    next_tracks: self.tracks[new].ptr(),
                    homes: self.homes.ptr(),
                },
            )?;
        }
        // The players in chunks, each chunk's kernels on its players alone (every
        // per-player array from the chunk's first player on; homes and list offsets are
        // the build's), an event after each chunk's packing: the host seals and sends a
        // chunk while the device chooses for the next (`ready`).
        // No players: one empty chunk, whose event `ready` still waits for.
        self.chunk_ends.clear();
        self.chunk_ends.extend(chunks.iter().scan(0, |end, &size| {
            *end += size;
            Some(*end)
        }));
        if self.chunk_ends.is_empty() {
            self.chunk_ends.push(0);
        }
        let chunks = self.chunk_ends.len();
        while self.chunk_done.len() < chunks {
            self.chunk_done.push(Event::new(gpu)?);
        }
        let start = match self.chunks_start.take() {
            Some(e) => e,
            None => Event::new(gpu)?,
        };
        self.choice_ms = None;
        let objects = if d.n == 0 { self.no_lists.ptr() } else { d.aoi_out.ptr() };
        let info = self.host_info.device_ptr::<RInfo>()?;
        let packed = self.host_packed.device_ptr::<RPacked>()?;
        let out = self.host_bodies.device_ptr::<u8>()?;
        let out_lens = self.host_lens.device_ptr::<u32>()?;
        // What every chunk's kernels share: the objects, the homes, the tracks, the lists.
        let (n, objs) = (d.n as u32, self.objs.ptr());
        if n > 0 {
            gpu.launch_grid(
                n.div_ceil(OBJECTS_BLOCK),
                OBJECTS_BLOCK,
                KReplicaObjects { n, pos: d.obj.pos.ptr(), ids: d.obj.id.ptr(), shapes: d.obj.shape.ptr(), objs },
            )?;
        }
        let (cfg, homes, next_tracks) = (self.config.ptr(), self.homes.ptr(), self.tracks[new].ptr());
        let (cands, chosen) = (self.cands.ptr(), self.chosen.ptr());
        gpu.record(start.raw)?;
        self.chunks_start = Some(start);
        for (c, done) in self.chunk_done[..chunks].iter().enumerate() {
            let range = self.chunk_range(c);
            let (first, count) = (range.start, range.len() as u32);
            if count > 0 {
                let offsets = offsets.add(first);
                let players = self.players.ptr().add(first);
                let counts = self.counts.ptr().add(2 * first);
                let (info, infos) = (info.add(first), self.infos.ptr().add(first));
                gpu.launch_grid(
                    count.div_ceil(PLAYERS_PER_BLOCK),
                    32 * PLAYERS_PER_BLOCK,
                    KReplicaDue {
                        nq: count,
                        cfg,
                        tick,
                        build: self.builds,
                        offsets,
                        objects,
                        n,
                        objs,
                        players,
                        homes,
                        old_tracks: self.tracks[old].ptr(),
                        next_tracks,
                        taken: self.taken.ptr(),
                        cands,
                        un: self.un.ptr(),
                        orph: self.orph.ptr(),
                        moved: self.moved.ptr(),
                        wanted: self.wanted.ptr(),
                        flights: self.flights.ptr(),
                        states: self.states.ptr(),
                        counts,
                        info,
                    },
                )?;
                gpu.launch_grid(
                    count,
                    RANK_BLOCK,
                    KReplicaRank { nq: count, offsets, counts, wanted: self.wanted.ptr(), ranked: self.ranked.ptr() },
                )?;
                gpu.launch_grid(
                    count.div_ceil(PLAYERS_PER_BLOCK),
                    32 * PLAYERS_PER_BLOCK,
                    KReplicaTake {
                        nq: count,
                        cfg,
                        tick,
                        offsets,
                        n,
                        objs,
                        players,
                        homes,
                        next_tracks,
                        cands,
                        counts,
                        ranked: self.ranked.ptr(),
                        chosen,
                        info,
                        infos,
                    },
                )?;
                gpu.launch_grid(
                    count.div_ceil(PACK_WARPS),
                    32 * PACK_WARPS,
                    KReplicaPack {
                        nq: count,
                        cfg,
                        tick,
                        dilation: u32::from(at.dilation_permille),
                        offsets,
                        players,
                        counts,
                        infos,
                        chosen,
                        ends: self.ends.ptr().add(first * mdg),
                        packed: packed.add(first),
                        out: out.add(first * mdg * BODY_STRIDE),
                        out_lens: out_lens.add(first * mdg),
                    },
                )?;
            }
            gpu.record(done.raw)?;
        }
        gpu.profile_host("host: replica buffers and launches", started);
        let no_objects = d.n == 0 || nq == 0;
        self.pending = Some(Pending { players: nq, max_datagrams: mdg, tick, used, no_objects, chunks, ready: 0 });
        self.placed = placement;
        Ok(())
    }

    /// Waits for the next chunk of the pending build (they come in order) and returns
    /// its players' indices; fails if a list was out of order (a device fault).
    fn ready(&mut self, d: &Resident) -> Result<Option<Range<usize>>, PhysicsError> {
        let Some(p) = self.pending.as_mut() else {
            return Err(PhysicsError::Device { stage: "replica", message: "no build to wait for".into() });
        };
        if p.ready == p.chunks {
            return Ok(None);
        }
        let c = p.ready;
        p.ready += 1;
        let last_chunk = p.ready == p.chunks;
        let range = self.chunk_range(c);
        let gpu = &d.gpu;
        gpu.bind()?;
        let started = Instant::now();
        self.chunk_done[c].wait()?;
        gpu.profile_host("host: wait for the replica kernels", started);
        if last_chunk {
            gpu.collect_profile()?;
            if let Some(start) = &self.chunks_start {
                self.choice_ms = Some(start.ms_to(&self.chunk_done[c])?);
            }
        }
        let started = Instant::now();
        let info = &self.host_info.slice::<RInfo>(range.end)[range.clone()];
        if let Some(i) = info.iter().position(|r| r.unsorted != 0) {
            let message = format!("player {}'s AOI list is not in ascending slot order", range.start + i);
            return Err(PhysicsError::Device { stage: "replica", message });
        }
        // By home, not by key: a store a player instead of a hash look-up.
        for (&(home, _), r) in self.placed.homes[range.clone()].iter().zip(info) {
            self.home_of.set_tracks(home, r.in_view);
        }
        gpu.profile_host("host: replica reports", started);
        Ok(Some(range))
    }

    fn commit(&mut self, d: &mut Resident, commits: &[RCommit]) -> Result<(), PhysicsError> {
        let Some(p) = self.pending else {
            return Err(PhysicsError::Device { stage: "replica", message: "a commit without a build".into() });
        };
        let nq = p.players;
        if p.ready != p.chunks {
            // The host's commits may not be written while the stream could still read
            // the last build's: waiting for a chunk of this build is what proves it can't.
            return Err(PhysicsError::Device {
                stage: "replica",
                message: "a commit before every chunk was ready".into(),
            });
        }
        if commits.len() != nq {
            return Err(PhysicsError::Device {
                stage: "replica",
                message: format!("{} commits for {nq} players", commits.len()),
            });
        }
        let gpu = &d.gpu;
        gpu.bind()?;
        let new = 1 - self.current;
        if nq > 0 {
            self.commits.ensure(gpu, nq * size_of::<RCommit>(), 1.25)?;
            self.host_commits.ensure(gpu, nq * size_of::<RCommit>())?;
            // The stream may still read last build's: `ready` waited for this build's since.
            self.host_commits.slice_mut::<RCommit>(nq).copy_from_slice(commits);
            gpu.upload_async(&self.commits, &self.host_commits, nq)?;
            let offsets = if p.no_objects { self.no_lists.ptr() } else { d.aoi_counts.ptr() };
            gpu.launch_grid(
                (nq as u32).div_ceil(PLAYERS_PER_BLOCK),
                32 * PLAYERS_PER_BLOCK,
                KReplicaCommit {
                    nq: nq as u32,
                    cfg: self.config.ptr(),
                    tick: p.tick,
                    offsets,
                    players: self.players.ptr(),
                    homes: self.homes.ptr(),
                    commits: self.commits.ptr(),
                    ends: self.ends.ptr(),
                    chosen: self.chosen.ptr(),
                    cands: self.cands.ptr(),
                    next_tracks: self.tracks[new].ptr(),
                    flights: self.flights.ptr(),
                    states: self.states.ptr(),
                },
            )?;
        }
        self.current = new;
        self.used = p.used;
        self.valid = true;
        self.pending = None;
        Ok(())
    }
}
