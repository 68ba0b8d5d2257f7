//! `myriad bench`: every scenario on every backend, medians per stage, in the layout of
//! the reference's Tables 1 and 2.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use myriad_core::{ObjectKind, PhysicsConfig, ScenarioSpec, World};
use myriad_cuda::create_backend;
use myriad_physics::{BackendKind, Stage, StepReport, TickConstants};
use myriad_server::ServerConfig;
use myriad_server::TickStage;
use myriad_server::outbound::OutboundKind;
use myriad_server::tick_bench::{TickBench, TickSample};
use serde::Serialize;

use crate::reference;
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
    /// Where the server tick selects each player's records: `auto` (on the device with a
    /// CUDA backend) or `host` (the host interest manager, for comparison).
    #[arg(long, default_value = "auto", value_parser = parse_outbound)]
    pub outbound: OutboundKind,
    /// UDP sockets the server tick sends on (config `udp_sockets`: 0 is one per core, at
    /// most 64).
    #[arg(long, default_value_t = ServerConfig::default().udp_sockets)]
    pub udp_sockets: usize,
    /// Players in each chunk the device outbound sends while the device builds the next
    /// (config `outbound_chunk_players`: 0 by the device's waves; at least the players:
    /// one chunk).
    #[arg(long, default_value_t = ServerConfig::default().outbound_chunk_players)]
    pub outbound_chunk_players: usize,
    #[command(flatten)]
    pub world: WorldArgs,
}

fn parse_outbound(s: &str) -> Result<OutboundKind, String> {
    match s {
        "auto" => Ok(OutboundKind::Auto),
        "host" => Ok(OutboundKind::Host),
        other => Err(format!("unknown outbound `{other}` (auto or host)")),
    }
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
    /// CPU time of the whole process per measured tick (all threads), in ms: on a busy
    /// machine wall times inflate, this does not.
    cpu_ms: f64,
    static_pairs: u64,
    dynamic_pairs: u64,
    static_contacts: u64,
    dynamic_contacts: u64,
    state_hash: String,
    /// Server tick only: players (one bot socket each), per-tick medians of what was
    /// sent and what the bots received and opened.
    #[serde(skip_serializing_if = "Option::is_none")]
    server: Option<ServerTick>,
    pub skipped: Option<String>,
}

/// What a server-tick row adds (medians per tick).
#[derive(Clone, Debug, Serialize)]
struct ServerTick {
    players: usize,
    aoi_size: f32,
    /// The part of `packets` spent in the backend's AOI query on the host (ms; 0 with the
    /// device outbound).
    aoi_query: f64,
    /// The part of `packets` spent waiting for the device's interest work (ms; 0 with the
    /// host outbound).
    device_wait: f64,
    datagrams: u64,
    bytes: u64,
    records: u64,
    actions_received: u64,
    /// Bytes sent per player and second at the nominal tick rate.
    bytes_per_player_s: f64,
    delivered: u64,
    rejected: u64,
    /// Smallest number over the measured ticks of players whose update held their own
    /// object.
    min_saw_own: usize,
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

    /// The stage times in the order of [`reference::STAGES`].
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

/// User + system CPU time of this process so far, in ms (0 where unsupported).
fn process_cpu_ms() -> f64 {
    #[cfg(unix)]
    {
        let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
        // SAFETY: getrusage writes a complete rusage into the pointer on success.
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } == 0 {
            // SAFETY: initialised by the successful call above.
            let u = unsafe { usage.assume_init() };
            let ms = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 / 1e3;
            return ms(u.ru_utime) + ms(u.ru_stime);
        }
    }
    0.0
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 { v[m] } else { (v[m - 1] + v[m]) / 2.0 }
}

fn median_u64(v: impl Iterator<Item = u64>) -> u64 {
    let mut v: Vec<u64> = v.collect();
    v.sort_unstable();
    v.get(v.len() / 2).copied().unwrap_or(0)
}

const PHYSICS: &str = "physics";
const SERVER: &str = "server";

