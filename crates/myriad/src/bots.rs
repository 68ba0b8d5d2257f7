//! `myriad bots`: a swarm of bots playing `user<i>` / `password<i>` against a server.

use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use myriad_client::{
    Behaviour, ClientConfig, ClientStats, Percentiles, Swarm, SwarmConfig, SwarmSnapshot, Trust, movement_ok_share,
};

/// Arguments of `myriad bots`.
#[derive(clap::Args, Debug)]
pub struct BotsArgs {
    /// Login service: HOST or HOST:PORT (port 7778 when omitted).
    #[arg(long, default_value = "127.0.0.1")]
    server: String,
    /// Number of bots.
    #[arg(long, default_value_t = 100)]
    count: usize,
    /// Account index of the first bot (`user<first>`).
    #[arg(long, default_value_t = 0)]
    first: usize,
    /// Actions per second per bot.
    #[arg(long, default_value_t = 30.0)]
    rate: f32,
    /// Stop after this many seconds (default: at Ctrl-C).
    #[arg(long)]
    duration: Option<f64>,
    /// random, circle, idle or shuttle (back and forth along x, across zone boundaries).
    #[arg(long, default_value = "random")]
    behaviour: Behaviour,
    /// Print JSON lines instead of text.
    #[arg(long)]
    json: bool,
    /// Pin this certificate (default: data/tls-cert.pem, the server's development one).
    #[arg(long, conflicts_with = "ca")]
    cert: Option<PathBuf>,
    /// Trust CA certificates from this PEM file instead of pinning.
    #[arg(long)]
    ca: Option<PathBuf>,
    /// Logins in flight at once.
    #[arg(long, default_value_t = 32)]
    login_concurrency: usize,
    /// Seconds between statistics lines.
    #[arg(long, default_value_t = 2.0)]
    every: f64,
    /// Bots that share one UDP socket and one task (the server tells their sessions
    /// apart by id). 1, the default, gives every bot a socket of its own, as real players
    /// have; larger groups let one machine run many more bots, or leave more of it to a
    /// server beside them.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=1024))]
    bots_per_socket: u16,
    /// The server's AOI edge (its `aoi_size`): each bot measures the staleness of the
    /// objects it holds within this cube around it.
    #[arg(long, default_value_t = 100.0)]
    aoi_size: f32,
}

fn resolve(server: &str) -> Result<(SocketAddr, String)> {
    let with_port = if server.parse::<SocketAddr>().is_ok()
        || server.rsplit_once(':').is_some_and(|(h, p)| !h.contains(':') && p.parse::<u16>().is_ok())
    {
        server.to_string()
    } else {
        format!("{server}:7778")
    };
    let addr = with_port
        .to_socket_addrs()
        .with_context(|| format!("resolving {with_port}"))?
        .next()
        .with_context(|| format!("{with_port} has no address"))?;
    let host = with_port.rsplit_once(':').map(|(h, _)| h.trim_matches(['[', ']']).to_string()).unwrap_or_default();
    Ok((addr, host))
}

/// The staleness of what the bots hold (since the swarm started), near and over the AOI.
fn staleness(s: &SwarmSnapshot) -> String {
    let (n, a) = (&s.staleness_near_ms, &s.staleness_all_ms);
    format!(
        "staleness ≤{:.0} p50/p99/max {:.0}/{:.0}/{:.0} ms, AOI {:.0}/{:.0}/{:.0} ms",
        myriad_client::quality::NEAR,
        n.p50,
        n.p99,
        n.max,
        a.p50,
        a.p99,
        a.max
    )
}

/// Percentiles as a JSON object.
fn percentiles_json(p: &Percentiles) -> serde_json::Value {
    serde_json::json!({"samples": p.samples, "p50": p.p50, "p99": p.p99, "max": p.max})
}

