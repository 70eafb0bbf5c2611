//! Which odometry a log's scans are matched with, and how late its laser stamps run against its
//! odometry stamps.
//!
//! A CARMEN log carries odometry twice: on each laser line (the pose the logger last had when it
//! wrote the line; in ACES that is the `ODOM` line before it, up to 0.1 s old) and as the `ODOM`
//! lines with their own stamps. Neither need be what the wheels read while the laser measured: a
//! laser is stamped when its scan has arrived, after it was taken. Used as the motion prior, an
//! odometry that runs ahead or behind the scans pulls every turn the wrong way.
//!
//! The scans say when the robot turned. [`calibrate`] compares the heading changes of a first
//! matcher pass with those of each odometry source, the `ODOM` track shifted by every latency
//! within ±[`MAX_LATENCY`], and keeps the source that agrees best (temporal calibration against
//! the motion the sensor itself saw, as Furgale et al., IROS 2013, calibrate a sensor's time
//! offset). The matched headings come from a pass that used the laser lines' odometry as its
//! prior, so the comparison leans towards that source: the `ODOM` track is taken only when it
//! agrees better all the same.

use crate::carmen::{CarmenLog, OdometryTrack};
use crate::pose::{Pose2, wrap_angle};

/// The largest latency searched, either way (s).
pub const MAX_LATENCY: f64 = 0.5;

/// The latency grid's step (s); the best step is refined by a parabola through its neighbours.
const LATENCY_STEP: f64 = 0.005;

/// Where the odometry of each scan comes from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OdometrySource {
    /// Each laser line's own odometry pose.
    LaserLines,
    /// The `ODOM` track read `latency` seconds before each laser stamp.
    Track {
        /// How much later a laser stamp is than the odometry stamp of the same instant (s).
        latency: f64,
    },
}

impl OdometrySource {
    /// One odometry pose per scan of `log`; `None` for [`OdometrySource::Track`] when the log
    /// has no `ODOM` lines.
    pub fn poses(&self, log: &CarmenLog) -> Option<Vec<Pose2>> {
        match *self {
            Self::LaserLines => Some(log.odometry_poses()),
            Self::Track { latency } => Some(track_poses(log, &log.odometry_track()?, latency)),
        }
    }
}

/// One pose per scan of `log`, read from `track` `latency` seconds before each laser stamp.
fn track_poses(log: &CarmenLog, track: &OdometryTrack, latency: f64) -> Vec<Pose2> {
    log.scans
        .iter()
        .map(|s| track.at(s.timestamp.seconds - latency))
        .collect()
}

/// How well each odometry source agrees with a matcher pass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// The laser lines' odometry: mean heading disagreement per scan (rad).
    pub laser_lines: f64,
    /// The `ODOM` track at its best latency: that latency (s) and its disagreement (rad), when
    /// the log has `ODOM` lines.
    pub track: Option<(f64, f64)>,
}

impl Calibration {
    /// The source that agrees best with the matched headings.
    pub fn best(&self) -> OdometrySource {
        match self.track {
            Some((latency, disagreement)) if disagreement < self.laser_lines => {
                OdometrySource::Track { latency }
            }
            _ => OdometrySource::LaserLines,
        }
    }
}

/// The mean, over consecutive scans, of the absolute difference between the heading change the
/// matcher found and the one `odometry` reports (rad): 0 when odometry turns exactly as the
/// scans did. `matched` and `odometry` hold one pose per scan.
pub fn heading_disagreement(matched: &[Pose2], odometry: &[Pose2]) -> f64 {
    assert_eq!(matched.len(), odometry.len(), "one odometry pose per scan");
    let pairs = matched.len().saturating_sub(1);
    if pairs == 0 {
        return 0.0;
    }
    let total: f64 = matched
        .windows(2)
        .zip(odometry.windows(2))
        .map(|(m, o)| {
            let turned = wrap_angle(m[1].theta - m[0].theta);
            let reported = wrap_angle(o[1].theta - o[0].theta);
            wrap_angle(turned - reported).abs()
        })
        .sum();
    total / pairs as f64
}

/// Scores every odometry source of `log` against `matched` (one pose per scan, from a matcher
/// pass over the same log).
pub fn calibrate(log: &CarmenLog, matched: &[Pose2]) -> Calibration {
    let laser_lines = heading_disagreement(matched, &log.odometry_poses());
    let track = log
        .odometry_track()
        .map(|track| best_latency(&track, log, matched));
    Calibration { laser_lines, track }
}

