//! The operator's flow off the Pi, with the real binaries: `scan3d pair` → `scan3d serve` →
//! `scan3d-sim rig` (the emulated sensor head: ptys and the I2C socket) → the real
//! `scan3d-edge` daemon on the rig's `edge.toml` → `scan3d scan --wait` → `scan3d snapshot`,
//! and the snapshot's map has the room's walls in it.
//!
//! The binaries are the workspace's own, found beside this test executable (`cargo test
//! --workspace` builds every binary of the workspace before it runs a test); run alone
//! (`cargo test -p scan3d-tests --test rig_e2e`) it builds them first through `$CARGO`.

use std::time::Duration;

use scan3d_map::octree::{Octree, SensorModel};
use scan3d_tests::operator::{OperatorRig, text, wait_until};

/// Generous: the machine may be busy with other tests.
const DEADLINE: Duration = Duration::from_secs(90);

#[test]
fn a_static_scan_through_the_real_edge_daemon_on_the_rig_maps_the_room() {
    let dir = tempfile::tempdir().expect("temp dir");
    let rig = OperatorRig::start(dir.path(), "edge-rig-01");
    let s = |path: &std::path::Path| path.to_str().expect("utf-8 path").to_owned();
    let p = |name: &str| rig.path(name);

    // All four sensors streaming, as `scan3d status --json` reports them.
    wait_until("the edge's sensors to stream", DEADLINE, || {
        let out = rig.scan3d(&["status", "--json"]);
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
    let out = rig.scan3d(&[
        "scan",
        "--edge",
        "edge-rig-01",
        "--at",
        "4,3,0",
        "--name",
        "centre",
        "--wait",
        "--json",
    ]);
    let edge_log = || rig.edge_log();
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
    let out = rig.scan3d(&["snapshot", "--edge", "edge-rig-01", "--out", &s(&snapshot)]);
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
