//! The server end to end: real TLS logins and sealed UDP sessions through the client
//! library, on loopback, with the embedded SQLite store in a temporary directory (and
//! MariaDB/MySQL for the persistence round trip when `MYSQL_URL` is set).

use std::path::Path;
use std::time::{Duration, Instant};

use myriad_client::{ClientConfig, ClientError, Connection, Credentials, Event, Swarm, SwarmConfig, Trust};
use myriad_protocol::login::RefusalReason;
use myriad_protocol::{ActionMask, DisconnectReason};
use myriad_server::{ServerConfig, ServerHandle};
use myriad_store::Store;

mod common;

/// A small, fast server: scenario 1's map with few NPCs, cheap password hashes, frequent
/// persistence.
fn config(dir: &Path) -> ServerConfig {
    ServerConfig { persist_interval_ms: 100, ..common::small_server(dir, 300) }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}

/// Creates `user0..user<n>` before the server starts (the store opened from the test's
/// own runtime, then closed).
fn seed(rt: &tokio::runtime::Runtime, config: &ServerConfig, n: u32) {
    rt.block_on(async {
        let store = Store::open(&myriad_server::store_config(config)).await.unwrap();
        store.seed_users(n).await.unwrap();
        store.close().await;
    });
}

/// Seeds `users` accounts and starts a server on `cfg`: the test's runtime, the server
/// and a client configuration that trusts it.
fn start(cfg: ServerConfig, users: u32) -> (tokio::runtime::Runtime, ServerHandle, ClientConfig) {
    let rt = runtime();
    seed(&rt, &cfg, users);
    let server = ServerHandle::start(cfg).unwrap();
    let cc = client(&server);
    (rt, server, cc)
}

fn client(server: &ServerHandle) -> ClientConfig {
    let trust = Trust::pin_file(server.certificate_path()).unwrap();
    let mut c = ClientConfig::new(server.login_addr(), &trust).unwrap();
    c.login_timeout = Duration::from_secs(20);
    c
}

/// Holds `mask` for `time`, receiving everything; returns the own position at the end.
async fn walk(c: &mut Connection, mask: u8, time: Duration) -> Option<[f32; 3]> {
    let end = Instant::now() + time;
    let mut next_send = Instant::now();
    while Instant::now() < end {
        if Instant::now() >= next_send {
            c.send_action(mask).await.unwrap();
            next_send += Duration::from_millis(33);
        }
        let _ = c.recv(Duration::from_millis(10)).await.unwrap();
    }
    c.own_position()
}

async fn wait_own_position(c: &mut Connection) -> [f32; 3] {
    let end = Instant::now() + Duration::from_secs(5);
    while Instant::now() < end {
        c.keepalive_if_due().await.unwrap();
        let _ = c.recv(Duration::from_millis(20)).await.unwrap();
        if let Some(p) = c.own_position() {
            return p;
        }
    }
    panic!("no update with the own object within 5 s");
}

#[test]
fn login_updates_and_commanded_movement() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let (rt, server, cc) = start(cfg, 2);
    rt.block_on(async {
        // The map on request: terrain samples and every static primitive.
        let with_map = ClientConfig { want_map: true, ..cc.clone() };
        let (accepted, map) = myriad_client::login(&with_map, &Credentials::test_user(1)).await.unwrap();
        let map = map.expect("map data was asked for");
        let d = &accepted.map;
        assert_eq!(map.samples.len(), (d.terrain_width * d.terrain_depth) as usize);
        assert_eq!(map.statics.len(), d.static_primitives as usize);
        assert!(map.statics.len() >= 3000, "scenario 1 has 3,000 static objects");
        let mut c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        assert!(c.accepted().map.terrain_width > 1);
        let start = wait_own_position(&mut c).await;
        assert!(c.mirror().len() > 1, "NPCs around the player are mirrored too");
        // Forward is +z.
        let end = walk(&mut c, ActionMask::FORWARD, Duration::from_millis(1500)).await.unwrap();
        assert!(end[2] - start[2] > 1.0, "moved forward: {start:?} -> {end:?}");
        assert!((end[0] - start[0]).abs() < 1.0, "and not sideways: {start:?} -> {end:?}");
        let right = walk(&mut c, ActionMask::RIGHT, Duration::from_millis(1500)).await.unwrap();
        assert!(right[0] - end[0] > 1.0, "moved right (+x): {end:?} -> {right:?}");
        let stats = c.stats();
        assert!(stats.updates > 30, "{stats:?}");
        assert_eq!(stats.decode_errors, 0);
        assert!(stats.last_tick > 0);
        // Stale marking: nothing is received for longer than the stale time.
        let later = Instant::now() + Duration::from_secs(5);
        assert_eq!(c.mirror_mut().mark_stale(later), c.mirror().len());
        c.disconnect().await.unwrap();
    });
    // user1 (the map download) never opened its UDP session and stays until it times out.
    let deadline = Instant::now() + Duration::from_secs(3);
    while server.players() > 1 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(server.players(), 1, "a Disconnect removes the player");
    server.shutdown().unwrap();
}

