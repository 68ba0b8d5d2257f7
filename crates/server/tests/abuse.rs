//! Issue 14: every attack of the table, against a real server on loopback,
//! bounded in count and time, through the same code as `myriad flood`
//! (`myriad_client::flood`). Each test asserts the defence (what the server counted,
//! what it answered, that legitimate players and logins still work), never timing.
//!
//! The tests of this file run one at a time (they share the process-wide
//! password-verification pool and the machine's cores).

use std::net::{IpAddr, SocketAddr};
use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use myriad_client::flood::{self, Bounds, StormAccounts, UdpKind};
use myriad_client::{ClientConfig, ClientError, Connection, Credentials, Event, Trust};
use myriad_protocol::login::RefusalReason;
use myriad_server::{ServerConfig, ServerHandle};
use myriad_store::Store;

static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner())
}

mod common;

fn config(dir: &Path) -> ServerConfig {
    common::small_server(dir, 300)
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}

fn start(cfg: ServerConfig, users: u32) -> (tokio::runtime::Runtime, ServerHandle, ClientConfig) {
    let rt = runtime();
    rt.block_on(async {
        let store = Store::open(&myriad_server::store_config(&cfg)).await.unwrap();
        store.seed_users(users).await.unwrap();
        store.close().await;
    });
    let server = ServerHandle::start(cfg).unwrap();
    let trust = Trust::pin_file(server.certificate_path()).unwrap();
    let mut cc = ClientConfig::new(server.login_addr(), &trust).unwrap();
    cc.login_timeout = Duration::from_secs(20);
    (rt, server, cc)
}

fn ip(s: &str) -> IpAddr {
    s.parse().unwrap()
}

/// Logs in, retrying while the answer says "retry later" (busy), for at most 10 s.
async fn login_with_retries(cc: &ClientConfig, creds: &Credentials, from: IpAddr) -> flood::Probe {
    let end = Instant::now() + Duration::from_secs(10);
    loop {
        let p = flood::probe_login(cc, creds, from).await;
        match &p.result {
            Err(ClientError::Refused { reason: RefusalReason::Busy, retry_after_ms }) if Instant::now() < end => {
                tokio::time::sleep(Duration::from_millis(u64::from(*retry_after_ms).clamp(10, 500))).await;
            }
            _ => return p,
        }
    }
}

/// Receives for `time`, counting state updates per 250 ms window.
async fn updates_per_window(c: &mut Connection, time: Duration) -> Vec<u32> {
    let start = Instant::now();
    let mut windows = vec![0u32; (time.as_millis() / 250).max(1) as usize];
    let mut next_keepalive = Instant::now();
    while start.elapsed() < time {
        if Instant::now() >= next_keepalive {
            let _ = c.send_action(0).await;
            next_keepalive += Duration::from_millis(100);
        }
        if let Ok(Some(Event::Update { .. })) = c.recv(Duration::from_millis(20)).await {
            let w = (start.elapsed().as_millis() / 250) as usize;
            if let Some(slot) = windows.get_mut(w) {
                *slot += 1;
            }
        }
    }
    windows
}

// Row 1: datagrams with a live session id, fresh sequences and random tags, as fast as
// one socket goes. Each used to cost a Poly1305 check; now at most the session's budget
// per tick reaches the tag check, and the other players keep getting every update.
#[test]
fn a_live_session_flood_pays_a_bounded_crypto_budget_and_players_keep_their_updates() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { receive_per_session: 8, receive_other_address: 2, ..config(dir.path()) };
    let (rt, server, cc) = start(cfg, 4);
    rt.block_on(async {
        let mut players = Vec::new();
        for i in 0..2 {
            players.push(Connection::connect(cc.clone(), Credentials::test_user(i)).await.unwrap());
        }
        // The attacker is a player too: it knows its own session id.
        let (attacker, _) = myriad_client::login(&cc, &Credentials::test_user(3)).await.unwrap();
        let udp = server.udp_addr();
        let target = SocketAddr::new(ip("127.0.0.1"), udp.port());
        let before = server.defence();
        let ticks_before = server.tick();
        let session_id = attacker.keys.session_id;
        let flood = std::thread::spawn(move || {
            let kind = UdpKind::LiveSession { session_id, first_sequence: 1 };
            flood::udp_flood(target, ip("127.0.0.1"), kind, Bounds::for_time(Duration::from_secs(2))).unwrap()
        });
        // A player's own session id, flooded from elsewhere, too.
        let victim = players[0].accepted().keys.session_id;
        let flood2 = std::thread::spawn(move || {
            let kind = UdpKind::LiveSession { session_id: victim, first_sequence: 1_000_000 };
            let bounds = Bounds { count: 0, rate: 20_000.0, duration: Duration::from_secs(2) };
            flood::udp_flood(target, ip("127.0.0.5"), kind, bounds).unwrap()
        });
        let receivers: Vec<_> = players
            .into_iter()
            .map(|mut p| tokio::spawn(async move { updates_per_window(&mut p, Duration::from_millis(2000)).await }))
            .collect();
        let mut windows = Vec::new();
        for r in receivers {
            windows.push(r.await.unwrap());
        }
        let report = flood.join().unwrap();
        let report2 = flood2.join().unwrap();
        let after = server.defence();
        let ticks = server.tick() - ticks_before + 2;
        assert!(report.sent > 1000, "the flood ran: {report:?}");
        assert_eq!(report.replies + report2.replies, 0, "nothing is sent back to a forged datagram");
        let checks = after.tag_checks - before.tag_checks;
        let dropped = after.over_budget - before.over_budget;
        // Per tick: the attacker's own budget (8), the victim's other-address budget (2),
        // and the players' own datagrams (a keep-alive every 100 ms each).
        assert!(checks <= ticks * (8 + 2 + 2 * 2), "{checks} tag checks over {ticks} ticks");
        assert!(dropped > 0, "the excess was dropped before the tag check");
        for (i, w) in windows.iter().enumerate() {
            assert!(w.iter().all(|&n| n > 0), "player {i} went without updates during the flood: {w:?}");
        }
    });
    server.shutdown().unwrap();
}

