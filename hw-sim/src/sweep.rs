//! Scanse Sweep emulator: the ASCII command/receipt protocol and the 7-byte data blocks
//! (research/lidar-protocols.md §2, checklist §3.4), driven by simulated time.
//!
//! Behaviour, beyond what the notes fix:
//! - Commands end at LF, CR or CRLF (empty lines are ignored). A line longer than
//!   [`MAX_LINE`] bytes is discarded up to its terminator; a 1-byte line is ignored.
//! - Unknown commands, and parameterless commands sent with a parameter, are answered
//!   `C1 C2 '1' '1' 'R' LF` (status `11`). This is our choice: the real reply is undocumented.
//!   Non-printable command bytes are echoed as `?` so receipts stay printable.
//! - MS/LR with a two-byte but invalid parameter echo it (`MSab\n11R\n`); with a parameter of
//!   another length they answer without echo (`MS11R\n`).
//! - MS while the motor is still settling is refused with `12` and changes nothing. An accepted
//!   MS restarts settling; MS and LR stop an active stream (the motor or laser is being
//!   reconfigured). DS while streaming answers `DS00P` and the stream goes on.
//! - DS checks 0 Hz (`13`) before settling (`12`).
//! - RR: no receipt; the device ignores every byte for `reboot_ms`, then settles for
//!   `settle_ms`. Speed and sample rate survive it, except a speed of 0, which comes back as 5.
//! - Host connects and disconnects change nothing (the stream goes on) but drop a partial line.
//! - IV uses libsweep's field widths (model 5, protocol 2, firmware 2, hardware 1, serial 8:
//!   21 bytes with the LF); config strings are truncated or left-padded with `0` to fit.
//! - ID reports laser state 1, mode 1, diagnostic 0, the motor speed code and the nominal
//!   sample rate of the code (0500, 0750, 1000, as in the manual's example); blocks are paced at the middle of the band (550, 775, 1025 Hz).
//! - Returns beyond `reliable_range_m` (10 m) survive with a probability falling linearly to 0
//!   at `max_return_range_m` (40 m); a lost return is sent as distance 0, strength 0.
//! - Strength = round(255 · (1 − r / max_return_range_m)²), at least 1 for a return: nearer
//!   is stronger. (The scanner reports only a range, so the material does not enter.)

use std::sync::Arc;

use nalgebra::Isometry3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scan3d_edge::lidar::RawSample;

use crate::device::{Device, WireUnit};
use crate::noise::RangeNoise;
use crate::world::{PoseSource, Scanner, World};

/// Longest command line (without terminator) the emulator buffers.
pub const MAX_LINE: usize = 16;

const NS_PER_SEC: u64 = 1_000_000_000;
const NS_PER_MS: u64 = 1_000_000;
/// Azimuth units per revolution (degrees × 16).
const RAW_PER_REV: u128 = 360 * 16;

/// Settings of the emulated Sweep (deserializable from the simulator's config file).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepEmulatorConfig {
    /// Motor speed at power-on, Hz (0–10; larger values are clamped to 10).
    pub motor_hz: u8,
    /// Sample-rate code at power-on: 1 = 500–600 Hz, 2 = 750–800 Hz, 3 = 1000–1050 Hz
    /// (clamped into 1–3).
    pub sample_rate_code: u8,
    /// Simulated time the motor needs to settle after power-on, RR and MS, milliseconds.
    pub settle_ms: u64,
    /// Simulated time RR keeps the device deaf and mute, milliseconds.
    pub reboot_ms: u64,
    /// IV model field (5 characters).
    pub model: String,
    /// IV protocol version (2 characters).
    pub protocol_version: String,
    /// IV firmware version (2 characters).
    pub firmware_version: String,
    /// IV hardware version (1 character).
    pub hardware_version: String,
    /// IV serial number (8 characters).
    pub serial_number: String,
    /// Serial bit rate: reported by ID (6 digits) and sets the wire rate (8N1: bitrate / 10).
    pub bitrate: u32,
    /// Returns up to this range (m) are always reported.
    pub reliable_range_m: f64,
    /// Beyond `reliable_range_m` the chance of a return falls linearly to 0 at this range (m).
    pub max_return_range_m: f64,
}

impl Default for SweepEmulatorConfig {
    fn default() -> Self {
        Self {
            motor_hz: 5,
            sample_rate_code: 1,
            settle_ms: 6_000,
            reboot_ms: 1_000,
            model: "SWEEP".to_owned(),
            protocol_version: "01".to_owned(),
            firmware_version: "11".to_owned(),
            hardware_version: "1".to_owned(),
            serial_number: "00000001".to_owned(),
            bitrate: 115_200,
            reliable_range_m: 10.0,
            max_return_range_m: 40.0,
        }
    }
}

