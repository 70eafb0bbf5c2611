//! `scan3d-edge probe`: the tool a user runs while wiring the Pi. It talks to one lidar and
//! prints what it finds as JSON lines: `info`, `health` (RPLidar) and one `revolution` per
//! full turn, then stops the device.
//!
//! [`Probe`] is the pure core (events in, lines out); [`run`] wires it to a serial port.

use std::ops::ControlFlow;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use serde::Serialize;

use crate::clock::Clock;
use crate::lidar::{DeviceInfo, DriverError, HealthStatus, LidarDriver, LidarEvent};
use crate::serial::{self, SerialEvent, SerialOptions};
use crate::timing::{Revolution, RevolutionAssembler, TimingConfig};

/// One line of probe output.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum ProbeLine {
    /// The device's identity.
    Info {
        /// `"A1"`, `"A2"` or `"Sweep"`.
        model: String,
        /// Firmware version text.
        firmware: String,
        /// Hardware revision.
        hardware: u32,
        /// Serial number text.
        serial: String,
    },
    /// RPLidar health.
    Health {
        /// Overall status.
        status: HealthStatus,
        /// Device error code.
        error_code: u16,
    },
    /// One full revolution, in the device's angle convention.
    Revolution {
        /// Estimated start time, edge clock ns.
        t0_ns: u64,
        /// Estimated end time (start of the next revolution), edge clock ns.
        t1_ns: u64,
        /// Angles as the device reports them (RPLidar clockwise).
        angles_deg: Vec<f32>,
        /// Ranges in metres, `0.0` = no return.
        ranges_m: Vec<f32>,
        /// Raw qualities (RPLidar 6-bit quality, Sweep signal strength).
        qualities: Vec<u8>,
        /// Per-sample measurement times, edge clock ns.
        times_ns: Vec<u64>,
    },
}

impl From<DeviceInfo> for ProbeLine {
    fn from(info: DeviceInfo) -> Self {
        Self::Info {
            model: info.model,
            firmware: info.firmware,
            hardware: info.hardware,
            serial: info.serial,
        }
    }
}

impl From<Revolution> for ProbeLine {
    fn from(rev: Revolution) -> Self {
        Self::Revolution {
            t0_ns: rev.t0_ns,
            t1_ns: rev.t1_ns,
            angles_deg: rev.samples.iter().map(|s| s.angle_deg).collect(),
            ranges_m: rev.samples.iter().map(|s| s.range_m).collect(),
            qualities: rev.samples.iter().map(|s| s.quality).collect(),
            times_ns: rev.samples.iter().map(|s| s.t_ns).collect(),
        }
    }
}

/// Why a probe failed.
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    /// The port could not be opened or was lost.
    #[error(transparent)]
    Serial(#[from] serial::SerialError),
    /// The driver gave up (no answer, wrong device, device error).
    #[error("{path}: {reason}")]
    Driver {
        /// The device path.
        path: PathBuf,
        /// The driver's reason (in the message, so not also a `source()`: printed once).
        reason: DriverError,
    },
    /// Nothing conclusive within the deadline.
    #[error("{path}: timed out after {seconds} s waiting for {waiting_for}")]
    Timeout {
        /// The device path.
        path: PathBuf,
        /// The deadline in (device) seconds.
        seconds: u64,
        /// What was still missing.
        waiting_for: &'static str,
    },
}

/// The probe's pure core: consumes shell events, produces output lines, decides when to stop.
#[derive(Debug)]
pub struct Probe {
    revolutions_wanted: usize,
    revolutions_seen: usize,
    got_info: bool,
    assembler: RevolutionAssembler,
    failure: Option<DriverError>,
}

impl Probe {
    /// A probe that stops after `revolutions` full revolutions.
    pub fn new(revolutions: usize) -> Self {
        Self {
            revolutions_wanted: revolutions,
            revolutions_seen: 0,
            got_info: false,
            assembler: RevolutionAssembler::new(TimingConfig::default()),
            failure: None,
        }
    }

