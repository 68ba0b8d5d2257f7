//! The viewer end to end: a real server in-process, the real `myriad-viewer` binary on a
//! virtual X display (Xvfb, Mesa's software OpenGL), a few frames, a screenshot, and
//! checks that the picture shows terrain, objects and the status line.
//!
//! Without `Xvfb` on the PATH the screenshot test prints why and passes, unless
//! `MYRIAD_REQUIRE_XVFB=1` (CI) makes that a failure. The error-message tests need no
//! display.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use myriad_client::{ClientConfig, Credentials, Trust};
use myriad_server::{ServerConfig, ServerHandle};
use myriad_store::{HashCost, MapId, PlayerState, Store, StoredShape};
use myriad_viewer::net::Snapshot;
use myriad_viewer::reconnect::Link;
use myriad_viewer::scene::{palette, terrain_height};

const VIEWER: &str = env!("CARGO_BIN_EXE_myriad-viewer");

/// Xvfb on a display it chose itself; killed when dropped, also when a test fails.
struct Xvfb {
    child: Child,
    display: String,
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn on_path(program: &str) -> bool {
    std::env::var_os("PATH").is_some_and(|paths| std::env::split_paths(&paths).any(|dir| dir.join(program).is_file()))
}

/// Starts Xvfb, or says why not: `None` means "skip".
fn start_xvfb() -> Option<Xvfb> {
    if !on_path("Xvfb") {
        let why = "Xvfb is not on the PATH (Debian: apt-get install xvfb libgl1-mesa-dri)";
        if std::env::var("MYRIAD_REQUIRE_XVFB").is_ok_and(|v| v == "1") {
            panic!("{why}, and MYRIAD_REQUIRE_XVFB=1");
        }
        eprintln!("SKIPPED: {why}; set MYRIAD_REQUIRE_XVFB=1 to make this a failure");
        return None;
    }
    // -displayfd: Xvfb picks a free display number and writes it to our pipe when ready.
    let mut child = Command::new("Xvfb")
        .args(["-displayfd", "1", "-screen", "0", "1280x720x24", "-nolisten", "tcp"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting Xvfb");
    let stdout = child.stdout.take().expect("piped");
    let mut xvfb = Xvfb { child, display: String::new() };
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line).expect("reading Xvfb's display number");
    let n: u32 = line.trim().parse().unwrap_or_else(|_| panic!("Xvfb said {line:?}, not a display number"));
    xvfb.display = format!(":{n}");
    Some(xvfb)
}

/// A small server: scenario 1's map, NPCs on a 20×20 grid 2.5 units apart around the map's
/// centre, cheap password hashes.
fn config(dir: &Path) -> ServerConfig {
    let fast = HashCost::INSECURE_FAST;
    ServerConfig {
        udp_addr: "127.0.0.1:0".parse().unwrap(),
        login_addr: "127.0.0.1:0".parse().unwrap(),
        npc_count: 400,
        npc_spacing: 2.5,
        data_dir: dir.to_path_buf(),
        hash_memory_kib: fast.m_kib,
        hash_passes: fast.t,
        hash_lanes: fast.p,
        log_stages_every_s: 0.0,
        backend: myriad_server::BackendKind::Cpu,
        ..ServerConfig::default()
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}

fn start_server(rt: &tokio::runtime::Runtime, dir: &Path) -> ServerHandle {
    let cfg = config(dir);
    rt.block_on(async {
        let store = Store::open(&myriad_server::store_config(&cfg)).await.unwrap();
        store.seed_users(2).await.unwrap();
        store.close().await;
    });
    ServerHandle::start(cfg).unwrap()
}

/// Puts `user0` just south of the NPC grid, facing it (the camera looks along +z).
fn place_player(rt: &tokio::runtime::Runtime, server: &ServerHandle) -> [f32; 3] {
    let trust = Trust::pin_file(server.certificate_path()).unwrap();
    let mut cc = ClientConfig::new(server.login_addr(), &trust).unwrap();
    cc.want_map = true;
    cc.login_timeout = Duration::from_secs(20);
    rt.block_on(async {
        // user1 downloads the map to learn its id and the ground height.
        let (accepted, map) = myriad_client::login(&cc, &Credentials::test_user(1)).await.unwrap();
        let map = map.unwrap();
        let d = &accepted.map;
        let (cx, cz) = ((d.bounds_min[0] + d.bounds_max[0]) / 2.0, (d.bounds_min[2] + d.bounds_max[2]) / 2.0);
        let (x, z) = (cx, cz - 34.0);
        let pos = [x, terrain_height(d, &map, x, z) + 1.0, z];
        let store = server.store();
        let user = store.find_user("user0").await.unwrap().unwrap();
        let shape = StoredShape::Capsule { radius: 0.4, half_height: 0.5 };
        store.create_player_state(&PlayerState::new(user.id, MapId(d.map_id), shape, pos)).await.unwrap();
        pos
    })
}

fn wait_with_timeout(mut child: Child, timeout: Duration) -> Output {
    let end = Instant::now() + timeout;
    loop {
        match child.try_wait().expect("waiting for the viewer") {
            Some(_) => return child.wait_with_output().expect("viewer output"),
            None if Instant::now() > end => {
                let _ = child.kill();
                let out = child.wait_with_output().expect("viewer output");
                panic!(
                    "the viewer did not finish within {timeout:?}\nstdout:\n{}\nstderr:\n{}",
                    String::from_utf8_lossy(&out.stdout),
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            None => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

struct Image {
    width: usize,
    height: usize,
    rgb: Vec<[u8; 3]>,
}

fn load_png(path: &Path) -> Image {
    let decoder = png::Decoder::new(BufReader::new(std::fs::File::open(path).expect("the screenshot exists")));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    let rgb = buf[..info.buffer_size()].chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    Image { width: info.width as usize, height: info.height as usize, rgb }
}

/// Whether a lit pixel has the hue of `c`: the same channel order with clear margins
/// (lighting scales brightness, so compare shape, not values).
fn has_hue(p: [u8; 3], c: three_d::Srgba) -> bool {
    let (p, c) = (p.map(i32::from), [c.r, c.g, c.b].map(i32::from));
    let sum = p[0] + p[1] + p[2];
    if sum < 60 {
        return false;
    }
    let csum = c[0] + c[1] + c[2];
    // Compare chromaticity (each channel's share of the sum) within 0.06.
    (0..3).all(|k| (p[k] * 1000 / sum - c[k] * 1000 / csum).abs() < 60)
}

#[test]
fn headless_run_draws_terrain_objects_and_status_line() {
    let Some(xvfb) = start_xvfb() else { return };
    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let server = start_server(&rt, dir.path());
    let pos = place_player(&rt, &server);
    let shot: PathBuf =
        std::env::var_os("MYRIAD_VIEWER_SCREENSHOT").map_or_else(|| dir.path().join("viewer.png"), PathBuf::from);
    let child = Command::new(VIEWER)
        .args(["--server", &server.login_addr().to_string(), "--user", "user0", "--cert"])
        .arg(server.certificate_path())
        .args(["--frames", "8", "--size", "960x540", "--terrain-res", "256", "--screenshot"])
        .arg(&shot)
        .env("DISPLAY", &xvfb.display)
        .env_remove("WAYLAND_DISPLAY")
        .env("LIBGL_ALWAYS_SOFTWARE", "1")
        .env("MYRIAD_PASSWORD", "password0")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starting the viewer");
    let out = wait_with_timeout(child, Duration::from_secs(180));
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    eprintln!("viewer stdout:\n{stdout}\nviewer stderr:\n{stderr}");
    assert!(out.status.success(), "the viewer failed: {:?}", out.status);
    assert!(!stderr.contains("password0"), "the password is never printed");
    assert!(stdout.contains("frame time"), "frame times are reported");

    let img = load_png(&shot);
    assert_eq!((img.width, img.height), (960, 540));
    let n = img.rgb.len();
    let distinct: std::collections::HashSet<[u8; 3]> = img.rgb.iter().copied().collect();
    let share = |f: &dyn Fn([u8; 3]) -> bool| img.rgb.iter().filter(|p| f(**p)).count();
    let terrain = share(&|p| {
        let [r, g, b] = p.map(i32::from);
        g > r + 8 && g > b + 8
    });
    let sky = share(&|p| has_hue(p, palette::SKY));
    let spheres = share(&|p| has_hue(p, palette::SPHERE));
    let boxes = share(&|p| has_hue(p, palette::BOX));
    let capsules = share(&|p| has_hue(p, palette::CAPSULE));
    let own = share(&|p| has_hue(p, palette::OWN));
    // The status line: white text on a dark band in the top rows.
    let top = &img.rgb[..img.width * 60];
    let text = top.iter().filter(|p| p.iter().all(|c| *c > 200)).count();
    let dark = top.iter().filter(|p| p.iter().all(|c| *c < 60)).count();
    eprintln!(
        "player at {pos:?}; {n} pixels, {} colours; terrain {terrain}, sky {sky}, spheres {spheres}, boxes {boxes}, capsules {capsules}, own {own}; status line: {text} light and {dark} dark pixels",
        distinct.len()
    );
    assert!(distinct.len() > 500, "a blank or flat frame: {} colours", distinct.len());
    assert!(terrain > n / 5, "terrain should cover a good part of the picture: {terrain} of {n}");
    assert!(sky > n / 50, "the sky shows above the horizon: {sky} of {n}");
    for (what, count) in [("spheres", spheres), ("boxes", boxes), ("capsules", capsules), ("the player", own)] {
        assert!(count > 100, "{what} should be visible: {count} pixels");
    }
    assert!(text > 200 && dark > 2000, "the status line is drawn: {text} light, {dark} dark pixels");
    server.shutdown().unwrap();
}

fn run_viewer(args: &[&str], envs: &[(&str, &str)]) -> (bool, String) {
    let mut cmd = Command::new(VIEWER);
    cmd.args(args).env_remove("MYRIAD_PASSWORD").env_remove("MYRIAD_USER").env_remove("WAYLAND_DISPLAY");
    cmd.env_remove("DISPLAY");
    for (k, v) in envs {
        cmd.env(k, v);
    }
    let child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().expect("starting the viewer");
    let out = wait_with_timeout(child, Duration::from_secs(60));
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn clear_errors_without_a_panic() {
    let fake_display = [("DISPLAY", ":4242")];
    let (ok, err) = run_viewer(&["--user", "u"], &fake_display);
    assert!(!ok && err.contains("no password"), "{err}");
    let (ok, err) = run_viewer(&["--user", "u", "--server", "localhost"], &[("MYRIAD_PASSWORD", "x")]);
    assert!(!ok && err.contains("HOST:PORT"), "{err}");
    let (ok, err) = run_viewer(&["--user", "u"], &[("MYRIAD_PASSWORD", "x")]);
    assert!(!ok && err.contains("no display"), "{err}");
    let (ok, err) =
        run_viewer(&["--user", "u", "--cert", "/nonexistent.pem"], &[("MYRIAD_PASSWORD", "x"), fake_display[0]]);
    assert!(!ok && err.contains("/nonexistent.pem") && err.contains("--cert"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let server = start_server(&rt, dir.path());
    let cert = server.certificate_path().to_str().unwrap().to_string();
    let addr = server.login_addr().to_string();
    let (ok, err) = run_viewer(
        &["--server", &addr, "--user", "user0", "--cert", &cert],
        &[("MYRIAD_PASSWORD", "wrong-secret"), fake_display[0]],
    );
    assert!(!ok && err.contains("wrong username or password"), "{err}");
    assert!(!err.contains("wrong-secret") && !err.contains("panicked"), "{err}");
    // Nothing listens on the server's UDP port over TCP.
    let closed = server.udp_addr().to_string();
    let (ok, err) = run_viewer(
        &["--server", &closed, "--user", "user0", "--cert", &cert],
        &[("MYRIAD_PASSWORD", "password0"), fake_display[0]],
    );
    assert!(!ok && err.contains("cannot reach the login service"), "{err}");
    // A display that does not exist: the login works, the window cannot open.
    let (ok, err) = run_viewer(
        &["--server", &addr, "--user", "user0", "--cert", &cert],
        &[("MYRIAD_PASSWORD", "password0"), fake_display[0]],
    );
    assert!(!ok && err.contains("cannot open a window"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    server.shutdown().unwrap();
}

/// Frame times with 10,000 extra objects in view (software rendering here, so the numbers
/// say little about a GPU; see docs/viewer.md). Run with
/// `cargo test --release -p myriad-viewer --test headless -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement, not a check: slow under software rendering"]
fn frame_times_with_many_objects() {
    let Some(xvfb) = start_xvfb() else { return };
    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let server = start_server(&rt, dir.path());
    place_player(&rt, &server);
    let objects = std::env::var("MYRIAD_VIEWER_BENCH_OBJECTS").unwrap_or_else(|_| "0,10000".into());
    let size = std::env::var("MYRIAD_VIEWER_BENCH_SIZE").unwrap_or_else(|_| "1280x720".into());
    let extra = std::env::var("MYRIAD_VIEWER_BENCH_ARGS").unwrap_or_default();
    for n in objects.split(',') {
        let child = Command::new(VIEWER)
            .args(["--server", &server.login_addr().to_string(), "--user", "user0", "--cert"])
            .arg(server.certificate_path())
            .args(["--frames", "60", "--size", &size, "--bench-objects", n])
            .args(extra.split_whitespace())
            .env("DISPLAY", &xvfb.display)
            .env_remove("WAYLAND_DISPLAY")
            .env("LIBGL_ALWAYS_SOFTWARE", "1")
            .env("MYRIAD_PASSWORD", "password0")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting the viewer");
        let out = wait_with_timeout(child, Duration::from_secs(590));
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        println!("--bench-objects {n} at {size} {extra}: {}", String::from_utf8_lossy(&out.stdout).trim());
    }
    server.shutdown().unwrap();
}

/// A server with `user0` placed by the NPCs, and the viewer's network thread (no window)
/// logged in as `user0`.
fn server_and_session(rt: &tokio::runtime::Runtime, dir: &Path) -> (ServerHandle, myriad_viewer::net::Session) {
    let server = start_server(rt, dir);
    place_player(rt, &server);
    let trust = Trust::pin_file(server.certificate_path()).unwrap();
    let cc = ClientConfig::new(server.login_addr(), &trust).unwrap();
    let session = myriad_viewer::net::Session::start(cc, Credentials::test_user(0)).unwrap();
    (server, session)
}

/// The first snapshot of `session` for which `f` holds, waiting up to `secs` seconds.
fn wait_for_snapshot(
    session: &myriad_viewer::net::Session,
    secs: u64,
    what: &str,
    f: &dyn Fn(&Snapshot) -> bool,
) -> std::sync::Arc<Snapshot> {
    let end = Instant::now() + Duration::from_secs(secs);
    loop {
        let s = session.shared.snapshot();
        if f(&s) {
            return s;
        }
        assert!(Instant::now() < end, "no snapshot with {what} within {secs} s: {s:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The network thread without a window: held keys reach the server at the tick rate, a
/// tapped jump is sent, and snapshots carry the world, the ping and the bandwidth.
#[test]
fn session_sends_held_keys_and_publishes_snapshots() {
    use myriad_protocol::ActionMask;
    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let (server, mut session) = server_and_session(&rt, dir.path());
    let map = &session.login().map;
    assert_eq!(map.samples.len(), (map.terrain_width * map.terrain_depth) as usize);
    assert!(!map.statics.is_empty(), "the map came with the login");
    let wait_for = |what: &str, f: &dyn Fn(&Snapshot) -> bool| wait_for_snapshot(&session, 10, what, f);
    let first = wait_for("the own position", &|s| s.own_position.is_some() && s.objects.len() > 1);
    let start = first.own_position.unwrap();
    session.shared.with_keys(|k| k.handle(three_d::Key::ArrowUp, true));
    let moved = wait_for("the player 2 units forward", &|s| s.own_position.is_some_and(|p| p[2] - start[2] > 2.0));
    let p = moved.own_position.unwrap();
    assert!((p[0] - start[0]).abs() < 1.0, "forward is +z only: {start:?} -> {p:?}");
    assert!(moved.tick > first.tick && moved.generation > first.generation);
    session.shared.with_keys(|k| k.handle(three_d::Key::ArrowUp, false));
    // A tap of space shorter than a tick still makes the player jump.
    let before = session.shared.snapshot().own_position.unwrap();
    session.shared.with_keys(|k| {
        k.handle(three_d::Key::Space, true);
        k.handle(three_d::Key::Space, false);
    });
    wait_for("the player off the ground", &|s| s.own_position.is_some_and(|p| p[1] - before[1] > 0.3));
    let s = wait_for("a ping and a bandwidth", &|s| s.ping.is_some() && s.bytes_per_s > 0.0);
    assert!(s.ping.unwrap() < Duration::from_secs(1), "{:?}", s.ping);
    assert_eq!(ActionMask::JUMP, 1 << 4);
    session.stop(Duration::from_secs(2));
    server.shutdown().unwrap();
}

/// The server stops under the viewer and a new one starts on the same ports with the same
/// database: the viewer says it is disconnected and when it will try again, logs in
/// again, and shows the new server's world with the status line back at "connected".
#[test]
fn the_viewer_comes_back_after_a_server_restart() {
    let dir = tempfile::tempdir().unwrap();
    let rt = runtime();
    let (server, mut session) = server_and_session(&rt, dir.path());
    let (login_addr, udp_addr) = (server.login_addr(), server.udp_addr());
    let first = wait_for_snapshot(&session, 10, "the world", &|s| s.link.is_connected() && s.objects.len() > 1);
    assert_eq!((first.login, session.login().number), (1, 1));

    server.shutdown().unwrap();
    let down =
        wait_for_snapshot(&session, 20, "the end of the session", &|s| matches!(s.link, Link::Reconnecting { .. }));
    let status = down.link.status(Instant::now());
    eprintln!("while the server is down: {status}");
    assert!(status.starts_with("disconnected: ") && status.contains("reconnecting in"), "{status}");
    assert!(down.objects.iter().all(|o| o.stale), "nothing is refreshed while the session is down");

    let mut cfg = config(dir.path());
    (cfg.login_addr, cfg.udp_addr) = (login_addr, udp_addr);
    let server = ServerHandle::start(cfg).unwrap();
    let back = wait_for_snapshot(&session, 90, "the new session's world", &|s| {
        s.login == 2 && s.link.is_connected() && s.own_position.is_some() && s.objects.len() > 1
    });
    let later = wait_for_snapshot(&session, 10, "a newer tick", &|s| s.login == 2 && s.tick > back.tick);
    assert_eq!(later.link.status(Instant::now()), "connected");
    assert_eq!(session.login().number, 2, "the session's login is the new one");
    assert!(later.objects.iter().any(|o| !o.stale), "updates arrive again");
    session.stop(Duration::from_secs(2));
    server.shutdown().unwrap();
}
