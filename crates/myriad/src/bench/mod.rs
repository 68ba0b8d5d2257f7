//! `myriad bench`: every scenario on every backend, medians per stage, in the layout of
//! the reference's Tables 1 and 2.
//!
//! [`measure`] runs the backends' steps and the server ticks and gives one [`Row`] per
//! run; [`report`] writes the rows as Markdown tables, JSON lines or CSV.

mod measure;
mod pace;
mod quality;
mod report;
mod shadow;

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use myriad_client::{Interpolation, Percentiles, QualitySummary};
use myriad_physics::BackendKind;
use myriad_server::ServerConfig;
use serde::Serialize;

use crate::scenario_args::{ScenarioName, WorldArgs};

/// Output formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Format {
    /// Markdown tables next to the reference's.
    Md,
    /// One JSON object per line.
    Json,
    /// Comma-separated values with a header.
    Csv,
}

/// Flags of `myriad bench`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Scenarios, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "1,2,3")]
    pub scenario: Vec<ScenarioName>,
    /// Backends, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "cpu,cpu-naive")]
    pub backend: Vec<BackendKind>,
    /// Measured ticks per run (after the warm-up).
    #[arg(long, default_value_t = 30)]
    pub ticks: u64,
    /// Ticks run before measuring.
    #[arg(long, default_value_t = 3)]
    pub warmup: u64,
    /// Output format on standard output.
    #[arg(long, value_enum, default_value = "md")]
    pub format: Format,
    /// Also write bench.md, bench.json, bench.csv and the plots (PNG and SVG) into this
    /// directory.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Run backends even when a tick takes longer than --max-tick-ms.
    #[arg(long)]
    pub force: bool,
    /// A backend whose first tick takes longer than this is skipped (the reference's "-").
    #[arg(long, default_value_t = 1000.0)]
    pub max_tick_ms: f64,
    /// Also run a scale sweep over these dynamic-object counts (comma-separated, e.g.
    /// 10000,100000,1000000): statics at half the count, users at 1/26 (scenario 3's
    /// share), the map grown to keep scenario 2's density.
    #[arg(long, value_delimiter = ',')]
    pub sweep: Vec<u32>,
    /// Skip the end-to-end server tick (by default each scenario also runs the full
    /// server tick on every non-naive backend, with one bot per user on loopback, for
    /// the `packets`, `send` and `receive` columns).
    #[arg(long)]
    pub physics_only: bool,
    /// Area-of-interest edge lengths of the server tick, in world units (comma-separated:
    /// one server-tick row per size, e.g. `14,100`).
    #[arg(long, value_delimiter = ',', default_values_t = [ServerConfig::default().aoi_size])]
    pub aoi_size: Vec<f32>,
    /// The server tick's per-player send budget, kbit/s (config `send_budget_kbps`).
    #[arg(long, default_value_t = ServerConfig::default().send_budget_kbps)]
    pub send_budget_kbps: f64,
    /// UDP sockets the server tick sends on (config `udp_sockets`: 0 is one per core, at
    /// most 64).
    #[arg(long, default_value_t = ServerConfig::default().udp_sockets)]
    pub udp_sockets: usize,
    /// Players of the server tick whose client mirror is compared with the server's world
    /// (staleness and error of Table 3's second part; a seeded sample, 0: none).
    #[arg(long, default_value_t = 64)]
    pub quality_players: usize,
    /// Ticks between two comparisons of the sampled mirrors with the world.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u64).range(1..))]
    pub quality_every: u64,
    /// The sampled clients' render delay, in ticks (the server sends every tick).
    #[arg(long, default_value_t = Interpolation::default().delay_ticks)]
    pub render_delay_ticks: f64,
    /// Also run a second configuration of protocol 3's replication (this byte budget in
    /// kbit/s per player, the near bound and simulated link below) beside the live server
    /// on the sampled players, and report both (`bench/shadow.rs`).
    #[arg(long)]
    pub shadow_budget_kbps: Option<f64>,
    /// The shadow's refresh bound of a changing object within 30 units, in ticks.
    #[arg(long, default_value_t = 3.0)]
    pub shadow_near_bound_ticks: f32,
    /// The shadow's simulated link: probability a datagram is lost, each way.
    #[arg(long, default_value_t = 0.0)]
    pub shadow_loss: f64,
    /// The shadow's simulated link: one-way delay, ms.
    #[arg(long, default_value_t = 0.0)]
    pub shadow_delay_ms: f64,
    /// The shadow's simulated link: spread of the delay either side, ms.
    #[arg(long, default_value_t = 0.0)]
    pub shadow_jitter_ms: f64,
    /// The sampled clients' extrapolation cap, ms.
    #[arg(long, default_value_t = Interpolation::default().max_extrapolation.as_millis() as u64)]
    pub max_extrapolation_ms: u64,
    /// Server tick: bots sharing one UDP socket (1: a socket each; 50,000 players need
    /// groups, or as many file descriptors).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub bots_per_socket: u64,
    /// Server tick: each bot opens (tag, replay window, decode) its datagrams every this
    /// many ticks, in turn, and matches the others to its session by header only (1:
    /// every datagram is opened).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub open_every: u64,
    #[command(flatten)]
    pub world: WorldArgs,
}