impl SweepEmulatorConfig {
    /// Probability that a true return at `range_m` reaches the host: 1 up to
    /// `reliable_range_m`, then linear down to 0 at `max_return_range_m`.
    pub fn return_probability(&self, range_m: f64) -> f64 {
        if range_m <= self.reliable_range_m {
            1.0
        } else if range_m >= self.max_return_range_m {
            0.0
        } else {
            (self.max_return_range_m - range_m) / (self.max_return_range_m - self.reliable_range_m)
        }
    }

    /// Signal strength (1–255) reported for a return at `range_m`: nearer is stronger.
    pub fn strength(&self, range_m: f64) -> u8 {
        let closeness = if self.max_return_range_m > 0.0 {
            (1.0 - range_m / self.max_return_range_m).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // In 1..=255 by construction, so the cast cannot truncate.
        (255.0 * closeness * closeness).round().clamp(1.0, 255.0) as u8
    }
}

/// The sample rate (Hz) blocks are paced at for a sample-rate code: the middle of its band.
pub fn sample_rate_hz(code: u8) -> u32 {
    match code {
        2 => 775,
        3 => 1025,
        _ => 550,
    }
}

/// The nominal rate (Hz) ID reports for a sample-rate code (the bottom of its band).
fn nominal_rate_hz(code: u8) -> u32 {
    match code {
        2 => 750,
        3 => 1000,
        _ => 500,
    }
}

/// An active DS stream.
#[derive(Debug, Clone)]
struct Stream {
    /// When DS was accepted.
    start_ns: u64,
    /// Blocks produced so far.
    produced: u64,
    /// Revolution number of the previous block, once there is one.
    prev_revolution: Option<u128>,
}

/// An emulated Scanse Sweep (see the [module docs](self) for its exact behaviour).
#[derive(Debug, Clone)]
pub struct SweepEmulator {
    config: SweepEmulatorConfig,
    scanner: Scanner,
    /// Where the sensor is at each block's sample time; `None`: fixed at `scanner.pose`.
    pose_source: Option<Arc<dyn PoseSource>>,
    rng: ChaCha8Rng,
    motor_hz: u8,
    rate_code: u8,
    /// The motor angle is 0 at this time (power-on, last MS, end of the last reboot).
    motor_ref_ns: u64,
    /// The motor is stable from this time on.
    settled_at_ns: u64,
    /// Rebooting (ignoring input) until this time.
    deaf_until_ns: u64,
    stream: Option<Stream>,
    line: Vec<u8>,
    line_overflow: bool,
    pending: Vec<WireUnit>,
    last_ns: u64,
}

impl SweepEmulator {
    /// A Sweep powered on at simulated time 0, measuring with `scanner` (which carries the
    /// pose, the range limits and the noise), its randomness seeded by `seed`.
    pub fn new(config: SweepEmulatorConfig, scanner: Scanner, seed: u64) -> Self {
        let motor_hz = config.motor_hz.min(10);
        let rate_code = config.sample_rate_code.clamp(1, 3);
        let settled_at_ns = config.settle_ms.saturating_mul(NS_PER_MS);
        Self {
            config,
            scanner,
            pose_source: None,
            rng: ChaCha8Rng::seed_from_u64(seed),
            motor_hz,
            rate_code,
            motor_ref_ns: 0,
            settled_at_ns,
            deaf_until_ns: 0,
            stream: None,
            line: Vec::new(),
            line_overflow: false,
            pending: Vec::new(),
            last_ns: 0,
        }
    }

    /// The same Sweep, but measuring from `source.pose_at(t)` for a block sampled at simulated
    /// time `t` (e.g. mounted on the turntable: [`crate::turntable::TurntableMount`]);
    /// `scanner.pose` is then unused. `source` must run on this emulator's time base (ns since
    /// power-on).
    pub fn with_pose_source(mut self, source: impl PoseSource + 'static) -> Self {
        self.pose_source = Some(Arc::new(source));
        self
    }

    /// A scanner with the Sweep's defaults: σ = [`RangeNoise::SWEEP`], 0.1–40 m.
    pub fn default_scanner(world: Arc<World>, pose: Isometry3<f64>) -> Scanner {
        Scanner {
            world,
            pose,
            noise: RangeNoise::SWEEP,
            min_range_m: 0.1,
            max_range_m: 40.0,
        }
    }

    /// Current motor speed code (Hz), as MI reports it.
    pub fn motor_hz(&self) -> u8 {
        self.motor_hz
    }

    /// Current sample-rate code (1–3), as LI reports it.
    pub fn sample_rate_code(&self) -> u8 {
        self.rate_code
    }

    /// Whether data blocks are being produced.
    pub fn is_streaming(&self) -> bool {
        self.stream.is_some()
    }

