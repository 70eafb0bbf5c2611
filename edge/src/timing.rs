//! Per-sample measurement times from serial arrival times, and revolution assembly: the one
//! estimator every lidar sample's time comes from.
//!
//! A serial read returns a burst of bytes some time after they were measured, so the arrival
//! time of a sample is its measurement time plus a varying delay (UART, USB latency timer,
//! scheduling). Within a revolution the device samples at a steady rate, so measurement time is
//! (nearly) linear in the beam angle. [`SampleClock`] fits `arrival = a + b·angle` under the
//! **lower envelope** of the arrivals over the last two turns of unwrapped beam angle — the
//! least-delayed samples, the same idea as NTP's minimum-delay filter
//! (`research/hardware.md` §5.4) — and subtracts the fixed transport latency. Angle progress
//! (rather than sample index) keeps the fit correct when samples were lost to corruption.
//!
//! **Causal, and the only one.** Each sample is stamped as it arrives, from the line fitted on
//! the two turns before it (refitted every 15°), and [`RevolutionAssembler`] puts that
//! same time into the revolution frame. The static-scan controller needs a measurement time per
//! sample as it arrives: whether a sample just past the blocked sector was taken before or after
//! the step finished decides its yaw, and it must be decided while the step is reported, not a
//! revolution later. A sample measured while the rotor still moved but delivered late (a USB
//! latency timer, a busy host) gets its measurement time back from the envelope, so it is judged
//! as taken before the step, not tagged with the new yaw. Stamping the revolution frame with a
//! second, after-the-fact fit would give the server other times than the ones the tags were
//! decided on; with one causal estimator, the time a sample is tagged by is the time it is
//! recorded with. What the causal fit gives up is interpolation: it extrapolates a line fitted
//! over the last two turns, which for a beam turning at a steady rate is the same line (two
//! turns rather than one keep the slope, and so the extrapolation, within 0.5 ms under 8 ms of
//! bursty jitter: `bursty_arrivals_are_mapped_back_to_measurement_times`). Only the first
//! 30° after the port opens have no fit yet (arrival times minus the latency are used); they
//! fall in the partial revolution before the first start flag, which is dropped.

use std::collections::VecDeque;

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
    /// Time of the first sample: names the revolution (strictly increasing from one revolution
    /// to the next of the same assembler).
    pub t0_ns: u64,
    /// Time of the sample that started the next revolution; for a revolution closed as soon as
    /// the driver said it was complete ([`RevolutionAssembler::complete`]), before that sample
    /// was decoded, one mean sample spacing after its last sample (the next revolution starts
    /// no earlier).
    pub t1_ns: u64,
    /// The samples in angle order, with the times they were stamped with as they arrived.
    pub samples: Vec<TimedSample>,
}

/// Where a stamped sample sits: sample `index` of the revolution whose first sample's time is
/// `t0_ns` (once that revolution is complete, its [`Revolution::t0_ns`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct RevolutionPosition {
    /// The revolution's [`Revolution::t0_ns`].
    pub t0_ns: u64,
    /// Index of the sample in [`Revolution::samples`].
    pub index: u32,
}

/// A sample as [`RevolutionAssembler::stamp`] timed it, and where it goes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StampedSample {
    /// The sample with its measurement time.
    pub sample: TimedSample,
    /// Its place in the revolution being assembled; `None` before the first revolution start
    /// (such samples are in no revolution frame).
    pub position: Option<RevolutionPosition>,
}