/// One statistics line between two snapshots.
pub fn stats_line(prev: &SwarmSnapshot, now: &SwarmSnapshot) -> String {
    let secs = (now.elapsed_s - prev.elapsed_s).max(1e-9);
    // After the swarm stopped nobody is connected: average over every bot then.
    let bots = if now.connected > 0 { now.connected } else { now.bots.max(1) } as f64;
    let r = now.totals.rates_since(&prev.totals, secs);
    format!(
        "t={:.0}s bots {}/{} (failed {}) | per bot {:.1} upd/s {:.1} kB/s | in view {:.0} | interval p50 {:.1} ms p99 {:.1} ms | {} | loss {:.2}% | own seen {} moves ok {:.0}% | rejected {} decode errors {} unresolved {} reconnects {} kicked {} banned {}",
        now.elapsed_s,
        now.connected,
        now.bots,
        now.logins_failed,
        r.updates_per_s / bots,
        r.bytes_per_s / bots / 1000.0,
        now.mean_in_view,
        now.interval_p50_ms,
        now.interval_p99_ms,
        staleness(now),
        now.loss * 100.0,
        now.own_object_seen,
        movement_ok_share(now) * 100.0,
        now.totals.rejected,
        now.totals.decode_errors,
        now.totals.unresolved,
        now.totals.reconnects,
        now.kicked,
        now.banned,
    )
}

/// The whole run, from the swarm's final snapshot. Taken after the swarm stopped, when
/// no bot is connected and none holds a view any more, it reports what the run did:
/// totals, rates over the run per bot, objects per update received, the run's interval
/// percentiles and loss.
pub fn run_line(last: &SwarmSnapshot) -> String {
    let t = &last.totals;
    let r = t.rates_since(&ClientStats::default(), last.elapsed_s);
    let bots = last.bots.max(1) as f64;
    let per_update = if t.updates > 0 { t.records as f64 / t.updates as f64 } else { 0.0 };
    format!(
        "{} bots for {:.0} s: logins {} ok, {} failed, {} reconnects | per bot {:.1} upd/s {:.1} kB/s | in view {:.0} per update | interval p50 {:.1} ms p99 {:.1} ms | {} | loss {:.2}% | own seen {}/{} moves ok {:.0}% | rejected {} decode errors {} unresolved {}",
        last.bots,
        last.elapsed_s,
        last.logins_ok,
        last.logins_failed,
        t.reconnects,
        r.updates_per_s / bots,
        r.bytes_per_s / bots / 1000.0,
        per_update,
        last.interval_p50_ms,
        last.interval_p99_ms,
        staleness(last),
        last.loss * 100.0,
        last.own_object_seen,
        last.bots,
        movement_ok_share(last) * 100.0,
        t.rejected,
        t.decode_errors,
        t.unresolved,
    )
}

/// The same as JSON.
pub fn stats_json(prev: &SwarmSnapshot, now: &SwarmSnapshot) -> serde_json::Value {
    let secs = (now.elapsed_s - prev.elapsed_s).max(1e-9);
    // After the swarm stopped nobody is connected: average over every bot then.
    let bots = if now.connected > 0 { now.connected } else { now.bots.max(1) } as f64;
    let r = now.totals.rates_since(&prev.totals, secs);
    serde_json::json!({
        "t_s": now.elapsed_s,
        "bots": now.bots,
        "connected": now.connected,
        "logins_ok": now.logins_ok,
        "logins_failed": now.logins_failed,
        "updates_per_s_per_bot": r.updates_per_s / bots,
        "bytes_per_s_per_bot": r.bytes_per_s / bots,
        "objects_in_view": now.mean_in_view,
        "interval_p50_ms": now.interval_p50_ms,
        "interval_p99_ms": now.interval_p99_ms,
        "interval_max_ms": now.interval_max_ms,
        "ticks_missed": now.ticks_missed,
        "staleness_near_ms": percentiles_json(&now.staleness_near_ms),
        "staleness_all_ms": percentiles_json(&now.staleness_all_ms),
        "loss": now.loss,
        "own_object_seen": now.own_object_seen,
        "moves_ok": now.moves_ok,
        "moves_wrong": now.moves_wrong,
        "rejected": now.totals.rejected,
        "decode_errors": now.totals.decode_errors,
        "unresolved": now.totals.unresolved,
        "reconnects": now.totals.reconnects,
        "kicked": now.kicked,
        "banned": now.banned,
        "first_error": now.first_error,
    })
}

/// Waits for Ctrl-C or `d`; true on Ctrl-C.
pub async fn interrupted_within(d: Duration) -> bool {
    tokio::select! {
        _ = tokio::signal::ctrl_c() => true,
        _ = tokio::time::sleep(d) => false,
    }
}

