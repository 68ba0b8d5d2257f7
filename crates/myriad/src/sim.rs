//! `myriad sim`: run a scenario for some ticks and print a summary and the state hash.

use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use myriad_core::{ActionScript, ObjectKind, PhysicsConfig};
use myriad_cuda::create_backend;
use myriad_physics::{BackendKind, TickConstants};
use serde::Serialize;

use crate::scenario_args::{ScenarioName, WorldArgs};

/// Flags of `myriad sim`.
#[derive(Args, Debug)]
pub struct SimArgs {
    /// The scenario.
    #[arg(long, value_enum, default_value = "1")]
    pub scenario: ScenarioName,
    /// The physics backend (`auto`, `cpu`, `cpu-naive`, `cuda`, `cuda-naive`); `auto` is
    /// `cuda` when a GPU is usable, else `cpu`.
    #[arg(long, default_value = "auto")]
    pub backend: BackendKind,
    /// Ticks to simulate.
    #[arg(long, default_value_t = 100)]
    pub ticks: u64,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// A script of players' actions (`TICK ENTITY MASK` lines, see
    /// `myriad_core::script`): each is set just before the step of its tick, as the
    /// server applies an action received before that tick.
    #[arg(long, value_name = "FILE")]
    pub actions: Option<std::path::PathBuf>,
    /// Split the world into this many zones (a grid as square as the count allows), each
    /// stepped by its own thread and backend, exchanging border states; the state hash is
    /// comparable with a run in one zone (see docs/zones.md).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=1024))]
    pub zones: u16,
    /// Carry the zones' messages over this NATS server (e.g. nats://127.0.0.1:4222)
    /// instead of in-process channels.
    #[arg(long, value_name = "URL")]
    pub nats: Option<String>,
    /// The cluster name of the zones on `--nats` (default: one of its own per run); on a
    /// locked-down server, the cluster whose zone credentials this process presents
    /// (`MYRIAD_NATS_USER`/`MYRIAD_NATS_PASSWORD` or `MYRIAD_NATS_CREDS`).
    #[arg(long, requires = "nats")]
    pub cluster: Option<String>,
    /// GPUs to spread zones over with the CUDA backends (zone i on device i mod N).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub gpus: u16,
    /// How far an object may move in one tick before zones must refuse to go on.
    #[arg(long, default_value_t = 2.0)]
    pub zone_max_step: f32,
    /// Move the zones' cuts toward balanced object counts per column and row (decided
    /// from the objects each zone owns, so the run is reproducible; see docs/zones.md,
    /// rebalancing). Without it the cuts stay and the load is only watched.
    #[arg(long, requires = "zones")]
    pub rebalance: bool,
    /// Ticks between the zones' load reports (and rebalancing decisions).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(3..))]
    pub rebalance_every: u64,
    #[command(flatten)]
    pub world: WorldArgs,
}

/// Zone figures of a zoned run, summed over the zones.
#[derive(Serialize)]
struct ZoneSummary {
    zones: usize,
    grid: (usize, usize),
    reach: f32,
    fabric: &'static str,
    /// Per zone: objects owned at the end.
    owned: Vec<usize>,
    /// Per zone: static primitives held.
    static_prims: Vec<usize>,
    ghost_records: u64,
    handoffs: u64,
    messages: u64,
    fabric_bytes: u64,
    /// Per zone: mean wait for neighbours, ms a tick.
    wait_ms: Vec<f64>,
    /// Per zone: mean physics step, ms a tick.
    physics_ms: Vec<f64>,
    /// Per zone: mean time assembling the zone's world and keeping results (the step less
    /// the physics), plus choosing and sending border states, ms a tick.
    overhead_ms: Vec<f64>,
    /// Per zone, of the overhead: the pass finding the slots near the edges, the rest of
    /// the world's edit, and of that the moving of slots, ms a tick.
    scan_ms: Vec<f64>,
    edit_ms: Vec<f64>,
    moving_ms: Vec<f64>,
    /// Per zone, of the physics: the backend's copies to and from the device, ms a tick.
    copies_ms: Vec<f64>,
    /// Per zone: objects inserted, removed, and ticks that moved slots, in all.
    slots: Vec<(u64, u64, u64)>,
    rejected: u64,
    /// Cut moves every zone applied.
    cut_moves: u64,
    /// Each move: decided at, applied at, new x cuts, new z cuts.
    moves: Vec<(u64, u64, Vec<f32>, Vec<f32>)>,
    /// The cuts at the end, along x and z.
    cuts: (Vec<f32>, Vec<f32>),
    /// Per zone: mean physics step over the last third of the run, ms a tick (measured).
    physics_ms_last_third: Vec<f64>,
    /// The slowest zone's physics step over the zones' mean, whole run and last third.
    slowest_over_mean: (f64, f64),
    /// The most loaded zone's owned objects over the mean, averaged over the report
    /// ticks of the whole run and of its last third (deterministic, unlike times).
    most_owned_over_mean: (f64, f64),
    /// Every report tick: tick, objects owned per zone, physics ms a tick per zone since
    /// the previous report.
    samples: Vec<(u64, Vec<usize>, Vec<f64>)>,
}

