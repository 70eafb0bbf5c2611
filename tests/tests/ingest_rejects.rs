//! The ingest server facing bad input and bad peers, over real QUIC on loopback:
//! - frames of another protocol version or over the size limit end that connection cleanly
//!   with a reason; a payload that does not decode, or a server → edge body, is recorded raw
//!   and acknowledged, so it leaves no gap; a gap itself does not stop acknowledgements;
//! - handshakes that never complete do not keep a paired edge out, and an authenticated
//!   connection that opens no stream is dropped;
//! - a second connection under a connected edge name replaces a silent old one and is refused
//!   while the old one is alive;
//! - an idle session recording is closed and reopened when its frames come back; an edge that
//!   buffers more than its limit is committed (and acknowledged) early;
//! - with the live pipeline on, a session with a gap and an unknown body is processed around
//!   them (through a one-frame queue, caught up from the recording), and a snapshot that cannot
//!   be written is an error while recording goes on.

use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use clap::Parser;
use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::uplink::client::{Uplink, UplinkConfig};
use scan3d_edge::uplink::spool::SpoolConfig;
use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::installation::{self, ServerThread};
use scan3d_hw_sim::maps::session_status;
use scan3d_map::octree::{Octree, SensorModel};
use scan3d_protocol::{
    Ack, Body, Command, Frame, FrameReader, HEADER_LEN, Heartbeat, LidarRevolution, MAGIC,
    PROTOCOL_VERSION, SensorId, encode,
};
use scan3d_server::ingest::control::{
    ProductRequest, request_products, request_snapshot, socket_path,
};
use scan3d_server::ingest::server::{IngestConfig, close_code};
use scan3d_server::pipeline::PipelineSettings;
use scan3d_server::pipeline::live::LiveSettings;
use scan3d_server::pipeline::offline::run_session;
use scan3d_server::recording::{session_dir, summarize_session};

struct Client {
    _endpoint: quinn::Endpoint,
    connection: quinn::Connection,
    send: quinn::SendStream,
    recv: quinn::RecvStream,
    reader: FrameReader,
    /// Every ack received so far, with its session.
    acks: Vec<(u64, Ack)>,
}

fn client_endpoint(bundle: &Path) -> quinn::Endpoint {
    let mut endpoint =
        quinn::Endpoint::client(SocketAddr::from(([127, 0, 0, 1], 0))).expect("endpoint");
    endpoint.set_default_client_config(client_config(bundle).expect("bundle"));
    endpoint
}

async fn connect(server: SocketAddr, bundle: &Path) -> Client {
    let endpoint = client_endpoint(bundle);
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
        reader: FrameReader::new(),
        acks: Vec::new(),
    }
}

impl Client {
    async fn send_heartbeat(&mut self, session_id: u64, seq: u64) {
        let frame = encode(&Frame::new(session_id, seq, Heartbeat { sent_ns: 1 })).expect("encode");
        self.send.write_all(&frame).await.expect("write");
    }

    /// Waits (at most 5 s) until every seq in `seqs` of `session_id` is covered by an ack.
    async fn acknowledged(&mut self, session_id: u64, seqs: &[u64]) -> bool {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        loop {
            let covered = |seq: &u64| {
                self.acks
                    .iter()
                    .any(|(session, ack)| *session == session_id && ack.covers(*seq))
            };
            if seqs.iter().all(covered) {
                return true;
            }
            let chunk = tokio::time::timeout_at(deadline, self.recv.read_chunk(4096, true)).await;
            let Ok(Ok(Some(chunk))) = chunk else {
                return false;
            };
            self.reader.push(&chunk.bytes);
            while let Ok(Some(frame)) = self.reader.next_frame() {
                if let Body::Ack(ack) = frame.body {
                    self.acks.push((frame.session_id, ack));
                }
            }
        }
    }

