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
    #[command(flatten)]
    pub world: WorldArgs,
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
    static_pairs: u64,
    dynamic_pairs: u64,
    static_contacts: u64,
    dynamic_contacts: u64,
    /// Scripted actions applied.
    actions: usize,
    state_hash: String,
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
    let mut backend = create_backend(args.backend)?;
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
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
        static_pairs: pairs[0],
        dynamic_pairs: pairs[1],
        static_contacts: pairs[2],
        dynamic_contacts: pairs[3],
        actions,
        state_hash: format!("{:016x}", world.state_hash()),
    };
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
        println!("pairs        {} static, {} dynamic (all ticks)", s.static_pairs, s.dynamic_pairs);
        println!("contacts     {} static, {} dynamic (all ticks)", s.static_contacts, s.dynamic_contacts);
        if args.actions.is_some() {
            println!("actions      {} applied from the script", s.actions);
        }
        println!("state hash   {}", s.state_hash);
    }
    Ok(())
}