#[test]
fn wrong_password_then_rate_limit() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { login_failures_per_account: 3, ..config(dir.path()) };
    let (rt, server, cc) = start(cfg, 1);
    rt.block_on(async {
        let bad = Credentials { username: "user0".into(), password: "nope".into() };
        for _ in 0..3 {
            match Connection::connect(cc.clone(), bad.clone()).await {
                Err(ClientError::Refused { reason: RefusalReason::WrongCredentials, .. }) => {}
                other => panic!("expected wrong credentials, got {other:?}"),
            }
        }
        // Locked now, even with the right password.
        match Connection::connect(cc.clone(), Credentials::test_user(0)).await {
            Err(ClientError::Refused { reason: RefusalReason::RateLimited, retry_after_ms }) => {
                assert!(retry_after_ms > 0)
            }
            other => panic!("expected rate limited, got {other:?}"),
        }
        // Unknown users are refused the same way as wrong passwords.
        let ghost = Credentials { username: "ghost".into(), password: "x".into() };
        assert!(matches!(
            Connection::connect(cc.clone(), ghost).await,
            Err(ClientError::Refused { reason: RefusalReason::WrongCredentials, .. })
        ));
    });
    server.shutdown().unwrap();
}

#[test]
fn second_login_replaces_first_and_max_players_is_enforced() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { max_players: 2, ..config(dir.path()) };
    let (rt, server, cc) = start(cfg, 3);
    rt.block_on(async {
        let mut first = Connection::connect(cc.clone(), Credentials::test_user(0)).await.unwrap();
        wait_own_position(&mut first).await;
        let mut second = Connection::connect(cc.clone(), Credentials::test_user(0)).await.unwrap();
        assert_eq!(second.entity_id(), first.entity_id(), "the same object, a new session");
        let mut replaced = false;
        let end = Instant::now() + Duration::from_secs(3);
        while Instant::now() < end && !replaced {
            if let Some(Event::Disconnected(r)) = first.recv(Duration::from_millis(50)).await.unwrap() {
                assert_eq!(r, DisconnectReason::Replaced);
                replaced = true;
            }
        }
        assert!(replaced, "the first session was told it was replaced");
        wait_own_position(&mut second).await;
        let _third = Connection::connect(cc.clone(), Credentials::test_user(1)).await.unwrap();
        match Connection::connect(cc.clone(), Credentials::test_user(2)).await {
            Err(ClientError::Refused { reason: RefusalReason::ServerFull, .. }) => {}
            other => panic!("expected server full, got {other:?}"),
        }
        // The count is published at the end of each tick.
        let end = Instant::now() + Duration::from_secs(1);
        while server.players() != 2 && Instant::now() < end {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        assert_eq!(server.players(), 2);
    });
    server.shutdown().unwrap();
}

/// Logs in, walks, leaves; restarts; checks the position survived.
fn persistence_round_trip(cfg: ServerConfig, user: Credentials, rt: &tokio::runtime::Runtime) {
    let server = ServerHandle::start(cfg.clone()).unwrap();
    let cc = client(&server);
    let left_at = rt.block_on(async {
        let mut c = Connection::connect(cc, user.clone()).await.unwrap();
        wait_own_position(&mut c).await;
        walk(&mut c, ActionMask::BACK, Duration::from_millis(800)).await;
        // Stand still so the position is settled when we leave.
        walk(&mut c, 0, Duration::from_millis(800)).await.unwrap()
    });
    // Graceful shutdown writes every position.
    server.shutdown().unwrap();
    let server = ServerHandle::start(cfg).unwrap();
    let cc = client(&server);
    let back_at = rt.block_on(async {
        let c = Connection::connect(cc, user).await.unwrap();
        c.accepted().position
    });
    let d: f32 = (0..3).map(|i| (back_at[i] - left_at[i]).powi(2)).sum::<f32>().sqrt();
    assert!(d < 0.5, "left at {left_at:?}, came back at {back_at:?}");
    server.shutdown().unwrap();
}

