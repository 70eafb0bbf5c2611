//! Slamtec RPLidar A1/A2 driver: a sans-I/O [`LidarDriver`] (research notes §1).
//!
//! Layers, each usable on its own:
//! - [`codec`]: request builders (exact bytes), response-descriptor hunting, GET_INFO /
//!   GET_HEALTH / GET_SAMPLERATE / GET_ACC_BOARD_FLAG payloads;
//! - [`nodes`]: standard 5-byte scan nodes with a plausibility-checked resync;
//! - [`capsules`]: legacy 84-byte express capsules with angle reconstruction;
//! - [`Rplidar`]: the session state machine below.
//!
//! # Session
//!
//! [`LidarDriver::start`] runs, one step after another:
//!
//! 1. `STOP`, wait [`RplidarConfig::stop_wait_ms`] (bytes in flight keep arriving), then
//!    [`Transmit::FlushInput`]. With [`RplidarConfig::reset_on_start`] (or [`Rplidar::reset`]):
//!    `RESET` instead, wait [`RplidarConfig::reset_wait_ms`] for the reboot and its ASCII banner,
//!    then flush.
//! 2. `GET_INFO`, retried every [`RplidarConfig::info_timeout_ms`] up to
//!    [`RplidarConfig::info_attempts`] times (or [`RplidarConfig::info_attempts_after_reset`]),
//!    then [`DriverError::NoAnswer`]. Garbage before the answer (a banner, stale nodes) is
//!    skipped by descriptor hunting. Emits [`LidarEvent::Info`].
//! 3. Model major ≥ 2 (A2): `GET_ACC_BOARD_FLAG` (if [`RplidarConfig::query_acc_board`]); bit 0
//!    set, no answer, or not asked → the motor is driven by `SET_MOTOR_PWM`; bit 0 clear → by
//!    DTR. Major 1 (A1): DTR.
//! 4. `GET_HEALTH` → [`LidarEvent::Health`]. Status Error (protection stop) →
//!    [`LidarEvent::Failed`] with [`DriverError::Device`]: the device needs a reset or a power
//!    cycle, which the caller decides (e.g. by calling [`Rplidar::reset`]).
//! 5. `GET_SAMPLERATE` when the firmware is ≥ 1.17 (no answer, or older firmware: 476 µs).
//! 6. Motor on (`SET_MOTOR_PWM(motor_pwm)` or `SetDtr(false)`), then `SCAN` / `FORCE_SCAN` or
//!    `EXPRESS_SCAN` (working mode 0, legacy capsules; firmware < 1.17 falls back to standard).
//!    The descriptor → [`LidarEvent::Scanning`], then [`LidarEvent::Sample`]s.
//!
//! # Revolution ends and read deadlines
//!
//! In express mode the driver says when a revolution is complete as soon as the bytes tell
//! ([`LidarEvent::RevolutionComplete`], see [`capsules`]), and when the bytes that complete the
//! revolution in progress will have arrived ([`LidarDriver::poll_read_deadline`]): the bytes
//! still missing, at one capsule per `max(32 × express sample period, 84 bytes on the wire)`,
//! after the last read, plus [`READ_DEADLINE_MARGIN_NS`]. The I/O shell reads then, so a
//! revolution leaves the edge within about a millisecond of its last capsule, while the reads in
//! between keep their slow pace. Standard-mode nodes carry the start flag on the node right
//! after the revolution's last one (0.5 ms later), so they need neither.
//!
//! While scanning, a stream that yields no valid frame for [`RplidarConfig::answer_timeout_ms`]
//! (or [`RplidarConfig::spinup_timeout_ms`] right after the descriptor, while the motor spins
//! up) produces a warning and the handshake restarts from step 1: the device may have been
//! reset or replugged. Other single answers time out after `answer_timeout_ms` and are retried
//! up to [`RplidarConfig::answer_attempts`] times.
//!
//! [`LidarDriver::stop`] sends `STOP`, then `SET_MOTOR_PWM(0)` (PWM motor) or `SetDtr(true)`
//! (DTR motor), and goes idle.
//!
//! # Counters
//!
//! [`DriverStats::frames_rejected`] and [`DriverStats::resyncs`] both count framing losses in the
//! sample stream (a node or capsule at an expected boundary that failed its checks);
//! [`DriverStats::bytes_discarded`] counts every byte skipped while hunting, received while no
//! answer was expected, or dropped by a flush.

pub mod capsules;
pub mod codec;
pub mod nodes;

use std::collections::VecDeque;

use serde::Deserialize;

use crate::lidar::{
    ArrivedSample, DriverError, DriverStats, HealthStatus, LidarDriver, LidarEvent, LidarKind,
    Transmit,
};
use capsules::{CAPSULE_LEN, CapsuleOutput, CapsuleParser, SAMPLES_PER_CAPSULE};
use codec::{ExpectedAnswer, Hunt, InfoAnswer, SampleRate};
use nodes::NodeParser;

const MS: u64 = 1_000_000;

/// How long after the predicted arrival of a revolution's last byte the read deadline falls:
/// the bytes of a capsule trickle at the wire rate, and a USB adapter hands them over in
/// packets; reading a little late costs one millisecond, reading early costs a read.
pub const READ_DEADLINE_MARGIN_NS: u64 = MS;

/// Edge-clock time by which `missing_bytes` more bytes have arrived after the read at
/// `last_read_ns`, the device sending one capsule per `capsule_ns`, plus
/// [`READ_DEADLINE_MARGIN_NS`] (saturating).
pub fn revolution_read_deadline(last_read_ns: u64, missing_bytes: usize, capsule_ns: u64) -> u64 {
    let missing = u128::try_from(missing_bytes).unwrap_or(u128::MAX);
    let wait = missing.saturating_mul(u128::from(capsule_ns)) / CAPSULE_LEN as u128;
    last_read_ns
        .saturating_add(u64::try_from(wait).unwrap_or(u64::MAX))
        .saturating_add(READ_DEADLINE_MARGIN_NS)
}

/// Edge-clock time one express capsule takes to come: its 32 samples at `sample_us` each, or
/// its 84 bytes on a `baud` line (10 bits a byte), whichever is longer.
pub fn capsule_period_ns(sample_us: u16, baud: u32) -> u64 {
    let sampling = SAMPLES_PER_CAPSULE as u64 * u64::from(sample_us) * 1_000;
    let wire = CAPSULE_LEN as u64 * 10 * 1_000_000_000 / u64::from(baud.max(1));
    sampling.max(wire)
}

