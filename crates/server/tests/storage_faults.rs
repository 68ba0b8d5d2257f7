//! Issue 15: a store that cannot write stops the start (a real write at start-up), with
//! the database's own error; a garbage database file names its cause.

use myriad_server::{ServerConfig, ServerError, ServerHandle};
use myriad_store::{HashCost, SQLITE_FILE_NAME, Store};

fn config(dir: &std::path::Path) -> ServerConfig {
    let fast = HashCost::INSECURE_FAST;
    ServerConfig {
        udp_addr: "127.0.0.1:0".parse().unwrap(),
        login_addr: "127.0.0.1:0".parse().unwrap(),
        npc_count: 50,
        data_dir: dir.to_path_buf(),
        hash_memory_kib: fast.m_kib,
        hash_passes: fast.t,
        hash_lanes: fast.p,
        log_stages_every_s: 0.0,
        backend: myriad_server::BackendKind::Cpu,
        ..ServerConfig::default()
    }
}

#[test]
fn a_read_only_store_stops_the_start() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    // Create and migrate the database, then serve it read-only (what a read-only data
    // directory does; file modes do not stop root, SQLite's open mode does).
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async { Store::open(&myriad_server::store_config(&config)).await.unwrap().close().await });
    drop(rt);
    let path = dir.path().join(SQLITE_FILE_NAME);
    config.database_url = format!("sqlite:{}?mode=ro", path.display());
    let err = ServerHandle::start(config).unwrap_err();
    assert!(matches!(err, ServerError::NotWritable(_)), "{err:?}");
    let text = err.to_string();
    assert!(text.contains("readonly") && text.contains("start-up"), "{text}");
}

#[test]
fn a_garbage_database_names_its_cause() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(SQLITE_FILE_NAME), vec![0x42; 4096]).unwrap();
    let err = ServerHandle::start(config(dir.path())).unwrap_err().to_string();
    assert!(err.contains("file is not a database"), "{err}");
}
