//! Integrity checks, online backups and restores of the database (issue 29).
//!
//! These work on the database itself, not through a [`Store`](crate::Store): a check
//! must not migrate (write) what it checks, a backup must not need the schema to be
//! current, and a restore replaces the file the store would hold open.
//!
//! # SQLite
//! - [`check_database`] runs `PRAGMA quick_check` (or `integrity_check`) on a read-only
//!   connection; [`Store::open`](crate::Store::open) runs the quick check before it
//!   touches the file, so a damaged database is refused before anything writes to it.
//! - [`backup_sqlite`] runs `VACUUM INTO` on a read-only connection: in WAL mode it reads
//!   one consistent snapshot while the server keeps writing. It writes a temporary file
//!   next to the destination, checks it, syncs it and only then gives it its name.
//! - [`restore_sqlite`] checks the backup, copies it (`VACUUM INTO` again, which folds in
//!   a WAL the backup may carry) to a temporary file next to the database, moves the old
//!   database and its WAL aside, and renames the copy into place. It holds the
//!   database's lock file ([`DatabaseLock`]), which a running server holds too, so it
//!   refuses while a server runs.
//!
//! # MariaDB
//! [`check_database`] runs `CHECK TABLE` on Myriad's tables. Backups are `mariadb-dump`'s
//! job (docs/server.md gives the command): [`backup_sqlite`] and [`restore_sqlite`] refuse
//! a MySQL URL with a message that says so.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::{Duration, Instant};

use sqlx::mysql::{MySqlConnectOptions, MySqlConnection};
use sqlx::sqlite::{SqliteConnectOptions, SqliteConnection};
use sqlx::{ConnectOptions, Connection, Row};

use crate::config::{Database, SQLITE_FILE_NAME};
use crate::error::{Result, StoreError};

/// How thorough a check is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CheckDepth {
    /// SQLite `PRAGMA quick_check` (every page and record, not the indexes' contents:
    /// linear in the file's size); MariaDB `CHECK TABLE … QUICK`.
    Quick,
    /// SQLite `PRAGMA integrity_check` (also that every index matches its table);
    /// MariaDB `CHECK TABLE … EXTENDED`.
    Full,
}

/// What a check found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IntegrityReport {
    /// The file or database checked (a URL without its password).
    pub database: String,
    /// How thorough the check was.
    pub depth: CheckDepth,
    /// The tables checked (MariaDB; empty on SQLite, whose check covers the whole file).
    pub tables: Vec<String>,
    /// What the check reported, one line each; empty when the database is intact.
    pub problems: Vec<String>,
    /// How long it took.
    pub elapsed: Duration,
}

impl IntegrityReport {
    /// Whether nothing was found.
    pub fn is_intact(&self) -> bool {
        self.problems.is_empty()
    }

    /// `Ok` when intact, [`StoreError::Damaged`] otherwise.
    pub fn require_intact(self) -> Result<IntegrityReport> {
        if self.is_intact() {
            Ok(self)
        } else {
            Err(StoreError::Damaged { database: self.database, problems: self.problems })
        }
    }
}

/// What a backup wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BackupReport {
    /// The backup file.
    pub path: PathBuf,
    /// Its size in bytes.
    pub bytes: u64,
    /// How long it took.
    pub elapsed: Duration,
}

/// Myriad's tables, checked by `CHECK TABLE` on MariaDB.
const MYRIAD_TABLES: [&str; 7] =
    ["users", "maps", "player_state", "static_objects", "store_probe", "admin_audit", "_sqlx_migrations"];

