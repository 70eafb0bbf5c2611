//! Operator commands through the real control socket to a real, connected edge connection:
//! a command the edge could not act on (a 5 MiB or a 4 KiB position name) is refused on the
//! socket with a clear error and never reaches the connection, which stays up and keeps
//! working.

use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::rig::{self, ServerThread};
use scan3d_protocol::{Ack, Body, Command, Frame, FrameReader, Heartbeat, encode};
use scan3d_server::ingest::control::{ControlRequest, request, socket_path};

const SESSION: u64 = 11;

/// Reads frames from the server until `wanted` matches one (or 5 s pass).
async fn receive(
    recv: &mut quinn::RecvStream,
    reader: &mut FrameReader,
    wanted: impl Fn(&Frame) -> bool,
) -> Option<Frame> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        while let Ok(Some(frame)) = reader.next_frame() {
            if wanted(&frame) {
                return Some(frame);
            }
        }
        let chunk = tokio::time::timeout_at(deadline, recv.read_chunk(4096, true)).await;
        let Ok(Ok(Some(chunk))) = chunk else {
            return None;
        };
        reader.push(&chunk.bytes);
    }
}

fn acked(seq: u64) -> impl Fn(&Frame) -> bool {
    move |frame| matches!(frame.body, Body::Ack(Ack::UpTo { seq: s }) if s >= seq)
}

/// `scan3d scan`'s request, from a blocking thread as the CLI makes it.
async fn operator(socket: &Path, command: Command) -> scan3d_server::ingest::control::ControlReply {
    let socket = socket.to_path_buf();
    tokio::task::spawn_blocking(move || {
        request(
            &socket,
            &ControlRequest {
                edge: rig::EDGE_NAME.into(),
                command,
            },
        )
    })
    .await
    .expect("join")
    .expect("the control socket answers")
}

/// A paired edge bundle, a running server with its control socket, and a runtime to drive
/// the edge's side from.
struct Site {
    dir: tempfile::TempDir,
    bundle: std::path::PathBuf,
    data: std::path::PathBuf,
    server: ServerThread,
    socket: std::path::PathBuf,
    runtime: tokio::runtime::Runtime,
}

impl Site {
    fn start() -> Self {
        let dir = tempfile::tempdir().expect("temp dir");
        let pki = dir.path().join("pki");
        let bundle = rig::pair_certificates(&pki).expect("pairing");
        let data = dir.path().join("data");
        let server = ServerThread::start(rig::ingest_config(&pki, &data, 0)).expect("server");
        let socket = socket_path(&data);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .expect("runtime");
        Site {
            dir,
            bundle,
            data,
            server,
            socket,
            runtime,
        }
    }
}

#[test]
fn an_oversized_command_is_refused_and_the_edge_stays_connected() {
    let Site {
        dir: _dir,
        bundle,
        data: _,
        server,
        socket,
        runtime,
    } = Site::start();
    runtime.block_on(async {
        let (_endpoint, connection, mut send, mut recv) =
            connect_edge(server.addr(), &bundle).await;
        let mut reader = FrameReader::new();
        let heartbeat = |seq| encode(&Frame::new(SESSION, seq, Heartbeat { sent_ns: 1 })).unwrap();
        send.write_all(&heartbeat(0)).await.expect("write");
        assert!(receive(&mut recv, &mut reader, acked(0)).await.is_some());
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        while !socket.exists() {
            assert!(tokio::time::Instant::now() < deadline, "no control socket");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }

        let start = |position: String| Command::StartStaticScan {
            position,
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: None,
        };
        // 5 MiB: refused by the socket's line limit before it is even parsed.
        let reply = operator(&socket, start("x".repeat(5 * 1024 * 1024))).await;
        assert!(!reply.ok, "{reply:?}");
        assert_eq!(
            reply.detail,
            "request line longer than 65536 bytes; closing the connection"
        );
        // Within the line limit but over the name limit: refused by the command check.
        let reply = operator(&socket, start("x".repeat(4096))).await;
        assert!(!reply.ok, "{reply:?}");
        assert_eq!(
            reply.detail,
            "invalid command: position name of 4096 bytes: must be 1 to 256 bytes"
        );

        // The connection is untouched: frames are still acknowledged, and a valid command
        // arrives on it.
        send.write_all(&heartbeat(1)).await.expect("write");
        assert!(
            receive(&mut recv, &mut reader, acked(1)).await.is_some(),
            "the edge connection did not survive the refused command"
        );
        let reply = operator(&socket, Command::StopStaticScan).await;
        assert!(reply.ok, "{reply:?}");
        let command = receive(&mut recv, &mut reader, |f| {
            matches!(f.body, Body::Command(_))
        })
        .await;
        assert_eq!(
            command.map(|f| f.body),
            Some(Body::Command(Command::StopStaticScan))
        );
        assert!(
            connection.close_reason().is_none(),
            "{:?}",
            connection.close_reason()
        );
        connection.close(0u32.into(), b"done");
    });
    let stats = server.stop();
    assert_eq!(stats.frames, 2, "{stats:?}");
}

/// Connects to `server` as the paired edge and opens the frame stream.
async fn connect_edge(
    server: SocketAddr,
    bundle: &Path,
) -> (
    quinn::Endpoint,
    quinn::Connection,
    quinn::SendStream,
    quinn::RecvStream,
) {
    let mut endpoint =
        quinn::Endpoint::client(SocketAddr::from(([127, 0, 0, 1], 0))).expect("endpoint");
    endpoint.set_default_client_config(client_config(bundle).expect("bundle"));
    let connection = endpoint
        .connect(server, "localhost")
        .expect("connect")
        .await
        .expect("handshake");
    let (send, recv) = connection.open_bi().await.expect("stream");
    (endpoint, connection, send, recv)
}

#[test]
fn a_command_sent_after_a_reconnect_is_recorded_not_taken_for_a_resend() {
    let Site {
        dir: _dir,
        bundle,
        data,
        server,
        socket,
        runtime,
    } = Site::start();
    let positions = ["first", "second"];
    runtime.block_on(async {
        // The same exchange on two connections of one session: a heartbeat, its ack, a command.
        for (seq, position) in positions.into_iter().enumerate() {
            let seq = seq as u64;
            let (_endpoint, connection, mut send, mut recv) =
                connect_edge(server.addr(), &bundle).await;
            let mut reader = FrameReader::new();
            let heartbeat = encode(&Frame::new(SESSION, seq, Heartbeat { sent_ns: 1 })).unwrap();
            send.write_all(&heartbeat).await.expect("write");
            assert!(receive(&mut recv, &mut reader, acked(seq)).await.is_some());
            let reply = operator(
                &socket,
                Command::StartStaticScan {
                    position: position.into(),
                    x_m: 0.0,
                    y_m: 0.0,
                    heading_deg: None,
                },
            )
            .await;
            assert!(reply.ok, "{reply:?}");
            let sent = receive(&mut recv, &mut reader, |f| {
                matches!(f.body, Body::Command(_))
            });
            assert!(sent.await.is_some(), "the command did not reach the edge");
            connection.close(0u32.into(), b"reconnecting");
            // The server replaces a closed connection at once; give it the close.
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    });
    server.stop();
    let recorded = scan3d_server::ingest::recorder::read_session(
        &scan3d_server::ingest::recorder::session_dir(&data, rig::EDGE_NAME, SESSION),
    )
    .expect("the session reads");
    let commands: Vec<String> = recorded
        .iter()
        .filter_map(|r| match &r.frame.body {
            Body::Command(Command::StartStaticScan { position, .. }) => Some(position.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(
        commands, positions,
        "every command sent must be in the recording"
    );
}
