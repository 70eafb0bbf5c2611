//! How well wheel odometry has agreed with the scans over the last few seconds.
//!
//! Odometry can be wrong for a stretch and right again after it: FR079's reads forward for
//! seconds while the robot backs up, and its heading runs 0.4 rad off for a few seconds
//! elsewhere. A motion prior that trusts it as much as its error model says pulls every match
//! of such a stretch towards it; with scans far enough apart the match settles between the
//! odometry and the scans, and the map is lost.
//!
//! [`OdometryAgreement`] compares the odometry's motion over the last `window` seconds with the
//! matches' over the same span, in the odometry model's standard deviations, translation and
//! heading apart. Where the mean squared error per degree of freedom exceeds `threshold`, it
//! widens that standard deviation of the next prediction by the square root of their ratio, up
//! to `max_widening` (an adaptive filter scaling its process noise by the innovations it
//! sees). Over a window, one late stamp (a step off one way and the next back) cancels out; a
//! stretch of wrong odometry adds up.

use std::collections::VecDeque;

use crate::pose::{Pose2, wrap_angle};

/// The most matches the window keeps, whatever their rate: it bounds the memory a bursty log
/// can take.
const MAX_TRACKED: usize = 4096;

/// The odometry's and the matches' poses over the last few seconds, and how far the
/// odometry's prediction is to be widened for the next scan.
#[derive(Debug, Clone, Default)]
pub struct OdometryAgreement {
    /// `(time, matched pose, odometry pose)`, oldest first: back to the newest one at least a
    /// window before the last.
    track: VecDeque<(f64, Pose2, Pose2)>,
    /// The last window's error (0 before a whole window).
    disagreement: Disagreement,
}

/// Mean squared error per degree of freedom, in the odometry model's standard deviations.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Disagreement {
    translation: f64,
    rotation: f64,
}

/// A factor on each of the odometry's standard deviations: translation (x and y) and heading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Widening {
    /// Along x and y.
    pub translation: f64,
    /// In heading.
    pub rotation: f64,
}

impl Widening {
    /// The odometry as its model says.
    pub const NONE: Self = Self {
        translation: 1.0,
        rotation: 1.0,
    };
}

/// The odometry's error model: the standard deviations it gives a step, the same as the
/// mapper's motion prior.
pub trait StepSigmas {
    /// `(translation m, rotation rad)` standard deviations of an odometry `step`.
    fn step_sigmas(&self, step: &Pose2) -> (f64, f64);
}

impl OdometryAgreement {
    /// Takes a match with the odometry's pose at the same scan, and measures the disagreement
    /// over the last `window` seconds (none until the matches span a whole window).
    pub fn observe(
        &mut self,
        time: f64,
        matched: Pose2,
        odometry: Pose2,
        window: f64,
        model: &impl StepSigmas,
    ) {
        self.track.push_back((time, matched, odometry));
        while self.track.len() > MAX_TRACKED
            || (self.track.len() > 2 && time - self.track[1].0 >= window)
        {
            self.track.pop_front();
        }
        let (then, matched_then, odometry_then) = self.track[0];
        self.disagreement = Disagreement::default();
        if time - then >= window {
            let by_odometry = odometry_then.between(&odometry);
            let by_scans = matched_then.between(&matched);
            let (translation, rotation) = model.step_sigmas(&by_odometry);
            let moved = (by_scans.x - by_odometry.x).hypot(by_scans.y - by_odometry.y);
            let turned = wrap_angle(by_scans.theta - by_odometry.theta);
            self.disagreement = Disagreement {
                translation: (moved / translation).powi(2) / 2.0,
                rotation: (turned / rotation).powi(2),
            };
        }
    }

    /// Forgets the track before the next observation: the odometry's error up to there has
    /// been dealt with (a slip the window search found), and is not to widen the scans after
    /// it.
    pub fn restart(&mut self) {
        self.track.clear();
        self.pause();
    }

    /// Forgets the last window's disagreement (a match not to be compared: untrusted, or a
    /// relocalisation); the track is kept.
    pub fn pause(&mut self) {
        self.disagreement = Disagreement::default();
    }

