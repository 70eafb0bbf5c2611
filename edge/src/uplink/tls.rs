//! The edge bundle → quinn client configuration: TLS 1.3 only, ring, the pairing CA as the only
//! root, the edge certificate for client authentication.
//!
//! The bundle is the directory `scan3d pair --dir DIR --edge NAME` writes as `DIR/edges/NAME`
//! on the server machine: `edge.pem`, `edge.key` (mode 0600) and `ca.pem`.
//!
//! TLS 1.3 caveat: with a certificate the server refuses, `connect()` still succeeds; the
//! server then closes the connection with a crypto error. An early close right after connect
//! is an authentication failure, not a network problem.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use quinn::crypto::rustls::{NoInitialCipherSuite, QuicClientConfig};
use rustls::RootCertStore;
use scan3d_service::link::{PemError, read_certs, read_private_key, transport_config};

/// The edge certificate in a bundle.
pub const BUNDLE_CERT: &str = "edge.pem";
/// The edge private key in a bundle.
pub const BUNDLE_KEY: &str = "edge.key";
/// The pairing CA certificate in a bundle.
pub const BUNDLE_CA: &str = "ca.pem";

pub use scan3d_service::link::{IDLE_TIMEOUT, KEEP_ALIVE_INTERVAL};

const PAIR_HINT: &str = "run `scan3d pair --dir DIR --edge NAME` on the server machine and copy DIR/edges/NAME to the Pi";

