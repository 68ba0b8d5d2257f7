//! The [`Store`] handle and how it opens: pool, pragmas, migrations, dummy hash.

use std::borrow::Cow;
use std::sync::Arc;

use sqlx::any::{AnyConnectOptions, AnyPoolOptions};
use sqlx::migrate::{Migration, MigrationType, Migrator};
use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{AnyConnection, AnyPool, AssertSqlSafe, ConnectOptions, Connection, Executor, SqlSafeStr};

use crate::config::{Database, SQLITE_FILE_NAME, StoreConfig};
use crate::error::{Result, StoreError};
use crate::integrity::{CheckDepth, sqlite_file, sqlite_problems};
use crate::password::{self, HashCost};

/// The database engine behind a [`Store`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dialect {
    /// Embedded SQLite.
    Sqlite,
    /// MySQL or MariaDB.
    MySql,
}

const SQLITE_INIT: &str = include_str!("../migrations/sqlite/0001_init.sql");
const MYSQL_INIT: &str = include_str!("../migrations/mysql/0001_init.sql");
const SQLITE_PROBE: &str = include_str!("../migrations/sqlite/0002_probe.sql");
const MYSQL_PROBE: &str = include_str!("../migrations/mysql/0002_probe.sql");
const SQLITE_ACCOUNTS: &str = include_str!("../migrations/sqlite/0003_account_control.sql");
const MYSQL_ACCOUNTS: &str = include_str!("../migrations/mysql/0003_account_control.sql");
const SQLITE_AUDIT: &str = include_str!("../migrations/sqlite/0004_admin_audit.sql");
const MYSQL_AUDIT: &str = include_str!("../migrations/mysql/0004_admin_audit.sql");

/// The embedded migrations of one dialect.
fn migrator(dialect: Dialect) -> Migrator {
    let (init, probe, accounts, audit) = match dialect {
        Dialect::Sqlite => (SQLITE_INIT, SQLITE_PROBE, SQLITE_ACCOUNTS, SQLITE_AUDIT),
        Dialect::MySql => (MYSQL_INIT, MYSQL_PROBE, MYSQL_ACCOUNTS, MYSQL_AUDIT),
    };
    let migration = |version, name, sql: &'static str| {
        Migration::new(version, Cow::Borrowed(name), MigrationType::Simple, sql.into_sql_str(), false)
    };
    Migrator::with_migrations(vec![
        migration(1, "init", init),
        migration(2, "probe", probe),
        migration(3, "account_control", accounts),
        migration(4, "admin_audit", audit),
    ])
}

/// Handle to the database: cheap to clone (the pool is shared), safe to use from any task.
///
/// Every method is `async` and never blocks the calling thread: SQL runs on the pool's
/// connections, password hashing on tokio's blocking pool.
///
/// # How it works
/// Both backends go through one [`AnyPool`], so every query is written once with `?`
/// placeholders and only basic types (i64, f64, text, blobs). The few statements whose
/// syntax differs (upserts, insert-or-ignore) pick their text from [`Dialect`]. The schema
/// is embedded at compile time, one folder per backend under `migrations/`, and applied
/// by sqlx's migrator when the store opens (it records applied versions in
/// `_sqlx_migrations`, so reopening is a no-op).
///
/// SQLite connections get `journal_mode=WAL` (readers never block the writer),
/// `synchronous=NORMAL` (safe with WAL: a power cut may lose the last commits, never
/// corrupt the file), `foreign_keys=ON` and a busy timeout, on every new connection.
#[derive(Clone)]
pub struct Store {
    pub(crate) pool: AnyPool,
    pub(crate) dialect: Dialect,
    pub(crate) hash_cost: HashCost,
    /// A hash of a fixed string at the configured cost, verified when a username does not
    /// exist so that a failed login costs the same time whether or not the user exists.
    pub(crate) dummy_hash: Arc<str>,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // The dummy hash is harmless, but hashes are never printed on principle.
        f.debug_struct("Store")
            .field("dialect", &self.dialect)
            .field("hash_cost", &self.hash_cost)
            .finish_non_exhaustive()
    }
}

