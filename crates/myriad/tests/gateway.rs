//! Players through gateways on a world run by zone processes: `myriad cluster --live`
//! (two zones) and two `myriad gateway`s, each with 12 bots walking back and forth across
//! the zones' boundary (`--behaviour shuttle`) for a minute. Zone 1 is killed (`kill -9`)
//! after 15 s and gateway 1 after 30 s.
//! - The live run, replayed from the rollback's checkpoint with the intents the zones
//!   logged (`myriad replay`), ends in the hash the live zones stored.
//! - Gateway 0's bots log in once and never reconnect (the cluster rolls back, their
//!   sessions stay), see their own objects, miss no tick's update, and their objects
//!   change zone without their sessions noticing.
//! - No object is ever claimed by two zones; the zones adopt every player's object, and
//!   remove gateway 1's players' objects once it is dead, and gateway 0's when its bots
//!   leave.
//!
//! Needs `NATS_URL` (CI sets it); skips with a message without it, fails under
//! `MYRIAD_REQUIRE_NATS=1`.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{
    Gateway, KEY, Killed, admin_get, collect_stderr, free_ports, free_ports_at, gateway, live_cluster, metric,
    replay_equal, zones_at_one_tick,
};

fn bots(g: &Gateway, first: u32, seconds: u32) -> Child {
    Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["bots", "--server", &format!("127.0.0.1:{}", g.login), "--count", "12", "--json"])
        .args(["--first", &first.to_string()])
        .args(["--duration", &seconds.to_string(), "--behaviour", "shuttle"])
        .args(["--cert", &format!("{}/tls-cert.pem", g.data.path().display())])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