    /// Produces every data block due up to `now_ns` into `pending`.
    fn advance(&mut self, now_ns: u64) {
        let Some(stream) = self.stream.as_mut() else {
            return;
        };
        let rate = u128::from(sample_rate_hz(self.rate_code));
        let motor_hz = u128::from(self.motor_hz);
        loop {
            let offset = (u128::from(stream.produced) + 1) * u128::from(NS_PER_SEC) / rate;
            let t = u128::from(stream.start_ns) + offset;
            if t > u128::from(now_ns) {
                break;
            }
            stream.produced += 1;
            // Angle travelled since the motor reference, in azimuth units, rounded.
            let since_ref = t.saturating_sub(u128::from(self.motor_ref_ns));
            let total = (since_ref * motor_hz * RAW_PER_REV + u128::from(NS_PER_SEC / 2))
                / u128::from(NS_PER_SEC);
            let revolution = total / RAW_PER_REV;
            // < 5760, fits in u16.
            let raw = (total % RAW_PER_REV) as u16;
            let sync = stream.prev_revolution.is_some_and(|p| revolution > p);
            stream.prev_revolution = Some(revolution);

            let azimuth_rad = (f64::from(raw) / 16.0).to_radians();
            let pose = match &self.pose_source {
                Some(source) => source.pose_at(u64::try_from(t).unwrap_or(u64::MAX)),
                None => self.scanner.pose,
            };
            let range = self
                .scanner
                .measure_from(&pose, azimuth_rad, &mut self.rng)
                .filter(|&r| {
                    let p = self.config.return_probability(r);
                    p >= 1.0 || self.rng.random::<f64>() < p
                });
            let cm = range.map_or(0, |r| (r * 100.0).round().clamp(0.0, 65_535.0) as u16);
            let strength = match range {
                Some(r) if cm > 0 => self.config.strength(r),
                _ => 0,
            };
            self.pending.push(data_block(sync, raw, cm, strength));
        }
    }

    fn settled(&self, now_ns: u64) -> bool {
        now_ns >= self.settled_at_ns
    }

    fn push(&mut self, bytes: Vec<u8>) {
        self.pending.push(WireUnit {
            bytes,
            samples: Vec::new(),
        });
    }

    fn on_line(&mut self, now_ns: u64, line: &[u8]) {
        let [c1, c2, param @ ..] = line else { return };
        let cmd = [printable(*c1), printable(*c2)];
        match (&cmd, param.is_empty()) {
            (b"DS", true) => {
                let status = if self.stream.is_some() {
                    *b"00"
                } else if self.motor_hz == 0 {
                    *b"13"
                } else if !self.settled(now_ns) {
                    *b"12"
                } else {
                    self.stream = Some(Stream {
                        start_ns: now_ns,
                        produced: 0,
                        prev_revolution: None,
                    });
                    *b"00"
                };
                self.push(status_receipt(cmd, status));
            }
            (b"DX", true) => {
                self.stream = None;
                self.push(status_receipt(cmd, *b"00"));
            }
            (b"MZ", true) => {
                let v = if self.settled(now_ns) { 0 } else { 1 };
                self.push(info_receipt(cmd, format!("{v:02}").as_bytes()));
            }
            (b"MI", true) => self.push(info_receipt(
                cmd,
                format!("{:02}", self.motor_hz).as_bytes(),
            )),
            (b"LI", true) => self.push(info_receipt(
                cmd,
                format!("{:02}", self.rate_code).as_bytes(),
            )),
            (b"IV", true) => {
                let c = &self.config;
                let fields = [
                    fixed(&c.model, 5),
                    fixed(&c.protocol_version, 2),
                    fixed(&c.firmware_version, 2),
                    fixed(&c.hardware_version, 1),
                    fixed(&c.serial_number, 8),
                ]
                .concat();
                self.push(info_receipt(cmd, &fields));
            }
            (b"ID", true) => {
                let fields = format!(
                    "{:06}110{:02}{:04}",
                    self.config.bitrate % 1_000_000,
                    self.motor_hz,
                    nominal_rate_hz(self.rate_code)
                );
                self.push(info_receipt(cmd, fields.as_bytes()));
            }
            (b"RR", true) => {
                self.stream = None;
                self.deaf_until_ns =
                    now_ns.saturating_add(self.config.reboot_ms.saturating_mul(NS_PER_MS));
                self.motor_ref_ns = self.deaf_until_ns;
                self.settled_at_ns = self
                    .deaf_until_ns
                    .saturating_add(self.config.settle_ms.saturating_mul(NS_PER_MS));
                if self.motor_hz == 0 {
                    self.motor_hz = 5;
                }
            }
            (b"MS", _) => self.on_param(now_ns, cmd, param, 0..=10),
            (b"LR", _) => self.on_param(now_ns, cmd, param, 1..=3),
            _ => self.push(status_receipt(cmd, *b"11")),
        }
    }

