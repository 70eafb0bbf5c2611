//! Session recordings: the layer beneath ingest, pose and pipeline. Every frame an edge sends,
//! exactly once, and every record the server makes about the session, durably, in MCAP files.
//!
//! Ingest hands each frame it receives to a [`SessionRecorder`] ([`SessionRecorder::append`]),
//! then calls [`SessionRecorder::commit`] before acknowledging: commit finishes the MCAP chunk
//! that holds the frames, flushes and fsyncs the file, and returns the highest sequence number
//! up to which everything is durable — the value for [`scan3d_protocol::Ack::UpTo`]. Pose and
//! the pipeline read recordings back with [`SessionReader`] (or the frame views
//! [`visit_session`], [`visit_session_items`], [`read_session`]).
//!
//! One file per concern:
//!
//! | module | what |
//! | --- | --- |
//! | [`schema`] | topics, message encodings, the edge timestamp of each body |
//! | [`seq_ranges`] | [`SeqRanges`], the one set-of-seqs type (recorded, durable, acknowledged, processed) |
//! | [`undecodable`] | the format of frames kept raw ([`UndecodableFrame`]) |
//! | [`server_record`] | server-made records ([`ServerRecord`]): their kinds, schemas and versions |
//! | `walker` | one MCAP file record by record, damaged chunks skipped and reported |
//! | [`reader`] | a session's files in order, deduplicated, from a sequence number or from where the last read ended ([`SessionReader`], [`ReadPosition`]) |
//! | `index` | `recorded.idx`: what each file holds, so opening and reading skip files |
//! | [`writer`] | [`SessionRecorder`]: appends, commits, file rotation, recovery at open |
//! | [`listing`] | `scan3d sessions`: [`list_sessions`], [`summarize_session`] |
//!
//! # Layout
//!
//! ```text
//! data_dir/sessions/<edge>/<session id, 16 lower-case hex digits>/0000.mcap
//!                                                                  0001.mcap  (after a restart)
//!                                                                  …
//!                                                                  recorded.idx
//! ```
//!
//! `<edge>` is the edge's name (from its client certificate): ASCII letters, digits, `.`, `_` and
//! `-`, not starting with a dot. Every [`SessionRecorder::open`] starts a **new** file, numbered
//! one past the highest existing one (and a recorder continues in the next one after
//! [`CHUNKS_PER_FILE`] commits); an existing file is never appended to. A server that
//! crashed leaves its last file without summary and perhaps with a half-written chunk.
//!
//! # Reading damaged files
//!
//! The readers walk each file record by record and check every chunk (its CRC, and that it
//! decompresses to the size it announces) before using any of its messages. A damaged chunk is
//! skipped and reported as a [`Loss`] (file, byte range, message count from the message index
//! that follows it); reading resumes at the chunk's declared end when a record starts there,
//! otherwise at the next chunk that validates (a scan for the chunk opcode). A record that runs
//! past the end of the file with nothing valid after it is the torn tail of a crash: the file
//! counts as cut short, which is no loss (nothing in it was acknowledged). Messages whose
//! channel was declared in a damaged chunk are still recognised by their own header.
//!
//! # Session index (`recorded.idx`)
//!
//! So that reopening a session (every reconnect) does not read and fsync every earlier file,
//! and a reader can start at a sequence number without reading what lies before it, the
//! recorder keeps a small text index of what the session's finished files hold (written when
//! it closes, when it continues in a new file, and at open after reading unindexed files):
//!
//! ```text
//! scan3d-recorded-index 2
//! file 0 183420 0-1520     (file number, length in bytes when indexed, the edge seqs in it)
//! file 1 96211 1522-1600
//! edge 0-1520 1522-1600    (every edge seq recorded, inclusive ranges; undecodable ones too)
//! commands 0-3             (every server command seq recorded)
//! crc 1c291d0a             (CRC-32 of all the lines above, hex)
//! ```
//!
//! A file's edge seqs are those first recorded in it; `?` instead of them means unknown (a
//! file indexed by version 1 of the index, `scan3d-recorded-index 1`, whose `file` lines end
//! after the length; it is still read). [`SessionRecorder::open`] trusts the index for each
//! listed file that still has exactly that length and reads (and fsyncs) only the others — the
//! file of a run that crashed or is still writing — then rewrites the index to cover them too,
//! so a file is read at most once. [`SessionReader::from_seq`] skips the leading files it lists,
//! unchanged, whose edge seqs all lie below the start. Crash safety: the index only lists files
//! already fsynced; it is replaced atomically (temporary file, fsync, rename, directory fsync);
//! a missing, torn or CRC-failing index, or one listing a file that is now missing or shorter,
//! is ignored and every file is read, as before the index existed. Failing to write it (a full
//! disk) only costs the next open that read.
//!
//! # Files
//!
//! Standard MCAP (profile `scan3d`), LZ4-compressed chunks with CRCs (older recordings: zstd,
//! still read), message indexes and a summary with statistics when the file was closed
//! properly. Chunks are at most about 1 MiB uncompressed, and every commit ends one.
//!
//! - A metadata record `scan3d-session` at the start holds `edge`, `session_id` (hex),
//!   `file_index` and `recorder` (the server version).
//! - Wire frames: one channel per stream, without schema (schema id 0). Message encoding
//!   `scan3d-frame`: the message data is the **exact** wire frame as received (or, for a
//!   command, as sent), the 10-byte S3DP header (magic, protocol version, payload length)
//!   followed by the postcard [`Frame`]; decode it with [`scan3d_protocol::decode`]. Channel
//!   metadata `body` names the body type (and `sensor` the lidar on lidar channels).
//!   Message `sequence` is the low 32 bits of the frame's `seq` (it wraps; the full `u64` is
//!   in the frame).
//! - Server-made records: one channel per kind, with a schema named after the kind and its
//!   version (`scan3d.ClockModel.v1`); message encoding `scan3d-record`, data `"S3DR"`, the
//!   kind's tag and version (u16 LE each) and the postcard payload (see [`server_record`]).
//!   Message `sequence` 0: they take no sequence number.
//! - `log_time` is the server's receive (or send, or making) time in ns since the UNIX epoch.
//!   `publish_time` is the edge's own timestamp of the body or record (ns on the edge's
//!   monotonic clock, another epoch), or `log_time` when it has none.
//!
//! | topic | what | `publish_time` |
//! | --- | --- | --- |
//! | `/scan3d/hello` | [`Body::Hello`] | log time |
//! | `/scan3d/lidar/<sensor>` | [`Body::Revolution`] (`rplidar`, `sweep`; `sensor<N>` for an unknown id) | `t1_ns` (end of the revolution) |
//! | `/scan3d/imu` | [`Body::Imu`] | `t_ns` |
//! | `/scan3d/stepper` | [`Body::Stepper`] | `t_ns` |
//! | `/scan3d/timesync` | [`ServerRecord::ClockModel`]: the server's edge-clock model each time it changes ([`SessionRecorder::append_record`]; read back with `pose::timesync::SessionClock`). Recordings made before server-made records hold [`Body::ClockModel`] wire frames here (server seqs shared with the commands); the reader hands those on as the same record | `valid_from_edge_ns` |
//! | `/scan3d/timepong` | [`Body::TimePong`] that came on the stream (pongs belong in datagrams, which are not recorded) | `t2_ns` |
//! | `/scan3d/status` | [`Body::Status`] | `t_ns` |
//! | `/scan3d/heartbeat` | [`Body::Heartbeat`] from the edge | `sent_ns` |
//! | `/scan3d/ack` | [`Body::Ack`] from the edge (it takes an edge sequence number too) | log time |
//! | `/scan3d/command` | [`Body::Command`] the server sent ([`SessionRecorder::append_command`]) | log time |
//! | `/scan3d/command_reply` | [`Body::CommandReply`]: the edge's answer to a command (accepted, waiting, refused with the reason) | `t_ns` |
//! | `/scan3d/mounts` | [`Body::Mounts`]: each configured sensor's pose in `base`, once per session after `Hello` | log time |
//! | `/scan3d/pass` | [`Body::Pass`]: a trolley pass started (name, pose in the room frame) or stopped | `t_ns` |
//! | `/scan3d/static_scan` | [`Body::StaticScan`]: start (position, step, mount), the yaws of a Sweep revolution's samples, warnings, end | `t_ns` (yaws: the revolution's `t0_ns`) |
//! | `/scan3d/undecodable` | a frame the server could not decode ([`SessionRecorder::append_undecodable`]); encoding `scan3d-undecodable`, see below | log time |
//!
//! A frame the server cannot decode (or will not record as what it claims to be) is kept rather
//! than skipped, so that its sequence number counts as recorded and acknowledgements move past
//! it: channel `/scan3d/undecodable`, message encoding `scan3d-undecodable`, message data
//! `"S3DU"`, the full `seq` (u64 LE), the reason's length (u16 LE), the reason (UTF-8, at most
//! [`UNDECODABLE_REASON_LIMIT`] bytes) and then the raw bytes as received. The readers count
//! these ([`SessionSummary::undecodable_frames`]) and do not hand them to frame visitors.
//!
//! # Versions
//!
//! Wire frames carry the protocol version in their header; postcard has no field tags, so a
//! recording whose frames name another version than [`PROTOCOL_VERSION`] is refused with one
//! line naming it ([`RecorderError::ProtocolVersion`]). New wire bodies go at the end of
//! [`Body`], so recordings of protocol 2 and later stay readable. Server-made records are
//! versioned per kind, in their schema name and header, never by `PROTOCOL_VERSION`: adding
//! one strands no recording.
//!
//! # Sequence numbers
//!
//! Edge frames and server-originated frames (commands) number their frames independently
//! (see [`Frame`]), so the recorder keeps two sets: a frame is a duplicate when its
//! `(session, direction, seq)` is already recorded, durable or buffered. Durable edge sequence
//! numbers are tracked as ranges; [`SessionRecorder::commit`] returns the contiguous prefix,
//! [`SessionRecorder::durable_ranges`] all of them. Server-made records take no sequence
//! number.

