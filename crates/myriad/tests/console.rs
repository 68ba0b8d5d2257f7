//! Issue 29's web console in a real browser: headless Chromium loads the console that
//! `myriad serve --admin` ships, against the server with bots playing; a screenshot of
//! the map is checked against the map data the page drew, the players table lists the
//! bots, a click on a Kick button ends a player's session with `Kicked` (the test's own
//! player, through the client library, which then logs in again), and a ban through the
//! Ban… dialog (a reason and an end time) ends a bot's session with `Banned`, its next
//! login is refused as banned, and the audit shows the ban. The map draws a gateway's
//! zone cuts where the API would give them.
//!
//! Chromium is Debian's package (`apt-get install chromium`, or `MYRIAD_CHROMIUM=path`);
//! without it the test skips with a message, unless `MYRIAD_REQUIRE_CHROMIUM=1` (CI).

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::{Killed, collect_stderr, free_ports};
use headless_chrome::protocol::cdp::Page::CaptureScreenshotFormatOption;
use headless_chrome::{Browser, LaunchOptions, Tab};
use myriad_client::{ClientConfig, ClientError, Connection, Credentials, SessionEnd, Trust};
use myriad_protocol::DisconnectReason;
use myriad_protocol::login::RefusalReason;

/// Cheap password hashes for the accounts the commands create (`--set` keys).
const FAST_HASH: [&str; 6] = ["--set", "hash_memory_kib=64", "--set", "hash_passes=1", "--set", "hash_lanes=1"];
/// Bots of `myriad bots` (`user0` …); the test's own player is the next account.
const BOTS: usize = 4;
/// The browser's window: the page's two columns side by side.
const WINDOW: (u32, u32) = (1280, 860);

/// Chromium's path, or `None` (the test skips) where it is missing and not required.
fn chromium() -> Option<PathBuf> {
    let path = std::env::var_os("MYRIAD_CHROMIUM").map_or_else(|| PathBuf::from("/usr/bin/chromium"), PathBuf::from);
    if path.is_file() {
        return Some(path);
    }
    let why = format!("no Chromium at {} (apt-get install chromium, or set MYRIAD_CHROMIUM)", path.display());
    assert!(std::env::var("MYRIAD_REQUIRE_CHROMIUM").as_deref() != Ok("1"), "MYRIAD_REQUIRE_CHROMIUM=1: {why}");
    eprintln!("SKIPPED: {why}");
    None
}

fn myriad(dir: &Path, args: &[&str]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_myriad"));
    cmd.args(args).arg("--data-dir").arg(dir).args(FAST_HASH).env("RUST_LOG", "info");
    cmd
}

/// Waits until `addr` accepts TCP connections.
fn wait_listening(addr: SocketAddr, what: &str) {
    let end = Instant::now() + Duration::from_secs(60);
    while std::net::TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_err() {
        assert!(Instant::now() < end, "{what} never listened on {addr}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// What the test's own player saw.
#[derive(Debug)]
enum Own {
    /// Logged in (again), playing as this entity.
    Playing(u64),
    /// The server ended the session.
    Ended(SessionEnd),
    /// The server refused its login (the player stops).
    Refused(RefusalReason),
    /// Logging in or playing failed.
    Failed(String),
}

/// The test's own player `user<index>` on a thread: plays (walks in a circle) until the
/// server ends its session, says why, logs in again and plays on, until `stop` or until
/// a login is refused.
fn own_player(login: SocketAddr, cert: PathBuf, index: usize, stop: Arc<AtomicBool>) -> mpsc::Receiver<Own> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let result: Result<(), String> = rt.block_on(async {
            let trust = Trust::pin_file(&cert).map_err(|e| e.to_string())?;
            let config = ClientConfig::new(login, &trust).map_err(|e| e.to_string())?;
            let mut conn =
                Connection::connect(config, Credentials::test_user(index)).await.map_err(|e| e.to_string())?;
            let _ = tx.send(Own::Playing(conn.entity_id()));
            let mut frame = 0u32;
            while !stop.load(Ordering::Relaxed) {
                if let Some(end) = conn.ended() {
                    let _ = tx.send(Own::Ended(end));
                    match conn.reconnect().await {
                        Ok(()) => {
                            let _ = tx.send(Own::Playing(conn.entity_id()));
                        }
                        Err(ClientError::Refused { reason, .. }) => {
                            let _ = tx.send(Own::Refused(reason));
                            return Ok(());
                        }
                        Err(e) => return Err(e.to_string()),
                    }
                }
                frame = frame.wrapping_add(1);
                // Forward, then right, … : a small circle.
                conn.send_action([1, 8, 2, 4][(frame / 30 % 4) as usize]).await.map_err(|e| e.to_string())?;
                conn.recv(Duration::from_millis(30)).await.map_err(|e| e.to_string())?;
            }
            conn.disconnect().await.map_err(|e| e.to_string())
        });
        if let Err(e) = result {
            let _ = tx.send(Own::Failed(e));
        }
    });
    rx
}

