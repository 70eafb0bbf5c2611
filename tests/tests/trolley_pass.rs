//! A trolley pass with the real binaries: `scan3d serve` + `scan3d-sim rig --trolley` (a short
//! path) + the real `scan3d-edge`, then `scan3d trolley start` / `stop`. The session records the
//! edge's sensor mounts (`Body::Mounts`, once, after its `Hello`) and both pass markers
//! (`Body::Pass`) at increasing edge times; a second start while the pass runs and a stop
//! with none running are refused by the edge with one line and a non-zero exit. (The server's
//! own refusal of an edge without RPLidar is `ingest::control::pass_refusal`, tested there:
//! the rig always has one.)
//!
//! Run alone (`cargo test -p scan3d-tests --test trolley_pass`) it builds the binaries first.

use std::time::Duration;

use scan3d_protocol::{Body, PassEvent, SensorId};
use scan3d_server::recording::{read_session_report, session_dir};
use scan3d_tests::operator::{OperatorRig, text, wait_until};

/// Generous: the machine may be busy with other tests.
const DEADLINE: Duration = Duration::from_secs(90);

const EDGE: &str = "edge-trolley-01";

/// One short leg along the room's south side after 2 s at rest.
const PATH: &str = "rest_s = 2.0\nstart = [1.6, 0.85]\n\n[[waypoint]]\nx = 3.0\ny = 0.85\n";