/// The deadline `ms` milliseconds after `now`, saturating: a configured timeout too long to
/// represent means "not before the end of time", never an overflow (a panic in debug builds, a
/// wrapped deadline in the past in release builds, which would fire at once).
fn deadline_after(now: u64, ms: u64) -> u64 {
    now.saturating_add(ms.saturating_mul(MS))
}
/// First firmware with EXPRESS_SCAN and GET_SAMPLERATE (1.17).
const FW_1_17: u16 = 0x0111;

/// Which scan command the driver starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScanMode {
    /// SCAN (or FORCE_SCAN): 5-byte nodes with a per-sample quality.
    Standard,
    /// EXPRESS_SCAN with legacy 84-byte capsules (fw ≥ 1.17): about twice the sample rate.
    #[default]
    Express,
}

/// RPLidar driver settings (the `[rplidar]` table of the edge config; every field optional).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RplidarConfig {
    /// Scan mode to request (default express).
    pub scan_mode: ScanMode,
    /// In standard mode, send FORCE_SCAN (no wait for stable rotation) instead of SCAN.
    pub force_scan: bool,
    /// A2 motor PWM duty (0..1023) sent before scanning (default 660, as the SDK).
    pub motor_pwm: u16,
    /// Ask an A2 for GET_ACC_BOARD_FLAG before choosing PWM motor control (default true).
    pub query_acc_board: bool,
    /// Serial baud rate. The I/O shell opens the port with it; the driver only uses it to
    /// tell how long a capsule takes on the wire (read deadlines).
    /// 115200 for A1 and A2M4–M8 (default), 256000 for A2M7/A2M12/A3.
    pub baud: u32,
    /// Time to wait for a single answer or, while scanning, for the next valid frame (2 s).
    pub answer_timeout_ms: u64,
    /// Tries for GET_HEALTH, GET_SAMPLERATE, GET_ACC_BOARD_FLAG and the scan request (2).
    pub answer_attempts: u32,
    /// Time to wait for each GET_INFO answer (500 ms, the SDK's `connect()` value).
    pub info_timeout_ms: u64,
    /// GET_INFO tries after STOP before giving up (4).
    pub info_attempts: u32,
    /// Wait after STOP before flushing the input (100 ms, as the SDK).
    pub stop_wait_ms: u64,
    /// Send RESET instead of STOP at the start of each handshake (default false).
    pub reset_on_start: bool,
    /// Wait after RESET for the reboot and its ASCII banner before flushing (1000 ms).
    pub reset_wait_ms: u64,
    /// GET_INFO tries after RESET (30, i.e. 15 s like rplidar_ros).
    pub info_attempts_after_reset: u32,
    /// Time allowed from the scan descriptor to the first valid frame: an A1 sends nothing until
    /// its motor has spun up, which takes well over 1 s (5000 ms).
    pub spinup_timeout_ms: u64,
}

impl Default for RplidarConfig {
    fn default() -> Self {
        Self {
            scan_mode: ScanMode::Express,
            force_scan: false,
            motor_pwm: 660,
            query_acc_board: true,
            baud: 115_200,
            answer_timeout_ms: 2000,
            answer_attempts: 2,
            info_timeout_ms: 500,
            info_attempts: 4,
            stop_wait_ms: 100,
            reset_on_start: false,
            reset_wait_ms: 1000,
            info_attempts_after_reset: 30,
            spinup_timeout_ms: 5000,
        }
    }
}

/// A setting of [`RplidarConfig`] outside what the driver and the device accept.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{key}` = {value} is out of range (allowed: {allowed})")]
pub struct RplidarConfigError {
    /// The key, as written in `[rplidar]`.
    pub key: &'static str,
    /// The value given.
    pub value: u64,
    /// The accepted range, for the message.
    pub allowed: &'static str,
}

/// Longest timeout or wait accepted, ms (10 minutes: anything longer is a typo, and a deadline
/// that far away would hide a dead device).
pub const MAX_TIMEOUT_MS: u64 = 600_000;

impl RplidarConfig {
    /// Checks every setting against what the device and the driver can use: a baud rate a
    /// serial port can run (9600–4000000; Slamtec lidars use 115200, 256000, 460800 or
    /// 1000000), a PWM duty in 0–1023, timeouts of 1 ms to [`MAX_TIMEOUT_MS`] (waits may be 0),
    /// and 1–1000 attempts.
    pub fn validate(&self) -> Result<(), RplidarConfigError> {
        let check =
            |key: &'static str, value: u64, range: std::ops::RangeInclusive<u64>, allowed| {
                if range.contains(&value) {
                    Ok(())
                } else {
                    Err(RplidarConfigError {
                        key,
                        value,
                        allowed,
                    })
                }
            };
        check(
            "baud",
            self.baud.into(),
            9_600..=4_000_000,
            "9600 to 4000000",
        )?;
        check("motor_pwm", self.motor_pwm.into(), 0..=1023, "0 to 1023")?;
        for (key, value) in [
            ("answer_timeout_ms", self.answer_timeout_ms),
            ("info_timeout_ms", self.info_timeout_ms),
            ("spinup_timeout_ms", self.spinup_timeout_ms),
        ] {
            check(key, value, 1..=MAX_TIMEOUT_MS, "1 to 600000 ms")?;
        }
        for (key, value) in [
            ("stop_wait_ms", self.stop_wait_ms),
            ("reset_wait_ms", self.reset_wait_ms),
        ] {
            check(key, value, 0..=MAX_TIMEOUT_MS, "0 to 600000 ms")?;
        }
        for (key, value) in [
            ("answer_attempts", self.answer_attempts),
            ("info_attempts", self.info_attempts),
            ("info_attempts_after_reset", self.info_attempts_after_reset),
        ] {
            check(key, value.into(), 1..=1000, "1 to 1000")?;
        }
        Ok(())
    }
}

/// How the motor is switched, decided from GET_INFO (and GET_ACC_BOARD_FLAG).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Motor {
    Unknown,
    Dtr,
    Pwm,
}

/// A request whose answer the session waits for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    Info,
    AccBoard,
    Health,
    SampleRate,
    Scan,
}

#[derive(Debug, Clone)]
struct Pending {
    step: Step,
    answer: ExpectedAnswer,
    request: Vec<u8>,
    attempts: u32,
    max_attempts: u32,
    timeout_ns: u64,
    deadline: u64,
    got_descriptor: bool,
}

#[derive(Debug, Clone)]
enum StreamParser {
    Nodes(NodeParser),
    Capsules(CapsuleParser),
}

#[derive(Debug, Clone)]
enum Phase {
    Idle,
    /// Waiting after STOP/RESET; then flush and GET_INFO with `info_attempts` tries.
    Settling {
        until: u64,
        info_attempts: u32,
    },
    Awaiting(Pending),
    Scanning {
        parser: StreamParser,
        deadline: u64,
        /// Edge-clock time one capsule takes to come (express), for read deadlines.
        capsule_ns: u64,
    },
}

