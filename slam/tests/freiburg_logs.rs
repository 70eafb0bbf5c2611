//! The Freiburg logs vendored for issue 22 (`testdata/slam/fr079.clf.gz`, `fr-clinic.clf.gz`):
//! the readers give FR079's 360-beam `FLASER` lines and the hospital's interlaced `ROBOTLASER1`
//! lines their geometry and laser offset, and the mapper on an excerpt of each beats what the
//! issue measured before (bounds with margin over map-update distances, not one outcome).

mod common;

use common::{excerpt, load};
use scan3d_slam::mapper::MapperConfig;
use scan3d_slam::offline::{RangeLimits, map_log_calibrated};
use scan3d_slam::pose::Pose2;
use scan3d_slam::relations::{EvalOptions, Trajectory, evaluate};

#[test]
fn fr079_is_360_half_degree_flaser_lines_with_odom_and_every_relation_hits_a_scan() {
    let (log, relations) = load("fr079");
    assert_eq!((log.scans.len(), log.odometry.len()), (4934, 8951));
    for scan in &log.scans {
        assert_eq!(scan.ranges.len(), 360);
        assert!((scan.angle_min + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((scan.angle_increment.to_degrees() - 0.5).abs() < 1e-12);
        assert!(!scan.offset_in_line);
        assert_eq!(scan.laser_offset, Pose2::default());
    }
    assert_eq!(log.front_laser_param, None);
    let report = evaluate(
        &Trajectory::from_scans(&log.scans, &log.odometry_poses()),
        &relations,
        &EvalOptions::default(),
    );
    assert_eq!(report.all.used, 1685);
    // The raw odometry baseline of testdata/slam/README.md.
    assert!((report.all.abs_trans_m.mean - 6.504).abs() < 0.001);
}

#[test]
fn the_hospital_is_interlaced_robotlaser1_lines_with_the_laser_022_m_ahead() {
    let (log, relations) = load("fr-clinic");
    assert_eq!((log.scans.len(), log.odometry.len()), (6917, 0));
    let mut starts: Vec<i64> = log
        .scans
        .iter()
        .map(|s| (s.angle_min.to_degrees() * 100.0).round() as i64)
        .collect();
    starts.sort_unstable();
    starts.dedup();
    assert_eq!(starts, vec![-9000, -8975, -8950, -8925]);
    for scan in &log.scans {
        assert!(matches!(scan.ranges.len(), 180 | 181));
        assert!(scan.offset_in_line);
        let o = scan.laser_offset;
        assert!((o.x - 0.22).abs() < 1e-5 && o.y.abs() < 1e-5 && o.theta.abs() < 1e-5);
    }
    let report = evaluate(
        &Trajectory::from_scans(&log.scans, &log.odometry_poses()),
        &relations,
        &EvalOptions::default(),
    );
    assert_eq!(report.all.used, 2820);
    assert!((report.all.abs_trans_m.mean - 0.615).abs() < 0.001);
}

/// The median and the worst of the relations error over map-update distances 0.3 / 0.4 / 0.5.
fn median_and_worst(
    name: &str,
    scans: usize,
    offset: Option<Pose2>,
    max_range: Option<f64>,
) -> (f64, f64, usize) {
    median_and_worst_with(name, scans, offset, max_range, true, 1)
}

/// [`median_and_worst`], with or without the log's odometry, matching the first laser line and
/// every `every`-th after it (`CarmenLog::keep_every`; the relations counted are those whose two
/// scans were kept).
fn median_and_worst_with(
    name: &str,
    scans: usize,
    offset: Option<Pose2>,
    max_range: Option<f64>,
    use_odometry: bool,
    every: usize,
) -> (f64, f64, usize) {
    let (mut log, relations) = load(name);
    if let Some(offset) = offset {
        log.set_front_laser_offset(offset);
    }
    let (mut log, relations) = excerpt(&log, &relations, scans);
    log.keep_every(every);
    let limits = RangeLimits::for_log(&log, 0.1, max_range);
    let mut used = 0;
    let mut errors: Vec<f64> = [0.3, 0.4, 0.5]
        .iter()
        .map(|&d| {
            let mut config = MapperConfig {
                map_update_distance: d,
                ..MapperConfig::default()
            };
            config.motion.use_odometry = use_odometry;
            let run = map_log_calibrated(&log, &config, &limits, |_| {}).run;
            let report = evaluate(&run.trajectory, &relations, &EvalOptions::default());
            if every <= 1 {
                assert_eq!(report.all.used, relations.relations.len());
            }
            used = report.all.used;
            report.all.abs_trans_m.mean
        })
        .collect();
    errors.sort_by(f64::total_cmp);
    println!("{name}, first {scans} scans, one in {every}: errors {errors:.4?}");
    (errors[1], errors[2], used)
}

#[test]
fn the_hospital_excerpt_with_its_laser_offset_stays_near_its_odometry() {
    let (median, worst, used) = median_and_worst("fr-clinic", 600, None, None);
    assert!(used > 100, "{used} relations");
    assert!(
        median <= 0.15 && worst <= 0.30,
        "median {median:.4} worst {worst:.4}"
    );
}

/// The whole FR079 log, with odometry. Before the per-scan odometry gate (a poor match tries
/// the constant-velocity prediction and a window search, `MotionConfig::poor_match_ratio`) the
/// matcher lost the map near 183 s, led by the odometry, and never found it again: 1.07 / 0.95
/// / 1.48 m at 0.4 / 0.3 / 0.5. After it one draw in a few still slipped (0.3 with the 30 m
/// range limit: 0.66 m; 0.45 with joined endpoints: 0.53 m). With the odometry widened where it
/// disagrees with the matches (`MotionConfig::odometry_check_window`) every draw from 0.3 to 0.5
/// is 0.040 m, and both bounds are the goals for FR079.
#[test]
fn fr079_with_odometry_keeps_the_map_over_map_update_distances() {
    let log = load("fr079").0;
    let (median, worst, used) = median_and_worst("fr079", log.scans.len(), None, None);
    assert!(used > 1000, "{used} relations");
    assert!(
        median <= 0.10 && worst <= 0.20,
        "median {median:.4} worst {worst:.4}"
    );
}

/// FR079 with one scan in two (0.19 m and 0.43 s apart, as the held-out log's), with odometry.
/// For seconds near 1515 s its odometry reads forward while the robot backs up; trusted as its error model says, it pulled the matches there between itself and the
/// scans and the map was lost at 0.4: 0.043 / 0.303 / 0.044 m. Widened where it disagrees with
/// the matches over the last seconds (`MotionConfig::odometry_check_window`): 0.043 / 0.044 /
/// 0.044 m.
#[test]
fn fr079_with_one_scan_in_two_keeps_the_map_where_its_odometry_is_wrong() {
    let log = load("fr079").0;
    let (median, worst, used) =
        median_and_worst_with("fr079", log.scans.len(), None, None, true, 2);
    assert!(used > 300, "{used} relations");
    assert!(
        median <= 0.10 && worst <= 0.15,
        "median {median:.4} worst {worst:.4}"
    );
}

#[test]
fn the_mapper_reports_the_robot_not_the_laser_that_sits_ahead_of_it() {
    let (log, relations) = load("fr-clinic");
    let (log, _) = excerpt(&log, &relations, 40);
    let limits = RangeLimits::for_log(&log, 0.1, None);
    let run = map_log_calibrated(&log, &MapperConfig::default(), &limits, |_| {}).run;
    for (pose, scan) in run.trajectory.poses.iter().zip(&log.scans).take(4) {
        let robot = scan.odometry;
        let laser = scan.laser_pose;
        let to_robot = (pose.pose.x - robot.x).hypot(pose.pose.y - robot.y);
        let to_laser = (pose.pose.x - laser.x).hypot(pose.pose.y - laser.y);
        // The scans agree with odometry to centimetres over the first four scans (0.051 m at
        // most); the laser is 0.22 m from the robot.
        assert!(
            to_robot < 0.08 && to_laser > 0.14,
            "line {}: {to_robot:.3} m from the robot, {to_laser:.3} m from the laser",
            scan.line
        );
    }
}

/// The first 450 Intel scans (90 s, 26 relations) without odometry: a constant-velocity
/// prior and the window search on every scan. Intel's laser lines come in bursts and its
/// corridors are seen at grazing angles; with the last interval's velocity and without joined
/// endpoints the three draws were 0.37 / 0.41 / 0.55 m, with the velocity over the last second
/// (`MotionConfig::velocity_window`) and joined endpoints (`UpdateModel::join_endpoints_within`)
/// 0.056 / 0.109 / 0.135 m; with the scans' clock (`MotionConfig::velocity_clock`) and wider
/// joins without odometry 0.014 / 0.043 / 0.063 m; with late lines that fit well set aside
/// too (`MotionConfig::out_of_order_turn_back`) 0.0125 / 0.0128 / 0.0150 m.
#[test]
fn intel_without_odometry_follows_its_first_corridors_over_map_update_distances() {
    let (median, worst, used) = median_and_worst_with("intel", 450, None, None, false, 1);
    assert!(used > 20, "{used} relations");
    assert!(
        median <= 0.15 && worst <= 0.30,
        "median {median:.4} worst {worst:.4}"
    );
}
