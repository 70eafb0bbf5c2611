//! The session pipeline and its offline drivers on recorded sessions (written with the real
//! recorder): the streamed map equals the old assemble-then-map path byte for byte, empty
//! sessions snapshot valid empty files, bad input is skipped and counted.

mod common;
mod pipeline_support;

use std::path::Path;
use std::time::{Duration, Instant};

use common::{arg, run_cli};
use pipeline_support::{DEMO_ROOM, SessionBuilder, break_chunk, position};
use scan3d_map::cloud::io;
use scan3d_map::cloud::scans::RevolutionCollector;
use scan3d_map::octree::{Octree, SensorModel};
use scan3d_server::pipeline::offline::{MAP_ONLY, run_session};
use scan3d_server::pipeline::{PipelineError, PipelineSettings, Products, SessionPipeline};
use scan3d_server::recording::read_session;

fn two_position_session() -> SessionBuilder {
    let mut s = SessionBuilder::new(0x5eed);
    s.rplidar_revolutions(3, 90);
    s.static_scan(&position("door", 1.0, 1.0, 0.0), 20, 120);
    s.rplidar_revolutions(2, 90);
    s.static_scan(&position("window", 3.0, 2.0, 45.0), 20, 120);
    s
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn a_session_mapped_through_the_pipeline_equals_assembling_to_scans_then_mapping() {
    let tmp = tempfile::tempdir().unwrap();
    let session = two_position_session().record(&tmp.path().join("data"), "pi");
    let scans = tmp.path().join("cloud.scans");
    run_cli(&["assemble", arg(&session), "--out", arg(&scans)]).unwrap();
    for extra in [
        &[][..],
        &["--max-range", "2.5"][..],
        &["--filter", "box:-1,-1,-1,5,5,2.0", "--hit", "0.8"][..],
    ] {
        let old = tmp.path().join("old.bt");
        let new = tmp.path().join("new.bt");
        let base = ["--resolution", "0.1", "--quiet"];
        let mut old_args = vec!["map", arg(&scans), "--out", arg(&old)];
        old_args.extend(base.iter().chain(extra));
        run_cli(&old_args).unwrap();
        let mut new_args = vec!["map", arg(&session), "--out", arg(&new)];
        new_args.extend(base.iter().chain(extra));
        let printed = run_cli(&new_args).unwrap();
        assert!(
            printed.contains("2 static scans at 2 positions"),
            "{printed}"
        );
        let (old, new) = (read(&old), read(&new));
        let tree = Octree::read(&new, SensorModel::default()).unwrap();
        assert!(
            tree.num_occupied() > 100,
            "a real map: {} occupied of {} leaves\n{printed}",
            tree.num_occupied(),
            tree.num_leaves()
        );
        assert!(
            old == new,
            "with {extra:?}: the streamed .bt differs from assemble + map"
        );
    }
}

#[test]
fn the_replay_snapshot_and_a_position_snapshot_equal_the_offline_maps() {
    let tmp = tempfile::tempdir().unwrap();
    let session = two_position_session().record(&tmp.path().join("data"), "pi");
    let out = tmp.path().join("replay");
    let printed = run_cli(&[
        "replay",
        arg(&session),
        "--resolution",
        "0.1",
        "--out",
        arg(&out),
    ])
    .unwrap();
    assert!(printed.contains("snapshot: 2 static scans"), "{printed}");
    let offline = tmp.path().join("offline.bt");
    run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.1",
        "--quiet",
        "--out",
        arg(&offline),
    ])
    .unwrap();
    assert!(
        read(&out.join("map.bt")) == read(&offline),
        "replay's map.bt differs from scan3d map"
    );
    // The cloud is every assembled point (no filters): what `scan3d assemble` writes.
    let assembled = tmp.path().join("assembled.ply");
    run_cli(&["assemble", arg(&session), "--out", arg(&assembled)]).unwrap();
    assert!(
        read(&out.join("cloud.ply")) == read(&assembled),
        "cloud.ply differs from assemble's PLY"
    );

    // One position's snapshot equals assembling only that position and mapping it.
    let settings = PipelineSettings {
        resolution_m: 0.1,
        ..PipelineSettings::default()
    };
    let (mut pipeline, _) = run_session(&session, &settings, Products::default(), false).unwrap();
    assert_eq!(pipeline.positions(), ["door", "window"]);
    let snap = pipeline
        .write_snapshot(&tmp.path().join("window"), Some("window"))
        .unwrap();
    let window_scans = tmp.path().join("window.scans");
    run_cli(&[
        "assemble",
        arg(&session),
        "--position",
        "window",
        "--out",
        arg(&window_scans),
    ])
    .unwrap();
    let window_bt = tmp.path().join("window.bt");
    run_cli(&[
        "map",
        arg(&window_scans),
        "--resolution",
        "0.1",
        "--quiet",
        "--out",
        arg(&window_bt),
    ])
    .unwrap();
    assert!(
        read(&snap.files[0]) == read(&window_bt),
        "the position's map.bt differs"
    );
    assert_ne!(
        read(&snap.files[0]),
        read(&offline),
        "a position's map is not the session's"
    );
    let err = pipeline
        .write_snapshot(tmp.path(), Some("attic"))
        .unwrap_err();
    assert!(
        err.to_string().contains("\"attic\"") && err.to_string().contains("door, window"),
        "{err}"
    );
}

