//! The message bodies carried by a [`crate::Frame`].
//!
//! All types are plain data (integers, floats, strings, vectors, enums) so that neither side needs
//! a maths library to use them. Times named `*_ns` are nanoseconds; which clock they are on is said
//! on each field (almost always the edge's monotonic clock).
//!
//! **Wire stability:** postcard encodes struct fields in declaration order and enum variants by
//! their index. Reordering fields or variants, inserting a variant anywhere but at the end, or
//! changing a field's type breaks the wire and needs a new [`crate::PROTOCOL_VERSION`].

use std::fmt;

use serde::{Deserialize, Serialize};

/// Which sensor a message is about: a one-byte id, kept open (a newtype, not an enum) so a newer
/// edge can report sensors an older server does not know by name.
///
/// | value | sensor |
/// | --- | --- |
/// | 0 | [`SensorId::RPLIDAR`] — horizontal Slamtec RPLidar A1/A2 |
/// | 1 | [`SensorId::SWEEP`] — vertical Scanse Sweep |
/// | 2 | [`SensorId::IMU`] — MPU-9250 + AK8963 |
/// | 3 | [`SensorId::STEPPER`] — the stepper that turns the Sweep |
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(transparent)]
pub struct SensorId(pub u8);

impl SensorId {
    /// The horizontal RPLidar (localisation scans).
    pub const RPLIDAR: SensorId = SensorId(0);
    /// The vertical Scanse Sweep (mapping scans).
    pub const SWEEP: SensorId = SensorId(1);
    /// The 9-axis IMU.
    pub const IMU: SensorId = SensorId(2);
    /// The stepper motor under the Sweep.
    pub const STEPPER: SensorId = SensorId(3);

    /// The sensor's short name, or `None` for an id this version does not know.
    pub fn name(self) -> Option<&'static str> {
        match self {
            SensorId::RPLIDAR => Some("rplidar"),
            SensorId::SWEEP => Some("sweep"),
            SensorId::IMU => Some("imu"),
            SensorId::STEPPER => Some("stepper"),
            _ => None,
        }
    }
}

impl fmt::Display for SensorId {
    /// The short name (`rplidar`, `sweep`, …), or `sensor#N` for an unknown id.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.name() {
            Some(name) => f.write_str(name),
            None => write!(f, "sensor#{}", self.0),
        }
    }
}

/// Identity of one sensor attached to the edge, as reported in [`Hello`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SensorInfo {
    /// Which sensor this is.
    pub sensor: SensorId,
    /// Model as the device reports it, e.g. `"A1"`, `"Sweep"`, `"MPU-9250"`.
    pub model: String,
    /// Firmware version as text (empty if the device has none to report).
    pub firmware: String,
    /// Serial number as text (empty if the device has none to report).
    pub serial: String,
}

/// First frame an edge sends on a new connection: who it is and what it has.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    /// The edge's configured name, e.g. `"trolley-pi"`.
    pub device_name: String,
    /// The edge software version, e.g. `"0.1.0"`.
    pub software_version: String,
    /// The protocol version the edge speaks ([`crate::PROTOCOL_VERSION`] when it was built).
    pub protocol_version: u16,
    /// The sensors the edge found at start-up.
    pub sensors: Vec<SensorInfo>,
    /// Identity of the clock every edge time of the session is on: on Linux the boot id
    /// (`/proc/sys/kernel/random/boot_id`), because CLOCK_MONOTONIC restarts at boot, not at
    /// process start; random when that cannot be read; all zeros when unknown. The server's
    /// clock model is discarded when it changes.
    pub clock_id: [u8; 16],
}

impl Hello {
    /// A hello for this build: `protocol_version` is [`crate::PROTOCOL_VERSION`], the clock
    /// identity unknown (all zeros; see [`Hello::with_clock_id`]).
    pub fn new(
        device_name: impl Into<String>,
        software_version: impl Into<String>,
        sensors: Vec<SensorInfo>,
    ) -> Self {
        Hello {
            device_name: device_name.into(),
            software_version: software_version.into(),
            protocol_version: crate::PROTOCOL_VERSION,
            sensors,
            clock_id: [0; 16],
        }
    }

    /// This hello with the edge clock's identity set.
    pub fn with_clock_id(mut self, clock_id: [u8; 16]) -> Self {
        self.clock_id = clock_id;
        self
    }

    /// Whether this build can talk to the peer that sent this hello
    /// (see [`crate::check_compatible`]).
    pub fn check_compatible(&self) -> Result<(), crate::IncompatibleVersion> {
        crate::check_compatible(self.protocol_version)
    }
}

