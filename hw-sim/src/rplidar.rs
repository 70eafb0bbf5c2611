//! Slamtec RPLidar A1/A2 emulator: the binary request/response protocol, standard scan nodes
//! and legacy express capsules (research notes `lidar-protocols.md` §1, checklist §3.4).
//!
//! A pure state machine ([`Device`]): host bytes and simulated time in, wire units out. What it
//! models:
//! - GET_INFO / GET_HEALTH / GET_SAMPLERATE, GET_LIDAR_CONF (fw ≥ 1.24) with two scan modes,
//!   Standard (0x81) and Express (0x82, typical), GET_ACC_BOARD_FLAG and SET_MOTOR_PWM on A2;
//! - SCAN / FORCE_SCAN / legacy EXPRESS_SCAN streams: the descriptor at once, samples once the
//!   motor is on and (except FORCE_SCAN) has spun up; any request the model knows ends a stream;
//!   streams survive client reconnects, like the real device;
//! - RESET: a text banner, then ~0.5 s of deafness;
//! - requests are validated by checksum; bad or unknown ones are ignored.
//!
//! Angles are clockwise seen from above (device convention): a sample reported at θ degrees was
//! measured with the [`Scanner`] at sensor azimuth α = −θ.
//!
//! Motor: an A1's motor is switched by DTR, which a pty cannot carry, so the A1 spins from
//! power-on; an A2 spins only while the last SET_MOTOR_PWM value is > 0.

use std::collections::VecDeque;
use std::sync::Arc;

use nalgebra::Isometry3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scan3d_edge::lidar::RawSample;
use tracing::debug;

use crate::device::{Device, WireUnit};
use crate::noise::RangeNoise;
use crate::world::{PoseSource, Scanner, World};

/// Which RPLidar the emulator pretends to be.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RplidarModel {
    /// A1M8: model byte 0x18, motor on DTR (always spinning here).
    #[default]
    A1,
    /// A2M8: model byte 0x28, motor on SET_MOTOR_PWM, answers GET_ACC_BOARD_FLAG.
    A2,
}

impl RplidarModel {
    /// The GET_INFO model byte (major in the high nibble).
    pub fn model_byte(self) -> u8 {
        match self {
            Self::A1 => 0x18,
            Self::A2 => 0x28,
        }
    }
}

/// What the emulated device reports and how it behaves.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(default)]
pub struct RplidarEmulatorConfig {
    /// A1 or A2.
    pub model: RplidarModel,
    /// Firmware major version (GET_INFO byte 2).
    pub firmware_major: u8,
    /// Firmware minor version (GET_INFO byte 1); GET_LIDAR_CONF needs ≥ 1.24.
    pub firmware_minor: u8,
    /// Hardware revision.
    pub hardware: u8,
    /// The 16 serial-number bytes.
    pub serial: [u8; 16],
    /// Line rate (115200 or 256000); the wire carries baud / 10 bytes per second.
    pub baud: u32,
    /// Simulated seconds from motor start until SCAN / EXPRESS samples flow.
    pub spinup_s: f64,
    /// GET_HEALTH status (0 good, 1 warning, 2 error).
    pub health_status: u8,
    /// GET_HEALTH error code.
    pub health_error_code: u16,
    /// Revolutions per second.
    pub rotation_hz: f64,
    /// Standard-mode sample period, µs (the wire may make it longer: 5 bytes per sample).
    pub standard_sample_us: u16,
    /// Express-mode sample period, µs (the wire may make it longer: 84 bytes per 32 samples).
    pub express_sample_us: u16,
    /// Simulated seconds the device ignores requests after RESET.
    pub reset_silence_s: f64,
}

impl Default for RplidarEmulatorConfig {
    fn default() -> Self {
        Self {
            model: RplidarModel::A1,
            firmware_major: 1,
            firmware_minor: 29,
            hardware: 7,
            serial: *b"scan3d-rplidar-1",
            baud: 115_200,
            spinup_s: 1.5,
            health_status: 0,
            health_error_code: 0,
            rotation_hz: 5.5,
            standard_sample_us: 500,
            express_sample_us: 250,
            reset_silence_s: 0.5,
        }
    }
}

/// A configuration value the emulator cannot work with.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RplidarConfigError {
    /// The baud rate is zero.
    #[error("baud rate must be positive")]
    Baud,
    /// The rotation rate is not a positive number.
    #[error("rotation rate must be a positive number of Hz, got {0}")]
    Rotation(f64),
    /// A sample period is zero.
    #[error("sample periods must be positive")]
    SamplePeriod,
    /// A duration is negative or not a number.
    #[error("{0} must be a non-negative number of seconds")]
    Duration(&'static str),
}

impl RplidarEmulatorConfig {
    /// Checks that the values make sense (the emulator clamps them anyway, so it never panics).
    pub fn validate(&self) -> Result<(), RplidarConfigError> {
        if self.baud == 0 {
            return Err(RplidarConfigError::Baud);
        }
        if !(self.rotation_hz.is_finite() && self.rotation_hz > 0.0) {
            return Err(RplidarConfigError::Rotation(self.rotation_hz));
        }
        if self.standard_sample_us == 0 || self.express_sample_us == 0 {
            return Err(RplidarConfigError::SamplePeriod);
        }
        for (name, v) in [
            ("spinup_s", self.spinup_s),
            ("reset_silence_s", self.reset_silence_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(RplidarConfigError::Duration(name));
            }
        }
        Ok(())
    }

    /// The ASCII banner printed after RESET, e.g.
    /// `RP LIDAR System.\r\nFirmware Ver 1.29 - rc2, HW Ver 7\r\nModel: 24\r\n`.
    pub fn reset_banner(&self) -> String {
        format!(
            "RP LIDAR System.\r\nFirmware Ver {}.{:02} - rc2, HW Ver {}\r\nModel: {}\r\n",
            self.firmware_major,
            self.firmware_minor,
            self.hardware,
            self.model.model_byte()
        )
    }
}

/// Shortest range an RPLidar A1/A2 reports, metres.
pub const MIN_RANGE_M: f64 = 0.15;
/// Longest range an RPLidar A1/A2 reports, metres (also GET_LIDAR_CONF max distance).
pub const MAX_RANGE_M: f64 = 12.0;

