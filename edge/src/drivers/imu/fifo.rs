//! The FIFO read path's pure parts: the record layout the driver configures, how often to read,
//! and the measurement time of every sample read from the FIFO ([`FifoClock`]).
//!
//! **Timestamps.** A FIFO read returns samples, not times. The chip writes one record per
//! sample period P (from SMPLRT_DIV, on its own oscillator: the nominal P is off by up to a
//! few per cent), so within one unbroken stream (since the last FIFO reset) the samples are
//! evenly spaced and sample `i` was measured at `t0 + i·P_chip`. What the host knows is an
//! upper bound per read: the newest sample in the FIFO when its count was read was measured
//! before that count transaction ended (`count_read_ns`). [`FifoClock`] fits the line
//! `t = a + b·i` that lies on or below those bounds over the last two seconds and is closest to
//! them (the lower envelope, [`crate::timing`]'s estimator, the same idea as NTP's
//! minimum-delay filter): the reads that came soonest after their newest sample define it, late
//! reads cannot pull it. Its slope is the chip's period on the edge clock (clamped to ±5 % of
//! the nominal one); before half a second of stream the nominal period anchored at the read
//! time is used. Reads are spaced by a non-whole number of sample periods
//! ([`fifo_read_interval_ns`]) so that their phase against the chip's sampling sweeps a whole
//! period within a few reads: some read always comes soon after a sample, which keeps the
//! envelope within a fraction of a period of the measurement times (within 1 ms at 200 Hz in
//! the tests, with a 2 % fast chip or a read in seven delayed by 3 ms; the per-sample path
//! stamped a reading when it was read, up to a period after it was measured). A FIFO reset (overflow,
//! an unreadable content) starts a new stream: [`FifoClock::restart`]. Stamps never go
//! backwards.

use std::collections::VecDeque;

use super::registers::mpu;
use crate::timing::lower_envelope_fit;

/// Bytes the MPU-9250's FIFO holds.
pub const FIFO_CAPACITY: usize = 512;
/// Bytes of the accel (6), temperature (2) and gyro (6) part of a record, in register order.
pub const MPU_RECORD_LEN: usize = 14;
/// Bytes of the AK8963 block the I2C master copies into EXT_SENS_DATA_00.. per sample: ST1,
/// HXL..HZH, ST2.
pub const MAG_RECORD_LEN: usize = 8;

/// What one FIFO record holds, as configured by the driver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FifoLayout {
    /// The AK8963 block (SLV0's EXT_SENS_DATA) follows the gyro.
    pub mag: bool,
}

impl FifoLayout {
    /// The FIFO_EN value: temperature, gyro x/y/z, accel, and SLV0 when the magnetometer is used.
    pub fn fifo_en(self) -> u8 {
        mpu::FIFO_EN_TEMP
            | mpu::FIFO_EN_GYRO
            | mpu::FIFO_EN_ACCEL
            | if self.mag { mpu::FIFO_EN_SLV0 } else { 0 }
    }

    /// Bytes per sample: 14, or 22 with the magnetometer.
    pub fn record_len(self) -> usize {
        MPU_RECORD_LEN + if self.mag { MAG_RECORD_LEN } else { 0 }
    }

    /// Whole records the FIFO holds (23 of 22 bytes, 36 of 14). A count above
    /// `records × record_len` can only come from an overflow: the chip then drops the oldest
    /// bytes and the content no longer starts at a record.
    pub fn capacity_records(self) -> usize {
        FIFO_CAPACITY / self.record_len()
    }
}

/// The time between two FIFO reads: `interval_ms`, shortened to half the time the FIFO takes to
/// fill (so one late wake-up does not overflow it), rounded down to whole sample periods and
/// less one, then lengthened by 0.382 of a period, so that successive reads fall at every phase of the
/// chip's sampling (see the module doc); at least one period.
pub fn fifo_read_interval_ns(interval_ms: u16, period_ns: u64, layout: FifoLayout) -> u64 {
    let period_ns = period_ns.max(1);
    let half_full_ns = (layout.capacity_records() as u64 / 2) * period_ns;
    let wanted_ns = (u64::from(interval_ms) * 1_000_000).min(half_full_ns);
    let whole = (wanted_ns / period_ns).max(1) - 1;
    (whole * period_ns + period_ns * 382 / 1000).max(period_ns)
}

