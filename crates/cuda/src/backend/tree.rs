//! The linear BVH on the device (`kernels/lbvh.cu`): boxes and Morton codes, the
//! one-sweep radix sort, Karras emission and the refit; and the dynamic boxes (or tree)
//! each step starts from.

use myriad_core::World;
use myriad_physics::PhysicsError;
use myriad_physics::lbvh::morton::MortonFrame;

use super::Resident;
use crate::device::{DevBuf, Gpu};
use crate::launch::{DevPtr, KBoxes, KBoxesMorton, KEmit, KRadixCounts, KRadixPass, KRefit, Node};

/// Passes of 8 bits over the 63-bit Morton codes.
const RADIX_PASSES: u32 = 8;
/// Keys per tile of a radix pass (one block of `k_radix_pass`).
const RADIX_TILE: usize = 2048;
/// Bytes of one internal node (`struct Node` in `kernels/lbvh.cu`).
pub(super) const NODE_BYTES: usize = 64;

const _: () = assert!(std::mem::size_of::<Node>() == NODE_BYTES);

/// What a tree is built (or refit) over: `n` objects at `pos ± half`, whose boxes it
/// writes into `boxes` (packed floats on the device).
#[derive(Clone, Copy)]
pub(super) struct Leaves {
    pub n: usize,
    pub pos: DevPtr<f32>,
    pub half: DevPtr<f32>,
    pub boxes: DevPtr<f32>,
}

/// A linear BVH on the device (`kernels/lbvh.cu`).
pub(super) struct Tree {
    keys: DevBuf<u64>,
    keys_tmp: DevBuf<u64>,
    /// `order[leaf]`: the object (or primitive) in that leaf.
    pub order: DevBuf<u32>,
    order_tmp: DevBuf<u32>,
    pub nodes: DevBuf<Node>,
    node_parent: DevBuf<u32>,
    leaf_parent: DevBuf<u32>,
    arrivals: DevBuf<u32>,
    hist: DevBuf<u32>,
    pub leaves: usize,
}

impl Tree {
    /// An empty tree; the first build allocates.
    pub fn new() -> Tree {
        Tree {
            keys: DevBuf::empty(),
            keys_tmp: DevBuf::empty(),
            order: DevBuf::empty(),
            order_tmp: DevBuf::empty(),
            nodes: DevBuf::empty(),
            node_parent: DevBuf::empty(),
            leaf_parent: DevBuf::empty(),
            arrivals: DevBuf::empty(),
            hist: DevBuf::empty(),
            leaves: 0,
        }
    }

    /// Writes the boxes of the leaves' objects into their `boxes` and builds the tree over
    /// them.
    pub fn build(&mut self, gpu: &Gpu, leaves: Leaves, frame: &MortonFrame) -> Result<(), PhysicsError> {
        let Leaves { n, pos, half, boxes } = leaves;
        self.leaves = n;
        if n == 0 {
            return Ok(());
        }
        for b in [&mut self.keys, &mut self.keys_tmp] {
            b.ensure(gpu, n * 8, 1.25)?;
        }
        for b in
            [&mut self.order, &mut self.order_tmp, &mut self.leaf_parent, &mut self.node_parent, &mut self.arrivals]
        {
            b.ensure(gpu, n * 4, 1.25)?;
        }
        self.nodes.ensure(gpu, n * NODE_BYTES, 1.25)?;
        let (m, s) = (frame.min, frame.scale);
        gpu.launch(
            n,
            KBoxesMorton {
                n: n as u32,
                pos,
                half,
                boxes,
                keys: self.keys.ptr(),
                vals: self.order.ptr(),
                mx: m.x,
                my: m.y,
                mz: m.z,
                sx: s.x,
                sy: s.y,
                sz: s.z,
            },
        )?;
        // One-sweep radix sort: the digit counts of all passes, then one launch a pass.
        // `hist` holds the 8 x 256 counts, the 8 tile counters and 8 x 256 status words
        // a tile, all zeroed at once.
        let tiles = n.div_ceil(RADIX_TILE);
        let words = RADIX_PASSES as usize * (256 + 1 + 256 * tiles);
        self.hist.ensure(gpu, words * 4, 1.25)?;
        gpu.zero(self.hist.ptr(), words)?;
        let counters = self.hist.ptr().add(256 * RADIX_PASSES as usize);
        let status = counters.add(RADIX_PASSES as usize);
        let blocks = n.div_ceil(256).min(1024);
        gpu.launch_grid(
            blocks as u32,
            256,
            KRadixCounts { keys: self.keys.ptr(), n: n as u32, hist: self.hist.ptr() },
        )?;
        for pass in 0..RADIX_PASSES {
            gpu.launch_grid(
                tiles as u32,
                256,
                KRadixPass {
                    keys_in: self.keys.ptr(),
                    vals_in: self.order.ptr(),
                    keys_out: self.keys_tmp.ptr(),
                    vals_out: self.order_tmp.ptr(),
                    n: n as u32,
                    pass,
                    hist: self.hist.ptr(),
                    status: status.add(pass as usize * 256 * tiles),
                    tile_counter: counters.add(pass as usize),
                },
            )?;
            std::mem::swap(&mut self.keys, &mut self.keys_tmp);
            std::mem::swap(&mut self.order, &mut self.order_tmp);
        }
        if n >= 2 {
            gpu.launch(
                n - 1,
                KEmit {
                    keys: self.keys.ptr(),
                    n: n as u32,
                    nodes: self.nodes.ptr(),
                    node_parent: self.node_parent.ptr(),
                    leaf_parent: self.leaf_parent.ptr(),
                },
            )?;
            gpu.zero(self.arrivals.ptr(), n - 1)?;
            self.launch_refit(gpu, n, boxes)?;
        }
        Ok(())
    }