/// Runs `myriad bots`.
pub fn run(args: BotsArgs) -> Result<()> {
    if args.count == 0 {
        bail!("--count must be at least 1");
    }
    let (addr, host) = resolve(&args.server)?;
    let trust = match (&args.ca, &args.cert) {
        (Some(ca), _) => Trust::ca_file(ca)?,
        (None, Some(cert)) => Trust::pin_file(cert)?,
        (None, None) => Trust::pin_file(std::path::Path::new("data/tls-cert.pem"))
            .context("no --cert or --ca given and data/tls-cert.pem is unreadable")?,
    };
    let mut client = ClientConfig::new(addr, &trust)?;
    client.server_name = host;
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let json = args.json;
    rt.block_on(async move {
        let swarm = Swarm::start(SwarmConfig {
            first: args.first,
            rate_hz: args.rate,
            behaviour: args.behaviour,
            login_concurrency: args.login_concurrency,
            bots_per_socket: usize::from(args.bots_per_socket),
            aoi_size: args.aoi_size,
            ..SwarmConfig::new(client, args.count)
        });
        let started = Instant::now();
        let limit = args.duration.map(Duration::from_secs_f64);
        let expired = || limit.is_some_and(|l| started.elapsed() >= l);
        let bar = if json {
            indicatif::ProgressBar::hidden()
        } else {
            indicatif::ProgressBar::new(args.count as u64)
        };
        bar.set_style(
            indicatif::ProgressStyle::with_template("logging in {bar:40} {pos}/{len} {per_sec} {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let mut stopped = false;
        loop {
            let s = swarm.snapshot();
            let done = s.logins_ok.min(s.bots as u64) + s.logins_failed;
            bar.set_position(done);
            bar.set_message(format!("{} failed", s.logins_failed));
            if done >= args.count as u64 || expired() {
                break;
            }
            if interrupted_within(Duration::from_millis(100)).await {
                stopped = true;
                break;
            }
        }
        bar.finish();
        let logged_in = started.elapsed().as_secs_f64();
        let s = swarm.snapshot();
        if json {
            println!("{}", serde_json::json!({"event": "logged_in", "ok": s.logins_ok, "failed": s.logins_failed, "seconds": logged_in, "logins_per_s": s.logins_ok as f64 / logged_in.max(1e-9)}));
        } else {
            println!("logins: {} ok, {} failed in {logged_in:.1} s ({:.0}/s)", s.logins_ok, s.logins_failed, s.logins_ok as f64 / logged_in.max(1e-9));
            if let Some(e) = &s.first_error {
                println!("first failure: {e}");
            }
        }
        let mut prev = swarm.snapshot();
        while !stopped && !expired() {
            let wait = Duration::from_secs_f64(args.every.max(0.1));
            let wait = limit.map_or(wait, |l| wait.min(l.saturating_sub(started.elapsed())));
            stopped = interrupted_within(wait).await;
            let now = swarm.snapshot();
            if json {
                println!("{}", stats_json(&prev, &now));
            } else {
                println!("{}", stats_line(&prev, &now));
            }
            prev = now;
        }
        let last = swarm.stop().await;
        if json {
            let mut v = stats_json(&SwarmSnapshot::default(), &last);
            v["event"] = "final".into();
            println!("{v}");
        } else {
            println!("final: {}", run_line(&last));
        }
        Ok::<(), anyhow::Error>(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// After the swarm stopped nobody is connected and nobody holds a view: the final
    /// line reports the run's figures, not the snapshot's zeros.
    #[test]
    fn the_final_line_reports_the_run_not_the_stopped_swarm() {
        let last = SwarmSnapshot {
            elapsed_s: 10.0,
            bots: 4,
            logins_ok: 4,
            connected: 0,
            mean_in_view: 0.0,
            own_object_seen: 4,
            totals: ClientStats { updates: 1200, records: 48_000, bytes: 4_000_000, ..ClientStats::default() },
            ..SwarmSnapshot::default()
        };
        let line = run_line(&last);
        assert!(line.starts_with("4 bots for 10 s: logins 4 ok"), "{line}");
        assert!(line.contains("per bot 30.0 upd/s 100.0 kB/s"), "{line}");
        assert!(line.contains("in view 40 per update"), "{line}");
        assert!(line.contains("own seen 4/4"), "{line}");
        assert!(line.contains("staleness ≤30 p50/p99/max 0/0/0 ms"), "{line}");
    }
}