/// Measurement times of FIFO samples from the times their counts were read (module doc).
#[derive(Debug, Clone)]
pub struct FifoClock {
    /// The nominal sample period, ns.
    period_ns: f64,
    /// Times are kept relative to this (the first read), for well-conditioned arithmetic.
    base_ns: Option<u64>,
    /// Index of the next sample in the stream since the last restart.
    next_index: u64,
    /// (index of a read's newest sample, count read time − base) over the last
    /// [`Self::WINDOW_S`].
    window: VecDeque<(f64, f64)>,
    /// The last stamp, so stamps never go backwards.
    last_ns: Option<u64>,
    /// Scratch space of the fit.
    hull: Vec<(f64, f64)>,
}

impl FifoClock {
    /// The envelope is fitted over this much stream.
    const WINDOW_S: f64 = 2.0;
    /// No fitted slope before the window spans this much.
    const MIN_SPAN_S: f64 = 0.5;
    /// The fitted period stays within this fraction of the nominal one.
    const MAX_RATE_ERROR: f64 = 0.05;

    /// A clock for samples `period_ns` apart (nominally).
    pub fn new(period_ns: u64) -> Self {
        Self {
            period_ns: period_ns.max(1) as f64,
            base_ns: None,
            next_index: 0,
            window: VecDeque::new(),
            last_ns: None,
            hull: Vec::new(),
        }
    }

    /// The FIFO was reset: the next sample starts a new stream (earlier reads say nothing
    /// about its times). Stamps still never go backwards.
    pub fn restart(&mut self) {
        self.next_index = 0;
        self.window.clear();
    }

