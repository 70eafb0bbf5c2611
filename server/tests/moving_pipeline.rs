//! Assembly along movement as a live pipeline stage (issue 21, part 3): the pose lane hands its
//! poses to the assembly lane, the moving stage places each pass's Sweep samples with the pose
//! at their own time; a live snapshot's `passes/NAME/cloud.ply` and `map.bt` are the bytes
//! `scan3d assemble --moving --pass NAME` writes from the recording.

mod pipeline_support;
mod trolley_support;

use std::path::Path;

use pipeline_support::{SessionBuilder, position};
use scan3d_protocol::{Body, Frame, Hello, SensorId, SensorInfo};
use scan3d_server::pipeline::{PipelineSettings, SessionPipeline};
use trolley_support::{SWEEP_SAMPLES, Trolley, scan3d, to_surface, trolley_session};

/// A live daemon's pipeline fed `frames` one by one (no flush: a live session goes on).
fn live(frames: impl IntoIterator<Item = Frame>) -> SessionPipeline {
    let mut pipeline = SessionPipeline::new(&PipelineSettings::default()).unwrap();
    for frame in frames {
        pipeline.on_frame(&frame);
    }
    pipeline
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn a_live_pass_snapshot_is_the_bytes_assemble_moving_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let session = trolley_session(Trolley::default());
    let dir = session.record(tmp.path(), "trolley");

    let mut pipeline = live(session.frames().cloned());
    let status = pipeline.status();
    let pass = status
        .passes
        .iter()
        .find(|p| p.name == "aisle")
        .expect("the pass in status");
    // 16 revolutions in the pass, all placed while the session goes on (the poses after the
    // stop covered the last one): none held, none dropped, no sample extrapolated or lost.
    assert_eq!(
        (pass.revolutions, pass.held, pass.dropped, pass.stopped),
        (16, 0, 0, true),
        "{pass:?}"
    );
    assert_eq!(pass.unplaced_samples, 0, "{pass:?}");
    assert_eq!(pass.samples, 16 * SWEEP_SAMPLES as u64, "{pass:?}");
    assert_eq!(pass.points, pass.samples, "no filter configured: {pass:?}");
    let json = serde_json::to_value(&status).unwrap();
    assert_eq!(json["passes"][0]["name"], "aisle", "{json}");
    assert_eq!(json["passes"][0]["revolutions"], 16, "{json}");
    // The standing revolutions outside the pass are not placed: the session's map has only
    // the pass's points (no static scan here).
    assert_eq!(status.points, pass.points);

    let snap = tmp.path().join("snap");
    pipeline.write_snapshot(&snap, None).unwrap();
    let live_ply = read(&snap.join("passes/aisle/cloud.ply"));
    let live_bt = read(&snap.join("passes/aisle/map.bt"));
    assert!(snap.join("passes/aisle/trajectory.tum").exists());

    let ply = tmp.path().join("aisle.ply");
    let bt = tmp.path().join("aisle.bt");
    let said = scan3d(&[
        "assemble",
        "--moving",
        dir.to_str().unwrap(),
        "--pass",
        "aisle",
        "--out",
        ply.to_str().unwrap(),
        "--bt",
        bt.to_str().unwrap(),
    ])
    .expect("the pass assembles");
    assert!(said.contains("16 Sweep revolutions placed"), "{said}");
    assert!(read(&ply) == live_ply, "cloud.ply differs live and offline");
    assert!(read(&bt) == live_bt, "map.bt differs live and offline");

    let cloud = scan3d_map::cloud::io::load(&ply, None).unwrap();
    let points: Vec<[f64; 3]> = cloud
        .iter()
        .flat_map(|b| b.points.iter().map(|p| p.map(f64::from)))
        .collect();
    assert_eq!(points.len(), 16 * SWEEP_SAMPLES);
    let mean = points.iter().map(|&p| to_surface(p)).sum::<f64>() / points.len() as f64;
    eprintln!("live pass: mean point-to-surface {:.2} cm", mean * 100.0);
    assert!(mean < 0.03, "mean point-to-surface {mean} m");
    let tree = scan3d_map::octree::Octree::read(&live_bt, Default::default()).unwrap();
    assert!(tree.num_occupied() > 100 && tree.num_free() > 100);
}

