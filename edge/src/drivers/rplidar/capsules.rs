//! Legacy express capsules (EXPRESS_SCAN answer type 0x82, 84 bytes; notes §1.7, §1.11).
//!
//! Layout: `b0 = 0xA | checksum[3:0]`, `b1 = 0x5 | checksum[7:4]` (sync nibbles in the high
//! halves), `b2..b3` = u16 LE (bit 15 S, bits 0..14 start angle q6), then 16 cabins of 5 bytes
//! (`u16 d1, u16 d2, u8 o`: distance in bits 2..15 in mm, dθ\[5:4\] in bits 0..1, dθ\[3:0\] in
//! the low / high nibble of `o`). Checksum = XOR of bytes 2..83.
//!
//! # Angles
//!
//! A capsule `P_i` is decoded when the next good capsule `P_{i+1}` arrives, exactly as the SDK's
//! `handler_capsules.cpp` does (all arithmetic in `f64` degrees, result rounded to `f32`):
//!
//! ```text
//! ω_i = start_q6(P_i) / 64,  diff = (start_q6(P_{i+1}) − start_q6(P_i)) / 64  (+360 if negative)
//! for k in 0..32 (cabin k/2, first or second distance by k%2):
//!     φ_k = (ω_i + diff·k/32) mod 360            uncorrected ("base") angle
//!     θ_k = (φ_k − dθ_k/8) mod 360               reported angle, in [0, 360); dθ unsigned q3
//!     range = distance_mm / 1000 m, quality = 47 if distance ≠ 0 else 0
//! ```
//!
//! # Revolution flag
//!
//! `new_revolution` is set on a sample whose **base** angle `φ_k` is smaller than the base angle
//! of the sample decoded just before it (across capsule boundaries, and across lost capsules);
//! the very first sample after `start` is never flagged. The base angle is used rather than
//! `θ_k` because the per-sample correction `dθ_k/8` (up to 7.9°) makes consecutive `θ` values
//! go backwards inside a revolution. (The SDK flags the sample *before* the wrap instead.)
//!
//! # Revolution end
//!
//! A revolution is complete once its last sample is decoded. When the wrap falls inside a
//! capsule, the flagged sample comes with that capsule's other samples and closes it. When it
//! falls between two capsules (the next capsule's `ω` is below the last base angle: about one
//! revolution in 32), the flagged sample would only be decoded when the capsule after next
//! arrives, 8 ms later; the parser knows from `ω_{i+1}` alone that `P_i`'s last sample ends the
//! revolution, and says so ([`CapsuleOutput::RevolutionComplete`]) right after it. From the
//! held capsule's `ω` and the last `diff` it also tells how many more bytes the revolution
//! needs ([`CapsuleParser::bytes_to_revolution_end`]), which the driver turns into a read
//! deadline.
//!
//! # Errors
//!
//! On a sync or checksum failure the parser slides one byte. A capsule with S = 1 (the device
//! restarted its angle sequence) drops the held capsule without decoding it, like the SDK.
//! Unlike the SDK, a held capsule survives a framing error: when the next good capsule arrives,
//! the start-angle gap decides. A gap within ±25 % of the last used `diff` means nothing was
//! lost (e.g. a stray byte between capsules) and the capsule is decoded normally; after damaged
//! bytes, a gap within ±25 % of twice that `diff` means exactly one capsule was lost, and the
//! held capsule is decoded with half the gap as its `diff`; anything else drops it. The same
//! check applies without damaged bytes: a clean stream whose angle jumps lost whole capsules
//! upstream (an overrun), and decoding across the jump would misplace every sample.

use crate::lidar::{DriverStats, RawSample};

