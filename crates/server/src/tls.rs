//! The login service's TLS identity: configured PEM files in production, or a
//! self-signed development certificate generated once into the data directory.
//!
//! Clients verify the server with the certificate itself (development: pin
//! `data_dir/tls-cert.pem`) or with their usual roots (production certificates).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};

use crate::config::ServerConfig;
use crate::error::ServerError;

/// File name of the development certificate inside the data directory.
pub const DEV_CERT_FILE: &str = "tls-cert.pem";
/// File name of the development private key inside the data directory.
pub const DEV_KEY_FILE: &str = "tls-key.pem";

/// Where the certificate and key the server uses live (generating the development pair
/// when no files are configured and none exist yet).
pub fn certificate_paths(config: &ServerConfig) -> Result<(PathBuf, PathBuf), ServerError> {
    if !config.tls_cert.as_os_str().is_empty() {
        return Ok((config.tls_cert.clone(), config.tls_key.clone()));
    }
    let cert = config.data_dir.join(DEV_CERT_FILE);
    let key = config.data_dir.join(DEV_KEY_FILE);
    if !(cert.exists() && key.exists()) {
        generate_dev_certificate(&cert, &key, &config.tls_names)?;
        tracing::info!(cert = %cert.display(), "generated a self-signed development certificate");
    }
    Ok((cert, key))
}

fn generate_dev_certificate(cert: &Path, key: &Path, extra: &[String]) -> Result<(), ServerError> {
    let mut names = vec!["localhost".to_string(), "127.0.0.1".to_string(), "::1".to_string()];
    names.extend(extra.iter().cloned());
    let pair = rcgen::generate_simple_self_signed(names).map_err(|e| ServerError::Tls(e.to_string()))?;
    if let Some(dir) = cert.parent() {
        std::fs::create_dir_all(dir).map_err(|e| ServerError::io(format!("creating {}", dir.display()), e))?;
    }
    write_private(key, pair.signing_key.serialize_pem().as_bytes())?;
    std::fs::write(cert, pair.cert.pem()).map_err(|e| ServerError::io(format!("writing {}", cert.display()), e))
}

/// Writes a file readable by its owner only (the private key).
fn write_private(path: &Path, bytes: &[u8]) -> Result<(), ServerError> {
    use std::io::Write;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    let mut f = options.open(path).map_err(|e| ServerError::io(format!("writing {}", path.display()), e))?;
    f.write_all(bytes).map_err(|e| ServerError::io(format!("writing {}", path.display()), e))
}

/// The rustls configuration of the login service: TLS 1.3 only, ring provider.
pub fn server_config(config: &ServerConfig) -> Result<Arc<rustls::ServerConfig>, ServerError> {
    let (cert_path, key_path) = certificate_paths(config)?;
    let tls = |what: &Path, e: rustls::pki_types::pem::Error| ServerError::Tls(format!("{}: {e}", what.display()));
    let certs = CertificateDer::pem_file_iter(&cert_path)
        .map_err(|e| tls(&cert_path, e))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| tls(&cert_path, e))?;
    if certs.is_empty() {
        return Err(ServerError::Tls(format!("{}: no certificate", cert_path.display())));
    }
    let key = PrivateKeyDer::from_pem_file(&key_path).map_err(|e| tls(&key_path, e))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let server = rustls::ServerConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| ServerError::Tls(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|e| ServerError::Tls(e.to_string()))?;
    Ok(Arc::new(server))
}
