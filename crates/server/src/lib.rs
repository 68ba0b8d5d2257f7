//! The authoritative game server of Myriad, as a library (`myriad serve` and
//! `myriad demo` are thin front ends).
//!
//! - [`config`]: [`ServerConfig`], a TOML file with per-key overrides.
//! - `tick` (private): the tick loop thread that owns the world and orchestrates one
//!   tick: receive, step, outbound, send, persistence, dilation, metrics.
//! - `session` (private): the sessions table, the one owner of every player's session.
//! - `inbound` (private): receiving and applying authenticated datagrams.
//! - [`outbound`]: the AOI query, interest selection, packing and sealing behind one
//!   trait ([`outbound::Outbound`]).
//! - [`transport`]: the datagram transport trait, UDP and in memory.
//! - [`stages`]: the stages of a server tick ([`TickStage`]), their times, and what a
//!   tick did ([`TickWork`]).
//! - `scripted` (feature `harness`): the server driven by a scripted sequence of actions
//!   in memory (the check that the server and `myriad sim` agree on the world).
//! - [`login`]: the TLS login service and its rate limiter.
//! - [`dilation`]: time dilation under overload.
//! - [`world`]: building the served map and its NPCs.
//! - [`tls`]: certificates (self-signed for development).
//! - [`status`]: what the tick loop reports each second.
//! - [`tick_bench`]: the end-to-end tick benchmark (the real tick, bots on loopback).
//! - [`admin`]: the admin API and web console on a listener of their own (issue 29).
//!
//! # Architecture
//!
//! One thread runs the tick loop and owns the world, the physics backend, the sessions
//! and the transport; nothing else touches them. A tokio runtime (two worker threads) runs the
//! login service, the database writer ([`myriad_store::Persister`]) and the metrics
//! endpoint. The login service reaches the tick loop only through a channel of join
//! requests, answered on a oneshot channel, so password hashing and database round
//! trips never delay a tick.
//!
//! ```no_run
//! # fn main() -> Result<(), myriad_server::ServerError> {
//! let server = myriad_server::ServerHandle::start(myriad_server::ServerConfig::default())?;
//! println!("login on {}", server.login_addr());
//! server.shutdown()?;
//! # Ok(()) }
//! ```

pub mod admin;
pub mod backups;
pub mod config;
pub mod dilation;
pub mod error;
pub mod gate;
mod inbound;
pub mod login;
pub mod outbound;
pub mod receiver;
pub mod registry;
#[cfg(feature = "harness")]
pub mod scripted;
mod session;
pub mod stages;
pub mod status;
mod tick;
pub mod tick_bench;
pub mod tls;
pub mod transport;
pub mod world;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::thread::JoinHandle;
use std::time::Duration;

pub use config::{OutboundKind, ServerConfig};
pub use error::{ConfigError, ServerError};
pub use myriad_physics::BackendKind;
pub use session::PLAYER_SHAPE;
pub use stages::{STAGES, StageTimes, TickStage, TickWork};
pub use status::ServerStatus;

use myriad_net::{Endpoint, EndpointConfig};
use myriad_store::{Database, FlushReport, Persister, PersisterConfig, PersisterStats, Store, StoreConfig};

use crate::status::ServerShared;

/// A running server. Dropping it shuts it down gracefully (as [`ServerHandle::shutdown`]).
pub struct ServerHandle {
    runtime: Option<tokio::runtime::Runtime>,
    tick_thread: Option<JoinHandle<()>>,
    shared: Arc<ServerShared>,
    persister: Persister,
    store: Store,
    login_addr: SocketAddr,
    udp_addr: SocketAddr,
    certificate: PathBuf,
    shutdown_flush: Duration,
    /// The SQLite database's lock file, held while the server runs (released when the
    /// handle drops, after the store closed), so that `myriad db restore` refuses to swap
    /// the file under it. `None` on MariaDB.
    _database_lock: Option<myriad_store::DatabaseLock>,
    /// The admin API, when `admin_addr` is set.
    admin: Option<admin::AdminRunning>,
}