#[test]
fn a_lidar_only_session_snapshots_a_valid_empty_bt_and_ply() {
    let tmp = tempfile::tempdir().unwrap();
    let mut s = SessionBuilder::new(7);
    s.rplidar_revolutions(5, 60);
    let session = s.record(&tmp.path().join("data"), "pi");
    let out = tmp.path().join("replay");
    let printed = run_cli(&["replay", arg(&session), "--out", arg(&out)]).unwrap();
    assert!(
        printed.contains("rplidar: 5 revolutions, 300 samples"),
        "{printed}"
    );
    let bt = read(&out.join("map.bt"));
    assert!(
        bt.starts_with(b"# Octomap OcTree binary file\n"),
        "OctoMap's header"
    );
    let text = String::from_utf8_lossy(&bt);
    assert!(
        text.contains("\nid OcTree\n") && text.contains("\nsize 0\n") && text.ends_with("data\n"),
        "{text}"
    );
    assert_eq!(
        Octree::read(&bt, SensorModel::default())
            .unwrap()
            .num_nodes(),
        0
    );
    let ot = read(&out.join("map.ot"));
    assert_eq!(
        Octree::read(&ot, SensorModel::default())
            .unwrap()
            .num_nodes(),
        0
    );
    let cloud = io::load(&out.join("cloud.ply"), None).unwrap();
    assert_eq!(cloud.iter().map(|s| s.points.len()).sum::<usize>(), 0);
    assert!(
        read(&out.join("cloud.ply"))
            .windows(16)
            .any(|w| w == b"element vertex 0")
    );
    // The 2D revolutions are written as `scan3d replay --out` always wrote them: the collector
    // over every recorded frame.
    let mut collector = RevolutionCollector::new();
    for recorded in read_session(&session).unwrap() {
        collector.on_frame(&recorded.frame);
    }
    let expected = collector
        .write_ply_files(&tmp.path().join("expected"))
        .unwrap();
    assert_eq!(expected.len(), 1);
    assert!(read(&out.join("scans/rplidar.ply")) == read(&expected[0]));
    assert!(
        printed.contains("wrote") && printed.contains("rplidar.ply"),
        "{printed}"
    );
}