#[test]
fn bots_walk_across_zones_through_gateways_that_outlive_a_rollback() {
    let Some(url) = myriad_testenv::nats_url() else { return };
    let cluster_name = format!("gw{}", std::process::id());
    let zone_metrics = free_ports(2);
    // The zone metrics are on zone_metrics + zone index.
    let metrics_port = zone_metrics.to_string();
    let extra = [
        "--checkpoint-every",
        "30",
        "--dead-ms",
        "1000",
        "--metrics-base-port",
        &metrics_port,
        "--keep-checkpoints",
        "400",
    ];
    let (cluster, rx) = live_cluster(&url, &cluster_name, 6000, &extra);
    let gateways = [gateway(&url, &cluster_name, 0), gateway(&url, &cluster_name, 1)];
    // The gateways are up once they have taken worlds from the zones.
    let start = Instant::now();
    for g in &gateways {
        while metric(g.metrics, "myriad_gateway_mirrors_total") < 30.0 {
            assert!(start.elapsed() < Duration::from_secs(90), "a gateway never followed the zones");
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    let mut log: Vec<String> = rx.try_iter().collect();
    let victim = log
        .iter()
        .find_map(|l| l.strip_prefix("zone 1 pid ").and_then(|p| p.trim().parse::<i32>().ok()))
        .unwrap_or_else(|| panic!("no zone 1 pid in {log:?}"));
    let zones = |name: &str| metric(zone_metrics, name) + metric(zone_metrics + 1, name);
    let staying = bots(&gateways[0], 0, 60);
    let mut leaving = bots(&gateways[1], 12, 40);
    std::thread::sleep(Duration::from_secs(15));
    assert_eq!(zones("myriad_zone_player_joins_total"), 24.0, "the zones adopted every player's object once");
    // The gateway's admin API (the server's code path): its role and its players.
    let state = admin_get(&gateways[0], "/api/state");
    assert_eq!((&state["role"], state["players"].as_u64()), (&serde_json::json!("gateway"), Some(12)), "{state}");
    let players = admin_get(&gateways[0], "/api/players");
    assert_eq!(players.as_array().map(Vec::len), Some(12), "{players}");
    assert_eq!(unsafe { libc::kill(victim, libc::SIGKILL) }, 0);
    std::thread::sleep(Duration::from_secs(15));
    let [g0, mut g1] = gateways;
    // Gateway 1 dies with its 12 players connected: the zones remove their objects.
    g1.process.0.kill().unwrap();
    let _ = g1.process.0.wait();
    let deadline = Instant::now() + Duration::from_secs(12);
    while zones("myriad_zone_player_orphans_total") < 12.0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(300));
    }
    let orphans = zones("myriad_zone_player_orphans_total");
    let _ = leaving.kill();
    let _ = leaving.wait();
    let out = staying.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let last: serde_json::Value =
        serde_json::from_str(text.lines().rev().find(|l| l.contains("\"final\"")).expect("a final line")).unwrap();
    log.extend(rx.try_iter());
    let handoffs = metric(g0.metrics, "myriad_gateway_player_handoffs_total");
    eprintln!("bots of gateway 0: {last}\nplayer hand-offs {handoffs}, orphans {orphans}\ncluster: {log:?}");
    assert_eq!(last["logins_ok"], 12, "{last}");
    assert_eq!(last["logins_failed"], 0, "{last}");
    assert_eq!(last["reconnects"], 0, "players stay connected through the rollback: {last}");
    assert_eq!(last["own_object_seen"], 12, "{last}");
    assert_eq!(last["ticks_missed"], 0, "no gap in the updates longer than one tick: {last}");
    // Walking still works after the rollback (a zone that lost the players' intents in it
    // made most moves fail once).
    let (ok, wrong) = (last["moves_ok"].as_u64().unwrap(), last["moves_wrong"].as_u64().unwrap());
    assert!(ok >= 2 * wrong, "moves ok {ok}, wrong {wrong}: {last}");
    assert_eq!(last["rejected"], 0, "{last}");
    assert_eq!(last["decode_errors"], 0, "{last}");
    // Through the zones' rollback too, every delta record met the state it names.
    assert_eq!(last["unresolved"], 0, "{last}");
    assert!(log.iter().any(|l| l.starts_with("fault ")), "the cluster saw the kill: {log:?}");
    assert!(orphans >= 12.0, "the dead gateway's players were removed ({orphans})");
    assert!(handoffs >= 1.0, "a player's object changed zone under its session");
    assert!(metric(g0.metrics, "myriad_gateway_rollbacks_total") >= 1.0, "the gateway followed the rollback");
    assert_eq!(metric(g0.metrics, "myriad_gateway_duplicates_total"), 0.0, "no object in two zones");
    // After the bots left, the zones take their objects out. Their counts add up only at
    // one tick: summed across a step of one zone, they miss or double an object handed
    // over in it (this read 5,999 once).
    let deadline = Instant::now() + Duration::from_secs(15);
    let mut owned = None;
    while owned.is_none_or(|(_, n)| n != 6000.0) && Instant::now() < deadline {
        owned = zones_at_one_tick(zone_metrics, 2, "myriad_zone_owned_objects").or(owned);
        std::thread::sleep(Duration::from_millis(100));
    }
    let owned = owned.expect("the zones' gauges at one tick");
    assert_eq!(owned.1, 6000.0, "back to the world's 6,000 objects once every player left (tick, count): {owned:?}");
    drop(cluster);
    // The live run replays bit for bit: from the checkpoint the rollback started at (the
    // oldest whose logs reach the end in one epoch) to the last tick both zones stored,
    // with the intents the zones logged, the world ends as the live one did.
    let args =
        "--zones 2 --scenario 1 --seed 1 --backend cpu --ticks 6000 --checkpoint-every 30 --keep-checkpoints 400";
    let r = replay_equal(&url, &cluster_name, KEY, &args.split(' ').collect::<Vec<_>>());
    let restart = log.iter().filter_map(|l| l.strip_prefix("epoch ")).next_back().unwrap_or_default().to_string();
    assert!(r["epoch"].as_u64().unwrap() >= 2, "the replay is of the epoch after the rollback: {r}, {restart}");
    assert!(r["intents"].as_u64().unwrap() > 40, "the players' intents were replayed: {r}");
    assert!(r["to"].as_u64().unwrap() > r["from"].as_u64().unwrap() + 600, "20 s and more replayed: {r}");
}

