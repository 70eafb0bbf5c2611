//! One static scan as the daemon runs it: the [`StaticScanController`] plus what turns its
//! events into protocol messages and stepper jobs.
//!
//! Sans-I/O like the controller: the Sweep worker feeds samples and step outcomes and carries
//! out the returned [`ScanAction`]s (submit a frame, move the stepper, go home). The messages
//! follow [`scan3d_protocol::StaticScan`]: `Started` (position, δφ, mount), one `Yaws` per Sweep
//! revolution naming it by its `t0_ns` and giving the yaw of runs of its sample indices, a
//! `Warning` for each late / failed / missed step, and `Finished` with the counters.
//!
//! **One timeline.** The samples come already timed, as [`crate::timing::RevolutionAssembler`]
//! stamped them when they arrived: the controller decides each yaw on the very time the sample
//! has in the Sweep's revolution frame, and the samples themselves travel only in that frame
//! (see [`crate::timing`] for why the one estimator is causal). A `Yaws` message is sent once
//! every sample of its revolution is decided (tagged, blocked or untrusted), so usually just
//! before the revolution frame itself; the server joins the two by `t0_ns` in either order.

use std::collections::VecDeque;

use scan3d_protocol::{
    Body, MountInfo, StaticScan, StaticScanEnd, StaticScanOutcome, StaticScanProblem,
    StaticScanStart, StaticScanWarning, StaticScanYaws, YawRun,
};

use crate::static_scan::{
    Half, ScanEvent, StaticScanConfig, StaticScanController, StaticScanError, StepCommand,
    TaggedSample,
};
use crate::timing::{RevolutionPosition, StampedSample, TimedSample};

/// What the caller must do for a [`ScanSession`].
#[derive(Debug, Clone, PartialEq)]
pub enum ScanAction {
    /// Submit this frame body to the uplink.
    Send(Body),
    /// Move the stepper now and report with [`ScanSession::on_step_done`] /
    /// [`ScanSession::on_step_failed`].
    Step(StepCommand),
    /// The scan is over: turn back home and release the coils.
    ReturnHome,
}

/// Where the operator put the turntable ([`scan3d_protocol::Command::StartStaticScan`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ScanPosition {
    /// The operator's name for it.
    pub name: String,
    /// x, metres, map frame.
    pub x_m: f64,
    /// y, metres, map frame.
    pub y_m: f64,
    /// φ0, degrees (0 when not given).
    pub heading_deg: f64,
}

/// The yaw runs of one Sweep revolution, as its samples are decided.
#[derive(Debug)]
struct RevolutionYaws {
    t0_ns: u64,
    runs: Vec<YawRun>,
    /// The scan revolution and half of the last run: a run never spans two halves, even of one
    /// yaw (with an azimuth zero other than 0, a Sweep revolution holds the second half at φ
    /// and the next first half at φ too), so each run is one half revolution's optical centre.
    last_half: Option<(u32, Half)>,
}

impl RevolutionYaws {
    fn tag(&mut self, index: u32, tagged: &TaggedSample) {
        let yaw_deg = tagged.yaw_deg as f32;
        let half = (tagged.revolution, tagged.half);
        match self.runs.last_mut() {
            Some(run)
                if run.yaw_deg == yaw_deg
                    && self.last_half == Some(half)
                    && run.first_index.checked_add(run.count) == Some(index) =>
            {
                run.count += 1;
            }
            _ => self.runs.push(YawRun {
                first_index: index,
                count: 1,
                yaw_deg,
            }),
        }
        self.last_half = Some(half);
    }
}

/// A running static scan.
#[derive(Debug)]
pub struct ScanSession {
    scan_id: u32,
    controller: StaticScanController,
    /// Where each sample fed and not yet decided sits in its revolution, in feeding order (the
    /// controller decides samples in the order they were fed).
    undecided: VecDeque<(u64, Option<RevolutionPosition>)>,
    /// The revolution whose samples are being decided.
    yaws: Option<RevolutionYaws>,
    ended: bool,
}