/// Bytes per capsule.
pub const CAPSULE_LEN: usize = 84;
/// Samples per capsule (16 cabins × 2).
pub const SAMPLES_PER_CAPSULE: usize = 32;
const FULL_TURN_Q6: u32 = 360 * 64;
/// Largest plausible start-angle step between consecutive capsules: 32 samples at the fastest
/// rotation and slowest sample rate an A1/A2 reaches (about 0.9° per sample), with margin.
const MAX_DIFF_Q6: u32 = 45 * 64;
/// Express samples have no quality; the SDK reports 47 << 2 (we keep the 6-bit scale).
const EXPRESS_QUALITY: u8 = 47;

/// What [`CapsuleParser::parse`] hands out, in stream order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CapsuleOutput {
    /// A decoded sample.
    Sample(RawSample),
    /// The sample before this was the last of its revolution: the next capsule's start angle
    /// wrapped (see the module doc, "Revolution end").
    RevolutionComplete,
}

/// A capsule that passed the sync and checksum checks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Capsule {
    restart: bool,
    start_q6: u32,
    cabins: [u8; 80],
}

impl Capsule {
    fn decode(bytes: &[u8; CAPSULE_LEN]) -> Option<Capsule> {
        let (head, cabins) = bytes.split_at(4);
        let [b0, b1, b2, b3] = [head[0], head[1], head[2], head[3]];
        if b0 >> 4 != 0xA || b1 >> 4 != 0x5 {
            return None;
        }
        let wanted = (b0 & 0x0F) | ((b1 & 0x0F) << 4);
        let actual = bytes.iter().skip(2).fold(0u8, |acc, b| acc ^ b);
        let start = u16::from_le_bytes([b2, b3]);
        let start_q6 = u32::from(start & 0x7FFF);
        if wanted != actual || start_q6 >= FULL_TURN_Q6 {
            return None;
        }
        let cabins = <[u8; 80]>::try_from(cabins).ok()?;
        Some(Capsule {
            restart: start & 0x8000 != 0,
            start_q6,
            cabins,
        })
    }
}

/// Express-capsule parser state (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct CapsuleParser {
    /// The last position was a capsule boundary (no framing error since the last good capsule).
    in_sync: bool,
    /// The last good capsule, waiting for its successor.
    held: Option<Capsule>,
    /// A framing error happened after `held` arrived.
    held_damaged: bool,
    /// `diff` (q6) used for the last decoded capsule.
    last_diff_q6: Option<u32>,
    /// Base angle of the last decoded sample, for the revolution flag.
    last_base_deg: Option<f64>,
}

impl CapsuleParser {
    /// A parser aligned on a capsule boundary (right after the scan descriptor).
    pub fn new() -> Self {
        Self {
            in_sync: true,
            ..Self::default()
        }
    }

    /// Parses as much of `buf` as possible. `emit(output, end)` gets every decoded sample (and
    /// every revolution end) with the offset in `buf` just past the capsule whose arrival
    /// allowed decoding it. Returns `(bytes consumed, capsules accepted)`.
    pub fn parse(
        &mut self,
        buf: &[u8],
        stats: &mut DriverStats,
        mut emit: impl FnMut(CapsuleOutput, usize),
    ) -> (usize, u64) {
        let mut pos = 0;
        let mut accepted = 0;
        while let Some(window) = buf.get(pos..pos + CAPSULE_LEN) {
            let capsule = <&[u8; CAPSULE_LEN]>::try_from(window)
                .ok()
                .and_then(Capsule::decode);
            match capsule {
                Some(capsule) => {
                    pos += CAPSULE_LEN;
                    accepted += 1;
                    self.in_sync = true;
                    self.accept(capsule, |s| emit(s, pos));
                }
                None => {
                    if self.in_sync {
                        stats.frames_rejected += 1;
                        stats.resyncs += 1;
                        self.in_sync = false;
                    }
                    self.held_damaged = true;
                    stats.bytes_discarded += 1;
                    pos += 1;
                }
            }
        }
        (pos, accepted)
    }

