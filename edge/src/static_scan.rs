//! The static-scan controller: one stepper move per Sweep revolution while the beam is blocked,
//! and every sample tagged with the turntable yaw φ it was taken at (the paper's eq. (1)).
//!
//! The Sweep spins in a vertical plane; θ is its device azimuth minus
//! [`StaticScanConfig::azimuth_zero_deg`], so θ = 0 points up and θ = 180° points down into the
//! base, where a sector of [`StaticScanConfig::blocked_sector_deg`] centred on 180° is blind.
//! Per revolution:
//!
//! ```text
//!  θ: 0° ─ first half: φ ─> 150° ─ blocked: step δφ ─> 210° ─ second half: φ + δφ ─> 360°
//!                            ^ StepCommand             ^ the step must be done here
//! ```
//!
//! φ + δφ then is the φ of the next revolution. The controller is sans-I/O and deterministic in
//! the style of `quinn-proto`: no threads, no clock, no I2C. The caller feeds samples with their
//! times ([`StaticScanController::on_sample`]), executes every [`ScanEvent::Step`] on the real
//! stepper (e.g. `stepper.run(&mut hat, cmd.as_move(), &mut delay)`) and reports the outcome
//! with [`StaticScanController::on_step_done`] or [`StaticScanController::on_step_failed`];
//! it pulls [`ScanEvent`]s with [`StaticScanController::poll_event`].
//!
//! **Never silently mis-tagged.** Whether a step finished in time is decided on timestamps,
//! not on call order: the first sample past the sector must be at least
//! [`StaticScanConfig::settle_ms`] later than the reported completion. Second-half samples that
//! arrive while the step is still in flight are held until the outcome is known, then tagged
//! with φ + δφ or, if the step was late or failed, reported as [`ScanEvent::Untrusted`] after a
//! [`ScanEvent::LateStep`] / [`ScanEvent::StepFailed`]. Samples inside the blocked sector are
//! always [`ScanEvent::Blocked`], never tagged.
//!
//! **Duration.** A scan takes one revolution per move: with the defaults (δφ = one step of a
//! 200-step motor = 1.8°, 180° in total) that is 100 revolutions, **100 s at 1 Hz and 50 s at
//! 2 Hz** from the first revolution start to [`ScanEvent::Finished`] (derived by simulation in
//! the tests), plus the return home (100 steps at 100 steps/s: 1 s).

use std::collections::VecDeque;

use serde::Deserialize;

use crate::drivers::stepper::{Direction, Move};
use crate::timing::TimedSample;

/// Held second-half samples beyond this count (a revolution's worth at any Sweep setting is far
/// less) mean the beam is not progressing: the pending step is then treated as late.
const MAX_HELD_SAMPLES: usize = 4096;

/// Settings of a static scan (`[static_scan]` in `edge.toml`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StaticScanConfig {
    /// Width of the blind sector centred on θ = 180°, degrees (default 60).
    pub blocked_sector_deg: f64,
    /// δφ in steps of the stepper's style, commanded once per Sweep revolution (default 1:
    /// 1.8° with a 200-step motor in full steps, direct drive).
    pub steps_per_revolution_of_sweep: u32,
    /// Total turn of the turntable, degrees (default 180: a half turn covers the sphere),
    /// rounded to whole steps.
    pub total_sweep_deg: f64,
    /// The device azimuth that points straight up (θ = 0 of eq. (1)), degrees (default 0).
    pub azimuth_zero_deg: f64,
    /// The fastest the motor follows, in steps of the stepper's style per second (default 100,
    /// the stepper's default `full_steps_per_sec`): a move of n steps needs n / rate.
    pub max_step_rate_hz: f64,
    /// Time after a reported step completion before a sample counts as taken at the new yaw,
    /// milliseconds (default 2): rotor settling. Samples are judged on their measurement times
    /// ([`crate::timing`]), so the serial latency needs no allowance here.
    pub settle_ms: f64,
    /// Consecutive failed steps after which the scan is aborted (default 3).
    pub max_step_failures: u32,
    /// Where the Sweep sits on the turntable (`[static_scan.mount]`); sent with every scan so
    /// the server can apply eq. (1) from the recording alone.
    pub mount: MountConfig,
}

/// The Sweep's optical centre relative to the turntable (the azimuth zero is
/// [`StaticScanConfig::azimuth_zero_deg`]).
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MountConfig {
    /// Distance from the turntable axis along the scan plane's normal, metres.
    pub axis_offset_m: f64,
    /// Height above the floor, metres.
    pub height_m: f64,
}

impl Default for StaticScanConfig {
    fn default() -> Self {
        Self {
            blocked_sector_deg: 60.0,
            steps_per_revolution_of_sweep: 1,
            total_sweep_deg: 180.0,
            azimuth_zero_deg: 0.0,
            max_step_rate_hz: 100.0,
            settle_ms: 2.0,
            max_step_failures: 3,
            mount: MountConfig::default(),
        }
    }
}

/// Whether a move fits in the blind sector at a given rotation rate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepBudget {
    /// Steps per move (δφ).
    pub steps: u32,
    /// The Sweep's rotation rate, revolutions per second.
    pub rotation_hz: f64,
    /// Time the move needs: steps / max step rate + settle time, ns.
    pub needed_ns: u64,
    /// Time the beam spends in the blocked sector, ns.
    pub available_ns: u64,
}

impl StepBudget {
    /// The move can finish before the beam leaves the sector.
    pub fn fits(&self) -> bool {
        self.needed_ns <= self.available_ns
    }
}

impl StaticScanConfig {
    /// Checks every setting; the controller only accepts a validated configuration.
    pub fn validate(&self) -> Result<(), StaticScanError> {
        if !(self.blocked_sector_deg.is_finite()
            && self.blocked_sector_deg > 0.0
            && self.blocked_sector_deg < 360.0)
        {
            return Err(StaticScanError::Sector(self.blocked_sector_deg));
        }
        if self.steps_per_revolution_of_sweep == 0
            || i32::try_from(self.steps_per_revolution_of_sweep).is_err()
        {
            return Err(StaticScanError::NotPositive(
                "steps_per_revolution_of_sweep",
            ));
        }
        for (name, value) in [
            ("total_sweep_deg", self.total_sweep_deg),
            ("max_step_rate_hz", self.max_step_rate_hz),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(StaticScanError::NotPositive(name));
            }
        }
        if !(self.settle_ms.is_finite() && self.settle_ms >= 0.0) {
            return Err(StaticScanError::NotPositive("settle_ms"));
        }
        if !self.azimuth_zero_deg.is_finite() {
            return Err(StaticScanError::NotPositive("azimuth_zero_deg"));
        }
        if self.max_step_failures == 0 {
            return Err(StaticScanError::NotPositive("max_step_failures"));
        }
        Ok(())
    }

    /// Predicts whether one move of δφ fits in the blocked sector at `rotation_hz`
    /// (`None` if the rate is not positive and finite). Usable at configuration time with the
    /// Sweep's configured motor speed.
    pub fn step_budget(&self, rotation_hz: f64) -> Option<StepBudget> {
        if !(rotation_hz.is_finite() && rotation_hz > 0.0) {
            return None;
        }
        let steps = self.steps_per_revolution_of_sweep;
        let needed_s = f64::from(steps) / self.max_step_rate_hz + self.settle_ms * 1e-3;
        let available_s = self.blocked_sector_deg / (360.0 * rotation_hz);
        Some(StepBudget {
            steps,
            rotation_hz,
            needed_ns: seconds_to_ns(needed_s),
            available_ns: seconds_to_ns(available_s),
        })
    }
}

