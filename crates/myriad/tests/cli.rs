//! The `myriad` command as other tools drive it: flags, JSON fields, errors.

use std::process::Command;

fn myriad(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_myriad")).args(args).env("RUST_LOG", "warn").output().expect("running myriad")
}

fn json_lines(out: &[u8]) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON: {l:?}: {e}")))
        .collect()
}

const SMALL: &[&str] = &[
    "--scenario",
    "custom",
    "--dynamic",
    "600",
    "--static",
    "90",
    "--users",
    "60",
    "--world-size",
    "64",
    "--terrain-samples",
    "65",
    "--origin",
    "-300,-20,5000",
];

#[test]
fn sim_prints_the_same_hash_on_both_backends() {
    let mut hashes = Vec::new();
    for backend in ["cpu", "cpu-naive"] {
        let mut args = vec!["sim", "--json", "--ticks", "40", "--backend", backend];
        args.extend_from_slice(SMALL);
        let out = myriad(&args);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let v = &json_lines(&out.stdout)[0];
        assert_eq!(v["dynamic"], 600);
        assert_eq!(v["users"], 60);
        assert_eq!(v["static_objects"], 90);
        assert_eq!(v["ticks"], 40);
        hashes.push(v["state_hash"].as_str().unwrap().to_string());
    }
    assert_eq!(hashes[0], hashes[1]);
    assert_eq!(hashes[0].len(), 16);
}

/// `sim --zones K` (and `--nats URL` when `NATS_URL` is set) prints the hash of the
/// single-process run.
#[test]
fn zoned_sim_prints_the_single_process_hash() {
    let hash = |extra: &[&str]| {
        let mut args = vec!["sim", "--json", "--ticks", "60", "--backend", "cpu"];
        args.extend_from_slice(SMALL);
        args.extend_from_slice(extra);
        let out = myriad(&args);
        assert!(out.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&out.stderr));
        json_lines(&out.stdout)[0].clone()
    };
    let want = hash(&[])["state_hash"].clone();
    for zones in ["2", "4", "9"] {
        let v = hash(&["--zones", zones]);
        assert_eq!(v["state_hash"], want, "{zones} zones");
        assert_eq!(v["zoned"]["zones"].as_u64().unwrap().to_string(), zones);
        assert_eq!(v["zoned"]["rejected"], 0);
    }
    // The NATS half skips with a message without a NATS server (fails under
    // MYRIAD_REQUIRE_NATS=1).
    if let Some(url) = myriad_testenv::nats_url() {
        let v = hash(&["--zones", "4", "--nats", &url]);
        assert_eq!(v["state_hash"], want, "over NATS");
        assert_eq!(v["zoned"]["fabric"], "nats");
    }
    let mut args = vec!["sim", "--zones", "400"];
    args.extend_from_slice(SMALL);
    let out = myriad(&args);
    assert!(!out.status.success(), "zones narrower than their margin are refused");
    assert!(String::from_utf8_lossy(&out.stderr).contains("use fewer zones"));
}

/// `sim --scenario moving-crowd --zones K --rebalance`: the crowd walks past the middle,
/// the cuts follow it, and the hash is one process's; other commands refuse the crowd.
#[test]
fn rebalanced_moving_crowd_keeps_the_single_process_hash() {
    let crowd = [
        "sim",
        "--json",
        "--ticks",
        "300",
        "--backend",
        "cpu",
        "--scenario",
        "moving-crowd",
        "--users",
        "600",
        "--dynamic",
        "300",
        "--static",
        "60",
        "--world-size",
        "128",
        "--terrain-samples",
        "65",
    ];
    let run = |extra: &[&str]| {
        let out = myriad(&[&crowd[..], extra].concat());
        assert!(out.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&out.stderr));
        json_lines(&out.stdout)[0].clone()
    };
    let one = run(&[]);
    assert!(one["users_mean_x"].as_f64().unwrap() > 64.0, "the crowd passed the middle: {}", one["users_mean_x"]);
    assert_eq!(one["users"], 600);
    for zones in ["2", "4", "9"] {
        let v = run(&["--zones", zones, "--rebalance", "--rebalance-every", "20"]);
        assert_eq!(v["state_hash"], one["state_hash"], "{zones} zones");
        let z = &v["zoned"];
        assert!(z["cut_moves"].as_u64().unwrap() > 0, "{zones} zones: {z}");
        assert_eq!(z["moves"].as_array().unwrap().len() as u64, z["cut_moves"].as_u64().unwrap());
        assert_eq!(z["owned"].as_array().unwrap().iter().map(|o| o.as_u64().unwrap()).sum::<u64>(), 900);
    }
    // Without --rebalance the cuts stay (the load is still reported).
    let fixed = run(&["--zones", "4"]);
    assert_eq!(fixed["zoned"]["cut_moves"], 0);
    assert_eq!(fixed["zoned"]["cuts"][0], serde_json::json!([0.0, 64.0, 128.0]));
    assert_eq!(fixed["state_hash"], one["state_hash"]);
    let out = myriad(&["bench", "--scenario", "moving-crowd"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("myriad sim --scenario moving-crowd"));
    let out = myriad(&["sim", "--rebalance"]);
    assert!(!out.status.success(), "--rebalance needs --zones");
}

