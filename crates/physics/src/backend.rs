//! The [`Backend`] trait every physics implementation provides, and what it reports.

use std::fmt;
use std::str::FromStr;

use myriad_core::{Aabb, World};
use serde::{Deserialize, Serialize};

use crate::consts::TickConstants;
use crate::error::PhysicsError;

/// The implementations, by the names the command line and configuration files use
/// (`cpu-naive`, `cpu`, `cuda-naive`, `cuda`, `auto`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BackendKind {
    /// One thread, all pairs: the reference's "CPU" column.
    CpuNaive,
    /// Rayon-parallel LBVH broad phase.
    Cpu,
    /// All pairs on the GPU: the reference's "naive GPU" column (crate `myriad-cuda`).
    CudaNaive,
    /// Device-resident state and an LBVH on the GPU (crate `myriad-cuda`).
    Cuda,
    /// `cuda` when a driver, NVRTC and a device are present, else `cpu` (crate
    /// `myriad-cuda` resolves it).
    Auto,
    /// Not a local implementation: a gateway's world, stepped remotely by a cluster's
    /// zones (crate `myriad-zone`'s `ZonesBackend`, whose step sends the players'
    /// intents and mirrors the zones' world over NATS). A gateway builds it from its
    /// cluster, so it cannot be chosen: no name parses to it, no configuration
    /// deserializes to it, and the factories refuse it.
    #[serde(skip_deserializing)]
    Zones,
}

impl BackendKind {
    /// The kinds this crate implements (the CPU backends): [`create_cpu_backend`] makes each.
    pub const ALL: [BackendKind; 2] = [BackendKind::CpuNaive, BackendKind::Cpu];
    /// Every kind a name can select, the CUDA ones and `auto` included (not
    /// [`BackendKind::Zones`], which no name selects).
    pub const EVERY: [BackendKind; 5] =
        [BackendKind::CpuNaive, BackendKind::Cpu, BackendKind::CudaNaive, BackendKind::Cuda, BackendKind::Auto];
    /// Their names, in the order of [`BackendKind::EVERY`].
    pub const NAMES: [&'static str; 5] = ["cpu-naive", "cpu", "cuda-naive", "cuda", "auto"];

    /// The command-line name (for [`BackendKind::Zones`], which has none, the name it is
    /// reported by).
    pub fn name(self) -> &'static str {
        match self {
            BackendKind::CpuNaive => "cpu-naive",
            BackendKind::Cpu => "cpu",
            BackendKind::CudaNaive => "cuda-naive",
            BackendKind::Cuda => "cuda",
            BackendKind::Auto => "auto",
            BackendKind::Zones => "zones",
        }
    }
}

impl fmt::Display for BackendKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BackendKind {
    type Err = PhysicsError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        BackendKind::EVERY.into_iter().find(|k| k.name() == s).ok_or_else(|| PhysicsError::UnknownBackend(s.into()))
    }
}

/// The stages of a step, in order, with the reference's names (docs/design.md, the tick;
/// reference results, Table 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Stage {
    /// Copying what changed to the device (0 on the CPU).
    Upload,
    /// Object boxes, Morton codes, sort, hierarchy and refit of the dynamic tree.
    BuildDynamicBvh,
    /// Candidate pairs of dynamic objects and static primitives.
    BroadStatic,
    /// Candidate pairs of dynamic objects.
    BroadDynamic,
    /// Exact tests and responses against statics.
    NarrowStatic,
    /// Exact tests and responses between dynamics.
    NarrowDynamic,
    /// NPC actions, gathering responses, forces, integration, limits and terrain.
    Forces,
}

impl Stage {
    /// Every stage, in order.
    pub const ALL: [Stage; 7] = [
        Stage::Upload,
        Stage::BuildDynamicBvh,
        Stage::BroadStatic,
        Stage::BroadDynamic,
        Stage::NarrowStatic,
        Stage::NarrowDynamic,
        Stage::Forces,
    ];

