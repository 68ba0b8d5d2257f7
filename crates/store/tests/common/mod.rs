//! Test harness: every store test is written once and run on each backend.
//!
//! [`backend_tests!`] turns `async fn name(db: TestDb)` into `name::sqlite` (a fresh
//! database in a temporary directory) and `name::mysql` (a fresh database on the server
//! named by `MYSQL_URL`, dropped afterwards). Without `MYSQL_URL` the MySQL variant prints
//! why it skips and passes, so a developer machine without MariaDB still runs the suite.

#![allow(dead_code, missing_docs)]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::time::Duration;

use myriad_store::{Database, Dialect, HashCost, Heightmap, MapId, NewMap, Store, StoreConfig, UserId, WorldBounds};
use sqlx::{Connection, Executor};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;

/// Runs each named `async fn(TestDb)` on SQLite and on MySQL. Attributes written before
/// a name (e.g. `#[ignore = "..."]`) go on both generated tests.
#[macro_export]
macro_rules! backend_tests {
    ($($(#[$meta:meta])* $name:ident),* $(,)?) => {$(
        mod $name {
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            $(#[$meta])*
            async fn sqlite() {
                let db = $crate::common::TestDb::sqlite().await;
                super::$name(db.clone()).await;
                db.cleanup().await;
            }

            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            $(#[$meta])*
            async fn mysql() {
                let Some(db) = $crate::common::TestDb::mysql().await else { return };
                super::$name(db.clone()).await;
                db.cleanup().await;
            }
        }
    )*};
}

/// The cheap hash cost used by tests.
pub const TEST_COST: HashCost = HashCost::INSECURE_FAST;

/// Test store settings: cheap hashes, short timeouts so outages are noticed quickly.
pub fn test_config(database: Database) -> StoreConfig {
    let mut config = match database {
        Database::SqliteDir(dir) => StoreConfig::sqlite(dir),
        Database::Url(url) => StoreConfig::url(url),
    };
    config.hash_cost = TEST_COST;
    config.acquire_timeout = Duration::from_secs(2);
    config.sqlite_busy_timeout = Duration::from_secs(2);
    config
}

#[derive(Clone)]
pub struct TestDb {
    pub store: Store,
    pub config: StoreConfig,
    kind: Arc<Kind>,
}

enum Kind {
    Sqlite { dir: tempfile::TempDir },
    MySql { admin_url: String, db_name: String, url: String },
}

static COUNTER: AtomicU32 = AtomicU32::new(0);

impl TestDb {
    pub async fn sqlite() -> TestDb {
        let dir = tempfile::tempdir().expect("temp dir");
        let config = test_config(Database::SqliteDir(dir.path().join("data")));
        let store = Store::open(&config).await.expect("open sqlite store");
        assert_eq!(store.dialect(), Dialect::Sqlite);
        TestDb { store, config, kind: Arc::new(Kind::Sqlite { dir }) }
    }

    /// A fresh database on the `MYSQL_URL` server, or `None` (after saying so) when the
    /// server is missing; under `MYRIAD_REQUIRE_MYSQL=1` a missing server fails instead.
    pub async fn mysql() -> Option<TestDb> {
        let admin_url = myriad_testenv::mysql_url()?;
        let db_name = format!(
            "myriad_t_{}_{}_{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed),
            myriad_store::now_ms() % 1_000_000
        );
        let mut admin = sqlx::mysql::MySqlConnection::connect(&admin_url).await.expect("connect to MYSQL_URL");
        admin
            .execute(sqlx::AssertSqlSafe(format!(
                "CREATE DATABASE `{db_name}` CHARACTER SET utf8mb4 COLLATE utf8mb4_unicode_ci"
            )))
            .await
            .expect("create test database (the MYSQL_URL user needs CREATE/DROP rights)");
        admin.close().await.ok();
        let url = with_database(&admin_url, &db_name);
        let config = test_config(Database::Url(url.clone()));
        let store = Store::open(&config).await.expect("open mysql store");
        assert_eq!(store.dialect(), Dialect::MySql);
        Some(TestDb { store, config, kind: Arc::new(Kind::MySql { admin_url, db_name, url }) })
    }

    pub fn dialect(&self) -> Dialect {
        self.store.dialect()
    }

    /// Opens a second store on the same database (another pool, migrations re-checked).
    pub async fn reopen(&self) -> Store {
        Store::open(&self.config).await.expect("reopen store")
    }

    /// A store on the same database whose connection the returned [`Outage`] can cut.
    pub async fn store_with_outage(&self) -> (Store, Outage) {
        match &*self.kind {
            Kind::Sqlite { .. } => {
                let Database::SqliteDir(dir) = &self.config.database else {
                    unreachable!("sqlite test db has a directory")
                };
                let mut config = self.config.clone();
                config.sqlite_busy_timeout = Duration::from_millis(50);
                let store = Store::open(&config).await.expect("open store");
                let path = dir.join(myriad_store::SQLITE_FILE_NAME);
                (store, Outage::SqliteLock { path, lock: None })
            }
            Kind::MySql { url, .. } => {
                let proxy = Proxy::start(upstream_addr(url)).await;
                let proxied = url.replacen(&upstream_authority(url), &proxy.addr.to_string(), 1);
                let mut config = self.config.clone();
                config.database = Database::Url(proxied);
                config.acquire_timeout = Duration::from_millis(500);
                let store = Store::open(&config).await.expect("open store through proxy");
                (store, Outage::Proxy(proxy))
            }
        }
    }

    /// Closes the store and drops the MySQL database. (A test that panics skips this;
    /// [`Kind`]'s `Drop` then drops the database from a helper thread.)
    pub async fn cleanup(&self) {
        self.store.close().await;
        if let Kind::MySql { admin_url, db_name, .. } = &*self.kind {
            drop_database(admin_url, db_name).await;
        }
    }

    /// A user with a unique name and password `pw-<name>`.
    pub async fn user(&self, name: &str) -> UserId {
        self.store.create_user(name, &format!("pw-{name}")).await.expect("create user")
    }

    /// A small map with the given name and no terrain.
    pub async fn map(&self, name: &str) -> MapId {
        Self::map_on(&self.store, name).await
    }

    /// [`TestDb::map`] on any store.
    pub async fn map_on(store: &Store, name: &str) -> MapId {
        store
            .create_map(&NewMap {
                name: name.to_owned(),
                heightmap: Heightmap::None,
                max_height: 10.0,
                bounds: WorldBounds { min: [0.0, 0.0, 0.0], max: [100.0, 50.0, 100.0] },
            })
            .await
            .expect("create map")
    }
}

async fn drop_database(admin_url: &str, db_name: &str) {
    if let Ok(mut admin) = sqlx::mysql::MySqlConnection::connect(admin_url).await {
        let _ = admin.execute(sqlx::AssertSqlSafe(format!("DROP DATABASE IF EXISTS `{db_name}`"))).await;
        admin.close().await.ok();
    }
}

impl Drop for Kind {
    fn drop(&mut self) {
        if let Kind::MySql { admin_url, db_name, .. } = self
            && std::thread::panicking()
        {
            // The test failed before `cleanup`: drop its database on a private runtime
            // (the test's runtime may be gone or blocked).
            let (admin_url, db_name) = (admin_url.clone(), db_name.clone());
            let _ = std::thread::spawn(move || {
                if let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() {
                    rt.block_on(drop_database(&admin_url, &db_name));
                }
            })
            .join();
        }
    }
}

/// Replaces the database name (the URL path) of a mysql:// URL.
fn with_database(url: &str, db: &str) -> String {
    let (base, query) = match url.split_once('?') {
        Some((b, q)) => (b, Some(q)),
        None => (url, None),
    };
    let scheme_end = base.find("://").map_or(0, |i| i + 3);
    let host_part = match base[scheme_end..].find('/') {
        Some(i) => &base[..scheme_end + i],
        None => base,
    };
    match query {
        Some(q) => format!("{host_part}/{db}?{q}"),
        None => format!("{host_part}/{db}"),
    }
}

/// `host:port` of a mysql:// URL.
fn upstream_authority(url: &str) -> String {
    let rest = &url[url.find("://").map_or(0, |i| i + 3)..];
    let rest = rest.split(['/', '?']).next().unwrap_or(rest);
    let host = rest.rsplit_once('@').map_or(rest, |(_, h)| h);
    host.to_owned()
}

fn upstream_addr(url: &str) -> SocketAddr {
    let authority = upstream_authority(url);
    let with_port = if authority.contains(':') { authority } else { format!("{authority}:3306") };
    let with_port = with_port.replace("localhost", "127.0.0.1");
    with_port.parse().expect("MYSQL_URL host must be an IP or localhost")
}

/// A way to make the database unreachable for one store and bring it back.
pub enum Outage {
    /// SQLite: another connection holds the write lock, so writes fail with SQLITE_BUSY.
    SqliteLock { path: PathBuf, lock: Option<sqlx::sqlite::SqliteConnection> },
    /// MySQL: the store talks through a TCP proxy that can drop every connection.
    Proxy(Proxy),
}

impl Outage {
    pub async fn cut(&mut self) {
        match self {
            Outage::SqliteLock { path, lock } => {
                let options = sqlx::sqlite::SqliteConnectOptions::new().filename(&*path);
                let mut conn =
                    sqlx::sqlite::SqliteConnection::connect_with(&options).await.expect("open locking connection");
                conn.execute("BEGIN EXCLUSIVE").await.expect("take write lock");
                *lock = Some(conn);
            }
            Outage::Proxy(proxy) => proxy.set_up(false),
        }
    }

    pub async fn restore(&mut self) {
        match self {
            Outage::SqliteLock { lock, .. } => {
                if let Some(mut conn) = lock.take() {
                    conn.execute("ROLLBACK").await.expect("release write lock");
                    conn.close().await.ok();
                }
            }
            Outage::Proxy(proxy) => proxy.set_up(true),
        }
    }
}

/// A TCP forwarder to MariaDB that can refuse and drop connections on demand.
pub struct Proxy {
    pub addr: SocketAddr,
    up: Arc<AtomicBool>,
    /// Bumped on every cut: forwarding tasks watch it and drop their sockets.
    generation: watch::Sender<u64>,
}

impl Proxy {
    async fn start(upstream: SocketAddr) -> Proxy {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind proxy");
        let addr = listener.local_addr().expect("proxy addr");
        let up = Arc::new(AtomicBool::new(true));
        let (generation, _) = watch::channel(0u64);
        let accept_up = up.clone();
        let accept_gen = generation.clone();
        tokio::spawn(async move {
            loop {
                let Ok((client, _)) = listener.accept().await else {
                    return;
                };
                if !accept_up.load(Ordering::SeqCst) {
                    drop(client);
                    continue;
                }
                let mut cut = accept_gen.subscribe();
                tokio::spawn(async move {
                    let Ok(mut server) = TcpStream::connect(upstream).await else {
                        return;
                    };
                    let mut client = client;
                    tokio::select! {
                        _ = tokio::io::copy_bidirectional(&mut client, &mut server) => {}
                        _ = cut.changed() => {}
                    }
                });
            }
        });
        Proxy { addr, up, generation }
    }

    fn set_up(&self, up: bool) {
        self.up.store(up, Ordering::SeqCst);
        if !up {
            self.generation.send_modify(|g| *g += 1);
        }
    }
}

/// Polls `check` every 20 ms until it holds or `timeout` passes; returns whether it held.
pub async fn wait_for(timeout: Duration, mut check: impl FnMut() -> bool) -> bool {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        if check() {
            return true;
        }
        if tokio::time::Instant::now() >= deadline {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}
