//! A static scan's progress folded from its [`StaticScan`] messages: revolutions, the yaw the
//! turntable reached, late and failed steps, and how it ended. Pure: `scan3d scan --wait`
//! follows a scan with it, and `scan3d status` shows it per position.

use scan3d_protocol::{StaticScan, StaticScanOutcome, StaticScanProblem};
use serde::{Deserialize, Serialize};

/// One static scan's progress, as its messages tell it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanProgress {
    /// The scan's number in its edge session.
    pub scan_id: u32,
    /// The position's name (empty until the scan's start is seen).
    pub position: String,
    /// The turn planned, degrees (0 until the start is seen).
    pub total_deg: f64,
    /// Sweep revolutions with yaws so far (the end's count once it ended).
    pub revolutions: u32,
    /// The largest turntable yaw reached, degrees (the final yaw once it ended).
    pub yaw_deg: f64,
    /// Steps that did not finish before the beam left the blocked sector.
    pub late_steps: u64,
    /// Steps the stepper reported failed.
    pub failed_steps: u64,
    /// Warnings of any kind.
    pub warnings: u64,
    /// Samples tagged with a yaw.
    pub tagged: u64,
    /// How it ended: `completed`, `aborted` or `stopped`; `None` while it runs.
    pub outcome: Option<String>,
}

impl ScanProgress {
    /// The progress of scan `scan_id` before any of its messages.
    pub fn new(scan_id: u32) -> Self {
        ScanProgress {
            scan_id,
            position: String::new(),
            total_deg: 0.0,
            revolutions: 0,
            yaw_deg: 0.0,
            late_steps: 0,
            failed_steps: 0,
            warnings: 0,
            tagged: 0,
            outcome: None,
        }
    }

    /// The scan a message is about.
    pub fn scan_of(message: &StaticScan) -> u32 {
        match message {
            StaticScan::Started(start) => start.scan_id,
            StaticScan::Yaws(yaws) => yaws.scan_id,
            StaticScan::Warning(warning) => warning.scan_id,
            StaticScan::Finished(end) => end.scan_id,
        }
    }

    /// Folds in one message; a message of another scan changes nothing (returns false).
    pub fn on_message(&mut self, message: &StaticScan) -> bool {
        if Self::scan_of(message) != self.scan_id {
            return false;
        }
        match message {
            StaticScan::Started(start) => {
                self.position = start.position.clone();
                self.total_deg = start.total_deg;
            }
            StaticScan::Yaws(yaws) => {
                self.revolutions = self.revolutions.saturating_add(1);
                self.tagged = self.tagged.saturating_add(yaws.tagged_samples());
                if let Some(max) = yaws
                    .runs
                    .iter()
                    .map(|run| f64::from(run.yaw_deg))
                    .filter(|yaw| yaw.is_finite())
                    .reduce(f64::max)
                {
                    self.yaw_deg = self.yaw_deg.max(max);
                }
            }
            StaticScan::Warning(warning) => {
                self.warnings = self.warnings.saturating_add(1);
                match warning.problem {
                    StaticScanProblem::LateStep => {
                        self.late_steps = self.late_steps.saturating_add(1)
                    }
                    StaticScanProblem::StepFailed => {
                        self.failed_steps = self.failed_steps.saturating_add(1)
                    }
                    StaticScanProblem::SectorMissed | StaticScanProblem::PredictedLate => {}
                }
            }
            StaticScan::Finished(end) => {
                self.revolutions = end.revolutions;
                if end.yaw_deg.is_finite() {
                    self.yaw_deg = end.yaw_deg;
                }
                self.late_steps = end.late_steps;
                self.failed_steps = end.failed_steps;
                self.tagged = end.tagged;
                self.outcome = Some(outcome_name(end.outcome).to_owned());
            }
        }
        true
    }

    /// Whether the scan ended.
    pub fn is_finished(&self) -> bool {
        self.outcome.is_some()
    }

    /// Whether it ended by turning the whole planned angle.
    pub fn completed(&self) -> bool {
        self.outcome.as_deref() == Some("completed")
    }

