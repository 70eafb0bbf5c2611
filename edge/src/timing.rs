//! Per-sample measurement times from serial arrival times, and revolution assembly.
//!
//! A serial read returns a burst of bytes some time after they were measured, so the arrival
//! time of a sample is its measurement time plus a varying delay (UART, USB latency timer,
//! scheduling). Within one revolution the device samples at a steady rate, so measurement
//! time is (nearly) linear in the beam angle. We fit `arrival = a + b·progress` and then move
//! the line down onto the **lower envelope** of the arrivals — the least-delayed samples, the
//! same idea as NTP's minimum-delay filter (`research/hardware.md` §5.4) — and finally subtract
//! the fixed transport latency. Angle progress (rather than sample index) keeps the fit correct
//! when samples were lost to corruption.

use serde::Serialize;

use crate::lidar::ArrivedSample;

/// One sample with its estimated measurement time on the edge clock.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TimedSample {
    /// Beam angle in degrees, device convention (see [`crate::lidar::RawSample`]).
    pub angle_deg: f32,
    /// Range in metres, `0.0` = no return.
    pub range_m: f32,
    /// Raw quality / signal strength.
    pub quality: u8,
    /// Estimated measurement time, edge clock, nanoseconds.
    pub t_ns: u64,
}

/// One full 360° revolution of a lidar with per-sample times.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Revolution {
    /// Estimated time at which the beam passed the revolution's first sample angle.
    pub t0_ns: u64,
    /// Estimated time at which the beam came back to that angle (start of the next revolution).
    pub t1_ns: u64,
    /// The samples in angle order.
    pub samples: Vec<TimedSample>,
}

/// Tunables of [`RevolutionAssembler`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimingConfig {
    /// Fixed transport latency subtracted from the lower envelope of arrivals, ns
    /// (serialisation of one frame plus the USB adapter's latency; calibratable).
    pub latency_ns: u64,
    /// Revolutions with fewer samples than this are discarded (startup fragments, resyncs).
    pub min_samples: usize,
}

impl Default for TimingConfig {
    fn default() -> Self {
        Self {
            latency_ns: 0,
            min_samples: 8,
        }
    }
}

/// Groups a sample stream into revolutions and stamps every sample with a measurement time.
///
/// A revolution starts at a sample flagged `new_revolution`; an angle wrap without the flag
/// (the flagged sample was lost to corruption) also closes it. Samples before the first
/// boundary belong to a partial revolution and are dropped.
#[derive(Debug, Clone)]
pub struct RevolutionAssembler {
    config: TimingConfig,
    current: Vec<ArrivedSample>,
    in_revolution: bool,
    dropped_samples: u64,
}

impl RevolutionAssembler {
    /// An assembler waiting for the first revolution boundary.
    pub fn new(config: TimingConfig) -> Self {
        Self {
            config,
            current: Vec::new(),
            in_revolution: false,
            dropped_samples: 0,
        }
    }

    /// Forget the revolution in progress (after a reconnect or a driver restart).
    pub fn reset(&mut self) {
        self.dropped_samples += self.current.len() as u64;
        self.current.clear();
        self.in_revolution = false;
    }

    /// Samples that never became part of an emitted revolution (partial or too short ones).
    pub fn dropped_samples(&self) -> u64 {
        self.dropped_samples
    }

    /// Add a sample; returns the revolution it completed, if any.
    pub fn push(&mut self, sample: ArrivedSample) -> Option<Revolution> {
        let boundary = sample.sample.new_revolution || self.wraps_without_flag(&sample);
        let mut finished = None;
        if boundary {
            if self.in_revolution {
                finished = self.finish();
            } else {
                self.dropped_samples += self.current.len() as u64;
                self.current.clear();
            }
            self.in_revolution = true;
        }
        self.current.push(sample);
        finished
    }

    /// The beam crossed 0° again although the start flag is missing (the flagged sample was
    /// lost to corruption).
    ///
    /// A crossing only ends a revolution that already covers most of a turn: reported angles
    /// may step backwards by a few degrees around the flag (RPLidar express angles carry a
    /// per-sample correction of up to 8°), so the flagged sample can read 357° and its
    /// successors 359° and then 0.3°, all in the same revolution.
    fn wraps_without_flag(&self, sample: &ArrivedSample) -> bool {
        let (Some(first), Some(last)) = (self.current.first(), self.current.last()) else {
            return false;
        };
        let crosses_zero = sample.sample.angle_deg + 180.0 < last.sample.angle_deg;
        let covered = angle_progress(first.sample.angle_deg, last.sample.angle_deg);
        self.in_revolution && crosses_zero && covered >= 270.0
    }

    fn finish(&mut self) -> Option<Revolution> {
        let samples = std::mem::take(&mut self.current);
        if samples.len() < self.config.min_samples.max(2) {
            self.dropped_samples += samples.len() as u64;
            return None;
        }
        Some(stamp_revolution(&samples, self.config.latency_ns))
    }
}