#[derive(Serialize)]
struct Summary {
    scenario: String,
    backend: String,
    description: String,
    seed: u64,
    ticks: u64,
    dynamic: usize,
    users: usize,
    static_objects: usize,
    static_prims: [usize; 3],
    total_ms: f64,
    mean_tick_ms: f64,
    /// Absent for a zoned run: zones count their ghosts' pairs too, so sums are not comparable.
    #[serde(skip_serializing_if = "Option::is_none")]
    static_pairs: Option<u64>,
    /// Absent for a zoned run: zones count their ghosts' pairs too, so sums are not comparable.
    #[serde(skip_serializing_if = "Option::is_none")]
    dynamic_pairs: Option<u64>,
    /// Absent for a zoned run: zones count their ghosts' pairs too, so sums are not comparable.
    #[serde(skip_serializing_if = "Option::is_none")]
    static_contacts: Option<u64>,
    /// Absent for a zoned run: zones count their ghosts' pairs too, so sums are not comparable.
    #[serde(skip_serializing_if = "Option::is_none")]
    dynamic_contacts: Option<u64>,
    /// Scripted actions applied.
    actions: usize,
    /// The users' mean x at the end (the moving crowd's position).
    #[serde(skip_serializing_if = "Option::is_none")]
    users_mean_x: Option<f32>,
    state_hash: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    zoned: Option<ZoneSummary>,
}

/// Runs `myriad sim`.
pub fn run(args: SimArgs) -> Result<()> {
    let (spec, mut world, generated) = args.world.build_with_script(args.scenario, args.ticks)?;
    let script = match &args.actions {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let file = ActionScript::parse(&text).with_context(|| format!("in {}", path.display()))?;
            // The file's lines after the scenario's, so that on one tick they win.
            ActionScript::new(generated.entries().iter().chain(file.entries()).copied().collect())
        }
        None => generated,
    };
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    if args.zones > 1 || args.nats.is_some() {
        return run_zoned(&args, &spec, &world, &script, &k);
    }
    let mut backend = create_backend(args.backend)?.backend;
    let mut pairs = [0u64; 4];
    let mut actions = 0;
    let start = Instant::now();
    for t in 0..args.ticks {
        actions += script.apply(&mut world)?;
        let r = backend.step(&mut world, &k).with_context(|| format!("tick {t}"))?;
        for (acc, v) in pairs.iter_mut().zip([r.static_pairs, r.dynamic_pairs, r.static_contacts, r.dynamic_contacts]) {
            *acc += v;
        }
    }
    let total_ms = start.elapsed().as_secs_f64() * 1e3;
    let s = Summary {
        scenario: spec.name.clone(),
        backend: backend.kind().to_string(),
        description: backend.description(),
        seed: spec.seed,
        ticks: args.ticks,
        dynamic: world.dynamics.len(),
        users: world.dynamics.kinds().iter().filter(|k| **k == ObjectKind::User).count(),
        static_objects: world.statics.objects().len(),
        static_prims: world.statics.prims_by_shape(),
        total_ms,
        mean_tick_ms: if args.ticks > 0 { total_ms / args.ticks as f64 } else { 0.0 },
        static_pairs: Some(pairs[0]),
        dynamic_pairs: Some(pairs[1]),
        static_contacts: Some(pairs[2]),
        dynamic_contacts: Some(pairs[3]),
        actions,
        users_mean_x: crowd_x(
            &args,
            world.dynamics.kinds().iter().copied().zip(world.dynamics.positions().iter().copied()),
        ),
        state_hash: format!("{:016x}", world.state_hash()),
        zoned: None,
    };
    print(&args, &s)
}

