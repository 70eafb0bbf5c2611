//! Intel's laser lines logged out of order: each line carries the odometry of when it was
//! taken, so the lines whose heading sits away from both neighbours (which agree) are known.
//! Without odometry the mapper must place such a scan where it was taken, from the scans
//! alone: by the window search when it is near the prediction, by matching it at the earlier
//! poses when it is beyond it (`MotionConfig::out_of_order_poses`). Checked against the
//! odometry field the mapper never sees.

mod common;

use common::{excerpt, load};
use scan3d_slam::mapper::MapperConfig;
use scan3d_slam::offline::{MapperRun, RangeLimits, map_log_calibrated};
use scan3d_slam::pose::{Pose2, wrap_angle};

/// The heading from `a` to `b` (rad).
fn turned(a: &Pose2, b: &Pose2) -> f64 {
    wrap_angle(b.theta - a.theta)
}

/// The lines (indices) whose odometry heading is more than 15° from both neighbours while the
/// neighbours are within 10° of each other: a scan taken before the one logged ahead of it.
fn logged_late(odometry: &[Pose2]) -> Vec<usize> {
    let (far, near) = (15f64.to_radians(), 10f64.to_radians());
    (1..odometry.len().saturating_sub(1))
        .filter(|&i| {
            let (before, this, after) = (&odometry[i - 1], &odometry[i], &odometry[i + 1]);
            turned(before, this).abs() > far
                && turned(this, after).abs() > far
                && turned(before, after).abs() < near
        })
        .collect()
}

/// The late lines whose pose the mapper turned from the line before's as the odometry did,
/// within 0.1 rad (5.7°).
fn placed(run: &MapperRun, odometry: &[Pose2], late: &[usize]) -> Vec<usize> {
    late.iter()
        .copied()
        .filter(|&i| {
            let got = turned(&run.results[i - 1].pose, &run.results[i].pose);
            let want = turned(&odometry[i - 1], &odometry[i]);
            wrap_angle(got - want).abs() < 0.1
        })
        .collect()
}

#[test]
fn intels_late_laser_lines_are_placed_where_they_were_taken_without_odometry() {
    let (log, relations) = load("intel");
    let (log, _) = excerpt(&log, &relations, 5200);
    let odometry = log.odometry_poses();
    let late = logged_late(&odometry);
    let limits = RangeLimits::for_log(&log, 0.1, None);
    let run = |out_of_order_poses: usize| {
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        config.motion.out_of_order_poses = out_of_order_poses;
        map_log_calibrated(&log, &config, &limits, |_| {}).run
    };
    let checked = run(MapperConfig::default().motion.out_of_order_poses);
    let unchecked = run(0);
    let (with, without) = (
        placed(&checked, &odometry, &late),
        placed(&unchecked, &odometry, &late),
    );
    let aside: Vec<usize> = (0..checked.results.len())
        .filter(|&i| checked.results[i].out_of_order)
        .collect();
    println!("late by odometry {late:?}");
    println!("placed {with:?}, without the check {without:?}; set aside {aside:?}");
    assert!(late.len() >= 10, "{late:?}");
    // Measured: 12 of the 13 placed with the check, 10 without (those the window search,
    // weighed against the prediction, reaches; 6 before the velocity clock).
    assert!(with.len() + 2 >= late.len(), "placed {with:?} of {late:?}");
    assert!(with.len() > without.len(), "{with:?} against {without:?}");
}
