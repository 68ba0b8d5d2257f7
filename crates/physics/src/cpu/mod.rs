//! The CPU backends: [`CpuNaive`] (one thread, all pairs) and [`CpuLbvh`] (rayon, LBVH).
//!
//! Both run the same step (`pipeline.rs`); they differ only in how candidate pairs are found
//! (the `BroadPhase` trait there) and whether stages run on one thread or on rayon's pool.
//! Everything after the broad phase is shared code, and the broad phases produce the same
//! canonically sorted pair lists, which is why the two agree bit for bit.

mod aoi_grid;
mod lbvh_backend;
mod naive;
pub(crate) mod pipeline;

pub use lbvh_backend::CpuLbvh;
pub use naive::CpuNaive;
