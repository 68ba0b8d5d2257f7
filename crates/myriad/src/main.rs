//! `myriad`: the command-line front end of the Myriad world server.
//!
//! Subcommands: `sim` (run a scenario and print its state hash) and `bench` (the
//! reference's result tables on this machine). The server, bots, admin and map
//! commands arrive with their issues.

mod bench;
mod plots;
mod reference;
mod scenario_args;
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
    }
}
