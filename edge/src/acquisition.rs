//! One lidar's acquisition thread: a driver on a serial port, assembled into timestamped
//! revolutions and handed over a channel.
//!
//! This is the piece the edge daemon runs per configured lidar (and the simulator's demo runs
//! the same code). It owns the port through [`crate::serial::run`], so unplug/replug recovery
//! comes for free; the receiver sees [`AcquisitionEvent::Lost`] / [`AcquisitionEvent::Opened`].

use std::ops::ControlFlow;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, Sender};
use std::thread::JoinHandle;
use std::time::Duration;

use crate::clock::SharedClock;
use crate::lidar::{DriverStats, LidarDriver, LidarEvent};
use crate::serial::{self, SerialError, SerialEvent, SerialOptions};
use crate::timing::{Revolution, RevolutionAssembler, StampedSample, TimingConfig};

/// What an acquisition thread reports.
#[derive(Debug, Clone, PartialEq)]
pub enum AcquisitionEvent {
    /// The port was opened; the device handshake starts.
    Opened,
    /// The device went away; the thread keeps trying to reopen it.
    Lost(String),
    /// A full revolution with per-sample times.
    Revolution(Revolution),
    /// One sample as soon as it arrived, with the measurement time and revolution position it
    /// has in its [`AcquisitionEvent::Revolution`] (one time per sample); only when the thread
    /// was spawned with `forward_samples` (the static-scan controller acts within a revolution).
    Sample(StampedSample),
    /// Any other driver event: info, health, scanning, warnings, and `Failed` (after which the
    /// thread restarts the handshake following a pause). Samples never come this way: they
    /// arrive assembled as [`AcquisitionEvent::Revolution`]s.
    Driver(LidarEvent),
}

/// What the thread leaves behind when it stops.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AcquisitionSummary {
    /// The driver's byte-stream counters.
    pub driver: DriverStats,
    /// Samples decoded but not part of any emitted revolution (partial revolutions).
    pub samples_outside_revolutions: u64,
    /// CPU time the thread used, for the edge's CPU budget.
    pub cpu_time: Duration,
}

/// A running acquisition thread.
pub struct Acquisition {
    shutdown: Arc<AtomicBool>,
    thread: Option<JoinHandle<Result<AcquisitionSummary, SerialError>>>,
}

/// Pause before restarting a driver that gave up (wrong answers, device error).
const RESTART_PAUSE: Duration = Duration::from_secs(1);

impl Acquisition {
    /// Starts reading `driver` on the port described by `options`. With `forward_samples`,
    /// every sample is also sent on its own, timed, as it arrives ([`AcquisitionEvent::Sample`]).
    pub fn spawn(
        mut driver: Box<dyn LidarDriver + Send>,
        options: SerialOptions,
        clock: SharedClock,
        timing: TimingConfig,
        forward_samples: bool,
    ) -> (Self, Receiver<AcquisitionEvent>) {
        let (tx, rx) = mpsc::channel();
        let shutdown = Arc::new(AtomicBool::new(false));
        let stop = shutdown.clone();
        let thread = std::thread::Builder::new()
            .name(format!("lidar {}", options.path.display()))
            .spawn(move || {
                let mut assembler = RevolutionAssembler::new(timing);
                while !stop.load(Ordering::Relaxed) {
                    let mut failed = false;
                    serial::run(driver.as_mut(), &options, clock.as_ref(), &stop, |event| {
                        forward(event, &mut assembler, &tx, &mut failed, forward_samples)
                    })?;
                    if failed {
                        std::thread::sleep(RESTART_PAUSE);
                    }
                }
                Ok(AcquisitionSummary {
                    driver: driver.stats(),
                    samples_outside_revolutions: assembler.dropped_samples(),
                    cpu_time: thread_cpu_time(),
                })
            })
            .map_err(|e| SerialError::Open {
                path: Default::default(),
                reason: e.to_string(),
            });
        let thread = match thread {
            Ok(handle) => Some(handle),
            Err(e) => {
                tracing::error!("cannot start acquisition thread: {e}");
                None
            }
        };
        (Self { shutdown, thread }, rx)
    }

    /// Stops the thread (the driver sends its stop command) and returns its summary.
    pub fn stop(mut self) -> Result<AcquisitionSummary, SerialError> {
        self.shutdown.store(true, Ordering::Relaxed);
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(SerialError::Lost {
                path: Default::default(),
                reason: "acquisition thread panicked".into(),
            }),
            None => Ok(AcquisitionSummary::default()),
        }
    }
}

impl Drop for Acquisition {
    fn drop(&mut self) {
        self.shutdown.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Turns shell events into acquisition events; `Break` when the driver failed (to restart it)
/// or the receiver is gone.
fn forward(
    event: SerialEvent,
    assembler: &mut RevolutionAssembler,
    tx: &Sender<AcquisitionEvent>,
    failed: &mut bool,
    forward_samples: bool,
) -> ControlFlow<()> {
    let out = match event {
        SerialEvent::Opened => {
            assembler.reset();
            AcquisitionEvent::Opened
        }
        SerialEvent::Lost(reason) => {
            assembler.reset();
            AcquisitionEvent::Lost(reason)
        }
        SerialEvent::Driver(LidarEvent::Sample(sample)) => {
            let stamped = assembler.stamp(sample);
            if forward_samples && tx.send(AcquisitionEvent::Sample(stamped.sample)).is_err() {
                return ControlFlow::Break(());
            }
            match stamped.finished {
                Some(rev) => AcquisitionEvent::Revolution(rev),
                None => return ControlFlow::Continue(()),
            }
        }
        SerialEvent::Driver(failure @ LidarEvent::Failed(_)) => {
            assembler.reset();
            *failed = true;
            let _ = tx.send(AcquisitionEvent::Driver(failure));
            return ControlFlow::Break(());
        }
        SerialEvent::Driver(other) => AcquisitionEvent::Driver(other),
    };
    if tx.send(out).is_err() {
        ControlFlow::Break(())
    } else {
        ControlFlow::Continue(())
    }
}

/// CPU time consumed by the calling thread so far.
fn thread_cpu_time() -> Duration {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map(Duration::from)
        .unwrap_or_default()
}
