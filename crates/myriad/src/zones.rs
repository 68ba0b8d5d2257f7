//! `myriad zone` and `myriad cluster`: one world on several processes over NATS.
//!
//! `myriad cluster --zones K` is the one-command local cluster: it finds NATS (or starts
//! a private `nats-server`, locked down by role, when none answers and one is installed:
//! `cluster_nats.rs`), starts K `myriad zone` processes, supervises them (restarting any
//! that exits, rolling the cluster back to its last consistent checkpoint) and prints
//! the final state hash, comparable with `myriad sim`. See docs/zones.md.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use myriad_core::{ActionScript, PhysicsConfig, ScenarioSpec, World};
use myriad_physics::{BackendKind, TickConstants};
use myriad_zone::checkpoint::JetStreamCheckpoints;
use myriad_zone::fabric_auth::NatsAuth;
use myriad_zone::nats::NatsLink;
use myriad_zone::process::{ProcessConfig, run_zone_process};
use myriad_zone::rebalance::announce::Announcement;
use myriad_zone::supervisor::{Event, SupervisorConfig, cut_move_line, supervise};
use myriad_zone::{ClusterKey, Fabric, NatsFabric, ZoneId, ZoneLayout};
use serde::Serialize;

use crate::cluster_nats::hand;
use crate::cluster_rebalance::live_options;
use crate::scenario_args::{ScenarioName, WorldArgs};

/// The environment variable that carries the cluster's key (at least 16 bytes) to zone
/// processes; never a flag, so that it stays out of `ps`.
pub const KEY_ENV: &str = "MYRIAD_CLUSTER_KEY";

/// What every process of a cluster must agree on.
#[derive(Args, Debug, Clone)]
pub struct ClusterCommon {
    /// The scenario.
    #[arg(long, value_enum, default_value = "1")]
    pub scenario: ScenarioName,
    /// The physics backend of each zone.
    #[arg(long, default_value = "auto")]
    pub backend: BackendKind,
    /// The last tick of the run.
    #[arg(long, default_value_t = 300)]
    pub ticks: u64,
    /// Zones (a grid as square as the count allows).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u16).range(1..=1024))]
    pub zones: u16,
    /// Ticks between checkpoints (30 = one second at 30 Hz).
    #[arg(long, default_value_t = 30)]
    pub checkpoint_every: u64,
    /// Checkpoints (with their intent log segments) each zone keeps, at least 3: `myriad
    /// replay` can start from the oldest.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(3..))]
    pub keep_checkpoints: u64,
    /// How long a zone waits for a neighbour before reporting a stall, in ms.
    #[arg(long, default_value_t = 3000)]
    pub stall_ms: u64,
    /// Ticks a second (0: as fast as the slowest zone).
    #[arg(long, default_value_t = 0.0)]
    pub tick_hz: f64,
    /// How far an object may move in one tick.
    #[arg(long, default_value_t = 2.0)]
    pub zone_max_step: f32,
    /// Serve gateways: zones publish their objects' states every tick and take players'
    /// joins, actions and leaves (`myriad gateway`); use with `--tick-hz 30` and a large
    /// `--ticks`.
    #[arg(long)]
    pub live: bool,
    /// What live zones send the gateways: `interest` (each gateway's subscribed cells,
    /// only what changed since it confirmed) or `mirror` (every object to every gateway,
    /// every tick). Gateways started by `myriad cluster` get the same.
    #[arg(long, value_enum, default_value = "interest")]
    pub gateway_states: GatewayStates,
    /// A script of players' actions (`TICK ENTITY MASK` lines).
    #[arg(long, value_name = "FILE")]
    pub actions: Option<PathBuf>,
    #[command(flatten)]
    pub world: WorldArgs,
}

/// What zones send gateways (docs/zones.md, "States by interest").
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum GatewayStates {
    /// Each gateway's view of the cells its players see, changes only.
    Interest,
    /// Every zone's every object to every gateway, every tick.
    Mirror,
}

