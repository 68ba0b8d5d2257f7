//! Issue 15: storage faults reach the operator with their real cause, and a store that
//! cannot write is found out at start-up by a real write.

use myriad_store::{SQLITE_FILE_NAME, Store, StoreConfig, StoreError, validate_username};

#[tokio::test]
async fn a_garbage_database_file_names_the_real_cause() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(SQLITE_FILE_NAME), vec![0x5a; 8192]).unwrap();
    let started = std::time::Instant::now();
    let err = Store::open(&StoreConfig::sqlite(dir.path())).await.unwrap_err();
    let text = err.to_string();
    assert!(text.contains("file is not a database"), "{text}");
    assert!(!text.contains("pool timed out"), "{text}");
    // The start-up integrity check finds it first (issue 29): damaged, not retryable.
    assert!(matches!(err, StoreError::Damaged { .. }) && !err.is_transient(), "not retryable: {err:?}");
    assert!(started.elapsed() < std::time::Duration::from_secs(3), "no wait for a pool timeout");
}

#[tokio::test]
async fn a_read_only_database_fails_the_write_check() {
    let dir = tempfile::tempdir().unwrap();
    // Create and migrate it writable, then reopen it read-only (as a read-only data
    // directory would; chmod does not stop root, the SQLite open mode does).
    let rw = Store::open(&StoreConfig::sqlite(dir.path())).await.unwrap();
    rw.check_writable().await.unwrap();
    rw.close().await;
    let path = dir.path().join(SQLITE_FILE_NAME);
    let ro = Store::open(&StoreConfig::url(format!("sqlite:{}?mode=ro", path.display()))).await.unwrap();
    let err = ro.check_writable().await.unwrap_err().to_string();
    assert!(err.contains("readonly") || err.contains("read-only"), "{err}");
    ro.close().await;
}

#[test]
fn user_names_follow_one_rule() {
    for bad in ["..", ".", "a..b", ".x", "x.", "a\u{200b}b", "a\u{7}b", "a b"] {
        assert!(validate_username(bad).is_err(), "{bad:?}");
    }
    assert!(validate_username("user.name-1_x").is_ok());
}