/// A row with the world's counts filled in and every measurement zero.
fn empty_row(label: &str, world: &World, kind: BackendKind, description: String, mode: &'static str) -> Row {
    let d = &world.dynamics;
    let users = d.kinds().iter().filter(|k| **k == ObjectKind::User).count();
    let [spheres, boxes, capsules] = world.statics.prims_by_shape();
    Row {
        scenario: label.into(),
        backend: kind.to_string(),
        mode,
        description,
        threads: rayon::current_num_threads(),
        ticks: 0,
        warmup: 0,
        dynamic: d.len(),
        users,
        npcs: d.len() - users,
        static_objects: world.statics.objects().len(),
        static_spheres: spheres,
        static_boxes: boxes,
        static_capsules: capsules,
        upload: 0.0,
        build_dynamic_bvh: 0.0,
        broad_static: 0.0,
        broad_dynamic: 0.0,
        narrow_static: 0.0,
        narrow_dynamic: 0.0,
        forces: 0.0,
        packets: 0.0,
        send: 0.0,
        receive: 0.0,
        physics_static_ms: 0.0,
        physics_dynamic_ms: 0.0,
        total_ms: 0.0,
        cpu_ms: 0.0,
        static_pairs: 0,
        dynamic_pairs: 0,
        static_contacts: 0,
        dynamic_contacts: 0,
        state_hash: String::new(),
        server: None,
        skipped: None,
    }
}

/// Sets the seven physics stages of `row`, `stage(s)` giving the median of stage `s`.
fn set_physics_stages(row: &mut Row, stage: impl Fn(Stage) -> f64) {
    row.upload = stage(Stage::Upload);
    row.build_dynamic_bvh = stage(Stage::BuildDynamicBvh);
    row.broad_static = stage(Stage::BroadStatic);
    row.broad_dynamic = stage(Stage::BroadDynamic);
    row.narrow_static = stage(Stage::NarrowStatic);
    row.narrow_dynamic = stage(Stage::NarrowDynamic);
    row.forces = stage(Stage::Forces);
}

fn bench_one(label: &str, world: &World, kind: BackendKind, args: &BenchArgs, progress: &Progress) -> Result<Row> {
    progress.start(format!("scenario {label} · {kind}"));
    let mut backend = create_backend(kind)?.backend;
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    let mut w = world.clone();
    let mut row = empty_row(label, world, kind, backend.description(), PHYSICS);
    row.ticks = args.ticks;
    row.warmup = args.warmup;
    let started = Instant::now();
    backend.step(&mut w, &k).context("first tick")?;
    progress.tick();
    let first_ms = started.elapsed().as_secs_f64() * 1e3;
    if first_ms > args.max_tick_ms && !args.force {
        row.skipped = Some(format!("first tick took {first_ms:.0} ms (> {} ms); --force runs it", args.max_tick_ms));
        progress.log(format!("  {kind}: skipped, {}", row.skipped.as_deref().unwrap_or_default()));
        progress.skip(args.warmup.saturating_sub(1) + args.ticks);
        return Ok(row);
    }
    for _ in 1..args.warmup {
        backend.step(&mut w, &k)?;
        progress.tick();
    }
    let mut reports: Vec<StepReport> = Vec::with_capacity(args.ticks as usize);
    let cpu_before = process_cpu_ms();
    for _ in 0..args.ticks {
        reports.push(backend.step(&mut w, &k)?);
        progress.tick();
    }
    row.cpu_ms = (process_cpu_ms() - cpu_before) / args.ticks.max(1) as f64;
    set_physics_stages(&mut row, |st| median(reports.iter().map(|r| r.ms(st)).collect()));
    row.physics_static_ms = median(reports.iter().map(StepReport::physics_static_ms).collect());
    row.physics_dynamic_ms = median(reports.iter().map(StepReport::physics_dynamic_ms).collect());
    row.total_ms = median(reports.iter().map(StepReport::total_ms).collect());
    row.static_pairs = median_u64(reports.iter().map(|r| r.static_pairs));
    row.dynamic_pairs = median_u64(reports.iter().map(|r| r.dynamic_pairs));
    row.static_contacts = median_u64(reports.iter().map(|r| r.static_contacts));
    row.dynamic_contacts = median_u64(reports.iter().map(|r| r.dynamic_contacts));
    row.state_hash = format!("{:016x}", w.state_hash());
    progress.log(format!(
        "  {kind}: {:.3} ms a tick (static {:.3}, dynamic {:.3}), hash {}",
        row.total_ms, row.physics_static_ms, row.physics_dynamic_ms, row.state_hash
    ));
    Ok(row)
}