impl GatewayStates {
    /// The flag's value.
    pub fn name(self) -> &'static str {
        match self {
            GatewayStates::Interest => "interest",
            GatewayStates::Mirror => "mirror",
        }
    }
}

/// Flags of `myriad zone`.
#[derive(Args, Debug)]
pub struct ZoneArgs {
    /// The cluster's name (one token of NATS subjects).
    #[arg(long)]
    pub cluster: String,
    /// This zone's index.
    #[arg(long)]
    pub zone: u16,
    /// The NATS server.
    #[arg(long, value_name = "URL", default_value = "nats://127.0.0.1:4222")]
    pub nats: String,
    /// The GPU (device ordinal) of the CUDA backends.
    #[arg(long, default_value_t = 0)]
    pub gpu: usize,
    /// Serve Prometheus metrics on this address (`/metrics`).
    #[arg(long)]
    pub metrics: Option<SocketAddr>,
    #[command(flatten)]
    pub common: ClusterCommon,
}

/// Flags of `myriad cluster`.
#[derive(Args, Debug)]
pub struct ClusterArgs {
    /// The NATS server; by default 127.0.0.1:4222, or a private `nats-server` started for
    /// the run when none answers there.
    #[arg(long, value_name = "URL")]
    pub nats: Option<String>,
    /// The cluster's name (default: one of its own per run).
    #[arg(long)]
    pub cluster: Option<String>,
    /// GPUs to spread the zones over (zone i on device i mod N).
    #[arg(long, default_value_t = 1)]
    pub gpus: usize,
    /// A zone whose heartbeat is older than this many ms is dead.
    #[arg(long, default_value_t = 1500)]
    pub dead_ms: u64,
    /// Serve each zone's Prometheus metrics on 127.0.0.1:(this port + zone index).
    #[arg(long)]
    pub metrics_base_port: Option<u16>,
    /// A directory of the roles' NATS credentials for `--nats` (`zone-<z>.creds`,
    /// `gateway.creds`, `supervisor.creds`, as `--write-nats-config` writes them); without
    /// it every process presents this one's (`MYRIAD_NATS_USER`/`MYRIAD_NATS_PASSWORD` or
    /// `MYRIAD_NATS_CREDS`; none: a server without auth).
    #[arg(long, value_name = "DIR")]
    pub nats_creds_dir: Option<PathBuf>,
    /// Start a private `nats-server` (locked down by role) even when one answers at
    /// 127.0.0.1:4222.
    #[arg(long, conflicts_with = "nats")]
    pub private_nats: bool,
    /// Write the NATS configuration of the cluster `--cluster NAME` of `--zones K` zones
    /// (an `authorization` block for an operator's `nats-server`, and each role's
    /// credentials file: one per zone, the gateways', the supervisor's) into DIR, and
    /// exit.
    #[arg(long, value_name = "DIR", requires = "cluster")]
    pub write_nats_config: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Gateways to start for players (with `--live`, on the map of a reference scenario:
    /// its statics, size and terrain, with any moving objects): gateway i serves
    /// UDP on 127.0.0.1:(gateway-port + 2i) and its TLS login on the next port, keeps its
    /// data (SQLite, certificate) in GATEWAY_DATA/gateway-i, and is restarted if it exits.
    #[arg(long, default_value_t = 0, requires = "live")]
    pub gateways: u16,
    /// The first gateway's UDP port.
    #[arg(long, default_value_t = 7700)]
    pub gateway_port: u16,
    /// Where the gateways keep their data.
    #[arg(long, default_value = "myriad-cluster")]
    pub gateway_data: PathBuf,
    /// Move the cuts while the cluster runs, from the step times the zones report (a zone
    /// over 80 % of the tick budget or 1.15 × the mean for 3 s gives up area; docs/zones.md,
    /// "Boundaries that follow the load").
    #[arg(long)]
    pub rebalance: bool,
    /// Ticks between the highest tick any zone reported and a cut move's tick: more than
    /// the zones step between two heartbeats (250 ms) and a delivery.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..))]
    pub rebalance_lead_ticks: u64,
    /// Instead of the step-time policy, exactly these moves (repeatable): `AT:X1,X2/Z1`
    /// moves the inner cuts (edges implied) to x = X1, X2 and z = Z1 at tick AT + the
    /// lead (an empty list keeps an axis's cuts).
    #[arg(long, value_name = "AT:XS/ZS", conflicts_with = "rebalance")]
    pub rebalance_force: Vec<String>,
    /// Serve the supervisor's Prometheus metrics (the zones' load and the cut moves) on
    /// this address (`/metrics`).
    #[arg(long)]
    pub supervisor_metrics: Option<SocketAddr>,
    #[command(flatten)]
    pub common: ClusterCommon,
}

pub(crate) struct Prepared {
    pub world: World,
    pub layout: ZoneLayout,
    pub script: ActionScript,
}

/// The longest run of the moving crowd in a cluster: its script (about one entry per
/// member every 40 ticks) is held whole by every process; 200,000 ticks (almost two
/// hours at 30 Hz) are 15 million entries for the default 3,000 members.
const MOVING_CROWD_MAX_TICKS: u64 = 200_000;

/// The world, layout and script every process of a cluster makes from its flags.
pub(crate) fn prepare(c: &ClusterCommon) -> Result<Prepared> {
    let (world, script) = if c.scenario == ScenarioName::MovingCrowd {
        // The crowd walks by a script made from the seed for the whole run, so every
        // process of the cluster makes the same one (and `myriad sim` too).
        if c.actions.is_some() {
            bail!("the moving crowd walks by its own script: drop --actions");
        }
        if c.ticks > MOVING_CROWD_MAX_TICKS {
            bail!("the moving crowd's script is made for the whole run: at most {MOVING_CROWD_MAX_TICKS} ticks");
        }
        let (_, world, script) = c.world.build_with_script(c.scenario, c.ticks)?;
        (world, script)
    } else {
        let (_, world) = c.world.build(c.scenario)?;
        let script = match &c.actions {
            Some(path) => {
                let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
                ActionScript::parse(&text).with_context(|| format!("in {}", path.display()))?
            }
            None => ActionScript::default(),
        };
        (world, script)
    };
    let layout = ZoneLayout::for_count(&world.bounds, c.zones, myriad_zone::pair_reach(&world), c.zone_max_step)?;
    Ok(Prepared { world, layout, script })
}

/// The cluster's key from [`KEY_ENV`].
pub fn key_from_env() -> Result<ClusterKey> {
    let secret = std::env::var(KEY_ENV).with_context(|| format!("{KEY_ENV} must hold the cluster's key"))?;
    Ok(ClusterKey::new(secret.as_bytes())?)
}

/// Runs `myriad zone`.
pub fn run_zone(args: ZoneArgs) -> Result<()> {
    let key = key_from_env()?;
    let p = prepare(&args.common)?;
    if args.zone as usize >= p.layout.len() {
        bail!("zone {} of {} zones", args.zone, p.layout.len());
    }
    if let Some(addr) = args.metrics {
        metrics_exporter_prometheus::PrometheusBuilder::new()
            .with_http_listener(addr)
            .install()
            .context("starting the metrics endpoint")?;
    }
    let zone = ZoneId(args.zone);
    let auth = NatsAuth::from_env()?;
    let fabric = NatsFabric::connect(&args.nats, &args.cluster, zone, &auth)?;
    let heartbeat = fabric.heartbeat(key.clone(), Duration::from_millis(250));
    let link = fabric.link();
    let mut store = JetStreamCheckpoints::open(link.rt.clone(), link.client.clone(), &args.cluster, key.clone())?;
    let c = &args.common;
    let cfg = ProcessConfig {
        zone,
        key,
        ticks: c.ticks,
        checkpoint_every: c.checkpoint_every,
        stall: Duration::from_millis(c.stall_ms),
        period: if c.tick_hz > 0.0 { Duration::from_secs_f64(1.0 / c.tick_hz) } else { Duration::ZERO },
        live: c.live,
        mirror: c.gateway_states == GatewayStates::Mirror,
        keep: c.keep_checkpoints,
    };
    let (kind, gpu) = (c.backend, args.gpu);
    let backend = move || Ok(myriad_cuda::create_backend_on(kind, gpu)?.backend);
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    run_zone_process(
        &cfg,
        Arc::new(p.layout),
        &p.world,
        &p.script,
        &k,
        &backend,
        Box::new(fabric) as Box<dyn Fabric>,
        &mut store,
        &heartbeat,
    )?;
    Ok(())
}

/// The flags of `myriad cluster` that zones do not take.
const CLUSTER_ONLY: &[&str] = &[
    "--nats",
    "--cluster",
    "--gpus",
    "--dead-ms",
    "--metrics-base-port",
    "--gateways",
    "--gateway-port",
    "--gateway-data",
    "--nats-creds-dir",
    "--private-nats",
    "--write-nats-config",
    "--rebalance",
    "--rebalance-lead-ticks",
    "--rebalance-force",
    "--supervisor-metrics",
];

/// The flags of [`CLUSTER_ONLY`] that take no value.
const SWITCHES: &[&str] = &["--private-nats", "--rebalance"];

/// The command line of the cluster, less its own flags: what every zone gets.
fn zone_flags() -> Vec<String> {
    let mut out = Vec::new();
    let mut args = std::env::args().skip_while(|a| a != "cluster").skip(1).peekable();
    while let Some(a) = args.next() {
        let name = a.split('=').next().unwrap_or_default().to_string();
        if name == "--json" {
            continue;
        }
        if CLUSTER_ONLY.contains(&name.as_str()) {
            if !a.contains('=') && !SWITCHES.contains(&name.as_str()) {
                args.next();
            }
            continue;
        }
        out.push(a);
    }
    out
}

/// Makes a child die with the cluster instead of waiting forever as an orphan.
fn die_with_parent(command: &mut Command) {
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::process::CommandExt;
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = command;
}

/// The flags every gateway of the cluster gets: its cluster, and the world's map (a
/// gateway builds the same map from the scenario and seed).
fn gateway_args(args: &ClusterArgs, zones: usize, url: &str, cluster: &str) -> Result<Vec<String>> {
    if args.gateways == 0 {
        return Ok(Vec::new());
    }
    let c = &args.common;
    // A gateway builds a reference scenario's map (bounds, terrain, statics) from its
    // number and seed and takes every moving object from the zones: the zones' world may
    // have other moving objects (counts, users, placement) on one of those maps.
    let spec = c.world.spec(c.scenario)?;
    let scenario = myriad_core::NUMBERED_SCENARIOS
        .into_iter()
        .find(|&n| c.world.heightmap.is_none() && ScenarioSpec::reference(n, spec.seed).is_ok_and(|r| r.same_map(&spec)))
        .ok_or_else(|| {
            anyhow::anyhow!(
                "--gateways serves the maps of the numbered scenarios 1 to 4 (a gateway builds its map from \
                 them): the world's statics, size, origin and terrain must be one of theirs; its moving objects may differ"
            )
        })?
        .to_string();
    let w = &c.world;
    if args.gateways > myriad_zone::gateway::MAX_GATEWAYS {
        bail!("--gateways {}: at most {}", args.gateways, myriad_zone::gateway::MAX_GATEWAYS);
    }
    Ok(["--cluster", cluster, "--zones", &zones.to_string(), "--nats", url, "--scenario", &scenario]
        .into_iter()
        .map(String::from)
        .chain(["--seed".to_string(), w.seed.to_string()])
        .chain(["--gateway-states".to_string(), c.gateway_states.name().to_string()])
        .chain(["--zone-max-step".to_string(), c.zone_max_step.to_string()])
        .collect())
}

#[derive(Serialize)]
struct ClusterSummary {
    zones: usize,
    ticks: u64,
    total_ms: f64,
    /// Every epoch's start: (epoch, checkpoint tick, its state hash).
    starts: Vec<(u64, u64, Option<String>)>,
    faults: Vec<String>,
    /// Cut moves announced.
    cut_moves: Vec<CutMoveSummary>,
    /// Ticks of the cut moves every zone applied.
    cut_moves_applied: Vec<u64>,
    /// Cut moves proposed and not announced, with why.
    cut_moves_refused: Vec<String>,
    /// Every zone's load about twice a second, from the heartbeats: how even the zones
    /// were (`scripts/rebalance-live.sh` reads these).
    load_samples: Vec<LoadSample>,
    state_hash: String,
}

/// The zones' loads at one look of the supervisor ([`Event::Progress`]).
#[derive(Serialize)]
struct LoadSample {
    epoch: u64,
    /// Seconds since the cluster started.
    at_s: f64,
    /// The lowest tick any zone had reached.
    tick: u64,
    /// Each zone's step time, ms (averaged over about a second; `null`: not heard).
    step_ms: Vec<Option<f64>>,
    /// Each zone's owned objects.
    owned: Vec<Option<u32>>,
}

/// A cut move the supervisor announced.
#[derive(Serialize)]
struct CutMoveSummary {
    epoch: u64,
    decided_at: u64,
    apply_at: u64,
    xs: Vec<f32>,
    zs: Vec<f32>,
}

/// A state hash as the cluster prints it.
fn hash_text(hash: u64) -> String {
    format!("{hash:016x}")
}

/// An epoch's start, as the cluster prints it: an event on standard error, a line of the
/// summary.
fn start_line(epoch: u64, tick: u64, hash: Option<&str>) -> String {
    format!("epoch {epoch}      from tick {tick}{}", hash.map(|h| format!(" (state hash {h})")).unwrap_or_default())
}

/// A fault, likewise.
fn fault_line(reason: &str) -> String {
    format!("fault        {reason}")
}

/// A supervisor's event as the cluster prints it on standard error, in the summary's
/// layout; the end is the summary's to report (`None`).
fn event_line(e: &Event) -> Option<String> {
    match e {
        Event::Started { epoch, tick, state_hash } => {
            Some(start_line(*epoch, *tick, state_hash.map(hash_text).as_deref()))
        }
        Event::Fault { reason, .. } => Some(fault_line(reason)),
        Event::Progress { epoch, tick, .. } => Some(format!("epoch {epoch}      at tick {tick}")),
        Event::Cuts { what: Announcement::Send { cut, .. }, .. } => {
            Some(format!("cut move     {}", cut_move_line(cut)))
        }
        Event::Cuts { what: Announcement::Applied(cut), .. } => {
            Some(format!("cut move     applied by every zone at tick {}", cut.apply_at))
        }
        Event::Cuts { what: Announcement::Refused { decided_at, reason }, .. } => {
            Some(format!("cut move     of tick {decided_at} refused: {reason}"))
        }
        Event::Cuts { .. } | Event::Done { .. } => None,
    }
}

/// Runs `myriad cluster`.
pub fn run_cluster(args: ClusterArgs) -> Result<()> {
    let cluster = args.cluster.clone().unwrap_or_else(|| format!("c{}", std::process::id()));
    myriad_zone::nats::check_cluster_name(&cluster)?;
    if let Some(dir) = &args.write_nats_config {
        // A user per zone: as many as the layout has.
        let zones = prepare(&args.common)?.layout.len() as u16;
        return crate::cluster_nats::write_config(dir, &cluster, zones);
    }
    let p = prepare(&args.common)?;
    let zones = p.layout.len();
    let rebalance = live_options(&args, &p.layout)?;
    if let Some(addr) = args.supervisor_metrics {
        metrics_exporter_prometheus::PrometheusBuilder::new()
            .with_http_listener(addr)
            .install()
            .context("starting the supervisor's metrics endpoint")?;
    }
    let nats = crate::cluster_nats::nats_for(
        args.nats.as_deref(),
        args.nats_creds_dir.as_deref(),
        args.private_nats,
        &cluster,
        zones as u16,
    )?;
    let url = nats.url.clone();
    // The key the gateways were given, or one of this run's own.
    let secret = std::env::var(KEY_ENV).unwrap_or_else(|_| myriad_zone::wire::random_secret());
    let key = ClusterKey::new(secret.as_bytes())?;
    let exe = std::env::current_exe()?;
    let flags = zone_flags();
    let spawn = |z: usize| -> Result<Child> {
        let metrics = args.metrics_base_port.map(|p| format!("127.0.0.1:{}", u32::from(p) + z as u32));
        let mut command = Command::new(&exe);
        command
            .arg("zone")
            .args(["--cluster", &cluster, "--zone", &z.to_string(), "--nats", &url])
            .args(["--gpu", &(z % args.gpus.max(1)).to_string()])
            .args(metrics.iter().flat_map(|m| ["--metrics", m.as_str()]))
            .args(&flags)
            .env(KEY_ENV, &secret)
            .stdin(Stdio::null());
        hand(&mut command, &nats.zones[z]);
        die_with_parent(&mut command);
        let child = command.spawn().with_context(|| format!("starting zone {z}"))?;
        eprintln!("zone {z} pid {}", child.id());
        Ok(child)
    };
    let mut children = (0..zones).map(spawn).collect::<Result<Vec<_>>>()?;
    let gateway_args = gateway_args(&args, zones, &url, &cluster)?;
    let spawn_gateway = |g: u16| -> Result<Child> {
        let (udp, login) =
            (u32::from(args.gateway_port) + 2 * u32::from(g), u32::from(args.gateway_port) + 2 * u32::from(g) + 1);
        let data = args.gateway_data.join(format!("gateway-{g}"));
        let mut command = Command::new(&exe);
        command
            .arg("gateway")
            .args(&gateway_args)
            .args(["--gateway", &g.to_string(), "--data-dir", &data.display().to_string()])
            .args(["--udp", &format!("127.0.0.1:{udp}"), "--login", &format!("127.0.0.1:{login}")])
            .args(
                args.metrics_base_port
                    .map(|p| format!("127.0.0.1:{}", u32::from(p) + 100 + u32::from(g)))
                    .iter()
                    .flat_map(|m| ["--metrics", m.as_str()]),
            )
            .env(KEY_ENV, &secret)
            .stdin(Stdio::null());
        hand(&mut command, &nats.gateway);
        die_with_parent(&mut command);
        let child = command.spawn().with_context(|| format!("starting gateway {g}"))?;
        eprintln!(
            "gateway {g} pid {}: login (TLS) 127.0.0.1:{login}, game (UDP) 127.0.0.1:{udp}, certificate {}",
            child.id(),
            data.join("tls-cert.pem").display()
        );
        Ok(child)
    };
    let mut gateways = (0..args.gateways).map(spawn_gateway).collect::<Result<Vec<_>>>()?;
    let link = NatsLink::connect(&url, format!("myriad-{cluster}-supervisor"), &nats.supervisor)?;
    let mut store = JetStreamCheckpoints::open(link.rt.clone(), link.client.clone(), &cluster, key.clone())?;
    let cfg = SupervisorConfig {
        cluster: cluster.clone(),
        key,
        zones,
        ticks: args.common.ticks,
        objects: (!args.common.live).then_some(p.world.dynamics.len()),
        dead_after: Duration::from_millis(args.dead_ms),
        checkpoint_every: args.common.checkpoint_every,
        layout: p.layout.clone(),
        rebalance,
    };
    let mut summary = ClusterSummary {
        zones,
        ticks: cfg.ticks,
        total_ms: 0.0,
        starts: Vec::new(),
        faults: Vec::new(),
        cut_moves: Vec::new(),
        cut_moves_applied: Vec::new(),
        cut_moves_refused: Vec::new(),
        load_samples: Vec::new(),
        state_hash: String::new(),
    };
    let start = Instant::now();
    let mut restart_error = None;
    let mut restarted = || {
        // A gateway that exits loses its players' sessions (the zones drop their
        // objects); it comes back for new logins.
        for (g, child) in gateways.iter_mut().enumerate() {
            if let Ok(Some(status)) = child.try_wait() {
                eprintln!("gateway {g} exited ({status}); restarting it");
                match spawn_gateway(g as u16) {
                    Ok(c) => *child = c,
                    Err(e) => restart_error = Some(e),
                }
            }
        }
        let mut out = Vec::new();
        for (z, child) in children.iter_mut().enumerate() {
            if let Ok(Some(status)) = child.try_wait() {
                eprintln!("zone {z} exited ({status}); restarting it");
                match spawn(z) {
                    Ok(c) => *child = c,
                    Err(e) => restart_error = Some(e),
                }
                out.push(ZoneId(z as u16));
            }
        }
        out
    };
    let mut on_event = |e: &Event| {
        if let Some(line) = event_line(e) {
            eprintln!("{line}");
        }
        match e {
            Event::Started { epoch, tick, state_hash } => {
                summary.starts.push((*epoch, *tick, state_hash.map(hash_text)))
            }
            Event::Fault { reason, .. } => summary.faults.push(reason.clone()),
            Event::Cuts { epoch, what: Announcement::Send { cut, .. } } => summary.cut_moves.push(CutMoveSummary {
                epoch: *epoch,
                decided_at: cut.decided_at,
                apply_at: cut.apply_at,
                xs: cut.xs.clone(),
                zs: cut.zs.clone(),
            }),
            Event::Cuts { what: Announcement::Applied(cut), .. } => summary.cut_moves_applied.push(cut.apply_at),
            Event::Cuts { what: Announcement::Refused { decided_at, reason }, .. } => {
                summary.cut_moves_refused.push(format!("tick {decided_at}: {reason}"))
            }
            Event::Progress { epoch, tick, beats } => summary.load_samples.push(LoadSample {
                epoch: *epoch,
                at_s: start.elapsed().as_secs_f64(),
                tick: *tick,
                step_ms: beats.iter().map(|b| b.map(|b| f64::from(b.load.step_us) / 1e3)).collect(),
                owned: beats.iter().map(|b| b.map(|b| b.load.owned)).collect(),
            }),
            Event::Cuts { .. } | Event::Done { .. } => {}
        }
    };
    let result = supervise(&cfg, &link, &mut store, &mut restarted, &mut on_event);
    for child in children.iter_mut().chain(gateways.iter_mut()) {
        let _ = child.kill();
        let _ = child.wait();
    }
    // A cluster named by this run cannot be resumed by another: leave no bucket behind.
    if args.cluster.is_none()
        && let Err(e) = store.delete()
    {
        eprintln!("warning: {e}");
    }
    if let Some(e) = restart_error {
        return Err(e);
    }
    let hash = result?;
    summary.total_ms = start.elapsed().as_secs_f64() * 1e3;
    summary.state_hash = hash_text(hash);
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!("zones        {zones} processes over NATS ({} ticks in {:.0} ms)", summary.ticks, summary.total_ms);
        for (epoch, tick, h) in &summary.starts {
            println!("{}", start_line(*epoch, *tick, h.as_deref()));
        }
        for f in &summary.faults {
            println!("{}", fault_line(f));
        }
        for m in &summary.cut_moves {
            let applied = if summary.cut_moves_applied.contains(&m.apply_at) { "applied" } else { "not applied" };
            println!(
                "cut move     epoch {}, decided at tick {}, tick {} ({applied}): x {:?}, z {:?}",
                m.epoch, m.decided_at, m.apply_at, m.xs, m.zs
            );
        }
        println!("state hash   {}", summary.state_hash);
    }
    Ok(())
}