/// One sample of a [`LidarRevolution`] (13 bytes or less on the wire: two `f32`, one `u8` and a
/// varint `u32`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RevolutionSample {
    /// Beam angle in degrees in `[0, 360)`, in the device's own convention
    /// (RPLidar clockwise seen from above, Sweep counter-clockwise).
    pub angle_deg: f32,
    /// Range in metres; `0.0` means "no return".
    pub range_m: f32,
    /// RPLidar: 6-bit quality (0–63). Sweep: signal strength (0–255).
    pub quality: u8,
    /// Sample time as an offset in nanoseconds from the revolution's
    /// [`t0_ns`](LidarRevolution::t0_ns): offsets keep a sample to 4 bytes of varint for
    /// revolutions up to 268 ms (5 bytes up to 4.29 s) where an absolute `u64` would take 8–9.
    pub offset_ns: u32,
}

/// Why a sample could not be added to a [`LidarRevolution`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error(
    "sample time {t_ns} ns is not within u32 nanoseconds after the revolution start {t0_ns} ns"
)]
pub struct SampleTimeError {
    /// The revolution's start time.
    pub t0_ns: u64,
    /// The rejected sample time.
    pub t_ns: u64,
}

/// One 360° revolution of a lidar, with a measurement time for every sample.
///
/// Sample times are stored as `u32` offsets from `t0_ns` (so a revolution may span at most
/// `u32::MAX` ns ≈ 4.29 s, four times the slowest Sweep rate). A 2000-sample revolution encodes to
/// about 26 KB.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LidarRevolution {
    /// Which lidar (normally [`SensorId::RPLIDAR`] or [`SensorId::SWEEP`]).
    pub sensor: SensorId,
    /// Edge monotonic clock (ns) at the start of the revolution; the base for sample offsets.
    /// Sample times only go forwards, so it also names the revolution within its sensor and
    /// session ([`StaticScanYaws::revolution_t0_ns`] refers to it).
    pub t0_ns: u64,
    /// Edge monotonic clock (ns) at the end of the revolution (the next one's start).
    pub t1_ns: u64,
    /// The samples in the order the device produced them.
    pub samples: Vec<RevolutionSample>,
}

impl LidarRevolution {
    /// An empty revolution spanning `t0_ns..t1_ns` on the edge clock.
    pub fn new(sensor: SensorId, t0_ns: u64, t1_ns: u64) -> Self {
        LidarRevolution {
            sensor,
            t0_ns,
            t1_ns,
            samples: Vec::new(),
        }
    }

    /// Appends a sample measured at `t_ns` (edge clock). Fails if `t_ns` is before `t0_ns` or more
    /// than `u32::MAX` ns after it.
    pub fn push(
        &mut self,
        angle_deg: f32,
        range_m: f32,
        quality: u8,
        t_ns: u64,
    ) -> Result<(), SampleTimeError> {
        let offset_ns = t_ns
            .checked_sub(self.t0_ns)
            .and_then(|d| u32::try_from(d).ok())
            .ok_or(SampleTimeError {
                t0_ns: self.t0_ns,
                t_ns,
            })?;
        self.samples.push(RevolutionSample {
            angle_deg,
            range_m,
            quality,
            offset_ns,
        });
        Ok(())
    }

    /// The absolute edge-clock time (ns) of each sample, in order (`t0_ns + offset_ns`, saturating
    /// at `u64::MAX` for nonsense input instead of overflowing).
    pub fn sample_times_ns(&self) -> impl Iterator<Item = u64> + '_ {
        self.samples
            .iter()
            .map(|s| self.t0_ns.saturating_add(u64::from(s.offset_ns)))
    }
}

/// One IMU reading, converted from raw counts to physical units on the edge.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ImuSample {
    /// Edge monotonic clock (ns) when the registers were read.
    pub t_ns: u64,
    /// Acceleration x, y, z in m/s² (sensor frame).
    pub accel_mps2: [f32; 3],
    /// Angular rate x, y, z in rad/s (sensor frame).
    pub gyro_radps: [f32; 3],
    /// Magnetic field x, y, z in µT, already rotated into the accelerometer's axes; NaN when the
    /// magnetometer had no new sample for this reading (it runs at 100 Hz, the IMU faster).
    pub mag_ut: [f32; 3],
    /// Orientation quaternion `[w, x, y, z]` from the edge's Madgwick filter, if it runs.
    pub orientation: Option<[f32; 4]>,
}

/// The stepper that turns the Sweep: where it was told to be and whether it holds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepperState {
    /// Edge monotonic clock (ns) when this state took effect.
    pub t_ns: u64,
    /// Commanded yaw of the Sweep in degrees (from the step index and the steps per turn).
    pub commanded_angle_deg: f32,
    /// Signed step count since the static scan started (negative if turned backwards).
    pub step_index: i64,
    /// `true` while the coils are energised and hold position, `false` once released.
    pub holding: bool,
}

/// First half of an NTP-style exchange, sent by the server in a QUIC datagram (never on the
/// stream, see [`crate::Frame`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TimePing {
    /// Server monotonic clock (ns) when the ping was sent (NTP t0). Monotonic, not wall time,
    /// so that stepping the laptop's clock cannot move it.
    pub t0_ns: u64,
}

