//! The live daemon's products against the offline tools, over the whole system: emulated
//! Sweep on the turntable → edge daemon → QUIC → server recording **and** live pipeline. After
//! a static scan, `scan3d snapshot` from the running daemon gives the `.bt` the offline
//! `scan3d map SESSION_DIR` makes from the recording with the same settings, byte for byte —
//! also when the pipeline's queue holds a single frame, so that nearly every frame is read
//! back from the recording (and `scan3d status` reports the lag).

use std::path::Path;
use std::sync::Arc;

use clap::Parser;
use scan3d_hw_sim::maps::{MapPlan, MapSetup, scan_map};
use scan3d_hw_sim::noise::RangeNoise;
use scan3d_hw_sim::truth::GroundTruth;
use scan3d_hw_sim::world::World;
use scan3d_map::cloud::assembly::Position;
use scan3d_map::octree::{Octree, SensorModel};

/// `scan3d map SESSION_DIR` with the settings the simulator's daemon maps with
/// (`maps::map_pipeline`: Table II filters per revolution, the plan's range cut).
fn offline_map(session: &Path, resolution: f64, max_range: f64, out: &Path) -> Vec<u8> {
    let args = [
        "scan3d".to_owned(),
        "map".into(),
        session.display().to_string(),
        "--resolution".into(),
        resolution.to_string(),
        "--max-range".into(),
        max_range.to_string(),
        "--filter".into(),
        "voxel:0.02".into(),
        "--filter".into(),
        "box:-0.2,-0.2,-0.2,8.05,5.9,3.2".into(),
        "--quiet".into(),
        "--out".into(),
        out.display().to_string(),
    ];
    let cli = scan3d_server::cli::Cli::try_parse_from(args).expect("arguments");
    scan3d_server::cli::execute(cli, &mut std::io::sink()).expect("scan3d map SESSION_DIR");
    std::fs::read(out).expect("the offline map")
}

#[test]
fn a_live_snapshot_after_a_static_scan_is_the_offline_map_byte_for_byte_even_through_a_one_frame_queue()
 {
    let world = Arc::new(World::conference_room());
    let truth = GroundTruth::new(&world);
    let dir = tempfile::tempdir().expect("temp dir");
    let clouds = dir.path().join("clouds");
    std::fs::create_dir_all(&clouds).expect("clouds dir");
    let resolution = 0.1;
    let setup = MapSetup {
        world: &world,
        truth: &truth,
        work: &dir.path().join("work"),
        data_dir: &dir.path().join("data"),
        clouds_dir: &clouds,
        time_scale: 10.0,
        seed: 3,
        noise: RangeNoise::SWEEP,
        resolution_m: resolution,
        queue_frames: 1,
        snapshots_dir: &dir.path().join("snapshots"),
        full_rates: false,
    };
    let plan = MapPlan {
        name: "live",
        positions: vec![Position {
            name: "west".into(),
            x_m: 1.5,
            y_m: 3.0,
            heading_deg: 0.0,
        }],
        motor_hz: 2,
        max_range_m: 6.0,
    };
    let result = scan_map(&plan, &setup).expect("the static scan runs end to end");
    let live = std::fs::read(result.snapshot_dir.join("map.bt")).expect("the live map.bt");
    let tree = Octree::read(&live, SensorModel::default()).expect("a valid .bt");
    assert!(
        tree.num_occupied() > 1000,
        "{} occupied voxels",
        tree.num_occupied()
    );
    let offline = offline_map(
        &result.session_dir,
        resolution,
        plan.max_range_m,
        &dir.path().join("offline.bt"),
    );
    assert!(
        live == offline,
        "the live map ({} bytes) differs from the offline one ({} bytes)",
        live.len(),
        offline.len()
    );
    for file in ["map.ot", "cloud.ply"] {
        assert!(result.snapshot_dir.join(file).exists(), "{file} missing");
    }
    // Through a one-frame queue the daemon fell behind and caught up from the recording; its
    // status said so.
    let status = &result.live_status;
    assert!(status["queue_overflows"].as_u64() > Some(0), "{status}");
    assert!(status["catch_ups"].as_u64() > Some(0), "{status}");
    assert!(status["max_lag_frames"].as_u64() > Some(0), "{status}");
    assert_eq!(status["positions"], serde_json::json!(["west"]), "{status}");
}
