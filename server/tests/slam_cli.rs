//! `scan3d slam` and `scan3d slam-eval` end to end on an excerpt of the vendored Intel log:
//! the trajectory file keeps the log's timestamps byte for byte, the map files are what ROS
//! map_server reads, the metric agrees with the library, and bad input stops with its line.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use common::{arg, run_cli};

fn testdata(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata/slam")
        .join(name)
}

/// The first `scans` FLASER lines of the Intel log (and the ODOM lines among them) as a plain
/// `.clf`, and the relations with both ends inside; returns the laser timestamps as written.
fn intel_excerpt(dir: &Path, scans: usize) -> (PathBuf, PathBuf, Vec<String>) {
    let gz = std::fs::File::open(testdata("intel.clf.gz")).unwrap();
    let reader = BufReader::new(flate2::read::GzDecoder::new(gz));
    let log = dir.join("intel-excerpt.clf");
    let mut out = std::fs::File::create(&log).unwrap();
    let mut stamps = Vec::new();
    for line in reader.lines() {
        let line = line.unwrap();
        if line.starts_with("FLASER") {
            let fields: Vec<&str> = line.split_whitespace().collect();
            stamps.push(fields[fields.len() - 3].to_string());
        }
        writeln!(out, "{line}").unwrap();
        if stamps.len() == scans {
            break;
        }
    }
    let last: f64 = stamps.last().unwrap().parse().unwrap();
    let relations = dir.join("intel-excerpt.relations");
    let mut rel_out = std::fs::File::create(&relations).unwrap();
    let text = std::fs::read_to_string(testdata("intel.relations")).unwrap();
    for line in text.lines() {
        let f: Vec<f64> = line
            .split_whitespace()
            .take(2)
            .map(|v| v.parse().unwrap())
            .collect();
        if f[0] <= last && f[1] <= last {
            writeln!(rel_out, "{line}").unwrap();
        }
    }
    (log, relations, stamps)
}