/// The edge's answer to a [`TimePing`], in a QUIC datagram of its own (never spooled, never
/// resent: a lost pong costs one exchange). The server records its own receive time t3 and has
/// the four NTP timestamps: offset = ((t1 − t0) + (t2 − t3)) / 2, delay = (t3 − t0) − (t2 − t1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TimePong {
    /// The ping's `t0_ns`, echoed (server clock).
    pub t0_ns: u64,
    /// Edge monotonic clock (ns) when the ping was received (NTP t1).
    pub t1_ns: u64,
    /// Edge monotonic clock (ns) when this pong was sent (NTP t2).
    pub t2_ns: u64,
}

/// How an edge's clock maps to the server's: the server's time-sync estimate, recorded in the
/// session (topic `/scan3d/timesync`) each time it changes so that a replay maps sample times
/// exactly as the live server did. Made by the server only; never sent to an edge. The server
/// records it as a record type of its own, not as a wire frame
/// ([`Body::ClockModel`](crate::Body::ClockModel) is the legacy form older recordings hold).
///
/// The offset θ (edge − server, NTP's sign) is linear in edge time:
/// `θ(t) = offset_ns + skew_ppm · 10⁻⁶ · (t − ref_edge_ns)`, and `server = t − θ(t)`
/// ([`ClockModel::to_server_ns`]). Server times are on the server's monotonic clock (UNIX time
/// at server start plus the time elapsed since, so a stepped wall clock does not move them).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ClockModel {
    /// θ at `ref_edge_ns`: edge clock minus server clock, ns.
    pub offset_ns: i64,
    /// Rate of change of θ, ppm of edge time (the edge clock's frequency error relative to the
    /// server's; crystals are typically within ±50 ppm).
    pub skew_ppm: f64,
    /// Bound on the mapping error for edge times between the oldest and newest exchange fitted
    /// (`fit_from_edge_ns..=fit_to_edge_ns`), ns; outside, it widens by `skew_bound_ppm` per
    /// unit of distance ([`ClockModel::error_bound_at`]).
    pub error_bound_ns: u64,
    /// Uncertainty of `skew_ppm`, ppm.
    pub skew_bound_ppm: f64,
    /// Edge time (ns) the offset refers to (the weighted centre of the exchanges fitted).
    pub ref_edge_ns: u64,
    /// Edge time (ns) of the oldest exchange fitted.
    pub fit_from_edge_ns: u64,
    /// Edge time (ns) of the newest exchange fitted.
    pub fit_to_edge_ns: u64,
    /// Edge time (ns) of the newest exchange in the fit: the model is the current one for edge
    /// times from here until the next model's.
    pub valid_from_edge_ns: u64,
    /// Smallest round trip among the exchanges fitted, ns (a quality figure).
    pub min_delay_ns: u64,
    /// Number of exchanges in the fit.
    pub exchanges: u32,
}

impl ClockModel {
    /// θ at `edge_ns` (edge − server, ns), computed in `i128`.
    pub fn offset_at(&self, edge_ns: u64) -> i128 {
        let since_ref = i128::from(edge_ns) - i128::from(self.ref_edge_ns);
        // The skew term is the only floating-point step: |since_ref| < 2^64 ns and
        // |skew| ≪ 10^6 ppm keep it far inside f64's exact integer range for real sessions.
        let drift = (self.skew_ppm * 1e-6 * since_ref as f64).round();
        let drift = if drift.is_finite() { drift as i128 } else { 0 };
        i128::from(self.offset_ns) + drift
    }

    /// The server time (ns, server monotonic clock) of edge time `edge_ns`, saturating at the
    /// ends of `u64`.
    pub fn to_server_ns(&self, edge_ns: u64) -> u64 {
        let server = i128::from(edge_ns) - self.offset_at(edge_ns);
        server.clamp(0, i128::from(u64::MAX)) as u64
    }

    /// Bound on the error of [`ClockModel::to_server_ns`] at `edge_ns`, ns.
    pub fn error_bound_at(&self, edge_ns: u64) -> u64 {
        let distance = if edge_ns < self.fit_from_edge_ns {
            self.fit_from_edge_ns - edge_ns
        } else {
            edge_ns.saturating_sub(self.fit_to_edge_ns)
        } as f64;
        let widening = (self.skew_bound_ppm.abs() * 1e-6 * distance).ceil();
        let widening = if widening.is_finite() {
            widening.min(u64::MAX as f64) as u64
        } else {
            u64::MAX
        };
        self.error_bound_ns.saturating_add(widening)
    }
}

/// Acknowledgement of frames received in the opposite direction of the same session.
///
/// Variant order is part of the wire: `UpTo` = 0, `Range` = 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Ack {
    /// Every sequence number `<= seq` is durably recorded (highest contiguous).
    UpTo {
        /// The highest contiguous acknowledged sequence number.
        seq: u64,
    },
    /// Sequence numbers `first..=last` are durably recorded (a block past a gap).
    Range {
        /// First acknowledged sequence number.
        first: u64,
        /// Last acknowledged sequence number (inclusive).
        last: u64,
    },
}