    /// MS and LR: a two-digit parameter within `valid`.
    fn on_param(
        &mut self,
        now_ns: u64,
        cmd: [u8; 2],
        param: &[u8],
        valid: std::ops::RangeInclusive<u8>,
    ) {
        let [p1, p2] = *param else {
            self.push(status_receipt(cmd, *b"11"));
            return;
        };
        let echo = [printable(p1), printable(p2)];
        let value = (p1.is_ascii_digit() && p2.is_ascii_digit())
            .then(|| (p1 - b'0') * 10 + (p2 - b'0'))
            .filter(|v| valid.contains(v));
        let status = match value {
            None => *b"11",
            Some(_) if &cmd == b"MS" && !self.settled(now_ns) => *b"12",
            Some(v) => {
                self.stream = None;
                if &cmd == b"MS" {
                    self.motor_hz = v;
                    self.motor_ref_ns = now_ns;
                    self.settled_at_ns =
                        now_ns.saturating_add(self.config.settle_ms.saturating_mul(NS_PER_MS));
                } else {
                    self.rate_code = v;
                }
                *b"00"
            }
        };
        self.push(param_receipt(cmd, echo, status));
    }
}

impl Device for SweepEmulator {
    fn wire_bytes_per_sec(&self) -> f64 {
        f64::from(self.config.bitrate) / 10.0
    }

    fn on_host_bytes(&mut self, now_ns: u64, bytes: &[u8]) {
        let now_ns = now_ns.max(self.last_ns);
        self.last_ns = now_ns;
        self.advance(now_ns);
        for &b in bytes {
            if now_ns < self.deaf_until_ns {
                self.line.clear();
                self.line_overflow = false;
                return;
            }
            match b {
                b'\r' | b'\n' => {
                    let line = std::mem::take(&mut self.line);
                    if !self.line_overflow {
                        self.on_line(now_ns, &line);
                    }
                    self.line_overflow = false;
                }
                _ if self.line.len() < MAX_LINE => self.line.push(b),
                _ => self.line_overflow = true,
            }
        }
    }

    fn on_connect(&mut self, _now_ns: u64) {
        self.line.clear();
        self.line_overflow = false;
    }

    fn on_disconnect(&mut self, _now_ns: u64) {
        self.line.clear();
        self.line_overflow = false;
    }

    fn poll_output(&mut self, now_ns: u64, out: &mut Vec<WireUnit>) {
        let now_ns = now_ns.max(self.last_ns);
        self.last_ns = now_ns;
        self.advance(now_ns);
        out.append(&mut self.pending);
    }
}

/// The receipt checksum character: `((S1 + S2) & 0x3F) + 0x30`.
fn status_sum(status: [u8; 2]) -> u8 {
    (status[0].wrapping_add(status[1]) & 0x3F) + 0x30
}

/// `C1 C2 S1 S2 SUM LF`.
fn status_receipt(cmd: [u8; 2], status: [u8; 2]) -> Vec<u8> {
    vec![
        cmd[0],
        cmd[1],
        status[0],
        status[1],
        status_sum(status),
        b'\n',
    ]
}

/// `C1 C2 P1 P2 LF S1 S2 SUM LF`.
fn param_receipt(cmd: [u8; 2], param: [u8; 2], status: [u8; 2]) -> Vec<u8> {
    vec![
        cmd[0],
        cmd[1],
        param[0],
        param[1],
        b'\n',
        status[0],
        status[1],
        status_sum(status),
        b'\n',
    ]
}

/// `C1 C2 <fields> LF`.
fn info_receipt(cmd: [u8; 2], fields: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(fields.len() + 3);
    v.extend_from_slice(&cmd);
    v.extend_from_slice(fields);
    v.push(b'\n');
    v
}

/// A 7-byte data block and the sample a correct decoder reports for it.
fn data_block(sync: bool, azimuth_raw: u16, distance_cm: u16, strength: u8) -> WireUnit {
    let [a0, a1] = azimuth_raw.to_le_bytes();
    let [d0, d1] = distance_cm.to_le_bytes();
    let head = [u8::from(sync), a0, a1, d0, d1, strength];
    let sum = head.iter().map(|&b| u32::from(b)).sum::<u32>() % 255;
    let mut bytes = head.to_vec();
    // < 255, fits in u8.
    bytes.push(sum as u8);
    WireUnit {
        bytes,
        samples: vec![RawSample {
            angle_deg: f32::from(azimuth_raw) / 16.0,
            range_m: f32::from(distance_cm) / 100.0,
            quality: strength,
            new_revolution: sync,
        }],
    }
}

/// The byte if it is printable ASCII, else `?`.
fn printable(b: u8) -> u8 {
    if b.is_ascii_graphic() { b } else { b'?' }
}

/// `s` fitted to `width` printable ASCII bytes: truncated, or left-padded with `0`.
fn fixed(s: &str, width: usize) -> Vec<u8> {
    let bytes: Vec<u8> = s.bytes().map(printable).take(width).collect();
    let mut v = vec![b'0'; width - bytes.len()];
    v.extend(bytes);
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    const S: u64 = 1_000_000_000;
    const MS: u64 = 1_000_000;

    /// A vertical scan plane (sensor x → world x, sensor y → world z) through the middle of the
    /// conference room at y = 3: every beam stays clear of the glass wall.
    fn vertical_pose() -> Isometry3<f64> {
        let rot = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2);
        Isometry3::from_parts(Translation3::new(4.0, 3.0, 1.5), rot)
    }