#[test]
fn a_sweep_revolution_waits_for_the_poses_that_cover_it() {
    let session = trolley_session(Trolley {
        after: 0,
        ..Trolley::default()
    });
    let frames: Vec<Frame> = session.frames().cloned().collect();
    let mut pipeline = SessionPipeline::new(&PipelineSettings::default()).unwrap();
    let mut waited = 0;
    let mut i = 0;
    while i < frames.len() {
        pipeline.on_frame(&frames[i]);
        let placed = pipeline.passes().first().map_or(0, |p| p.revolutions);
        let is_sweep =
            matches!(&frames[i].body, Body::Revolution(r) if r.sensor == SensorId::SWEEP);
        if waited == 0 && is_sweep && placed > 0 && i + 1 < frames.len() {
            // The revolution just sent ends after the newest pose: not placed yet, and placed
            // once the next RPLidar revolution's pose comes.
            assert!(
                matches!(&frames[i + 1].body, Body::Revolution(r) if r.sensor == SensorId::RPLIDAR)
            );
            pipeline.on_frame(&frames[i + 1]);
            let after = pipeline.passes()[0].revolutions;
            assert_eq!(after, placed + 1, "placed once the next RPLidar pose came");
            waited += 1;
            i += 1;
        }
        i += 1;
    }
    assert_eq!(waited, 1);
    // The pass's last revolutions have no pose after them in this session: they wait (in the
    // lane for the Poses stream, or held by the stage) until the end, then are placed with the
    // poses there are (extrapolated at most 50 ms, the rest counted).
    let pass = &pipeline.passes()[0];
    assert!(pass.revolutions < 16, "{pass:?}");
    pipeline.flush();
    let pass = &pipeline.passes()[0];
    assert_eq!((pass.held, pass.revolutions), (0, 16), "{pass:?}");
    assert!(pass.unplaced_samples > 0, "{pass:?}");
}

#[test]
fn a_session_without_rplidar_never_waits_for_poses() {
    let mut s = SessionBuilder::new(0x0216);
    s.push(Hello::new(
        "head",
        "test",
        vec![SensorInfo {
            sensor: SensorId::SWEEP,
            model: String::new(),
            firmware: String::new(),
            serial: String::new(),
        }],
    ));
    s.static_scan(&position("p1", 2.0, 1.5, 0.0), 12, 90);
    let frames: Vec<Frame> = s.frames().cloned().collect();
    let mut pipeline = live(frames.iter().cloned());
    let status = pipeline.status();
    assert_eq!(status.stream_releases, 0, "nothing waited for: {status:?}");
    assert!(status.points > 0, "the scan is mapped as it comes");
    let through = status.points;
    pipeline.flush();
    let flushed = pipeline.status().points;
    // At most the last revolution waits for the Sweep's next one, none for poses.
    assert!(flushed - through <= 2 * 90, "{through} then {flushed}");
    assert!(pipeline.passes().is_empty());
}

#[test]
fn a_pass_stopped_without_its_start_is_ignored_and_nothing_is_lost() {
    let clean = live(trolley_session(Trolley::default()).frames().cloned());
    let stray = live(
        trolley_session(Trolley {
            stray_stop: true,
            ..Trolley::default()
        })
        .frames()
        .cloned(),
    );
    assert_eq!(stray.moving().unwrap().stray_stops(), 1);
    assert_eq!(clean.moving().unwrap().stray_stops(), 0);
    assert_eq!(stray.passes(), clean.passes());
    assert!(!stray.maps().pass_cloud("aisle").is_empty());
    assert!(stray.maps().pass_cloud("aisle") == clean.maps().pass_cloud("aisle"));
}