#[test]
fn slam_writes_one_pose_per_scan_with_the_logs_timestamps_and_a_map_server_map() {
    let dir = tempfile::tempdir().unwrap();
    let (log, relations, stamps) = intel_excerpt(dir.path(), 800);
    let traj = dir.path().join("traj.txt");
    let map = dir.path().join("intel");
    let said = run_cli(&[
        "slam",
        arg(&log),
        "--out",
        arg(&traj),
        "--map",
        arg(&map),
        "--no-loop-closure",
    ])
    .expect("slam");
    assert!(said.contains("800 laser lines matched"), "{said}");

    let lines: Vec<String> = std::fs::read_to_string(&traj)
        .unwrap()
        .lines()
        .map(str::to_owned)
        .collect();
    assert_eq!(lines.len(), 800);
    for (line, stamp) in lines.iter().zip(&stamps) {
        assert_eq!(line.split_whitespace().next(), Some(stamp.as_str()));
        assert_eq!(line.split_whitespace().count(), 4, "{line}");
    }

    let yaml = std::fs::read_to_string(dir.path().join("intel.yaml")).unwrap();
    for key in [
        "image: intel.pgm",
        "resolution: 0.05",
        "origin: [",
        "occupied_thresh: 0.65",
        "free_thresh: 0.196",
        "negate: 0",
    ] {
        assert!(yaml.contains(key), "{key} missing from\n{yaml}");
    }
    let pgm = std::fs::read(dir.path().join("intel.pgm")).unwrap();
    assert!(pgm.starts_with(b"P5\n"));
    // The image is the extent of the cells seen, as the summary says.
    let map_line = said
        .lines()
        .find(|l| l.starts_with("map: "))
        .unwrap_or_else(|| panic!("no map line in {said}"));
    let cells = map_line
        .split_once(" m (")
        .and_then(|(_, rest)| rest.split_once(" cells of 0.05 m)"))
        .map(|(cells, _)| cells.replace(" × ", " "))
        .unwrap_or_else(|| panic!("{map_line}"));
    let header = String::from_utf8_lossy(&pgm[..pgm.len().min(80)]).into_owned();
    assert!(
        header.contains(&format!("\n{cells}\n255\n")),
        "{header:?} vs {map_line}"
    );
    assert!(
        map_line.contains(" cells held over 2 grid(s) ("),
        "{map_line}"
    );
    // Occupied (0), free (254) and unknown (205) cells are all there.
    for value in [0u8, 254, 205] {
        assert!(pgm[20..].contains(&value), "no pixel of value {value}");
    }
    let png = std::fs::read(dir.path().join("intel.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"));

    // The metric: the CLI's JSON, over every relation inside the excerpt, beating odometry's
    // rotation error on them (the library's own test holds the numbers).
    let json = run_cli(&["slam-eval", arg(&traj), arg(&relations), "--json"]).expect("slam-eval");
    let report: serde_json::Value = serde_json::from_str(&json).unwrap();
    let total = std::fs::read_to_string(&relations).unwrap().lines().count() as u64;
    assert!(total > 30);
    assert_eq!(report["used"].as_u64(), Some(total), "{report}");
    assert_eq!(report["matched_within_10us"].as_u64(), Some(total));
    let mean = report["abs_trans_m"]["mean"].as_f64().unwrap();
    assert!(mean < 0.03, "{mean}");
    let table = run_cli(&["slam-eval", arg(&traj), arg(&relations)]).expect("slam-eval");
    assert!(table.contains("Absolute translational (m)"), "{table}");

    // `--worst 3`: the three largest translational errors, largest first, with the relations'
    // timestamps as the file wrote them.
    let json = run_cli(&[
        "slam-eval",
        arg(&traj),
        arg(&relations),
        "--json",
        "--worst",
        "3",
    ])
    .expect("slam-eval --worst");
    let report: serde_json::Value = serde_json::from_str(&json).unwrap();
    let worst = report["worst"].as_array().expect("a worst list");
    assert_eq!(worst.len(), 3);
    let errors: Vec<f64> = worst
        .iter()
        .map(|w| w["trans_m"].as_f64().unwrap())
        .collect();
    assert!(errors.windows(2).all(|w| w[0] >= w[1]), "{errors:?}");
    let max = report["max_trans_m"].as_f64().unwrap();
    assert!((errors[0] - max).abs() < 1e-12, "{errors:?} vs {max}");
    let t1 = worst[0]["t1"]["text"].as_str().unwrap();
    let file = std::fs::read_to_string(&relations).unwrap();
    assert!(file.lines().any(|l| l.starts_with(t1)), "{t1}");
    let table = run_cli(&["slam-eval", arg(&traj), arg(&relations), "--worst", "2"])
        .expect("slam-eval --worst");
    assert!(table.contains("worst relations"), "{table}");
    assert!(table.contains(t1), "{table}");
}

#[test]
fn a_malformed_log_line_stops_slam_with_its_line_number_unless_lenient() {
    let dir = tempfile::tempdir().unwrap();
    let (log, _, _) = intel_excerpt(dir.path(), 50);
    let mut text = std::fs::read_to_string(&log).unwrap();
    let bad_line = text.lines().count() + 1;
    text.push_str("FLASER 180 1.0 2.0 oops\n");
    let bad = dir.path().join("bad.clf");
    std::fs::write(&bad, &text).unwrap();
    let traj = dir.path().join("traj.txt");
    let error = run_cli(&["slam", arg(&bad), "--out", arg(&traj)]).unwrap_err();
    let message = format!("{error:#}");
    assert!(message.contains(&format!("line {bad_line}")), "{message}");
    assert!(!message.contains('\n'), "one line: {message}");
    assert!(!traj.exists(), "nothing written on a failed read");

    let said = run_cli(&["slam", arg(&bad), "--out", arg(&traj), "--lenient"]).expect("lenient");
    assert!(said.contains("skipped 1 malformed line"), "{said}");
    assert_eq!(std::fs::read_to_string(&traj).unwrap().lines().count(), 50);
}

#[test]
fn slam_eval_refuses_a_malformed_trajectory_with_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let traj = dir.path().join("traj.txt");
    std::fs::write(&traj, "1.000000 0 0 0\n2.000000 0 zero 0\n").unwrap();
    let error = run_cli(&["slam-eval", arg(&traj), arg(&testdata("intel.relations"))]).unwrap_err();
    let message = format!("{error:#}");
    assert!(message.contains("line 2"), "{message}");
}

mod pipeline_support;

