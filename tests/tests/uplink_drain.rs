//! Shutting the uplink down while a write is blocked (the server takes no more bytes: flow
//! control) ends at the drain deadline, not when the backlog is written; what was not written
//! stays in the spool for the next start.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::clock::MonotonicClock;
use scan3d_edge::uplink::client::{Uplink, UplinkConfig};
use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::installation;
use scan3d_protocol::{DeviceStatus, SensorId, StatusEvent};
use scan3d_server::ingest::tls::server_config;

#[test]
fn a_shutdown_with_a_write_blocked_by_flow_control_ends_at_the_drain_deadline() {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = dir.path().join("pki");
    let bundle = installation::pair_certificates(&pki).expect("pairing");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        // A server that accepts the edge's stream and never reads from it.
        let server = quinn::Endpoint::server(
            server_config(&pki).expect("server config"),
            SocketAddr::from(([127, 0, 0, 1], 0)),
        )
        .expect("server endpoint");
        let addr = server.local_addr().expect("addr");
        let (accepted_tx, accepted_rx) = tokio::sync::oneshot::channel();
        let _server = tokio::spawn(async move {
            let connection = server
                .accept()
                .await
                .expect("incoming")
                .await
                .expect("handshake");
            let streams = connection.accept_bi().await.expect("stream");
            let _ = accepted_tx.send(());
            std::future::pending::<()>().await;
            drop((streams, connection, server));
        });

        let section = installation::uplink_section(addr, &bundle);
        let mut config = UplinkConfig::new(
            section.server.clone(),
            section.tls_name().to_owned(),
            client_config(&bundle).expect("bundle"),
            section
                .spool_config(dir.path().join("spool"))
                .expect("spool"),
        );
        let drain = Duration::from_millis(500);
        config.drain_timeout = drain;
        let (uplink, handle, _commands) =
            Uplink::new(config, Arc::new(MonotonicClock::new()), 7).expect("uplink");
        // ~3.8 MB of frames: more than the server's 2 MiB stream window lets through.
        let reason = "x".repeat(60_000);
        for t_ns in 0..64 {
            handle
                .submit(DeviceStatus {
                    t_ns,
                    sensor: SensorId::RPLIDAR,
                    event: StatusEvent::SensorLost,
                    reason: reason.clone(),
                })
                .expect("spooled");
        }
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let task = tokio::spawn(uplink.run(stopped));
        tokio::time::timeout(Duration::from_secs(10), accepted_rx)
            .await
            .expect("the edge connected")
            .expect("accepted");
        // Let the writes fill the window and block.
        tokio::time::sleep(Duration::from_millis(300)).await;
        let asked = Instant::now();
        stop.send(true).expect("stop");
        let stats = tokio::time::timeout(Duration::from_secs(10), task)
            .await
            .expect("the uplink must stop at its drain deadline, not after the backlog")
            .expect("join");
        let took = asked.elapsed();
        assert!(
            took >= drain && took < drain + Duration::from_millis(1500),
            "shutdown took {took:?} with a {drain:?} drain timeout"
        );
        assert!(
            stats.frames_sent < 64,
            "the server never read, yet {} frames were written",
            stats.frames_sent
        );
        assert_eq!(
            handle.pending(),
            64,
            "every unacknowledged frame stays spooled"
        );
    });
}