/// `myriad cluster --gateways 2` starts the gateways with the zones: bots log in to
/// gateway 0 and see their own objects; a login of one of their accounts at gateway 1
/// replaces that bot's session at gateway 0 (one session per account in the cluster);
/// the cluster ends at its last tick as usual.
#[test]
fn a_cluster_starts_its_gateways_and_one_account_has_one_session() {
    let Some(url) = myriad_testenv::nats_url() else { return };
    let bin = env!("CARGO_BIN_EXE_myriad");
    let dir = tempfile::tempdir().unwrap();
    for g in 0..2 {
        let data = dir.path().join(format!("gateway-{g}"));
        let seeded = Command::new(bin)
            .args(["user", "seed", "--count", "5", "--data-dir", data.to_str().unwrap()])
            .output()
            .unwrap();
        assert!(seeded.status.success(), "{}", String::from_utf8_lossy(&seeded.stderr));
    }
    // Four ports in a row for the gateways' UDP and login; the zones' metrics on
    // `metrics` and the next, the gateways' 100 above.
    let port = free_ports(4);
    let metrics = loop {
        let m = free_ports(2);
        if free_ports_at(m + 100, 2) {
            break m;
        }
    };
    let cluster = Command::new(bin)
        .args(["cluster", "--json", "--nats", &url, "--cluster", &format!("gc{}", std::process::id())])
        .args(["--zones", "2", "--live", "--gateways", "2", "--gateway-port", &port.to_string()])
        .args(["--gateway-data", dir.path().to_str().unwrap(), "--scenario", "1", "--backend", "cpu"])
        .args(["--tick-hz", "30", "--ticks", "900", "--metrics-base-port", &metrics.to_string()])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut cluster = Killed(cluster);
    let log = collect_stderr(&mut cluster.0);
    let login = |g: u16| format!("127.0.0.1:{}", port + 2 * g + 1);
    let start = Instant::now();
    while std::net::TcpStream::connect(login(0)).is_err() || std::net::TcpStream::connect(login(1)).is_err() {
        // Debug builds of two zones, two gateways and the cluster each build the map,
        // on a CI machine's two cores beside the other test of this file.
        let exited = cluster.0.try_wait().unwrap();
        if exited.is_some() || start.elapsed() > Duration::from_secs(150) {
            std::thread::sleep(Duration::from_millis(300));
            let log: Vec<String> = log.try_iter().collect();
            panic!("the cluster's gateways never listened (cluster {exited:?}); its log: {log:#?}");
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let cert = |g: u16| dir.path().join(format!("gateway-{g}/tls-cert.pem")).display().to_string();
    let five = Command::new(bin)
        .args(["bots", "--server", &login(0), "--count", "5", "--duration", "8", "--json", "--cert", &cert(0)])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_secs(3));
    // user0 logs in at gateway 1 as well.
    let one = Command::new(bin)
        .args(["bots", "--server", &login(1), "--count", "1", "--duration", "2", "--json", "--cert", &cert(1)])
        .output()
        .unwrap();
    assert!(one.status.success());
    let out = five.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let last: serde_json::Value =
        serde_json::from_str(text.lines().rev().find(|l| l.contains("\"final\"")).expect("a final line")).unwrap();
    assert_eq!(last["logins_ok"].as_u64().unwrap() - last["reconnects"].as_u64().unwrap(), 5, "{last}");
    assert_eq!(last["own_object_seen"], 5, "{last}");
    let taken = metric(metrics + 100, "myriad_sessions_taken_total");
    assert!(taken >= 1.0, "user0's session at gateway 0 was replaced by its login at gateway 1");
    assert!(last["reconnects"].as_u64().unwrap() >= 1, "user0's bot logged in again: {last}");
    let status = cluster.0.wait().unwrap();
    assert!(status.success(), "the cluster ends at its last tick");
}