#[test]
fn slam_of_a_recorded_session_follows_the_rplidar_through_a_room() {
    // A lidar pushed 1.2 m along a 4 × 3 m box room while turning 0.3 rad/s, 5.5 revolutions a
    // second, each sample taken where the lidar was at its time.
    let dir = tempfile::tempdir().unwrap();
    let mut session = pipeline_support::SessionBuilder::new(0x51a);
    let start = [1.0, 1.4, 0.1];
    // It stands for 1 s first: a revolution taken while moving cannot be de-skewed before
    // there is a motion estimate, so the first map would be smeared.
    let mut truth = session.rplidar_moving(6, 720, start, [0.0; 3]);
    truth.extend(session.rplidar_moving(24, 720, start, [0.28, 0.02, 0.3]));
    let session_dir = session.record(dir.path(), "trolley");
    let traj = dir.path().join("session.txt");
    let config = dir.path().join("slam.toml");
    // A small room: integrate every 10 cm / 0.1 rad (as the simulated-room tests do).
    std::fs::write(
        &config,
        "map_update_distance = 0.1\nmap_update_angle = 0.1\n",
    )
    .unwrap();
    let said = run_cli(&[
        "slam",
        arg(&session_dir),
        "--out",
        arg(&traj),
        "--config",
        arg(&config),
    ])
    .expect("slam of a session");
    assert!(said.contains("30 session revolutions matched"), "{said}");
    let poses: Vec<Vec<f64>> = std::fs::read_to_string(&traj)
        .unwrap()
        .lines()
        .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(poses.len(), 30);
    // Timestamps: the middle of each revolution's samples on the edge clock, 0.18 s apart.
    assert!(
        (poses[1][0] - poses[0][0] - 0.18).abs() < 1e-6,
        "{:?}",
        &poses[..2]
    );
    // The trajectory starts at the identity: compare motions relative to the first pose.
    let t0 = truth[0];
    let (s, c) = (-t0[2]).sin_cos();
    let errors: Vec<(f64, f64)> = poses
        .iter()
        .zip(&truth)
        .map(|(pose, t)| {
            let (dx, dy) = (t[0] - t0[0], t[1] - t0[1]);
            let want = [c * dx - s * dy, s * dx + c * dy, t[2] - t0[2]];
            (
                (pose[1] - want[0]).hypot(pose[2] - want[1]),
                (pose[3] - want[2]).abs().to_degrees(),
            )
        })
        .collect();
    let worst = errors
        .iter()
        .fold((0.0f64, 0.0f64), |a, e| (a.0.max(e.0), a.1.max(e.1)));
    eprintln!("errors (m, deg): {errors:.4?}");
    // Even the revolution in which it starts moving, which the motion so far says is standing
    // still: the refinement finds its velocity with its pose.
    assert!(worst.0 < 0.001 && worst.1 < 0.02, "worst {worst:?}");
}

#[test]
fn a_mounted_lidar_gives_the_trajectory_of_the_base() {
    use scan3d_server::pose::scan_matching::map_session;
    use scan3d_slam::mapper::MapperConfig;
    use scan3d_slam::offline::RangeLimits;
    use scan3d_slam::pose::{Pose2, wrap_angle};

    // The lidar sits 0.3 m ahead of and 0.1 m left of the base's origin, turned 0.2 rad; it
    // stands 1 s, then moves and turns at 0.3 rad/s, its path swinging about the base's.
    let mount = Pose2::new(0.3, 0.1, 0.2);
    let dir = tempfile::tempdir().unwrap();
    let mut session = pipeline_support::SessionBuilder::new(0x3a7);
    let start = [1.4, 1.3, 0.1];
    let mut lidar = session.rplidar_moving(6, 720, start, [0.0; 3]);
    lidar.extend(session.rplidar_moving(24, 720, start, [0.2, 0.05, 0.3]));
    let session_dir = session.record(dir.path(), "mounted");
    let base: Vec<Pose2> = lidar
        .iter()
        .map(|&[x, y, heading]| Pose2::new(x, y, heading).compose(&mount.inverse()))
        .collect();
    let config = MapperConfig {
        map_update_distance: 0.1,
        map_update_angle: 0.1,
        ..MapperConfig::default()
    };
    let limits = RangeLimits {
        min_range: 0.1,
        max_range: None,
        no_return: None,
    };
    // The trajectory starts at the identity: compare each pose with the base's motion since its
    // first pose.
    let worst = |mount: &Pose2| {
        let (run, _) = map_session(&session_dir, &config, &limits, Some(mount), false, |_| {})
            .expect("the session is matched");
        assert_eq!(run.trajectory.poses.len(), base.len());
        run.trajectory
            .poses
            .iter()
            .zip(&base)
            .map(|(found, truth)| {
                let want = base[0].between(truth);
                let p = found.pose;
                (
                    (p.x - want.x).hypot(p.y - want.y),
                    wrap_angle(p.theta - want.theta).abs().to_degrees(),
                )
            })
            .fold((0.0f64, 0.0f64), |a, e| (a.0.max(e.0), a.1.max(e.1)))
    };
    let mounted = worst(&mount);
    let unmounted = worst(&Pose2::default());
    eprintln!("worst (m, deg): with the mount {mounted:?}, without {unmounted:?}");
    assert!(mounted.0 < 0.002 && mounted.1 < 0.05, "{mounted:?}");
    // Without its mount the lidar's own path is reported: centimetres off the base's.
    assert!(unmounted.0 > 0.05, "{unmounted:?}");
}

