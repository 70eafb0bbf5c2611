//! Mutual TLS of the ingest endpoint over real quinn endpoints on loopback: a paired edge is
//! accepted and identified; no certificate, a foreign CA's certificate, or a client that does
//! not trust the server's CA are all refused before any stream data is accepted; revoked
//! (after a reload of the revocation list) and expired certificates are refused; a renewed
//! bundle connects.

use std::net::{Ipv4Addr, SocketAddr};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use quinn::ConnectionError;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use scan3d_server::ingest::pki::{Layout, PairRequest, Validity, pair, pair_with, renew, revoke};
use scan3d_server::ingest::tls::{
    CrlStatus, edge_identity, reloadable_server_config, server_config,
};

const LIMIT: Duration = Duration::from_secs(10);

/// QUIC transport error code of a TLS alert (RFC 9001 §4.8: 0x100 + alert).
fn crypto_code(alert: u8) -> u64 {
    0x100 + u64::from(alert)
}
const ALERT_UNKNOWN_CA: u8 = 48;
const ALERT_CERTIFICATE_REQUIRED: u8 = 116;
const ALERT_CERTIFICATE_REVOKED: u8 = 44;
const ALERT_CERTIFICATE_EXPIRED: u8 = 45;

fn paired(dir: &Path, edge: &str) {
    pair(&PairRequest {
        dir: dir.to_path_buf(),
        edge: edge.to_owned(),
        server_names: vec![],
        force: false,
    })
    .unwrap();
}

/// What the client presents: the bundle of `cert_from` (or nothing), trusting `roots_from`'s CA.
/// A local stand-in for the edge crate's `client_config` (the server must not depend on it).
fn client_config(roots_from: &Path, cert_from: Option<(&Path, &str)>) -> quinn::ClientConfig {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut roots = rustls::RootCertStore::empty();
    roots
        .add(CertificateDer::from_pem_file(Layout::new(roots_from).ca_cert()).unwrap())
        .unwrap();
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .unwrap()
        .with_root_certificates(roots);
    let mut tls = match cert_from {
        Some((dir, edge)) => {
            let layout = Layout::new(dir);
            let chain = vec![CertificateDer::from_pem_file(layout.edge_cert(edge)).unwrap()];
            let key = PrivateKeyDer::from_pem_file(layout.edge_key(edge)).unwrap();
            builder.with_client_auth_cert(chain, key).unwrap()
        }
        None => builder.with_no_client_auth(),
    };
    tls.alpn_protocols = vec![scan3d_protocol::ALPN.to_vec()];
    quinn::ClientConfig::new(Arc::new(
        quinn::crypto::rustls::QuicClientConfig::try_from(tls).unwrap(),
    ))
}

/// What the server saw of one connection attempt.
#[derive(Debug)]
enum Seen {
    /// Handshake done: the edge identity and the bytes of the first bidirectional stream.
    Accepted(String, Vec<u8>),
    /// The handshake failed on the server side.
    Refused(ConnectionError),
}

/// A server on 127.0.0.1:0 from `pki_dir` that handles exactly one connection attempt.
fn serve_once(pki_dir: &Path) -> (SocketAddr, tokio::task::JoinHandle<Seen>) {
    let config = server_config(pki_dir).unwrap();
    let endpoint =
        quinn::Endpoint::server(config, SocketAddr::from((Ipv4Addr::LOCALHOST, 0))).unwrap();
    let addr = endpoint.local_addr().unwrap();
    let task = tokio::spawn(async move {
        let incoming = endpoint.accept().await.unwrap();
        let conn = match incoming.await {
            Ok(conn) => conn,
            Err(e) => return Seen::Refused(e),
        };
        let name = edge_identity(&conn).unwrap();
        let (mut send, mut recv) = conn.accept_bi().await.unwrap();
        let bytes = recv.read_to_end(64 * 1024).await.unwrap();
        send.write_all(b"ok").await.unwrap();
        send.finish().unwrap();
        conn.closed().await;
        Seen::Accepted(name, bytes)
    });
    (addr, task)
}

