//! `myriad admin …`: the command-line client of a running server's admin API (issue 29;
//! docs/server.md, "Admin API"). It finds the API and its token as the server does, from
//! the server's configuration (`admin_addr`, `admin_token_file`, the data directory), or
//! from `--addr` and `--token-file`. Plain HTTP: the API listens on loopback (or an
//! allowed network) only.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};

use crate::admin::read_password;
use crate::serve::ConfigArgs;

/// Where the API is and how to prove who we are.
#[derive(clap::Args, Debug)]
pub struct ApiArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// The admin API's address (default: the configuration's `admin_addr`, else
    /// 127.0.0.1 at the login port + 2).
    #[arg(long)]
    addr: Option<SocketAddr>,
    /// The file holding the token (default: the configuration's `admin_token_file`, else
    /// `<data_dir>/admin.token`).
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Print the API's JSON answer as it is.
    #[arg(long)]
    json: bool,
}

/// `myriad admin`.
#[derive(clap::Subcommand, Debug)]
pub enum AdminCommand {
    /// The server's state: version, backend, tick, players, dilation, stage times.
    State {
        #[command(flatten)]
        api: ApiArgs,
    },
    /// The players online: account, entity, address, connected since, position, bytes/s.
    Players {
        #[command(flatten)]
        api: ApiArgs,
    },
    /// End a player's session (it may log in again).
    Kick {
        /// Account name.
        account: String,
        /// Why (kept in the audit trail).
        #[arg(long, default_value = "")]
        reason: String,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Ban an account: refused at login until the end; a session in play ends.
    Ban {
        /// Account name.
        account: String,
        /// Why (at most 255 bytes).
        #[arg(long)]
        reason: String,
        /// When the ban ends, RFC 3339 (e.g. 2026-12-24T18:00:00Z); default: never.
        #[arg(long)]
        until: Option<String>,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Lift an account's ban.
    Unban {
        /// Account name.
        account: String,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Disable an account (refused at login; a session in play ends).
    Disable {
        /// Account name.
        account: String,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Enable a disabled account.
    Enable {
        /// Account name.
        account: String,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Delete an account and its saved positions (a session in play ends first).
    Delete {
        /// Account name.
        account: String,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Set an account's password; it is asked for (or read from standard input).
    Passwd {
        /// Account name.
        account: String,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// List accounts (by id).
    Accounts {
        /// Most accounts to list.
        #[arg(long, default_value_t = 100)]
        limit: u32,
        /// Accounts to skip.
        #[arg(long, default_value_t = 0)]
        offset: u32,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// The audit trail, newest first.
    Audit {
        /// Most entries to show.
        #[arg(long, default_value_t = 50)]
        limit: u32,
        #[command(flatten)]
        api: ApiArgs,
    },
    /// Print the web console's address with the token in its fragment (never sent to
    /// the server; keep it private).
    ConsoleUrl {
        #[command(flatten)]
        api: ApiArgs,
    },
}

/// The API's client: its base URL and token.
struct Client {
    base: String,
    token: String,
    agent: ureq::Agent,
    json: bool,
}

impl Client {
    fn new(args: &ApiArgs) -> Result<Client> {
        let config = args.config.effective()?;
        let addr = match args.addr.or(config.admin_addr) {
            Some(a) => a,
            None => SocketAddr::from(([127, 0, 0, 1], config.login_addr.port().wrapping_add(2))),
        };
        // A listener on every address is reached on loopback.
        let addr = if addr.ip().is_unspecified() { SocketAddr::from(([127, 0, 0, 1], addr.port())) } else { addr };
        let path = args.token_file.clone().unwrap_or_else(|| myriad_server::admin::token_path(&config));
        let token = std::fs::read_to_string(&path)
            .with_context(|| {
                format!("reading the admin token {} (is the server running with --admin?)", path.display())
            })?
            .trim()
            .to_string();
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(30)))
            .build()
            .into();
        Ok(Client { base: format!("http://{addr}"), token, agent, json: args.json })
    }

    /// Sends a request to `path` (a body for POST); the JSON answer, or the API's error.
    fn call(&self, method: &str, path: &str, body: Option<Value>) -> Result<Value> {
        let url = format!("{}{path}", self.base);
        let auth = format!("Bearer {}", self.token);
        let actor = std::env::var("USER").unwrap_or_default();
        let response = match method {
            "GET" => self.agent.get(&url).header("authorization", &auth).header("x-myriad-actor", &actor).call(),
            "DELETE" => self.agent.delete(&url).header("authorization", &auth).header("x-myriad-actor", &actor).call(),
            _ => {
                let request = self.agent.post(&url).header("authorization", &auth).header("x-myriad-actor", &actor);
                match body {
                    Some(b) => request.send_json(b),
                    None => request.send_empty(),
                }
            }
        };
        let mut response = response.with_context(|| format!("{method} {url}"))?;
        let status = response.status();
        let text = response.body_mut().read_to_string().with_context(|| format!("reading the answer of {url}"))?;
        let value: Value = serde_json::from_str(&text).with_context(|| format!("{url} answered {status}: {text}"))?;
        if !status.is_success() {
            let message = value.get("error").and_then(Value::as_str).unwrap_or(&text);
            bail!("{method} {path}: {status}: {message}");
        }
        Ok(value)
    }

    /// Prints `value` as JSON when asked, else with `human`.
    fn show(&self, value: &Value, human: impl FnOnce(&Value)) {
        if self.json {
            println!("{}", serde_json::to_string_pretty(value).unwrap_or_default());
        } else {
            human(value);
        }
    }
}

/// A JSON value as plain text (strings without quotes).
fn plain(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        Value::Null => "-".into(),
        other => other.to_string(),
    }
}

/// Percent-encodes an account name for a URL path (names are ASCII letters, digits and
/// `_-.`, which need none; anything else is the server's to refuse, intact).
fn segment(name: &str) -> String {
    name.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"_-.".contains(&b) { (b as char).to_string() } else { format!("%{b:02X}") }
        })
        .collect()
}

/// Runs `myriad admin …`.
pub fn admin(command: AdminCommand) -> Result<()> {
    match command {
        AdminCommand::State { api } => {
            let c = Client::new(&api)?;
            let v = c.call("GET", "/api/state", None)?;
            c.show(&v, |v| {
                for key in
                    ["role", "version", "backend", "tick", "tick_hz", "players", "dilation", "tick_ms", "uptime_s"]
                {
                    println!("{key:<9} {}", plain(&v[key]));
                }
                if let Some(stages) = v["stages_ms"].as_object() {
                    let line: Vec<String> =
                        stages.iter().map(|(k, ms)| format!("{k}={:.2}", ms.as_f64().unwrap_or(0.0))).collect();
                    println!("stages    {}", line.join(" "));
                }
            });
        }
        AdminCommand::Players { api } => {
            let c = Client::new(&api)?;
            let v = c.call("GET", "/api/players", None)?;
            c.show(&v, |v| {
                let rows = v.as_array().cloned().unwrap_or_default();
                println!(
                    "{:<20} {:>8} {:>8} {:<22} {:<25} {:>26} {:>10}",
                    "account", "user", "entity", "address", "connected since", "position", "bytes/s"
                );
                for p in &rows {
                    let pos: Vec<String> = p["position"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .map(|x| format!("{:.1}", x.as_f64().unwrap_or(f64::NAN)))
                        .collect();
                    println!(
                        "{:<20} {:>8} {:>8} {:<22} {:<25} {:>26} {:>10.0}",
                        plain(&p["account"]),
                        plain(&p["user_id"]),
                        plain(&p["entity"]),
                        plain(&p["addr"]),
                        plain(&p["connected_since"]),
                        pos.join(", "),
                        p["bytes_per_s"].as_f64().unwrap_or(0.0)
                    );
                }
                println!("{} online", rows.len());
            });
        }
        AdminCommand::Kick { account, reason, api } => {
            let c = Client::new(&api)?;
            let v =
                c.call("POST", &format!("/api/players/{}/kick", segment(&account)), Some(json!({"reason": reason})))?;
            c.show(&v, |_| println!("kicked {account}"));
        }
        AdminCommand::Ban { account, reason, until, api } => {
            let c = Client::new(&api)?;
            let body = json!({"reason": reason, "until": until});
            let v = c.call("POST", &format!("/api/accounts/{}/ban", segment(&account)), Some(body))?;
            c.show(&v, |v| {
                let until = v["until"].as_str().map_or("without end".to_string(), |t| format!("until {t}"));
                let kicked = if v["kicked"] == json!(true) { "; its session ended" } else { "" };
                println!("banned {account} {until}{kicked}");
            });
        }
        AdminCommand::Unban { account, api } => simple(&api, &account, "unban", "unbanned")?,
        AdminCommand::Disable { account, api } => simple(&api, &account, "disable", "disabled")?,
        AdminCommand::Enable { account, api } => simple(&api, &account, "enable", "enabled")?,
        AdminCommand::Delete { account, api } => {
            let c = Client::new(&api)?;
            let v = c.call("DELETE", &format!("/api/accounts/{}", segment(&account)), None)?;
            c.show(&v, |_| println!("deleted {account}"));
        }
        AdminCommand::Passwd { account, api } => {
            let c = Client::new(&api)?;
            let password = read_password()?;
            let path = format!("/api/accounts/{}/password", segment(&account));
            let v = c.call("POST", &path, Some(json!({"password": password})))?;
            c.show(&v, |_| println!("password of {account} changed"));
        }
        AdminCommand::Accounts { limit, offset, api } => {
            let c = Client::new(&api)?;
            let v = c.call("GET", &format!("/api/accounts?limit={limit}&offset={offset}"), None)?;
            c.show(&v, |v| {
                for a in v.as_array().into_iter().flatten() {
                    let mut state = Vec::new();
                    if a["disabled"] == json!(true) {
                        state.push("disabled".to_string());
                    }
                    if a["banned"] == json!(true) {
                        let until = a["banned_until"].as_str().map_or("without end".into(), |t| format!("until {t}"));
                        state.push(format!("banned ({}) {until}", plain(&a["ban_reason"])));
                    }
                    println!(
                        "{:>8} {:<32} {} {}",
                        plain(&a["user_id"]),
                        plain(&a["account"]),
                        plain(&a["created_at"]),
                        state.join(", ")
                    );
                }
            });
        }
        AdminCommand::Audit { limit, api } => {
            let c = Client::new(&api)?;
            let v = c.call("GET", &format!("/api/audit?limit={limit}"), None)?;
            c.show(&v, |v| {
                for e in v.as_array().into_iter().flatten() {
                    let ok = if e["ok"] == json!(true) { "ok" } else { "REFUSED" };
                    println!(
                        "{} {:<7} {:<20} {:<9} {:<24} from {} {}",
                        plain(&e["at"]),
                        ok,
                        plain(&e["actor"]),
                        plain(&e["action"]),
                        plain(&e["target"]),
                        plain(&e["from"]),
                        plain(&e["detail"])
                    );
                }
            });
        }
        AdminCommand::ConsoleUrl { api } => {
            let c = Client::new(&api)?;
            println!("{}/#token={}", c.base, c.token);
        }
    }
    Ok(())
}

/// An action without a body whose answer needs no more than a line.
fn simple(api: &ApiArgs, account: &str, action: &str, done: &str) -> Result<()> {
    let c = Client::new(api)?;
    let v = c.call("POST", &format!("/api/accounts/{}/{action}", segment(account)), None)?;
    c.show(&v, |v| {
        let kicked = if v["kicked"] == json!(true) { "; its session ended" } else { "" };
        println!("{done} {account}{kicked}");
    });
    Ok(())
}
