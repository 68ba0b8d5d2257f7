//! Issue 15: a store that cannot write stops the start (a real write at start-up), with
//! the database's own error; a garbage database file names its cause.

use myriad_server::{ServerConfig, ServerError, ServerHandle};
use myriad_store::{SQLITE_FILE_NAME, Store};

mod common;

fn config(dir: &std::path::Path) -> ServerConfig {
    ServerConfig { backend: myriad_server::BackendKind::Cpu, ..common::small_server(dir, 50) }
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
