//! What the cluster tests share: children killed with the test, their standard error on
//! a thread, free ports, one process's hash to compare with, a replay checked equal, and
//! gateways with their metrics and admin API.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

/// A child process killed (and reaped) when the test ends, however it ends.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Collects a child's standard error on a thread (a pipe nobody reads stops the child
/// once it is full); the lines arrive on the receiver.
pub fn collect_stderr(child: &mut Child) -> std::sync::mpsc::Receiver<String> {
    let stderr = BufReader::new(child.stderr.take().expect("stderr piped"));
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    rx
}

/// The first of `n` consecutive ports that are free on loopback for TCP and UDP alike.
///
/// They are taken below the kernel's ephemeral range (32768 and up on Linux): a port the
/// kernel hands out for `127.0.0.1:0` can be handed to another socket (a bot's, in the
/// test running beside this one) before the server binds it, and a gateway that cannot
/// bind its UDP port never listens (the cluster restarts it in a loop).
pub fn free_ports(n: u16) -> u16 {
    use std::sync::atomic::{AtomicU16, Ordering};
    static NEXT: AtomicU16 = AtomicU16::new(0);
    let spread = (std::process::id() % 400) as u16 * 30;
    loop {
        let base = 20_000 + (spread + NEXT.fetch_add(n, Ordering::Relaxed)) % 12_000;
        if free_ports_at(base, n) {
            return base;
        }
    }
}

/// Whether ports `base .. base + n` are free on loopback for TCP and UDP.
pub fn free_ports_at(base: u16, n: u16) -> bool {
    (base..base + n).all(|p| {
        std::net::TcpListener::bind(("127.0.0.1", p)).is_ok() && std::net::UdpSocket::bind(("127.0.0.1", p)).is_ok()
    })
}

/// `myriad sim`'s state hash of scenario 1 on `cpu` after `ticks` ticks.
pub fn sim_hash(ticks: u64) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["sim", "--json", "--backend", "cpu", "--scenario", "1", "--ticks", &ticks.to_string()])
        .output()
        .unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    v["state_hash"].as_str().unwrap().to_string()
}

/// Runs `myriad replay --json --nats url --cluster name` with `args` and the cluster key
/// `key`, checks that it succeeded and ended equal to the live run, and returns its
/// summary.
pub fn replay_equal(url: &str, name: &str, key: &str, args: &[&str]) -> serde_json::Value {
    let replay = std::process::Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["replay", "--json", "--nats", url, "--cluster", name])
        .args(args)
        .env("MYRIAD_CLUSTER_KEY", key)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&replay.stdout);
    assert!(replay.status.success(), "{text}\n{}", String::from_utf8_lossy(&replay.stderr));
    let r: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    eprintln!("replay: {r}");
    assert_eq!(r["equal"], true, "{r}");
    r
}

/// The sum of a metric's samples (all label sets) on a Prometheus endpoint.
pub fn metric(port: u16, name: &str) -> f64 {
    sample(&scrape(port), name).unwrap_or(0.0)
}

/// A Prometheus endpoint's page (empty when it does not answer).
fn scrape(port: u16) -> String {
    (|| -> std::io::Result<String> {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
        s.write_all(b"GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n")?;
        let mut body = String::new();
        s.read_to_string(&mut body)?;
        Ok(body)
    })()
    .unwrap_or_default()
}

/// The sum of a metric's samples on a page, `None` when it has none.
fn sample(page: &str, name: &str) -> Option<f64> {
    page.lines()
        .filter(|l| l.starts_with(name) && l[name.len()..].starts_with([' ', '{']))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .reduce(|a, b| a + b)
}