    /// Sends one valid heartbeat and waits for the server's acknowledgement of it.
    async fn heartbeat_is_acknowledged(&mut self, session_id: u64, seq: u64) -> bool {
        self.send_heartbeat(session_id, seq).await;
        self.acknowledged(session_id, &[seq]).await
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

/// A frame with a valid header whose payload starts with `session_id` and `seq` (varints) and
/// then carries body tag 127, which no version has.
fn undecodable_frame(session_id: u64, seq: u64) -> Vec<u8> {
    let mut payload = Vec::new();
    for mut value in [session_id, seq] {
        while value >= 0x80 {
            payload.push((value as u8) | 0x80);
            value >>= 7;
        }
        payload.push(value as u8);
    }
    payload.extend_from_slice(&[0x7f, 0x01, 0x02]);
    let mut frame = header(PROTOCOL_VERSION, payload.len() as u32);
    frame.extend_from_slice(&payload);
    frame
}

struct Site {
    dir: tempfile::TempDir,
    bundle: PathBuf,
    server: ServerThread,
    runtime: tokio::runtime::Runtime,
}

/// A paired temporary installation with the server running (its configuration tuned by
/// `tune`), and a runtime for test clients.
fn start_server_with(tune: impl FnOnce(&mut IngestConfig)) -> Site {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = dir.path().join("pki");
    let bundle = installation::pair_certificates(&pki).expect("pairing");
    let mut config = installation::ingest_config(&pki, &dir.path().join("data"), 0);
    tune(&mut config);
    let server = ServerThread::start(config).expect("server");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    Site {
        dir,
        bundle,
        server,
        runtime,
    }
}

fn start_server() -> Site {
    start_server_with(|_| {})
}

#[test]
fn bad_frames_close_the_connection_cleanly_and_the_server_keeps_serving() {
    let site = start_server();
    let (addr, bundle) = (site.server.addr(), &site.bundle);
    site.runtime.block_on(async {
        // Another protocol version: refused by the header alone.
        let mut client = connect(addr, bundle).await;
        client
            .send
            .write_all(&header(PROTOCOL_VERSION + 1, 1))
            .await
            .expect("write");
        // The server may have closed the connection on the header alone already.
        let _ = client.send.write_all(&[0]).await;
        let (code, reason) = client.closed_by_server().await;
        assert_eq!(code, u64::from(close_code::PROTOCOL_ERROR));
        assert!(reason.contains("version"), "{reason}");

        // Over the size limit: refused as soon as the header arrives, nothing buffered.
        let mut client = connect(addr, bundle).await;
        client
            .send
            .write_all(&header(PROTOCOL_VERSION, 5 << 20))
            .await
            .expect("write");
        let (code, reason) = client.closed_by_server().await;
        assert_eq!(code, u64::from(close_code::PROTOCOL_ERROR));
        assert!(reason.contains("exceeds the maximum"), "{reason}");

        // A good header with a payload from which not even the seq can be read: dropped and
        // counted (nothing to acknowledge); the connection stays usable.
        let mut client = connect(addr, bundle).await;
        let mut garbage = header(PROTOCOL_VERSION, 3);
        garbage.extend_from_slice(&[0xff, 0xff, 0xff]);
        client.send.write_all(&garbage).await.expect("write");
        assert!(
            client.heartbeat_is_acknowledged(42, 0).await,
            "the connection did not survive a malformed frame"
        );
    });
    let stats = site.server.stop();
    assert_eq!(stats.rejected, 2, "{stats:?}");
    assert_eq!(stats.unidentified, 1, "{stats:?}");
    assert_eq!(stats.frames, 1, "{stats:?}");
}

#[test]
fn a_frame_that_does_not_decode_is_recorded_raw_and_every_frame_after_it_acknowledged() {
    let site = start_server();
    let session = 0x00ba_d001;
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        client.send_heartbeat(session, 0).await;
        client
            .send
            .write_all(&undecodable_frame(session, 1))
            .await
            .expect("write");
        for seq in 2..=5 {
            client.send_heartbeat(session, seq).await;
        }
        assert!(
            client.acknowledged(session, &[0, 1, 2, 3, 4, 5]).await,
            "acks received: {:?}",
            client.acks
        );
    });
    let stats = site.server.stop();
    assert_eq!((stats.frames, stats.undecodable), (5, 1), "{stats:?}");
    let dir = session_dir(
        &site.dir.path().join("data"),
        installation::EDGE_NAME,
        session,
    );
    let summary = summarize_session(installation::EDGE_NAME, session, &dir).expect("summary");
    assert_eq!(
        (summary.frames, summary.undecodable_frames),
        (5, 1),
        "{summary:?}"
    );
}

