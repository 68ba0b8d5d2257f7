//! Measuring: each scenario's backend steps and server ticks, as [`Row`]s of medians.

use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use myriad_client::Interpolation;
use myriad_core::{ObjectKind, PhysicsConfig, ScenarioSpec, World};
use myriad_cuda::create_backend;
use myriad_interest::ReplicationConfig;
use myriad_physics::{BackendKind, Stage, StepReport, TickConstants};
use myriad_server::ServerConfig;
use myriad_server::TickStage;
use myriad_server::tick_bench::{BotOptions, TickBench, TickSample};

use super::pace::Pace;
use super::quality::{QualityConfig, QualityProbe};
use super::shadow::Link;
use super::{BenchArgs, PHYSICS, QualityRow, Row, SERVER, ServerTick};

/// Ticks of a server-tick run between two lines of where its wall time went
/// ([`Pace`]).
const PACE_TICKS: u32 = 10;

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

fn mean(v: impl ExactSizeIterator<Item = f64>) -> f64 {
    let n = v.len();
    if n == 0 { 0.0 } else { v.sum::<f64>() / n as f64 }
}

fn median_u64(v: impl Iterator<Item = u64>) -> u64 {
    let mut v: Vec<u64> = v.collect();
    v.sort_unstable();
    v.get(v.len() / 2).copied().unwrap_or(0)
}

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
        mean_ms: 0.0,
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
    row.mean_ms = mean(reports.iter().map(StepReport::total_ms));
    row.static_pairs = median_u64(reports.iter().map(|r| r.static_pairs));
    row.dynamic_pairs = median_u64(reports.iter().map(|r| r.dynamic_pairs));
    row.static_contacts = median_u64(reports.iter().map(|r| r.static_contacts));
    row.dynamic_contacts = median_u64(reports.iter().map(|r| r.dynamic_contacts));
    row.state_hash = format!("{:016x}", w.state_hash());
    progress.log(format!(
        "  {kind}: {:.3} ms a tick (mean {:.3}; static {:.3}, dynamic {:.3}), hash {}",
        row.total_ms, row.mean_ms, row.physics_static_ms, row.physics_dynamic_ms, row.state_hash
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
        udp_sockets: args.udp_sockets,
        send_budget_kbps: args.send_budget_kbps,
        ..ServerConfig::default()
    };
    let tick_rate_hz = config.tick_rate.round() as u16;
    let config_max_datagrams = config.max_datagrams_per_player;
    let bots = BotOptions {
        bots_per_socket: usize::try_from(args.bots_per_socket).context("--bots-per-socket")?,
        open_every: args.open_every,
    };
    let starting = Instant::now();
    let mut bench = TickBench::with_bots(config, world.clone(), backend, bots).context("starting the server tick")?;
    progress.note(format!(
        "  the server and {} bots ready in {:.1} s",
        bench.players(),
        starting.elapsed().as_secs_f64()
    ));
    if bench.ready_resent() > 0 {
        eprintln!(
            "note: {} Ready sent again before every player was active (a full receive buffer)",
            bench.ready_resent()
        );
    }
    let interpolation = Interpolation {
        delay_ticks: args.render_delay_ticks,
        max_extrapolation: std::time::Duration::from_millis(args.max_extrapolation_ms),
    };
    // A bot that opens its datagrams only in turn (`--open-every`) holds what it skipped
    // as lost: its mirror's staleness would measure the bench, not the protocol.
    let quality_players = if args.open_every == 1 { args.quality_players } else { 0 };
    if quality_players == 0 && args.quality_players > 0 {
        eprintln!("note: --open-every {} leaves the staleness and error probe off", args.open_every);
    }
    let mut probe = QualityProbe::new(
        &bench,
        QualityConfig {
            players: quality_players,
            every: args.quality_every,
            seed: args.world.seed,
            aoi_size: aoi,
            tick_rate_hz,
            interpolation,
            shadow: args.shadow_budget_kbps.map(|kbps| {
                let config = ReplicationConfig {
                    budget_bytes_per_tick: (kbps * 1000.0 / 8.0 / f64::from(tick_rate_hz.max(1))) as f32,
                    near_bound_ticks: args.shadow_near_bound_ticks,
                    ..ReplicationConfig::default()
                };
                let link =
                    Link { loss: args.shadow_loss, delay_ms: args.shadow_delay_ms, jitter_ms: args.shadow_jitter_ms };
                (config, config_max_datagrams, link)
            }),
        },
    );
    let (total, mut pace) = (args.warmup + args.ticks, Pace::new(PACE_TICKS));
    // One tick's parts into `pace`, logged every few ticks.
    let mut paced = |done: u64, began: Instant, probed: Instant, sample: &TickSample| {
        let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
        let wall = ms(began.elapsed());
        if let Some(line) = pace.add(done, total, wall, sample.total_ms(), sample.bots_ms, ms(probed.elapsed())) {
            progress.note(line);
        }
    };
    for done in 1..=args.warmup {
        let began = Instant::now();
        let sample = bench.tick_with(|bot, tick, records| probe.on_update(bot, tick, records))?;
        let probed = Instant::now();
        // Measures nothing yet; the shadows (if any) fill their clients as the bots do.
        probe.after_tick(bench.world());
        paced(done, began, probed, &sample);
        progress.tick();
    }
    probe.start_measuring();
    bench.restart_profile();
    let mut samples: Vec<TickSample> = Vec::with_capacity(args.ticks as usize);
    let mut probe_ms = 0.0;
    let cpu_before = process_cpu_ms();
    for done in args.warmup + 1..=total {
        let began = Instant::now();
        let sample = bench.tick_with(|bot, tick, records| probe.on_update(bot, tick, records))?;
        let (probed, probe_cpu) = (Instant::now(), process_cpu_ms());
        probe.after_tick(bench.world());
        probe_ms += process_cpu_ms() - probe_cpu;
        paced(done, began, probed, &sample);
        samples.push(sample);
        progress.tick();
    }
    // The bots send and drain in this process too, on one thread, and the probe compares
    // the sampled mirrors with the world (its CPU time, measured around it): take both
    // out of the process's CPU time, as the reference's clients ran on other machines.
    let bots_ms: f64 = samples.iter().map(|s| s.bots_ms).sum::<f64>() + probe_ms;
    row.cpu_ms = ((process_cpu_ms() - cpu_before - bots_ms) / args.ticks.max(1) as f64).max(0.0);
    let stage = |t: TickStage| median(samples.iter().map(|s| s.work.stages[t]).collect());
    set_physics_stages(&mut row, |st| stage(TickStage::Physics(st)));
    row.packets = stage(TickStage::Packets);
    row.send = stage(TickStage::Send);
    row.receive = stage(TickStage::Receive);
    row.physics_static_ms = row.upload + row.broad_static + row.narrow_static;
    row.physics_dynamic_ms = row.build_dynamic_bvh + row.broad_dynamic + row.narrow_dynamic + row.forces;
    row.total_ms = median(samples.iter().map(TickSample::total_ms).collect());
    row.mean_ms = mean(samples.iter().map(TickSample::total_ms));
    row.state_hash = format!("{:016x}", bench.world().state_hash());
    let m = |f: fn(&TickSample) -> u64| median_u64(samples.iter().map(f));
    let bytes = m(|s| s.work.bytes);
    let tick_rate = f64::from(ServerConfig::default().tick_rate);
    let server = ServerTick {
        players: bench.players(),
        aoi_size: aoi,
        aoi_query: median(samples.iter().map(|s| s.work.aoi_ms).collect()),
        datagrams: m(|s| s.work.datagrams),
        bytes,
        records: m(|s| s.work.records as u64),
        actions_received: m(|s| s.work.received),
        bytes_per_player_s: bytes as f64 * tick_rate / bench.players().max(1) as f64,
        bots_per_socket: args.bots_per_socket,
        open_every: args.open_every,
        delivered: m(|s| s.delivered),
        opened: m(|s| s.opened),
        lost: samples.iter().map(|s| s.lost).sum(),
        rejected: samples.iter().map(|s| s.rejected).sum(),
        unresolved: samples.iter().map(|s| s.unresolved).sum(),
        min_saw_own: samples.iter().map(|s| s.saw_own).min().unwrap_or(0),
        ready_resent: bench.ready_resent(),
        opening_bots: samples.iter().min_by_key(|s| s.saw_own).map_or(0, |s| s.opening_bots),
        quality: (probe.players() > 0)
            .then(|| QualityRow::new(probe.players(), args.quality_every, args.render_delay_ticks, &probe)),
        shadow: probe.shadow_row(),
    };
    if server.rejected > 0 {
        anyhow::bail!("{} datagrams the bots could not open: the server tick is broken", server.rejected);
    }
    if server.unresolved > 0 {
        anyhow::bail!("{} records the bots could not resolve: the server's deltas are broken", server.unresolved);
    }
    if server.lost > 0 {
        // Not the server's fault, but the figure then counts traffic nobody received.
        progress.log(format!(
            "  warning: {} datagrams over {} ticks never reached a bot (full bot socket buffers: lower \
             --bots-per-socket or raise net.core.rmem_max)",
            server.lost, args.ticks
        ));
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

    /// Logs `line` where no bar is drawn (a log file, the GPU machine's runs), whose
    /// reader has nothing else to go by while the run goes; a terminal has the bar.
    fn note(&self, line: String) {
        if self.bar.is_hidden() {
            self.log(line);
        }
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