#[test]
fn a_reference_of_another_resolution_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let session = two_position_session().record(&tmp.path().join("data"), "pi");
    let reference = tmp.path().join("ref.bt");
    run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.2",
        "--quiet",
        "--out",
        arg(&reference),
    ])
    .unwrap();
    let settings = PipelineSettings {
        resolution_m: 0.1,
        reference: Some(reference.clone()),
        ..PipelineSettings::default()
    };
    let err = SessionPipeline::new(&settings).unwrap_err();
    assert!(
        matches!(err, PipelineError::ReferenceResolution { found, expected, .. } if found == 0.2 && expected == 0.1),
        "{err:?}"
    );
    let line = err.to_string();
    assert!(
        line.contains("ref.bt") && line.contains("0.2 m") && line.contains("0.1 m"),
        "{line}"
    );
    let missing = PipelineSettings {
        reference: Some(tmp.path().join("nope.bt")),
        ..settings
    };
    let err = SessionPipeline::new(&missing).unwrap_err();
    assert!(err.to_string().contains("nope.bt"), "{err}");
}

#[test]
fn a_gap_and_an_undecodable_frame_are_skipped_and_counted_and_the_rest_is_mapped() {
    let tmp = tempfile::tempdir().unwrap();
    let mut s = SessionBuilder::new(9);
    s.rplidar_revolutions(2, 60);
    s.skip_seqs(3);
    s.undecodable();
    s.static_scan(&position("door", 1.0, 1.0, 0.0), 20, 120);
    s.undecodable();
    let session = s.record(&tmp.path().join("data"), "pi");
    let settings = PipelineSettings {
        resolution_m: 0.1,
        ..PipelineSettings::default()
    };
    let printed = run_cli(&["replay", arg(&session)]).unwrap();
    assert!(
        printed
            .contains("skipped: 3 frames missing from the session, 2 undecodable, 0 out of order"),
        "{printed}"
    );
    let (mut pipeline, report) = run_session(&session, &settings, MAP_ONLY, false).unwrap();
    assert_eq!(report.undecodable_frames, 2);
    let status = pipeline.status();
    assert_eq!(
        (
            status.missing_frames,
            status.undecodable_frames,
            status.stale_frames
        ),
        (3, 2, 0)
    );
    assert_eq!(status.frames, s.frames().count() as u64);
    assert!(
        status.points > 1000,
        "the static scan after the gap is mapped: {}",
        status.points
    );
    // The same frames fed in memory give the same map.
    let mut direct = SessionPipeline::with_products(&settings, MAP_ONLY).unwrap();
    for frame in s.frames() {
        direct.on_frame(frame);
    }
    assert!(
        direct.maps().session_map().to_octree().to_bt_bytes()
            == pipeline.maps().session_map().to_octree().to_bt_bytes()
    );
    // A frame whose seq was already passed (a late resend) is skipped, not mapped twice.
    let before = direct.status().points;
    let again = s.frames().nth(10).unwrap().clone();
    direct.on_frame(&again);
    let status = direct.status();
    assert_eq!((status.stale_frames, status.points), (1, before));
}

