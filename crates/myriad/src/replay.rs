//! `myriad replay`: re-runs a cluster's world from a checkpoint its zones stored, with the
//! intents they logged, and compares the end with the checkpoints of the live run's last
//! tick (docs/zones.md, "Live runs replay bit for bit").

use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use myriad_core::PhysicsConfig;
use myriad_physics::TickConstants;
use myriad_zone::ZoneId;
use myriad_zone::checkpoint::{CheckpointStore, JetStreamCheckpoints};
use myriad_zone::fabric_auth::NatsAuth;
use myriad_zone::nats::NatsLink;
use myriad_zone::replay::{load, replay};
use myriad_zone::supervisor::assemble;
use serde::Serialize;

use crate::zones::{ClusterCommon, key_from_env, prepare};

/// Flags of `myriad replay`: the cluster's own (scenario, zones, ticks, checkpoint
/// interval, ...), its name and NATS server, and where to start.
#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// The cluster's name (its checkpoints and logs are in the bucket `myriad-<name>`;
    /// `myriad cluster --cluster NAME` keeps it).
    #[arg(long)]
    pub cluster: String,
    /// The NATS server.
    #[arg(long, value_name = "URL", default_value = "nats://127.0.0.1:4222")]
    pub nats: String,
    /// The checkpoint to start from (default: the oldest whose logs reach `--to` in one
    /// epoch).
    #[arg(long)]
    pub from: Option<u64>,
    /// The checkpoint to end at, compared with the live run's (default: the latest that
    /// every zone stored, at most `--ticks`: a run that ended, or one stopped early).
    #[arg(long)]
    pub to: Option<u64>,
    /// GPUs to spread the zones over (zone i on device i mod N).
    #[arg(long, default_value_t = 1)]
    pub gpus: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub common: ClusterCommon,
}

#[derive(Serialize)]
struct ReplaySummary {
    zones: usize,
    from: u64,
    to: u64,
    epoch: u64,
    intents: usize,
    cut_moves: usize,
    replay_ms: f64,
    state_hash: String,
    live_state_hash: String,
    equal: bool,
}

/// Runs `myriad replay`; fails when the replay ends elsewhere than the live run.
pub fn run(args: ReplayArgs) -> Result<()> {
    let key = key_from_env()?;
    let c = &args.common;
    let p = prepare(c)?;
    let zones = p.layout.len();
    // The supervisor role's credentials (it reads the bucket), from the environment.
    let link = NatsLink::connect(&args.nats, format!("myriad-{}-replay", args.cluster), &NatsAuth::from_env()?)?;
    let mut store = JetStreamCheckpoints::open(link.rt.clone(), link.client.clone(), &args.cluster, key.clone())?;
    let every = c.checkpoint_every.max(1);
    let to = match args.to {
        Some(t) => t,
        None => {
            // The last tick, then every checkpoint tick below it, newest first.
            let below = (0..=c.ticks / every).rev().map(|i| i * every).filter(|t| *t < c.ticks);
            let candidates: Vec<u64> = std::iter::once(c.ticks).chain(below).collect();
            store
                .latest_consistent(zones, &candidates)?
                .with_context(|| format!("no tick of cluster {} that every zone stored", args.cluster))?
        }
    };
    let candidates: Vec<u64> = match args.from {
        Some(t) => vec![t],
        None => {
            let last = to / every * every;
            let oldest = last.saturating_sub(c.keep_checkpoints * every);
            (oldest / every..=last / every).map(|i| i * every).filter(|t| *t <= to).collect()
        }
    };
    let mut loaded = None;
    let mut last_error = None;
    for from in candidates {
        match load(&mut store, &key, zones, from, to) {
            Ok(l) => {
                loaded = Some((from, l));
                break;
            }
            Err(e) => last_error = Some(e),
        }
    }
    let Some((from, (epoch, inputs))) = loaded else {
        bail!("no checkpoint to replay from: {}", last_error.map_or("none stored".into(), |e| e.to_string()));
    };
    // Every zone logs every cut move it applied: count them once, and the intents of all.
    let moves_of = |z: &myriad_zone::replay::ZoneReplay| {
        z.entries.iter().filter(|(_, m)| myriad_zone::replay::is_cut_move(m)).count()
    };
    let cut_moves = inputs.first().map_or(0, moves_of);
    let intents = inputs.iter().map(|z| z.entries.len() - moves_of(z)).sum();
    let live = assemble(&mut store, zones, to, None)?.0;
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    let (kind, gpus) = (c.backend, args.gpus.max(1));
    let backend = move |z: ZoneId| Ok(myriad_cuda::create_backend_on(kind, z.0 as usize % gpus)?.backend);
    let start = Instant::now();
    let run = replay(&p.world, p.layout, &p.script, &k, &backend, inputs, &key, from, to)?;
    let summary = ReplaySummary {
        zones,
        from,
        to,
        epoch,
        intents,
        cut_moves,
        replay_ms: start.elapsed().as_secs_f64() * 1e3,
        state_hash: format!("{:016x}", run.state_hash),
        live_state_hash: format!("{live:016x}"),
        equal: run.state_hash == live,
    };
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!(
            "replay       {zones} zones, ticks {from}..{to} of epoch {epoch}, {intents} intents messages, {} cut \
             moves, {:.0} ms",
            summary.cut_moves, summary.replay_ms
        );
        println!("state hash   {} (live: {})", summary.state_hash, summary.live_state_hash);
    }
    if !summary.equal {
        bail!("the replay ends in {}, the live run in {}", summary.state_hash, summary.live_state_hash);
    }
    Ok(())
}
