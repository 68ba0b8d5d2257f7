//! `myriad flood`: attack a server on this machine the way issue 14's table did, bounded
//! in rate, count and time, and measure what it costs the server (through its metrics
//! endpoint) and whether legitimate logins still get in.
//!
//! Loopback only: a target or source that is not a loopback address is refused before
//! anything is sent. The attacks themselves are `myriad_client::flood` (the same code
//! the server's abuse tests run).

use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr, TcpStream, ToSocketAddrs};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use myriad_client::flood::{self, Bounds, StormAccounts, UdpKind};
use myriad_client::{ClientConfig, ClientError, Credentials, Trust};
use serde::Serialize;

/// The attacks of issue 14.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// Datagrams naming a live session (logs in as --user to learn its session id), with
    /// fresh sequence numbers and random tags, from one socket.
    Session,
    /// Random datagrams of 34 to 1200 bytes, from one socket.
    Garbage,
    /// 1,400-byte datagrams, from one socket.
    Oversized,
    /// One correctly sealed datagram with sequence u64::MAX (as --user), then checks that
    /// the session still answers.
    MaxSeq,
    /// Wrong-password logins for --user from --sources addresses, --concurrency at once.
    Logins,
    /// Logins for unknown users from --sources addresses, --concurrency at once.
    UnknownLogins,
    /// --count idle TCP connections to the login port from --source, held for
    /// --duration.
    Connections,
    /// Wrong passwords for --user from --source, --count times (then the probe shows
    /// whether the owner can still log in from elsewhere).
    Lockout,
    /// Not an attack: a control. One thread spins on a core for --duration and sends
    /// nothing, so the figures show what a flooder's own CPU use costs a server that
    /// shares the machine's cores with it, apart from what its datagrams cost.
    Busy,
}

/// Arguments of `myriad flood`.
#[derive(clap::Args, Debug)]
pub struct FloodArgs {
    /// Which attack.
    #[arg(long, value_enum)]
    mode: Mode,
    /// Login service: HOST:PORT (loopback only).
    #[arg(long, default_value = "127.0.0.1:7778")]
    server: String,
    /// Game port (UDP) for garbage and oversized: HOST:PORT (loopback only).
    #[arg(long, default_value = "127.0.0.1:7777")]
    udp: String,
    /// Seconds the attack lasts (at most 300).
    #[arg(long, default_value_t = 10.0)]
    duration: f64,
    /// Datagrams or logins per second at most (0: as fast as one socket or the tasks go).
    #[arg(long, default_value_t = 0.0)]
    rate: f64,
    /// Datagrams, logins or connections at most (0: no count limit; connections: 4097
    /// when 0).
    #[arg(long, default_value_t = 0)]
    count: u64,
    /// Account of the attacker (session, max-seq) or the account attacked (logins,
    /// lockout).
    #[arg(long, default_value = "user0")]
    user: String,
    /// Password of --user for session and max-seq.
    #[arg(long, default_value = "password0")]
    password: String,
    /// Logins in flight at once (logins, unknown-logins).
    #[arg(long, default_value_t = 64)]
    concurrency: usize,
    /// Source addresses used by the login storms: 127.0.0.10 and the next N-1.
    #[arg(long, default_value_t = 200)]
    sources: u32,
    /// Source address of the single-source attacks (loopback).
    #[arg(long, default_value = "127.0.0.1")]
    source: IpAddr,
    /// A legitimate login tried during the attack (user name; none: no probe).
    #[arg(long)]
    probe_user: Option<String>,
    /// Its password.
    #[arg(long, default_value = "")]
    probe_password: String,
    /// Its source address (loopback, not one of the attack's).
    #[arg(long, default_value = "127.0.0.2")]
    probe_source: IpAddr,
    /// Seconds between probes.
    #[arg(long, default_value_t = 1.0)]
    probe_every: f64,
    /// The server's metrics endpoint (HOST:PORT): ticks/s and tick times before and
    /// during the attack.
    #[arg(long)]
    metrics: Option<SocketAddr>,
    /// Seconds of the baseline measured before the attack (with --metrics).
    #[arg(long, default_value_t = 3.0)]
    baseline: f64,
    /// Pin this certificate (default: data/tls-cert.pem, the server's development one).
    #[arg(long)]
    cert: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// Login request version the attack and the probe send (an older one than the
    /// server serves is refused as an outdated client before any credential check).
    #[arg(long, default_value_t = myriad_protocol::login::LOGIN_VERSION)]
    login_version: u8,
}