// Row 2 and the oversized-datagram edge: garbage costs no cryptography and no reply.
#[test]
fn garbage_and_oversized_datagrams_cost_no_cryptography() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let (rt, server, cc) = start(config(dir.path()), 1);
    rt.block_on(async {
        let mut player = Connection::connect(cc.clone(), Credentials::test_user(0)).await.unwrap();
        let target = SocketAddr::new(ip("127.0.0.1"), server.udp_addr().port());
        let before = server.defence();
        let garbage = std::thread::spawn(move || {
            let bounds = Bounds { count: 50_000, rate: 0.0, duration: Duration::from_secs(2) };
            let a = flood::udp_flood(target, ip("127.0.0.1"), UdpKind::Garbage, bounds).unwrap();
            let b = flood::udp_flood(target, ip("127.0.0.1"), UdpKind::Oversized, bounds).unwrap();
            (a, b)
        });
        let windows = updates_per_window(&mut player, Duration::from_millis(1500)).await;
        let (a, b) = garbage.join().unwrap();
        assert!(a.sent > 0 && b.sent > 0);
        assert_eq!(a.replies + b.replies, 0);
        let after = server.defence();
        // Only the player's own keep-alives reach the tag check.
        assert!(after.tag_checks - before.tag_checks <= 40, "{before:?} -> {after:?}");
        assert!(windows.iter().all(|&n| n > 0), "{windows:?}");
    });
    server.shutdown().unwrap();
}

// Row 6: a correctly sealed datagram with sequence u64::MAX used to freeze its session.
#[test]
fn a_sealed_datagram_with_sequence_u64_max_is_dropped_and_the_session_goes_on() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let (rt, server, cc) = start(config(dir.path()), 1);
    rt.block_on(async {
        let r = flood::max_sequence(&cc, &Credentials::test_user(0)).await.unwrap();
        assert!(!r.answered_forged, "nothing answers the u64::MAX datagram");
        assert!(r.session_alive, "the session still answers afterwards");
    });
    server.shutdown().unwrap();
}

// Row 3: wrong-password logins from many addresses (no per-address limit triggers).
// Password checks queue behind a bounded pool; the excess is told "busy, retry" at once;
// unknown users cost no hash at all; a legitimate login still gets in.
#[test]
fn a_wrong_password_storm_gets_busy_answers_and_a_legitimate_login_gets_in() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        // A real cost (a few ms a check in an optimised build), one hashing thread, a
        // short queue.
        hash_memory_kib: 4096,
        hash_passes: 2,
        login_concurrency: 1,
        login_queue: 2,
        login_queue_deadline_ms: 300,
        // No limit stops this storm: every attempt reaches the queue.
        login_failures_per_account: 1000,
        login_failures_per_addr: 100_000,
        ..config(dir.path())
    };
    let (rt, server, cc) = start(cfg, 2);
    rt.block_on(async {
        let sources = flood::loopback_sources(10, 20);
        let bounds = Bounds { count: 0, rate: 0.0, duration: Duration::from_secs(2) };
        let storm_cc = cc.clone();
        let storm = tokio::spawn(async move {
            flood::login_storm(&storm_cc, &sources, StormAccounts::One("user1".into()), 48, bounds).await.unwrap()
        });
        tokio::time::sleep(Duration::from_millis(500)).await;
        // The storm's addresses have failures by now; one with none goes to the front of
        // the queue: in at the first try.
        let probe = flood::probe_login(&cc, &Credentials::test_user(0), ip("127.0.0.2")).await;
        let report = storm.await.unwrap();
        assert!(probe.result.is_ok(), "the legitimate login failed: {:?} ({report:?})", probe.result);
        assert!(report.seconds >= 1.9, "the storm lasted past the probe: {report:?}");
        // And again with retries after the storm (nothing left behind).
        assert!(login_with_retries(&cc, &Credentials::test_user(0), ip("127.0.0.3")).await.result.is_ok());
        let busy = report.answers.get(&RefusalReason::Busy.to_string()).copied().unwrap_or(0);
        assert!(busy > 0, "the queue filled and said so: {report:?}");
        assert!(server.defence().logins_busy >= busy);
        assert!(!report.answers.contains_key("accepted"));

        // Unknown users: no hashing at all.
        let verified = myriad_store::hash_pool_stats().verified;
        let sources = flood::loopback_sources(600, 100);
        let bounds = Bounds { count: 200, rate: 0.0, duration: Duration::from_secs(4) };
        let report = flood::login_storm(&cc, &sources, StormAccounts::Unknown, 16, bounds).await.unwrap();
        assert_eq!(report.answers.get(&RefusalReason::WrongCredentials.to_string()), Some(&report.attempts));
        assert_eq!(myriad_store::hash_pool_stats().verified, verified, "unknown users cost no hash");
        assert!(server.defence().unknown_users_refused >= report.attempts);
    });
    server.shutdown().unwrap();
}

