//! Who may say what on the fabric: the NATS users of a cluster's three roles (zone,
//! gateway, supervisor), their publish and subscribe permissions, and the `nats-server`
//! configuration that grants them.
//!
//! Every message is signed with the cluster's key, so a stranger cannot forge one; but a
//! signed message can be *replayed* by anyone who can publish on the subject (an old
//! heartbeat hiding a dead zone, for example). Permissions close that to everyone whose
//! credentials do not hold the role: a gateway cannot publish border states, states,
//! heartbeats, control, cut moves or checkpoints; a zone cannot publish session claims,
//! intents or cut moves,
//! nor another zone's heartbeat (each zone has its own user, allowed its own heartbeat
//! subject only, and the supervisor checks the subject against the heartbeat's zone); a
//! client without credentials cannot connect at all. The table is in `docs/zones.md`
//! ("Who may publish what").
//!
//! [`NatsAuth`] is what a process presents: a user and password (from the environment
//! or a credentials file, never from the command line) and, for `tls://` servers, the
//! certificate authority to trust.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::checkpoint::bucket_name;
use crate::claims::sessions_subject;
use crate::error::ZoneError;
use crate::layout::ZoneId;
use crate::nats::{
    check_cluster_name, control_subject, cuts_subject, heartbeat_subject, heartbeats_subject, intents_subject,
    states_subject, subscriptions_subject, views_subject,
};

/// The user name variable (with [`PASSWORD_ENV`]).
pub const USER_ENV: &str = "MYRIAD_NATS_USER";
/// The password variable.
pub const PASSWORD_ENV: &str = "MYRIAD_NATS_PASSWORD";
/// A credentials file: `MYRIAD_NATS_USER=...` and `MYRIAD_NATS_PASSWORD=...` lines.
pub const CREDS_ENV: &str = "MYRIAD_NATS_CREDS";
/// A PEM file of the certificate authorities to trust for `tls://` servers.
pub const CA_ENV: &str = "MYRIAD_NATS_CA";
/// A PEM client certificate for servers that verify clients (with [`CLIENT_KEY_ENV`]).
pub const CLIENT_CERT_ENV: &str = "MYRIAD_NATS_CERT";
/// The client certificate's PEM key.
pub const CLIENT_KEY_ENV: &str = "MYRIAD_NATS_KEY";

/// A process's part in a cluster.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Role {
    /// `myriad zone` of this zone: steps it, talks to its neighbours, stores
    /// checkpoints, beats its own heartbeat.
    Zone(ZoneId),
    /// `myriad gateway`: sends its players' intents, mirrors the states, claims sessions.
    Gateway,
    /// `myriad cluster`'s supervisor (also `myriad replay`): control, heartbeats,
    /// checkpoints.
    Supervisor,
}

impl Role {
    /// Every role of a cluster of `zones` zones, in the order the configuration lists
    /// them: the zones, the gateways, the supervisor.
    pub fn all(zones: u16) -> Vec<Role> {
        (0..zones).map(|z| Role::Zone(ZoneId(z))).chain([Role::Gateway, Role::Supervisor]).collect()
    }

    /// The role's name in user names and file names: `zone-<z>`, `gateway`,
    /// `supervisor`.
    pub fn name(self) -> String {
        match self {
            Role::Zone(z) => format!("zone-{}", z.0),
            Role::Gateway => "gateway".into(),
            Role::Supervisor => "supervisor".into(),
        }
    }
}

/// The NATS user of `role` in `cluster`: `myriad-<cluster>-<role>`.
pub fn user_name(cluster: &str, role: Role) -> String {
    format!("myriad-{cluster}-{}", role.name())
}

/// What one role may publish and subscribe to (NATS subject patterns).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Permissions {
    /// Subjects the role may publish on.
    pub publish: Vec<String>,
    /// Subjects the role may subscribe to.
    pub subscribe: Vec<String>,
}

impl Permissions {
    /// Whether the role may publish on `subject`.
    pub fn may_publish(&self, subject: &str) -> bool {
        self.publish.iter().any(|p| subject_matches(p, subject))
    }

    /// Whether the role may subscribe to `subject` (a literal subject).
    pub fn may_subscribe(&self, subject: &str) -> bool {
        self.subscribe.iter().any(|p| subject_matches(p, subject))
    }
}