#[test]
fn persistence_round_trip_sqlite() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let rt = runtime();
    seed(&rt, &cfg, 1);
    persistence_round_trip(cfg, Credentials::test_user(0), &rt);
}

#[test]
fn persistence_round_trip_mysql() {
    let Some(url) = myriad_testenv::mysql_url() else { return };
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { database_url: url, ..config(dir.path()) };
    let rt = runtime();
    // Unique per run: the `test` database keeps its users between CI runs.
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
    let name = format!("srv{}_{}", std::process::id(), nanos % 1_000_000_000_000);
    let user = Credentials { username: name.clone(), password: "secret-pass".into() };
    rt.block_on(async {
        let store = Store::open(&myriad_server::store_config(&cfg)).await.unwrap();
        store.create_user(&user.username, &user.password).await.unwrap();
        store.close().await;
    });
    persistence_round_trip(cfg, user, &rt);
}

#[test]
fn crash_recovery_resumes_at_last_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let (rt, server, cc) = start(cfg.clone(), 1);
    let last = rt.block_on(async {
        let mut c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        wait_own_position(&mut c).await;
        walk(&mut c, ActionMask::LEFT, Duration::from_millis(800)).await;
        // Still for several persistence intervals: the checkpoint is this position.
        walk(&mut c, 0, Duration::from_millis(1200)).await.unwrap()
    });
    // No goodbye, no final flush: like kill -9.
    server.crash();
    let server = ServerHandle::start(cfg).unwrap();
    let cc = client(&server);
    let resumed =
        rt.block_on(async { Connection::connect(cc, Credentials::test_user(0)).await.unwrap().accepted().position });
    let d: f32 = (0..3).map(|i| (resumed[i] - last[i]).powi(2)).sum::<f32>().sqrt();
    assert!(d < 0.5, "last seen at {last:?}, resumed at {resumed:?}");
    server.shutdown().unwrap();
}

#[test]
fn time_dilation_engages_under_load_and_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let (rt, server, cc) = start(cfg, 1);
    rt.block_on(async {
        let mut c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        wait_own_position(&mut c).await;
        // 60 ms of work per 33 ms tick.
        server.set_artificial_load(Duration::from_millis(60));
        let end = Instant::now() + Duration::from_secs(15);
        while server.dilation_permille() > 700 && Instant::now() < end {
            walk(&mut c, 0, Duration::from_millis(200)).await;
        }
        assert!(server.dilation_permille() <= 700, "dilation {}", server.dilation_permille());
        walk(&mut c, 0, Duration::from_millis(500)).await;
        assert!(c.dilation_permille() < 1000, "clients see the dilation in their updates");
        server.set_artificial_load(Duration::ZERO);
        let end = Instant::now() + Duration::from_secs(15);
        while server.dilation_permille() < 1000 && Instant::now() < end {
            walk(&mut c, 0, Duration::from_millis(200)).await;
        }
        assert_eq!(server.dilation_permille(), 1000, "back to real time");
    });
    server.shutdown().unwrap();
}

// Issue 14: docs/protocol.md promised ServerInfo whenever the dilation changes; the
// server only ever sent it in answer to Ready.
#[test]
fn server_info_is_sent_again_when_the_dilation_changes() {
    let dir = tempfile::tempdir().unwrap();
    let (rt, server, cc) = start(config(dir.path()), 1);
    rt.block_on(async {
        let mut c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        wait_own_position(&mut c).await;
        server.set_artificial_load(Duration::from_millis(60));
        let end = Instant::now() + Duration::from_secs(15);
        let mut infos = Vec::new();
        let mut next_keepalive = Instant::now();
        while Instant::now() < end && !infos.iter().any(|&d| d < 1000) {
            if Instant::now() >= next_keepalive {
                c.send_action(0).await.unwrap();
                next_keepalive += Duration::from_millis(200);
            }
            if let Ok(Some(Event::Info(info))) = c.recv(Duration::from_millis(20)).await {
                infos.push(info.dilation_permille);
            }
        }
        assert!(infos.iter().any(|&d| d < 1000), "no ServerInfo announced the dilation: {infos:?}");
        server.set_artificial_load(Duration::ZERO);
    });
    server.shutdown().unwrap();
}