impl std::fmt::Debug for ServerHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServerHandle").field("login", &self.login_addr).field("udp", &self.udp_addr).finish()
    }
}

/// The store configuration of a server configuration.
pub fn store_config(config: &ServerConfig) -> StoreConfig {
    let database = if config.database_url.is_empty() {
        Database::SqliteDir(config.data_dir.clone())
    } else {
        Database::Url(config.database_url.clone())
    };
    let mut store = StoreConfig::sqlite(&config.data_dir).hash_cost(config.hash_cost());
    store.database = database;
    store
}

/// Makes the tick's physics backend on the tick thread, from the world it will step
/// ([`ServerHandle::start_with`]).
pub type BackendFactory =
    Box<dyn FnOnce(&mut myriad_core::World) -> Result<Box<dyn myriad_physics::Backend>, ServerError> + Send>;

impl ServerHandle {
    /// Opens the store, builds the world, binds the UDP and login ports, and starts the
    /// tick loop and the login service. Call it outside any tokio runtime: the server
    /// owns its own.
    ///
    /// The physics backend comes from the one backend factory,
    /// [`myriad_cuda::create_backend`], on the tick thread (GPU contexts belong to the
    /// thread that uses them): `auto` picks the GPU when one is usable, else `cpu`.
    pub fn start(config: ServerConfig) -> Result<ServerHandle, ServerError> {
        ServerHandle::start_with(config, None, None)
    }