// Row 4: 4,000 idle connections from one address. The per-address cap closes all but a
// few at once, the handshake deadline closes the rest, and a login from another address
// gets in meanwhile.
#[test]
fn idle_connections_from_one_address_do_not_lock_out_another() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { login_connections_per_addr: 16, login_handshake_timeout_ms: 1000, ..config(dir.path()) };
    let (rt, server, cc) = start(cfg, 1);
    rt.block_on(async {
        let target = server.login_addr();
        let idle = tokio::spawn(flood::idle_connections(target, ip("127.0.0.1"), 4000, Duration::from_secs(3)));
        // Wait until the flood's connections have reached the server.
        let end = Instant::now() + Duration::from_secs(20);
        while server.defence().connections_refused < 3900 && Instant::now() < end {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let probe = flood::probe_login(&cc, &Credentials::test_user(0), ip("127.0.0.2")).await;
        assert!(probe.result.is_ok(), "{:?}", probe.result);
        let r = idle.await.unwrap().unwrap();
        assert_eq!(r.connected + r.connect_failed, 4000);
        assert!(r.closed_at_once >= r.connected - 16, "{r:?}");
        assert_eq!(r.open_at_end, 0, "the handshake deadline closed the held ones: {r:?}");
        assert!(server.defence().handshake_timeouts >= 1);
    });
    server.shutdown().unwrap();
}

// Row 5: five wrong passwords used to lock the account for everyone for 60 s.
#[test]
fn a_stranger_cannot_lock_the_owner_out() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { login_failures_per_account: 5, ..config(dir.path()) };
    let (rt, server, cc) = start(cfg, 1);
    rt.block_on(async {
        let stranger = ip("127.0.0.3");
        let wrong = Credentials { username: "USER0".into(), password: "guess".into() };
        let mut answers = Vec::new();
        for _ in 0..8 {
            match flood::probe_login(&cc, &wrong, stranger).await.result {
                Err(ClientError::Refused { reason, .. }) => answers.push(reason),
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(&answers[..5], &[RefusalReason::WrongCredentials; 5]);
        assert!(answers[5..].iter().all(|r| *r == RefusalReason::RateLimited), "{answers:?}");
        // The owner, from its own address with no failures, gets in.
        let owner = flood::probe_login(&cc, &Credentials::test_user(0), ip("127.0.0.4")).await;
        assert!(owner.result.is_ok(), "{:?}", owner.result);
        // The stranger's address stays locked for this account, even with the password.
        let again = flood::probe_login(&cc, &Credentials::test_user(0), stranger).await;
        assert!(matches!(again.result, Err(ClientError::Refused { reason: RefusalReason::RateLimited, .. })));
    });
    server.shutdown().unwrap();
}

// `myriad_logins_total{result="bad_request"}` was never incremented.
#[test]
fn a_malformed_login_request_is_answered_and_counted() {
    let _one = serial();
    let dir = tempfile::tempdir().unwrap();
    let (rt, server, cc) = start(config(dir.path()), 1);
    rt.block_on(async {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let tcp = tokio::net::TcpStream::connect(server.login_addr()).await.unwrap();
        let name = rustls_pki_types::ServerName::try_from("localhost").unwrap();
        let mut tls = tokio_rustls::TlsConnector::from(cc.tls.clone()).connect(name, tcp).await.unwrap();
        // A frame of the right size holding a request of an unknown version.
        tls.write_all(&[4, 0, 0, 0, 0x01, 9, 0, 0]).await.unwrap();
        let mut answer = Vec::new();
        let _ = tls.read_to_end(&mut answer).await;
        assert_eq!(&answer[4..6], &[0x82, RefusalReason::BadRequest as u8], "{answer:?}");
        assert_eq!(server.defence().bad_requests, 1);
    });
    server.shutdown().unwrap();
}
