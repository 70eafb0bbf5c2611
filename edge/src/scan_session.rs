//! One static scan as the daemon runs it: the [`StaticScanController`] plus what turns its
//! events into protocol messages and stepper jobs.
//!
//! Sans-I/O like the controller: the Sweep worker feeds samples and step outcomes and carries
//! out the returned [`ScanAction`]s (submit a frame, move the stepper, go home). The messages
//! follow [`scan3d_protocol::StaticScan`]: `Started` (position, δφ, mount), one `Samples` per
//! revolution with every tagged sample's yaw, a `Warning` for each late / failed / missed step,
//! and `Finished` with the counters.

use scan3d_protocol::{
    Body, MountInfo, StaticScan, StaticScanEnd, StaticScanOutcome, StaticScanProblem,
    StaticScanSamples, StaticScanStart, StaticScanWarning, TaggedSweepSample,
};

use crate::lidar::ArrivedSample;
use crate::static_scan::{
    ScanEvent, StaticScanConfig, StaticScanController, StaticScanError, StepCommand,
};
use crate::timing::TimedSample;

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

/// Measurement times from arrival times, as each sample arrives: within a revolution the
/// beam turns at a steady rate, so arrival time against unwrapped beam angle is a line plus
/// the serial latency. The line fitted under the **lower envelope** of the last revolution's
/// arrivals ([`crate::timing`]'s Moon–Skelly–Towsley fit, here made causal) gives each new
/// sample's measurement time. Without it, a sample measured while the rotor still moved but
/// delivered late (a USB latency timer, a busy host) would look as if it were taken after the
/// step and be tagged with the new yaw.
#[derive(Debug, Default)]
struct MeasurementTimes {
    /// Unwrapped beam angle of the last sample, degrees.
    unwrapped_deg: Option<f64>,
    /// (unwrapped angle, arrival ns) over the last revolution.
    window: std::collections::VecDeque<(f64, f64)>,
    /// The current line `arrival = a + b·angle` and the angle it was fitted at.
    fit: Option<(f64, f64, f64)>,
    /// The last estimate, so estimates never go backwards.
    last_ns: u64,
}

impl MeasurementTimes {
    /// Refit after the beam turned this far.
    const REFIT_DEG: f64 = 5.0;
    /// No fit before the window spans this much.
    const MIN_SPAN_DEG: f64 = 30.0;

    /// The measurement time of a sample at device angle `angle_deg` that arrived at
    /// `arrival_ns` (never later than its arrival, never before the previous estimate).
    fn estimate(&mut self, angle_deg: f64, arrival_ns: u64) -> u64 {
        let unwrapped = match self.unwrapped_deg {
            None => angle_deg,
            Some(previous) => {
                let delta = (angle_deg - previous.rem_euclid(360.0)).rem_euclid(360.0);
                previous + if delta > 180.0 { delta - 360.0 } else { delta }
            }
        };
        self.unwrapped_deg = Some(unwrapped);
        self.window.push_back((unwrapped, arrival_ns as f64));
        while self
            .window
            .front()
            .is_some_and(|&(u, _)| unwrapped - u > 360.0)
        {
            self.window.pop_front();
        }
        let span = self.window.front().map_or(0.0, |&(u, _)| unwrapped - u);
        let stale = self
            .fit
            .is_none_or(|(_, _, at)| (unwrapped - at).abs() >= Self::REFIT_DEG);
        if span >= Self::MIN_SPAN_DEG && stale {
            let (x, y): (Vec<f64>, Vec<f64>) = self.window.iter().copied().unzip();
            let (a, b) = crate::timing::lower_envelope_fit(&x, &y);
            self.fit = Some((a, b, unwrapped));
        }
        let estimate = match self.fit {
            Some((a, b, _)) if span >= Self::MIN_SPAN_DEG => {
                (a + b * unwrapped).clamp(0.0, arrival_ns as f64) as u64
            }
            _ => arrival_ns,
        };
        self.last_ns = self.last_ns.max(estimate);
        self.last_ns
    }
}