/// The RPLidar A1/A2 protocol state machine. See the [module docs](self) for the session.
#[derive(Debug, Clone)]
pub struct Rplidar {
    config: RplidarConfig,
    phase: Phase,
    /// Received bytes not consumed yet.
    buf: Vec<u8>,
    /// Stream offset of `buf[0]` (bytes received before it).
    buf_offset: u64,
    /// `(stream offset just past a read, now_ns of that read)`, oldest first, for `arrival_ns`.
    reads: VecDeque<(u64, u64)>,
    /// `now_ns` of the last read that brought bytes, for read deadlines.
    last_read_ns: Option<u64>,
    transmits: VecDeque<Transmit>,
    events: VecDeque<LidarEvent>,
    stats: DriverStats,
    info: Option<InfoAnswer>,
    motor: Motor,
    sample_rate: SampleRate,
    resyncs_reported: u64,
    next_resync_report: u64,
}

impl Rplidar {
    /// An idle driver; call [`LidarDriver::start`] once the port is open.
    pub fn new(config: RplidarConfig) -> Self {
        Self {
            config,
            phase: Phase::Idle,
            buf: Vec::with_capacity(4096),
            buf_offset: 0,
            reads: VecDeque::new(),
            last_read_ns: None,
            transmits: VecDeque::new(),
            events: VecDeque::new(),
            stats: DriverStats::default(),
            info: None,
            motor: Motor::Unknown,
            sample_rate: SampleRate::DEFAULT,
            resyncs_reported: 0,
            next_resync_report: 0,
        }
    }

    /// The settings this driver was built with.
    pub fn config(&self) -> &RplidarConfig {
        &self.config
    }

    /// The last GET_INFO answer of this session, if any.
    pub fn device(&self) -> Option<&InfoAnswer> {
        self.info.as_ref()
    }

    /// Restarts the handshake with RESET instead of STOP: the core reboots and prints an ASCII
    /// banner, so the driver waits [`RplidarConfig::reset_wait_ms`], flushes, and polls GET_INFO
    /// up to [`RplidarConfig::info_attempts_after_reset`] times. Use it to clear a protection
    /// stop ([`HealthStatus::Error`]).
    pub fn reset(&mut self, now_ns: u64) {
        self.transmits.clear();
        self.motor = Motor::Unknown;
        self.begin(now_ns, true);
    }

    /// Starts a handshake (STOP or RESET), dropping any parser state and buffered bytes.
    fn begin(&mut self, now: u64, reset: bool) {
        self.discard_buffer();
        self.info = None;
        self.sample_rate = SampleRate::DEFAULT;
        if reset {
            self.transmits.push_back(Transmit::Write(codec::reset()));
            self.phase = Phase::Settling {
                until: deadline_after(now, self.config.reset_wait_ms),
                info_attempts: self.config.info_attempts_after_reset,
            };
        } else {
            self.transmits.push_back(Transmit::Write(codec::stop()));
            self.phase = Phase::Settling {
                until: deadline_after(now, self.config.stop_wait_ms),
                info_attempts: self.config.info_attempts,
            };
        }
    }

    fn discard_buffer(&mut self) {
        self.stats.bytes_discarded += self.buf.len() as u64;
        self.consume(self.buf.len());
    }

    /// Drops the first `n` buffered bytes.
    fn consume(&mut self, n: usize) {
        let n = n.min(self.buf.len());
        self.buf.drain(..n);
        self.buf_offset += n as u64;
        while self
            .reads
            .front()
            .is_some_and(|&(end, _)| end <= self.buf_offset)
        {
            self.reads.pop_front();
        }
    }

    fn fail(&mut self, error: DriverError) {
        self.events.push_back(LidarEvent::Failed(error));
        self.phase = Phase::Idle;
    }

    fn warn(&mut self, text: String) {
        self.events.push_back(LidarEvent::Warning(text));
    }

    /// Sends a request whose answer is awaited.
    fn request(&mut self, now: u64, step: Step, max_attempts: u32, timeout_ms: u64) {
        let (request, answer) = match step {
            Step::Info => (codec::get_info(), codec::ANSWER_INFO),
            Step::AccBoard => (codec::get_acc_board_flag(), codec::ANSWER_ACC_BOARD_FLAG),
            Step::Health => (codec::get_health(), codec::ANSWER_HEALTH),
            Step::SampleRate => (codec::get_samplerate(), codec::ANSWER_SAMPLERATE),
            Step::Scan => self.scan_request(),
        };
        self.transmits.push_back(Transmit::Write(request.clone()));
        self.phase = Phase::Awaiting(Pending {
            step,
            answer,
            request,
            attempts: 1,
            max_attempts: max_attempts.max(1),
            timeout_ns: timeout_ms.saturating_mul(MS),
            deadline: deadline_after(now, timeout_ms),
            got_descriptor: false,
        });
    }

    fn express_supported(&self) -> bool {
        self.info.is_some_and(|i| i.firmware >= FW_1_17)
    }

    fn scan_request(&self) -> (Vec<u8>, ExpectedAnswer) {
        match (
            self.config.scan_mode,
            self.express_supported(),
            self.config.force_scan,
        ) {
            (ScanMode::Express, true, _) => (codec::express_scan(0), codec::ANSWER_EXPRESS),
            (_, _, true) => (codec::force_scan(), codec::ANSWER_FORCE_SCAN),
            _ => (codec::scan(), codec::ANSWER_SCAN),
        }
    }

    fn answer_request(&mut self, now: u64, step: Step) {
        self.request(
            now,
            step,
            self.config.answer_attempts,
            self.config.answer_timeout_ms,
        );
    }

    fn after_info(&mut self, now: u64, info: InfoAnswer) {
        self.events.push_back(LidarEvent::Info(info.device_info()));
        self.info = Some(info);
        if !matches!(info.major(), 1 | 2) {
            self.warn(format!(
                "model byte 0x{:02X} is neither an A1 nor an A2; trying the A-series protocol",
                info.model
            ));
        }
        if info.major() >= 2 {
            if self.config.query_acc_board {
                self.answer_request(now, Step::AccBoard);
                return;
            }
            self.motor = Motor::Pwm;
        } else {
            self.motor = Motor::Dtr;
        }
        self.answer_request(now, Step::Health);
    }

    fn after_health(&mut self, now: u64) {
        if self.express_supported() {
            self.answer_request(now, Step::SampleRate);
        } else {
            self.start_scan(now);
        }
    }

