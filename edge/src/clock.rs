//! The edge's monotonic clock, injected so tests and the simulator can run on scaled time.

use std::sync::Arc;
use std::time::{Duration, Instant};

/// A monotonic clock in nanoseconds since an arbitrary epoch (the edge's process start).
///
/// Every sample on the edge is stamped with one clock; passing it in keeps parsers pure and
/// lets a simulation run the edge faster than real time.
pub trait Clock: Send + Sync {
    /// Nanoseconds since this clock's epoch; never decreases.
    fn now_ns(&self) -> u64;

    /// How long a real-time sleep must be for `ns` of this clock's time to pass.
    fn real_duration(&self, ns: u64) -> Duration {
        Duration::from_nanos(ns)
    }
}

/// Shared handle to a clock.
pub type SharedClock = Arc<dyn Clock>;

/// An embedded-hal [`DelayNs`](embedded_hal::delay::DelayNs) that waits `ns` of a clock's time
/// (real time for [`MonotonicClock`], `ns / scale` for [`ScaledClock`]), so drivers paced by a
/// delay — the stepper's step period, the IMU's reset waits — follow a scaled simulation.
#[derive(Clone)]
pub struct ClockDelay(pub SharedClock);

impl embedded_hal::delay::DelayNs for ClockDelay {
    fn delay_ns(&mut self, ns: u32) {
        std::thread::sleep(self.0.real_duration(u64::from(ns)));
    }
}

/// CLOCK_MONOTONIC via [`Instant`], the clock the edge uses on real hardware.
#[derive(Debug, Clone, Copy)]
pub struct MonotonicClock {
    epoch: Instant,
}

impl MonotonicClock {
    /// A clock whose epoch is now.
    pub fn new() -> Self {
        Self {
            epoch: Instant::now(),
        }
    }
}

impl Default for MonotonicClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for MonotonicClock {
    fn now_ns(&self) -> u64 {
        u64::try_from(self.epoch.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }
}

/// A monotonic clock running `scale` times faster than real time.
///
/// The hw-sim emulators run their devices `scale` times faster; an edge on the same scale sees
/// the sample rates, revolution periods and timeouts of the real device.
#[derive(Debug, Clone, Copy)]
pub struct ScaledClock {
    epoch: Instant,
    scale: f64,
}

impl ScaledClock {
    /// The real instant at which this clock read 0 (to align a simulated device's clock).
    pub fn epoch(&self) -> Instant {
        self.epoch
    }

    /// A clock whose epoch is now, advancing `scale` nanoseconds per real nanosecond.
    ///
    /// Non-finite or non-positive scales are treated as 1.
    pub fn new(scale: f64) -> Self {
        let scale = if scale.is_finite() && scale > 0.0 {
            scale
        } else {
            1.0
        };
        Self {
            epoch: Instant::now(),
            scale,
        }
    }

    /// The time-scale factor.
    pub fn scale(&self) -> f64 {
        self.scale
    }
}

impl Clock for ScaledClock {
    fn now_ns(&self) -> u64 {
        (self.epoch.elapsed().as_nanos() as f64 * self.scale) as u64
    }

    fn real_duration(&self, ns: u64) -> Duration {
        Duration::from_nanos((ns as f64 / self.scale) as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scaled_clock_runs_faster_and_converts_durations_back() {
        let clock = ScaledClock::new(10.0);
        assert_eq!(
            clock.real_duration(1_000_000_000),
            Duration::from_millis(100)
        );
        let a = clock.now_ns();
        std::thread::sleep(Duration::from_millis(20));
        let b = clock.now_ns();
        assert!(
            b - a >= 200_000_000,
            "10x clock advanced only {} ns in 20 ms",
            b - a
        );
    }

    #[test]
    fn invalid_scale_falls_back_to_real_time() {
        assert_eq!(ScaledClock::new(0.0).scale(), 1.0);
        assert_eq!(ScaledClock::new(f64::NAN).scale(), 1.0);
    }
}
