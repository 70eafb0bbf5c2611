//! The scan3d wire protocol: the frames the edge (Raspberry Pi daemon) and the server exchange.
//!
//! Pure code: serde types, postcard encoding and a length-prefixed framing with a decoder over
//! byte slices. No I/O, no async, no clock; the edge's uplink and the server's ingest wrap it.
//!
//! # Wire layout
//!
//! Every frame is a fixed 10-byte header followed by a postcard payload:
//!
//! ```text
//!  0      3 4    5 6          9 10                        10+len
//! +--------+------+------------+---------------------------+
//! | "S3DP" | ver  |    len     |  postcard(Frame)          |
//! |  magic | u16  |  u32 LE    |  session_id  varint u64   |
//! | 4 bytes|  LE  |  payload   |  seq         varint u64   |
//! |        |      |  bytes     |  body tag    varint       |
//! |        |      |            |  body fields ...          |
//! +--------+------+------------+---------------------------+
//! ```
//!
//! - `magic` is ASCII `S3DP` (`53 33 44 50`), see [`MAGIC`].
//! - `ver` is [`PROTOCOL_VERSION`]; a receiver rejects any other version
//!   ([`DecodeError::UnsupportedVersion`]).
//! - `len` counts payload bytes only; header + payload is at most [`MAX_FRAME_LEN`] (4 MiB).
//! - The payload is the [`Frame`] in postcard's format: integers wider than a byte as LEB128
//!   varints (signed ones zig-zagged), `f32`/`f64` as little-endian IEEE 754, `bool` and `u8` as
//!   one byte, strings and vectors as a varint length then the items, `Option` as `00` or
//!   `01` + value, enum variants as a varint index. It must fill `len` exactly.
//!
//! For example, `Frame { session_id: 1, seq: 2, body: Heartbeat { sent_ns: 3 } }` is
//! `53 33 44 50 02 00 04 00 00 00 01 02 07 03`.
//!
//! # Frames
//!
//! Every [`Frame`] carries the edge's session id (random `u64` per edge boot) and a sequence
//! number (per session, per direction). Its [`Body`] is one of (the tag is the wire value):
//!
//! | tag | body | direction | content |
//! | --- | --- | --- | --- |
//! | 0 | [`Hello`] | edge → server | device name, software and protocol version, [`SensorInfo`] per sensor, clock identity |
//! | 1 | [`LidarRevolution`] | edge → server | one 360° revolution: angle, range, quality and time offset per sample, t0/t1 |
//! | 2 | [`ImuSample`] | edge → server | accel, gyro, mag triples, optional orientation quaternion |
//! | 3 | [`StepperState`] | edge → server | commanded angle, step index, holding / released |
//! | 4 | [`TimePing`] | server → edge, datagram | NTP t0 (server monotonic clock) |
//! | 5 | [`TimePong`] | edge → server, datagram | t0 echoed, t1 receive and t2 send (edge clock); the server adds t3 |
//! | 6 | [`Ack`] | both | highest contiguous sequence number, or a range |
//! | 7 | [`Heartbeat`] | both | sender's clock |
//! | 8 | [`DeviceStatus`] | edge → server | sensor lost / back, acquisition paused / resumed, with a reason |
//! | 9 | [`Command`] | server → edge | start static scan at a named position, stop it, set a motor speed, start / stop a trolley pass |
//! | 10 | [`StaticScan`] | edge → server | static 3D scan: start (position, step, mount), the yaws of each Sweep revolution's samples as runs of sample indices, warnings, end |
//! | 11 | [`ClockModel`] | none (legacy: only in older recordings) | edge → server clock mapping; kept so recordings made before the server recorded it as its own record type still decode; never sent, never written |
//! | 12 | [`CommandReply`] | edge → server | the answer to a [`Command`] (by its frame's `seq`): accepted (with the static scan's id), waiting (for the Sweep, say), or refused with the reason |
//! | 13 | [`SensorMounts`] | edge → server | each configured sensor's pose in `base` ([`SensorMount`]: x, y, z in m; roll, pitch, yaw in degrees); once per session right after the first `Hello` |
//! | 14 | [`PassMarker`] | edge → server | a trolley pass started (name, x, y, heading in the room frame) or stopped, at an edge time ([`PassEvent`]) |
//!
//! **One sample timeline.** Every lidar sample travels once, in its [`LidarRevolution`], with
//! the one measurement time the edge estimated for it. During a static scan the edge adds, per
//! Sweep revolution, a [`StaticScan::Yaws`] message naming that revolution by its `t0_ns` and
//! giving the turntable yaw φ of runs of its sample indices ([`YawRun`]); θ of eq. (1) is
//! [`theta_deg`] on both sides.
//!
//! Time-sync pings and pongs travel as QUIC datagrams (one frame each, `seq` 0, neither
//! acknowledged nor resent); every other frame goes on the reliable stream.
//!
//! Sensors are named by [`SensorId`] (0 rplidar, 1 sweep, 2 imu, 3 stepper). All edge times are
//! nanoseconds on the edge's monotonic clock.
//!
//! **Reordering enum variants or struct fields breaks the wire**: new variants go at the end, and
//! any other change needs a new [`PROTOCOL_VERSION`].
//!
//! # Use
//!
//! ```
//! use scan3d_protocol::{Frame, FrameReader, Heartbeat, decode, encode};
//!
//! let frame = Frame::new(0x5eed, 0, Heartbeat { sent_ns: 42 });
//! let bytes = encode(&frame)?;
//! assert_eq!(decode(&bytes)?, (frame.clone(), bytes.len()));
//!
//! // From a stream, in arbitrary chunks:
//! let mut reader = FrameReader::new();
//! reader.push(&bytes[..3]);
//! assert_eq!(reader.next_frame()?, None);
//! reader.push(&bytes[3..]);
//! assert_eq!(reader.next_frame()?, Some(frame));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![warn(missing_docs)]

mod codec;
mod frame;
mod types;
mod version;

pub use codec::{
    DecodeError, EncodeError, FrameHeader, FrameReader, HEADER_LEN, MAGIC, MAX_FRAME_LEN, decode,
    decode_header, decode_ids, encode,
};
pub use frame::{Body, Direction, Frame};
pub use types::{
    Ack, ClockModel, Command, CommandOutcome, CommandReply, DeviceStatus, Heartbeat, Hello,
    ImuSample, InvalidCommand, InvalidMounts, LidarRevolution, MAX_MOTOR_SPEED_HZ,
    MAX_POSITION_NAME_LEN, MAX_SENSOR_MOUNTS, MountInfo, PassEvent, PassMarker, RevolutionSample,
    SampleTimeError, SensorId, SensorInfo, SensorMount, SensorMounts, StaticScan, StaticScanEnd,
    StaticScanOutcome, StaticScanProblem, StaticScanStart, StaticScanWarning, StaticScanYaws,
    StatusEvent, StepperState, TimePing, TimePong, YawRun, theta_deg,
};
pub use version::{IncompatibleVersion, PROTOCOL_VERSION, check_compatible};

/// The QUIC/TLS application protocol name (ALPN) of the edge↔server link; it carries the
/// protocol version so a mismatched peer fails the TLS handshake with a clear reason.
pub const ALPN: &[u8] = b"scan3d/1";
