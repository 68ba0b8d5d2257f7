//! Linear bounding volume hierarchy after Karras, "Maximizing Parallelism in the
//! Construction of BVHs, Octrees, and k-d Trees" (HPG 2012).
//!
//! # How it works
//! 1. Each object's box centre gets a 63-bit Morton code over the world bounds
//!    ([`morton`]); any world size and origin work.
//! 2. The codes are radix-sorted with the object indices as values ([`radix`]); the
//!    sorted order is the leaf order.
//! 3. The `n - 1` internal nodes are emitted in parallel, each independently: node `i`
//!    finds the direction and extent of its key range and its split by binary searches
//!    on the length of common prefixes (δ). **Duplicate codes** are handled with Karras's
//!    tie-break: when two codes are equal, δ is `64 + clz(i ^ j)` on the leaf indices, as
//!    if each key were extended by its position.
//! 4. Boxes are refitted bottom-up in parallel: each leaf walks towards the root and an
//!    atomic counter per node stops the first of the two children to arrive, so the
//!    second computes the union once both are final.
//! 5. Queries walk the tree with a fixed stack. δ strictly grows from a node to its
//!    internal children, so the depth is at most 97 and a stack of 128 never overflows.
//!
//! Every node also records the last leaf of its range, which lets the self-query report
//! each pair once (only leaves after the querying one), the role the reference gave to
//! "the largest Morton code reachable".
//!
//! # Performance note
//! The build is O(n log n) in the sort and O(n) otherwise, all stages parallel. A
//! backend may [`Lbvh::refit`] its dynamic tree for up to [`tree_refits`] steps in a row
//! before it builds it again: a refit skips the Morton codes, the sort and the emission,
//! and the tree's nodes fit a little less tightly each step the objects move.

pub mod morton;
pub mod radix;

use std::sync::atomic::{AtomicU32, Ordering};

use myriad_core::Aabb;
use rayon::prelude::*;

use crate::par::SharedMut;
use morton::MortonFrame;

/// How many steps in a row a backend refits its dynamic tree before one builds it again,
/// unless `MYRIAD_TREE_REFITS` says otherwise ([`tree_refits`]). Results never depend on
/// it: what the broad phase reports is sorted, so a tree's shape never shows.
pub const TREE_REFITS: u32 = 7;

/// `MYRIAD_TREE_REFITS` (a count of steps; 0: every step builds its tree), or
/// [`TREE_REFITS`] when it is unset. A value that is not a count is reported on stderr
/// and ignored. Read when a backend is created.
pub fn tree_refits() -> u32 {
    match std::env::var("MYRIAD_TREE_REFITS") {
        Err(_) => TREE_REFITS,
        Ok(v) => v.trim().parse().unwrap_or_else(|_| {
            eprintln!("MYRIAD_TREE_REFITS={v:?} is not a count of steps; using {TREE_REFITS}");
            TREE_REFITS
        }),
    }
}

/// Marks a child reference as a leaf (leaf index in the low bits).
const LEAF: u32 = 1 << 31;
/// Traversal stack capacity; see the module docs for why it is never exceeded.
const STACK: usize = 128;

/// Scratch space for one traversal, reused across queries (clearing a fresh array per
/// query costs more than the query on small trees).
pub struct Stack([u32; STACK]);

impl Default for Stack {
    fn default() -> Self {
        Stack([0; STACK])
    }
}

/// An internal node. It holds its children's boxes rather than its own, so a traversal
/// step tests both children from one 64-byte cache line without touching them.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Node {
    /// Boxes of the left and right child.
    boxes: [Aabb; 2],
    /// Children: an internal node index, or a leaf index with [`LEAF`] set.
    child: [u32; 2],
    /// The last (highest) leaf index under each child.
    last: [u32; 2],
}

/// A linear BVH over a set of boxes.
#[derive(Debug, Default)]
pub struct Lbvh {
    /// `order[leaf]` is the caller's index of the box in that leaf.
    order: Vec<u32>,
    /// Leaf boxes in leaf order.
    leaves: Vec<Aabb>,
    /// Internal nodes; the root is node 0 when there are at least two leaves.
    nodes: Vec<Node>,
    /// Parent of each internal node (the root's is unused) and of each leaf.
    node_parent: Vec<AtomicU32>,
    leaf_parent: Vec<AtomicU32>,
    /// Per-node arrival counters of the refit, reset before each refit.
    arrivals: Vec<AtomicU32>,
    scratch_keys: Vec<u64>,
    scratch_values: Vec<u32>,
    keys: Vec<u64>,
}

impl Lbvh {
    /// Number of leaves.
    pub fn len(&self) -> usize {
        self.leaves.len()
    }

    /// The caller's indices in leaf (Morton) order: neighbours in this order are
    /// neighbours in space, so processing objects in it keeps caches warm.
    pub fn leaf_order(&self) -> &[u32] {
        &self.order
    }

    /// Whether the tree is empty.
    pub fn is_empty(&self) -> bool {
        self.leaves.is_empty()
    }