fn seconds_to_ns(s: f64) -> u64 {
    (s * 1e9).round().clamp(0.0, u64::MAX as f64) as u64
}

/// Why a configuration or a caller's report was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StaticScanError {
    /// A numeric setting is zero, negative or not finite.
    #[error("static scan setting `{0}` must be positive and finite")]
    NotPositive(&'static str),
    /// The blocked sector must be wider than 0° and narrower than 360°.
    #[error("blocked sector of {0}° is invalid (more than 0°, less than 360°)")]
    Sector(f64),
    /// The stepper's step angle is not positive and finite.
    #[error("step angle {0}° is invalid (positive and finite)")]
    StepAngle(f64),
    /// The total sweep is less than half a step.
    #[error("a total sweep of {total_deg}° is less than one step of {step_deg}°")]
    SweepTooSmall {
        /// Configured total sweep, degrees.
        total_deg: f64,
        /// The stepper's step angle, degrees.
        step_deg: f64,
    },
    /// A step outcome was reported while no step was in flight.
    #[error("a step outcome was reported but no step is in flight")]
    NoStepInFlight,
    /// The stepper is set to step faster than the motor can follow: steps would be lost and
    /// every later yaw would be wrong, so no scan starts.
    #[error(
        "the stepper steps at {commanded_hz:.0} steps/s but the motor follows at most \
         {max_hz:.0} (static_scan.max_step_rate_hz): steps would be lost"
    )]
    Overspeed {
        /// The stepper's configured rate, steps per second.
        commanded_hz: f64,
        /// The motor's limit.
        max_hz: f64,
    },
    /// A failed step reported more steps done than commanded.
    #[error("{done} steps reported done of a move of {commanded}")]
    StepsDone {
        /// Steps reported done.
        done: i32,
        /// Steps commanded.
        commanded: i32,
    },
}

/// A move for the caller to execute on the stepper now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepCommand {
    /// Steps of the stepper's style; positive = [`Direction::Forward`] (increasing φ).
    pub steps: i32,
    /// Predicted time the beam leaves the blocked sector (edge clock, ns): the move must be
    /// complete by then. `None` before the rotation rate is known.
    pub deadline_ns: Option<u64>,
}

impl StepCommand {
    /// The move for [`crate::drivers::stepper::Stepper::run`].
    pub fn as_move(&self) -> Move {
        Move {
            direction: if self.steps >= 0 {
                Direction::Forward
            } else {
                Direction::Backward
            },
            steps: u64::from(self.steps.unsigned_abs()),
        }
    }
}

/// Which half of a revolution a sample belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Half {
    /// θ before the blocked sector (from 0° up): the yaw before this revolution's move.
    First,
    /// θ after the blocked sector: the yaw after this revolution's move.
    Second,
}

/// A sample with the turntable yaw in effect when it was taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TaggedSample {
    /// The sample as fed (device azimuth, range, quality, time).
    pub sample: TimedSample,
    /// θ of eq. (1): device azimuth minus the azimuth zero, degrees in [0, 360).
    pub theta_deg: f64,
    /// φ, degrees from home (yaw steps × step angle).
    pub yaw_deg: f64,
    /// φ in steps of the stepper's style from home.
    pub yaw_steps: i64,
    /// Which half of the revolution.
    pub half: Half,
    /// Revolution index (counted from 0 at the start of the scan).
    pub revolution: u32,
}

/// Why a sample is reported as [`ScanEvent::Untrusted`] instead of tagged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UntrustedReason {
    /// Second half of a revolution whose move did not finish before the beam left the sector.
    LateStep,
    /// Second half of a revolution whose move failed: the rotor position is uncertain.
    StepFailed,
    /// Taken while a move (late from an earlier revolution) was still in flight or settling.
    StepInFlight,
    /// The azimuth went backwards without a revolution wrap: the sample fits no half.
    OutOfOrder,
    /// The azimuth is not a finite number.
    InvalidAzimuth,
}

/// What the controller reports, in order.
#[derive(Debug, Clone, PartialEq)]
pub enum ScanEvent {
    /// Execute this move now (the beam just entered the blocked sector).
    Step(StepCommand),
    /// A sample with its yaw, ready for eq. (1).
    Tagged(TaggedSample),
    /// A sample inside the blocked sector: it sees the base, never a 3D point.
    Blocked(TimedSample),
    /// A sample whose yaw is not known for sure; do not use it.
    Untrusted {
        /// The sample as fed.
        sample: TimedSample,
        /// Why.
        reason: UntrustedReason,
    },
    /// A move did not finish before the beam left the blocked sector.
    LateStep {
        /// Revolution of the move.
        revolution: u32,
        /// Time of the first sample past the sector (the real deadline), ns.
        expected_by_ns: u64,
        /// Reported completion, or `None` if still in flight when the revolution ended.
        done_at_ns: Option<u64>,
    },
    /// The caller reported a failed move.
    StepFailed {
        /// Revolution of the move.
        revolution: u32,
        /// Steps that were done before the failure (they count towards φ).
        steps_done: i32,
        /// When the failure was reported, ns.
        at_ns: u64,
    },
    /// No sample fell into the blocked sector this revolution (samples lost), so no move was
    /// made; the second half keeps φ.
    SectorMissed {
        /// The revolution.
        revolution: u32,
    },
    /// A move of δφ at the maximum step rate cannot fit in the sector at the measured
    /// rotation rate: expect [`ScanEvent::LateStep`]s.
    PredictedLate(StepBudget),
    /// The turntable turned the total sweep and the last revolution ended.
    Finished {
        /// Time of the first sample after the last revolution, ns.
        at_ns: u64,
        /// Final φ, degrees.
        yaw_deg: f64,
        /// Full revolutions from the first revolution start.
        revolutions: u32,
    },
    /// Too many consecutive moves failed; the scan stopped.
    Aborted {
        /// When, ns.
        at_ns: u64,
        /// φ reached, degrees.
        yaw_deg: f64,
        /// Consecutive failures.
        failures: u32,
    },
    /// Turn back to home (after [`ScanEvent::Finished`] or [`ScanEvent::Aborted`]), e.g. with
    /// [`crate::drivers::stepper::Stepper::return_home`].
    ReturnHome {
        /// The controller's count of steps to undo (−φ in steps).
        steps: i64,
    },
}