impl Ack {
    /// Whether this ack covers sequence number `seq`.
    pub fn covers(&self, seq: u64) -> bool {
        match *self {
            Ack::UpTo { seq: top } => seq <= top,
            Ack::Range { first, last } => first <= seq && seq <= last,
        }
    }
}

/// "Still here" when there is nothing else to send; either side may send it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Heartbeat {
    /// The sender's clock (ns) when it was sent (edge monotonic or server clock).
    pub sent_ns: u64,
}

/// What happened to a sensor or to acquisition.
///
/// Variant order is part of the wire: `SensorLost` = 0, `SensorBack` = 1,
/// `AcquisitionPaused` = 2, `AcquisitionResumed` = 3.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum StatusEvent {
    /// The sensor stopped answering or was unplugged.
    SensorLost,
    /// The sensor answers again after having been lost.
    SensorBack,
    /// The edge stopped acquiring from the sensor on purpose (e.g. spool full, command).
    AcquisitionPaused,
    /// Acquisition from the sensor continues.
    AcquisitionResumed,
}

/// A change in the edge's state worth a log line on the server.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceStatus {
    /// Edge monotonic clock (ns) when it happened.
    pub t_ns: u64,
    /// The sensor concerned.
    pub sensor: SensorId,
    /// What happened.
    pub event: StatusEvent,
    /// Why, for a human: e.g. `"no answer to GET_HEALTH after 3 attempts"`.
    pub reason: String,
}

/// An order from the server to the edge.
///
/// Variant order is part of the wire: `StartStaticScan` = 0, `StopStaticScan` = 1,
/// `SetMotorSpeed` = 2, `StartPass` = 3, `StopPass` = 4.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Command {
    /// Start a static 3D scan (the stepper turns the Sweep) at a named, known position.
    StartStaticScan {
        /// Name of the position, e.g. `"p1"`; used to splice positions later.
        position: String,
        /// Position x in metres in the map frame.
        x_m: f64,
        /// Position y in metres in the map frame.
        y_m: f64,
        /// Heading in degrees in the map frame, if known.
        heading_deg: Option<f64>,
    },
    /// Stop the running static scan and release the stepper.
    StopStaticScan,
    /// Set a lidar's rotation rate.
    SetMotorSpeed {
        /// Which lidar.
        sensor: SensorId,
        /// Target rotation rate in revolutions per second (Hz).
        hz: f32,
    },
    /// Open a trolley pass: the head stands at a known place of the room now (anchoring the
    /// session's trajectory there); the edge answers with a [`PassMarker`] stamped on its clock.
    StartPass {
        /// The pass's name (1 to [`MAX_POSITION_NAME_LEN`] bytes, no control characters);
        /// `None`: the edge names it `pass-N`, N counting from 1 in its session.
        name: Option<String>,
        /// Where `base` stands: x in metres in the room frame.
        x_m: f64,
        /// y in metres in the room frame.
        y_m: f64,
        /// Heading of `base` in degrees in the room frame (0 when the operator gave none).
        heading_deg: f64,
    },
    /// Close the running trolley pass (the edge answers with a [`PassMarker`]).
    StopPass,
}

/// The edge's answer to one [`Command`] (`Body::CommandReply`, edge → server, tag 12): which
/// command it answers, and whether the edge acted on it. Recorded like every edge frame, so a
/// session's recording says what was asked and what the edge did.
///
/// Every command gets a reply. A [`CommandOutcome::Waiting`] reply is followed by an
/// [`CommandOutcome::Accepted`] or [`CommandOutcome::Refused`] reply to the same command once
/// the edge can decide (e.g. the Sweep starts streaming).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandReply {
    /// The `seq` of the server frame that carried the command (the server's numbering in this
    /// session).
    pub command_seq: u64,
    /// Edge monotonic clock (ns) when the edge decided.
    pub t_ns: u64,
    /// What the edge did.
    pub outcome: CommandOutcome,
}

/// What the edge did with a [`Command`].
///
/// Variant order is part of the wire: `Accepted` = 0, `Waiting` = 1, `Refused` = 2.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum CommandOutcome {
    /// Carried out. For [`Command::StartStaticScan`] and [`Command::StopStaticScan`]: the
    /// static scan started or being stopped (its [`StaticScanStart::scan_id`]).
    Accepted {
        /// The static scan concerned, if the command is about one.
        scan_id: Option<u32>,
    },
    /// Accepted, but it cannot start yet (the Sweep is not streaming): the edge waits and
    /// replies again, `Accepted` or `Refused`, to the same command.
    Waiting {
        /// What the edge waits for, for a human.
        reason: String,
    },
    /// Not carried out; nothing changed on the edge.
    Refused {
        /// Why, for a human: e.g. `"no [stepper] in edge.toml: static scans are off"`.
        reason: String,
    },
}

