//! The IMU thread: reads the MPU-9250 + AK8963, fuses each reading with Madgwick on the edge,
//! and hands an [`ImuSample`] (raw values plus orientation) to the daemon.
//!
//! In FIFO mode (the default) it wakes every [`fifo_read_interval_ns`] (about 37 ms at 200 Hz),
//! reads the FIFO's count and its whole records (two bus transactions) and stamps each sample
//! with [`FifoClock`] from the time the count was read: the samples and their rates are those
//! of the per-sample path, the bus and the thread wake 27 times a second instead of 200. An
//! overflow (the thread was not scheduled for about 115 ms) or a content that cannot be aligned
//! is logged and counted; the driver has reset the FIFO and the next samples start a new
//! stream. In register mode it polls [`Mpu9250::read`] at the sample rate and stamps each
//! reading with the time it was read.
//!
//! Bus errors are retried by the driver; a read that still fails is skipped (logged at debug),
//! and after [`MAX_CONSECUTIVE_FAILURES`] in a row the chip is re-initialised (with a pause)
//! while the daemon reports the IMU lost, with the last error, in one line; a run of failures
//! that recovers before that is logged once, at warn, when it ends.

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
use crate::drivers::imu::{
    ChipIds, Error, FifoClock, FifoLayout, FifoRead, ImuReading, Mpu9250, fifo_read_interval_ns,
};
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
    /// FIFO overflows (samples lost).
    pub fifo_overflows: u64,
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
                let mut imu = Mpu9250::new(bus, section.driver.clone());
                let mut report = ImuReport::default();
                while !stopping.load(Ordering::Relaxed) {
                    match imu.init(&mut delay) {
                        Ok(ids) => on_event(ImuEvent::Ready(ids)),
                        Err(e) => {
                            on_event(ImuEvent::Lost(e.to_string()));
                            std::thread::sleep(Duration::from_secs(1));
                            continue;
                        }
                    }
                    let mut reader = Reader {
                        section: &section,
                        clock: &clock,
                        stopping: &stopping,
                        report: &mut report,
                        fusion: Fusion::new(&section),
                        failures: Failures::default(),
                    };
                    let lost = match imu.fifo_layout() {
                        Some(layout) => reader.run_fifo(&mut imu, layout, &mut on_event),
                        None => reader.run_registers(&mut imu, &mut on_event),
                    };
                    if let Some(reason) = lost {
                        on_event(ImuEvent::Lost(reason));
                        std::thread::sleep(Duration::from_secs(1));
                    }
                }
                report.transactions = imu.stats().transactions;
                report.fifo_overflows = imu.stats().fifo_overflows;
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

/// One initialised run of the IMU thread: reads until stopped or lost.
struct Reader<'a> {
    section: &'a ImuSection,
    clock: &'a SharedClock,
    stopping: &'a AtomicBool,
    report: &'a mut ImuReport,
    fusion: Fusion,
    failures: Failures,
}

impl Reader<'_> {
    /// FIFO mode: a batch every read interval. Returns why the IMU is lost, or `None` when
    /// stopped.
    fn run_fifo<I: I2c>(
        &mut self,
        imu: &mut Mpu9250<I>,
        layout: FifoLayout,
        on_event: &mut impl FnMut(ImuEvent),
    ) -> Option<String> {
        let period_ns = u64::from(self.section.driver.sample_period_ns());
        let interval_ns =
            fifo_read_interval_ns(self.section.driver.fifo_read_interval_ms, period_ns, layout);
        let mut stamps = FifoClock::new(period_ns);
        let (mut readings, mut times) = (Vec::new(), Vec::new());
        let mut wake = Wake::new(self.clock, interval_ns);
        while !self.stopping.load(Ordering::Relaxed) {
            wake.sleep(self.clock);
            readings.clear();
            let clock = self.clock;
            let batch = imu.fifo_count().and_then(|count| {
                // The end of the count transaction bounds the newest counted sample's time.
                let counted_ns = clock.now_ns();
                imu.read_fifo(count, &mut readings)
                    .map(|read| (read, counted_ns))
            });
            match batch {
                Ok((FifoRead::Samples { samples, restarted }, counted_ns)) => {
                    self.failures.recovered();
                    if restarted {
                        stamps.restart();
                        self.fusion.gap();
                    }
                    times.clear();
                    stamps.stamp(counted_ns, samples, &mut times);
                    for (reading, &t_ns) in readings.iter().zip(&times) {
                        self.emit(reading, t_ns, period_ns, on_event);
                    }
                }
                Ok((FifoRead::Overflow { count }, _)) => {
                    self.failures.recovered();
                    self.report.fifo_overflows += 1;
                    tracing::warn!(
                        count,
                        overflows = self.report.fifo_overflows,
                        "IMU FIFO overflowed (not read for too long): samples lost, FIFO reset"
                    );
                }
                Ok((FifoRead::Misaligned, _)) => {
                    self.failures.recovered();
                    tracing::warn!(
                        "IMU FIFO content not aligned to its records: discarded, FIFO reset"
                    );
                }
                Err(e) => {
                    if let Some(reason) = self.failed(&e) {
                        return Some(reason);
                    }
                }
            }
        }
        None
    }

    /// Register mode: one reading per sample period, stamped when it was read.
    fn run_registers<I: I2c>(
        &mut self,
        imu: &mut Mpu9250<I>,
        on_event: &mut impl FnMut(ImuEvent),
    ) -> Option<String> {
        let period_ns = u64::from(self.section.driver.sample_period_ns());
        let mut wake = Wake::new(self.clock, period_ns);
        while !self.stopping.load(Ordering::Relaxed) {
            wake.sleep(self.clock);
            match imu.read() {
                Ok(reading) => {
                    self.failures.recovered();
                    let t_ns = self.clock.now_ns();
                    self.emit(&reading, t_ns, period_ns, on_event);
                }
                Err(e) => {
                    if let Some(reason) = self.failed(&e) {
                        return Some(reason);
                    }
                }
            }
        }
        None
    }

    /// Counts a failed read; the reason the IMU is lost once there were too many in a row.
    fn failed<E: embedded_hal::i2c::Error>(&mut self, e: &Error<E>) -> Option<String> {
        self.report.failed_reads += 1;
        self.failures.failed(e.to_string())
    }

    fn emit(
        &mut self,
        reading: &ImuReading,
        t_ns: u64,
        period_ns: u64,
        on_event: &mut impl FnMut(ImuEvent),
    ) {
        self.report.samples += 1;
        let sample = self.fusion.fuse(reading, t_ns, period_ns);
        on_event(ImuEvent::Sample(sample));
    }
}

