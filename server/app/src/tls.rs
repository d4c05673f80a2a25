//! TLS for the listener (`tls-cert`, `tls-key`): the server's certificate chain and private key, read from PEM
//! files into a rustls server configuration (ring's primitives, TLS 1.2 and 1.3). The handshake itself runs on
//! each accepted connection in [`crate::http`], under the header-read timeout.

use std::path::Path;
use std::sync::Arc;

use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls::{self, ServerConfig};

#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("reading {path}: {source}")]
    Read { path: String, source: std::io::Error },
    #[error("{path} holds no {what} in PEM: {detail}")]
    Pem { path: String, what: &'static str, detail: String },
    #[error("the certificate chain of {cert} and the key of {key} make no TLS configuration: {source}")]
    Config { cert: String, key: String, source: rustls::Error },
}

/// The acceptor of a server presenting the chain in `cert` (PEM, leaf first) with the private key in `key` (PEM:
/// PKCS#8, PKCS#1 or SEC1).
pub fn acceptor(cert: &Path, key: &Path) -> Result<TlsAcceptor, TlsError> {
    let chain = certificates(cert)?;
    let key_pem = read(key)?;
    let private_key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| TlsError::Pem {
        path: key.display().to_string(),
        what: "private key",
        detail: e.to_string(),
    })?;
    let config_error =
        |source| TlsError::Config { cert: cert.display().to_string(), key: key.display().to_string(), source };
    let config = ServerConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
        .with_safe_default_protocol_versions()
        .map_err(config_error)?
        .with_no_client_auth()
        .with_single_cert(chain, private_key)
        .map_err(config_error)?;
    Ok(TlsAcceptor::from(Arc::new(config)))
}

/// Every certificate of the PEM file `path`, in order (a server's chain, or the roots a client trusts); at least
/// one.
pub fn certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let pem_error = |detail: String| TlsError::Pem { path: path.display().to_string(), what: "certificate", detail };
    let chain = CertificateDer::pem_slice_iter(&read(path)?)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| pem_error(e.to_string()))?;
    if chain.is_empty() {
        return Err(pem_error("no CERTIFICATE section".into()));
    }
    Ok(chain)
}

fn read(path: &Path) -> Result<Vec<u8>, TlsError> {
    std::fs::read(path).map_err(|source| TlsError::Read { path: path.display().to_string(), source })
}