fn client(config: quinn::ClientConfig) -> quinn::Endpoint {
    let mut endpoint = quinn::Endpoint::client(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))).unwrap();
    endpoint.set_default_client_config(config);
    endpoint
}

/// Connects and tries to send a frame; returns how the connection ended for the client.
/// With TLS 1.3 `connect()` may succeed even when the server refuses the client certificate:
/// the refusal arrives as a close right after.
async fn attempt_refused(config: quinn::ClientConfig, addr: SocketAddr) -> ConnectionError {
    let endpoint = client(config);
    let connecting = endpoint.connect(addr, "localhost").unwrap();
    let conn = match tokio::time::timeout(LIMIT, connecting).await.unwrap() {
        Ok(conn) => conn,
        Err(e) => return e,
    };
    if let Ok((mut send, _recv)) = conn.open_bi().await {
        let _ = send.write_all(b"should never be read").await;
        let _ = send.finish();
    }
    tokio::time::timeout(LIMIT, conn.closed()).await.unwrap()
}

fn close_code(e: &ConnectionError) -> u64 {
    match e {
        ConnectionError::ConnectionClosed(close) => u64::from(close.error_code),
        ConnectionError::TransportError(t) => u64::from(t.code),
        other => panic!("expected a TLS failure, got {other:?}"),
    }
}

async fn server_refusal(task: tokio::task::JoinHandle<Seen>) -> ConnectionError {
    match tokio::time::timeout(LIMIT, task).await.unwrap().unwrap() {
        Seen::Refused(e) => e,
        Seen::Accepted(name, bytes) => {
            panic!("server accepted {name:?} and read {} bytes", bytes.len())
        }
    }
}

#[tokio::test]
async fn a_paired_edge_is_accepted_and_identified() {
    let pki = tempfile::tempdir().unwrap();
    paired(pki.path(), "lab_pi-01.a");
    let (addr, server) = serve_once(pki.path());

    let endpoint = client(client_config(pki.path(), Some((pki.path(), "lab_pi-01.a"))));
    let conn = tokio::time::timeout(LIMIT, endpoint.connect(addr, "localhost").unwrap())
        .await
        .unwrap()
        .unwrap();
    let (mut send, mut recv) = conn.open_bi().await.unwrap();
    send.write_all(&[0x01, 0x02, 0xfe, 0xff]).await.unwrap();
    send.finish().unwrap();
    let reply = tokio::time::timeout(LIMIT, recv.read_to_end(16))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(reply, b"ok");
    conn.close(0u32.into(), b"bye");

    match tokio::time::timeout(LIMIT, server).await.unwrap().unwrap() {
        Seen::Accepted(name, bytes) => {
            assert_eq!(name, "lab_pi-01.a");
            assert_eq!(bytes, [0x01, 0x02, 0xfe, 0xff]);
        }
        Seen::Refused(e) => panic!("paired edge refused: {e}"),
    }
    endpoint.wait_idle().await;
}

#[tokio::test]
async fn a_client_without_certificate_is_refused() {
    let pki = tempfile::tempdir().unwrap();
    paired(pki.path(), "pi-01");
    let (addr, server) = serve_once(pki.path());

    let client_end = attempt_refused(client_config(pki.path(), None), addr).await;
    assert!(
        matches!(client_end, ConnectionError::ConnectionClosed(_)),
        "{client_end:?}"
    );
    assert_eq!(
        close_code(&client_end),
        crypto_code(ALERT_CERTIFICATE_REQUIRED),
        "{client_end}"
    );
    let server_end = server_refusal(server).await;
    assert_eq!(
        close_code(&server_end),
        crypto_code(ALERT_CERTIFICATE_REQUIRED),
        "{server_end}"
    );
}