// Commands (lidar-protocols.md §1.4).
const CMD_STOP: u8 = 0x25;
const CMD_RESET: u8 = 0x40;
const CMD_SCAN: u8 = 0x20;
const CMD_FORCE_SCAN: u8 = 0x21;
const CMD_EXPRESS_SCAN: u8 = 0x82;
const CMD_GET_INFO: u8 = 0x50;
const CMD_GET_HEALTH: u8 = 0x52;
const CMD_GET_SAMPLERATE: u8 = 0x59;
const CMD_GET_LIDAR_CONF: u8 = 0x84;
const CMD_SET_MOTOR_PWM: u8 = 0xF0;
const CMD_GET_ACC_BOARD_FLAG: u8 = 0xFF;

// Answer types.
const ANS_INFO: u8 = 0x04;
const ANS_HEALTH: u8 = 0x06;
const ANS_SAMPLERATE: u8 = 0x15;
const ANS_LIDAR_CONF: u8 = 0x20;
const ANS_MEASUREMENT: u8 = 0x81;
const ANS_CAPSULED: u8 = 0x82;
const ANS_ACC_BOARD_FLAG: u8 = 0xFF;

/// Full circle in q6 degrees.
const FULL_Q6: u32 = 360 * 64;
/// Requests must be complete within this long (manual: 5 s).
const REQUEST_TIMEOUT_NS: u64 = 5_000_000_000;
/// PWM reference value reported by GET_LIDAR_CONF 0x01 (what clients send to start the motor).
const PWM_REF: u16 = 660;
/// Samples per express capsule.
const CAPSULE_SAMPLES: u64 = 32;

/// Which scan stream is running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StreamKind {
    Standard,
    Express,
}

/// A running scan stream.
#[derive(Debug, Clone)]
struct Stream {
    kind: StreamKind,
    /// Time of the first sample, `None` while the motor is off (no samples ever flow).
    t0_ns: Option<u64>,
    period_ns: u64,
    /// Standard: nodes emitted; express: capsules emitted.
    emitted: u64,
    /// The previous sample's reported angle (for the new-revolution flag).
    prev_angle: Option<f64>,
    /// The express angle-offset random walk (0..=31, unsigned q3 degrees).
    dtheta: u8,
}

/// The RPLidar A1/A2 emulator.
#[derive(Debug, Clone)]
pub struct RplidarEmulator {
    config: RplidarEmulatorConfig,
    scanner: Scanner,
    /// Where the sensor is at each sample's time; `None`: fixed at `scanner.pose`.
    pose_source: Option<Arc<dyn PoseSource>>,
    rng: ChaCha8Rng,
    rx: Vec<u8>,
    rx_started_ns: u64,
    out: VecDeque<WireUnit>,
    motor_on_since_ns: Option<u64>,
    stream: Option<Stream>,
    deaf_until_ns: u64,
}

impl RplidarEmulator {
    /// An emulator measuring with `scanner`, drawing noise and angle offsets from `seed`.
    pub fn new(config: RplidarEmulatorConfig, scanner: Scanner, seed: u64) -> Self {
        let motor_on_since_ns = match config.model {
            RplidarModel::A1 => Some(0),
            RplidarModel::A2 => None,
        };
        Self {
            config,
            scanner,
            pose_source: None,
            rng: ChaCha8Rng::seed_from_u64(seed),
            rx: Vec::new(),
            rx_started_ns: 0,
            out: VecDeque::new(),
            motor_on_since_ns,
            stream: None,
            deaf_until_ns: 0,
        }
    }

    /// The same RPLidar, but measuring from `source.pose_at(t)` for a sample taken at simulated
    /// time `t` (e.g. on a moving trolley: [`crate::trolley::OnBase`]); `scanner.pose` is then
    /// unused. `source` must run on this emulator's time base (ns since power-on).
    pub fn with_pose_source(mut self, source: impl PoseSource + 'static) -> Self {
        self.pose_source = Some(Arc::new(source));
        self
    }

