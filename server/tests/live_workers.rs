//! The live driver's session workers (`scan3d serve`'s `LivePipelines`, fed as ingest feeds it):
//! an idle worker is retired (its products on disk, `snapshot` serves them byte for byte,
//! `status` marks the session retired) and a later frame rebuilds it from the recording;
//! `status` answers while a large snapshot is being written, and the snapshot's bytes are those
//! of the same pipeline written in one go.

mod pipeline_support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use pipeline_support::{DEMO_ROOM, SessionBuilder, position};
use scan3d_protocol::Frame;
use scan3d_server::ingest::server::IngestEvent;
use scan3d_server::pipeline::live::{LivePipelines, LiveSessionStatus, LiveSettings};
use scan3d_server::pipeline::{PipelineSettings, SessionPipeline};

const EDGE: &str = "pi-live";

/// Every file under `dir`, by path relative to it.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(at) = dirs.pop() {
        for entry in std::fs::read_dir(&at).unwrap_or_else(|e| panic!("{}: {e}", at.display())) {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                out.insert(path.strip_prefix(dir).unwrap().to_path_buf(), bytes);
            }
        }
    }
    out
}

/// The files a pipeline fed `frames` in order writes as its snapshot (of `position`).
fn expected(
    settings: &PipelineSettings,
    frames: &[Frame],
    dir: &Path,
    position: Option<&str>,
) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut pipeline = SessionPipeline::new(settings).unwrap();
    for frame in frames {
        pipeline.on_frame(frame);
    }
    pipeline.write_snapshot(dir, position).unwrap();
    files(dir)
}

fn feed(live: &LivePipelines, frames: &[Frame]) {
    for frame in frames {
        live.on_event(IngestEvent::Frame {
            edge: EDGE.into(),
            frame: frame.clone(),
        });
    }
}

/// The status line of the edge's only session.
fn session_status(live: &LivePipelines) -> Option<LiveSessionStatus> {
    let edge = live.status().edges.into_iter().find(|e| e.name == EDGE)?;
    edge.sessions.into_iter().next()
}

/// Waits (at most a minute) until `done`.
fn wait_for(what: &str, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while !done() {
        assert!(Instant::now() < deadline, "timed out waiting until {what}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn an_idle_session_is_retired_served_from_disk_and_revived_by_a_later_frame() {
    let data = tempfile::tempdir().unwrap();
    let mut s = SessionBuilder::new(0x7e71);
    s.rplidar_revolutions(3, 90);
    s.static_scan(&position("door", 1.0, 1.0, 0.0), 20, 120);
    s.rplidar_revolutions(2, 90);
    let split = s.frames().count();
    s.static_scan(&position("window", 3.0, 2.0, 45.0), 20, 120);
    s.record(data.path(), EDGE);
    let frames: Vec<Frame> = s.frames().cloned().collect();
    let (before, after) = frames.split_at(split);

    let mut settings = LiveSettings::new(PipelineSettings::default(), data.path().to_path_buf());
    settings.retire_after = Some(Duration::from_millis(300));
    settings.catch_up_retry = Duration::from_millis(10);
    let live = LivePipelines::new(settings.clone()).unwrap();
    feed(&live, before);
    wait_for("the idle session is retired", || {
        session_status(&live).is_some_and(|s| s.retired)
    });
    let status = session_status(&live).unwrap();
    assert_eq!(status.pipeline.frames, split as u64, "its last status");
    assert_eq!(status.pipeline.positions, ["door"]);
    let retired_dir = data
        .path()
        .join("retired")
        .join(EDGE)
        .join(format!("{:016x}", s.session_id));
    assert!(retired_dir.join("map.bt").is_file(), "products on disk");

    let out = tempfile::tempdir().unwrap();
    let want = expected(&settings.pipeline, before, &out.path().join("want"), None);
    let (id, snapshot) = live
        .snapshot(EDGE, None, None, &out.path().join("retired"))
        .unwrap();
    assert_eq!(id, s.session_id);
    assert_eq!(files(&out.path().join("retired")), want, "served from disk");
    assert_eq!(
        snapshot.files.len(),
        want.len(),
        "the snapshot lists the files"
    );
    let want_door = expected(
        &settings.pipeline,
        before,
        &out.path().join("want-door"),
        Some("door"),
    );
    live.snapshot(EDGE, None, Some("door"), &out.path().join("door"))
        .unwrap();
    assert_eq!(files(&out.path().join("door")), want_door);
    let unknown = live
        .snapshot(EDGE, None, Some("window"), &out.path().join("x"))
        .unwrap_err();
    assert!(unknown.to_string().contains("door"), "{unknown}");

    // The session goes on: its pipeline is rebuilt from the recording and takes the new frames.
    feed(&live, after);
    wait_for("the revived session has every frame", || {
        session_status(&live)
            .is_some_and(|s| s.pipeline.frames == frames.len() as u64 && s.lag_frames == 0)
    });
    let want_all = expected(
        &settings.pipeline,
        &frames,
        &out.path().join("want-all"),
        None,
    );
    assert_ne!(want_all, want, "the later frames add to the products");
    live.snapshot(EDGE, None, None, &out.path().join("revived"))
        .unwrap();
    assert_eq!(files(&out.path().join("revived")), want_all);
    live.shutdown();
}

#[test]
fn status_answers_while_a_large_snapshot_is_written_and_the_bytes_are_unchanged() {
    let data = tempfile::tempdir().unwrap();
    let mut s = SessionBuilder::in_room(0xb16, DEMO_ROOM);
    for (name, x, y) in [("sw", 1.2, 1.2), ("se", 6.6, 1.6), ("ne", 6.6, 4.2)] {
        s.static_scan(&position(name, x, y, 0.0), 60, 400);
    }
    let frames: Vec<Frame> = s.frames().cloned().collect();
    let pipeline = PipelineSettings {
        // Statistical outlier removal over the whole cloud: the snapshot's heavy part.
        snapshot_filters: vec!["sor:16,1.0".parse().unwrap()],
        ..PipelineSettings::default()
    };
    let mut settings = LiveSettings::new(pipeline, data.path().to_path_buf());
    settings.retire_after = None;
    settings.queue_frames = frames.len();
    let live = LivePipelines::new(settings.clone()).unwrap();
    feed(&live, &frames);
    wait_for("every frame is processed", || {
        session_status(&live)
            .is_some_and(|s| s.pipeline.frames == frames.len() as u64 && s.lag_frames == 0)
    });

    let out = tempfile::tempdir().unwrap();
    let snapshot_dir = out.path().join("live");
    let writer = {
        let live = live.clone();
        let dir = snapshot_dir.clone();
        std::thread::spawn(move || live.snapshot(EDGE, None, None, &dir))
    };
    let mut answered_while_writing = 0;
    let mut slowest = Duration::ZERO;
    while !writer.is_finished() {
        let asked = Instant::now();
        let status = session_status(&live).expect("the session's line");
        slowest = slowest.max(asked.elapsed());
        assert_eq!(status.pipeline.frames, frames.len() as u64);
        if !writer.is_finished() {
            answered_while_writing += 1;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    writer.join().unwrap().unwrap();
    assert!(
        answered_while_writing >= 5,
        "status answered {answered_while_writing} times while the snapshot was written"
    );
    assert!(
        slowest < Duration::from_secs(5),
        "a status took {slowest:?}"
    );
    let want = expected(&settings.pipeline, &frames, &out.path().join("want"), None);
    assert_eq!(files(&snapshot_dir), want);
    live.shutdown();
}
