//! `myriad relay`: a lossy UDP relay between bots (or a viewer) and a server on this
//! machine, to try the protocol as players on real networks would use it (this kernel
//! has no `netem`). The relay is `myriad_client::relay`, which the tests use too.
//!
//! A login answer names the server's UDP port, and the client sends to the login host's
//! address on that port; so the server's UDP goes on another loopback address and the
//! relay takes its place on the login host's:
//!
//! ```text
//! myriad serve --login 127.0.0.1:7778 --udp 127.0.0.2:7777
//! myriad relay --listen 127.0.0.1:7777 --server 127.0.0.2:7777 --loss 0.1 --delay-ms 50 --jitter-ms 20
//! myriad bots --server 127.0.0.1:7778 --count 50 --duration 20
//! ```

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result};
use myriad_client::relay::{DirectionStats, Link, MAX_DURATION, Relay, RelayConfig, RelayStats};

/// Arguments of `myriad relay`.
#[derive(clap::Args, Debug)]
pub struct RelayArgs {
    /// Where clients send (loopback only): the login host's address and the server's
    /// announced UDP port.
    #[arg(long)]
    listen: SocketAddr,
    /// The server's UDP address (loopback only).
    #[arg(long)]
    server: SocketAddr,
    /// Share of datagrams dropped, each way (0 to 1).
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// Delay of every datagram, ms.
    #[arg(long, default_value_t = 0)]
    delay_ms: u64,
    /// The delay varies uniformly by up to this much either way, ms.
    #[arg(long, default_value_t = 0)]
    jitter_ms: u64,
    /// Share of datagrams delivered twice (0 to 1).
    #[arg(long, default_value_t = 0.0)]
    duplicate: f64,
    /// Share of datagrams held back so that later ones overtake them (0 to 1).
    #[arg(long, default_value_t = 0.0)]
    reorder: f64,
    /// Seed of the decisions (the same seed and traffic give the same fates).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Stop after this many seconds (at most an hour).
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
    /// Stop after this many datagrams, both ways together.
    #[arg(long, default_value_t = 10_000_000)]
    max_datagrams: u64,
}

/// Runs the relay until its duration or datagram bound, or Ctrl-C; prints what it did.
pub fn run(args: RelayArgs) -> Result<()> {
    let duration =
        Duration::try_from_secs_f64(args.duration).ok().filter(|d| *d <= MAX_DURATION).with_context(|| {
            format!("--duration {} is not a number of seconds up to {}", args.duration, MAX_DURATION.as_secs())
        })?;
    let link = Link {
        loss: args.loss,
        delay: Duration::from_millis(args.delay_ms),
        jitter: Duration::from_millis(args.jitter_ms),
        duplicate: args.duplicate,
        reorder: args.reorder,
    };
    let config = RelayConfig {
        seed: args.seed,
        max_datagrams: args.max_datagrams,
        ..RelayConfig::new(args.listen, args.server, link, duration)
    };
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let stats = rt.block_on(async {
        let relay = Relay::start(config).await?;
        eprintln!("relaying {} -> {} for {duration:?} ({link:?}, seed {})", relay.local_addr(), args.server, args.seed);
        let mut every = tokio::time::interval(Duration::from_millis(200));
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        for n in 1u64.. {
            tokio::select! {
                _ = &mut ctrl_c => break,
                _ = every.tick() => {
                    if relay.is_finished() {
                        break;
                    }
                    if n % 25 == 0 {
                        eprintln!("{}", line(&relay.stats()));
                    }
                }
            }
        }
        anyhow::Ok(relay.stop().await)
    })?;
    println!("{}", line(&stats));
    Ok(())
}

/// One line of figures.
fn line(s: &RelayStats) -> String {
    let d = |name: &str, d: &DirectionStats| {
        format!(
            "{name}: received {} lost {} duplicated {} reordered {} sent {}",
            d.received, d.lost, d.duplicated, d.reordered, d.sent
        )
    };
    format!("peers {} | {} | {}", s.peers, d("to server", &s.upstream), d("to clients", &s.downstream))
}
