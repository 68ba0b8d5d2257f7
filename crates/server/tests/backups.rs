//! Issue 29: periodic online backups (`backup_every_s`, `backup_keep`) while the server
//! runs; each is a whole, checked database, and only the newest are kept.

use std::time::{Duration, Instant};

use myriad_server::{ServerConfig, ServerHandle};
use myriad_store::{CheckDepth, Database, check_database};

mod common;

#[test]
fn periodic_backups_are_whole_and_pruned() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { backup_every_s: 1, backup_keep: 2, ..common::small_server(dir.path(), 20) };
    let server = ServerHandle::start(cfg).unwrap();
    let backups = myriad_server::backups::backup_dir(dir.path());
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(server.store().seed_users(3)).unwrap();
    // Three or more intervals: at least three backups made (names seen), two kept. A
    // new backup is renamed into place before the oldest is deleted, so three can be
    // seen for a moment: wait for the pruning.
    let end = Instant::now() + Duration::from_secs(30);
    let mut seen = std::collections::BTreeSet::new();
    let files = loop {
        std::thread::sleep(Duration::from_millis(100));
        let mut files: Vec<_> = std::fs::read_dir(&backups)
            .map(|d| d.map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|x| x == "db")).collect())
            .unwrap_or_default();
        files.sort();
        seen.extend(files.iter().cloned());
        // Checked as copies taken at once: the next interval may prune one meanwhile.
        let kept = dir.path().join("kept");
        let _ = std::fs::remove_dir_all(&kept);
        std::fs::create_dir(&kept).unwrap();
        let copies: std::io::Result<Vec<_>> = files
            .iter()
            .map(|f| {
                let to = kept.join(f.file_name().unwrap());
                std::fs::copy(f, &to).map(|_| to)
            })
            .collect();
        match copies {
            Ok(copies) if seen.len() >= 3 && copies.len() <= 2 => break copies,
            _ if Instant::now() > end => break files,
            _ => {}
        }
    };
    assert!(seen.len() >= 3, "backups made: {seen:?}");
    assert_eq!(files.len(), 2, "{files:?}");
    for file in &files {
        let database = Database::Url(format!("sqlite://{}", file.display()));
        let report = rt.block_on(check_database(&database, CheckDepth::Full)).unwrap();
        assert!(report.is_intact(), "{report:?}");
        // A copy: opening sets WAL mode, a write the backup itself should not get.
        let copy = dir.path().join("copy.db");
        std::fs::copy(file, &copy).unwrap();
        let config = myriad_store::StoreConfig::url(format!("sqlite://{}", copy.display()));
        let store = rt.block_on(myriad_store::Store::open(&config)).unwrap();
        assert!(rt.block_on(store.find_user("user2")).unwrap().is_some(), "the accounts are in {}", file.display());
        rt.block_on(store.close());
        std::fs::remove_file(&copy).unwrap();
    }
    server.shutdown().unwrap();
}
