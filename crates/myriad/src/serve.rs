//! `myriad serve`: run the world server until SIGINT/SIGTERM.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, Result};
use myriad_server::{ServerConfig, ServerHandle};

/// Configuration flags shared by `serve` and `demo`: a TOML file, then per-key overrides.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ConfigArgs {
    /// Configuration file (TOML; `myriad serve --print-config` shows every key).
    #[arg(long, short = 'c', env = "MYRIAD_CONFIG")]
    pub config: Option<PathBuf>,
    /// Ticks per second.
    #[arg(long)]
    pub tick_rate: Option<f32>,
    /// UDP address of the game traffic.
    #[arg(long)]
    pub udp: Option<SocketAddr>,
    /// Address of the TLS login service.
    #[arg(long)]
    pub login: Option<SocketAddr>,
    /// Serve Prometheus metrics on this address (`/metrics`).
    #[arg(long)]
    pub metrics: Option<SocketAddr>,
    /// Players' walking speed (units/s).
    #[arg(long)]
    pub speed: Option<f32>,
    /// Most players at once.
    #[arg(long)]
    pub max_players: Option<u32>,
    /// Number of NPCs.
    #[arg(long)]
    pub npcs: Option<u32>,
    /// Grid spacing of NPCs (0 = uniformly at random).
    #[arg(long)]
    pub npc_spacing: Option<f32>,
    /// Map imported with `myriad map import` (default: the generated scenario map).
    #[arg(long)]
    pub map: Option<String>,
    /// Numbered scenario (1, 2, 3, 4) whose map is generated when no map is named.
    #[arg(long)]
    pub scenario: Option<u8>,
    /// Seed of the generated map and NPC placement.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Edge of the area-of-interest box (units).
    #[arg(long)]
    pub aoi: Option<f32>,
    /// Data directory (SQLite database, development certificate).
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Database URL (mysql://user:pass@host:port/db); default: SQLite in the data directory.
    #[arg(long, env = "MYRIAD_DATABASE_URL")]
    pub database_url: Option<String>,
    /// Physics backend: cpu, cpu-naive, cuda, cuda-naive, auto.
    #[arg(long)]
    pub backend: Option<String>,
    /// Milliseconds between position checkpoints.
    #[arg(long)]
    pub persist_ms: Option<u64>,
    /// Serve the admin API and console on ADDR (default: 127.0.0.1 at the login port + 2).
    #[arg(long, value_name = "ADDR", num_args = 0..=1)]
    pub admin: Option<Option<SocketAddr>>,
    /// Any other key: `--set key=value` (repeatable; the value is TOML).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

impl ConfigArgs {
    /// The file (or the defaults) with every override applied.
    pub fn effective(&self) -> Result<ServerConfig> {
        let mut c = match &self.config {
            Some(path) => ServerConfig::load(path)?,
            None => ServerConfig::default(),
        };
        let mut set = |key: &str, value: Option<String>| -> Result<()> {
            if let Some(v) = value {
                c.set(key, &v)?;
            }
            Ok(())
        };
        let q = |s: &str| format!("{s:?}");
        set("tick_rate", self.tick_rate.map(|v| v.to_string()))?;
        set("udp_addr", self.udp.map(|v| q(&v.to_string())))?;
        set("login_addr", self.login.map(|v| q(&v.to_string())))?;
        set("metrics_addr", self.metrics.map(|v| q(&v.to_string())))?;
        set("player_speed", self.speed.map(|v| v.to_string()))?;
        set("max_players", self.max_players.map(|v| v.to_string()))?;
        set("npc_count", self.npcs.map(|v| v.to_string()))?;
        set("npc_spacing", self.npc_spacing.map(|v| v.to_string()))?;
        set("map", self.map.as_deref().map(q))?;
        set("scenario", self.scenario.map(|v| v.to_string()))?;
        set("seed", self.seed.map(|v| v.to_string()))?;
        set("aoi_size", self.aoi.map(|v| v.to_string()))?;
        set("data_dir", self.data_dir.as_ref().map(|v| q(&v.display().to_string())))?;
        set("database_url", self.database_url.as_deref().map(q))?;
        set("backend", self.backend.as_deref().map(q))?;
        set("persist_interval_ms", self.persist_ms.map(|v| v.to_string()))?;
        for kv in &self.set {
            let (k, v) = kv.split_once('=').with_context(|| format!("--set {kv}: expected KEY=VALUE"))?;
            c.set(k.trim(), v.trim())?;
        }
        // After every other key: the default address follows the login port.
        if let Some(addr) = self.admin {
            let addr = addr.unwrap_or_else(|| SocketAddr::from(([127, 0, 0, 1], c.login_addr.port().wrapping_add(2))));
            c.set("admin_addr", &q(&addr.to_string()))?;
        }
        Ok(c)
    }
}

/// Arguments of `myriad serve`.
#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// Print the effective configuration (TOML) and exit.
    #[arg(long)]
    print_config: bool,
}

/// Starts the server.
pub fn start(config: ServerConfig) -> Result<ServerHandle> {
    ServerHandle::start(config).context("starting the server")
}

/// Waits for SIGINT or SIGTERM (or `limit`, when given).
pub fn wait_for_shutdown(limit: Option<std::time::Duration>) -> Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    rt.block_on(async {
        #[cfg(unix)]
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        let limit = async {
            match limit {
                Some(d) => tokio::time::sleep(d).await,
                None => std::future::pending().await,
            }
        };
        #[cfg(unix)]
        tokio::select! {
            r = tokio::signal::ctrl_c() => r?,
            _ = term.recv() => {}
            _ = limit => {}
        }
        #[cfg(not(unix))]
        tokio::select! {
            r = tokio::signal::ctrl_c() => r?,
            _ = limit => {}
        }
        Ok(())
    })
}

pub fn run(args: ServeArgs) -> Result<()> {
    let config = args.config.effective()?;
    if args.print_config {
        print!("{}", config.to_toml());
        return Ok(());
    }
    let server = start(config)?;
    eprintln!(
        "myriad: serving; login (TLS) on {}, game (UDP) on {}, certificate {}; Ctrl-C to stop",
        server.login_addr(),
        server.udp_addr(),
        server.certificate_path().display()
    );
    if let (Some(addr), Some(token)) = (server.admin_addr(), server.admin_token_path()) {
        eprintln!("myriad: admin API and console on http://{addr}/ (token in {})", token.display());
    }
    wait_for_shutdown(None)?;
    eprintln!("myriad: shutting down, writing every position");
    let report = server.shutdown()?;
    eprintln!("myriad: stopped; every position saved ({} written in the last flush)", report.rows_written);
    Ok(())
}