/// Stamps one revolution's samples (first sample = revolution start) with measurement times.
pub fn stamp_revolution(samples: &[ArrivedSample], latency_ns: u64) -> Revolution {
    let Some(first) = samples.first() else {
        return Revolution {
            t0_ns: 0,
            t1_ns: 0,
            samples: Vec::new(),
        };
    };
    // Unwrapped angle travelled since the first sample; small backward steps stay negative.
    let mut travelled = 0.0;
    let mut previous = first.sample.angle_deg;
    let progress: Vec<f64> = samples
        .iter()
        .map(|s| {
            travelled += signed_step(previous, s.sample.angle_deg);
            previous = s.sample.angle_deg;
            travelled
        })
        .collect();
    // Arrivals relative to the first one keep the arithmetic in a well-conditioned range.
    let base = first.arrival_ns;
    let arrivals: Vec<f64> = samples
        .iter()
        .map(|s| s.arrival_ns as f64 - base as f64)
        .collect();
    let (intercept, slope) = lower_envelope_fit(&progress, &arrivals);
    let time_at = |x: f64| -> u64 {
        let t = base as f64 + intercept + slope * x - latency_ns as f64;
        if t <= 0.0 { 0 } else { t.round() as u64 }
    };
    Revolution {
        t0_ns: time_at(0.0),
        t1_ns: time_at(360.0),
        samples: samples
            .iter()
            .zip(&progress)
            .map(|(s, &x)| TimedSample {
                angle_deg: s.sample.angle_deg,
                range_m: s.sample.range_m,
                quality: s.sample.quality,
                t_ns: time_at(x),
            })
            .collect(),
    }
}

/// Degrees from `from` to `to` going forwards, in `[0, 360)`.
fn angle_progress(from: f32, to: f32) -> f64 {
    (f64::from(to) - f64::from(from)).rem_euclid(360.0)
}

/// The step from `from` to `to` taken the short way round, in `[-180, 180)`.
fn signed_step(from: f32, to: f32) -> f64 {
    (f64::from(to) - f64::from(from) + 180.0).rem_euclid(360.0) - 180.0
}