fn print(args: &SimArgs, s: &Summary) -> Result<()> {
    if args.json {
        println!("{}", serde_json::to_string(&s)?);
    } else {
        println!("scenario     {} (seed {})", s.scenario, s.seed);
        println!("backend      {}", s.description);
        println!(
            "objects      {} dynamic ({} users), {} static ({} spheres, {} boxes, {} capsules)",
            s.dynamic, s.users, s.static_objects, s.static_prims[0], s.static_prims[1], s.static_prims[2]
        );
        println!("ticks        {} in {:.1} ms ({:.3} ms a tick)", s.ticks, s.total_ms, s.mean_tick_ms);
        if let (Some(sp), Some(dp), Some(sc), Some(dc)) =
            (s.static_pairs, s.dynamic_pairs, s.static_contacts, s.dynamic_contacts)
        {
            println!("pairs        {sp} static, {dp} dynamic (all ticks)");
            println!("contacts     {sc} static, {dc} dynamic (all ticks)");
        }
        if args.actions.is_some() || s.actions > 0 {
            println!("actions      {} applied from the script", s.actions);
        }
        if let Some(x) = s.users_mean_x {
            println!("crowd        users' mean x at the end {x:.1}");
        }
        if let Some(z) = &s.zoned {
            println!(
                "zones        {} ({} x {}, reach {:.2}) over {}: {} ghost records, {} hand-offs, {} messages, {:.1} MB",
                z.zones,
                z.grid.0,
                z.grid.1,
                z.reach,
                z.fabric,
                z.ghost_records,
                z.handoffs,
                z.messages,
                z.fabric_bytes as f64 / 1e6
            );
            println!("owned        {:?} (static primitives held {:?})", z.owned, z.static_prims);
            let ms = |v: &[f64]| v.iter().map(|w| format!("{w:.2}")).collect::<Vec<_>>().join(", ");
            println!(
                "per zone     physics [{}], zone overhead [{}], wait [{}] ms a tick",
                ms(&z.physics_ms),
                ms(&z.overhead_ms),
                ms(&z.wait_ms)
            );
            println!(
                "  of which   scan [{}], edit [{}] (moving slots [{}]); device copies [{}] ms a tick",
                ms(&z.scan_ms),
                ms(&z.edit_ms),
                ms(&z.moving_ms),
                ms(&z.copies_ms)
            );
            println!(
                "  slots      inserted {:?}, removed {:?}, ticks that moved slots {:?}",
                z.slots.iter().map(|s| s.0).collect::<Vec<_>>(),
                z.slots.iter().map(|s| s.1).collect::<Vec<_>>(),
                z.slots.iter().map(|s| s.2).collect::<Vec<_>>()
            );
            println!("rejected     {} messages", z.rejected);
            println!("cut moves    {} (cuts at the end: x {:?}, z {:?})", z.cut_moves, z.cuts.0, z.cuts.1);
            for (decided, applied, xs, zs) in &z.moves {
                println!("  move       decided at tick {decided}, applied at {applied}: x {xs:?}, z {zs:?}");
            }
            println!(
                "load         most loaded zone's objects over the mean: {:.2} (whole run), {:.2} (last third)",
                z.most_owned_over_mean.0, z.most_owned_over_mean.1
            );
            println!(
                "             slowest zone's physics over the mean: {:.2} (whole run), {:.2} (last third: [{}] ms a tick)",
                z.slowest_over_mean.0,
                z.slowest_over_mean.1,
                ms(&z.physics_ms_last_third)
            );
        }
        println!("state hash   {}", s.state_hash);
    }
    Ok(())
}

