//! `myriad`: the command-line front end of the Myriad world server.
//!
//! Subcommands, one module each (`myriad help <command>` gives their flags):
//! - `sim` ([`sim`]): run a scenario (in one process, or split into zones) and print
//!   its state hash.
//! - `bench` ([`bench`](mod@bench)): the reference's result tables on this machine.
//! - `serve` ([`serve`]): the world server, until SIGINT/SIGTERM.
//! - `demo` ([`demo`]): a server on the embedded database with built-in bots.
//! - `bots` ([`bots`]): a swarm of bots against a server.
//! - `flood` ([`flood`]): a bounded attack on a server on this machine, measured.
//! - `relay` ([`relay`]): a seeded, lossy UDP relay between clients and a server on this
//!   machine (loopback only, bounded).
//! - `zone`, `cluster` ([`zones`]): one zone process, and a supervised cluster of them
//!   over NATS.
//! - `gateway` ([`gateway`]): logins and sessions for a world run by zones.
//! - `user` ([`users`]), `map` ([`admin`]): accounts and maps.
//! - `db` ([`db`]): integrity check, online backup and restore of the store.
//! - `admin` ([`admin_client`]): the client of a running server's admin API.

mod admin;
mod admin_client;
mod bench;
mod bots;
mod cluster_nats;
mod cluster_rebalance;
mod db;
mod demo;
mod flood;
mod gateway;
mod plots;
mod reference;
mod relay;
mod replay;
mod scenario_args;
mod serve;
mod sim;
mod users;
mod zones;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

/// Myriad: a GPU-accelerated authoritative MMO world server.
#[derive(Parser, Debug)]
#[command(name = "myriad", version, about)]
struct Cli {
    /// Worker threads for the parallel CPU backend (default: one per core).
    #[arg(long, global = true, env = "MYRIAD_THREADS")]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Simulate a scenario for some ticks; print a summary and the state hash.
    Sim(sim::SimArgs),
    /// Measure every scenario on every backend, in the layout of the reference's tables.
    Bench(bench::BenchArgs),
    /// Run the world server (TLS login, UDP game traffic) until SIGINT/SIGTERM.
    Serve(serve::ServeArgs),
    /// Serve a scenario on the embedded database with built-in bots and a live status line.
    Demo(demo::DemoArgs),
    /// Run a swarm of bots (`user<i>` / `password<i>`) against a server.
    Bots(bots::BotsArgs),
    /// Attack a server on this machine (loopback only, bounded) and measure the cost.
    Flood(flood::FloodArgs),
    /// Relay UDP between clients and a server on this machine, losing, delaying,
    /// duplicating and reordering datagrams (loopback only, bounded).
    Relay(relay::RelayArgs),
    /// Run one zone of a world split over several processes (see `cluster`).
    Zone(zones::ZoneArgs),
    /// Run a world split into zones, one process each, over NATS, supervised.
    Cluster(zones::ClusterArgs),
    /// Log players in and hold their sessions for a world run by zones (`cluster --live`).
    Gateway(gateway::GatewayArgs),
    /// Re-run a cluster's world from a stored checkpoint with the intents its zones
    /// logged, and compare the end with the stored result.
    Replay(replay::ReplayArgs),
    /// Manage accounts (also disable, ban, reset passwords) on the database.
    #[command(subcommand)]
    User(users::UserCommand),
    /// Manage maps.
    #[command(subcommand)]
    Map(admin::MapCommand),
    /// Check, back up or restore the database.
    #[command(subcommand)]
    Db(db::DbCommand),
    /// Operate a running server through its admin API (players, kicks, bans, accounts, audit).
    #[command(subcommand)]
    Admin(admin_client::AdminCommand),
}

/// Large allocations at or above this size get their own mapping, returned to the system
/// when freed.
const MMAP_THRESHOLD: i32 = 4 << 20;

/// Free memory an arena keeps at its top before giving it back to the system.
const TRIM_THRESHOLD: i32 = 64 << 20;

/// Makes glibc's allocator give large freed blocks back to the system.
///
/// Each password check allocates Argon2's working memory (19 MiB at the default cost).
/// glibc serves the first such block with `mmap`, then raises its mmap threshold to the
/// size of what was freed (up to 32 MiB), so every later block comes from an arena and
/// stays resident once freed; with many hashing threads (one arena each) the server held
/// 3.3 GB after 300 logins, and grew until killed under a burst of 1,000 (issue 15).
/// A fixed threshold turns the dynamic adjustment off: blocks of 4 MiB or more (the
/// hashes; nothing the tick allocates is that large) are mapped and unmapped, everything
/// smaller stays in the arenas as before. Chosen over swapping the allocator (no
/// allocator crate is on the approved list, and this is one call); the cost, measured,
/// is a few page faults per login, and the buffer reuse of the hashing pool makes it
/// moot for hashes.
///
/// A fixed threshold also fixes the trim threshold, which glibc would otherwise have
/// raised with it: at its default (128 KiB) every arena handed back the top of what the
/// tick freed (its buffers of megabytes a tick: 3.2 MB of recipients alone at
/// 50,000 players), and the next tick faulted the same pages in again, 670 page faults
/// a tick at scenario 2's 5,000 players on the development VM. Arenas now keep up to
/// 64 MiB free at their top (315 faults a tick, the rest from elsewhere); the Argon2
/// blocks are mapped on their own as above, so they are not kept.
fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; called once at start-up, before
    // any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD);
    }
}

fn main() -> Result<()> {
    return_freed_memory();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,async_nats=warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    if let Some(n) = cli.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("configuring the thread pool")?;
    }
    match cli.command {
        Command::Sim(a) => sim::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Serve(a) => serve::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Bots(a) => bots::run(a),
        Command::Flood(a) => flood::run(a),
        Command::Relay(a) => relay::run(a),
        Command::Zone(a) => zones::run_zone(a),
        Command::Cluster(a) => zones::run_cluster(a),
        Command::Gateway(a) => gateway::run(a),
        Command::Replay(a) => replay::run(a),
        Command::User(c) => users::user(c),
        Command::Db(c) => db::db(c),
        Command::Map(c) => admin::map(c),
        Command::Admin(c) => admin_client::admin(c),
    }
}