impl ScanSession {
    /// Starts scan number `scan_id` at `position`. `step_angle_deg` is the stepper's output
    /// angle per step and `step_rate_hz` the rate it steps at: above the motor's limit
    /// ([`StaticScanConfig::max_step_rate_hz`]) steps would be lost, so the scan is refused;
    /// below it, the controller budgets moves at the real rate. Returns the session and the
    /// `Started` message to send.
    pub fn start(
        scan_id: u32,
        position: ScanPosition,
        config: &StaticScanConfig,
        stepper: (f64, f64),
        now_ns: u64,
    ) -> Result<(Self, ScanAction), StaticScanError> {
        let (step_angle_deg, step_rate_hz) = stepper;
        if !(step_rate_hz.is_finite() && step_rate_hz > 0.0) {
            return Err(StaticScanError::NotPositive("step rate"));
        }
        if step_rate_hz > config.max_step_rate_hz * (1.0 + 1e-9) {
            return Err(StaticScanError::Overspeed {
                commanded_hz: step_rate_hz,
                max_hz: config.max_step_rate_hz,
            });
        }
        let budgeted = StaticScanConfig {
            max_step_rate_hz: step_rate_hz,
            ..config.clone()
        };
        let controller = StaticScanController::new(budgeted, step_angle_deg)?;
        let started = StaticScanStart {
            scan_id,
            t_ns: now_ns,
            position: position.name,
            x_m: position.x_m,
            y_m: position.y_m,
            heading_deg: position.heading_deg,
            step_deg: step_angle_deg * f64::from(config.steps_per_revolution_of_sweep),
            total_deg: controller.target_steps() as f64 * step_angle_deg,
            blocked_sector_deg: config.blocked_sector_deg,
            mount: MountInfo {
                axis_offset_m: config.mount.axis_offset_m,
                height_m: config.mount.height_m,
                azimuth_zero_deg: config.azimuth_zero_deg,
            },
        };
        let session = Self {
            scan_id,
            controller,
            undecided: VecDeque::new(),
            yaws: None,
            ended: false,
        };
        Ok((
            session,
            ScanAction::Send(StaticScan::Started(started).into()),
        ))
    }

    /// The scan's number within the edge session.
    pub fn scan_id(&self) -> u32 {
        self.scan_id
    }

    /// Whether `Finished` was emitted (the session can be dropped).
    pub fn is_over(&self) -> bool {
        self.ended
    }

    /// The controller (yaw, revolution, counters).
    pub fn controller(&self) -> &StaticScanController {
        &self.controller
    }

    /// Feeds one Sweep sample as the revolution assembler stamped it on arrival: the controller
    /// decides its yaw on that time, and a tag refers to its place in the revolution.
    pub fn on_sample(&mut self, sample: &StampedSample, out: &mut Vec<ScanAction>) {
        if self.ended {
            return;
        }
        self.undecided
            .push_back((sample.sample.t_ns, sample.position));
        self.controller.on_sample(&sample.sample);
        self.drain(out);
    }

    /// The stepper finished the last [`ScanAction::Step`] at `t_ns` (edge clock).
    pub fn on_step_done(&mut self, t_ns: u64, out: &mut Vec<ScanAction>) {
        if let Err(e) = self.controller.on_step_done(t_ns) {
            tracing::warn!(error = %e, "step completion not expected by the controller");
        }
        self.drain(out);
    }

    /// The stepper failed the last [`ScanAction::Step`] after `steps_done` steps.
    pub fn on_step_failed(&mut self, t_ns: u64, steps_done: i32, out: &mut Vec<ScanAction>) {
        if let Err(e) = self.controller.on_step_failed(t_ns, steps_done) {
            tracing::warn!(error = %e, "step failure not expected by the controller");
        }
        self.drain(out);
    }