#[test]
fn a_trolley_pass_is_recorded_with_the_mounts_and_both_markers_at_edge_times() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("path.toml");
    std::fs::write(&path, PATH).expect("path.toml");
    let path = path.to_str().expect("utf-8 path").to_owned();
    let rig = OperatorRig::start_with_rig_args(dir.path(), EDGE, &["--trolley", &path]);

    // The RPLidar streaming (its Hello lists it, so the server lets a pass start).
    wait_until("the edge's RPLidar to stream", DEADLINE, || {
        let out = rig.scan3d(&["status", "--json"]);
        let Ok(status) = serde_json::from_slice::<serde_json::Value>(&out.stdout) else {
            return false;
        };
        status["edges"]
            .as_array()
            .into_iter()
            .flatten()
            .flat_map(|edge| edge["sensors"].as_array().cloned().unwrap_or_default())
            .any(|sensor| sensor["kind"] == "rplidar" && sensor["state"] == "streaming")
    });

    let trolley = |args: &[&str]| {
        let mut all = vec!["trolley"];
        all.extend_from_slice(args);
        rig.scan3d(&all)
    };
    let out = trolley(&["start", "--edge", EDGE, "--at", "1.6,0.85,0", "--json"]);
    assert!(
        out.status.success(),
        "trolley start: {}{}\nedge log:\n{}",
        text(&out.stdout),
        text(&out.stderr),
        rig.edge_log()
    );
    let reply: serde_json::Value = serde_json::from_slice(&out.stdout).expect("start --json");
    assert_eq!(reply["state"], "accepted", "{reply}");
    assert_eq!(
        reply["pass"]["event"]["Started"]["name"], "pass-1",
        "{reply}"
    );
    let session = u64::from_str_radix(reply["session"].as_str().expect("session"), 16)
        .expect("a hex session id");

    // A second start while it runs: the edge refuses, one line, non-zero.
    let out = trolley(&["start", "--edge", EDGE, "--at", "0,0,0"]);
    assert!(!out.status.success(), "a second start was accepted");
    let stderr = text(&out.stderr);
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(stderr.contains("a pass is already running"), "{stderr}");

    // Stop once the edge has streamed revolutions after the start: wait for the recording to
    // hold an RPLidar revolution that began after the start marker.
    let dir_of_session = session_dir(&rig.path("data"), EDGE, session);
    let started_ns = |frames: &[scan3d_server::recording::RecordedFrame]| {
        frames.iter().find_map(|f| match &f.frame.body {
            Body::Pass(marker) if matches!(marker.event, PassEvent::Started { .. }) => {
                Some(marker.t_ns)
            }
            _ => None,
        })
    };
    wait_until("revolutions after the pass started", DEADLINE, || {
        let Ok((frames, _)) = read_session_report(&dir_of_session) else {
            return false;
        };
        // An RPLidar and a whole Sweep revolution after the start: the live moving stage
        // then has samples of the pass to place.
        started_ns(&frames).is_some_and(|t| {
            [SensorId::RPLIDAR, SensorId::SWEEP].iter().all(|&sensor| {
                frames.iter().any(|f| {
                    matches!(&f.frame.body, Body::Revolution(rev)
                        if rev.sensor == sensor && rev.t0_ns > t)
                })
            })
        })
    });
    let out = trolley(&["stop", "--edge", EDGE]);
    assert!(
        out.status.success(),
        "trolley stop: {}{}",
        text(&out.stdout),
        text(&out.stderr)
    );
    assert!(
        text(&out.stdout).starts_with(&format!("edge {EDGE} stopped pass \"pass-1\"")),
        "{}",
        text(&out.stdout)
    );
    let out = trolley(&["stop", "--edge", EDGE]);
    assert!(!out.status.success(), "a stop with no pass was accepted");
    let stderr = text(&out.stderr);
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(stderr.contains("no pass is running"), "{stderr}");

    // The recording: the mounts once, right after the first Hello, and both markers in order.
    let mut recorded = None;
    wait_until("both pass markers in the recording", DEADLINE, || {
        let Ok((frames, _)) = read_session_report(&dir_of_session) else {
            return false;
        };
        let markers = frames
            .iter()
            .filter(|f| matches!(f.frame.body, Body::Pass(_)))
            .count();
        let done = markers >= 2;
        recorded = Some(frames);
        done
    });
    let frames = recorded.expect("frames");
    let mounts: Vec<_> = frames
        .iter()
        .filter_map(|f| match &f.frame.body {
            Body::Mounts(mounts) => Some((f.frame.seq, mounts.clone())),
            _ => None,
        })
        .collect();
    assert_eq!(mounts.len(), 1, "the mounts once per session: {mounts:?}");
    let (mounts_seq, mounts) = &mounts[0];
    let first_hello = frames
        .iter()
        .find(|f| matches!(f.frame.body, Body::Hello(_)))
        .map(|f| f.frame.seq)
        .expect("a Hello");
    assert_eq!(
        *mounts_seq,
        first_hello + 1,
        "the mounts right after the Hello"
    );
    assert_eq!(mounts.validate(), Ok(()));
    // The trolley's RPLidar: 0.2 m ahead, 0.4 m up, level (docs/simulator.md).
    let rplidar = mounts.get(SensorId::RPLIDAR).expect("the RPLidar's mount");
    assert_eq!(
        (rplidar.x_m, rplidar.y_m, rplidar.z_m, rplidar.yaw_deg),
        (0.2, 0.0, 0.4, 0.0)
    );
    assert!(mounts.get(SensorId::SWEEP).is_some() && mounts.get(SensorId::IMU).is_some());

    let markers: Vec<_> = frames
        .iter()
        .filter_map(|f| match &f.frame.body {
            Body::Pass(marker) => Some(marker.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(markers.len(), 2, "{markers:?}");
    assert_eq!(
        markers[0].event,
        PassEvent::Started {
            name: "pass-1".into(),
            x_m: 1.6,
            y_m: 0.85,
            heading_deg: 0.0
        }
    );
    assert_eq!(
        markers[1].event,
        PassEvent::Stopped {
            name: "pass-1".into()
        }
    );
    assert!(
        markers[0].t_ns < markers[1].t_ns,
        "edge times must increase: {markers:?}"
    );

    // The live daemon placed the pass's Sweep samples along the trajectory (the moving stage
    // after the poses) and timed its poses.
    let session_id = format!("{session:016x}");
    let mut last = serde_json::Value::Null;
    wait_until("the pass's points in the live status", DEADLINE, || {
        let out = rig.scan3d(&["status", "--json"]);
        let Ok(status) = serde_json::from_slice::<serde_json::Value>(&out.stdout) else {
            return false;
        };
        let found = status["edges"]
            .as_array()
            .into_iter()
            .flatten()
            .flat_map(|edge| edge["sessions"].as_array().cloned().unwrap_or_default())
            .find(|s| s["id"] == session_id.as_str());
        let Some(found) = found else { return false };
        last = found.clone();
        found["passes"].as_array().is_some_and(|passes| {
            passes.iter().any(|p| {
                p["name"] == "pass-1" && p["stopped"] == true && p["points"].as_u64() > Some(0)
            })
        })
    });
    let latency = &last["revolution_to_pose"];
    assert!(
        latency["count"].as_u64() > Some(0) && latency["p50_ms"].as_f64().is_some(),
        "no revolution-to-pose latency in the status: {last}"
    );
    let snapshot = dir.path().join("snapshot");
    let out = rig.scan3d(&[
        "snapshot",
        "--edge",
        EDGE,
        "--session",
        &session_id,
        "--out",
        snapshot.to_str().expect("utf-8 path"),
    ]);
    assert!(
        out.status.success(),
        "snapshot: {}{}",
        text(&out.stdout),
        text(&out.stderr)
    );
    let pass_dir = snapshot.join("passes").join("pass-1");
    let ply = std::fs::read(pass_dir.join("cloud.ply")).expect("passes/pass-1/cloud.ply");
    assert!(ply.starts_with(b"ply\n"), "not a PLY file");
    let bt = std::fs::read(pass_dir.join("map.bt")).expect("passes/pass-1/map.bt");
    assert!(
        bt.starts_with(b"# Octomap OcTree binary file"),
        "not a .bt file"
    );
    assert!(
        pass_dir.join("trajectory.tum").exists(),
        "no trajectory.tum"
    );
}