/// Tick figures over a window, from the server's metrics.
#[derive(Debug, Clone, Copy, Default, Serialize)]
struct TickWindow {
    ticks_per_s: f64,
    mean_tick_ms: f64,
    /// Median tick time, interpolated within the histogram's buckets.
    median_tick_ms: f64,
}

#[derive(Debug, Default, Serialize)]
struct ProbeSummary {
    tries: u32,
    ok: u32,
    refused: std::collections::BTreeMap<String, u32>,
    latency_ms: Vec<f64>,
}

#[derive(Debug, Serialize)]
struct Report {
    mode: Mode,
    seconds: f64,
    attack: serde_json::Value,
    before: Option<TickWindow>,
    during: Option<TickWindow>,
    probe: Option<ProbeSummary>,
}

fn loopback(addr: &str) -> Result<SocketAddr> {
    let a = addr.to_socket_addrs().with_context(|| format!("resolving {addr}"))?.next().context("no address")?;
    flood::check_loopback(a.ip())?;
    Ok(a)
}

/// Runs `myriad flood`.
pub fn run(args: FloodArgs) -> Result<()> {
    if !(args.duration > 0.0 && args.duration <= flood::MAX_DURATION.as_secs_f64()) {
        bail!("--duration must be more than 0 and at most {} s", flood::MAX_DURATION.as_secs());
    }
    let login_addr = loopback(&args.server)?;
    let udp_addr = loopback(&args.udp)?;
    flood::check_loopback(args.source)?;
    flood::check_loopback(args.probe_source)?;
    if let Some(m) = args.metrics {
        flood::check_loopback(m.ip())?;
    }
    let cert = args.cert.clone().unwrap_or_else(|| PathBuf::from("data/tls-cert.pem"));
    let trust = Trust::pin_file(&cert).with_context(|| format!("reading the certificate {}", cert.display()))?;
    let mut cc = ClientConfig::new(login_addr, &trust)?;
    cc.login_timeout = Duration::from_secs(20);
    cc.login_version = args.login_version;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    rt.block_on(attack(args, cc, udp_addr))
}