#[test]
fn bench_reports_every_stage_and_the_table_columns() {
    let dir = std::env::temp_dir().join(format!("myriad-bench-{}", std::process::id()));
    let mut args = vec![
        "bench",
        "--format",
        "json",
        "--ticks",
        "5",
        "--warmup",
        "1",
        "--backend",
        "cpu,cpu-naive",
        "--aoi-size",
        "14,100",
        "--out",
    ];
    let dir_s = dir.to_string_lossy().to_string();
    args.push(&dir_s);
    args.extend_from_slice(SMALL);
    let out = myriad(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rows = json_lines(&out.stdout);
    // Two physics rows, then the whole server tick on the non-naive backend, once per
    // AOI size.
    assert_eq!(rows.len(), 4);
    assert_eq!(
        [&rows[0]["mode"], &rows[1]["mode"], &rows[2]["mode"], &rows[3]["mode"]],
        ["physics", "physics", "server", "server"]
    );
    assert_eq!([&rows[2]["server"]["aoi_size"], &rows[3]["server"]["aoi_size"]], [14.0, 100.0]);
    let per_player = |r: &serde_json::Value| r["server"]["bytes_per_player_s"].as_f64().unwrap();
    assert!(per_player(&rows[3]) > per_player(&rows[2]), "a larger view sends more");
    for r in &rows {
        for key in [
            "upload",
            "build_dynamic_bvh",
            "broad_static",
            "broad_dynamic",
            "narrow_static",
            "narrow_dynamic",
            "forces",
            "packets",
            "send",
            "physics_static_ms",
            "physics_dynamic_ms",
            "mean_ms",
            "dynamic",
            "static_objects",
            "static_boxes",
            "static_capsules",
            "users",
            "static_pairs",
            "dynamic_pairs",
            "state_hash",
        ] {
            assert!(r.get(key).is_some(), "missing {key} in {r}");
        }
        assert!(r["physics_dynamic_ms"].as_f64().unwrap() > 0.0);
        assert!(r["mean_ms"].as_f64().unwrap() > 0.0);
        assert_eq!(r["static_boxes"], 150);
        assert_eq!(r["static_capsules"], 30);
    }
    assert_eq!(rows[0]["state_hash"], rows[1]["state_hash"]);
    // The server tick fills the columns a physics run leaves at 0, and its datagrams
    // reached every bot, each seeing its own object.
    let server = &rows[2];
    assert_eq!(server["backend"], "cpu");
    for key in ["packets", "send", "receive"] {
        assert!(server[key].as_f64().unwrap() > 0.0, "{key} in {server}");
    }
    assert_eq!(server["server"]["players"], 60);
    assert_eq!(server["server"]["min_saw_own"], 60);
    assert_eq!(server["server"]["rejected"], 0);
    assert!(server["server"]["delivered"].as_u64().unwrap() >= 60);
    assert_eq!(server["server"]["opened"], server["server"]["delivered"], "every datagram opened by default");
    assert_eq!(server["server"]["lost"], 0);
    for f in ["bench.md", "bench.json", "bench.csv"] {
        let text = std::fs::read_to_string(dir.join(f)).unwrap();
        assert!(text.contains("cpu-naive"), "{f}");
    }
    for f in ["stages-custom.png", "stages-custom.svg"] {
        assert!(std::fs::metadata(dir.join(f)).unwrap().len() > 1000, "{f} is drawn");
    }
    // Every CSV line has the header's number of fields (quoted commas do not count).
    let csv = std::fs::read_to_string(dir.join("bench.csv")).unwrap();
    let fields =
        |line: &str| line.chars().fold((1, false), |(n, q), c| (n + usize::from(c == ',' && !q), q ^ (c == '"'))).0;
    let lines: Vec<&str> = csv.lines().collect();
    assert!(lines[0].contains("server.players") && lines[0].contains("receive"), "{}", lines[0]);
    assert!(lines.iter().all(|l| fields(l) == fields(lines[0])), "{csv}");
    let md = std::fs::read_to_string(dir.join("bench.md")).unwrap();
    assert!(md.contains("396.5"), "the reference's Table 1 is printed beside ours");
    assert!(md.contains("Table 3") && md.contains("cpu server tick, AOI 14"), "{md}");
    assert!(md.contains("kB/s per player"), "{md}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_scale_sweep_adds_rows_and_a_log_log_plot() {
    let dir = std::env::temp_dir().join(format!("myriad-sweep-{}", std::process::id()));
    let d = dir.to_string_lossy().to_string();
    let args = [
        "bench",
        "--format",
        "json",
        "--ticks",
        "2",
        "--warmup",
        "1",
        "--backend",
        "cpu",
        "--scenario",
        "custom",
        "--dynamic",
        "300",
        "--static",
        "60",
        "--users",
        "10",
        "--world-size",
        "64",
        "--terrain-samples",
        "65",
        "--sweep",
        "200,400",
        "--out",
        &d,
    ];
    let out = myriad(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rows = json_lines(&out.stdout);
    let sweep: Vec<_> = rows.iter().filter(|r| r["scenario"].as_str().unwrap().starts_with("sweep")).collect();
    assert_eq!(sweep.len(), 2);
    assert_eq!(sweep[1]["dynamic"], 400);
    assert_eq!(sweep[1]["static_objects"], 200);
    assert!(std::fs::metadata(dir.join("sweep.svg")).unwrap().len() > 1000);
    assert!(std::fs::metadata(dir.join("sweep.png")).unwrap().len() > 1000);
    std::fs::remove_dir_all(&dir).ok();
}

/// Runs `myriad` and returns its standard output's JSON lines, failing on a failed run.
fn json_run(args: &[&str]) -> Vec<serde_json::Value> {
    let out = myriad(args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    json_lines(&out.stdout)
}

/// Each row's backend and mode, in order.
fn backends_and_modes(rows: &[serde_json::Value]) -> Vec<(&str, &str)> {
    rows.iter().map(|r| (r["backend"].as_str().unwrap(), r["mode"].as_str().unwrap())).collect()
}

#[test]
fn slow_backends_are_skipped_unless_forced() {
    let mut args = vec!["bench", "--format", "json", "--ticks", "2", "--warmup", "1", "--max-tick-ms", "0"];
    args.extend_from_slice(SMALL);
    // Every first tick is too slow: both physics rows say why, and the server tick of a
    // skipped backend is not run at all.
    let rows = json_run(&args);
    assert_eq!(backends_and_modes(&rows), [("cpu", "physics"), ("cpu-naive", "physics")], "{rows:?}");
    assert!(rows.iter().all(|r| r["skipped"].as_str().is_some_and(|why| why.contains("--force"))), "{rows:?}");
    args.push("--force");
    let rows = json_run(&args);
    assert_eq!(
        backends_and_modes(&rows),
        [("cpu", "physics"), ("cpu-naive", "physics"), ("cpu", "server")],
        "{rows:?}"
    );
    for r in &rows {
        assert!(r["skipped"].is_null(), "{r}");
        assert!(r["total_ms"].as_f64().is_some_and(|ms| ms > 0.0), "measured: {r}");
        assert_eq!(r["state_hash"].as_str().map(str::len), Some(16), "{r}");
    }
}

/// The zones backend is a gateway's, built from its cluster: no flag selects it.
#[test]
fn the_zones_backend_cannot_be_chosen() {
    let out = myriad(&["sim", "--backend", "zones"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown backend") && err.contains("zones"), "{err}");
}

#[test]
fn bad_input_gets_a_clear_error() {
    let out = myriad(&["sim", "--backend", "quantum"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown backend"));

    let out = myriad(&["sim", "--scenario", "2", "--dynamic", "5"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--scenario custom"));

    let out = myriad(&["sim", "--scenario", "custom", "--heightmap", "/nonexistent/h.png"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("loading heightmap") && err.contains("/nonexistent/h.png"), "{err}");

    let out = myriad(&["sim", "--scenario", "custom", "--origin", "1,2"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("three finite numbers"));
}

#[test]
fn a_heightmap_file_can_replace_the_generated_terrain() {
    let dir = std::env::temp_dir().join(format!("myriad-hm-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("ramp.raw");
    // A 33×33 ramp along x.
    let bytes: Vec<u8> = (0..33 * 33).flat_map(|i| ((i % 33) as u16 * 2000).to_le_bytes()).collect();
    std::fs::write(&path, bytes).unwrap();
    let p = path.to_string_lossy().to_string();
    let hash = |extra: &[&str]| {
        let mut args = vec!["sim", "--json", "--ticks", "10", "--backend", "cpu"];
        args.extend_from_slice(SMALL);
        args.extend_from_slice(extra);
        json_run(&args)[0]["state_hash"].as_str().unwrap().to_string()
    };
    let generated = hash(&[]);
    let on_file = hash(&["--heightmap", &p]);
    assert_ne!(on_file, generated, "the heightmap changed the world");

    // The same world built here on the file's terrain (SMALL's flags, applied as
    // `WorldArgs::spec` applies them) ends in the same state.
    let mut spec = myriad_core::ScenarioSpec::custom(1);
    spec.dynamic = 600;
    spec.static_objects = 90;
    spec.users = 60;
    spec.world_size = 64.0;
    spec.terrain_samples = 65;
    spec.origin = myriad_core::Vec3::new(-300.0, -20.0, 5000.0);
    let terrain = myriad_core::Terrain::from_raw(&path, None, spec.max_height, spec.terrain_placement()).unwrap();
    let mut world = spec.build_on(terrain).unwrap();
    let mut backend = myriad_physics::create_cpu_backend(myriad_physics::BackendKind::Cpu).unwrap();
    let k = myriad_physics::TickConstants::new(&myriad_core::PhysicsConfig::default(), 1.0);
    for _ in 0..10 {
        backend.step(&mut world, &k).unwrap();
    }
    assert_eq!(on_file, format!("{:016x}", world.state_hash()), "the file's terrain, and only it, was used");
    std::fs::remove_dir_all(&dir).ok();
}
