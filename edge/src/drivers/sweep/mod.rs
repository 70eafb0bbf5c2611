//! Scanse Sweep driver: a sans-I/O [`LidarDriver`] (research notes §2).
//!
//! The session mirrors libsweep's verified sequence (§2.5), with retries and validation added:
//!
//! ```text
//! start: DX ─35 ms─ FlushInput, DX → DX00P ─ ID ─ IV (→ Info) ─ MI
//!        ─ [MSnn if the configured speed differs, or MS05 if the motor is at 0 Hz]
//!        ─ [LRnn if configured] ─ MZ every 500 ms until 00 ─ DS → Scanning, data blocks
//! DS 12 (motor not stable): Warning, wait `ds_retry_interval_ms`, poll MZ, DS again.
//! DS 13 (motor stopped):    Warning, MS with the configured speed (05 if none, as libsweep does),
//!                           settle, DS again.
//! stop: DX.   No valid data block for `silence_timeout_ms` while scanning: Warning + start over.
//! ```
//!
//! Unanswered commands are re-sent up to `max_attempts` times, then the driver reports
//! [`DriverError::NoAnswer`]. Receipts are hunted for by their two-letter echo, so garbage and
//! data blocks still in flight (e.g. before `DX00P\n`) are skipped.
//!
//! Data blocks are framed by [`block::Framer`]: a block is emitted only once the aligned block
//! after it confirms it (one block of latency), so a window that passes the weak mod-255
//! checksum by chance is not emitted. Blocks with the communication-error bit (e0) are
//! counted ([`Sweep::error_blocks`]) and not emitted; as libsweep does, their sync bit still cuts
//! revolutions: it is carried to the next emitted sample's `new_revolution`.

pub mod block;
pub mod protocol;
#[cfg(test)]
mod tests;

use std::collections::VecDeque;

use crate::lidar::{
    ArrivedSample, DeviceInfo, DriverError, DriverStats, LidarDriver, LidarEvent, LidarKind,
    RawSample, Transmit,
};
use block::{DataBlock, Framer};
use protocol::{Command, DeviceStatus, Param, Receipt, Status};

const MS: u64 = 1_000_000;
/// libsweep's pause between the first DX and the flush.
const DX_DRAIN_NS: u64 = 35 * MS;
/// MZ polling interval while the motor settles (libsweep: 500 ms).
const MZ_POLL_NS: u64 = 500 * MS;
/// Sample rate assumed if the device reports 0 Hz (code 01's lower bound).
const FALLBACK_SAMPLE_HZ: u16 = 500;

/// Sweep driver settings (the `[sweep]` section of the edge config). All fields have defaults.
#[derive(Debug, Clone, PartialEq, Eq, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepConfig {
    /// Motor speed to set before scanning, 1–10 Hz; `None` keeps the device's (persisted) speed.
    pub motor_hz: Option<u8>,
    /// Sample-rate code to set: 1 = 500–600 Hz, 2 = 750–800 Hz, 3 = 1000–1050 Hz; `None` keeps
    /// the device's.
    pub sample_rate_code: Option<u8>,
    /// How long the motor may take to report a stable speed (MZ 00) before giving up.
    pub settle_timeout_ms: u64,
    /// How long to wait for a receipt before re-sending the command.
    pub answer_timeout_ms: u64,
    /// Pause after `DS` answered 12 (motor not stable) before polling MZ and retrying.
    pub ds_retry_interval_ms: u64,
    /// While scanning, restart the session after this long without a valid data block.
    pub silence_timeout_ms: u64,
    /// Times a command is sent without an answer before [`DriverError::NoAnswer`].
    pub max_attempts: u32,
    /// Times `DS` may be refused (12/13) in one session before [`DriverError::Device`].
    pub max_ds_retries: u32,
}

