//! Edge → QUIC → server end to end: emulated lidars on ptys, the edge daemon, the ingest server,
//! and the MCAP recording, checked sample by sample against what the emulators sent.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::config::UplinkSection;
use scan3d_hw_sim::installation::{
    self, Delivery, EdgeThread, LidarOptions, ServerThread, SimLidars, account,
};
use scan3d_server::recording::session_dir;

const TIME_SCALE: f64 = 10.0;

/// These tests each run two emulated lidars, an edge daemon and a server: on a 2-core machine
/// two of them at once starve the emulators and the edge of CPU (the edge then sees a silent
/// device and restarts its handshake, which is correct but not what these tests are about).
/// They take turns.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn take_turn() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

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
        // A loaded machine can overrun the emulator's pty (bytes never sent, as a UART
        // overrun); only the capsule each dropped unit leaves undecodable may go with them.
        assert!(
            d.missing_in_span <= d.overrun_allowance(),
            "{d:?}: samples lost between emulator and recording"
        );
        assert_eq!(
            d.recorded_samples, d.edge_samples,
            "{d:?}: recording differs from what the edge sent"
        );
    }
}

/// A temporary installation: a directory with paired certificates, recordings and edge state.
struct Site {
    dir: tempfile::TempDir,
    bundle: PathBuf,
}

