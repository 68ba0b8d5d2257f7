//! The store's error type.
//!
//! Callers branch on the variant: a login service answers "wrong credentials" and
//! "database unavailable" differently, and the write-behind [`Persister`](crate::Persister)
//! retries only [`StoreError::Unavailable`]. No variant ever carries a password or a hash.

/// Everything a store operation can fail with.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The requested row does not exist.
    #[error("not found: {0}")]
    NotFound(String),
    /// The username does not exist or the password does not match. The two cases are
    /// deliberately indistinguishable, so a caller cannot probe for usernames.
    #[error("wrong username or password")]
    WrongCredentials,
    /// A user with this username (compared case-insensitively) already exists.
    #[error("username already taken")]
    UsernameTaken,
    /// A row with this key already exists (e.g. a player state for the same user and map,
    /// or a static object id on a map).
    #[error("already exists: {0}")]
    AlreadyExists(String),
    /// The arguments were rejected before reaching the database.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// The database could not be reached or is temporarily unable to serve (connection
    /// refused or lost, pool timeout, SQLite file locked). Retrying later may succeed.
    #[error("database unavailable: {0}")]
    Unavailable(#[source] sqlx::Error),
    /// Any other database error (constraint violation, bad data, migration failure...).
    #[error("database error: {0}")]
    Database(#[source] sqlx::Error),
    /// A migration could not be applied.
    #[error("migration failed: {0}")]
    Migration(#[source] sqlx::migrate::MigrateError),
    /// Password hashing failed, or a background task panicked or was cancelled.
    #[error("internal error: {0}")]
    Internal(String),
    /// The password was right but the account is disabled by an operator
    /// ([`Store::set_disabled`](crate::Store::set_disabled)). Only told after a correct
    /// password, so it reveals nothing to someone guessing.
    #[error("the account is disabled")]
    AccountDisabled,
    /// The password was right but the account is banned
    /// ([`Store::ban`](crate::Store::ban)); `until_ms` is the end of the ban (milliseconds
    /// since the Unix epoch), `None` for a ban without end.
    #[error("the account is banned")]
    AccountBanned {
        /// When the ban ends; `None`: it does not.
        until_ms: Option<i64>,
    },
    /// The database file (or a table, on MariaDB) failed its integrity check: nothing is
    /// written to it. `database` names the file or the database (never a password).
    #[error(
        "database {database} is damaged ({} problem(s); first: {}): it is left untouched. \
         Stop the server and restore a backup with `myriad db restore BACKUP`; \
         `myriad db check --full` lists every problem",
        problems.len(),
        problems.first().map_or("unknown", String::as_str)
    )]
    Damaged {
        /// The file (SQLite) or database (MariaDB) checked.
        database: String,
        /// What the check reported, one line each.
        problems: Vec<String>,
    },
    /// Another process holds the database's lock file (a running server): a restore
    /// must wait until it stops.
    #[error("database {database} is in use (another process holds {}); stop the server first", lock.display())]
    InUse {
        /// The database file.
        database: String,
        /// The lock file held by the other process.
        lock: std::path::PathBuf,
    },
    /// A file operation of a backup or a restore failed.
    #[error("{what}: {source}")]
    File {
        /// What was being done, with the path.
        what: String,
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

impl StoreError {
    /// Whether retrying the same operation later may succeed (the database was unreachable).
    pub fn is_transient(&self) -> bool {
        matches!(self, StoreError::Unavailable(_))
    }
}

/// SQLite result codes that mean "try again later" rather than "this statement is wrong":
/// SQLITE_BUSY (5), SQLITE_LOCKED (6), SQLITE_READONLY (8: the file or its directory lost
/// write permission, an operator can give it back), SQLITE_IOERR (10), SQLITE_FULL (13)
/// and SQLITE_CANTOPEN (14), with their extended variants (the low byte is the primary
/// code). The persister keeps states queued and retries these instead of dropping rows.
const SQLITE_TRANSIENT: [i64; 6] = [5, 6, 8, 10, 13, 14];

/// MySQL/MariaDB server errors that mean the server is going away or overloaded:
/// ER_CON_COUNT_ERROR (1040), ER_SERVER_SHUTDOWN (1053), ER_LOCK_WAIT_TIMEOUT (1205),
/// ER_LOCK_DEADLOCK (1213), ER_QUERY_INTERRUPTED (1317), ER_CONNECTION_KILLED (1927).
const MYSQL_TRANSIENT: [i64; 6] = [1040, 1053, 1205, 1213, 1317, 1927];

/// Whether a sqlx error means "the database is unreachable or busy, try again later".
pub(crate) fn is_transient(err: &sqlx::Error) -> bool {
    use sqlx::Error as E;
    match err {
        E::Io(_) | E::Tls(_) | E::PoolTimedOut | E::PoolClosed | E::WorkerCrashed => true,
        // A broken packet stream is what a connection cut mid-reply looks like.
        E::Protocol(_) => true,
        E::Database(db) => {
            if let Some(my) = db.try_downcast_ref::<sqlx::mysql::MySqlDatabaseError>() {
                // SQLSTATE class 08 is "connection exception".
                MYSQL_TRANSIENT.contains(&i64::from(my.number()))
                    || my.code().is_some_and(|state| state.starts_with("08"))
            } else if db.try_downcast_ref::<sqlx::sqlite::SqliteError>().is_some() {
                // SQLite reports its extended result code; the low byte is the primary code.
                db.code().and_then(|c| c.parse::<i64>().ok()).is_some_and(|c| SQLITE_TRANSIENT.contains(&(c & 0xff)))
            } else {
                false
            }
        }
        _ => false,
    }
}

impl From<sqlx::Error> for StoreError {
    fn from(err: sqlx::Error) -> Self {
        if is_transient(&err) { StoreError::Unavailable(err) } else { StoreError::Database(err) }
    }
}

impl From<sqlx::migrate::MigrateError> for StoreError {
    fn from(err: sqlx::migrate::MigrateError) -> Self {
        use sqlx::migrate::MigrateError as M;
        match err {
            M::Execute(e) | M::ExecuteMigration(e, _) if is_transient(&e) => StoreError::Unavailable(e),
            other => StoreError::Migration(other),
        }
    }
}

/// Whether a database error is a unique-key (or primary-key) violation.
pub(crate) fn is_unique_violation(err: &sqlx::Error) -> bool {
    err.as_database_error().is_some_and(|db| db.is_unique_violation())
}

impl StoreError {
    /// A [`StoreError::File`] for `what` (which names the path).
    pub(crate) fn file(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> StoreError {
        let what = what.into();
        move |source| StoreError::File { what, source }
    }
}

/// Shorthand for results of store operations.
pub type Result<T, E = StoreError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn connection_errors_are_transient() {
        let io = sqlx::Error::Io(std::io::Error::from(std::io::ErrorKind::ConnectionRefused));
        assert!(StoreError::from(io).is_transient());
        assert!(StoreError::from(sqlx::Error::PoolTimedOut).is_transient());
        assert!(StoreError::from(sqlx::Error::PoolClosed).is_transient());
        assert!(!StoreError::from(sqlx::Error::RowNotFound).is_transient());
        assert!(!StoreError::WrongCredentials.is_transient());
    }

    #[test]
    fn messages_never_carry_secrets() {
        // The variants that talk about credentials have fixed messages.
        assert_eq!(StoreError::WrongCredentials.to_string(), "wrong username or password");
        assert_eq!(StoreError::UsernameTaken.to_string(), "username already taken");
    }
}