/// What one sample did to a [`RevolutionAssembler`].
#[derive(Debug, Clone, PartialEq)]
pub struct Stamped {
    /// The sample, timed.
    pub sample: StampedSample,
    /// The revolution this sample completed (it starts the next one), if any. A revolution of
    /// fewer than [`TimingConfig::min_samples`] samples is dropped instead: positions that named
    /// it refer to no frame.
    pub finished: Option<Revolution>,
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

/// Measurement times from arrival times, causally: the line under the lower envelope of the
/// arrivals over the last two turns of beam travel (see the module doc), never later than a
/// sample's arrival and never before the previous estimate.
#[derive(Debug, Clone, Default)]
pub struct SampleClock {
    latency_ns: u64,
    /// Arrivals are kept relative to this (the first one after a reset), for well-conditioned
    /// arithmetic.
    base_ns: Option<u64>,
    /// Unwrapped beam angle of the last sample, degrees.
    unwrapped_deg: Option<f64>,
    /// (unwrapped angle, arrival − base) over the last [`Self::WINDOW_DEG`].
    window: VecDeque<(f64, f64)>,
    /// The current line `arrival − base = a + b·angle` and the angle it was fitted at.
    fit: Option<(f64, f64, f64)>,
    /// The last estimate, so estimates never go backwards.
    last_ns: u64,
    /// Samples pushed into and popped from the window since the last reset, and the push
    /// index of the newest sample that came before its predecessor (by x, then y): the window
    /// is sorted unless that pair is still in it. So a refit need not scan for order.
    pushed: u64,
    popped: u64,
    last_inversion: Option<u64>,
    /// Scratch space of the fit: the window sorted (when jitter unsorted it) and its hull.
    sorted: Vec<(f64, f64)>,
    hull: Vec<(f64, f64)>,
}

impl SampleClock {
    /// Refit after the beam turned this far: a refit costs a pass over the window (two turns,
    /// ~800 RPLidar samples), and the line it gives holds for a steady beam: eight refits a
    /// turn follow a motor's speed changes, and every estimate stays clamped to its arrival.
    const REFIT_DEG: f64 = 45.0;
    /// No fit before the window spans this much.
    const MIN_SPAN_DEG: f64 = 30.0;
    /// The envelope is fitted over this much beam travel (two turns).
    const WINDOW_DEG: f64 = 720.0;

    /// A clock subtracting `latency_ns` of fixed transport latency.
    pub fn new(latency_ns: u64) -> Self {
        Self {
            latency_ns,
            ..Self::default()
        }
    }

    /// Forgets the beam's history (after a reconnect); estimates still never go backwards.
    pub fn reset(&mut self) {
        *self = Self {
            latency_ns: self.latency_ns,
            last_ns: self.last_ns,
            ..Self::default()
        };
    }

    /// The measurement time of a sample at device angle `angle_deg` that arrived at
    /// `arrival_ns` (never later than its arrival, never before the previous estimate).
    pub fn estimate(&mut self, angle_deg: f64, arrival_ns: u64) -> u64 {
        let base = *self.base_ns.get_or_insert(arrival_ns);
        let arrival = arrival_ns as f64 - base as f64;
        let unwrapped = match self.unwrapped_deg {
            None => angle_deg,
            Some(previous) => {
                let delta = (angle_deg - previous.rem_euclid(360.0)).rem_euclid(360.0);
                // More than half a turn forward is a small step backwards (jitter).
                previous + if delta > 180.0 { delta - 360.0 } else { delta }
            }
        };
        self.unwrapped_deg = Some(unwrapped);
        let point = (unwrapped, arrival);
        if self
            .window
            .back()
            .is_some_and(|last| by_x_then_y(last, &point).is_gt())
        {
            self.last_inversion = Some(self.pushed);
        }
        self.window.push_back(point);
        self.pushed += 1;
        while self
            .window
            .front()
            .is_some_and(|&(u, _)| unwrapped - u > Self::WINDOW_DEG)
        {
            self.window.pop_front();
            self.popped += 1;
        }
        let span = self.window.front().map_or(0.0, |&(u, _)| unwrapped - u);
        let stale = self
            .fit
            .is_none_or(|(_, _, at)| (unwrapped - at).abs() >= Self::REFIT_DEG);
        if span >= Self::MIN_SPAN_DEG && stale {
            // Beam angles only go forwards but for small backward steps (jitter): the window
            // is nearly always sorted already. It is unless the newest out-of-order pair (the
            // sample at `last_inversion` and the one before it) is still in it.
            let sorted = self
                .last_inversion
                .is_none_or(|index| index < self.popped + 1);
            let window = self.window.make_contiguous();
            let points = if sorted {
                debug_assert!(window.is_sorted_by(|p, q| by_x_then_y(p, q).is_le()));
                &*window
            } else {
                self.sorted.clear();
                self.sorted.extend_from_slice(window);
                self.sorted.sort_by(by_x_then_y);
                &self.sorted
            };
            let (a, b) = lower_envelope_fit(points, &mut self.hull);
            self.fit = Some((a, b, unwrapped));
        }
        let line = match self.fit {
            Some((a, b, _)) if span >= Self::MIN_SPAN_DEG => a + b * unwrapped,
            _ => arrival,
        };
        let estimate = (base as f64 + line - self.latency_ns as f64).clamp(0.0, arrival_ns as f64);
        self.last_ns = self.last_ns.max(estimate.round() as u64);
        self.last_ns
    }