/// A running static scan.
#[derive(Debug)]
pub struct ScanSession {
    scan_id: u32,
    controller: StaticScanController,
    times: MeasurementTimes,
    batch: Option<StaticScanSamples>,
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
            times: MeasurementTimes::default(),
            batch: None,
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

    /// Feeds one Sweep sample as it arrived; its measurement time is estimated from the
    /// arrival times (see `MeasurementTimes`) before the controller decides its yaw.
    pub fn on_sample(&mut self, sample: &ArrivedSample, out: &mut Vec<ScanAction>) {
        if self.ended {
            return;
        }
        let t_ns = self
            .times
            .estimate(f64::from(sample.sample.angle_deg), sample.arrival_ns);
        self.controller.on_sample(&TimedSample {
            angle_deg: sample.sample.angle_deg,
            range_m: sample.sample.range_m,
            quality: sample.sample.quality,
            t_ns,
        });
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
                    if self
                        .batch
                        .as_ref()
                        .is_some_and(|b| b.revolution != tagged.revolution)
                    {
                        self.flush(out);
                    }
                    let batch = self.batch.get_or_insert_with(|| StaticScanSamples {
                        scan_id: self.scan_id,
                        revolution: tagged.revolution,
                        t_ns: tagged.sample.t_ns,
                        samples: Vec::with_capacity(1024),
                    });
                    batch.samples.push(TaggedSweepSample {
                        azimuth_deg: tagged.sample.angle_deg,
                        range_m: tagged.sample.range_m,
                        quality: tagged.sample.quality,
                        yaw_deg: tagged.yaw_deg as f32,
                    });
                }
                ScanEvent::Blocked(_) | ScanEvent::Untrusted { .. } => {}
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

