//! The turntable thread: owns the motor HAT and the stepper, executes moves for static scans
//! and reports when each finished (edge clock), so the Sweep worker never blocks on I2C.
//!
//! ```text
//!  Sweep worker ──TurntableJob──> turntable thread ──I2C──> PCA9685 HAT ──> stepper
//!        ^                               │
//!        └────────TurntableReport────────┘  (+ a StepperState frame after every move)
//! ```

use std::sync::mpsc::{self, Receiver, Sender};
use std::thread::JoinHandle;

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;
use scan3d_protocol::StepperState;

use crate::clock::SharedClock;
use crate::drivers::stepper::{MotorHat, Move, Stepper, StepperConfig};

/// What the turntable thread is asked to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TurntableJob {
    /// Make this move now.
    Move(Move),
    /// Go back to home (straight back, no cable wrap) and release the coils.
    Home,
}

/// What the turntable thread reports back, in job order.
#[derive(Debug, Clone, PartialEq)]
pub enum TurntableReport {
    /// The move finished at `t_ns` (edge clock).
    Moved {
        /// Completion time.
        t_ns: u64,
    },
    /// The move stopped on an I2C error after `steps_done` steps.
    Failed {
        /// When the error came.
        t_ns: u64,
        /// Steps done before it (signed, forward positive).
        steps_done: i32,
        /// The driver's error.
        error: String,
    },
    /// Home reached and coils released (`Err` = where it failed).
    Home(Result<(), String>),
}

/// A running turntable thread.
pub struct Turntable {
    jobs: Sender<TurntableJob>,
    reports: Receiver<TurntableReport>,
    step_angle_deg: f64,
    step_rate_hz: f64,
    thread: Option<JoinHandle<()>>,
}

impl Turntable {
    /// Initialises the HAT (errors name the chip and address) and starts the thread. Every
    /// state change is handed to `on_state` (the daemon streams it as a `Stepper` frame).
    /// A HAT that does not answer yet (an emulated bus that starts later, a bus that went
    /// away) is logged and initialised again before the next job, at most once a second;
    /// jobs fail until it answers. Only a configuration error refuses to start.
    pub fn spawn<I, D>(
        bus: I,
        mut delay: D,
        config: &StepperConfig,
        clock: SharedClock,
        on_state: impl Fn(StepperState) + Send + 'static,
    ) -> anyhow::Result<Self>
    where
        I: I2c + Send + 'static,
        D: DelayNs + Send + 'static,
    {
        let mut stepper = Stepper::new(config)?;
        let mut hat = MotorHat::new(bus, config.address, config.retries);
        let mut ready = match hat.init(&mut delay) {
            Ok(()) => true,
            Err(e) => {
                tracing::error!(error = %e, "stepper HAT not answering; trying again before each move");
                false
            }
        };
        let mut last_init = std::time::Instant::now();
        let step_angle_deg = stepper.step_angle_deg();
        let step_rate_hz = 1e9 / f64::from(stepper.step_period_ns().max(1));
        let (jobs, job_rx) = mpsc::channel::<TurntableJob>();
        let (report_tx, reports) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("stepper".into())
            .spawn(move || {
                let state = |stepper: &Stepper, t_ns: u64| StepperState {
                    t_ns,
                    commanded_angle_deg: stepper.commanded_angle_deg() as f32,
                    step_index: stepper.position(),
                    holding: stepper.is_energised(),
                };
                while let Ok(job) = job_rx.recv() {
                    if !ready {
                        // At most one attempt a second, however fast jobs come.
                        let since = last_init.elapsed();
                        if since < std::time::Duration::from_secs(1) {
                            std::thread::sleep(std::time::Duration::from_secs(1) - since);
                        }
                        last_init = std::time::Instant::now();
                        match hat.init(&mut delay) {
                            Ok(()) => {
                                tracing::info!("stepper HAT answering");
                                ready = true;
                            }
                            Err(e) => {
                                let error = format!("stepper HAT not answering: {e}");
                                let report = match job {
                                    TurntableJob::Move(_) => TurntableReport::Failed {
                                        t_ns: clock.now_ns(),
                                        steps_done: 0,
                                        error,
                                    },
                                    TurntableJob::Home => TurntableReport::Home(Err(error)),
                                };
                                if report_tx.send(report).is_err() {
                                    break;
                                }
                                continue;
                            }
                        }
                    }
                    let report = match job {
                        TurntableJob::Move(mv) => {
                            let before = stepper.position();
                            match stepper.run(&mut hat, mv, &mut delay) {
                                Ok(()) => TurntableReport::Moved {
                                    t_ns: clock.now_ns(),
                                },
                                Err(e) => TurntableReport::Failed {
                                    t_ns: clock.now_ns(),
                                    steps_done: i32::try_from(stepper.position() - before)
                                        .unwrap_or(0),
                                    error: e.to_string(),
                                },
                            }
                        }
                        TurntableJob::Home => TurntableReport::Home(
                            stepper
                                .return_home(&mut hat, &mut delay)
                                .and_then(|_| stepper.release(&mut hat))
                                .map_err(|e| e.to_string()),
                        ),
                    };
                    // After a bus error the HAT may have been reset (an emulator restarted).
                    if matches!(
                        report,
                        TurntableReport::Failed { .. } | TurntableReport::Home(Err(_))
                    ) {
                        ready = false;
                    }
                    on_state(state(&stepper, clock.now_ns()));
                    if report_tx.send(report).is_err() {
                        break;
                    }
                }
                // Never leave the coils energised (they heat up holding a position).
                if let Err(e) = stepper.release(&mut hat) {
                    tracing::warn!(error = %e, "releasing the stepper coils failed");
                }
            })?;
        Ok(Self {
            jobs,
            reports,
            step_angle_deg,
            step_rate_hz,
            thread: Some(thread),
        })
    }

    /// Output-shaft degrees per step.
    pub fn step_angle_deg(&self) -> f64 {
        self.step_angle_deg
    }

    /// Steps per second of a paced move (the stepper's configured speed).
    pub fn step_rate_hz(&self) -> f64 {
        self.step_rate_hz
    }

    /// Queues a job; `false` if the thread is gone.
    pub fn submit(&self, job: TurntableJob) -> bool {
        self.jobs.send(job).is_ok()
    }

    /// The next report, if one is ready.
    pub fn try_report(&self) -> Option<TurntableReport> {
        self.reports.try_recv().ok()
    }

    /// Waits for the next report (for the return home at shutdown).
    pub fn wait_report(&self, timeout: std::time::Duration) -> Option<TurntableReport> {
        self.reports.recv_timeout(timeout).ok()
    }
}

impl Drop for Turntable {
    fn drop(&mut self) {
        // Closing the job channel ends the thread after its current job.
        let (closed, _) = mpsc::channel();
        drop(std::mem::replace(&mut self.jobs, closed));
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