mod index;
pub mod listing;
pub mod reader;
pub mod schema;
pub mod seq_ranges;
pub mod server_record;
pub mod undecodable;
mod walker;
pub mod writer;

use std::fs::{self, File};
use std::io;
use std::path::{Path, PathBuf};

use mcap::McapError;
#[cfg(doc)]
use scan3d_protocol::{Body, Frame, PROTOCOL_VERSION};

pub use listing::{SessionSummary, is_being_written, list_sessions, summarize_session};
pub use reader::{
    Loss, ReadPosition, RecordedFrame, SessionItem, SessionReader, SessionRecord, SessionReport,
    check_losses, read_session, read_session_checked, read_session_report, visit_session,
    visit_session_items,
};
pub use schema::{MESSAGE_ENCODING, PROFILE, SESSION_METADATA, body_name, topic};
pub use seq_ranges::SeqRanges;
pub use server_record::{RecordKind, RecordedServerRecord, ServerRecord, ServerRecordError};
pub use undecodable::{
    UNDECODABLE_ENCODING, UNDECODABLE_REASON_LIMIT, UNDECODABLE_TOPIC, UndecodableFrame,
};
pub use writer::{Appended, CHUNKS_PER_FILE, SessionRecorder};

/// Why recording or reading a session failed.
#[derive(Debug, thiserror::Error)]
pub enum RecorderError {
    /// A file system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory concerned.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The MCAP writer failed (usually an I/O error underneath).
    #[error("{path}: MCAP: {source}")]
    Mcap {
        /// The file being written.
        path: PathBuf,
        /// The underlying error.
        source: McapError,
    },
    /// The edge name cannot be used as a directory name.
    #[error(
        "edge name {0:?} is not usable as a directory name (ASCII letters, digits, '.', '_', '-'; not starting with '.')"
    )]
    InvalidEdgeName(String),
    /// The frame belongs to another session than the recorder's.
    #[error("frame of session {got:016x} given to the recorder of session {expected:016x}")]
    WrongSession {
        /// The recorder's session.
        expected: u64,
        /// The frame's session.
        got: u64,
    },
    /// [`SessionRecorder::append`] got a server → edge body, or
    /// [`SessionRecorder::append_command`] got something else than a command.
    #[error("frame {seq} has a {body} body, which does not belong on this path")]
    Misdirected {
        /// The frame's sequence number.
        seq: u64,
        /// The body type.
        body: &'static str,
    },
    /// Part of a recording could not be read (damaged chunks); what was lost is in the message.
    /// [`read_session_report`] reads what is left.
    #[error("{dir}: recording damaged: {losses}")]
    Damaged {
        /// The session directory.
        dir: PathBuf,
        /// What was lost ([`SessionReport::loss_line`]).
        losses: String,
    },
    /// The session was recorded by a build speaking another protocol version (postcard has no
    /// field tags: its frames cannot be read as this version's). Nothing of it is read.
    #[error(
        "session {} was recorded with protocol version {version}; this build reads version {supported}",
        dir.display()
    )]
    ProtocolVersion {
        /// The session directory.
        dir: PathBuf,
        /// The version in the recorded frames' headers.
        version: u16,
        /// [`PROTOCOL_VERSION`].
        supported: u16,
    },
    /// An earlier write or sync failed; the file's state is unknown. Drop this recorder and
    /// [`SessionRecorder::open`] the session again (it continues in a new file).
    #[error("recorder for {0} failed earlier; open the session again")]
    Failed(PathBuf),
}

