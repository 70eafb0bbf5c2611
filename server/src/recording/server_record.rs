//! Server-made records: what the server itself adds to a session's recording (clock models
//! today; poses, pass markers, watermark releases and command stamps are meant to follow).
//!
//! They are not wire frames. Each kind ([`RecordKind`]) has its own topic and its own MCAP
//! schema, named with the kind's version (`scan3d.ClockModel.v1`); the message data says the
//! same in a small header, so a record is recognised even when the chunk that declared its
//! channel is damaged:
//!
//! ```text
//! "S3DR"  kind tag (u16 LE)  kind version (u16 LE)  postcard payload
//! ```
//!
//! So a new kind, or a new version of one, needs no `PROTOCOL_VERSION` bump and strands no
//! recording: a reader decodes the versions it knows and skips (and counts) the others.
//! Recordings written before this layer hold clock models as wire frames
//! (`Body::ClockModel` on `/scan3d/timesync`); the reader hands those on as
//! [`ServerRecord::ClockModel`] too (see [`super::reader`]).

use scan3d_protocol::ClockModel;

/// Message encoding of a server-made record's channel (layout in the module documentation).
pub const SERVER_RECORD_ENCODING: &str = "scan3d-record";

/// Encoding of the MCAP schema of a server-made record: its data is a text describing the
/// payload (the Rust type, postcard-encoded), for people and tools.
pub const SERVER_RECORD_SCHEMA_ENCODING: &str = "scan3d-record-schema";

/// First bytes of a server-made record's message data.
pub(crate) const SERVER_RECORD_MAGIC: [u8; 4] = *b"S3DR";

/// Length of the header before the payload: magic, tag, version.
const HEADER_LEN: usize = 8;

/// The kinds of server-made record, each with its tag, version, topic and schema.
///
/// A kind's tag never changes and is never reused; its version goes up when its payload
/// changes (readers keep decoding the older versions they know).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RecordKind {
    /// [`ServerRecord::ClockModel`]: tag 1.
    ClockModel,
}

impl RecordKind {
    /// Every kind this build writes.
    pub const ALL: [RecordKind; 1] = [RecordKind::ClockModel];

    /// The kind's tag in the message header.
    pub fn tag(self) -> u16 {
        match self {
            RecordKind::ClockModel => 1,
        }
    }

    /// The kind with this tag, if this build knows it.
    pub fn from_tag(tag: u16) -> Option<Self> {
        Self::ALL.into_iter().find(|kind| kind.tag() == tag)
    }

    /// The version of the payload this build writes.
    pub fn version(self) -> u16 {
        match self {
            // The postcard encoding of `scan3d_protocol::ClockModel` as of protocol version 2.
            RecordKind::ClockModel => 1,
        }
    }

    /// The kind's name: the type in the schema name.
    pub fn name(self) -> &'static str {
        match self {
            RecordKind::ClockModel => "ClockModel",
        }
    }

    /// The MCAP topic its records are written on.
    pub fn topic(self) -> &'static str {
        match self {
            // The topic the clock models had as wire frames: one topic for both.
            RecordKind::ClockModel => "/scan3d/timesync",
        }
    }

    /// The MCAP schema name of `version` of this kind: `scan3d.<name>.v<version>`.
    pub fn schema_name(self, version: u16) -> String {
        format!("scan3d.{}.v{version}", self.name())
    }

    /// The MCAP schema data: what the payload is, for people and tools.
    pub fn schema_text(self) -> &'static str {
        match self {
            RecordKind::ClockModel => {
                "postcard scan3d_protocol::ClockModel { offset_ns: i64, skew_ppm: f64, \
                 error_bound_ns: u64, skew_bound_ppm: f64, ref_edge_ns: u64, \
                 fit_from_edge_ns: u64, fit_to_edge_ns: u64, valid_from_edge_ns: u64, \
                 min_delay_ns: u64, exchanges: u32 }"
            }
        }
    }
}

/// A record the server makes and writes into a session's recording (not a wire frame).
#[derive(Debug, Clone, PartialEq)]
pub enum ServerRecord {
    /// The server's model of the edge clock, each time it changes, so a replay maps sample
    /// times exactly as the live server did (`pose::timesync::SessionClock` reads them back).
    ClockModel(ClockModel),
}

impl From<ClockModel> for ServerRecord {
    fn from(model: ClockModel) -> Self {
        ServerRecord::ClockModel(model)
    }
}

/// Why message data is not a server-made record this build can read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ServerRecordError {
    /// The data does not start with the record header.
    #[error("not a server-made record (no S3DR header)")]
    NotARecord,
    /// A kind or version this build does not know (a newer server wrote it).
    #[error("server-made record of unknown kind {tag} version {version}")]
    Unknown {
        /// The kind's tag.
        tag: u16,
        /// The kind's version.
        version: u16,
    },
    /// The header is known, the payload does not decode.
    #[error("{kind:?} record (version {version}): {reason}")]
    Payload {
        /// The kind.
        kind: RecordKind,
        /// Its version.
        version: u16,
        /// postcard's error, or the bytes left over.
        reason: String,
    },
}

impl ServerRecord {
    /// Its kind.
    pub fn kind(&self) -> RecordKind {
        match self {
            ServerRecord::ClockModel(_) => RecordKind::ClockModel,
        }
    }

