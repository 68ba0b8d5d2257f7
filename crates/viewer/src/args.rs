//! Command-line flags.

use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;

/// `myriad-viewer`: log in one player and show the world around it.
/// It has no `Debug`, so the password cannot end up in a log by accident.
#[derive(clap::Parser, Clone)]
#[command(name = "myriad-viewer", version, about)]
pub struct Args {
    /// Login service of the server (HOST:PORT).
    #[arg(long, default_value = "127.0.0.1:7778")]
    pub server: String,
    /// Account name.
    #[arg(long, env = "MYRIAD_USER")]
    pub user: String,
    /// Password (prefer the environment variable: a flag shows in the process list).
    #[arg(long, env = "MYRIAD_PASSWORD", hide_env_values = true)]
    pub password: Option<String>,
    /// Pin this certificate: the server's development certificate, `<data_dir>/tls-cert.pem`.
    #[arg(long, default_value = "data/tls-cert.pem")]
    pub cert: PathBuf,
    /// Trust CA certificates from this PEM file instead of pinning (production servers).
    #[arg(long)]
    pub ca: Option<PathBuf>,
    /// Far plane in units: objects farther from the camera are not drawn.
    #[arg(long, default_value_t = 300.0)]
    pub far: f32,
    /// Window size, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x720", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Most terrain vertices per side (the heightmap is decimated beyond that).
    #[arg(long, default_value_t = 512)]
    pub terrain_res: u32,
    /// Render this many frames after the first world update, print frame times, exit.
    #[arg(long)]
    pub frames: Option<u64>,
    /// Save the last frame as a PNG here (with --frames).
    #[arg(long, requires = "frames")]
    pub screenshot: Option<PathBuf>,
    /// Add this many synthetic objects around the player (drawn like the server's, updated
    /// with every snapshot) to measure rendering under load.
    #[arg(long, default_value_t = 0)]
    pub bench_objects: usize,
    /// Multisample anti-aliasing samples (0, 2, 4, 8); 0 is much cheaper in software
    /// rendering.
    #[arg(long, default_value_t = 4, value_parser = parse_msaa)]
    pub msaa: u8,
    /// Seconds to wait for the first world update with --frames before giving up.
    #[arg(long, default_value_t = 30.0)]
    pub wait: f64,
    /// How far the drawn world trails the server, in ticks (objects are interpolated
    /// between the states around that time; 0 draws the newest states).
    #[arg(long, default_value_t = myriad_client::Interpolation::default().delay_ticks, value_parser = parse_delay)]
    pub render_delay_ticks: f64,
    /// How long an object is extrapolated past its newest state before it is held, ms.
    #[arg(long, default_value_t = myriad_client::Interpolation::default().max_extrapolation.as_millis() as u64)]
    pub max_extrapolation_ms: u64,
}

/// Parses a render delay in ticks: finite, 0 to 30.
pub fn parse_delay(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(d) if (0.0..=30.0).contains(&d) => Ok(d),
        _ => Err(format!("{s:?}: a number of ticks from 0 to 30")),
    }
}

/// Parses `WIDTHxHEIGHT`.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("{s:?}: expected WIDTHxHEIGHT, e.g. 1280x720"))?;
    let parse = |v: &str| v.trim().parse::<u32>().ok().filter(|n| (16..=16384).contains(n));
    match (parse(w), parse(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err(format!("{s:?}: width and height must be whole numbers from 16 to 16384")),
    }
}

/// Parses a multisample count: 0, 2, 4 or 8.
pub fn parse_msaa(s: &str) -> Result<u8, String> {
    match s.parse::<u8>() {
        Ok(n @ (0 | 2 | 4 | 8)) => Ok(n),
        _ => Err(format!("{s:?}: 0, 2, 4 or 8")),
    }
}

/// Resolves `HOST:PORT` to an address, and returns the host part (the name the server's
/// certificate is checked against when trusting a CA).
pub fn resolve_server(s: &str) -> Result<(SocketAddr, String), String> {
    let bad = |why: String| format!("--server {s:?}: {why}");
    let (host, port) = s.rsplit_once(':').ok_or_else(|| bad("expected HOST:PORT, e.g. 127.0.0.1:7778".into()))?;
    port.parse::<u16>().map_err(|_| bad(format!("{port:?} is not a port number")))?;
    let host = host.trim_start_matches('[').trim_end_matches(']').to_string();
    if host.is_empty() {
        return Err(bad("no host".into()));
    }
    let addr = s
        .to_socket_addrs()
        .map_err(|e| bad(format!("cannot resolve: {e}")))?
        .next()
        .ok_or_else(|| bad("the name has no address".into()))?;
    Ok((addr, host))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[test]
    fn sizes() {
        assert_eq!(parse_size("1280x720"), Ok((1280, 720)));
        assert_eq!(parse_size("640X480"), Ok((640, 480)));
        assert!(parse_size("1280").is_err());
        assert!(parse_size("0x720").is_err());
        assert!(parse_size("axb").is_err());
        assert_eq!(parse_msaa("8"), Ok(8));
        assert!(parse_msaa("3").is_err());
    }

    #[test]
    fn server_addresses() {
        let (addr, host) = resolve_server("127.0.0.1:7778").unwrap();
        assert_eq!(addr, "127.0.0.1:7778".parse().unwrap());
        assert_eq!(host, "127.0.0.1");
        let (addr, host) = resolve_server("[::1]:9").unwrap();
        assert_eq!((addr.port(), host.as_str()), (9, "::1"));
        assert!(resolve_server("localhost").unwrap_err().contains("HOST:PORT"));
        assert!(resolve_server("127.0.0.1:http").unwrap_err().contains("not a port"));
        assert!(resolve_server(":7778").is_err());
    }

    #[test]
    fn flags_and_defaults() {
        let a = Args::try_parse_from(["myriad-viewer", "--user", "user3", "--frames", "5", "--screenshot", "s.png"])
            .unwrap();
        assert_eq!(a.server, "127.0.0.1:7778");
        assert_eq!(a.cert, PathBuf::from("data/tls-cert.pem"));
        assert_eq!((a.frames, a.size, a.far), (Some(5), (1280, 720), 300.0));
        assert!(Args::try_parse_from(["myriad-viewer", "--user", "u", "--screenshot", "s.png"]).is_err());
        let p = Args::try_parse_from(["v", "--user", "u", "--password", "pw", "--ca", "ca.pem"]).unwrap();
        assert_eq!((p.password.as_deref(), p.ca), (Some("pw"), Some(PathBuf::from("ca.pem"))));
    }
}