    /// Later estimates are at least `t_ns`.
    fn floor(&mut self, t_ns: u64) {
        self.last_ns = self.last_ns.max(t_ns);
    }
}

/// Groups a sample stream into revolutions and stamps every sample with its measurement time
/// as it arrives ([`SampleClock`]).
///
/// A revolution starts at a sample flagged `new_revolution`; an angle wrap without the flag
/// (the flagged sample was lost to corruption) also closes it. When the driver knows from the
/// bytes that the last sample ended its revolution ([`crate::lidar::LidarEvent::RevolutionComplete`]),
/// [`RevolutionAssembler::complete`] closes it at once and the next sample starts the next
/// one. Samples before the first boundary belong to a partial revolution and are dropped.
#[derive(Debug, Clone)]
pub struct RevolutionAssembler {
    config: TimingConfig,
    clock: SampleClock,
    current: Vec<TimedSample>,
    in_revolution: bool,
    /// The last revolution was closed by [`Self::complete`]: the next sample starts one.
    completed: bool,
    /// `t0_ns` of the last revolution started, so the next one's is strictly later.
    last_t0_ns: Option<u64>,
    dropped_samples: u64,
}

impl RevolutionAssembler {
    /// An assembler waiting for the first revolution boundary.
    pub fn new(config: TimingConfig) -> Self {
        Self {
            config,
            clock: SampleClock::new(config.latency_ns),
            current: Vec::new(),
            in_revolution: false,
            completed: false,
            last_t0_ns: None,
            dropped_samples: 0,
        }
    }

    /// Forget the revolution in progress (after a reconnect or a driver restart).
    pub fn reset(&mut self) {
        self.dropped_samples += self.current.len() as u64;
        self.current.clear();
        self.in_revolution = false;
        self.completed = false;
        self.clock.reset();
    }

    /// Samples that never became part of an emitted revolution (partial or too short ones).
    pub fn dropped_samples(&self) -> u64 {
        self.dropped_samples
    }

    /// Add a sample; returns the revolution it completed, if any.
    pub fn push(&mut self, sample: ArrivedSample) -> Option<Revolution> {
        self.stamp(sample).finished
    }

    /// The driver said the last sample pushed was the last of its revolution
    /// ([`crate::lidar::LidarEvent::RevolutionComplete`]): closes that revolution now, with
    /// [`Revolution::t1_ns`] one mean sample spacing after its last sample, and returns it
    /// (unless it is too short, or no revolution was in progress: a partial one is dropped).
    /// The next sample starts the next revolution, flagged or not; it is timed no earlier than
    /// this `t1_ns`, so revolutions never overlap.
    pub fn complete(&mut self) -> Option<Revolution> {
        if self.completed {
            return None;
        }
        self.completed = true;
        if !self.in_revolution {
            self.dropped_samples += self.current.len() as u64;
            self.current.clear();
            return None;
        }
        let (first, last) = (self.current.first()?.t_ns, self.current.last()?.t_ns);
        let gaps = self.current.len().saturating_sub(1).max(1) as u64;
        let t1_ns = last.saturating_add((last.saturating_sub(first) / gaps).max(1));
        self.clock.floor(t1_ns);
        self.finish(t1_ns)
    }