/// The tick every zone's gauges describe (`myriad_zone_tick`) and the sum of the zones'
/// gauge `name` at it, the zones' metrics on `base .. base + zones`; `None` when the
/// zones are at different ticks. Zones step apart: summed across one zone's step, a
/// count misses or doubles what that step handed over. Each page is read twice and must
/// say the same: one scraped while its zone exported may pair the values of one tick
/// with the next's or the one before.
pub fn zones_at_one_tick(base: u16, zones: u16, name: &str) -> Option<(u64, f64)> {
    let read = |z: u16| {
        let page = scrape(base + z);
        Some((sample(&page, "myriad_zone_tick")?, sample(&page, name)?))
    };
    let first: Vec<_> = (0..zones).map(read).collect::<Option<_>>()?;
    let again: Vec<_> = (0..zones).map(read).collect::<Option<_>>()?;
    let tick = first[0].0;
    (first == again && first.iter().all(|(t, _)| *t == tick)).then(|| (tick as u64, first.iter().map(|(_, v)| v).sum()))
}

/// `GET path` on a gateway's admin API with its token (from its data directory).
pub fn admin_get(g: &Gateway, path: &str) -> serde_json::Value {
    use std::io::{Read, Write};
    let token = std::fs::read_to_string(g.data.path().join("admin.token")).unwrap();
    let mut s = std::net::TcpStream::connect(("127.0.0.1", g.admin)).unwrap();
    let request = format!("GET {path} HTTP/1.0\r\nHost: x\r\nAuthorization: Bearer {}\r\n\r\n", token.trim());
    s.write_all(request.as_bytes()).unwrap();
    let mut answer = String::new();
    s.read_to_string(&mut answer).unwrap();
    let body = answer.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    serde_json::from_str(body).unwrap_or_else(|e| panic!("{path}: {e}: {answer}"))
}

/// The cluster key of the cluster tests.
pub const KEY: &str = "a-test-key-of-more-than-sixteen-bytes";

/// A `myriad gateway` of the tests' clusters (two zones, scenario 1, seed 1), with its
/// metrics and admin API, killed with the test.
pub struct Gateway {
    pub process: Killed,
    pub data: tempfile::TempDir,
    pub login: u16,
    pub metrics: u16,
    pub admin: u16,
}

/// Starts `myriad cluster --live` named `name` on `url`: two zones of scenario 1 (seed
/// 1, cpu) at 30 Hz for `ticks` ticks, with `extra` arguments; killed with the test, its
/// standard error on the receiver.
pub fn live_cluster(url: &str, name: &str, ticks: u64, extra: &[&str]) -> (Killed, std::sync::mpsc::Receiver<String>) {
    let mut cluster = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["cluster", "--nats", url, "--cluster", name, "--zones", "2", "--live"])
        .args(["--scenario", "1", "--seed", "1", "--backend", "cpu", "--tick-hz", "30", "--ticks", &ticks.to_string()])
        .args(extra)
        .env("MYRIAD_CLUSTER_KEY", KEY)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = collect_stderr(&mut cluster);
    (Killed(cluster), log)
}

/// Starts gateway `index` of `cluster` (24 accounts seeded in its data directory).
pub fn gateway(url: &str, cluster: &str, index: u16) -> Gateway {
    let bin = env!("CARGO_BIN_EXE_myriad");
    let data = tempfile::tempdir().unwrap();
    let d = data.path().to_str().unwrap();
    // Gateway g's bots are user(12g) .. user(12g + 11): one account, one session in the
    // cluster (a login at another gateway would replace it).
    let seeded = Command::new(bin).args(["user", "seed", "--count", "24", "--data-dir", d]).output().unwrap();
    assert!(seeded.status.success(), "{}", String::from_utf8_lossy(&seeded.stderr));
    let (udp, login, metrics, admin) = (free_ports(1), free_ports(1), free_ports(1), free_ports(1));
    let process = Command::new(bin)
        .args(["gateway", "--nats", url, "--cluster", cluster, "--zones", "2", "--gateway", &index.to_string()])
        .args(["--scenario", "1", "--seed", "1", "--backend", "cpu", "--data-dir", d])
        .args(["--udp", &format!("127.0.0.1:{udp}"), "--login", &format!("127.0.0.1:{login}")])
        .args(["--metrics", &format!("127.0.0.1:{metrics}"), "--admin", &format!("127.0.0.1:{admin}")])
        .env("MYRIAD_CLUSTER_KEY", KEY)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    Gateway { process: Killed(process), data, login, metrics, admin }
}
