//! How the client trusts the login server: a pinned certificate (the development one in
//! the server's data directory) or CA certificates (production).

use std::path::Path;
use std::sync::Arc;

use rustls::DigitallySignedStruct;
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, verify_tls12_signature, verify_tls13_signature};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};

use crate::error::ClientError;

/// Which server certificates the client accepts.
#[derive(Debug, Clone)]
pub enum Trust {
    /// Exactly these certificates (byte for byte), whatever name they carry: pinning the
    /// server's self-signed development certificate.
    Pinned(Vec<CertificateDer<'static>>),
    /// Certificates chaining to these CA roots and valid for the server name.
    Roots(Vec<CertificateDer<'static>>),
}

fn read_pem(path: &Path) -> Result<Vec<CertificateDer<'static>>, ClientError> {
    let err = |e: rustls::pki_types::pem::Error| ClientError::Tls(format!("{}: {e}", path.display()));
    let certs = CertificateDer::pem_file_iter(path).map_err(err)?.collect::<Result<Vec<_>, _>>().map_err(err)?;
    if certs.is_empty() {
        return Err(ClientError::Tls(format!("{}: no certificate", path.display())));
    }
    Ok(certs)
}

impl Trust {
    /// Pins the certificate(s) of a PEM file (e.g. `data/tls-cert.pem`).
    pub fn pin_file(path: &Path) -> Result<Self, ClientError> {
        Ok(Trust::Pinned(read_pem(path)?))
    }

    /// Trusts the CA certificates of a PEM file.
    pub fn ca_file(path: &Path) -> Result<Self, ClientError> {
        Ok(Trust::Roots(read_pem(path)?))
    }

    /// The rustls configuration: TLS 1.3 only, ring provider.
    pub fn client_config(&self) -> Result<Arc<rustls::ClientConfig>, ClientError> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let builder = rustls::ClientConfig::builder_with_provider(provider.clone())
            .with_protocol_versions(&[&rustls::version::TLS13])
            .map_err(|e| ClientError::Tls(e.to_string()))?;
        let config = match self {
            Trust::Pinned(certs) => builder
                .dangerous()
                .with_custom_certificate_verifier(Arc::new(PinnedVerifier { certs: certs.clone(), provider }))
                .with_no_client_auth(),
            Trust::Roots(certs) => {
                let mut roots = rustls::RootCertStore::empty();
                for c in certs {
                    roots.add(c.clone()).map_err(|e| ClientError::Tls(e.to_string()))?;
                }
                builder.with_root_certificates(roots).with_no_client_auth()
            }
        };
        Ok(Arc::new(config))
    }
}

/// Accepts only the pinned certificates, and still checks that the server proves it
/// holds their key (the handshake signatures).
#[derive(Debug)]
struct PinnedVerifier {
    certs: Vec<CertificateDer<'static>>,
    provider: Arc<CryptoProvider>,
}

impl ServerCertVerifier for PinnedVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        if self.certs.iter().any(|c| c.as_ref() == end_entity.as_ref()) {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::InvalidCertificate(rustls::CertificateError::UnknownIssuer))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        verify_tls12_signature(message, cert, dss, &self.provider.signature_verification_algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        verify_tls13_signature(message, cert, dss, &self.provider.signature_verification_algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<rustls::SignatureScheme> {
        self.provider.signature_verification_algorithms.supported_schemes()
    }
}
