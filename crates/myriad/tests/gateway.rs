//! Players through a gateway on a world run by zone processes: `myriad cluster --live`
//! (two zones), `myriad gateway`, and `myriad bots` walking for 25 s, with zone 1 killed
//! (`kill -9`) in the middle. Every bot logs in at the gateway once, never reconnects
//! (the cluster rolls back, the sessions stay), sees its own object in its updates, and
//! no object is ever claimed by two zones; the zones adopt the players' objects and take
//! them out when the bots leave.
//! Needs `NATS_URL` (CI sets it); skips with a message without it.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn metric(port: u16, name: &str) -> f64 {
    let body = (|| -> std::io::Result<String> {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
        s.write_all(b"GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n")?;
        let mut body = String::new();
        s.read_to_string(&mut body)?;
        Ok(body)
    })()
    .unwrap_or_default();
    body.lines()
        .filter(|l| l.starts_with(name) && l[name.len()..].starts_with([' ', '{']))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

struct Killed(Child);
impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn bots_play_through_a_gateway_across_zones_and_a_rollback() {
    let Ok(url) = std::env::var("NATS_URL") else {
        eprintln!("skipped: NATS_URL is not set (CI sets it; e.g. NATS_URL=nats://127.0.0.1:4222)");
        return;
    };
    let bin = env!("CARGO_BIN_EXE_myriad");
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap();
    let cluster_name = format!("gw{}", std::process::id());
    let key = "a-test-key-of-more-than-sixteen-bytes";
    let (zone_metrics, gw_metrics, udp, login) = (free_port(), free_port(), free_port(), free_port());
    // The zone metrics are on zone_metrics + zone index.
    let mut cluster = Command::new(bin)
        .args(["cluster", "--nats", &url, "--cluster", &cluster_name, "--zones", "2", "--live"])
        .args(["--scenario", "1", "--seed", "1", "--backend", "cpu", "--tick-hz", "30", "--ticks", "3000"])
        .args(["--checkpoint-every", "30", "--dead-ms", "1000", "--metrics-base-port", &zone_metrics.to_string()])
        .env("MYRIAD_CLUSTER_KEY", key)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = BufReader::new(cluster.stderr.take().unwrap());
    let cluster = Killed(cluster);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let seeded = Command::new(bin).args(["user", "seed", "--count", "20", "--data-dir", data]).output().unwrap();
    assert!(seeded.status.success(), "{}", String::from_utf8_lossy(&seeded.stderr));
    let gateway = Command::new(bin)
        .args(["gateway", "--nats", &url, "--cluster", &cluster_name, "--zones", "2"])
        .args(["--scenario", "1", "--seed", "1", "--backend", "cpu", "--data-dir", data])
        .args(["--udp", &format!("127.0.0.1:{udp}"), "--login", &format!("127.0.0.1:{login}")])
        .args(["--metrics", &format!("127.0.0.1:{gw_metrics}")])
        .env("MYRIAD_CLUSTER_KEY", key)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let _gateway = Killed(gateway);
    // The gateway is up once it has taken worlds from the zones.
    let start = Instant::now();
    while metric(gw_metrics, "myriad_gateway_mirrors_total") < 30.0 {
        assert!(start.elapsed() < Duration::from_secs(60), "the gateway never followed the zones");
        std::thread::sleep(Duration::from_millis(200));
    }
    let bots = Command::new(bin)
        .args(["bots", "--server", &format!("127.0.0.1:{login}"), "--count", "20", "--duration", "25", "--json"])
        .args(["--cert", &format!("{data}/tls-cert.pem")])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Kill zone 1 ten seconds into the bots' run.
    let mut victim = None;
    let mut log = Vec::new();
    while victim.is_none() && start.elapsed() < Duration::from_secs(90) {
        if let Ok(line) = rx.recv_timeout(Duration::from_millis(200)) {
            victim = line.strip_prefix("zone 1 pid ").and_then(|p| p.trim().parse::<i32>().ok());
            log.push(line);
        }
    }
    let victim = victim.unwrap_or_else(|| panic!("no zone 1 pid in {log:?}"));
    std::thread::sleep(Duration::from_secs(10));
    let joined = metric(zone_metrics, "myriad_zone_player_joins_total")
        + metric(zone_metrics + 1, "myriad_zone_player_joins_total");
    assert_eq!(unsafe { libc::kill(victim, libc::SIGKILL) }, 0);
    let out = bots.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let last: serde_json::Value =
        serde_json::from_str(text.lines().rev().find(|l| l.contains("\"final\"")).expect("a final line")).unwrap();
    log.extend(rx.try_iter());
    eprintln!("bots: {last}\ncluster: {log:?}");
    assert_eq!(last["logins_ok"], 20, "{last}");
    assert_eq!(last["logins_failed"], 0, "{last}");
    assert_eq!(last["reconnects"], 0, "players stay connected through the rollback: {last}");
    assert_eq!(last["own_object_seen"], 20, "{last}");
    assert_eq!(last["rejected"], 0, "{last}");
    assert_eq!(last["decode_errors"], 0, "{last}");
    assert!(log.iter().any(|l| l.contains("Fault")), "the cluster saw the kill: {log:?}");
    assert_eq!(joined, 20.0, "the zones adopted every player's object once before the kill");
    assert!(metric(gw_metrics, "myriad_gateway_rollbacks_total") >= 1.0, "the gateway followed the rollback");
    assert_eq!(metric(gw_metrics, "myriad_gateway_duplicates_total"), 0.0, "no object in two zones");
    // After the bots left, the zones take their objects out (within a refresh or two).
    let owned = || {
        metric(zone_metrics, "myriad_zone_owned_objects") + metric(zone_metrics + 1, "myriad_zone_owned_objects")
    };
    let deadline = Instant::now() + Duration::from_secs(15);
    while owned() != 6000.0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(300));
    }
    assert_eq!(owned(), 6000.0, "the world is back to its 6,000 objects once every player left");
    drop(cluster);
}
