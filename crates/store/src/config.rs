//! How to reach the database and how expensive password hashes are.

use std::path::PathBuf;
use std::time::Duration;

use crate::password::HashCost;

/// Name of the SQLite database file inside the data directory.
pub const SQLITE_FILE_NAME: &str = "myriad.db";

/// Which database the store talks to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Database {
    /// Embedded SQLite: the file [`SQLITE_FILE_NAME`] in this directory, both created on
    /// first use.
    SqliteDir(PathBuf),
    /// A database URL: `mysql://user:password@host:port/db` (MySQL or MariaDB), or
    /// `sqlite://path/to/file.db` / `sqlite:path` for a specific SQLite file.
    Url(String),
}

/// Settings of a [`Store`](crate::Store).
#[derive(Debug, Clone)]
pub struct StoreConfig {
    /// Where the data lives.
    pub database: Database,
    /// Argon2id cost of new password hashes (and of the dummy hash checked when a username
    /// does not exist, so that both paths take the same time).
    pub hash_cost: HashCost,
    /// Largest number of pooled connections. SQLite serialises writers anyway, so a few
    /// suffice there; MySQL benefits from more when many logins run at once.
    pub max_connections: u32,
    /// How long an operation waits for a connection before failing with
    /// [`StoreError::Unavailable`](crate::StoreError::Unavailable). While the database is
    /// down every operation takes this long, so keep it short.
    pub acquire_timeout: Duration,
    /// SQLite only: how long a statement waits for another connection's write lock before
    /// failing with `SQLITE_BUSY` (reported as unavailable).
    pub sqlite_busy_timeout: Duration,
    /// SQLite only: run `PRAGMA quick_check` on an existing file before opening it, and
    /// refuse a damaged one ([`StoreError::Damaged`](crate::StoreError::Damaged)). On by
    /// default; it reads the whole file once (about a second per GB on an SSD).
    pub check_at_open: bool,
}

impl StoreConfig {
    /// Embedded SQLite in `dir` with default settings.
    pub fn sqlite(dir: impl Into<PathBuf>) -> Self {
        Self::with_database(Database::SqliteDir(dir.into()))
    }

    /// A database URL (`mysql://...` or `sqlite:...`) with default settings.
    pub fn url(url: impl Into<String>) -> Self {
        Self::with_database(Database::Url(url.into()))
    }

    fn with_database(database: Database) -> Self {
        StoreConfig {
            database,
            hash_cost: HashCost::DEFAULT,
            max_connections: 8,
            acquire_timeout: Duration::from_secs(5),
            sqlite_busy_timeout: Duration::from_secs(5),
            check_at_open: true,
        }
    }

    /// Replaces the hash cost (builder style).
    pub fn hash_cost(mut self, cost: HashCost) -> Self {
        self.hash_cost = cost;
        self
    }
}
