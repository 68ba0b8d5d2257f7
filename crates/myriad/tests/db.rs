//! Issue 29 through the binary: a damaged database is refused by every command that
//! would write to it (untouched), a backup taken while a server with bots runs restores
//! whole into a fresh data directory, and the offline account commands round-trip.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use myriad_store::{Account, HashCost, PlayerState, Store, StoreConfig, StoredShape, WorldBounds, now_ms};

/// Cheap password hashes for the accounts the commands create (`--set` keys).
const FAST_HASH: [&str; 6] = ["--set", "hash_memory_kib=64", "--set", "hash_passes=1", "--set", "hash_lanes=1"];

fn myriad_cmd(dir: &Path, args: &[&str]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_myriad"));
    cmd.args(args).arg("--data-dir").arg(dir).args(FAST_HASH).env("RUST_LOG", "warn");
    cmd
}

/// Runs a command to its end, or kills it after `limit` (a command that should have
/// refused to start must not hang the test).
fn run(dir: &Path, args: &[&str], stdin: &str, limit: Duration) -> Output {
    let mut child = myriad_cmd(dir, args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running myriad");
    child.stdin.take().unwrap().write_all(stdin.as_bytes()).unwrap();
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > limit {
            child.kill().unwrap();
            let out = child.wait_with_output().unwrap();
            panic!("myriad {args:?} still ran after {limit:?}: {}", text(&out));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

fn ok(dir: &Path, args: &[&str], stdin: &str) -> String {
    let out = run(dir, args, stdin, Duration::from_secs(60));
    assert!(out.status.success(), "myriad {args:?} failed: {}", text(&out));
    text(&out)
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap()
}

fn store_config(dir: &Path) -> StoreConfig {
    StoreConfig::sqlite(dir).hash_cost(HashCost::INSECURE_FAST)
}

#[test]
fn a_damaged_database_is_refused_by_every_writer_and_left_untouched() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    // Enough rows for a file of many pages.
    rt().block_on(async {
        let store = Store::open(&store_config(&dir)).await.unwrap();
        store.seed_users(400).await.unwrap();
        let map = store
            .create_map(&myriad_store::NewMap {
                name: "m".into(),
                heightmap: myriad_store::Heightmap::None,
                max_height: 10.0,
                bounds: myriad_store::WorldBounds { min: [0.0; 3], max: [100.0, 50.0, 100.0] },
            })
            .await
            .unwrap();
        let mut states = Vec::new();
        for i in 0..400 {
            let user = store.find_user(&format!("user{i}")).await.unwrap().unwrap();
            states.push(PlayerState::new(user.id, map, StoredShape::Sphere { radius: 0.5 }, [i as f32, 1.0, 2.0]));
        }
        store.save_player_states(&states).await.unwrap();
        store.close().await;
    });
    let file = dir.join("myriad.db");
    let len = std::fs::metadata(&file).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&file).unwrap().set_len(len / 2).unwrap();
    let before = std::fs::read(&file).unwrap();

    let png = tmp.path().join("hills.png");
    let at = myriad_core::terrain::TerrainPlacement {
        origin_x: 0.0,
        origin_z: 0.0,
        extent_x: 1.0,
        extent_z: 1.0,
        base_y: 0.0,
    };
    myriad_core::Terrain::generate(5, 9, 9, 1.0, at).unwrap().write_png(&png).unwrap();
    let png = png.display().to_string();
    let limit = Duration::from_secs(60);
    for (args, stdin) in [
        (vec!["serve", "--login", "127.0.0.1:0", "--udp", "127.0.0.1:0", "--npcs", "10"], ""),
        (vec!["demo", "--bots", "1", "--duration", "2", "--npcs", "10"], ""),
        (vec!["user", "add", "bob"], "secret\n"),
        (vec!["user", "seed", "--count", "2"], ""),
        (vec!["user", "ban", "user1", "--reason", "x"], ""),
        (vec!["map", "import", &png, "--max-height", "10"], ""),
        (vec!["db", "check"], ""),
    ] {
        let out = run(&dir, &args, stdin, limit);
        let said = text(&out);
        assert!(!out.status.success(), "myriad {args:?} accepted a damaged database: {said}");
        assert!(said.contains(&file.display().to_string()), "myriad {args:?} names the file: {said}");
        if args[0] != "db" {
            assert!(said.contains("myriad db restore"), "myriad {args:?} says how to restore: {said}");
        }
        assert_eq!(std::fs::read(&file).unwrap(), before, "myriad {args:?} wrote nothing");
    }
    let full = run(&dir, &["db", "check", "--full"], "", limit);
    assert!(!full.status.success(), "{}", text(&full));
}

/// A `myriad demo` child whose standard error is read line by line.
struct Demo {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl Demo {
    fn start(dir: &Path, bots: usize, seconds: u32) -> Demo {
        let bots = bots.to_string();
        let seconds = seconds.to_string();
        let args = ["demo", "--bots", &bots, "--duration", &seconds, "--npcs", "50", "--persist-ms", "100"];
        let mut child = myriad_cmd(dir, &args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("running myriad demo");
        let (tx, lines) = mpsc::channel();
        let stderr = child.stderr.take().unwrap();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Demo { child, lines }
    }

    /// Waits for a status line with every bot connected.
    fn wait_for(&self, needle: &str, limit: Duration) {
        let end = Instant::now() + limit;
        let mut seen = Vec::new();
        while Instant::now() < end {
            match self.lines.recv_timeout(Duration::from_millis(200)) {
                Ok(line) if line.contains(needle) => return,
                Ok(line) => seen.push(line),
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
        panic!("no {needle:?} from the demo in {limit:?}; it said:\n{}", seen.join("\n"));
    }
}

impl Drop for Demo {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
        }
        let _ = self.child.wait();
    }
}

/// Bots playing while the backup is taken.
const BACKUP_BOTS: usize = 100;

/// Players' top walking speed (the server's default `player_speed`, which the demo
/// keeps), in units per second.
const PLAYER_SPEED: f32 = 5.0;

/// Every account and the one saved position of each, from a stopped server's database.
fn accounts_and_positions(dir: &Path) -> (Vec<Account>, Vec<WorldBounds>, Vec<PlayerState>) {
    rt().block_on(async {
        let store = Store::open(&store_config(dir)).await.unwrap();
        let accounts = store.list_accounts(None, 10_000).await.unwrap();
        let maps = store.list_maps().await.unwrap();
        assert_eq!(maps.len(), 1, "the demo's map");
        let states = store.list_player_states(maps[0].id).await.unwrap();
        store.close().await;
        (accounts, maps.iter().map(|m| m.bounds).collect(), states)
    })
}

#[test]
fn a_backup_taken_while_bots_play_restores_every_account_and_position() {
    let started = Instant::now();
    let tmp = tempfile::tempdir().unwrap();
    let live = tmp.path().join("live");
    // A long cap: the test ends the demo with Ctrl-C once the backup is taken.
    let mut demo = Demo::start(&live, BACKUP_BOTS, 300);
    demo.wait_for(&format!("bots {BACKUP_BOTS}/{BACKUP_BOTS}"), Duration::from_secs(90));
    let joined = started.elapsed();
    // Let a few checkpoints (every 100 ms) land, then back up while the bots move.
    std::thread::sleep(Duration::from_millis(500));
    let backup = tmp.path().join("live-backup.db");
    let backup_started_ms = now_ms();
    let said = ok(&live, &["db", "backup", &backup.display().to_string()], "");
    let backup_ended_ms = now_ms();
    assert!(said.contains("backed up to"), "{said}");
    // The server holds the database: a restore into it is refused while it runs.
    let refused = run(&live, &["db", "restore", &backup.display().to_string()], "", Duration::from_secs(60));
    assert!(!refused.status.success() && text(&refused).contains("in use"), "{}", text(&refused));
    let refused = run(&live, &["db", "backup", &backup.display().to_string()], "", Duration::from_secs(60));
    assert!(!refused.status.success() && text(&refused).contains("--force"), "{}", text(&refused));
    // Ctrl-C: the bots say goodbye, the server saves every position and stops.
    assert_eq!(unsafe { libc::kill(demo.child.id() as i32, libc::SIGINT) }, 0);
    let status = demo.child.wait().unwrap();
    assert!(status.success(), "the demo ended well");

    let fresh = tmp.path().join("fresh");
    let said = ok(&fresh, &["db", "restore", &backup.display().to_string()], "");
    assert!(said.contains("restored"), "{said}");
    let said = ok(&fresh, &["db", "check", "--full"], "");
    assert!(said.contains("intact"), "{said}");

    // Every account is there as the server left it (the bots' accounts were made before
    // the server started; playing changes none of them).
    let (live_accounts, _, live_states) = accounts_and_positions(&live);
    let (accounts, bounds, states) = accounts_and_positions(&fresh);
    assert_eq!(live_accounts.len(), BACKUP_BOTS);
    assert_eq!(accounts, live_accounts, "the backup's accounts");
    rt().block_on(async {
        let restored = Store::open(&store_config(&fresh)).await.unwrap();
        for i in 0..BACKUP_BOTS {
            let name = format!("user{i}");
            restored.check_credentials(&name, &format!("password{i}")).await.unwrap_or_else(|e| panic!("{name}: {e}"));
        }
        restored.close().await;
    });

    // Every bot's position is there, saved while it played: the server went on saving
    // after the backup, so the live one is the same or later, and no farther from the
    // backup's than a player walks in the time between the two (twice the top speed,
    // for pushes from others, plus a unit for rounding and falls).
    assert_eq!(live_states.len(), BACKUP_BOTS, "the live database has every bot's position");
    assert_eq!(states.len(), BACKUP_BOTS, "the backup has every bot's position");
    let b = &bounds[0];
    let mut same = 0;
    for (state, last) in states.iter().zip(&live_states) {
        assert_eq!(state.user_id, last.user_id);
        let account = accounts.iter().find(|a| a.id == state.user_id);
        assert!(account.is_some(), "the position of user id {:?} has an account", state.user_id);
        assert!(
            (0..3).all(|k| state.position[k] >= b.min[k] - 1.0 && state.position[k] <= b.max[k] + 1.0),
            "{state:?} is in the map"
        );
        assert!(state.updated_at_ms <= backup_ended_ms, "{state:?} was saved before the backup ended");
        assert!(state.updated_at_ms <= last.updated_at_ms, "{state:?} is not later than the server's last {last:?}");
        let walked = f32::hypot(last.position[0] - state.position[0], last.position[2] - state.position[2]);
        let seconds = (last.updated_at_ms - state.updated_at_ms) as f32 / 1000.0;
        assert!(
            walked <= 2.0 * PLAYER_SPEED * seconds + 1.0,
            "{:?} moved {walked} units in {seconds} s between the backup and the end",
            state.user_id
        );
        same += usize::from(state.position == last.position && state.updated_at_ms == last.updated_at_ms);
    }
    // The backup is of the running server, not of its end: the bots moved on after it.
    assert!(same < BACKUP_BOTS, "every position in the backup is the final one");
    let newest = states.iter().map(|s| s.updated_at_ms).max().unwrap();
    assert!(newest >= backup_started_ms - 2_000, "the backup holds the checkpoints of its time ({newest})");
    eprintln!(
        "{BACKUP_BOTS} bots joined in {joined:?}; the backup took {} ms; {same} positions unchanged since; test {:?}",
        backup_ended_ms - backup_started_ms,
        started.elapsed()
    );
}

#[test]
fn offline_account_commands_round_trip() {
    let tmp = tempfile::tempdir().unwrap();
    let dir: PathBuf = tmp.path().join("data");
    ok(&dir, &["user", "add", "alice"], "first pw\n");
    ok(&dir, &["user", "add", "bob"], "bob pw\n");
    let said = ok(&dir, &["user", "disable", "alice"], "");
    assert!(said.contains("disabled alice"), "{said}");
    let list = ok(&dir, &["user", "list"], "");
    let line = |list: &str, name: &str| list.lines().find(|l| l.contains(name)).map(str::to_owned).unwrap();
    assert!(line(&list, "alice").ends_with("disabled"), "{list}");
    assert!(line(&list, "bob").ends_with("active"), "{list}");
    ok(&dir, &["user", "enable", "alice"], "");
    ok(&dir, &["user", "ban", "bob", "--reason", "spamming chat", "--until", "2999-01-01T00:00:00Z"], "");
    let list = ok(&dir, &["user", "list"], "");
    assert!(line(&list, "alice").ends_with("active"), "{list}");
    assert!(line(&list, "bob").contains("banned (spamming chat) until 2999-01-01T00:00:00Z"), "{list}");
    let past = run(
        &dir,
        &["user", "ban", "bob", "--reason", "x", "--until", "2001-01-01T00:00:00Z"],
        "",
        Duration::from_secs(60),
    );
    assert!(!past.status.success() && text(&past).contains("not in the future"), "{}", text(&past));
    let bad = run(&dir, &["user", "ban", "bob", "--reason", "x", "--until", "soon"], "", Duration::from_secs(60));
    assert!(!bad.status.success() && text(&bad).contains("RFC 3339"), "{}", text(&bad));

    let said = ok(&dir, &["user", "passwd", "alice"], "second pw\n");
    assert!(!said.contains("second pw"), "the password is never echoed: {said}");
    rt().block_on(async {
        let store = Store::open(&store_config(&dir)).await.unwrap();
        store.check_credentials("alice", "second pw").await.expect("the new password works");
        assert!(store.check_credentials("alice", "first pw").await.is_err());
        assert!(matches!(
            store.check_credentials("bob", "bob pw").await,
            Err(myriad_store::StoreError::AccountBanned { until_ms: Some(_) })
        ));
        store.close().await;
    });
    ok(&dir, &["user", "unban", "bob"], "");
    ok(&dir, &["user", "delete", "alice"], "");
    let list = ok(&dir, &["user", "list"], "");
    assert!(!list.contains("alice") && line(&list, "bob").ends_with("active"), "{list}");
    let gone = run(&dir, &["user", "disable", "alice"], "", Duration::from_secs(60));
    assert!(!gone.status.success() && text(&gone).contains("not found"), "{}", text(&gone));
    rt().block_on(async {
        let store = Store::open(&store_config(&dir)).await.unwrap();
        store.check_credentials("bob", "bob pw").await.expect("bob is unbanned");
        store.close().await;
    });
}

/// The parts of `mysql://user:password@host:port/db` the mariadb tools take as flags.
struct MariaDb {
    user: String,
    password: String,
    host: String,
    port: String,
    /// The URL up to (without) the database name.
    base: String,
}

impl MariaDb {
    fn parse(url: &str) -> MariaDb {
        let rest = url.strip_prefix("mysql://").or_else(|| url.strip_prefix("mariadb://")).expect("a mysql:// URL");
        let authority = rest.split(['/', '?']).next().unwrap();
        let (userinfo, host_port) = authority.rsplit_once('@').expect("MYSQL_URL names a user");
        let (user, password) = userinfo.split_once(':').unwrap_or((userinfo, ""));
        let (host, port) = host_port.split_once(':').unwrap_or((host_port, "3306"));
        MariaDb {
            user: user.into(),
            password: password.into(),
            host: host.into(),
            port: port.into(),
            base: format!("mysql://{authority}"),
        }
    }

    /// A mariadb tool with the connection flags (the password through the environment,
    /// not the command line).
    fn tool(&self, name: &str) -> Command {
        let mut cmd = Command::new(name);
        cmd.args(["-h", &self.host, "-P", &self.port, "-u", &self.user]).env("MYSQL_PWD", &self.password);
        cmd
    }

    fn sql(&self, statement: &str) {
        let out = self.tool("mariadb").args(["-e", statement]).output().expect("running mariadb");
        assert!(out.status.success(), "{statement}: {}", text(&out));
    }
}

#[test]
fn a_mariadb_dump_restores_and_passes_db_check() {
    let Some(url) = myriad_testenv::mysql_url() else { return };
    if Command::new("mariadb-dump").arg("--version").output().is_err() {
        eprintln!("SKIPPED: mariadb-dump is not installed");
        return;
    }
    let db = MariaDb::parse(&url);
    let (src, dst) =
        (format!("myriad_dump_src_{}", std::process::id()), format!("myriad_dump_dst_{}", std::process::id()));
    let create = |name: &str| {
        db.sql(&format!(
            "DROP DATABASE IF EXISTS {name}; CREATE DATABASE {name} CHARACTER SET utf8mb4 COLLATE utf8mb4_unicode_ci"
        ))
    };
    create(&src);
    let tmp = tempfile::tempdir().unwrap();
    let src_url = format!("{}/{src}", db.base);
    let dst_url = format!("{}/{dst}", db.base);
    ok(tmp.path(), &["user", "seed", "--count", "3", "--database-url", &src_url], "");
    ok(tmp.path(), &["user", "ban", "user1", "--reason", "dumped", "--database-url", &src_url], "");
    // The command docs/server.md gives.
    let dump = db
        .tool("mariadb-dump")
        .args(["--single-transaction", "--routines", "--triggers", &src])
        .output()
        .expect("running mariadb-dump");
    assert!(dump.status.success(), "{}", String::from_utf8_lossy(&dump.stderr));
    create(&dst);
    let mut restore = db.tool("mariadb").arg(&dst).stdin(Stdio::piped()).spawn().expect("running mariadb");
    restore.stdin.take().unwrap().write_all(&dump.stdout).unwrap();
    assert!(restore.wait().unwrap().success(), "the dump restores");
    let said = ok(tmp.path(), &["db", "check", "--full", "--database-url", &dst_url], "");
    assert!(
        said.contains("intact") && said.contains("users") && !said.contains(&format!(":{}@", db.password)),
        "{said}"
    );
    let list = ok(tmp.path(), &["user", "list", "--database-url", &dst_url], "");
    assert!(list.lines().any(|l| l.contains("user1") && l.contains("banned (dumped)")), "{list}");
    assert_eq!(list.lines().filter(|l| l.contains("user")).count(), 3, "{list}");
    let refused = run(tmp.path(), &["db", "backup", "x.db", "--database-url", &dst_url], "", Duration::from_secs(60));
    assert!(!refused.status.success() && text(&refused).contains("mariadb-dump"), "{}", text(&refused));
    db.sql(&format!("DROP DATABASE {src}; DROP DATABASE {dst}"));
}