/// The latency within ±[`MAX_LATENCY`] at which the track's heading changes agree best with
/// `matched`, and that disagreement.
fn best_latency(track: &OdometryTrack, log: &CarmenLog, matched: &[Pose2]) -> (f64, f64) {
    let at = |latency: f64| heading_disagreement(matched, &track_poses(log, track, latency));
    let steps = (MAX_LATENCY / LATENCY_STEP).round() as i32;
    let costs: Vec<(f64, f64)> = (-steps..=steps)
        .map(|k| {
            let latency = f64::from(k) * LATENCY_STEP;
            (latency, at(latency))
        })
        .collect();
    let best = (0..costs.len())
        .min_by(|&a, &b| costs[a].1.total_cmp(&costs[b].1))
        .expect("at least one latency");
    if best == 0 || best + 1 == costs.len() {
        return costs[best];
    }
    // The vertex of the parabola through the best step and its two neighbours.
    let (before, here, after) = (costs[best - 1].1, costs[best].1, costs[best + 1].1);
    let curvature = before - 2.0 * here + after;
    if curvature <= 0.0 {
        return costs[best];
    }
    let offset = (0.5 * (before - after) / curvature).clamp(-0.5, 0.5) * LATENCY_STEP;
    let latency = costs[best].0 + offset;
    let refined = at(latency);
    if refined < here {
        (latency, refined)
    } else {
        costs[best]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::carmen::{ReadOptions, read_log};

    /// A log whose robot turns back and forth (heading `sin(t)`, one `ODOM` line every 0.1 s)
    /// and whose laser, scanning every 0.2 s, is stamped `latency` late; the laser lines carry
    /// the last `ODOM` pose, as in ACES.
    fn turning_log(latency: f64) -> (CarmenLog, Vec<Pose2>) {
        let mut text = String::new();
        let mut truth = Vec::new();
        let heading = |t: f64| t.sin();
        let mut last_odom = Pose2::default();
        for k in 0..400 {
            let t = f64::from(k) * 0.1;
            let pose = Pose2::new(0.0, 0.0, heading(t));
            text += &format!("ODOM 0 0 {} 0 0 0 {t:.6} nohost 0\n", pose.theta);
            if k % 2 == 1 {
                // The scan was taken at t, and stamped latency later.
                let stamp = t + latency;
                text += &format!(
                    "FLASER 2 1 1 0 0 {0} 0 0 {0} {stamp:.6} nohost 0\n",
                    last_odom.theta
                );
                truth.push(Pose2::new(0.0, 0.0, heading(t)));
            }
            last_odom = pose;
        }
        let log = read_log(text.as_bytes(), &ReadOptions { lenient: false }).expect("a log");
        (log, truth)
    }

    #[test]
    fn the_latency_of_the_laser_stamps_is_found_from_the_headings_the_scans_saw() {
        for latency in [0.0, 0.1, -0.07, 0.234] {
            let (log, truth) = turning_log(latency);
            let calibration = calibrate(&log, &truth);
            let (found, disagreement) = calibration.track.expect("ODOM lines");
            assert!(
                (found - latency).abs() < 0.01,
                "latency {latency}: found {found}"
            );
            // The track read at the right time agrees better than the stale laser-line poses.
            assert!(
                disagreement < calibration.laser_lines / 5.0,
                "{calibration:?}"
            );
            assert_eq!(calibration.best(), OdometrySource::Track { latency: found });
        }
    }

    #[test]
    fn laser_lines_that_agree_better_are_kept() {
        let (log, _) = turning_log(0.1);
        // A matcher that followed the laser lines' odometry exactly.
        let matched = log.odometry_poses();
        let calibration = calibrate(&log, &matched);
        assert_eq!(calibration.laser_lines, 0.0);
        assert_eq!(calibration.best(), OdometrySource::LaserLines);
    }

    #[test]
    fn heading_disagreement_is_the_mean_absolute_turn_difference_across_the_wrap() {
        let matched = [
            Pose2::new(0.0, 0.0, 3.1),
            Pose2::new(0.0, 0.0, -3.1),
            Pose2::new(0.0, 0.0, -3.0),
        ];
        // Turns of +0.0832 and +0.1 rad; the odometry reports +0.0832 and +0.3.
        let odometry = [
            Pose2::new(0.0, 0.0, 1.0),
            Pose2::new(0.0, 0.0, 1.0 + (std::f64::consts::TAU - 6.2)),
            Pose2::new(0.0, 0.0, 1.3 + (std::f64::consts::TAU - 6.2)),
        ];
        let d = heading_disagreement(&matched, &odometry);
        assert!((d - 0.1).abs() < 1e-9, "{d}");
        assert_eq!(heading_disagreement(&matched[..1], &odometry[..1]), 0.0);
    }
}
