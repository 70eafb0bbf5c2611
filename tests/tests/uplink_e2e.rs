//! Edge → QUIC → server end to end: emulated lidars on ptys, the edge daemon, the ingest server,
//! and the MCAP recording, checked sample by sample against what the emulators sent.

use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_hw_sim::rig::{
    self, Delivery, EdgeThread, LidarOptions, ServerThread, SimLidars, account,
};
use scan3d_server::ingest::recorder::session_dir;

const TIME_SCALE: f64 = 10.0;

fn clock() -> SharedClock {
    Arc::new(ScaledClock::new(TIME_SCALE))
}

fn lidar_options() -> LidarOptions {
    LidarOptions {
        time_scale: TIME_SCALE,
        sweep_settle_ms: 1000,
        ..Default::default()
    }
}

/// Waits (real time) until `done` or panics after `timeout`.
fn wait_until(timeout: Duration, what: &str, mut done: impl FnMut() -> bool) {
    let end = Instant::now() + timeout;
    while !done() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn assert_exactly_once(deliveries: &[Delivery]) {
    for d in deliveries {
        eprintln!("{d:?}");
        assert!(
            d.revolutions >= 5,
            "{d:?}: too few revolutions to mean anything"
        );
        assert_eq!(
            d.unexplained, 0,
            "{d:?}: recorded samples the emulator never sent"
        );
        assert_eq!(
            d.missing_in_span, 0,
            "{d:?}: samples lost between emulator and recording"
        );
        assert_eq!(
            d.recorded_samples, d.edge_samples,
            "{d:?}: recording differs from what the edge sent"
        );
    }
}

#[test]
fn a_clean_run_records_every_sample_exactly_once() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = rig::pair_certificates(&dir.path().join("pki")).expect("pairing");
    let server = ServerThread::start(rig::ingest_config(
        &dir.path().join("pki"),
        &dir.path().join("data"),
        0,
    ))
    .expect("server");
    let lidars = SimLidars::start(&dir.path().join("links"), &lidar_options()).expect("lidars");
    let uplink = rig::uplink_section(server.addr(), &bundle);
    let config = lidars.edge_config(&dir.path().join("edge-state"), Some(uplink));
    let session_id = rand::random::<u64>();
    let edge = EdgeThread::start(config, clock(), session_id).expect("edge");
    std::thread::sleep(Duration::from_secs(2));
    let report = edge.stop().expect("edge report");
    let stats = server.stop();
    let uplink = report.uplink.clone().expect("uplink stats");
    assert_eq!(uplink.auth_failures, 0);
    assert_eq!(stats.duplicates, 0, "{stats:?}");
    let deliveries = account(
        &session_dir(&dir.path().join("data"), rig::EDGE_NAME, session_id),
        &lidars,
        Some(&report),
    )
    .expect("recording readable");
    assert_exactly_once(&deliveries);
    lidars.shutdown();
}
