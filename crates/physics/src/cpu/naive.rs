//! `cpu-naive`: one thread, every pair tested (the reference's "CPU" column).

use myriad_core::{Aabb, World};

use super::pipeline::{BroadPhase, Exec, Scratch, dynamic_aabbs, run_step};
use crate::backend::{AoiResults, Backend, BackendKind, StepReport};
use crate::consts::TickConstants;
use crate::error::PhysicsError;

/// The all-pairs CPU backend. Its cost grows with the square of the object count: it is
/// the baseline the others are checked and measured against.
#[derive(Default)]
pub struct CpuNaive {
    broad: AllPairs,
    scratch: Scratch,
}

#[derive(Default)]
struct AllPairs {
    static_aabbs: Vec<Aabb>,
}

impl BroadPhase for AllPairs {
    fn build_dynamic(&mut self, world: &World, _aabbs: &[Aabb]) {
        let st = &world.statics;
        self.static_aabbs.clear();
        self.static_aabbs.extend((0..st.prim_count()).map(|i| st.aabb(i)));
    }

    fn static_pairs(&mut self, _world: &World, aabbs: &[Aabb], out: &mut Vec<u64>) {
        for (i, a) in aabbs.iter().enumerate() {
            for (p, b) in self.static_aabbs.iter().enumerate() {
                if a.overlaps(b) {
                    out.push((i as u64) << 32 | p as u64);
                }
            }
        }
    }

    fn dynamic_pairs(&mut self, aabbs: &[Aabb], out: &mut Vec<u64>) {
        for (i, a) in aabbs.iter().enumerate() {
            for (j, b) in aabbs.iter().enumerate().skip(i + 1) {
                if a.overlaps(b) {
                    out.push((i as u64) << 32 | j as u64);
                }
            }
        }
    }
}

impl Backend for CpuNaive {
    fn kind(&self) -> BackendKind {
        BackendKind::CpuNaive
    }

    fn description(&self) -> String {
        "cpu-naive (1 thread, all pairs)".into()
    }

    fn step(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        Ok(run_step(Exec::Serial, world, k, &mut self.broad, &mut self.scratch))
    }

    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        let aabbs = &mut self.scratch.aabbs;
        dynamic_aabbs(Exec::Serial, &world.dynamics, aabbs);
        out.clear();
        out.offsets.push(0);
        for q in boxes {
            out.objects.extend((0..aabbs.len() as u32).filter(|&i| aabbs[i as usize].overlaps(q)));
            out.offsets.push(out.objects.len() as u32);
        }
        Ok(())
    }
}
