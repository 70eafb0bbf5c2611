//! Wheel odometry's systematic error, learned from the matches as the log goes.
//!
//! Wheels whose diameters differ turn the robot's odometry a little on every metre; a wrong
//! wheel base scales every turn; a wrong diameter scales every distance. Used as the motion
//! prior, such odometry pulls each match the same way by a fraction of its error, and a map
//! built scan after scan keeps that fraction: the heading leaks away along a corridor.
//!
//! [`OdometryBias`] fits three numbers to the differences between what the odometry said and
//! what the scans found, over the recent matches (recursive least squares with exponential
//! forgetting, shrunk towards no error when there is little to go on): the rotation per radian
//! turned, the rotation per metre driven forward, and the translation scale. The mapper
//! corrects each odometry increment with them before predicting (UMBmark's systematic errors,
//! Borenstein & Feng 1996, estimated online instead of on a test square).

use crate::carmen::CarmenLog;
use crate::pose::{Pose2, wrap_angle};

/// How much evidence of "no error" the estimate starts with and keeps: as if this many
/// radians² of turning and metres² of driving had agreed exactly (a few steps' worth).
const SHRINKAGE: f64 = 0.05;

/// An odometry step shorter than this (m) says nothing about the translation scale.
const MIN_STEP: f64 = 0.005;

/// The largest correction taken, either way. An estimate beyond it is a sign that something
/// other than the wheels is wrong.
const LIMITS: WheelError = WheelError {
    per_rad: 0.2,
    per_m: 0.1,
    scale: 0.2,
};

/// A systematic error of wheel odometry, as a correction of its steps or as an error put into
/// them: each step's turn grows by `per_rad` of itself plus `per_m` radians per metre driven
/// forward, and its translation by `scale` of itself.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WheelError {
    /// Rotation per radian turned (a wrong wheel base).
    pub per_rad: f64,
    /// Rotation per metre driven forward, rad/m (wheels of different diameters).
    pub per_m: f64,
    /// Translation per metre driven (a wrong wheel diameter).
    pub scale: f64,
}

impl WheelError {
    /// `step` (an odometry increment in the frame of its start) with this error applied.
    pub fn apply(&self, step: &Pose2) -> Pose2 {
        Pose2::new(
            step.x * (1.0 + self.scale),
            step.y * (1.0 + self.scale),
            step.theta * (1.0 + self.per_rad) + self.per_m * step.x,
        )
    }
}

/// Slips of the wheels put into a log's odometry: every `every` seconds one step jumps
/// `translation` metres forward and `rotation` radians, the signs alternating.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Slips {
    /// Time between slips (s).
    pub every: f64,
    /// How far each slip jumps along the step (m).
    pub translation: f64,
    /// How far each slip turns (rad).
    pub rotation: f64,
}

/// Puts `error` (and `slips`) into every odometry pose of `log`, its laser lines' and its
/// `ODOM` lines' alike: the poses are taken as one stream in time order, each step between
/// consecutive ones is distorted, and the stream is integrated again from the first pose. A
/// robustness test of the matcher against worse wheels than the log's (`scan3d slam
/// --odometry-error`).
pub fn distort_odometry(log: &mut CarmenLog, error: &WheelError, slips: Option<&Slips>) {
    // (time, laser line or ODOM line, index), stably in time order.
    let mut order: Vec<(f64, bool, usize)> = log
        .scans
        .iter()
        .enumerate()
        .map(|(i, s)| (s.timestamp.seconds, true, i))
        .chain(
            log.odometry
                .iter()
                .enumerate()
                .map(|(i, o)| (o.timestamp.seconds, false, i)),
        )
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut next_slip = order
        .first()
        .zip(slips)
        .map_or(f64::INFINITY, |(first, s)| first.0 + s.every);
    let mut sign = 1.0;
    let mut previous: Option<(Pose2, Pose2)> = None;
    for (time, laser, i) in order {
        let original = if laser {
            log.scans[i].odometry
        } else {
            log.odometry[i].pose
        };
        let distorted = match previous {
            None => original,
            Some((before, distorted_before)) => {
                let mut step = error.apply(&before.between(&original));
                if let Some(s) = slips.filter(|_| time >= next_slip) {
                    step = step.compose(&Pose2::new(sign * s.translation, 0.0, sign * s.rotation));
                    sign = -sign;
                    next_slip += s.every.max(f64::MIN_POSITIVE);
                }
                distorted_before.compose(&step)
            }
        };
        previous = Some((original, distorted));
        if laser {
            let scan = &mut log.scans[i];
            // The line's laser pose keeps its place relative to the robot's.
            scan.laser_pose = distorted.compose(&scan.odometry.between(&scan.laser_pose));
            scan.odometry = distorted;
        } else {
            log.odometry[i].pose = distorted;
        }
    }
}