#[test]
fn slam_of_a_damaged_session_fails_unless_lenient_and_counts_undecodable_frames() {
    let dir = tempfile::tempdir().unwrap();
    let mut session = pipeline_support::SessionBuilder::new(0x5d);
    // Enough revolutions for several MCAP chunks.
    session.rplidar_moving(60, 2000, [1.0, 1.4, 0.1], [0.0; 3]);
    session.undecodable();
    session.rplidar_moving(60, 2000, [1.0, 1.4, 0.1], [0.0; 3]);
    let session_dir = session.record(dir.path(), "trolley");
    let traj = dir.path().join("t.txt");
    let said = run_cli(&["slam", arg(&session_dir), "--out", arg(&traj), "--quiet"])
        .expect("an undecodable frame is counted, not fatal");
    assert!(
        said.contains("skipped 1 frames the server recorded but could not decode"),
        "{said}"
    );
    // One flipped bit in a chunk breaks its CRC: the revolutions in it are lost.
    let chunks = pipeline_support::break_chunk(&session_dir.join("0000.mcap"), 0);
    assert!(chunks >= 2, "{chunks} chunks");
    std::fs::remove_file(&traj).unwrap();
    let err = run_cli(&["slam", arg(&session_dir), "--out", arg(&traj), "--quiet"]).unwrap_err();
    let line = format!("{err:#}");
    assert!(
        line.contains("recording damaged") && line.contains("--lenient"),
        "{line}"
    );
    assert!(
        !traj.exists(),
        "no trajectory from a damaged recording without --lenient"
    );
    let said = run_cli(&[
        "slam",
        arg(&session_dir),
        "--out",
        arg(&traj),
        "--quiet",
        "--lenient",
    ])
    .expect("--lenient matches the rest");
    let lines = std::fs::read_to_string(&traj).unwrap().lines().count();
    assert!(lines > 0 && lines < 120, "{lines} poses; {said}");
}

