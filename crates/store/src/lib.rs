//! SQL persistence of Myriad: users, maps, per-map player state and static objects.
//!
//! One [`Store`] API over two backends, both through sqlx's `Any` driver:
//! - **embedded SQLite** (the default): a file in a data directory, created on first
//!   run, in WAL mode with a busy timeout;
//! - **MySQL / MariaDB**, given a `mysql://` URL, for production.
//!
//! The schema is embedded and migrated when the store opens (one folder of migrations per
//! backend under `migrations/`). Methods mirror the reference design's stored procedures
//! (`NewUser`, `CheckUserAndRetrieveInfo`, `NewMap`, `GetMapStaticObjects`, ...), plus
//! batched writes. Passwords are hashed with Argon2id on tokio's blocking pool.
//!
//! [`Persister`] sits in front of the store for the tick loop: it takes position
//! snapshots without ever waiting on the database, coalesces them per player and writes
//! them in batches, riding out database outages.
//!
//! ```no_run
//! # async fn demo() -> Result<(), myriad_store::StoreError> {
//! use myriad_store::{Store, StoreConfig};
//! let store = Store::open(&StoreConfig::sqlite("data")).await?;
//! store.seed_users(10).await?;
//! let user = store.check_credentials("user3", "password3").await?;
//! # Ok(()) }
//! ```

mod accounts;
mod audit;
mod config;
mod error;
mod integrity;
mod maps;
mod model;
mod names;
mod password;
mod persister;
mod players;
mod store;
mod users;

pub use accounts::{Account, Ban, MAX_BAN_REASON_LEN, validate_ban_reason};
pub use audit::{AuditEntry, MAX_AUDIT_LIST};
pub use config::{Database, SQLITE_FILE_NAME, StoreConfig};
pub use error::{Result, StoreError};
pub use integrity::{
    BackupReport, CheckDepth, DatabaseLock, IntegrityReport, backup_sqlite, check_database, restore_sqlite, sqlite_file,
};
pub use maps::{MAX_HEIGHTMAP_PATH_LEN, MAX_HEIGHTMAP_SAMPLES, MAX_MAP_NAME_LEN};
pub use model::{
    Heightmap, LoginInfo, MapId, MapInfo, MapSummary, NewMap, PlayerState, SeedReport, StaticObject, StoredShape,
    UserId, WorldBounds, now_ms,
};
pub use names::{MAX_USERNAME_LEN, validate_username};
pub use password::{HashCost, MAX_PASSWORD_LEN, hash_password, validate_password, verify_password};
pub use password::{HashPoolStats, configure_hash_pool, hash_pool_stats};
pub use persister::{FlushReport, Persister, PersisterConfig, PersisterStats, ShutdownLoss, SubmitError};
pub use store::{Dialect, Store};
pub use users::{MAX_SEED_USERS, User};