async fn attack(args: FloodArgs, cc: ClientConfig, udp_addr: SocketAddr) -> Result<()> {
    let duration = Duration::from_secs_f64(args.duration);
    let bounds = Bounds { count: args.count, rate: args.rate, duration };
    let before = match args.metrics {
        Some(m) => {
            let a = scrape(m).await?;
            tokio::time::sleep(Duration::from_secs_f64(args.baseline)).await;
            Some(window(&a, &scrape(m).await?, args.baseline))
        }
        None => None,
    };
    let start_metrics = match args.metrics {
        Some(m) => Some(scrape(m).await?),
        None => None,
    };
    let started = Instant::now();
    // The probe runs beside the attack, for its duration.
    let probe = args.probe_user.clone().map(|user| {
        let creds = Credentials { username: user, password: args.probe_password.clone() };
        let (cc, from, every) = (cc.clone(), args.probe_source, Duration::from_secs_f64(args.probe_every.max(0.05)));
        tokio::spawn(async move {
            let mut s = ProbeSummary::default();
            // Let the attack build up first.
            tokio::time::sleep(every.min(duration / 4)).await;
            while started.elapsed() + Duration::from_millis(100) < duration {
                let p = flood::probe_login(&cc, &creds, from).await;
                s.tries += 1;
                s.latency_ms.push((p.latency.as_secs_f64() * 1e4).round() / 10.0);
                match p.result {
                    Ok(_) => s.ok += 1,
                    Err(ClientError::Refused { reason, .. }) => *s.refused.entry(reason.to_string()).or_default() += 1,
                    Err(e) => *s.refused.entry(e.to_string()).or_default() += 1,
                }
                tokio::time::sleep(every).await;
            }
            s
        })
    });
    let attack = match args.mode {
        Mode::Session | Mode::Garbage | Mode::Oversized => {
            let (kind, target) = match args.mode {
                Mode::Session => {
                    // A player knows its own session id: log in as one to learn it.
                    let creds = Credentials { username: args.user.clone(), password: args.password.clone() };
                    let (accepted, _) = myriad_client::login(&cc, &creds).await.context("logging in as --user")?;
                    let kind = UdpKind::LiveSession { session_id: accepted.keys.session_id, first_sequence: 1 };
                    (kind, SocketAddr::new(cc.login_addr.ip(), accepted.udp_port))
                }
                Mode::Garbage => (UdpKind::Garbage, udp_addr),
                _ => (UdpKind::Oversized, udp_addr),
            };
            let source = args.source;
            let r = tokio::task::spawn_blocking(move || flood::udp_flood(target, source, kind, bounds)).await??;
            serde_json::json!({
                "sent": r.sent, "send_errors": r.send_errors, "replies": r.replies,
                "per_s": r.rate().round(), "seconds": r.seconds,
            })
        }
        Mode::Busy => {
            let spun = tokio::task::spawn_blocking(move || {
                let start = Instant::now();
                let mut x = 0u64;
                while start.elapsed() < duration {
                    for _ in 0..10_000 {
                        x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
                    }
                }
                start.elapsed().as_secs_f64()
            })
            .await?;
            serde_json::json!({ "spun_s": (spun * 100.0).round() / 100.0 })
        }
        Mode::MaxSeq => {
            let creds = Credentials { username: args.user.clone(), password: args.password.clone() };
            let r = flood::max_sequence(&cc, &creds).await?;
            serde_json::json!({ "answered_forged": r.answered_forged, "session_alive": r.session_alive })
        }
        Mode::Logins | Mode::UnknownLogins => {
            let sources = flood::loopback_sources(10, args.sources.max(1));
            let accounts =
                if args.mode == Mode::Logins { StormAccounts::One(args.user.clone()) } else { StormAccounts::Unknown };
            let r = flood::login_storm(&cc, &sources, accounts, args.concurrency, bounds).await?;
            serde_json::json!({
                "attempts": r.attempts, "per_s": (r.attempts as f64 / r.seconds.max(1e-9)).round(),
                "answers": r.answers, "seconds": r.seconds,
            })
        }
        Mode::Connections => {
            let count = if args.count == 0 { 4097 } else { args.count.min(60_000) } as u32;
            let r = flood::idle_connections(cc.login_addr, args.source, count, duration).await?;
            serde_json::json!({
                "connected": r.connected, "connect_failed": r.connect_failed,
                "closed_at_once": r.closed_at_once, "closed_later": r.closed_later, "open_at_end": r.open_at_end,
            })
        }
        Mode::Lockout => {
            let wrong = Credentials { username: args.user.clone(), password: "not-the-password".into() };
            let mut answers = std::collections::BTreeMap::<String, u32>::new();
            let n = if args.count == 0 { 10 } else { args.count.min(10_000) };
            for _ in 0..n {
                if started.elapsed() >= duration {
                    break;
                }
                let p = flood::probe_login(&cc, &wrong, args.source).await;
                let key = match p.result {
                    Ok(_) => "accepted".to_string(),
                    Err(ClientError::Refused { reason, .. }) => reason.to_string(),
                    Err(e) => e.to_string(),
                };
                *answers.entry(key).or_default() += 1;
            }
            serde_json::json!({ "answers": answers })
        }
    };
    let during = match (args.metrics, &start_metrics) {
        (Some(m), Some(a)) => Some(window(a, &scrape(m).await?, started.elapsed().as_secs_f64())),
        _ => None,
    };
    let probe = match probe {
        Some(p) => Some(p.await?),
        None => None,
    };
    let report = Report { mode: args.mode, seconds: started.elapsed().as_secs_f64(), attack, before, during, probe };
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print_text(&report);
    }
    Ok(())
}