    /// A [`Scanner`] with RPLidar defaults: [`RangeNoise::RPLIDAR`], [`MIN_RANGE_M`]–[`MAX_RANGE_M`].
    pub fn default_scanner(world: Arc<World>, pose: Isometry3<f64>) -> Scanner {
        Scanner {
            world,
            pose,
            noise: RangeNoise::RPLIDAR,
            min_range_m: MIN_RANGE_M,
            max_range_m: MAX_RANGE_M,
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &RplidarEmulatorConfig {
        &self.config
    }

    /// True while a scan stream (standard or express) is running.
    pub fn is_scanning(&self) -> bool {
        self.stream.is_some()
    }

    /// Nanoseconds one wire byte takes (8N1).
    fn byte_ns(&self) -> f64 {
        1e10 / f64::from(self.config.baud.max(1))
    }

    /// The sample period of a stream kind: the configured one, or longer if the wire is slower.
    fn period_ns(&self, kind: StreamKind) -> u64 {
        let (configured_us, bytes_per_sample) = match kind {
            StreamKind::Standard => (self.config.standard_sample_us, 5.0),
            StreamKind::Express => (self.config.express_sample_us, 84.0 / CAPSULE_SAMPLES as f64),
        };
        let wire = (self.byte_ns() * bytes_per_sample).ceil() as u64;
        (u64::from(configured_us.max(1)) * 1000).max(wire)
    }

    /// The rotor angle (degrees, clockwise, in `[0, 360)`) at `t_ns`, given the motor start.
    fn rotor_angle_deg(&self, motor_on_ns: u64, t_ns: u64) -> f64 {
        let secs = t_ns.saturating_sub(motor_on_ns) as f64 * 1e-9;
        let hz = if self.config.rotation_hz > 0.0 {
            self.config.rotation_hz
        } else {
            1.0
        };
        ((secs * hz).fract() * 360.0).rem_euclid(360.0)
    }

    /// The rotor angle rounded to q6, in `[0, 360·64)`.
    fn rotor_angle_q6(&self, motor_on_ns: u64, t_ns: u64) -> u32 {
        ((self.rotor_angle_deg(motor_on_ns, t_ns) * 64.0).round() as u32) % FULL_Q6
    }

    /// Measures at the device angle `theta_deg` (clockwise) at simulated time `t_ns`: range in
    /// metres, or `None`.
    fn measure(&mut self, theta_deg: f64, t_ns: u64) -> Option<f64> {
        let pose = match &self.pose_source {
            Some(source) => source.pose_at(t_ns),
            None => self.scanner.pose,
        };
        self.scanner
            .measure_from(&pose, -theta_deg.to_radians(), &mut self.rng)
    }

    fn start_stream(&mut self, now_ns: u64, kind: StreamKind, wait_for_spinup: bool) {
        let spinup_ns = if wait_for_spinup {
            (self.config.spinup_s.max(0.0) * 1e9) as u64
        } else {
            0
        };
        let t0_ns = self
            .motor_on_since_ns
            .map(|on| now_ns.max(on.saturating_add(spinup_ns)));
        let dtheta = self.rng.random_range(0..32u8);
        self.stream = Some(Stream {
            kind,
            t0_ns,
            period_ns: self.period_ns(kind),
            emitted: 0,
            prev_angle: None,
            dtheta,
        });
    }

    /// Appends to `self.out` every stream unit whose last sample is measured by `now_ns`.
    fn generate(&mut self, now_ns: u64) {
        let Some(mut stream) = self.stream.take() else {
            return;
        };
        if let (Some(t0), Some(motor_on)) = (stream.t0_ns, self.motor_on_since_ns) {
            loop {
                match stream.kind {
                    StreamKind::Standard => {
                        let t = t0 + stream.emitted * stream.period_ns;
                        if t > now_ns {
                            break;
                        }
                        let unit = self.standard_node(&mut stream, motor_on, t);
                        self.out.push_back(unit);
                    }
                    StreamKind::Express => {
                        let span = CAPSULE_SAMPLES * stream.period_ns;
                        let t_start = t0 + stream.emitted * span;
                        if t_start + span > now_ns {
                            break;
                        }
                        let unit = self.express_capsule(&mut stream, motor_on, t_start, span);
                        self.out.push_back(unit);
                    }
                }
                stream.emitted += 1;
            }
        }
        self.stream = Some(stream);
    }

    /// One standard node measured at `t_ns` (§1.6).
    fn standard_node(&mut self, stream: &mut Stream, motor_on: u64, t_ns: u64) -> WireUnit {
        let angle_q6 = self.rotor_angle_q6(motor_on, t_ns);
        let angle = f64::from(angle_q6) / 64.0;
        let range = self.measure(angle, t_ns);
        let dist_q2 = range.map_or(0, |r| (r * 4000.0).round().clamp(0.0, 65535.0) as u16);
        let quality = if dist_q2 == 0 {
            0
        } else {
            quality_for(range.unwrap_or(0.0))
        };
        let start = stream.prev_angle.is_some_and(|p| angle < p);
        stream.prev_angle = Some(angle);
        let b0 = (quality << 2) | if start { 0b01 } else { 0b10 };
        let a = ((angle_q6 as u16) << 1) | 1;
        let [a0, a1] = a.to_le_bytes();
        let [d0, d1] = dist_q2.to_le_bytes();
        WireUnit {
            bytes: vec![b0, a0, a1, d0, d1],
            samples: vec![RawSample {
                angle_deg: f32::from(angle_q6 as u16) / 64.0,
                range_m: f32::from(dist_q2) / 4000.0,
                quality,
                new_revolution: start,
            }],
        }
    }

    /// One legacy express capsule (§1.7) whose 32 samples start at `t_start`.
    ///
    /// The capsule's start angle is ω_i (the rotor angle at `t_start`, q6) and the next
    /// capsule's is ω_{i+1} (at `t_start + span`). Sample k is reported, exactly as the decoder
    /// reconstructs it, at θ_k = ω_i + ((ω_{i+1} − ω_i) mod 360)·k/32 − dθ_k/8, wrapped into
    /// [0, 360); all terms are multiples of 1/2048°, so the value is exact in f32 and f64
    /// whatever the order of operations. The world is measured at that θ_k.
    ///
    /// dθ_k (6-bit field, kept in 0..=31) follows a random walk with steps −1, 0 or +1 (+1 only
    /// when one sample step exceeds 1/8°), so reported angles keep increasing between
    /// revolution wraps.
    ///
    /// `new_revolution` follows the edge driver's rule: a sample is the first of a revolution
    /// when its angle is smaller than the previous sample's. The header's S bit is set only on
    /// the first capsule of the stream.
    fn express_capsule(
        &mut self,
        stream: &mut Stream,
        motor_on: u64,
        t_start: u64,
        span: u64,
    ) -> WireUnit {
        let omega_q6 = self.rotor_angle_q6(motor_on, t_start);
        let next_q6 = self.rotor_angle_q6(motor_on, t_start + span);
        let diff_q6 = (next_q6 + FULL_Q6 - omega_q6) % FULL_Q6;
        let omega = f64::from(omega_q6) / 64.0;
        let diff = f64::from(diff_q6) / 64.0;
        let may_grow = diff / 32.0 > 0.125;

        let mut bytes = vec![0u8; 84];
        let header = (omega_q6 as u16) | if stream.emitted == 0 { 0x8000 } else { 0 };
        bytes[2..4].copy_from_slice(&header.to_le_bytes());
        let mut samples = Vec::with_capacity(CAPSULE_SAMPLES as usize);
        let mut cabin = [0u8; 5];
        for k in 0..CAPSULE_SAMPLES as usize {
            if k > 0 || stream.emitted > 0 {
                let step: i8 = match self.rng.random_range(0..3u8) {
                    0 => -1,
                    2 if may_grow => 1,
                    _ => 0,
                };
                stream.dtheta = stream.dtheta.saturating_add_signed(step).min(31);
            }
            let dtheta = stream.dtheta;
            let theta =
                (omega + diff * k as f64 / 32.0 - f64::from(dtheta) / 8.0).rem_euclid(360.0);
            let t_k = t_start + span * k as u64 / CAPSULE_SAMPLES;
            let dist_mm = self
                .measure(theta, t_k)
                .map_or(0u16, |r| (r * 1000.0).round().clamp(0.0, 16383.0) as u16);
            let start = stream.prev_angle.is_some_and(|p| theta < p);
            stream.prev_angle = Some(theta);
            samples.push(RawSample {
                angle_deg: theta as f32,
                range_m: f32::from(dist_mm) / 1000.0,
                quality: if dist_mm == 0 { 0 } else { 47 },
                new_revolution: start,
            });
            // Cabin layout: d1 (u16), d2 (u16), offsets (u8: dθ1[3:0] | dθ2[3:0] << 4).
            let field = (dist_mm << 2) | u16::from((dtheta >> 4) & 0b11);
            if k % 2 == 0 {
                cabin[0..2].copy_from_slice(&field.to_le_bytes());
                cabin[4] = dtheta & 0x0F;
            } else {
                cabin[2..4].copy_from_slice(&field.to_le_bytes());
                cabin[4] |= (dtheta & 0x0F) << 4;
                let at = 4 + (k / 2) * 5;
                bytes[at..at + 5].copy_from_slice(&cabin);
            }
        }
        let checksum = bytes[2..].iter().fold(0u8, |acc, b| acc ^ b);
        bytes[0] = 0xA0 | (checksum & 0x0F);
        bytes[1] = 0x50 | (checksum >> 4);
        WireUnit { bytes, samples }
    }

    fn answer(&mut self, answer_type: u8, data: &[u8]) {
        let mut bytes = descriptor(data.len() as u32, false, answer_type).to_vec();
        bytes.extend_from_slice(data);
        self.out.push_back(WireUnit {
            bytes,
            samples: Vec::new(),
        });
    }

    fn firmware_at_least(&self, major: u8, minor: u8) -> bool {
        (self.config.firmware_major, self.config.firmware_minor) >= (major, minor)
    }

    /// Parses and handles every complete request in the receive buffer.
    fn handle_requests(&mut self, now_ns: u64) {
        loop {
            let Some(start) = self.rx.iter().position(|&b| b == 0xA5) else {
                self.rx.clear();
                return;
            };
            self.rx.drain(..start);
            let Some(&cmd) = self.rx.get(1) else { return };
            if cmd & 0x80 == 0 {
                self.rx.drain(..2);
                self.handle_request(now_ns, cmd, &[]);
                continue;
            }
            let Some(&size) = self.rx.get(2) else { return };
            let total = 4 + usize::from(size);
            let Some(packet) = self.rx.get(..total) else {
                return;
            };
            let checksum = packet[..total - 1].iter().fold(0u8, |acc, b| acc ^ b);
            if checksum != packet[total - 1] {
                debug!(cmd, "request with a bad checksum ignored");
                self.rx.drain(..1);
                continue;
            }
            let payload = packet[3..total - 1].to_vec();
            self.rx.drain(..total);
            self.handle_request(now_ns, cmd, &payload);
        }
    }

    fn handle_request(&mut self, now_ns: u64, cmd: u8, payload: &[u8]) {
        let a2 = self.config.model == RplidarModel::A2;
        debug!(cmd = format_args!("{cmd:#04x}"), ?payload, "request");
        // An A1 does not know the A2's accessory-board commands: they change nothing.
        if !a2 && matches!(cmd, CMD_SET_MOTOR_PWM | CMD_GET_ACC_BOARD_FLAG) {
            return;
        }
        let known = matches!(
            cmd,
            CMD_STOP
                | CMD_RESET
                | CMD_SCAN
                | CMD_FORCE_SCAN
                | CMD_EXPRESS_SCAN
                | CMD_GET_INFO
                | CMD_GET_HEALTH
                | CMD_GET_SAMPLERATE
                | CMD_GET_LIDAR_CONF
                | CMD_SET_MOTOR_PWM
                | CMD_GET_ACC_BOARD_FLAG
        );
        if !known {
            debug!(cmd, "unknown command ignored");
            return;
        }
        // Any request ends a running stream (§1.2).
        self.stream = None;
        match cmd {
            CMD_STOP => {}
            CMD_RESET => {
                let banner = self.config.reset_banner().into_bytes();
                self.out.push_back(WireUnit {
                    bytes: banner,
                    samples: Vec::new(),
                });
                let silence = (self.config.reset_silence_s.max(0.0) * 1e9) as u64;
                self.deaf_until_ns = now_ns.saturating_add(silence);
                self.rx.clear();
            }
            CMD_SCAN | CMD_FORCE_SCAN => {
                self.out.push_back(WireUnit {
                    bytes: descriptor(5, true, ANS_MEASUREMENT).to_vec(),
                    samples: Vec::new(),
                });
                self.start_stream(now_ns, StreamKind::Standard, cmd == CMD_SCAN);
            }
            CMD_EXPRESS_SCAN => {
                // Legacy capsules only: working mode 0 (fw < 1.24 clients) or 1 ("Express").
                if payload.len() == 5 && matches!(payload.first(), Some(0 | 1)) {
                    self.out.push_back(WireUnit {
                        bytes: descriptor(84, true, ANS_CAPSULED).to_vec(),
                        samples: Vec::new(),
                    });
                    self.start_stream(now_ns, StreamKind::Express, true);
                } else {
                    debug!(?payload, "unsupported express scan request ignored");
                }
            }
            CMD_GET_INFO => {
                let c = &self.config;
                let mut data = vec![
                    c.model.model_byte(),
                    c.firmware_minor,
                    c.firmware_major,
                    c.hardware,
                ];
                data.extend_from_slice(&c.serial);
                self.answer(ANS_INFO, &data);
            }
            CMD_GET_HEALTH => {
                let [e0, e1] = self.config.health_error_code.to_le_bytes();
                self.answer(ANS_HEALTH, &[self.config.health_status, e0, e1]);
            }
            CMD_GET_SAMPLERATE => {
                let mut data = self.config.standard_sample_us.to_le_bytes().to_vec();
                data.extend_from_slice(&self.config.express_sample_us.to_le_bytes());
                self.answer(ANS_SAMPLERATE, &data);
            }
            // fw < 1.24 does not know GET_LIDAR_CONF: no answer.
            CMD_GET_LIDAR_CONF if self.firmware_at_least(1, 24) => self.lidar_conf(payload),
            CMD_SET_MOTOR_PWM => {
                if let [lo, hi] = payload {
                    let pwm = u16::from_le_bytes([*lo, *hi]);
                    match (pwm > 0, self.motor_on_since_ns) {
                        (true, None) => self.motor_on_since_ns = Some(now_ns),
                        (false, Some(_)) => self.motor_on_since_ns = None,
                        _ => {}
                    }
                }
            }
            CMD_GET_ACC_BOARD_FLAG => {
                // Bit 0: the motor speed is controlled by SET_MOTOR_PWM.
                self.answer(ANS_ACC_BOARD_FLAG, &1u32.to_le_bytes());
            }
            _ => {}
        }
    }

    /// GET_LIDAR_CONF: `u32 type [+ u16 scan_mode]` → `u32 type` echo + value. Unknown types
    /// and modes get no answer (the SDK then times out and uses its defaults).
    fn lidar_conf(&mut self, payload: &[u8]) {
        let Some(&[t0, t1, t2, t3]) = payload.get(..4) else {
            return;
        };
        let conf_type = u32::from_le_bytes([t0, t1, t2, t3]);
        let mode = match payload.get(4..6) {
            Some(&[m0, m1]) => Some(u16::from_le_bytes([m0, m1])),
            _ => None,
        };
        let mode_value = |standard: Vec<u8>, express: Vec<u8>| match mode.unwrap_or(0) {
            0 => Some(standard),
            1 => Some(express),
            _ => None,
        };
        let value: Option<Vec<u8>> = match conf_type {
            0x70 => Some(2u16.to_le_bytes().to_vec()),
            0x71 => mode_value(
                (u32::from(self.config.standard_sample_us) << 8)
                    .to_le_bytes()
                    .to_vec(),
                (u32::from(self.config.express_sample_us) << 8)
                    .to_le_bytes()
                    .to_vec(),
            ),
            0x74 => {
                let q8 = (self.scanner.max_range_m.max(0.0) * 256.0).round() as u32;
                mode_value(q8.to_le_bytes().to_vec(), q8.to_le_bytes().to_vec())
            }
            0x75 => mode_value(vec![ANS_MEASUREMENT], vec![ANS_CAPSULED]),
            0x7C => Some(1u16.to_le_bytes().to_vec()),
            0x7F => mode_value(b"Standard\0".to_vec(), b"Express\0".to_vec()),
            0x01 => {
                let rpm = (self.config.rotation_hz * 60.0).round().clamp(0.0, 65535.0) as u16;
                let mut v = rpm.to_le_bytes().to_vec();
                v.extend_from_slice(&PWM_REF.to_le_bytes());
                Some(v)
            }
            _ => None,
        };
        match value {
            Some(value) => {
                let mut data = conf_type.to_le_bytes().to_vec();
                data.extend_from_slice(&value);
                self.answer(ANS_LIDAR_CONF, &data);
            }
            None => debug!(conf_type, ?mode, "GET_LIDAR_CONF type not answered"),
        }
    }
}

/// The 7-byte response descriptor (§1.3).
fn descriptor(len: u32, multiple: bool, answer_type: u8) -> [u8; 7] {
    let word = (len & 0x3FFF_FFFF) | if multiple { 1 << 30 } else { 0 };
    let [l0, l1, l2, l3] = word.to_le_bytes();
    [0xA5, 0x5A, l0, l1, l2, l3, answer_type]
}

/// Standard-node quality for a return at `range_m`: strong up close, weaker far away
/// (60 at 0 m, down 3 per metre, at least 10).
fn quality_for(range_m: f64) -> u8 {
    (60.0 - 3.0 * range_m).round().clamp(10.0, 60.0) as u8
}

impl Device for RplidarEmulator {
    fn wire_bytes_per_sec(&self) -> f64 {
        f64::from(self.config.baud) / 10.0
    }

    fn on_host_bytes(&mut self, now_ns: u64, bytes: &[u8]) {
        self.generate(now_ns);
        if now_ns < self.deaf_until_ns {
            debug!(n = bytes.len(), "bytes ignored while rebooting");
            return;
        }
        if !self.rx.is_empty() && now_ns.saturating_sub(self.rx_started_ns) > REQUEST_TIMEOUT_NS {
            self.rx.clear();
        }
        if self.rx.is_empty() {
            self.rx_started_ns = now_ns;
        }
        self.rx.extend_from_slice(bytes);
        self.handle_requests(now_ns);
        // Keep the buffer bounded whatever a client sends (no request is longer than 259 B).
        if self.rx.len() > 512 {
            let excess = self.rx.len() - 512;
            self.rx.drain(..excess);
        }
    }

    fn on_connect(&mut self, _now_ns: u64) {
        self.rx.clear();
    }

    fn on_disconnect(&mut self, _now_ns: u64) {
        self.rx.clear();
    }

    fn poll_output(&mut self, now_ns: u64, out: &mut Vec<WireUnit>) {
        self.generate(now_ns);
        out.extend(self.out.drain(..));
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Translation3;

    use super::*;

    const MS: u64 = 1_000_000;
    const S: u64 = 1_000_000_000;

    /// A bare 8 × 6 × 3 m room (walls only), so expected ranges follow from geometry.
    fn bare_room() -> Arc<World> {
        let toml = r#"
            [room]
            min = [0.0, 0.0, 0.0]
            max = [8.0, 6.0, 3.0]
            [[box]]
            name = "west"
            min = [-0.1, -0.1, -0.1]
            max = [0.0, 6.1, 3.1]
            [[box]]
            name = "east"
            min = [8.0, -0.1, -0.1]
            max = [8.1, 6.1, 3.1]
            [[box]]
            name = "south"
            min = [-0.1, -0.1, -0.1]
            max = [8.1, 0.0, 3.1]
            [[box]]
            name = "north"
            min = [-0.1, 6.0, -0.1]
            max = [8.1, 6.1, 3.1]
        "#;
        Arc::new(World::from_toml_str(toml).unwrap())
    }

    /// Range from (4, 3) to the bare room's walls along the device angle `theta_deg`
    /// (clockwise from +x, seen from above).
    fn expected_range(theta_deg: f64) -> f64 {
        let a = -theta_deg.to_radians();
        let (dx, dy) = (a.cos(), a.sin());
        let tx = if dx > 1e-12 {
            4.0 / dx
        } else if dx < -1e-12 {
            -4.0 / dx
        } else {
            f64::MAX
        };
        let ty = if dy > 1e-12 {
            3.0 / dy
        } else if dy < -1e-12 {
            -3.0 / dy
        } else {
            f64::MAX
        };
        tx.min(ty)
    }

    fn emulator(config: RplidarEmulatorConfig) -> RplidarEmulator {
        let mut scanner = RplidarEmulator::default_scanner(
            bare_room(),
            Isometry3::from_parts(Translation3::new(4.0, 3.0, 0.4), Default::default()),
        );
        scanner.noise = RangeNoise::NONE;
        RplidarEmulator::new(config, scanner, 1)
    }

    fn quick() -> RplidarEmulatorConfig {
        RplidarEmulatorConfig {
            spinup_s: 0.0,
            ..RplidarEmulatorConfig::default()
        }
    }

    fn poll(emu: &mut RplidarEmulator, now: u64) -> Vec<WireUnit> {
        let mut out = Vec::new();
        emu.poll_output(now, &mut out);
        out
    }

    fn bytes(units: &[WireUnit]) -> Vec<u8> {
        units.iter().flat_map(|u| u.bytes.iter().copied()).collect()
    }

    fn ask(emu: &mut RplidarEmulator, now: u64, request: &[u8]) -> Vec<u8> {
        emu.on_host_bytes(now, request);
        bytes(&poll(emu, now))
    }

    fn hex(s: &str) -> Vec<u8> {
        s.split_whitespace()
            .map(|b| u8::from_str_radix(b, 16).unwrap())
            .collect()
    }

    #[test]
    fn get_info_health_samplerate_answers() {
        let mut emu = emulator(quick());
        let mut info = hex("A5 5A 14 00 00 00 04 18 1D 01 07");
        info.extend_from_slice(b"scan3d-rplidar-1");
        assert_eq!(ask(&mut emu, 0, &hex("A5 50")), info);
        assert_eq!(
            ask(&mut emu, MS, &hex("A5 52")),
            hex("A5 5A 03 00 00 00 06 00 00 00")
        );
        assert_eq!(
            ask(&mut emu, 2 * MS, &hex("A5 59")),
            hex("A5 5A 04 00 00 00 15 F4 01 FA 00")
        );

        let cfg = RplidarEmulatorConfig {
            model: RplidarModel::A2,
            health_status: 1,
            health_error_code: 0x1234,
            ..quick()
        };
        let mut emu = emulator(cfg);
        assert_eq!(&ask(&mut emu, 0, &hex("A5 50"))[7..8], &[0x28]);
        assert_eq!(
            ask(&mut emu, 0, &hex("A5 52")),
            hex("A5 5A 03 00 00 00 06 01 34 12")
        );
    }

    #[test]
    fn lidar_conf_answers_the_sdk_queries() {
        let mut emu = emulator(quick());
        // Typical mode (example request from the notes) → 1 (Express).
        assert_eq!(
            ask(&mut emu, 0, &hex("A5 84 04 7C 00 00 00 59")),
            hex("A5 5A 06 00 00 00 20 7C 00 00 00 01 00")
        );
        // µs per sample of mode 1, q8: 250 × 256 = 0xFA00.
        assert_eq!(
            ask(&mut emu, 0, &hex("A5 84 06 71 00 00 00 01 00 57")),
            hex("A5 5A 08 00 00 00 20 71 00 00 00 00 FA 00 00")
        );
        let conf = |t: u8, mode: Option<u8>| {
            let mut req = vec![0xA5, 0x84, 4, t, 0, 0, 0];
            if let Some(m) = mode {
                req[2] = 6;
                req.extend_from_slice(&[m, 0]);
            }
            let cs = req.iter().fold(0, |a, b| a ^ b);
            req.push(cs);
            req
        };
        // Mode count 2.
        assert_eq!(
            ask(&mut emu, 0, &conf(0x70, None)),
            hex("A5 5A 06 00 00 00 20 70 00 00 00 02 00")
        );
        // Answer types.
        assert_eq!(
            ask(&mut emu, 0, &conf(0x75, Some(0))),
            hex("A5 5A 05 00 00 00 20 75 00 00 00 81")
        );
        assert_eq!(
            ask(&mut emu, 0, &conf(0x75, Some(1))),
            hex("A5 5A 05 00 00 00 20 75 00 00 00 82")
        );
        // Max distance 12 m q8 = 3072 = 0x0C00.
        assert_eq!(
            ask(&mut emu, 0, &conf(0x74, Some(1))),
            hex("A5 5A 08 00 00 00 20 74 00 00 00 00 0C 00 00")
        );
        // Mode names, NUL-terminated.
        let mut name = hex("A5 5A 0C 00 00 00 20 7F 00 00 00");
        name.extend_from_slice(b"Express\0");
        assert_eq!(ask(&mut emu, 0, &conf(0x7F, Some(1))), name);
        // Desired rotation: 4 bytes, rpm 330 (0x014A), pwm 660 (0x0294).
        assert_eq!(
            ask(&mut emu, 0, &conf(0x01, None)),
            hex("A5 5A 08 00 00 00 20 01 00 00 00 4A 01 94 02")
        );
        // A third mode and unknown types get no answer.
        assert!(ask(&mut emu, 0, &conf(0x75, Some(2))).is_empty());
        assert!(ask(&mut emu, 0, &conf(0x33, None)).is_empty());

        // Firmware older than 1.24 ignores GET_LIDAR_CONF.
        let mut old = emulator(RplidarEmulatorConfig {
            firmware_minor: 20,
            ..quick()
        });
        assert!(ask(&mut old, 0, &hex("A5 84 04 7C 00 00 00 59")).is_empty());
    }

    #[test]
    fn bad_checksums_and_noise_are_ignored() {
        let mut emu = emulator(quick());
        assert!(ask(&mut emu, 0, &hex("A5 82 05 00 00 00 00 00 23")).is_empty());
        assert!(!emu.is_scanning());
        // Garbage before a valid request, and a request split over two writes.
        assert!(ask(&mut emu, 0, &hex("00 FF 13")).is_empty());
        assert!(ask(&mut emu, 0, &hex("A5")).is_empty());
        assert_eq!(
            ask(&mut emu, 0, &hex("52")),
            hex("A5 5A 03 00 00 00 06 00 00 00")
        );
    }

    /// Decodes standard nodes by the notes (§1.6), checking sync and check bits.
    fn decode_node(b: &[u8]) -> RawSample {
        assert_eq!(b.len(), 5);
        let s = b[0] & 1;
        assert_eq!((b[0] >> 1) & 1, s ^ 1, "S and !S");
        let a = u16::from_le_bytes([b[1], b[2]]);
        assert_eq!(a & 1, 1, "check bit");
        let angle_q6 = a >> 1;
        assert!(u32::from(angle_q6) < 360 * 64);
        RawSample {
            angle_deg: f32::from(angle_q6) / 64.0,
            range_m: f32::from(u16::from_le_bytes([b[3], b[4]])) / 4000.0,
            quality: b[0] >> 2,
            new_revolution: s == 1,
        }
    }

    #[test]
    fn standard_scan_descriptor_then_nodes_after_spinup() {
        let mut emu = emulator(RplidarEmulatorConfig::default()); // 1.5 s spin-up from power-on
        assert_eq!(ask(&mut emu, 0, &hex("A5 20")), hex("A5 5A 05 00 00 40 81"));
        assert!(
            poll(&mut emu, 1_400 * MS).is_empty(),
            "nodes before spin-up"
        );
        let units = poll(&mut emu, 3 * S);
        // 1.5 s of nodes at 500 µs.
        assert!(
            (2990..=3010).contains(&units.len()),
            "{} nodes",
            units.len()
        );
        let mut prev: Option<f32> = None;
        let mut revolutions = 0;
        for u in &units {
            let s = decode_node(&u.bytes);
            assert_eq!(u.samples, vec![s]);
            // Clockwise device angle θ → world direction (cos −θ, sin −θ) from (4, 3).
            let expected = expected_range(f64::from(s.angle_deg));
            assert!(
                (f64::from(s.range_m) - expected).abs() < 0.001,
                "{s:?} vs {expected}"
            );
            assert_eq!(s.new_revolution, prev.is_some_and(|p| s.angle_deg < p));
            revolutions += usize::from(s.new_revolution);
            prev = Some(s.angle_deg);
        }
        // 1.5 s at 5.5 Hz: 8 or 9 wraps.
        assert!((8..=9).contains(&revolutions), "{revolutions}");
        // The angle advances 5.5 × 360° × 500 µs ≈ 0.99° per node.
        let a0 = units[10].samples[0].angle_deg;
        let a1 = units[11].samples[0].angle_deg;
        assert!(((a1 - a0).rem_euclid(360.0) - 0.99).abs() < 0.02);
    }

    #[test]
    fn standard_rate_is_limited_by_the_wire() {
        // Ask for 100 µs per sample: 5 bytes at 11 520 B/s take 434 µs, so ≈ 2304 nodes/s.
        let cfg = RplidarEmulatorConfig {
            standard_sample_us: 100,
            ..quick()
        };
        let mut emu = emulator(cfg);
        ask(&mut emu, 0, &hex("A5 21"));
        let n = poll(&mut emu, 2 * S).len();
        assert!((4600..=4610).contains(&n), "{n} nodes in 2 s");
        // At 256000 baud the wire allows 5120 nodes/s.
        let cfg = RplidarEmulatorConfig {
            standard_sample_us: 100,
            baud: 256_000,
            ..quick()
        };
        let mut emu = emulator(cfg);
        ask(&mut emu, 0, &hex("A5 20"));
        let n = poll(&mut emu, S).len();
        assert!((5110..=5125).contains(&n), "{n} nodes in 1 s");
    }

    /// Decodes legacy capsules pairwise by the notes (§1.7), checking sync and checksum.
    fn decode_capsules(units: &[WireUnit]) -> Vec<(f32, f32)> {
        let header = |b: &[u8]| {
            assert_eq!(b.len(), 84);
            assert_eq!((b[0] >> 4, b[1] >> 4), (0xA, 0x5), "sync nibbles");
            let cs = b[2..].iter().fold(0u8, |a, x| a ^ x);
            assert_eq!((b[0] & 0xF) | (b[1] << 4), cs, "checksum");
            u16::from_le_bytes([b[2], b[3]])
        };
        let mut out = Vec::new();
        for pair in units.windows(2) {
            let (cur, next) = (&pair[0].bytes, &pair[1].bytes);
            let w0 = f64::from(header(cur) & 0x7FFF) / 64.0;
            let w1 = f64::from(header(next) & 0x7FFF) / 64.0;
            let diff = if w1 < w0 { w1 + 360.0 - w0 } else { w1 - w0 };
            for k in 0..32 {
                let c = &cur[4 + (k / 2) * 5..4 + (k / 2) * 5 + 5];
                let d = u16::from_le_bytes(if k % 2 == 0 {
                    [c[0], c[1]]
                } else {
                    [c[2], c[3]]
                });
                let low = if k % 2 == 0 { c[4] & 0xF } else { c[4] >> 4 };
                let dtheta = (((d & 3) as u8) << 4) | low;
                let theta =
                    (w0 + diff * k as f64 / 32.0 - f64::from(dtheta) / 8.0).rem_euclid(360.0);
                out.push((theta as f32, f32::from(d >> 2) / 1000.0));
            }
        }
        out
    }

    #[test]
    fn express_capsules_decode_to_the_listed_samples() {
        let mut emu = emulator(quick());
        assert_eq!(
            ask(&mut emu, 0, &hex("A5 82 05 00 00 00 00 00 22")),
            hex("A5 5A 54 00 00 40 82")
        );
        let units = poll(&mut emu, 2 * S);
        // 2 s at 250 µs = 8000 samples = 250 capsules of 32.
        assert_eq!(units.len(), 250);
        assert!(units.iter().all(|u| u.samples.len() == 32));
        // S bit only on the first capsule.
        assert!(units[0].bytes[3] & 0x80 != 0);
        assert!(units[1..].iter().all(|u| u.bytes[3] & 0x80 == 0));
        let decoded = decode_capsules(&units);
        let listed: Vec<RawSample> = units[..units.len() - 1]
            .iter()
            .flat_map(|u| u.samples.iter().copied())
            .collect();
        assert_eq!(decoded.len(), listed.len());
        let mut prev: Option<f32> = None;
        let mut revolutions = 0;
        let mut offsets_seen = [false; 64];
        for (&(angle, range), s) in decoded.iter().zip(&listed) {
            assert_eq!((angle, range), (s.angle_deg, s.range_m));
            assert!((0.0..360.0).contains(&angle));
            let expected = expected_range(f64::from(angle));
            assert!(
                (f64::from(range) - expected).abs() < 0.001,
                "{s:?} vs {expected}"
            );
            assert_eq!(s.quality, 47);
            assert_eq!(s.new_revolution, prev.is_some_and(|p| angle < p));
            revolutions += usize::from(s.new_revolution);
            prev = Some(angle);
        }
        // 2 s at 5.5 Hz: 10 or 11 wraps, never a spurious one.
        assert!((10..=11).contains(&revolutions), "{revolutions}");
        for u in &units {
            for c in u.bytes[4..].chunks(5) {
                let d1 = ((c[0] & 3) << 4) | (c[4] & 0xF);
                let d2 = ((c[2] & 3) << 4) | (c[4] >> 4);
                offsets_seen[usize::from(d1)] = true;
                offsets_seen[usize::from(d2)] = true;
            }
        }
        assert!(
            offsets_seen[32..].iter().all(|s| !s),
            "dθ must stay in 0..=31"
        );
        assert!(
            offsets_seen.iter().filter(|&&s| s).count() > 8,
            "dθ should vary"
        );
    }

    #[test]
    fn a2_streams_only_after_pwm_and_answers_acc_board_flag() {
        let mut emu = emulator(RplidarEmulatorConfig {
            model: RplidarModel::A2,
            ..quick()
        });
        assert_eq!(
            ask(&mut emu, 0, &hex("A5 FF 04 00 00 00 00 5E")),
            hex("A5 5A 04 00 00 00 FF 01 00 00 00")
        );
        assert_eq!(ask(&mut emu, 0, &hex("A5 20")), hex("A5 5A 05 00 00 40 81"));
        assert!(
            poll(&mut emu, 3 * S).is_empty(),
            "A2 streamed with the motor off"
        );
        // PWM 660 (ends the idle stream), then scan again: nodes flow.
        assert!(ask(&mut emu, 3 * S, &hex("A5 F0 02 94 02 C1")).is_empty());
        // No spin-up in this config: the first node comes right after the descriptor.
        let first = ask(&mut emu, 3 * S, &hex("A5 20"));
        assert_eq!(first.len(), 7 + 5);
        assert_eq!(first[..7], hex("A5 5A 05 00 00 40 81"));
        assert_eq!(poll(&mut emu, 3 * S + 100 * MS).len(), 200);
        // PWM 0 stops the motor: a new scan stays silent.
        ask(&mut emu, 4 * S, &hex("A5 F0 02 00 00 57"));
        ask(&mut emu, 4 * S, &hex("A5 20"));
        assert!(poll(&mut emu, 5 * S).is_empty());

        // An A1 ignores both commands, and they do not end its stream.
        let mut a1 = emulator(quick());
        assert!(ask(&mut a1, 0, &hex("A5 FF 04 00 00 00 00 5E")).is_empty());
        ask(&mut a1, 0, &hex("A5 20"));
        ask(&mut a1, MS, &hex("A5 F0 02 00 00 57"));
        assert!(a1.is_scanning());
        assert!(poll(&mut a1, 100 * MS).len() >= 190);
    }

    #[test]
    fn a1_waits_for_spinup_after_power_on_and_scan_waits_longer_than_force_scan() {
        let mut emu = emulator(RplidarEmulatorConfig::default());
        // SCAN at 1 s: first node at 1.5 s.
        ask(&mut emu, S, &hex("A5 20"));
        assert!(poll(&mut emu, 1_499 * MS).is_empty());
        assert!(!poll(&mut emu, 1_501 * MS).is_empty());
        // A2 FORCE_SCAN right after the motor starts: nodes without the spin-up wait.
        let mut a2 = emulator(RplidarEmulatorConfig {
            model: RplidarModel::A2,
            ..Default::default()
        });
        ask(&mut a2, 0, &hex("A5 F0 02 94 02 C1"));
        ask(&mut a2, 0, &hex("A5 21"));
        assert!(poll(&mut a2, 10 * MS).len() >= 19);
        ask(&mut a2, 20 * MS, &hex("A5 20"));
        assert!(poll(&mut a2, 1_400 * MS).is_empty());
        assert!(!poll(&mut a2, 1_600 * MS).is_empty());
    }

    #[test]
    fn express_rate_is_4000_samples_per_second() {
        let mut emu = emulator(quick());
        ask(&mut emu, 0, &hex("A5 82 05 01 00 00 00 00 23"));
        let samples: usize = poll(&mut emu, 3 * S).iter().map(|u| u.samples.len()).sum();
        assert_eq!(samples, 12_000);
    }

    #[test]
    fn reset_prints_the_banner_then_ignores_requests_for_a_while() {
        let mut emu = emulator(quick());
        ask(&mut emu, 0, &hex("A5 20"));
        let out = ask(&mut emu, 10 * MS, &hex("A5 40"));
        let banner: &[u8] =
            b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc2, HW Ver 7\r\nModel: 24\r\n";
        // The 20 nodes measured in (0, 10 ms], then the banner.
        assert_eq!(out.len(), 20 * 5 + banner.len());
        assert!(out.ends_with(banner));
        assert!(!emu.is_scanning());
        assert!(
            ask(&mut emu, 300 * MS, &hex("A5 52")).is_empty(),
            "answered while rebooting"
        );
        assert_eq!(
            ask(&mut emu, 600 * MS, &hex("A5 52")),
            hex("A5 5A 03 00 00 00 06 00 00 00")
        );
    }

    #[test]
    fn a_new_request_ends_the_stream_and_the_stream_survives_reconnects() {
        let mut emu = emulator(quick());
        emu.on_host_bytes(0, &hex("A5 20"));
        emu.on_disconnect(50 * MS);
        emu.on_connect(60 * MS);
        let units = poll(&mut emu, 100 * MS);
        // The descriptor, then nodes at 0, 0.5, …, 100 ms.
        assert_eq!(units[0].bytes, hex("A5 5A 05 00 00 40 81"));
        assert_eq!(units.len(), 1 + 201);
        // GET_HEALTH mid-stream: the nodes due so far, the answer, then silence.
        let out = ask(&mut emu, 110 * MS, &hex("A5 52"));
        assert_eq!(out.len(), 20 * 5 + 10);
        assert!(out.ends_with(&hex("A5 5A 03 00 00 00 06 00 00 00")));
        assert!(poll(&mut emu, S).is_empty());
        // STOP ends an express stream too.
        ask(&mut emu, S, &hex("A5 82 05 00 00 00 00 00 22"));
        ask(&mut emu, 2 * S, &hex("A5 25"));
        assert!(poll(&mut emu, 3 * S).is_empty());
    }

    #[test]
    fn same_seed_same_bytes() {
        let run = |seed| {
            let mut s = RplidarEmulator::default_scanner(
                bare_room(),
                Isometry3::translation(4.0, 3.0, 0.4),
            );
            s.noise = RangeNoise::RPLIDAR;
            let mut emu = RplidarEmulator::new(quick(), s, seed);
            ask(&mut emu, 0, &hex("A5 82 05 00 00 00 00 00 22"));
            bytes(&poll(&mut emu, S))
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }

    #[test]
    fn config_validation_and_toml() {
        assert_eq!(RplidarEmulatorConfig::default().validate(), Ok(()));
        let bad = RplidarEmulatorConfig {
            rotation_hz: 0.0,
            ..Default::default()
        };
        assert_eq!(bad.validate(), Err(RplidarConfigError::Rotation(0.0)));
        let cfg: RplidarEmulatorConfig = toml::from_str("model = \"a2\"\nbaud = 256000").unwrap();
        assert_eq!(cfg.model, RplidarModel::A2);
        assert_eq!(cfg.baud, 256_000);
        assert_eq!(cfg.firmware_minor, 29);
    }
}