impl Default for SweepConfig {
    fn default() -> Self {
        Self {
            motor_hz: None,
            sample_rate_code: None,
            settle_timeout_ms: 15_000,
            answer_timeout_ms: 1_000,
            ds_retry_interval_ms: 1_000,
            silence_timeout_ms: 2_000,
            max_attempts: 3,
            max_ds_retries: 5,
        }
    }
}

/// An invalid [`SweepConfig`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SweepConfigError {
    /// Motor speed outside 1–10 Hz (0 would stop the motor, and DS then refuses to scan).
    #[error("sweep motor_hz must be 1..=10, got {0}")]
    MotorHz(u8),
    /// Sample-rate code other than 1, 2 or 3.
    #[error("sweep sample_rate_code must be 1, 2 or 3, got {0}")]
    SampleRateCode(u8),
    /// A timeout or count that must be positive is zero.
    #[error("sweep {0} must be greater than zero")]
    Zero(&'static str),
}

/// Where the session is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Not talking to the device; input is discarded.
    Idle,
    /// First DX sent; everything is ignored until the flush at `until_ns`.
    Draining { until_ns: u64 },
    /// Waiting for the receipt to `cmd`.
    Awaiting {
        cmd: Command,
        attempts: u32,
        deadline_ns: u64,
    },
    /// Waiting to poll MZ again.
    Pause { until_ns: u64 },
    /// Data blocks are flowing.
    Streaming { last_block_ns: u64 },
    /// DX sent by [`LidarDriver::stop`]; idle after its receipt or the deadline.
    Stopping { deadline_ns: u64 },
}

/// Received bytes not yet parsed, with the time each read arrived.
#[derive(Debug, Default)]
struct Rx {
    buf: Vec<u8>,
    /// Stream offset of `buf[0]`.
    base: u64,
    /// `(stream offset just past the read, arrival ns)`, oldest first.
    chunks: VecDeque<(u64, u64)>,
}

impl Rx {
    fn push(&mut self, now_ns: u64, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
        let end = self.base + self.buf.len() as u64;
        match self.chunks.back_mut() {
            Some(last) if last.1 == now_ns => last.0 = end,
            _ => self.chunks.push_back((end, now_ns)),
        }
    }

    /// Arrival time of the read that delivered the byte just before stream offset `end`.
    fn arrival_ns(&self, end: u64) -> u64 {
        self.chunks
            .iter()
            .find(|c| c.0 >= end)
            .or(self.chunks.back())
            .map_or(0, |c| c.1)
    }

    /// Drop the first `n` bytes.
    fn consume(&mut self, n: usize) {
        let n = n.min(self.buf.len());
        self.buf.drain(..n);
        self.base += n as u64;
        while self.chunks.front().is_some_and(|c| c.0 <= self.base) {
            self.chunks.pop_front();
        }
    }
}

/// The Scanse Sweep protocol driver (sans-I/O; see the module docs for the session).
#[derive(Debug)]
pub struct Sweep {
    config: SweepConfig,
    phase: Phase,
    rx: Rx,
    framer: Framer,
    transmits: VecDeque<Transmit>,
    events: VecDeque<LidarEvent>,
    stats: DriverStats,
    error_blocks: u64,
    /// An error block carried the sync bit; the next emitted sample starts the revolution.
    pending_sync: bool,
    info: Option<DeviceInfo>,
    device_status: Option<DeviceStatus>,
    motor_hz: u8,
    sample_rate_hz: u16,
    /// What to send once MZ reports 00.
    after_settle: Command,
    settle_deadline_ns: u64,
    ds_refusals: u32,
}

