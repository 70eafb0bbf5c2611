//! `scan3d assemble --moving` (issue 21, part 3, offline): a recorded trolley pass in the demo
//! room (RPLidar revolutions and a vertical Sweep ray-cast from where they truly were at each
//! sample's time, a pass started where the trolley stood) assembled through the command; the
//! points must lie on the room's true surfaces, closer than the naive placement (every sample at
//! its revolution's start pose) puts them.

mod pipeline_support;
mod trolley_support;

use std::path::{Path, PathBuf};

use scan3d_map::cloud::moving::{BaseTrajectory, FnTrajectory, RigidTransform, place_revolution};
use scan3d_protocol::{Body, SensorId};
use scan3d_server::cli::assemble_moving::session_trajectory;
use trolley_support::{SWEEP_MOUNT, Trolley, scan3d, to_surface, trolley_session};

/// Samples per Sweep revolution.
const SWEEP_SAMPLES: usize = 360;

/// What to put in the recording.
struct Options {
    rplidar: bool,
    sweep_mount: bool,
}

/// Standing 10 revolutions, the pass "aisle" started where the trolley stands, 12 revolutions
/// straight at 0.5 m/s diagonally to the walls, 12 turning at 0.6 rad/s while moving, the pass
/// stopped (no `Hello`). Returns the session directory.
fn record(dir: &Path, options: &Options) -> PathBuf {
    trolley_session(Trolley {
        rplidar: options.rplidar,
        hello: false,
        sweep_mount: options.sweep_mount,
        sweep_samples: SWEEP_SAMPLES,
        stretches: [10, 12, 12],
        after: 0,
        stray_stop: false,
        second_start: false,
    })
    .record(dir, "trolley")
}

/// Mean distance to the room's surfaces of every point of `bundles`.
fn mean_to_surface<'a>(points: impl Iterator<Item = [f64; 3]> + 'a) -> (f64, usize) {
    let (sum, n) = points.fold((0.0, 0usize), |(sum, n), p| (sum + to_surface(p), n + 1));
    (sum / n.max(1) as f64, n)
}

#[test]
fn a_trolley_pass_assembled_along_movement_lies_on_the_rooms_surfaces() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = record(
        tmp.path(),
        &Options {
            rplidar: true,
            sweep_mount: true,
        },
    );
    let dir_arg = dir.to_str().unwrap();
    let ply = tmp.path().join("pass.ply");
    let bt = tmp.path().join("pass.bt");
    let said = scan3d(&[
        "assemble",
        "--moving",
        dir_arg,
        "--out",
        ply.to_str().unwrap(),
        "--bt",
        bt.to_str().unwrap(),
    ])
    .expect("the pass assembles");
    assert!(said.contains("in the room frame"), "{said}");

    let cloud = scan3d_map::cloud::io::load(&ply, None).expect("the PLY reads back");
    let (mean, points) = mean_to_surface(
        cloud
            .iter()
            .flat_map(|b| b.points.iter().map(|p| p.map(f64::from))),
    );
    // Every sample has a return: 34 revolutions of 360, less those of the first and last
    // half revolutions farther than 50 ms from the trajectory's first and last pose (the
    // RPLidar's poses are at its revolutions' middles).
    assert!(
        (33 * SWEEP_SAMPLES..=34 * SWEEP_SAMPLES).contains(&points),
        "{points}: {said}"
    );
    assert!(
        cloud.len() > 34 * 2,
        "per-sample origins: several bundles per moving revolution, got {}",
        cloud.len()
    );

    // The naive placement: every sample at its revolution's start pose, same trajectory.
    let tracked = session_trajectory(&dir, false).unwrap();
    let trajectory = &tracked.trajectory;
    let mount = RigidTransform::from_sensor_mount(&SWEEP_MOUNT);
    let mut naive = Vec::new();
    let mut own = Vec::new();
    for frame in record_frames(&dir) {
        let Body::Revolution(rev) = frame else {
            continue;
        };
        if rev.sensor != SensorId::SWEEP {
            continue;
        }
        let at_start = FnTrajectory {
            span_ns: trajectory.span_ns().unwrap(),
            pose_at: |_| trajectory.base_pose_at(rev.t0_ns),
        };
        let tolerance = 50_000_000;
        naive.extend(place_revolution(&rev, &at_start, &mount, tolerance).samples);
        own.extend(place_revolution(&rev, trajectory, &mount, tolerance).samples);
    }
    let (naive_mean, _) = mean_to_surface(naive.iter().map(|s| s.point));
    let (own_mean, _) = mean_to_surface(own.iter().map(|s| s.point));
    eprintln!(
        "mean point-to-surface: assembled {:.2} cm (command), {:.2} cm (own times, in-test), \
         naive {:.2} cm",
        mean * 100.0,
        own_mean * 100.0,
        naive_mean * 100.0
    );
    assert!(mean < 0.03, "mean point-to-surface {mean} m");
    assert!(
        naive_mean > 1.5 * mean,
        "naive {naive_mean} m against {mean} m"
    );

    let tree = std::fs::read(&bt).expect("the octree was written");
    let tree = scan3d_map::octree::Octree::read(&tree, Default::default()).expect("a .bt");
    assert!(tree.num_occupied() > 100 && tree.num_free() > 100);

    // Only the pass: the 10 standing revolutions before its start are left out.
    let pass_ply = tmp.path().join("aisle.ply");
    scan3d(&[
        "assemble",
        "--moving",
        dir_arg,
        "--out",
        pass_ply.to_str().unwrap(),
        "--pass",
        "aisle",
    ])
    .expect("the pass assembles");
    let pass = scan3d_map::cloud::io::load(&pass_ply, None).unwrap();
    let pass_points: usize = pass.iter().map(|b| b.points.len()).sum();
    // The pass's 24 revolutions, less the end of the last (after the last pose, as above).
    assert!(
        (23 * SWEEP_SAMPLES..=24 * SWEEP_SAMPLES).contains(&pass_points),
        "{pass_points}"
    );
}