/// Longest [`Command::StartStaticScan`] position name, in bytes (UTF-8). The name travels in
/// every [`StaticScanStart`] and ends up in file names and tables, so it is meant to be short
/// (`"p1"`, `"door"`); 256 bytes leaves room for descriptive names.
pub const MAX_POSITION_NAME_LEN: usize = 256;

/// Fastest lidar rotation rate a [`Command::SetMotorSpeed`] may ask for, Hz. The RPLidar A1/A2
/// turns at 5–15 Hz and the Sweep at 1–10 Hz; anything far above is a typo.
pub const MAX_MOTOR_SPEED_HZ: f32 = 100.0;

/// Why a [`Command`] cannot be sent to an edge ([`Command::validate`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InvalidCommand {
    /// The position name is empty or longer than [`MAX_POSITION_NAME_LEN`] bytes.
    #[error("position name of {len} bytes: must be 1 to {max} bytes")]
    PositionNameLength {
        /// The name's length in bytes.
        len: usize,
        /// [`MAX_POSITION_NAME_LEN`].
        max: usize,
    },
    /// The position name contains a control character (newline, NUL, …).
    #[error("position name {name:?} contains a control character")]
    PositionNameControl {
        /// The rejected name.
        name: String,
    },
    /// A coordinate or angle is NaN or infinite.
    #[error("{field} = {value} is not a finite number")]
    NotFinite {
        /// Which field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// A motor speed outside `(0, MAX_MOTOR_SPEED_HZ]`.
    #[error("motor speed {hz} Hz is outside (0, {max}] Hz")]
    MotorSpeed {
        /// The requested rate.
        hz: f32,
        /// [`MAX_MOTOR_SPEED_HZ`].
        max: f32,
    },
    /// The command's frame would not fit in [`crate::MAX_FRAME_LEN`].
    #[error("the command does not fit in a frame: {0}")]
    Frame(crate::EncodeError),
}

impl Command {
    /// Checks that the command is one an edge can act on and that its frame can be encoded, so
    /// nothing invalid ever reaches a connection: a position (or pass) name of 1 to
    /// [`MAX_POSITION_NAME_LEN`] bytes without control characters, finite coordinates and
    /// heading, a motor speed in `(0, MAX_MOTOR_SPEED_HZ]`, and a frame (with the largest
    /// session id and sequence number) within [`crate::MAX_FRAME_LEN`].
    pub fn validate(&self) -> Result<(), InvalidCommand> {
        let check_name = |name: &String| {
            if name.is_empty() || name.len() > MAX_POSITION_NAME_LEN {
                return Err(InvalidCommand::PositionNameLength {
                    len: name.len(),
                    max: MAX_POSITION_NAME_LEN,
                });
            }
            if name.chars().any(char::is_control) {
                return Err(InvalidCommand::PositionNameControl { name: name.clone() });
            }
            Ok(())
        };
        let finite = |field: &'static str, value: f64| {
            if value.is_finite() {
                Ok(())
            } else {
                Err(InvalidCommand::NotFinite { field, value })
            }
        };
        match self {
            Command::StartStaticScan {
                position,
                x_m,
                y_m,
                heading_deg,
            } => {
                check_name(position)?;
                finite("x_m", *x_m)?;
                finite("y_m", *y_m)?;
                if let Some(heading) = heading_deg {
                    finite("heading_deg", *heading)?;
                }
            }
            Command::StartPass {
                name,
                x_m,
                y_m,
                heading_deg,
            } => {
                if let Some(name) = name {
                    check_name(name)?;
                }
                finite("x_m", *x_m)?;
                finite("y_m", *y_m)?;
                finite("heading_deg", *heading_deg)?;
            }
            Command::StopStaticScan | Command::StopPass => {}
            Command::SetMotorSpeed { hz, .. } => {
                if !(hz.is_finite() && *hz > 0.0 && *hz <= MAX_MOTOR_SPEED_HZ) {
                    return Err(InvalidCommand::MotorSpeed {
                        hz: *hz,
                        max: MAX_MOTOR_SPEED_HZ,
                    });
                }
            }
        }
        // The limits above keep every command far below the frame limit; encoding the largest
        // possible frame keeps that true if a field is added without a limit.
        let frame = crate::Frame::new(u64::MAX, u64::MAX, self.clone());
        crate::encode(&frame)
            .map(drop)
            .map_err(InvalidCommand::Frame)
    }
}

/// A static 3D scan's messages (the paper's §III-A): the edge turns the Sweep on the stepper,
/// one step per revolution while the beam is blocked, and gives every sample it trusts the
/// turntable yaw φ it was taken at, so the server can apply eq. (1) from the recording alone.
///
/// The samples themselves travel once, in the Sweep's [`LidarRevolution`] frames, with the one
/// time each has; [`StaticScanYaws`] only names a revolution (its `t0_ns`) and the yaw of runs of
/// its sample indices.
///
/// Variant order is part of the wire: `Started` = 0, `Yaws` = 1, `Warning` = 2,
/// `Finished` = 3.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum StaticScan {
    /// A scan began at a known position (answers [`Command::StartStaticScan`]).
    Started(StaticScanStart),
    /// The yaws of one Sweep revolution's samples (protocol version 2; version 1 carried the
    /// samples again here).
    Yaws(StaticScanYaws),
    /// Something went wrong for part of the scan; the affected samples were not tagged.
    Warning(StaticScanWarning),
    /// The scan ended (complete, aborted or stopped) and the turntable went home.
    Finished(StaticScanEnd),
}

