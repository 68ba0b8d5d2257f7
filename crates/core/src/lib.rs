//! The world model of Myriad: everything the simulation, the network and the store share.
//!
//! - [`shape`]: the three primitive shapes (sphere, axis-aligned box, vertical capsule) and
//!   their compact form, half extents plus radius, which every backend uses.
//! - [`aabb`]: axis-aligned bounding boxes.
//! - [`world`]: the world state: dynamic objects in structure-of-arrays form ([`Dynamics`]),
//!   static scenery made of primitives ([`Statics`]), the terrain and the world bounds.
//! - [`terrain`]: the heightmap, generated from a seed or loaded from a file, with the
//!   bilinear sampling every backend must reproduce bit for bit.
//! - [`scenario`]: seeded generators for the reference's three scenarios, scenario 4
//!   (scenario 3 scaled to 50,000 players) and custom ones;
//!   [`crowd`]: a crowd walking across the map (its load moves from zone to zone).
//! - [`rng`]: counter-based random numbers (a hash of seed, object and tick), the same on
//!   every machine and reproducible on a GPU.
//! - [`config`]: the physics parameters shared by all backends.
//! - [`script`]: scripted actions for reproducible runs (`myriad sim --actions`).
//!
//! This crate does no I/O beyond reading heightmap files and knows nothing about
//! backends, sockets or databases.

pub mod aabb;
pub mod action;
pub mod config;
pub mod crowd;
pub mod error;
pub mod rng;
pub mod scenario;
pub mod script;
pub mod shape;
pub mod stamp;
pub mod terrain;
pub mod world;

pub use aabb::Aabb;
pub use action::Action;
pub use config::PhysicsConfig;
pub use crowd::MovingCrowd;
pub use error::CoreError;
pub use glam::Vec3;
pub use scenario::{NUMBERED_SCENARIOS, Placement, ScenarioSpec};
pub use script::{ActionScript, ScriptError, ScriptedAction};
pub use shape::{Shape, ShapeKind};
pub use stamp::Stamp;
pub use terrain::Terrain;
pub use world::{Dynamics, EntityId, HeldState, ObjectKind, ObjectState, StaticKind, Statics, World, hash_state};