/// The systematic error of wheel odometry, estimated from matched steps.
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryBias {
    /// The forgetting factor per observed step, `1 − 1/window`.
    keep: f64,
    /// Rotation: normal equations over (turned, driven forward) for (per rad, per m).
    rotation_information: [[f64; 2]; 2],
    rotation_moment: [f64; 2],
    /// Translation: the sum of squared step lengths and of length × excess.
    translation_information: f64,
    translation_moment: f64,
    /// The current estimate, as the correction to apply (all 0 when the odometry is exact).
    estimate: WheelError,
}

impl OdometryBias {
    /// A bias estimate that forgets with a time constant of `window` observed steps.
    pub fn new(window: f64) -> Self {
        Self {
            keep: 1.0 - 1.0 / window.max(1.0),
            rotation_information: [[0.0; 2]; 2],
            rotation_moment: [0.0; 2],
            translation_information: 0.0,
            translation_moment: 0.0,
            estimate: WheelError::default(),
        }
    }

    /// The estimate, as the correction that takes an odometry step to the matched one.
    pub fn estimate(&self) -> WheelError {
        self.estimate
    }

    /// `step` (an odometry increment in the frame of its start) as the estimate corrects it.
    pub fn correct(&self, step: &Pose2) -> Pose2 {
        self.estimate.apply(step)
    }

    /// Adds one step: what the odometry said (`odometry`) and what the matches found (`found`),
    /// both in the frame of the step's start. `rotation_sigma` is the prior's rotation standard
    /// deviation for the step: a difference beyond four of them is a slip or a bad match, not
    /// the wheels, and is left out.
    pub fn observe(&mut self, odometry: &Pose2, found: &Pose2, rotation_sigma: f64) {
        let excess = wrap_angle(found.theta - odometry.theta);
        if excess.abs() <= 4.0 * rotation_sigma {
            let phi = [odometry.theta, odometry.x];
            for (i, row) in self.rotation_information.iter_mut().enumerate() {
                for (j, cell) in row.iter_mut().enumerate() {
                    *cell = self.keep * *cell + phi[i] * phi[j];
                }
            }
            for (moment, phi) in self.rotation_moment.iter_mut().zip(phi) {
                *moment = self.keep * *moment + phi * excess;
            }
        }
        let length = odometry.x.hypot(odometry.y);
        if length >= MIN_STEP {
            // The found step along the odometry's direction, less the odometry's length.
            let along = (found.x * odometry.x + found.y * odometry.y) / length - length;
            if along.abs() <= 0.5 * length {
                self.translation_information =
                    self.keep * self.translation_information + length * length;
                self.translation_moment = self.keep * self.translation_moment + length * along;
            }
        }
        self.solve();
    }