    /// Ends the scan early (operator stop, Sweep lost, daemon stopping): what was tagged is
    /// sent, then `Finished` with [`StaticScanOutcome::Stopped`], then the way home.
    pub fn stop(&mut self, now_ns: u64, out: &mut Vec<ScanAction>) {
        if self.ended {
            return;
        }
        self.drain(out);
        if !self.ended {
            self.finish(
                StaticScanOutcome::Stopped,
                now_ns,
                self.controller.yaw_deg(),
                out,
            );
            out.push(ScanAction::ReturnHome);
        }
    }

    fn drain(&mut self, out: &mut Vec<ScanAction>) {
        while let Some(event) = self.controller.poll_event() {
            match event {
                ScanEvent::Step(command) => out.push(ScanAction::Step(command)),
                ScanEvent::Tagged(tagged) => {
                    if let Some(position) = self.decided(&tagged.sample, out)
                        && let Some(yaws) = self.yaws.as_mut()
                    {
                        yaws.tag(position.index, &tagged);
                    }
                }
                ScanEvent::Blocked(sample) | ScanEvent::Untrusted { sample, .. } => {
                    self.decided(&sample, out);
                }
                ScanEvent::LateStep {
                    revolution,
                    expected_by_ns,
                    done_at_ns,
                } => {
                    let detail = match done_at_ns {
                        Some(done) => format!(
                            "step done {:.1} ms after the beam left the blocked sector",
                            done.saturating_sub(expected_by_ns) as f64 / 1e6
                        ),
                        None => "step still running when the revolution ended".into(),
                    };
                    self.warn(
                        StaticScanProblem::LateStep,
                        revolution,
                        expected_by_ns,
                        detail,
                        out,
                    );
                }
                ScanEvent::StepFailed {
                    revolution,
                    steps_done,
                    at_ns,
                } => self.warn(
                    StaticScanProblem::StepFailed,
                    revolution,
                    at_ns,
                    format!("stepper error after {steps_done} steps"),
                    out,
                ),
                ScanEvent::SectorMissed { revolution } => self.warn(
                    StaticScanProblem::SectorMissed,
                    revolution,
                    0,
                    "no sample in the blocked sector: no step this revolution".into(),
                    out,
                ),
                ScanEvent::PredictedLate(budget) => {
                    let revolution = self.controller.revolution();
                    self.warn(
                        StaticScanProblem::PredictedLate,
                        revolution,
                        0,
                        format!(
                            "{} step(s) need {:.1} ms but the sector lasts {:.1} ms at {:.2} Hz",
                            budget.steps,
                            budget.needed_ns as f64 / 1e6,
                            budget.available_ns as f64 / 1e6,
                            budget.rotation_hz
                        ),
                        out,
                    );
                }
                ScanEvent::Finished { at_ns, yaw_deg, .. } => {
                    self.finish(StaticScanOutcome::Completed, at_ns, yaw_deg, out);
                }
                ScanEvent::Aborted { at_ns, yaw_deg, .. } => {
                    self.finish(StaticScanOutcome::Aborted, at_ns, yaw_deg, out);
                }
                ScanEvent::ReturnHome { .. } => out.push(ScanAction::ReturnHome),
            }
        }
    }

    /// The controller decided the oldest undecided sample: its place in its revolution. A
    /// sample of a new revolution first sends the finished revolution's yaws.
    fn decided(
        &mut self,
        sample: &TimedSample,
        out: &mut Vec<ScanAction>,
    ) -> Option<RevolutionPosition> {
        let Some((t_ns, position)) = self.undecided.pop_front() else {
            tracing::error!("the controller decided a sample that was not fed");
            return None;
        };
        debug_assert_eq!(t_ns, sample.t_ns, "samples are decided in feeding order");
        let position = position?;
        if self.yaws.as_ref().is_none_or(|y| y.t0_ns != position.t0_ns) {
            self.flush(out);
            self.yaws = Some(RevolutionYaws {
                t0_ns: position.t0_ns,
                runs: Vec::new(),
                last_half: None,
            });
        }
        Some(position)
    }