/// The SQLite file of `database`, or `None` for MySQL and in-memory databases.
pub fn sqlite_file(database: &Database) -> Result<Option<PathBuf>> {
    match database {
        Database::SqliteDir(dir) => Ok(Some(dir.join(SQLITE_FILE_NAME))),
        Database::Url(url) if url.starts_with("sqlite:") => {
            let options = SqliteConnectOptions::from_str(url)
                .map_err(|e| StoreError::InvalidInput(format!("bad database URL: {e}")))?;
            let file = options.get_filename();
            Ok((file != Path::new(":memory:") && !file.as_os_str().is_empty()).then(|| file.to_path_buf()))
        }
        Database::Url(_) => Ok(None),
    }
}

/// A URL fit for messages: the password (between the user's `:` and the last `@` of
/// the authority) replaced by `***`.
fn redacted(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else { return url.to_string() };
    let authority_end = rest.find('/').unwrap_or(rest.len());
    let (authority, path) = rest.split_at(authority_end);
    match authority.rsplit_once('@') {
        Some((userinfo, host)) => match userinfo.split_once(':') {
            Some((user, _)) => format!("{scheme}://{user}:***@{host}{path}"),
            None => url.to_string(),
        },
        None => url.to_string(),
    }
}

/// Checks a database without writing to it: `PRAGMA quick_check`/`integrity_check` on
/// SQLite, `CHECK TABLE` on Myriad's tables on MariaDB. A damaged database is an `Ok`
/// report with problems (see [`IntegrityReport::require_intact`]); an `Err` means the
/// check itself could not run (no such file, server unreachable).
pub async fn check_database(database: &Database, depth: CheckDepth) -> Result<IntegrityReport> {
    let started = Instant::now();
    if let Some(file) = sqlite_file(database)? {
        if !file.is_file() {
            return Err(StoreError::NotFound(format!("no database file at {}", file.display())));
        }
        let problems = sqlite_problems(&file, depth).await?;
        let database = file.display().to_string();
        return Ok(IntegrityReport { database, depth, tables: Vec::new(), problems, elapsed: started.elapsed() });
    }
    let Database::Url(url) = database else { unreachable!("a data directory is always SQLite") };
    if !(url.starts_with("mysql:") || url.starts_with("mariadb:")) {
        return Err(StoreError::InvalidInput("database URL must start with mysql:, mariadb: or sqlite:".into()));
    }
    let options = MySqlConnectOptions::from_str(&url.replacen("mariadb:", "mysql:", 1))
        .map_err(|e| StoreError::InvalidInput(format!("bad database URL: {e}")))?;
    let mut conn = options.connect().await?;
    let (tables, problems) = mysql_problems(&mut conn, depth).await?;
    conn.close().await?;
    Ok(IntegrityReport { database: redacted(url), depth, tables, problems, elapsed: started.elapsed() })
}

/// Opens an existing SQLite file read-only (with a busy timeout: a checkpoint of a
/// running server may hold a lock for a moment).
async fn open_read_only(file: &Path) -> Result<SqliteConnection> {
    let options = SqliteConnectOptions::new()
        .filename(file)
        .read_only(true)
        .create_if_missing(false)
        .busy_timeout(Duration::from_secs(10));
    Ok(options.connect().await?)
}

/// The problems `PRAGMA quick_check`/`integrity_check` reports for `file` (empty when it
/// answers `ok`). SQLite's "malformed" and "not a database" errors, which a badly damaged
/// file gives instead of rows, are problems too.
pub(crate) async fn sqlite_problems(file: &Path, depth: CheckDepth) -> Result<Vec<String>> {
    let pragma = match depth {
        CheckDepth::Quick => "PRAGMA quick_check",
        CheckDepth::Full => "PRAGMA integrity_check",
    };
    let mut conn = match open_read_only(file).await {
        Ok(c) => c,
        Err(StoreError::Database(e)) if is_corruption(&e) => return Ok(vec![e.to_string()]),
        Err(e) => return Err(e),
    };
    let rows = sqlx::query(pragma).fetch_all(&mut conn).await;
    let _ = conn.close().await;
    let rows = match rows {
        Ok(rows) => rows,
        Err(e) if is_corruption(&e) => return Ok(vec![e.to_string()]),
        Err(e) => return Err(e.into()),
    };
    let lines: Vec<String> = rows.iter().map(|r| r.try_get::<String, _>(0)).collect::<Result<_, _>>()?;
    Ok(if lines == ["ok"] { Vec::new() } else { lines })
}