    fn start_scan(&mut self, now: u64) {
        match self.motor {
            Motor::Pwm => self
                .transmits
                .push_back(Transmit::Write(codec::set_motor_pwm(self.config.motor_pwm))),
            Motor::Dtr | Motor::Unknown => self.transmits.push_back(Transmit::SetDtr(false)),
        }
        if self.config.scan_mode == ScanMode::Express && !self.express_supported() {
            self.warn("firmware older than 1.17 has no express scan; using standard scan".into());
        }
        self.answer_request(now, Step::Scan);
    }

    /// Handles a complete single answer (`payload.len() == pending.answer.len`).
    fn on_answer(&mut self, now: u64, step: Step, payload: &[u8]) {
        match step {
            Step::Info => {
                if let Ok(p) = <&[u8; 20]>::try_from(payload) {
                    self.after_info(now, InfoAnswer::parse(p));
                }
            }
            Step::AccBoard => {
                if let Ok(p) = <&[u8; 4]>::try_from(payload) {
                    self.motor = if codec::parse_acc_board_pwm(p) {
                        Motor::Pwm
                    } else {
                        Motor::Dtr
                    };
                }
                self.answer_request(now, Step::Health);
            }
            Step::Health => {
                let Ok(p) = <&[u8; 3]>::try_from(payload) else {
                    return;
                };
                match codec::parse_health(p) {
                    Ok((status, error_code)) => {
                        self.events
                            .push_back(LidarEvent::Health { status, error_code });
                        if status == HealthStatus::Error {
                            self.fail(DriverError::Device(format!(
                                "health status Error (protection stop), error code 0x{error_code:04X}; \
                                 reset or power-cycle the device"
                            )));
                            return;
                        }
                    }
                    Err(e) => self.warn(format!("GET_HEALTH: {e}; continuing")),
                }
                self.after_health(now);
            }
            Step::SampleRate => {
                if let Ok(p) = <&[u8; 4]>::try_from(payload) {
                    self.sample_rate = SampleRate::parse(p);
                }
                self.start_scan(now);
            }
            // The scan answer has no single payload: see `on_scan_descriptor`.
            Step::Scan => {}
        }
    }

    fn on_scan_descriptor(&mut self, now: u64, answer: &ExpectedAnswer) {
        let (parser, period_us) = if answer.data_type == codec::ANSWER_EXPRESS.data_type {
            (
                StreamParser::Capsules(CapsuleParser::new()),
                self.sample_rate.express_us,
            )
        } else {
            (
                StreamParser::Nodes(NodeParser::new()),
                self.sample_rate.standard_us,
            )
        };
        self.events.push_back(LidarEvent::Scanning {
            sample_period_ns: u64::from(period_us) * 1000,
        });
        self.resyncs_reported = self.stats.resyncs;
        self.phase = Phase::Scanning {
            parser,
            deadline: deadline_after(now, self.config.spinup_timeout_ms),
            capsule_ns: capsule_period_ns(self.sample_rate.express_us, self.config.baud),
        };
    }

    fn on_timeout(&mut self, now: u64, pending: Pending) {
        if pending.attempts < pending.max_attempts {
            self.warn(format!(
                "no answer to {} (attempt {}/{}), retrying",
                pending.answer.command, pending.attempts, pending.max_attempts
            ));
            self.discard_buffer();
            self.transmits
                .push_back(Transmit::Write(pending.request.clone()));
            self.phase = Phase::Awaiting(Pending {
                attempts: pending.attempts + 1,
                deadline: now.saturating_add(pending.timeout_ns),
                got_descriptor: false,
                ..pending
            });
            return;
        }
        let no_answer = DriverError::NoAnswer {
            command: pending.answer.command,
            attempts: pending.attempts,
        };
        match pending.step {
            Step::Info | Step::Health | Step::Scan => self.fail(no_answer),
            Step::AccBoard => {
                self.warn(format!(
                    "{no_answer}; assuming PWM motor control (model is A2)"
                ));
                self.motor = Motor::Pwm;
                self.answer_request(now, Step::Health);
            }
            Step::SampleRate => {
                self.warn(format!("{no_answer}; assuming 476 µs per sample"));
                self.start_scan(now);
            }
        }
    }

    /// Runs the current phase over the buffered bytes until it needs more.
    fn process(&mut self, now: u64) {
        loop {
            match &mut self.phase {
                Phase::Idle | Phase::Settling { .. } => {
                    self.discard_buffer();
                    return;
                }
                Phase::Awaiting(pending) if !pending.got_descriptor => {
                    match codec::hunt_descriptor(&self.buf, &pending.answer) {
                        Hunt::Found(at) => {
                            pending.got_descriptor = true;
                            let answer = pending.answer;
                            let step = pending.step;
                            self.stats.bytes_discarded += at as u64;
                            self.consume(at + codec::DESCRIPTOR_LEN);
                            if step == Step::Scan {
                                self.on_scan_descriptor(now, &answer);
                            }
                        }
                        Hunt::NotYet { discard } => {
                            self.stats.bytes_discarded += discard as u64;
                            self.consume(discard);
                            return;
                        }
                    }
                }
                Phase::Awaiting(pending) => {
                    let len = usize::try_from(pending.answer.len).unwrap_or(usize::MAX);
                    let step = pending.step;
                    let Some(payload) = self.buf.get(..len) else {
                        return;
                    };
                    let payload = payload.to_vec();
                    self.consume(len);
                    self.on_answer(now, step, &payload);
                }
                Phase::Scanning { .. } => {
                    self.parse_stream(now);
                    return;
                }
            }
        }
    }

    fn parse_stream(&mut self, now: u64) {
        let Phase::Scanning {
            parser, deadline, ..
        } = &mut self.phase
        else {
            return;
        };
        let events = &mut self.events;
        let reads = &self.reads;
        let base = self.buf_offset;
        let mut read_index = 0;
        let mut emitted = 0u64;
        let mut emit = |output: CapsuleOutput, end: usize| {
            let sample = match output {
                CapsuleOutput::Sample(sample) => sample,
                CapsuleOutput::RevolutionComplete => {
                    events.push_back(LidarEvent::RevolutionComplete);
                    return;
                }
            };
            let end = base + end as u64;
            while reads
                .get(read_index)
                .is_some_and(|&(read_end, _)| read_end < end)
            {
                read_index += 1;
            }
            let arrival_ns = reads.get(read_index).map_or(now, |&(_, t)| t);
            events.push_back(LidarEvent::Sample(ArrivedSample { sample, arrival_ns }));
            emitted += 1;
        };
        let (consumed, frames) = match parser {
            StreamParser::Nodes(p) => p.parse(&self.buf, &mut self.stats, |sample, end| {
                emit(CapsuleOutput::Sample(sample), end)
            }),
            StreamParser::Capsules(p) => p.parse(&self.buf, &mut self.stats, &mut emit),
        };
        if frames > 0 {
            *deadline = deadline_after(now, self.config.answer_timeout_ms);
        }
        self.stats.samples_emitted += emitted;
        self.consume(consumed);
        if self.stats.resyncs > self.resyncs_reported && now >= self.next_resync_report {
            let lost = self.stats.resyncs - self.resyncs_reported;
            self.resyncs_reported = self.stats.resyncs;
            self.next_resync_report = deadline_after(now, 1000);
            self.warn(format!(
                "scan stream lost framing {lost} time(s); resynchronised"
            ));
        }
    }
}

