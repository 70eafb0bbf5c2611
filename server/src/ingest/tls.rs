//! rustls/quinn configuration of the ingest endpoint: TLS 1.3 only, ring, client certificates
//! required and verified against the pairing CA (see [`super::pki`] for the files).
//!
//! Revocation: the verifier checks client certificates against `DIR/crl.pem` (written by
//! `scan3d pair --revoke/--renew/--force`), read when the configuration is built and again by
//! [`reload_revocation_lists`] (`scan3d serve` calls it on SIGHUP), without a restart. A reload
//! applies to new handshakes; an edge already connected with a certificate revoked since keeps
//! its connection until it reconnects (at the latest when its link drops). Expired client
//! certificates are refused by the handshake (the server has a real-time clock).
//!
//! TLS 1.3 caveat: a client without an acceptable certificate still sees its `connect()`
//! succeed; the server then closes the connection with a crypto error (for example
//! `certificate_required`, alert 116) before any stream data is accepted.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError, RwLock, Weak};

use quinn::crypto::rustls::{NoInitialCipherSuite, QuicServerConfig};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, CertificateRevocationListDer, UnixTime};
use rustls::server::WebPkiClientVerifier;
use rustls::server::danger::{ClientCertVerified, ClientCertVerifier};
use rustls::{DigitallySignedStruct, DistinguishedName, RootCertStore, SignatureScheme};
use scan3d_service::link::{PemError, read_certs, read_private_key};

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
    /// The revocation list is unreadable, not a CRL, or not issued by the CA.
    #[error("{}: unusable revocation list: {reason}", path.display())]
    BadCrl {
        /// `DIR/crl.pem`.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
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

/// The QUIC server configuration of the ingest endpoint, from `DIR/ca.pem`, `DIR/crl.pem` (if
/// present) and `DIR/server/server.{pem,key}`: TLS 1.3 only, ring provider, client certificates
/// required, verified against the CA and the revocation list, ALPN [`scan3d_protocol::ALPN`],
/// transport from [`transport_config`]. The server key must not be accessible to other users
/// ([`scan3d_service::link::check_key_mode`]). The verifier is registered for
/// [`reload_revocation_lists`].
pub fn server_config(pki_dir: &Path) -> Result<quinn::ServerConfig, TlsError> {
    Ok(reloadable_server_config(pki_dir)?.0)
}

/// [`server_config`] and its verifier, whose [`RevocableVerifier::reload`] re-reads the CRL.
pub fn reloadable_server_config(
    pki_dir: &Path,
) -> Result<(quinn::ServerConfig, Arc<RevocableVerifier>), TlsError> {
    let layout = Layout::new(pki_dir);
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier = Arc::new(RevocableVerifier::new(layout.clone(), provider.clone())?);
    let (cert_path, key_path) = (layout.server_cert(), layout.server_key());
    let chain = read_certs(&cert_path)?;
    let key = read_private_key(&key_path)?;
    let mut tls = rustls::ServerConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(TlsError::Config)?
        .with_client_cert_verifier(verifier.clone())
        .with_single_cert(chain, key)
        .map_err(|source| TlsError::CertKey {
            cert: cert_path,
            key: key_path,
            source,
        })?;
    tls.alpn_protocols = vec![scan3d_protocol::ALPN.to_vec()];
    let mut config = quinn::ServerConfig::with_crypto(Arc::new(QuicServerConfig::try_from(tls)?));
    config.transport_config(Arc::new(transport_config()));
    lock(&LIVE_VERIFIERS).push(Arc::downgrade(&verifier));
    Ok((config, verifier))
}

/// Every verifier [`reloadable_server_config`] built that is still in use.
static LIVE_VERIFIERS: Mutex<Vec<Weak<RevocableVerifier>>> = Mutex::new(Vec::new());

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Re-reads the revocation list of every live server configuration (one per running endpoint;
/// `scan3d serve` has one) and returns each one's PKI directory and outcome. A configuration
/// whose new list is unusable keeps its previous one.
pub fn reload_revocation_lists() -> Vec<(PathBuf, Result<CrlStatus, TlsError>)> {
    let live: Vec<Arc<RevocableVerifier>> = {
        let mut verifiers = lock(&LIVE_VERIFIERS);
        verifiers.retain(|v| v.strong_count() > 0);
        verifiers.iter().filter_map(Weak::upgrade).collect()
    };
    live.iter()
        .map(|v| (v.layout.root().to_path_buf(), v.reload()))
        .collect()
}

/// What a verifier checks revocation against.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CrlStatus {
    /// `DIR/crl.pem` does not exist: no certificate is revoked (a PKI made before revocation
    /// existed; the next `scan3d pair` run creates the list).
    Absent,
    /// `DIR/crl.pem` with this many revoked certificates.
    Loaded {
        /// Revoked serial numbers in the list.
        revoked: usize,
    },
}

/// The client-certificate verifier of the ingest endpoint: webpki's, against the pairing CA and
/// the current revocation list, replaceable while the endpoint runs ([`Self::reload`]).
#[derive(Debug)]
pub struct RevocableVerifier {
    layout: Layout,
    provider: Arc<CryptoProvider>,
    roots: Arc<RootCertStore>,
    hints: Vec<DistinguishedName>,
    current: RwLock<Arc<dyn ClientCertVerifier>>,
}

impl RevocableVerifier {
    fn new(layout: Layout, provider: Arc<CryptoProvider>) -> Result<Self, TlsError> {
        let ca_path = layout.ca_cert();
        let mut roots = RootCertStore::empty();
        for cert in read_certs(&ca_path)? {
            roots.add(cert).map_err(|source| TlsError::BadCa {
                path: ca_path.clone(),
                source,
            })?;
        }
        let roots = Arc::new(roots);
        let hints = roots.subjects();
        let (inner, status) = build_verifier(&layout, &roots, &provider)?;
        tracing::info!(pki = %layout.root().display(), ?status, "client certificate revocation list");
        Ok(RevocableVerifier {
            layout,
            provider,
            roots,
            hints,
            current: RwLock::new(inner),
        })
    }

    /// Re-reads `DIR/crl.pem` and verifies new handshakes against it. On error the previous
    /// list stays in force.
    pub fn reload(&self) -> Result<CrlStatus, TlsError> {
        let (inner, status) = build_verifier(&self.layout, &self.roots, &self.provider)?;
        *self.current.write().unwrap_or_else(PoisonError::into_inner) = inner;
        Ok(status)
    }

    fn inner(&self) -> Arc<dyn ClientCertVerifier> {
        self.current
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

impl ClientCertVerifier for RevocableVerifier {
    fn offer_client_auth(&self) -> bool {
        true
    }

    fn client_auth_mandatory(&self) -> bool {
        true
    }

    fn root_hint_subjects(&self) -> &[DistinguishedName] {
        &self.hints
    }

    fn verify_client_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        now: UnixTime,
    ) -> Result<ClientCertVerified, rustls::Error> {
        self.inner()
            .verify_client_cert(end_entity, intermediates, now)
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<rustls::client::danger::HandshakeSignatureValid, rustls::Error> {
        self.inner().verify_tls12_signature(message, cert, dss)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<rustls::client::danger::HandshakeSignatureValid, rustls::Error> {
        self.inner().verify_tls13_signature(message, cert, dss)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.inner().supported_verify_schemes()
    }
}

/// webpki's verifier for the CA `roots` and the CRL in `DIR/crl.pem`, if there is one. Only the
/// edge certificate is checked (the CA is the trust anchor; there are no intermediates), and a
/// certificate the list cannot speak for is refused.
fn build_verifier(
    layout: &Layout,
    roots: &Arc<RootCertStore>,
    provider: &Arc<CryptoProvider>,
) -> Result<(Arc<dyn ClientCertVerifier>, CrlStatus), TlsError> {
    let crl_path = layout.crl();
    let builder = WebPkiClientVerifier::builder_with_provider(roots.clone(), provider.clone());
    let (builder, status) = match std::fs::read(&crl_path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => (builder, CrlStatus::Absent),
        Err(e) => {
            return Err(TlsError::BadCrl {
                path: crl_path,
                reason: e.to_string(),
            });
        }
        Ok(pem) => {
            let bad = |reason: String| TlsError::BadCrl {
                path: crl_path.clone(),
                reason,
            };
            let der = CertificateRevocationListDer::from_pem_slice(&pem)
                .map_err(|e| bad(format!("no PEM CRL: {e}")))?;
            let revoked = pki::check_crl(&der, &layout.ca_cert()).map_err(bad)?;
            (
                builder.with_crls([der]).only_check_end_entity_revocation(),
                CrlStatus::Loaded { revoked },
            )
        }
    };
    let verifier = builder.build().map_err(|source| TlsError::Verifier {
        path: layout.ca_cert(),
        source,
    })?;
    Ok((verifier, status))
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

    #[test]
    fn a_server_key_readable_by_others_is_refused() {
        use std::os::unix::fs::PermissionsExt;
        let dir = paired("pi-01");
        let key = Layout::new(dir.path()).server_key();
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o640)).unwrap();
        let err = server_config(dir.path()).unwrap_err();
        assert!(
            matches!(err, TlsError::Pem(PemError::KeyTooOpen { mode: 0o640, .. })),
            "{err}"
        );
        assert!(err.to_string().contains("server.key"), "{err}");
    }

    #[test]
    fn a_revocation_list_of_another_ca_is_refused_and_the_old_one_kept() {
        let a = paired("pi-01");
        let b = paired("pi-01");
        let (_config, verifier) = reloadable_server_config(a.path()).unwrap();
        fs_copy(&Layout::new(b.path()).crl(), &Layout::new(a.path()).crl());
        let err = verifier.reload().unwrap_err();
        assert!(matches!(err, TlsError::BadCrl { .. }), "{err}");
        assert!(err.to_string().contains("not by the CA"), "{err}");
        assert!(server_config(a.path()).is_err());
        // Without a list at all, nothing is revoked (a PKI from before revocation).
        std::fs::remove_file(Layout::new(a.path()).crl()).unwrap();
        assert_eq!(verifier.reload().unwrap(), CrlStatus::Absent);
    }
}