/// Whether the NATS pattern `pattern` (`*` one token, `>` the rest) covers `subject`.
pub fn subject_matches(pattern: &str, subject: &str) -> bool {
    let mut s = subject.split('.');
    for p in pattern.split('.') {
        match (p, s.next()) {
            (">", Some(_)) => return true,
            ("*", Some(_)) => {}
            (p, Some(t)) if p == t => {}
            _ => return false,
        }
    }
    s.next().is_none()
}

/// The requests replies come back on (JetStream's answers and acks).
const INBOX: &str = "_INBOX.>";

/// What async-nats (0.51)'s object store publishes for the cluster's bucket, as a
/// server's trace of every operation shows: the stream's info (`get_object_store`) and
/// creation (`create_object_store`); `put`: chunks and metadata on `$O.<bucket>.>` and a
/// purge of an older version's chunks; `info`: a direct get of the last metadata (the
/// bucket is made with `allow_direct`); `get`: an ordered push consumer on the chunks
/// (its creation, and the replies to the server's flow-control messages, which come
/// once a read is large); `delete`: metadata and a purge. `delete_bucket` adds the
/// stream's deletion (the supervisor only). Every grant names the cluster's stream.
fn object_store(cluster: &str, delete_bucket: bool) -> Vec<String> {
    let bucket = bucket_name(cluster);
    let stream = format!("OBJ_{bucket}");
    let mut out = vec![
        format!("$JS.API.STREAM.INFO.{stream}"),
        format!("$JS.API.STREAM.CREATE.{stream}"),
        format!("$JS.API.STREAM.PURGE.{stream}"),
        format!("$JS.API.DIRECT.GET.{stream}.>"),
        format!("$JS.API.CONSUMER.CREATE.{stream}"),
        format!("$JS.FC.{stream}.>"),
        format!("$O.{bucket}.>"),
    ];
    if delete_bucket {
        out.push(format!("$JS.API.STREAM.DELETE.{stream}"));
    }
    out
}

/// The permissions of `role` in `cluster`, from the subject table of `docs/zones.md`.
pub fn permissions(cluster: &str, role: Role) -> Permissions {
    let zones = format!("myriad.{cluster}.zone.*");
    match role {
        Role::Zone(z) => Permissions {
            publish: [zones.clone(), heartbeat_subject(cluster, z), states_subject(cluster), views_subject(cluster)]
                .into_iter()
                .chain(object_store(cluster, false))
                .collect(),
            subscribe: vec![
                zones,
                control_subject(cluster),
                intents_subject(cluster),
                cuts_subject(cluster),
                subscriptions_subject(cluster),
                INBOX.into(),
            ],
        },
        Role::Gateway => Permissions {
            publish: vec![intents_subject(cluster), sessions_subject(cluster), subscriptions_subject(cluster)],
            // Control and cuts read-only: the gateway's map of the cuts (never routed by).
            subscribe: vec![
                states_subject(cluster),
                sessions_subject(cluster),
                views_subject(cluster),
                control_subject(cluster),
                cuts_subject(cluster),
            ],
        },
        Role::Supervisor => Permissions {
            publish: [control_subject(cluster), cuts_subject(cluster)]
                .into_iter()
                .chain(object_store(cluster, true))
                .collect(),
            subscribe: vec![heartbeats_subject(cluster), INBOX.into()],
        },
    }
}

/// One role's user and password.
#[derive(Clone, PartialEq, Eq)]
pub struct RoleCredentials {
    /// The role.
    pub role: Role,
    /// The NATS user.
    pub user: String,
    /// Its password (hex, so it needs no quoting anywhere).
    pub password: String,
}

impl std::fmt::Debug for RoleCredentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RoleCredentials({:?}, {:?}, ..)", self.role, self.user)
    }
}

impl RoleCredentials {
    /// The credentials file of this role (see [`CREDS_ENV`]).
    pub fn creds_file(&self) -> String {
        format!("{USER_ENV}={}\n{PASSWORD_ENV}={}\n", self.user, self.password)
    }

    /// How a process presents them.
    pub fn auth(&self) -> NatsAuth {
        NatsAuth::user(&self.user, &self.password)
    }
}