impl RecorderError {
    /// Whether this is a failure of the storage (I/O error, full disk, a recorder broken by
    /// one, a damaged file) rather than of what the caller gave (edge name, session, body).
    /// The ingest server closes the connection with `STORAGE_ERROR` for these (the edge keeps
    /// its spool and retries), with `PROTOCOL_ERROR` only for the others.
    pub fn is_storage(&self) -> bool {
        match self {
            RecorderError::Io { .. }
            | RecorderError::Mcap { .. }
            | RecorderError::Damaged { .. }
            // What is on disk, not what the caller gave.
            | RecorderError::ProtocolVersion { .. }
            | RecorderError::Failed(_) => true,
            RecorderError::InvalidEdgeName(_)
            | RecorderError::WrongSession { .. }
            | RecorderError::Misdirected { .. } => false,
        }
    }

    pub(crate) fn io(path: &Path) -> impl FnOnce(io::Error) -> RecorderError + '_ {
        move |source| RecorderError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// The MCAP files of a session directory, `(index, path)` in index order. Other files are ignored.
pub(crate) fn session_files(dir: &Path) -> Result<Vec<(u64, PathBuf)>, RecorderError> {
    let mut files = Vec::new();
    for entry in fs::read_dir(dir).map_err(RecorderError::io(dir))? {
        let entry = entry.map_err(RecorderError::io(dir))?;
        let name = entry.file_name();
        let Some(stem) = name.to_str().and_then(|n| n.strip_suffix(".mcap")) else {
            continue;
        };
        if stem.is_empty() || !stem.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        if let Ok(index) = stem.parse::<u64>() {
            files.push((index, entry.path()));
        }
    }
    files.sort();
    Ok(files)
}

/// Whether `edge` is safe as one directory name.
pub(crate) fn valid_edge_name(edge: &str) -> bool {
    !edge.is_empty()
        && edge.len() <= 255
        && !edge.starts_with('.')
        && edge
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// The directory of a session: `data_dir/sessions/<edge>/<session id as 16 hex digits>`.
pub fn session_dir(data_dir: &Path, edge: &str, session_id: u64) -> PathBuf {
    data_dir
        .join("sessions")
        .join(edge)
        .join(format!("{session_id:016x}"))
}

/// fsyncs a directory so that entries created in it survive a power cut.
pub(crate) fn sync_dir(dir: &Path) -> Result<(), RecorderError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(RecorderError::io(dir))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edge_names_are_single_safe_components() {
        for good in ["trolley-pi", "pi_2", "edge.lab", "A1"] {
            assert!(valid_edge_name(good), "{good}");
        }
        for bad in ["", ".", "..", ".hidden", "a/b", "a\\b", "pi 2", "é", "a\0b"] {
            assert!(!valid_edge_name(bad), "{bad:?}");
        }
    }

    #[test]
    fn session_dir_uses_16_hex_digits() {
        assert_eq!(
            session_dir(Path::new("/d"), "pi", 0x5eed),
            Path::new("/d/sessions/pi/0000000000005eed")
        );
    }

    #[test]
    fn only_numbered_mcap_files_count() {
        let tmp = tempfile::tempdir().expect("tempdir");
        for name in [
            "0002.mcap",
            "0000.mcap",
            "10.mcap",
            "x.mcap",
            "0001.mcap.tmp",
            "notes",
        ] {
            fs::write(tmp.path().join(name), b"").expect("write");
        }
        let names: Vec<u64> = session_files(tmp.path())
            .expect("list")
            .into_iter()
            .map(|(i, _)| i)
            .collect();
        assert_eq!(names, vec![0, 2, 10]);
    }
}