    /// Rebuilds the tree over `boxes`, with Morton codes over `bounds`. Buffers are reused
    /// between builds. At most 2^31 - 1 boxes.
    pub fn build(&mut self, boxes: &[Aabb], bounds: &Aabb) {
        let n = boxes.len();
        assert!(n < LEAF as usize, "an LBVH holds fewer than 2^31 leaves");
        let frame = MortonFrame::new(bounds);
        self.keys.clear();
        self.keys.par_extend(boxes.par_iter().map(|b| frame.code(b.center())));
        self.order.clear();
        self.order.par_extend(0..n as u32);
        radix::sort_pairs(
            &mut self.keys,
            &mut self.order,
            3 * morton::BITS_PER_AXIS,
            &mut self.scratch_keys,
            &mut self.scratch_values,
        );
        self.leaves.clear();
        self.leaves.par_extend(self.order.par_iter().map(|&o| boxes[o as usize]));
        self.emit_hierarchy();
        self.refit_internal();
    }

    /// Updates every box without changing the topology (positions moved, the set of
    /// objects did not). `boxes` is indexed like the `build` input. Queries stay exact;
    /// only their speed degrades as objects drift from their build-time neighbours.
    pub fn refit(&mut self, boxes: &[Aabb]) {
        assert_eq!(boxes.len(), self.leaves.len(), "refit needs the same objects as the build");
        let order = &self.order;
        self.leaves.par_iter_mut().zip(order.par_iter()).for_each(|(l, &o)| *l = boxes[o as usize]);
        self.refit_internal();
    }

    /// δ(i, j): the length of the common prefix of the keys of leaves `i` and `j`, with the
    /// leaf index appended to break ties; −1 outside the leaves.
    #[inline]
    fn delta(keys: &[u64], i: i64, j: i64) -> i32 {
        if j < 0 || j >= keys.len() as i64 {
            return -1;
        }
        let (a, b) = (keys[i as usize], keys[j as usize]);
        if a == b { 64 + ((i as u32) ^ (j as u32)).leading_zeros() as i32 } else { (a ^ b).leading_zeros() as i32 }
    }

    /// Karras's parallel construction of the internal nodes (boxes are filled by refit).
    fn emit_hierarchy(&mut self) {
        let n = self.leaves.len();
        self.nodes.clear();
        if n < 2 {
            return;
        }
        let keys = &self.keys;
        self.nodes.par_extend((0..n - 1).into_par_iter().map(|i| {
            let i = i as i64;
            let d: i64 = if Self::delta(keys, i, i + 1) - Self::delta(keys, i, i - 1) >= 0 { 1 } else { -1 };
            // Upper bound of the range length, then its exact length, by doubling and
            // binary search on δ.
            let dmin = Self::delta(keys, i, i - d);
            let mut lmax: i64 = 2;
            while Self::delta(keys, i, i + lmax * d) > dmin {
                lmax *= 2;
            }
            let mut l: i64 = 0;
            let mut t = lmax / 2;
            while t >= 1 {
                if Self::delta(keys, i, i + (l + t) * d) > dmin {
                    l += t;
                }
                t /= 2;
            }
            let j = i + l * d;
            // The split: the last position sharing more than δ(i, j) bits with i.
            let dnode = Self::delta(keys, i, j);
            let mut s: i64 = 0;
            let mut div: i64 = 2;
            loop {
                let t = (l + div - 1) / div;
                if Self::delta(keys, i, i + (s + t) * d) > dnode {
                    s += t;
                }
                if t == 1 {
                    break;
                }
                div *= 2;
            }
            let gamma = i + s * d + d.min(0);
            let (first, last) = (i.min(j), i.max(j));
            let left = if first == gamma { gamma as u32 | LEAF } else { gamma as u32 };
            let right = if last == gamma + 1 { (gamma + 1) as u32 | LEAF } else { (gamma + 1) as u32 };
            // The left child covers [first, gamma], the right one [gamma + 1, last].
            Node { boxes: [Aabb::EMPTY; 2], child: [left, right], last: [gamma as u32, last as u32] }
        }));
        // Parents: every node except the root is the child of exactly one node.
        // Buffers persist between builds; every entry is overwritten below.
        self.node_parent.resize_with(n - 1, AtomicU32::default);
        self.leaf_parent.resize_with(n, AtomicU32::default);
        let (node_parent, leaf_parent) = (&self.node_parent, &self.leaf_parent);
        self.nodes.par_iter().enumerate().for_each(|(p, node)| {
            for c in node.child {
                let slot = if c & LEAF != 0 { &leaf_parent[(c & !LEAF) as usize] } else { &node_parent[c as usize] };
                slot.store(p as u32, Ordering::Relaxed);
            }
        });
    }

