//! The edge's spool on a real full disk: a tiny tmpfs runs out of space while the server is
//! down, the uplink refuses frames (nothing taken, nothing dropped) and reports it, the disk
//! grows, writes succeed again, and every frame reaches the server's recording once, in order.
//!
//! The deterministic version of this, with injected `ENOSPC`, runs everywhere
//! (`scan3d-edge`'s `daemon` and `uplink::spool` unit tests). This one needs root to mount a
//! tmpfs, so it is ignored by default; run it with
//! `cargo test -p scan3d-tests --test edge_storage -- --ignored` (as root).

use std::net::SocketAddr;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::clock::{MonotonicClock, SharedClock};
use scan3d_edge::uplink::client::{SubmitError, Uplink, UplinkConfig};
use scan3d_edge::uplink::spool::SpoolConfig;
use scan3d_edge::uplink::tls;
use scan3d_hw_sim::installation::{self, ServerThread};
use scan3d_protocol::{Body, DeviceStatus, SensorId, StatusEvent};
use scan3d_server::recording::{read_session, session_dir};

/// A tmpfs mounted for the test's lifetime.
struct Tmpfs<'a>(&'a Path);

impl<'a> Tmpfs<'a> {
    fn mount(dir: &'a Path, size: &str) -> Self {
        std::fs::create_dir_all(dir).unwrap();
        run(
            "mount",
            &["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"],
            dir,
        );
        Tmpfs(dir)
    }

    fn resize(&self, size: &str) {
        run("mount", &["-o", &format!("remount,size={size}")], self.0);
    }
}

impl Drop for Tmpfs<'_> {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.0).status();
    }
}

fn run(program: &str, args: &[&str], dir: &Path) {
    let status = Command::new(program)
        .args(args)
        .arg(dir)
        .status()
        .unwrap_or_else(|e| panic!("{program}: {e}"));
    assert!(
        status.success(),
        "{program} {args:?} {}: {status} (needs root)",
        dir.display()
    );
}

fn wait_until(timeout: Duration, what: &str, mut done: impl FnMut() -> bool) {
    let end = Instant::now() + timeout;
    while !done() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A status frame of about 1 KiB whose reason says which one it is.
fn status(n: usize) -> DeviceStatus {
    DeviceStatus {
        t_ns: n as u64,
        sensor: SensorId::RPLIDAR,
        event: StatusEvent::SensorBack,
        reason: format!("frame {n:05} {}", "x".repeat(1000)),
    }
}

#[test]
#[ignore = "needs root to mount a tmpfs; run with --ignored"]
fn a_full_disk_pauses_the_spool_without_losing_a_frame_and_everything_arrives_once_it_has_room() {
    let site = tempfile::tempdir().unwrap();
    let bundle = installation::pair_certificates(&site.path().join("pki")).unwrap();
    let spool_dir = site.path().join("spool");
    let disk = Tmpfs::mount(&spool_dir, "64k");
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let server_addr = SocketAddr::from(([127, 0, 0, 1], port));

    let mut spool = SpoolConfig::new(&spool_dir);
    spool.memory_limit_bytes = 8 << 10;
    spool.disk_limit_bytes = 16 << 20; // far more than the tmpfs: the disk fills first
    spool.segment_bytes = 16 << 10;
    let config = UplinkConfig::new(
        server_addr.to_string(),
        "localhost".into(),
        tls::client_config(&bundle).unwrap(),
        spool,
    );
    let clock: SharedClock = Arc::new(MonotonicClock::new());
    let session_id = rand::random::<u64>();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (uplink, handle, _commands) = Uplink::new(config, clock, session_id).unwrap();
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let task = runtime.spawn(uplink.run(stop_rx));

    // The server is down: frames go to memory, then to the tmpfs until it is full.
    let mut next = 0;
    let refused = loop {
        match handle.submit(status(next)) {
            Ok(_) => next += 1,
            Err(SubmitError::Unwritable { reason }) => break reason,
            Err(e) => panic!("frame {next}: {e}"),
        }
        assert!(next < 1000, "the 64 KiB disk never filled");
    };
    assert!(refused.contains("No space left on device"), "{refused}");
    assert!(next > 8, "only {next} frames before the disk filled");
    assert!(!handle.has_room(), "paused while the disk is full");
    assert_eq!(handle.stats().storage_episodes, 1);

    // The disk grows: the retried writes succeed, the refused frame goes in, more follow.
    disk.resize("4m");
    wait_until(Duration::from_secs(10), "writes to succeed again", || {
        handle.has_room()
    });
    let total = next + 40;
    for n in next..total {
        handle.submit(status(n)).unwrap();
    }
    let server = ServerThread::start(installation::ingest_config(
        &site.path().join("pki"),
        &site.path().join("data"),
        port,
    ))
    .unwrap();
    wait_until(Duration::from_secs(60), "every frame acknowledged", || {
        handle.pending() == 0
    });
    stop_tx.send(true).unwrap();
    let stats = runtime.block_on(task).unwrap();
    server.stop();
    assert_eq!(stats.storage_episodes, 1, "{stats:?}");
    assert_eq!(stats.frames_lost_on_edge, 0, "{stats:?}");

    let session = session_dir(
        &site.path().join("data"),
        installation::EDGE_NAME,
        session_id,
    );
    let recorded: Vec<(u64, String)> = read_session(&session)
        .unwrap()
        .into_iter()
        .filter_map(|f| match f.frame.body {
            Body::Status(status) => Some((f.frame.seq, status.reason)),
            _ => None,
        })
        .collect();
    let expected: Vec<(u64, String)> = (0..total).map(|n| (n as u64, status(n).reason)).collect();
    assert_eq!(recorded.len(), expected.len());
    assert!(recorded == expected, "every frame once, in order");
    drop(disk);
}
