//! Myriad's broad phase run standalone on an [`AabbSet`], call for call as the `cpu`
//! backend runs it inside a step (`myriad_physics::cpu`, `lbvh_backend.rs`):
//!
//! 1. object boxes `centre ± half` (parallel), then the dynamic LBVH rebuilt from scratch;
//! 2. dynamic–static pairs: every object's box queried against the static LBVH, objects
//!    taken in the dynamic tree's Morton order in chunks of 512, then a parallel sort;
//! 3. dynamic–dynamic pairs: the tree's self-query, then a parallel sort.
//!
//! The static tree is built once ([`OurBroadPhase::build_statics`]), as the backend
//! rebuilds it only when the statics change. The backend's own types are private, so
//! this repeats those few calls on the public [`Lbvh`] API; the test
//! `broad_phase_pairs.rs` checks that the pair counts equal the backend's `StepReport`.
//!
//! Everything runs on the rayon pool of the caller: install a one-thread pool to measure
//! it single-threaded.

use myriad_core::Aabb;
use myriad_physics::lbvh::{Lbvh, Stack};
use rayon::prelude::*;

use crate::aabb_set::AabbSet;
use crate::pairs::{Pairs, pack};

/// Objects per rayon task in the static query (the backend's `CHUNK`).
const CHUNK: usize = 512;

/// Myriad's two LBVHs and their buffers, reused between calls.
#[derive(Default)]
pub struct OurBroadPhase {
    statics: Lbvh,
    dynamics: Lbvh,
    aabbs: Vec<Aabb>,
}

impl OurBroadPhase {
    /// Builds the static tree over the set's static boxes.
    pub fn build_statics(&mut self, set: &AabbSet) {
        let boxes: Vec<Aabb> = set
            .static_centres
            .par_iter()
            .zip(set.static_halves.par_iter())
            .map(|(c, h)| Aabb::from_center_half(*c, *h))
            .collect();
        self.statics.build(&boxes, &set.bounds);
    }

    /// Every overlapping pair of the set's current dynamic boxes, with each other and
    /// with the static tree of the last [`OurBroadPhase::build_statics`]. Rebuilds the
    /// dynamic tree, as the backend does every tick.
    pub fn pairs(&mut self, set: &AabbSet, out: &mut Pairs) {
        out.clear();
        self.aabbs.clear();
        self.aabbs.par_extend(
            set.dynamic_centres
                .par_iter()
                .zip(set.dynamic_halves.par_iter())
                .map(|(c, h)| Aabb::from_center_half(*c, *h)),
        );
        self.dynamics.build(&self.aabbs, &set.bounds);

        let (tree, aabbs) = (&self.statics, &self.aabbs);
        let parts: Vec<Vec<u64>> = self
            .dynamics
            .leaf_order()
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut local = Vec::new();
                let mut stack = Stack::default();
                for &obj in chunk {
                    tree.query_with(&aabbs[obj as usize], &mut stack, |p| local.push(pack(obj, p)));
                }
                local
            })
            .collect();
        out.statics.reserve(parts.iter().map(Vec::len).sum());
        for p in parts {
            out.statics.extend_from_slice(&p);
        }
        out.statics.par_sort_unstable();

        self.dynamics.self_pairs(&mut out.dynamic);
        out.dynamic.par_sort_unstable();
    }
}
