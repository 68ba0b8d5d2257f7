//! Issue 29: the admin API through real HTTP on loopback, against an in-process server
//! with players in play (the client library's connections). Refusals (no token, wrong
//! token, an address not allowed) are refused, counted and audited; kick and ban end
//! sessions with their reasons, the kicked player logs in again, the banned one is
//! refused until its ban ends; disable, enable, delete and a new password take effect;
//! every action is in the audit table.

use std::net::{IpAddr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use myriad_client::{ClientConfig, ClientError, Connection, Credentials, Event, Trust};
use myriad_protocol::DisconnectReason;
use myriad_protocol::login::RefusalReason;
use myriad_server::{ServerConfig, ServerHandle};
use serde_json::{Value, json};

mod common;

/// The admin API as a test reaches it.
struct Api {
    base: String,
    token: String,
    agent: ureq::Agent,
}

impl Api {
    fn new(addr: SocketAddr, token: String) -> Api {
        let agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(20)))
            .build()
            .into();
        Api { base: format!("http://{addr}"), token, agent }
    }

    /// `method path` with `token` (none: no Authorization header) and `body`.
    fn send(&self, method: &str, path: &str, token: Option<&str>, body: Option<&str>) -> (u16, Value) {
        let url = format!("{}{path}", self.base);
        let auth = token.map(|t| format!("Bearer {t}"));
        let response = match method {
            "GET" | "DELETE" => {
                let mut r = if method == "GET" { self.agent.get(&url) } else { self.agent.delete(&url) };
                if let Some(a) = &auth {
                    r = r.header("authorization", a);
                }
                r.call()
            }
            _ => {
                let mut r = self.agent.post(&url).header("x-myriad-actor", "tester");
                if let Some(a) = &auth {
                    r = r.header("authorization", a);
                }
                match body {
                    Some(b) => r.header("content-type", "application/json").send(b),
                    None => r.send_empty(),
                }
            }
        };
        let mut response = response.unwrap_or_else(|e| panic!("{method} {url}: {e}"));
        let status = response.status().as_u16();
        let text = response.body_mut().read_to_string().unwrap();
        (status, serde_json::from_str(&text).unwrap_or(Value::String(text)))
    }

    fn get(&self, path: &str) -> (u16, Value) {
        self.send("GET", path, Some(&self.token.clone()), None)
    }

    fn post(&self, path: &str, body: Value) -> (u16, Value) {
        self.send("POST", path, Some(&self.token.clone()), Some(&body.to_string()))
    }

    /// The audit trail, newest first.
    fn audit(&self) -> Vec<Value> {
        let (status, v) = self.get("/api/audit?limit=1000");
        assert_eq!(status, 200, "{v}");
        v.as_array().unwrap().clone()
    }
}

/// The audit entries of `action` on `target`, newest first.
fn entries<'a>(audit: &'a [Value], action: &str, target: &str) -> Vec<&'a Value> {
    audit.iter().filter(|e| e["action"] == action && e["target"] == target).collect()
}

fn start(dir: &std::path::Path, admin_addr: &str) -> (ServerHandle, Api) {
    let cfg = ServerConfig {
        admin_addr: Some(admin_addr.parse().unwrap()),
        persist_interval_ms: 100,
        ..common::small_server(dir, 40)
    };
    let server = ServerHandle::start(cfg).unwrap();
    let token = std::fs::read_to_string(server.admin_token_path().unwrap()).unwrap().trim().to_string();
    let port = server.admin_addr().unwrap().port();
    let api = Api::new(SocketAddr::from(([127, 0, 0, 1], port)), token);
    (server, api)
}

/// This machine's IPv4 address on its default route (no packet is sent: connecting a
/// UDP socket only picks the route), if it has one that is not loopback.
fn non_loopback_ipv4() -> Option<IpAddr> {
    let socket = UdpSocket::bind("0.0.0.0:0").ok()?;
    socket.connect("192.0.2.1:9").ok()?;
    let ip = socket.local_addr().ok()?.ip();
    (!ip.is_loopback() && !ip.is_unspecified()).then_some(ip)
}

