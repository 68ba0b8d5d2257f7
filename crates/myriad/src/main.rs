//! `myriad`: the command-line front end of the Myriad world server.
//!
//! Subcommands: `sim` (run a scenario and print its state hash) and `bench` (the
//! reference's result tables on this machine). The server, bots, admin and map
//! commands arrive with their issues.

mod admin;
mod bench;
mod bots;
mod demo;
mod flood;
mod plots;
mod reference;
mod scenario_args;
mod serve;
mod sim;

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
    /// Manage accounts.
    #[command(subcommand)]
    User(admin::UserCommand),
    /// Manage maps.
    #[command(subcommand)]
    Map(admin::MapCommand),
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
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
        Command::User(c) => admin::user(c),
        Command::Map(c) => admin::map(c),
    }
}