impl LidarDriver for Rplidar {
    fn kind(&self) -> LidarKind {
        LidarKind::Rplidar
    }

    fn start(&mut self, now_ns: u64) {
        self.transmits.clear();
        self.motor = Motor::Unknown;
        self.begin(now_ns, self.config.reset_on_start);
    }

    fn stop(&mut self, _now_ns: u64) {
        self.transmits.push_back(Transmit::Write(codec::stop()));
        match self.motor {
            Motor::Pwm => self
                .transmits
                .push_back(Transmit::Write(codec::set_motor_pwm(0))),
            Motor::Dtr => self.transmits.push_back(Transmit::SetDtr(true)),
            Motor::Unknown => {}
        }
        self.discard_buffer();
        self.phase = Phase::Idle;
    }

    fn handle_input(&mut self, now_ns: u64, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        self.stats.bytes_in += bytes.len() as u64;
        self.last_read_ns = Some(now_ns);
        self.buf.extend_from_slice(bytes);
        self.reads
            .push_back((self.buf_offset + self.buf.len() as u64, now_ns));
        self.process(now_ns);
    }

    fn handle_timeout(&mut self, now_ns: u64) {
        match std::mem::replace(&mut self.phase, Phase::Idle) {
            Phase::Settling {
                until,
                info_attempts,
            } if now_ns >= until => {
                self.discard_buffer();
                self.transmits.push_back(Transmit::FlushInput);
                self.request(
                    now_ns,
                    Step::Info,
                    info_attempts,
                    self.config.info_timeout_ms,
                );
            }
            Phase::Awaiting(pending) if now_ns >= pending.deadline => {
                self.on_timeout(now_ns, pending);
            }
            Phase::Scanning { deadline, .. } if now_ns >= deadline => {
                self.warn(
                    "scan stream went silent (the device may have been reset); restarting the \
                     handshake"
                        .into(),
                );
                self.begin(now_ns, false);
            }
            other => self.phase = other,
        }
    }

    fn poll_timeout(&self) -> Option<u64> {
        match &self.phase {
            Phase::Idle => None,
            Phase::Settling { until, .. } => Some(*until),
            Phase::Awaiting(pending) => Some(pending.deadline),
            Phase::Scanning { deadline, .. } => Some(*deadline),
        }
    }

    fn poll_read_deadline(&self) -> Option<u64> {
        let Phase::Scanning {
            parser: StreamParser::Capsules(parser),
            capsule_ns,
            ..
        } = &self.phase
        else {
            return None;
        };
        let needed = parser.bytes_to_revolution_end()?;
        let missing = needed.saturating_sub(self.buf.len());
        Some(revolution_read_deadline(
            self.last_read_ns?,
            missing,
            *capsule_ns,
        ))
    }

    fn poll_transmit(&mut self) -> Option<Transmit> {
        self.transmits.pop_front()
    }

    fn poll_event(&mut self) -> Option<LidarEvent> {
        self.events.pop_front()
    }