impl Store {
    /// Opens (creating if needed) the database described by `config` and applies pending
    /// migrations.
    ///
    /// Fails with [`StoreError::Unavailable`] when the server cannot be reached,
    /// [`StoreError::InvalidInput`] for a malformed URL or hash cost, and
    /// [`StoreError::Migration`] when the schema cannot be brought up to date. An
    /// existing SQLite file first gets `PRAGMA quick_check` (unless
    /// [`StoreConfig::check_at_open`] is off) and a damaged one fails with
    /// [`StoreError::Damaged`], untouched.
    pub async fn open(config: &StoreConfig) -> Result<Store> {
        sqlx::any::install_default_drivers();
        config.hash_cost.validate()?;

        let (dialect, options) = connect_options(&config.database).await?;
        // A damaged SQLite file is refused before anything (the WAL pragma, a migration,
        // the caller) writes to it: writing into malformed pages spreads the damage.
        if dialect == Dialect::Sqlite
            && config.check_at_open
            && let Some(file) = sqlite_file(&config.database)?.filter(|f| f.is_file())
        {
            let problems = sqlite_problems(&file, CheckDepth::Quick).await?;
            if !problems.is_empty() {
                return Err(StoreError::Damaged { database: file.display().to_string(), problems });
            }
        }
        let busy_ms = i64::try_from(config.sqlite_busy_timeout.as_millis()).unwrap_or(i64::MAX);
        let pragmas = format!(
            "PRAGMA journal_mode = WAL; PRAGMA synchronous = NORMAL; \
             PRAGMA foreign_keys = ON; PRAGMA busy_timeout = {busy_ms};"
        );
        // One connection by hand first: the pool retries a failing connect until its
        // acquire timeout and then only says "pool timed out", while the operator needs
        // the real cause ("file is not a database", "access denied", "connection
        // refused").
        {
            let mut first = tokio::time::timeout(config.acquire_timeout, AnyConnection::connect_with(&options))
                .await
                .map_err(|_| StoreError::Unavailable(sqlx::Error::PoolTimedOut))??;
            if dialect == Dialect::Sqlite {
                first.execute(AssertSqlSafe(pragmas.clone())).await?;
                // Reading the schema fails on a file that is not a database.
                first.execute("SELECT count(*) FROM sqlite_master").await?;
            }
            first.close().await?;
        }
        let mut pool_options = AnyPoolOptions::new()
            .max_connections(config.max_connections.max(1))
            .acquire_timeout(config.acquire_timeout);
        if dialect == Dialect::Sqlite {
            pool_options = pool_options.after_connect(move |conn, _meta| {
                let pragmas = pragmas.clone();
                Box::pin(async move {
                    conn.execute(AssertSqlSafe(pragmas)).await?;
                    Ok(())
                })
            });
        }
        let pool = pool_options.connect_with(options).await?;
        migrator(dialect).run(&pool).await?;

        let cost = config.hash_cost;
        let dummy_hash =
            password::spawn_blocking(move || password::hash_blocking(cost, b"myriad/no-such-user")).await??;

        tracing::info!(?dialect, "store opened");
        Ok(Store { pool, dialect, hash_cost: cost, dummy_hash: dummy_hash.into() })
    }

    /// Proves that the database accepts writes: rewrites the one row of `store_probe` in a
    /// committed transaction. The server calls it before it accepts players, so a
    /// read-only file, a full disk or a user without write grants stops the start with
    /// the database's own error instead of dropping every position later.
    pub async fn check_writable(&self) -> Result<()> {
        let mut tx = self.pool.begin().await?;
        sqlx::query("DELETE FROM store_probe").execute(&mut *tx).await?;
        sqlx::query("INSERT INTO store_probe (id, written_at) VALUES (1, ?)")
            .bind(crate::model::now_ms())
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(())
    }

    /// The engine behind this store.
    pub fn dialect(&self) -> Dialect {
        self.dialect
    }

    /// The cost used for new password hashes.
    pub fn hash_cost(&self) -> HashCost {
        self.hash_cost
    }

    /// Closes every pooled connection, waiting for operations in flight. Later calls fail
    /// with [`StoreError::Unavailable`].
    pub async fn close(&self) {
        self.pool.close().await;
    }
}

/// Parses the configured location into connect options, creating the SQLite directory.
async fn connect_options(database: &Database) -> Result<(Dialect, AnyConnectOptions)> {
    match database {
        Database::SqliteDir(dir) => {
            tokio::fs::create_dir_all(dir).await.map_err(|e| {
                StoreError::InvalidInput(format!("cannot create data directory {}: {e}", dir.display()))
            })?;
            // Build the URL from the path so that spaces, `?` and `#` are escaped.
            let url =
                SqliteConnectOptions::new().filename(dir.join(SQLITE_FILE_NAME)).create_if_missing(true).to_url_lossy();
            Ok((Dialect::Sqlite, AnyConnectOptions::from_url(&url)?))
        }
        Database::Url(url) => {
            let dialect = if url.starts_with("mysql:") || url.starts_with("mariadb:") {
                Dialect::MySql
            } else if url.starts_with("sqlite:") {
                Dialect::Sqlite
            } else {
                return Err(StoreError::InvalidInput(
                    "database URL must start with mysql:, mariadb: or sqlite:".into(),
                ));
            };
            let mut options: AnyConnectOptions =
                url.parse().map_err(|e: sqlx::Error| StoreError::InvalidInput(format!("bad database URL: {e}")))?;
            if dialect == Dialect::Sqlite && !url.contains("mode=") {
                // Like the data-directory form, create the file on first use.
                options.database_url.query_pairs_mut().append_pair("mode", "rwc");
            }
            Ok((dialect, options))
        }
    }
}