/// The whole server tick on `kind` with one bot per user of the world.
fn server_one(
    label: &str,
    world: &World,
    kind: BackendKind,
    aoi: f32,
    args: &BenchArgs,
    progress: &Progress,
) -> Result<Row> {
    progress.start(format!("scenario {label} · {kind} server tick, AOI {aoi}"));
    let backend = create_backend(kind)?;
    let mut row = empty_row(label, world, kind, backend.backend.description(), SERVER);
    row.ticks = args.ticks;
    row.warmup = args.warmup;
    let config = ServerConfig {
        aoi_size: aoi,
        outbound: args.outbound,
        udp_sockets: args.udp_sockets,
        outbound_chunk_players: args.outbound_chunk_players,
        ..ServerConfig::default()
    };
    let mut bench = TickBench::new(config, world.clone(), backend).context("starting the server tick")?;
    for _ in 0..args.warmup {
        bench.tick()?;
        progress.tick();
    }
    let mut samples: Vec<TickSample> = Vec::with_capacity(args.ticks as usize);
    let cpu_before = process_cpu_ms();
    for _ in 0..args.ticks {
        samples.push(bench.tick()?);
        progress.tick();
    }
    // The bots send and drain in this process too, on one thread: take their time out
    // of the process's CPU time, as the reference's clients ran on other machines.
    let bots_ms: f64 = samples.iter().map(|s| s.bots_ms).sum();
    row.cpu_ms = ((process_cpu_ms() - cpu_before - bots_ms) / args.ticks.max(1) as f64).max(0.0);
    let stage = |t: TickStage| median(samples.iter().map(|s| s.work.stages[t]).collect());
    set_physics_stages(&mut row, |st| stage(TickStage::Physics(st)));
    row.packets = stage(TickStage::Packets);
    row.send = stage(TickStage::Send);
    row.receive = stage(TickStage::Receive);
    row.physics_static_ms = row.upload + row.broad_static + row.narrow_static;
    row.physics_dynamic_ms = row.build_dynamic_bvh + row.broad_dynamic + row.narrow_dynamic + row.forces;
    row.total_ms = median(samples.iter().map(TickSample::total_ms).collect());
    row.state_hash = format!("{:016x}", bench.world().state_hash());
    let m = |f: fn(&TickSample) -> u64| median_u64(samples.iter().map(f));
    let bytes = m(|s| s.work.bytes);
    let tick_rate = f64::from(ServerConfig::default().tick_rate);
    let server = ServerTick {
        players: bench.players(),
        aoi_size: aoi,
        aoi_query: median(samples.iter().map(|s| s.work.aoi_ms).collect()),
        device_wait: median(samples.iter().map(|s| s.work.device_wait_ms).collect()),
        datagrams: m(|s| s.work.datagrams),
        bytes,
        records: m(|s| s.work.records as u64),
        actions_received: m(|s| s.work.received),
        bytes_per_player_s: bytes as f64 * tick_rate / bench.players().max(1) as f64,
        delivered: m(|s| s.delivered),
        rejected: samples.iter().map(|s| s.rejected).sum(),
        min_saw_own: samples.iter().map(|s| s.saw_own).min().unwrap_or(0),
    };
    if server.rejected > 0 {
        anyhow::bail!("{} datagrams the bots could not open: the server tick is broken", server.rejected);
    }
    progress.log(format!(
        "  {kind} server tick, AOI {aoi}: {:.3} ms (packets {:.3}, send {:.3}, receive {:.3}), {} players, {} datagrams a tick",
        row.total_ms, row.packets, row.send, row.receive, server.players, server.datagrams
    ));
    row.server = Some(server);
    Ok(row)
}

