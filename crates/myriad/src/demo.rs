//! `myriad demo`: a server on the embedded database with built-in bots playing, and a
//! live status line.

use std::io::{IsTerminal, Write};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use myriad_client::{Behaviour, ClientConfig, Swarm, SwarmConfig, SwarmSnapshot, Trust};
use myriad_physics::Stage;
use myriad_server::{ServerStatus, TickStage};
use myriad_store::Store;

use crate::bots::{interrupted_within, run_line};
use crate::serve::ConfigArgs;

/// Arguments of `myriad demo`.
#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// Number of built-in bots.
    #[arg(long, default_value_t = 100)]
    bots: usize,
    /// What the bots do: random, circle, idle, shuttle.
    #[arg(long, default_value = "random")]
    behaviour: Behaviour,
    /// Stop after this many seconds (default: at Ctrl-C).
    #[arg(long)]
    duration: Option<f64>,
}

/// The status line's abbreviation of a stage.
fn short_name(stage: TickStage) -> &'static str {
    match stage {
        TickStage::Physics(Stage::Upload) => "up",
        TickStage::Physics(Stage::BuildDynamicBvh) => "bvh",
        TickStage::Physics(Stage::BroadStatic) => "bs",
        TickStage::Physics(Stage::BroadDynamic) => "bd",
        TickStage::Physics(Stage::NarrowStatic) => "ns",
        TickStage::Physics(Stage::NarrowDynamic) => "nd",
        TickStage::Physics(Stage::Forces) => "f",
        TickStage::Packets => "pk",
        TickStage::Send => "tx",
        TickStage::Receive => "rx",
    }
}

fn status_line(s: &ServerStatus, bots: &SwarmSnapshot) -> String {
    let stages: Vec<String> = s.stages.iter().map(|(t, v)| format!("{} {v:.1}", short_name(t))).collect();
    format!(
        "tick {} {:.0}/s {:.1} ms [{}] players {} objects {} out {:.0} kB/s tidi {:.2} | bots {}/{} view {:.0} p99 {:.0} ms",
        s.tick,
        s.ticks_per_s,
        s.tick_ms,
        stages.join(" "),
        s.players,
        s.objects,
        s.bytes_per_s / 1000.0,
        f64::from(s.dilation_permille) / 1000.0,
        bots.connected,
        bots.bots,
        bots.mean_in_view,
        bots.interval_p99_ms,
    )
}

/// Runs `myriad demo`.
pub fn run(args: DemoArgs) -> Result<()> {
    let mut config = args.config.effective()?;
    // A self-contained demo: loopback and free ports unless told otherwise.
    if args.config.login.is_none() {
        config.login_addr = "127.0.0.1:0".parse()?;
    }
    if args.config.udp.is_none() {
        config.udp_addr = "127.0.0.1:0".parse()?;
    }
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    std::fs::create_dir_all(&config.data_dir)?;
    eprintln!("demo: creating {} bot accounts (Argon2id, once)", args.bots);
    rt.block_on(async {
        let store = Store::open(&myriad_server::store_config(&config)).await?;
        store.seed_users(args.bots as u32).await?;
        store.close().await;
        Ok::<(), myriad_store::StoreError>(())
    })
    .context("seeding the bot accounts")?;
    let server = crate::serve::start(config)?;
    eprintln!(
        "demo: server up (login {}, udp {}); {} bots joining; Ctrl-C to stop",
        server.login_addr(),
        server.udp_addr(),
        args.bots
    );
    let trust = Trust::pin_file(server.certificate_path())?;
    let client = ClientConfig::new(server.login_addr(), &trust)?;
    let tty = std::io::stderr().is_terminal();
    let limit = args.duration.map(Duration::from_secs_f64);
    let final_bots = rt.block_on(async {
        let swarm = Swarm::start(SwarmConfig { behaviour: args.behaviour, ..SwarmConfig::new(client, args.bots) });
        let started = Instant::now();
        loop {
            let wait = limit
                .map_or(Duration::from_secs(1), |l| Duration::from_secs(1).min(l.saturating_sub(started.elapsed())));
            let stop = interrupted_within(wait).await;
            let line = status_line(&server.status(), &swarm.snapshot());
            let mut err = std::io::stderr().lock();
            if tty {
                let _ = write!(err, "\r\x1b[2K{line}");
            } else {
                let _ = writeln!(err, "{line}");
            }
            let _ = err.flush();
            if stop || limit.is_some_and(|l| started.elapsed() >= l) {
                break;
            }
        }
        if tty {
            eprintln!();
        }
        swarm.stop().await
    });
    println!("bots: {}", run_line(&final_bots));
    println!("server: {}", server.status().stage_line());
    server.shutdown()?;
    Ok(())
}