    fn stats(&self) -> DriverStats {
        self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::{DeviceInfo, RawSample};

    const INFO_DESC: [u8; 7] = [0xA5, 0x5A, 0x14, 0x00, 0x00, 0x00, 0x04];
    const HEALTH_DESC: [u8; 7] = [0xA5, 0x5A, 0x03, 0x00, 0x00, 0x00, 0x06];
    const RATE_DESC: [u8; 7] = [0xA5, 0x5A, 0x04, 0x00, 0x00, 0x00, 0x15];
    const ACC_DESC: [u8; 7] = [0xA5, 0x5A, 0x04, 0x00, 0x00, 0x00, 0xFF];
    const SCAN_DESC: [u8; 7] = [0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81];
    const EXPRESS_DESC: [u8; 7] = [0xA5, 0x5A, 0x54, 0x00, 0x00, 0x40, 0x82];
    const SERIAL: [u8; 16] = [
        0x9E, 0xE2, 0x9A, 0xF0, 0xC4, 0xE3, 0x9E, 0xD5, 0xA3, 0xE5, 0x9E, 0xF2, 0x5A, 0x63, 0x3E,
        0x1B,
    ];
    const SERIAL_TEXT: &str = "9EE29AF0C4E39ED5A3E59EF25A633E1B";
    const BANNER: &[u8] = b"RP LIDAR System.\r\nFirmware Ver 1.25 - rc2, HW Ver 5\r\nModel: 18\r\n";

    fn ms(t: u64) -> u64 {
        t * MS
    }

    fn info_answer(model: u8, fw_major: u8, fw_minor: u8) -> Vec<u8> {
        let mut v = INFO_DESC.to_vec();
        v.extend_from_slice(&[model, fw_minor, fw_major, 0x05]);
        v.extend_from_slice(&SERIAL);
        v
    }

    fn answer(desc: [u8; 7], payload: &[u8]) -> Vec<u8> {
        [&desc[..], payload].concat()
    }

    fn tx(d: &mut Rplidar) -> Vec<Transmit> {
        std::iter::from_fn(|| d.poll_transmit()).collect()
    }

    fn ev(d: &mut Rplidar) -> Vec<LidarEvent> {
        std::iter::from_fn(|| d.poll_event()).collect()
    }

    fn w(bytes: &[u8]) -> Transmit {
        Transmit::Write(bytes.to_vec())
    }

    /// STOP, the 100 ms wait, flush and the first GET_INFO.
    fn to_get_info(d: &mut Rplidar) {
        d.start(0);
        assert_eq!(tx(d), [w(&[0xA5, 0x25])]);
        assert_eq!(d.poll_timeout(), Some(ms(100)));
        d.handle_timeout(ms(99));
        assert!(tx(d).is_empty());
        d.handle_timeout(ms(100));
        assert_eq!(tx(d), [Transmit::FlushInput, w(&[0xA5, 0x50])]);
        assert_eq!(d.poll_timeout(), Some(ms(600)));
    }

    #[test]
    fn validation_names_the_key_and_the_allowed_range() {
        assert_eq!(RplidarConfig::default().validate(), Ok(()));
        let bad = |config: RplidarConfig| config.validate().unwrap_err().to_string();
        let message = bad(RplidarConfig {
            baud: 0,
            ..RplidarConfig::default()
        });
        assert_eq!(
            message,
            "`baud` = 0 is out of range (allowed: 9600 to 4000000)"
        );
        let message = bad(RplidarConfig {
            answer_timeout_ms: u64::MAX,
            ..RplidarConfig::default()
        });
        assert!(
            message.starts_with("`answer_timeout_ms` = 18446744073709551615"),
            "{message}"
        );
        let message = bad(RplidarConfig {
            info_attempts: 0,
            ..RplidarConfig::default()
        });
        assert!(message.starts_with("`info_attempts` = 0"), "{message}");
    }

    #[test]
    fn a1_express_handshake_and_samples() {
        let mut d = Rplidar::new(RplidarConfig::default());
        assert_eq!(d.kind(), LidarKind::Rplidar);
        to_get_info(&mut d);
        // Stale nodes and a stale SCAN descriptor before the answer, split over two reads.
        let mut input = vec![0xBE, 0x01, 0x2D, 0x70, 0x17];
        input.extend_from_slice(&SCAN_DESC);
        input.extend(info_answer(0x18, 1, 29));
        d.handle_input(ms(110), &input[..15]);
        assert!(ev(&mut d).is_empty());
        d.handle_input(ms(111), &input[15..]);
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Info(DeviceInfo {
                model: "A1".into(),
                firmware: "1.29".into(),
                hardware: 5,
                serial: SERIAL_TEXT.into(),
            })]
        );
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x52])]);
        assert_eq!(d.poll_timeout(), Some(ms(2111)));

        d.handle_input(ms(120), &answer(HEALTH_DESC, &[0, 0, 0]));
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Health {
                status: HealthStatus::Good,
                error_code: 0
            }]
        );
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x59])]);

        d.handle_input(ms(130), &answer(RATE_DESC, &[0xDC, 0x01, 0xFA, 0x00]));
        assert_eq!(
            tx(&mut d),
            [
                Transmit::SetDtr(false),
                w(&[0xA5, 0x82, 0x05, 0x00, 0x00, 0x00, 0x00, 0x00, 0x22])
            ]
        );
        assert!(ev(&mut d).is_empty());

        d.handle_input(ms(140), &EXPRESS_DESC);
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Scanning {
                sample_period_ns: 250_000
            }]
        );
        assert_eq!(d.poll_timeout(), Some(ms(5140)), "spin-up allowance");

        let samples: [(u16, u8); 32] = std::array::from_fn(|k| (2000 + k as u16, 0));
        let c0 = capsules::tests::encode(0, false, &samples);
        let c1 = capsules::tests::encode(30 * 64, false, &samples);
        d.handle_input(ms(150), &c0);
        d.handle_input(ms(160), &c1[..50]);
        assert!(ev(&mut d).is_empty());
        d.handle_input(ms(170), &c1[50..]);
        let events = ev(&mut d);
        assert_eq!(events.len(), 32);
        for (k, e) in events.iter().enumerate() {
            let want = RawSample {
                angle_deg: 30.0 * k as f32 / 32.0,
                range_m: f32::from(2000 + k as u16) / 1000.0,
                quality: 47,
                new_revolution: false,
            };
            assert_eq!(
                *e,
                LidarEvent::Sample(ArrivedSample {
                    sample: want,
                    arrival_ns: ms(170)
                })
            );
        }
        assert_eq!(
            d.poll_timeout(),
            Some(ms(2170)),
            "watchdog re-armed by good frames"
        );

        let stats = d.stats();
        assert_eq!(stats.bytes_in, (input.len() + 10 + 11 + 7 + 168) as u64);
        assert_eq!(stats.bytes_discarded, 12, "stale node and stale descriptor");
        assert_eq!(stats.samples_emitted, 32);
        assert_eq!((stats.frames_rejected, stats.resyncs), (0, 0));

        d.stop(ms(200));
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x25]), Transmit::SetDtr(true)]);
        assert_eq!(d.poll_timeout(), None);
    }

    /// An A1 (firmware 1.29, 250 µs a sample) streaming express capsules since 140 ms.
    fn express_scanning() -> Rplidar {
        let mut d = Rplidar::new(RplidarConfig::default());
        to_get_info(&mut d);
        d.handle_input(ms(111), &info_answer(0x18, 1, 29));
        d.handle_input(ms(120), &answer(HEALTH_DESC, &[0, 0, 0]));
        d.handle_input(ms(130), &answer(RATE_DESC, &[0xDC, 0x01, 0xFA, 0x00]));
        d.handle_input(ms(140), &EXPRESS_DESC);
        assert!(matches!(
            ev(&mut d).last(),
            Some(LidarEvent::Scanning { .. })
        ));
        tx(&mut d);
        d
    }

    #[test]
    fn a_capsule_takes_its_samples_time_or_its_wire_time() {
        // 32 × 250 µs = 8 ms; 84 bytes at 115 200 Bd take 7.29 ms.
        assert_eq!(capsule_period_ns(250, 115_200), ms(8));
        // 32 × 100 µs = 3.2 ms, but the wire needs 7.29 ms.
        assert_eq!(capsule_period_ns(100, 115_200), 7_291_666);
        // Half a capsule missing after a read at 1 s: 4 ms, plus the margin.
        assert_eq!(
            revolution_read_deadline(ms(1000), 42, ms(8)),
            ms(1004) + READ_DEADLINE_MARGIN_NS
        );
        assert_eq!(revolution_read_deadline(u64::MAX - 1, 84, ms(8)), u64::MAX);
    }

    #[test]
    fn express_revolutions_close_and_are_read_when_their_last_capsule_is_in() {
        let mut d = express_scanning();
        assert_eq!(d.poll_read_deadline(), None, "no capsule yet");
        // A rotor turning 30° a capsule (8 ms): capsule 12 starts at 0° again, so the wrap
        // falls between capsules 11 and 12.
        let samples: [(u16, u8); 32] = std::array::from_fn(|k| (2000 + k as u16, 0));
        let capsule = |i: u64| capsules::tests::encode((i % 12) as u16 * 30 * 64, false, &samples);
        // The way crate::acquisition assembles them: `feed` returns the revolutions closed.
        let mut assembler = crate::timing::RevolutionAssembler::new(Default::default());
        let mut feed = |d: &mut Rplidar, at: u64, bytes: &[u8]| {
            d.handle_input(at, bytes);
            let mut closed = Vec::new();
            for event in ev(d) {
                match event {
                    LidarEvent::Sample(s) => closed.extend(assembler.push(s)),
                    LidarEvent::RevolutionComplete => closed.extend(assembler.complete()),
                    other => panic!("unexpected {other:?}"),
                }
            }
            closed
        };
        feed(&mut d, ms(150), &capsule(0));
        feed(&mut d, ms(158), &capsule(1));
        // Capsule 1 held: the revolution's last sample is capsule 11's, decoded once capsule
        // 12 is in: 11 capsules of 8 ms after this read.
        assert_eq!(d.poll_read_deadline(), Some(ms(158 + 88) + MS));
        feed(&mut d, ms(162), &capsule(2)[..42]);
        assert_eq!(d.poll_read_deadline(), Some(ms(162 + 84) + MS));
        feed(&mut d, ms(166), &capsule(2)[42..]);
        // The first revolution: from the flagged sample of capsule 12 to capsule 23's last.
        for i in 3..24 {
            assert!(feed(&mut d, ms(150 + 8 * i), &capsule(i)).is_empty());
        }
        assert_eq!(d.poll_read_deadline(), Some(ms(150 + 8 * 23 + 8) + MS));
        // Capsule 24 (0°) completes the revolution with this read, not with capsule 25's.
        let closed = feed(&mut d, ms(150 + 8 * 24), &capsule(24));
        assert_eq!(closed.len(), 1);
        assert_eq!(closed[0].samples.len(), 12 * 32);
        assert!(closed[0].t1_ns > closed[0].samples[383].t_ns);
        // The next one is due 12 capsules on; capsule 25 closes nothing more.
        assert_eq!(d.poll_read_deadline(), Some(ms(150 + 8 * 36) + MS));
        assert!(feed(&mut d, ms(150 + 8 * 25), &capsule(25)).is_empty());
    }

    #[test]
    fn a2_standard_handshake_uses_pwm() {
        let config = RplidarConfig {
            scan_mode: ScanMode::Standard,
            ..RplidarConfig::default()
        };
        let mut d = Rplidar::new(config);
        to_get_info(&mut d);
        d.handle_input(ms(110), &info_answer(0x28, 1, 29));
        assert!(matches!(&ev(&mut d)[..], [LidarEvent::Info(i)] if i.model == "A2"));
        assert_eq!(
            tx(&mut d),
            [w(&[0xA5, 0xFF, 0x04, 0x00, 0x00, 0x00, 0x00, 0x5E])]
        );
        d.handle_input(ms(120), &answer(ACC_DESC, &[1, 0, 0, 0]));
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x52])]);
        // Error code 0x0102 little-endian.
        d.handle_input(ms(130), &answer(HEALTH_DESC, &[1, 0x02, 0x01]));
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Health {
                status: HealthStatus::Warning,
                error_code: 0x0102
            }]
        );
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x59])]);
        d.handle_input(ms(140), &answer(RATE_DESC, &[0xDC, 0x01, 0xFA, 0x00]));
        assert_eq!(
            tx(&mut d),
            [w(&[0xA5, 0xF0, 0x02, 0x94, 0x02, 0xC1]), w(&[0xA5, 0x20])]
        );

        let mut input = SCAN_DESC.to_vec();
        input.extend_from_slice(&[0xBD, 0x01, 0x00, 0x40, 0x1F]); // S, 0°, 2 m
        input.extend(nodes::tests::encode(false, 47, 64, 6000)); // 1°, 1.5 m
        input.extend(nodes::tests::encode(false, 47, 128, 0)); // 2°, no return
        d.handle_input(ms(150), &input);
        assert_eq!(
            ev(&mut d),
            [
                LidarEvent::Scanning {
                    sample_period_ns: 476_000
                },
                LidarEvent::Sample(ArrivedSample {
                    sample: RawSample {
                        angle_deg: 0.0,
                        range_m: 2.0,
                        quality: 47,
                        new_revolution: true
                    },
                    arrival_ns: ms(150),
                }),
                LidarEvent::Sample(ArrivedSample {
                    sample: RawSample {
                        angle_deg: 1.0,
                        range_m: 1.5,
                        quality: 47,
                        new_revolution: false
                    },
                    arrival_ns: ms(150),
                }),
            ]
        );
        // The last node waits for its successor, then carries its own read's time.
        d.handle_input(ms(160), &nodes::tests::encode(false, 47, 192, 4));
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Sample(ArrivedSample {
                sample: RawSample {
                    angle_deg: 2.0,
                    range_m: 0.0,
                    quality: 47,
                    new_revolution: false
                },
                arrival_ns: ms(150),
            })]
        );
        d.stop(ms(200));
        assert_eq!(
            tx(&mut d),
            [w(&[0xA5, 0x25]), w(&[0xA5, 0xF0, 0x02, 0x00, 0x00, 0x57])]
        );
    }

    #[test]
    fn old_firmware_skips_samplerate_and_express() {
        let mut d = Rplidar::new(RplidarConfig::default());
        to_get_info(&mut d);
        d.handle_input(ms(110), &info_answer(0x18, 1, 10));
        ev(&mut d);
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x52])]);
        d.handle_input(ms(120), &answer(HEALTH_DESC, &[0, 0, 0]));
        assert_eq!(tx(&mut d), [Transmit::SetDtr(false), w(&[0xA5, 0x20])]);
        let events = ev(&mut d);
        assert!(matches!(
            &events[..],
            [LidarEvent::Health { .. }, LidarEvent::Warning(_)]
        ));
        d.handle_input(ms(130), &SCAN_DESC);
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Scanning {
                sample_period_ns: 476_000
            }]
        );
    }

    #[test]
    fn get_info_retries_then_fails() {
        let mut d = Rplidar::new(RplidarConfig::default());
        to_get_info(&mut d);
        for (attempt, t) in [(1, 600), (2, 1100), (3, 1600)] {
            d.handle_timeout(ms(t));
            assert_eq!(
                tx(&mut d),
                [w(&[0xA5, 0x50])],
                "retry after attempt {attempt}"
            );
            assert!(matches!(&ev(&mut d)[..], [LidarEvent::Warning(_)]));
            assert_eq!(d.poll_timeout(), Some(ms(t + 500)));
        }
        d.handle_timeout(ms(2100));
        assert!(tx(&mut d).is_empty());
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Failed(DriverError::NoAnswer {
                command: "GET_INFO",
                attempts: 4
            })]
        );
        assert_eq!(d.poll_timeout(), None);
        // Idle: input is dropped and counted.
        d.handle_input(ms(2200), &info_answer(0x18, 1, 29));
        assert!(ev(&mut d).is_empty());
        assert_eq!(d.stats().bytes_discarded, 27);
    }

    #[test]
    fn late_answer_after_a_retry_is_accepted() {
        let mut d = Rplidar::new(RplidarConfig::default());
        to_get_info(&mut d);
        d.handle_timeout(ms(600));
        tx(&mut d);
        ev(&mut d);
        d.handle_input(ms(700), &info_answer(0x18, 1, 29));
        assert!(matches!(&ev(&mut d)[..], [LidarEvent::Info(_)]));
    }

    #[test]
    fn reset_skips_the_banner() {
        let config = RplidarConfig {
            reset_on_start: true,
            ..RplidarConfig::default()
        };
        let mut d = Rplidar::new(config);
        d.start(0);
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x40])]);
        assert_eq!(d.poll_timeout(), Some(ms(1000)));
        d.handle_input(ms(20), &BANNER[..30]);
        d.handle_timeout(ms(1000));
        assert_eq!(tx(&mut d), [Transmit::FlushInput, w(&[0xA5, 0x50])]);
        // Late banner bytes before the answer are skipped by descriptor hunting.
        let mut input = BANNER[30..].to_vec();
        input.extend(info_answer(0x18, 1, 29));
        d.handle_input(ms(1010), &input);
        assert!(matches!(&ev(&mut d)[..], [LidarEvent::Info(i)] if i.serial == SERIAL_TEXT));
        assert_eq!(d.stats().bytes_discarded, BANNER.len() as u64);
        // After a reset, GET_INFO is retried up to 30 times.
        let mut d = Rplidar::new(RplidarConfig {
            reset_on_start: true,
            ..RplidarConfig::default()
        });
        d.start(0);
        d.handle_timeout(ms(1000));
        for i in 1..30 {
            d.handle_timeout(ms(1000 + 500 * i));
        }
        assert!(
            ev(&mut d)
                .iter()
                .all(|e| matches!(e, LidarEvent::Warning(_)))
        );
        d.handle_timeout(ms(1000 + 500 * 30));
        assert_eq!(
            ev(&mut d),
            [LidarEvent::Failed(DriverError::NoAnswer {
                command: "GET_INFO",
                attempts: 30
            })]
        );
    }

    #[test]
    fn public_reset_sends_reset() {
        let mut d = Rplidar::new(RplidarConfig::default());
        to_get_info(&mut d);
        d.reset(ms(300));
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x40])]);
        assert_eq!(d.poll_timeout(), Some(ms(1300)));
    }

    #[test]
    fn health_error_fails() {
        let mut d = Rplidar::new(RplidarConfig::default());
        to_get_info(&mut d);
        d.handle_input(ms(110), &info_answer(0x18, 1, 29));
        ev(&mut d);
        tx(&mut d);
        d.handle_input(ms(120), &answer(HEALTH_DESC, &[2, 0x05, 0x80]));
        let events = ev(&mut d);
        assert_eq!(
            events[0],
            LidarEvent::Health {
                status: HealthStatus::Error,
                error_code: 0x8005
            }
        );
        assert!(
            matches!(&events[1], LidarEvent::Failed(DriverError::Device(m)) if m.contains("0x8005"))
        );
        assert!(tx(&mut d).is_empty());
        assert_eq!(d.poll_timeout(), None);
    }

    #[test]
    fn silent_stream_restarts_the_handshake() {
        let config = RplidarConfig {
            scan_mode: ScanMode::Standard,
            ..RplidarConfig::default()
        };
        let mut d = Rplidar::new(config);
        to_get_info(&mut d);
        d.handle_input(ms(110), &info_answer(0x18, 1, 29));
        d.handle_input(ms(120), &answer(HEALTH_DESC, &[0, 0, 0]));
        d.handle_input(ms(130), &answer(RATE_DESC, &[0xDC, 0x01, 0xFA, 0x00]));
        d.handle_input(ms(140), &SCAN_DESC);
        ev(&mut d);
        tx(&mut d);
        // Garbage does not count as progress.
        d.handle_input(ms(3000), &[0x00; 40]);
        assert!(matches!(&ev(&mut d)[..], [LidarEvent::Warning(m)] if m.contains("framing")));
        assert_eq!(d.stats().resyncs, 1);
        assert_eq!(d.poll_timeout(), Some(ms(5140)));
        d.handle_timeout(ms(5140));
        assert!(matches!(&ev(&mut d)[..], [LidarEvent::Warning(_)]));
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x25])]);
        assert_eq!(d.poll_timeout(), Some(ms(5240)));
    }

    #[test]
    fn timeouts_too_long_to_represent_saturate_to_the_end_of_time() {
        // Found by fuzz/fuzz_targets/rplidar.rs (fuzz/regressions/rplidar/): `now + ms * MS`
        // overflowed for a configured timeout of more than u64::MAX / 1e6 ms.
        let never = u64::MAX;
        let config = RplidarConfig {
            stop_wait_ms: never,
            info_timeout_ms: never,
            reset_wait_ms: never,
            answer_timeout_ms: never,
            spinup_timeout_ms: never,
            ..RplidarConfig::default()
        };
        let mut d = Rplidar::new(config.clone());
        d.start(ms(1));
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x25])]);
        assert_eq!(
            d.poll_timeout(),
            Some(never),
            "STOP settles until the end of time"
        );
        d.handle_timeout(never);
        assert_eq!(tx(&mut d), [Transmit::FlushInput, w(&[0xA5, 0x50])]);
        assert_eq!(
            d.poll_timeout(),
            Some(never),
            "GET_INFO waits until the end of time"
        );
        d.handle_timeout(never);
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x50])], "the retry is sent");
        assert_eq!(d.poll_timeout(), Some(never));

        let mut d = Rplidar::new(config);
        d.reset(ms(1));
        assert_eq!(tx(&mut d), [w(&[0xA5, 0x40])]);
        assert_eq!(
            d.poll_timeout(),
            Some(never),
            "RESET settles until the end of time"
        );
    }

    #[test]
    fn config_deserialises_with_defaults() {
        let c: RplidarConfig = toml::from_str("scan_mode = \"standard\"\nmotor_pwm = 500").unwrap();
        assert_eq!(c.scan_mode, ScanMode::Standard);
        assert_eq!(c.motor_pwm, 500);
        assert_eq!(
            (c.baud, c.answer_timeout_ms, c.info_attempts),
            (115_200, 2000, 4)
        );
        assert!(toml::from_str::<RplidarConfig>("scan_mod = \"standard\"").is_err());
    }
}