    /// Bottom-up union of the internal boxes from the leaf boxes.
    fn refit_internal(&mut self) {
        let n = self.leaves.len();
        if n < 2 {
            return;
        }
        self.arrivals.resize_with(n - 1, AtomicU32::default);
        self.arrivals.par_iter().for_each(|a| a.store(0, Ordering::Relaxed));
        let arrivals = &self.arrivals;
        let leaves = &self.leaves;
        let node_parent = &self.node_parent;
        let leaf_parent = &self.leaf_parent;
        let nodes = SharedMut::new(&mut self.nodes);
        // Stores `aabb` as the box of child `c` in its parent `p`. The two children of a
        // node write different fields of it, so only that field is written.
        let store_side = |p: usize, c: u32, aabb: Aabb| {
            // SAFETY: `p` is in bounds; `child` was written before this parallel phase and
            // is only read; box `side` of `p` is written by the thread that finished child
            // `c`, once, and read only after the parent's arrival counter orders it.
            unsafe {
                let node = nodes.ptr(p);
                let side = usize::from((*node).child[1] == c);
                std::ptr::addr_of_mut!((*node).boxes[side]).write(aabb);
            }
        };
        (0..n).into_par_iter().for_each(|leaf| {
            let mut node = leaf_parent[leaf].load(Ordering::Relaxed) as usize;
            let mut from = leaf as u32 | LEAF;
            let mut aabb = leaves[leaf];
            loop {
                // Both children write into the same parent, so the writes themselves
                // must not overlap: each thread writes its side, then arrives; the
                // first to arrive stops and the second (which sees 1) finds both sides
                // final. AcqRel orders the first one's write before the second's read.
                store_side(node, from, aabb);
                if arrivals[node].fetch_add(1, Ordering::AcqRel) == 0 {
                    return;
                }
                // SAFETY: only the second arrival reaches here, once per node, after both
                // sides were stored.
                let current = unsafe { nodes.read(node) };
                aabb = current.boxes[0].union(&current.boxes[1]);
                if node == 0 {
                    return;
                }
                from = node as u32;
                node = node_parent[node].load(Ordering::Relaxed) as usize;
            }
        });
    }

    /// Calls `f(leaf)` for every leaf whose box overlaps `query`, with leaf index at least
    /// `min_leaf`. `stack` is scratch space, reused between calls to avoid clearing a
    /// fresh array per query.
    #[inline]
    fn visit(&self, query: &Aabb, min_leaf: u32, stack: &mut Stack, mut f: impl FnMut(u32)) {
        let n = self.leaves.len();
        if n < 2 {
            if n == 1 && min_leaf == 0 && self.leaves[0].overlaps(query) {
                f(0);
            }
            return;
        }
        let stack = &mut stack.0;
        stack[0] = 0; // the root
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            // Written out for both sides: a loop over the two sides costs more than the
            // box tests themselves here, the hottest loop of the CPU backend.
            if node.last[0] >= min_leaf && node.boxes[0].overlaps(query) {
                let c = node.child[0];
                if c & LEAF != 0 {
                    f(c & !LEAF);
                } else {
                    stack[top] = c;
                    top += 1;
                }
            }
            if node.last[1] >= min_leaf && node.boxes[1].overlaps(query) {
                let c = node.child[1];
                if c & LEAF != 0 {
                    f(c & !LEAF);
                } else {
                    // Cannot overflow: the depth is at most 97 (module docs) and each
                    // level leaves at most one sibling on the stack.
                    stack[top] = c;
                    top += 1;
                }
            }
        }
    }

    /// Calls `f(index)` with the caller's index of every box overlapping `query`.
    #[inline]
    pub fn query(&self, query: &Aabb, f: impl FnMut(u32)) {
        self.query_with(query, &mut Stack::default(), f);
    }

    /// [`Lbvh::query`] with a caller-provided traversal stack, for loops of queries.
    #[inline]
    pub fn query_with(&self, query: &Aabb, stack: &mut Stack, mut f: impl FnMut(u32)) {
        self.visit(query, 0, stack, |leaf| f(self.order[leaf as usize]));
    }

    /// Every overlapping pair of boxes, as `(min index, max index)` packed into a `u64`
    /// (`min << 32 | max`), appended to `out` in no particular order. Parallel over leaves.
    pub fn self_pairs(&self, out: &mut Vec<u64>) {
        let n = self.leaves.len();
        let chunk = 256;
        let parts: Vec<Vec<u64>> = (0..n.div_ceil(chunk))
            .into_par_iter()
            .map(|c| {
                let mut local = Vec::new();
                let mut stack = Stack::default();
                for leaf in c * chunk..((c + 1) * chunk).min(n) {
                    let a = self.order[leaf];
                    self.visit(&self.leaves[leaf], leaf as u32 + 1, &mut stack, |other| {
                        let b = self.order[other as usize];
                        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
                        local.push((lo as u64) << 32 | hi as u64);
                    });
                }
                local
            })
            .collect();
        out.reserve(parts.iter().map(Vec::len).sum());
        for p in parts {
            out.extend_from_slice(&p);
        }
    }
}

#[cfg(test)]
mod tests;