    /// The factors (1 to `max_widening`) by which the next odometry prediction's translation
    /// and heading standard deviations are to be multiplied.
    pub fn widening(&self, threshold: f64, max_widening: f64) -> Widening {
        let widen = |squared: f64| {
            if threshold <= 0.0 {
                1.0
            } else {
                (squared / threshold)
                    .sqrt()
                    .clamp(1.0, max_widening.max(1.0))
            }
        };
        Widening {
            translation: widen(self.disagreement.translation),
            rotation: widen(self.disagreement.rotation),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mapper's default odometry model: 0.2 m per metre, 0.2 rad per radian and 0.05 rad
    /// per metre, at least 1 cm and 5 mrad.
    struct Model;

    impl StepSigmas for Model {
        fn step_sigmas(&self, step: &Pose2) -> (f64, f64) {
            let distance = step.x.hypot(step.y);
            (
                (0.2 * distance).max(0.01),
                (0.2 * step.theta.abs() + 0.05 * distance).max(0.005),
            )
        }
    }

    /// Drives 0.1 m/s forward for 10 s, scans at 4 Hz; the scans back up at `scans_speed` from
    /// `from` s on; returns the widening after each scan, over a 3 s window.
    fn widenings(scans_speed: f64, from: f64, threshold: f64) -> Vec<Widening> {
        let mut agreement = OdometryAgreement::default();
        let mut matched_x = 0.0;
        (0..40)
            .map(|k| {
                let time = f64::from(k) * 0.25;
                matched_x += 0.025 * if time > from { scans_speed / 0.1 } else { 1.0 };
                agreement.observe(
                    time,
                    Pose2::new(matched_x, 0.0, 0.0),
                    Pose2::new(0.1 * time, 0.0, 0.0),
                    3.0,
                    &Model,
                );
                agreement.widening(threshold, 4.0)
            })
            .collect()
    }

    #[test]
    fn odometry_that_agrees_with_the_scans_is_not_widened() {
        assert!(
            widenings(0.1, 0.0, 5.0)
                .iter()
                .all(|&w| w == Widening::NONE)
        );
    }

    #[test]
    fn a_stretch_of_odometry_reading_forward_while_the_robot_backs_up_is_widened() {
        let after: Vec<f64> = widenings(-0.1, 5.0, 5.0)
            .iter()
            .map(|w| {
                assert_eq!(w.rotation, 1.0, "the heading agrees");
                w.translation
            })
            .collect();
        // Nothing before the stretch, nor while the window's error is below the threshold: at
        // 6 s the scans are 0.2 m behind the odometry's 0.3 m over the window (its sigma 0.06 m),
        // 5.6 sigma² per degree of freedom, widened by sqrt(5.6 / 5).
        assert!(after[..24].iter().all(|&w| w == 1.0), "{after:?}");
        assert!(
            (after[24] - (5.56_f64 / 5.0).sqrt()).abs() < 0.01,
            "{after:?}"
        );
        // Half a metre at 7.5 s: 34.7 per degree of freedom, sqrt(34.7 / 5) = 2.63.
        assert!((after[30] - 2.63).abs() < 0.01, "{after:?}");
        assert!(
            after[21..].windows(2).all(|w| w[1] >= w[0] - 1e-12),
            "{after:?}"
        );
        // Never wider than the limit.
        assert_eq!(widenings(-0.1, 5.0, 0.5)[30].translation, 4.0);
    }

    /// The widening after each scan when the scan at 5 s is matched 0.1 m behind the odometry
    /// and the next agrees again, over a `window`.
    fn after_a_late_stamp(window: f64) -> Vec<Widening> {
        let mut agreement = OdometryAgreement::default();
        (0..40)
            .map(|k| {
                let time = f64::from(k) * 0.25;
                let late = if k == 20 { -0.1 } else { 0.0 };
                agreement.observe(
                    time,
                    Pose2::new(0.1 * time + late, 0.0, 0.0),
                    Pose2::new(0.1 * time, 0.0, 0.0),
                    window,
                    &Model,
                );
                agreement.widening(5.0, 4.0)
            })
            .collect()
    }

    #[test]
    fn a_late_stamp_that_the_next_scan_makes_up_cancels_over_the_window() {
        assert!(after_a_late_stamp(3.0).iter().all(|&w| w == Widening::NONE));
        // Step by step, the late scan and the next disagree by 0.1 m against a 1 cm sigma: 50
        // sigma² per degree of freedom, widened by sqrt(50 / 5).
        let alone = after_a_late_stamp(0.2);
        for k in [20, 21] {
            assert!(
                (alone[k].translation - 10_f64.sqrt()).abs() < 1e-9,
                "{alone:?}"
            );
        }
        assert_eq!(alone[22], Widening::NONE, "{alone:?}");
    }

    /// Scans at 4 Hz driving 0.1 m/s, the odometry jumping 0.3 m ahead at 5 s; with `restart`,
    /// the track is restarted at the slip (the search found it). The widening after each scan,
    /// at a threshold of 1 σ² per degree of freedom (the slip is 3.1 over the window).
    fn after_a_slip(restart: bool) -> Vec<Widening> {
        let mut agreement = OdometryAgreement::default();
        (0..40)
            .map(|k| {
                let time = f64::from(k) * 0.25;
                let slipped = if k >= 20 { 0.3 } else { 0.0 };
                if restart && k == 20 {
                    agreement.restart();
                }
                agreement.observe(
                    time,
                    Pose2::new(0.1 * time, 0.0, 0.0),
                    Pose2::new(0.1 * time + slipped, 0.0, 0.0),
                    3.0,
                    &Model,
                );
                agreement.widening(1.0, 4.0)
            })
            .collect()
    }

    #[test]
    fn a_slip_the_search_has_found_does_not_widen_the_scans_after_it() {
        assert!(after_a_slip(true).iter().all(|&w| w == Widening::NONE));
        // Kept in the track, the slip widens the scans of the next three seconds.
        let kept = after_a_slip(false);
        assert!(kept[20..32].iter().all(|w| w.translation > 1.0), "{kept:?}");
        assert_eq!(kept[32], Widening::NONE, "{kept:?}");
    }
}