    /// Add a sample: its measurement time, its place in the revolution, and the revolution it
    /// completed, if any.
    pub fn stamp(&mut self, sample: ArrivedSample) -> Stamped {
        let completed = std::mem::take(&mut self.completed);
        let boundary =
            sample.sample.new_revolution || completed || self.wraps_without_flag(&sample);
        let mut t_ns = self
            .clock
            .estimate(f64::from(sample.sample.angle_deg), sample.arrival_ns);
        let mut finished = None;
        if boundary {
            if let Some(last) = self.last_t0_ns
                && t_ns <= last
            {
                // Flat arrivals (a stalled clock): keep revolution names unique.
                t_ns = last + 1;
                self.clock.floor(t_ns);
            }
            if self.in_revolution {
                finished = self.finish(t_ns);
            } else {
                self.dropped_samples += self.current.len() as u64;
                self.current.clear();
            }
            self.in_revolution = true;
            self.last_t0_ns = Some(t_ns);
        }
        let timed = TimedSample {
            angle_deg: sample.sample.angle_deg,
            range_m: sample.sample.range_m,
            quality: sample.sample.quality,
            t_ns,
        };
        let position = match (self.in_revolution, self.current.first()) {
            (false, _) => None,
            (true, first) => Some(RevolutionPosition {
                t0_ns: first.map_or(t_ns, |f| f.t_ns),
                index: u32::try_from(self.current.len()).unwrap_or(u32::MAX),
            }),
        };
        self.current.push(timed);
        Stamped {
            sample: StampedSample {
                sample: timed,
                position,
            },
            finished,
        }
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
        let crosses_zero = sample.sample.angle_deg + 180.0 < last.angle_deg;
        let covered = angle_progress(first.angle_deg, last.angle_deg);
        self.in_revolution && crosses_zero && covered >= 270.0
    }

