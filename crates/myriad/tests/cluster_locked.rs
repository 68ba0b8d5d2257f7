//! `myriad cluster` on a locked-down NATS server:
//! - its private `nats-server` (`--private-nats`) admits only its roles' users (a
//!   client without credentials is refused) and the run, checkpoints included, ends in
//!   one process's hash;
//! - an operator's `nats-server` run with the configuration `--write-nats-config`
//!   writes: a live cluster with a gateway and bots (zones, gateway and supervisor each
//!   with its own role's credentials) serves its players, the server logs no
//!   permissions violation, and `myriad replay` with the supervisor's credentials file
//!   ends in the live run's hash.
//!
//! Needs the `nats-server` program; skips with a message without it, fails under
//! `MYRIAD_REQUIRE_NATS=1`.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use myriad_testenv::nats_server;
use myriad_zone::fabric_auth::NatsAuth;
use myriad_zone::nats::NatsLink;

mod common;
use common::{Killed, collect_stderr, free_ports, sim_hash};

const KEY: &str = "a-test-key-of-more-than-sixteen-bytes";

#[test]
fn a_private_server_admits_only_the_clusters_roles_and_the_run_equals_one_process() {
    if nats_server().is_none() {
        return;
    }
    let mut cluster = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["cluster", "--json", "--private-nats", "--zones", "2", "--scenario", "1", "--backend", "cpu"])
        .args(["--ticks", "120", "--tick-hz", "30", "--checkpoint-every", "30"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = collect_stderr(&mut cluster);
    let mut cluster = Killed(cluster);
    let addr = loop {
        let line = log.recv_timeout(Duration::from_secs(60)).expect("the cluster names its server");
        if let Some(rest) = line.strip_prefix("started a private nats-server on ") {
            break rest.split_whitespace().next().unwrap().to_string();
        }
    };
    // While it runs: a client without credentials, or with another cluster's, is refused.
    let url = format!("nats://{addr}");
    let e = NatsLink::connect(&url, "outsider".into(), &NatsAuth::default()).err().expect("refused");
    assert!(e.to_string().contains("NATS wants credentials"), "{e}");
    let guess = NatsAuth::user(&format!("myriad-c{}-gateway", cluster.0.id()), "guess");
    assert!(NatsLink::connect(&url, "outsider".into(), &guess).is_err());
    let mut out = String::new();
    std::io::Read::read_to_string(cluster.0.stdout.as_mut().unwrap(), &mut out).unwrap();
    assert!(cluster.0.wait().unwrap().success(), "{out}; {:?}", log.try_iter().collect::<Vec<_>>());
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["state_hash"].as_str().unwrap(), sim_hash(120), "{v}");
    assert!(v["faults"].as_array().unwrap().is_empty(), "{v}");
}

#[test]
fn an_operators_server_with_the_written_configuration_serves_a_live_cluster() {
    let Some(exe) = nats_server() else { return };
    let bin = env!("CARGO_BIN_EXE_myriad");
    let dir = tempfile::tempdir().unwrap();
    let name = format!("op{}", std::process::id());
    let conf_dir = dir.path().join("nats");
    let wrote = Command::new(bin)
        .args(["cluster", "--cluster", &name, "--zones", "2", "--write-nats-config", conf_dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(wrote.status.success(), "{}", String::from_utf8_lossy(&wrote.stderr));
    let files = ["zone-0.creds", "zone-1.creds", "gateway.creds", "supervisor.creds"].map(String::from);
    for file in std::iter::once(format!("myriad-{name}.conf")).chain(files) {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(conf_dir.join(&file)).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600, "{file}");
    }
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let server_log = dir.path().join("nats.log");
    let _server = Killed(
        Command::new(exe)
            .args(["-a", "127.0.0.1", "-p", &port.to_string(), "-js", "-sd"])
            .arg(dir.path().join("js"))
            .arg("-c")
            .arg(conf_dir.join(format!("myriad-{name}.conf")))
            .arg("-l")
            .arg(&server_log)
            .spawn()
            .unwrap(),
    );
    let url = format!("nats://127.0.0.1:{port}");
    let start = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(start.elapsed() < Duration::from_secs(10), "nats-server did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    let data = dir.path().join("gateways");
    let seeded = Command::new(bin)
        .args(["user", "seed", "--count", "4", "--data-dir", data.join("gateway-0").to_str().unwrap()])
        .output()
        .unwrap();
    assert!(seeded.status.success(), "{}", String::from_utf8_lossy(&seeded.stderr));
    let ports = free_ports(2);
    let mut cluster = Command::new(bin)
        .args(["cluster", "--json", "--nats", &url, "--cluster", &name, "--nats-creds-dir"])
        .arg(&conf_dir)
        .args(["--zones", "2", "--live", "--gateways", "1", "--gateway-port", &ports.to_string()])
        .args(["--gateway-data", data.to_str().unwrap(), "--scenario", "1", "--backend", "cpu"])
        .args(["--tick-hz", "30", "--ticks", "1200", "--checkpoint-every", "30"])
        .env("MYRIAD_CLUSTER_KEY", KEY)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = collect_stderr(&mut cluster);
    let mut cluster = Killed(cluster);
    let login = format!("127.0.0.1:{}", ports + 1);
    let start = Instant::now();
    while std::net::TcpStream::connect(&login).is_err() {
        let exited = cluster.0.try_wait().unwrap();
        if exited.is_some() || start.elapsed() > Duration::from_secs(150) {
            panic!("the gateway never listened ({exited:?}): {:#?}", log.try_iter().collect::<Vec<_>>());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let cert = data.join("gateway-0/tls-cert.pem");
    let bots = Command::new(bin)
        .args(["bots", "--server", &login, "--count", "4", "--duration", "6", "--json", "--behaviour", "shuttle"])
        .arg("--cert")
        .arg(&cert)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&bots.stdout);
    let last: serde_json::Value =
        serde_json::from_str(text.lines().rev().find(|l| l.contains("\"final\"")).expect("a final line")).unwrap();
    assert_eq!(last["logins_ok"], 4, "{last}");
    assert_eq!(last["reconnects"], 0, "{last}");
    assert_eq!(last["own_object_seen"], 4, "the zones took the gateway's intents, it their states: {last}");
    assert!(cluster.0.wait().unwrap().success(), "{:#?}", log.try_iter().collect::<Vec<_>>());
    let nats_log = std::fs::read_to_string(&server_log).unwrap();
    assert!(!nats_log.contains("Violation"), "every role stayed inside its permissions: {nats_log}");
    // The replay reads the checkpoints with the supervisor's credentials file.
    let replay = Command::new(bin)
        .args(["replay", "--json", "--nats", &url, "--cluster", &name, "--zones", "2"])
        .args(["--scenario", "1", "--seed", "1", "--backend", "cpu", "--ticks", "1200", "--checkpoint-every", "30"])
        .env("MYRIAD_CLUSTER_KEY", KEY)
        .env("MYRIAD_NATS_CREDS", conf_dir.join("supervisor.creds"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&replay.stdout);
    assert!(replay.status.success(), "{text}\n{}", String::from_utf8_lossy(&replay.stderr));
    let r: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    assert_eq!(r["equal"], true, "{r}");
    let nats_log = std::fs::read_to_string(&server_log).unwrap();
    assert!(!nats_log.contains("Violation"), "the replay stayed inside the supervisor's permissions: {nats_log}");
}