impl Sweep {
    /// A driver for `config`, idle until [`LidarDriver::start`].
    pub fn new(config: SweepConfig) -> Result<Self, SweepConfigError> {
        if let Some(hz) = config.motor_hz.filter(|hz| !(1..=10).contains(hz)) {
            return Err(SweepConfigError::MotorHz(hz));
        }
        if let Some(code) = config.sample_rate_code.filter(|c| !(1..=3).contains(c)) {
            return Err(SweepConfigError::SampleRateCode(code));
        }
        for (name, value) in [
            ("settle_timeout_ms", config.settle_timeout_ms),
            ("answer_timeout_ms", config.answer_timeout_ms),
            ("ds_retry_interval_ms", config.ds_retry_interval_ms),
            ("silence_timeout_ms", config.silence_timeout_ms),
            ("max_attempts", u64::from(config.max_attempts)),
        ] {
            if value == 0 {
                return Err(SweepConfigError::Zero(name));
            }
        }
        Ok(Self {
            config,
            phase: Phase::Idle,
            rx: Rx::default(),
            framer: Framer::new(Framer::max_step_for(10, 500)),
            transmits: VecDeque::new(),
            events: VecDeque::new(),
            stats: DriverStats::default(),
            error_blocks: 0,
            pending_sync: false,
            info: None,
            device_status: None,
            motor_hz: 0,
            sample_rate_hz: 0,
            after_settle: Command::Ds,
            settle_deadline_ns: 0,
            ds_refusals: 0,
        })
    }

    /// The settings this driver was built with.
    pub fn config(&self) -> &SweepConfig {
        &self.config
    }

    /// Identity from the last IV receipt.
    pub fn device_info(&self) -> Option<&DeviceInfo> {
        self.info.as_ref()
    }

    /// Settings from the last ID receipt (as reported, before any MS/LR of this session).
    pub fn device_status(&self) -> Option<&DeviceStatus> {
        self.device_status.as_ref()
    }

    /// Motor speed in Hz the session is using (from ID/MI, or the MS this driver sent).
    pub fn motor_hz(&self) -> u8 {
        self.motor_hz
    }

    /// Nominal sample rate in Hz (from ID, or the LR code this driver set: 500/750/1000).
    pub fn sample_rate_hz(&self) -> u16 {
        self.sample_rate_hz
    }

    /// Valid data blocks with the communication-error bit (e0) set, which are not emitted.
    pub fn error_blocks(&self) -> u64 {
        self.error_blocks
    }

    /// Whether the driver is in the scanning phase (after `DS 00`).
    pub fn is_scanning(&self) -> bool {
        matches!(self.phase, Phase::Streaming { .. })
    }

    fn ms(v: u64) -> u64 {
        v.saturating_mul(MS)
    }

    fn warn(&mut self, msg: String) {
        self.events.push_back(LidarEvent::Warning(msg));
    }

    fn fail(&mut self, err: DriverError) {
        self.phase = Phase::Idle;
        self.framer.reset();
        self.events.push_back(LidarEvent::Failed(err));
    }

    /// Send `cmd` and wait for its receipt.
    fn send(&mut self, now_ns: u64, cmd: Command) {
        self.send_attempt(now_ns, cmd, 1);
    }

    /// Send `cmd` for the `attempts`-th time and wait for its receipt.
    fn send_attempt(&mut self, now_ns: u64, cmd: Command, attempts: u32) {
        self.transmits.push_back(Transmit::Write(cmd.encode()));
        self.phase = Phase::Awaiting {
            cmd,
            attempts,
            deadline_ns: now_ns.saturating_add(Self::ms(self.config.answer_timeout_ms)),
        };
    }

    /// Poll MZ until 00 (within the settle timeout), then send `then`.
    fn begin_settle(&mut self, now_ns: u64, then: Command) {
        self.after_settle = then;
        self.settle_deadline_ns = now_ns.saturating_add(Self::ms(self.config.settle_timeout_ms));
        self.send(now_ns, Command::Mz);
    }

    /// The motor speed is set: set the sample rate if configured, then settle and scan.
    fn after_motor(&mut self, now_ns: u64) {
        match self.config.sample_rate_code.and_then(Param::new) {
            Some(code) => self.send(now_ns, Command::Lr(code)),
            None => self.begin_settle(now_ns, Command::Ds),
        }
    }

