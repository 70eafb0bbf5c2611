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
//! # Errors
//!
//! On a sync or checksum failure the parser slides one byte. A capsule with S = 1 (the device
//! restarted its angle sequence) drops the held capsule without decoding it, like the SDK.
//! Unlike the SDK, a held capsule survives a framing error: when the next good capsule arrives,
//! the start-angle gap decides. A gap within ±25 % of the last used `diff` means nothing was
//! lost (e.g. a stray byte between capsules) and the capsule is decoded normally; a gap within
//! ±25 % of twice that `diff` means exactly one capsule was lost, and the held capsule is decoded
//! with half the gap as its `diff`; anything else drops it.

use crate::lidar::{DriverStats, RawSample};

/// Bytes per capsule.
pub const CAPSULE_LEN: usize = 84;
/// Samples per capsule (16 cabins × 2).
pub const SAMPLES_PER_CAPSULE: usize = 32;
const FULL_TURN_Q6: u32 = 360 * 64;
/// Express samples have no quality; the SDK reports 47 << 2 (we keep the 6-bit scale).
const EXPRESS_QUALITY: u8 = 47;

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

    /// Parses as much of `buf` as possible. `emit(sample, end)` gets every decoded sample with
    /// the offset in `buf` just past the capsule whose arrival allowed decoding it. Returns
    /// `(bytes consumed, capsules accepted)`.
    pub fn parse(
        &mut self,
        buf: &[u8],
        stats: &mut DriverStats,
        mut emit: impl FnMut(RawSample, usize),
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

    fn accept(&mut self, next: Capsule, mut emit: impl FnMut(RawSample)) {
        let held = self.held.replace(next);
        let damaged = std::mem::replace(&mut self.held_damaged, false);
        let Some(held) = held else { return };
        if next.restart {
            return;
        }
        let gap = (next.start_q6 + FULL_TURN_Q6 - held.start_q6) % FULL_TURN_Q6;
        let diff = if !damaged {
            Some(gap)
        } else {
            match self.last_diff_q6 {
                Some(d) if 4 * gap.abs_diff(d) <= d => Some(gap),
                Some(d) if 4 * gap.abs_diff(2 * d) <= 2 * d => Some(gap / 2),
                _ => None,
            }
        };
        if let Some(diff) = diff {
            self.decode(&held, diff, &mut emit);
            self.last_diff_q6 = Some(diff);
        }
    }

    fn decode(&mut self, capsule: &Capsule, diff_q6: u32, emit: &mut impl FnMut(RawSample)) {
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
                emit(RawSample {
                    angle_deg: to_f32_deg(angle),
                    range_m: f32::from(distance_mm) / 1000.0,
                    quality: if distance_mm != 0 { EXPRESS_QUALITY } else { 0 },
                    new_revolution,
                });
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