#[test]
fn a_prepared_snapshot_writes_the_pose_lanes_files_as_they_were_when_taken() {
    let tmp = tempfile::tempdir().unwrap();
    let frames: Vec<Frame> = trolley_session(Trolley::default())
        .frames()
        .cloned()
        .collect();
    // Into the pass: the trajectory, the pass's and the grid are there, and will change.
    let (now, later) = frames.split_at(frames.len() * 2 / 3);
    let mut pipeline = live(now.iter().cloned());
    let at_once = tmp.path().join("at-once");
    pipeline.write_snapshot(&at_once, None).unwrap();
    let prepared = pipeline
        .prepare_snapshot(&tmp.path().join("prepared"), None)
        .unwrap();
    for frame in later {
        pipeline.on_frame(frame);
    }
    let written = prepared.write().unwrap();
    let after = tmp.path().join("after");
    pipeline.write_snapshot(&after, None).unwrap();
    let files = [
        "trajectory.tum",
        "passes/aisle/trajectory.tum",
        "grid.pgm",
        "grid.yaml",
        "grid.png",
        "trajectory_fused.tum",
        "passes/aisle/trajectory_fused.tum",
        "yaw_sources.csv",
    ];
    for file in files {
        assert!(
            written.files.contains(&written.dir.join(file)),
            "{file} listed: {:?}",
            written.files
        );
        assert!(
            read(&written.dir.join(file)) == read(&at_once.join(file)),
            "{file}: the prepared snapshot's bytes are not those of the moment it was taken"
        );
    }
    for file in ["trajectory.tum", "grid.png", "trajectory_fused.tum"] {
        assert!(
            read(&after.join(file)) != read(&at_once.join(file)),
            "{file}: the later frames changed nothing, the test proves nothing"
        );
    }
}

/// The edge times of a TUM file's lines, s.
fn tum_times(path: &Path) -> Vec<f64> {
    String::from_utf8(read(path))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(' ').next().unwrap().parse().unwrap())
        .collect()
}

#[test]
fn a_start_while_a_pass_is_open_closes_it_there_in_every_stage() {
    let tmp = tempfile::tempdir().unwrap();
    let options = Trolley {
        second_start: true,
        ..Trolley::default()
    };
    let mut pipeline = live(trolley_session(options).frames().cloned());
    pipeline.flush();
    let [standing, straight, turning] = options.stretches;
    let start_of = |revolutions: usize| {
        SessionBuilder::new(0).now_ns() + (revolutions as u64) * trolley_support::REVOLUTION_NS
    };
    let (aisle_ns, turn_ns) = (start_of(standing), start_of(standing + straight));
    let pose = pipeline.pose().unwrap();
    let moving = pipeline.moving().unwrap();
    let spans = vec![
        ("aisle".to_string(), aisle_ns, Some(turn_ns)),
        ("turn".to_string(), turn_ns, None),
    ];
    assert_eq!(pose.pass_spans(), spans);
    assert_eq!(moving.pass_spans(), spans);
    // "aisle"'s own stop came after "turn" closed it: ignored.
    assert_eq!(moving.stray_stops(), 1);

    // Each Sweep sample placed once, in the pass its time is in ([start, stop)).
    let passes = pipeline.passes();
    let [aisle, turn] = [&passes[0], &passes[1]];
    assert_eq!((aisle.name.as_str(), aisle.stopped), ("aisle", true));
    assert_eq!((turn.name.as_str(), turn.stopped), ("turn", false));
    assert_eq!(
        aisle.samples,
        (straight * SWEEP_SAMPLES) as u64,
        "{aisle:?}"
    );
    let turn_samples = ((turning + options.after) * SWEEP_SAMPLES) as u64;
    assert_eq!(
        turn.samples + turn.unplaced_samples,
        turn_samples,
        "{turn:?}"
    );

    // The pose and fusion stages cut their per-pass trajectories at the same times.
    let snap = tmp.path().join("snap");
    pipeline.write_snapshot(&snap, None).unwrap();
    for (name, from, to) in [("aisle", aisle_ns, turn_ns), ("turn", turn_ns, u64::MAX)] {
        let dir = snap.join("passes").join(name);
        let matcher = tum_times(&dir.join("trajectory.tum"));
        let fused = tum_times(&dir.join("trajectory_fused.tum"));
        assert!(!matcher.is_empty());
        assert_eq!(matcher, fused, "{name}");
        let (from, to) = (from as f64 * 1e-9, to as f64 * 1e-9);
        assert!(
            matcher.iter().all(|&t| from <= t && t < to),
            "{name}: {matcher:?}"
        );
    }
}