/// Where the Sweep sits on the turntable, as configured on the edge (`[static_scan.mount]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MountInfo {
    /// Distance of the optical centre from the turntable axis along the scan plane's normal, m.
    pub axis_offset_m: f64,
    /// Height of the optical centre above the floor, m.
    pub height_m: f64,
    /// The device azimuth that points straight up (θ = 0 of eq. (1)), degrees.
    pub azimuth_zero_deg: f64,
}

impl MountInfo {
    /// θ of eq. (1) for a device azimuth on this mount (see [`theta_deg`]).
    pub fn theta_deg(&self, azimuth_deg: f64) -> f64 {
        theta_deg(azimuth_deg, self.azimuth_zero_deg)
    }
}

/// θ of eq. (1), degrees in `[0, 360)`: the Sweep's device azimuth minus the mount's azimuth
/// zero (the device azimuth that points straight up), so θ = 0 is up and θ = 180° down into the
/// base. The one definition the edge's blocked-sector logic and the server's eq. (1) share.
/// NaN in, NaN out.
pub fn theta_deg(azimuth_deg: f64, azimuth_zero_deg: f64) -> f64 {
    match (azimuth_deg - azimuth_zero_deg).rem_euclid(360.0) {
        // rem_euclid rounds a tiny negative difference up to exactly 360.
        t if t >= 360.0 => 0.0,
        t => t,
    }
}

/// The start of a static scan: position, step and mount, everything eq. (1) needs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StaticScanStart {
    /// Number of the scan within the edge session (0, 1, …).
    pub scan_id: u32,
    /// Edge monotonic clock (ns) when the scan started.
    pub t_ns: u64,
    /// The operator's name for the position.
    pub position: String,
    /// Position x in the map frame, metres.
    pub x_m: f64,
    /// Position y in the map frame, metres.
    pub y_m: f64,
    /// φ0: turntable yaw 0 in the map frame, degrees (0 when the operator gave none).
    pub heading_deg: f64,
    /// δφ per revolution, degrees.
    pub step_deg: f64,
    /// Total turn planned, degrees.
    pub total_deg: f64,
    /// Width of the blind sector centred on θ = 180°, degrees.
    pub blocked_sector_deg: f64,
    /// The mount geometry.
    pub mount: MountInfo,
}

/// Consecutive samples of one Sweep revolution taken at one turntable yaw: indices
/// `first_index .. first_index + count` of [`LidarRevolution::samples`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct YawRun {
    /// Index of the run's first sample in the revolution.
    pub first_index: u32,
    /// Number of samples in the run.
    pub count: u32,
    /// Turntable yaw φ from home, degrees.
    pub yaw_deg: f32,
}

/// The turntable yaws of one Sweep revolution's samples during a static scan.
///
/// The revolution is the [`LidarRevolution`] of [`SensorId::SWEEP`] in the same session whose
/// `t0_ns` is `revolution_t0_ns` (unique per sensor and session: the edge's sample times only go
/// forwards). Samples covered by no run are not tagged: in the blocked sector, or not trusted
/// (a late or failed step, a step in flight). Runs are in index order and do not overlap.
/// Either frame may come first on the wire; the server joins them by `t0_ns`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StaticScanYaws {
    /// The scan.
    pub scan_id: u32,
    /// `t0_ns` of the Sweep revolution the indices refer to (edge clock).
    pub revolution_t0_ns: u64,
    /// The tagged runs of samples.
    pub runs: Vec<YawRun>,
}

impl StaticScanYaws {
    /// Samples tagged by all runs together (saturating).
    pub fn tagged_samples(&self) -> u64 {
        self.runs
            .iter()
            .fold(0u64, |n, run| n.saturating_add(u64::from(run.count)))
    }
}

/// What went wrong during a static scan.
///
/// Variant order is part of the wire: `LateStep` = 0, `StepFailed` = 1, `SectorMissed` = 2,
/// `PredictedLate` = 3.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum StaticScanProblem {
    /// A step did not finish before the beam left the blocked sector: the second half of the
    /// revolution was dropped, not mis-tagged.
    LateStep,
    /// The stepper reported an error during a step.
    StepFailed,
    /// No sample fell into the blocked sector, so no step was made that revolution.
    SectorMissed,
    /// δφ at the motor's maximum rate cannot fit in the blocked sector at this rotation rate.
    PredictedLate,
}