    /// Handles one event, appending output lines to `out`; `Break` once done or failed.
    pub fn on_event(&mut self, event: SerialEvent, out: &mut Vec<ProbeLine>) -> ControlFlow<()> {
        match event {
            SerialEvent::Opened | SerialEvent::Lost(_) => self.assembler.reset(),
            SerialEvent::Drained => {}
            SerialEvent::Driver(LidarEvent::Info(info)) => {
                self.got_info = true;
                out.push(info.into());
            }
            SerialEvent::Driver(LidarEvent::Health { status, error_code }) => {
                out.push(ProbeLine::Health { status, error_code });
            }
            SerialEvent::Driver(LidarEvent::Sample(sample)) => {
                if let Some(rev) = self.assembler.push(sample) {
                    out.push(rev.into());
                    self.revolutions_seen += 1;
                }
            }
            SerialEvent::Driver(LidarEvent::RevolutionComplete) => {
                if let Some(rev) = self.assembler.complete() {
                    out.push(rev.into());
                    self.revolutions_seen += 1;
                }
            }
            SerialEvent::Driver(LidarEvent::Warning(text)) => tracing::warn!("{text}"),
            SerialEvent::Driver(LidarEvent::Scanning { sample_period_ns }) => {
                tracing::info!(sample_period_ns, "scanning");
            }
            SerialEvent::Driver(LidarEvent::Failed(error)) => {
                self.failure = Some(error);
                return ControlFlow::Break(());
            }
        }
        if self.done() {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    }

    /// All wanted revolutions were seen.
    pub fn done(&self) -> bool {
        self.revolutions_seen >= self.revolutions_wanted
    }
}

/// Probe options shared by both device kinds.
#[derive(Debug, Clone)]
pub struct ProbeOptions {
    /// Device path.
    pub path: PathBuf,
    /// Line rate.
    pub baud: u32,
    /// Revolutions to print.
    pub revolutions: usize,
    /// Give up after this much device time (ns) without finishing.
    pub deadline_ns: u64,
}

/// Runs a probe with `driver` on a real port, printing each line through `emit` as it comes.
pub fn run<D: LidarDriver + ?Sized>(
    driver: &mut D,
    options: &ProbeOptions,
    clock: Arc<dyn Clock>,
    mut emit: impl FnMut(&ProbeLine),
) -> Result<(), ProbeError> {
    let mut serial_options = SerialOptions::new(&options.path, options.baud);
    serial_options.reconnect = false;
    let shutdown = Arc::new(AtomicBool::new(false));
    let timed_out = Arc::new(AtomicBool::new(false));
    let watchdog = {
        let (shutdown, timed_out) = (shutdown.clone(), timed_out.clone());
        let real = clock.real_duration(options.deadline_ns);
        std::thread::spawn(move || {
            let step = Duration::from_millis(20);
            let mut waited = Duration::ZERO;
            while waited < real && !shutdown.load(Ordering::Relaxed) {
                std::thread::sleep(step);
                waited += step;
            }
            if !shutdown.load(Ordering::Relaxed) {
                timed_out.store(true, Ordering::Relaxed);
                shutdown.store(true, Ordering::Relaxed);
            }
        })
    };
    let mut probe = Probe::new(options.revolutions);
    let mut lines = Vec::new();
    let result = serial::run(
        driver,
        &serial_options,
        clock.as_ref(),
        &shutdown,
        |event| {
            let flow = probe.on_event(event, &mut lines);
            for line in lines.drain(..) {
                emit(&line);
            }
            flow
        },
    );
    let was_timeout = timed_out.load(Ordering::Relaxed);
    shutdown.store(true, Ordering::Relaxed);
    let _ = watchdog.join();
    result?;
    if let Some(reason) = probe.failure.take() {
        return Err(ProbeError::Driver {
            path: options.path.clone(),
            reason,
        });
    }
    if was_timeout && !probe.done() {
        return Err(ProbeError::Timeout {
            path: options.path.clone(),
            seconds: options.deadline_ns / 1_000_000_000,
            waiting_for: if probe.got_info {
                "full revolutions"
            } else {
                "the device to answer"
            },
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::{ArrivedSample, RawSample};

    fn sample(angle: f32, start: bool, t: u64) -> SerialEvent {
        SerialEvent::Driver(LidarEvent::Sample(ArrivedSample {
            sample: RawSample {
                angle_deg: angle,
                range_m: 1.5,
                quality: 40,
                new_revolution: start,
            },
            arrival_ns: t,
        }))
    }

    #[test]
    fn prints_info_health_and_stops_after_the_wanted_revolutions() {
        let mut probe = Probe::new(2);
        let mut out = Vec::new();
        let info = DeviceInfo {
            model: "A1".into(),
            firmware: "1.29".into(),
            hardware: 7,
            serial: "00".repeat(16),
        };
        assert!(
            probe
                .on_event(SerialEvent::Driver(LidarEvent::Info(info)), &mut out)
                .is_continue()
        );
        let health = LidarEvent::Health {
            status: HealthStatus::Good,
            error_code: 0,
        };
        assert!(
            probe
                .on_event(SerialEvent::Driver(health), &mut out)
                .is_continue()
        );
        let mut flow = ControlFlow::Continue(());
        let mut t = 0;
        'outer: for _rev in 0..4 {
            for k in 0..20 {
                t += 1_000_000;
                flow = probe.on_event(sample(k as f32 * 18.0, k == 0, t), &mut out);
                if flow.is_break() {
                    break 'outer;
                }
            }
        }
        assert!(flow.is_break());
        let json: Vec<String> = out
            .iter()
            .map(|l| serde_json::to_string(l).expect("serialisable"))
            .collect();
        assert_eq!(
            json[0],
            format!(
                r#"{{"type":"info","model":"A1","firmware":"1.29","hardware":7,"serial":"{}"}}"#,
                "00".repeat(16)
            )
        );
        assert_eq!(
            json[1],
            r#"{"type":"health","status":"good","error_code":0}"#
        );
        assert_eq!(out.len(), 4);
        match &out[2] {
            ProbeLine::Revolution {
                angles_deg,
                ranges_m,
                qualities,
                t0_ns,
                t1_ns,
                ..
            } => {
                assert_eq!(angles_deg.len(), 20);
                assert_eq!(angles_deg[1], 18.0);
                assert!(ranges_m.iter().all(|&r| r == 1.5));
                assert!(qualities.iter().all(|&q| q == 40));
                assert!(t1_ns > t0_ns);
            }
            other => panic!("expected a revolution, got {other:?}"),
        }
    }

    #[test]
    fn a_driver_failure_stops_the_probe() {
        let mut probe = Probe::new(3);
        let mut out = Vec::new();
        let failed = LidarEvent::Failed(DriverError::NoAnswer {
            command: "GET_INFO",
            attempts: 3,
        });
        assert!(
            probe
                .on_event(SerialEvent::Driver(failed), &mut out)
                .is_break()
        );
        assert!(out.is_empty());
        assert!(probe.failure.is_some());
    }
}