#[test]
fn refusals_are_refused_counted_and_audited() {
    let dir = tempfile::tempdir().unwrap();
    // Bound to every address, allowed from loopback only (the default allow list).
    let (server, api) = start(dir.path(), "0.0.0.0:0");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(server.admin_token_path().unwrap()).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600, "the generated token is the owner's alone");
        assert_eq!(api.token.len(), 64);
    }
    let (status, body) = api.send("GET", "/api/state", None, None);
    assert_eq!((status, &body["error"]), (401, &json!("a valid bearer token is required")));
    let wrong: String = api.token.chars().rev().collect();
    assert_eq!(api.send("GET", "/api/players", Some(&wrong), None).0, 401);
    assert_eq!(api.send("POST", "/api/players/user0/kick", Some("short"), Some("{}")).0, 401);
    assert_eq!(api.send("GET", "/api/nope", None, None).0, 401, "unknown routes need the token too");
    let stats = server.admin_stats();
    assert_eq!((stats.no_token, stats.wrong_token, stats.ok), (2, 2, 0), "{stats:?}");

    // The console's files need no token (they hold no data); unknown ones are 404.
    let (status, page) = api.send("GET", "/", None, None);
    assert_eq!(status, 200);
    assert!(page.as_str().is_some_and(|p| p.contains("<")), "{page}");
    assert_eq!(api.send("GET", "/console/missing.js", None, None).0, 404);

    // From a non-loopback address of this machine: refused even with the right token.
    let forbidden_before = server.admin_stats().forbidden;
    match non_loopback_ipv4() {
        Some(ip) => {
            let outside = Api::new(SocketAddr::new(ip, server.admin_addr().unwrap().port()), api.token.clone());
            let (status, body) = outside.get("/api/state");
            assert_eq!(status, 403, "{body}");
            assert_eq!(outside.send("GET", "/", None, None).0, 403, "the console too");
            assert_eq!(server.admin_stats().forbidden, forbidden_before + 2);
            let audit = api.audit();
            let refused = entries(&audit, "refused", "/api/state");
            assert!(
                refused.iter().any(|e| e["detail"] == "address not allowed"
                    && e["from"].as_str().unwrap().starts_with(&ip.to_string())
                    && e["ok"] == false),
                "{audit:?}"
            );
        }
        None => eprintln!("SKIPPED the address check: this machine has no non-loopback IPv4 address"),
    }

    // Malformed requests are answered with a reason and counted.
    let (status, body) = api.get("/api/map?cells=0");
    assert_eq!(status, 400);
    assert!(body["error"].as_str().unwrap().contains("cells"), "{body}");
    assert_eq!(api.get("/api/map?cells=257").0, 400);
    assert_eq!(api.get("/api/nope").0, 404);
    let (status, body) = api.send("POST", "/api/players/user0/kick", Some(&api.token), Some("{not json"));
    assert_eq!(status, 400, "{body}");
    assert_eq!(api.post("/api/players/no%20spaces/kick", json!({})).0, 400);
    // A name with an escape character: refused, and audited without it (the trail is
    // printed on terminals).
    assert_eq!(api.post("/api/players/a%1B%5B31mb/kick", json!({})).0, 400);
    let stats = server.admin_stats();
    assert_eq!(stats.bad_request, 5, "{stats:?}");
    assert_eq!(stats.not_found, 2, "{stats:?}");

    // Every refusal is in the audit table, with where it came from and why.
    let audit = api.audit();
    assert_eq!(entries(&audit, "refused", "/api/state")[..].iter().filter(|e| e["detail"] == "no token").count(), 1);
    assert_eq!(entries(&audit, "refused", "/api/players")[0]["detail"], "wrong token");
    assert_eq!(entries(&audit, "refused", "/api/players/user0/kick")[0]["detail"], "wrong token");
    for e in entries(&audit, "refused", "/api/state") {
        assert_eq!((&e["actor"], &e["ok"]), (&json!("anonymous"), &json!(false)));
    }
    // A refused action is audited as not done, with the caller the header named.
    let kicks = entries(&audit, "kick", "user0");
    assert_eq!(kicks.len(), 1, "{audit:?}");
    assert_eq!((&kicks[0]["ok"], &kicks[0]["actor"]), (&json!(false), &json!("token:tester")));
    assert!(kicks[0]["from"].as_str().unwrap().starts_with("127.0.0.1:"));
    assert_eq!(entries(&audit, "kick", "a\u{fffd}[31mb").len(), 1, "{audit:?}");
    // Newest first, in RFC 3339.
    assert!(audit[0]["at"].as_str().unwrap().ends_with('Z'));

    // A flood of bad tokens is counted in full but audited at most 20 a second (so it
    // cannot fill the database).
    let before = server.admin_stats();
    let mut sent = 0;
    while server.admin_stats().audits_suppressed == before.audits_suppressed {
        assert!(sent < 500, "500 refusals in a row were all audited");
        assert_eq!(api.send("GET", "/api/audit", Some(&wrong), None).0, 401);
        sent += 1;
    }
    let flood = server.admin_stats();
    assert_eq!(flood.wrong_token - before.wrong_token, sent, "{flood:?}");
    let suppressed = flood.audits_suppressed - before.audits_suppressed;
    let audited = entries(&api.audit(), "refused", "/api/audit").len() as u64;
    assert_eq!(audited + suppressed, sent, "each refusal audited or counted as not");
    server.shutdown().unwrap();
}