/// A problem during a static scan, for the session log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StaticScanWarning {
    /// The scan.
    pub scan_id: u32,
    /// Edge monotonic clock (ns).
    pub t_ns: u64,
    /// Revolution concerned.
    pub revolution: u32,
    /// What happened.
    pub problem: StaticScanProblem,
    /// Details for a human.
    pub detail: String,
}

/// How a static scan ended.
///
/// Variant order is part of the wire: `Completed` = 0, `Aborted` = 1, `Stopped` = 2.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum StaticScanOutcome {
    /// The turntable turned the whole planned angle.
    Completed,
    /// Too many failed steps.
    Aborted,
    /// Stopped by a command, a lost Sweep or the daemon shutting down.
    Stopped,
}

/// The end of a static scan with its counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StaticScanEnd {
    /// The scan.
    pub scan_id: u32,
    /// Edge monotonic clock (ns).
    pub t_ns: u64,
    /// How it ended.
    pub outcome: StaticScanOutcome,
    /// Final yaw before returning home, degrees.
    pub yaw_deg: f64,
    /// Full revolutions.
    pub revolutions: u32,
    /// Samples tagged with a yaw (as the controller decided; those in a revolution the edge
    /// dropped, e.g. a partial one after a reconnect, are in no [`StaticScanYaws`]).
    pub tagged: u64,
    /// Samples in the blocked sector.
    pub blocked: u64,
    /// Samples not trusted (late or failed steps).
    pub untrusted: u64,
    /// Late steps.
    pub late_steps: u64,
    /// Failed steps.
    pub failed_steps: u64,
}

/// Most entries a [`SensorMounts`] may hold: one per [`SensorId`] (a one-byte id).
pub const MAX_SENSOR_MOUNTS: usize = 256;

/// One sensor's pose in the head's `base` frame, as configured on the edge
/// (`[rplidar.mount]`, `[sweep.mount]`, `[imu.mount]`): a translation, then a rotation by
/// roll about x, pitch about y and yaw about z (`R = Rz(yaw) · Ry(pitch) · Rx(roll)`), taking
/// the sensor's own axes to `base`'s.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SensorMount {
    /// The sensor.
    pub sensor: SensorId,
    /// Position of the sensor's origin in `base`, x, metres.
    pub x_m: f64,
    /// y, metres.
    pub y_m: f64,
    /// z, metres.
    pub z_m: f64,
    /// Rotation about x, degrees.
    pub roll_deg: f64,
    /// Rotation about y, degrees.
    pub pitch_deg: f64,
    /// Rotation about z, degrees.
    pub yaw_deg: f64,
}

/// The edge's sensor mounts (`Body::Mounts`, edge → server, tag 13), sent once per session
/// right after its first [`Hello`] (and recorded like it), so the server knows where each
/// sensor sits on the head. A sensor with no mount section is absent (the server takes it at
/// the origin of `base`). Kept out of [`Hello`] so recordings made before it still decode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorMounts {
    /// One entry per configured mount, each sensor at most once.
    pub sensors: Vec<SensorMount>,
}

/// Why a [`SensorMounts`] cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InvalidMounts {
    /// More than [`MAX_SENSOR_MOUNTS`] entries.
    #[error("{count} sensor mounts: at most {max}")]
    TooMany {
        /// The number of entries.
        count: usize,
        /// [`MAX_SENSOR_MOUNTS`].
        max: usize,
    },
    /// A sensor has two entries.
    #[error("the {sensor} mount is given twice")]
    Duplicate {
        /// The sensor.
        sensor: SensorId,
    },
    /// A coordinate or angle is NaN or infinite.
    #[error("the {sensor} mount's {field} = {value} is not a finite number")]
    NotFinite {
        /// The sensor.
        sensor: SensorId,
        /// Which field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
}

impl SensorMounts {
    /// The mount of `sensor`, if the edge sent one.
    pub fn get(&self, sensor: SensorId) -> Option<&SensorMount> {
        self.sensors.iter().find(|m| m.sensor == sensor)
    }

    /// Checks what a receiver relies on: at most [`MAX_SENSOR_MOUNTS`] entries, each sensor
    /// once, every value finite.
    pub fn validate(&self) -> Result<(), InvalidMounts> {
        if self.sensors.len() > MAX_SENSOR_MOUNTS {
            return Err(InvalidMounts::TooMany {
                count: self.sensors.len(),
                max: MAX_SENSOR_MOUNTS,
            });
        }
        let mut seen = [false; MAX_SENSOR_MOUNTS];
        for mount in &self.sensors {
            let slot = &mut seen[usize::from(mount.sensor.0)];
            if std::mem::replace(slot, true) {
                return Err(InvalidMounts::Duplicate {
                    sensor: mount.sensor,
                });
            }
            for (field, value) in [
                ("x_m", mount.x_m),
                ("y_m", mount.y_m),
                ("z_m", mount.z_m),
                ("roll_deg", mount.roll_deg),
                ("pitch_deg", mount.pitch_deg),
                ("yaw_deg", mount.yaw_deg),
            ] {
                if !value.is_finite() {
                    return Err(InvalidMounts::NotFinite {
                        sensor: mount.sensor,
                        field,
                        value,
                    });
                }
            }
        }
        Ok(())
    }
}