/// Fresh credentials for every role of `cluster` of `zones` zones, with 192-bit random
/// passwords.
pub fn new_credentials(cluster: &str, zones: u16) -> Result<Vec<RoleCredentials>, ZoneError> {
    check_cluster_name(cluster)?;
    Ok(Role::all(zones)
        .into_iter()
        .map(|role| RoleCredentials { role, user: user_name(cluster, role), password: crate::wire::random_secret() })
        .collect())
}

fn quoted_list(items: &[String]) -> String {
    items.iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ")
}

/// The `authorization` block of a `nats-server` configuration that admits `creds` (of
/// `cluster`) with their roles' permissions and nobody else.
pub fn render_authorization(cluster: &str, creds: &[RoleCredentials]) -> Result<String, ZoneError> {
    check_cluster_name(cluster)?;
    let mut out =
        format!("# Myriad cluster {cluster:?}: one user per role (docs/zones.md, \"Who may publish what\").\n");
    out.push_str("authorization {\n  users = [\n");
    for c in creds {
        let safe = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        if !safe(&c.user) || !safe(&c.password) {
            return Err(ZoneError::Fabric(format!("user {:?}: names and passwords are [A-Za-z0-9_-]", c.user)));
        }
        let p = permissions(cluster, c.role);
        let _ = write!(
            out,
            "    {{\n      user: \"{}\"\n      password: \"{}\"\n      permissions: {{\n        \
             publish: {{ allow: [{}] }}\n        subscribe: {{ allow: [{}] }}\n      }}\n    }}\n",
            c.user,
            c.password,
            quoted_list(&p.publish),
            quoted_list(&p.subscribe)
        );
    }
    out.push_str("  ]\n}\n");
    Ok(out)
}

/// A whole configuration for a private `nats-server` on `listen` (`host:port`) with
/// JetStream in `store_dir`, admitting `creds` only.
pub fn render_server_config(
    cluster: &str,
    creds: &[RoleCredentials],
    listen: &str,
    store_dir: &Path,
) -> Result<String, ZoneError> {
    let dir = store_dir.to_str().filter(|d| !d.contains('"') && !d.contains('\\'));
    let dir =
        dir.ok_or_else(|| ZoneError::Fabric(format!("store directory {}: not a plain path", store_dir.display())))?;
    Ok(format!(
        "listen: \"{listen}\"\njetstream {{\n  store_dir: \"{dir}\"\n}}\n{}",
        render_authorization(cluster, creds)?
    ))
}

/// What a process presents to NATS: optionally a user and password, and the TLS
/// material for `tls://` servers. The default presents nothing (a server without auth).
#[derive(Clone, Default, PartialEq, Eq)]
pub struct NatsAuth {
    user: Option<(String, String)>,
    ca: Option<PathBuf>,
    client_cert: Option<(PathBuf, PathBuf)>,
}

impl std::fmt::Debug for NatsAuth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the password.
        f.debug_struct("NatsAuth")
            .field("user", &self.user.as_ref().map(|(u, _)| u))
            .field("ca", &self.ca)
            .field("client_cert", &self.client_cert)
            .finish()
    }
}

impl NatsAuth {
    /// A user and password.
    pub fn user(user: &str, password: &str) -> NatsAuth {
        NatsAuth { user: Some((user.to_string(), password.to_string())), ..NatsAuth::default() }
    }

    /// Also trusts the certificate authorities in the PEM file `ca` for `tls://` servers.
    pub fn with_ca(mut self, ca: PathBuf) -> NatsAuth {
        self.ca = Some(ca);
        self
    }

    /// The user, if any.
    pub fn user_name(&self) -> Option<&str> {
        self.user.as_ref().map(|(u, _)| u.as_str())
    }

    /// From the process's environment (see [`NatsAuth::from_lookup`]).
    pub fn from_env() -> Result<NatsAuth, ZoneError> {
        NatsAuth::from_lookup(|k| std::env::var(k).ok().filter(|v| !v.is_empty()))
    }

