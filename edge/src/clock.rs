//! The edge's monotonic clock, injected so tests and the simulator can run on scaled time.

use std::sync::Arc;
use std::time::{Duration, Instant};

/// A monotonic clock in nanoseconds since an arbitrary epoch.
///
/// Every sample on the edge is stamped with one clock; passing it in keeps parsers pure and
/// lets a simulation run the edge faster than real time.
pub trait Clock: Send + Sync {
    /// Nanoseconds since this clock's epoch; never decreases.
    fn now_ns(&self) -> u64;

    /// Which epoch [`Clock::now_ns`] counts from, sent in `Hello::clock_id`: two readings with
    /// the same identity are on one time line, so the server keeps or discards its clock model
    /// by it. All zeros: unknown (the server then relies on the session id alone).
    fn clock_id(&self) -> [u8; 16] {
        [0; 16]
    }

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

/// Linux CLOCK_MONOTONIC, the clock the edge uses on real hardware: nanoseconds since boot,
/// so its identity is the boot id (`/proc/sys/kernel/random/boot_id`) and a restarted daemon
/// stays on the same time line.
#[derive(Debug, Clone, Copy)]
pub struct MonotonicClock {
    clock_id: [u8; 16],
}

/// Where Linux publishes the id of the current boot (a UUID, new at every boot).
const BOOT_ID_PATH: &str = "/proc/sys/kernel/random/boot_id";

impl MonotonicClock {
    /// The system's monotonic clock; its identity is the boot id, or random when that cannot be
    /// read (then every process is its own time line, which is the safe assumption).
    pub fn new() -> Self {
        let clock_id = std::fs::read_to_string(BOOT_ID_PATH)
            .ok()
            .and_then(|text| parse_uuid(&text))
            .unwrap_or_else(|| {
                tracing::warn!(
                    path = BOOT_ID_PATH,
                    "cannot read the boot id; using a random clock identity"
                );
                rand::random()
            });
        Self { clock_id }
    }
}

/// The 16 bytes of a UUID written as hex with or without dashes (`ddf71301-17cf-…`).
fn parse_uuid(text: &str) -> Option<[u8; 16]> {
    let digits: Vec<u8> = text
        .trim()
        .chars()
        .filter(|&c| c != '-')
        .map(|c| c.to_digit(16).map(|d| d as u8))
        .collect::<Option<_>>()?;
    if digits.len() != 32 {
        return None;
    }
    let mut id = [0; 16];
    for (byte, pair) in id.iter_mut().zip(digits.chunks_exact(2)) {
        *byte = pair[0] << 4 | pair[1];
    }
    Some(id)
}

impl Default for MonotonicClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for MonotonicClock {
    fn now_ns(&self) -> u64 {
        // CLOCK_MONOTONIC cannot fail on Linux with a valid clock id; 0 is a safe fallback for
        // a platform without it (every later reading is then also 0).
        nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
            .map(|t| {
                let ns = i128::from(t.tv_sec()) * 1_000_000_000 + i128::from(t.tv_nsec());
                ns.clamp(0, i128::from(u64::MAX)) as u64
            })
            .unwrap_or(0)
    }

    fn clock_id(&self) -> [u8; 16] {
        self.clock_id
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
    /// Random: the epoch is this process's.
    clock_id: [u8; 16],
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
            clock_id: rand::random(),
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

    fn clock_id(&self) -> [u8; 16] {
        self.clock_id
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
    fn the_boot_id_is_read_as_the_16_bytes_of_its_uuid() {
        assert_eq!(
            parse_uuid("ddf71301-17cf-4d09-aa5c-31ba0a17ebf8\n"),
            Some([
                0xdd, 0xf7, 0x13, 0x01, 0x17, 0xcf, 0x4d, 0x09, 0xaa, 0x5c, 0x31, 0xba, 0x0a, 0x17,
                0xeb, 0xf8
            ])
        );
        assert_eq!(parse_uuid("ddf71301-17cf"), None);
        assert_eq!(parse_uuid("not a uuid at all, but 32 chars!"), None);
        // Two monotonic clocks of one boot are one time line; scaled clocks are each their own.
        assert_eq!(
            MonotonicClock::new().clock_id(),
            MonotonicClock::new().clock_id()
        );
        assert_ne!(
            ScaledClock::new(2.0).clock_id(),
            ScaledClock::new(2.0).clock_id()
        );
        let (a, b) = (
            MonotonicClock::new().now_ns(),
            MonotonicClock::new().now_ns(),
        );
        assert!(b >= a && a > 0);
    }

    #[test]
    fn invalid_scale_falls_back_to_real_time() {
        assert_eq!(ScaledClock::new(0.0).scale(), 1.0);
        assert_eq!(ScaledClock::new(f64::NAN).scale(), 1.0);
    }
}
