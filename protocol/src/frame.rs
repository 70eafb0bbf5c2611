//! [`Frame`]: the unit exchanged between edge and server, and its [`Body`].

use serde::{Deserialize, Serialize};

use crate::types::{
    Ack, ClockModel, Command, CommandReply, DeviceStatus, Heartbeat, Hello, ImuSample,
    LidarRevolution, PassMarker, SensorMounts, StaticScan, StepperState, TimePing, TimePong,
};

/// One message with its session and sequence number.
///
/// Both directions of a connection use the **edge's** session id (random per edge boot); each
/// direction numbers its own frames from 0 within the session. The server acknowledges edge frames
/// with [`Ack`] by these sequence numbers, and resent frames keep their original number, so
/// receiving one twice is harmless.
///
/// **Two paths.** Every frame on the connection's reliable stream is sequenced and (edge →
/// server) acknowledged. Time-sync frames ([`Body::TimePing`], [`Body::TimePong`]) travel
/// instead as one frame per QUIC datagram (the same encoding): they carry `seq` 0, are neither
/// sequence-numbered nor acknowledged, and are never spooled or resent, so a backlog on the
/// stream cannot delay them and a reconnect cannot replay a stale one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// Random id chosen by the edge at boot; a new id means a new edge clock epoch.
    pub session_id: u64,
    /// Per-session, per-direction sequence number.
    pub seq: u64,
    /// The message.
    pub body: Body,
}

impl Frame {
    /// A frame carrying `body` (anything convertible, e.g. a [`Hello`] or an [`Ack`]).
    pub fn new(session_id: u64, seq: u64, body: impl Into<Body>) -> Self {
        Frame {
            session_id,
            seq,
            body: body.into(),
        }
    }
}

/// Which way a message normally travels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Sent by the edge to the server.
    EdgeToServer,
    /// Sent by the server to the edge.
    ServerToEdge,
    /// Either side may send it.
    Both,
}

/// The message inside a [`Frame`].
///
/// **The variant order is the wire tag** (postcard writes the variant index as a varint) and must
/// never change: add new variants at the end only, and bump [`crate::PROTOCOL_VERSION`] for
/// anything else.
///
/// | tag | variant | direction |
/// | --- | --- | --- |
/// | 0 | [`Body::Hello`] | edge → server |
/// | 1 | [`Body::Revolution`] | edge → server |
/// | 2 | [`Body::Imu`] | edge → server |
/// | 3 | [`Body::Stepper`] | edge → server |
/// | 4 | [`Body::TimePing`] | server → edge |
/// | 5 | [`Body::TimePong`] | edge → server |
/// | 6 | [`Body::Ack`] | both |
/// | 7 | [`Body::Heartbeat`] | both |
/// | 8 | [`Body::Status`] | edge → server |
/// | 9 | [`Body::Command`] | server → edge |
/// | 10 | [`Body::StaticScan`] | edge → server |
/// | 11 | [`Body::ClockModel`] | none: legacy, only read from older recordings |
/// | 12 | [`Body::CommandReply`] | edge → server |
/// | 13 | [`Body::Mounts`] | edge → server |
/// | 14 | [`Body::Pass`] | edge → server |
///
/// `TimePing` and `TimePong` travel in QUIC datagrams, not on the stream (see [`Frame`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Body {
    /// Edge identity and sensor inventory; first frame of a connection.
    Hello(Hello),
    /// One lidar revolution with per-sample times.
    Revolution(LidarRevolution),
    /// One IMU reading.
    Imu(ImuSample),
    /// Stepper state change.
    Stepper(StepperState),
    /// Time-sync request carrying the server's send time (a datagram).
    TimePing(TimePing),
    /// Time-sync answer carrying t0, t1 and t2 (a datagram).
    TimePong(TimePong),
    /// Acknowledgement of received frames.
    Ack(Ack),
    /// Keep-alive.
    Heartbeat(Heartbeat),
    /// Sensor lost / back, acquisition paused / resumed.
    Status(DeviceStatus),
    /// Order from the server.
    Command(Command),
    /// Static 3D scan: start, the yaws of each Sweep revolution's samples, warnings, end.
    StaticScan(StaticScan),
    /// Legacy: the server's mapping of the edge clock as recordings of protocol 2 held it
    /// before the server recorded it as a record type of its own (the server's
    /// `recording::ServerRecord`). The tag stays so those recordings decode; nothing sends
    /// this body or writes it any more (the server's recorder refuses it), and a server that
    /// receives one treats it as a misdirected frame.
    ClockModel(ClockModel),
    /// The edge's answer to a [`Body::Command`]: accepted, waiting or refused with the reason.
    CommandReply(CommandReply),
    /// The sensors' poses in `base` from the edge's config; once per session after `Hello`.
    Mounts(SensorMounts),
    /// A trolley pass starting or stopping, stamped on the edge's clock.
    Pass(PassMarker),
}

impl Body {
    /// The variant's name (`"Hello"`, `"TimePong"`, …), for logs, errors and channel metadata.
    pub fn name(&self) -> &'static str {
        match self {
            Body::Hello(_) => "Hello",
            Body::Revolution(_) => "Revolution",
            Body::Imu(_) => "Imu",
            Body::Stepper(_) => "Stepper",
            Body::TimePing(_) => "TimePing",
            Body::TimePong(_) => "TimePong",
            Body::Ack(_) => "Ack",
            Body::Heartbeat(_) => "Heartbeat",
            Body::Status(_) => "Status",
            Body::Command(_) => "Command",
            Body::StaticScan(_) => "StaticScan",
            Body::ClockModel(_) => "ClockModel",
            Body::CommandReply(_) => "CommandReply",
            Body::Mounts(_) => "Mounts",
            Body::Pass(_) => "Pass",
        }
    }

    /// Whether the server makes this body (a command, a time ping, a clock model): numbered in
    /// the server's own sequence, never part of an edge's.
    pub fn is_server_made(&self) -> bool {
        self.direction() == Direction::ServerToEdge
    }

    /// Which way this message normally travels, so a receiver can reject misdirected frames.
    pub fn direction(&self) -> Direction {
        match self {
            Body::Hello(_)
            | Body::Revolution(_)
            | Body::Imu(_)
            | Body::Stepper(_)
            | Body::TimePong(_)
            | Body::Status(_)
            | Body::StaticScan(_)
            | Body::CommandReply(_)
            | Body::Mounts(_)
            | Body::Pass(_) => Direction::EdgeToServer,
            // A clock model originates at the server (it is recorded, not sent): an edge that
            // sends one is misdirected like one sending a command.
            Body::TimePing(_) | Body::Command(_) | Body::ClockModel(_) => Direction::ServerToEdge,
            Body::Ack(_) | Body::Heartbeat(_) => Direction::Both,
        }
    }
}

macro_rules! body_from {
    ($($ty:ident => $variant:ident),* $(,)?) => {
        $(
            impl From<$ty> for Body {
                fn from(value: $ty) -> Self {
                    Body::$variant(value)
                }
            }
        )*
    };
}

body_from! {
    Hello => Hello,
    LidarRevolution => Revolution,
    ImuSample => Imu,
    StepperState => Stepper,
    TimePing => TimePing,
    TimePong => TimePong,
    Ack => Ack,
    Heartbeat => Heartbeat,
    DeviceStatus => Status,
    Command => Command,
    StaticScan => StaticScan,
    ClockModel => ClockModel,
    CommandReply => CommandReply,
    SensorMounts => Mounts,
    PassMarker => Pass,
}