#[test]
fn a_gap_in_the_sequence_numbers_does_not_stop_acknowledgements() {
    let site = start_server();
    let session = 0x0000_9a90;
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        // Seq 2 never comes (e.g. lost with a torn spool record on the edge).
        for seq in [0, 1, 3, 4, 5] {
            client.send_heartbeat(session, seq).await;
        }
        assert!(
            client.acknowledged(session, &[0, 1, 3, 4, 5]).await,
            "acks received: {:?}",
            client.acks
        );
        assert!(
            !client.acks.iter().any(|(_, ack)| ack.covers(2)),
            "seq 2 was acknowledged without being recorded: {:?}",
            client.acks
        );
    });
    site.server.stop();
}

/// The edge's real uplink sends a server → edge body at seq 1 (a misdirected frame), then
/// ordinary frames: the server records and acknowledges it like any other, so the spool drains.
#[test]
fn a_misdirected_frame_at_seq_1_does_not_keep_the_edge_spool_from_draining() {
    let site = start_server();
    let spool = site.dir.path().join("spool");
    let clock: SharedClock = Arc::new(ScaledClock::new(1.0));
    let session = 0x05e9_0001;
    let config = UplinkConfig::new(
        site.server.addr().to_string(),
        "localhost".into(),
        client_config(&site.bundle).expect("bundle"),
        SpoolConfig::new(&spool),
    );
    let (uplink, handle, _commands) = Uplink::new(config, clock, session).expect("uplink");
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let running = site.runtime.spawn(uplink.run(stopped));
    assert_eq!(handle.submit(Heartbeat { sent_ns: 1 }).expect("submit"), 0);
    assert_eq!(handle.submit(Command::StopStaticScan).expect("submit"), 1);
    for _ in 2..20 {
        handle.submit(Heartbeat { sent_ns: 2 }).expect("submit");
    }
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while handle.pending() > 0 && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    let pending = handle.pending();
    let _ = stop.send(true);
    let uplink_stats = site.runtime.block_on(running).expect("uplink task");
    assert_eq!(pending, 0, "frames left in the spool: {uplink_stats:?}");
    let stats = site.server.stop();
    // 19 frames and the time-sync pongs the edge sent meanwhile.
    assert!(stats.frames >= 19, "{stats:?}");
    assert_eq!(stats.misdirected, 1, "{stats:?}");
}

#[test]
fn an_authenticated_edge_that_opens_no_stream_is_dropped() {
    let site = start_server_with(|config| {
        config.limits.first_stream_timeout = Duration::from_millis(300);
    });
    site.runtime.block_on(async {
        let endpoint = client_endpoint(&site.bundle);
        let connection = endpoint
            .connect(site.server.addr(), "localhost")
            .expect("connect")
            .await
            .expect("handshake");
        let closed = tokio::time::timeout(Duration::from_secs(5), connection.closed())
            .await
            .expect("the server closes an idle connection");
        match closed {
            quinn::ConnectionError::ApplicationClosed(close) => {
                assert_eq!(
                    close.error_code.into_inner(),
                    u64::from(close_code::PROTOCOL_ERROR)
                );
                let reason = String::from_utf8_lossy(&close.reason).into_owned();
                assert!(reason.contains("no stream"), "{reason}");
            }
            other => panic!("expected an application close, got {other}"),
        }
    });
    let stats = site.server.stop();
    assert_eq!((stats.connections, stats.no_stream), (1, 1), "{stats:?}");
}

/// A peer that sends one valid QUIC Initial (from its own UDP address) and never anything else:
/// a quinn client talks to a black hole that passes its first datagram on to the server and
/// drops everything else, both ways.
struct BareInitial {
    _endpoint: quinn::Endpoint,
    /// The server's answers arrive here and are never read.
    _upstream: UdpSocket,
}

async fn bare_initial(server: SocketAddr, bundle: &Path) -> BareInitial {
    let hole = UdpSocket::bind("127.0.0.1:0").expect("udp");
    hole.set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    let upstream = UdpSocket::bind("127.0.0.1:0").expect("udp");
    let endpoint = client_endpoint(bundle);
    let connecting = endpoint
        .connect(hole.local_addr().expect("addr"), "localhost")
        .expect("connect");
    tokio::spawn(async move {
        let _ = connecting.await;
    });
    let first = tokio::task::spawn_blocking(move || {
        let mut datagram = vec![0; 65_535];
        let (len, _) = hole.recv_from(&mut datagram).expect("the client's Initial");
        datagram.truncate(len);
        datagram
    })
    .await
    .expect("read");
    assert!(
        first.len() >= 1200,
        "a client Initial is padded to 1200 bytes"
    );
    upstream.send_to(&first, server).expect("forward");
    BareInitial {
        _endpoint: endpoint,
        _upstream: upstream,
    }
}

