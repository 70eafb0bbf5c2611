//! Fault injection on the serial line: stray bytes, bit flips and dropped bytes, drawn per byte
//! from a seeded generator, with a [`SentLog`] of every sample that went out and whether its
//! bytes were disturbed, so tests can tell "the driver rejected garbage" from "the driver lost
//! good data".
//!
//! The injector is pure: [`WireUnit`]s in, bytes and log entries out. The pty runner records the
//! entries in the [`SentLog`] once the unit's last byte has been written to the pty.

use std::sync::{Arc, Mutex, PoisonError};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scan3d_edge::lidar::RawSample;

use crate::device::WireUnit;

/// Per-byte fault probabilities (each in `[0, 1]`; values outside are clamped).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Deserialize)]
#[serde(default)]
pub struct FaultConfig {
    /// Chance that a random stray byte is inserted before each byte.
    pub stray_rate: f64,
    /// Chance that one random bit of each byte is flipped.
    pub bitflip_rate: f64,
    /// Chance that each byte is dropped (never sent).
    pub drop_rate: f64,
}

impl FaultConfig {
    /// A line corrupted at `rate` events per byte, split evenly: stray bytes at `rate / 2` and
    /// bit flips at `rate / 2`, no drops. So `corrupt(0.001)` disturbs about one byte position
    /// in a thousand.
    pub fn corrupt(rate: f64) -> Self {
        Self {
            stray_rate: rate / 2.0,
            bitflip_rate: rate / 2.0,
            drop_rate: 0.0,
        }
    }

    /// True when no fault can ever happen.
    pub fn is_clean(&self) -> bool {
        self.stray_rate <= 0.0 && self.bitflip_rate <= 0.0 && self.drop_rate <= 0.0
    }
}

/// One sample the emulator put on the wire.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SentSample {
    /// The sample as a correct decoder must report it.
    pub sample: RawSample,
    /// Any byte of the sample's unit was flipped or dropped, or a stray byte was inserted inside
    /// or right before the unit.
    pub touched: bool,
}

/// A unit after fault injection.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct InjectedUnit {
    /// The bytes to put on the wire.
    pub bytes: Vec<u8>,
    /// The unit's samples, all marked touched if any fault hit the unit.
    pub samples: Vec<SentSample>,
    /// Number of faults applied to this unit (stray bytes + flips + drops).
    pub faults: u32,
}

/// Applies a [`FaultConfig`] to wire units, deterministically for a given seed.
#[derive(Debug, Clone)]
pub struct FaultInjector {
    config: FaultConfig,
    rng: ChaCha8Rng,
}