/// Why the edge bundle could not be turned into a client configuration.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A bundle file is missing, unreadable, not PEM, or holds no certificate.
    #[error("{0}; {PAIR_HINT}")]
    Pem(#[from] PemError),
    /// The CA certificate is not acceptable as a trust anchor.
    #[error("{}: not usable as the server CA: {source}; {PAIR_HINT}", path.display())]
    BadCa {
        /// The file.
        path: PathBuf,
        /// rustls' error.
        source: rustls::Error,
    },
    /// The certificate and key are unusable together (e.g. from two different pairings).
    #[error("{} / {}: {source}; {PAIR_HINT}", cert.display(), key.display())]
    CertKey {
        /// The certificate file.
        cert: PathBuf,
        /// The key file.
        key: PathBuf,
        /// rustls' error.
        source: rustls::Error,
    },
    /// rustls rejected the protocol-version selection (not expected with ring).
    #[error("TLS configuration: {0}")]
    Config(rustls::Error),
    /// The rustls configuration has no cipher suite QUIC can use.
    #[error("QUIC crypto configuration: {0}")]
    Quic(#[from] NoInitialCipherSuite),
}

/// The quinn client configuration from an edge bundle directory (`edge.pem`, `edge.key`,
/// `ca.pem`): TLS 1.3 only, ring provider, roots = the pairing CA only, the edge certificate
/// for client authentication, ALPN [`scan3d_protocol::ALPN`], keep-alive
/// [`KEEP_ALIVE_INTERVAL`] and idle timeout [`IDLE_TIMEOUT`]. The server name given to
/// `Endpoint::connect` must be one of the server certificate's names (`--server-name`).
pub fn client_config(bundle_dir: &Path) -> Result<quinn::ClientConfig, TlsError> {
    let (cert_path, key_path, ca_path) = (
        bundle_dir.join(BUNDLE_CERT),
        bundle_dir.join(BUNDLE_KEY),
        bundle_dir.join(BUNDLE_CA),
    );
    let mut roots = RootCertStore::empty();
    for ca in read_certs(&ca_path)? {
        roots.add(ca).map_err(|source| TlsError::BadCa {
            path: ca_path.clone(),
            source,
        })?;
    }
    let chain = read_certs(&cert_path)?;
    // A key others can read is refused, as ssh does: the bundle's key is the edge's identity.
    let key = read_private_key(&key_path)?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(TlsError::Config)?
        .with_root_certificates(roots)
        .with_client_auth_cert(chain, key)
        .map_err(|source| TlsError::CertKey {
            cert: cert_path,
            key: key_path,
            source,
        })?;
    tls.alpn_protocols = vec![scan3d_protocol::ALPN.to_vec()];
    let mut config = quinn::ClientConfig::new(Arc::new(QuicClientConfig::try_from(tls)?));
    config.transport_config(Arc::new(uplink_transport_config()));
    Ok(config)
}

/// The link's shared transport settings with BBR congestion control, for the edge, which sends
/// nearly all the bytes. On a lossy, jittery link (the soak run: 5 % loss, 200 ± 50 ms each way,
/// reordering) quinn's default Cubic takes reordering for loss and collapsed to ~2 frames/s
/// per edge against 10.5 produced; BBR, which does not back off on loss alone, kept 16 edges
/// up with nothing left spooled (`tests/tests/soak.rs`).
pub fn uplink_transport_config() -> quinn::TransportConfig {
    let mut transport = transport_config();
    transport.congestion_controller_factory(Arc::new(quinn::congestion::BbrConfig::default()));
    transport
}

#[cfg(test)]
mod tests {
    use std::net::{Ipv4Addr, SocketAddr};
    use std::time::Duration;

    use rcgen::{
        BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer,
        KeyPair, KeyUsagePurpose,
    };
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

    use super::*;
    use crate::uplink::client::{ConnectFailure, classify};

    /// A CA with a server certificate for `localhost` and one client certificate.
    struct TestPki {
        ca_pem: String,
        server_der: CertificateDer<'static>,
        server_key: Vec<u8>,
        edge_pem: String,
        edge_key_pem: String,
        edge_der: CertificateDer<'static>,
    }

    fn test_pki(ca_name: &str) -> TestPki {
        let ca_key = KeyPair::generate().unwrap();
        let mut ca_params = CertificateParams::default();
        ca_params.distinguished_name = rcgen::DistinguishedName::new();
        ca_params
            .distinguished_name
            .push(DnType::CommonName, ca_name);
        ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        ca_params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let ca_cert = ca_params.self_signed(&ca_key).unwrap();
        let issuer = Issuer::new(ca_params, ca_key);

        let server_key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(vec!["localhost".to_owned()]).unwrap();
        params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
        params.use_authority_key_identifier_extension = true;
        let server_cert = params.signed_by(&server_key, &issuer).unwrap();

        let edge_key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(vec!["pi-01".to_owned()]).unwrap();
        params.distinguished_name.push(DnType::CommonName, "pi-01");
        params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
        params.use_authority_key_identifier_extension = true;
        let edge_cert = params.signed_by(&edge_key, &issuer).unwrap();

        TestPki {
            ca_pem: ca_cert.pem(),
            server_der: server_cert.der().clone(),
            server_key: server_key.serialize_der(),
            edge_pem: edge_cert.pem(),
            edge_key_pem: edge_key.serialize_pem(),
            edge_der: edge_cert.der().clone(),
        }
    }

    fn write_bundle(pki: &TestPki) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(BUNDLE_CERT), &pki.edge_pem).unwrap();
        write_key(&dir.path().join(BUNDLE_KEY), &pki.edge_key_pem);
        std::fs::write(dir.path().join(BUNDLE_CA), &pki.ca_pem).unwrap();
        dir
    }

    /// Writes a private key readable by its owner only, as `scan3d pair` does.
    fn write_key(path: &Path, pem: &str) {
        use std::os::unix::fs::PermissionsExt;
        std::fs::write(path, pem).unwrap();
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).unwrap();
    }

    /// A quinn server on 127.0.0.1 requiring client certificates from `pki`'s CA.
    fn server(pki: &TestPki) -> quinn::Endpoint {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut roots = RootCertStore::empty();
        roots
            .add(CertificateDer::from_pem_slice(pki.ca_pem.as_bytes()).unwrap())
            .unwrap();
        let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(
            Arc::new(roots),
            provider.clone(),
        )
        .build()
        .unwrap();
        let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(pki.server_key.clone()));
        let mut tls = rustls::ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13])
            .unwrap()
            .with_client_cert_verifier(verifier)
            .with_single_cert(vec![pki.server_der.clone()], key)
            .unwrap();
        tls.alpn_protocols = vec![scan3d_protocol::ALPN.to_vec()];
        let config = quinn::ServerConfig::with_crypto(Arc::new(
            quinn::crypto::rustls::QuicServerConfig::try_from(tls).unwrap(),
        ));
        quinn::Endpoint::server(config, SocketAddr::from((Ipv4Addr::LOCALHOST, 0))).unwrap()
    }

    fn client_endpoint(bundle: &Path) -> quinn::Endpoint {
        let mut endpoint =
            quinn::Endpoint::client(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))).unwrap();
        endpoint.set_default_client_config(client_config(bundle).unwrap());
        endpoint
    }

    const LIMIT: Duration = Duration::from_secs(10);

    #[tokio::test]
    async fn the_bundle_authenticates_and_carries_data() {
        let pki = test_pki("test CA");
        let bundle = write_bundle(&pki);
        let server = server(&pki);
        let addr = server.local_addr().unwrap();
        let expected_leaf = pki.edge_der.clone();
        let accept = tokio::spawn(async move {
            let conn = server.accept().await.unwrap().await.unwrap();
            let chain = conn
                .peer_identity()
                .unwrap()
                .downcast::<Vec<CertificateDer<'static>>>()
                .unwrap();
            assert_eq!(chain.first(), Some(&expected_leaf));
            assert_eq!(
                conn.handshake_data()
                    .unwrap()
                    .downcast::<quinn::crypto::rustls::HandshakeData>()
                    .unwrap()
                    .protocol,
                Some(scan3d_protocol::ALPN.to_vec())
            );
            let (mut send, mut recv) = conn.accept_bi().await.unwrap();
            let got = recv.read_to_end(1024).await.unwrap();
            send.write_all(b"ack").await.unwrap();
            send.finish().unwrap();
            conn.closed().await;
            got
        });

        let client = client_endpoint(bundle.path());
        let conn = tokio::time::timeout(LIMIT, client.connect(addr, "localhost").unwrap())
            .await
            .unwrap()
            .unwrap();
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        send.write_all(&[0x5c, 0x3d, 0x00, 0xff]).await.unwrap();
        send.finish().unwrap();
        let reply = tokio::time::timeout(LIMIT, recv.read_to_end(16))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(reply, b"ack");
        conn.close(0u32.into(), b"done");
        let got = tokio::time::timeout(LIMIT, accept).await.unwrap().unwrap();
        assert_eq!(got, [0x5c, 0x3d, 0x00, 0xff]);
        client.wait_idle().await;
    }

    #[tokio::test]
    async fn a_server_from_another_ca_is_not_trusted() {
        let ours = test_pki("our CA");
        let theirs = test_pki("their CA");
        let bundle = write_bundle(&ours);
        let server = server(&theirs);
        let addr = server.local_addr().unwrap();
        tokio::spawn(async move {
            if let Some(incoming) = server.accept().await {
                let _ = incoming.await;
            }
        });
        let client = client_endpoint(bundle.path());
        let result = tokio::time::timeout(LIMIT, client.connect(addr, "localhost").unwrap())
            .await
            .unwrap();
        match result {
            Err(quinn::ConnectionError::TransportError(e)) => {
                // unknown_ca (48) as a QUIC crypto error (0x100 + alert).
                assert_eq!(u64::from(e.code), 0x100 + 48, "{e}");
            }
            other => panic!("expected a handshake failure, got {other:?}"),
        }
    }

    /// Accepts connections forever, letting each handshake run to its end.
    fn serve_handshakes(server: quinn::Endpoint) {
        tokio::spawn(async move {
            while let Some(incoming) = server.accept().await {
                tokio::spawn(async move {
                    if let Ok(connection) = incoming.await {
                        connection.closed().await;
                    }
                });
            }
        });
    }

    /// Connects with `bundle` and returns how the connection failed (waiting for the close a
    /// TLS 1.3 server sends after the client thinks the handshake is done).
    async fn failure(bundle: &Path, addr: SocketAddr, name: &str) -> ConnectFailure {
        let client = client_endpoint(bundle);
        let connecting = client.connect(addr, name).unwrap();
        let error = tokio::time::timeout(LIMIT, async {
            match connecting.await {
                Ok(connection) => connection.closed().await,
                Err(e) => e,
            }
        })
        .await
        .expect("the connection ends");
        classify(&error)
    }

    #[tokio::test]
    async fn a_server_certificate_from_another_ca_is_blamed_on_this_edge_not_the_server() {
        let ours = test_pki("our CA");
        let theirs = test_pki("their CA");
        let bundle = write_bundle(&ours);
        let server = server(&theirs);
        let addr = server.local_addr().unwrap();
        serve_handshakes(server);
        match failure(bundle.path(), addr, "localhost").await {
            ConnectFailure::ServerCertificateRejected { reason } => {
                assert!(reason.contains("UnknownIssuer"), "{reason}")
            }
            other => panic!("expected this edge to reject the server, got {other:?}"),
        }
    }

    #[tokio::test]
    async fn a_server_certificate_for_another_name_is_blamed_on_this_edge() {
        let pki = test_pki("test CA");
        let bundle = write_bundle(&pki);
        let server = server(&pki);
        let addr = server.local_addr().unwrap();
        serve_handshakes(server);
        match failure(bundle.path(), addr, "elsewhere.example").await {
            ConnectFailure::ServerCertificateRejected { reason } => {
                assert!(reason.contains("not valid for name"), "{reason}")
            }
            other => panic!("expected this edge to reject the server, got {other:?}"),
        }
    }

    #[tokio::test]
    async fn an_edge_certificate_from_another_ca_is_blamed_on_the_server_refusing_it() {
        let ours = test_pki("our CA");
        let stranger = test_pki("another pairing");
        // The right CA for the server, but an edge certificate from another pairing.
        let bundle = write_bundle(&TestPki {
            edge_pem: stranger.edge_pem.clone(),
            edge_key_pem: stranger.edge_key_pem.clone(),
            edge_der: stranger.edge_der.clone(),
            ..test_pki_clone(&ours)
        });
        let server = server(&ours);
        let addr = server.local_addr().unwrap();
        serve_handshakes(server);
        match failure(bundle.path(), addr, "localhost").await {
            ConnectFailure::RefusedByServer { alert, .. } => {
                assert_eq!(alert, "UnknownCA")
            }
            other => panic!("expected the server to refuse this edge, got {other:?}"),
        }
    }

    fn test_pki_clone(pki: &TestPki) -> TestPki {
        TestPki {
            ca_pem: pki.ca_pem.clone(),
            server_der: pki.server_der.clone(),
            server_key: pki.server_key.clone(),
            edge_pem: pki.edge_pem.clone(),
            edge_key_pem: pki.edge_key_pem.clone(),
            edge_der: pki.edge_der.clone(),
        }
    }

    #[test]
    fn missing_files_are_named_with_the_fix() {
        let pki = test_pki("test CA");
        let bundle = write_bundle(&pki);
        for file in [BUNDLE_CA, BUNDLE_CERT, BUNDLE_KEY] {
            let path = bundle.path().join(file);
            let saved = std::fs::read(&path).unwrap();
            std::fs::remove_file(&path).unwrap();
            let err = client_config(bundle.path()).unwrap_err();
            assert!(
                matches!(&err, TlsError::Pem(e) if e.path() == path),
                "{err}"
            );
            let msg = err.to_string();
            assert!(
                msg.contains(file) && msg.contains("scan3d pair --dir DIR --edge NAME"),
                "{msg}"
            );
            std::fs::write(&path, saved).unwrap();
            if file == BUNDLE_KEY {
                use std::os::unix::fs::PermissionsExt;
                std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
            }
        }
        assert!(client_config(bundle.path()).is_ok());
    }

    #[test]
    fn a_bundle_key_readable_by_others_is_refused_with_the_fix() {
        use std::os::unix::fs::PermissionsExt;
        let pki = test_pki("test CA");
        let bundle = write_bundle(&pki);
        let key = bundle.path().join(BUNDLE_KEY);
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).unwrap();
        let err = client_config(bundle.path()).unwrap_err();
        assert!(
            matches!(&err, TlsError::Pem(PemError::KeyTooOpen { path, .. }) if *path == key),
            "{err}"
        );
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert!(client_config(bundle.path()).is_ok());
    }

    #[test]
    fn a_key_from_another_pairing_is_refused() {
        let pki = test_pki("test CA");
        let other = test_pki("test CA");
        let bundle = write_bundle(&pki);
        write_key(&bundle.path().join(BUNDLE_KEY), &other.edge_key_pem);
        let err = client_config(bundle.path()).unwrap_err();
        assert!(matches!(err, TlsError::CertKey { .. }), "{err}");
    }

    #[test]
    fn an_empty_ca_file_is_reported() {
        let pki = test_pki("test CA");
        let bundle = write_bundle(&pki);
        std::fs::write(bundle.path().join(BUNDLE_CA), "").unwrap();
        let err = client_config(bundle.path()).unwrap_err();
        assert!(
            matches!(err, TlsError::Pem(PemError::NoCertificate { .. })),
            "{err}"
        );
    }
}