    /// The share of the planned turn reached, 0 to 1 (0 before the start is seen).
    pub fn fraction(&self) -> f64 {
        if self.total_deg > 0.0 {
            (self.yaw_deg / self.total_deg).clamp(0.0, 1.0)
        } else {
            0.0
        }
    }

    /// One line for a human: `static scan 0 at "door": 12 revolutions, yaw 45.0° of 360.0°, 0 late steps`.
    pub fn summary(&self) -> String {
        format!(
            "static scan {} at {:?}: {} revolutions, yaw {:.1}° of {:.1}°, {} late steps, {} failed steps",
            self.scan_id,
            self.position,
            self.revolutions,
            self.yaw_deg,
            self.total_deg,
            self.late_steps,
            self.failed_steps
        )
    }
}

/// The name of an outcome in status and replies.
pub fn outcome_name(outcome: StaticScanOutcome) -> &'static str {
    match outcome {
        StaticScanOutcome::Completed => "completed",
        StaticScanOutcome::Aborted => "aborted",
        StaticScanOutcome::Stopped => "stopped",
    }
}

#[cfg(test)]
mod tests {
    use scan3d_protocol::{
        MountInfo, StaticScanEnd, StaticScanStart, StaticScanWarning, StaticScanYaws, YawRun,
    };

    use super::*;

    fn start(scan_id: u32) -> StaticScan {
        StaticScan::Started(StaticScanStart {
            scan_id,
            t_ns: 0,
            position: "door".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 0.0,
            step_deg: 1.8,
            total_deg: 180.0,
            blocked_sector_deg: 60.0,
            mount: MountInfo {
                axis_offset_m: 0.0,
                height_m: 0.5,
                azimuth_zero_deg: 0.0,
            },
        })
    }

    fn yaws(scan_id: u32, yaw_deg: f32) -> StaticScan {
        StaticScan::Yaws(StaticScanYaws {
            scan_id,
            revolution_t0_ns: 0,
            runs: vec![
                YawRun {
                    first_index: 0,
                    count: 10,
                    yaw_deg: yaw_deg - 1.8,
                },
                YawRun {
                    first_index: 10,
                    count: 5,
                    yaw_deg,
                },
            ],
        })
    }

    #[test]
    fn progress_folds_revolutions_yaw_and_late_steps_and_the_end_has_the_last_word() {
        let mut progress = ScanProgress::new(1);
        assert!(!progress.on_message(&start(0)), "another scan's start");
        assert!(progress.on_message(&start(1)));
        assert_eq!(progress.position, "door");
        assert_eq!(progress.fraction(), 0.0);
        assert!(progress.on_message(&yaws(1, 45.0)));
        assert!(progress.on_message(&yaws(1, 90.0)));
        assert!(!progress.on_message(&yaws(2, 170.0)));
        assert_eq!(progress.revolutions, 2);
        assert_eq!(progress.tagged, 30);
        assert_eq!(progress.yaw_deg, 90.0);
        assert_eq!(progress.fraction(), 0.5);
        progress.on_message(&StaticScan::Warning(StaticScanWarning {
            scan_id: 1,
            t_ns: 0,
            revolution: 2,
            problem: StaticScanProblem::LateStep,
            detail: String::new(),
        }));
        assert_eq!((progress.late_steps, progress.warnings), (1, 1));
        assert!(!progress.is_finished());
        assert_eq!(
            progress.summary(),
            "static scan 1 at \"door\": 2 revolutions, yaw 90.0° of 180.0°, 1 late steps, 0 failed steps"
        );
        progress.on_message(&StaticScan::Finished(StaticScanEnd {
            scan_id: 1,
            t_ns: 0,
            outcome: StaticScanOutcome::Stopped,
            yaw_deg: 91.8,
            revolutions: 3,
            tagged: 40,
            blocked: 0,
            untrusted: 0,
            late_steps: 2,
            failed_steps: 0,
        }));
        assert!(progress.is_finished());
        assert!(!progress.completed());
        assert_eq!(progress.outcome.as_deref(), Some("stopped"));
        assert_eq!((progress.revolutions, progress.late_steps), (3, 2));
        assert_eq!(progress.yaw_deg, 91.8);
    }
}