    /// Appends to `out` the times of the next `samples` samples of the stream, oldest first,
    /// which were all in the FIFO when its count was read at `count_read_ns` (the end of the
    /// count transaction, edge clock).
    pub fn stamp(&mut self, count_read_ns: u64, samples: usize, out: &mut Vec<u64>) {
        if samples == 0 {
            return;
        }
        let base = *self.base_ns.get_or_insert(count_read_ns);
        let newest = self.next_index + samples as u64 - 1;
        let (x_newest, y_newest) = (newest as f64, count_read_ns as f64 - base as f64);
        self.window.push_back((x_newest, y_newest));
        let window_samples = Self::WINDOW_S * 1e9 / self.period_ns;
        while self
            .window
            .front()
            .is_some_and(|&(x, _)| x_newest - x > window_samples)
        {
            self.window.pop_front();
        }
        let span_s = self
            .window
            .front()
            .map_or(0.0, |&(x, _)| (x_newest - x) * self.period_ns * 1e-9);
        let slope = if span_s >= Self::MIN_SPAN_S {
            // Indices only grow, so the window is sorted as the fit needs.
            let (_, b) = lower_envelope_fit(self.window.make_contiguous(), &mut self.hull);
            b.clamp(
                self.period_ns * (1.0 - Self::MAX_RATE_ERROR),
                self.period_ns * (1.0 + Self::MAX_RATE_ERROR),
            )
        } else {
            self.period_ns
        };
        // The highest line of that slope under every read in the window.
        let intercept = if span_s >= Self::MIN_SPAN_S {
            self.window
                .iter()
                .map(|&(x, y)| y - slope * x)
                .fold(f64::INFINITY, f64::min)
        } else {
            y_newest - slope * x_newest
        };
        for index in self.next_index..=newest {
            let t = base as f64 + intercept + slope * index as f64;
            let t = t.max(0.0).round() as u64;
            let t = match self.last_ns {
                Some(last) if t <= last => last + 1,
                _ => t,
            };
            self.last_ns = Some(t);
            out.push(t);
        }
        self.next_index = newest + 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    #[test]
    fn layout_of_the_records() {
        let with_mag = FifoLayout { mag: true };
        assert_eq!(with_mag.fifo_en(), 0xF9);
        assert_eq!(with_mag.record_len(), 22);
        assert_eq!(with_mag.capacity_records(), 23);
        let without = FifoLayout { mag: false };
        assert_eq!(without.fifo_en(), 0xF8);
        assert_eq!(without.capacity_records(), 36);
    }

    #[test]
    fn read_interval_sweeps_the_phase_and_leaves_half_the_fifo() {
        let layout = FifoLayout { mag: true };
        // 40 ms at 200 Hz: 7 whole periods + 0.382 of one.
        assert_eq!(fifo_read_interval_ns(40, 5 * MS, layout), 36_910_000);
        // 1 kHz: 23 records fill in 23 ms; half of it is 11 ms.
        assert_eq!(fifo_read_interval_ns(40, MS, layout), 10_382_000);
        // Never shorter than a period.
        assert_eq!(fifo_read_interval_ns(1, 5 * MS, layout), 5 * MS);
    }

    /// Reads every `interval` of a chip sampling every `chip_period` from `t0`, each count
    /// read ending `delay(read)` after it was asked: the stamps against the true times.
    fn run(
        nominal_period: u64,
        chip_period: f64,
        interval: u64,
        reads: usize,
        delay: impl Fn(usize) -> u64,
    ) -> Vec<(u64, f64)> {
        let t0 = 1_000.0 * MS as f64 + 1234.0;
        let mut clock = FifoClock::new(nominal_period);
        let mut stamped = Vec::new();
        let mut next_sample = 0u64;
        let mut out = Vec::new();
        for read in 0..reads {
            let asked = 1_000 * MS + 3 * MS + read as u64 * interval;
            // Samples measured by the time the count was latched (the ask).
            let mut samples = 0;
            while t0 + (next_sample + samples as u64) as f64 * chip_period <= asked as f64 {
                samples += 1;
            }
            out.clear();
            clock.stamp(asked + delay(read), samples, &mut out);
            for (k, &t) in out.iter().enumerate() {
                stamped.push((t, t0 + (next_sample + k as u64) as f64 * chip_period));
            }
            next_sample += samples as u64;
        }
        stamped
    }

    #[test]
    fn stamps_converge_on_the_measurement_times_under_jitter() {
        let period = 5 * MS;
        let interval = fifo_read_interval_ns(40, period, FifoLayout { mag: true });
        // The count transaction returns 30 to 150 µs after the chip latched the count, and
        // every 7th read 3 ms later (preempted): pseudo-random.
        let delay = |read: usize| {
            30_000
                + (read as u64 * 7_919 % 13) * 10_000
                + if read.is_multiple_of(7) { 3_000_000 } else { 0 }
        };
        let stamped = run(period, period as f64, interval, 200, delay);
        let after_fit: Vec<f64> = stamped[200..]
            .iter()
            .map(|&(t, truth)| t as f64 - truth)
            .collect();
        let worst = after_fit.iter().fold(0.0f64, |w, e| w.max(e.abs()));
        assert!(worst < 1e6, "worst error {worst} ns");
        // Stamps never go backwards and are never after the read that delivered them.
        assert!(stamped.windows(2).all(|w| w[0].0 < w[1].0));
    }

    #[test]
    fn a_chip_running_fast_is_followed() {
        // The chip's oscillator 2 % fast: the nominal period alone would drift 8 ms over the
        // two-second window; the fitted slope follows it, within a millisecond.
        let period = 5 * MS;
        let interval = fifo_read_interval_ns(40, period, FifoLayout { mag: true });
        let delay = |read: usize| 30_000 + (read as u64 * 7_919 % 13) * 10_000;
        let stamped = run(period, period as f64 * 0.98, interval, 300, delay);
        let worst = stamped[400..]
            .iter()
            .map(|&(t, truth)| (t as f64 - truth).abs())
            .fold(0.0f64, f64::max);
        assert!(worst < 1e6, "worst error {worst} ns");
    }

    #[test]
    fn a_restart_anchors_the_new_stream_at_its_first_read() {
        let mut clock = FifoClock::new(5 * MS);
        let mut out = Vec::new();
        clock.stamp(100 * MS, 3, &mut out);
        assert_eq!(out, [90 * MS, 95 * MS, 100 * MS]);
        clock.restart();
        out.clear();
        clock.stamp(200 * MS, 2, &mut out);
        assert_eq!(out, [195 * MS, 200 * MS]);
        out.clear();
        clock.stamp(201 * MS, 0, &mut out);
        assert!(out.is_empty());
    }
}