/// `myriad sim --zones K [--nats URL]`: the same world split into zones on threads.
fn run_zoned(
    args: &SimArgs,
    spec: &myriad_core::ScenarioSpec,
    world: &myriad_core::World,
    script: &ActionScript,
    k: &TickConstants,
) -> Result<()> {
    use myriad_zone::{Fabric, MemoryFabric, NatsFabric, ZoneError, ZoneId, ZoneLayout};
    let layout = ZoneLayout::for_count(&world.bounds, args.zones, myriad_zone::pair_reach(world), args.zone_max_step)?;
    let n = layout.len();
    let (fabrics, fabric): (Vec<Box<dyn Fabric>>, _) = match &args.nats {
        None => (MemoryFabric::mesh(n).into_iter().map(|f| Box::new(f) as Box<dyn Fabric>).collect(), "memory"),
        Some(url) => {
            // A cluster name of its own per run by default, so that concurrent runs never mix.
            let cluster = args.cluster.clone().unwrap_or_else(|| format!("sim-{}-{}", std::process::id(), world.seed));
            // The zones' credentials, from the environment (none: a server without auth).
            let auth = myriad_zone::fabric_auth::NatsAuth::from_env()?;
            let f = (0..n)
                .map(|z| {
                    NatsFabric::connect(url, &cluster, ZoneId(z as u16), &auth).map(|f| Box::new(f) as Box<dyn Fabric>)
                })
                .collect::<Result<Vec<_>, _>>()
                .context("connecting the zones to NATS")?;
            (f, "nats")
        }
    };
    let gpus = args.gpus as usize;
    let kind = args.backend;
    let backend = move |z: ZoneId| -> Result<Box<dyn myriad_physics::Backend>, ZoneError> {
        Ok(myriad_cuda::create_backend_on(kind, z.0 as usize % gpus)?.backend)
    };
    let description = backend(ZoneId(0))?.description();
    let grid = layout.shape();
    let reach = layout.reach();
    let mut opts = myriad_zone::RunOptions::new(args.ticks, std::time::Duration::from_secs(300));
    // Always watched (reports cost a histogram of the owned objects every
    // `--rebalance-every` ticks); moved with --rebalance.
    let policy = if args.rebalance {
        myriad_zone::rebalance::Policy::Counts(Default::default())
    } else {
        myriad_zone::rebalance::Policy::Watch
    };
    opts.rebalance = Some(myriad_zone::RebalanceOptions {
        every: args.rebalance_every,
        policy,
        ..myriad_zone::RebalanceOptions::default()
    });
    let run = myriad_zone::run_zoned(world, layout, script, k, &backend, fabrics, &opts)?;
    let log = run.rebalance.clone().unwrap_or_default();
    let last_third = last_third(&log.samples, n, run.tick, args.ticks);
    let physics: Vec<f64> =
        run.stats.iter().map(|s| s.physics.as_secs_f64() * 1e3 / args.ticks.max(1) as f64).collect();
    // The ticks alone, as for one process: world assembly and backend start-up excluded.
    let total_ms = run.ticks_ms;
    let ticks = args.ticks.max(1) as f64;
    let zoned = ZoneSummary {
        zones: n,
        grid,
        reach,
        fabric,
        owned: run.stats.iter().map(|s| s.owned).collect(),
        static_prims: run.static_prims.clone(),
        ghost_records: run.stats.iter().map(|s| s.ghosts_in).sum(),
        handoffs: run.stats.iter().map(|s| s.handoffs_in).sum(),
        messages: run.stats.iter().map(|s| s.messages.0).sum(),
        fabric_bytes: run.stats.iter().map(|s| s.bytes.0).sum(),
        wait_ms: run.stats.iter().map(|s| s.wait.as_secs_f64() * 1e3 / ticks).collect(),
        physics_ms: run.stats.iter().map(|s| s.physics.as_secs_f64() * 1e3 / ticks).collect(),
        overhead_ms: run.stats.iter().map(|s| (s.step + s.send - s.physics).as_secs_f64() * 1e3 / ticks).collect(),
        scan_ms: run.stats.iter().map(|s| s.scan.as_secs_f64() * 1e3 / ticks).collect(),
        edit_ms: run.stats.iter().map(|s| s.edit.as_secs_f64() * 1e3 / ticks).collect(),
        moving_ms: run.stats.iter().map(|s| s.moving.as_secs_f64() * 1e3 / ticks).collect(),
        copies_ms: run.stats.iter().map(|s| s.copies.as_secs_f64() * 1e3 / ticks).collect(),
        slots: run.stats.iter().map(|s| (s.slots_inserted, s.slots_removed, s.moving_ticks)).collect(),
        rejected: run.stats.iter().map(|s| s.rejected_total()).sum(),
        cut_moves: run.cut_moves,
        moves: log.moves.iter().map(|m| (m.decided_at, m.apply_at, m.xs.clone(), m.zs.clone())).collect(),
        cuts: log.cuts.clone(),
        slowest_over_mean: (slowest_over_mean(&physics), slowest_over_mean(&last_third)),
        physics_ms_last_third: last_third,
        most_owned_over_mean: (
            owned_over_mean(&log.samples, 0),
            owned_over_mean(&log.samples, run.tick - args.ticks / 3 + 1),
        ),
        samples: log.samples.iter().map(|s| (s.tick, s.owned.clone(), s.physics_ms.clone())).collect(),
    };
    let s = Summary {
        scenario: spec.name.clone(),
        backend: kind.to_string(),
        description: format!("{description}, {n} zones"),
        seed: spec.seed,
        ticks: args.ticks,
        dynamic: run.objects.len(),
        users: run.objects.iter().filter(|o| o.kind == ObjectKind::User).count(),
        static_objects: world.statics.objects().len(),
        static_prims: world.statics.prims_by_shape(),
        total_ms,
        mean_tick_ms: total_ms / ticks,
        // Pair counts are per zone and include ghosts' pairs: not comparable, not shown.
        static_pairs: None,
        dynamic_pairs: None,
        static_contacts: None,
        dynamic_contacts: None,
        actions: run.actions,
        users_mean_x: crowd_x(args, run.objects.iter().map(|o| (o.kind, o.pos))),
        state_hash: format!("{:016x}", run.state_hash),
        zoned: Some(zoned),
    };
    print(args, &s)
}