    fn solve(&mut self) {
        let [[a, b], [c, d]] = self.rotation_information;
        let (a, d) = (a + SHRINKAGE, d + SHRINKAGE);
        let det = a * d - b * c;
        let [m0, m1] = self.rotation_moment;
        let (per_rad, per_m) = ((d * m0 - b * m1) / det, (a * m1 - c * m0) / det);
        let scale = self.translation_moment / (self.translation_information + SHRINKAGE);
        self.estimate = WheelError {
            per_rad: per_rad.clamp(-LIMITS.per_rad, LIMITS.per_rad),
            per_m: per_m.clamp(-LIMITS.per_m, LIMITS.per_m),
            scale: scale.clamp(-LIMITS.scale, LIMITS.scale),
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Steps of a robot driving forward 0.2 m and turning a little, alternately left and right.
    fn steps(n: usize) -> Vec<Pose2> {
        (0..n)
            .map(|k| {
                let turn = if k % 3 == 0 { 0.1 } else { -0.04 };
                Pose2::new(0.2, 0.0, turn)
            })
            .collect()
    }

    fn magnitude(e: &WheelError) -> f64 {
        e.per_rad.abs() + e.per_m.abs() + e.scale.abs()
    }

    #[test]
    fn exact_odometry_is_left_as_it_is() {
        let mut bias = OdometryBias::new(200.0);
        for step in steps(500) {
            bias.observe(&step, &step, 0.01);
        }
        assert!(magnitude(&bias.estimate()) < 1e-12, "{:?}", bias.estimate());
    }

    #[test]
    fn a_drift_per_metre_a_turn_scale_and_a_wheel_scale_are_learned_and_corrected() {
        // The wheels over-report distance by 5 %, turns by 10 %, and turn 0.02 rad per metre.
        let wheels = WheelError {
            per_rad: 0.1,
            per_m: 0.02,
            scale: 0.05,
        };
        let mut bias = OdometryBias::new(200.0);
        for truth in steps(600) {
            bias.observe(&wheels.apply(&truth), &truth, 0.01);
        }
        let e = bias.estimate();
        // The inverse errors: 1 / 1.1 − 1 per radian, −0.02 / 1.1 / 1.05 per odometry metre.
        assert!((e.per_rad - (1.0 / 1.1 - 1.0)).abs() < 0.01, "{e:?}");
        assert!((e.per_m + 0.02 / 1.05 / 1.1).abs() < 0.002, "{e:?}");
        assert!((e.scale - (1.0 / 1.05 - 1.0)).abs() < 0.002, "{e:?}");
        // A corrected step is within a few milliradians and a millimetre of the truth (the
        // odometry's own step is 35 mrad and 12 mm off).
        let truth = Pose2::new(0.25, 0.0, 0.3);
        let corrected = bias.correct(&wheels.apply(&truth));
        assert!(
            (corrected.theta - truth.theta).abs() < 3e-3,
            "{corrected:?}"
        );
        assert!((corrected.x - truth.x).abs() < 1e-3, "{corrected:?}");
    }

    #[test]
    fn a_slip_is_left_out_and_a_few_steps_move_the_estimate_part_of_the_way() {
        let mut bias = OdometryBias::new(200.0);
        let step = Pose2::new(0.2, 0.0, 0.0);
        // One slip of 0.3 rad: far beyond four prior sigmas, ignored.
        bias.observe(&step, &Pose2::new(0.2, 0.0, 0.3), 0.01);
        assert_eq!(bias.estimate().per_m, 0.0);
        // Two steps each 0.01 rad off: shrunk towards no error (0.05 rad/m would fit them).
        for _ in 0..2 {
            bias.observe(&step, &Pose2::new(0.2, 0.0, 0.01), 0.01);
        }
        let per_m = bias.estimate().per_m;
        assert!(per_m > 0.0 && per_m < 0.035, "{per_m}");
    }

    #[test]
    fn the_estimate_forgets_an_old_error_when_the_odometry_changes() {
        let mut bias = OdometryBias::new(100.0);
        let step = Pose2::new(0.2, 0.0, 0.0);
        for _ in 0..500 {
            bias.observe(&step, &Pose2::new(0.2, 0.0, 0.004), 0.01);
        }
        assert!((bias.estimate().per_m - 0.02).abs() < 0.002);
        for _ in 0..500 {
            bias.observe(&step, &step, 0.01);
        }
        assert!(bias.estimate().per_m.abs() < 0.002, "{:?}", bias.estimate());
    }

    /// A log whose robot drives 1 m along x in ten laser lines, with an `ODOM` line between
    /// each two.
    fn straight_log() -> CarmenLog {
        use crate::carmen::{LaserScan, OdometryReading};
        use crate::text::Timestamp;
        let stamp = |t: f64| Timestamp::parse(&format!("{t:.3}"), "t").expect("a time");
        let mut log = CarmenLog::default();
        for k in 0..=10 {
            let t = f64::from(k);
            let pose = Pose2::new(0.1 * t, 0.0, 0.0);
            log.scans.push(LaserScan {
                line: 2 * k as usize + 1,
                timestamp: stamp(t),
                ranges: vec![1.0],
                angle_min: 0.0,
                angle_increment: 0.01,
                max_range: None,
                odometry: pose,
                laser_offset: Pose2::new(0.2, 0.0, 0.0),
                offset_in_line: true,
                laser_pose: pose.compose(&Pose2::new(0.2, 0.0, 0.0)),
            });
            log.odometry.push(OdometryReading {
                line: 2 * k as usize + 2,
                timestamp: stamp(t + 0.5),
                pose: Pose2::new(0.1 * t + 0.05, 0.0, 0.0),
                tv: 0.1,
                rv: 0.0,
                accel: 0.0,
            });
        }
        log
    }

    #[test]
    fn a_distorted_log_turns_both_odometry_streams_alike_and_keeps_the_laser_on_the_robot() {
        let mut log = straight_log();
        let error = WheelError {
            per_rad: 0.0,
            per_m: 0.1,
            scale: 0.0,
        };
        distort_odometry(&mut log, &error, None);
        // 0.1 rad per metre: after 1 m the heading is 0.1, after 0.55 m 0.055, in either stream.
        let last = log.scans.last().expect("scans").odometry;
        assert!((last.theta - 0.1).abs() < 1e-9, "{last:?}");
        let odom = log.odometry[5].pose;
        assert!((odom.theta - 0.055).abs() < 1e-9, "{odom:?}");
        for scan in &log.scans {
            let offset = scan.odometry.between(&scan.laser_pose);
            assert!((offset.x - 0.2).abs() < 1e-9 && offset.theta.abs() < 1e-9);
        }
    }

    #[test]
    fn slips_jump_every_so_often_with_alternating_signs() {
        let mut log = straight_log();
        let slips = Slips {
            every: 4.0,
            translation: 0.3,
            rotation: 0.2,
        };
        distort_odometry(&mut log, &WheelError::default(), Some(&slips));
        // Slips at 4 s (+) and 8 s (−): the headings step up, then back.
        let theta = |k: usize| log.scans[k].odometry.theta;
        assert_eq!(theta(3), 0.0);
        assert!((theta(4) - 0.2).abs() < 1e-9 && (theta(7) - 0.2).abs() < 1e-9);
        assert!(theta(8).abs() < 1e-9 && theta(10).abs() < 1e-9);
    }
}
