//! Issue 29 through the binaries: `myriad serve --admin`, bots playing (`myriad bots`),
//! and `myriad admin players|kick|ban|audit|state|console-url` reading the token from
//! the data directory. The kicked bot logs in again; the banned one stays out; both are
//! in the audit trail; a wrong token is refused.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;

use common::Killed;

/// A cheap password hash, so that the debug build logs the bots in quickly.
const CHEAP_HASH: [&str; 4] = ["--set", "hash_memory_kib=256", "--set", "hash_passes=1"];

fn myriad() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_myriad"));
    c.env("RUST_LOG", "warn");
    c
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// `myriad admin <args>` against the server of `data` at `addr`.
fn admin(data: &Path, addr: &str, args: &[&str]) -> Output {
    myriad().arg("admin").args(args).args(["--data-dir", data.to_str().unwrap(), "--addr", addr]).output().unwrap()
}

/// `myriad admin players --json`: the accounts online.
fn online(data: &Path, addr: &str) -> Vec<String> {
    let o = admin(data, addr, &["players", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    v.as_array().unwrap().iter().map(|p| p["account"].as_str().unwrap().to_string()).collect()
}

/// Waits until `ok` holds of the accounts online.
fn wait_online(data: &Path, addr: &str, what: &str, ok: impl Fn(&[String]) -> bool) -> Vec<String> {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let now = online(data, addr);
        if ok(&now) {
            return now;
        }
        assert!(Instant::now() < deadline, "{what}: online {now:?}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Waits for a `myriad bots --json` line for which `ok` holds.
fn wait_bots(lines: &Receiver<Value>, what: &str, ok: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match lines.recv_timeout(left) {
            Ok(line) if ok(&line) => return line,
            Ok(_) => {}
            Err(_) => panic!("the bots never reported {what}"),
        }
    }
}

#[test]
fn serve_admin_kick_ban_and_audit_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path();
    let d = data.to_str().unwrap();
    let seed = myriad().args(["user", "seed", "--count", "2", "--data-dir", d]).args(CHEAP_HASH).output().unwrap();
    assert!(seed.status.success(), "{}", text(&seed));

    let mut server = Killed(
        myriad()
            .args(["serve", "--data-dir", d, "--udp", "127.0.0.1:0", "--login", "127.0.0.1:0"])
            .args(["--admin", "127.0.0.1:0", "--backend", "cpu", "--npcs", "100"])
            .args(CHEAP_HASH)
            .env("RUST_LOG", "info")
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    // "login (TLS) on ADDR, …" and "admin API and console on http://ADDR/ (token in …)".
    let stderr = common::collect_stderr(&mut server.0);
    let (mut login, mut addr, mut logged) = (None, None, Vec::new());
    let deadline = Instant::now() + Duration::from_secs(60);
    while login.is_none() || addr.is_none() {
        let line = stderr.recv_timeout(deadline.saturating_duration_since(Instant::now())).expect("server started");
        logged.push(line.clone());
        if let Some(rest) = line.split("login (TLS) on ").nth(1) {
            login = rest.split(',').next().map(str::to_string);
        }
        if let Some(rest) = line.split("admin API and console on http://").nth(1) {
            addr = rest.split('/').next().map(str::to_string);
        }
    }
    let (login, addr) = (login.unwrap(), addr.unwrap());

    let cert = data.join("tls-cert.pem");
    let mut bots = Killed(
        myriad()
            .args(["bots", "--server", &login, "--cert", cert.to_str().unwrap(), "--count", "2"])
            .args(["--rate", "10", "--duration", "90", "--every", "0.3", "--json", "--behaviour", "idle"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let (tx, lines) = std::sync::mpsc::channel();
    let stdout = BufReader::new(bots.0.stdout.take().unwrap());
    std::thread::spawn(move || {
        for line in stdout.lines().map_while(Result::ok) {
            if let Ok(v) = serde_json::from_str::<Value>(&line) {
                let _ = tx.send(v);
            }
        }
    });
    wait_online(data, &addr, "both bots in play", |now| now.len() == 2);

    let state = admin(data, &addr, &["state"]);
    assert!(state.status.success() && text(&state).contains("role      server"), "{}", text(&state));
    let table = admin(data, &addr, &["players"]);
    assert!(text(&table).contains("user0") && text(&table).contains("2 online"), "{}", text(&table));

    // Kick: the bot hears "kicked" and logs in again.
    let kick = admin(data, &addr, &["kick", "user0", "--reason", "cli test"]);
    assert!(kick.status.success() && text(&kick).contains("kicked user0"), "{}", text(&kick));
    wait_bots(&lines, "a kick", |l| l["kicked"].as_u64() >= Some(1));
    wait_bots(&lines, "the kicked bot back", |l| l["reconnects"].as_u64() >= Some(1) && l["connected"] == 2);
    wait_online(data, &addr, "user0 back", |now| now.iter().any(|a| a == "user0"));

    // Ban: the bot hears "banned" and stays out (its logins are refused).
    let ban = admin(data, &addr, &["ban", "user1", "--reason", "cli ban"]);
    assert!(
        ban.status.success() && text(&ban).contains("banned user1 without end; its session ended"),
        "{}",
        text(&ban)
    );
    wait_bots(&lines, "a ban", |l| l["banned"].as_u64() >= Some(1));
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(online(data, &addr), ["user0"], "the banned bot stays out");
    let unknown = admin(data, &addr, &["kick", "user1"]);
    assert!(!unknown.status.success() && text(&unknown).contains("not online"), "{}", text(&unknown));

    let audit = admin(data, &addr, &["audit"]);
    let audit = text(&audit);
    let has = |action: &str, target: &str, ok: &str| {
        audit.lines().any(|l| l.contains(&format!(" {action} ")) && l.contains(target) && l.contains(ok))
    };
    assert!(has("kick", "user0", " ok "), "{audit}");
    assert!(has("ban", "user1", " ok "), "{audit}");
    assert!(has("kick", "user1", "REFUSED"), "{audit}");

    // The account commands.
    let accounts = text(&admin(data, &addr, &["accounts"]));
    assert!(accounts.lines().any(|l| l.contains("user1") && l.contains("banned (cli ban) without end")), "{accounts}");
    let unban = admin(data, &addr, &["unban", "user1"]);
    assert!(unban.status.success() && text(&unban).contains("unbanned user1"), "{}", text(&unban));
    let disable = admin(data, &addr, &["disable", "user1"]);
    assert!(disable.status.success() && text(&disable).contains("disabled user1"), "{}", text(&disable));
    assert!(text(&admin(data, &addr, &["accounts", "--limit", "1", "--offset", "1"])).contains("disabled"));
    let enable = admin(data, &addr, &["enable", "user1"]);
    assert!(enable.status.success(), "{}", text(&enable));
    let mut passwd = myriad()
        .args(["admin", "passwd", "user1", "--data-dir", d, "--addr", &addr])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::io::Write::write_all(&mut passwd.stdin.take().unwrap(), b"another secret\n").unwrap();
    let passwd = passwd.wait_with_output().unwrap();
    assert!(passwd.status.success() && text(&passwd).contains("password of user1 changed"), "{}", text(&passwd));
    let missing = admin(data, &addr, &["delete", "nobody"]);
    assert!(!missing.status.success() && text(&missing).contains("404"), "{}", text(&missing));
    let audit = text(&admin(data, &addr, &["audit", "--limit", "100"]));
    for action in ["unban", "disable", "enable", "password"] {
        assert!(audit.lines().any(|l| l.contains(&format!(" {action} ")) && l.contains("user1")), "{action}: {audit}");
    }
    assert!(!audit.contains("another secret"), "no password in the audit trail");

    // The console's address carries the token in its fragment.
    let url = admin(data, &addr, &["console-url"]);
    let token = std::fs::read_to_string(data.join("admin.token")).unwrap();
    assert_eq!(String::from_utf8_lossy(&url.stdout).trim(), format!("http://{addr}/#token={}", token.trim()));

    // A wrong token is refused (and the refusal is audited).
    let wrong = data.join("wrong.token");
    std::fs::write(&wrong, "0".repeat(64)).unwrap();
    let refused =
        myriad().args(["admin", "state", "--addr", &addr, "--token-file", wrong.to_str().unwrap()]).output().unwrap();
    assert!(!refused.status.success() && text(&refused).contains("401"), "{}", text(&refused));
    let audit = text(&admin(data, &addr, &["audit", "--limit", "5"]));
    assert!(audit.contains("refused") && audit.contains("wrong token"), "{audit}");

    // Whatever the server logged, the token is not in it.
    logged.extend(stderr.try_iter());
    assert!(logged.iter().all(|l| !l.contains(token.trim())), "the token was logged");
    assert!(logged.iter().any(|l| l.contains("session ended by an operator")), "{logged:?}");
}
