//! The admin commands (`myriad user …`, `myriad map …`) against an embedded store in a
//! temporary data directory, checked through the store itself.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use myriad_core::Terrain;
use myriad_core::terrain::TerrainPlacement;
use myriad_store::{Store, StoreConfig};

fn data_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("myriad-admin-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn myriad(dir: &Path, args: &[&str], stdin: &str) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_myriad"))
        .args(args)
        .arg("--data-dir")
        .arg(dir)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running myriad");
    child.stdin.take().unwrap().write_all(stdin.as_bytes()).unwrap();
    child.wait_with_output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn store(dir: &Path) -> (tokio::runtime::Runtime, Store) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let s = rt.block_on(Store::open(&StoreConfig::sqlite(dir))).unwrap();
    (rt, s)
}

#[test]
fn user_add_and_seed_create_accounts_that_can_log_in() {
    let dir = data_dir("users");
    let o = myriad(&dir, &["user", "add", "alice"], "correct horse\n");
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("created user alice"));
    // The password never appears in the output.
    assert!(!text(&o).contains("correct horse"));

    let again = myriad(&dir, &["user", "add", "alice"], "other\n");
    assert!(!again.status.success());
    assert!(text(&again).to_lowercase().contains("taken") || text(&again).contains("exists"), "{}", text(&again));
    let empty = myriad(&dir, &["user", "add", "bob"], "\n");
    assert!(!empty.status.success() && text(&empty).contains("empty password"), "{}", text(&empty));
    let bad_name = myriad(&dir, &["user", "add", "no spaces allowed"], "pw\n");
    assert!(!bad_name.status.success(), "{}", text(&bad_name));

    let seed = myriad(&dir, &["user", "seed", "--count", "3"], "");
    assert!(seed.status.success(), "{}", text(&seed));
    assert!(text(&seed).contains("3 created"), "{}", text(&seed));
    let reseed = myriad(&dir, &["user", "seed", "--count", "3"], "");
    assert!(text(&reseed).contains("0 created, 3 already there"), "{}", text(&reseed));

    let (rt, s) = store(&dir);
    rt.block_on(s.check_credentials("alice", "correct horse")).expect("alice logs in");
    assert!(rt.block_on(s.check_credentials("alice", "other")).is_err());
    rt.block_on(s.check_credentials("user2", "password2")).expect("seeded users log in");
    assert!(rt.block_on(s.find_user("bob")).unwrap().is_none(), "a failed add creates nothing");
    rt.block_on(s.close());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn map_import_and_list() {
    let dir = data_dir("maps");
    std::fs::create_dir_all(&dir).unwrap();
    let png = dir.join("hills.png");
    let at = TerrainPlacement { origin_x: 0.0, origin_z: 0.0, extent_x: 1.0, extent_z: 1.0, base_y: 0.0 };
    let terrain = Terrain::generate(5, 33, 33, 1.0, at).unwrap();
    terrain.write_png(&png).unwrap();

    let o = myriad(&dir, &["map", "import", png.to_str().unwrap(), "--max-height", "50"], "");
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("imported map hills"), "{}", text(&o));
    let list = myriad(&dir, &["map", "list"], "");
    assert!(list.status.success() && text(&list).contains("hills"), "{}", text(&list));

    // A file that is not a PNG: a clear error naming it, nothing imported.
    let junk = dir.join("junk.png");
    std::fs::write(&junk, b"not a png").unwrap();
    let bad = myriad(&dir, &["map", "import", junk.to_str().unwrap(), "--max-height", "50"], "");
    assert!(!bad.status.success() && text(&bad).contains("junk.png"), "{}", text(&bad));

    let (rt, s) = store(&dir);
    let maps = rt.block_on(s.list_maps()).unwrap();
    assert_eq!(maps.iter().filter(|m| m.name == "hills").count(), 1);
    assert!(maps.iter().all(|m| m.name != "junk"));
    let id = rt.block_on(s.map_id_by_name("hills")).unwrap();
    let info = rt.block_on(s.get_map(id)).unwrap();
    assert_eq!(info.max_height, 50.0);
    match info.heightmap {
        myriad_store::Heightmap::Inline { width, height, samples } => {
            assert_eq!((width, height), (33, 33));
            assert_eq!(samples, terrain.samples());
        }
        other => panic!("expected an inline heightmap, got {other:?}"),
    }
    rt.block_on(s.close());
    std::fs::remove_dir_all(&dir).ok();
}
