//! One paired edge sending frames of 1,500 distinct session ids must not exhaust the server's
//! file descriptors or memory (issue 10, defect 2): at most `max_sessions_per_edge` recordings
//! are open at once, every frame is still recorded and acknowledged.
//!
//! Alone in its test binary: it counts this process's descriptors (`/proc/self/fd`) and
//! resident memory (`VmRSS` in `/proc/self/status`), which the in-process server shares.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::time::Duration;

use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::installation::{self, ServerThread};
use scan3d_protocol::{Ack, Body, Frame, FrameReader, Heartbeat, encode};
use scan3d_server::ingest::server::IngestLimits;
use scan3d_server::recording::list_sessions;

const SESSIONS: u64 = 1500;

fn open_fds() -> usize {
    std::fs::read_dir("/proc/self/fd")
        .expect("/proc/self/fd")
        .count()
}

fn rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let kib: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS");
    kib / 1024.0
}

#[test]
fn fifteen_hundred_session_ids_from_one_edge_keep_fds_and_memory_bounded() {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = dir.path().join("pki");
    let data = dir.path().join("data");
    let bundle = installation::pair_certificates(&pki).expect("pairing");
    let fds_before = open_fds();
    let rss_before = rss_mib();
    let server = ServerThread::start(installation::ingest_config(&pki, &data, 0)).expect("server");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .expect("runtime");
    let addr = server.addr();
    let (fds_connected, rss_connected) = runtime.block_on(async {
        let mut endpoint =
            quinn::Endpoint::client(SocketAddr::from(([127, 0, 0, 1], 0))).expect("endpoint");
        endpoint.set_default_client_config(client_config(&bundle).expect("bundle"));
        let connection = endpoint
            .connect(addr, "localhost")
            .expect("connect")
            .await
            .expect("handshake");
        let (mut send, mut recv) = connection.open_bi().await.expect("stream");
        let acked = tokio::spawn(async move {
            let mut acked = HashSet::new();
            let mut reader = FrameReader::new();
            while acked.len() < SESSIONS as usize {
                let Ok(Some(chunk)) = recv.read_chunk(64 * 1024, true).await else {
                    break;
                };
                reader.push(&chunk.bytes);
                while let Ok(Some(frame)) = reader.next_frame() {
                    if let Body::Ack(Ack::UpTo { seq: 0 }) = frame.body {
                        acked.insert(frame.session_id);
                    }
                }
            }
            acked
        });
        for session in 1..=SESSIONS {
            let frame = encode(&Frame::new(session, 0, Heartbeat { sent_ns: session })).unwrap();
            send.write_all(&frame).await.expect("write");
        }
        let acked = tokio::time::timeout(Duration::from_secs(240), acked)
            .await
            .expect("every session acknowledged in time")
            .expect("reader");
        assert_eq!(acked.len(), SESSIONS as usize, "sessions acknowledged");
        let measured = (open_fds(), rss_mib());
        connection.close(0u32.into(), b"done");
        endpoint.wait_idle().await;
        measured
    });
    // Give the server task a moment to notice the close and close its recordings.
    std::thread::sleep(Duration::from_millis(500));
    let (fds_after, rss_after) = (open_fds(), rss_mib());
    let stats = server.stop();
    eprintln!(
        "fds: {fds_before} before, {fds_connected} with the edge connected, {fds_after} after it left; \
         RSS MiB: {rss_before:.1} before, {rss_connected:.1} connected, {rss_after:.1} after; {stats:?}"
    );
    let max_open = IngestLimits::default().max_sessions_per_edge as u64;
    assert!(
        stats.peak_recorders_open <= max_open,
        "{} recorders open at once (limit {max_open})",
        stats.peak_recorders_open
    );
    assert!(fds_connected < 400, "{fds_connected} fds open");
    assert!(fds_after < 400, "{fds_after} fds open");
    assert!(
        rss_connected - rss_before < 300.0,
        "RSS grew by {:.1} MiB",
        rss_connected - rss_before
    );
    assert_eq!(stats.frames, SESSIONS, "{stats:?}");
    assert!(stats.sessions_evicted >= SESSIONS - max_open, "{stats:?}");
    let sessions = list_sessions(&data).expect("sessions");
    assert_eq!(sessions.len(), SESSIONS as usize);
    assert!(
        sessions.iter().all(|s| s.frames == 1),
        "every session holds its frame"
    );
}