    /// The edge time (ns, edge monotonic clock) the record refers to, if any: the MCAP
    /// `publish_time` it is written with.
    pub fn edge_time_ns(&self) -> Option<u64> {
        match self {
            ServerRecord::ClockModel(model) => Some(model.valid_from_edge_ns),
        }
    }

    /// The message data: header, then the postcard payload of the current version.
    pub fn encode(&self) -> Vec<u8> {
        let kind = self.kind();
        let mut data = Vec::with_capacity(HEADER_LEN + 96);
        data.extend_from_slice(&SERVER_RECORD_MAGIC);
        data.extend_from_slice(&kind.tag().to_le_bytes());
        data.extend_from_slice(&kind.version().to_le_bytes());
        let payload = match self {
            ServerRecord::ClockModel(model) => postcard::to_extend(model, data),
        };
        // Plain structs of numbers: postcard cannot fail on them.
        payload.expect("a server-made record always serialises")
    }

    /// Reads message data written by [`encode`](Self::encode) (this or an earlier version).
    pub fn decode(data: &[u8]) -> Result<Self, ServerRecordError> {
        let rest = data
            .strip_prefix(&SERVER_RECORD_MAGIC)
            .ok_or(ServerRecordError::NotARecord)?;
        let (tag, rest) = rest
            .split_first_chunk::<2>()
            .ok_or(ServerRecordError::NotARecord)?;
        let (version, payload) = rest
            .split_first_chunk::<2>()
            .ok_or(ServerRecordError::NotARecord)?;
        let (tag, version) = (u16::from_le_bytes(*tag), u16::from_le_bytes(*version));
        let unknown = ServerRecordError::Unknown { tag, version };
        let kind = RecordKind::from_tag(tag).ok_or(unknown.clone())?;
        let bad = |reason: String| ServerRecordError::Payload {
            kind,
            version,
            reason,
        };
        match (kind, version) {
            (RecordKind::ClockModel, 1) => {
                whole(payload).map(ServerRecord::ClockModel).map_err(bad)
            }
            _ => Err(unknown),
        }
    }
}

/// Decodes a payload that must be exactly one `T`.
fn whole<'a, T: serde::Deserialize<'a>>(payload: &'a [u8]) -> Result<T, String> {
    match postcard::take_from_bytes::<T>(payload) {
        Ok((value, [])) => Ok(value),
        Ok((_, rest)) => Err(format!("{} bytes after the payload", rest.len())),
        Err(e) => Err(e.to_string()),
    }
}

/// A server-made record read back from a recording.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedServerRecord {
    /// The MCAP topic it was recorded on.
    pub topic: String,
    /// When the server made it, ns since the UNIX epoch.
    pub log_time_ns: u64,
    /// The record.
    pub record: ServerRecord,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> ClockModel {
        ClockModel {
            offset_ns: -3_000_000_123,
            skew_ppm: 41.5,
            error_bound_ns: 250_000,
            skew_bound_ppm: 0.75,
            ref_edge_ns: 10_000_000_000,
            fit_from_edge_ns: 9_000_000_000,
            fit_to_edge_ns: 11_000_000_000,
            valid_from_edge_ns: 11_000_000_000,
            min_delay_ns: 800_000,
            exchanges: 12,
        }
    }

    #[test]
    fn a_clock_model_round_trips_behind_its_header() {
        let record = ServerRecord::ClockModel(model());
        let data = record.encode();
        assert_eq!(&data[..8], b"S3DR\x01\x00\x01\x00");
        assert_eq!(ServerRecord::decode(&data), Ok(record.clone()));
        assert_eq!(record.edge_time_ns(), Some(11_000_000_000));
        assert_eq!(
            RecordKind::ClockModel.schema_name(1),
            "scan3d.ClockModel.v1"
        );
        assert_eq!(record.kind().topic(), "/scan3d/timesync");
    }

    #[test]
    fn unknown_kinds_versions_and_bad_payloads_are_told_apart() {
        let data = ServerRecord::ClockModel(model()).encode();
        assert_eq!(
            ServerRecord::decode(b"S3DU\x01\x00\x01\x00"),
            Err(ServerRecordError::NotARecord)
        );
        assert_eq!(
            ServerRecord::decode(b"S3DR\x01"),
            Err(ServerRecordError::NotARecord)
        );
        let mut newer = data.clone();
        newer[6] = 2;
        assert_eq!(
            ServerRecord::decode(&newer),
            Err(ServerRecordError::Unknown { tag: 1, version: 2 })
        );
        let mut other = data.clone();
        other[4] = 9;
        assert_eq!(
            ServerRecord::decode(&other),
            Err(ServerRecordError::Unknown { tag: 9, version: 1 })
        );
        let cut = &data[..data.len() - 1];
        assert!(matches!(
            ServerRecord::decode(cut),
            Err(ServerRecordError::Payload {
                kind: RecordKind::ClockModel,
                version: 1,
                ..
            })
        ));
        let mut long = data.clone();
        long.push(0);
        assert_eq!(
            ServerRecord::decode(&long).unwrap_err().to_string(),
            "ClockModel record (version 1): 1 bytes after the payload"
        );
    }
}
