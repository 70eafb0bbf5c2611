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
use crate::lidar::{DriverStats, LidarDriver, LidarEvent, LidarKind};
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
    /// The samples of one serial read as soon as it returned, each with the measurement time
    /// and revolution position it has in its [`AcquisitionEvent::Revolution`] (one time per
    /// sample); only when the thread was spawned with `forward_samples` (the static-scan
    /// controller acts within a revolution). One event per read, not per sample: the receiver
    /// wakes once for a batch.
    Samples(Vec<StampedSample>),
    /// Any other driver event: info, health, scanning, warnings, and `Failed` (after which the
    /// thread restarts the handshake following a pause). Samples and revolution ends never
    /// come this way: they arrive assembled as [`AcquisitionEvent::Revolution`]s.
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
    /// Whether samples are forwarded ([`Acquisition::forward_samples`]).
    forwarding: Arc<AtomicBool>,
    thread: Option<JoinHandle<Result<AcquisitionSummary, SerialError>>>,
}

/// Pause before restarting a driver that gave up (wrong answers, device error).
const RESTART_PAUSE: Duration = Duration::from_secs(1);

impl Acquisition {
    /// Starts reading `driver` on the port described by `options`, on a thread named after
    /// the device family (`rplidar`, `sweep`). With `forward_samples`, every sample is also
    /// sent, timed, as its read returns ([`AcquisitionEvent::Samples`]); that can be turned on
    /// and off later with [`Acquisition::forward_samples`].
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
        let forwarding = Arc::new(AtomicBool::new(forward_samples));
        let wanted = forwarding.clone();
        let name = match driver.kind() {
            LidarKind::Rplidar => "rplidar",
            LidarKind::Sweep => "sweep",
        };
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || {
                let mut assembler = RevolutionAssembler::new(timing);
                let mut forwarding = forward_samples.then(Vec::new);
                while !stop.load(Ordering::Relaxed) {
                    let mut failed = false;
                    serial::run(driver.as_mut(), &options, clock.as_ref(), &stop, |event| {
                        let drained = event == SerialEvent::Drained;
                        let flow =
                            forward(event, &mut assembler, &tx, &mut failed, &mut forwarding);
                        // A read's batch went out: the next read follows the current wish, so
                        // a batch is forwarded whole or not at all.
                        let on = wanted.load(Ordering::Relaxed);
                        if drained && on != forwarding.is_some() {
                            forwarding = on.then(Vec::new);
                        }
                        flow
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
        (
            Self {
                shutdown,
                forwarding,
                thread,
            },
            rx,
        )
    }

    /// Turns forwarding every sample ([`AcquisitionEvent::Samples`]) on or off, from the next
    /// read on. Off, the receiver is woken only by revolutions and the device's other events
    /// (the Sweep worker needs the samples only while a static scan runs or waits).
    pub fn forward_samples(&self, on: bool) {
        self.forwarding.store(on, Ordering::Relaxed);
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

/// Sends the samples gathered since the last batch, if any; `false` when the receiver is gone.
fn send_samples(
    forwarding: &mut Option<Vec<StampedSample>>,
    tx: &Sender<AcquisitionEvent>,
) -> bool {
    match forwarding {
        Some(batch) if !batch.is_empty() => tx
            .send(AcquisitionEvent::Samples(std::mem::take(batch)))
            .is_ok(),
        _ => true,
    }
}

/// Turns shell events into acquisition events; `Break` when the driver failed (to restart it)
/// or the receiver is gone. With `forwarding` (`Some`), stamped samples gather there and go out
/// as one [`AcquisitionEvent::Samples`] per read, always before any later event.
fn forward(
    event: SerialEvent,
    assembler: &mut RevolutionAssembler,
    tx: &Sender<AcquisitionEvent>,
    failed: &mut bool,
    forwarding: &mut Option<Vec<StampedSample>>,
) -> ControlFlow<()> {
    let out = match event {
        SerialEvent::Driver(LidarEvent::Sample(sample)) => {
            let stamped = assembler.stamp(sample);
            if let Some(batch) = forwarding.as_mut() {
                batch.push(stamped.sample);
            }
            match stamped.finished {
                Some(rev) => AcquisitionEvent::Revolution(rev),
                None => return ControlFlow::Continue(()),
            }
        }
        SerialEvent::Driver(LidarEvent::RevolutionComplete) => match assembler.complete() {
            Some(rev) => AcquisitionEvent::Revolution(rev),
            None => return ControlFlow::Continue(()),
        },
        SerialEvent::Drained => {
            return if send_samples(forwarding, tx) {
                ControlFlow::Continue(())
            } else {
                ControlFlow::Break(())
            };
        }
        SerialEvent::Opened => {
            assembler.reset();
            AcquisitionEvent::Opened
        }
        SerialEvent::Lost(reason) => {
            assembler.reset();
            AcquisitionEvent::Lost(reason)
        }
        SerialEvent::Driver(failure @ LidarEvent::Failed(_)) => {
            assembler.reset();
            *failed = true;
            if send_samples(forwarding, tx) {
                let _ = tx.send(AcquisitionEvent::Driver(failure));
            }
            return ControlFlow::Break(());
        }
        SerialEvent::Driver(other) => AcquisitionEvent::Driver(other),
    };
    // The samples gathered so far go first: the receiver sees events in the device's order.
    if send_samples(forwarding, tx) && tx.send(out).is_ok() {
        ControlFlow::Continue(())
    } else {
        ControlFlow::Break(())
    }
}

/// CPU time consumed by the calling thread so far.
fn thread_cpu_time() -> Duration {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map(Duration::from)
        .unwrap_or_default()
}