/// SQLITE_CORRUPT (11) and SQLITE_NOTADB (26), with their extended codes.
fn is_corruption(err: &sqlx::Error) -> bool {
    err.as_database_error()
        .and_then(|db| db.code())
        .and_then(|c| c.parse::<i64>().ok())
        .is_some_and(|c| matches!(c & 0xff, 11 | 26))
}

/// `CHECK TABLE` on those of Myriad's tables that exist: the tables and the problems
/// (an `error` message, or a `status` other than `OK`).
async fn mysql_problems(conn: &mut MySqlConnection, depth: CheckDepth) -> Result<(Vec<String>, Vec<String>)> {
    let existing: Vec<String> = sqlx::query_scalar(
        "SELECT CAST(table_name AS CHAR) FROM information_schema.tables WHERE table_schema = DATABASE()",
    )
    .fetch_all(&mut *conn)
    .await?;
    let tables: Vec<String> =
        MYRIAD_TABLES.iter().filter(|t| existing.iter().any(|e| e == *t)).map(|t| t.to_string()).collect();
    if tables.is_empty() {
        return Ok((tables, vec!["none of Myriad's tables exist in this database".into()]));
    }
    let option = match depth {
        CheckDepth::Quick => "QUICK",
        CheckDepth::Full => "EXTENDED",
    };
    // The names come from the constant list above, never from input.
    let sql =
        format!("CHECK TABLE {} {option}", tables.iter().map(|t| format!("`{t}`")).collect::<Vec<_>>().join(", "));
    let rows = sqlx::raw_sql(sqlx::AssertSqlSafe(sql)).fetch_all(&mut *conn).await?;
    let mut problems = Vec::new();
    for row in rows {
        let text = |i: usize| -> Result<String> {
            Ok(match row.try_get::<String, _>(i) {
                Ok(s) => s,
                Err(_) => String::from_utf8_lossy(&row.try_get::<Vec<u8>, _>(i)?).into_owned(),
            })
        };
        let (table, kind, message) = (text(0)?, text(2)?, text(3)?);
        let bad = kind.eq_ignore_ascii_case("error") || (kind.eq_ignore_ascii_case("status") && message != "OK");
        if bad {
            problems.push(format!("{table}: {kind}: {message}"));
        }
    }
    Ok((tables, problems))
}

/// The path of a temporary file next to `target`, unique to this process.
fn temp_next_to(target: &Path, what: &str) -> PathBuf {
    let name = target.file_name().map_or_else(|| "myriad".into(), |n| n.to_string_lossy().into_owned());
    target.with_file_name(format!(".{name}.{what}-{}", std::process::id()))
}

/// `VACUUM INTO` from the SQLite file `source` to the new file `dest` (removed first if a
/// stale one is there), then a quick check of `dest` and an fsync.
async fn vacuum_into(source: &Path, dest: &Path) -> Result<()> {
    match std::fs::remove_file(dest) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(StoreError::file(format!("removing {}", dest.display()))(e)),
    }
    let mut conn = open_read_only(source).await?;
    let dest_text =
        dest.to_str().ok_or_else(|| StoreError::InvalidInput(format!("{} is not UTF-8", dest.display())))?;
    let done = sqlx::query("VACUUM INTO ?").bind(dest_text).execute(&mut conn).await;
    let _ = conn.close().await;
    if let Err(e) = done {
        let _ = std::fs::remove_file(dest);
        return Err(e.into());
    }
    let problems = sqlite_problems(dest, CheckDepth::Quick).await?;
    if !problems.is_empty() {
        let _ = std::fs::remove_file(dest);
        return Err(StoreError::Damaged { database: dest.display().to_string(), problems });
    }
    // VACUUM INTO does not sync what it wrote; a backup must survive a power cut.
    File::open(dest).and_then(|f| f.sync_all()).map_err(StoreError::file(format!("syncing {}", dest.display())))?;
    Ok(())
}

