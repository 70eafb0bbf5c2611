//! The operator's flow off the Pi, with the real binaries: `scan3d pair` → `scan3d serve` →
//! `scan3d-sim rig` (the emulated sensor head: ptys and the I2C socket) → the real
//! `scan3d-edge` daemon on the rig's `edge.toml` → `scan3d scan --wait` → `scan3d snapshot`,
//! and the snapshot's map has the room's walls in it.
//!
//! The binaries are the workspace's own, found beside this test executable (`cargo test
//! --workspace` builds every binary of the workspace before it runs a test); run alone
//! (`cargo test -p scan3d-tests --test rig_e2e`) it builds them first through `$CARGO`.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use scan3d_map::octree::{Octree, SensorModel};

/// Generous: the machine may be busy with other tests.
const DEADLINE: Duration = Duration::from_secs(90);

/// The directory holding the workspace's binaries (target/<profile>/).
fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/rig_e2e-HASH → target/<profile>
    exe.parent()
        .and_then(Path::parent)
        .expect("test executable under target/<profile>/deps")
        .to_path_buf()
}

/// Path of a workspace binary, built through `$CARGO` when it is not there yet.
fn binary(name: &str, package: &str) -> PathBuf {
    let path = bin_dir().join(name);
    if !path.exists() {
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
        let status = Command::new(cargo)
            .args(["build", "-p", package, "--bin", name])
            .status()
            .expect("run cargo build");
        assert!(status.success(), "cargo build --bin {name} failed");
    }
    assert!(
        path.exists(),
        "{} not found after building it",
        path.display()
    );
    path
}