/// Receives until `want` happens or `within` passes; whether it happened.
async fn pump(c: &mut Connection, within: Duration, mut want: impl FnMut(&Event, &Connection) -> bool) -> bool {
    let end = Instant::now() + within;
    while Instant::now() < end {
        c.on_timer(Instant::now()).await.unwrap();
        if let Some(event) = c.recv(Duration::from_millis(20)).await.unwrap()
            && want(&event, c)
        {
            return true;
        }
    }
    false
}

async fn in_play(cc: &ClientConfig, user: usize) -> Connection {
    let mut c = Connection::connect(cc.clone(), Credentials::test_user(user)).await.unwrap();
    assert!(pump(&mut c, Duration::from_secs(10), |_, c| c.own_position().is_some()).await, "user{user} in play");
    c
}

fn refusal(result: Result<Connection, ClientError>) -> RefusalReason {
    match result {
        Err(ClientError::Refused { reason, .. }) => reason,
        Err(e) => panic!("expected a refusal, got {e:?}"),
        Ok(_) => panic!("expected a refusal, the login was accepted"),
    }
}

/// A server with its admin API on loopback, four seeded accounts, a runtime for the
/// test's clients and their configuration (pinned to the server's certificate).
fn with_players(dir: &std::path::Path) -> (ServerHandle, Api, tokio::runtime::Runtime, ClientConfig) {
    let (server, api) = start(dir, "127.0.0.1:0");
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    rt.block_on(server.store().seed_users(4)).unwrap();
    let trust = Trust::pin_file(server.certificate_path()).unwrap();
    let mut cc = ClientConfig::new(server.login_addr(), &trust).unwrap();
    cc.login_timeout = Duration::from_secs(20);
    (server, api, rt, cc)
}

fn player<'a>(players: &'a Value, account: &str) -> Option<&'a Value> {
    players.as_array().unwrap().iter().find(|p| p["account"] == account)
}

