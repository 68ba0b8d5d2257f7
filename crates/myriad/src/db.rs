//! `myriad db …`: integrity check, online backup and restore of the store (issue 29).
//!
//! The work is [`myriad_store`]'s (`check_database`, `backup_sqlite`, `restore_sqlite`);
//! this module reads the server's configuration to find the database and reports.

use std::path::PathBuf;

use anyhow::{Context, Result};
use myriad_store::{CheckDepth, check_database};

use crate::admin::{StoreArgs, runtime};

/// `myriad db`.
#[derive(clap::Subcommand, Debug)]
pub enum DbCommand {
    /// Check the database: SQLite `PRAGMA quick_check` (`integrity_check` with --full),
    /// MariaDB `CHECK TABLE` on Myriad's tables. Exits non-zero when damaged.
    Check {
        /// The thorough check (also every index against its table); slower.
        #[arg(long)]
        full: bool,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Back the SQLite database up to a new file, also while the server runs. (MariaDB:
    /// use mariadb-dump, see docs/server.md.)
    Backup {
        /// The backup file to write.
        path: PathBuf,
        /// Replace `path` if it exists.
        #[arg(long)]
        force: bool,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Replace the SQLite database with a backup, for a stopped server (refused while a
    /// server holds the database). The old database is kept beside it.
    Restore {
        /// The backup file (made by `myriad db backup`).
        path: PathBuf,
        #[command(flatten)]
        store: StoreArgs,
    },
}

/// Runs `myriad db …`.
pub fn db(cmd: DbCommand) -> Result<()> {
    let rt = runtime()?;
    match cmd {
        DbCommand::Check { full, store } => {
            let config = store.store_config()?;
            let depth = if full { CheckDepth::Full } else { CheckDepth::Quick };
            let report = rt.block_on(check_database(&config.database, depth)).context("checking the database")?;
            let what =
                if report.tables.is_empty() { String::new() } else { format!(" ({})", report.tables.join(", ")) };
            if report.is_intact() {
                println!(
                    "{}{what}: intact ({:?} check, {:.1} s)",
                    report.database,
                    depth,
                    report.elapsed.as_secs_f64()
                );
            } else {
                for problem in &report.problems {
                    eprintln!("{}: {problem}", report.database);
                }
                report.require_intact()?;
            }
        }
        DbCommand::Backup { path, force, store } => {
            let config = store.store_config()?;
            let report =
                rt.block_on(myriad_store::backup_sqlite(&config.database, &path, force)).context("backing up")?;
            println!(
                "backed up to {} ({} bytes, {:.1} s); restore it with `myriad db restore {}` on a stopped server",
                report.path.display(),
                report.bytes,
                report.elapsed.as_secs_f64(),
                report.path.display()
            );
        }
        DbCommand::Restore { path, store } => {
            let config = store.store_config()?;
            let moved =
                rt.block_on(myriad_store::restore_sqlite(&config.database, &path)).context("restoring the backup")?;
            let target = myriad_store::sqlite_file(&config.database)?.context("a SQLite store has a file")?;
            match moved {
                Some(old) => println!(
                    "restored {} into {}; the previous database is kept as {}",
                    path.display(),
                    target.display(),
                    old.display()
                ),
                None => println!("restored {} into {}", path.display(), target.display()),
            }
        }
    }
    Ok(())
}