#[test]
fn handshakes_that_never_complete_do_not_keep_a_paired_edge_out() {
    let site = start_server_with(|config| {
        config.max_connections = 2;
        config.limits.retry_above_handshakes = 4;
        config.limits.handshake_timeout = Duration::from_secs(1);
    });
    let addr = site.server.addr();
    site.runtime.block_on(async {
        let mut bad = Vec::new();
        for _ in 0..6 {
            bad.push(bare_initial(addr, &site.bundle).await);
        }
        // Let the server take all six in.
        tokio::time::sleep(Duration::from_millis(200)).await;
        let started = tokio::time::Instant::now();
        let mut edge = tokio::time::timeout(Duration::from_secs(3), connect(addr, &site.bundle))
            .await
            .expect("the edge connects while the bare Initials hang");
        assert!(edge.heartbeat_is_acknowledged(0xed9e, 0).await);
        assert!(started.elapsed() < Duration::from_secs(3));
        // The stalled handshakes time out; the edge stays connected and acknowledged.
        tokio::time::sleep(Duration::from_millis(1500)).await;
        assert!(edge.heartbeat_is_acknowledged(0xed9e, 1).await);
        drop(bad);
    });
    let stats = site.server.stop();
    assert_eq!(stats.connections, 1, "{stats:?}");
    // Four Initials got a handshake (then timed out); the other two and the edge, arriving
    // with four handshakes in progress, had to validate their address first.
    assert_eq!(stats.handshake_timeouts, 4, "{stats:?}");
    assert_eq!(stats.address_validations, 3, "{stats:?}");
}

#[test]
fn a_reconnecting_edge_replaces_its_old_connection_once_that_is_silent() {
    let site = start_server_with(|config| {
        config.limits.replace_after_silence = Duration::from_millis(800);
    });
    let relay = scan3d_tests::relay::UdpRelay::start(site.server.addr()).expect("relay");
    let session = 7;
    site.runtime.block_on(async {
        let mut old = connect(relay.local_addr(), &site.bundle).await;
        assert!(old.heartbeat_is_acknowledged(session, 0).await);
        // The old path dies without the server noticing (no close reaches it); the edge comes
        // back on a new connection from another address.
        relay.cut();
        tokio::time::sleep(Duration::from_millis(1200)).await;
        let mut new = connect(site.server.addr(), &site.bundle).await;
        assert!(new.heartbeat_is_acknowledged(session, 1).await);
    });
    let stats = site.server.stop();
    assert_eq!((stats.replaced, stats.duplicate_names), (1, 0), "{stats:?}");
    assert_eq!((stats.frames, stats.duplicates), (2, 0), "{stats:?}");
    let dir = session_dir(
        &site.dir.path().join("data"),
        installation::EDGE_NAME,
        session,
    );
    let frames = scan3d_server::recording::read_session(&dir).expect("recording");
    assert_eq!(
        frames.iter().map(|f| f.frame.seq).collect::<Vec<_>>(),
        vec![0, 1]
    );
    relay.shutdown();
}

