//! What a test does when an outside service or library it needs (MariaDB, NATS, NVRTC) is
//! missing: on a user's machine (`cargo test --workspace`) it skips with a message; where
//! the variable `MYRIAD_REQUIRE_<NAME>=1` is set (CI sets one per dependency), it fails,
//! so a check CI says it runs cannot pass by skipping.
//!
//! A dev-dependency only: no library crate of the workspace uses it.

use std::fmt::Display;
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

/// Whether `require_var` is set to `1`: a missing dependency fails the test.
pub fn required(require_var: &str) -> bool {
    std::env::var(require_var).is_ok_and(|v| v == "1")
}

/// Reports a missing dependency: panics (failing the test) with `why` when `require_var`
/// is `1`, otherwise prints that the test skips and how to make that a failure. The
/// caller returns after it.
pub fn missing(require_var: &str, why: impl Display) {
    report(required(require_var), require_var, why);
}

/// [`missing`] with the variable already read.
fn report(required: bool, require_var: &str, why: impl Display) {
    if required {
        panic!("{why}, and {require_var}=1: this test must run here");
    }
    eprintln!("SKIPPED: {why}; set {require_var}=1 to make this a failure");
}

/// The URL of a service from `url_var` (for example `NATS_URL`), or `None` after
/// [`missing`] when the variable is unset or nothing answers at its host and port: a
/// service that is down is as missing as one never configured. `example` is a URL to
/// suggest.
pub fn service_url(url_var: &str, require_var: &str, example: &str) -> Option<String> {
    let Some(url) = std::env::var(url_var).ok().filter(|u| !u.is_empty()) else {
        missing(require_var, format!("{url_var} is not set (e.g. {url_var}={example})"));
        return None;
    };
    if let Err(e) = reach(&url) {
        missing(require_var, format!("{url_var}={url}, but {e}"));
        return None;
    }
    Some(url)
}

/// `NATS_URL` (the zones' tests), required under `MYRIAD_REQUIRE_NATS=1`.
pub fn nats_url() -> Option<String> {
    service_url("NATS_URL", "MYRIAD_REQUIRE_NATS", "nats://127.0.0.1:4222")
}

/// The `nats-server` program (for tests that start a server of their own, with a
/// configuration of theirs): `NATS_SERVER` if set, else the first of `nats-server` on the
/// `PATH`, `/usr/sbin/nats-server` and `/usr/local/bin/nats-server` that runs; `None`
/// after [`missing`] (under `MYRIAD_REQUIRE_NATS`) when there is none.
pub fn nats_server() -> Option<std::path::PathBuf> {
    let given = std::env::var("NATS_SERVER").ok().filter(|p| !p.is_empty());
    let mut candidates =
        given.iter().map(String::as_str).chain(["nats-server", "/usr/sbin/nats-server", "/usr/local/bin/nats-server"]);
    let runs = |p: &&str| {
        std::process::Command::new(p)
            .arg("--version")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    };
    let found = candidates.find(runs).map(std::path::PathBuf::from);
    if found.is_none() {
        missing("MYRIAD_REQUIRE_NATS", "no nats-server program (NATS_SERVER, PATH, /usr/sbin, /usr/local/bin)");
    }
    found
}

/// `MYSQL_URL` (the MariaDB tests), required under `MYRIAD_REQUIRE_MYSQL=1`.
pub fn mysql_url() -> Option<String> {
    service_url("MYSQL_URL", "MYRIAD_REQUIRE_MYSQL", "mysql://myriad:myriad@127.0.0.1:3306/test")
}

/// Opens (and drops) a TCP connection to the URL's `host:port`.
fn reach(url: &str) -> Result<(), String> {
    let addr = host_port(url).ok_or_else(|| "the URL names no host:port".to_string())?;
    let mut last = format!("{addr} resolves to no address");
    for a in addr.to_socket_addrs().map_err(|e| format!("{addr} does not resolve: {e}"))? {
        match TcpStream::connect_timeout(&a, Duration::from_secs(2)) {
            Ok(_) => return Ok(()),
            Err(e) => last = format!("nothing answers at {a}: {e}"),
        }
    }
    Err(last)
}

/// `host:port` of `scheme://[user[:password]@]host:port[/path]`.
fn host_port(url: &str) -> Option<&str> {
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    let authority = rest.split(['/', '?']).next()?;
    let host_port = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    host_port.contains(':').then_some(host_port)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn host_and_port_come_from_the_authority() {
        assert_eq!(host_port("nats://127.0.0.1:4222"), Some("127.0.0.1:4222"));
        assert_eq!(host_port("mysql://myriad:se@cret@127.0.0.1:3306/test"), Some("127.0.0.1:3306"));
        assert_eq!(host_port("mysql://localhost:3306/test?ssl=false"), Some("localhost:3306"));
        assert_eq!(host_port("nats://localhost"), None);
    }

    #[test]
    fn a_closed_port_is_reported_and_an_open_one_is_reached() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let open = listener.local_addr().unwrap();
        assert_eq!(reach(&format!("nats://{open}")), Ok(()));
        drop(listener);
        let err = reach(&format!("nats://{open}")).unwrap_err();
        assert!(err.contains("nothing answers"), "{err}");
    }

    #[test]
    #[should_panic(expected = "the service is not here, and MYRIAD_REQUIRE_X=1: this test must run here")]
    fn a_required_dependency_that_is_missing_fails() {
        report(true, "MYRIAD_REQUIRE_X", "the service is not here");
    }

    #[test]
    fn an_optional_dependency_that_is_missing_skips() {
        assert!(!required("MYRIAD_TESTENV_NEVER_SET"));
        assert_eq!(service_url("MYRIAD_TESTENV_NEVER_SET_URL", "MYRIAD_TESTENV_NEVER_SET", "nats://x:1"), None);
    }
}