#[test]
fn two_hundred_bots_end_to_end() {
    bots_end_to_end(1);
}

/// The same with 25 bots a socket: the server tells the sessions behind one address
/// apart by id, and each group's task hands every datagram to its bot.
#[test]
fn two_hundred_bots_sharing_sockets_end_to_end() {
    bots_end_to_end(25);
}

fn bots_end_to_end(bots_per_socket: usize) {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let (rt, server, cc) = start(cfg, 200);
    let report = rt.block_on(async {
        let swarm = Swarm::start(SwarmConfig { bots_per_socket, ..SwarmConfig::new(cc, 200) });
        let end = Instant::now() + Duration::from_secs(60);
        while swarm.snapshot().logins_ok < 200 && swarm.snapshot().logins_failed == 0 && Instant::now() < end {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // A few seconds of play.
        tokio::time::sleep(Duration::from_secs(4)).await;
        swarm.stop().await
    });
    assert_eq!(report.logins_ok, 200, "{report:?}");
    assert_eq!(report.logins_failed, 0, "{report:?}");
    assert_eq!(report.own_object_seen, 200, "every bot saw its own object: {report:?}");
    // A bot logs in again after hearing nothing for a while: that would mean its first
    // Ready was lost (the receiver thread must know a session before its keys leave).
    assert_eq!(report.totals.reconnects, 0, "no bot had to log in again: {report:?}");
    assert_eq!(report.totals.decode_errors, 0, "{report:?}");
    assert_eq!(report.totals.rejected, 0, "{report:?}");
    assert!(report.moves_ok > report.moves_wrong, "{report:?}");
    assert!(report.interval_p50_ms > 0.0, "intervals were recorded: {report:?}");
    let deadline = Instant::now() + Duration::from_secs(5);
    while server.players() > 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(server.players(), 0, "every bot said goodbye");
    server.shutdown().unwrap();
}

/// A bot on a shared socket whose session another login of its account replaced logs in
/// again on the same socket, and its neighbours on the socket play on undisturbed.
#[test]
fn a_replaced_bot_on_a_shared_socket_logs_in_again() {
    let dir = tempfile::tempdir().unwrap();
    let (rt, server, cc) = start(config(dir.path()), 20);
    let report = rt.block_on(async {
        let swarm = Swarm::start(SwarmConfig {
            bots_per_socket: 10,
            silence_reconnect: Duration::from_secs(2),
            ..SwarmConfig::new(cc.clone(), 20)
        });
        let end = Instant::now() + Duration::from_secs(30);
        while swarm.snapshot().own_object_seen < 20 && Instant::now() < end {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // user3 logs in elsewhere: the server ends bot 3's session (Replaced)...
        let intruder = Connection::connect(cc, Credentials::test_user(3)).await.unwrap();
        let end = Instant::now() + Duration::from_secs(20);
        while swarm.snapshot().totals.reconnects == 0 && Instant::now() < end {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        drop(intruder);
        // ...and bot 3 took it back; everybody plays on. A bot that heard nothing for
        // 2 s would log in again (its new session's datagrams not reaching it, say).
        tokio::time::sleep(Duration::from_secs(4)).await;
        swarm.stop().await
    });
    assert_eq!(report.logins_failed, 0, "{report:?}");
    assert_eq!(report.totals.reconnects, 1, "bot 3 logged in again: {report:?}");
    assert_eq!(report.logins_ok, 21, "{report:?}");
    assert_eq!(report.own_object_seen, 20, "{report:?}");
    assert_eq!(report.connected, 0, "{report:?}");
    assert_eq!(report.totals.decode_errors, 0, "{report:?}");
    assert!(report.first_error.is_none(), "{report:?}");
    server.shutdown().unwrap();
}

/// A port free right now on loopback (for tests that restart a server on the same ports).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

#[test]
fn client_reconnects_after_server_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (login, udp) = (free_port(), free_port());
    let cfg = ServerConfig {
        login_addr: format!("127.0.0.1:{login}").parse().unwrap(),
        udp_addr: format!("127.0.0.1:{udp}").parse().unwrap(),
        ..config(dir.path())
    };
    let (rt, server, cc) = start(cfg.clone(), 1);
    let mut c = rt.block_on(async {
        let mut c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        wait_own_position(&mut c).await;
        c
    });
    server.shutdown().unwrap();
    rt.block_on(async {
        let end = Instant::now() + Duration::from_secs(3);
        while c.disconnected().is_none() && Instant::now() < end {
            let _ = c.recv(Duration::from_millis(50)).await;
        }
        assert_eq!(c.disconnected(), Some(DisconnectReason::Shutdown), "told about the shutdown");
    });
    let server = ServerHandle::start(cfg).unwrap();
    rt.block_on(async {
        c.reconnect().await.unwrap();
        assert!(c.mirror().is_empty(), "a fresh mirror after a new login");
        wait_own_position(&mut c).await;
        assert_eq!(c.stats().reconnects, 1);
        assert_eq!(c.stats().decode_errors, 0);
    });
    server.shutdown().unwrap();
}

#[test]
fn unauthenticated_datagrams_get_no_reply() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path());
    let (rt, server, cc) = start(cfg, 1);
    rt.block_on(async {
        // A real session exists, so its id is live: forge datagrams carrying it.
        let c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        let session = c.accepted().keys.session_id;
        let probe = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        probe.connect(server.udp_addr()).await.unwrap();
        let mut forged = vec![1u8, 0x03];
        forged.extend_from_slice(&session.to_le_bytes());
        forged.extend_from_slice(&0u64.to_le_bytes());
        forged.extend_from_slice(&[0u8; 16]);
        for d in [vec![], vec![0xff; 5], vec![0u8; 1200], forged] {
            probe.send(&d).await.unwrap();
        }
        let mut buf = [0u8; 2048];
        let got = tokio::time::timeout(Duration::from_millis(700), probe.recv(&mut buf)).await;
        assert!(got.is_err(), "the server answered an unauthenticated datagram");
    });
    assert_eq!(server.players(), 1, "forged datagrams changed nothing");
    server.shutdown().unwrap();
}