    fn flush(&mut self, out: &mut Vec<ScanAction>) {
        if let Some(batch) = self.batch.take() {
            out.push(ScanAction::Send(StaticScan::Samples(batch).into()));
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
    use super::*;
    use crate::lidar::RawSample;

    /// A Sweep at `hz` with `per_rev` evenly spaced samples, all at 2 m.
    fn sample(i: u64, per_rev: u64, hz: f64) -> ArrivedSample {
        let angle = (i % per_rev) as f64 * 360.0 / per_rev as f64;
        ArrivedSample {
            sample: RawSample {
                angle_deg: angle as f32,
                range_m: 2.0,
                quality: 100,
                new_revolution: i.is_multiple_of(per_rev),
            },
            arrival_ns: (i as f64 * 1e9 / (hz * per_rev as f64)) as u64,
        }
    }

    fn position() -> ScanPosition {
        ScanPosition {
            name: "p".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 90.0,
        }
    }

    /// Runs a whole scan with a stepper that finishes each move `step_ms` after the command.
    fn run(config: &StaticScanConfig, step_ms: f64) -> Vec<ScanAction> {
        let (mut session, started) =
            ScanSession::start(3, position(), config, (1.8, 100.0), 0).unwrap();
        let mut all = vec![started];
        let mut out = Vec::new();
        let per_rev = 360;
        let mut pending: Option<u64> = None;
        for i in 0..(per_rev * 120) {
            let s = sample(i, per_rev, 1.0);
            if let Some(done) = pending
                && s.arrival_ns >= done
            {
                session.on_step_done(done, &mut out);
                pending = None;
            }
            session.on_sample(&s, &mut out);
            for action in out.drain(..) {
                if let ScanAction::Step(_) = action {
                    pending = Some(s.arrival_ns + (step_ms * 1e6) as u64);
                }
                all.push(action);
            }
            if session.is_over() {
                break;
            }
        }
        all
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

    #[test]
    fn a_full_scan_sends_start_samples_per_revolution_and_end() {
        let config = StaticScanConfig::default();
        let actions = run(&config, 10.0);
        let messages = bodies(&actions);
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
        let revolutions: Vec<&StaticScanSamples> = messages
            .iter()
            .filter_map(|m| match m {
                StaticScan::Samples(s) => Some(s),
                _ => None,
            })
            .collect();
        assert_eq!(revolutions.len(), 100);
        let tagged: u64 = revolutions.iter().map(|r| r.samples.len() as u64).sum();
        assert_eq!(tagged, end.tagged);
        // Revolution 10: first half at 10 steps, second half at 11 steps (eq. (1)'s φ, φ+δφ).
        let r10 = revolutions[10];
        let first = r10.samples.iter().find(|s| s.azimuth_deg < 150.0).unwrap();
        let second = r10.samples.iter().find(|s| s.azimuth_deg > 210.0).unwrap();
        assert!((first.yaw_deg - 18.0).abs() < 1e-4, "{first:?}");
        assert!((second.yaw_deg - 19.8).abs() < 1e-4, "{second:?}");
        assert!(
            r10.samples
                .iter()
                .all(|s| !(150.0..=210.0).contains(&s.azimuth_deg))
        );
        assert_eq!(actions.last(), Some(&ScanAction::ReturnHome));
        assert_eq!(
            actions
                .iter()
                .filter(|a| matches!(a, ScanAction::Step(_)))
                .count(),
            100
        );
    }

    #[test]
    fn late_steps_are_reported_and_their_halves_not_sent() {
        // A step that takes 200 ms cannot fit in a 60° sector at 1 Hz (167 ms).
        let config = StaticScanConfig::default();
        let actions = run(&config, 200.0);
        let messages = bodies(&actions);
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
        // No sample past the sector was sent with a yaw it may not have had.
        for m in &messages {
            if let StaticScan::Samples(s) = m {
                assert!(
                    s.samples.iter().all(|x| x.azimuth_deg < 150.0),
                    "revolution {} sent second-half samples",
                    s.revolution
                );
            }
        }
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
        let mut out = Vec::new();
        for i in 0..800 {
            session.on_sample(&sample(i, 360, 1.0), &mut out);
        }
        assert!(out.iter().any(|a| matches!(
            a,
            ScanAction::Send(Body::StaticScan(StaticScan::Warning(w)))
                if w.problem == StaticScanProblem::PredictedLate
        )));
    }

    #[test]
    fn measurement_times_take_the_least_delayed_phase() {
        let mut times = MeasurementTimes::default();
        // 1 Hz, a sample every degree measured at i ms·(1000/360); arrivals late by 1 ms plus
        // a burst of 40 ms every 50 samples.
        let mut worst: u64 = 0;
        for i in 0..1080u64 {
            let measured = i * 1_000_000_000 / 360;
            let late = if i % 50 < 5 { 40_000_000 } else { 1_000_000 };
            let estimate = times.estimate((i % 360) as f64, measured + late);
            if i > 400 {
                worst = worst.max(estimate.abs_diff(measured + 1_000_000));
            }
        }
        // After a revolution, every estimate is within rounding of the 1 ms floor.
        assert!(worst < 10_000, "worst error {worst} ns");
    }

    #[test]
    fn stop_flushes_and_goes_home() {
        let config = StaticScanConfig::default();
        let (mut session, _) = ScanSession::start(0, position(), &config, (1.8, 100.0), 0).unwrap();
        let mut out = Vec::new();
        for i in 0..500 {
            session.on_sample(&sample(i, 360, 1.0), &mut out);
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
        assert!(
            matches!(messages.last(), Some(StaticScan::Finished(end)) if end.outcome == StaticScanOutcome::Stopped)
        );
        assert_eq!(out.last(), Some(&ScanAction::ReturnHome));
        let mut again = Vec::new();
        session.stop(3_000_000_000, &mut again);
        assert!(again.is_empty());
    }
}
