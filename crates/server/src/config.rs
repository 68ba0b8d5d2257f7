//! The server's configuration: a TOML file, overridable key by key.
//!
//! Every setting the reference design fixes in code (docs/design.md, server settings:
//! tick rate, UDP port, player speed, maximum players, NPC count and spacing, map, AOI
//! box size) and what a real
//! server needs (addresses, data directory, database, backend, persistence, login
//! limits, password-hash cost) is a key of [`ServerConfig`]. Unknown keys are errors, and
//! every error names the key ([`ConfigError`]).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use myriad_core::PhysicsConfig;
use myriad_physics::BackendKind;
use myriad_store::HashCost;
use serde::{Deserialize, Serialize};

use crate::error::ConfigError;

/// The most UDP sockets a server opens on its port.
const MAX_UDP_SOCKETS: usize = 64;

/// Where the players' replicas live and choose their records (config key `outbound`;
/// the implementations are in [`crate::outbound`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OutboundKind {
    /// On the device with a CUDA backend, on the host otherwise.
    #[default]
    Auto,
    /// On the host whatever the backend.
    Host,
}

/// The default per-player send budget, kilobits per second: 30.5 kB/s. At AOI 14 a
/// player's view asks for much less (about 7.4 kB/s on scenario 3) and the budget does
/// not bind; at AOI 100 (about 2,600 objects in view on scenario 3) it keeps objects
/// within 30 units within 100 ms where 8 kB/s left them a second behind. Objects that
/// waited `max_wait_ticks` go even over it, about 2 % more there, so a player gets about
/// 31 kB/s: within the 32 kB/s asked of AOI 100, which 256 kbit/s exceeded by 1–4 %
/// (`docs/benchmarks.md`, "The default budget").
pub const DEFAULT_SEND_BUDGET_KBPS: f64 = 244.0;

