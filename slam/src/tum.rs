//! TUM trajectories (`t x y z qx qy qz qw` per line, `#` comments) read as 2D poses, and the
//! absolute trajectory error of one against a reference in the same frame: what
//! `scan3d traj-eval` prints for a live pass's `trajectory.tum` against the simulator's
//! `--truth`.
//!
//! No alignment is fitted: both trajectories must be in the same frame (the pass anchors the
//! live one in the room), so an error in the anchor counts. Each estimated pose is compared
//! with the reference interpolated at its time (linearly in position, along the shorter arc
//! in heading); poses outside the reference's span are not compared.

use std::io::BufRead;

use serde::Serialize;

use crate::pose::{Pose2, wrap_angle};
use crate::text::{LineError, LineReader, NextLine};

/// One pose of a TUM file: its time (s) and the 2D part of the pose (yaw from the quaternion).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TumPose {
    /// Time, seconds.
    pub t: f64,
    /// x, y and the yaw about z.
    pub pose: Pose2,
}

/// Lines read at most (a 10 Hz trajectory of 11 days; a hostile file stops there).
pub const MAX_TUM_LINES: usize = 10_000_000;

/// Reads a TUM trajectory; blank lines and `#` comments are skipped, times must increase.
pub fn read_tum(input: impl BufRead) -> Result<Vec<TumPose>, LineError> {
    let mut reader = LineReader::new(input);
    let mut poses: Vec<TumPose> = Vec::new();
    loop {
        let (number, line) = match reader.next_line()? {
            NextLine::End => break,
            NextLine::TooLong(error) => return Err(error),
            NextLine::Line(number, line) => (number, line),
        };
        let error = |what: String| LineError { line: number, what };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if poses.len() == MAX_TUM_LINES {
            return Err(error(format!("more than {MAX_TUM_LINES} poses")));
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != 8 {
            return Err(error(format!(
                "{} fields, a TUM line has 8: t x y z qx qy qz qw",
                fields.len()
            )));
        }
        let mut v = [0.0; 8];
        for (slot, field) in v.iter_mut().zip(&fields) {
            *slot = field
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| error(format!("{field:?} is not a finite number")))?;
        }
        let [t, x, y, _z, qx, qy, qz, qw] = v;
        if poses.last().is_some_and(|p| t <= p.t) {
            return Err(error(format!("time {t} does not follow the line before")));
        }
        // Yaw about z of the rotation (ZYX convention).
        let yaw = (2.0 * (qw * qz + qx * qy)).atan2(1.0 - 2.0 * (qy * qy + qz * qz));
        poses.push(TumPose {
            t,
            pose: Pose2::new(x, y, yaw),
        });
    }
    Ok(poses)
}

/// The reference at time `t`, interpolated between the two poses around it.
fn reference_at(reference: &[TumPose], t: f64) -> Option<Pose2> {
    let after = reference.partition_point(|p| p.t < t);
    let b = reference.get(after)?;
    if b.t == t {
        return Some(b.pose);
    }
    let a = reference.get(after.checked_sub(1)?)?;
    let u = (t - a.t) / (b.t - a.t);
    Some(a.pose.interpolate(&b.pose, u))
}

/// The absolute trajectory error of an estimate against a reference.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrajectoryError {
    /// Estimated poses compared (within the reference's span).
    pub compared: usize,
    /// Estimated poses outside the reference's span, not compared.
    pub outside: usize,
    /// Root mean square of the position errors, m.
    pub position_rmse_m: f64,
    /// The largest position error, m.
    pub position_max_m: f64,
    /// Root mean square of the heading errors, degrees.
    pub heading_rmse_deg: f64,
    /// The largest heading error, degrees.
    pub heading_max_deg: f64,
}

/// Compares every estimated pose within `[from, to]` (s; the whole span when `None`) with the
/// reference at its time; `None` when no pose could be compared.
pub fn trajectory_error(
    estimate: &[TumPose],
    reference: &[TumPose],
    from: Option<f64>,
    to: Option<f64>,
) -> Option<TrajectoryError> {
    let (mut n, mut outside) = (0usize, 0usize);
    let (mut sum_p, mut max_p, mut sum_h, mut max_h) = (0.0, 0.0f64, 0.0, 0.0f64);
    for e in estimate {
        if from.is_some_and(|f| e.t < f) || to.is_some_and(|t| e.t > t) {
            continue;
        }
        let Some(r) = reference_at(reference, e.t) else {
            outside += 1;
            continue;
        };
        let dp = (e.pose.x - r.x).hypot(e.pose.y - r.y);
        let dh = wrap_angle(e.pose.theta - r.theta).abs().to_degrees();
        n += 1;
        sum_p += dp * dp;
        sum_h += dh * dh;
        max_p = max_p.max(dp);
        max_h = max_h.max(dh);
    }
    (n > 0).then(|| TrajectoryError {
        compared: n,
        outside,
        position_rmse_m: (sum_p / n as f64).sqrt(),
        position_max_m: max_p,
        heading_rmse_deg: (sum_h / n as f64).sqrt(),
        heading_max_deg: max_h,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tum(text: &str) -> Vec<TumPose> {
        read_tum(text.as_bytes()).unwrap()
    }

    #[test]
    fn a_tum_file_reads_as_times_and_2d_poses() {
        let poses = tum(
            "# header\n1.0 2 3 0 0 0 0.7071067811865476 0.7071067811865476\n\n2.5 4 5 0.1 0 0 0 1\n",
        );
        assert_eq!(poses.len(), 2);
        assert!((poses[0].pose.theta - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert_eq!(
            (poses[1].t, poses[1].pose.x, poses[1].pose.theta),
            (2.5, 4.0, 0.0)
        );
    }

    #[test]
    fn bad_lines_are_refused_with_their_number() {
        for (text, line, what) in [
            ("1 2 3\n", 1, "3 fields"),
            ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", 2, "does not follow"),
            ("# c\n1 0 0 nan 0 0 0 1\n", 2, "finite"),
        ] {
            let err = read_tum(text.as_bytes()).unwrap_err();
            assert_eq!(err.line, line, "{text:?}");
            assert!(err.what.contains(what), "{err:?}");
        }
    }

    #[test]
    fn the_error_is_taken_against_the_reference_interpolated_at_each_time() {
        let reference = tum("0 0 0 0 0 0 0 1\n2 2 0 0 0 0 0.7071067811865476 0.7071067811865476\n");
        // At t = 1 the reference is at (1, 0) heading 45°.
        let estimate =
            tum("1 1 0.03 0 0 0 0.3826834323650898 0.9238795325112867\n3 9 9 0 0 0 0 1\n");
        let e = trajectory_error(&estimate, &reference, None, None).unwrap();
        assert_eq!((e.compared, e.outside), (1, 1));
        assert!((e.position_rmse_m - 0.03).abs() < 1e-9, "{e:?}");
        assert!(e.heading_rmse_deg < 1e-6, "{e:?}");
        assert!(trajectory_error(&estimate, &reference, Some(2.0), None).is_none());
    }
}