    fn exact_scanner() -> Scanner {
        let mut s =
            SweepEmulator::default_scanner(Arc::new(World::conference_room()), vertical_pose());
        s.noise = RangeNoise::NONE;
        s
    }

    fn emulator(settle_ms: u64) -> SweepEmulator {
        let config = SweepEmulatorConfig {
            settle_ms,
            ..SweepEmulatorConfig::default()
        };
        SweepEmulator::new(config, exact_scanner(), 1)
    }

    /// Sends `cmd` at `now` and returns everything output up to then, concatenated.
    fn send(dev: &mut SweepEmulator, now: u64, cmd: &[u8]) -> Vec<u8> {
        dev.on_host_bytes(now, cmd);
        let mut out = Vec::new();
        dev.poll_output(now, &mut out);
        out.into_iter().flat_map(|u| u.bytes).collect()
    }

    #[test]
    fn answers_dx_when_idle_and_accepts_all_terminators() {
        let mut dev = emulator(6_000);
        assert_eq!(send(&mut dev, 0, b"DX\n"), b"DX00P\n");
        assert_eq!(send(&mut dev, MS, b"DX\r"), b"DX00P\n");
        assert_eq!(send(&mut dev, 2 * MS, b"DX\r\n"), b"DX00P\n");
        assert_eq!(send(&mut dev, 3 * MS, b"MI\r\nLI\n"), b"MI05\nLI01\n");
        // A command split over two writes.
        assert_eq!(send(&mut dev, 4 * MS, b"M"), b"");
        assert_eq!(send(&mut dev, 5 * MS, b"I\n"), b"MI05\n");
    }

    #[test]
    fn version_and_device_info() {
        let mut dev = emulator(0);
        // libsweep's layout: model(5) protocol(2) firmware(2) hardware(1) serial(8) LF = 21 bytes.
        assert_eq!(send(&mut dev, 0, b"IV\n"), b"IVSWEEP0111100000001\n");
        assert_eq!(send(&mut dev, 0, b"ID\n"), b"ID115200110050500\n");
        assert_eq!(send(&mut dev, 0, b"LR03\n"), b"LR03\n00P\n");
        assert_eq!(send(&mut dev, 0, b"MS10\n"), b"MS10\n00P\n");
        assert_eq!(send(&mut dev, 0, b"ID\n"), b"ID115200110101000\n");
        let custom = SweepEmulatorConfig {
            serial_number: "1234".to_owned(),
            firmware_version: "17".to_owned(),
            ..SweepEmulatorConfig::default()
        };
        let mut dev = SweepEmulator::new(custom, exact_scanner(), 1);
        assert_eq!(send(&mut dev, 0, b"IV\n"), b"IVSWEEP0117100001234\n");
    }

    #[test]
    fn settle_timing_gates_ds() {
        let mut dev = emulator(6_000);
        assert_eq!(send(&mut dev, 0, b"MZ\n"), b"MZ01\n");
        assert_eq!(send(&mut dev, 5_999 * MS, b"DS\n"), b"DS12S\n");
        assert!(!dev.is_streaming());
        assert_eq!(send(&mut dev, 6 * S, b"MZ\n"), b"MZ00\n");
        assert_eq!(send(&mut dev, 6 * S, b"DS\n"), b"DS00P\n");
        assert!(dev.is_streaming());
    }

    #[test]
    fn motor_speed_command() {
        let mut dev = emulator(1_000);
        // Refused while settling, nothing changes.
        assert_eq!(send(&mut dev, 0, b"MS03\n"), b"MS03\n12S\n");
        assert_eq!(send(&mut dev, 0, b"MI\n"), b"MI05\n");
        assert_eq!(send(&mut dev, S, b"MS07\n"), b"MS07\n00P\n");
        assert_eq!(send(&mut dev, S, b"MI\n"), b"MI07\n");
        // MS restarts settling.
        assert_eq!(send(&mut dev, S + 999 * MS, b"MZ\n"), b"MZ01\n");
        assert_eq!(send(&mut dev, 2 * S, b"MZ\n"), b"MZ00\n");
        // Validation.
        assert_eq!(send(&mut dev, 2 * S, b"MS11\n"), b"MS11\n11R\n");
        assert_eq!(send(&mut dev, 2 * S, b"MSab\n"), b"MSab\n11R\n");
        assert_eq!(send(&mut dev, 2 * S, b"MS5\n"), b"MS11R\n");
        assert_eq!(send(&mut dev, 2 * S, b"MS\n"), b"MS11R\n");
        assert_eq!(send(&mut dev, 2 * S, b"MI\n"), b"MI07\n");
        // 0 Hz: settles, then DS says the motor is stopped.
        assert_eq!(send(&mut dev, 2 * S, b"MS00\n"), b"MS00\n00P\n");
        assert_eq!(send(&mut dev, 3 * S, b"MZ\n"), b"MZ00\n");
        assert_eq!(send(&mut dev, 3 * S, b"DS\n"), b"DS13T\n");
        assert!(!dev.is_streaming());
    }