impl Site {
    fn new() -> Self {
        let dir = tempfile::tempdir().expect("temp dir");
        let bundle = installation::pair_certificates(&dir.path().join("pki")).expect("pairing");
        Self { dir, bundle }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// The in-process server on loopback `port` (0 = any).
    fn server(&self, port: u16) -> ServerThread {
        ServerThread::start(installation::ingest_config(
            &self.path("pki"),
            &self.path("data"),
            port,
        ))
        .expect("server")
    }

    fn lidars(&self, options: &LidarOptions) -> SimLidars {
        SimLidars::start(&self.path("links"), options).expect("lidars")
    }

    /// Starts the edge daemon streaming to `server`; returns it and its session id.
    fn edge(
        &self,
        lidars: &SimLidars,
        server: SocketAddr,
        clock: SharedClock,
        tune: impl FnOnce(&mut UplinkSection),
    ) -> (EdgeThread, u64) {
        let mut uplink = installation::uplink_section(server, &self.bundle);
        tune(&mut uplink);
        let config = lidars.edge_config(&self.path("edge-state"), Some(uplink));
        let session_id = rand::random::<u64>();
        (
            EdgeThread::start(config, clock, session_id).expect("edge"),
            session_id,
        )
    }

    fn session(&self, session_id: u64) -> PathBuf {
        session_dir(&self.path("data"), installation::EDGE_NAME, session_id)
    }
}

#[test]
fn a_clean_run_records_every_sample_exactly_once() {
    let _turn = take_turn();
    let site = Site::new();
    let server = site.server(0);
    let lidars = site.lidars(&lidar_options());
    let (edge, session_id) = site.edge(&lidars, server.addr(), clock(), |_| {});
    std::thread::sleep(Duration::from_secs(2));
    let report = edge.stop().expect("edge report");
    let stats = server.stop();
    let uplink = report.uplink.clone().expect("uplink stats");
    assert_eq!(uplink.auth_failures, 0);
    assert_eq!(stats.duplicates, 0, "{stats:?}");
    let deliveries =
        account(&site.session(session_id), &lidars, Some(&report)).expect("recording readable");
    assert_exactly_once(&deliveries);
    lidars.shutdown();
}

#[test]
fn a_thirty_second_network_cut_loses_nothing() {
    let _turn = take_turn();
    let site = Site::new();
    let server = site.server(0);
    let relay = scan3d_tests::relay::UdpRelay::start(server.addr()).expect("relay");
    // Real time for the network (QUIC timers), scaled time for the sensors: 30 s of cut is
    // 300 s of sensor data at x10, so run the sensors at real speed here.
    let options = LidarOptions {
        time_scale: 1.0,
        sweep_settle_ms: 500,
        ..Default::default()
    };
    let lidars = site.lidars(&options);
    let real_time: SharedClock = Arc::new(ScaledClock::new(1.0));
    let (edge, session_id) = site.edge(&lidars, relay.local_addr(), real_time, |_| {});
    std::thread::sleep(Duration::from_secs(3));
    relay.cut();
    std::thread::sleep(Duration::from_secs(30));
    relay.restore();
    // After the cut the edge reconnects (backoff ≤ 5 s) and resends everything unacknowledged.
    std::thread::sleep(Duration::from_secs(8));
    let report = edge.stop().expect("edge report");
    let stats = server.stop();
    let uplink = report.uplink.clone().expect("uplink stats");
    assert!(
        uplink.connections >= 2,
        "the edge never reconnected: {uplink:?}"
    );
    assert_eq!(uplink.auth_failures, 0);
    eprintln!("{uplink:?} {stats:?}");
    let deliveries =
        account(&site.session(session_id), &lidars, Some(&report)).expect("recording readable");
    assert_exactly_once(&deliveries);
    relay.shutdown();
    lidars.shutdown();
}

/// The server's body when this test binary is re-run as a child process (see
/// `the_server_killed_mid_run_loses_nothing`): `scan3d serve --config $SCAN3D_CHILD_SERVER_CONFIG`.
#[test]
#[ignore = "runs only as the child process of the server crash test"]
fn server_child_process() {
    let Ok(config) = std::env::var("SCAN3D_CHILD_SERVER_CONFIG") else {
        return;
    };
    use clap::Parser;
    let cli = scan3d_server::cli::Cli::parse_from(["scan3d", "serve", "--config", &config]);
    scan3d_server::cli::execute(cli, &mut std::io::sink()).expect("server ran");
}

fn spawn_server_process(config: &std::path::Path) -> std::process::Child {
    std::process::Command::new(std::env::current_exe().expect("test binary"))
        .args([
            "server_child_process",
            "--exact",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env("SCAN3D_CHILD_SERVER_CONFIG", config)
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("server child process")
}

fn free_udp_port() -> u16 {
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("udp socket");
    socket.local_addr().expect("local addr").port()
}

#[test]
fn the_server_killed_mid_run_loses_nothing() {
    let _turn = take_turn();
    let site = Site::new();
    let port = free_udp_port();
    let config = site.path("server.toml");
    std::fs::write(
        &config,
        format!(
            "listen = \"127.0.0.1:{port}\"\npki_dir = {:?}\ndata_dir = {:?}\ncommit_interval_ms = 50\n",
            site.path("pki").display().to_string(),
            site.path("data").display().to_string()
        ),
    )
    .expect("server.toml");
    let mut server = spawn_server_process(&config);
    let lidars = site.lidars(&lidar_options());
    let server_addr = SocketAddr::from(([127, 0, 0, 1], port));
    let (edge, session_id) = site.edge(&lidars, server_addr, clock(), |_| {});
    let session = site.session(session_id);
    wait_until(Duration::from_secs(20), "a first recording", || {
        session.join("0000.mcap").exists()
    });
    std::thread::sleep(Duration::from_secs(2));
    server.kill().expect("SIGKILL the server");
    let _ = server.wait();
    std::thread::sleep(Duration::from_secs(1));
    let mut server = spawn_server_process(&config);
    // The restarted server continues the session in a new file; the edge resends what was not
    // acknowledged and the server drops what it already had on disk.
    wait_until(Duration::from_secs(20), "a second recording file", || {
        session.join("0001.mcap").exists()
    });
    std::thread::sleep(Duration::from_secs(2));
    let report = edge.stop().expect("edge report");
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(server.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .expect("SIGTERM the server");
    let status = server.wait().expect("server exit");
    assert!(
        status.success(),
        "server did not exit cleanly after SIGTERM: {status}"
    );
    let uplink = report.uplink.clone().expect("uplink stats");
    assert!(uplink.connections >= 2, "{uplink:?}");
    let deliveries = account(&session, &lidars, Some(&report)).expect("recording readable");
    assert_exactly_once(&deliveries);
    lidars.shutdown();
}

#[test]
fn with_the_server_down_frames_spill_to_disk_pause_acquisition_and_all_arrive_later() {
    let _turn = take_turn();
    use scan3d_protocol::{Body, StatusEvent};
    let site = Site::new();
    let port = free_udp_port();
    let lidars = site.lidars(&lidar_options());
    // About 0.6 MB of frames per real second at x10: memory spills after ~2 s, the spool is
    // full after ~5 s.
    let (edge, session_id) = site.edge(
        &lidars,
        SocketAddr::from(([127, 0, 0, 1], port)),
        clock(),
        |uplink| {
            uplink.spool_memory_mb = 1;
            uplink.spool_disk_mb = 2;
        },
    );
    let spool_dir = site.path("edge-state").join("spool");
    let spilled = || {
        std::fs::read_dir(&spool_dir)
            .map(|entries| {
                entries
                    .flatten()
                    .any(|e| e.metadata().is_ok_and(|m| m.len() > 0))
            })
            .unwrap_or(false)
    };
    wait_until(Duration::from_secs(20), "frames spilled to disk", spilled);
    std::thread::sleep(Duration::from_secs(6));
    let server = site.server(port);
    std::thread::sleep(Duration::from_secs(6));
    let report = edge.stop().expect("edge report");
    server.stop();
    for (sensor, lidar) in &report.lidars {
        assert!(
            lidar.pauses >= 1,
            "{sensor}: acquisition never paused: {lidar:?}"
        );
    }
    let session = site.session(session_id);
    let frames = scan3d_server::recording::read_session(&session).expect("recording");
    let events: Vec<StatusEvent> = frames
        .iter()
        .filter_map(|f| match &f.frame.body {
            Body::Status(status) => Some(status.event),
            _ => None,
        })
        .collect();
    assert!(
        events.contains(&StatusEvent::AcquisitionPaused),
        "{events:?}"
    );
    assert!(
        events.contains(&StatusEvent::AcquisitionResumed),
        "{events:?}"
    );
    let deliveries = account(&session, &lidars, Some(&report)).expect("recording readable");
    for d in &deliveries {
        eprintln!("{d:?}");
        assert_eq!(d.unexplained, 0, "{d:?}");
        // While paused the lidar is not read at all, so only edge → server is checked here.
        assert_eq!(d.recorded_samples, d.edge_samples, "{d:?}");
    }
    lidars.shutdown();
}