#[test]
fn kick_and_ban_end_sessions_in_play() {
    let dir = tempfile::tempdir().unwrap();
    let (server, api, rt, cc) = with_players(dir.path());
    rt.block_on(async {
        let mut c0 = in_play(&cc, 0).await;
        let mut c1 = in_play(&cc, 1).await;
        // Let a few ticks of updates count, then read the players as the tick sees them.
        pump(&mut c0, Duration::from_millis(300), |_, _| false).await;
        api.get("/api/players");
        pump(&mut c1, Duration::from_millis(500), |_, _| false).await;
        let (status, players) = api.get("/api/players");
        assert_eq!(status, 200, "{players}");
        assert_eq!(players.as_array().unwrap().len(), 2, "{players}");
        let p0 = player(&players, "user0").expect("user0 online");
        assert_eq!(p0["entity"], json!(c0.accepted().entity_id));
        let addr: SocketAddr = p0["addr"].as_str().unwrap().parse().unwrap();
        assert_eq!(addr, c0.socket().local_addr().unwrap(), "the address its datagrams come from");
        assert!(p0["connected_since"].as_str().unwrap().ends_with('Z'));
        assert!(p0["bytes_per_s"].as_f64().unwrap() > 0.0, "updates were sent to it: {p0}");
        let own = c0.own_position().unwrap();
        let pos: Vec<f64> = p0["position"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        assert!((pos[0] - f64::from(own[0])).abs() < 2.0 && (pos[2] - f64::from(own[2])).abs() < 2.0, "{pos:?}");

        let (status, state) = api.get("/api/state");
        assert_eq!(status, 200);
        assert_eq!((state["players"].as_u64(), &state["role"]), (Some(2), &json!("server")));
        assert_eq!(state["version"], env!("CARGO_PKG_VERSION"));
        assert!(state["tick"].as_u64().unwrap() > 0 && state["dilation"].as_f64().unwrap() > 0.0);
        assert!(state["stages_ms"].as_object().unwrap().contains_key("receive"), "{state}");
        assert_ne!(state["backend"], "starting");

        let (status, map) = api.get("/api/map?cells=16");
        assert_eq!(status, 200);
        let density = map["npc_density"].as_array().unwrap();
        assert_eq!(density.len(), 256);
        assert_eq!(density.iter().map(|v| v.as_u64().unwrap()).sum::<u64>(), 40, "every NPC in one cell");
        assert_eq!(map["players"].as_array().unwrap().len(), 2);
        assert_eq!(map["cuts"], Value::Null);
        assert!(map["bounds"]["max_x"].as_f64().unwrap() > map["bounds"]["min_x"].as_f64().unwrap());

        // Kick: the client library reports it; the player may come back.
        let (status, body) = api.post("/api/players/user0/kick", json!({"reason": "testing kicks"}));
        assert_eq!((status, &body), (200, &json!({"kicked": true})));
        let told = pump(&mut c0, Duration::from_secs(3), |e, _| matches!(e, Event::Disconnected(_))).await;
        assert!(told && c0.disconnected() == Some(DisconnectReason::Kicked), "{:?}", c0.disconnected());
        let (_, players) = api.get("/api/players");
        assert!(player(&players, "user0").is_none(), "kicked: {players}");
        let mut back = in_play(&cc, 0).await;
        // The list is at most one snapshot period (200 ms) old.
        let end = Instant::now() + Duration::from_secs(2);
        let players = loop {
            let (_, players) = api.get("/api/players");
            if player(&players, "user0").is_some() || Instant::now() > end {
                break players;
            }
        };
        assert!(player(&players, "user0").is_some(), "the kicked player logged in again: {players}");
        assert_eq!(api.post("/api/players/user3/kick", json!({})).0, 404, "user3 is not online");

        // Ban with an end a little ahead: the session ends (Banned), logins are refused
        // until the end, then accepted.
        let until_ms = myriad_store::now_ms() + 2500;
        let until = myriad_server::admin::rfc3339::format_ms(until_ms);
        let (status, body) = api.post("/api/accounts/user1/ban", json!({"reason": "testing bans", "until": until}));
        assert_eq!(status, 200, "{body}");
        assert_eq!(body["kicked"], true);
        let told = pump(&mut c1, Duration::from_secs(3), |e, _| matches!(e, Event::Disconnected(_))).await;
        assert!(told && c1.disconnected() == Some(DisconnectReason::Banned), "{:?}", c1.disconnected());
        assert_eq!(refusal(Connection::connect(cc.clone(), Credentials::test_user(1)).await), RefusalReason::Banned);
        let (_, accounts) = api.get("/api/accounts");
        let a1 = accounts.as_array().unwrap().iter().find(|a| a["account"] == "user1").unwrap().clone();
        assert_eq!((&a1["banned"], &a1["ban_reason"]), (&json!(true), &json!("testing bans")), "{a1}");
        let wait = (until_ms - myriad_store::now_ms()).max(0) as u64 + 200;
        tokio::time::sleep(Duration::from_millis(wait)).await;
        let again = in_play(&cc, 1).await;
        drop(again);
        // A ban without end, lifted by unban.
        assert_eq!(api.post("/api/accounts/user3/ban", json!({"reason": "no end"})).0, 200);
        assert_eq!(refusal(Connection::connect(cc.clone(), Credentials::test_user(3)).await), RefusalReason::Banned);
        assert_eq!(api.post("/api/accounts/user3/unban", json!({})).0, 200);
        drop(in_play(&cc, 3).await);
        // Bad bans: an end in the past, a time that is not one, no reason.
        let past = api.post("/api/accounts/user2/ban", json!({"reason": "x", "until": "2001-01-01T00:00:00Z"}));
        assert_eq!(past.0, 400, "{past:?}");
        assert_eq!(api.post("/api/accounts/user2/ban", json!({"reason": "x", "until": "soon"})).0, 400);
        assert_eq!(api.post("/api/accounts/user2/ban", json!({"until": null})).0, 400);
        back.disconnect().await.unwrap();
    });
    let audit = api.audit();
    let kicks = entries(&audit, "kick", "user0");
    assert_eq!(kicks.len(), 1);
    assert_eq!((&kicks[0]["ok"], &kicks[0]["detail"]), (&json!(true), &json!("testing kicks")));
    assert_eq!(entries(&audit, "kick", "user3")[0]["ok"], false);
    let bans = entries(&audit, "ban", "user1");
    assert!(bans[0]["ok"] == true && bans[0]["detail"].as_str().unwrap().contains("testing bans"), "{bans:?}");
    assert_eq!(entries(&audit, "ban", "user3")[0]["ok"], true);
    assert_eq!(entries(&audit, "unban", "user3")[0]["ok"], true);
    assert_eq!(entries(&audit, "ban", "user2").iter().filter(|e| e["ok"] == false).count(), 3);
    server.shutdown().unwrap();
}

#[test]
fn account_actions_take_effect_and_are_audited() {
    let dir = tempfile::tempdir().unwrap();
    let (server, api, rt, cc) = with_players(dir.path());
    rt.block_on(async {
        // Disable a player in play: its session ends, its logins are refused; enable.
        let mut c2 = in_play(&cc, 2).await;
        let (status, body) = api.post("/api/accounts/user2/disable", json!({}));
        assert_eq!((status, &body["kicked"]), (200, &json!(true)), "{body}");
        assert!(pump(&mut c2, Duration::from_secs(3), |e, _| matches!(e, Event::Disconnected(_))).await);
        assert_eq!(c2.disconnected(), Some(DisconnectReason::Kicked));
        assert_eq!(refusal(Connection::connect(cc.clone(), Credentials::test_user(2)).await), RefusalReason::Disabled);
        let (_, accounts) = api.get("/api/accounts?limit=2&offset=2");
        let names: Vec<&str> = accounts.as_array().unwrap().iter().map(|a| a["account"].as_str().unwrap()).collect();
        assert_eq!(names, ["user2", "user3"], "a page by id");
        assert_eq!(accounts[0]["disabled"], true);
        assert_eq!(api.post("/api/accounts/user2/enable", json!({})).0, 200);
        drop(in_play(&cc, 2).await);

        // A new password: the old one is refused, the new one accepted; never audited.
        let (status, _) = api.post("/api/accounts/user1/password", json!({"password": "a new secret"}));
        assert_eq!(status, 200);
        assert_eq!(
            refusal(Connection::connect(cc.clone(), Credentials::test_user(1)).await),
            RefusalReason::WrongCredentials
        );
        let fresh = Credentials { username: "user1".into(), password: "a new secret".into() };
        drop(Connection::connect(cc.clone(), fresh).await.expect("the new password logs in"));
        assert_eq!(api.post("/api/accounts/user1/password", json!({"password": ""})).0, 400);

        // Delete a player in play: its session ends and the account is gone.
        let mut c3 = in_play(&cc, 3).await;
        let (status, body) = api.send("DELETE", "/api/accounts/user3", Some(&api.token), None);
        assert_eq!((status, &body["kicked"]), (200, &json!(true)), "{body}");
        assert!(pump(&mut c3, Duration::from_secs(3), |e, _| matches!(e, Event::Disconnected(_))).await);
        assert_eq!(
            refusal(Connection::connect(cc.clone(), Credentials::test_user(3)).await),
            RefusalReason::WrongCredentials
        );
        assert!(server.store().account("user3").await.unwrap().is_none());
        assert_eq!(api.send("DELETE", "/api/accounts/user3", Some(&api.token), None).0, 404);
        assert_eq!(api.post("/api/accounts/nobody/disable", json!({})).0, 404);
    });
    let audit = api.audit();
    for (action, target) in [("disable", "user2"), ("enable", "user2"), ("password", "user1"), ("delete", "user3")] {
        let found = entries(&audit, action, target);
        assert!(found.iter().any(|e| e["ok"] == true), "{action} {target}: {audit:?}");
    }
    assert_eq!(entries(&audit, "delete", "user3").iter().filter(|e| e["ok"] == false).count(), 1);
    assert_eq!(entries(&audit, "disable", "nobody")[0]["ok"], false);
    let text = serde_json::to_string(&audit).unwrap();
    assert!(!text.contains("a new secret"), "a password never reaches the audit trail");
    server.shutdown().unwrap();
}