    /// The configured motor speed, or libsweep's 5 Hz when none is configured.
    fn motor_target(&self) -> Param {
        self.config
            .motor_hz
            .and_then(Param::new)
            .unwrap_or(Param::DEFAULT_MOTOR_HZ)
    }

    /// Start over: the libsweep DX / 35 ms / flush / DX dance.
    fn restart(&mut self, now_ns: u64) {
        self.transmits.clear();
        self.discard_buffered();
        self.framer.reset();
        self.pending_sync = false;
        self.ds_refusals = 0;
        self.transmits
            .push_back(Transmit::Write(Command::Dx.encode()));
        self.phase = Phase::Draining {
            until_ns: now_ns.saturating_add(DX_DRAIN_NS),
        };
    }

    fn discard_buffered(&mut self) {
        let n = self.rx.buf.len();
        self.stats.bytes_discarded += n as u64;
        self.rx.consume(n);
    }

    fn on_receipt(&mut self, now_ns: u64, cmd: Command, receipt: Receipt) {
        match (cmd, receipt) {
            (Command::Dx, Receipt::Status(st)) => {
                if st != Status::Ok {
                    self.warn(format!("DX answered {st}; continuing"));
                }
                self.send(now_ns, Command::Id);
            }
            (Command::Id, Receipt::Device(d)) => {
                self.device_status = Some(d);
                self.motor_hz = d.motor_hz;
                self.sample_rate_hz = d.sample_rate_hz;
                self.send(now_ns, Command::Iv);
            }
            (Command::Iv, Receipt::Version(v)) => {
                if !v.model.eq_ignore_ascii_case("SWEEP") {
                    self.fail(DriverError::WrongDevice(format!(
                        "IV reports model {:?}, expected SWEEP",
                        v.model
                    )));
                    return;
                }
                let info = v.device_info();
                self.info = Some(info.clone());
                self.events.push_back(LidarEvent::Info(info));
                self.send(now_ns, Command::Mi);
            }
            (Command::Mi, Receipt::Value(hz)) => {
                self.motor_hz = hz;
                let wanted = match self.config.motor_hz {
                    Some(want) if want != hz => Some(self.motor_target()),
                    None if hz == 0 => Some(self.motor_target()),
                    _ => None,
                };
                match wanted {
                    Some(p) => self.send(now_ns, Command::Ms(p)),
                    None => self.after_motor(now_ns),
                }
            }
            (Command::Ms(p), Receipt::ParamStatus(_, st)) => match st {
                Status::Ok => {
                    self.motor_hz = p.value();
                    self.after_motor(now_ns);
                }
                Status::MotorNotStable => {
                    self.warn(format!(
                        "MS{:02}: motor speed still stabilising; waiting",
                        p.value()
                    ));
                    self.begin_settle(now_ns, Command::Ms(p));
                }
                other => self.fail(DriverError::Device(format!(
                    "MS{:02} (motor speed {} Hz) refused: {other}",
                    p.value(),
                    p.value()
                ))),
            },
            (Command::Lr(p), Receipt::ParamStatus(_, st)) => match st {
                Status::Ok => {
                    self.sample_rate_hz = match p.value() {
                        2 => 750,
                        3 => 1000,
                        _ => 500,
                    };
                    self.begin_settle(now_ns, Command::Ds);
                }
                Status::MotorNotStable => {
                    self.warn(format!("LR{:02}: motor not stable; waiting", p.value()));
                    self.begin_settle(now_ns, Command::Lr(p));
                }
                other => self.fail(DriverError::Device(format!(
                    "LR{:02} (sample-rate code) refused: {other}",
                    p.value()
                ))),
            },
            (Command::Mz, Receipt::Value(v)) => {
                if v == 0 {
                    let next = self.after_settle;
                    self.send(now_ns, next);
                } else if now_ns >= self.settle_deadline_ns {
                    self.fail(DriverError::Device(format!(
                        "motor speed not stable after {} ms (MZ {v:02})",
                        self.config.settle_timeout_ms
                    )));
                } else {
                    self.phase = Phase::Pause {
                        until_ns: now_ns.saturating_add(MZ_POLL_NS),
                    };
                }
            }
            (Command::Ds, Receipt::Status(st)) => self.on_ds(now_ns, st),
            (cmd, other) => self.fail(DriverError::Device(format!(
                "unexpected receipt to {}: {other:?}",
                cmd.name()
            ))),
        }
    }

