//! The IMU thread: reads the MPU-9250 + AK8963 at its configured rate, fuses each reading with
//! Madgwick on the edge, and hands an [`ImuSample`] (raw values plus orientation) to the daemon.
//!
//! Bus errors are retried by the driver; a reading that still fails is logged and skipped, and
//! after [`MAX_CONSECUTIVE_FAILURES`] the chip is re-initialised (with a pause) while the
//! daemon reports the IMU lost, then back.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use scan3d_protocol::ImuSample;

use crate::clock::SharedClock;
use crate::config::ImuSection;
use crate::drivers::imu::{ChipIds, Mpu9250};
use crate::madgwick::Madgwick;

/// Failed readings in a row after which the chip is initialised again.
pub const MAX_CONSECUTIVE_FAILURES: u32 = 10;

/// What the IMU thread reports.
#[derive(Debug, Clone, PartialEq)]
pub enum ImuEvent {
    /// The chips answered the init sequence.
    Ready(ChipIds),
    /// A fused reading.
    Sample(ImuSample),
    /// The IMU stopped answering (init failed or too many failed reads).
    Lost(String),
}

/// Counters of a finished IMU thread.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ImuReport {
    /// Readings handed over.
    pub samples: u64,
    /// Readings that failed.
    pub failed_reads: u64,
    /// I2C transactions (including retries).
    pub transactions: u64,
}

/// A running IMU thread.
pub struct ImuWorker {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<ImuReport>>,
}

impl ImuWorker {
    /// Starts reading; `on_event` runs on the IMU thread for every event.
    pub fn spawn<I, D>(
        bus: I,
        mut delay: D,
        section: ImuSection,
        clock: SharedClock,
        mut on_event: impl FnMut(ImuEvent) + Send + 'static,
    ) -> std::io::Result<Self>
    where
        I: I2c + Send + 'static,
        D: DelayNs + Send + 'static,
    {
        let stop = Arc::new(AtomicBool::new(false));
        let stopping = stop.clone();
        let thread = std::thread::Builder::new()
            .name("imu".into())
            .spawn(move || {
                let period_ns = u64::from(section.driver.sample_period_ns());
                let mut imu = Mpu9250::new(bus, section.driver.clone());
                let mut report = ImuReport::default();
                'init: while !stopping.load(Ordering::Relaxed) {
                    match imu.init(&mut delay) {
                        Ok(ids) => on_event(ImuEvent::Ready(ids)),
                        Err(e) => {
                            on_event(ImuEvent::Lost(e.to_string()));
                            std::thread::sleep(Duration::from_secs(1));
                            continue;
                        }
                    }
                    let mut filter = initial_filter(&section);
                    let mut failures = 0;
                    let mut next_ns = clock.now_ns();
                    let mut last_ns: Option<u64> = None;
                    while !stopping.load(Ordering::Relaxed) {
                        next_ns += period_ns;
                        let now = clock.now_ns();
                        if next_ns > now {
                            std::thread::sleep(clock.real_duration(next_ns - now));
                        } else if now - next_ns > 10 * period_ns {
                            next_ns = now; // fell far behind (suspended): do not burst
                        }
                        let reading = match imu.read() {
                            Ok(reading) => reading,
                            Err(e) => {
                                report.failed_reads += 1;
                                failures += 1;
                                tracing::warn!(error = %e, "IMU read failed");
                                if failures >= MAX_CONSECUTIVE_FAILURES {
                                    on_event(ImuEvent::Lost(e.to_string()));
                                    std::thread::sleep(Duration::from_secs(1));
                                    continue 'init;
                                }
                                continue;
                            }
                        };
                        failures = 0;
                        let t_ns = clock.now_ns();
                        let dt_s = last_ns.map_or(period_ns as f64 * 1e-9, |last| {
                            t_ns.saturating_sub(last) as f64 * 1e-9
                        });
                        last_ns = Some(t_ns);
                        let v = |v: [f32; 3]| Vector3::from(v.map(f64::from));
                        let (gyro, accel) = (v(reading.gyro_rad_s), v(reading.accel_m_s2));
                        filter = match (filter, reading.mag_ut) {
                            (Some(mut f), Some(mag)) => {
                                f.update_marg(gyro, accel, v(mag), dt_s);
                                Some(f)
                            }
                            (Some(mut f), None) => {
                                f.update_imu(gyro, accel, dt_s);
                                Some(f)
                            }
                            (None, Some(mag)) => {
                                Madgwick::from_accel_mag(section.beta, accel, v(mag)).ok()
                            }
                            (None, None) => None,
                        };
                        report.samples += 1;
                        on_event(ImuEvent::Sample(ImuSample {
                            t_ns,
                            accel_mps2: reading.accel_m_s2,
                            gyro_radps: reading.gyro_rad_s,
                            mag_ut: reading.mag_ut.unwrap_or([f32::NAN; 3]),
                            orientation: filter.as_ref().map(|f| f.wxyz().map(|c| c as f32)),
                        }));
                    }
                }
                report.transactions = imu.stats().transactions;
                report
            })?;
        Ok(Self {
            stop,
            thread: Some(thread),
        })
    }

    /// Stops the thread and returns its counters.
    pub fn stop(mut self) -> ImuReport {
        self.stop.store(true, Ordering::Relaxed);
        self.thread
            .take()
            .and_then(|t| t.join().ok())
            .unwrap_or_default()
    }
}

impl Drop for ImuWorker {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// The filter from the configured initial orientation, or `None` to start from the first
/// accelerometer + magnetometer pair.
fn initial_filter(section: &ImuSection) -> Option<Madgwick> {
    let [w, x, y, z] = section.initial_orientation_wxyz?;
    let q = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
    match Madgwick::new(section.beta, q) {
        Ok(filter) => Some(filter),
        Err(e) => {
            tracing::warn!(error = %e, "initial orientation refused; using the first accel+mag pair");
            None
        }
    }
}