/// Syncs a directory, so that a rename in it survives a power cut.
fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir).and_then(|f| f.sync_all()).map_err(StoreError::file(format!("syncing {}", dir.display())))
}

/// Backs up a SQLite database to the new file `dest`, while a server may be writing it.
///
/// Refuses an existing `dest` unless `overwrite`; the backup is written to a temporary
/// file in `dest`'s directory, checked and synced, and renamed to `dest` only when
/// complete, so `dest` is never a partial file. A MySQL URL is refused: use
/// `mariadb-dump` (docs/server.md).
pub async fn backup_sqlite(database: &Database, dest: &Path, overwrite: bool) -> Result<BackupReport> {
    let started = Instant::now();
    let Some(source) = sqlite_file(database)? else {
        return Err(StoreError::InvalidInput(
            "backups of a MariaDB/MySQL store are made with mariadb-dump (see docs/server.md, \"Integrity and backups\")".into(),
        ));
    };
    if !source.is_file() {
        return Err(StoreError::NotFound(format!("no database file at {}", source.display())));
    }
    if !overwrite && dest.exists() {
        return Err(StoreError::AlreadyExists(format!("{} (use --force to replace it)", dest.display())));
    }
    let temp = temp_next_to(dest, "partial");
    vacuum_into(&source, &temp).await?;
    // Checked just above; an operator racing two backups to one name is not a case
    // worth a platform-specific no-replace rename.
    if !overwrite && dest.exists() {
        let _ = std::fs::remove_file(&temp);
        return Err(StoreError::AlreadyExists(format!("{} (use --force to replace it)", dest.display())));
    }
    std::fs::rename(&temp, dest).map_err(StoreError::file(format!("renaming the backup to {}", dest.display())))?;
    if let Some(dir) = dest.parent().filter(|d| !d.as_os_str().is_empty()) {
        sync_dir(dir)?;
    }
    let bytes = std::fs::metadata(dest).map_err(StoreError::file(format!("reading {}", dest.display())))?.len();
    Ok(BackupReport { path: dest.to_path_buf(), bytes, elapsed: started.elapsed() })
}

/// Replaces the SQLite database of `database` with the backup `backup`, for a stopped
/// server; returns where the old database was moved (`None` when there was none).
///
/// The backup must pass a quick check and hold Myriad's tables. The database's lock
/// ([`DatabaseLock`]) is taken for the whole restore, so it fails with
/// [`StoreError::InUse`] while a server runs. The old database and its WAL are renamed
/// to `<file>.replaced-<ms>` (and `-wal`), never deleted; its `-shm` is removed.
pub async fn restore_sqlite(database: &Database, backup: &Path) -> Result<Option<PathBuf>> {
    let Some(target) = sqlite_file(database)? else {
        return Err(StoreError::InvalidInput(
            "a MariaDB/MySQL store is restored with the mariadb client from a mariadb-dump file (see docs/server.md)"
                .into(),
        ));
    };
    if !backup.is_file() {
        return Err(StoreError::NotFound(format!("no backup file at {}", backup.display())));
    }
    let problems = sqlite_problems(backup, CheckDepth::Quick).await?;
    if !problems.is_empty() {
        return Err(StoreError::Damaged { database: backup.display().to_string(), problems });
    }
    require_myriad_schema(backup).await?;
    let dir = target.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(StoreError::file(format!("creating {}", dir.display())))?;
    let _lock = DatabaseLock::acquire(&target)?;
    let temp = temp_next_to(&target, "restoring");
    vacuum_into(backup, &temp).await?;
    let moved = if target.exists() {
        let aside = PathBuf::from(format!("{}.replaced-{}", target.display(), crate::model::now_ms()));
        // The WAL goes with its database: applied to the restored file it would corrupt it.
        let wal = PathBuf::from(format!("{}-wal", target.display()));
        if wal.exists() {
            let wal_aside = PathBuf::from(format!("{}-wal", aside.display()));
            std::fs::rename(&wal, &wal_aside).map_err(StoreError::file(format!("moving {} aside", wal.display())))?;
        }
        std::fs::rename(&target, &aside).map_err(StoreError::file(format!("moving {} aside", target.display())))?;
        Some(aside)
    } else {
        None
    };
    let shm = PathBuf::from(format!("{}-shm", target.display()));
    match std::fs::remove_file(&shm) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(StoreError::file(format!("removing {}", shm.display()))(e)),
    }
    std::fs::rename(&temp, &target)
        .map_err(StoreError::file(format!("renaming the restored copy to {}", target.display())))?;
    sync_dir(dir)?;
    Ok(moved)
}