#[test]
fn metrics_come_at_most_once_a_second_and_a_snapshot_scores_like_scan3d_eval() {
    let tmp = tempfile::tempdir().unwrap();
    let session = two_position_session().record(&tmp.path().join("data"), "pi");
    let reference = tmp.path().join("ref.bt");
    run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.1",
        "--quiet",
        "--out",
        arg(&reference),
    ])
    .unwrap();
    let settings = PipelineSettings {
        resolution_m: 0.1,
        reference: Some(reference.clone()),
        ..PipelineSettings::default()
    };
    let s = two_position_session();
    let frames: Vec<_> = s.frames().cloned().collect();
    let half = frames.len() / 2;
    let mut pipeline = SessionPipeline::new(&settings).unwrap();
    let t0 = Instant::now();
    assert_eq!(pipeline.status_at(t0).metrics, None, "no map, no metrics");
    for f in &frames[..half] {
        pipeline.on_frame(f);
    }
    let first = pipeline.status_at(t0 + Duration::from_millis(1));
    let m1 = first.metrics.clone().expect("metrics once there is a map");
    assert!(first.occupied_voxels > 0 && first.free_voxels > 0);
    for f in &frames[half..] {
        pipeline.on_frame(f);
    }
    let soon = pipeline.status_at(t0 + Duration::from_millis(500));
    assert_eq!(
        soon.metrics.as_ref(),
        Some(&m1),
        "not recomputed within a second"
    );
    assert!(soon.points > first.points);
    let later = pipeline.status_at(t0 + Duration::from_millis(1001));
    let m2 = later.metrics.clone().unwrap();
    assert_ne!(m2, m1);
    assert_eq!(
        m2.iou.occupied,
        Some(1.0),
        "the whole session is the reference itself"
    );

    let snap = pipeline
        .write_snapshot(&tmp.path().join("snap"), None)
        .unwrap();
    let names: Vec<_> = snap
        .files
        .iter()
        .map(|p| p.file_name().unwrap().to_str().unwrap().to_string())
        .collect();
    assert_eq!(
        names,
        [
            "map.bt",
            "map.ot",
            "cloud.ply",
            "metrics.json",
            "metrics.txt",
            "trajectory.tum",
            "grid.pgm",
            "grid.yaml",
            "grid.png",
            "trajectory_fused.tum",
            "yaw_sources.csv"
        ]
    );
    let eval = run_cli(&[
        "eval",
        "--reference",
        arg(&reference),
        arg(&snap.files[0]),
        "--json",
    ])
    .unwrap();
    let expected: serde_json::Value = serde_json::from_str(&eval).unwrap();
    let written: serde_json::Value = serde_json::from_slice(&read(&snap.files[3])).unwrap();
    assert_eq!(
        written, expected,
        "metrics.json = scan3d eval --reference REF map.bt --json"
    );
    // Through text both ways: serde_json's parser may round the last bit differently.
    let returned = serde_json::to_string(&snap.metrics.unwrap()).unwrap();
    assert_eq!(
        serde_json::from_str::<serde_json::Value>(&returned).unwrap(),
        expected
    );
}

#[test]
fn an_unwritable_snapshot_directory_is_an_error_naming_it() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let mut pipeline = SessionPipeline::new(&PipelineSettings::default()).unwrap();
    let err = pipeline
        .write_snapshot(&file.join("sub"), None)
        .unwrap_err();
    assert!(matches!(err, PipelineError::Write { .. }), "{err:?}");
    assert!(err.to_string().contains("a-file"), "{err}");
}

#[test]
fn the_map_command_refuses_whole_cloud_filters_on_a_session() {
    let tmp = tempfile::tempdir().unwrap();
    let session = two_position_session().record(&tmp.path().join("data"), "pi");
    let err = run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.1",
        "--filter",
        "sor:8,1.0",
        "--out",
        arg(&tmp.path().join("x.bt")),
    ])
    .unwrap_err();
    assert!(format!("{err:#}").contains("sor:8,1"), "{err:#}");
}

#[test]
fn snapshot_filters_touch_the_written_cloud_only() {
    let s = two_position_session();
    let sor: scan3d_map::cloud::filter::Filter = "sor:8,0.5".parse().unwrap();
    let base = PipelineSettings {
        resolution_m: 0.1,
        ..PipelineSettings::default()
    };
    let filtered = PipelineSettings {
        snapshot_filters: vec![sor.clone()],
        ..base.clone()
    };
    let tmp = tempfile::tempdir().unwrap();
    let mut plain = SessionPipeline::new(&base).unwrap();
    let mut smooth = SessionPipeline::new(&filtered).unwrap();
    for f in s.frames() {
        plain.on_frame(f);
        smooth.on_frame(f);
    }
    let a = plain.write_snapshot(&tmp.path().join("a"), None).unwrap();
    let b = smooth.write_snapshot(&tmp.path().join("b"), None).unwrap();
    assert!(
        read(&a.files[0]) == read(&b.files[0]),
        "the octree is not filtered"
    );
    assert!(
        b.points < a.points,
        "SOR removed points: {} of {}",
        b.points,
        a.points
    );
    let expected = sor.apply(&plain.maps().cloud(None)).unwrap();
    let mut ply = Vec::new();
    scan3d_map::cloud::ply::write_ply_bundles(&mut ply, &expected, io::Encoding::Binary).unwrap();
    assert!(
        read(&b.files[2]) == ply,
        "cloud.ply is the cloud through the snapshot filters"
    );
}