fn print_text(r: &Report) {
    println!("mode {:?}: {:.1} s", r.mode, r.seconds);
    println!("attack: {}", r.attack);
    let line = |name: &str, w: &Option<TickWindow>| {
        if let Some(w) = w {
            println!(
                "{name}: {:.1} ticks/s, tick mean {:.2} ms, median {:.2} ms",
                w.ticks_per_s, w.mean_tick_ms, w.median_tick_ms
            );
        }
    };
    line("before", &r.before);
    line("during", &r.during);
    if let Some(p) = &r.probe {
        let mut l = p.latency_ms.clone();
        l.sort_by(f64::total_cmp);
        let max = l.last().copied().unwrap_or(0.0);
        let median = l.get(l.len() / 2).copied().unwrap_or(0.0);
        println!(
            "probe logins: {} ok of {}, refused {:?}, latency median {median:.1} ms max {max:.1} ms",
            p.ok, p.tries, p.refused
        );
    }
}

/// The counters of the server's `/metrics` that the tick figures come from.
#[derive(Debug, Default, Clone)]
struct Scrape {
    ticks: f64,
    tick_sum: f64,
    tick_count: f64,
    /// (upper bound in seconds, cumulative count), ascending.
    buckets: Vec<(f64, f64)>,
}

async fn scrape(addr: SocketAddr) -> Result<Scrape> {
    tokio::task::spawn_blocking(move || scrape_blocking(addr)).await?
}

fn scrape_blocking(addr: SocketAddr) -> Result<Scrape> {
    let mut s =
        TcpStream::connect_timeout(&addr, Duration::from_secs(2)).with_context(|| format!("metrics at {addr}"))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(s, "GET /metrics HTTP/1.0\r\nHost: {addr}\r\n\r\n")?;
    let mut text = String::new();
    s.read_to_string(&mut text)?;
    let mut out = Scrape::default();
    for line in text.lines() {
        let Some((name, value)) = line.rsplit_once(' ') else { continue };
        let Ok(v) = value.parse::<f64>() else { continue };
        if name == "myriad_ticks_total" {
            out.ticks = v;
        } else if name == "myriad_tick_duration_seconds_sum" {
            out.tick_sum = v;
        } else if name == "myriad_tick_duration_seconds_count" {
            out.tick_count = v;
        } else if let Some(le) = name.strip_prefix("myriad_tick_duration_seconds_bucket{le=\"") {
            let le = le.trim_end_matches("\"}");
            let bound = if le == "+Inf" { f64::INFINITY } else { le.parse().unwrap_or(f64::INFINITY) };
            out.buckets.push((bound, v));
        }
    }
    out.buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

fn window(a: &Scrape, b: &Scrape, seconds: f64) -> TickWindow {
    let n = b.tick_count - a.tick_count;
    let mean = if n > 0.0 { (b.tick_sum - a.tick_sum) / n * 1000.0 } else { 0.0 };
    // Median: the bucket holding the middle tick, interpolated linearly inside it.
    let mut median = 0.0;
    let mut lower = (0.0, 0.0);
    for (i, &(bound, cum_b)) in b.buckets.iter().enumerate() {
        let cum = cum_b - a.buckets.get(i).map_or(0.0, |x| x.1);
        if cum >= n / 2.0 && n > 0.0 {
            let (lo_bound, lo_cum) = lower;
            let upper = if bound.is_finite() { bound } else { lo_bound * 2.0 };
            let frac = if cum > lo_cum { (n / 2.0 - lo_cum) / (cum - lo_cum) } else { 0.0 };
            median = (lo_bound + (upper - lo_bound) * frac) * 1000.0;
            break;
        }
        lower = (bound, cum);
    }
    TickWindow { ticks_per_s: (b.ticks - a.ticks) / seconds.max(1e-9), mean_tick_ms: mean, median_tick_ms: median }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_is_interpolated_in_its_bucket() {
        let a = Scrape::default();
        let b = Scrape {
            ticks: 100.0,
            tick_sum: 1.0,
            tick_count: 100.0,
            buckets: vec![(0.005, 10.0), (0.01, 90.0), (0.02, 100.0), (f64::INFINITY, 100.0)],
        };
        let w = window(&a, &b, 10.0);
        assert_eq!(w.ticks_per_s, 10.0);
        assert!((w.mean_tick_ms - 10.0).abs() < 1e-9);
        assert!((w.median_tick_ms - 7.5).abs() < 1e-9, "{}", w.median_tick_ms);
    }

    #[test]
    fn non_loopback_targets_are_refused() {
        assert!(loopback("127.0.0.1:7778").is_ok());
        assert!(loopback("10.1.2.3:7778").is_err());
    }
}