    #[test]
    fn sample_rate_command() {
        let mut dev = emulator(0);
        assert_eq!(send(&mut dev, 0, b"LR02\n"), b"LR02\n00P\n");
        assert_eq!(send(&mut dev, 0, b"LI\n"), b"LI02\n");
        for bad in [&b"LR04\n"[..], b"LR00\n", b"LR1x\n"] {
            let mut want = bad[..4].to_vec();
            want.extend_from_slice(b"\n11R\n");
            assert_eq!(send(&mut dev, 0, bad), want);
        }
        assert_eq!(send(&mut dev, 0, b"LR2\n"), b"LR11R\n");
        assert_eq!(send(&mut dev, 0, b"LI\n"), b"LI02\n");
    }

    #[test]
    fn unknown_and_malformed_commands_get_status_11() {
        let mut dev = emulator(0);
        assert_eq!(send(&mut dev, 0, b"XY\n"), b"XY11R\n");
        assert_eq!(send(&mut dev, 0, b"LV\n"), b"LV11R\n");
        assert_eq!(send(&mut dev, 0, b"DS07\n"), b"DS11R\n");
        assert_eq!(send(&mut dev, 0, b"\x01\xffZ\n"), b"??11R\n");
        // One-byte lines and over-long lines are dropped.
        assert_eq!(send(&mut dev, 0, b"D\n"), b"");
        assert_eq!(send(&mut dev, 0, b"MIMIMIMIMIMIMIMIMIMI\nMI\n"), b"MI05\n");
        assert!(!dev.is_streaming());
    }

    #[test]
    fn reboot_is_silent_then_settles_and_keeps_settings() {
        let config = SweepEmulatorConfig {
            settle_ms: 500,
            reboot_ms: 200,
            ..Default::default()
        };
        let mut dev = SweepEmulator::new(config, exact_scanner(), 1);
        assert_eq!(send(&mut dev, S, b"LR02\n"), b"LR02\n00P\n");
        assert_eq!(send(&mut dev, S, b"MS00\n"), b"MS00\n00P\n");
        // RR: no receipt; the rest of the write and anything during the reboot is ignored.
        assert_eq!(send(&mut dev, 2 * S, b"RR\nMI\n"), b"");
        assert_eq!(send(&mut dev, 2 * S + 199 * MS, b"MI\n"), b"");
        assert_eq!(send(&mut dev, 2 * S + 200 * MS, b"MZ\n"), b"MZ01\n");
        // Sample rate kept; speed 0 came back as 5.
        assert_eq!(
            send(&mut dev, 2 * S + 200 * MS, b"LI\nMI\n"),
            b"LI02\nMI05\n"
        );
        assert_eq!(send(&mut dev, 2 * S + 700 * MS, b"MZ\n"), b"MZ00\n");
    }

    /// Decodes a block by hand per lidar-protocols.md §2.4, checking its checksum.
    fn decode(b: &[u8]) -> (bool, u16, u16, u8) {
        assert_eq!(b.len(), 7);
        let sum: u32 = b[..6].iter().map(|&x| u32::from(x)).sum();
        assert_eq!(u32::from(b[6]), sum % 255, "checksum of {b:02x?}");
        assert_eq!(b[0] & 0xFE, 0, "error bits set");
        (
            b[0] & 1 == 1,
            u16::from(b[1]) | u16::from(b[2]) << 8,
            u16::from(b[3]) | u16::from(b[4]) << 8,
            b[5],
        )
    }

    #[test]
    fn block_encoding_matches_the_notes_example() {
        // lidar-protocols.md §2.4: `01 A0 05 FA 00 C8 6A` = sync, 90.0°, 250 cm, strength 200.
        let unit = data_block(true, 0x05A0, 250, 200);
        assert_eq!(unit.bytes, [0x01, 0xA0, 0x05, 0xFA, 0x00, 0xC8, 0x6A]);
        assert_eq!(
            unit.samples,
            [RawSample {
                angle_deg: 90.0,
                range_m: 2.5,
                quality: 200,
                new_revolution: true
            }]
        );
    }

