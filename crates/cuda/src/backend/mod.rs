//! The two CUDA backends, over one device-resident pipeline.
//!
//! # How it works
//! World state lives on the device between steps; a step uploads only what the host
//! changed, downloads the new actions into pinned buffers, and leaves the positions,
//! the previous positions and the flags on the device until the host reads them
//! (`held`: all of them, or some positions, which a kernel gathers). The upload
//! (`sync`, and [`StepReport::upload_bytes`] counts it):
//! - when the device copy was made right after the last step and every change since is
//!   on the world's record (`Dynamics::changes`: a zone's one `apply_sorted` a tick and
//!   its actions), only the record travels (`patch`): the runs of kept slots and the
//!   written states in one staged copy, then `k_patch_gather` moves the kept objects to
//!   their new slots in a spare set of arrays (swapped in, the old set kept as the next
//!   spare) and `k_patch_scatter` writes the staged states (`kernels/patch.cu`); the
//!   actions travel whole when any was set. The bytes follow the objects that changed,
//!   not the world's size;
//! - otherwise the generation counters decide: everything after spawns, despawns or an
//!   edit off the record, positions, actions and flags after teleports, the actions
//!   alone after new actions, nothing when nothing changed;
//! - the statics, the terrain and the constants when they change.
//!
//! Per tick:
//!
//! 1. `build_dynamic_bvh`: object boxes; for `cuda` also Morton codes, the radix sort,
//!    Karras emission and the refit (`kernels/lbvh.cu`), or, for up to
//!    [`Backend::set_tree_refits`] steps in a row after a build while the device's slots
//!    keep their objects and only the steps moved them (no upload of positions, no patch
//!    that moves slots or writes states), only the boxes and the refit of the last tree.
//! 2. `broad_static`, `broad_dynamic`: each object counts the static primitives and the
//!    other objects its box overlaps (tree walk for `cuda`, every target for
//!    `cuda-naive`); an exclusive scan gives each object its exact range; the host reads
//!    the two totals and grows the pair buffers to them (so no pair is ever dropped);
//!    a second pass writes and sorts each range (`kernels/broad.cu`).
//! 3. `narrow_static`, `narrow_dynamic`, `forces`: one thread per object sums its
//!    responses in the CPU's order and integrates (`kernels/physics.cu`).
//!
//! The two backends differ only in how step 2 finds candidates.
//!
//! # Code map
//! [`CudaBackend`] is a handle on the device-resident state (`Resident`), which it shares
//! with the device replicas ([`crate::replica::DeviceReplicas`], from
//! [`CudaBackend::device_replicas`]): the two run one after the other on the tick's
//! thread, so the lock between them is never contended. One file per stage, each adding
//! methods to `Resident` or holding the stage's device state:
//! - `sync`: the device copies of the world and their uploads, the pinned download
//!   buffers;
//! - `patch`: the incremental upload of a recorded change (the spare arrays, the staging
//!   buffer and its layout, the check that a record fits the device copy);
//! - `tree`: the LBVH build (and the dynamic boxes of `cuda-naive`);
//! - `scan`: exclusive prefix sums;
//! - `broad`: the count and write passes, and [`CudaBackend::broad_pairs`];
//! - `narrow`, `forces`: the narrow-phase launches, the force and integration launch;
//! - `step`: one tick in order, the download of the new state and the stage times;
//! - `held`: the positions, previous positions and flags a step leaves on the device,
//!   their fetch when the host first reads them, and the gather of some positions;
//! - `aoi`: area-of-interest queries (the device replicas start from its lists,
//!   which stay on the device), and `grid`, the columns `cuda` answers them from.
//!
//! Every launch goes through the typed argument structs of the crate's `launch` module.
//!
//! # Performance note
//! Stage times come from CUDA events; the host's own time in a step (launch calls, the
//! mid-step read of the pair totals, copying the state into the `World`) is added to
//! `upload`, so the stages sum to the wall-clock time of the step.

mod aoi;
mod broad;
mod forces;
mod grid;
mod held;
mod narrow;
mod patch;
mod scan;
mod step;
mod sync;
mod tree;

use std::sync::{Arc, Mutex, MutexGuard};

use myriad_core::{Aabb, World};
use myriad_physics::{AoiResults, Backend, BackendKind, PhysicsError, StepReport, TickConstants};

use crate::device::{DevBuf, Event, Gpu, Pinned};
use crate::params::DeviceParams;
use grid::Grid;
use held::HeldPool;
use patch::Patch;
use scan::Scan;
use sync::{Host, Objects, Prims};
use tree::Tree;

/// Events recorded per step (stage boundaries and the download's checkpoints).
const EVENTS: usize = 15;