    /// Writes the boxes of the same `n` objects, at their new positions, and refits the
    /// tree's node boxes over them, keeping its shape and leaf order: every box still
    /// bounds its subtree, so the walks find every overlap (what the broad phase reports
    /// is sorted, so the tree's shape never shows in a result); only how tightly the
    /// nodes fit degrades as the objects move. The caller makes sure `n` and the slots'
    /// meaning are those of the last build.
    pub fn refit(&mut self, gpu: &Gpu, leaves: Leaves) -> Result<(), PhysicsError> {
        let Leaves { n, pos, half, boxes } = leaves;
        debug_assert_eq!(n, self.leaves, "a refit keeps the tree's leaves");
        if n == 0 {
            return Ok(());
        }
        gpu.launch(n, KBoxes { n: n as u32, pos, half, boxes })?;
        if n >= 2 {
            gpu.zero(self.arrivals.ptr(), n - 1)?;
            self.launch_refit(gpu, n, boxes)?;
        }
        Ok(())
    }

    /// `k_refit` over this tree's leaves, whose boxes are in `boxes`.
    fn launch_refit(&self, gpu: &Gpu, n: usize, boxes: DevPtr<f32>) -> Result<(), PhysicsError> {
        gpu.launch(
            n,
            KRefit {
                n: n as u32,
                order: self.order.ptr(),
                boxes,
                nodes: self.nodes.ptr(),
                node_parent: self.node_parent.ptr(),
                leaf_parent: self.leaf_parent.ptr(),
                arrivals: self.arrivals.ptr(),
            },
        )
    }
}

impl Resident {
    /// Dynamic boxes (and, for `cuda`, the dynamic tree) at the device's positions: the
    /// last tree refit when it is over the same slots and has been refit fewer than
    /// `tree_refits` times since it was built, else a new one.
    pub(super) fn build_dynamic(&mut self, world: &World) -> Result<(), PhysicsError> {
        if self.naive() {
            return self.build_boxes();
        }
        let o = &self.obj;
        let leaves = Leaves { n: self.n, pos: o.pos.ptr(), half: o.half.ptr(), boxes: o.boxes.ptr() };
        match self.tree_age {
            Some(age) if age < self.tree_refits && self.dyn_tree.leaves == self.n => {
                self.dyn_tree.refit(&self.gpu, leaves)?;
                self.tree_age = Some(age + 1);
            }
            _ => {
                let frame = MortonFrame::new(&world.bounds);
                self.dyn_tree.build(&self.gpu, leaves, &frame)?;
                self.tree_age = Some(0);
            }
        }
        Ok(())
    }

    /// The dynamic boxes alone (the same boxes as the tree's build writes).
    pub(super) fn build_boxes(&mut self) -> Result<(), PhysicsError> {
        let o = &self.obj;
        self.gpu.launch(self.n, KBoxes { n: self.n as u32, pos: o.pos.ptr(), half: o.half.ptr(), boxes: o.boxes.ptr() })
    }
}
