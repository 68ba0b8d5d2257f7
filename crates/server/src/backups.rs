//! Periodic online backups of the SQLite database (`backup_every_s`, `backup_keep`).
//!
//! A task on the server's async runtime, never the tick thread: every `backup_every_s`
//! it writes `<data_dir>/backups/myriad-<ms since the epoch>.db` with
//! [`myriad_store::backup_sqlite`] (`VACUUM INTO` a temporary file, checked, synced,
//! renamed), then deletes all but the newest `backup_keep` backups. A failed backup is
//! logged and counted (`myriad_backups_total{result="failed"}`) and tried again at the
//! next interval; it never stops the server.

use std::path::{Path, PathBuf};
use std::time::Duration;

use myriad_store::Database;

/// Prefix and suffix of the backup files this task writes (and the only files it deletes).
const PREFIX: &str = "myriad-";
const SUFFIX: &str = ".db";

/// Width of the zero-padded millisecond stamp, so that names sort by time.
const STAMP_WIDTH: usize = 15;

/// The folder of periodic backups in `data_dir`.
pub fn backup_dir(data_dir: &Path) -> PathBuf {
    data_dir.join("backups")
}

/// Backs `database` up into `dir` every `every`, keeping the newest `keep`. Runs until
/// the runtime shuts down.
pub(crate) async fn run(database: Database, dir: PathBuf, every: Duration, keep: usize) {
    let mut interval = tokio::time::interval_at(tokio::time::Instant::now() + every, every);
    // After a slow backup (or a suspended machine), one backup, not a burst.
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        interval.tick().await;
        match once(&database, &dir, keep).await {
            Ok((path, removed)) => {
                metrics::counter!("myriad_backups_total", "result" => "ok").increment(1);
                tracing::info!(path = %path.display(), removed, "periodic backup written");
            }
            Err(e) => {
                metrics::counter!("myriad_backups_total", "result" => "failed").increment(1);
                tracing::warn!(dir = %dir.display(), error = %e, "periodic backup failed; retrying at the next interval");
            }
        }
    }
}

/// One backup and the pruning after it: the new file and how many old ones were deleted.
async fn once(database: &Database, dir: &Path, keep: usize) -> Result<(PathBuf, usize), myriad_store::StoreError> {
    tokio::fs::create_dir_all(dir)
        .await
        .map_err(|e| myriad_store::StoreError::File { what: format!("creating {}", dir.display()), source: e })?;
    let stamp = myriad_store::now_ms().max(0);
    let path = dir.join(format!("{PREFIX}{stamp:0STAMP_WIDTH$}{SUFFIX}"));
    let report = myriad_store::backup_sqlite(database, &path, false).await?;
    let removed = prune(dir, keep)
        .map_err(|e| myriad_store::StoreError::File { what: format!("pruning {}", dir.display()), source: e })?;
    Ok((report.path, removed))
}

/// Deletes all but the newest `keep` backup files in `dir` (names of this task's form
/// only: an operator's own files there are left alone); returns how many it deleted.
pub(crate) fn prune(dir: &Path, keep: usize) -> std::io::Result<usize> {
    let mut backups: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(is_backup_name))
        .collect();
    backups.sort();
    let excess = backups.len().saturating_sub(keep);
    for old in &backups[..excess] {
        std::fs::remove_file(old)?;
    }
    Ok(excess)
}

fn is_backup_name(name: &str) -> bool {
    name.strip_prefix(PREFIX)
        .and_then(|rest| rest.strip_suffix(SUFFIX))
        .is_some_and(|stamp| stamp.len() == STAMP_WIDTH && stamp.bytes().all(|b| b.is_ascii_digit()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prune_keeps_the_newest_and_ignores_other_files() {
        let dir = tempfile::tempdir().unwrap();
        for stamp in [3u64, 1, 2, 10] {
            std::fs::write(dir.path().join(format!("{PREFIX}{stamp:0STAMP_WIDTH$}{SUFFIX}")), b"x").unwrap();
        }
        std::fs::write(dir.path().join("mine.db"), b"x").unwrap();
        std::fs::write(dir.path().join("myriad-1.db"), b"x").unwrap();
        assert_eq!(prune(dir.path(), 2).unwrap(), 2);
        let mut left: Vec<String> =
            std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        left.sort();
        assert_eq!(left, ["mine.db", "myriad-000000000000003.db", "myriad-000000000000010.db", "myriad-1.db"]);
    }
}