#[test]
fn metrics_endpoint_serves_stage_histograms() {
    use std::io::{Read, Write};
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    // The only test that installs the process-wide metrics recorder.
    let cfg = ServerConfig { metrics_addr: Some(format!("127.0.0.1:{port}").parse().unwrap()), ..config(dir.path()) };
    let (rt, server, cc) = start(cfg, 1);
    rt.block_on(async {
        let mut c = Connection::connect(cc, Credentials::test_user(0)).await.unwrap();
        wait_own_position(&mut c).await;
        walk(&mut c, 0, Duration::from_millis(500)).await;
    });
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).unwrap();
    for needle in [
        "myriad_tick_duration_seconds_bucket",
        "myriad_stage_duration_seconds_bucket{stage=\"broad_dynamic\"",
        "stage=\"packets\"",
        "stage=\"send\"",
        // Other tests' servers in this process feed the same global recorder, so values
        // are not checked, only that each series exists.
        "myriad_players ",
        "myriad_time_dilation",
        "myriad_bytes_sent_total",
        "myriad_logins_total{result=\"ok\"}",
    ] {
        assert!(body.contains(needle), "{needle} missing from /metrics:\n{body}");
    }
    server.shutdown().unwrap();
}

#[test]
fn client_refuses_a_server_with_another_certificate() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let rt = runtime();
    let cfg_b = config(b.path());
    seed(&rt, &cfg_b, 1);
    let server_a = ServerHandle::start(config(a.path())).unwrap();
    let server_b = ServerHandle::start(cfg_b).unwrap();
    // Pin A's certificate, talk to B: the handshake must fail before any credential is sent.
    let trust = Trust::pin_file(server_a.certificate_path()).unwrap();
    let cc = ClientConfig::new(server_b.login_addr(), &trust).unwrap();
    let result = rt.block_on(Connection::connect(cc, Credentials::test_user(0)));
    assert!(matches!(result, Err(ClientError::Io { what: "TLS handshake", .. })), "{result:?}");
    assert_eq!(server_b.players(), 0);
    server_a.shutdown().unwrap();
    server_b.shutdown().unwrap();
}