/// The wake-up schedule: every `interval_ns`, without bursts after a suspension.
struct Wake {
    next_ns: u64,
    interval_ns: u64,
}

impl Wake {
    fn new(clock: &SharedClock, interval_ns: u64) -> Self {
        Self {
            next_ns: clock.now_ns(),
            interval_ns,
        }
    }

    fn sleep(&mut self, clock: &SharedClock) {
        self.next_ns += self.interval_ns;
        let now = clock.now_ns();
        if self.next_ns > now {
            std::thread::sleep(clock.real_duration(self.next_ns - now));
        } else if now - self.next_ns > 10 * self.interval_ns {
            self.next_ns = now; // fell far behind (suspended): do not burst
        }
    }
}

/// Failed reads in a row, logged once per run of failures rather than once per read.
#[derive(Default)]
struct Failures {
    in_a_row: u32,
    last_error: String,
}

impl Failures {
    /// A read failed: the reason the IMU is lost once [`MAX_CONSECUTIVE_FAILURES`] came in a
    /// row (the run then ends, unlogged here: the daemon logs the loss).
    fn failed(&mut self, error: String) -> Option<String> {
        self.in_a_row += 1;
        tracing::debug!(%error, in_a_row = self.in_a_row, "IMU read failed");
        if self.in_a_row >= MAX_CONSECUTIVE_FAILURES {
            self.in_a_row = 0;
            return Some(error);
        }
        self.last_error = error;
        None
    }

    /// A read succeeded: a run of failures that ended is logged once.
    fn recovered(&mut self) {
        if self.in_a_row > 0 {
            tracing::warn!(
                failed_reads = self.in_a_row,
                last_error = %self.last_error,
                "IMU reads failed, then recovered"
            );
            self.in_a_row = 0;
        }
    }
}

/// Madgwick over the readings, each with its time.
struct Fusion {
    beta: f64,
    filter: Option<Madgwick>,
    last_ns: Option<u64>,
    /// The calibrated field's check (`mag_field_ut`), if configured.
    field: Option<crate::calibrate::FieldMonitor>,
}

impl Fusion {
    fn new(section: &ImuSection) -> Self {
        Self {
            beta: section.beta,
            filter: initial_filter(section),
            last_ns: None,
            field: crate::calibrate::FieldMonitor::from_config(&section.driver),
        }
    }

    /// Samples were lost: the next one integrates one nominal period, not the gap.
    fn gap(&mut self) {
        self.last_ns = None;
    }

    fn fuse(&mut self, reading: &ImuReading, t_ns: u64, period_ns: u64) -> ImuSample {
        let dt_s = self.last_ns.map_or(period_ns as f64 * 1e-9, |last| {
            t_ns.saturating_sub(last) as f64 * 1e-9
        });
        self.last_ns = Some(t_ns);
        if let (Some(monitor), Some(mag)) = (&mut self.field, reading.mag_ut)
            && let Some(warning) = monitor.check(t_ns, mag)
        {
            tracing::warn!("{warning}");
        }
        let v = |v: [f32; 3]| Vector3::from(v.map(f64::from));
        let (gyro, accel) = (v(reading.gyro_rad_s), v(reading.accel_m_s2));
        self.filter = match (self.filter.take(), reading.mag_ut) {
            (Some(mut f), Some(mag)) => {
                f.update_marg(gyro, accel, v(mag), dt_s);
                Some(f)
            }
            (Some(mut f), None) => {
                f.update_imu(gyro, accel, dt_s);
                Some(f)
            }
            (None, Some(mag)) => Madgwick::from_accel_mag(self.beta, accel, v(mag)).ok(),
            (None, None) => None,
        };
        ImuSample {
            t_ns,
            accel_mps2: reading.accel_m_s2,
            gyro_radps: reading.gyro_rad_s,
            mag_ut: reading.mag_ut.unwrap_or([f32::NAN; 3]),
            orientation: self.filter.as_ref().map(|f| f.wxyz().map(|c| c as f32)),
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
