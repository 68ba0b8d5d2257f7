//! `myriad user …`: accounts in the store, for an operator at the database (issue 29).
//!
//! These work on the database directly. Disabling, banning, a new password or a deletion
//! take effect at the account's next login, also while a server runs (each login reads
//! the account's row); a player already in play stays until it leaves.

use anyhow::{Context, Result};
use myriad_store::{Account, UserId, now_ms};

use crate::admin::{StoreArgs, read_password, runtime};
use myriad_server::admin::rfc3339;

/// `myriad user`.
#[derive(clap::Subcommand, Debug)]
pub enum UserCommand {
    /// Create an account; the password is asked for (or read from standard input).
    Add {
        /// Account name (letters, digits, `_`, `-`, `.`; at most 32 bytes).
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Create the test accounts `user<i>` / `password<i>` for i in 0..count (existing ones are kept).
    Seed {
        /// How many.
        #[arg(long, default_value_t = 100)]
        count: u32,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// List the accounts: id, name, created, state (disabled, banned: reason, until).
    List {
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Disable an account: its logins are refused ("the account is disabled").
    Disable {
        /// Account name.
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Enable a disabled account.
    Enable {
        /// Account name.
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Delete an account and its saved positions.
    Delete {
        /// Account name.
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Set an account's password; it is asked for (or read from standard input).
    Passwd {
        /// Account name.
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Ban an account: its logins are refused ("the account is banned") until the end.
    Ban {
        /// Account name.
        name: String,
        /// Why (shown by `user list`; at most 255 bytes).
        #[arg(long)]
        reason: String,
        /// When the ban ends, RFC 3339 (e.g. 2026-12-24T18:00:00Z); default: never.
        #[arg(long)]
        until: Option<String>,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Lift an account's ban.
    Unban {
        /// Account name.
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
}

/// Accounts fetched per query by `user list`.
const LIST_PAGE: u32 = 1000;

/// Runs `myriad user …`.
pub fn user(cmd: UserCommand) -> Result<()> {
    let rt = runtime()?;
    match cmd {
        UserCommand::Add { name, store } => {
            let password = read_password()?;
            let store = store.open(&rt)?;
            let id = rt.block_on(store.create_user(&name, &password)).with_context(|| format!("creating {name}"))?;
            rt.block_on(store.close());
            println!("created user {name} (id {})", id.0);
        }
        UserCommand::Seed { count, store } => {
            let store = store.open(&rt)?;
            let t = std::time::Instant::now();
            let r = rt.block_on(store.seed_users(count)).context("seeding users")?;
            rt.block_on(store.close());
            println!(
                "user0..user{}: {} created, {} already there ({:.1} s)",
                count.saturating_sub(1),
                r.created,
                r.skipped,
                t.elapsed().as_secs_f64()
            );
        }
        UserCommand::List { store } => {
            let store = store.open(&rt)?;
            let now = now_ms();
            println!("{:>8}  {:<32} {:<20}  state", "id", "name", "created");
            let mut after: Option<UserId> = None;
            loop {
                let page = rt.block_on(store.list_accounts(after, LIST_PAGE)).context("listing accounts")?;
                let Some(last) = page.last() else { break };
                after = Some(last.id);
                for account in &page {
                    println!(
                        "{:>8}  {:<32} {:<20}  {}",
                        account.id.0,
                        account.username,
                        rfc3339::format_ms(account.created_at_ms),
                        state(account, now)
                    );
                }
            }
            rt.block_on(store.close());
        }
        UserCommand::Disable { name, store } => {
            let store = store.open(&rt)?;
            rt.block_on(store.set_disabled(&name, true)).with_context(|| format!("disabling {name}"))?;
            rt.block_on(store.close());
            println!("disabled {name}: its logins are refused until `myriad user enable {name}`");
        }
        UserCommand::Enable { name, store } => {
            let store = store.open(&rt)?;
            rt.block_on(store.set_disabled(&name, false)).with_context(|| format!("enabling {name}"))?;
            rt.block_on(store.close());
            println!("enabled {name}");
        }
        UserCommand::Delete { name, store } => {
            let store = store.open(&rt)?;
            rt.block_on(store.delete_user(&name)).with_context(|| format!("deleting {name}"))?;
            rt.block_on(store.close());
            println!("deleted {name} and its saved positions");
        }
        UserCommand::Passwd { name, store } => {
            let password = read_password()?;
            let store = store.open(&rt)?;
            rt.block_on(store.set_password(&name, &password)).with_context(|| format!("setting {name}'s password"))?;
            rt.block_on(store.close());
            println!("password of {name} changed");
        }
        UserCommand::Ban { name, reason, until, store } => {
            let until_ms =
                until.as_deref().map(rfc3339::parse_ms).transpose().map_err(anyhow::Error::msg).context("--until")?;
            let store = store.open(&rt)?;
            rt.block_on(store.ban(&name, &reason, until_ms)).with_context(|| format!("banning {name}"))?;
            rt.block_on(store.close());
            match until_ms {
                Some(t) => println!("banned {name} until {}", rfc3339::format_ms(t)),
                None => println!("banned {name} until `myriad user unban {name}`"),
            }
        }
        UserCommand::Unban { name, store } => {
            let store = store.open(&rt)?;
            rt.block_on(store.unban(&name)).with_context(|| format!("unbanning {name}"))?;
            rt.block_on(store.close());
            println!("unbanned {name}");
        }
    }
    Ok(())
}

/// An account's state for `user list`: `active`, `disabled`, `banned (reason) until …`;
/// a ban that has ended reads `ban ended …`.
fn state(account: &Account, now_ms: i64) -> String {
    let mut parts = Vec::new();
    if account.disabled {
        parts.push("disabled".to_string());
    }
    if let Some(ban) = &account.ban {
        let until =
            ban.until_ms.map_or_else(|| "without end".to_string(), |t| format!("until {}", rfc3339::format_ms(t)));
        if ban.in_force_at(now_ms) {
            parts.push(format!("banned ({}) {until}", ban.reason));
        } else {
            parts.push(format!("ban ended ({}) {until}", ban.reason));
        }
    }
    if parts.is_empty() { "active".into() } else { parts.join(", ") }
}