    /// [`ServerHandle::start`] with another physics backend and a session registry:
    /// `backend` is called on the tick thread with the prepared world (which it may
    /// adjust) and returns the backend; `registry` shares sessions with other servers. A
    /// zones gateway serves this way, with a backend whose step is done by the zones
    /// (`myriad_zone::ZonesBackend`) and the cluster's registry.
    pub fn start_with(
        config: ServerConfig,
        backend: Option<BackendFactory>,
        registry: Option<Box<dyn registry::SessionRegistry>>,
    ) -> Result<ServerHandle, ServerError> {
        config.validate()?;
        std::fs::create_dir_all(&config.data_dir)
            .map_err(|e| ServerError::io(format!("creating data directory {}", config.data_dir.display()), e))?;
        // The verification pool takes its size at its first use; a second server in the
        // same process (tests) shares the first one's pool.
        // Password checks run a little below the tick (like the async runtime's workers):
        // a burst of logins then takes the CPU the tick leaves, not the tick's share.
        if !myriad_store::configure_hash_pool(config.hashing_threads(), || set_thread_nice(IO_THREAD_NICE)) {
            tracing::debug!("the password-verification pool was already running");
        }
        let started = std::sync::atomic::AtomicUsize::new(0);
        let background_low_priority = config.background_low_priority;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(IO_WORKERS)
            .thread_name("myriad-io")
            .on_thread_start(move || {
                // Tokio starts its worker threads first, when the runtime is built; every
                // later thread is a blocking-pool thread (file work, the database's
                // blocking calls): those go lowest, the workers a little below the tick.
                let blocking = started.fetch_add(1, Ordering::Relaxed) >= IO_WORKERS;
                set_thread_nice(if blocking && background_low_priority {
                    BLOCKING_THREAD_NICE
                } else {
                    IO_THREAD_NICE
                });
            })
            .enable_all()
            .build()
            .map_err(|e| ServerError::io("starting the async runtime", e))?;
        let store_settings = store_config(&config);
        // Before the store opens (and may create the file): a restore in progress holds it.
        let database_lock = myriad_store::DatabaseLock::for_database(&store_settings.database)?;
        let store = runtime.block_on(Store::open(&store_settings))?;
        // A real write before any player is accepted: a store that cannot write stops
        // the start here, with the database's own error.
        runtime.block_on(store.check_writable()).map_err(ServerError::NotWritable)?;
        let prepared = runtime.block_on(world::prepare(&config, &store))?;
        tracing::info!(
            map = %prepared.description.name,
            npcs = prepared.world.dynamics.len(),
            statics = prepared.description.static_primitives,
            "world ready"
        );
        let endpoints = Endpoint::bind_group(EndpointConfig::new(config.udp_addr), config.udp_socket_count())?;
        let udp_addr = endpoints[0].local_addr();
        let certificate = tls::certificate_paths(&config)?.0;
        let acceptor = tokio_rustls::TlsAcceptor::from(tls::server_config(&config)?);
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind(config.login_addr))
            .map_err(|e| ServerError::io(format!("binding the login service to {}", config.login_addr), e))?;
        let login_addr = listener.local_addr().map_err(|e| ServerError::io("login address", e))?;
        let persister = {
            let _guard = runtime.enter();
            let interval = Duration::from_millis(config.persist_interval_ms);
            // Retries at most 2 s apart, so that the log says "back up" soon after the
            // database returns (the default backoff grows to 10 s).
            let retry_max = Duration::from_secs(2);
            Persister::start(store.clone(), PersisterConfig { interval, retry_max, ..PersisterConfig::default() })?
        };
        if let Some(addr) = config.metrics_addr {
            let _guard = runtime.enter();
            install_metrics(addr)?;
            tracing::info!(%addr, "metrics on /metrics");
        }
        let shared = Arc::new(ServerShared::default());
        shared.dilation_permille.store(1000, Ordering::Relaxed);
        let (commands, receiver) = std::sync::mpsc::channel();
        let map =
            login::ServedMap { id: prepared.map_id, description: prepared.description, frame: prepared.map_frame };
        let service = Arc::new(login::LoginService::new(
            &config,
            acceptor,
            store.clone(),
            map,
            udp_addr.port(),
            commands,
            shared.clone(),
        ));
        runtime.spawn(service.serve(listener));
        if config.backup_every_s > 0 {
            let dir = backups::backup_dir(&config.data_dir);
            let every = Duration::from_secs(config.backup_every_s);
            tracing::info!(dir = %dir.display(), ?every, keep = config.backup_keep, "periodic backups");
            runtime.spawn(backups::run(store_settings.database.clone(), dir, every, config.backup_keep as usize));
        }
        // A server started with a registry serves a cluster's zones: a gateway.
        let role = if registry.is_some() { admin::Role::Gateway } else { admin::Role::Server };
        let (admin, tick_admin) = match admin::start(&config, &runtime, store.clone(), shared.clone(), role)? {
            Some((running, tick_side)) => (Some(running), Some(tick_side)),
            None => (None, None),
        };
        let transport: Box<dyn transport::Transport> = if config.receive_thread {
            let threaded = receiver::ThreadedUdp::start(endpoints, config.receive_limits())
                .map_err(|e| ServerError::io("starting the receive thread", e))?;
            Box::new(threaded)
        } else {
            Box::new(transport::UdpTransport::group(endpoints))
        };
        let (ready, backend_result) = std::sync::mpsc::sync_channel(1);
        let map_id = prepared.map_id;
        let world = prepared.world;
        let tick_config = config.clone();
        let tick_shared = shared.clone();
        let persister_for_tick = persister.clone();
        let tick_thread = std::thread::Builder::new()
            .name("myriad-tick".into())
            .spawn(move || {
                let mut world = world;
                let made = match backend {
                    Some(make) => make(&mut world).map(myriad_cuda::CreatedBackend::from),
                    None => myriad_cuda::create_backend(tick_config.backend).map_err(ServerError::from),
                };
                let created = match made {
                    Ok(b) => {
                        tracing::info!(backend = %b.backend.description(), "physics backend ready");
                        let _ = ready.send(Ok(()));
                        b
                    }
                    Err(e) => {
                        let _ = ready.send(Err(e));
                        return;
                    }
                };
                let mut builder = tick::TickLoop::builder(tick_config, world, created.backend, transport)
                    .device_replicas(created.device_replicas)
                    .persister(Box::new(persister_for_tick), map_id)
                    .commands(receiver)
                    .admin(tick_admin)
                    .shared(tick_shared);
                if let Some(registry) = registry {
                    builder = builder.registry(registry);
                }
                let tick_loop = builder.build();
                tick_loop.run();
            })
            .map_err(|e| ServerError::io("starting the tick thread", e))?;
        match backend_result.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                let _ = tick_thread.join();
                runtime.shutdown_background();
                return Err(e);
            }
            Err(_) => {
                runtime.shutdown_background();
                return Err(ServerError::Internal("the tick thread died while starting".into()));
            }
        }
        tracing::info!(%login_addr, %udp_addr, backend = %config.backend, tick_rate = config.tick_rate, "server started");
        Ok(ServerHandle {
            runtime: Some(runtime),
            tick_thread: Some(tick_thread),
            shared,
            persister,
            store,
            login_addr,
            udp_addr,
            certificate,
            shutdown_flush: Duration::from_secs_f32(config.shutdown_flush_s),
            _database_lock: database_lock,
            admin,
        })
    }

    /// Address of the admin API and console, when `admin_addr` is set (with the real
    /// port when 0 was configured).
    pub fn admin_addr(&self) -> Option<SocketAddr> {
        self.admin.as_ref().map(|a| a.addr)
    }

    /// The file holding the admin API's bearer token, when the API runs.
    pub fn admin_token_path(&self) -> Option<&std::path::Path> {
        self.admin.as_ref().map(|a| a.token_path.as_path())
    }

    /// What the admin API answered since start, by outcome (zero when it does not run).
    pub fn admin_stats(&self) -> admin::AdminStats {
        self.admin.as_ref().map(|a| a.shared.counters.snapshot()).unwrap_or_default()
    }

    /// Address of the TLS login service (with the real port when 0 was configured).
    pub fn login_addr(&self) -> SocketAddr {
        self.login_addr
    }

    /// Address of the UDP game traffic.
    pub fn udp_addr(&self) -> SocketAddr {
        self.udp_addr
    }

    /// The certificate the login service presents (clients pin it in development).
    pub fn certificate_path(&self) -> &std::path::Path {
        &self.certificate
    }

    /// The last one-second summary of the tick loop.
    pub fn status(&self) -> ServerStatus {
        self.shared.status.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Players logged in now.
    pub fn players(&self) -> usize {
        self.shared.players.load(Ordering::Relaxed)
    }

    /// The current tick.
    pub fn tick(&self) -> u64 {
        self.shared.tick.load(Ordering::Relaxed)
    }

    /// The current time dilation in thousandths of real time.
    pub fn dilation_permille(&self) -> u16 {
        self.shared.dilation_permille.load(Ordering::Relaxed) as u16
    }

    /// Counters of the database writer.
    pub fn persister_stats(&self) -> PersisterStats {
        self.persister.stats()
    }

    /// The store the server uses (for tests and tools in the same process).
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// What the abuse defences did since start (receive budget, login limits).
    pub fn defence(&self) -> status::DefenceStats {
        self.shared.defence.snapshot()
    }

    /// Adds busy time to every tick, as if the world had more work (load tests).
    pub fn set_artificial_load(&self, per_tick: Duration) {
        let us = per_tick.as_micros().min(u32::MAX as u128) as u32;
        self.shared.artificial_load_us.store(us, Ordering::Relaxed);
    }

    /// Stops gracefully: disconnects every player, writes every position, closes the
    /// store. Returns what the last flush wrote, or [`ServerError::PositionsLost`] (how
    /// many, and why) when the database did not take them within `shutdown_flush_s`.
    pub fn shutdown(mut self) -> Result<FlushReport, ServerError> {
        self.stop_gracefully()
    }

    fn stop_gracefully(&mut self) -> Result<FlushReport, ServerError> {
        self.shared.stop.store(true, Ordering::Release);
        if let Some(t) = self.tick_thread.take()
            && t.join().is_err()
        {
            tracing::error!("the tick thread panicked");
        }
        let Some(runtime) = self.runtime.take() else {
            return Ok(FlushReport::default());
        };
        let report = runtime.block_on(self.persister.shutdown(self.shutdown_flush));
        // Closing waits for connections in flight; when the database already failed the
        // deadline, nothing more is waited for (the deadline is the whole shutdown's).
        let grace = if report.is_ok() { Duration::from_secs(1) } else { Duration::from_millis(100) };
        let store = &self.store;
        if runtime.block_on(async { tokio::time::timeout(grace, store.close()).await }).is_err() {
            tracing::warn!(?grace, "the database connections did not close in time; abandoned");
        }
        runtime.shutdown_timeout(grace);
        let stats = self.persister.stats();
        match report {
            Ok(report) => {
                tracing::info!(
                    written = report.rows_written,
                    dropped_while_running = stats.dropped_total(),
                    "server stopped; every position saved"
                );
                Ok(report)
            }
            Err(loss) => {
                tracing::error!(
                    lost = loss.lost,
                    written = loss.rows_written,
                    dropped_while_running = stats.dropped_total() - loss.lost,
                    error = %loss.cause,
                    "server stopped; player positions lost"
                );
                Err(ServerError::PositionsLost(loss))
            }
        }
    }

    /// Stops abruptly, as a `kill -9` would: no final positions, no flush, the database
    /// writer is abandoned mid-flight. Only what was already committed survives. For
    /// crash-recovery tests.
    pub fn crash(mut self) {
        self.shared.crash.store(true, Ordering::Release);
        self.shared.stop.store(true, Ordering::Release);
        if let Some(t) = self.tick_thread.take() {
            let _ = t.join();
        }
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

impl Drop for ServerHandle {
    fn drop(&mut self) {
        if self.runtime.is_some()
            && let Err(e) = self.stop_gracefully()
        {
            tracing::warn!(error = %e, "shutdown left positions unwritten");
        }
    }
}

/// Niceness of the async runtime's worker threads (TLS handshakes, login checks, the
/// database writer, metrics): under a login storm they yield the CPU to the tick thread,
/// which keeps the default priority.
const IO_THREAD_NICE: i32 = 10;

/// Worker threads of the async runtime (login I/O, database writer, metrics).
const IO_WORKERS: usize = 2;

/// Niceness of the runtime's blocking threads with `background_low_priority`: the
/// lowest normal priority, so they get the CPU the tick and its physics threads do not
/// want, yet still run every few milliseconds. Not `SCHED_IDLE`: measured, an idle-class
/// thread that holds an allocator lock while a busy machine never lets it run stalls the
/// tick for seconds (priority inversion).
const BLOCKING_THREAD_NICE: i32 = 19;

/// Sets the calling thread's nice value (Linux: nice values are per thread; lowering
/// one's own priority needs no privilege). Failure only costs the tick its head start,
/// so it is logged, not fatal.
pub(crate) fn set_thread_nice(nice: i32) {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: a plain system call on the calling thread (`gettid` names it).
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, nice) };
        if rc != 0 {
            tracing::debug!(error = %std::io::Error::last_os_error(), nice, "cannot lower a thread's priority");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
}

fn install_metrics(addr: SocketAddr) -> Result<(), ServerError> {
    use metrics_exporter_prometheus::{Matcher, PrometheusBuilder};
    let tick_buckets = [0.001, 0.002, 0.005, 0.01, 0.02, 0.033, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0];
    PrometheusBuilder::new()
        .with_http_listener(addr)
        .set_buckets_for_metric(Matcher::Suffix("duration_seconds".into()), &tick_buckets)
        .map_err(|e| ServerError::Metrics(e.to_string()))?
        .install()
        .map_err(|e| ServerError::Metrics(e.to_string()))
}