/// A stage that counts the rays handed to it.
struct CountRays(std::sync::Arc<std::sync::atomic::AtomicU64>);

impl scan3d_server::pipeline::Stage for CountRays {
    fn on_frame(
        &mut self,
        ctx: &mut scan3d_server::pipeline::StageContext,
        _frame: &scan3d_protocol::Frame,
    ) {
        let n: usize = ctx.rays.iter().map(|r| r.rays.points.len()).sum();
        self.0
            .fetch_add(n as u64, std::sync::atomic::Ordering::Relaxed);
    }
}

#[test]
fn an_added_stage_sees_every_filtered_origin_group() {
    let count = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let settings = PipelineSettings {
        resolution_m: 0.1,
        revolution_filters: vec!["voxel:0.2".parse().unwrap()],
        ..PipelineSettings::default()
    };
    let mut pipeline = SessionPipeline::new(&settings).unwrap();
    pipeline.add_stage(Box::new(CountRays(count.clone())));
    for f in two_position_session().frames() {
        pipeline.on_frame(f);
    }
    let status = pipeline.status();
    assert!(status.points > 0);
    assert_eq!(
        count.load(std::sync::atomic::Ordering::Relaxed),
        status.points
    );
    let mut unfiltered = SessionPipeline::new(&PipelineSettings {
        revolution_filters: vec![],
        ..settings
    })
    .unwrap();
    for f in two_position_session().frames() {
        unfiltered.on_frame(f);
    }
    assert!(
        status.points < unfiltered.status().points,
        "the voxel grid thins each revolution"
    );
}

#[test]
fn mapping_a_damaged_session_fails_unless_lenient_and_then_maps_the_readable_rest() {
    let tmp = tempfile::tempdir().unwrap();
    // Six static scans in about four chunks: a damaged chunk loses part of them.
    let mut s = SessionBuilder::new(0xda);
    for i in 0..6 {
        s.static_scan(&position("door", 1.0 + 0.3 * i as f64, 1.0, 0.0), 20, 120);
    }
    let session = s.record(&tmp.path().join("data"), "pi");
    let clean = tmp.path().join("clean.bt");
    run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.1",
        "--quiet",
        "--out",
        arg(&clean),
    ])
    .unwrap();
    // One flipped bit in the middle of the second chunk breaks its CRC.
    let chunks = break_chunk(&session.join("0000.mcap"), 1);
    assert!(chunks >= 3, "{chunks} chunks");
    let out = tmp.path().join("damaged.bt");
    let err = run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.1",
        "--out",
        arg(&out),
    ])
    .unwrap_err();
    let line = format!("{err:#}");
    assert!(
        line.contains("recording damaged") && line.contains("--lenient"),
        "{line}"
    );
    assert!(
        !out.exists(),
        "nothing written from a damaged recording without --lenient"
    );
    let printed = run_cli(&[
        "map",
        arg(&session),
        "--resolution",
        "0.1",
        "--lenient",
        "--out",
        arg(&out),
    ])
    .unwrap();
    assert!(
        printed.contains("frames missing from the session"),
        "{printed}"
    );
    let (damaged, clean) = (read(&out), read(&clean));
    assert!(damaged != clean, "the lost frames are missing from the map");
    assert!(
        Octree::read(&damaged, SensorModel::default())
            .unwrap()
            .num_occupied()
            > 0
    );
}

