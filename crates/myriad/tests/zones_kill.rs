//! Kill -9 of a zone process mid-run, and a zone that stalls: `myriad cluster` notices
//! (and restarts a dead one), rolls every zone back to the last checkpoint they all
//! stored, and ends in the state hash of one process; the checkpoint it resumed from has
//! the hash of one process at that tick.
//! Needs `NATS_URL` (CI sets it); skips with a message without it, fails under
//! `MYRIAD_REQUIRE_NATS=1`.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use myriad_testenv::nats_url;

mod common;
use common::sim_hash;

/// Runs a 4-zone cluster on scenario 1 for `ticks` ticks, calls `disrupt` with zone 1's
/// process id once every zone is past tick 70, and checks that the cluster noticed a
/// fault, resumed from a checkpoint with one process's hash at its tick, and ended with
/// one process's hash. Returns the faults it reported.
fn disrupted_run(url: &str, ticks: u64, disrupt: impl FnOnce(i32)) -> Vec<String> {
    let mut cluster = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["cluster", "--json", "--nats", url, "--zones", "4", "--scenario", "1", "--backend", "cpu"])
        .args(["--ticks", &ticks.to_string(), "--tick-hz", "60", "--checkpoint-every", "30", "--dead-ms", "1000"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The cluster names its zones' processes on stderr.
    let stderr = BufReader::new(cluster.stderr.take().unwrap());
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let start = Instant::now();
    let mut victim = None;
    let mut log = Vec::new();
    while victim.is_none() && start.elapsed() < Duration::from_secs(30) {
        if let Ok(line) = rx.recv_timeout(Duration::from_millis(200)) {
            victim = line.strip_prefix("zone 1 pid ").map(|p| p.trim().parse::<i32>().unwrap());
            log.push(line);
        }
    }
    let victim = victim.unwrap_or_else(|| panic!("no zone 1 pid in {log:?}"));
    // Kill it once every zone is past tick 70, so that a checkpoint after the start (30
    // or 60) is behind everyone: the cluster prints its progress as events.
    let past = |l: &str| {
        l.strip_prefix("epoch 1      at tick ").and_then(|r| r.trim().parse::<u64>().ok()).is_some_and(|t| t > 70)
    };
    while !log.iter().any(|l| past(l)) && start.elapsed() < Duration::from_secs(120) {
        if let Ok(line) = rx.recv_timeout(Duration::from_millis(200)) {
            log.push(line);
        }
    }
    assert!(log.iter().any(|l| past(l)), "the cluster never got past tick 70: {log:#?}");
    disrupt(victim);
    let out = cluster.wait_with_output().unwrap();
    log.extend(rx.try_iter());
    assert!(out.status.success(), "cluster failed: {log:#?}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let faults = v["faults"].as_array().unwrap();
    assert!(!faults.is_empty(), "the kill was noticed: {v}");
    let starts = v["starts"].as_array().unwrap();
    assert!(starts.len() >= 2, "a second epoch started: {v}");
    let resumed = &starts[starts.len() - 1];
    let tick = resumed[1].as_u64().unwrap();
    assert!(tick > 0 && tick.is_multiple_of(30), "resumed from a checkpoint: {v}");
    assert_eq!(resumed[2].as_str().unwrap(), sim_hash(tick), "the checkpoint is one process's state at its tick");
    assert_eq!(v["state_hash"].as_str().unwrap(), sim_hash(ticks), "the end is one process's state");
    eprintln!("{faults:?}; resumed from tick {tick}; hashes equal");
    faults.iter().map(|f| f.as_str().unwrap().to_string()).collect()
}

fn signal(pid: i32, sig: i32) {
    // SAFETY: sending a signal to a process id we started; no memory is involved.
    assert_eq!(unsafe { libc::kill(pid, sig) }, 0);
}

#[test]
fn a_killed_zone_rolls_the_cluster_back_to_a_consistent_checkpoint() {
    let Some(url) = nats_url() else { return };
    let faults = disrupted_run(&url, 240, |pid| signal(pid, libc::SIGKILL));
    assert!(faults.iter().any(|f| f == "zone 1 exited"), "{faults:?}");
}

/// A zone that stops answering without exiting (SIGSTOP for 2.5 s, then SIGCONT) is
/// declared silent after `--dead-ms`; the cluster rolls back, and the zone, once it runs
/// again, takes the halt and the new start like the others.
#[test]
fn a_stalled_zone_rolls_the_cluster_back_too() {
    let Some(url) = nats_url() else { return };
    let faults = disrupted_run(&url, 240, |pid| {
        signal(pid, libc::SIGSTOP);
        std::thread::sleep(Duration::from_millis(2500));
        signal(pid, libc::SIGCONT);
    });
    assert!(faults.iter().any(|f| f.starts_with("zone 1 silent")), "{faults:?}");
}

/// Each zone serves its counters on its Prometheus endpoint while the cluster runs.
#[test]
fn zones_serve_their_metrics() {
    let Some(url) = nats_url() else { return };
    let port = {
        // A free pair of ports: bind two, note them, let them go.
        let a = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        a.local_addr().unwrap().port()
    };
    let mut cluster = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["cluster", "--json", "--nats", url.as_str(), "--zones", "2", "--scenario", "1", "--backend", "cpu"])
        .args(["--ticks", "240", "--tick-hz", "60", "--metrics-base-port", &port.to_string()])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    let mut page = String::new();
    while start.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(500));
        let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", port)) else { continue };
        use std::io::{Read, Write};
        s.write_all(b"GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n").unwrap();
        page.clear();
        let _ = s.read_to_string(&mut page);
        if page.contains("myriad_zone_ticks_total{zone=\"0\"}") {
            break;
        }
    }
    // The run ends by itself (and stops its zones).
    assert!(cluster.wait().unwrap().success());
    for name in ["myriad_zone_owned_objects", "myriad_zone_ghosts_in_total", "myriad_zone_wait_seconds_total"] {
        assert!(page.contains(&format!("{name}{{zone=\"0\"}}")), "{name} missing from {page}");
    }
}