#[tokio::test]
async fn a_certificate_from_a_foreign_ca_is_refused() {
    let pki = tempfile::tempdir().unwrap();
    paired(pki.path(), "pi-01");
    let foreign = tempfile::tempdir().unwrap();
    paired(foreign.path(), "pi-01");
    let (addr, server) = serve_once(pki.path());

    // Trusts our server, presents a certificate our CA never signed (same CN).
    let config = client_config(pki.path(), Some((foreign.path(), "pi-01")));
    let client_end = attempt_refused(config, addr).await;
    assert!(
        matches!(client_end, ConnectionError::ConnectionClosed(_)),
        "{client_end:?}"
    );
    assert_eq!(
        close_code(&client_end),
        crypto_code(ALERT_UNKNOWN_CA),
        "{client_end}"
    );
    let server_end = server_refusal(server).await;
    assert_eq!(
        close_code(&server_end),
        crypto_code(ALERT_UNKNOWN_CA),
        "{server_end}"
    );
}

#[tokio::test]
async fn a_client_that_does_not_trust_the_server_fails_the_handshake() {
    let pki = tempfile::tempdir().unwrap();
    paired(pki.path(), "pi-01");
    let foreign = tempfile::tempdir().unwrap();
    paired(foreign.path(), "pi-01");
    let (addr, server) = serve_once(pki.path());

    // A valid edge certificate, but the roots are another CA's.
    let endpoint = client(client_config(foreign.path(), Some((pki.path(), "pi-01"))));
    let result = tokio::time::timeout(LIMIT, endpoint.connect(addr, "localhost").unwrap())
        .await
        .unwrap();
    match result {
        Err(e @ ConnectionError::TransportError(_)) => {
            assert_eq!(close_code(&e), crypto_code(ALERT_UNKNOWN_CA), "{e}");
        }
        other => panic!("expected a local handshake failure, got {other:?}"),
    }
    let server_end = server_refusal(server).await;
    assert!(
        matches!(server_end, ConnectionError::ConnectionClosed(_)),
        "{server_end:?}"
    );
    assert_eq!(close_code(&server_end), crypto_code(ALERT_UNKNOWN_CA));
}

/// A server on 127.0.0.1:0 that handshakes every connection attempt and reports, per attempt,
/// the edge name it accepted or the error it refused with.
fn serve_many(
    config: quinn::ServerConfig,
) -> (
    SocketAddr,
    tokio::sync::mpsc::UnboundedReceiver<Result<String, ConnectionError>>,
) {
    let endpoint =
        quinn::Endpoint::server(config, SocketAddr::from((Ipv4Addr::LOCALHOST, 0))).unwrap();
    let addr = endpoint.local_addr().unwrap();
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        while let Some(incoming) = endpoint.accept().await {
            let seen = match incoming.await {
                Ok(conn) => {
                    let name = edge_identity(&conn).unwrap();
                    conn.close(0u32.into(), b"seen");
                    Ok(name)
                }
                Err(e) => Err(e),
            };
            if tx.send(seen).is_err() {
                break;
            }
        }
    });
    (addr, rx)
}

/// One connection attempt with `edge`'s bundle from `pki`; what the server made of it.
async fn attempt(
    pki: &Path,
    edge: &str,
    addr: SocketAddr,
    seen: &mut tokio::sync::mpsc::UnboundedReceiver<Result<String, ConnectionError>>,
) -> Result<String, u64> {
    let endpoint = client(client_config(pki, Some((pki, edge))));
    let connecting = endpoint.connect(addr, "localhost").unwrap();
    let _ = tokio::time::timeout(LIMIT, connecting).await.unwrap();
    let result = tokio::time::timeout(LIMIT, seen.recv())
        .await
        .unwrap()
        .unwrap();
    result.map_err(|e| close_code(&e))
}