/// A head standing 10 revolutions, then a pass started where it stands, then 30 revolutions of
/// motion; returns the session and the true poses at the revolutions' middles.
fn trolley_session() -> (SessionBuilder, Vec<[f64; 3]>) {
    let mut s = SessionBuilder::in_room(0x7011, DEMO_ROOM);
    let start = [2.5, 2.0, 0.3];
    let mut truth = s.rplidar_moving(10, 360, start, [0.0; 3]);
    s.push(scan3d_protocol::PassMarker {
        t_ns: s.now_ns(),
        event: scan3d_protocol::PassEvent::Started {
            name: "aisle 1".into(),
            x_m: start[0],
            y_m: start[1],
            heading_deg: start[2].to_degrees(),
        },
    });
    truth.extend(s.rplidar_moving(30, 360, start, [0.3, 0.1, 0.2]));
    s.push(scan3d_protocol::PassMarker {
        t_ns: s.now_ns(),
        event: scan3d_protocol::PassEvent::Stopped {
            name: "aisle 1".into(),
        },
    });
    (s, truth)
}

#[test]
fn the_live_pose_stage_gives_the_poses_of_scan3d_slam_and_a_pass_anchors_them_in_the_room() {
    let (session, truth) = trolley_session();
    let tmp = tempfile::tempdir().unwrap();
    let dir = session.record(tmp.path(), "trolley");
    let (mut pipeline, _) = run_session(
        &dir,
        &PipelineSettings::default(),
        Products::default(),
        false,
    )
    .unwrap();
    let stage = pipeline
        .pose()
        .expect("the live daemon's products have the pose stage");
    let (offline, _) = scan3d_server::pose::scan_matching::map_session(
        &dir,
        &scan3d_slam::mapper::MapperConfig::default(),
        &scan3d_server::pipeline::pose_stage::POSE_RANGE_LIMITS,
        None,
        false,
        |_| {},
    )
    .unwrap();
    assert_eq!(stage.poses().len(), 40);
    let live: Vec<_> = stage.poses().iter().map(|p| p.pose).collect();
    let off: Vec<_> = offline.trajectory.poses.iter().map(|p| p.pose).collect();
    assert_eq!(live, off, "the same poses live and offline");
    assert_eq!(stage.passes(), ["aisle 1"]);

    let status = pipeline.status().pose.expect("a pose");
    let [x, y, heading] = *truth.last().unwrap();
    assert!(status.anchored);
    assert!(
        (status.x - x).hypot(status.y - y) < 0.05,
        "{status:?} against ({x}, {y})"
    );
    assert!(
        (status.yaw_deg - heading.to_degrees()).abs() < 1.0,
        "{status:?}"
    );
    assert!(
        (status.path_m - 30.0 * 0.18 * 0.3f64.hypot(0.1)).abs() < 0.1,
        "{status:?}"
    );
    assert!(status.covariance[0] > 0.0 && status.covariance[8] > 0.0);

    let snap = pipeline
        .write_snapshot(&tmp.path().join("snap"), None)
        .unwrap();
    let tum = std::fs::read_to_string(tmp.path().join("snap/trajectory.tum")).unwrap();
    let rows: Vec<Vec<f64>> = tum
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(' ').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 40);
    assert!(rows.iter().all(|r| r.len() == 8));
    // The standing poses, before the pass, are carried into the room frame too.
    assert!(
        (rows[0][1] - 2.5).abs() < 0.03 && (rows[0][2] - 2.0).abs() < 0.03,
        "{:?}",
        rows[0]
    );
    let pass =
        std::fs::read_to_string(tmp.path().join("snap/passes/aisle_1/trajectory.tum")).unwrap();
    assert_eq!(pass.lines().filter(|l| !l.starts_with('#')).count(), 30);
    for name in ["grid.pgm", "grid.yaml", "grid.png"] {
        assert!(snap.files.iter().any(|f| f.ends_with(name)), "{name}");
    }
}