    /// Bytes that must still arrive, counted from just past the held capsule, before the last
    /// sample of the revolution in progress is decoded; `None` while that cannot be told (out
    /// of sync, no capsule held, no `diff` yet). The held capsule's samples and those of the
    /// capsules after it continue at the last `diff` per capsule; the last one below 360° is
    /// decoded when the capsule after its own has arrived.
    pub fn bytes_to_revolution_end(&self) -> Option<usize> {
        if !self.in_sync || self.held_damaged {
            return None;
        }
        let held = self.held?;
        let diff = u64::from(self.last_diff_q6.filter(|&d| d > 0)?);
        // Sample j after the held capsule's first has base angle ω + diff·j/32 (q6): the last
        // one of the revolution is the largest j with diff·j < 32·(360° − ω).
        let before_wrap = 32 * u64::from(FULL_TURN_Q6 - held.start_q6.min(FULL_TURN_Q6 - 1));
        let last = (before_wrap - 1) / diff;
        let capsules = last / SAMPLES_PER_CAPSULE as u64 + 1;
        usize::try_from(capsules).ok()?.checked_mul(CAPSULE_LEN)
    }

    fn accept(&mut self, next: Capsule, mut emit: impl FnMut(CapsuleOutput)) {
        let held = self.held.replace(next);
        let damaged = std::mem::replace(&mut self.held_damaged, false);
        let Some(held) = held else { return };
        if next.restart {
            return;
        }
        let gap = (next.start_q6 + FULL_TURN_Q6 - held.start_q6) % FULL_TURN_Q6;
        let diff = match self.last_diff_q6 {
            Some(d) if 4 * gap.abs_diff(d) <= d => Some(gap),
            // Damaged bytes in between: one corrupted capsule, decode across it.
            Some(d) if damaged && 4 * gap.abs_diff(2 * d) <= 2 * d => Some(gap / 2),
            // A clean stream whose angle jumps: whole capsules vanished (an overrun upstream of
            // the serial port), and capsules carry no sequence number to tell how many.
            Some(_) => None,
            None if !damaged && gap <= MAX_DIFF_Q6 => Some(gap),
            None => None,
        };
        if let Some(diff) = diff {
            self.decode(&held, diff, &mut emit);
            self.last_diff_q6 = Some(diff);
            // The next capsule's first sample has base angle ω_{i+1}: below the last one, it
            // will be flagged, so the revolution ended with the sample just decoded.
            let next_base = f64::from(next.start_q6) / 64.0;
            if self.last_base_deg.is_some_and(|last| next_base < last) {
                emit(CapsuleOutput::RevolutionComplete);
            }
        }
    }

    fn decode(&mut self, capsule: &Capsule, diff_q6: u32, emit: &mut impl FnMut(CapsuleOutput)) {
        let omega = f64::from(capsule.start_q6) / 64.0;
        let diff = f64::from(diff_q6) / 64.0;
        for (j, cabin) in capsule.cabins.chunks_exact(5).enumerate() {
            let [d1l, d1h, d2l, d2h, o] = [cabin[0], cabin[1], cabin[2], cabin[3], cabin[4]];
            let halves = [
                (u16::from_le_bytes([d1l, d1h]), o & 0x0F),
                (u16::from_le_bytes([d2l, d2h]), o >> 4),
            ];
            for (half, (field, dtheta_low)) in halves.into_iter().enumerate() {
                let k = (2 * j + half) as f64;
                let dtheta_q3 = ((field & 0x3) << 4) as u8 | dtheta_low;
                let distance_mm = field >> 2;
                let base = wrap_deg(omega + diff * k / 32.0);
                let angle = wrap_deg(base - f64::from(dtheta_q3) / 8.0);
                let new_revolution = self.last_base_deg.is_some_and(|prev| base < prev);
                self.last_base_deg = Some(base);
                emit(CapsuleOutput::Sample(RawSample {
                    angle_deg: to_f32_deg(angle),
                    range_m: f32::from(distance_mm) / 1000.0,
                    quality: if distance_mm != 0 { EXPRESS_QUALITY } else { 0 },
                    new_revolution,
                }));
            }
        }
    }
}

