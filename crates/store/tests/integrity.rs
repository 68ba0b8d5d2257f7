//! SQLite integrity checks, online backups and restores (issue 29).

mod common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use common::test_config;
use myriad_store::{
    CheckDepth, Database, DatabaseLock, MapId, PlayerState, SQLITE_FILE_NAME, Store, StoreError, StoredShape,
    backup_sqlite, check_database, restore_sqlite,
};

/// A data directory with `users` accounts (each with a position on one map), closed.
async fn populated(dir: &Path, users: u32) -> MapId {
    let store = Store::open(&test_config(Database::SqliteDir(dir.into()))).await.unwrap();
    store.seed_users(users).await.unwrap();
    let map = common::TestDb::map_on(&store, "m").await;
    let mut states = Vec::new();
    for i in 0..users {
        let user = store.find_user(&format!("user{i}")).await.unwrap().unwrap();
        states.push(PlayerState::new(user.id, map, StoredShape::Sphere { radius: 0.5 }, [i as f32, 1.0, 2.0]));
    }
    store.save_player_states(&states).await.unwrap();
    store.close().await;
    map
}

fn db_file(dir: &Path) -> PathBuf {
    dir.join(SQLITE_FILE_NAME)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_database_is_refused_and_left_untouched() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    populated(&dir, 400).await;
    let file = db_file(&dir);
    let len = std::fs::metadata(&file).unwrap().len();
    assert!(len > 64 * 1024, "a file of many pages ({len} bytes)");
    let f = std::fs::OpenOptions::new().write(true).open(&file).unwrap();
    f.set_len(len / 2).unwrap();
    drop(f);
    let before = std::fs::read(&file).unwrap();

    let report = check_database(&Database::SqliteDir(dir.clone()), CheckDepth::Quick).await.unwrap();
    assert!(!report.is_intact(), "{report:?}");
    match Store::open(&test_config(Database::SqliteDir(dir.clone()))).await {
        Err(StoreError::Damaged { database, problems }) => {
            assert_eq!(database, file.display().to_string());
            assert!(!problems.is_empty());
        }
        other => panic!("expected Damaged, got {other:?}"),
    }
    let message = StoreError::Damaged { database: "f".into(), problems: vec!["p".into()] }.to_string();
    assert!(message.contains("myriad db restore"), "{message}");
    assert_eq!(std::fs::read(&file).unwrap(), before, "nothing written");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overwritten_pages_are_found_by_the_check() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    populated(&dir, 400).await;
    let file = db_file(&dir);
    let mut bytes = std::fs::read(&file).unwrap();
    // Pages 3 and 4 (of 4 KiB) become garbage; page 1 (the header and schema) is kept.
    for b in &mut bytes[2 * 4096..4 * 4096] {
        *b = 0xA5;
    }
    std::fs::write(&file, &bytes).unwrap();
    let report = check_database(&Database::SqliteDir(dir.clone()), CheckDepth::Full).await.unwrap();
    assert!(!report.is_intact(), "{report:?}");
    assert!(matches!(Store::open(&test_config(Database::SqliteDir(dir))).await, Err(StoreError::Damaged { .. })));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backup_taken_during_writes_restores_everything() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("live");
    let map = populated(&dir, 50).await;
    let live = Store::open(&test_config(Database::SqliteDir(dir.clone()))).await.unwrap();
    // A writer keeps moving every player while the backup runs.
    let writer = {
        let live = live.clone();
        tokio::spawn(async move {
            let mut round = 0u32;
            loop {
                let mut states = Vec::new();
                for i in 0..50 {
                    let user = live.find_user(&format!("user{i}")).await.unwrap().unwrap();
                    let x = i as f32 + round as f32 * 100.0;
                    states.push(PlayerState::new(user.id, map, StoredShape::Sphere { radius: 0.5 }, [x, 1.0, 2.0]));
                }
                live.save_player_states(&states).await.unwrap();
                round += 1;
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
    };
    tokio::time::sleep(Duration::from_millis(100)).await;
    let backup = tmp.path().join("backup.db");
    let report = backup_sqlite(&Database::SqliteDir(dir.clone()), &backup, false).await.unwrap();
    assert!(report.bytes > 0 && backup.is_file());
    // A second backup to the same name is refused without overwrite, allowed with it.
    assert!(matches!(
        backup_sqlite(&Database::SqliteDir(dir.clone()), &backup, false).await,
        Err(StoreError::AlreadyExists(_))
    ));
    backup_sqlite(&Database::SqliteDir(dir.clone()), &backup, true).await.unwrap();
    writer.abort();
    live.close().await;

    let fresh = Database::SqliteDir(tmp.path().join("fresh"));
    assert_eq!(restore_sqlite(&fresh, &backup).await.unwrap(), None, "nothing to move aside");
    assert!(check_database(&fresh, CheckDepth::Full).await.unwrap().is_intact());
    let restored = Store::open(&test_config(fresh.clone())).await.unwrap();
    let states = restored.list_player_states(map).await.unwrap();
    assert_eq!(states.len(), 50);
    // One consistent snapshot: every player from the same round of the writer.
    let rounds: Vec<i64> = states.iter().map(|s| (s.position[0] / 100.0).floor() as i64).collect();
    assert!(rounds.windows(2).all(|w| w[0] == w[1]), "{rounds:?}");
    for i in 0..50 {
        restored.check_credentials(&format!("user{i}"), &format!("password{i}")).await.unwrap();
    }
    restored.close().await;

    // Restoring over an existing database keeps the old one aside.
    let moved = restore_sqlite(&fresh, &backup).await.unwrap().expect("old database moved aside");
    assert!(moved.is_file());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restore_refuses_while_the_lock_is_held_and_refuses_bad_backups() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    populated(&dir, 3).await;
    let database = Database::SqliteDir(dir.clone());
    let backup = tmp.path().join("b.db");
    backup_sqlite(&database, &backup, false).await.unwrap();
    let lock = DatabaseLock::for_database(&database).unwrap().expect("sqlite has a lock");
    assert!(matches!(restore_sqlite(&database, &backup).await, Err(StoreError::InUse { .. })));
    drop(lock);
    restore_sqlite(&database, &backup).await.expect("restores once the lock is free");

    let not_myriad = tmp.path().join("other.db");
    let other = Store::open(&test_config(Database::Url(format!("sqlite://{}", not_myriad.display())))).await.unwrap();
    other.close().await;
    sqlx_drop_users(&not_myriad).await;
    assert!(matches!(restore_sqlite(&database, &not_myriad).await, Err(StoreError::InvalidInput(_))));

    let garbage = tmp.path().join("garbage.db");
    std::fs::write(&garbage, vec![0x42u8; 8192]).unwrap();
    assert!(matches!(restore_sqlite(&database, &garbage).await, Err(StoreError::Damaged { .. })));
    assert!(matches!(
        backup_sqlite(&Database::Url("mysql://u:p@127.0.0.1/x".into()), &tmp.path().join("m.db"), false).await,
        Err(StoreError::InvalidInput(m)) if m.contains("mariadb-dump")
    ));
}

/// Makes a SQLite file that is a database but not Myriad's.
async fn sqlx_drop_users(file: &Path) {
    use sqlx::{Connection, Executor};
    let mut conn = sqlx::SqliteConnection::connect(&format!("sqlite://{}", file.display())).await.unwrap();
    conn.execute("PRAGMA foreign_keys = OFF; DROP TABLE player_state; DROP TABLE users").await.unwrap();
    conn.close().await.unwrap();
}