/// A trolley pass beginning or ending (`Body::Pass`, edge → server, tag 14): the edge's answer
/// to [`Command::StartPass`] / [`Command::StopPass`], stamped on the edge's clock so the pass
/// begins and ends at an edge sample time, live and in replay alike.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PassMarker {
    /// Edge monotonic clock (ns) when the edge acted on the command.
    pub t_ns: u64,
    /// What happened.
    pub event: PassEvent,
}

/// What a [`PassMarker`] marks.
///
/// Variant order is part of the wire: `Started` = 0, `Stopped` = 1.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum PassEvent {
    /// A pass opened with `base` at this pose in the room frame.
    Started {
        /// The pass's name (the operator's, or `pass-N`).
        name: String,
        /// x of `base` in the room frame, metres.
        x_m: f64,
        /// y of `base` in the room frame, metres.
        y_m: f64,
        /// Heading of `base` in the room frame, degrees.
        heading_deg: f64,
    },
    /// The pass of this name closed.
    Stopped {
        /// The pass's name.
        name: String,
    },
}

impl PassEvent {
    /// The pass's name.
    pub fn name(&self) -> &str {
        match self {
            PassEvent::Started { name, .. } | PassEvent::Stopped { name } => name,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn start(position: &str, x_m: f64, heading_deg: Option<f64>) -> Command {
        Command::StartStaticScan {
            position: position.to_owned(),
            x_m,
            y_m: 2.0,
            heading_deg,
        }
    }

    #[test]
    fn theta_is_the_azimuth_from_the_mount_zero_in_zero_to_360() {
        assert_eq!(theta_deg(90.0, 0.0), 90.0);
        assert_eq!(theta_deg(30.0, 90.0), 300.0);
        assert_eq!(theta_deg(359.5, 359.5), 0.0);
        // A difference that rounds to −0.0…01 wraps to 0, never to 360.
        assert_eq!(theta_deg(-1e-20, 0.0), 0.0);
        assert!(theta_deg(f64::NAN, 0.0).is_nan());
        let mount = MountInfo {
            axis_offset_m: 0.0,
            height_m: 0.0,
            azimuth_zero_deg: 180.0,
        };
        assert_eq!(mount.theta_deg(180.0), 0.0);
        assert_eq!(mount.theta_deg(0.0), 180.0);
    }

    #[test]
    fn ordinary_commands_are_valid() {
        assert_eq!(start("door", 1.0, Some(90.0)).validate(), Ok(()));
        assert_eq!(
            start(&"p".repeat(MAX_POSITION_NAME_LEN), -1e6, None).validate(),
            Ok(())
        );
        assert_eq!(Command::StopStaticScan.validate(), Ok(()));
        let speed = |hz| Command::SetMotorSpeed {
            sensor: SensorId::SWEEP,
            hz,
        };
        assert_eq!(speed(5.0).validate(), Ok(()));
        assert_eq!(speed(MAX_MOTOR_SPEED_HZ).validate(), Ok(()));
        for hz in [0.0, -1.0, f32::NAN, f32::INFINITY, MAX_MOTOR_SPEED_HZ * 2.0] {
            assert!(
                matches!(speed(hz).validate(), Err(InvalidCommand::MotorSpeed { .. })),
                "{hz}"
            );
        }
    }

    #[test]
    fn a_five_mebibyte_position_name_is_refused_before_encoding() {
        let huge = "x".repeat(5 * 1024 * 1024);
        let err = start(&huge, 1.0, None).validate().unwrap_err();
        assert_eq!(
            err,
            InvalidCommand::PositionNameLength {
                len: 5 * 1024 * 1024,
                max: MAX_POSITION_NAME_LEN
            }
        );
        assert_eq!(
            err.to_string(),
            "position name of 5242880 bytes: must be 1 to 256 bytes"
        );
        let err = start(&"y".repeat(MAX_POSITION_NAME_LEN + 1), 1.0, None).validate();
        assert!(matches!(
            err,
            Err(InvalidCommand::PositionNameLength { len: 257, .. })
        ));
        let err = start("", 1.0, None).validate();
        assert!(matches!(
            err,
            Err(InvalidCommand::PositionNameLength { len: 0, .. })
        ));
    }

    #[test]
    fn control_characters_and_non_finite_numbers_are_refused() {
        assert!(matches!(
            start("a\nb", 1.0, None).validate(),
            Err(InvalidCommand::PositionNameControl { .. })
        ));
        assert!(matches!(
            start("a", f64::NAN, None).validate(),
            Err(InvalidCommand::NotFinite { field: "x_m", .. })
        ));
        assert!(matches!(
            start("a", 1.0, Some(f64::NEG_INFINITY)).validate(),
            Err(InvalidCommand::NotFinite {
                field: "heading_deg",
                ..
            })
        ));
    }
}