/// The progress bar of a long run (hidden when standard error is not a terminal, where
/// the log lines are printed plainly instead).
struct Progress {
    bar: ProgressBar,
}

impl Progress {
    fn new(total_ticks: u64) -> Self {
        let bar = ProgressBar::with_draw_target(Some(total_ticks), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template("{bar:30} {pos}/{len} ticks, {elapsed} (eta {eta}) {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        Progress { bar }
    }

    fn start(&self, what: String) {
        self.bar.set_message(what);
    }

    fn tick(&self) {
        self.bar.inc(1);
    }

    fn skip(&self, ticks: u64) {
        self.bar.inc(ticks);
    }

    fn log(&self, line: String) {
        if self.bar.is_hidden() { eprintln!("{line}") } else { self.bar.println(line) }
    }
}

fn is_naive(kind: BackendKind) -> bool {
    matches!(kind, BackendKind::CpuNaive | BackendKind::CudaNaive)
}

/// Runs the benchmark and returns its rows.
pub fn measure(args: &BenchArgs) -> Result<Vec<Row>> {
    let per_run = args.warmup.max(1) + args.ticks;
    let server_runs = if args.physics_only {
        0
    } else {
        args.backend.iter().filter(|k| !is_naive(**k)).count() * args.aoi_size.len()
    };
    let runs = args.scenario.len() * (args.backend.len() + server_runs) + args.sweep.len() * args.backend.len();
    let progress = Progress::new(runs as u64 * per_run);
    let mut rows = Vec::new();
    for &name in &args.scenario {
        let started = Instant::now();
        progress.start(format!("generating scenario {name:?}"));
        let (spec, world) = args.world.build(name)?;
        progress.log(format!(
            "scenario {}: {} dynamic, {} static objects, generated in {:.1} s",
            spec.name,
            world.dynamics.len(),
            world.statics.objects().len(),
            started.elapsed().as_secs_f64()
        ));
        for &kind in &args.backend {
            rows.push(
                bench_one(&spec.name, &world, kind, args, &progress)
                    .with_context(|| format!("scenario {} on {kind}", spec.name))?,
            );
        }
        if args.physics_only {
            continue;
        }
        for &kind in args.backend.iter().filter(|k| !is_naive(**k)) {
            let physics_skipped =
                rows.iter().any(|r| r.scenario == spec.name && r.backend == kind.to_string() && r.skipped.is_some());
            if physics_skipped {
                progress.skip(per_run * args.aoi_size.len() as u64);
                continue;
            }
            for &aoi in &args.aoi_size {
                rows.push(
                    server_one(&spec.name, &world, kind, aoi, args, &progress)
                        .with_context(|| format!("server tick of scenario {} on {kind}, AOI {aoi}", spec.name))?,
                );
            }
        }
    }
    for &n in &args.sweep {
        let spec = sweep_spec(n, args.world.seed);
        progress.start(format!("generating {}", spec.name));
        let world = spec.build().with_context(|| format!("generating sweep point {n}"))?;
        progress.log(format!(
            "{}: {n} dynamic, {} static objects, map {:.0} units",
            spec.name, spec.static_objects, spec.world_size
        ));
        for &kind in &args.backend {
            rows.push(
                bench_one(&spec.name, &world, kind, args, &progress)
                    .with_context(|| format!("{} on {kind}", spec.name))?,
            );
        }
    }
    progress.bar.finish_and_clear();
    Ok(rows)
}

/// A sweep point: `n` dynamic objects at scenario 2's density, statics at half.
pub fn sweep_spec(n: u32, seed: u64) -> ScenarioSpec {
    let mut spec = ScenarioSpec::custom(seed);
    spec.name = format!("sweep-{n}");
    spec.dynamic = n;
    spec.static_objects = n / 2;
    spec.users = (n / 26).clamp(1, n.max(1)).min(n);
    spec.world_size = (1024.0 * (n as f64 / 55_000.0).sqrt()).max(64.0) as f32;
    spec
}

fn fmt_ms(v: f64) -> String {
    if v >= 100.0 {
        format!("{v:.0}")
    } else if v >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// Markdown: our Table 1 and Table 2, then the reference's.
pub fn markdown(rows: &[Row], args: &BenchArgs) -> String {
    let mut s = String::new();
    let threads = rows.first().map_or(0, |r| r.threads);
    let _ = writeln!(
        s,
        "#### Table 1: physics time per tick (ms, median of {} ticks after {} warm-up)\n",
        args.ticks, args.warmup
    );
    let _ = writeln!(
        s,
        "| scenario | backend | static | dynamic | total | CPU per tick | dynamic pairs | static pairs | state hash |"
    );
    let _ = writeln!(s, "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |");
    for r in rows.iter().filter(|r| !r.is_server()) {
        match &r.skipped {
            Some(why) => {
                let _ = writeln!(s, "| {} | {} | - | - | - | | | | {why} |", r.scenario, r.backend);
            }
            None => {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} | {} | {} | {} | `{}` |",
                    r.scenario,
                    r.backend,
                    fmt_ms(r.physics_static_ms),
                    fmt_ms(r.physics_dynamic_ms),
                    fmt_ms(r.total_ms),
                    fmt_ms(r.cpu_ms),
                    r.dynamic_pairs,
                    r.static_pairs,
                    r.state_hash
                );
            }
        }
    }
    // Table 2 is the whole server tick where it was run; without it (--physics-only),
    // the physics rows with `packets` and `send` at 0.
    let server_rows: Vec<&Row> = rows.iter().filter(|r| r.is_server() && r.skipped.is_none()).collect();
    let table2: Vec<&Row> = if server_rows.is_empty() {
        rows.iter().filter(|r| r.skipped.is_none()).collect()
    } else {
        server_rows.clone()
    };
    let _ = writeln!(s, "\n#### Table 2: time per stage (ms, medians)\n");
    let _ = writeln!(s, "| scenario | backend | {} |", reference::STAGES.join(" | "));
    let _ = writeln!(s, "| --- | --- |{}", " ---: |".repeat(reference::STAGES.len()));
    for r in &table2 {
        let cells: Vec<String> = r.stages().iter().map(|&v| fmt_ms(v)).collect();
        let _ = writeln!(s, "| {} | {} | {} |", r.scenario, r.label(), cells.join(" | "));
    }
    if server_rows.is_empty() {
        let _ = writeln!(
            s,
            "\n`packets` and `send` belong to the server tick and are 0 in a physics-only run. cpu threads: {threads}."
        );
    } else {
        let _ = writeln!(
            s,
            "\n#### Table 3: the whole server tick (medians per tick; one bot socket per user on loopback)\n"
        );
        let _ = writeln!(
            s,
            "| scenario | backend | AOI edge | players | tick | server CPU | receive | packets | of which host AOI query | of which device wait | send | datagrams | KiB sent | kB/s per player | records | actions in | opened by bots | min. players seeing themselves |"
        );
        let _ = writeln!(s, "| --- | --- |{}", " ---: |".repeat(16));
        for r in &server_rows {
            let Some(t) = &r.server else { continue };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.0} | {:.1} | {} | {} | {} | {} |",
                r.scenario,
                r.backend,
                t.aoi_size,
                t.players,
                fmt_ms(r.total_ms),
                fmt_ms(r.cpu_ms),
                fmt_ms(r.receive),
                fmt_ms(r.packets),
                fmt_ms(t.aoi_query),
                fmt_ms(t.device_wait),
                fmt_ms(r.send),
                t.datagrams,
                t.bytes as f64 / 1024.0,
                t.bytes_per_player_s / 1000.0,
                t.records,
                t.actions_received,
                t.delivered,
                t.min_saw_own
            );
        }
        let _ = writeln!(
            s,
            "\n`tick` is the sum of the stages (receive included); `server CPU` is the process's CPU time less the bots'. \
             `send` is the mean socket's time sending (the sockets send at once, and with the device outbound \
             beside the device's work), `packets` the rest of building and sending; `of which host AOI query`: \
             the backend's AOI query on the host (0 with the device outbound); `of which device wait`: \
             the time the tick waited for the device's query, selection, packing and sealing (0 on the host). \
             `kB/s per player`: bytes sent per tick and player at the nominal tick rate ({} Hz). \
             Each bot sends an action every {} ticks. cpu threads: {threads}.",
            ServerConfig::default().tick_rate,
            myriad_server::tick_bench::ACTION_EVERY
        );
    }
    let _ = writeln!(s, "\n#### The reference ({})\n", reference::MACHINE);
    let _ = writeln!(
        s,
        "| scenario | CPU static | CPU dynamic | naive GPU static | naive GPU dynamic | optimized GPU static | optimized GPU dynamic |"
    );
    let _ = writeln!(s, "| --- | ---: | ---: | ---: | ---: | ---: | ---: |");
    for (name, v) in reference::TABLE1 {
        let cells: Vec<String> = v.iter().map(|c| c.map_or("-".into(), |x| format!("{x}"))).collect();
        let _ = writeln!(s, "| {name} | {} |", cells.join(" | "));
    }
    let _ = writeln!(s, "\n| scenario (optimized GPU) | {} |", reference::STAGES.join(" | "));
    let _ = writeln!(s, "| --- |{}", " ---: |".repeat(reference::STAGES.len()));
    for (name, v) in reference::TABLE2 {
        let cells: Vec<String> = v.iter().map(|x| format!("{x}")).collect();
        let _ = writeln!(s, "| {name} | {} |", cells.join(" | "));
    }
    s
}