    /// Streams for `seconds` after settling and returns the data units, checking that the
    /// first output is the DS receipt.
    fn stream(dev: &mut SweepEmulator, start: u64, seconds: u64) -> Vec<WireUnit> {
        dev.on_host_bytes(start, b"DS\n");
        let mut out = Vec::new();
        for k in 1..=seconds {
            dev.poll_output(start + k * S, &mut out);
        }
        assert_eq!(
            out.first().map(|u| u.bytes.as_slice()),
            Some(&b"DS00P\n"[..])
        );
        out.remove(0);
        out
    }

    #[test]
    fn block_stream_rate_sync_and_geometry() {
        for (code, rate) in [(1u8, 550usize), (2, 775), (3, 1025)] {
            let mut dev = emulator(0);
            let cmd = format!("LR{code:02}\n");
            assert_eq!(
                send(&mut dev, 0, cmd.as_bytes()),
                format!("LR{code:02}\n00P\n").as_bytes()
            );
            let blocks = stream(&mut dev, 0, 2);
            assert_eq!(blocks.len(), 2 * rate, "code {code}");
            let mut syncs = 0;
            let mut prev_raw: Option<u16> = None;
            let reference = exact_scanner();
            let mut rng = ChaCha8Rng::seed_from_u64(99);
            for unit in &blocks {
                let (sync, raw, cm, strength) = decode(&unit.bytes);
                assert!(raw < 5760);
                assert_eq!(
                    unit.samples,
                    [RawSample {
                        angle_deg: f32::from(raw) / 16.0,
                        range_m: f32::from(cm) / 100.0,
                        quality: strength,
                        new_revolution: sync,
                    }]
                );
                // Counter-clockwise at 5 Hz: raw advances 5760 · 5 / rate per block.
                if let Some(p) = prev_raw {
                    let step = (i32::from(raw) - i32::from(p)).rem_euclid(5760);
                    let want = 5760.0 * 5.0 / rate as f64;
                    assert!(
                        (f64::from(step) - want).abs() <= 1.0,
                        "step {step}, want {want}"
                    );
                    assert_eq!(sync, raw < p, "sync exactly on the wrap ({p} → {raw})");
                }
                prev_raw = Some(raw);
                syncs += usize::from(sync);
                // The room is closed and ≤ 10 m away: every beam returns its exact range.
                let want = reference.measure((f64::from(raw) / 16.0).to_radians(), &mut rng);
                let want_cm = want.map(|r| (r * 100.0).round() as u16);
                assert_eq!(Some(cm), want_cm, "azimuth {}", f64::from(raw) / 16.0);
                assert!(strength > 0);
            }
            // 5 revolutions per second; the first block of the stream is not a sync.
            assert!((9..=10).contains(&syncs), "syncs {syncs}");
        }
    }

    #[test]
    fn distances_match_hand_geometry() {
        // Straight up from z = 1.5 to the ceiling at 3.0; straight down to the table top at 0.75;
        // along +x to the east wall at x = 8 (4 m); along −x to the west wall (4 m).
        let mut dev = emulator(0);
        let blocks = stream(&mut dev, 0, 1);
        let near = |deg: f64| {
            blocks
                .iter()
                .map(|u| decode(&u.bytes))
                .min_by_key(|&(_, raw, _, _)| {
                    let d = (f64::from(raw) / 16.0 - deg).rem_euclid(360.0);
                    (d.min(360.0 - d) * 1000.0) as u64
                })
                .map(|(_, raw, cm, _)| (f64::from(raw) / 16.0, cm))
        };
        for (deg, range) in [(90.0, 1.5), (270.0, 0.75), (0.0, 4.0), (180.0, 4.0)] {
            let (got_deg, cm) = near(deg).expect("blocks were produced");
            // Within ±1.7° of the axis (one block step at 550 Hz is 3.3°), the range differs
            // from the on-axis one by a factor 1/cos ≤ 1.0005.
            assert!(
                ((got_deg - deg + 180.0).rem_euclid(360.0) - 180.0).abs() <= 1.7,
                "{got_deg}"
            );
            let want = range * 100.0 / (got_deg - deg).to_radians().cos();
            assert!(
                (f64::from(cm) - want).abs() <= 0.5 + 1e-9,
                "{deg}°: {cm} cm, want {want}"
            );
        }
    }

    #[test]
    fn blocks_are_paced_at_their_own_sample_times() {
        let mut dev = emulator(0);
        dev.on_host_bytes(0, b"DS\n");
        let mut out = Vec::new();
        // 550 Hz: block k is due at k / 550 s. At 10 ms, blocks 1..=5 (≤ 9.09 ms) are out.
        dev.poll_output(10 * MS, &mut out);
        assert_eq!(out.len(), 1 + 5);
        dev.poll_output(10 * MS, &mut out);
        assert_eq!(out.len(), 1 + 5);
        // Block 6 is due at ⌊6e9 / 550⌋ ns = 10 909 090 ns.
        dev.poll_output(10_909_089, &mut out);
        assert_eq!(out.len(), 1 + 5);
        dev.poll_output(10_909_090, &mut out);
        assert_eq!(out.len(), 1 + 6);
    }

