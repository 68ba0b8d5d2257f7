//! Side-by-side comparisons of Myriad's physics with peer engines, for the benchmarks.
//!
//! This library holds only what does not depend on a peer: the AABB sets both sides are
//! given ([`aabb_set`]), Myriad's broad phase run standalone on such a set exactly as the
//! `cpu` backend runs it ([`ours`]), and pair-list helpers ([`pairs`]). The peer itself
//! (Rapier) is a dev-dependency: the code that drives it lives in `common/rapier_side.rs`,
//! compiled into the `rapier` bench and the `broad_phase_pairs` test only, so nothing that
//! depends on this crate ever builds Rapier.

pub mod aabb_set;
pub mod ours;
pub mod pairs;

pub use aabb_set::{AabbSet, Lattice};
pub use ours::OurBroadPhase;
pub use pairs::{PairDiff, Pairs, pack, unpack};