/// Fits the line `y = a + b·x` that lies on or below every point and is as close to them as
/// possible (minimises the summed vertical gap).
///
/// This is the linear-programming clock-skew estimator of Moon, Skelly and Towsley (1999): the
/// optimum is the edge of the points' lower convex hull that spans the mean of `x`. Late
/// arrivals only ever lie above the line, so they cannot pull it; only the least-delayed
/// samples define it. A negative slope (time running backwards) is clamped to zero.
pub(crate) fn lower_envelope_fit(x: &[f64], y: &[f64]) -> (f64, f64) {
    let mut points: Vec<(f64, f64)> = x.iter().copied().zip(y.iter().copied()).collect();
    points.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.total_cmp(&q.1)));
    // Andrew's monotone chain, lower hull only; for equal x keep the lowest y.
    let mut hull: Vec<(f64, f64)> = Vec::new();
    for p in points {
        if hull.last().is_some_and(|last| last.0 == p.0) {
            continue;
        }
        while hull.len() >= 2 {
            let (o, a) = (hull[hull.len() - 2], hull[hull.len() - 1]);
            let cross = (a.0 - o.0) * (p.1 - o.1) - (a.1 - o.1) * (p.0 - o.0);
            if cross <= 0.0 {
                hull.pop();
            } else {
                break;
            }
        }
        hull.push(p);
    }
    let n = x.len().max(1) as f64;
    let mean_x = x.iter().sum::<f64>() / n;
    let segment = hull
        .windows(2)
        .find(|w| w[1].0 >= mean_x)
        .or_else(|| hull.windows(2).last());
    let (a, b) = match segment {
        Some(w) => {
            let b = ((w[1].1 - w[0].1) / (w[1].0 - w[0].0)).max(0.0);
            (w[0].1 - b * w[0].0, b)
        }
        None => (y.iter().copied().fold(f64::INFINITY, f64::min), 0.0),
    };
    // With the slope clamped the line may cross a point; lower it onto the envelope again.
    let min_gap = x
        .iter()
        .zip(y)
        .map(|(xi, yi)| yi - (a + b * xi))
        .fold(f64::INFINITY, f64::min);
    (
        if min_gap.is_finite() {
            a + min_gap.min(0.0)
        } else {
            a
        },
        b,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::RawSample;

    /// A revolution of `n` samples measured every `period_ns` from `t_start`, delivered in
    /// serial reads of `chunk` samples, each read returning `delay(i)` after its last sample.
    fn synthetic(
        n: usize,
        period_ns: u64,
        t_start: u64,
        chunk: usize,
        delay: impl Fn(usize) -> u64,
    ) -> (Vec<ArrivedSample>, Vec<u64>) {
        let truth: Vec<u64> = (0..n).map(|i| t_start + i as u64 * period_ns).collect();
        let samples = (0..n)
            .map(|i| {
                let chunk_end = ((i / chunk + 1) * chunk - 1).min(n - 1);
                ArrivedSample {
                    sample: RawSample {
                        angle_deg: (i as f32 * 360.0 / n as f32) + 0.5,
                        range_m: 1.0,
                        quality: 47,
                        new_revolution: i == 0,
                    },
                    arrival_ns: truth[chunk_end] + delay(i / chunk),
                }
            })
            .collect();
        (samples, truth)
    }

    #[test]
    fn bursty_arrivals_are_mapped_back_to_measurement_times() {
        // 2000 samples/s, chunks of 32 samples, latency 2 ms plus 0..8 ms of pseudo-random jitter.
        let latency = 2_000_000;
        let (samples, truth) = synthetic(360, 500_000, 1_000_000_000, 32, |c| {
            latency + (c as u64 * 7919 % 9) * 1_000_000
        });
        let rev = stamp_revolution(&samples, latency);
        for (s, t) in rev.samples.iter().zip(&truth) {
            let err = s.t_ns as i64 - *t as i64;
            assert!(err.abs() < 1_000_000, "sample time off by {err} ns");
        }
        // 360 samples over 359.5 degrees of progress: the beam returns after 360 * 0.5 ms.
        let period = rev.t1_ns - rev.t0_ns;
        assert!(
            (period as i64 - 180_000_000).abs() < 2_000_000,
            "period {period}"
        );
    }

    #[test]
    fn lost_samples_do_not_skew_times() {
        let (mut samples, truth) = synthetic(400, 250_000, 5_000_000, 16, |_| 300_000);
        let mut truth = truth;
        // Drop a run of 40 samples in the middle (a resync).
        samples.drain(150..190);
        truth.drain(150..190);
        let rev = stamp_revolution(&samples, 300_000);
        for (s, t) in rev.samples.iter().zip(&truth) {
            assert!((s.t_ns as i64 - *t as i64).abs() < 300_000);
        }
    }

    fn sample(angle: f32, start: bool, t: u64) -> ArrivedSample {
        ArrivedSample {
            sample: RawSample {
                angle_deg: angle,
                range_m: 2.0,
                quality: 10,
                new_revolution: start,
            },
            arrival_ns: t,
        }
    }

    #[test]
    fn assembler_cuts_on_start_flags_and_drops_the_leading_partial_revolution() {
        let mut asm = RevolutionAssembler::new(TimingConfig {
            latency_ns: 0,
            min_samples: 2,
        });
        let mut revs = Vec::new();
        let mut t = 0;
        for rev in 0..3 {
            for k in 0..10 {
                let angle = if rev == 0 {
                    200.0 + k as f32 * 10.0
                } else {
                    k as f32 * 36.0
                };
                t += 1000;
                revs.extend(asm.push(sample(angle, rev > 0 && k == 0, t)));
            }
        }
        assert_eq!(
            revs.len(),
            1,
            "only the revolution closed by the third start flag"
        );
        assert_eq!(revs[0].samples.len(), 10);
        assert_eq!(asm.dropped_samples(), 10);
        assert!(revs[0].samples.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
    }

    #[test]
    fn a_wrap_without_start_flag_still_closes_the_revolution() {
        let mut asm = RevolutionAssembler::new(TimingConfig {
            latency_ns: 0,
            min_samples: 2,
        });
        let mut out = Vec::new();
        out.extend(asm.push(sample(0.0, true, 10)));
        for (k, angle) in [60.0, 120.0, 180.0, 240.0, 300.0].into_iter().enumerate() {
            out.extend(asm.push(sample(angle, false, 20 + 10 * k as u64)));
        }
        // The flagged sample at 0° of the next revolution was lost; 10° arrives instead.
        out.extend(asm.push(sample(10.0, false, 85)));
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].samples.len(), 6);
    }

    #[test]
    fn small_backward_steps_after_the_start_flag_do_not_cut_the_revolution() {
        let mut asm = RevolutionAssembler::new(TimingConfig {
            latency_ns: 0,
            min_samples: 2,
        });
        let mut out = Vec::new();
        // Express angles carry a per-sample correction: the flagged sample may read 357° and
        // its successors 358°, 359.5°, then 0.3° and onwards, all in the same revolution.
        let angles = [357.0, 358.0, 359.5, 0.3, 90.0, 180.0, 270.0, 350.0];
        for (k, &a) in angles.iter().enumerate() {
            out.extend(asm.push(sample(a, k == 0, 1000 * k as u64)));
        }
        out.extend(asm.push(sample(356.5, true, 9000)));
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].samples.len(), angles.len());
        assert!(out[0].samples.windows(2).all(|w| w[0].t_ns <= w[1].t_ns));
    }

    #[test]
    fn single_arrival_time_gives_flat_but_valid_times() {
        let samples: Vec<_> = (0..10)
            .map(|i| sample(i as f32 * 30.0, i == 0, 5_000))
            .collect();
        let rev = stamp_revolution(&samples, 1_000);
        assert!(rev.samples.iter().all(|s| s.t_ns == 4_000));
        assert_eq!(rev.t0_ns, 4_000);
    }
}
