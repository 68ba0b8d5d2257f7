//! Physics of Myriad: broad phase on linear BVHs, exact narrow phase for the six shape
//! pairs, impulse responses, Verlet integration, terrain and world limits, behind one
//! [`Backend`] trait with CPU implementations (the CUDA ones live in their own crate).
//!
//! Module map:
//! - [`narrow`]: contact tests, one file per shape pair;
//! - [`response`]: what a contact does, and the deterministic per-object gather;
//! - [`integrate`]: NPC random walk, forces, Verlet step, limits;
//! - [`lbvh`]: Karras's linear BVH with Morton codes and a radix sort;
//! - [`cpu`]: the `cpu-naive` and `cpu` backends over one shared pipeline;
//! - [`backend`]: the trait, stage names and reports;
//! - [`consts`]: per-tick constants shared by every backend;
//! - [`conformance`]: the behaviour every backend must show, as checks any backend's
//!   tests can run.
//!
//! No I/O happens here.

pub mod backend;
pub mod conformance;
pub mod consts;
pub mod cpu;
pub mod error;
pub mod integrate;
pub mod lbvh;
pub mod narrow;
mod par;
pub mod response;

pub use backend::{AoiResults, Backend, BackendKind, Stage, StepReport, ZoneCuts, create_cpu_backend};
pub use consts::TickConstants;
pub use error::PhysicsError;
