//! The ingest server facing bad input from an authenticated edge: frames of another protocol
//! version or over the size limit end that connection cleanly with a reason; a malformed
//! payload is skipped and the connection stays usable; the server keeps serving throughout.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::rig::{self, ServerThread};
use scan3d_protocol::{Ack, Body, Frame, FrameReader, HEADER_LEN, Heartbeat, MAGIC, encode};
use scan3d_server::ingest::server::close_code;

struct Client {
    _endpoint: quinn::Endpoint,
    connection: quinn::Connection,
    send: quinn::SendStream,
    recv: quinn::RecvStream,
}

async fn connect(server: SocketAddr, bundle: &Path) -> Client {
    let mut endpoint =
        quinn::Endpoint::client(SocketAddr::from(([127, 0, 0, 1], 0))).expect("endpoint");
    endpoint.set_default_client_config(client_config(bundle).expect("bundle"));
    let connection = endpoint
        .connect(server, "localhost")
        .expect("connect")
        .await
        .expect("handshake");
    let (send, recv) = connection.open_bi().await.expect("stream");
    Client {
        _endpoint: endpoint,
        connection,
        send,
        recv,
    }
}

impl Client {
    /// Sends one valid heartbeat and waits for the server's acknowledgement of it.
    async fn heartbeat_is_acknowledged(&mut self, session_id: u64, seq: u64) -> bool {
        let frame = encode(&Frame::new(session_id, seq, Heartbeat { sent_ns: 1 })).expect("encode");
        if self.send.write_all(&frame).await.is_err() {
            return false;
        }
        let mut reader = FrameReader::new();
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        while tokio::time::Instant::now() < deadline {
            let chunk = tokio::time::timeout_at(deadline, self.recv.read_chunk(4096, true)).await;
            let Ok(Ok(Some(chunk))) = chunk else {
                return false;
            };
            reader.push(&chunk.bytes);
            while let Ok(Some(frame)) = reader.next_frame() {
                if let Body::Ack(Ack::UpTo { seq: acked }) = frame.body
                    && acked >= seq
                {
                    return true;
                }
            }
        }
        false
    }

    /// Waits for the server to close the connection; returns (application code, reason).
    async fn closed_by_server(&self) -> (u64, String) {
        let error = tokio::time::timeout(Duration::from_secs(5), self.connection.closed())
            .await
            .expect("the server closes the connection");
        match error {
            quinn::ConnectionError::ApplicationClosed(close) => (
                close.error_code.into_inner(),
                String::from_utf8_lossy(&close.reason).into_owned(),
            ),
            other => panic!("expected an application close, got {other}"),
        }
    }
}

fn header(version: u16, payload_len: u32) -> Vec<u8> {
    let mut bytes = MAGIC.to_vec();
    bytes.extend_from_slice(&version.to_le_bytes());
    bytes.extend_from_slice(&payload_len.to_le_bytes());
    assert_eq!(bytes.len(), HEADER_LEN);
    bytes
}

/// A paired temporary installation with the server running, and a runtime for test clients.
fn start_server() -> (
    tempfile::TempDir,
    PathBuf,
    ServerThread,
    tokio::runtime::Runtime,
) {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = dir.path().join("pki");
    let bundle = rig::pair_certificates(&pki).expect("pairing");
    let server =
        ServerThread::start(rig::ingest_config(&pki, &dir.path().join("data"), 0)).expect("server");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    (dir, bundle, server, runtime)
}

#[test]
fn bad_frames_close_the_connection_cleanly_and_the_server_keeps_serving() {
    let (_dir, bundle, server, runtime) = start_server();
    let addr = server.addr();
    runtime.block_on(async {
        // Another protocol version: refused by the header alone.
        let mut client = connect(addr, &bundle).await;
        client.send.write_all(&header(2, 1)).await.expect("write");
        client.send.write_all(&[0]).await.expect("write");
        let (code, reason) = client.closed_by_server().await;
        assert_eq!(code, u64::from(close_code::PROTOCOL_ERROR));
        assert!(reason.contains("version"), "{reason}");

        // Over the size limit: refused as soon as the header arrives, nothing buffered.
        let mut client = connect(addr, &bundle).await;
        client
            .send
            .write_all(&header(1, 5 << 20))
            .await
            .expect("write");
        let (code, reason) = client.closed_by_server().await;
        assert_eq!(code, u64::from(close_code::PROTOCOL_ERROR));
        assert!(reason.contains("exceeds the maximum"), "{reason}");

        // A good header with a garbage payload is skipped; the connection stays usable.
        let mut client = connect(addr, &bundle).await;
        let mut garbage = header(1, 3);
        garbage.extend_from_slice(&[0xff, 0xff, 0xff]);
        client.send.write_all(&garbage).await.expect("write");
        assert!(
            client.heartbeat_is_acknowledged(42, 0).await,
            "the connection did not survive a malformed frame"
        );
    });
    let stats = server.stop();
    assert_eq!(stats.rejected, 3, "{stats:?}");
    assert_eq!(stats.frames, 1, "{stats:?}");
}

#[test]
fn a_reconnecting_edge_replaces_its_old_connection() {
    let (dir, bundle, server, runtime) = start_server();
    let addr = server.addr();
    runtime.block_on(async {
        let mut old = connect(addr, &bundle).await;
        assert!(old.heartbeat_is_acknowledged(7, 0).await);
        // The edge comes back on a new connection before the server noticed the old one die.
        let mut new = connect(addr, &bundle).await;
        assert!(new.heartbeat_is_acknowledged(7, 1).await);
        let (code, reason) = old.closed_by_server().await;
        assert_eq!(code, u64::from(close_code::DONE));
        assert!(reason.contains("replaced"), "{reason}");
    });
    let stats = server.stop();
    assert_eq!((stats.frames, stats.duplicates), (2, 0), "{stats:?}");
    let data = dir.path().join("data");
    let session = scan3d_server::ingest::recorder::session_dir(&data, rig::EDGE_NAME, 7);
    let frames = scan3d_server::ingest::recorder::read_session(&session).expect("recording");
    assert_eq!(
        frames.iter().map(|f| f.frame.seq).collect::<Vec<_>>(),
        vec![0, 1]
    );
}