    fn on_ds(&mut self, now_ns: u64, st: Status) {
        if st == Status::Ok {
            let sample_hz = if self.sample_rate_hz == 0 {
                FALLBACK_SAMPLE_HZ
            } else {
                self.sample_rate_hz
            };
            self.framer = Framer::new(Framer::max_step_for(
                u32::from(self.motor_hz),
                u32::from(sample_hz),
            ));
            self.events.push_back(LidarEvent::Scanning {
                sample_period_ns: 1_000_000_000 / u64::from(sample_hz),
            });
            self.phase = Phase::Streaming {
                last_block_ns: now_ns,
            };
            return;
        }
        self.ds_refusals += 1;
        if self.ds_refusals > self.config.max_ds_retries
            || !matches!(st, Status::MotorNotStable | Status::MotorStopped)
        {
            self.fail(DriverError::Device(format!(
                "DS refused: {st} ({} times)",
                self.ds_refusals
            )));
            return;
        }
        if st == Status::MotorStopped {
            let p = self.motor_target();
            self.warn(format!(
                "DS: motor stopped (0 Hz); setting MS{:02} and retrying",
                p.value()
            ));
            self.send(now_ns, Command::Ms(p));
        } else {
            let pause = Self::ms(self.config.ds_retry_interval_ms);
            self.warn(format!(
                "DS: motor speed not yet stable; retrying in {} ms",
                self.config.ds_retry_interval_ms
            ));
            let until_ns = now_ns.saturating_add(pause);
            self.after_settle = Command::Ds;
            self.settle_deadline_ns =
                until_ns.saturating_add(Self::ms(self.config.settle_timeout_ms));
            self.phase = Phase::Pause { until_ns };
        }
    }

    /// Parse whatever the current phase expects from the buffered bytes.
    fn process(&mut self, now_ns: u64) {
        let mut pos = 0usize;
        loop {
            let rest = self.rx.buf.get(pos..).unwrap_or_default();
            if rest.is_empty() {
                break;
            }
            let expected = match self.phase {
                Phase::Awaiting { cmd, .. } => cmd,
                Phase::Stopping { .. } => Command::Dx,
                Phase::Streaming { .. } => {
                    pos += self.feed_blocks(now_ns, pos);
                    break;
                }
                Phase::Idle | Phase::Draining { .. } | Phase::Pause { .. } => {
                    self.stats.bytes_discarded += rest.len() as u64;
                    pos += rest.len();
                    break;
                }
            };
            let hunt = protocol::hunt_receipt(expected, rest);
            pos += hunt.consumed;
            self.stats.bytes_discarded += hunt.discarded as u64;
            self.stats.frames_rejected += hunt.rejected as u64;
            let Some(receipt) = hunt.receipt else {
                break;
            };
            if matches!(self.phase, Phase::Stopping { .. }) {
                self.phase = Phase::Idle;
            } else {
                self.on_receipt(now_ns, expected, receipt);
            }
        }
        self.rx.consume(pos);
    }