/// What the device copy of the dynamics was made from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Synced {
    /// `Dynamics::generation` (every host-side change).
    pub generation: u64,
    /// `Dynamics::action_generation` (actions set by the host).
    pub action_generation: u64,
    /// `Dynamics::layout_generation` (objects added or removed).
    pub layout: u64,
    /// `Dynamics::stamp`: tells two worlds with equal generation counters apart (a
    /// backend moved from one world to another, or to a clone).
    pub identity: u64,
}

impl Synced {
    /// The state of `world` now.
    pub fn of(world: &myriad_core::World) -> Synced {
        let d = &world.dynamics;
        Synced {
            generation: d.generation(),
            action_generation: d.action_generation(),
            layout: d.layout_generation(),
            identity: d.stamp(),
        }
    }
}

/// A CUDA backend: `cuda` (LBVH) or `cuda-naive` (all pairs): a handle on the device
/// and the world's copy there, which the device replicas share.
pub struct CudaBackend {
    resident: Arc<Mutex<Resident>>,
}

/// What a CUDA backend keeps on the device between calls: the world's copy, the stage
/// buffers, the AOI lists of the last query, and the device itself.
pub(crate) struct Resident {
    kind: BackendKind,
    /// Objects on the device (`usize::MAX`: unknown, the next call uploads everything).
    pub(crate) n: usize,
    /// Which dynamics the device holds; `None`: upload everything.
    synced: Option<Synced>,
    /// (stamp, generation) of the statics on the device.
    statics_key: Option<(u64, u64)>,
    /// The stamp of the terrain on the device.
    terrain_key: Option<u64>,
    params_key: Option<DeviceParams>,
    /// The dynamics generation the dynamic boxes were built at (the AOI query reuses them;
    /// the step builds its own).
    boxes_fresh: Option<u64>,
    pub(crate) obj: Objects,
    /// The incremental upload's spare arrays and staging buffers.
    patch: Patch,
    prims: Prims,
    dyn_tree: Tree,
    /// Steps that refit `dyn_tree` since it was built over the device's current slots;
    /// `None` when the slots changed (or nothing was built): the next step rebuilds.
    tree_age: Option<u32>,
    /// How many steps in a row may refit the dynamic tree before one rebuilds it.
    tree_refits: u32,
    static_tree: Tree,
    /// The columns the AOI queries of `cuda` are answered from.
    grid: Grid,
    scan: Scan,
    static_pairs: DevBuf<u32>,
    dynamic_pairs: DevBuf<u32>,
    aoi_boxes: DevBuf<f32>,
    /// The order in which the AOI queries' threads take their boxes (`aoi::query_order`).
    aoi_order: DevBuf<u32>,
    /// For how many boxes `aoi_order` was computed, and the queries since.
    order_age: Option<(usize, u32)>,
    /// The last AOI query's list offsets and slots ([`Resident::aoi_on_device`]).
    pub(crate) aoi_counts: DevBuf<u32>,
    pub(crate) aoi_out: DevBuf<u32>,
    params: DevBuf<DeviceParams>,
    counters: DevBuf<u32>,
    samples: DevBuf<u16>,
    host: Host,
    /// The positions, previous positions and flags of recent steps, held on the device
    /// for the worlds that have not read them (`held`).
    held: HeldPool,
    events: Vec<Event>,
    // Last: the context must outlive every buffer above (fields drop in order).
    pub(crate) gpu: Gpu,
}

impl CudaBackend {
    /// Probes the machine and sets up a backend of `kind` (`Cuda` or `CudaNaive`). Fails
    /// with [`PhysicsError::Unavailable`] saying why when there is no driver, NVRTC or
    /// device, or the kernels do not load.
    pub fn new(kind: BackendKind) -> Result<CudaBackend, PhysicsError> {
        CudaBackend::on_device(kind, 0)
    }

    /// [`CudaBackend::new`] on device `ordinal` (zones of one process, one per GPU).
    pub fn on_device(kind: BackendKind, ordinal: usize) -> Result<CudaBackend, PhysicsError> {
        let resident = Arc::new(Mutex::new(Resident::on_device(kind, ordinal)?));
        // The held copies gather some positions through the backend they came from.
        lock(&resident).held = HeldPool::new(Arc::downgrade(&resident));
        Ok(CudaBackend { resident })
    }

    /// Every player's replica on this backend's device (protocol version 3's choices
    /// made there), sharing the device state with the backend.
    pub fn device_replicas(&self) -> crate::replica::DeviceReplicas {
        crate::replica::DeviceReplicas::new(self.resident.clone())
    }