#[test]
fn slam_says_which_odometry_it_used_and_refuses_a_latency_it_cannot_apply() {
    let dir = tempfile::tempdir().unwrap();
    let (log, _, _) = intel_excerpt(dir.path(), 300);
    let traj = dir.path().join("traj.txt");
    let slam = |extra: &[&str]| {
        let mut args = vec!["slam", arg(&log), "--out", arg(&traj), "--quiet"];
        args.extend_from_slice(extra);
        run_cli(&args)
    };

    // By default the ODOM lines are calibrated against a first pass, and the line says how
    // each source agreed with it.
    let said = slam(&[]).expect("calibrated");
    let line = said
        .lines()
        .find(|l| l.starts_with("odometry: "))
        .expect(&said);
    assert!(
        line.contains("mean heading disagreement per scan with a first pass: the laser lines "),
        "{line}"
    );
    assert!(line.contains(", the ODOM lines at "), "{line}");

    let said = slam(&["--laser-odometry"]).expect("laser lines");
    assert!(
        said.contains("odometry: the laser lines' own poses\n"),
        "{said}"
    );
    let said = slam(&["--odometry-latency", "-0.05"]).expect("fixed latency");
    assert!(
        said.contains("odometry: the ODOM lines, read -0.050 s before each laser stamp\n"),
        "{said}"
    );
    let said = slam(&["--no-odometry"]).expect("no odometry");
    assert!(!said.contains("odometry: "), "{said}");

    let error = format!("{:#}", slam(&["--odometry-latency", "2"]).unwrap_err());
    assert_eq!(error, "--odometry-latency must be within ±0.5 s, not 2");

    // A log without ODOM lines has no track to read late.
    let text = std::fs::read_to_string(&log).unwrap();
    let lasers_only = dir.path().join("lasers-only.clf");
    std::fs::write(
        &lasers_only,
        text.lines()
            .filter(|l| !l.starts_with("ODOM"))
            .map(|l| format!("{l}\n"))
            .collect::<String>(),
    )
    .unwrap();
    let error = run_cli(&[
        "slam",
        arg(&lasers_only),
        "--out",
        arg(&traj),
        "--quiet",
        "--odometry-latency",
        "0.1",
    ])
    .unwrap_err();
    let error = format!("{error:#}");
    assert!(
        error.ends_with("--odometry-latency needs ODOM lines, and the log has none"),
        "{error}"
    );
    let said = run_cli(&["slam", arg(&lasers_only), "--out", arg(&traj), "--quiet"])
        .expect("laser lines only");
    assert!(
        said.contains("odometry: the laser lines' own poses\n"),
        "{said}"
    );
}

#[test]
fn slam_distorts_the_odometry_when_asked_and_says_how() {
    let dir = tempfile::tempdir().unwrap();
    let (log, _, _) = intel_excerpt(dir.path(), 200);
    let slam = |out: &str, extra: &[&str]| {
        let traj = dir.path().join(out);
        let mut args = vec!["slam", arg(&log), "--out", arg(&traj), "--quiet"];
        args.extend_from_slice(extra);
        run_cli(&args).map(|said| (said, std::fs::read_to_string(&traj).unwrap()))
    };
    let (said, clean) = slam("clean.txt", &["--laser-odometry"]).expect("clean");
    assert!(!said.contains("distorted"), "{said}");
    // Every third laser line: a third of the poses, at the kept lines' times.
    let (said, sparse) = slam("sparse.txt", &["--laser-odometry", "--every", "3"]).expect("every");
    assert!(
        said.contains("kept 1 laser line in 3: 67 scans\n"),
        "{said}"
    );
    let times = |t: &str| -> Vec<String> {
        t.lines()
            .map(|l| l.split(' ').next().unwrap().to_string())
            .collect()
    };
    let expected: Vec<String> = times(&clean).into_iter().step_by(3).collect();
    assert_eq!(times(&sparse), expected);
    let error = format!("{:#}", slam("bad.txt", &["--every", "0"]).unwrap_err());
    assert!(error.contains("--every"), "{error}");
    let (said, distorted) = slam(
        "distorted.txt",
        &[
            "--laser-odometry",
            "--odometry-error",
            "0,0.02,0.05",
            "--odometry-slips",
            "30,0.1,0.05",
        ],
    )
    .expect("distorted");
    assert!(
        said.contains(
            "odometry distorted: +0 rad per rad turned, +0.02 rad per m driven, +0.05 of every \
             distance; a slip of 0.1 m and 0.05 rad every 30 s\n"
        ),
        "{said}"
    );
    // The matcher saw other odometry: the same scans, other poses.
    assert_eq!(clean.lines().count(), distorted.lines().count());
    assert_ne!(clean, distorted);

    let error = format!(
        "{:#}",
        slam("bad.txt", &["--odometry-error", "0,0.9,0"]).unwrap_err()
    );
    assert!(error.contains("each term must be within ±0.5"), "{error}");

    // A session has no laser lines or wheel odometry to change: refused, not ignored.
    let session = tempfile::tempdir().unwrap();
    let traj = dir.path().join("session.txt");
    for change in [["--odometry-slips", "60,0.3,0.15"], ["--every", "2"]] {
        let mut args = vec!["slam", arg(session.path()), "--out", arg(&traj)];
        args.extend_from_slice(&change);
        let error = format!("{:#}", run_cli(&args).unwrap_err());
        assert!(error.contains("is a session, which has neither"), "{error}");
    }
}