/// Everything `myriad serve` can be told. See `docs/server.md` for each key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// Simulation ticks per second.
    pub tick_rate: f32,
    /// UDP address of the game traffic (the reference's UDP port).
    pub udp_addr: SocketAddr,
    /// UDP sockets on `udp_addr` (`SO_REUSEPORT`), each sending its share of a tick's
    /// datagrams on its own core; 0 picks one per core (at most 64).
    pub udp_sockets: usize,
    /// TCP address of the TLS login service.
    pub login_addr: SocketAddr,
    /// Address of the Prometheus `/metrics` endpoint; none disables it.
    pub metrics_addr: Option<SocketAddr>,
    /// Players' top walking speed in units per second.
    pub player_speed: f32,
    /// Most players logged in at once; further logins are refused with "server full".
    pub max_players: u32,
    /// Non-player objects moved by the server's random walk.
    pub npc_count: u32,
    /// Distance between NPCs on a regular grid; 0 places them uniformly at random.
    pub npc_spacing: f32,
    /// Map to serve: the name of a map imported with `myriad map import`, or empty for
    /// the generated map of `scenario` and `seed`.
    pub map: String,
    /// Numbered scenario (1, 2, 3 or 4; [`myriad_core::ScenarioSpec::reference`]) whose
    /// terrain and statics are generated when `map` is empty.
    pub scenario: u8,
    /// Seed of generated terrain, statics and NPC placement.
    pub seed: u64,
    /// Edge length of the area-of-interest box centred on each player.
    pub aoi_size: f32,
    /// Most update datagrams a player receives per tick: the ceiling that even objects
    /// sent over the byte budget (starving ones) stay under.
    pub max_datagrams_per_player: usize,
    /// Where each player's replica chooses its records: `auto` (on the device with a
    /// CUDA backend, else on the host) or `host`. The bytes are the same.
    pub outbound: OutboundKind,
    /// Each player's send budget in kilobits per second, datagram headers and tags
    /// included: what its updates spend on average (protocol version 3's priority
    /// accumulator decides what fits; an object that waited too long goes over it).
    pub send_budget_kbps: f64,
    /// How often a changing object within 30 units of a player is sent, at most every
    /// this many ticks (1 to 30): 1 draws near objects as exactly as every state would,
    /// for the bytes of sending each of them every tick.
    pub near_bound_ticks: u32,
    /// Data directory: the SQLite database and the development TLS certificate.
    pub data_dir: PathBuf,
    /// Database URL (`mysql://user:pass@host/db`); empty uses SQLite in `data_dir`.
    pub database_url: String,
    /// Physics backend (`cpu`, `cpu-naive`, `cuda`, `cuda-naive`, or `auto`: CUDA when a
    /// driver, NVRTC and a device are present, else `cpu`). An unknown name is an error
    /// naming this key.
    pub backend: BackendKind,
    /// How often player positions are handed to the database writer, in milliseconds.
    pub persist_interval_ms: u64,
    /// A player that sent nothing for this long is disconnected, in seconds.
    pub session_timeout_s: f32,
    /// Failed logins allowed per client address within `login_window_s`.
    pub login_failures_per_addr: u32,
    /// Failed logins allowed per account within `login_window_s`.
    pub login_failures_per_account: u32,
    /// Window of the failed-login limits, in seconds.
    pub login_window_s: u64,
    /// Password checks running at once: the threads of the hashing pool (each Argon2id
    /// check takes a core for tens of ms). 0 sizes it from the cores, leaving one for
    /// the tick: `cores - 1`, at least 1.
    pub login_concurrency: usize,
    /// Argon2id memory cost of new password hashes, in KiB.
    pub hash_memory_kib: u32,
    /// Argon2id passes.
    pub hash_passes: u32,
    /// Argon2id lanes.
    pub hash_lanes: u32,
    /// PEM certificate chain of the login service; empty generates (once) a self-signed
    /// development certificate in `data_dir`.
    pub tls_cert: PathBuf,
    /// PEM private key matching `tls_cert`.
    pub tls_key: PathBuf,
    /// Extra host names and addresses the development certificate is valid for (besides
    /// `localhost`, `127.0.0.1` and `::1`).
    pub tls_names: Vec<String>,
    /// Whether time dilation may slow the world down when ticks overrun their budget.
    pub dilation: bool,
    /// Slowest the world may run under dilation, in thousandths of real time.
    pub dilation_min_permille: u16,
    /// Seconds between per-stage timing lines in the log (0 = never).
    pub log_stages_every_s: f32,

    // Abuse limits (issue 14): receive budget, hashing queue, login connections.
    /// Datagrams per session per tick from the session's own address that may reach the
    /// tag check; more are dropped before any cryptography.
    pub receive_per_session: u16,
    /// Datagrams per session per tick from any other address (address migration, the
    /// first Ready) that may reach the tag check.
    pub receive_other_address: u16,
    /// Share of the nominal tick period the receive stage may take, in percent, when
    /// the tick receives itself (`receive_thread = false`).
    pub receive_time_percent: u8,
    /// Receive and gate datagrams on a thread of their own, at a lower priority, so
    /// that a flood costs the tick nothing but the tag checks the budget allows
    /// (`crate::receiver`). Off: the tick receives, within `receive_time_percent`.
    pub receive_thread: bool,
    /// Password checks that may wait for a hashing thread; beyond that a login is
    /// refused at once with "busy, retry".
    pub login_queue: usize,
    /// Longest a password check may wait for a hashing thread, in milliseconds; then
    /// the login is refused with "busy, retry".
    pub login_queue_deadline_ms: u64,
    /// Login connections one client address may hold open; more are closed at once.
    pub login_connections_per_addr: u32,
    /// Deadline of the TLS handshake and the login request, in milliseconds.
    pub login_handshake_timeout_ms: u64,
    /// How long shutdown keeps trying to write the last positions before it gives up and
    /// reports how many were lost (a hard deadline, database waits included).
    pub shutdown_flush_s: f32,
    /// Limit on `npc_count + max_players`: every object costs memory (world arrays,
    /// trees, per-player interest state), so a typo cannot make the server allocate until
    /// the machine runs out. Raise it to serve more.
    pub max_objects: u32,
    /// Run the async runtime's blocking threads (hashing new passwords, file work) at the
    /// lowest normal priority (nice 19 on Linux), so that they mostly take CPU the tick
    /// does not want. Login checks run on the store's verification pool instead, sized
    /// by `login_concurrency` (the cores less one by default).
    pub background_low_priority: bool,
    /// Limit on the memory that password checks may take at once,
    /// `login_concurrency × hash_memory_kib`, in MiB. Raise it for a bigger pool.
    pub max_hash_memory_mib: u32,
    /// Seconds between online backups of the SQLite database into
    /// `<data_dir>/backups/` (0 = none). SQLite only: a MariaDB store is backed up with
    /// `mariadb-dump` (docs/server.md).
    pub backup_every_s: u64,
    /// Backups kept in `<data_dir>/backups/`: the newest this many; older ones are
    /// deleted after each new backup.
    pub backup_keep: u32,
    /// Address of the admin API and console ([`crate::admin`]); none (the default)
    /// disables it. `myriad serve --admin` sets it to `127.0.0.1:<login port + 2>`.
    pub admin_addr: Option<SocketAddr>,
    /// Addresses and CIDR networks the admin API accepts connections from (default:
    /// loopback only), whatever `admin_addr` binds to.
    pub admin_allow: Vec<String>,
    /// File holding the admin API's bearer token; empty generates (once) a random token
    /// into `<data_dir>/admin.token`, mode 0600.
    pub admin_token_file: PathBuf,
}

