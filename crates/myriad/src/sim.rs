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
    rejected: u64,
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
    state_hash: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    zoned: Option<ZoneSummary>,
}

/// Runs `myriad sim`.
pub fn run(args: SimArgs) -> Result<()> {
    let (spec, mut world) = args.world.build(args.scenario)?;
    let script = match &args.actions {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            ActionScript::parse(&text).with_context(|| format!("in {}", path.display()))?
        }
        None => ActionScript::default(),
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
        if args.actions.is_some() {
            println!("actions      {} applied from the script", s.actions);
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
            println!("rejected     {} messages", z.rejected);
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
    let opts = myriad_zone::RunOptions::new(args.ticks, std::time::Duration::from_secs(300));
    let run = myriad_zone::run_zoned(world, layout, script, k, &backend, fabrics, &opts)?;
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
        rejected: run.stats.iter().map(|s| s.rejected_total()).sum(),
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
        state_hash: format!("{:016x}", run.state_hash),
        zoned: Some(zoned),
    };
    print(args, &s)
}