    /// From variables: [`USER_ENV`] and [`PASSWORD_ENV`], or [`CREDS_ENV`] naming a
    /// credentials file (not both); [`CA_ENV`]; [`CLIENT_CERT_ENV`] with
    /// [`CLIENT_KEY_ENV`]. Nothing set: no credentials.
    pub fn from_lookup(var: impl Fn(&str) -> Option<String>) -> Result<NatsAuth, ZoneError> {
        let bad = |m: String| ZoneError::Fabric(m);
        let user = match (var(CREDS_ENV), var(USER_ENV), var(PASSWORD_ENV)) {
            (Some(_), Some(_), _) | (Some(_), _, Some(_)) => {
                return Err(bad(format!("{CREDS_ENV} and {USER_ENV}/{PASSWORD_ENV} are both set: give one")));
            }
            (Some(file), None, None) => {
                let text =
                    std::fs::read_to_string(&file).map_err(|e| bad(format!("reading {CREDS_ENV}={file}: {e}")))?;
                Some(parse_creds(&text).map_err(|e| bad(format!("{CREDS_ENV}={file}: {e}")))?)
            }
            (None, Some(u), Some(p)) => Some((u, p)),
            (None, None, None) => None,
            (None, _, _) => return Err(bad(format!("{USER_ENV} and {PASSWORD_ENV} go together"))),
        };
        let client_cert = match (var(CLIENT_CERT_ENV), var(CLIENT_KEY_ENV)) {
            (Some(c), Some(k)) => Some((PathBuf::from(c), PathBuf::from(k))),
            (None, None) => None,
            _ => return Err(bad(format!("{CLIENT_CERT_ENV} and {CLIENT_KEY_ENV} go together"))),
        };
        Ok(NatsAuth { user, ca: var(CA_ENV).map(PathBuf::from), client_cert })
    }

    /// The variables that hand these credentials to a child process (with
    /// [`CREDS_ENV`] to remove, so that a file of the parent's does not conflict).
    pub fn env(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        if let Some((u, p)) = &self.user {
            out.push((USER_ENV, u.clone()));
            out.push((PASSWORD_ENV, p.clone()));
        }
        if let Some(ca) = &self.ca {
            out.push((CA_ENV, ca.display().to_string()));
        }
        if let Some((c, k)) = &self.client_cert {
            out.push((CLIENT_CERT_ENV, c.display().to_string()));
            out.push((CLIENT_KEY_ENV, k.display().to_string()));
        }
        out
    }

    /// The connection options for `url` (TLS is required when it says `tls://`).
    pub fn options(&self, url: &str) -> async_nats::ConnectOptions {
        let mut o = async_nats::ConnectOptions::new();
        if let Some((u, p)) = &self.user {
            o = o.user_and_password(u.clone(), p.clone());
        }
        if url.trim_start().to_ascii_lowercase().starts_with("tls://") {
            o = o.require_tls(true);
        }
        if let Some(ca) = &self.ca {
            o = o.add_root_certificates(ca.clone());
        }
        if let Some((c, k)) = &self.client_cert {
            o = o.add_client_certificate(c.clone(), k.clone());
        }
        o
    }
}

/// Parses a credentials file: `MYRIAD_NATS_USER=...` and `MYRIAD_NATS_PASSWORD=...`
/// lines (blank lines and `#` comments allowed; anything else is an error).
pub fn parse_creds(text: &str) -> Result<(String, String), String> {
    let (mut user, mut password) = (None, None);
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        match line.split_once('=') {
            Some((USER_ENV, v)) if user.is_none() => user = Some(v.trim().to_string()),
            Some((PASSWORD_ENV, v)) if password.is_none() => password = Some(v.trim().to_string()),
            _ => return Err(format!("line {}: expected one {USER_ENV}=... and one {PASSWORD_ENV}=...", i + 1)),
        }
    }
    match (user, password) {
        (Some(u), Some(p)) if !u.is_empty() && !p.is_empty() => Ok((u, p)),
        _ => Err(format!("needs a {USER_ENV}=... and a {PASSWORD_ENV}=... line")),
    }
}

/// Writes `text` to `path`, readable by its owner only (created so: never a moment
/// readable by others).
pub fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create(true).truncate(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut o, 0o600);
    let mut f = o.open(path)?;
    #[cfg(unix)]
    std::fs::set_permissions(path, std::os::unix::fs::PermissionsExt::from_mode(0o600))?;
    f.write_all(text.as_bytes())
}

#[cfg(test)]
#[path = "fabric_auth_tests.rs"]
mod tests;