    fn finish(&mut self, t1_ns: u64) -> Option<Revolution> {
        let samples = std::mem::take(&mut self.current);
        if samples.len() < self.config.min_samples.max(2) {
            self.dropped_samples += samples.len() as u64;
            return None;
        }
        Some(Revolution {
            t0_ns: samples[0].t_ns,
            t1_ns,
            samples,
        })
    }
}

/// Degrees from `from` to `to` going forwards, in `[0, 360)`.
fn angle_progress(from: f32, to: f32) -> f64 {
    (f64::from(to) - f64::from(from)).rem_euclid(360.0)
}

/// The order [`lower_envelope_fit`] wants its points in: by x, then y.
fn by_x_then_y(p: &(f64, f64), q: &(f64, f64)) -> std::cmp::Ordering {
    p.0.total_cmp(&q.0).then(p.1.total_cmp(&q.1))
}

/// Fits the line `y = a + b·x` that lies on or below every point and is as close to them as
/// possible (minimises the summed vertical gap). `points` must be sorted [`by_x_then_y`];
/// `hull` is scratch space, so that refitting allocates nothing.
///
/// This is the linear-programming clock-skew estimator of Moon, Skelly and Towsley (1999): the
/// optimum is the edge of the points' lower convex hull that spans the mean of `x`. Late
/// arrivals only ever lie above the line, so they cannot pull it; only the least-delayed
/// samples define it. A negative slope (time running backwards) is clamped to zero.
pub(crate) fn lower_envelope_fit(points: &[(f64, f64)], hull: &mut Vec<(f64, f64)>) -> (f64, f64) {
    // Andrew's monotone chain, lower hull only; for equal x keep the lowest y. The mean of x
    // is summed in the same pass.
    hull.clear();
    let mut sum_x = 0.0;
    for &p in points {
        sum_x += p.0;
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
    let n = points.len().max(1) as f64;
    let mean_x = sum_x / n;
    let segment = hull
        .windows(2)
        .find(|w| w[1].0 >= mean_x)
        .or_else(|| hull.windows(2).last());
    let (a, b) = match segment {
        Some(w) => {
            let b = ((w[1].1 - w[0].1) / (w[1].0 - w[0].0)).max(0.0);
            (w[0].1 - b * w[0].0, b)
        }
        None => (
            points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min),
            0.0,
        ),
    };
    // With the slope clamped the line may cross a point; lower it onto the envelope again.
    // The lowest point under a line is a vertex of the lower hull (every other point lies on
    // or above the hull), so the hull's vertices are enough.
    let min_gap = hull
        .iter()
        .map(|&(xi, yi)| yi - (a + b * xi))
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

    const MS: u64 = 1_000_000;

    /// `revolutions` revolutions of `per_rev` samples measured every `period_ns` from `t_start`,
    /// delivered in serial reads of `chunk` samples, each read returning `delay(read)` after its
    /// last sample. Returns the samples and their true measurement times.
    fn synthetic(
        per_rev: usize,
        revolutions: usize,
        period_ns: u64,
        t_start: u64,
        chunk: usize,
        delay: impl Fn(usize) -> u64,
    ) -> (Vec<ArrivedSample>, Vec<u64>) {
        let n = per_rev * revolutions;
        let truth: Vec<u64> = (0..n).map(|i| t_start + i as u64 * period_ns).collect();
        let samples = (0..n)
            .map(|i| {
                let chunk_end = ((i / chunk + 1) * chunk - 1).min(n - 1);
                ArrivedSample {
                    sample: RawSample {
                        angle_deg: ((i % per_rev) as f32 * 360.0 / per_rev as f32) + 0.5,
                        range_m: 1.0,
                        quality: 47,
                        new_revolution: i % per_rev == 0,
                    },
                    arrival_ns: truth[chunk_end] + delay(i / chunk),
                }
            })
            .collect();
        (samples, truth)
    }

    fn assemble(
        samples: &[ArrivedSample],
        latency_ns: u64,
    ) -> (Vec<StampedSample>, Vec<Revolution>) {
        let mut asm = RevolutionAssembler::new(TimingConfig {
            latency_ns,
            min_samples: 2,
        });
        let mut stamped = Vec::new();
        let mut revs = Vec::new();
        for s in samples {
            let out = asm.stamp(*s);
            stamped.push(out.sample);
            revs.extend(out.finished);
        }
        (stamped, revs)
    }

    #[test]
    fn bursty_arrivals_are_mapped_back_to_measurement_times() {
        // 2000 samples/s, chunks of 32 samples, latency 2 ms plus 0..8 ms of pseudo-random
        // jitter. After the first revolution (the envelope's history), every time is within
        // 0.5 ms of the truth.
        let latency = 2 * MS;
        let (samples, truth) = synthetic(360, 3, 500_000, 1_000_000_000, 32, |c| {
            latency + (c as u64 * 7919 % 9) * MS
        });
        let (stamped, revs) = assemble(&samples, latency);
        assert_eq!(revs.len(), 2);
        for (s, t) in stamped.iter().zip(&truth).skip(360) {
            let err = s.sample.t_ns as i64 - *t as i64;
            assert!(err.abs() < 500_000, "sample time off by {err} ns");
        }
        // 360 samples per turn: the next revolution starts 360 × 0.5 ms later.
        let period = revs[1].t1_ns - revs[1].t0_ns;
        assert!(
            (period as i64 - 180_000_000).abs() < 2_000_000,
            "period {period}"
        );
    }

    #[test]
    fn lost_samples_do_not_skew_times() {
        let (mut samples, mut truth) = synthetic(400, 2, 250_000, 5_000_000, 16, |_| 300_000);
        // Drop a run of 40 samples in the middle of the second revolution (a resync).
        samples.drain(550..590);
        truth.drain(550..590);
        let (stamped, _) = assemble(&samples, 300_000);
        for (s, t) in stamped.iter().zip(&truth).skip(400) {
            assert!((s.sample.t_ns as i64 - *t as i64).abs() < 300_000);
        }
    }

    #[test]
    fn a_revolution_carries_the_times_its_samples_were_stamped_with_as_they_arrived() {
        let (samples, _) = synthetic(100, 4, MS, 0, 10, |c| (c as u64 % 3) * MS);
        let (stamped, revs) = assemble(&samples, 0);
        assert_eq!(revs.len(), 3, "the fourth is still open");
        for rev in &revs {
            let members: Vec<_> = stamped
                .iter()
                .filter(|s| s.position.is_some_and(|p| p.t0_ns == rev.t0_ns))
                .collect();
            assert_eq!(members.len(), rev.samples.len());
            for (k, (s, r)) in members.iter().zip(&rev.samples).enumerate() {
                assert_eq!(s.position.unwrap().index as usize, k);
                assert_eq!(&s.sample, r, "one time per sample");
            }
            assert_eq!(rev.t0_ns, rev.samples[0].t_ns);
        }
        // The next revolution starts where the last ended.
        assert!(revs.windows(2).all(|w| w[0].t1_ns == w[1].t0_ns));
    }

    #[test]
    fn measurement_times_take_the_least_delayed_phase() {
        let mut times = SampleClock::new(0);
        // 1 Hz, a sample every degree measured at i ms·(1000/360); arrivals late by 1 ms plus
        // a burst of 40 ms every 50 samples.
        let mut worst: u64 = 0;
        for i in 0..1080u64 {
            let measured = i * 1_000_000_000 / 360;
            let late = if i % 50 < 5 { 40 * MS } else { MS };
            let estimate = times.estimate((i % 360) as f64, measured + late);
            if i > 400 {
                worst = worst.max(estimate.abs_diff(measured + MS));
            }
        }
        // After a revolution, every estimate is within rounding of the 1 ms floor.
        assert!(worst < 10_000, "worst error {worst} ns");
    }

    #[test]
    fn the_window_s_order_is_tracked_through_jitter_and_refits_on_the_sorted_window() {
        // Angles that step back by a little now and then (the window then holds an
        // out-of-order pair until it slides past it): the order tracking must say "unsorted"
        // exactly then (a debug assertion checks every "sorted"), and the estimates still
        // follow the truth.
        let mut times = SampleClock::new(0);
        let mut worst: u64 = 0;
        for i in 0..2000u64 {
            let jitter = if i % 97 == 0 { -1.5 } else { 0.0 };
            let angle = ((i as f64 * 0.9) + jitter).rem_euclid(360.0);
            let measured = i * 250_000;
            let estimate = times.estimate(angle, measured + MS + (i % 7) * 100_000);
            if i > 900 {
                worst = worst.max(estimate.abs_diff(measured + MS));
            }
        }
        assert!(worst < 700_000, "worst error {worst} ns");
    }

    #[test]
    fn the_envelope_line_lies_under_every_point_and_touches_one() {
        // Pseudo-random clouds: the fitted line is under every point, and on at least one
        // (the lowering onto the envelope looks at the hull's vertices only).
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut hull = Vec::new();
        for _ in 0..200 {
            let mut points: Vec<(f64, f64)> = (0..60)
                .map(|i| (i as f64 + next() * 0.5, 3.0 * i as f64 + next() * 10.0))
                .collect();
            points.sort_by(by_x_then_y);
            let (a, b) = lower_envelope_fit(&points, &mut hull);
            let gaps: Vec<f64> = points.iter().map(|&(x, y)| y - (a + b * x)).collect();
            let lowest = gaps.iter().copied().fold(f64::INFINITY, f64::min);
            assert!(lowest >= -1e-9, "a point under the line: {lowest}");
            assert!(lowest < 1e-9, "the line touches no point: {lowest}");
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
        let mut lead_positions = Vec::new();
        let mut t = 0;
        for rev in 0..3 {
            for k in 0..10 {
                let angle = if rev == 0 {
                    200.0 + k as f32 * 10.0
                } else {
                    k as f32 * 36.0
                };
                t += 1000;
                let out = asm.stamp(sample(angle, rev > 0 && k == 0, t));
                if rev == 0 {
                    lead_positions.push(out.sample.position);
                }
                revs.extend(out.finished);
            }
        }
        assert_eq!(
            revs.len(),
            1,
            "only the revolution closed by the third start flag"
        );
        assert_eq!(revs[0].samples.len(), 10);
        assert_eq!(asm.dropped_samples(), 10);
        assert!(lead_positions.iter().all(Option::is_none));
        assert!(revs[0].samples.windows(2).all(|w| w[0].t_ns <= w[1].t_ns));
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
    fn a_revolution_the_driver_says_is_complete_closes_before_the_next_start_flag() {
        let mut asm = RevolutionAssembler::new(TimingConfig {
            latency_ns: 0,
            min_samples: 2,
        });
        // Before any start flag: the partial revolution is dropped, nothing is emitted.
        asm.push(sample(300.0, false, 500));
        assert_eq!(asm.complete(), None);
        assert_eq!(asm.dropped_samples(), 1);
        // A revolution of 8 samples 1 µs apart (one arrival each: the times are the arrivals).
        let mut out = Vec::new();
        for k in 0..8u64 {
            out.extend(asm.push(sample(k as f32 * 45.0, k == 0, 1_000 + 1_000 * k)));
        }
        assert!(out.is_empty(), "no start flag has closed it");
        let rev = asm.complete().expect("closed by the driver's word");
        assert_eq!(rev.samples.len(), 8);
        assert_eq!(rev.t0_ns, 1_000);
        // One mean spacing after the last sample (8 µs).
        assert_eq!(rev.t1_ns, 9_000);
        assert_eq!(asm.complete(), None, "said twice, closed once");
        // The next revolution's flagged sample starts it, and closes nothing more; it is timed
        // no earlier than the closed revolution's end although it arrived earlier.
        assert_eq!(asm.push(sample(0.5, true, 8_500)), None);
        for k in 1..8u64 {
            assert_eq!(
                asm.push(sample(k as f32 * 45.0, false, 9_000 + 1_000 * k)),
                None
            );
        }
        let next = asm
            .push(sample(1.0, true, 17_000))
            .expect("the next start flag");
        assert_eq!(next.t0_ns, 9_000);
        assert!(next.t0_ns >= rev.t1_ns);
        assert_eq!(next.samples.len(), 8);
        // Unflagged, a sample after the driver's word still starts the next revolution.
        for k in 1..8u64 {
            asm.push(sample(k as f32 * 45.0, false, 17_000 + 1_000 * k));
        }
        let third = asm.complete().expect("complete");
        assert_eq!(third.samples.len(), 8);
        assert_eq!(asm.push(sample(2.0, false, 25_000)), None);
        let position = asm.stamp(sample(45.0, false, 26_000)).sample.position;
        assert_eq!(
            position.map(|p| p.index),
            Some(1),
            "the unflagged sample started one"
        );
        assert_eq!(asm.dropped_samples(), 1);
    }

    #[test]
    fn single_arrival_time_gives_flat_but_valid_times_and_unique_revolution_names() {
        // Every sample of two revolutions arrives in one read at 5 µs; latency 1 µs.
        let mut asm = RevolutionAssembler::new(TimingConfig {
            latency_ns: 1_000,
            min_samples: 2,
        });
        let mut revs = Vec::new();
        for i in 0..21 {
            revs.extend(asm.push(sample((i % 10) as f32 * 30.0, i % 10 == 0, 5_000)));
        }
        assert_eq!(revs.len(), 2);
        assert!(revs[0].samples.iter().all(|s| s.t_ns == 4_000));
        assert_eq!(revs[0].t0_ns, 4_000);
        // The next revolution's start is bumped by 1 ns so that t0 names it uniquely.
        assert_eq!((revs[0].t1_ns, revs[1].t0_ns), (4_001, 4_001));
        assert!(revs[1].samples.iter().all(|s| s.t_ns == 4_001));
    }
}