    /// The reference's name (`upload`, `build_dynamic_bvh`, ...).
    pub const fn name(self) -> &'static str {
        match self {
            Stage::Upload => "upload",
            Stage::BuildDynamicBvh => "build_dynamic_bvh",
            Stage::BroadStatic => "broad_static",
            Stage::BroadDynamic => "broad_dynamic",
            Stage::NarrowStatic => "narrow_static",
            Stage::NarrowDynamic => "narrow_dynamic",
            Stage::Forces => "forces",
        }
    }
}

/// What one step did and how long each stage took.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepReport {
    /// Milliseconds per stage, indexed like [`Stage::ALL`].
    pub stage_ms: [f64; 7],
    /// Candidate (broad-phase) pairs of a dynamic object and a static primitive.
    pub static_pairs: u64,
    /// Candidate pairs of dynamic objects.
    pub dynamic_pairs: u64,
    /// Static pairs that touched and were not already separating.
    pub static_contacts: u64,
    /// Dynamic pairs that touched and were not already separating.
    pub dynamic_contacts: u64,
    /// Bytes copied from the host to a device to bring its copy of the world up to date
    /// for this step (0 for the CPU backends): how a zone's upload per tick is measured
    /// against its boundary traffic. Missing in reports written before it existed.
    #[serde(default)]
    pub upload_bytes: u64,
    /// Bytes copied from a device back to the host by this step (0 for the CPU
    /// backends): on `cuda` the new positions and actions, and the previous positions
    /// and flags only when the step could not leave them on the device. Missing in
    /// reports written before it existed.
    #[serde(default)]
    pub download_bytes: u64,
}

impl StepReport {
    /// The time of one stage.
    pub fn ms(&self, stage: Stage) -> f64 {
        self.stage_ms[stage as usize]
    }

    /// Table 1's "static" column: broad and narrow phase against statics.
    pub fn physics_static_ms(&self) -> f64 {
        self.ms(Stage::BroadStatic) + self.ms(Stage::NarrowStatic)
    }

    /// Table 1's "dynamic" column: everything else of the step (upload, the dynamic
    /// tree, dynamic broad and narrow phase, forces).
    pub fn physics_dynamic_ms(&self) -> f64 {
        self.ms(Stage::Upload)
            + self.ms(Stage::BuildDynamicBvh)
            + self.ms(Stage::BroadDynamic)
            + self.ms(Stage::NarrowDynamic)
            + self.ms(Stage::Forces)
    }

    /// The whole step.
    pub fn total_ms(&self) -> f64 {
        self.stage_ms.iter().sum()
    }
}

/// Area-of-interest results for a batch of query boxes, in compressed-row form: the
/// objects of query `q` are `objects[offsets[q]..offsets[q + 1]]`, as dynamic slots in
/// ascending order.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct AoiResults {
    /// `queries + 1` offsets into `objects`.
    pub offsets: Vec<u32>,
    /// Dynamic slots, grouped by query, ascending within each.
    pub objects: Vec<u32>,
}

impl AoiResults {
    /// Number of queries answered.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Whether no query was answered.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The slots inside query `q`'s box.
    pub fn get(&self, q: usize) -> &[u32] {
        &self.objects[self.offsets[q] as usize..self.offsets[q + 1] as usize]
    }

    /// Empties the results, keeping the buffers.
    pub fn clear(&mut self) {
        self.offsets.clear();
        self.objects.clear();
    }
}

/// A physics implementation.
///
/// A backend may keep state between calls (trees, device buffers), but the [`World`] is
/// the source of truth: after [`Backend::step`] returns, the world's dynamic state is the
/// new state, and a backend must notice changes the host made between steps (spawns,
/// despawns, teleports, actions) through the world's generation counters.
///
/// **Contract:** every backend produces the same world, bit for bit, from the same world
/// and constants (see `response` for how contact sums are ordered).
pub trait Backend: Send {
    /// Which implementation this is.
    fn kind(&self) -> BackendKind;