/// The users' mean x, for the moving crowd (whose users are the crowd).
fn crowd_x(args: &SimArgs, objects: impl Iterator<Item = (ObjectKind, myriad_core::Vec3)>) -> Option<f32> {
    if args.scenario != ScenarioName::MovingCrowd {
        return None;
    }
    let (sum, n) =
        objects.filter(|(k, _)| *k == ObjectKind::User).fold((0.0f64, 0u32), |(s, n), (_, p)| (s + p.x as f64, n + 1));
    (n > 0).then(|| (sum / n as f64) as f32)
}

/// Each zone's mean physics ms a tick over the samples of the last third of a run of
/// `ticks` ticks ending at `end`.
fn last_third(samples: &[myriad_zone::rebalance::LoadSample], zones: usize, end: u64, ticks: u64) -> Vec<f64> {
    let from = end - ticks / 3;
    let (mut ms, mut n) = (vec![0.0; zones], 0u64);
    for s in samples.iter().filter(|s| s.tick > from) {
        for (acc, v) in ms.iter_mut().zip(&s.physics_ms) {
            *acc += v * s.ticks as f64;
        }
        n += s.ticks;
    }
    ms.iter().map(|v| v / n.max(1) as f64).collect()
}

/// The largest figure over the mean (1 when all are equal; 0 when there are none).
fn slowest_over_mean(v: &[f64]) -> f64 {
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    if mean > 0.0 { v.iter().copied().fold(0.0, f64::max) / mean } else { 0.0 }
}

/// The mean over the samples from tick `from` on of the most loaded zone's objects over
/// the zones' mean.
fn owned_over_mean(samples: &[myriad_zone::rebalance::LoadSample], from: u64) -> f64 {
    let ratios: Vec<f64> = samples
        .iter()
        .filter(|s| s.tick >= from)
        .map(|s| slowest_over_mean(&s.owned.iter().map(|&o| o as f64).collect::<Vec<_>>()))
        .collect();
    ratios.iter().sum::<f64>() / ratios.len().max(1) as f64
}
