//! `myriad-viewer`, the visual client of Myriad: logs in one player and shows the world
//! around it as the reference's Unity client did — the heightmap terrain, the static
//! scenery, the dynamic objects in view drawn by shape with GPU instancing, a
//! third-person camera, arrow keys and space, and a status line. It logs in again, with
//! backoff, when its session ends or the server restarts.
//!
//! - [`scene`]: what to draw as plain data (terrain mesh, instance transforms, colours,
//!   the view filter); no GL, unit-tested.
//! - [`camera`]: the follow camera's math.
//! - [`input`]: keys to the protocol's action mask.
//! - [`hud`]: the status line, ping, bandwidth and frame-time measurements.
//! - [`net`]: the network thread and the snapshots it publishes; it logs in again when a
//!   session ends.
//! - [`reconnect`]: the backoff schedule and the link state of the status line.
//! - [`screenshot`]: saving a frame as PNG.
//! - [`app`]: the window and the render loop (the only module that needs GL).
//! - [`args`]: command-line flags.

pub mod app;
pub mod args;
pub mod camera;
pub mod hud;
pub mod input;
pub mod net;
pub mod reconnect;
pub mod scene;
pub mod screenshot;

pub use app::run;
pub use args::Args;