    /// A human-readable description (threads, device name, ...).
    fn description(&self) -> String;

    /// Advances the world by one tick.
    ///
    /// **The step is the single owner of `world.tick`:** it increments it by exactly one
    /// (NPC turns are drawn from it, and device copies are keyed on it); no caller, the
    /// server included, ever changes it.
    fn step(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError>;

    /// For each query box, the dynamic objects whose boxes overlap it (touching counts),
    /// at the world's current positions.
    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError>;

    /// The cuts between the zones that step the world, for a backend whose step is
    /// remote (a gateway of a zones cluster): what an operator's map draws. `None` (the
    /// default): the world is stepped here, in one piece.
    fn zone_cuts(&self) -> Option<ZoneCuts> {
        None
    }

    /// How many steps in a row may refit the dynamic tree before one builds it again (0:
    /// every step builds it; the default comes from `MYRIAD_TREE_REFITS`, see
    /// [`crate::lbvh::tree_refits`]). A backend without a dynamic tree ignores it.
    /// Results never depend on it, only the time of a step does.
    fn set_tree_refits(&mut self, _refits: u32) {}

    /// How many steps refit the dynamic tree since it was last built (`None`: no tree
    /// over the world's current objects, or a backend without one).
    fn tree_age(&self) -> Option<u32> {
        None
    }
}

/// How a zones cluster splits the world, as a gateway knows it ([`Backend::zone_cuts`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ZoneCuts {
    /// Cuts along x, ascending, the world's edges included.
    pub xs: Vec<f32>,
    /// Cuts along z, ascending, the world's edges included.
    pub zs: Vec<f32>,
    /// The zones' run (epoch) of the world the gateway shows (0: none taken yet).
    pub run: u64,
    /// The zones' tick of that world (`None`: none taken yet).
    pub zone_tick: Option<u64>,
    /// The zones' tick the cuts took effect at: a cut move's `apply_at`, the tick the
    /// run started from, or 0 for the layout every cluster starts with.
    pub since_tick: u64,
}

/// Creates one of the CPU backends this crate implements (`cpu-naive`, `cpu`).
///
/// This is not the backend factory: `myriad_cuda::create_backend` is, the one place
/// that knows every kind and resolves `auto` (to `cuda` when a GPU is usable, else
/// `cpu`). Asked for a CUDA kind or `auto`, this gives [`PhysicsError::Unavailable`].
pub fn create_cpu_backend(kind: BackendKind) -> Result<Box<dyn Backend>, PhysicsError> {
    Ok(match kind {
        BackendKind::CpuNaive => Box::new(crate::cpu::CpuNaive::default()),
        BackendKind::Cpu => Box::new(crate::cpu::CpuLbvh::default()),
        BackendKind::CudaNaive | BackendKind::Cuda | BackendKind::Auto => {
            return Err(PhysicsError::Unavailable {
                backend: kind.name(),
                reason: "the CUDA backends and auto are created by myriad_cuda::create_backend".into(),
            });
        }
        BackendKind::Zones => {
            return Err(PhysicsError::Unavailable {
                backend: kind.name(),
                reason: "a gateway's zones backend is built from its cluster (myriad_zone::ZonesBackend), \
                         not by a factory; choose a local backend"
                    .into(),
            });
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serde_and_command_line_names_agree() {
        for kind in BackendKind::EVERY {
            let json = serde_json::to_string(&kind).unwrap();
            assert_eq!(json, format!("\"{}\"", kind.name()));
            assert_eq!(serde_json::from_str::<BackendKind>(&json).unwrap(), kind);
            assert_eq!(kind.name().parse::<BackendKind>().unwrap(), kind);
        }
        assert!(serde_json::from_str::<BackendKind>("\"quantum\"").is_err());
    }
}