/// Counters of what the controller reported.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ScanStats {
    /// Samples tagged with a yaw.
    pub tagged: u64,
    /// Samples in the blocked sector.
    pub blocked: u64,
    /// Samples reported untrusted.
    pub untrusted: u64,
    /// Samples fed after the scan ended (ignored).
    pub ignored: u64,
    /// Moves commanded.
    pub steps_commanded: u64,
    /// Late moves.
    pub late_steps: u64,
    /// Failed moves.
    pub failed_steps: u64,
    /// Revolutions without a sample in the blocked sector.
    pub sectors_missed: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Before the first revolution start (the scan began inside or after the sector).
    Lead,
    /// Before the sector.
    First,
    /// In the sector.
    InSector,
    /// After the sector.
    Second,
    /// Finished or aborted.
    Over,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Region {
    First,
    Blocked,
    Second,
}

#[derive(Debug, Clone, Copy)]
enum Outcome {
    Done { at_ns: u64 },
    Failed,
}

#[derive(Debug, Clone, Copy)]
struct PendingStep {
    steps: i32,
    revolution: u32,
    outcome: Option<Outcome>,
    /// Still in flight after its revolution ended (its lateness was already reported).
    overdue: bool,
}

#[derive(Debug, Clone)]
enum SecondHalf {
    Trusted,
    Held {
        exit_ns: u64,
        samples: Vec<TimedSample>,
    },
    Untrusted(UntrustedReason),
}

/// Rotation rate from sample times: angle travelled over time across the last revolution.
#[derive(Debug, Clone, Default)]
struct RateEstimator {
    last: Option<(u64, f64)>,
    window: VecDeque<(u64, f64)>,
}

impl RateEstimator {
    /// Window points are kept at least this far apart.
    const POINT_DEG: f64 = 5.0;
    /// No estimate before the beam travelled this far.
    const MIN_SPAN_DEG: f64 = 30.0;

    fn push(&mut self, t_ns: u64, theta_deg: f64) {
        let unwrapped = match self.last {
            None => theta_deg,
            Some((_, previous)) => {
                let delta = (theta_deg - previous.rem_euclid(360.0)).rem_euclid(360.0);
                // More than half a turn forward is a small step backwards (jitter).
                previous + if delta > 180.0 { delta - 360.0 } else { delta }
            }
        };
        self.last = Some((t_ns, unwrapped));
        if self
            .window
            .back()
            .is_none_or(|&(_, u)| unwrapped - u >= Self::POINT_DEG)
        {
            self.window.push_back((t_ns, unwrapped));
        }
        while self.window.len() > 1
            && self
                .window
                .front()
                .is_some_and(|&(_, u)| unwrapped - u > 360.0)
        {
            self.window.pop_front();
        }
    }

    fn deg_per_s(&self) -> Option<f64> {
        let (t1, u1) = self.last?;
        let &(t0, u0) = self.window.front()?;
        if u1 - u0 < Self::MIN_SPAN_DEG || t1 <= t0 {
            return None;
        }
        Some((u1 - u0) / ((t1 - t0) as f64 * 1e-9))
    }
}

/// Drives a static scan: commands one move per revolution and tags every sample with φ.
#[derive(Debug, Clone)]
pub struct StaticScanController {
    config: StaticScanConfig,
    step_angle_deg: f64,
    sector_start_deg: f64,
    sector_end_deg: f64,
    target_steps: i64,
    settle_ns: u64,
    yaw_steps: i64,
    settled_at_ns: u64,
    revolution: u32,
    had_lead: bool,
    phase: Phase,
    last_theta: Option<f64>,
    step: Option<PendingStep>,
    second: SecondHalf,
    failures: u32,
    rate: RateEstimator,
    last_fit: Option<bool>,
    events: VecDeque<ScanEvent>,
    stats: ScanStats,
}