#[test]
fn a_second_live_device_under_a_connected_name_is_refused_and_the_first_keeps_recording() {
    let site = start_server();
    site.runtime.block_on(async {
        let mut first = connect(site.server.addr(), &site.bundle).await;
        assert!(first.heartbeat_is_acknowledged(1, 0).await);
        // Same certificate, another device: its connection is refused, not the first one's.
        // The server may refuse it as soon as the handshake ends, before the twin has opened
        // a stream, so the twin only tries to send and then waits for the close.
        let twin_endpoint = client_endpoint(&site.bundle);
        let twin = twin_endpoint
            .connect(site.server.addr(), "localhost")
            .expect("connect")
            .await
            .expect("handshake");
        if let Ok((mut send, _recv)) = twin.open_bi().await {
            let frame = encode(&Frame::new(2, 0, Heartbeat { sent_ns: 1 })).expect("encode");
            // A write may fail once the refusal has arrived; the close reason tells why.
            let _ = send.write_all(&frame).await;
        }
        let closed = tokio::time::timeout(Duration::from_secs(5), twin.closed())
            .await
            .expect("the server closes the twin's connection");
        let quinn::ConnectionError::ApplicationClosed(close) = closed else {
            panic!("expected an application close, got {closed}");
        };
        assert_eq!(
            close.error_code.into_inner(),
            u64::from(close_code::DUPLICATE_EDGE),
            "{}",
            String::from_utf8_lossy(&close.reason)
        );
        assert!(first.heartbeat_is_acknowledged(1, 1).await);
        assert!(first.connection.close_reason().is_none());
    });
    let stats = site.server.stop();
    assert_eq!((stats.duplicate_names, stats.replaced), (1, 0), "{stats:?}");
    assert_eq!((stats.connections, stats.frames), (1, 2), "{stats:?}");
}

#[test]
fn an_idle_session_is_closed_and_reopened_when_its_frames_come_back() {
    let site = start_server_with(|config| {
        config.limits.session_idle_timeout = Duration::from_millis(300);
    });
    let session = 0x1d1e;
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        assert!(client.heartbeat_is_acknowledged(session, 0).await);
        tokio::time::sleep(Duration::from_secs(1)).await;
        // A resend of seq 0 (a duplicate) and a new frame: acknowledged by the reopened
        // recording.
        client.acks.clear();
        client.send_heartbeat(session, 0).await;
        client.send_heartbeat(session, 1).await;
        assert!(
            client.acknowledged(session, &[0, 1]).await,
            "{:?}",
            client.acks
        );
    });
    let stats = site.server.stop();
    assert!(stats.sessions_idle_closed >= 1, "{stats:?}");
    assert_eq!((stats.frames, stats.duplicates), (2, 1), "{stats:?}");
    let dir = session_dir(
        &site.dir.path().join("data"),
        installation::EDGE_NAME,
        session,
    );
    let frames = scan3d_server::recording::read_session(&dir).expect("recording");
    assert_eq!(
        frames.iter().map(|f| f.frame.seq).collect::<Vec<_>>(),
        vec![0, 1]
    );
}

#[test]
fn an_edge_over_its_buffer_limit_is_committed_and_acknowledged_before_the_commit_interval() {
    let site = start_server_with(|config| {
        config.commit_interval = Duration::from_secs(60);
        config.limits.max_buffered_bytes_per_edge = 32 * 1024;
    });
    let session = 0xb1f;
    let revolution = |seq: u64| {
        let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 0, 200_000_000);
        for i in 0..2000u32 {
            rev.push(i as f32 * 0.18, 3.0, 40, u64::from(i) * 100_000)
                .expect("sample time");
        }
        encode(&Frame::new(session, seq, rev)).expect("encode")
    };
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        // ~26 KB each: two take the edge past 32 KiB. (The commit interval's first tick may
        // commit seq 0 alone, if it comes after it: then seq 2 is the one over the limit.)
        for seq in 0..3 {
            client
                .send
                .write_all(&revolution(seq))
                .await
                .expect("write");
        }
        assert!(
            client.acknowledged(session, &[0, 1]).await,
            "{:?}",
            client.acks
        );
    });
    let stats = site.server.stop();
    assert_eq!(stats.early_commits, 1, "{stats:?}");
}

#[test]
fn after_a_reconnect_the_server_acknowledges_again_what_it_already_holds() {
    let site = start_server();
    let session = 0x00ac_0001;
    site.runtime.block_on(async {
        let mut first = connect(site.server.addr(), &site.bundle).await;
        // Seq 1 is missing: 2 and 3 can only be acknowledged as a range.
        for seq in [0, 2, 3] {
            first.send_heartbeat(session, seq).await;
        }
        assert!(
            first.acknowledged(session, &[0, 2, 3]).await,
            "{:?}",
            first.acks
        );
        first.connection.close(0u32.into(), b"edge going away");
        first._endpoint.wait_idle().await;
        // The edge did not see those acks (say), so it resends 2 and 3 on a new connection.
        let mut second = connect(site.server.addr(), &site.bundle).await;
        for seq in [2, 3] {
            second.send_heartbeat(session, seq).await;
        }
        assert!(
            second.acknowledged(session, &[2, 3]).await,
            "{:?}",
            second.acks
        );
        assert!(!second.acks.iter().any(|(_, ack)| ack.covers(1)));
    });
    let stats = site.server.stop();
    assert_eq!((stats.frames, stats.duplicates), (3, 2), "{stats:?}");
}