/// Edge bundle files as they are now (a copy, as the Pi would hold it).
fn copy_bundle(pki: &Path, edge: &str, to: &Path) {
    let layout = Layout::new(pki);
    let copy = Layout::new(to);
    std::fs::create_dir_all(copy.edge_dir(edge)).unwrap();
    std::fs::copy(layout.ca_cert(), copy.ca_cert()).unwrap();
    for (from, into) in [
        (layout.edge_cert(edge), copy.edge_cert(edge)),
        (layout.edge_key(edge), copy.edge_key(edge)),
    ] {
        std::fs::copy(from, into).unwrap();
    }
}

#[tokio::test]
async fn a_revoked_certificate_is_refused_at_the_handshake_after_a_reload() {
    let pki = tempfile::tempdir().unwrap();
    paired(pki.path(), "pi-01");
    paired(pki.path(), "pi-02");
    let (config, verifier) = reloadable_server_config(pki.path()).unwrap();
    let (addr, mut seen) = serve_many(config);
    assert_eq!(
        attempt(pki.path(), "pi-01", addr, &mut seen).await,
        Ok("pi-01".into())
    );

    let outcome = revoke(pki.path(), "pi-01", std::time::SystemTime::now()).unwrap();
    assert_eq!(outcome.revoked.len(), 1);
    // Until the server reloads the list, nothing changes (documented).
    assert_eq!(
        attempt(pki.path(), "pi-01", addr, &mut seen).await,
        Ok("pi-01".into())
    );

    assert_eq!(verifier.reload().unwrap(), CrlStatus::Loaded { revoked: 1 });
    assert_eq!(
        attempt(pki.path(), "pi-01", addr, &mut seen).await,
        Err(crypto_code(ALERT_CERTIFICATE_REVOKED))
    );
    // Another edge of the same CA is unaffected.
    assert_eq!(
        attempt(pki.path(), "pi-02", addr, &mut seen).await,
        Ok("pi-02".into())
    );
}

#[tokio::test]
async fn a_renewed_bundle_connects_and_the_old_one_is_refused() {
    let pki = tempfile::tempdir().unwrap();
    paired(pki.path(), "pi-01");
    let old = tempfile::tempdir().unwrap();
    copy_bundle(pki.path(), "pi-01", old.path());
    let (config, verifier) = reloadable_server_config(pki.path()).unwrap();
    let (addr, mut seen) = serve_many(config);

    let outcome = renew(
        pki.path(),
        "pi-01",
        &[],
        Validity::default(),
        std::time::SystemTime::now(),
    )
    .unwrap();
    assert_eq!(outcome.revoked.len(), 1);
    verifier.reload().unwrap();
    assert_eq!(
        attempt(pki.path(), "pi-01", addr, &mut seen).await,
        Ok("pi-01".into())
    );
    assert_eq!(
        attempt(old.path(), "pi-01", addr, &mut seen).await,
        Err(crypto_code(ALERT_CERTIFICATE_REVOKED))
    );

    // `pair --force` re-issues and revokes in the same way.
    let older = tempfile::tempdir().unwrap();
    copy_bundle(pki.path(), "pi-01", older.path());
    let forced = pair(&PairRequest {
        dir: pki.path().to_path_buf(),
        edge: "pi-01".into(),
        server_names: vec![],
        force: true,
    })
    .unwrap();
    assert_eq!(forced.revoked.len(), 1);
    verifier.reload().unwrap();
    assert_eq!(
        attempt(older.path(), "pi-01", addr, &mut seen).await,
        Err(crypto_code(ALERT_CERTIFICATE_REVOKED))
    );
    assert_eq!(
        attempt(pki.path(), "pi-01", addr, &mut seen).await,
        Ok("pi-01".into())
    );
}