    /// Sends the yaws of the revolution being decided, if it has any tagged sample.
    fn flush(&mut self, out: &mut Vec<ScanAction>) {
        if let Some(yaws) = self.yaws.take()
            && !yaws.runs.is_empty()
        {
            out.push(ScanAction::Send(
                StaticScan::Yaws(StaticScanYaws {
                    scan_id: self.scan_id,
                    revolution_t0_ns: yaws.t0_ns,
                    runs: yaws.runs,
                })
                .into(),
            ));
        }
    }

    fn warn(
        &mut self,
        problem: StaticScanProblem,
        revolution: u32,
        t_ns: u64,
        detail: String,
        out: &mut Vec<ScanAction>,
    ) {
        tracing::warn!(scan = self.scan_id, revolution, ?problem, %detail, "static scan");
        out.push(ScanAction::Send(
            StaticScan::Warning(StaticScanWarning {
                scan_id: self.scan_id,
                t_ns,
                revolution,
                problem,
                detail,
            })
            .into(),
        ));
    }

    fn finish(
        &mut self,
        outcome: StaticScanOutcome,
        t_ns: u64,
        yaw_deg: f64,
        out: &mut Vec<ScanAction>,
    ) {
        self.flush(out);
        let stats = self.controller.stats();
        self.ended = true;
        out.push(ScanAction::Send(
            StaticScan::Finished(StaticScanEnd {
                scan_id: self.scan_id,
                t_ns,
                outcome,
                yaw_deg,
                revolutions: self.controller.revolution(),
                tagged: stats.tagged,
                blocked: stats.blocked,
                untrusted: stats.untrusted,
                late_steps: stats.late_steps,
                failed_steps: stats.failed_steps,
            })
            .into(),
        ));
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;
    use crate::lidar::{ArrivedSample, RawSample};
    use crate::timing::{Revolution, RevolutionAssembler, TimingConfig};

    const MS: u64 = 1_000_000;

    /// Sample `i` of a Sweep at `hz` with `per_rev` evenly spaced samples, all at 2 m, measured
    /// at its nominal time and arriving `delay_ns` later.
    fn sample(i: u64, per_rev: u64, hz: f64, delay_ns: u64) -> ArrivedSample {
        let angle = (i % per_rev) as f64 * 360.0 / per_rev as f64;
        ArrivedSample {
            sample: RawSample {
                angle_deg: angle as f32,
                range_m: 2.0,
                quality: 100,
                new_revolution: i.is_multiple_of(per_rev),
            },
            arrival_ns: measured(i, per_rev, hz) + delay_ns,
        }
    }

    fn measured(i: u64, per_rev: u64, hz: f64) -> u64 {
        (i as f64 * 1e9 / (hz * per_rev as f64)) as u64
    }

    fn position() -> ScanPosition {
        ScanPosition {
            name: "p".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 90.0,
        }
    }

    /// What a run produced: every action, and the Sweep revolution frames by `t0_ns`.
    struct Run {
        actions: Vec<ScanAction>,
        revolutions: HashMap<u64, Revolution>,
    }

    /// Runs a scan at 1 Hz, 360 samples per revolution, through the real revolution assembler
    /// (as the acquisition thread does): move number k finishes `step_ns(k)` after the arrival
    /// of the sample that commanded it, and sample i arrives `delay_ns(i)` after it was taken.
    fn run_with(
        config: &StaticScanConfig,
        step_ns: impl Fn(usize) -> u64,
        delay_ns: impl Fn(u64) -> u64,
    ) -> Run {
        let (mut session, started) =
            ScanSession::start(3, position(), config, (1.8, 100.0), 0).unwrap();
        let mut assembler = RevolutionAssembler::new(TimingConfig::default());
        let mut run = Run {
            actions: vec![started],
            revolutions: HashMap::new(),
        };
        let mut out = Vec::new();
        let per_rev = 360;
        let mut pending: Option<u64> = None;
        let mut moves = 0;
        for i in 0..(per_rev * 120) {
            let s = sample(i, per_rev, 1.0, delay_ns(i));
            if let Some(done) = pending
                && s.arrival_ns >= done
            {
                session.on_step_done(done, &mut out);
                pending = None;
            }
            let stamped = assembler.stamp(s);
            if let Some(rev) = stamped.finished {
                run.revolutions.insert(rev.t0_ns, rev);
            }
            session.on_sample(&stamped.sample, &mut out);
            for action in out.drain(..) {
                if let ScanAction::Step(_) = action {
                    pending = Some(s.arrival_ns + step_ns(moves));
                    moves += 1;
                }
                run.actions.push(action);
            }
            if session.is_over() {
                break;
            }
        }
        run
    }

    fn run(config: &StaticScanConfig, step_ms: f64) -> Run {
        run_with(config, |_| (step_ms * 1e6) as u64, |_| 0)
    }

    fn bodies(actions: &[ScanAction]) -> Vec<&StaticScan> {
        actions
            .iter()
            .filter_map(|a| match a {
                ScanAction::Send(Body::StaticScan(s)) => Some(s),
                _ => None,
            })
            .collect()
    }

    fn yaws<'a>(messages: &[&'a StaticScan]) -> Vec<&'a StaticScanYaws> {
        messages
            .iter()
            .filter_map(|m| match m {
                StaticScan::Yaws(y) => Some(y),
                _ => None,
            })
            .collect()
    }

    /// Each tagged sample of `yaws`, from its revolution frame: (device azimuth, yaw).
    fn tagged_samples(run: &Run, yaws: &StaticScanYaws) -> Vec<(f32, f32)> {
        let rev = &run.revolutions[&yaws.revolution_t0_ns];
        yaws.runs
            .iter()
            .flat_map(|r| {
                let range = r.first_index as usize..(r.first_index + r.count) as usize;
                rev.samples[range].iter().map(|s| (s.angle_deg, r.yaw_deg))
            })
            .collect()
    }

    #[test]
    fn a_full_scan_sends_start_the_yaws_of_each_revolution_by_sample_index_and_end() {
        let config = StaticScanConfig::default();
        let run = run(&config, 10.0);
        let messages = bodies(&run.actions);
        let StaticScan::Started(start) = messages[0] else {
            panic!("first message {:?}", messages[0]);
        };
        assert_eq!((start.scan_id, start.position.as_str()), (3, "p"));
        assert_eq!((start.step_deg, start.total_deg), (1.8, 180.0));
        let StaticScan::Finished(end) = messages.last().unwrap() else {
            panic!("last message {:?}", messages.last());
        };
        assert_eq!(end.outcome, StaticScanOutcome::Completed);
        assert_eq!(end.revolutions, 100);
        assert!((end.yaw_deg - 180.0).abs() < 1e-9);
        assert_eq!((end.late_steps, end.failed_steps), (0, 0));
        let revolutions = yaws(&messages);
        assert_eq!(revolutions.len(), 100);
        let tagged: u64 = revolutions.iter().map(|r| r.tagged_samples()).sum();
        assert_eq!(tagged, end.tagged);
        // Every message names a revolution frame that was sent, and each of its revolutions once.
        let mut t0s: Vec<u64> = revolutions.iter().map(|r| r.revolution_t0_ns).collect();
        t0s.dedup();
        assert_eq!(t0s.len(), 100);
        // Revolution 10: the first half (θ 0°–149°, indices 0–149) at 10 steps, the second
        // (θ 211°–359°) at 11 steps (eq. (1)'s φ, φ+δφ); the blocked sector is in no run.
        let r10 = revolutions[10];
        assert_eq!(
            r10.runs,
            [
                YawRun {
                    first_index: 0,
                    count: 150,
                    yaw_deg: 18.0,
                },
                YawRun {
                    first_index: 211,
                    count: 149,
                    yaw_deg: 19.8,
                },
            ]
        );
        let samples = tagged_samples(&run, r10);
        assert!(samples.iter().all(|(az, _)| !(150.0..=210.0).contains(az)));
        assert!(
            samples
                .iter()
                .all(|&(az, yaw)| (yaw == 18.0) == (az < 150.0))
        );
        assert_eq!(run.actions.last(), Some(&ScanAction::ReturnHome));
        assert_eq!(
            run.actions
                .iter()
                .filter(|a| matches!(a, ScanAction::Step(_)))
                .count(),
            100
        );
    }

    #[test]
    fn with_an_azimuth_zero_a_sweep_revolution_holds_runs_of_two_halves_kept_apart() {
        // The device's 90° points up: a Sweep revolution (device 0°–360°) holds θ 270°–360° of
        // one scan revolution's second half, then the next one's first half (θ 0°–149°) at the
        // same yaw, then θ 211°–269° after the step.
        let config = StaticScanConfig {
            azimuth_zero_deg: 90.0,
            ..StaticScanConfig::default()
        };
        let run = run(&config, 10.0);
        let messages = bodies(&run.actions);
        let r10 = yaws(&messages)[10];
        let shape: Vec<(u32, u32)> = r10.runs.iter().map(|r| (r.first_index, r.count)).collect();
        assert_eq!(shape, [(0, 90), (90, 150), (301, 59)]);
        assert_eq!(r10.runs[0].yaw_deg, r10.runs[1].yaw_deg);
        assert!((r10.runs[2].yaw_deg - r10.runs[1].yaw_deg - 1.8).abs() < 1e-4);
    }

    #[test]
    fn a_revolution_of_yaws_costs_a_few_dozen_bytes_instead_of_a_copy_of_its_samples() {
        let run = run(&StaticScanConfig::default(), 10.0);
        let messages = bodies(&run.actions);
        let revolutions = yaws(&messages);
        let bytes: Vec<usize> = revolutions
            .iter()
            .map(|y| {
                let frame =
                    scan3d_protocol::Frame::new(u64::MAX, 1 << 20, StaticScan::Yaws((*y).clone()));
                scan3d_protocol::encode(&frame).unwrap().len()
            })
            .collect();
        let tagged = revolutions[10].tagged_samples();
        // Version 1 repeated every tagged sample (f32 azimuth, f32 range, u8 quality, f32 yaw).
        let v1_bytes = 13 * tagged as usize;
        let max = *bytes.iter().max().unwrap();
        println!(
            "static-scan bytes per revolution of {tagged} tagged samples: {max} (v1: over {v1_bytes})"
        );
        assert!(max <= 64, "{max} bytes");
    }

    #[test]
    fn late_steps_are_reported_and_their_halves_not_tagged() {
        // A step that takes 200 ms cannot fit in a 60° sector at 1 Hz (167 ms).
        let config = StaticScanConfig::default();
        let run = run(&config, 200.0);
        let messages = bodies(&run.actions);
        let late = messages
            .iter()
            .filter(
                |m| matches!(m, StaticScan::Warning(w) if w.problem == StaticScanProblem::LateStep),
            )
            .count();
        assert!(late >= 90, "{late} late-step warnings");
        let StaticScan::Finished(end) = messages.last().unwrap() else {
            panic!("no end");
        };
        assert_eq!(end.late_steps as usize, late);
        assert!(end.untrusted > 0);
        // No sample past the sector was tagged with a yaw it may not have had.
        for y in yaws(&messages) {
            assert!(
                tagged_samples(&run, y).iter().all(|(az, _)| *az < 150.0),
                "revolution {} tagged second-half samples",
                y.revolution_t0_ns
            );
        }
    }

    #[test]
    fn a_sample_taken_before_the_step_settled_but_delivered_late_is_not_tagged_with_the_new_yaw() {
        // Every sample arrives 0.5 ms after it was taken, except θ 200°–215°: one read 5 ms
        // after sample 215. The first move is commanded on sample 150 (θ = 150°) and reported
        // done 1 ms before sample 211, the first past the sector, was taken: with the 2 ms
        // settle time that sample was taken while the rotor settled. By its arrival time it
        // would look settled; by its measurement time (the envelope's) it is not.
        let config = StaticScanConfig::default();
        let m = |i| measured(i, 360, 1.0);
        let delay = |i: u64| {
            if (200..=215).contains(&i) {
                m(215) + 5 * MS - m(i)
            } else {
                MS / 2
            }
        };
        let first_move = m(211) - MS - (m(150) + MS / 2);
        let run = run_with(
            &config,
            |k| if k == 0 { first_move } else { 10 * MS },
            delay,
        );
        let messages = bodies(&run.actions);
        let late: Vec<_> = messages
            .iter()
            .filter_map(|m| match m {
                StaticScan::Warning(w) if w.problem == StaticScanProblem::LateStep => {
                    Some(w.revolution)
                }
                _ => None,
            })
            .collect();
        assert_eq!(late, [0]);
        let revolutions = yaws(&messages);
        assert_eq!(
            revolutions[0].runs,
            [YawRun {
                first_index: 0,
                count: 150,
                yaw_deg: 0.0,
            }],
            "revolution 0's second half is untrusted"
        );
        // The rotor did arrive: revolution 1 is at 1.8° and 3.6°.
        let yaws1: Vec<f32> = revolutions[1].runs.iter().map(|r| r.yaw_deg).collect();
        assert_eq!(yaws1, [1.8, 3.6]);
    }

    #[test]
    fn a_stepper_faster_than_the_motor_is_refused_and_a_slow_one_predicted_late() {
        let config = StaticScanConfig::default(); // the motor follows 100 steps/s
        let err = ScanSession::start(0, position(), &config, (1.8, 400.0), 0).unwrap_err();
        assert!(matches!(
            err,
            StaticScanError::Overspeed { commanded_hz, max_hz } if commanded_hz == 400.0 && max_hz == 100.0
        ));
        // 5 steps/s: a 200 ms move cannot fit in the 167 ms sector at 1 Hz.
        let (mut session, _) = ScanSession::start(0, position(), &config, (1.8, 5.0), 0).unwrap();
        let mut assembler = RevolutionAssembler::new(TimingConfig::default());
        let mut out = Vec::new();
        for i in 0..800 {
            let stamped = assembler.stamp(sample(i, 360, 1.0, 0));
            session.on_sample(&stamped.sample, &mut out);
        }
        assert!(out.iter().any(|a| matches!(
            a,
            ScanAction::Send(Body::StaticScan(StaticScan::Warning(w)))
                if w.problem == StaticScanProblem::PredictedLate
        )));
    }

    #[test]
    fn stop_flushes_and_goes_home() {
        let config = StaticScanConfig::default();
        let (mut session, _) = ScanSession::start(0, position(), &config, (1.8, 100.0), 0).unwrap();
        let mut assembler = RevolutionAssembler::new(TimingConfig::default());
        let mut out = Vec::new();
        for i in 0..500 {
            let stamped = assembler.stamp(sample(i, 360, 1.0, 0));
            session.on_sample(&stamped.sample, &mut out);
            if out.iter().any(|a| matches!(a, ScanAction::Step(_))) {
                session.on_step_done(stamped.sample.sample.t_ns + 10 * MS, &mut out);
            }
        }
        out.clear();
        session.stop(2_000_000_000, &mut out);
        assert!(session.is_over());
        let messages: Vec<&StaticScan> = out
            .iter()
            .filter_map(|a| match a {
                ScanAction::Send(Body::StaticScan(s)) => Some(s),
                _ => None,
            })
            .collect();
        // The open revolution's first half (samples 360–499, θ 0°–139°) is sent before the end.
        let [StaticScan::Yaws(open), StaticScan::Finished(end)] = messages.as_slice() else {
            panic!("{messages:?}");
        };
        assert_eq!(end.outcome, StaticScanOutcome::Stopped);
        assert_eq!(
            open.runs,
            [YawRun {
                first_index: 0,
                count: 140,
                yaw_deg: 1.8,
            }]
        );
        assert_eq!(out.last(), Some(&ScanAction::ReturnHome));
        let mut again = Vec::new();
        session.stop(3_000_000_000, &mut again);
        assert!(again.is_empty());
    }
}