impl StaticScanController {
    /// A controller at φ = 0 for a stepper whose step is `step_angle_deg` at the turntable
    /// (`Stepper::step_angle_deg()`, which includes the step style and the gear ratio).
    pub fn new(config: StaticScanConfig, step_angle_deg: f64) -> Result<Self, StaticScanError> {
        config.validate()?;
        if !(step_angle_deg.is_finite() && step_angle_deg > 0.0) {
            return Err(StaticScanError::StepAngle(step_angle_deg));
        }
        let target = (config.total_sweep_deg / step_angle_deg).round();
        if target < 1.0 {
            return Err(StaticScanError::SweepTooSmall {
                total_deg: config.total_sweep_deg,
                step_deg: step_angle_deg,
            });
        }
        let half_sector = config.blocked_sector_deg / 2.0;
        Ok(Self {
            step_angle_deg,
            sector_start_deg: 180.0 - half_sector,
            sector_end_deg: 180.0 + half_sector,
            target_steps: target.min(i64::MAX as f64) as i64,
            settle_ns: seconds_to_ns(config.settle_ms * 1e-3),
            config,
            yaw_steps: 0,
            settled_at_ns: 0,
            revolution: 0,
            had_lead: false,
            phase: Phase::Lead,
            last_theta: None,
            step: None,
            second: SecondHalf::Trusted,
            failures: 0,
            rate: RateEstimator::default(),
            last_fit: None,
            events: VecDeque::new(),
            stats: ScanStats::default(),
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &StaticScanConfig {
        &self.config
    }

    /// φ in steps from home (steps reported done).
    pub fn yaw_steps(&self) -> i64 {
        self.yaw_steps
    }

    /// φ in degrees from home.
    pub fn yaw_deg(&self) -> f64 {
        self.yaw_steps as f64 * self.step_angle_deg
    }

    /// Steps from home at which the scan is complete (total sweep / step angle, rounded).
    pub fn target_steps(&self) -> i64 {
        self.target_steps
    }

    /// The current revolution index.
    pub fn revolution(&self) -> u32 {
        self.revolution
    }

    /// The Sweep's rotation rate estimated from sample times, revolutions per second.
    pub fn rotation_hz(&self) -> Option<f64> {
        self.rate.deg_per_s().map(|d| d / 360.0)
    }

    /// The scan finished or was aborted; further samples are ignored.
    pub fn is_over(&self) -> bool {
        self.phase == Phase::Over
    }

    /// Counters since construction.
    pub fn stats(&self) -> ScanStats {
        self.stats
    }

    /// The next event, if any.
    pub fn poll_event(&mut self) -> Option<ScanEvent> {
        self.events.pop_front()
    }

    /// Feeds one Sweep sample; `angle_deg` is the device azimuth and `t_ns` its measurement time
    /// on the edge clock, the one it has in its revolution frame
    /// ([`crate::timing::RevolutionAssembler::stamp`]). Samples must come in stream order.
    pub fn on_sample(&mut self, sample: &TimedSample) {
        if self.phase == Phase::Over {
            self.stats.ignored += 1;
            return;
        }
        let azimuth = f64::from(sample.angle_deg);
        if !azimuth.is_finite() {
            self.untrusted(*sample, UntrustedReason::InvalidAzimuth);
            return;
        }
        let theta = self.theta_of(azimuth);
        self.rate.push(sample.t_ns, theta);
        if self.last_fit.is_none() {
            self.check_budget();
        }
        let region = self.region(theta);
        match self.last_theta {
            None if region == Region::First => self.phase = Phase::First,
            None => self.had_lead = true,
            Some(last) if theta + 180.0 < last => {
                self.end_revolution(sample.t_ns);
                if self.phase == Phase::Over {
                    return;
                }
            }
            Some(_) => {}
        }
        self.last_theta = Some(theta);
        match (self.phase, region) {
            (Phase::Over, _) => {}
            (phase, Region::Blocked) => {
                if phase == Phase::First {
                    self.enter_sector(sample.t_ns, theta);
                }
                self.stats.blocked += 1;
                self.events.push_back(ScanEvent::Blocked(*sample));
            }
            (Phase::First, Region::First) => self.tag_unless_moving(*sample, theta, Half::First),
            (_, Region::First) => self.untrusted(*sample, UntrustedReason::OutOfOrder),
            (Phase::First, Region::Second) => {
                self.stats.sectors_missed += 1;
                self.events.push_back(ScanEvent::SectorMissed {
                    revolution: self.revolution,
                });
                self.phase = Phase::Second;
                self.second = if self.step.is_some() {
                    SecondHalf::Untrusted(UntrustedReason::StepInFlight)
                } else {
                    SecondHalf::Trusted
                };
                self.second_half(*sample, theta);
            }
            (Phase::InSector, Region::Second) => self.exit_sector(*sample, theta),
            (Phase::Second, Region::Second) => self.second_half(*sample, theta),
            (Phase::Lead, Region::Second) => self.tag_unless_moving(*sample, theta, Half::Second),
        }
    }

    /// Reports that the last [`ScanEvent::Step`] completed at `t_ns` (edge clock): the time
    /// the rotor is at the new position, i.e. the last coil write plus one step period.
    pub fn on_step_done(&mut self, t_ns: u64) -> Result<(), StaticScanError> {
        let step = self.in_flight()?;
        self.yaw_steps += i64::from(step.steps);
        self.failures = 0;
        self.settled_at_ns = t_ns.saturating_add(self.settle_ns);
        if step.overdue {
            // Its lateness was reported when its revolution ended.
            self.step = None;
            return Ok(());
        }
        match std::mem::replace(&mut self.second, SecondHalf::Trusted) {
            SecondHalf::Held { exit_ns, samples } => {
                self.step = None;
                self.judge(step.revolution, exit_ns, t_ns);
                for sample in samples {
                    let theta = self.theta_of(f64::from(sample.angle_deg));
                    self.second_half(sample, theta);
                }
            }
            other => {
                // Still in the sector: judged when the beam leaves it.
                self.second = other;
                if let Some(pending) = self.step.as_mut() {
                    pending.outcome = Some(Outcome::Done { at_ns: t_ns });
                }
            }
        }
        Ok(())
    }

    /// Reports that the last [`ScanEvent::Step`] failed at `t_ns` after `steps_done` of its
    /// steps (the stepper's index reflects them). The revolution's second half is untrusted;
    /// the move is retried at the next sector, and the scan aborts after
    /// [`StaticScanConfig::max_step_failures`] consecutive failures.
    pub fn on_step_failed(&mut self, t_ns: u64, steps_done: i32) -> Result<(), StaticScanError> {
        let step = self.in_flight()?;
        let within = if step.steps >= 0 {
            (0..=step.steps).contains(&steps_done)
        } else {
            (step.steps..=0).contains(&steps_done)
        };
        if !within {
            return Err(StaticScanError::StepsDone {
                done: steps_done,
                commanded: step.steps,
            });
        }
        self.yaw_steps += i64::from(steps_done);
        self.failures += 1;
        self.settled_at_ns = t_ns.saturating_add(self.settle_ns);
        self.stats.failed_steps += 1;
        self.events.push_back(ScanEvent::StepFailed {
            revolution: step.revolution,
            steps_done,
            at_ns: t_ns,
        });
        if step.overdue {
            self.step = None;
        } else {
            match std::mem::replace(&mut self.second, SecondHalf::Trusted) {
                SecondHalf::Held { samples, .. } => {
                    self.step = None;
                    self.second = SecondHalf::Untrusted(UntrustedReason::StepFailed);
                    for sample in samples {
                        self.untrusted(sample, UntrustedReason::StepFailed);
                    }
                }
                other => {
                    // Still in the sector: the second half is judged when the beam leaves it.
                    self.second = other;
                    if let Some(pending) = self.step.as_mut() {
                        pending.outcome = Some(Outcome::Failed);
                    }
                }
            }
        }
        if self.failures >= self.config.max_step_failures {
            self.step = None;
            self.phase = Phase::Over;
            self.events.push_back(ScanEvent::Aborted {
                at_ns: t_ns,
                yaw_deg: self.yaw_deg(),
                failures: self.failures,
            });
            self.events.push_back(ScanEvent::ReturnHome {
                steps: -self.yaw_steps,
            });
        }
        Ok(())
    }

    fn in_flight(&self) -> Result<PendingStep, StaticScanError> {
        self.step
            .filter(|s| s.outcome.is_none())
            .ok_or(StaticScanError::NoStepInFlight)
    }

    /// θ of eq. (1) in [0, 360) for a finite device azimuth (the protocol's one definition,
    /// which the server's eq. (1) uses too).
    fn theta_of(&self, azimuth_deg: f64) -> f64 {
        scan3d_protocol::theta_deg(azimuth_deg, self.config.azimuth_zero_deg)
    }

    fn region(&self, theta: f64) -> Region {
        if theta < self.sector_start_deg {
            Region::First
        } else if theta <= self.sector_end_deg {
            Region::Blocked
        } else {
            Region::Second
        }
    }

    fn check_budget(&mut self) {
        let Some(budget) = self
            .rotation_hz()
            .and_then(|hz| self.config.step_budget(hz))
        else {
            return;
        };
        let fits = budget.fits();
        if !fits && self.last_fit != Some(false) {
            self.events.push_back(ScanEvent::PredictedLate(budget));
        }
        self.last_fit = Some(fits);
    }

    fn enter_sector(&mut self, t_ns: u64, theta: f64) {
        self.phase = Phase::InSector;
        if self.step.is_some() || self.yaw_steps >= self.target_steps {
            return;
        }
        let remaining = self.target_steps - self.yaw_steps;
        let steps = i64::from(self.config.steps_per_revolution_of_sweep).min(remaining);
        let steps = i32::try_from(steps).unwrap_or(i32::MAX);
        let deadline_ns = self.rate.deg_per_s().map(|deg_per_s| {
            let to_exit_s = (self.sector_end_deg - theta).max(0.0) / deg_per_s;
            t_ns.saturating_add(seconds_to_ns(to_exit_s))
        });
        self.step = Some(PendingStep {
            steps,
            revolution: self.revolution,
            outcome: None,
            overdue: false,
        });
        self.stats.steps_commanded += 1;
        self.events
            .push_back(ScanEvent::Step(StepCommand { steps, deadline_ns }));
    }

    /// The first sample past the sector: decide (or defer) the second half's trust.
    fn exit_sector(&mut self, sample: TimedSample, theta: f64) {
        self.phase = Phase::Second;
        self.second = SecondHalf::Trusted;
        if let Some(step) = self.step {
            match step.outcome {
                _ if step.overdue => {
                    self.second = SecondHalf::Untrusted(UntrustedReason::StepInFlight);
                }
                None => {
                    self.second = SecondHalf::Held {
                        exit_ns: sample.t_ns,
                        samples: Vec::new(),
                    };
                }
                Some(Outcome::Done { at_ns }) => {
                    self.step = None;
                    self.judge(step.revolution, sample.t_ns, at_ns);
                }
                Some(Outcome::Failed) => {
                    self.step = None;
                    self.second = SecondHalf::Untrusted(UntrustedReason::StepFailed);
                }
            }
        }
        self.second_half(sample, theta);
    }

    /// Sets the second half's trust from the exit time and the completion time of its move.
    fn judge(&mut self, revolution: u32, exit_ns: u64, done_at_ns: u64) {
        if exit_ns >= done_at_ns.saturating_add(self.settle_ns) {
            self.second = SecondHalf::Trusted;
        } else {
            self.report_late(revolution, exit_ns, Some(done_at_ns));
            self.second = SecondHalf::Untrusted(UntrustedReason::LateStep);
        }
    }

    fn report_late(&mut self, revolution: u32, expected_by_ns: u64, done_at_ns: Option<u64>) {
        self.stats.late_steps += 1;
        self.events.push_back(ScanEvent::LateStep {
            revolution,
            expected_by_ns,
            done_at_ns,
        });
    }

    fn second_half(&mut self, sample: TimedSample, theta: f64) {
        match &mut self.second {
            SecondHalf::Trusted => self.tag_unless_moving(sample, theta, Half::Second),
            SecondHalf::Held { exit_ns, samples } => {
                samples.push(sample);
                if samples.len() > MAX_HELD_SAMPLES {
                    let exit_ns = *exit_ns;
                    self.give_up_on_held(exit_ns);
                }
            }
            SecondHalf::Untrusted(reason) => {
                let reason = *reason;
                self.untrusted(sample, reason);
            }
        }
    }

    /// The move is still in flight and the held second half can wait no longer: it is late.
    fn give_up_on_held(&mut self, exit_ns: u64) {
        let held = std::mem::replace(
            &mut self.second,
            SecondHalf::Untrusted(UntrustedReason::LateStep),
        );
        if let Some(step) = self.step.as_mut() {
            step.overdue = true;
            let revolution = step.revolution;
            self.report_late(revolution, exit_ns, None);
        }
        if let SecondHalf::Held { samples, .. } = held {
            for sample in samples {
                self.untrusted(sample, UntrustedReason::LateStep);
            }
        }
    }

    fn end_revolution(&mut self, t_ns: u64) {
        match self.phase {
            Phase::Lead | Phase::Over => {}
            Phase::First => {
                self.stats.sectors_missed += 1;
                self.events.push_back(ScanEvent::SectorMissed {
                    revolution: self.revolution,
                });
            }
            Phase::InSector => {
                if let Some(step) = self.step.as_mut() {
                    if step.outcome.is_some() {
                        self.step = None;
                    } else if !step.overdue {
                        step.overdue = true;
                        let revolution = step.revolution;
                        self.report_late(revolution, t_ns, None);
                    }
                }
            }
            Phase::Second => {
                if let SecondHalf::Held { exit_ns, .. } = self.second {
                    self.give_up_on_held(exit_ns);
                }
            }
        }
        self.second = SecondHalf::Trusted;
        self.revolution = self.revolution.saturating_add(1);
        self.check_budget();
        if self.step.is_none() && self.yaw_steps >= self.target_steps {
            self.phase = Phase::Over;
            self.events.push_back(ScanEvent::Finished {
                at_ns: t_ns,
                yaw_deg: self.yaw_deg(),
                revolutions: self.revolution - u32::from(self.had_lead),
            });
            self.events.push_back(ScanEvent::ReturnHome {
                steps: -self.yaw_steps,
            });
        } else {
            self.phase = Phase::First;
        }
    }

    /// Tags a sample with the current φ, unless a move is in flight or still settling.
    fn tag_unless_moving(&mut self, sample: TimedSample, theta: f64, half: Half) {
        let moving = self.step.is_some_and(|s| s.outcome.is_none());
        if moving || sample.t_ns < self.settled_at_ns {
            self.untrusted(sample, UntrustedReason::StepInFlight);
            return;
        }
        self.stats.tagged += 1;
        self.events.push_back(ScanEvent::Tagged(TaggedSample {
            sample,
            theta_deg: theta,
            yaw_deg: self.yaw_deg(),
            yaw_steps: self.yaw_steps,
            half,
            revolution: self.revolution,
        }));
    }

    fn untrusted(&mut self, sample: TimedSample, reason: UntrustedReason) {
        self.stats.untrusted += 1;
        self.events
            .push_back(ScanEvent::Untrusted { sample, reason });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drivers::stepper::{Stepper, StepperConfig};

    /// Edge-clock time of the first synthetic sample.
    const T0: u64 = 1_000_000_000;

    /// A synthetic Sweep: `per_rev` samples per revolution, one every `period_ns`, θ from
    /// `start_index` × 360°/`per_rev`, device azimuth = θ + `zero` (wrapping at 360°).
    fn sweep(
        per_rev: u64,
        period_ns: u64,
        zero: f64,
        start_index: u64,
        count: u64,
    ) -> Vec<TimedSample> {
        (0..count)
            .map(|i| {
                let theta = 360.0 * ((start_index + i) % per_rev) as f64 / per_rev as f64;
                TimedSample {
                    angle_deg: (theta + zero).rem_euclid(360.0) as f32,
                    range_m: 2.0,
                    quality: 100,
                    t_ns: T0 + i * period_ns,
                }
            })
            .collect()
    }

    /// Ground truth of sample `i` of [`sweep`] started at index 0: (revolution, θ).
    fn truth(per_rev: u64, i: u64) -> (u64, f64) {
        (i / per_rev, 360.0 * (i % per_rev) as f64 / per_rev as f64)
    }

    fn index_of(sample: &TimedSample, period_ns: u64) -> u64 {
        (sample.t_ns - T0) / period_ns
    }

    fn controller(config: StaticScanConfig) -> StaticScanController {
        let stepper = Stepper::new(&StepperConfig::default()).unwrap();
        StaticScanController::new(config, stepper.step_angle_deg()).unwrap()
    }

    fn drain(ctrl: &mut StaticScanController, out: &mut Vec<ScanEvent>) {
        while let Some(event) = ctrl.poll_event() {
            out.push(event);
        }
    }

    /// What a run produced: all events, and the sample fed just before each step command.
    struct Run {
        events: Vec<ScanEvent>,
        triggers: Vec<TimedSample>,
    }

    /// Feeds `samples` like a caller executing moves: move number k (from 0) is reported done
    /// `move_ns(k)` after the sample that triggered it, before the first sample at or after
    /// that time.
    fn run(
        ctrl: &mut StaticScanController,
        samples: &[TimedSample],
        mut move_ns: impl FnMut(usize) -> u64,
    ) -> Run {
        let mut events = Vec::new();
        let mut triggers = Vec::new();
        let mut done_at: Option<u64> = None;
        for sample in samples {
            if let Some(at) = done_at.filter(|&at| at <= sample.t_ns) {
                ctrl.on_step_done(at).unwrap();
                done_at = None;
                drain(ctrl, &mut events);
            }
            ctrl.on_sample(sample);
            let start = events.len();
            drain(ctrl, &mut events);
            for event in &events[start..] {
                if let ScanEvent::Step(_) = event {
                    assert!(done_at.is_none(), "a step while one is in flight");
                    done_at = Some(sample.t_ns + move_ns(triggers.len()));
                    triggers.push(*sample);
                }
            }
        }
        Run { events, triggers }
    }

    fn tagged(events: &[ScanEvent]) -> impl Iterator<Item = &TaggedSample> {
        events.iter().filter_map(|e| match e {
            ScanEvent::Tagged(t) => Some(t),
            _ => None,
        })
    }

    fn steps(events: &[ScanEvent]) -> Vec<StepCommand> {
        events
            .iter()
            .filter_map(|e| match e {
                ScanEvent::Step(c) => Some(*c),
                _ => None,
            })
            .collect()
    }

    const MS: u64 = 1_000_000;

    #[test]
    fn the_step_is_commanded_on_entering_the_sector_once_per_revolution() {
        // 1 Hz, 1000 samples/s: 0.36° per sample; the first θ ≥ 150° is sample 417 (150.12°).
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(1000, MS, 0.0, 0, 5 * 1000 + 1);
        let out = run(&mut ctrl, &samples, |_| 10 * MS);
        let commands = steps(&out.events);
        assert_eq!(commands.len(), 5);
        for (k, (command, trigger)) in commands.iter().zip(&out.triggers).enumerate() {
            assert_eq!(command.steps, 1);
            assert_eq!(command.as_move().direction, Direction::Forward);
            assert_eq!(trigger.t_ns, T0 + (k as u64 * 1000 + 417) * MS);
            // The beam leaves the sector at 210°: (210 − 150.12)/360 s later.
            let deadline = command.deadline_ns.expect("rate known after 150°");
            let expected = trigger.t_ns as f64 + (210.0 - 150.12) / 360.0 * 1e9;
            assert!(
                (deadline as f64 - expected).abs() < 10_000.0,
                "{deadline} {expected}"
            );
        }
        assert_eq!(ctrl.stats().steps_commanded, 5);
        assert_eq!(ctrl.stats().late_steps, 0);
        let hz = ctrl.rotation_hz().unwrap();
        assert!((hz - 1.0).abs() < 1e-4, "{hz}");
    }

    #[test]
    fn the_halves_carry_phi_and_phi_plus_delta_phi_and_the_sector_is_never_tagged() {
        // 2 Hz, 1000 samples/s: 500 samples per revolution, 0.72° apart.
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(500, MS, 0.0, 0, 3 * 500 + 1);
        let out = run(&mut ctrl, &samples, |_| 10 * MS);
        let mut count = 0;
        for t in tagged(&out.events) {
            let (rev, theta) = truth(500, index_of(&t.sample, MS));
            assert!(
                !(150.0..=210.0).contains(&theta),
                "tagged inside the sector: {theta}"
            );
            let (half, yaw) = if theta < 150.0 {
                (Half::First, rev as f64 * 1.8)
            } else {
                (Half::Second, (rev + 1) as f64 * 1.8)
            };
            assert_eq!((t.half, u64::from(t.revolution)), (half, rev), "θ {theta}");
            assert!(
                (t.yaw_deg - yaw).abs() < 1e-9,
                "rev {rev} θ {theta}: {}",
                t.yaw_deg
            );
            assert!((t.theta_deg - theta).abs() < 1e-4);
            count += 1;
        }
        // Per revolution, θ = 150.48° (sample 209) … 209.52° (sample 291) are blocked: 83.
        let blocked = out
            .events
            .iter()
            .filter(|e| matches!(e, ScanEvent::Blocked(_)))
            .count();
        assert_eq!(blocked, 3 * 83);
        assert_eq!(count + blocked, samples.len());
        // The next revolution starts at φ + δφ of the last one.
        let last = tagged(&out.events).last().unwrap();
        assert_eq!((last.revolution, last.yaw_steps), (3, 3));
    }

    /// Runs a whole default scan; returns (Finished time − start, events).
    fn full_scan(per_rev: u64) -> (u64, Vec<ScanEvent>, StaticScanController) {
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(per_rev, MS, 0.0, 0, 101 * per_rev);
        let out = run(&mut ctrl, &samples, |_| 10 * MS);
        let finished_at = out
            .events
            .iter()
            .find_map(|e| match e {
                ScanEvent::Finished { at_ns, .. } => Some(*at_ns),
                _ => None,
            })
            .expect("finished");
        (finished_at - T0, out.events, ctrl)
    }

    #[test]
    fn a_180_degree_scan_takes_100_revolutions_100_s_at_1_hz_and_50_s_at_2_hz() {
        for (per_rev, seconds) in [(1000, 100), (500, 50)] {
            let (duration_ns, events, ctrl) = full_scan(per_rev);
            assert_eq!(
                duration_ns,
                seconds * 1_000_000_000,
                "{per_rev} samples/rev"
            );
            assert_eq!(steps(&events).len(), 100);
            let tail: Vec<_> = events
                .iter()
                .skip_while(|e| !matches!(e, ScanEvent::Finished { .. }))
                .collect();
            let [
                ScanEvent::Finished {
                    yaw_deg,
                    revolutions,
                    ..
                },
                ScanEvent::ReturnHome { steps },
            ] = tail.as_slice()
            else {
                panic!("{tail:?}");
            };
            assert!((yaw_deg - 180.0).abs() < 1e-9);
            assert_eq!((*revolutions, *steps), (100, -100));
            assert!(ctrl.is_over());
            // The last revolution after the finish is ignored, not tagged.
            assert_eq!(ctrl.stats().ignored, per_rev - 1);
            let last = tagged(&events).last().unwrap();
            assert_eq!((last.revolution, last.half), (99, Half::Second));
            assert!((last.yaw_deg - 180.0).abs() < 1e-9);
        }
    }

    #[test]
    fn a_late_step_is_reported_and_its_second_half_is_not_tagged() {
        // 2 Hz: the beam enters at sample 209 and leaves at sample 292 (210.24°), 83 ms later.
        // The first move takes 100 ms; the others 10 ms.
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(500, MS, 0.0, 0, 2 * 500 + 1);
        let out = run(
            &mut ctrl,
            &samples,
            |k| if k == 0 { 100 * MS } else { 10 * MS },
        );
        let late: Vec<_> = out
            .events
            .iter()
            .filter(|e| matches!(e, ScanEvent::LateStep { .. }))
            .collect();
        assert_eq!(
            late,
            [&ScanEvent::LateStep {
                revolution: 0,
                expected_by_ns: T0 + 292 * MS,
                done_at_ns: Some(T0 + 309 * MS),
            }]
        );
        for t in tagged(&out.events) {
            let (rev, theta) = truth(500, index_of(&t.sample, MS));
            assert!(
                rev != 0 || theta < 150.0,
                "rev 0 second half tagged: {theta}"
            );
        }
        let untrusted: Vec<_> = out
            .events
            .iter()
            .filter_map(|e| match e {
                ScanEvent::Untrusted { sample, reason } => Some((index_of(sample, MS), *reason)),
                _ => None,
            })
            .collect();
        let expected: Vec<_> = (292..500).map(|i| (i, UntrustedReason::LateStep)).collect();
        assert_eq!(untrusted, expected);
        // The rotor did arrive: revolution 1 starts at 1.8° and ends at 3.6°.
        let rev1: Vec<_> = tagged(&out.events).filter(|t| t.revolution == 1).collect();
        assert!(
            rev1.iter()
                .all(|t| t.yaw_steps == 1 + i64::from(t.half == Half::Second))
        );
        assert_eq!(rev1.len(), 500 - 83);
    }

    #[test]
    fn a_step_still_moving_at_the_end_of_its_revolution_taints_samples_until_it_is_done() {
        // The first move takes 600 ms at 2 Hz: done at sample 809, in revolution 1.
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(500, MS, 0.0, 0, 3 * 500 + 1);
        let out = run(
            &mut ctrl,
            &samples,
            |k| if k == 0 { 600 * MS } else { 10 * MS },
        );
        assert!(out.events.contains(&ScanEvent::LateStep {
            revolution: 0,
            expected_by_ns: T0 + 292 * MS,
            done_at_ns: None,
        }));
        // No second move while the first is in flight: revolution 1 gets none.
        let trigger_indices: Vec<_> = out.triggers.iter().map(|s| index_of(s, MS)).collect();
        assert_eq!(trigger_indices, [209, 1209]);
        for event in &out.events {
            match event {
                ScanEvent::Tagged(t) => {
                    let i = index_of(&t.sample, MS);
                    assert!(!(209..1000).contains(&i), "tagged while moving: {i}");
                    if i >= 1000 {
                        // From revolution 2 on, one move behind: φ = (rev − 1) + half.
                        let rev = (i / 500) as i64;
                        assert_eq!(t.yaw_steps, rev - 1 + i64::from(t.half == Half::Second));
                    }
                }
                ScanEvent::Untrusted { sample, reason } => {
                    let i = index_of(sample, MS);
                    let expected = if i < 500 {
                        UntrustedReason::LateStep
                    } else {
                        UntrustedReason::StepInFlight
                    };
                    assert_eq!(*reason, expected, "sample {i}");
                }
                _ => {}
            }
        }
        // Rev 0 second half (292..500), rev 1 first half (500..709) and second half (792..1000).
        assert_eq!(ctrl.stats().untrusted, 208 + 209 + 208);
        assert_eq!(ctrl.stats().late_steps, 1);
    }

    #[test]
    fn second_half_samples_fed_before_the_done_report_are_held_and_judged_on_time_stamps() {
        // A caller on two threads reports the move after the beam left the sector, but the
        // move finished (by its timestamp) at 219 ms, long before the exit at 292 ms.
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(500, MS, 0.0, 0, 500);
        let mut events = Vec::new();
        for sample in &samples[..400] {
            ctrl.on_sample(sample);
        }
        drain(&mut ctrl, &mut events);
        assert_eq!(steps(&events).len(), 1);
        assert!(tagged(&events).all(|t| t.half == Half::First));
        ctrl.on_step_done(T0 + 219 * MS).unwrap();
        for sample in &samples[400..] {
            ctrl.on_sample(sample);
        }
        drain(&mut ctrl, &mut events);
        let second: Vec<_> = tagged(&events).filter(|t| t.half == Half::Second).collect();
        assert_eq!(second.len(), 500 - 292);
        assert!(second.iter().all(|t| t.yaw_steps == 1));
        assert_eq!(ctrl.stats().late_steps, 0);
        assert_eq!(
            ctrl.on_step_done(T0 + 500 * MS),
            Err(StaticScanError::NoStepInFlight)
        );
    }

    #[test]
    fn the_budget_predicts_late_steps_from_the_motor_speed() {
        // 60° at 2 Hz lasts 1/12 s = 83.33 ms; 30 steps at 100 steps/s need 300 ms + 2 ms.
        let late = StaticScanConfig {
            steps_per_revolution_of_sweep: 30,
            ..StaticScanConfig::default()
        };
        let budget = late.step_budget(2.0).unwrap();
        assert_eq!(
            budget,
            StepBudget {
                steps: 30,
                rotation_hz: 2.0,
                needed_ns: 302_000_000,
                available_ns: 83_333_333,
            }
        );
        assert!(!budget.fits());
        let fine = StaticScanConfig::default().step_budget(2.0).unwrap();
        assert_eq!(
            (fine.needed_ns, fine.available_ns),
            (12_000_000, 83_333_333)
        );
        assert!(fine.fits());
        assert_eq!(StaticScanConfig::default().step_budget(0.0), None);

        // The same from a sample stream: warned once, early, and then late for real.
        let mut ctrl = controller(late);
        let samples = sweep(500, MS, 0.0, 0, 2 * 500 + 1);
        let out = run(&mut ctrl, &samples, |_| 300 * MS);
        let first = out
            .events
            .iter()
            .position(|e| matches!(e, ScanEvent::PredictedLate(_)))
            .expect("predicted late");
        assert!(
            first
                < out
                    .events
                    .iter()
                    .position(|e| matches!(e, ScanEvent::Step(_)))
                    .unwrap()
        );
        let ScanEvent::PredictedLate(b) = &out.events[first] else {
            unreachable!()
        };
        assert!((b.rotation_hz - 2.0).abs() < 1e-3 && !b.fits());
        let predicted = out
            .events
            .iter()
            .filter(|e| matches!(e, ScanEvent::PredictedLate(_)))
            .count();
        assert_eq!(predicted, 1);
        assert!(ctrl.stats().late_steps >= 1);

        let mut ctrl = controller(StaticScanConfig::default());
        let out = run(&mut ctrl, &samples, |_| 10 * MS);
        assert!(
            !out.events
                .iter()
                .any(|e| matches!(e, ScanEvent::PredictedLate(_)))
        );
    }

    #[test]
    fn the_azimuth_zero_offset_moves_the_sector_and_the_halves() {
        // The device's 90° points up: blocked device azimuths 240°–300°; 0°–90° is the
        // second half (θ 270°–360°), not a new revolution.
        let config = StaticScanConfig {
            azimuth_zero_deg: 90.0,
            ..StaticScanConfig::default()
        };
        let mut ctrl = controller(config);
        let samples = sweep(1000, MS, 90.0, 0, 2 * 1000 + 1);
        let mut events = Vec::new();
        let mut done_at = None;
        for s in &samples {
            if let Some(at) = done_at.filter(|&at| at <= s.t_ns) {
                ctrl.on_step_done(at).unwrap();
                done_at = None;
            }
            ctrl.on_sample(s);
            while let Some(e) = ctrl.poll_event() {
                if let ScanEvent::Step(_) = e {
                    assert!((240.0..241.0).contains(&s.angle_deg), "{}", s.angle_deg);
                    done_at = Some(s.t_ns + 10 * MS);
                }
                events.push(e);
            }
        }
        assert_eq!(steps(&events).len(), 2);
        for e in &events {
            match e {
                ScanEvent::Blocked(s) => assert!((240.0..=300.0).contains(&s.angle_deg)),
                ScanEvent::Tagged(t) => {
                    let az = t.sample.angle_deg;
                    let rev = index_of(&t.sample, MS) / 1000;
                    let second = !(90.0..240.0).contains(&az);
                    assert_eq!(t.half == Half::Second, second, "{az}");
                    assert_eq!(t.yaw_steps, rev as i64 + i64::from(second), "{az}");
                    assert!((t.theta_deg - (f64::from(az) - 90.0).rem_euclid(360.0)).abs() < 1e-9);
                }
                ScanEvent::Step(_) => {}
                other => panic!("unexpected {other:?}"),
            }
        }
    }

    #[test]
    fn failed_steps_untrust_the_second_half_are_retried_and_abort_after_three() {
        let mut ctrl = controller(StaticScanConfig::default());
        let samples = sweep(500, MS, 0.0, 0, 4 * 500);
        let mut events = Vec::new();
        let mut failed_revolutions = 0;
        for s in &samples {
            ctrl.on_sample(s);
            let start = events.len();
            drain(&mut ctrl, &mut events);
            if events[start..]
                .iter()
                .any(|e| matches!(e, ScanEvent::Step(_)))
            {
                assert_eq!(
                    ctrl.on_step_failed(s.t_ns + MS, 2),
                    Err(StaticScanError::StepsDone {
                        done: 2,
                        commanded: 1
                    })
                );
                ctrl.on_step_failed(s.t_ns + MS, 0).unwrap();
                failed_revolutions += 1;
                drain(&mut ctrl, &mut events);
            }
        }
        assert_eq!(failed_revolutions, 3);
        assert_eq!(ctrl.stats().failed_steps, 3);
        let tail = &events[events.len() - 2..];
        assert_eq!(
            tail,
            [
                ScanEvent::Aborted {
                    at_ns: T0 + (2 * 500 + 209 + 1) * MS,
                    yaw_deg: 0.0,
                    failures: 3,
                },
                ScanEvent::ReturnHome { steps: 0 },
            ]
        );
        // Revolutions 0 and 1: second halves untrusted, first halves tagged at φ = 0.
        for e in &events {
            match e {
                ScanEvent::Tagged(t) => {
                    assert_eq!((t.half, t.yaw_steps), (Half::First, 0));
                }
                ScanEvent::Untrusted { sample, reason } => {
                    assert_eq!(*reason, UntrustedReason::StepFailed);
                    assert!(truth(500, index_of(sample, MS)).1 > 210.0);
                }
                _ => {}
            }
        }
        assert_eq!(ctrl.stats().untrusted, 2 * 208);
    }

    #[test]
    fn a_revolution_without_sector_samples_makes_no_move() {
        // Samples 150°–210° of revolution 0 are lost; the scan starts inside the sector.
        let mut ctrl = controller(StaticScanConfig::default());
        let samples: Vec<_> = sweep(500, MS, 0.0, 250, 2 * 500)
            .into_iter()
            .filter(|s| !(259..=541).contains(&((s.t_ns - T0) / MS)))
            .collect();
        let out = run(&mut ctrl, &samples, |_| 10 * MS);
        // Index 0 is θ = 180° (lead, blocked); revolution 1 starts at index 250.
        assert!(matches!(out.events[0], ScanEvent::Blocked(_)));
        assert!(
            out.events
                .contains(&ScanEvent::SectorMissed { revolution: 1 })
        );
        let trigger_indices: Vec<_> = out.triggers.iter().map(|s| index_of(s, MS)).collect();
        assert_eq!(trigger_indices, [959]);
        for t in tagged(&out.events) {
            let i = index_of(&t.sample, MS);
            let expected = if i < 960 { 0 } else { 1 };
            assert_eq!(t.yaw_steps, expected, "sample {i}");
        }
    }

    #[test]
    fn configuration_is_validated_and_read_from_toml() {
        let config: StaticScanConfig =
            toml::from_str("blocked_sector_deg = 40.0\nazimuth_zero_deg = 90.0").unwrap();
        assert_eq!(
            config,
            StaticScanConfig {
                blocked_sector_deg: 40.0,
                azimuth_zero_deg: 90.0,
                ..StaticScanConfig::default()
            }
        );
        assert!(toml::from_str::<StaticScanConfig>("sector = 1.0").is_err());
        let bad = |config: StaticScanConfig| StaticScanController::new(config, 1.8).err();
        assert_eq!(
            bad(StaticScanConfig {
                blocked_sector_deg: 0.0,
                ..StaticScanConfig::default()
            }),
            Some(StaticScanError::Sector(0.0))
        );
        assert_eq!(
            bad(StaticScanConfig {
                max_step_rate_hz: f64::NAN,
                ..StaticScanConfig::default()
            }),
            Some(StaticScanError::NotPositive("max_step_rate_hz"))
        );
        assert_eq!(
            StaticScanController::new(StaticScanConfig::default(), 0.0).err(),
            Some(StaticScanError::StepAngle(0.0))
        );
        assert_eq!(
            StaticScanController::new(StaticScanConfig::default(), 1.8)
                .unwrap()
                .target_steps(),
            100
        );
    }
}
