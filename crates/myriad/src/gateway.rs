//! `myriad gateway`: the server players log in to when the world runs as zones.
//!
//! It is `myriad serve` (TLS login, UDP sessions, interest management, persistence)
//! whose physics backend is the zones themselves ([`myriad_zone::ZonesBackend`]): each
//! tick it sends the zones its players' joins, actions and leaves and takes the newest
//! world they finished. Start the zones with `myriad cluster --live` (same scenario,
//! seed, cluster name and `MYRIAD_CLUSTER_KEY`). See docs/zones.md, gateways.

use std::time::Duration;

use anyhow::{Context, Result, bail};
use myriad_server::registry::SessionRegistry;
use myriad_server::{ServerError, ServerHandle};
use myriad_zone::claims::NatsSessions;
use myriad_zone::fabric_auth::NatsAuth;
use myriad_zone::gateway::MAX_GATEWAYS;
use myriad_zone::nats::NatsGatewayLink;
use myriad_zone::subscription::InterestConfig;
use myriad_zone::{GatewayConfig, ZonesBackend};

use crate::serve::{ConfigArgs, wait_for_shutdown};
use crate::zones::{GatewayStates, key_from_env};

/// Flags of `myriad gateway`.
#[derive(clap::Args, Debug)]
pub struct GatewayArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// The cluster's name (as given to `myriad cluster --cluster`).
    #[arg(long)]
    cluster: String,
    /// Zones in the cluster.
    #[arg(long)]
    zones: u16,
    /// This gateway's index (each gateway gives its players ids of its own).
    #[arg(long, default_value_t = 0)]
    gateway: u16,
    /// The NATS server.
    #[arg(long, value_name = "URL", default_value = "nats://127.0.0.1:4222")]
    nats: String,
    /// Longest wait of a tick for the zones' next world, in ms (then the tick keeps the
    /// last one).
    #[arg(long, default_value_t = 15)]
    wait_ms: u64,
    /// Ticks between re-sending every player's action to the zones.
    #[arg(long, default_value_t = 30)]
    refresh_ticks: u64,
    /// What to take from the zones: `interest` (subscribe to the cells the players see)
    /// or `mirror` (every object, every tick); as the zones were started with.
    #[arg(long, value_enum, default_value = "interest")]
    gateway_states: GatewayStates,
    /// The side of a subscription's cells (default: an eighth of the AOI size, larger
    /// where the map would need more than 262,144 cells).
    #[arg(long)]
    interest_cell: Option<f32>,
    /// Ticks between the positions a subscription is computed from and the zones'
    /// views that follow it, which the cells' margin covers.
    #[arg(long, default_value_t = 8)]
    interest_lag_ticks: u64,
    /// Ticks a cell stays subscribed after it was last needed.
    #[arg(long, default_value_t = 30)]
    interest_linger_ticks: u64,
    /// How far an object may move in one tick (as the zones were given).
    #[arg(long, default_value_t = 2.0)]
    zone_max_step: f32,
    /// Stop after this many seconds (default: at SIGINT/SIGTERM).
    #[arg(long)]
    duration: Option<f64>,
}

/// Runs `myriad gateway`.
pub fn run(args: GatewayArgs) -> Result<()> {
    if args.gateway >= MAX_GATEWAYS {
        bail!("--gateway {}: at most {MAX_GATEWAYS} gateways (0..{})", args.gateway, MAX_GATEWAYS - 1);
    }
    if args.zones == 0 {
        bail!("--zones must be at least 1");
    }
    let key = key_from_env()?;
    let config = args.config.effective()?;
    // The gateway role's credentials, from the environment or a file (docs/zones.md).
    let auth = NatsAuth::from_env()?;
    let link = NatsGatewayLink::connect(&args.nats, &args.cluster, args.gateway, &auth)
        .with_context(|| format!("joining cluster {}", args.cluster))?;
    let cfg_key = key.clone();
    let mut cfg = GatewayConfig {
        gateway: args.gateway,
        key,
        zones: args.zones as usize,
        wait: Duration::from_millis(args.wait_ms),
        refresh: args.refresh_ticks,
        interest: None,
    };
    let aoi = config.aoi_size;
    let interest = (args.gateway_states == GatewayStates::Interest).then_some(());
    let (cell, lag, linger, max_step) =
        (args.interest_cell, args.interest_lag_ticks, args.interest_linger_ticks, args.zone_max_step);
    let factory: myriad_server::BackendFactory = Box::new(move |world| {
        // The largest object's half extent, from the world's own objects (before the
        // zones' replace them): the reach is twice it and a little more.
        let player = myriad_server::PLAYER_SHAPE.half_extents();
        let half = (myriad_zone::pair_reach(world) / 2.0).max(player.x).max(player.z);
        cfg.interest = interest.map(|()| InterestConfig {
            aoi_half: aoi / 2.0,
            cell: cell.unwrap_or_else(|| InterestConfig::default_cell(aoi, &world.bounds)),
            margin: InterestConfig::margin_for(lag, max_step, half),
            linger,
        });
        let backend = ZonesBackend::new(cfg, Box::new(link)).map_err(|e| ServerError::Internal(e.to_string()))?;
        backend.prepare(world);
        Ok(Box::new(backend))
    });
    let sessions = NatsSessions::connect(&args.nats, &args.cluster, args.gateway, cfg_key, &auth)
        .with_context(|| format!("joining cluster {}'s sessions", args.cluster))?;
    let server = ServerHandle::start_with(config, Some(factory), Some(Box::new(Registry(sessions))))
        .context("starting the gateway")?;
    eprintln!(
        "myriad: gateway {} of cluster {}; login (TLS) on {}, game (UDP) on {}, certificate {}",
        args.gateway,
        args.cluster,
        server.login_addr(),
        server.udp_addr(),
        server.certificate_path().display()
    );
    if let (Some(addr), Some(token)) = (server.admin_addr(), server.admin_token_path()) {
        eprintln!("myriad: admin API and console on http://{addr}/ (token in {})", token.display());
    }
    wait_for_shutdown(args.duration.map(Duration::from_secs_f64))?;
    let report = server.shutdown()?;
    eprintln!("myriad: gateway stopped; every position saved ({} written in the last flush)", report.rows_written);
    Ok(())
}

/// The cluster's session claims as the server's registry: a login at another gateway
/// replaces the session here.
struct Registry(NatsSessions);

impl SessionRegistry for Registry {
    fn claim(&mut self, username: &str) {
        self.0.claim(username);
    }

    fn taken(&mut self) -> Vec<String> {
        self.0.taken()
    }
}