/// The highest `max_objects` accepted: the slot and entity indices are 32-bit and a
/// million objects already take gigabytes with their players' interest state.
pub const MAX_OBJECTS_CEILING: u32 = 100_000_000;

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            tick_rate: 30.0,
            udp_addr: "0.0.0.0:7777".parse().expect("valid literal"),
            udp_sockets: 0,
            login_addr: "0.0.0.0:7778".parse().expect("valid literal"),
            metrics_addr: None,
            player_speed: 5.0,
            max_players: 10_000,
            npc_count: 5_000,
            npc_spacing: 0.0,
            map: String::new(),
            scenario: 1,
            seed: 1,
            aoi_size: 100.0,
            max_datagrams_per_player: 2,
            outbound: OutboundKind::Auto,
            send_budget_kbps: DEFAULT_SEND_BUDGET_KBPS,
            near_bound_ticks: 3,
            data_dir: PathBuf::from("data"),
            database_url: String::new(),
            backend: BackendKind::Auto,
            persist_interval_ms: 500,
            session_timeout_s: 10.0,
            login_failures_per_addr: 20,
            login_failures_per_account: 5,
            login_window_s: 60,
            login_concurrency: 0,
            hash_memory_kib: HashCost::DEFAULT.m_kib,
            hash_passes: HashCost::DEFAULT.t,
            hash_lanes: HashCost::DEFAULT.p,
            tls_cert: PathBuf::new(),
            tls_key: PathBuf::new(),
            tls_names: Vec::new(),
            dilation: true,
            dilation_min_permille: 100,
            log_stages_every_s: 10.0,
            receive_per_session: 8,
            receive_other_address: 2,
            receive_time_percent: 25,
            receive_thread: true,
            login_queue: 32,
            login_queue_deadline_ms: 1500,
            login_connections_per_addr: 16,
            login_handshake_timeout_ms: 5000,
            shutdown_flush_s: 10.0,
            max_objects: 1_000_000,
            max_hash_memory_mib: 4096,
            background_low_priority: true,
            backup_every_s: 0,
            backup_keep: 24,
            admin_addr: None,
            admin_allow: crate::admin::allow::default_allow(),
            admin_token_file: PathBuf::new(),
        }
    }
}

