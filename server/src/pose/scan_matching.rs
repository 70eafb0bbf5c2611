//! 2D scan matching of a recorded session: the horizontal RPLidar's revolutions become
//! [`Scan`]s for `scan3d-slam`'s mapper, each beam with its own time so the revolution is
//! de-skewed (at 5.5 Hz and 0.5 rad/s a revolution turns 5°).
//!
//! A revolution's scan time is its end (`t1_ns`), its beams timed back from it; the mapper
//! returns each revolution's pose for the middle of its beams, and that is the time the
//! trajectory gives it. Times are the edge's monotonic clock: one clock for the whole session
//! is what matching needs. The trajectory's timestamps are those times in seconds, with six
//! decimals.
//!
//! The trajectory is of `base`: each revolution is matched with the lidar's mount (its pose in
//! `base`: x, y and yaw of the 2D part) as the sensor offset, so a lidar mounted off the
//! turning axis gives the base's path, not its own swing. Each pose carries the mapper's
//! velocity and covariance ([`TrajectoryPose::of`]).

use std::path::Path;

use scan3d_map::cloud::scans::scan_plane_point;
use scan3d_protocol::Body;
use scan3d_slam::mapper::{MapperConfig, Scan};
use scan3d_slam::offline::{MapperRun, RangeLimits};
use scan3d_slam::pose::Pose2;
use scan3d_slam::relations::{Trajectory, TrajectoryPose};

use crate::pipeline::pose_stage::PoseTracker;
use crate::recording::{RecorderError, SessionReport, check_losses, visit_session};

/// The mapper's scan for one lidar revolution: endpoints within `limits` in the sensor frame
/// (x forward at angle 0, counter-clockwise), each with its time relative to the revolution's
/// end; the lidar sits at `mount` in `base` (x, y, yaw; the identity when the lidar is `base`).
pub fn revolution_scan(
    revolution: &scan3d_protocol::LidarRevolution,
    limits: &RangeLimits,
    mount: &Pose2,
) -> Scan {
    let end = revolution.t1_ns;
    let mut hits = Vec::with_capacity(revolution.samples.len());
    let mut hit_times = Vec::with_capacity(revolution.samples.len());
    for sample in &revolution.samples {
        let range = f64::from(sample.range_m);
        // 0 is the wire's "no return".
        if sample.range_m <= 0.0
            || range < limits.min_range
            || limits.max_range.is_some_and(|max| range > max)
        {
            continue;
        }
        let [x, y, _] = scan_plane_point(revolution.sensor, sample.angle_deg, sample.range_m);
        hits.push((f64::from(x), f64::from(y)));
        let t = revolution.t0_ns + u64::from(sample.offset_ns);
        hit_times.push(-((end.saturating_sub(t)) as f64) * 1e-9);
    }
    Scan {
        time: end as f64 * 1e-9,
        hits,
        hit_times,
        odometry: None,
        sensor_offset: *mount,
        rotation: None,
    }
}

/// Matches every RPLidar revolution of a recorded session, in recording order (with the gyro's
/// turn between revolutions from its IMU samples, as the live [`PoseTracker`] takes them: the
/// edge sends a sample when it reads it and a revolution at its end, so recording order is
/// sample-time order for these two), streaming the
/// recording (memory: the map, not the session), the lidar at `mount` in `base` (`None`: where
/// the session's `Body::Mounts` puts the RPLidar, as the live pose stage takes it; `base` itself
/// without one); each pose of the trajectory is the base's, stamped
/// with the time it is for, the middle of its revolution's beams (edge clock, s). A damaged recording fails with
/// [`RecorderError::Damaged`] unless `lenient` (then the readable rest is mapped, with a
/// warning); frames the server could not decode are counted in the returned report, not
/// fatal. `progress` gets the revolutions done.
pub fn map_session(
    session_dir: &Path,
    config: &MapperConfig,
    limits: &RangeLimits,
    mount: Option<&Pose2>,
    lenient: bool,
    mut progress: impl FnMut(usize),
) -> Result<(MapperRun, SessionReport), RecorderError> {
    let mut tracker = PoseTracker::new(
        *config,
        *limits,
        mount.copied().unwrap_or_default(),
        mount.is_some(),
    );
    let mut results = Vec::new();
    let mut poses = Vec::new();
    let recording = visit_session(session_dir, |recorded| {
        match &recorded.frame.body {
            Body::Mounts(mounts) => tracker.on_mounts(mounts),
            Body::Imu(sample) => tracker.on_imu(sample),
            Body::Revolution(revolution) => {
                if let Some(result) = tracker.on_revolution(revolution) {
                    poses.push(TrajectoryPose::of(&result));
                    results.push(result);
                    progress(results.len());
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    check_losses(&recording, session_dir, lenient)?;
    let run = MapperRun {
        trajectory: Trajectory { poses },
        results,
        mapper: tracker.mapper().clone(),
    };
    Ok((run, recording))
}

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_protocol::{LidarRevolution, SensorId};

    #[test]
    fn a_revolution_becomes_endpoints_timed_back_from_its_end() {
        let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 1_000_000_000, 1_200_000_000);
        // RPLidar angles are clockwise: 90° is to the right (−y).
        rev.push(90.0, 2.0, 40, 1_050_000_000).expect("time");
        rev.push(180.0, 0.0, 0, 1_100_000_000).expect("time");
        rev.push(270.0, 9.0, 40, 1_150_000_000).expect("time");
        let limits = RangeLimits {
            min_range: 0.1,
            max_range: Some(6.0),
            no_return: None,
        };
        let scan = revolution_scan(&rev, &limits, &Pose2::default());
        assert_eq!(scan.hits.len(), 1, "no return and beyond 6 m dropped");
        assert!(scan.hits[0].0.abs() < 1e-6 && (scan.hits[0].1 + 2.0).abs() < 1e-6);
        assert!((scan.hit_times[0] + 0.15).abs() < 1e-12);
        assert!((scan.time - 1.2).abs() < 1e-12);
    }
}