/// The server with the live pipeline on, its queue `queue_frames` long (1: every frame beyond
/// the first in a burst is read back from the recording).
fn start_live_server(queue_frames: usize) -> Site {
    start_live_server_with(|live| live.queue_frames = queue_frames)
}

/// The server with the live pipeline on, its settings tuned by `tune`.
fn start_live_server_with(tune: impl FnOnce(&mut LiveSettings)) -> Site {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = dir.path().join("pki");
    let bundle = installation::pair_certificates(&pki).expect("pairing");
    let data = dir.path().join("data");
    let config = installation::ingest_config(&pki, &data, 0);
    let mut live = LiveSettings::new(PipelineSettings::default(), data);
    tune(&mut live);
    let server = ServerThread::start_live(config, live).expect("server");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    Site {
        dir,
        bundle,
        server,
        runtime,
    }
}

/// A revolution frame of eight RPLidar samples.
fn revolution(session_id: u64, seq: u64) -> Vec<u8> {
    let t0 = seq * 100_000_000;
    let mut rev = LidarRevolution::new(SensorId::RPLIDAR, t0, t0 + 100_000_000);
    for i in 0..8u8 {
        rev.push(f32::from(i) * 45.0, 2.0, 40, t0 + u64::from(i) * 1_000_000)
            .expect("sample time");
    }
    encode(&Frame::new(session_id, seq, rev)).expect("encode")
}

/// The session's line of `scan3d status` once its pipeline has taken `frames` frames and caught
/// up (at most 10 s).
fn live_session_status(site: &Site, session_id: u64, frames: u64) -> serde_json::Value {
    let socket = socket_path(&site.dir.path().join("data"));
    let id = format!("{session_id:016x}");
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let reply = request_products(&socket, &ProductRequest::Status).expect("status");
        assert!(reply.ok, "{reply:?}");
        let line = session_status(reply.data.as_ref(), &id);
        if let Some(line) = &line
            && line["frames"] == frames
            && line["lag_frames"] == 0
        {
            return line.clone();
        }
        assert!(
            std::time::Instant::now() < deadline,
            "session {id} never reached {frames} frames: {line:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_live_session_with_a_gap_and_an_unknown_body_is_processed_around_them_and_all_acknowledged() {
    let site = start_live_server(1);
    let session = 0x0001_1fe0;
    // 2 is a body no version has, 5 never comes: 19 frames the pipeline can use.
    let sent: Vec<u64> = (0..=20).filter(|&seq| seq != 2 && seq != 5).collect();
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        for &seq in &sent {
            if seq == 3 {
                client
                    .send
                    .write_all(&undecodable_frame(session, 2))
                    .await
                    .expect("write");
            }
            client
                .send
                .write_all(&revolution(session, seq))
                .await
                .expect("write");
        }
        let mut acknowledged = sent.clone();
        acknowledged.push(2);
        assert!(
            client.acknowledged(session, &acknowledged).await,
            "acks received: {:?}",
            client.acks
        );
    });
    let live = live_session_status(&site, session, 19);
    assert_eq!(live["revolutions"], 19, "{live}");
    assert_eq!(live["samples"], 19 * 8, "{live}");
    assert_eq!(live["missing_frames"], 1, "{live}");
    assert_eq!(live["undecodable_frames"], 1, "{live}");
    // The one-frame queue overflowed: the worker caught up from the recording, and said so.
    assert!(live["queue_overflows"].as_u64() > Some(0), "{live}");
    assert!(live["catch_ups"].as_u64() > Some(0), "{live}");
    assert!(live["max_lag_frames"].as_u64() > Some(0), "{live}");
    // The same counts as the recording replayed offline.
    let dir = session_dir(
        &site.dir.path().join("data"),
        installation::EDGE_NAME,
        session,
    );
    let (mut offline, _) = run_session(
        &dir,
        &PipelineSettings::default(),
        Default::default(),
        false,
    )
    .expect("replay");
    let offline = serde_json::to_value(offline.status()).expect("json");
    for key in [
        "frames",
        "samples",
        "revolutions",
        "missing_frames",
        "undecodable_frames",
    ] {
        assert_eq!(
            live[key], offline[key],
            "{key}: live {live}, offline {offline}"
        );
    }
    site.server.stop();
}