    /// The resident state, for one call.
    fn resident(&self) -> MutexGuard<'_, Resident> {
        lock(&self.resident)
    }

    /// The candidate pairs of the world as it is, without stepping: static pairs as
    /// `object << 32 | primitive` sorted by (object, primitive), dynamic pairs as
    /// `a << 32 | b` with `a < b`, sorted. For checking the broad phase against the CPU.
    pub fn broad_pairs(&mut self, world: &World) -> Result<(Vec<u64>, Vec<u64>), PhysicsError> {
        self.resident().checked(|d| d.broad_pairs_impl(world))
    }
}

/// Locks the resident state. A panic during a call leaves it poisoned and possibly half
/// updated: it is then invalidated, so the next call uploads everything.
pub(crate) fn lock(resident: &Mutex<Resident>) -> MutexGuard<'_, Resident> {
    resident.lock().unwrap_or_else(|poisoned| {
        resident.clear_poison();
        let mut d = poisoned.into_inner();
        d.invalidate();
        d
    })
}

impl Resident {
    fn on_device(kind: BackendKind, ordinal: usize) -> Result<Resident, PhysicsError> {
        let name = kind.name();
        if !matches!(kind, BackendKind::Cuda | BackendKind::CudaNaive) {
            return Err(PhysicsError::Unavailable { backend: name, reason: "not a CUDA backend kind".into() });
        }
        let gpu = Gpu::new(ordinal).map_err(|reason| PhysicsError::Unavailable { backend: name, reason })?;
        let events = (0..EVENTS).map(|_| Event::new(&gpu)).collect::<Result<Vec<_>, _>>()?;
        let p = Pinned::empty;
        Ok(Resident {
            kind,
            n: 0,
            synced: None,
            statics_key: None,
            terrain_key: None,
            params_key: None,
            boxes_fresh: None,
            obj: Objects::new(),
            patch: Patch::new(),
            prims: Prims::new(),
            dyn_tree: Tree::new(),
            tree_age: None,
            tree_refits: myriad_physics::lbvh::tree_refits(),
            static_tree: Tree::new(),
            grid: Grid::new(),
            scan: Scan { sums: DevBuf::empty() },
            static_pairs: DevBuf::empty(),
            dynamic_pairs: DevBuf::empty(),
            aoi_boxes: DevBuf::empty(),
            aoi_order: DevBuf::empty(),
            order_age: None,
            aoi_counts: DevBuf::empty(),
            aoi_out: DevBuf::empty(),
            params: DevBuf::empty(),
            counters: DevBuf::empty(),
            samples: DevBuf::empty(),
            host: Host {
                pos: p(),
                prev: p(),
                action: p(),
                flags: p(),
                small: p(),
                aoi_offsets: p(),
                aoi_objects: p(),
                aoi_boxes: p(),
                aoi_order: p(),
                gather_slots: p(),
                gather_pos: p(),
            },
            held: HeldPool::default(),
            events,
            gpu,
        })
    }

    fn naive(&self) -> bool {
        self.kind == BackendKind::CudaNaive
    }

    fn description(&self) -> String {
        let how = if self.naive() { "all pairs" } else { "LBVH, device-resident" };
        format!("{} ({}, sm_{}, {how})", self.kind, self.gpu.info.name, self.gpu.info.arch)
    }

    /// Makes the next call upload everything: after an error the device copy may be
    /// half updated.
    pub(crate) fn invalidate(&mut self) {
        self.synced = None;
        self.n = usize::MAX;
    }

    /// Runs `call`, invalidating the device copy if it fails.
    fn checked<T>(&mut self, call: impl FnOnce(&mut Resident) -> Result<T, PhysicsError>) -> Result<T, PhysicsError> {
        let r = call(self);
        if r.is_err() {
            self.invalidate();
        }
        r
    }

    fn step_impl(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        // A step whose pair lists outgrew their buffers is redone once with buffers of
        // the exact size (the world is only written after a complete step).
        let mut sent = 0;
        match self.try_step(world, k, &mut sent)? {
            Some(report) => Ok(report),
            None => self.try_step(world, k, &mut sent)?.ok_or(PhysicsError::Device {
                stage: "broad phase",
                message: "pair buffers still too small after growing them to the exact count".into(),
            }),
        }
    }
}

impl Drop for Resident {
    fn drop(&mut self) {
        if let Some(table) = self.gpu.profile_table() {
            eprintln!("per-kernel device time, {} ({} objects):\n{table}", self.description(), self.n);
        }
    }
}

impl Backend for CudaBackend {
    fn kind(&self) -> BackendKind {
        self.resident().kind
    }

    fn description(&self) -> String {
        self.resident().description()
    }

    fn step(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        self.resident().checked(|d| d.step_impl(world, k))
    }

    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        self.resident().checked(|d| d.query_impl(world, boxes, out))
    }

    fn set_tree_refits(&mut self, refits: u32) {
        self.resident().tree_refits = refits;
    }

    fn tree_age(&self) -> Option<u32> {
        self.resident().tree_age
    }
}