#[tokio::test]
async fn an_expired_certificate_is_refused() {
    let pki = tempfile::tempdir().unwrap();
    // CA and server certificate issued now; only the edge's certificate is old.
    paired(pki.path(), "pi-now");
    let three_years_ago = std::time::SystemTime::now() - Duration::from_secs(3 * 365 * 86_400);
    let request = PairRequest {
        dir: pki.path().to_path_buf(),
        edge: "pi-old".into(),
        server_names: vec![],
        force: false,
    };
    pair_with(&request, Validity::default(), three_years_ago).unwrap();
    let (addr, mut seen) = serve_many(server_config(pki.path()).unwrap());
    assert_eq!(
        attempt(pki.path(), "pi-old", addr, &mut seen).await,
        Err(crypto_code(ALERT_CERTIFICATE_EXPIRED))
    );
    // A fresh certificate of the same (still valid) CA is accepted.
    renew(
        pki.path(),
        "pi-old",
        &[],
        Validity::default(),
        std::time::SystemTime::now(),
    )
    .unwrap();
    assert_eq!(
        attempt(pki.path(), "pi-old", addr, &mut seen).await,
        Ok("pi-old".into())
    );
}

/// Whether a handshake with `edge`'s bundle is refused by a running `scan3d serve`: the
/// refusal (alert code) arrives as a close right after `connect()`; an accepted edge's
/// connection stays open (the daemon waits for its stream).
async fn daemon_refusal(pki: &Path, edge: &str, addr: SocketAddr) -> Option<u64> {
    let endpoint = client(client_config(pki, Some((pki, edge))));
    let connecting = endpoint.connect(addr, "localhost").unwrap();
    let conn = match tokio::time::timeout(LIMIT, connecting).await.unwrap() {
        Ok(conn) => conn,
        Err(e) => return Some(close_code(&e)),
    };
    let refused = match tokio::time::timeout(Duration::from_millis(500), conn.closed()).await {
        Ok(e) => Some(close_code(&e)),
        Err(_) => None,
    };
    conn.close(0u32.into(), b"done");
    refused
}

/// Reads the daemon's stderr on a thread; lines arrive on the channel.
fn stderr_lines(child: &mut std::process::Child) -> std::sync::mpsc::Receiver<String> {
    use std::io::BufRead;
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

fn wait_for(lines: &std::sync::mpsc::Receiver<String>, needle: &str) -> String {
    let deadline = std::time::Instant::now() + LIMIT;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        match lines.recv_timeout(left) {
            Ok(line) if line.contains(needle) => return line,
            Ok(_) => {}
            Err(e) => panic!("no log line with {needle:?}: {e}"),
        }
    }
}

#[tokio::test]
async fn sighup_makes_a_running_server_refuse_a_revoked_edge() {
    let tmp = tempfile::tempdir().unwrap();
    let pki = tmp.path().join("pki");
    paired(&pki, "pi-01");
    paired(&pki, "pi-02");
    let port = std::net::UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let config = tmp.path().join("server.toml");
    std::fs::write(
        &config,
        format!(
            "listen = \"127.0.0.1:{port}\"\npki_dir = {:?}\ndata_dir = {:?}\n",
            pki.display().to_string(),
            tmp.path().join("data").display().to_string()
        ),
    )
    .unwrap();
    let mut daemon = std::process::Command::new(env!("CARGO_BIN_EXE_scan3d"))
        .args(["serve", "--config", config.to_str().unwrap()])
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let lines = stderr_lines(&mut daemon);
    wait_for(&lines, "scan3d server ready");
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    assert_eq!(daemon_refusal(&pki, "pi-01", addr).await, None);

    revoke(&pki, "pi-01", std::time::SystemTime::now()).unwrap();
    let pid = nix::unistd::Pid::from_raw(i32::try_from(daemon.id()).unwrap());
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGHUP).unwrap();
    let reloaded = wait_for(&lines, "revocation list reloaded");
    assert!(reloaded.contains("revoked: 1"), "{reloaded}");
    assert_eq!(
        daemon_refusal(&pki, "pi-01", addr).await,
        Some(crypto_code(ALERT_CERTIFICATE_REVOKED))
    );
    assert_eq!(daemon_refusal(&pki, "pi-02", addr).await, None);

    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
    let status = daemon.wait().unwrap();
    assert!(status.success(), "{status}");
}