/// The decoded frame bodies of a recorded session, in recording order.
fn record_frames(dir: &Path) -> Vec<Body> {
    let mut bodies = Vec::new();
    let _report = scan3d_server::recording::visit_session(dir, |recorded| {
        bodies.push(recorded.frame.body);
        Ok(())
    })
    .unwrap();
    bodies
}

#[test]
fn bad_input_is_refused_with_one_clear_line() {
    let tmp = tempfile::tempdir().unwrap();
    let no_rplidar = record(
        &tmp.path().join("a"),
        &Options {
            rplidar: false,
            sweep_mount: true,
        },
    );
    let no_mount = record(
        &tmp.path().join("b"),
        &Options {
            rplidar: true,
            sweep_mount: false,
        },
    );
    let good = record(
        &tmp.path().join("c"),
        &Options {
            rplidar: true,
            sweep_mount: true,
        },
    );
    let out = tmp.path().join("x.ply");
    let out = out.to_str().unwrap();
    let run = |dir: &Path, extra: &[&str]| {
        let mut args = vec!["assemble", "--moving", dir.to_str().unwrap(), "--out", out];
        args.extend_from_slice(extra);
        scan3d(&args).expect_err("refused")
    };
    let errors = [
        run(&no_rplidar, &[]),
        run(&no_mount, &[]),
        run(&good, &["--pass", "aisle 2"]),
    ];
    assert!(errors[0].contains("no RPLidar revolution"), "{}", errors[0]);
    assert!(
        errors[1].contains("no Sweep mount recorded"),
        "{}",
        errors[1]
    );
    assert!(
        errors[2].contains("no pass named \"aisle 2\"") && errors[2].contains("passes: aisle"),
        "{}",
        errors[2]
    );
    for e in &errors {
        assert_eq!(e.lines().count(), 1, "{e}");
    }
    // --pass without --moving is a usage error.
    let e = scan3d(&[
        "assemble",
        good.to_str().unwrap(),
        "--out",
        out,
        "--pass",
        "aisle",
    ])
    .expect_err("refused");
    assert!(e.contains("--moving"), "{e}");
}