/// One JSON object per line.
pub fn json(rows: &[Row]) -> Result<String> {
    let mut s = String::new();
    for r in rows {
        s.push_str(&serde_json::to_string(r)?);
        s.push('\n');
    }
    Ok(s)
}

/// CSV with a header line: one column per field, nested fields as `server.players`
/// and so on, empty where a row does not have the field (physics rows have no
/// `server.*`).
pub fn csv(rows: &[Row]) -> Result<String> {
    fn flatten(prefix: &str, v: &serde_json::Value, out: &mut Vec<(String, String)>) {
        match v {
            serde_json::Value::Object(o) => {
                for (k, v) in o {
                    let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                    flatten(&key, v, out);
                }
            }
            serde_json::Value::String(t) => out.push((prefix.into(), format!("\"{}\"", t.replace('"', "\"\"")))),
            serde_json::Value::Null => out.push((prefix.into(), String::new())),
            other => out.push((prefix.into(), other.to_string())),
        }
    }
    let mut flat = Vec::with_capacity(rows.len());
    let mut header: Vec<String> = Vec::new();
    for r in rows {
        let mut cells = Vec::new();
        flatten("", &serde_json::to_value(r)?, &mut cells);
        for (k, _) in &cells {
            if !header.contains(k) {
                header.push(k.clone());
            }
        }
        flat.push(cells);
    }
    let mut s = header.join(",");
    s.push('\n');
    for cells in &flat {
        let line: Vec<&str> =
            header.iter().map(|h| cells.iter().find(|(k, _)| k == h).map_or("", |(_, v)| v.as_str())).collect();
        s.push_str(&line.join(","));
        s.push('\n');
    }
    Ok(s)
}

/// Runs `myriad bench`.
pub fn run(args: BenchArgs) -> Result<()> {
    let rows = measure(&args)?;
    let md = markdown(&rows, &args);
    let js = json(&rows)?;
    let cs = csv(&rows)?;
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
