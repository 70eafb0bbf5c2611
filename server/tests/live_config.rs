//! `scan3d serve` with a `[pipeline]` it cannot run, and `scan3d status` / `scan3d snapshot`
//! without a daemon: one readable error each, before anything is served.

mod common;

use common::{arg, run_cli};
use scan3d_map::octree::{Octree, Resolution, SensorModel};

#[test]
fn a_reference_map_of_another_resolution_stops_the_daemon_at_start_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let reference = dir.path().join("ref.bt");
    let tree = Octree::empty(Resolution::new(0.1).unwrap(), SensorModel::default());
    std::fs::write(&reference, tree.to_bt_bytes()).unwrap();
    let config = dir.path().join("server.toml");
    std::fs::write(
        &config,
        format!(
            "data_dir = {:?}\n[pipeline]\nresolution_m = 0.05\nreference = {:?}\n",
            dir.path().join("data"),
            reference
        ),
    )
    .unwrap();
    let error = run_cli(&["serve", "--config", arg(&config)])
        .unwrap_err()
        .to_string();
    assert!(error.starts_with("[pipeline]: "), "{error}");
    assert!(error.contains(arg(&reference)), "{error}");
    assert!(error.contains("0.1") && error.contains("0.05"), "{error}");
    // Nothing was started: no control socket left behind.
    assert!(!dir.path().join("data/control.sock").exists());
}

#[test]
fn status_and_snapshot_without_a_running_daemon_say_where_they_looked() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    for args in [
        vec!["status", "--data-dir", arg(&data)],
        vec![
            "snapshot",
            "--edge",
            "pi",
            "--out",
            arg(dir.path()),
            "--data-dir",
            arg(&data),
        ],
    ] {
        let error = run_cli(&args).unwrap_err().to_string();
        assert!(
            error.contains("control.sock") && error.contains("scan3d serve"),
            "{args:?}: {error}"
        );
    }
}