#[test]
fn a_snapshot_into_an_unwritable_directory_fails_and_the_daemon_keeps_recording() {
    let site = start_live_server(256);
    let session = 0x0005_11a9;
    let data = site.dir.path().join("data");
    let socket = socket_path(&data);
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        for seq in 0..5 {
            client
                .send
                .write_all(&revolution(session, seq))
                .await
                .expect("write");
        }
        assert!(client.acknowledged(session, &[0, 1, 2, 3, 4]).await);
        // A directory below a regular file cannot be created, whoever runs the test.
        let blocker = site.dir.path().join("not-a-dir");
        std::fs::write(&blocker, b"x").expect("file");
        let unwritable = blocker.join("snapshot");
        let error = request_snapshot(&socket, installation::EDGE_NAME, None, None, &unwritable)
            .expect_err("the snapshot must fail");
        assert!(
            error
                .to_string()
                .contains(&unwritable.display().to_string()),
            "{error}"
        );
        // Recording and acknowledging go on.
        for seq in 5..10 {
            client
                .send
                .write_all(&revolution(session, seq))
                .await
                .expect("write");
        }
        assert!(client.acknowledged(session, &[5, 6, 7, 8, 9]).await);
    });
    live_session_status(&site, session, 10);
    // A lidar-only session: `scan3d snapshot` exits 0 with a valid empty map and cloud, the
    // same map the offline `scan3d map SESSION_DIR` makes.
    let out = site.dir.path().join("snapshot");
    let args = [
        "scan3d",
        "snapshot",
        "--edge",
        installation::EDGE_NAME,
        "--out",
    ];
    let mut args: Vec<String> = args.iter().map(ToString::to_string).collect();
    args.extend([
        out.display().to_string(),
        "--data-dir".into(),
        data.display().to_string(),
    ]);
    let cli = scan3d_server::cli::Cli::try_parse_from(&args).expect("arguments");
    scan3d_server::cli::execute(cli, &mut std::io::sink()).expect("scan3d snapshot");
    let bt = std::fs::read(out.join("map.bt")).expect("map.bt");
    let tree = Octree::read(&bt, SensorModel::default()).expect("a valid .bt");
    assert_eq!(tree.num_leaves(), 0);
    let ply = std::fs::read_to_string(out.join("cloud.ply")).expect("cloud.ply");
    assert!(ply.contains("element vertex 0"), "{ply}");
    let offline = site.dir.path().join("offline.bt");
    let dir = session_dir(&data, installation::EDGE_NAME, session);
    let cli = scan3d_server::cli::Cli::try_parse_from([
        "scan3d".to_owned(),
        "map".into(),
        dir.display().to_string(),
        "--resolution".into(),
        "0.05".into(),
        "--quiet".into(),
        "--out".into(),
        offline.display().to_string(),
    ])
    .expect("arguments");
    scan3d_server::cli::execute(cli, &mut std::io::sink()).expect("scan3d map");
    assert_eq!(bt, std::fs::read(&offline).expect("offline map"));
    site.server.stop();
}

#[test]
fn periodic_snapshots_are_written_into_the_data_directory_while_the_session_streams() {
    let site =
        start_live_server_with(|live| live.snapshot_every = Some(Duration::from_millis(200)));
    let session = 0x0000_5a95;
    let snapshots = site
        .dir
        .path()
        .join("data/snapshots")
        .join(installation::EDGE_NAME)
        .join(format!("{session:016x}"));
    site.runtime.block_on(async {
        let mut client = connect(site.server.addr(), &site.bundle).await;
        for seq in 0..3 {
            client
                .send
                .write_all(&revolution(session, seq))
                .await
                .expect("write");
        }
        assert!(client.acknowledged(session, &[0, 1, 2]).await);
    });
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    // Each file of a snapshot appears whole (written aside, then renamed), one after another.
    for file in ["map.bt", "map.ot", "cloud.ply"] {
        while !snapshots.join(file).exists() {
            assert!(
                std::time::Instant::now() < deadline,
                "no periodic {file} in {}",
                snapshots.display()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    site.server.stop();
}