impl ServerConfig {
    /// Parses a TOML document; unknown keys and bad values name the key.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let config: ServerConfig = toml::from_str(text).map_err(|e| ConfigError::Parse(e.to_string()))?;
        config.validate()?;
        Ok(config)
    }

    /// Reads and parses a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ConfigError::Io { path: path.to_path_buf(), reason: e.to_string() })?;
        Self::from_toml(&text).map_err(|e| match e {
            ConfigError::Parse(reason) => ConfigError::File { path: path.to_path_buf(), reason },
            other => other,
        })
    }

    /// The configuration as TOML (what `myriad serve --print-config` shows).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot render the configuration: {e}\n"))
    }

    /// Sets one key from its TOML text (`key = value` on the command line); the value is
    /// parsed as TOML, and as a plain string if that fails (`map = my-map`).
    pub fn set(&mut self, key: &str, value: &str) -> Result<(), ConfigError> {
        let mut table = toml::Table::try_from(&*self).map_err(|e| ConfigError::Parse(e.to_string()))?;
        if !table.contains_key(key) && !OPTIONAL_KEYS.contains(&key) {
            return Err(ConfigError::UnknownKey(key.to_string()));
        }
        let parsed = format!("v = {value}")
            .parse::<toml::Table>()
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or_else(|| toml::Value::String(value.to_string()));
        table.insert(key.to_string(), parsed);
        let next: ServerConfig = table
            .try_into()
            .map_err(|e: toml::de::Error| ConfigError::Value { key: key.to_string(), reason: e.to_string() })?;
        next.validate()?;
        *self = next;
        Ok(())
    }

    /// Checks every value, naming the first bad key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |key: &str, reason: String| Err(ConfigError::Value { key: key.into(), reason });
        if !(self.tick_rate.is_finite() && self.tick_rate >= 1.0 && self.tick_rate <= 1000.0) {
            return bad("tick_rate", format!("{} (1 to 1000)", self.tick_rate));
        }
        if !(self.player_speed.is_finite() && self.player_speed >= 0.0) {
            return bad("player_speed", format!("{} (a speed ≥ 0)", self.player_speed));
        }
        if self.max_players == 0 {
            return bad("max_players", "must be at least 1".into());
        }
        if !(self.npc_spacing.is_finite() && self.npc_spacing >= 0.0) {
            return bad("npc_spacing", format!("{} (≥ 0)", self.npc_spacing));
        }
        if self.map.is_empty() && !myriad_core::NUMBERED_SCENARIOS.contains(&self.scenario) {
            return bad("scenario", format!("{} (1, 2, 3 or 4)", self.scenario));
        }
        if !(self.aoi_size.is_finite() && self.aoi_size > 0.0) {
            return bad("aoi_size", format!("{} (> 0)", self.aoi_size));
        }
        if self.udp_sockets > MAX_UDP_SOCKETS {
            return bad("udp_sockets", format!("{} (0 for one per core, or 1 to {MAX_UDP_SOCKETS})", self.udp_sockets));
        }
        if !(1..=64).contains(&self.max_datagrams_per_player) {
            return bad("max_datagrams_per_player", format!("{} (1 to 64)", self.max_datagrams_per_player));
        }
        if !(self.send_budget_kbps.is_finite() && (1.0..=100_000.0).contains(&self.send_budget_kbps)) {
            return bad("send_budget_kbps", format!("{} (1 to 100000)", self.send_budget_kbps));
        }
        if !(1..=30).contains(&self.near_bound_ticks) {
            return bad("near_bound_ticks", format!("{} (1 to 30)", self.near_bound_ticks));
        }
        if self.persist_interval_ms == 0 || self.persist_interval_ms > 60_000 {
            return bad("persist_interval_ms", format!("{} (1 to 60000)", self.persist_interval_ms));
        }
        if !(self.session_timeout_s.is_finite() && self.session_timeout_s >= 1.0) {
            return bad("session_timeout_s", format!("{} (≥ 1)", self.session_timeout_s));
        }
        if self.login_window_s == 0 {
            return bad("login_window_s", "must be at least 1".into());
        }
        if self.login_concurrency > 1024 {
            return bad("login_concurrency", format!("{} (0 = from the cores, up to 1024)", self.login_concurrency));
        }
        if let Err(e) = self.hash_cost().validate() {
            return bad("hash_memory_kib", e.to_string());
        }
        if self.tls_cert.as_os_str().is_empty() != self.tls_key.as_os_str().is_empty() {
            return bad("tls_key", "tls_cert and tls_key must be given together".into());
        }
        if !(1..=1000).contains(&self.dilation_min_permille) {
            return bad("dilation_min_permille", format!("{} (1 to 1000)", self.dilation_min_permille));
        }
        if !(self.log_stages_every_s.is_finite() && self.log_stages_every_s >= 0.0) {
            return bad("log_stages_every_s", format!("{}", self.log_stages_every_s));
        }
        if self.backup_every_s > 0 && !(self.database_url.is_empty() || self.database_url.starts_with("sqlite:")) {
            return bad("backup_every_s", "periodic backups are for SQLite; back MariaDB up with mariadb-dump".into());
        }
        if !(1..=10_000).contains(&self.backup_keep) {
            return bad("backup_keep", format!("{} (1 to 10000)", self.backup_keep));
        }
        if let Err(reason) = crate::admin::allow::AllowList::parse(&self.admin_allow) {
            return bad("admin_allow", reason);
        }
        self.validate_abuse_limits()?;
        self.validate_limits()?;
        self.physics().validate().map_err(|e| ConfigError::Value { key: "physics".into(), reason: e.to_string() })
    }

    /// The receive gate's limits (`receive_*` keys). The time share is of the nominal
    /// period, so a dilated tick does not receive for longer.
    pub(crate) fn receive_limits(&self) -> crate::gate::ReceiveLimits {
        let nominal = std::time::Duration::from_secs_f64(1.0 / f64::from(self.tick_rate));
        crate::gate::ReceiveLimits {
            per_session: self.receive_per_session,
            other_address: self.receive_other_address,
            time: nominal.mul_f64(f64::from(self.receive_time_percent) / 100.0),
        }
    }

    /// UDP sockets to open: `udp_sockets`, or one per core (at most 64) when it is 0.
    /// Each socket's sends run on their own core: on the 16-core GPU host, 16 sockets
    /// sent scenario 3's tick in 2.9 ms at AOI 14 where 8 took 4.5 (`docs/benchmarks.md`).
    pub fn udp_socket_count(&self) -> usize {
        match self.udp_sockets {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()).min(MAX_UDP_SOCKETS),
            n => n,
        }
    }

    fn validate_abuse_limits(&self) -> Result<(), ConfigError> {
        let bad = |key: &str, reason: String| Err(ConfigError::Value { key: key.into(), reason });
        if !(1..=1024).contains(&self.receive_per_session) {
            return bad("receive_per_session", format!("{} (1 to 1024)", self.receive_per_session));
        }
        if !(1..=1024).contains(&self.receive_other_address) {
            return bad("receive_other_address", format!("{} (1 to 1024)", self.receive_other_address));
        }
        if !(1..=100).contains(&self.receive_time_percent) {
            return bad("receive_time_percent", format!("{} (1 to 100)", self.receive_time_percent));
        }
        if self.login_queue > 100_000 {
            return bad("login_queue", format!("{} (0 to 100000)", self.login_queue));
        }
        if !(1..=60_000).contains(&self.login_queue_deadline_ms) {
            return bad("login_queue_deadline_ms", format!("{} (1 to 60000)", self.login_queue_deadline_ms));
        }
        if self.login_connections_per_addr == 0 {
            return bad("login_connections_per_addr", "must be at least 1".into());
        }
        if !(100..=60_000).contains(&self.login_handshake_timeout_ms) {
            return bad("login_handshake_timeout_ms", format!("{} (100 to 60000)", self.login_handshake_timeout_ms));
        }
        Ok(())
    }

    /// The limits on what scales memory: each error names the value, the limit and the
    /// key that raises it.
    fn validate_limits(&self) -> Result<(), ConfigError> {
        let bad = |key: &str, reason: String| Err(ConfigError::Value { key: key.into(), reason });
        if !(self.shutdown_flush_s.is_finite() && (0.1..=3600.0).contains(&self.shutdown_flush_s)) {
            return bad("shutdown_flush_s", format!("{} (0.1 to 3600 seconds)", self.shutdown_flush_s));
        }
        if self.max_objects == 0 || self.max_objects > MAX_OBJECTS_CEILING {
            return bad("max_objects", format!("{} (1 to {MAX_OBJECTS_CEILING})", self.max_objects));
        }
        let objects = u64::from(self.npc_count) + u64::from(self.max_players);
        if objects > u64::from(self.max_objects) {
            let key = if u64::from(self.npc_count) > u64::from(self.max_objects) { "npc_count" } else { "max_players" };
            return bad(
                key,
                format!(
                    "npc_count {} + max_players {} = {objects} objects exceeds the limit max_objects = {}; \
                     raise max_objects (up to {MAX_OBJECTS_CEILING}) if the machine has the memory for it",
                    self.npc_count, self.max_players, self.max_objects
                ),
            );
        }
        let hash_mib = self.hashing_threads() as u64 * u64::from(self.hash_memory_kib) / 1024;
        if hash_mib > u64::from(self.max_hash_memory_mib) {
            return bad(
                "login_concurrency",
                format!(
                    "{} hashing threads (login_concurrency) × hash_memory_kib {} = {hash_mib} MiB of \
                     password-hash memory exceeds the limit max_hash_memory_mib = {}; lower one of them or raise \
                     max_hash_memory_mib",
                    self.hashing_threads(),
                    self.hash_memory_kib,
                    self.max_hash_memory_mib
                ),
            );
        }
        Ok(())
    }

    /// Threads of the password-hashing pool: `login_concurrency`, or when it is 0 the
    /// cores less one for the tick (at least 1).
    pub fn hashing_threads(&self) -> usize {
        if self.login_concurrency > 0 {
            return self.login_concurrency;
        }
        std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1)).max(1)
    }

    /// The Argon2id cost of new password hashes.
    pub fn hash_cost(&self) -> HashCost {
        HashCost { m_kib: self.hash_memory_kib, t: self.hash_passes, p: self.hash_lanes }
    }

    /// What each player is sent: at most `max_datagrams_per_player` datagrams a tick
    /// and `send_budget_kbps` on average at `tick_rate`, near objects at most every
    /// `near_bound_ticks`.
    pub fn interest(&self) -> myriad_interest::InterestConfig {
        let mut c = myriad_interest::InterestConfig::with_budget(
            self.max_datagrams_per_player,
            self.send_budget_kbps,
            f64::from(self.tick_rate),
        );
        c.replication.near_bound_ticks = self.near_bound_ticks as f32;
        c
    }

    /// The physics parameters (the defaults with this tick rate and player speed).
    pub fn physics(&self) -> PhysicsConfig {
        PhysicsConfig { tick_rate: self.tick_rate, move_speed: self.player_speed, ..PhysicsConfig::default() }
    }
}