    #[test]
    fn dx_stops_the_stream_after_blocks_already_due() {
        let mut dev = emulator(0);
        let mut out = Vec::new();
        dev.on_host_bytes(0, b"DS\n");
        dev.poll_output(100 * MS, &mut out);
        let before = out.len();
        dev.on_host_bytes(200 * MS, b"DX\n");
        dev.poll_output(S, &mut out);
        // 55 blocks due up to 100 ms, another 55 by 200 ms, then the receipt and nothing more.
        assert_eq!(before, 1 + 55);
        assert_eq!(out.len(), 1 + 110 + 1);
        assert_eq!(
            out.last().map(|u| u.bytes.as_slice()),
            Some(&b"DX00P\n"[..])
        );
        assert!(
            out[1..111]
                .iter()
                .all(|u| u.bytes.len() == 7 && u.samples.len() == 1)
        );
    }

    #[test]
    fn streaming_survives_host_reconnects_and_settings_persist() {
        let mut dev = emulator(0);
        assert_eq!(send(&mut dev, 0, b"MS07\n"), b"MS07\n00P\n");
        let mut out = Vec::new();
        dev.on_host_bytes(0, b"DS\n");
        dev.poll_output(S, &mut out);
        dev.on_disconnect(S);
        // A half-written command from the old host is forgotten.
        dev.on_host_bytes(S, b"M");
        dev.on_connect(2 * S);
        dev.poll_output(3 * S, &mut out);
        assert_eq!(out.len(), 1 + 3 * 550);
        let raws: Vec<u16> = out[1..].iter().map(|u| decode(&u.bytes).1).collect();
        // Continuous rotation at 7 Hz across the reconnect: 5760 · 7 / 550 ≈ 73.3 per block.
        for w in raws.windows(2) {
            let step = (i32::from(w[1]) - i32::from(w[0])).rem_euclid(5760);
            assert!((73..=74).contains(&step), "step {step}");
        }
        // The old host's stray "M" was dropped on reconnect, so "I" alone is ignored.
        assert!(send(&mut dev, 3 * S, b"I\n").is_empty());
        assert_eq!(send(&mut dev, 3 * S, b"DX\nMI\n"), b"DX00P\nMI07\n");
    }

    #[test]
    fn far_returns_fall_off_beyond_ten_metres() {
        let c = SweepEmulatorConfig::default();
        assert_eq!(c.return_probability(9.99), 1.0);
        assert_eq!(c.return_probability(10.0), 1.0);
        assert!((c.return_probability(25.0) - 0.5).abs() < 1e-12);
        assert_eq!(c.return_probability(40.0), 0.0);
        assert_eq!(c.return_probability(55.0), 0.0);
        assert!(c.strength(0.5) > c.strength(4.0) && c.strength(4.0) > c.strength(30.0));
        assert_eq!(c.strength(0.0), 255);
        assert_eq!(c.strength(40.0), 1);

        // A long hall: a wall 25 m ahead of a flat scanner. Beams within ±2° (about one per
        // revolution, 1000 revolutions) see it at 25.0–25.02 m; about half of them come back
        // (standard error of the fraction ≈ 0.016).
        let wall = crate::world::Primitive {
            name: "far_wall".to_owned(),
            shape: crate::world::Shape::Box(crate::world::Aabb::new(
                [25.0, -5.0, -5.0],
                [26.0, 5.0, 5.0],
            )),
            material: crate::world::Material::Opaque,
        };
        let world = World::new(
            crate::world::Aabb::new([0.0; 3], [25.0, 1.0, 1.0]),
            vec![wall],
        );
        let world = Arc::new(world.expect("a valid world"));
        let mut scanner = SweepEmulator::default_scanner(world, Isometry3::identity());
        scanner.noise = RangeNoise::NONE;
        let mut dev = SweepEmulator::new(SweepEmulatorConfig { settle_ms: 0, ..c }, scanner, 3);
        let blocks = stream(&mut dev, 0, 200);
        let ahead: Vec<u16> = blocks
            .iter()
            .map(|u| decode(&u.bytes))
            .filter(|&(_, raw, _, _)| !(32..5728).contains(&raw))
            .map(|(_, _, cm, _)| cm)
            .collect();
        let returned = ahead.iter().filter(|&&cm| cm > 0).count() as f64 / ahead.len() as f64;
        assert!(ahead.len() >= 1000, "{}", ahead.len());
        assert!(
            (returned - 0.5).abs() < 0.05,
            "returned fraction {returned}"
        );
        assert!(
            ahead
                .iter()
                .all(|&cm| cm == 0 || (2500..=2502).contains(&cm))
        );
    }

    #[test]
    fn wire_rate_is_115200_8n1() {
        assert_eq!(emulator(0).wire_bytes_per_sec(), 11_520.0);
    }
}