/// A child process killed when the test ends, whatever happens.
struct Daemon(Child);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn(program: &Path, args: &[&str], log: &Path) -> Daemon {
    let log = std::fs::File::create(log).expect("log file");
    Daemon(
        Command::new(program)
            .args(args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", program.display())),
    )
}

fn run(program: &Path, args: &[&str]) -> Output {
    Command::new(program)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", program.display()))
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Waits until `ready` holds, polling; panics with `what` after the deadline.
fn wait_until(what: &str, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < DEADLINE, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn a_static_scan_through_the_real_edge_daemon_on_the_rig_maps_the_room() {
    let scan3d = binary("scan3d", "scan3d-server");
    let edge = binary("scan3d-edge", "scan3d-edge");
    let sim = binary("scan3d-sim", "scan3d-hw-sim");
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path();
    let p = |name: &str| root.join(name);
    let s = |path: &Path| path.to_str().expect("utf-8 path").to_owned();

    // The head: it prints its four paths once they exist.
    let mut rig = spawn(&sim, &["rig", "--dir", &s(&p("head"))], &p("rig.log"));
    let stdout = rig.0.stdout.take().expect("rig stdout");
    let printed: Vec<String> = BufReader::new(stdout)
        .lines()
        .take(4)
        .map(|l| l.expect("rig stdout line"))
        .collect();
    assert!(
        printed.iter().any(|l| l.ends_with("edge.toml")),
        "rig printed {printed:?}; log: {}",
        std::fs::read_to_string(p("rig.log")).unwrap_or_default()
    );

    // Pairing and the server on a free loopback port.
    let out = run(
        &scan3d,
        &["pair", "--dir", &s(&p("pki")), "--edge", "edge-rig-01"],
    );
    assert!(out.status.success(), "pair: {}", text(&out.stderr));
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|socket| socket.local_addr())
        .expect("free port")
        .port();
    let server_toml = p("server.toml");
    std::fs::write(
        &server_toml,
        format!(
            "listen = \"127.0.0.1:{port}\"\npki_dir = \"{}\"\ndata_dir = \"{}\"\n",
            s(&p("pki")),
            s(&p("data"))
        ),
    )
    .expect("server.toml");
    let _server = spawn(
        &scan3d,
        &["serve", "--config", &s(&server_toml)],
        &p("serve.log"),
    );

    // The operator's edge.toml: device_name and state_dir, the rig's sections, [uplink].
    let sections = std::fs::read_to_string(p("head/edge.toml")).expect("rig's edge.toml");
    let edge_toml = p("edge.toml");
    std::fs::write(
        &edge_toml,
        format!(
            "device_name = \"edge-rig-01\"\nstate_dir = \"{}\"\n{sections}\n[uplink]\n\
             server = \"127.0.0.1:{port}\"\nserver_name = \"localhost\"\npki_dir = \"{}\"\n",
            s(&p("edge-state")),
            s(&p("pki/edges/edge-rig-01"))
        ),
    )
    .expect("edge.toml");
    let out = run(&edge, &["check-config", "--config", &s(&edge_toml)]);
    assert!(
        out.status.success(),
        "check-config refused the rig's edge.toml: {}",
        text(&out.stderr)
    );
    let _edge = spawn(&edge, &["--config", &s(&edge_toml)], &p("edge.log"));

    // All four sensors streaming, as `scan3d status --json` reports them.
    wait_until("the edge's sensors to stream", || {
        let out = run(&scan3d, &["status", "--json", "--config", &s(&server_toml)]);
        let Ok(status) = serde_json::from_slice::<serde_json::Value>(&out.stdout) else {
            return false;
        };
        let streaming: Vec<String> = status["edges"]
            .as_array()
            .into_iter()
            .flatten()
            .flat_map(|edge| edge["sensors"].as_array().cloned().unwrap_or_default())
            .filter(|sensor| sensor["state"] == "streaming")
            .filter_map(|sensor| sensor["kind"].as_str().map(str::to_owned))
            .collect();
        ["rplidar", "sweep", "imu"]
            .iter()
            .all(|kind| streaming.iter().any(|s| s == kind))
    });

    // The scan, followed to its end.
    let out = run(
        &scan3d,
        &[
            "scan",
            "--config",
            &s(&server_toml),
            "--edge",
            "edge-rig-01",
            "--at",
            "4,3,0",
            "--name",
            "centre",
            "--wait",
            "--json",
        ],
    );
    let edge_log = || std::fs::read_to_string(p("edge.log")).unwrap_or_default();
    assert!(
        out.status.success(),
        "scan --wait failed: {}{}\nedge log:\n{}",
        text(&out.stdout),
        text(&out.stderr),
        edge_log()
    );
    let reply: serde_json::Value = serde_json::from_slice(&out.stdout).expect("scan --json");
    assert_eq!(reply["state"], "completed", "{reply}");
    assert!(
        reply["progress"]["yaw_deg"].as_f64().unwrap_or(0.0) >= 179.0,
        "the turntable did not turn through 180°: {reply}"
    );

    // The snapshot's map: the room's walls (x = 0 and 8 m, y = 0 and 6 m) are occupied.
    let snapshot = p("snapshot");
    let out = run(
        &scan3d,
        &[
            "snapshot",
            "--config",
            &s(&server_toml),
            "--edge",
            "edge-rig-01",
            "--out",
            &s(&snapshot),
        ],
    );
    assert!(out.status.success(), "snapshot: {}", text(&out.stderr));
    let bytes = std::fs::read(snapshot.join("map.bt")).expect("map.bt");
    let tree = Octree::read_bt(&bytes, SensorModel::default()).expect("a valid .bt");
    let model = SensorModel::default();
    let mut on_wall = [0usize; 4];
    for leaf in tree.leaves() {
        if !model.is_occupied(leaf.log_odds) {
            continue;
        }
        let [x, y, z] = leaf.center(tree.resolution());
        if !(0.3..2.5).contains(&z) {
            continue;
        }
        for (i, distance) in [x.abs(), (x - 8.0).abs(), y.abs(), (y - 6.0).abs()]
            .into_iter()
            .enumerate()
        {
            if distance < 0.15 {
                on_wall[i] += 1;
            }
        }
    }
    eprintln!("occupied voxels on the west, east, south, north walls: {on_wall:?}");
    let walls_seen = on_wall.iter().filter(|&&n| n >= 30).count();
    assert!(
        walls_seen >= 3,
        "occupied voxels on the west, east, south, north walls: {on_wall:?}"
    );

    // The edge's own log names the I2C devices it drove.
    let log = edge_log();
    assert!(log.contains("IMU ready"), "edge log:\n{log}");
    assert!(log.contains("I2C socket connected"), "edge log:\n{log}");
}