/// One line of results: a scenario on a backend.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub scenario: String,
    pub backend: String,
    /// `physics` (the backend's step alone) or `server` (the whole server tick).
    pub mode: &'static str,
    description: String,
    threads: usize,
    ticks: u64,
    warmup: u64,
    pub dynamic: usize,
    users: usize,
    npcs: usize,
    static_objects: usize,
    static_spheres: usize,
    static_boxes: usize,
    static_capsules: usize,
    upload: f64,
    build_dynamic_bvh: f64,
    broad_static: f64,
    broad_dynamic: f64,
    narrow_static: f64,
    narrow_dynamic: f64,
    forces: f64,
    packets: f64,
    send: f64,
    receive: f64,
    physics_static_ms: f64,
    physics_dynamic_ms: f64,
    pub total_ms: f64,
    /// The mean of the same ticks: work done every few ticks (a tree built every fourth
    /// step, a checkpoint) shows here, where the median may hide it.
    pub mean_ms: f64,
    /// CPU time of the whole process per measured tick (all threads), in ms: on a busy
    /// machine wall times inflate, this does not.
    cpu_ms: f64,
    static_pairs: u64,
    dynamic_pairs: u64,
    static_contacts: u64,
    dynamic_contacts: u64,
    state_hash: String,
    /// Server tick only: players, per-tick medians of what was sent and what the bots
    /// received and opened.
    #[serde(skip_serializing_if = "Option::is_none")]
    server: Option<ServerTick>,
    pub skipped: Option<String>,
}

/// What a server-tick row adds (medians per tick).
#[derive(Clone, Debug, Serialize)]
struct ServerTick {
    players: usize,
    aoi_size: f32,
    /// The part of `packets` spent in the backend's AOI query (ms).
    aoi_query: f64,
    datagrams: u64,
    bytes: u64,
    records: u64,
    actions_received: u64,
    /// Bytes sent per player and second at the nominal tick rate.
    bytes_per_player_s: f64,
    /// Bots sharing a socket.
    bots_per_socket: u64,
    /// Ticks between two openings of a bot's datagrams.
    open_every: u64,
    /// Datagrams that reached the bot they were for.
    delivered: u64,
    /// Of those, datagrams the bots opened.
    opened: u64,
    /// Datagrams no bot received, over all measured ticks.
    lost: u64,
    rejected: u64,
    /// Delta records the bots could not resolve (0 unless the deltas are broken).
    unresolved: u64,
    /// Smallest number over the measured ticks of players opening their datagrams whose
    /// update held their own object, and how many opened on that tick.
    min_saw_own: usize,
    opening_bots: usize,
    /// `Ready` sent again at the start to players the first did not make active.
    ready_resent: u64,
    /// What the sampled players' clients held and drew, over the run (`quality.rs`).
    #[serde(skip_serializing_if = "Option::is_none")]
    quality: Option<QualityRow>,
    /// A second configuration of protocol 3 beside the live server, on the same players
    /// (`shadow.rs`).
    #[serde(skip_serializing_if = "Option::is_none")]
    shadow: Option<shadow::ShadowRow>,
}