/// Refuses a file that is a SQLite database but not Myriad's (no `users` table or no
/// migration history).
async fn require_myriad_schema(file: &Path) -> Result<()> {
    let mut conn = open_read_only(file).await?;
    let found: i64 = sqlx::query_scalar(
        "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name IN ('users', '_sqlx_migrations')",
    )
    .fetch_one(&mut conn)
    .await?;
    let _ = conn.close().await;
    if found != 2 {
        return Err(StoreError::InvalidInput(format!("{} is not a Myriad database", file.display())));
    }
    Ok(())
}

/// An exclusive lock on `<database file>.lock`, held by a running server and by a restore,
/// so that a restore never swaps the file under a server. The kernel releases it when
/// the holder exits, even when killed, so a crash leaves no stale lock.
#[derive(Debug)]
pub struct DatabaseLock {
    _file: File,
    path: PathBuf,
}

impl DatabaseLock {
    /// Takes the lock of the SQLite file `database_file`, or fails with
    /// [`StoreError::InUse`] when another process (or another handle in this one) holds
    /// it.
    pub fn acquire(database_file: &Path) -> Result<DatabaseLock> {
        let path = PathBuf::from(format!("{}.lock", database_file.display()));
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .map_err(StoreError::file(format!("opening the lock file {}", path.display())))?;
        match file.try_lock() {
            Ok(()) => Ok(DatabaseLock { _file: file, path }),
            Err(std::fs::TryLockError::WouldBlock) => {
                Err(StoreError::InUse { database: database_file.display().to_string(), lock: path })
            }
            Err(std::fs::TryLockError::Error(e)) => Err(StoreError::file(format!("locking {}", path.display()))(e)),
        }
    }

    /// Takes the lock of `database` when it is a SQLite file; `None` for MySQL.
    pub fn for_database(database: &Database) -> Result<Option<DatabaseLock>> {
        sqlite_file(database)?.map(|file| DatabaseLock::acquire(&file)).transpose()
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_lose_their_password() {
        assert_eq!(redacted("mysql://u:s3cr@t@db:3306/x"), "mysql://u:***@db:3306/x");
        assert_eq!(redacted("mysql://u@db/x"), "mysql://u@db/x");
        assert_eq!(redacted("mysql://db/x"), "mysql://db/x");
    }

    #[test]
    fn sqlite_files_of_databases() {
        let dir = Database::SqliteDir("/d".into());
        assert_eq!(sqlite_file(&dir).unwrap(), Some(PathBuf::from("/d/myriad.db")));
        assert_eq!(sqlite_file(&Database::Url("sqlite:///a/b.db".into())).unwrap(), Some(PathBuf::from("/a/b.db")));
        assert_eq!(sqlite_file(&Database::Url("mysql://u:p@h/d".into())).unwrap(), None);
    }
}
