//! The NATS server of `myriad cluster` and the credentials its processes present: a
//! private `nats-server` locked down by role (`myriad_zone::fabric_auth`), or an
//! operator's server with credentials the operator gives. See docs/zones.md, "Who may
//! publish what".

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use myriad_zone::ZoneId;
use myriad_zone::fabric_auth::{
    CA_ENV, CLIENT_CERT_ENV, CLIENT_KEY_ENV, CREDS_ENV, NatsAuth, PASSWORD_ENV, Role, USER_ENV, new_credentials,
    parse_creds, render_authorization, render_server_config, write_private,
};

/// Where a cluster's processes find NATS, and what each role presents there.
pub(crate) struct ClusterNats {
    /// The server's URL.
    pub url: String,
    /// Each zone's credentials, by zone.
    pub zones: Vec<NatsAuth>,
    /// The gateways'.
    pub gateway: NatsAuth,
    /// The supervisor's (this process).
    pub supervisor: NatsAuth,
    /// The private server, stopped when this is dropped.
    _local: Option<LocalNats>,
}

/// A private NATS server for one run.
struct LocalNats {
    child: Child,
    _dir: tempfile::TempDir,
}

impl Drop for LocalNats {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The file of `role`'s credentials in a directory written by [`write_config`].
fn creds_path(dir: &Path, role: Role) -> PathBuf {
    dir.join(format!("{}.creds", role.name()))
}

/// Every role's credentials from `dir` (`zone-<z>.creds` for each of `zones` zones,
/// `gateway.creds`, `supervisor.creds`), each with the certificate material of this
/// process's environment (`MYRIAD_NATS_CA`, ...).
fn from_dir(dir: &Path, zones: u16) -> Result<(Vec<NatsAuth>, NatsAuth, NatsAuth)> {
    let base = NatsAuth::from_env()?;
    let read = |role: Role| -> Result<NatsAuth> {
        let path = creds_path(dir, role);
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let (user, password) = parse_creds(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        // The same TLS material for every role: one server, one authority.
        let pairs = base.env();
        let var = |k: &str| match k {
            USER_ENV => Some(user.clone()),
            PASSWORD_ENV => Some(password.clone()),
            _ => pairs.iter().find(|(n, _)| *n == k).map(|(_, v)| v.clone()),
        };
        Ok(NatsAuth::from_lookup(var)?)
    };
    let z = (0..zones).map(|z| read(Role::Zone(ZoneId(z)))).collect::<Result<Vec<_>>>()?;
    Ok((z, read(Role::Gateway)?, read(Role::Supervisor)?))
}

/// Hands `auth` to a child in its environment, and nothing of this process's own NATS
/// credentials (a credentials file of the parent's would conflict with them).
pub(crate) fn hand(command: &mut Command, auth: &NatsAuth) {
    for var in [USER_ENV, PASSWORD_ENV, CREDS_ENV, CA_ENV, CLIENT_CERT_ENV, CLIENT_KEY_ENV] {
        command.env_remove(var);
    }
    command.envs(auth.env());
}

/// The NATS of cluster `cluster` of `zones` zones: `url` when given (or 127.0.0.1:4222
/// when something answers there and `private` is off), with the roles' credentials from
/// `creds_dir` or, without it, this process's own for everyone (`MYRIAD_NATS_USER`,
/// ...; none: a server without auth); else a private `nats-server` locked down for
/// `cluster`.
pub(crate) fn nats_for(
    url: Option<&str>,
    creds_dir: Option<&Path>,
    private: bool,
    cluster: &str,
    zones: u16,
) -> Result<ClusterNats> {
    let default = "127.0.0.1:4222";
    let given = match url {
        Some(u) => Some(u.to_string()),
        None if !private
            && std::net::TcpStream::connect_timeout(&default.parse()?, Duration::from_millis(300)).is_ok() =>
        {
            Some(format!("nats://{default}"))
        }
        None => None,
    };
    if let Some(url) = given {
        let (zones, gateway, supervisor) = match creds_dir {
            Some(dir) => from_dir(dir, zones)?,
            None => {
                let own = NatsAuth::from_env()?;
                (vec![own.clone(); zones as usize], own.clone(), own)
            }
        };
        return Ok(ClusterNats { url, zones, gateway, supervisor, _local: None });
    }
    if creds_dir.is_some() {
        bail!("--nats-creds-dir names an operator's credentials: give its server with --nats URL");
    }
    start_private(cluster, zones)
}

/// Starts a `nats-server` on a free port of 127.0.0.1 that admits the roles of
/// `cluster` (of `zones` zones) with fresh random passwords (its configuration, mode
/// 0600, in a private temporary folder with its JetStream store).
fn start_private(cluster: &str, zones: u16) -> Result<ClusterNats> {
    let exe = ["nats-server", "/usr/sbin/nats-server", "/usr/local/bin/nats-server"]
        .into_iter()
        .find(|p| Command::new(p).arg("--version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok())
        .context("no NATS server answers at 127.0.0.1:4222 and nats-server is not installed: pass --nats URL")?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
    let addr: SocketAddr = format!("127.0.0.1:{port}").parse()?;
    let dir = tempfile::tempdir()?;
    let creds = new_credentials(cluster, zones)?;
    let config = dir.path().join("nats-server.conf");
    write_private(&config, &render_server_config(cluster, &creds, &addr.to_string(), &dir.path().join("js"))?)
        .with_context(|| format!("writing {}", config.display()))?;
    let child = Command::new(exe)
        .arg("-c")
        .arg(&config)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .context("starting nats-server")?;
    let local = LocalNats { child, _dir: dir };
    let start = Instant::now();
    while std::net::TcpStream::connect_timeout(&addr, Duration::from_millis(100)).is_err() {
        if start.elapsed() > Duration::from_secs(10) {
            bail!("the nats-server started for this run does not answer");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!("started a private nats-server on {addr} for this run (a user per role, random passwords)");
    let auth = |role: Role| creds.iter().find(|c| c.role == role).map(|c| c.auth()).expect("every role");
    Ok(ClusterNats {
        url: format!("nats://{addr}"),
        zones: (0..zones).map(|z| auth(Role::Zone(ZoneId(z)))).collect(),
        gateway: auth(Role::Gateway),
        supervisor: auth(Role::Supervisor),
        _local: Some(local),
    })
}

/// `myriad cluster --write-nats-config DIR --cluster NAME --zones K`: writes the
/// `authorization` block an operator's `nats-server` needs for cluster `cluster` of
/// `zones` zones (`myriad-NAME.conf`) and each role's credentials file (`zone-<z>.creds`,
/// `gateway.creds`, `supervisor.creds`), all mode 0600, with fresh random passwords.
pub(crate) fn write_config(dir: &Path, cluster: &str, zones: u16) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let creds = new_credentials(cluster, zones)?;
    let conf = dir.join(format!("myriad-{cluster}.conf"));
    write_private(&conf, &render_authorization(cluster, &creds)?)
        .with_context(|| format!("writing {}", conf.display()))?;
    for c in &creds {
        let path = creds_path(dir, c.role);
        write_private(&path, &c.creds_file()).with_context(|| format!("writing {}", path.display()))?;
    }
    eprintln!(
        "wrote {} and {}/{{zone-<z>,gateway,supervisor}}.creds: run nats-server with JetStream and that file \
         (e.g. `nats-server -js -c {}`), then `myriad cluster --nats URL --cluster {cluster} --nats-creds-dir {}`",
        conf.display(),
        dir.display(),
        conf.display(),
        dir.display()
    );
    Ok(())
}