/// Staleness and error percentiles of what sampled clients held and drew.
#[derive(Clone, Copy, Debug, Serialize)]
struct QualityRowFigures {
    /// Age of the state held of objects within 30 units, ms (of the newest state in the
    /// quality table; the information age in the shadow's, `shadow.rs`).
    staleness_near_ms: Spread,
    /// The same over every object of the AOI.
    staleness_all_ms: Spread,
    /// Distance between the drawn and the true position, objects within 30 units.
    error_near: Spread,
    /// The same over the whole AOI.
    error_all: Spread,
    /// Objects within 30 units of which the client held nothing when sampled.
    missing_near: u64,
    /// Objects of the AOI of which the client held nothing when sampled.
    missing_all: u64,
}

impl From<QualitySummary> for QualityRowFigures {
    fn from(s: QualitySummary) -> Self {
        QualityRowFigures {
            staleness_near_ms: s.staleness_near_ms.into(),
            staleness_all_ms: s.staleness_all_ms.into(),
            error_near: s.error_near.into(),
            error_all: s.error_all.into(),
            missing_near: s.missing_near,
            missing_all: s.missing_all,
        }
    }
}

/// Percentiles of one measure in the JSON and CSV.
#[derive(Clone, Copy, Debug, Serialize)]
struct Spread {
    samples: u64,
    p50: f64,
    p99: f64,
    max: f64,
}

impl From<Percentiles> for Spread {
    fn from(p: Percentiles) -> Self {
        Spread { samples: p.samples, p50: p.p50, p99: p.p99, max: p.max }
    }
}

/// The staleness and error of what sampled players got (`bench/quality.rs`).
#[derive(Clone, Copy, Debug, Serialize)]
struct QualityRow {
    /// Players sampled.
    players: usize,
    /// Ticks between two samples.
    every: u64,
    /// The clients' render delay, ticks.
    render_delay_ticks: f64,
    /// The figures (the same JSON keys as before, flattened).
    #[serde(flatten)]
    figures: QualityRowFigures,
    /// The information age (as `staleness_*`) and the error again, sampled alike.
    information: QualityRowFigures,
}

impl QualityRow {
    fn new(players: usize, every: u64, render_delay_ticks: f64, probe: &quality::QualityProbe) -> Self {
        let (figures, information) = (probe.summary().into(), probe.information_summary().into());
        QualityRow { players, every, render_delay_ticks, figures, information }
    }
}

impl Row {
    /// Whether the row belongs to the scale sweep.
    pub fn is_sweep(&self) -> bool {
        self.scenario.starts_with("sweep")
    }

    /// Whether the row is a whole server tick.
    pub fn is_server(&self) -> bool {
        self.mode == SERVER
    }

    /// The backend, with "server tick" and the AOI edge on server-tick rows.
    pub fn label(&self) -> String {
        match &self.server {
            Some(t) => format!("{} server tick, AOI {}", self.backend, t.aoi_size),
            None => self.backend.clone(),
        }
    }

    /// The stage times in the order of [`crate::reference::STAGES`].
    pub fn stages(&self) -> [f64; 9] {
        [
            self.upload,
            self.build_dynamic_bvh,
            self.broad_static,
            self.broad_dynamic,
            self.narrow_static,
            self.narrow_dynamic,
            self.forces,
            self.packets,
            self.send,
        ]
    }
}

/// [`Row::mode`] of a backend's step alone.
const PHYSICS: &str = "physics";
/// [`Row::mode`] of a whole server tick.
const SERVER: &str = "server";

/// Runs `myriad bench`.
pub fn run(args: BenchArgs) -> Result<()> {
    let rows = measure::measure(&args)?;
    let md = report::markdown(&rows, &args);
    let js = report::json(&rows)?;
    let cs = report::csv(&rows)?;
    match args.format {
        Format::Md => print!("{md}"),
        Format::Json => print!("{js}"),
        Format::Csv => print!("{cs}"),
    }
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for (name, text) in [("bench.md", &md), ("bench.json", &js), ("bench.csv", &cs)] {
            let path = dir.join(name);
            std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
        }
        let plots = crate::plots::draw_all(&rows, dir)?;
        eprintln!("wrote bench.md, bench.json, bench.csv and {} plots to {}", plots.len(), dir.display());
    }
    Ok(())
}
