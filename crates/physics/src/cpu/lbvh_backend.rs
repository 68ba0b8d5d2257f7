//! `cpu`: the parallel CPU backend, with an LBVH over the statics (rebuilt when they
//! change) and one over the dynamic objects (built every tick, or refit for up to
//! [`crate::lbvh::tree_refits`] ticks in a row while the objects stay the same).

use myriad_core::{Aabb, World};
use rayon::prelude::*;

use super::aoi_grid::AoiGrid;
use super::pipeline::{BroadPhase, Exec, Scratch, dynamic_aabbs, run_step};
use crate::backend::{AoiResults, Backend, BackendKind, StepReport};
use crate::consts::TickConstants;
use crate::error::PhysicsError;
use crate::lbvh::{Lbvh, Stack};

/// Objects handled per rayon task in the per-object traversals.
const CHUNK: usize = 512;

/// The rayon-parallel LBVH backend.
#[derive(Default)]
pub struct CpuLbvh {
    broad: Trees,
    scratch: Scratch,
    /// The AOI query's grid (the dynamic tree serves the step only).
    aoi: AoiGrid,
}

struct Trees {
    statics: Lbvh,
    /// (`Statics::stamp`, `Statics::generation`) the static tree was built for.
    statics_generation: Option<(u64, u64)>,
    dynamics: Lbvh,
    /// The world as the last step left it, and how many steps have refit the dynamic
    /// tree since it was built; `None` before a step.
    fit: Option<(Counters, u32)>,
    /// The age at which the dynamic tree is built again instead of refit.
    refits: u32,
}

impl Default for Trees {
    fn default() -> Trees {
        Trees {
            statics: Lbvh::default(),
            statics_generation: None,
            dynamics: Lbvh::default(),
            fit: None,
            refits: crate::lbvh::tree_refits(),
        }
    }
}

/// What tells whether the dynamic tree's leaves still mean the world's objects at the
/// places this backend last put them.
#[derive(Clone, Copy, PartialEq, Eq)]
struct Counters {
    stamp: u64,
    layout: u64,
    /// `generation - action_generation`: every change but a new action.
    moves: u64,
}

impl Counters {
    fn of(world: &World) -> Counters {
        let d = &world.dynamics;
        Counters {
            stamp: d.stamp(),
            layout: d.layout_generation(),
            moves: d.generation().wrapping_sub(d.action_generation()),
        }
    }
}

impl Trees {
    fn ensure_statics(&mut self, world: &World) {
        let st = &world.statics;
        let key = (st.stamp(), st.generation());
        if self.statics_generation != Some(key) {
            let boxes: Vec<Aabb> = (0..st.prim_count()).into_par_iter().map(|i| st.aabb(i)).collect();
            self.statics.build(&boxes, &world.bounds);
            self.statics_generation = Some(key);
        }
    }
}

impl BroadPhase for Trees {
    fn build_dynamic(&mut self, world: &World, aabbs: &[Aabb]) {
        // Refit only a tree over the same objects, which only this backend's steps and
        // new actions changed since (a teleport may put an object anywhere).
        let now = Counters::of(world);
        match self.fit {
            Some((seen, age)) if seen == now && age < self.refits && self.dynamics.len() == aabbs.len() => {
                self.dynamics.refit(aabbs);
                self.fit = Some((seen, age + 1));
            }
            _ => {
                self.dynamics.build(aabbs, &world.bounds);
                self.fit = Some((now, 0));
            }
        }
    }

    fn stepped(&mut self, world: &World) {
        if let Some((seen, _)) = &mut self.fit {
            *seen = Counters::of(world);
        }
    }

    fn static_pairs(&mut self, world: &World, aabbs: &[Aabb], out: &mut Vec<u64>) {
        self.ensure_statics(world);
        let tree = &self.statics;
        // Query in the dynamic tree's Morton order: consecutive queries then walk the
        // same parts of the static tree. The canonical order is restored by the sort.
        let parts: Vec<Vec<u64>> = self
            .dynamics
            .leaf_order()
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut local = Vec::new();
                let mut stack = Stack::default();
                for &obj in chunk {
                    let key = (obj as u64) << 32;
                    tree.query_with(&aabbs[obj as usize], &mut stack, |p| local.push(key | p as u64));
                }
                local
            })
            .collect();
        out.reserve(parts.iter().map(Vec::len).sum());
        for p in parts {
            out.extend_from_slice(&p);
        }
        // Pairs are unique, so an unstable sort is still deterministic.
        out.par_sort_unstable();
    }

    fn dynamic_pairs(&mut self, _aabbs: &[Aabb], out: &mut Vec<u64>) {
        self.dynamics.self_pairs(out);
        // Pairs are unique, so an unstable sort is still deterministic.
        out.par_sort_unstable();
    }
}

impl Backend for CpuLbvh {
    fn kind(&self) -> BackendKind {
        BackendKind::Cpu
    }

    fn description(&self) -> String {
        format!("cpu (rayon, {} threads, LBVH)", rayon::current_num_threads())
    }

    fn step(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        if world.dynamics.len() >= 1 << 31 {
            return Err(PhysicsError::TooManyObjects { count: world.dynamics.len(), max: (1 << 31) - 1 });
        }
        Ok(run_step(Exec::Parallel, world, k, &mut self.broad, &mut self.scratch))
    }

    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        let d = &world.dynamics;
        self.aoi.prepare((d.stamp(), d.generation()), |aabbs| dynamic_aabbs(Exec::Parallel, d, aabbs), boxes);
        self.aoi.query_all(boxes, &mut out.offsets, &mut out.objects);
        Ok(())
    }

    fn set_tree_refits(&mut self, refits: u32) {
        self.broad.refits = refits;
    }

    fn tree_age(&self) -> Option<u32> {
        self.broad.fit.map(|(_, age)| age)
    }
}