fn next(rx: &mpsc::Receiver<Own>, limit: Duration) -> Own {
    match rx.recv_timeout(limit) {
        Ok(Own::Failed(e)) => panic!("the test's player failed: {e}"),
        Ok(said) => said,
        Err(e) => panic!("the test's player said nothing in {limit:?}: {e}"),
    }
}

/// Evaluates `expression` (which gives a string) in the page.
fn eval(tab: &Tab, expression: &str) -> String {
    let v = tab.evaluate(expression, true).unwrap_or_else(|e| panic!("{expression}: {e}"));
    match v.value {
        Some(serde_json::Value::String(s)) => s,
        other => panic!("{expression} gave {other:?} ({:?})", v.description),
    }
}

/// Polls `check` on the page until it holds.
fn wait_until(tab: &Tab, what: &str, limit: Duration, check: &str) {
    assert!(holds_within(tab, limit, check), "{what}: not in {limit:?}; the page says {}", page_text(tab));
}

/// Whether `check` holds on the page within `limit` (polled).
fn holds_within(tab: &Tab, limit: Duration, check: &str) -> bool {
    let end = Instant::now() + limit;
    loop {
        if eval(tab, &format!("String(Boolean({check}))")) == "true" {
            return true;
        }
        if Instant::now() >= end {
            return false;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn page_text(tab: &Tab) -> String {
    eval(tab, "document.body.innerText.slice(0, 2000)")
}

/// Clicks the middle of the element `selector` with the mouse (input events, as a
/// person's click).
fn click(tab: &Tab, selector: &str) {
    let at = eval(
        tab,
        &format!(
            "(() => {{ const e = document.querySelector('{selector}'); e.scrollIntoView({{block: 'center'}}); \
             const r = e.getBoundingClientRect(); return JSON.stringify([r.left + r.width / 2, r.top + r.height / 2]); }})()"
        ),
    );
    let [x, y]: [f64; 2] = serde_json::from_str(&at).unwrap();
    tab.click_point(headless_chrome::browser::tab::point::Point { x, y }).unwrap();
}

/// The accounts in the players table.
fn table_accounts(tab: &Tab) -> Vec<String> {
    let json =
        eval(tab, "JSON.stringify([...document.querySelectorAll('#players tbody tr')].map(tr => tr.dataset.account))");
    serde_json::from_str(&json).unwrap()
}

#[test]
fn the_console_shows_the_world_kicks_and_bans_players() {
    let Some(chrome) = chromium() else { return };
    let started = Instant::now();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    let seeded = myriad(&dir, &["user", "seed", "--count", &(BOTS + 1).to_string()]).output().unwrap();
    assert!(seeded.status.success(), "{}", String::from_utf8_lossy(&seeded.stderr));

    let port = free_ports(3);
    let (login, udp, admin) = (format!("127.0.0.1:{port}"), format!("127.0.0.1:{}", port + 1), port + 2);
    let admin_addr: SocketAddr = format!("127.0.0.1:{admin}").parse().unwrap();
    let mut serve = myriad(&dir, &["serve", "--login", &login, "--udp", &udp, "--npcs", "300"])
        .args(["--admin", &admin_addr.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let _server_log = collect_stderr(&mut serve);
    let _serve = Killed(serve);
    wait_listening(login.parse().unwrap(), "the login service");
    wait_listening(admin_addr, "the admin listener");
    let token = std::fs::read_to_string(dir.join("admin.token")).unwrap().trim().to_string();
    let cert = dir.join("tls-cert.pem");
    let cert_arg = cert.display().to_string();
    let bots = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(["bots", "--server", &login, "--count", &BOTS.to_string(), "--cert", &cert_arg, "--json"])
        .args(["--behaviour", "circle", "--every", "1"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let _bots = Killed(bots);
    let stop = Arc::new(AtomicBool::new(false));
    let own = own_player(login.parse().unwrap(), cert.clone(), BOTS, stop.clone());
    let own_name = format!("user{BOTS}");
    let Own::Playing(entity) = next(&own, Duration::from_secs(30)) else { panic!("the test's player did not log in") };

    let browser = Browser::new(
        LaunchOptions::default_builder()
            .path(Some(chrome))
            .headless(true)
            // Root in a container has no user namespaces for Chromium's sandbox.
            .sandbox(false)
            .window_size(Some(WINDOW))
            .idle_browser_timeout(Duration::from_secs(120))
            .build()
            .unwrap(),
    )
    .expect("Chromium starts");

    // A wrong token: the page asks for one; the right one through the input works.
    let tab = browser.new_tab().unwrap();
    tab.navigate_to(&format!("http://{admin_addr}/#token=00")).unwrap().wait_until_navigated().unwrap();
    wait_until(&tab, "the token form", Duration::from_secs(20), "!document.getElementById('token-form').hidden");
    assert!(eval(&tab, "document.getElementById('error').textContent").contains("401"), "{}", page_text(&tab));
    tab.find_element("#token-input").unwrap().type_into(&token).unwrap();
    tab.press_key("Enter").unwrap();
    wait_until(&tab, "a table after the token", Duration::from_secs(20), "document.querySelector('#players tbody tr')");
    tab.close(false).unwrap();

    // The address `myriad admin console-url` prints.
    let tab = browser.new_tab().unwrap();
    tab.navigate_to(&format!("http://{admin_addr}/#token={token}")).unwrap().wait_until_navigated().unwrap();
    let everyone: Vec<String> = (0..=BOTS).map(|i| format!("user{i}")).collect();
    let all_in_table = format!(
        "{}.every(a => document.querySelector(`#players tbody tr[data-account=\"${{a}}\"]`))",
        serde_json::to_string(&everyone).unwrap()
    );
    wait_until(&tab, "every player in the table", Duration::from_secs(30), &all_in_table);
    assert_eq!(eval(&tab, "location.href"), format!("http://{admin_addr}/"), "the token leaves the address");
    assert_eq!(eval(&tab, "sessionStorage.getItem('myriad-admin-token')"), token);
    assert_eq!(table_accounts(&tab), everyone, "the table lists the players in order");
    let own_row = format!("#players tbody tr[data-account=\"{own_name}\"]");
    let row = eval(&tab, &format!("document.querySelector('{own_row}').innerText"));
    assert!(row.contains(&entity.to_string()), "{own_name}'s row shows its entity {entity}: {row}");
    // A few samples in the stage chart, then the picture, with the map data it shows
    // (read before and after: a refresh in between takes another).
    wait_until(&tab, "the stage chart", Duration::from_secs(20), "state.history.length >= 3");
    let (shot, drawn) = loop {
        let before = eval(&tab, "JSON.stringify(state.map)");
        let shot = tab.capture_screenshot(CaptureScreenshotFormatOption::Png, None, None, true).unwrap();
        if eval(&tab, "JSON.stringify(state.map)") == before {
            break (shot, serde_json::from_str::<serde_json::Value>(&before).unwrap());
        }
    };
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("console.png");
    std::fs::write(&out, &shot).unwrap();
    eprintln!("screenshot: {} ({} bytes)", out.display(), shot.len());
    check_map(&shot, &tab, &drawn);
    check_stage_chart(&tab);

    // Kick through the page: the player's session ends with Kicked; it logs in again.
    // The page redraws its table every second, and on a loaded machine a redraw between
    // finding the button and the click can move it (a column widens): a click that
    // brought no answer within 10 s is made again, as a person would; a click that was
    // answered is never repeated (the kick is checked below, once, in the audit).
    let kicked = format!("document.getElementById('notice').textContent === 'Kicked {own_name}.'");
    let mut clicks = 0;
    while clicks < 3 {
        click(&tab, &format!("button.kick[data-account=\"{own_name}\"]"));
        clicks += 1;
        if holds_within(&tab, Duration::from_secs(10), &kicked) {
            break;
        }
        eprintln!("the click on Kick brought no answer in 10 s; clicking again");
    }
    match next(&own, Duration::from_secs(20)) {
        Own::Ended(SessionEnd::Disconnected(DisconnectReason::Kicked)) => {}
        other => panic!("after the click the session went on or ended otherwise: {other:?}"),
    }
    wait_until(&tab, "the notice", Duration::from_secs(10), &kicked);
    let Own::Playing(again) = next(&own, Duration::from_secs(30)) else {
        panic!("the kicked player could not log in again")
    };
    wait_until(
        &tab,
        "the player back in the table",
        Duration::from_secs(20),
        &format!(
            "document.querySelector('{own_row}') && document.querySelector('{own_row}').innerText.includes('{again}')"
        ),
    );
    let audit: serde_json::Value =
        serde_json::from_str(&eval(&tab, "(async () => JSON.stringify(await api('GET', '/api/audit?limit=20')))()"))
            .unwrap();
    let kick = audit.as_array().unwrap().iter().find(|e| e["action"] == "kick" && e["target"] == own_name.as_str());
    assert!(kick.is_some_and(|e| e["ok"] == true), "the kick is in the audit: {audit}");
    assert_eq!(
        eval(&tab, "document.getElementById('error').hidden ? '' : document.getElementById('error').textContent"),
        ""
    );

    ban_through_the_dialog(&tab, &own, &own_name);
    check_cut_lines(&tab);
    stop.store(true, Ordering::Relaxed);
    eprintln!("console test: {:?}", started.elapsed());
}

/// Ban through the page: the Ban… button opens the dialog, which takes a reason and an
/// end a day ahead (local time, as the picker shows it); the player's session ends with
/// `Banned`, its next login is refused as banned, it leaves the table, and the audit
/// shows the ban with its reason and end.
fn ban_through_the_dialog(tab: &Tab, own: &mpsc::Receiver<Own>, account: &str) {
    click(tab, &format!("button.ban[data-account=\"{account}\"]"));
    wait_until(tab, "the ban dialog", Duration::from_secs(10), "document.getElementById('ban-dialog').open");
    assert_eq!(eval(tab, "document.getElementById('ban-account').textContent"), account);
    tab.find_element("#ban-reason").unwrap().type_into("griefing at spawn").unwrap();
    // A day ahead in the picker's local time (`YYYY-MM-DDTHH:MM`), and the instant it
    // names, as the page will send it.
    let until = eval(
        tab,
        "(() => { const d = new Date(Date.now() + 86400000); d.setSeconds(0, 0); \
         const p = (n) => String(n).padStart(2, '0'); \
         document.getElementById('ban-until').value = `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())}T${p(d.getHours())}:${p(d.getMinutes())}`; \
         return d.toISOString().replace(/\\.\\d{3}Z$/, 'Z'); })()",
    );
    click(tab, "#ban-confirm");
    match next(own, Duration::from_secs(20)) {
        Own::Ended(SessionEnd::Disconnected(DisconnectReason::Banned)) => {}
        other => panic!("after the ban the session went on or ended otherwise: {other:?}"),
    }
    match next(own, Duration::from_secs(30)) {
        Own::Refused(RefusalReason::Banned) => {}
        other => panic!("the banned player's login was not refused as banned: {other:?}"),
    }
    wait_until(
        tab,
        "the ban's notice",
        Duration::from_secs(10),
        &format!("document.getElementById('notice').textContent === 'Banned {account} until {until} and kicked it.'"),
    );
    assert_eq!(eval(tab, "String(document.getElementById('ban-dialog').open)"), "false", "the dialog closed");
    wait_until(
        tab,
        "the banned player out of the table",
        Duration::from_secs(20),
        &format!("!document.querySelector('#players tbody tr[data-account=\"{account}\"]')"),
    );
    let audit: serde_json::Value =
        serde_json::from_str(&eval(tab, "(async () => JSON.stringify(await api('GET', '/api/audit?limit=20')))()"))
            .unwrap();
    let ban = audit.as_array().unwrap().iter().find(|e| e["action"] == "ban" && e["target"] == account);
    let detail = format!("griefing at spawn (until {until})");
    assert!(
        ban.is_some_and(|e| e["ok"] == true && e["detail"] == detail.as_str() && e["actor"] == "token:console"),
        "the ban is in the audit as {detail:?}: {audit}"
    );
    let accounts: serde_json::Value =
        serde_json::from_str(&eval(tab, "(async () => JSON.stringify(await api('GET', '/api/accounts')))()")).unwrap();
    let row = accounts.as_array().unwrap().iter().find(|a| a["account"] == account).unwrap();
    assert_eq!((&row["banned"], &row["banned_until"]), (&serde_json::json!(true), &serde_json::json!(until)), "{row}");
}

/// The map draws zone cuts (as a gateway's `/api/map` gives them: edges included) as
/// dashed red lines at the inner cuts, and none at the world's edges: drawn by the
/// page's own `drawMap` on a canvas of the map's size, from the last map with cuts
/// added. Each line is counted away from where the other crosses it.
fn check_cut_lines(tab: &Tab) {
    let columns: serde_json::Value = serde_json::from_str(&eval(
        tab,
        "(() => { const m = JSON.parse(JSON.stringify(state.map)); const b = m.bounds; \
         const xCut = b.min_x + (b.max_x - b.min_x) * 0.3, zCut = b.min_z + (b.max_z - b.min_z) * 0.6; \
         m.cuts = {xs: [b.min_x, xCut, b.max_x], zs: [b.min_z, zCut, b.max_z], run: 1, zone_tick: 90, since_tick: 60}; \
         m.players = []; \
         const c = document.createElement('canvas'); c.width = $('map').width; c.height = $('map').height; \
         drawMap(c, m); \
         const w = b.max_x - b.min_x, h = b.max_z - b.min_z; \
         const scale = Math.min((c.width - 2) / w, (c.height - 2) / h); \
         const ox = (c.width - w * scale) / 2, oy = (c.height - h * scale) / 2; \
         const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
         const red = (x, y) => { const i = (Math.floor(y) * c.width + Math.floor(x)) * 4; return d[i] > 200 && d[i + 1] < 120 && d[i + 2] < 120; }; \
         const px = ox + (xCut - b.min_x) * scale, pz = oy + (b.max_z - zCut) * scale; \
         const column = (x) => { let n = 0; for (let y = oy + 1; y < oy + h * scale - 1; y++) if (Math.abs(y - pz) > 3 && red(x, y)) n++; return n; }; \
         const row = (y) => { let n = 0; for (let x = ox + 1; x < ox + w * scale - 1; x++) if (Math.abs(x - px) > 3 && red(x, y)) n++; return n; }; \
         return JSON.stringify({cut_x: column(px), beside_x: column(px + 12), cut_z: row(pz), beside_z: row(pz + 12), \
           edge: column(ox + 0.5) + row(oy + 0.5), length: Math.min(w, h) * scale}); })()",
    ))
    .unwrap();
    let n = |k: &str| columns[k].as_f64().unwrap();
    // Dashes of 6 on, 4 off: well over a third of the line's pixels are wholly red (the
    // ends of a dash may be blended).
    assert!(n("cut_x") > n("length") * 0.35 && n("cut_z") > n("length") * 0.35, "the cuts are drawn: {columns}");
    assert_eq!((n("beside_x"), n("beside_z"), n("edge")), (0.0, 0.0, 0.0), "nothing red off the cuts: {columns}");
}

/// The map canvas in the screenshot against the data it was drawn from: a player dot at
/// every player, and every cell away from them in the colour its NPC density gives.
fn check_map(shot: &[u8], tab: &Tab, map: &serde_json::Value) {
    let (width, pixels) = decode_rgb(shot);
    let rect: serde_json::Value = serde_json::from_str(&eval(
        tab,
        "(() => { const r = document.getElementById('map').getBoundingClientRect(); \
         return JSON.stringify({x: r.left, y: r.top, w: r.width, cw: document.getElementById('map').width, \
         dpr: devicePixelRatio}); })()",
    ))
    .unwrap();
    let f = |k: &str| rect[k].as_f64().unwrap();
    let (dpr, css_per_px) = (f("dpr"), f("w") / f("cw"));
    let b = &map["bounds"];
    let g = |k: &str| b[k].as_f64().unwrap();
    let (w, h) = (g("max_x") - g("min_x"), g("max_z") - g("min_z"));
    let canvas = f("cw");
    let scale = ((canvas - 2.0) / w).min((canvas - 2.0) / h);
    let (ox, oy) = ((canvas - w * scale) / 2.0, (canvas - h * scale) / 2.0);
    // Canvas pixel -> screenshot pixel.
    let pixel = |cx: f64, cy: f64| {
        let (sx, sy) = ((f("x") + cx * css_per_px) * dpr, (f("y") + cy * css_per_px) * dpr);
        let (sx, sy) = (sx.floor() as usize, sy.floor() as usize);
        pixels[(sy * width + sx) * 3..][..3].try_into().unwrap()
    };
    assert!(map["cuts"].is_null(), "a server alone has no zone cuts: {}", map["cuts"]);
    let players = map["players"].as_array().unwrap();
    assert_eq!(players.len(), BOTS + 1, "the map shows every player: {players:?}");
    let is_player = |[r, g, b]: [u8; 3]| r > 200 && g > 170 && b < 120;
    for p in players {
        let (cx, cy) = (
            ox + (p["x"].as_f64().unwrap() - g("min_x")) * scale,
            oy + (g("max_z") - p["z"].as_f64().unwrap()) * scale,
        );
        let near = (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (dx as f64, dy as f64)));
        assert!(
            near.clone().any(|(dx, dy)| is_player(pixel(cx + dx, cy + dy))),
            "no dot for {p} at ({cx:.0}, {cy:.0})"
        );
    }
    let n = map["cells"].as_u64().unwrap() as usize;
    let density: Vec<u64> = map["npc_density"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap()).collect();
    assert_eq!(density.len(), n * n);
    let cell_centre = |i: usize| {
        let (row, col) = (i / n, i % n);
        (ox + (col as f64 + 0.5) * w * scale / n as f64, oy + (n as f64 - row as f64 - 0.5) * h * scale / n as f64)
    };
    let far_from_players = |(cx, cy): (f64, f64)| {
        players.iter().all(|p| {
            let px = ox + (p["x"].as_f64().unwrap() - g("min_x")) * scale;
            let py = oy + (g("max_z") - p["z"].as_f64().unwrap()) * scale;
            (px - cx).hypot(py - cy) > 8.0
        })
    };
    // The page's colours: the world, and NPC blue over it with an opacity that grows
    // with the square root of the density.
    let (world, npc) = ([26.0, 34.0, 48.0], [64.0, 150.0, 255.0]);
    let max = *density.iter().max().unwrap();
    assert!(max > 0, "the server reports NPCs");
    let expect = |d: u64| {
        let a = if d == 0 { 0.0 } else { 0.15 + 0.85 * (d as f64 / max as f64).sqrt() };
        [0, 1, 2].map(|k| world[k] * (1.0 - a) + npc[k] * a)
    };
    let mut checked = 0;
    for i in (0..n * n).filter(|&i| far_from_players(cell_centre(i))) {
        let (cx, cy) = cell_centre(i);
        let got: [u8; 3] = pixel(cx, cy);
        let want = expect(density[i]);
        assert!(
            (0..3).all(|k| (f64::from(got[k]) - want[k]).abs() <= 6.0),
            "cell {i} (density {} of {max}) is {got:?}, not {want:?}",
            density[i]
        );
        checked += 1;
    }
    assert!(checked > n * n / 2, "most cells are away from the players ({checked})");
}

/// The stage chart has drawn stacked areas: coloured pixels in its plot.
fn check_stage_chart(tab: &Tab) {
    let coloured = eval(
        tab,
        "(() => { const c = document.getElementById('stages'); \
         const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0; \
         for (let i = 0; i < d.length; i += 4) if (Math.max(d[i], d[i + 1], d[i + 2]) - Math.min(d[i], d[i + 1], d[i + 2]) > 80) n++; \
         return String(n); })()",
    );
    let legend =
        eval(tab, "JSON.stringify([...document.querySelectorAll('#stage-legend li')].map(li => li.dataset.stage))");
    let legend: Vec<String> = serde_json::from_str(&legend).unwrap();
    assert!(coloured.parse::<u32>().unwrap() > 100, "the stage chart drew areas ({coloured} coloured pixels)");
    assert!(!legend.is_empty(), "the chart names its stages");
}

/// The screenshot's width and RGB pixels.
fn decode_rgb(png_bytes: &[u8]) -> (usize, Vec<u8>) {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(png_bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let rgb = buf[..info.buffer_size()].chunks(channels).flat_map(|p| [p[0], p[1], p[2]]).collect();
    (info.width as usize, rgb)
}