impl FaultInjector {
    /// An injector drawing from a generator seeded with `seed`.
    pub fn new(config: FaultConfig, seed: u64) -> Self {
        Self {
            config,
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> FaultConfig {
        self.config
    }

    /// Corrupts one unit. For each byte, in order: maybe insert a stray byte before it, then
    /// maybe drop it, else maybe flip one of its bits.
    pub fn inject(&mut self, unit: &WireUnit) -> InjectedUnit {
        let mut bytes = Vec::with_capacity(unit.bytes.len() + 2);
        let mut faults = 0u32;
        if self.config.is_clean() {
            bytes.extend_from_slice(&unit.bytes);
        } else {
            for &b in &unit.bytes {
                if chance(&mut self.rng, self.config.stray_rate) {
                    bytes.push(self.rng.random::<u8>());
                    faults += 1;
                }
                if chance(&mut self.rng, self.config.drop_rate) {
                    faults += 1;
                    continue;
                }
                if chance(&mut self.rng, self.config.bitflip_rate) {
                    bytes.push(b ^ (1u8 << self.rng.random_range(0..8u32)));
                    faults += 1;
                } else {
                    bytes.push(b);
                }
            }
        }
        let touched = faults > 0;
        let samples = unit
            .samples
            .iter()
            .map(|&sample| SentSample { sample, touched })
            .collect();
        InjectedUnit {
            bytes,
            samples,
            faults,
        }
    }
}

/// Draws `true` with probability `p` (clamped to `[0, 1]`; NaN counts as 0).
fn chance<R: Rng + ?Sized>(rng: &mut R, p: f64) -> bool {
    if p.is_nan() || p <= 0.0 {
        false
    } else if p >= 1.0 {
        true
    } else {
        rng.random::<f64>() < p
    }
}

/// A shared, cloneable record of every sample that went out on the wire, in order.
#[derive(Debug, Clone, Default)]
pub struct SentLog {
    inner: Arc<Mutex<Vec<SentSample>>>,
}

impl SentLog {
    /// An empty log.
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends samples that were just sent.
    pub fn record(&self, samples: &[SentSample]) {
        if samples.is_empty() {
            return;
        }
        self.lock().extend_from_slice(samples);
    }

    /// A copy of everything recorded so far.
    pub fn snapshot(&self) -> Vec<SentSample> {
        self.lock().clone()
    }

    /// Number of samples recorded so far.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// True when nothing has been recorded.
    pub fn is_empty(&self) -> bool {
        self.lock().is_empty()
    }

    /// Forgets everything recorded so far.
    pub fn clear(&self) {
        self.lock().clear();
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<SentSample>> {
        // A panic while holding the lock cannot leave a Vec half-updated in a way that matters
        // for a log, so a poisoned lock is still usable.
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(angle: f32) -> RawSample {
        RawSample {
            angle_deg: angle,
            range_m: 1.5,
            quality: 47,
            new_revolution: false,
        }
    }

    fn unit(bytes: &[u8], n: usize) -> WireUnit {
        WireUnit {
            bytes: bytes.to_vec(),
            samples: (0..n).map(|i| sample(i as f32)).collect(),
        }
    }

    #[test]
    fn clean_config_passes_bytes_untouched() {
        let mut inj = FaultInjector::new(FaultConfig::default(), 7);
        let u = unit(&[0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81], 2);
        let out = inj.inject(&u);
        assert_eq!(out.bytes, vec![0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81]);
        assert_eq!(out.faults, 0);
        assert_eq!(
            out.samples,
            vec![
                SentSample {
                    sample: sample(0.0),
                    touched: false
                },
                SentSample {
                    sample: sample(1.0),
                    touched: false
                }
            ]
        );
    }

    #[test]
    fn rate_one_strays_before_every_byte() {
        let cfg = FaultConfig {
            stray_rate: 1.0,
            ..FaultConfig::default()
        };
        let mut inj = FaultInjector::new(cfg, 1);
        let out = inj.inject(&unit(&[1, 2, 3], 1));
        assert_eq!(out.bytes.len(), 6);
        assert_eq!([out.bytes[1], out.bytes[3], out.bytes[5]], [1, 2, 3]);
        assert_eq!(out.faults, 3);
        assert!(out.samples[0].touched);
    }

    #[test]
    fn rate_one_flips_exactly_one_bit_per_byte() {
        let cfg = FaultConfig {
            bitflip_rate: 1.0,
            ..FaultConfig::default()
        };
        let mut inj = FaultInjector::new(cfg, 2);
        let input = [0x00, 0xFF, 0xA5, 0x5A];
        let out = inj.inject(&unit(&input, 0));
        assert_eq!(out.bytes.len(), 4);
        for (a, b) in input.iter().zip(&out.bytes) {
            assert_eq!((a ^ b).count_ones(), 1, "{a:#04x} vs {b:#04x}");
        }
    }

    #[test]
    fn rate_one_drop_sends_nothing() {
        let cfg = FaultConfig {
            drop_rate: 1.0,
            ..FaultConfig::default()
        };
        let mut inj = FaultInjector::new(cfg, 3);
        let out = inj.inject(&unit(&[1, 2, 3, 4, 5], 1));
        assert!(out.bytes.is_empty());
        assert_eq!(out.faults, 5);
        assert!(out.samples[0].touched);
    }

    #[test]
    fn corrupt_splits_the_rate() {
        assert_eq!(
            FaultConfig::corrupt(0.01),
            FaultConfig {
                stray_rate: 0.005,
                bitflip_rate: 0.005,
                drop_rate: 0.0
            }
        );
        assert!(FaultConfig::corrupt(0.0).is_clean());
    }

    #[test]
    fn same_seed_same_faults_other_seed_differs() {
        let cfg = FaultConfig {
            stray_rate: 0.1,
            bitflip_rate: 0.1,
            drop_rate: 0.1,
        };
        let data: Vec<u8> = (0..=255).collect();
        let u = unit(&data, 3);
        let run = |seed| {
            let mut inj = FaultInjector::new(cfg, seed);
            (0..20).map(|_| inj.inject(&u).bytes).collect::<Vec<_>>()
        };
        assert_eq!(run(42), run(42));
        assert_ne!(run(42), run(43));
    }

    #[test]
    fn fault_counts_follow_the_rates() {
        let data = vec![0u8; 1000];
        let u = unit(&data, 0);
        // One fault kind at a time, 200 000 bytes each.
        for (cfg, expected) in [
            (
                FaultConfig {
                    stray_rate: 0.02,
                    ..FaultConfig::default()
                },
                0.02,
            ),
            (
                FaultConfig {
                    bitflip_rate: 0.01,
                    ..FaultConfig::default()
                },
                0.01,
            ),
            (
                FaultConfig {
                    drop_rate: 0.005,
                    ..FaultConfig::default()
                },
                0.005,
            ),
        ] {
            let mut inj = FaultInjector::new(cfg, 11);
            let n_bytes = 200_000.0;
            let faults: u32 = (0..200).map(|_| inj.inject(&u).faults).sum();
            let rate = f64::from(faults) / n_bytes;
            assert!(
                (rate - expected).abs() < expected * 0.1,
                "rate {rate} vs {expected}"
            );
        }
    }

    #[test]
    fn touched_fraction_matches_unit_size() {
        // 5-byte units at 1 % flips: P(touched) = 1 - 0.99^5 ≈ 4.9 %.
        let mut inj = FaultInjector::new(
            FaultConfig {
                bitflip_rate: 0.01,
                ..Default::default()
            },
            5,
        );
        let u = unit(&[1, 2, 3, 4, 5], 1);
        let n = 20_000;
        let touched = (0..n).filter(|_| inj.inject(&u).samples[0].touched).count();
        let frac = touched as f64 / n as f64;
        let expected = 1.0 - 0.99f64.powi(5);
        assert!((frac - expected).abs() < 0.006, "{frac} vs {expected}");
    }

    #[test]
    fn out_of_range_rates_do_not_panic() {
        let cfg = FaultConfig {
            stray_rate: f64::NAN,
            bitflip_rate: -1.0,
            drop_rate: 7.0,
        };
        let mut inj = FaultInjector::new(cfg, 0);
        assert!(inj.inject(&unit(&[1, 2], 0)).bytes.is_empty());
    }

    #[test]
    fn sent_log_is_shared_between_clones() {
        let log = SentLog::new();
        let other = log.clone();
        other.record(&[SentSample {
            sample: sample(3.0),
            touched: true,
        }]);
        assert_eq!(log.len(), 1);
        assert_eq!(log.snapshot()[0].sample.angle_deg, 3.0);
        log.clear();
        assert!(other.is_empty());
    }
}
