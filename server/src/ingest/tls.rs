//! rustls/quinn configuration of the ingest endpoint: TLS 1.3 only, ring, client certificates
//! required and verified against the pairing CA (see [`super::pki`] for the files).
//!
//! TLS 1.3 caveat: a client without an acceptable certificate still sees its `connect()`
//! succeed; the server then closes the connection with a crypto error (for example
//! `certificate_required`, alert 116) before any stream data is accepted.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use quinn::crypto::rustls::{NoInitialCipherSuite, QuicServerConfig};
use rustls::RootCertStore;
use rustls::crypto::CryptoProvider;
use rustls::pki_types::CertificateDer;
use rustls::server::WebPkiClientVerifier;
use rustls::server::danger::ClientCertVerifier;
use scan3d_service::link::{PemError, read_certs, read_key};

use super::pki::{self, Layout};

pub use scan3d_service::link::{
    IDLE_TIMEOUT, KEEP_ALIVE_INTERVAL, RECEIVE_WINDOW, STREAM_RECEIVE_WINDOW, transport_config,
};

/// Why the TLS configuration could not be built, or a peer could not be identified.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A PEM file is missing, unreadable, not PEM, or holds no certificate.
    #[error("{0}; create the PKI with `scan3d pair --dir DIR --edge NAME`")]
    Pem(#[from] PemError),
    /// The CA certificate is not acceptable as a trust anchor.
    #[error("{}: not usable as the client CA: {source}", path.display())]
    BadCa {
        /// The file.
        path: PathBuf,
        /// rustls' error.
        source: rustls::Error,
    },
    /// The client-certificate verifier could not be built.
    #[error("{}: client certificate verifier: {source}", path.display())]
    Verifier {
        /// The CA file it was built from.
        path: PathBuf,
        /// rustls' error.
        source: rustls::server::VerifierBuilderError,
    },
    /// The certificate and key are unusable together (e.g. the key is not the certificate's).
    #[error("{} / {}: {source}", cert.display(), key.display())]
    CertKey {
        /// The certificate file.
        cert: PathBuf,
        /// The key file.
        key: PathBuf,
        /// rustls' error.
        source: rustls::Error,
    },
    /// rustls rejected the protocol-version selection (ring lacks TLS 1.3; not expected).
    #[error("TLS configuration: {0}")]
    Config(rustls::Error),
    /// The rustls configuration has no cipher suite QUIC can use.
    #[error("QUIC crypto configuration: {0}")]
    Quic(#[from] NoInitialCipherSuite),
    /// The connection carries no client certificate chain.
    #[error("the connection has no verified client certificate")]
    NoPeerCertificate,
    /// The client certificate could not be parsed.
    #[error("client certificate: {0}")]
    BadPeerCertificate(String),
    /// The client certificate's CN is missing or not a valid edge name.
    #[error("client certificate: {0}")]
    BadEdgeName(pki::PkiError),
}

/// The QUIC server configuration of the ingest endpoint, from `DIR/ca.pem` and
/// `DIR/server/server.{pem,key}`: TLS 1.3 only, ring provider, client certificates required
/// and verified against the CA, ALPN [`scan3d_protocol::ALPN`], transport from
/// [`transport_config`].
pub fn server_config(pki_dir: &Path) -> Result<quinn::ServerConfig, TlsError> {
    let layout = Layout::new(pki_dir);
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier = client_verifier(&layout.ca_cert(), provider.clone())?;
    let (cert_path, key_path) = (layout.server_cert(), layout.server_key());
    let chain = read_certs(&cert_path)?;
    let key = read_key(&key_path)?;
    let mut tls = rustls::ServerConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(TlsError::Config)?
        .with_client_cert_verifier(verifier)
        .with_single_cert(chain, key)
        .map_err(|source| TlsError::CertKey {
            cert: cert_path,
            key: key_path,
            source,
        })?;
    tls.alpn_protocols = vec![scan3d_protocol::ALPN.to_vec()];
    let mut config = quinn::ServerConfig::with_crypto(Arc::new(QuicServerConfig::try_from(tls)?));
    config.transport_config(Arc::new(transport_config()));
    Ok(config)
}

/// The identity of the edge at the other end: the CN of its client certificate, which the
/// handshake has verified against the pairing CA. The CN must also be a valid edge name
/// ([`pki::validate_edge_name`]) since it names directories on the server.
pub fn edge_identity(conn: &quinn::Connection) -> Result<String, TlsError> {
    let chain = conn
        .peer_identity()
        .and_then(|id| id.downcast::<Vec<CertificateDer<'static>>>().ok())
        .ok_or(TlsError::NoPeerCertificate)?;
    let leaf = chain.first().ok_or(TlsError::NoPeerCertificate)?;
    edge_name_of(leaf)
}

/// The edge name (CN) in a DER certificate.
fn edge_name_of(der: &CertificateDer<'_>) -> Result<String, TlsError> {
    let (_, cert) = x509_parser::parse_x509_certificate(der)
        .map_err(|e| TlsError::BadPeerCertificate(e.to_string()))?;
    let cn = cert
        .subject()
        .iter_common_name()
        .next()
        .ok_or_else(|| TlsError::BadPeerCertificate("no common name".to_owned()))?
        .as_str()
        .map_err(|e| TlsError::BadPeerCertificate(format!("common name: {e}")))?;
    pki::validate_edge_name(cn).map_err(TlsError::BadEdgeName)?;
    Ok(cn.to_owned())
}

fn client_verifier(
    ca_path: &Path,
    provider: Arc<CryptoProvider>,
) -> Result<Arc<dyn ClientCertVerifier>, TlsError> {
    let mut roots = RootCertStore::empty();
    for cert in read_certs(ca_path)? {
        roots.add(cert).map_err(|source| TlsError::BadCa {
            path: ca_path.to_path_buf(),
            source,
        })?;
    }
    WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
        .build()
        .map_err(|source| TlsError::Verifier {
            path: ca_path.to_path_buf(),
            source,
        })
}

#[cfg(test)]
mod tests {
    use rustls::pki_types::pem::PemObject;

    use super::*;
    use crate::ingest::pki::{PairRequest, pair};

    fn paired(edge: &str) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        pair(&PairRequest {
            dir: dir.path().to_path_buf(),
            edge: edge.to_owned(),
            server_names: vec![],
            force: false,
        })
        .unwrap();
        dir
    }

    #[test]
    fn edge_name_is_the_certificate_cn() {
        let dir = paired("pi-07");
        let der =
            CertificateDer::from_pem_file(Layout::new(dir.path()).edge_cert("pi-07")).unwrap();
        assert_eq!(edge_name_of(&der).unwrap(), "pi-07");
    }

    #[test]
    fn a_cn_that_is_not_an_edge_name_is_refused() {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::default();
        params.distinguished_name = rcgen::DistinguishedName::new();
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, "../etc");
        let cert = params.self_signed(&key).unwrap();
        assert!(matches!(
            edge_name_of(cert.der()),
            Err(TlsError::BadEdgeName(_))
        ));
    }

    #[test]
    fn server_config_loads_a_paired_directory() {
        let dir = paired("pi-01");
        assert!(server_config(dir.path()).is_ok());
    }

    #[test]
    fn missing_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let err = server_config(dir.path()).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("ca.pem"), "{msg}");
        assert!(msg.contains("scan3d pair"), "{msg}");
    }

    #[test]
    fn a_server_key_from_another_pairing_is_refused() {
        let a = paired("pi-01");
        let b = paired("pi-01");
        fs_copy(
            &Layout::new(b.path()).server_key(),
            &Layout::new(a.path()).server_key(),
        );
        let err = server_config(a.path()).unwrap_err();
        assert!(matches!(err, TlsError::CertKey { .. }), "{err}");
    }

    fn fs_copy(from: &Path, to: &Path) {
        std::fs::copy(from, to).unwrap();
    }
}