    /// Frame data blocks from `rx.buf[start..]`; returns the bytes consumed.
    fn feed_blocks(&mut self, now_ns: u64, start: usize) -> usize {
        let data = self.rx.buf.get(start..).unwrap_or_default();
        let base = self.rx.base + start as u64;
        let rx = &self.rx;
        let events = &mut self.events;
        let stats = &mut self.stats;
        let error_blocks = &mut self.error_blocks;
        let pending_sync = &mut self.pending_sync;
        let mut any = false;
        let counts = self.framer.feed(data, |b: DataBlock, end| {
            any = true;
            if b.comm_error {
                *error_blocks += 1;
                *pending_sync |= b.sync;
                return;
            }
            let new_revolution = b.sync || std::mem::take(pending_sync);
            events.push_back(LidarEvent::Sample(ArrivedSample {
                sample: RawSample {
                    angle_deg: b.azimuth_deg(),
                    range_m: b.range_m(),
                    quality: b.strength,
                    new_revolution,
                },
                arrival_ns: rx.arrival_ns(base + end as u64),
            }));
            stats.samples_emitted += 1;
        });
        self.stats.bytes_discarded += counts.discarded;
        self.stats.frames_rejected += counts.rejected;
        self.stats.resyncs += counts.resyncs;
        if any {
            self.phase = Phase::Streaming {
                last_block_ns: now_ns,
            };
        }
        counts.consumed
    }
}

impl LidarDriver for Sweep {
    fn kind(&self) -> LidarKind {
        LidarKind::Sweep
    }

    fn start(&mut self, now_ns: u64) {
        self.restart(now_ns);
    }

    fn stop(&mut self, now_ns: u64) {
        self.transmits.clear();
        self.framer.reset();
        self.transmits
            .push_back(Transmit::Write(Command::Dx.encode()));
        self.phase = Phase::Stopping {
            deadline_ns: now_ns.saturating_add(Self::ms(self.config.answer_timeout_ms)),
        };
    }

    fn handle_input(&mut self, now_ns: u64, bytes: &[u8]) {
        self.stats.bytes_in += bytes.len() as u64;
        if bytes.is_empty() {
            return;
        }
        self.rx.push(now_ns, bytes);
        self.process(now_ns);
    }

    fn handle_timeout(&mut self, now_ns: u64) {
        match self.phase {
            Phase::Draining { until_ns } if now_ns >= until_ns => {
                self.discard_buffered();
                self.transmits.push_back(Transmit::FlushInput);
                self.send(now_ns, Command::Dx);
            }
            Phase::Awaiting {
                cmd,
                attempts,
                deadline_ns,
            } if now_ns >= deadline_ns => {
                if attempts >= self.config.max_attempts {
                    self.fail(DriverError::NoAnswer {
                        command: cmd.name(),
                        attempts,
                    });
                } else {
                    self.warn(format!("no answer to {}; sending it again", cmd.name()));
                    self.send_attempt(now_ns, cmd, attempts + 1);
                }
            }
            Phase::Pause { until_ns } if now_ns >= until_ns => self.send(now_ns, Command::Mz),
            Phase::Streaming { last_block_ns }
                if now_ns
                    >= last_block_ns.saturating_add(Self::ms(self.config.silence_timeout_ms)) =>
            {
                self.warn(format!(
                    "no valid data for {} ms while scanning; restarting the session",
                    self.config.silence_timeout_ms
                ));
                self.restart(now_ns);
            }
            Phase::Stopping { deadline_ns } if now_ns >= deadline_ns => {
                self.phase = Phase::Idle;
            }
            _ => {}
        }
    }

    fn poll_timeout(&self) -> Option<u64> {
        match self.phase {
            Phase::Idle => None,
            Phase::Draining { until_ns } | Phase::Pause { until_ns } => Some(until_ns),
            Phase::Awaiting { deadline_ns, .. } | Phase::Stopping { deadline_ns } => {
                Some(deadline_ns)
            }
            Phase::Streaming { last_block_ns } => {
                Some(last_block_ns.saturating_add(Self::ms(self.config.silence_timeout_ms)))
            }
        }
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