/// `a` wrapped into `[0, 360)`.
fn wrap_deg(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    if r >= 360.0 { 0.0 } else { r }
}

/// `f32` of an angle in `[0, 360)`, keeping the upper bound open after rounding.
fn to_f32_deg(a: f64) -> f32 {
    let f = a as f32;
    if f >= 360.0 { 0.0 } else { f }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// Encodes a legacy capsule from the layout in the notes (§1.7), independently of the
    /// decoder: `samples[k] = (distance_mm, dθ_q3)`.
    pub(crate) fn encode(start_q6: u16, restart: bool, samples: &[(u16, u8); 32]) -> [u8; 84] {
        let mut b = [0u8; 84];
        let start = start_q6 | if restart { 0x8000 } else { 0 };
        b[2..4].copy_from_slice(&start.to_le_bytes());
        for j in 0..16 {
            let (d1, t1) = samples[2 * j];
            let (d2, t2) = samples[2 * j + 1];
            let f1 = (d1 << 2) | u16::from(t1 >> 4);
            let f2 = (d2 << 2) | u16::from(t2 >> 4);
            let at = 4 + 5 * j;
            b[at..at + 2].copy_from_slice(&f1.to_le_bytes());
            b[at + 2..at + 4].copy_from_slice(&f2.to_le_bytes());
            b[at + 4] = (t1 & 0x0F) | ((t2 & 0x0F) << 4);
        }
        let checksum = b[2..].iter().fold(0u8, |a, x| a ^ x);
        b[0] = 0xA0 | (checksum & 0x0F);
        b[1] = 0x50 | (checksum >> 4);
        b
    }

    /// Capsule `i`'s samples: distance `1000·(i+1) + k` (0 for k = 1), dθ = k (0..31).
    fn samples(i: u16) -> [(u16, u8); 32] {
        std::array::from_fn(|k| (if k == 1 { 0 } else { 1000 * (i + 1) + k as u16 }, k as u8))
    }

    /// The expected sample `k` of capsule `i` (start `omega`°, `diff`°), from the notes' formula.
    fn expected(i: u16, k: usize, omega: f64, diff: f64) -> RawSample {
        let (d, t) = samples(i)[k];
        let theta = (omega + diff * k as f64 / 32.0 - f64::from(t) / 8.0).rem_euclid(360.0);
        RawSample {
            angle_deg: theta as f32,
            range_m: f32::from(d) / 1000.0,
            quality: if d == 0 { 0 } else { 47 },
            new_revolution: false,
        }
    }

    fn run(bytes: &[u8]) -> (Vec<(RawSample, usize)>, DriverStats) {
        let mut parser = CapsuleParser::new();
        let mut stats = DriverStats::default();
        let mut out = Vec::new();
        let mut buf = Vec::new();
        let mut base = 0;
        // Odd-sized reads to exercise partial capsules.
        for chunk in bytes.chunks(37) {
            buf.extend_from_slice(chunk);
            let (consumed, _) = parser.parse(&buf, &mut stats, |output, end| {
                if let CapsuleOutput::Sample(s) = output {
                    out.push((s, base + end));
                }
            });
            buf.drain(..consumed);
            base += consumed;
        }
        (out, stats)
    }

    /// Capsules `i` at `i · 30°` for the given indices (an index not listed is "lost").
    fn stream(indices: &[u16]) -> Vec<u8> {
        indices
            .iter()
            .flat_map(|&i| encode(i * 30 * 64, false, &samples(i)))
            .collect()
    }

    #[test]
    fn consecutive_capsules_decode_with_the_sdk_formula() {
        let (out, stats) = run(&stream(&[0, 1]));
        assert_eq!(out.len(), 32, "the second capsule waits for a successor");
        // Hand-computed: k = 0: 0 − 0/8 = 0°; k = 1: 0.9375 − 0.125 = 0.8125° with no return;
        // k = 8: 7.5 − 1 = 6.5°; k = 31: 29.0625 − 3.875 = 25.1875°.
        assert_eq!(
            out[0].0,
            RawSample {
                angle_deg: 0.0,
                range_m: 1.0,
                quality: 47,
                new_revolution: false
            }
        );
        assert_eq!(
            out[1].0,
            RawSample {
                angle_deg: 0.8125,
                range_m: 0.0,
                quality: 0,
                new_revolution: false
            }
        );
        assert_eq!(out[8].0.angle_deg, 6.5);
        assert_eq!(out[31].0.angle_deg, 25.1875);
        for (k, (s, end)) in out.iter().enumerate() {
            assert_eq!(*s, expected(0, k, 0.0, 30.0));
            assert_eq!(*end, 168, "decoded when the second capsule completed");
        }
        assert_eq!(stats, DriverStats::default());
    }

    #[test]
    fn negative_angles_wrap_and_the_revolution_flag_follows_the_base_angle() {
        // 340° then 10°: diff 30°; base angles 340 + 0.9375·k cross 360° at k = 22 (0.625°).
        // Sample 0 of the first capsule has dθ 0; sample 3 has 0.375° at 342.8125 − 0.375.
        let bytes = [
            encode(340 * 64, false, &samples(0)),
            encode(10 * 64, false, &samples(1)),
        ];
        let bytes: Vec<u8> = bytes.concat();
        let (out, _) = run(&[bytes.as_slice(), &encode(40 * 64, false, &samples(2))].concat());
        assert_eq!(out.len(), 64);
        let flagged: Vec<usize> = out
            .iter()
            .enumerate()
            .filter(|(_, (s, _))| s.new_revolution)
            .map(|(k, _)| k)
            .collect();
        assert_eq!(flagged, [22]);
        // k = 22: base 0.625°, dθ 22/8 = 2.75° → 357.875°, flagged although θ did not wrap.
        assert_eq!(out[22].0.angle_deg, 357.875);
        assert_eq!(out[3].0.angle_deg, 342.4375);
        // k = 23: base 1.5625, dθ 2.875 → 358.6875.
        assert_eq!(out[23].0.angle_deg, 358.6875);
    }

    /// Every output of `bytes` fed in one piece, revolution ends included.
    fn outputs(parser: &mut CapsuleParser, bytes: &[u8]) -> Vec<CapsuleOutput> {
        let mut out = Vec::new();
        let mut stats = DriverStats::default();
        let (consumed, _) = parser.parse(bytes, &mut stats, |output, _| out.push(output));
        assert_eq!(consumed, bytes.len());
        out
    }

    /// Capsule `i` of a rotor turning 30° a capsule from `offset_deg`, wrapped into [0°, 360°).
    fn turning(i: u16, offset_deg: u16) -> [u8; 84] {
        encode(((offset_deg + 30 * i) % 360) * 64, false, &samples(i))
    }

    #[test]
    fn a_wrap_between_capsules_ends_the_revolution_before_its_flagged_sample_is_decoded() {
        let mut parser = CapsuleParser::new();
        assert_eq!(parser.bytes_to_revolution_end(), None, "nothing held");
        let head: Vec<u8> = (0..2).flat_map(|i| turning(i, 0)).collect();
        assert_eq!(outputs(&mut parser, &head).len(), 32);
        // Capsule 1 (30°) is held; the revolution's last sample (359.06°) is capsule 11's
        // last, decoded once capsule 12 is in: 11 more capsules.
        assert_eq!(parser.bytes_to_revolution_end(), Some(11 * CAPSULE_LEN));
        let body: Vec<u8> = (2..12).flat_map(|i| turning(i, 0)).collect();
        let out = outputs(&mut parser, &body);
        assert_eq!(out.len(), 10 * 32);
        assert!(!out.contains(&CapsuleOutput::RevolutionComplete));
        assert_eq!(parser.bytes_to_revolution_end(), Some(CAPSULE_LEN));
        // Capsule 12 starts at 0°: capsule 11 decodes, and its last sample ends the revolution
        // although the flagged sample (capsule 12's first) waits for capsule 13.
        let out = outputs(&mut parser, &turning(12, 0));
        assert_eq!(out.len(), 33);
        assert_eq!(out[32], CapsuleOutput::RevolutionComplete);
        assert!(
            out.iter()
                .all(|o| !matches!(o, CapsuleOutput::Sample(s) if s.new_revolution))
        );
        // The next revolution ends 12 capsules after capsule 12 (whose successor is needed).
        assert_eq!(parser.bytes_to_revolution_end(), Some(12 * CAPSULE_LEN));
        let out = outputs(&mut parser, &turning(13, 0));
        assert!(matches!(out[0], CapsuleOutput::Sample(s) if s.new_revolution));
        assert!(!out.contains(&CapsuleOutput::RevolutionComplete));
    }

    #[test]
    fn a_wrap_inside_a_capsule_is_ended_by_the_flagged_sample_alone() {
        // From 15°: capsule 11 covers 345°..374°, the wrap is at its sample 16.
        let mut parser = CapsuleParser::new();
        let head: Vec<u8> = (0..2).flat_map(|i| turning(i, 15)).collect();
        outputs(&mut parser, &head);
        // Held at 45°: the last sample below 360° is the 336th after it, in capsule 11.
        assert_eq!(parser.bytes_to_revolution_end(), Some(11 * CAPSULE_LEN));
        let body: Vec<u8> = (2..13).flat_map(|i| turning(i, 15)).collect();
        let out = outputs(&mut parser, &body);
        assert_eq!(out.len(), 11 * 32);
        assert!(!out.contains(&CapsuleOutput::RevolutionComplete));
        let flagged: Vec<usize> = out
            .iter()
            .enumerate()
            .filter(|(_, o)| matches!(o, CapsuleOutput::Sample(s) if s.new_revolution))
            .map(|(k, _)| k)
            .collect();
        // Capsules 1 to 11 came out: capsule 11's sample 16.
        assert_eq!(flagged, [10 * 32 + 16]);
        // Held capsule 12 at 15°: this revolution ends in capsule 23, 12 capsules on.
        assert_eq!(parser.bytes_to_revolution_end(), Some(12 * CAPSULE_LEN));
    }

    #[test]
    fn no_revolution_end_is_predicted_across_damaged_bytes() {
        let mut parser = CapsuleParser::new();
        let mut bytes: Vec<u8> = (0..2).flat_map(|i| turning(i, 0)).collect();
        bytes.extend([0x00; 100]);
        let mut stats = DriverStats::default();
        parser.parse(&bytes, &mut stats, |_, _| {});
        assert_eq!(parser.bytes_to_revolution_end(), None);
        let next = turning(2, 0);
        parser.parse(&next, &mut stats, |_, _| {});
        assert!(parser.bytes_to_revolution_end().is_some(), "in sync again");
    }

    #[test]
    fn capsules_that_vanished_without_a_trace_drop_the_held_one() {
        // An overrun upstream removed capsules 2..=5 whole: capsule 1 is followed directly by
        // capsule 6. Decoding 1 with the 150° gap would misplace all its samples.
        let (out, stats) = run(&stream(&[0, 1, 6, 7, 8]));
        let got: Vec<RawSample> = out.iter().map(|(s, _)| *s).collect();
        let mut want: Vec<RawSample> = (0..32).map(|k| expected(0, k, 0.0, 30.0)).collect();
        want.extend((0..32).map(|k| expected(6, k, 180.0, 30.0)));
        want.extend((0..32).map(|k| expected(7, k, 210.0, 30.0)));
        assert_eq!(got, want);
        assert_eq!(
            stats.frames_rejected, 0,
            "nothing was corrupt, only missing"
        );
    }

    #[test]
    fn corrupt_capsule_is_skipped_and_one_lost_capsule_is_recovered() {
        let mut bytes = stream(&[0, 1, 2, 3, 4]);
        bytes[2 * 84 + 40] ^= 0x10; // capsule 2 fails its checksum
        let (out, stats) = run(&bytes);
        let got: Vec<RawSample> = out.iter().map(|(s, _)| *s).collect();
        let mut want: Vec<RawSample> = (0..32).map(|k| expected(0, k, 0.0, 30.0)).collect();
        // Capsule 1 is held across the error and decoded with half the 60° gap to capsule 3.
        want.extend((0..32).map(|k| expected(1, k, 30.0, 30.0)));
        want.extend((0..32).map(|k| expected(3, k, 90.0, 30.0)));
        assert_eq!(got, want);
        assert_eq!(
            (stats.frames_rejected, stats.resyncs, stats.bytes_discarded),
            (1, 1, 84)
        );
    }

    #[test]
    fn two_lost_capsules_drop_the_held_one() {
        let mut bytes = stream(&[0, 1, 2, 3, 4, 5]);
        bytes[2 * 84 + 10] ^= 0x01;
        bytes[3 * 84 + 10] ^= 0x01;
        let (out, stats) = run(&bytes);
        let sources: Vec<u16> = out
            .iter()
            .map(|(s, _)| (s.range_m * 1000.0).round() as u16 / 1000)
            .collect();
        assert_eq!(
            sources.iter().filter(|&&c| c == 1).count(),
            31,
            "capsule 0 (one no-return)"
        );
        assert_eq!(sources.iter().filter(|&&c| c == 5).count(), 31, "capsule 4");
        assert_eq!(out.len(), 64, "capsule 1 dropped, 2 and 3 lost, 5 held");
        assert_eq!(
            (stats.frames_rejected, stats.resyncs, stats.bytes_discarded),
            (1, 1, 168)
        );
    }

    #[test]
    fn stray_byte_between_capsules_loses_nothing() {
        let mut bytes = stream(&[0, 1]);
        bytes.push(0x42);
        bytes.extend(stream(&[2, 3]));
        let (out, stats) = run(&bytes);
        let got: Vec<RawSample> = out.iter().map(|(s, _)| *s).collect();
        let want: Vec<RawSample> = (0..3u16)
            .flat_map(|i| (0..32).map(move |k| expected(i, k, f64::from(i) * 30.0, 30.0)))
            .collect();
        assert_eq!(got, want);
        assert_eq!((stats.resyncs, stats.bytes_discarded), (1, 1));
    }

    #[test]
    fn restart_flag_drops_the_held_capsule() {
        let mut bytes = stream(&[0, 1]);
        bytes.extend(encode(200 * 64, true, &samples(7)));
        bytes.extend(encode(230 * 64, false, &samples(8)));
        let (out, _) = run(&bytes);
        let got: Vec<RawSample> = out.iter().map(|(s, _)| *s).collect();
        let mut want: Vec<RawSample> = (0..32).map(|k| expected(0, k, 0.0, 30.0)).collect();
        want.extend((0..32).map(|k| expected(7, k, 200.0, 30.0)));
        assert_eq!(got, want);
    }

    #[test]
    fn sync_nibbles_and_angle_range_are_checked() {
        let good = encode(0, false, &samples(0));
        assert!(Capsule::decode(&good).is_some());
        let mut bad_sync = good;
        bad_sync[1] = (bad_sync[1] & 0x0F) | 0x60;
        assert!(Capsule::decode(&bad_sync).is_none());
        // 400° has a valid checksum but is not an angle.
        assert!(Capsule::decode(&encode(400 * 64, false, &samples(0))).is_none());
    }
}