/// Keys whose default (none) does not appear in the TOML rendering.
const OPTIONAL_KEYS: &[&str] = &["metrics_addr", "admin_addr"];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_round_trip_through_toml() {
        let c = ServerConfig::default();
        c.validate().unwrap();
        assert_eq!(ServerConfig::from_toml(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn unknown_key_is_named() {
        let err = ServerConfig::from_toml("tick_rate = 20\ntick_rat = 30\n").unwrap_err().to_string();
        assert!(err.contains("tick_rat"), "{err}");
    }

    #[test]
    fn wrong_type_is_named() {
        let err = ServerConfig::from_toml("max_players = \"many\"\n").unwrap_err().to_string();
        assert!(err.contains("max_players"), "{err}");
    }

    #[test]
    fn bad_value_is_named() {
        let err = ServerConfig::from_toml("tick_rate = 0\n").unwrap_err().to_string();
        assert!(err.contains("tick_rate"), "{err}");
        let err = ServerConfig::from_toml("backend = \"quantum\"\n").unwrap_err().to_string();
        assert!(err.contains("backend"), "{err}");
    }

    #[test]
    fn file_errors_name_the_file_line_and_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("server.toml");
        std::fs::write(&path, "tick_rate = 30\nnpc_count = -5\n").unwrap();
        let err = ServerConfig::load(&path).unwrap_err().to_string();
        assert!(err.contains("server.toml") && err.contains("npc_count") && err.contains("line 2"), "{err}");
        let missing = ServerConfig::load(&dir.path().join("nope.toml")).unwrap_err().to_string();
        assert!(missing.contains("nope.toml"), "{missing}");
        std::fs::write(&path, "aoi_size = 64.0\nmap = \"island\"\n").unwrap();
        let ok = ServerConfig::load(&path).unwrap();
        assert_eq!((ok.aoi_size, ok.map.as_str()), (64.0, "island"));
    }

    #[test]
    fn admin_keys_are_checked_and_named() {
        let mut c = ServerConfig::default();
        c.set("admin_addr", "\"127.0.0.1:7780\"").unwrap();
        assert_eq!(c.admin_addr, Some("127.0.0.1:7780".parse().unwrap()));
        c.set("admin_allow", "[\"10.0.0.0/8\", \"::1\"]").unwrap();
        assert_eq!(c.admin_allow.len(), 2);
        let err = c.set("admin_allow", "[\"10.0.0.0/40\"]").unwrap_err().to_string();
        assert!(err.contains("admin_allow") && err.contains("10.0.0.0/40"), "{err}");
        assert_eq!(ServerConfig::from_toml(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn set_overrides_and_checks() {
        let mut c = ServerConfig::default();
        c.set("tick_rate", "20").unwrap();
        c.set("map", "island").unwrap();
        c.set("metrics_addr", "\"127.0.0.1:9100\"").unwrap();
        assert_eq!(c.tick_rate, 20.0);
        assert_eq!(c.map, "island");
        assert_eq!(c.metrics_addr, Some("127.0.0.1:9100".parse().unwrap()));
        assert!(c.set("nope", "1").unwrap_err().to_string().contains("nope"));
        assert!(c.set("max_players", "0").unwrap_err().to_string().contains("max_players"));
        assert_eq!(c.max_players, 10_000, "a failed set leaves the config unchanged");
    }

    #[test]
    fn replication_keys_are_checked_and_reach_the_replicas() {
        let mut c = ServerConfig::default();
        for (key, value) in [("near_bound_ticks", "0"), ("near_bound_ticks", "31"), ("outbound", "\"gpu\"")] {
            assert!(c.set(key, value).unwrap_err().to_string().contains(key), "{key} = {value}");
        }
        c.set("near_bound_ticks", "1").unwrap();
        c.set("outbound", "\"host\"").unwrap();
        assert_eq!(c.outbound, OutboundKind::Host);
        assert_eq!(c.interest().replication.near_bound_ticks, 1.0);
        assert_eq!(ServerConfig::default().interest().replication.near_bound_ticks, 3.0);
    }

    #[test]
    fn abuse_limits_are_checked_and_named() {
        let mut c = ServerConfig::default();
        for (key, value) in [
            ("receive_per_session", "0"),
            ("receive_other_address", "0"),
            ("receive_time_percent", "0"),
            ("receive_time_percent", "101"),
            ("login_queue_deadline_ms", "0"),
            ("login_connections_per_addr", "0"),
            ("login_handshake_timeout_ms", "10"),
            ("login_concurrency", "5000"),
        ] {
            assert!(c.set(key, value).unwrap_err().to_string().contains(key), "{key} = {value}");
        }
        assert!(c.hashing_threads() >= 1, "0 sizes the pool from the cores");
        c.set("login_concurrency", "3").unwrap();
        assert_eq!(c.hashing_threads(), 3);
    }

    #[test]
    fn limits_name_the_limit_and_how_to_raise_it() {
        let err = ServerConfig::from_toml("npc_count = 4000000000\n").unwrap_err().to_string();
        assert!(err.contains("npc_count") && err.contains("max_objects = 1000000") && err.contains("raise"), "{err}");
        let ok = ServerConfig::from_toml("npc_count = 2000000\nmax_objects = 3000000\n").unwrap();
        assert_eq!(ok.npc_count, 2_000_000);
        let err = ServerConfig::from_toml("max_players = 2000000\n").unwrap_err().to_string();
        assert!(err.contains("max_players") && err.contains("max_objects"), "{err}");
        let err = ServerConfig::from_toml("max_objects = 4000000000\n").unwrap_err().to_string();
        assert!(err.contains("max_objects") && err.contains("100000000"), "{err}");
        let err = ServerConfig::from_toml("login_concurrency = 1000\n").unwrap_err().to_string();
        assert!(err.contains("max_hash_memory_mib") && err.contains("login_concurrency"), "{err}");
        let err = ServerConfig::from_toml("shutdown_flush_s = 0\n").unwrap_err().to_string();
        assert!(err.contains("shutdown_flush_s"), "{err}");
    }
}
