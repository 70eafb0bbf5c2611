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

/// The late lines (`late`, each compared `ahead` lines on) whose pose the mapper turned from
/// the line before's as the odometry did, within 0.1 rad (5.7°).
fn placed(run: &MapperRun, odometry: &[Pose2], late: &[usize], ahead: usize) -> Vec<usize> {
    late.iter()
        .copied()
        .filter(|&i| {
            let got = turned(&run.results[i - 1].pose, &run.results[i + ahead].pose);
            let want = turned(&odometry[i - 1], &odometry[i + ahead]);
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
        placed(&checked, &odometry, &late, 0),
        placed(&unchecked, &odometry, &late, 0),
    );
    let aside: Vec<usize> = (0..checked.results.len())
        .filter(|&i| checked.results[i].out_of_order)
        .collect();
    println!("late by odometry {late:?}");
    println!("placed {with:?}, without the check {without:?}; set aside {aside:?}");
    assert!(late.len() >= 10, "{late:?}");
    // Measured: 13 of the 13 placed with the check (12 before it also set aside late lines
    // that fit well), 10 without (those the window search, weighed against the prediction,
    // reaches; 6 before the velocity clock).
    assert!(with.len() + 2 >= late.len(), "placed {with:?} of {late:?}");
    assert!(with.len() > without.len(), "{with:?} against {without:?}");
}

/// A late line the window search places well, turned back against the turn, is set aside too
/// (`MotionConfig::out_of_order_turn_back`, `out_of_order_back`): the line after it is then
/// predicted from the last line in order, not from the late one.
#[test]
fn the_line_after_a_late_one_is_predicted_from_the_last_line_in_order() {
    let (log, relations) = load("intel");
    let (log, _) = excerpt(&log, &relations, 5200);
    let odometry = log.odometry_poses();
    let late: Vec<usize> = logged_late(&odometry)
        .into_iter()
        .filter(|&i| i + 1 < odometry.len())
        .collect();
    let limits = RangeLimits::for_log(&log, 0.1, None);
    let run = |went_back: bool| {
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        if !went_back {
            config.motion.out_of_order_back = 0.0;
            config.motion.out_of_order_turn_back = 0.0;
        }
        map_log_calibrated(&log, &config, &limits, |_| {}).run
    };
    let (checked, unchecked) = (run(true), run(false));
    let recognised = |run: &MapperRun| -> Vec<usize> {
        late.iter()
            .copied()
            .filter(|&i| run.results[i].out_of_order)
            .collect()
    };
    let (aside, aside_without) = (recognised(&checked), recognised(&unchecked));
    let with = placed(&checked, &odometry, &late, 1);
    let without = placed(&unchecked, &odometry, &late, 1);
    println!("of {late:?}: set aside {aside:?}, without the rule {aside_without:?}");
    println!("the line after each: placed {with:?}, without the rule {without:?}");
    // Measured: 11 of the 13 set aside, 3 without the rule (the ones that match poorly); the
    // line after placed for 13, 12 without.
    assert!(
        aside.len() >= 8 && aside.len() >= aside_without.len() + 5,
        "set aside {aside:?}, without the rule {aside_without:?}"
    );
    assert!(with.len() >= without.len(), "{with:?} against {without:?}");
    assert!(with.len() + 2 >= late.len(), "placed {with:?} of {late:?}");
}
