//! Durable session recordings: every frame an edge sends, exactly once, in MCAP files.
//!
//! The server hands each frame it receives to a [`SessionRecorder`] ([`SessionRecorder::append`]),
//! then calls [`SessionRecorder::commit`] before acknowledging: commit finishes the MCAP chunk that
//! holds the frames, flushes and fsyncs the file, and returns the highest sequence number up to
//! which everything is durable — the value for [`scan3d_protocol::Ack::UpTo`].
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
//! [`SessionRecorder::close`] writes a small text index of what the session's files hold:
//!
//! ```text
//! scan3d-recorded-index 1
//! file 0 183420            (file number, length in bytes it had when indexed; one per file)
//! file 1 96211
//! edge 0-1520 1522-1600    (every edge seq recorded, inclusive ranges; undecodable ones too)
//! commands 0-3             (every server command seq recorded)
//! crc 1c291d0a             (CRC-32 of all the lines above, hex)
//! ```
//!
//! [`SessionRecorder::open`] trusts it for each listed file that still has exactly that length
//! and reads (and fsyncs) only the others — the file of a run that crashed or is still
//! writing — then rewrites the index to cover them too, so a file is read at most once. Crash
//! safety: the index only lists files already fsynced; it is replaced atomically (temporary
//! file, fsync, rename, directory fsync); a missing, torn or CRC-failing index, or one listing
//! a file that is now missing or shorter, is ignored and every file is read, as before the
//! index existed. Failing to write it (a full disk) only costs the next open that read.
//!
//! # Files
//!
//! Standard MCAP (profile `scan3d`), LZ4-compressed chunks with CRCs (older recordings: zstd,
//! still read), message indexes and a summary with statistics when the file was closed
//! properly. Chunks are at most about 1 MiB uncompressed, and every commit ends one.
//!
//! - A metadata record `scan3d-session` at the start holds `edge`, `session_id` (hex),
//!   `file_index` and `recorder` (the server version).
//! - One channel per stream, without schema (schema id 0). Message encoding `scan3d-frame`:
//!   the message data is the **exact** wire frame as received, the 10-byte S3DP header (magic,
//!   protocol version, payload length) followed by the postcard [`Frame`]; decode it with
//!   [`scan3d_protocol::decode`]. Channel metadata `body` names the body type (and `sensor` the
//!   lidar on lidar channels).
//! - Message `sequence` is the low 32 bits of the frame's `seq` (it wraps; the full `u64` is in
//!   the frame). `log_time` is the server's receive time in ns since the UNIX epoch.
//!   `publish_time` is the edge's own timestamp of the body (ns on the edge's monotonic clock,
//!   another epoch), or `log_time` when the body has none.
//!
//! | topic | body | `publish_time` |
//! | --- | --- | --- |
//! | `/scan3d/hello` | [`Body::Hello`] | log time |
//! | `/scan3d/lidar/<sensor>` | [`Body::Revolution`] (`rplidar`, `sweep`; `sensor<N>` for an unknown id) | `t1_ns` (end of the revolution) |
//! | `/scan3d/imu` | [`Body::Imu`] | `t_ns` |
//! | `/scan3d/stepper` | [`Body::Stepper`] | `t_ns` |
//! | `/scan3d/timesync` | [`Body::ClockModel`]: the server's edge-clock model each time it changes ([`SessionRecorder::append_clock_model`]; read back with `pose::timesync::SessionClock`) | `valid_from_edge_ns` |
//! | `/scan3d/timepong` | [`Body::TimePong`] that came on the stream (pongs belong in datagrams, which are not recorded) | `t2_ns` |
//! | `/scan3d/status` | [`Body::Status`] | `t_ns` |
//! | `/scan3d/heartbeat` | [`Body::Heartbeat`] from the edge | `sent_ns` |
//! | `/scan3d/ack` | [`Body::Ack`] from the edge (it takes an edge sequence number too) | log time |
//! | `/scan3d/command` | [`Body::Command`] the server sent ([`SessionRecorder::append_command`]) | log time |
//! | `/scan3d/command_reply` | [`Body::CommandReply`]: the edge's answer to a command (accepted, waiting, refused with the reason) | `t_ns` |
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
//! # Sequence numbers
//!
//! Edge frames and server-originated frames (commands, clock models) number their frames
//! independently (see [`Frame`]), so the recorder keeps two sets: a frame is a duplicate when its `(session, direction, seq)` is already
//! recorded, durable or buffered. Durable edge sequence numbers are tracked as ranges;
//! [`SessionRecorder::commit`] returns the contiguous prefix, [`SessionRecorder::durable_ranges`]
//! all of them.

use std::collections::{BTreeMap, HashMap};
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufWriter, Read, Seek, SeekFrom, Write};
use std::ops::RangeInclusive;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::records::{MessageHeader, Metadata};
use mcap::{Compression, McapError, WriteOptions, Writer};
use scan3d_protocol::{Body, DecodeError, Direction, Frame, PROTOCOL_VERSION, StaticScan, decode};
use serde::Serialize;

/// The MCAP message encoding of every channel: S3DP header + postcard [`Frame`].
pub const MESSAGE_ENCODING: &str = "scan3d-frame";

/// The MCAP profile written in the file header.
pub const PROFILE: &str = "scan3d";

/// Name of the metadata record at the start of every file.
pub const SESSION_METADATA: &str = "scan3d-session";

/// Topic of frames recorded with [`SessionRecorder::append_undecodable`].
pub const UNDECODABLE_TOPIC: &str = "/scan3d/undecodable";

/// Message encoding of [`UNDECODABLE_TOPIC`] (layout in the module documentation).
pub const UNDECODABLE_ENCODING: &str = "scan3d-undecodable";

/// First bytes of an undecodable-frame message, so it is recognised even when the chunk that
/// declared its channel is damaged.
const UNDECODABLE_MAGIC: [u8; 4] = *b"S3DU";

/// Longest reason kept with an undecodable frame, in bytes (longer ones are cut at a character
/// boundary): the reason is for people, the raw bytes are the evidence.
pub const UNDECODABLE_REASON_LIMIT: usize = 1024;

/// Largest record the readers accept (a chunk is at most ~1 MiB plus one 4 MiB frame), so a
/// corrupt length field cannot make them allocate gigabytes.
const RECORD_LENGTH_LIMIT: usize = 64 * 1024 * 1024;

/// Target uncompressed chunk size; a commit ends a chunk earlier.
const CHUNK_SIZE: u64 = 1024 * 1024;

/// Chunks after which a recorder finishes its file and continues in the next one: the MCAP
/// writer keeps an index entry (a few hundred bytes) per chunk until the file is finished, and
/// every commit ends a chunk, so this bounds what a busy recorder holds (about 300 KB; a new
/// file every ~100 s at the default 100 ms commit interval).
pub const CHUNKS_PER_FILE: u64 = 1024;

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

    fn io(path: &Path) -> impl FnOnce(io::Error) -> RecorderError + '_ {
        move |source| RecorderError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// What [`SessionRecorder::append`] did with a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Appended {
    /// Written to the open chunk; durable after the next [`SessionRecorder::commit`].
    Buffered,
    /// Already recorded (durable or buffered): ignored.
    Duplicate,
}

/// The body type's name, as in [`Body`] (used in channel metadata and errors).
pub fn body_name(body: &Body) -> &'static str {
    body.name()
}

/// The MCAP topic a frame with this body is recorded on (see the module table). `TimePing` only
/// travels server → edge and is never recorded; it maps to `/scan3d/timeping` for completeness.
pub fn topic(body: &Body) -> String {
    match body {
        Body::Hello(_) => "/scan3d/hello".into(),
        Body::Revolution(rev) => match rev.sensor.name() {
            Some(name) => format!("/scan3d/lidar/{name}"),
            None => format!("/scan3d/lidar/sensor{}", rev.sensor.0),
        },
        Body::Imu(_) => "/scan3d/imu".into(),
        Body::Stepper(_) => "/scan3d/stepper".into(),
        Body::TimePing(_) => "/scan3d/timeping".into(),
        Body::TimePong(_) => "/scan3d/timepong".into(),
        Body::Ack(_) => "/scan3d/ack".into(),
        Body::Heartbeat(_) => "/scan3d/heartbeat".into(),
        Body::Status(_) => "/scan3d/status".into(),
        Body::Command(_) => "/scan3d/command".into(),
        Body::StaticScan(_) => "/scan3d/static_scan".into(),
        Body::ClockModel(_) => "/scan3d/timesync".into(),
        Body::CommandReply(_) => "/scan3d/command_reply".into(),
    }
}

/// The edge's timestamp of a body (its monotonic clock), if it has one.
fn edge_time_ns(body: &Body) -> Option<u64> {
    match body {
        Body::Revolution(rev) => Some(rev.t1_ns),
        Body::Imu(imu) => Some(imu.t_ns),
        Body::Stepper(st) => Some(st.t_ns),
        Body::TimePong(pong) => Some(pong.t2_ns),
        Body::Status(status) => Some(status.t_ns),
        Body::Heartbeat(hb) => Some(hb.sent_ns),
        Body::StaticScan(scan) => Some(match scan {
            StaticScan::Started(start) => start.t_ns,
            StaticScan::Yaws(yaws) => yaws.revolution_t0_ns,
            StaticScan::Warning(warning) => warning.t_ns,
            StaticScan::Finished(end) => end.t_ns,
        }),
        Body::ClockModel(model) => Some(model.valid_from_edge_ns),
        Body::CommandReply(reply) => Some(reply.t_ns),
        Body::Hello(_) | Body::TimePing(_) | Body::Ack(_) | Body::Command(_) => None,
    }
}

/// A set of sequence numbers stored as disjoint, non-adjacent inclusive ranges, so that its
/// size grows with the number of gaps, not with the number of members (a session with a
/// permanent hole early on must not cost a few bytes per later frame).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct SeqSet {
    /// `start -> end` (inclusive) of each range.
    ranges: BTreeMap<u64, u64>,
}

impl SeqSet {
    pub(crate) fn contains(&self, seq: u64) -> bool {
        self.ranges
            .range(..=seq)
            .next_back()
            .is_some_and(|(_, &end)| seq <= end)
    }

    /// Adds `seq`; `false` if it was already there.
    pub(crate) fn insert(&mut self, seq: u64) -> bool {
        if self.contains(seq) {
            return false;
        }
        let below = seq.checked_sub(1).and_then(|prev| {
            self.ranges
                .range(..=prev)
                .next_back()
                .filter(|(_, end)| **end == prev)
                .map(|(&start, _)| start)
        });
        let above = seq
            .checked_add(1)
            .and_then(|next| self.ranges.remove(&next));
        match (below, above) {
            (Some(start), Some(end)) => self.ranges.insert(start, end),
            (Some(start), None) => self.ranges.insert(start, seq),
            (None, Some(end)) => self.ranges.insert(seq, end),
            (None, None) => self.ranges.insert(seq, seq),
        };
        true
    }

    /// Adds a whole range; ranges must come in increasing order, disjoint and non-adjacent
    /// from what is already there (as [`ranges`](Self::ranges) lists them). `false` otherwise,
    /// leaving the set unchanged.
    fn push_range(&mut self, range: RangeInclusive<u64>) -> bool {
        let (start, end) = (*range.start(), *range.end());
        let after_last = match self.ranges.last_key_value() {
            None => true,
            Some((_, &last_end)) => last_end.checked_add(1).is_some_and(|next| start > next),
        };
        if start > end || !after_last {
            return false;
        }
        self.ranges.insert(start, end);
        true
    }

    /// The largest member.
    pub(crate) fn last(&self) -> Option<u64> {
        self.ranges.last_key_value().map(|(_, &end)| end)
    }

    /// The highest `S` such that every seq `<= S` is in the set.
    fn prefix(&self) -> Option<u64> {
        self.ranges.get(&0).copied()
    }

    /// Every member as sorted, disjoint, non-adjacent inclusive ranges (the prefix first).
    fn ranges(&self) -> Vec<RangeInclusive<u64>> {
        self.ranges
            .iter()
            .map(|(&start, &end)| start..=end)
            .collect()
    }

    /// The seqs below the largest member that are not members, as ranges.
    fn holes(&self) -> Vec<RangeInclusive<u64>> {
        let mut holes = Vec::new();
        let mut next = 0u64;
        for (&start, &end) in &self.ranges {
            if start > next {
                holes.push(next..=start - 1);
            }
            match end.checked_add(1) {
                Some(n) => next = n,
                None => break,
            }
        }
        holes
    }
}

/// Deduplication key of a recorded frame: edge frames and server-originated ones number
/// separately.
fn dedup_key(frame: &Frame) -> (u64, bool) {
    (frame.session_id, server_originated(&frame.body))
}

/// Whether the server made this body (a command it sent, a clock model): numbered in the
/// server's sequence, not the edge's.
fn server_originated(body: &Body) -> bool {
    body.is_server_made()
}

/// The message data of an undecodable frame (see the module documentation).
fn undecodable_message(seq: u64, reason: &str, raw: &[u8]) -> Vec<u8> {
    let mut cut = reason.len().min(UNDECODABLE_REASON_LIMIT);
    while !reason.is_char_boundary(cut) {
        cut -= 1;
    }
    let reason = &reason.as_bytes()[..cut];
    let mut data = Vec::with_capacity(UNDECODABLE_MAGIC.len() + 10 + reason.len() + raw.len());
    data.extend_from_slice(&UNDECODABLE_MAGIC);
    data.extend_from_slice(&seq.to_le_bytes());
    // `cut` <= UNDECODABLE_REASON_LIMIT < 2^16.
    data.extend_from_slice(&(reason.len() as u16).to_le_bytes());
    data.extend_from_slice(reason);
    data.extend_from_slice(raw);
    data
}

/// Parses [`undecodable_message`]'s layout; `None` if `data` does not have it.
fn parse_undecodable(log_time_ns: u64, data: &[u8]) -> Option<UndecodableFrame> {
    let rest = data.strip_prefix(&UNDECODABLE_MAGIC)?;
    let (seq, rest) = rest.split_first_chunk::<8>()?;
    let (len, rest) = rest.split_first_chunk::<2>()?;
    let len = usize::from(u16::from_le_bytes(*len));
    if len > UNDECODABLE_REASON_LIMIT || len > rest.len() {
        return None;
    }
    let (reason, raw) = rest.split_at(len);
    Some(UndecodableFrame {
        log_time_ns,
        seq: u64::from_le_bytes(*seq),
        reason: String::from_utf8_lossy(reason).into_owned(),
        raw: raw.to_vec(),
    })
}

/// A frame recorded with [`SessionRecorder::append_undecodable`], read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UndecodableFrame {
    /// Server receive time, ns since the UNIX epoch.
    pub log_time_ns: u64,
    /// The edge sequence number it was recorded under.
    pub seq: u64,
    /// Why the server could not decode it.
    pub reason: String,
    /// The bytes as received.
    pub raw: Vec<u8>,
}

/// One frame read back from a recording.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedFrame {
    /// The MCAP topic it was recorded on.
    pub topic: String,
    /// Server receive time, ns since the UNIX epoch.
    pub log_time_ns: u64,
    /// The exact wire bytes (S3DP header + postcard payload).
    pub raw: Vec<u8>,
    /// `raw`, decoded.
    pub frame: Frame,
}

/// A stretch of a session file that could not be read (a damaged chunk or record): the frames
/// in it are lost to the readers, which read on after it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Loss {
    /// The file.
    pub file: PathBuf,
    /// Offset of the first unreadable byte.
    pub start: u64,
    /// Offset one past the last unreadable byte (where reading resumed, or the end of the file).
    pub end: u64,
    /// Chunk records known to lie in the stretch (0 when the stretch starts with a record that
    /// is not recognisable as one).
    pub chunks: u64,
    /// Messages lost, when the file's message index says (`None`: unknown).
    pub messages: Option<u64>,
    /// What was wrong.
    pub reason: String,
}

impl std::fmt::Display for Loss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: bytes {}..{} unreadable ({} chunk{}, {} messages lost): {}",
            self.file.display(),
            self.start,
            self.end,
            self.chunks,
            if self.chunks == 1 { "" } else { "s" },
            self.messages
                .map_or_else(|| "an unknown number of".to_string(), |n| n.to_string()),
            self.reason
        )
    }
}

/// How reading a session directory went, beyond the frames themselves.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
#[must_use = "a session read may have lost frames: check `losses`"]
pub struct SessionReport {
    /// Number of MCAP files.
    pub files: usize,
    /// Files that end early (a crash cut them short; read up to their last complete chunk).
    pub incomplete_files: usize,
    /// Messages that are not decodable `scan3d-frame`s (skipped).
    pub skipped_messages: u64,
    /// Frames the server received but could not decode, recorded raw on
    /// [`UNDECODABLE_TOPIC`] (each seq once; not visited as frames).
    pub undecodable_frames: u64,
    /// Total size of the files in bytes.
    pub bytes: u64,
    /// Damaged stretches skipped (empty when everything recorded was read). A file cut short
    /// by a crash is not a loss: what it lacks was never acknowledged.
    pub losses: Vec<Loss>,
    /// Edge sequence numbers below the highest one read that are in no file, as ranges. With
    /// losses, these are the frames the damaged stretches probably held (an edge numbers its
    /// frames without gaps, but frames it never delivered are missing too).
    pub missing_seqs: Vec<RangeInclusive<u64>>,
}

impl SessionReport {
    /// One line on what was lost (`None` when nothing was): the files, byte ranges, counts and
    /// the missing seqs.
    pub fn loss_line(&self) -> Option<String> {
        if self.losses.is_empty() {
            return None;
        }
        let mut line = self
            .losses
            .iter()
            .map(Loss::to_string)
            .collect::<Vec<_>>()
            .join("; ");
        if !self.missing_seqs.is_empty() {
            let seqs = self
                .missing_seqs
                .iter()
                .map(|r| {
                    if r.start() == r.end() {
                        r.start().to_string()
                    } else {
                        format!("{}..={}", r.start(), r.end())
                    }
                })
                .collect::<Vec<_>>()
                .join(", ");
            line.push_str(&format!("; edge seqs missing: {seqs}"));
        }
        Some(line)
    }
}

/// What one recording directory holds, for `scan3d sessions`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct SessionSummary {
    /// The edge's name.
    pub edge: String,
    /// The edge's session id.
    pub session_id: u64,
    /// The session directory.
    pub dir: PathBuf,
    /// Number of MCAP files.
    pub files: usize,
    /// Files that end early (a crash cut them short; read up to their last complete chunk).
    pub incomplete_files: usize,
    /// Unique frames (duplicates across files counted once).
    pub frames: u64,
    /// Unique frames per topic.
    pub frames_per_topic: BTreeMap<String, u64>,
    /// Messages that are not decodable `scan3d-frame`s (skipped).
    pub skipped_messages: u64,
    /// Frames the server received but could not decode, recorded raw on
    /// [`UNDECODABLE_TOPIC`] (each seq once; not counted in `frames`).
    pub undecodable_frames: u64,
    /// Earliest server receive time (ns since the UNIX epoch), if any frame.
    pub first_log_time_ns: Option<u64>,
    /// Latest server receive time (ns since the UNIX epoch), if any frame.
    pub last_log_time_ns: Option<u64>,
    /// The first lidar or IMU sample's time (edge monotonic clock, ns), if any.
    pub first_sample_ns: Option<u64>,
    /// The last lidar or IMU sample's time (edge monotonic clock, ns), if any.
    pub last_sample_ns: Option<u64>,
    /// Files a live server is writing now ([`is_being_written`]); they are counted in
    /// `incomplete_files` too, as they have no end yet.
    pub files_being_written: usize,
    /// Total size of the files in bytes.
    pub bytes: u64,
    /// Damaged stretches skipped, and the seqs they probably held (see [`SessionReport`]).
    pub losses: Vec<Loss>,
    /// See [`SessionReport::missing_seqs`].
    pub missing_seqs: Vec<RangeInclusive<u64>>,
}

/// How reading one file ended.
#[derive(Debug, Default)]
struct FileScan {
    /// It ended at the end magic (closed properly) rather than at a torn record.
    complete: bool,
    /// Messages skipped because they are not decodable frames.
    skipped: u64,
    /// The file's length when it was read.
    len: u64,
    /// Damaged stretches skipped.
    losses: Vec<Loss>,
}

/// The MCAP files of a session directory, `(index, path)` in index order. Other files are ignored.
fn session_files(dir: &Path) -> Result<Vec<(u64, PathBuf)>, RecorderError> {
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

/// Length of an MCAP record's opcode and length prefix.
const RECORD_HEAD: u64 = 9;

/// Smallest chunk record body: start and end time, uncompressed size, CRC, compression string
/// length, records length.
const CHUNK_HEADER_MIN: u64 = 8 + 8 + 8 + 4 + 4 + 8;

/// How many bytes the resynchronisation scan reads at a time.
const RESYNC_WINDOW: usize = 256 * 1024;

/// Whether `op` is an opcode the MCAP specification defines (0x01..=0x0F) or a private one.
fn known_opcode(op: u8) -> bool {
    (0x01..=0x0F).contains(&op) || op >= 0x80
}

/// `mcap::parse_record` for the records the readers use (chunk, message index, channel,
/// message), after checking that every length prefix in `body` fits inside it: the parser
/// reserves a prefix's length before reading, so a 28-byte file could otherwise ask for
/// gigabytes (found by `fuzz/fuzz_targets/mcap_session.rs`). Other records are `None`: the
/// readers never need them.
fn parse_record_checked(
    op: u8,
    body: &[u8],
) -> Option<Result<mcap::records::Record<'_>, mcap::McapError>> {
    use mcap::records::op;
    let mut fields = Prefixed { rest: body };
    let fits = match op {
        // start, end, uncompressed size (u64), CRC (u32), compression, records (u64 length).
        op::CHUNK => fields.skip(28) && fields.string() && fields.bytes_u64(),
        // channel id (u16), then (log time, offset) pairs behind a u32 byte length.
        op::MESSAGE_INDEX => fields.skip(2) && fields.bytes_u32(),
        // id, schema id (u16 each), topic, message encoding, metadata (u32 byte length).
        op::CHANNEL => fields.skip(4) && fields.string() && fields.string() && fields.string_map(),
        // channel (u16), sequence (u32), log and publish time (u64): the data is the rest.
        op::MESSAGE => fields.skip(22),
        _ => return None,
    };
    Some(if fits {
        mcap::parse_record(op, body)
    } else {
        Err(mcap::McapError::UnexpectedEof)
    })
}

/// Walks the length-prefixed fields of an MCAP record body without allocating.
struct Prefixed<'a> {
    rest: &'a [u8],
}

impl Prefixed<'_> {
    fn skip(&mut self, n: usize) -> bool {
        match self.rest.get(n..) {
            Some(rest) => {
                self.rest = rest;
                true
            }
            None => false,
        }
    }

    fn prefix<const N: usize>(&mut self) -> Option<u64> {
        let (head, _) = self.rest.split_first_chunk::<N>()?;
        let mut bytes = [0u8; 8];
        bytes[..N].copy_from_slice(head);
        self.rest = &self.rest[N..];
        Some(u64::from_le_bytes(bytes))
    }

    fn string(&mut self) -> bool {
        self.bytes_u32()
    }

    fn bytes_u32(&mut self) -> bool {
        self.prefix::<4>()
            .and_then(|n| usize::try_from(n).ok())
            .is_some_and(|n| self.skip(n))
    }

    /// A `map<string, string>`: a u32 byte length, then key and value strings that must each
    /// fit inside that length.
    fn string_map(&mut self) -> bool {
        let Some(len) = self.prefix::<4>().and_then(|n| usize::try_from(n).ok()) else {
            return false;
        };
        let Some((map, rest)) = self.rest.split_at_checked(len) else {
            return false;
        };
        self.rest = rest;
        let mut entries = Prefixed { rest: map };
        while !entries.rest.is_empty() {
            if !(entries.string() && entries.string()) {
                return false;
            }
        }
        true
    }

    fn bytes_u64(&mut self) -> bool {
        self.prefix::<8>()
            .and_then(|n| usize::try_from(n).ok())
            .is_some_and(|n| self.skip(n))
    }
}

/// Decompresses and CRC-checks one chunk record body; the chunk's records on success, why not
/// otherwise. Sizes are checked before anything is allocated.
fn chunk_records(body: &[u8]) -> Result<Vec<u8>, String> {
    let record = parse_record_checked(mcap::records::op::CHUNK, body)
        .unwrap_or(Err(mcap::McapError::UnexpectedEof))
        .map_err(|e| format!("chunk header: {e}"))?;
    let mcap::records::Record::Chunk { header, data } = record else {
        return Err("not a chunk".into());
    };
    let size = usize::try_from(header.uncompressed_size)
        .ok()
        .filter(|&s| s <= RECORD_LENGTH_LIMIT)
        .ok_or_else(|| {
            format!(
                "chunk claims {} bytes uncompressed (limit {RECORD_LENGTH_LIMIT})",
                header.uncompressed_size
            )
        })?;
    let records = match header.compression.as_str() {
        "" => data.into_owned(),
        "zstd" => zstd::bulk::decompress(&data, size).map_err(|e| format!("zstd: {e}"))?,
        "lz4" => {
            let mut out = Vec::with_capacity(size);
            let decoder = lz4::Decoder::new(&data[..]).map_err(|e| format!("lz4: {e}"))?;
            // One byte more than announced, to notice a chunk that is longer.
            decoder
                .take(size as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| format!("lz4: {e}"))?;
            out
        }
        other => return Err(format!("unsupported chunk compression {other:?}")),
    };
    if records.len() != size {
        return Err(format!(
            "chunk holds {} bytes uncompressed, its header says {size}",
            records.len()
        ));
    }
    if header.uncompressed_crc != 0 {
        let crc = crc32fast::hash(&records);
        if crc != header.uncompressed_crc {
            return Err(format!(
                "chunk CRC mismatch (stored {:08x}, computed {crc:08x})",
                header.uncompressed_crc
            ));
        }
    }
    Ok(records)
}

/// A channel as the reader needs it: topic and message encoding.
type ChannelInfo = (String, String);

/// Reads one session file record by record with positioned reads, so that a damaged stretch is
/// skipped instead of ending the file.
struct FileWalker<'a> {
    path: &'a Path,
    file: File,
    len: u64,
    channels: HashMap<u16, ChannelInfo>,
}

impl FileWalker<'_> {
    fn read_at(&self, pos: u64, len: usize) -> Result<Vec<u8>, RecorderError> {
        let mut buf = vec![0; len];
        self.file
            .read_exact_at(&mut buf, pos)
            .map_err(RecorderError::io(self.path))?;
        Ok(buf)
    }

    /// Opcode and body length of the record at `pos`, if its whole record lies in the file.
    fn record_at(&self, pos: u64) -> Result<Option<(u8, u64)>, RecorderError> {
        if self.len.saturating_sub(pos) < RECORD_HEAD {
            return Ok(None);
        }
        let head = self.read_at(pos, RECORD_HEAD as usize)?;
        let body_len = u64::from_le_bytes(head[1..9].try_into().expect("8 bytes"));
        let fits = body_len <= self.len - pos - RECORD_HEAD;
        Ok(fits.then_some((head[0], body_len)))
    }

    /// Whether a record can start at `pos`: the end of the file or a known record that fits.
    fn plausible_boundary(&self, pos: u64) -> Result<bool, RecorderError> {
        if pos == self.len {
            return Ok(true);
        }
        Ok(self.record_at(pos)?.is_some_and(|(op, _)| known_opcode(op)))
    }

    /// The body of a chunk at `pos` if its header is consistent and it decompresses with a
    /// matching CRC: the cheap checks first, so that scanning for chunks stays fast.
    fn valid_chunk_at(&self, pos: u64) -> Result<Option<(u64, Vec<u8>)>, RecorderError> {
        let Some((op, body_len)) = self.record_at(pos)? else {
            return Ok(None);
        };
        if op != mcap::records::op::CHUNK
            || body_len < CHUNK_HEADER_MIN
            || body_len > RECORD_LENGTH_LIMIT as u64
        {
            return Ok(None);
        }
        let fixed = self.read_at(pos + RECORD_HEAD, CHUNK_HEADER_MIN as usize - 8)?;
        let uncompressed = u64::from_le_bytes(fixed[16..24].try_into().expect("8 bytes"));
        let name_len = u64::from(u32::from_le_bytes(fixed[28..32].try_into().expect("4")));
        if uncompressed > RECORD_LENGTH_LIMIT as u64 || name_len > 4 {
            return Ok(None);
        }
        let body = self.read_at(pos + RECORD_HEAD, body_len as usize)?;
        Ok(chunk_records(&body).ok().map(|records| (body_len, records)))
    }

    /// The offset of the next valid chunk at or after `from`, or of the data-end record of a
    /// file that was closed properly; `None` if there is neither.
    fn resync(&self, from: u64) -> Result<Option<u64>, RecorderError> {
        let mut window_start = from;
        while window_start < self.len {
            let n = usize::try_from((self.len - window_start).min(RESYNC_WINDOW as u64))
                .expect("window fits");
            let window = self.read_at(window_start, n)?;
            for (i, &byte) in window.iter().enumerate() {
                let pos = window_start + i as u64;
                let found = match byte {
                    mcap::records::op::CHUNK => self.valid_chunk_at(pos)?.is_some(),
                    mcap::records::op::DATA_END => {
                        self.record_at(pos)? == Some((mcap::records::op::DATA_END, 4))
                            && self.ends_with_magic()?
                    }
                    _ => false,
                };
                if found {
                    return Ok(Some(pos));
                }
            }
            window_start += n as u64;
        }
        Ok(None)
    }

    fn ends_with_magic(&self) -> Result<bool, RecorderError> {
        let magic_len = mcap::MAGIC.len() as u64;
        if self.len < 2 * magic_len {
            return Ok(false);
        }
        Ok(self.read_at(self.len - magic_len, mcap::MAGIC.len())? == mcap::MAGIC)
    }

    /// Messages the message-index records right after a chunk ending at `pos` list.
    fn indexed_messages_at(&self, mut pos: u64) -> Result<Option<u64>, RecorderError> {
        let mut count = None;
        while let Some((op, body_len)) = self.record_at(pos)? {
            if op != mcap::records::op::MESSAGE_INDEX || body_len > RECORD_LENGTH_LIMIT as u64 {
                break;
            }
            let body = self.read_at(pos + RECORD_HEAD, body_len as usize)?;
            match parse_record_checked(op, &body) {
                Some(Ok(mcap::records::Record::MessageIndex(index))) => {
                    *count.get_or_insert(0) += index.records.len() as u64;
                }
                _ => break,
            }
            pos += RECORD_HEAD + body_len;
        }
        Ok(count)
    }

    /// Hands the messages of a chunk's (or the data section's) records to `visit`.
    fn visit_records(
        &mut self,
        records: &[u8],
        scan: &mut FileScan,
        visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
    ) -> Result<(), RecorderError> {
        let mut rest = records;
        while !rest.is_empty() {
            let Some((head, after)) = rest.split_first_chunk::<9>() else {
                scan.skipped += 1;
                break;
            };
            let body_len = u64::from_le_bytes(head[1..9].try_into().expect("8 bytes"));
            let Some(body_len) = usize::try_from(body_len).ok().filter(|&l| l <= after.len())
            else {
                tracing::warn!(path = %self.path.display(), "a record overruns its chunk; rest of the chunk skipped");
                scan.skipped += 1;
                break;
            };
            let (body, next) = after.split_at(body_len);
            rest = next;
            match parse_record_checked(head[0], body) {
                None => {}
                Some(Ok(mcap::records::Record::Channel(channel))) => {
                    self.channels
                        .insert(channel.id, (channel.topic, channel.message_encoding));
                }
                Some(Ok(mcap::records::Record::Message { header, data })) => {
                    let channel = self.channels.get(&header.channel_id);
                    if let Some(item) = message_item(self.path, channel, header.log_time, &data) {
                        visit(item)?;
                    } else {
                        scan.skipped += 1;
                    }
                }
                Some(Ok(_)) => {}
                Some(Err(e)) => {
                    tracing::warn!(path = %self.path.display(), error = %e, "unparsable record skipped");
                    scan.skipped += 1;
                }
            }
        }
        Ok(())
    }
}

/// What a message is: a frame, an undecodable frame, or `None` (not ours, or not decodable).
/// Without its channel (declared in a damaged chunk), the data tells: undecodable frames start
/// with their own magic, frames with the S3DP header.
fn message_item(
    path: &Path,
    channel: Option<&ChannelInfo>,
    log_time_ns: u64,
    data: &[u8],
) -> Option<Item> {
    let encoding = channel.map(|(_, encoding)| encoding.as_str());
    let undecodable = match encoding {
        Some(encoding) => encoding == UNDECODABLE_ENCODING,
        None => data.starts_with(&UNDECODABLE_MAGIC),
    };
    if undecodable {
        return parse_undecodable(log_time_ns, data).map(Item::Undecodable);
    }
    if encoding.is_some_and(|e| e != MESSAGE_ENCODING) {
        return None;
    }
    match decode(data) {
        Ok((frame, used)) if used == data.len() => Some(Item::Frame(RecordedFrame {
            topic: channel.map_or_else(|| topic(&frame.body), |(topic, _)| topic.clone()),
            log_time_ns,
            raw: data.to_vec(),
            frame,
        })),
        Ok(_) => {
            tracing::warn!(path = %path.display(), "message with bytes after its frame skipped");
            None
        }
        Err(DecodeError::UnsupportedVersion { got, .. }) => Some(Item::OtherVersion(got)),
        Err(e) => {
            tracing::warn!(path = %path.display(), error = %e, "undecodable message skipped");
            None
        }
    }
}

/// Reads every message of one file that lies in a CRC-checked chunk. A damaged chunk or record
/// is skipped and reported ([`FileScan::losses`]): reading resumes after it (at its declared
/// end when a record starts there, otherwise at the next chunk that validates). A record that
/// runs past the end of the file with nothing valid after it is the torn tail a crash leaves:
/// the file is incomplete, nothing is lost.
fn scan_file(
    path: &Path,
    visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
) -> Result<FileScan, RecorderError> {
    use mcap::records::op;
    let file = File::open(path).map_err(RecorderError::io(path))?;
    let len = file.metadata().map_err(RecorderError::io(path))?.len();
    let mut walker = FileWalker {
        path,
        file,
        len,
        channels: HashMap::new(),
    };
    let mut scan = FileScan {
        len,
        ..FileScan::default()
    };
    let magic_len = mcap::MAGIC.len() as u64;
    if len < magic_len {
        // Empty or cut inside the magic: a file a crash left right after creating it.
        return Ok(scan);
    }
    let mut pos = magic_len;
    if walker.read_at(0, mcap::MAGIC.len())? != mcap::MAGIC {
        pos = 0;
    }
    // The start and reason of a damaged stretch being skipped.
    let mut damage: Option<(u64, String)> = (pos == 0).then(|| (0, "bad magic".to_string()));
    loop {
        if let Some((start, reason)) = damage.take() {
            // Whether the stretch starts with what claims to be a chunk.
            let chunks = u64::from(walker.read_at(start, 1)?[0] == op::CHUNK);
            match walker.resync(start + 1)? {
                Some(resume) => {
                    scan.losses.push(Loss {
                        file: path.to_path_buf(),
                        start,
                        end: resume,
                        chunks,
                        messages: None,
                        reason,
                    });
                    pos = resume;
                }
                None if walker.record_at(start)?.is_none() && start != 0 => {
                    tracing::info!(path = %path.display(), offset = start, "recording ends early (cut short?); read up to its last complete chunk");
                    return Ok(scan);
                }
                None => {
                    scan.losses.push(Loss {
                        file: path.to_path_buf(),
                        start,
                        end: len,
                        chunks,
                        messages: None,
                        reason,
                    });
                    return Ok(scan);
                }
            }
        }
        if pos == len {
            // The data section ends without data-end record and summary: a crash.
            return Ok(scan);
        }
        let Some((opcode, body_len)) = walker.record_at(pos)? else {
            damage = Some((pos, "record runs past the end of the file".into()));
            continue;
        };
        if !known_opcode(opcode) {
            damage = Some((pos, format!("unknown record opcode {opcode:#04x}")));
            continue;
        }
        let next = pos + RECORD_HEAD + body_len;
        match opcode {
            op::CHUNK => {
                let checked = if body_len > RECORD_LENGTH_LIMIT as u64 {
                    Err(format!(
                        "chunk of {body_len} bytes (limit {RECORD_LENGTH_LIMIT})"
                    ))
                } else {
                    chunk_records(&walker.read_at(pos + RECORD_HEAD, body_len as usize)?)
                };
                match checked {
                    Ok(records) => walker.visit_records(&records, &mut scan, visit)?,
                    Err(reason) if walker.plausible_boundary(next)? => {
                        // The chunk's extent is intact, only its content is not: skip exactly it.
                        let messages = walker.indexed_messages_at(next)?;
                        tracing::warn!(path = %path.display(), offset = pos, %reason, "damaged chunk skipped");
                        scan.losses.push(Loss {
                            file: path.to_path_buf(),
                            start: pos,
                            end: next,
                            chunks: 1,
                            messages,
                            reason,
                        });
                    }
                    Err(reason) => {
                        damage = Some((pos, reason));
                        continue;
                    }
                }
            }
            op::MESSAGE | op::CHANNEL => {
                if body_len > RECORD_LENGTH_LIMIT as u64 {
                    damage = Some((pos, format!("record of {body_len} bytes")));
                    continue;
                }
                let record = walker.read_at(pos, (RECORD_HEAD + body_len) as usize)?;
                walker.visit_records(&record, &mut scan, visit)?;
            }
            op::DATA_END | op::FOOTER => {
                scan.complete = walker.ends_with_magic()?;
                return Ok(scan);
            }
            _ => {}
        }
        pos = next;
    }
}

/// Results of [`visit_files`].
struct DirScan {
    report: SessionReport,
    /// `(index, length read)` of each file.
    lengths: Vec<(u64, u64)>,
}

/// One record read back from a session file.
#[derive(Debug)]
enum Item {
    Frame(RecordedFrame),
    Undecodable(UndecodableFrame),
    /// A frame whose header names another protocol version (an old recording).
    OtherVersion(u16),
}

/// Visits every item of the given files, each frame `(session, direction, seq)` and each
/// undecodable seq once.
fn visit_files(
    files: &[(u64, PathBuf)],
    visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
) -> Result<DirScan, RecorderError> {
    let mut seen: HashMap<(u64, bool), SeqSet> = HashMap::new();
    let mut edge_seqs = SeqSet::default();
    let mut undecodable_seen = SeqSet::default();
    let mut out = DirScan {
        report: SessionReport {
            files: files.len(),
            ..SessionReport::default()
        },
        lengths: Vec::with_capacity(files.len()),
    };
    for (index, path) in files {
        let scan = scan_file(path, &mut |item| {
            let first = match &item {
                Item::Frame(recorded) => seen
                    .entry(dedup_key(&recorded.frame))
                    .or_default()
                    .insert(recorded.frame.seq),
                Item::Undecodable(undecodable) => undecodable_seen.insert(undecodable.seq),
                Item::OtherVersion(_) => true,
            };
            match &item {
                Item::Frame(recorded) if !server_originated(&recorded.frame.body) => {
                    edge_seqs.insert(recorded.frame.seq);
                }
                Item::Frame(_) | Item::OtherVersion(_) => {}
                Item::Undecodable(undecodable) => {
                    edge_seqs.insert(undecodable.seq);
                }
            }
            if first { visit(item) } else { Ok(()) }
        })?;
        let report = &mut out.report;
        report.bytes += scan.len;
        if !scan.complete {
            report.incomplete_files += 1;
        }
        report.skipped_messages += scan.skipped;
        report.losses.extend(scan.losses);
        out.lengths.push((*index, scan.len));
    }
    out.report.undecodable_frames = undecodable_seen.ranges().iter().map(range_len).sum();
    out.report.missing_seqs = edge_seqs.holes();
    Ok(out)
}

/// Number of members of an inclusive range (saturating at `u64::MAX`).
fn range_len(range: &RangeInclusive<u64>) -> u64 {
    (range.end() - range.start()).saturating_add(1)
}

/// Calls `visit` for every frame of a session directory, file by file in order, each
/// `(session, direction, seq)` once. Files cut short are read up to their last complete chunk;
/// damaged chunks are skipped and reported in the returned [`SessionReport`] (check
/// [`SessionReport::losses`]); undecodable frames are counted, not visited. Streaming: memory
/// does not grow with the recording. A session recorded with another protocol version fails
/// with [`RecorderError::ProtocolVersion`] at its first such frame.
pub fn visit_session(
    session_dir: &Path,
    mut visit: impl FnMut(RecordedFrame) -> Result<(), RecorderError>,
) -> Result<SessionReport, RecorderError> {
    visit_session_items(session_dir, |item| match item {
        SessionItem::Frame(recorded) => visit(recorded),
        SessionItem::Undecodable(_) => Ok(()),
    })
}

/// All frames of a session directory in recording order, duplicates removed, with the report
/// of what could not be read (see [`visit_session`]).
pub fn read_session_report(
    session_dir: &Path,
) -> Result<(Vec<RecordedFrame>, SessionReport), RecorderError> {
    let mut frames = Vec::new();
    let report = visit_session(session_dir, |frame| {
        frames.push(frame);
        Ok(())
    })?;
    Ok((frames, report))
}

/// All frames of a session directory in recording order, duplicates removed; fails with
/// [`RecorderError::Damaged`] if any part of the recording could not be read (use
/// [`read_session_report`] to take what is readable).
pub fn read_session(session_dir: &Path) -> Result<Vec<RecordedFrame>, RecorderError> {
    read_session_checked(session_dir, false)
}

/// [`read_session`], or with `lenient` the readable frames of a damaged recording, with a
/// warning saying what was lost (what the offline commands' `--lenient` does).
pub fn read_session_checked(
    session_dir: &Path,
    lenient: bool,
) -> Result<Vec<RecordedFrame>, RecorderError> {
    let (frames, report) = read_session_report(session_dir)?;
    check_losses(&report, session_dir, lenient)?;
    Ok(frames)
}

/// What the offline commands do with a damaged recording: without `lenient`, fail with
/// [`RecorderError::Damaged`] naming what was lost; with it, warn and go on with the rest.
pub fn check_losses(
    report: &SessionReport,
    session_dir: &Path,
    lenient: bool,
) -> Result<(), RecorderError> {
    match report.loss_line() {
        None => Ok(()),
        Some(line) if lenient => {
            tracing::warn!(dir = %session_dir.display(), "recording damaged, going on with the rest: {line}");
            Ok(())
        }
        Some(line) => Err(RecorderError::Damaged {
            dir: session_dir.to_path_buf(),
            losses: line,
        }),
    }
}

/// Whether a recording file is being written now: a live server holds an exclusive lock on
/// every file it writes, released when it closes the file or dies.
pub fn is_being_written(path: &Path) -> bool {
    fs::File::open(path)
        .is_ok_and(|file| matches!(file.try_lock_shared(), Err(fs::TryLockError::WouldBlock)))
}

/// Summarises one session directory (see [`SessionSummary`]); damage is reported in it, not
/// as an error.
pub fn summarize_session(
    edge: &str,
    session_id: u64,
    session_dir: &Path,
) -> Result<SessionSummary, RecorderError> {
    let mut frames = 0;
    let mut frames_per_topic: BTreeMap<String, u64> = BTreeMap::new();
    let mut first_log_time_ns: Option<u64> = None;
    let mut last_log_time_ns: Option<u64> = None;
    let mut first_sample_ns: Option<u64> = None;
    let mut last_sample_ns: Option<u64> = None;
    let report = visit_session(session_dir, |recorded| {
        frames += 1;
        let t = recorded.log_time_ns;
        first_log_time_ns = Some(first_log_time_ns.map_or(t, |f| f.min(t)));
        last_log_time_ns = Some(last_log_time_ns.map_or(t, |l| l.max(t)));
        // The data's own times (edge clock): a revolution spans t0..t1, a reading its t.
        let span = match &recorded.frame.body {
            Body::Revolution(rev) => Some((rev.t0_ns, rev.t1_ns)),
            Body::Imu(imu) => Some((imu.t_ns, imu.t_ns)),
            _ => None,
        };
        if let Some((from, to)) = span {
            first_sample_ns = Some(first_sample_ns.map_or(from, |f| f.min(from)));
            last_sample_ns = Some(last_sample_ns.map_or(to, |l| l.max(to)));
        }
        *frames_per_topic.entry(recorded.topic).or_default() += 1;
        Ok(())
    })?;
    let files_being_written = session_files(session_dir)?
        .iter()
        .filter(|(_, path)| is_being_written(path))
        .count();
    Ok(SessionSummary {
        edge: edge.to_string(),
        session_id,
        dir: session_dir.to_path_buf(),
        files: report.files,
        incomplete_files: report.incomplete_files,
        frames,
        frames_per_topic,
        skipped_messages: report.skipped_messages,
        undecodable_frames: report.undecodable_frames,
        first_log_time_ns,
        last_log_time_ns,
        first_sample_ns,
        last_sample_ns,
        files_being_written,
        bytes: report.bytes,
        losses: report.losses,
        missing_seqs: report.missing_seqs,
    })
}

/// Every session under `data_dir/sessions`, sorted by edge then session id. Directories whose
/// names do not fit the layout are skipped with a warning; a missing `sessions` directory means
/// no sessions.
pub fn list_sessions(data_dir: &Path) -> Result<Vec<SessionSummary>, RecorderError> {
    let sessions = data_dir.join("sessions");
    let edges = match fs::read_dir(&sessions) {
        Ok(entries) => entries,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(RecorderError::io(&sessions)(e)),
    };
    let mut found = Vec::new();
    for edge in edges {
        let edge = edge.map_err(RecorderError::io(&sessions))?;
        let edge_dir = edge.path();
        if !edge_dir.is_dir() {
            continue;
        }
        let Some(edge_name) = edge.file_name().to_str().map(str::to_string) else {
            tracing::warn!(dir = %edge_dir.display(), "skipping a directory with a non-UTF-8 name");
            continue;
        };
        for session in fs::read_dir(&edge_dir).map_err(RecorderError::io(&edge_dir))? {
            let session = session.map_err(RecorderError::io(&edge_dir))?;
            let dir = session.path();
            if !dir.is_dir() {
                continue;
            }
            let id = session
                .file_name()
                .to_str()
                .filter(|n| n.len() == 16)
                .and_then(|n| u64::from_str_radix(n, 16).ok());
            match id {
                Some(id) => found.push((edge_name.clone(), id, dir)),
                None => {
                    tracing::warn!(dir = %dir.display(), "skipping a directory that is not a session id");
                }
            }
        }
    }
    found.sort();
    found
        .into_iter()
        .map(|(edge, id, dir)| summarize_session(&edge, id, &dir))
        .collect()
}

/// One item of a session for [`visit_session_items`]: a frame, or an edge frame the server
/// recorded without being able to decode it (its seq was received, so it is no gap).
#[derive(Debug)]
pub enum SessionItem {
    /// A decoded frame.
    Frame(RecordedFrame),
    /// A frame recorded on [`UNDECODABLE_TOPIC`].
    Undecodable(UndecodableFrame),
}

/// [`visit_session`], visiting the undecodable frames too (in recording order, each seq once),
/// for readers that tell a gap in the sequence numbers from a frame they cannot read.
pub fn visit_session_items(
    session_dir: &Path,
    mut visit: impl FnMut(SessionItem) -> Result<(), RecorderError>,
) -> Result<SessionReport, RecorderError> {
    let files = session_files(session_dir)?;
    let scan = visit_files(&files, &mut |item| match item {
        Item::Frame(recorded) => visit(SessionItem::Frame(recorded)),
        Item::Undecodable(undecodable) => visit(SessionItem::Undecodable(undecodable)),
        Item::OtherVersion(version) => Err(RecorderError::ProtocolVersion {
            dir: session_dir.to_path_buf(),
            version,
            supported: PROTOCOL_VERSION,
        }),
    })?;
    Ok(scan.report)
}

/// Whether `edge` is safe as one directory name.
fn valid_edge_name(edge: &str) -> bool {
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
fn sync_dir(dir: &Path) -> Result<(), RecorderError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(RecorderError::io(dir))
}

/// Name of the session index in a session directory (format in the module documentation).
const INDEX_FILE: &str = "recorded.idx";

/// First line of the session index: its format and version.
const INDEX_HEADER: &str = "scan3d-recorded-index 1";

/// Largest session index the recorder reads (it lists ranges, not frames: kilobytes).
const INDEX_LIMIT: u64 = 16 * 1024 * 1024;

/// What the session index says: the files it covers, with the length each had when it was
/// read or closed, and every edge and command seq those files hold.
#[derive(Debug, Default, PartialEq, Eq)]
struct SessionIndex {
    files: BTreeMap<u64, u64>,
    edge: SeqSet,
    commands: SeqSet,
}

fn encode_index(index: &SessionIndex) -> String {
    use std::fmt::Write as _;
    let mut text = format!("{INDEX_HEADER}\n");
    for (file, len) in &index.files {
        let _ = writeln!(text, "file {file} {len}");
    }
    for (name, set) in [("edge", &index.edge), ("commands", &index.commands)] {
        text.push_str(name);
        for range in set.ranges() {
            let _ = write!(text, " {}-{}", range.start(), range.end());
        }
        text.push('\n');
    }
    let crc = crc32fast::hash(text.as_bytes());
    let _ = writeln!(text, "crc {crc:08x}");
    text
}

fn parse_index(text: &str) -> Result<SessionIndex, String> {
    let crc_at = text.rfind("crc ").ok_or("no crc line")?;
    let (body, crc_line) = text.split_at(crc_at);
    let stored = crc_line
        .strip_prefix("crc ")
        .and_then(|c| c.strip_suffix('\n'))
        .and_then(|c| u32::from_str_radix(c, 16).ok())
        .ok_or("unreadable crc line")?;
    if crc32fast::hash(body.as_bytes()) != stored {
        return Err("crc mismatch".into());
    }
    let mut lines = body.lines();
    if lines.next() != Some(INDEX_HEADER) {
        return Err("unknown format".into());
    }
    let mut index = SessionIndex::default();
    let (mut edge, mut commands) = (false, false);
    for line in lines {
        let mut words = line.split(' ');
        match words.next() {
            Some("file") => {
                let mut number = || words.next().and_then(|w| w.parse::<u64>().ok());
                let (Some(file), Some(len)) = (number(), number()) else {
                    return Err(format!("bad line {line:?}"));
                };
                if index.files.insert(file, len).is_some() {
                    return Err(format!("file {file} listed twice"));
                }
            }
            Some(name @ ("edge" | "commands")) => {
                let (set, done) = if name == "edge" {
                    (&mut index.edge, &mut edge)
                } else {
                    (&mut index.commands, &mut commands)
                };
                if std::mem::replace(done, true) {
                    return Err(format!("{name} listed twice"));
                }
                for word in words {
                    let range = word
                        .split_once('-')
                        .and_then(|(a, b)| Some(a.parse::<u64>().ok()?..=b.parse::<u64>().ok()?))
                        .ok_or_else(|| format!("bad range {word:?}"))?;
                    if !set.push_range(range) {
                        return Err(format!("range {word} out of order"));
                    }
                }
            }
            _ => return Err(format!("bad line {line:?}")),
        }
    }
    if !(edge && commands) {
        return Err("seq lines missing".into());
    }
    Ok(index)
}

/// The session index of `dir`, if there is a valid one (an invalid one is logged and ignored:
/// the files are then read instead).
fn read_index(dir: &Path) -> Option<SessionIndex> {
    let path = dir.join(INDEX_FILE);
    let file = match File::open(&path) {
        Ok(file) => file,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return None,
        Err(e) => {
            tracing::warn!(path = %path.display(), error = %e, "session index unreadable; reading the files instead");
            return None;
        }
    };
    let mut text = String::new();
    let read = file.take(INDEX_LIMIT + 1).read_to_string(&mut text);
    let parsed = match read {
        Ok(n) if n as u64 > INDEX_LIMIT => Err(format!("larger than {INDEX_LIMIT} bytes")),
        Ok(_) => parse_index(&text),
        Err(e) => Err(e.to_string()),
    };
    match parsed {
        Ok(index) => Some(index),
        Err(reason) => {
            tracing::warn!(path = %path.display(), %reason, "session index invalid; reading the files instead");
            None
        }
    }
}

/// Replaces the session index of `dir` atomically: a temporary file (named after `tag`, the
/// writer's own file number, so two recorders of one session never share it), fsynced, renamed
/// over the index, and the directory fsynced.
fn write_index(dir: &Path, index: &SessionIndex, tag: u64) -> Result<(), RecorderError> {
    let tmp = dir.join(format!("{INDEX_FILE}.{tag:04}.tmp"));
    let path = dir.join(INDEX_FILE);
    let written = (|| {
        let mut file = File::create(&tmp)?;
        file.write_all(encode_index(index).as_bytes())?;
        file.sync_all()?;
        fs::rename(&tmp, &path)
    })();
    if let Err(e) = written {
        let _ = fs::remove_file(&tmp);
        return Err(RecorderError::Io { path, source: e });
    }
    sync_dir(dir)
}

/// Finishes a recording file: summary, footer and end magic, flushed and fsynced. Returns its
/// length.
fn finish_file(
    mut writer: Writer<BufWriter<SharedFile>>,
    sync: &File,
    path: &Path,
) -> Result<u64, RecorderError> {
    writer.finish().map_err(|source| RecorderError::Mcap {
        path: path.to_path_buf(),
        source,
    })?;
    let mut inner = writer.into_inner();
    inner.flush().map_err(RecorderError::io(path))?;
    drop(inner);
    sync.sync_data().map_err(RecorderError::io(path))?;
    Ok(sync.metadata().map_err(RecorderError::io(path))?.len())
}

/// The recording file, shared by the MCAP writer and the recorder's fsync: one descriptor.
#[derive(Debug, Clone)]
struct SharedFile(Arc<File>);

impl Write for SharedFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        (&*self.0).write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        (&*self.0).flush()
    }
}

impl Seek for SharedFile {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        (&*self.0).seek(pos)
    }
}

/// Capacity of the buffer between the MCAP writer and the file: small, because an idle
/// recorder keeps it, and chunks are written through when they are larger anyway.
const WRITE_BUFFER: usize = 8 * 1024;

/// Records one edge session into a new MCAP file of its directory, acknowledging only what is
/// synced to disk.
///
/// Not thread-safe by design: one recorder per edge connection task. After any error from
/// [`append`](Self::append) or [`commit`](Self::commit) the recorder refuses further work
/// ([`RecorderError::Failed`]); open the session again to continue in a new file.
/// Dropping it without [`close`](Self::close) lets the MCAP writer finish the file best-effort
/// (no fsync, no index update); a crash leaves the file without summary, which the readers
/// tolerate. An open recorder costs one file descriptor and about 15 KB while idle (an 8 KiB
/// write buffer, the channel table, the seq ranges), plus one chunk index per commit until
/// [`CHUNKS_PER_FILE`] makes it continue in a new file; while a chunk is open, its LZ4 encoder
/// adds about 200 KB.
pub struct SessionRecorder {
    edge: String,
    session_id: u64,
    dir: PathBuf,
    path: PathBuf,
    /// This file's number in the session directory.
    file_index: u64,
    writer: Writer<BufWriter<SharedFile>>,
    /// The file, to fsync what the writer flushed.
    sync: Arc<File>,
    /// Chunks committed to this file (see [`CHUNKS_PER_FILE`]).
    chunks: u64,
    channels: HashMap<String, u16>,
    /// Edge seqs recorded (durable or buffered): the duplicate check.
    seen: SeqSet,
    /// Edge seqs synced to disk: what may be acknowledged.
    durable: SeqSet,
    /// Server command seqs recorded.
    commands: SeqSet,
    /// Earlier files whose frames `seen` and `commands` include, with their lengths: the
    /// session index [`close`](Self::close) writes.
    covered: BTreeMap<u64, u64>,
    /// Edge seqs written since the last commit.
    pending: Vec<u64>,
    /// Whether anything (edge frame or command) was written since the last commit.
    dirty: bool,
    failed: bool,
}

impl std::fmt::Debug for SessionRecorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionRecorder")
            .field("path", &self.path)
            .field("durable_prefix", &self.durable.prefix())
            .field("pending", &self.pending.len())
            .field("failed", &self.failed)
            .finish_non_exhaustive()
    }
}

/// A recording file just created and started.
struct NewFile {
    index: u64,
    path: PathBuf,
    file: Arc<File>,
    writer: Writer<BufWriter<SharedFile>>,
}

/// What [`SessionRecorder::open`] learns from the files already there.
struct Recovered {
    edge: SeqSet,
    commands: SeqSet,
    covered: BTreeMap<u64, u64>,
}

/// Learns which seqs the files of `dir` hold: from the session index for the files it covers
/// (each must still be at least as long as the index says, or the index is ignored), by
/// reading the others (files a crashed or concurrent run left). Files read are fsynced (an
/// earlier run may not have), then the index is rewritten to cover them, so each file is read
/// at most once.
fn recover(dir: &Path, session_id: u64) -> Result<Recovered, RecorderError> {
    let files = session_files(dir)?;
    let mut lengths = BTreeMap::new();
    for (index, path) in &files {
        let len = fs::metadata(path).map_err(RecorderError::io(path))?.len();
        lengths.insert(*index, len);
    }
    let mut index = read_index(dir).unwrap_or_default();
    if let Some((file, len)) = index
        .files
        .iter()
        .find(|(file, len)| lengths.get(file).is_none_or(|now| now < len))
    {
        tracing::warn!(dir = %dir.display(), file, len, "session index lists a file that is missing or shorter; reading all files");
        index = SessionIndex::default();
    }
    let unread: Vec<(u64, PathBuf)> = files
        .iter()
        .filter(|(file, _)| index.files.get(file) != lengths.get(file))
        .cloned()
        .collect();
    if !unread.is_empty() {
        let (edge, commands) = (&mut index.edge, &mut index.commands);
        let scan = visit_files(&unread, &mut |item| {
            match item {
                Item::Frame(recorded) if recorded.frame.session_id == session_id => {
                    if server_originated(&recorded.frame.body) {
                        commands.insert(recorded.frame.seq);
                    } else {
                        edge.insert(recorded.frame.seq);
                    }
                }
                // Another version's frames are not this session's (its id is random per boot).
                Item::Frame(_) | Item::OtherVersion(_) => {}
                Item::Undecodable(undecodable) => {
                    edge.insert(undecodable.seq);
                }
            }
            Ok(())
        })?;
        if let Some(line) = scan.report.loss_line() {
            tracing::warn!(dir = %dir.display(), "earlier recording damaged, its frames count as not recorded: {line}");
        }
        // What an earlier run wrote but did not sync may still sit in the page cache: sync it
        // before counting it as durable.
        for (_, path) in &unread {
            File::open(path)
                .and_then(|f| f.sync_all())
                .map_err(RecorderError::io(path))?;
        }
        index.files.extend(scan.lengths);
        let tag = files.last().map_or(0, |(last, _)| *last);
        if let Err(e) = write_index(dir, &index, tag) {
            // Only a cost: the next open reads these files again.
            tracing::warn!(error = %e, "cannot update the session index");
        }
    }
    Ok(Recovered {
        edge: index.edge,
        commands: index.commands,
        covered: index.files,
    })
}

impl SessionRecorder {
    /// Opens the recording of `edge`'s session `session_id` under `data_dir`: creates the
    /// directory, learns which frames are already durable (from the session index, reading
    /// only the files it does not cover; see [`recover`]) and starts the next-numbered file.
    /// Its cost does not grow with the number or size of the files a clean [`close`](Self::close)
    /// indexed. On failure nothing is left behind (no empty file); storage failures (a full
    /// disk) are [`RecorderError::is_storage`].
    pub fn open(data_dir: &Path, edge: &str, session_id: u64) -> Result<Self, RecorderError> {
        if !valid_edge_name(edge) {
            return Err(RecorderError::InvalidEdgeName(edge.to_string()));
        }
        let sessions = data_dir.join("sessions");
        let edge_dir = sessions.join(edge);
        let dir = session_dir(data_dir, edge, session_id);
        fs::create_dir_all(&dir).map_err(RecorderError::io(&dir))?;
        // Make the directory entries themselves durable (cheap when nothing changed).
        for d in [data_dir, &sessions, &edge_dir] {
            sync_dir(d)?;
        }

        let recovered = recover(&dir, session_id)?;
        let NewFile {
            index: file_index,
            path,
            file,
            writer,
        } = Self::create_file(&dir, edge, session_id)?;
        tracing::info!(
            path = %path.display(),
            durable_prefix = ?recovered.edge.prefix(),
            "recording session"
        );
        Ok(SessionRecorder {
            edge: edge.to_string(),
            session_id,
            dir,
            path,
            file_index,
            writer,
            sync: file,
            chunks: 0,
            channels: HashMap::new(),
            durable: recovered.edge.clone(),
            seen: recovered.edge,
            commands: recovered.commands,
            covered: recovered.covered,
            pending: Vec::new(),
            dirty: false,
            failed: false,
        })
    }

    /// Creates the next-numbered file of `dir` and starts it ([`start_file`](Self::start_file));
    /// on failure removes it again, so that a full disk does not leave an empty file per attempt.
    fn create_file(dir: &Path, edge: &str, session_id: u64) -> Result<NewFile, RecorderError> {
        let file_index = session_files(dir)?
            .last()
            .map_or(0, |(last, _)| last.saturating_add(1));
        let path = dir.join(format!("{file_index:04}.mcap"));
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(RecorderError::io(&path))?;
        // Held while the file is written, so `scan3d sessions` can tell a recording being
        // written from one a crash cut short (see [`is_being_written`]).
        if let Err(e) = file.try_lock() {
            tracing::warn!(path = %path.display(), error = %e, "cannot lock the new recording file");
        }
        let file = Arc::new(file);
        let started = Self::start_file(&path, file.clone(), edge, session_id, file_index)
            .and_then(|writer| sync_dir(dir).map(|()| writer));
        match started {
            Ok(writer) => Ok(NewFile {
                index: file_index,
                path,
                file,
                writer,
            }),
            Err(e) => {
                drop(file);
                if let Err(remove) = fs::remove_file(&path) {
                    tracing::warn!(path = %path.display(), error = %remove, "cannot remove the file that could not be started");
                }
                let _ = sync_dir(dir);
                Err(e)
            }
        }
    }

    /// Writes the MCAP header and the session metadata into a new file and pushes them to the
    /// kernel, so that a full disk shows here rather than at the first commit.
    fn start_file(
        path: &Path,
        file: Arc<File>,
        edge: &str,
        session_id: u64,
        file_index: u64,
    ) -> Result<Writer<BufWriter<SharedFile>>, RecorderError> {
        let mcap_err = |source| RecorderError::Mcap {
            path: path.to_path_buf(),
            source,
        };
        // LZ4, not zstd: the writer keeps a zstd context (3.7 MB measured) for the life of the
        // file, an LZ4 encoder only while a chunk is open, and every commit closes the chunk.
        // LZ4 is also cheaper in CPU; its files are larger (about 2x on pseudo-random
        // revolutions).
        let options = WriteOptions::new()
            .compression(Some(Compression::Lz4))
            .chunk_size(Some(CHUNK_SIZE))
            .profile(PROFILE)
            .library(format!("scan3d-server {}", env!("CARGO_PKG_VERSION")));
        let mut writer = options
            .create(BufWriter::with_capacity(WRITE_BUFFER, SharedFile(file)))
            .map_err(mcap_err)?;
        let metadata = Metadata {
            name: SESSION_METADATA.to_string(),
            metadata: BTreeMap::from([
                ("edge".to_string(), edge.to_string()),
                ("session_id".to_string(), format!("{session_id:016x}")),
                ("file_index".to_string(), file_index.to_string()),
                (
                    "recorder".to_string(),
                    format!("scan3d-server {}", env!("CARGO_PKG_VERSION")),
                ),
            ]),
        };
        writer.write_metadata(&metadata).map_err(mcap_err)?;
        writer.flush().map_err(mcap_err)?;
        Ok(writer)
    }

    /// The edge's name.
    pub fn edge(&self) -> &str {
        &self.edge
    }

    /// The session being recorded.
    pub fn session_id(&self) -> u64 {
        self.session_id
    }

    /// The session directory.
    pub fn session_dir(&self) -> &Path {
        &self.dir
    }

    /// The file this recorder writes.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The highest `S` such that every edge frame `<= S` is durable, as of the last commit.
    pub fn durable_prefix(&self) -> Option<u64> {
        self.durable.prefix()
    }

    /// Every edge seq durable as of the last commit, as sorted, disjoint, non-adjacent inclusive
    /// ranges (the contiguous prefix first, when frame 0 is durable): what to acknowledge with
    /// `Ack::Range`s when there are gaps. Undecodable frames
    /// ([`append_undecodable`](Self::append_undecodable)) count as durable.
    pub fn durable_ranges(&self) -> Vec<RangeInclusive<u64>> {
        self.durable.ranges()
    }

    /// The lowest sequence number above every command (and clock model) recorded in this
    /// session, on any connection: the server numbers its frames to the edge from here after a reconnect, so
    /// a new command is never taken for a resend of an old one.
    pub fn next_command_seq(&self) -> u64 {
        self.commands
            .ranges
            .last_key_value()
            .map_or(0, |(_, &end)| end.saturating_add(1))
    }

    /// Number of edge frames buffered since the last commit.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Records an edge → server frame: `raw` must be the exact bytes received and `frame` their
    /// decoding; `receive_time_ns` is the server's receive time (ns since the UNIX epoch).
    /// Returns [`Appended::Duplicate`] (and writes nothing) if this seq is already recorded.
    pub fn append(
        &mut self,
        raw: &[u8],
        frame: &Frame,
        receive_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        self.check(frame)?;
        if frame.body.direction() == Direction::ServerToEdge {
            return Err(RecorderError::Misdirected {
                seq: frame.seq,
                body: body_name(&frame.body),
            });
        }
        if self.seen.contains(frame.seq) {
            return Ok(Appended::Duplicate);
        }
        self.write(raw, frame, receive_time_ns)?;
        self.seen.insert(frame.seq);
        self.pending.push(frame.seq);
        Ok(Appended::Buffered)
    }

    /// Records an edge → server frame that cannot be decoded (or must not be recorded as what
    /// it claims, e.g. a misdirected body) under the edge sequence number `seq`: `raw` are the
    /// bytes as received, `reason` says why (cut to [`UNDECODABLE_REASON_LIMIT`] bytes),
    /// `log_time_ns` is the server's receive time. It is written on [`UNDECODABLE_TOPIC`] and
    /// `seq` counts as recorded: durable (acknowledgeable) after the next commit, and a later
    /// frame with the same seq is a [`Appended::Duplicate`]. Returns `Duplicate` (and writes
    /// nothing) if `seq` is already recorded.
    pub fn append_undecodable(
        &mut self,
        seq: u64,
        raw: &[u8],
        reason: &str,
        log_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        if self.seen.contains(seq) {
            return Ok(Appended::Duplicate);
        }
        let channel_id = self.channel(UNDECODABLE_TOPIC, UNDECODABLE_ENCODING, BTreeMap::new())?;
        let header = MessageHeader {
            channel_id,
            sequence: seq as u32,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        let data = undecodable_message(seq, reason, raw);
        let written = self.writer.write_to_known_channel(&header, &data);
        self.mcap_result(written)?;
        self.dirty = true;
        self.seen.insert(seq);
        self.pending.push(seq);
        Ok(Appended::Buffered)
    }

    /// Records a [`Body::Command`] the server sent to the edge (server → edge sequence numbers,
    /// deduplicated separately from the edge's); `send_time_ns` is the server's send time.
    pub fn append_command(
        &mut self,
        raw: &[u8],
        frame: &Frame,
        send_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        self.append_server_frame(raw, frame, send_time_ns, |body| {
            matches!(body, Body::Command(_))
        })
    }

    /// Records a [`Body::ClockModel`] the server made, numbered in the same sequence as its
    /// commands ([`SessionRecorder::next_command_seq`]); `log_time_ns` is when it was made.
    pub fn append_clock_model(
        &mut self,
        raw: &[u8],
        frame: &Frame,
        log_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        self.append_server_frame(raw, frame, log_time_ns, |body| {
            matches!(body, Body::ClockModel(_))
        })
    }

    fn append_server_frame(
        &mut self,
        raw: &[u8],
        frame: &Frame,
        send_time_ns: u64,
        expected: fn(&Body) -> bool,
    ) -> Result<Appended, RecorderError> {
        self.check(frame)?;
        if !expected(&frame.body) {
            return Err(RecorderError::Misdirected {
                seq: frame.seq,
                body: body_name(&frame.body),
            });
        }
        if self.commands.contains(frame.seq) {
            return Ok(Appended::Duplicate);
        }
        self.write(raw, frame, send_time_ns)?;
        self.commands.insert(frame.seq);
        Ok(Appended::Buffered)
    }

    fn check(&self, frame: &Frame) -> Result<(), RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        if frame.session_id != self.session_id {
            return Err(RecorderError::WrongSession {
                expected: self.session_id,
                got: frame.session_id,
            });
        }
        Ok(())
    }

    fn write(&mut self, raw: &[u8], frame: &Frame, log_time: u64) -> Result<(), RecorderError> {
        let topic = topic(&frame.body);
        let channel_id = match self.channels.get(&topic) {
            Some(&id) => id,
            None => {
                let mut metadata =
                    BTreeMap::from([("body".to_string(), body_name(&frame.body).to_string())]);
                if let Body::Revolution(rev) = &frame.body {
                    metadata.insert("sensor".to_string(), rev.sensor.to_string());
                }
                self.channel(&topic, MESSAGE_ENCODING, metadata)?
            }
        };
        let header = MessageHeader {
            channel_id,
            // The low 32 bits: MCAP's sequence is a u32 and wraps; the frame keeps the u64.
            sequence: frame.seq as u32,
            log_time,
            publish_time: edge_time_ns(&frame.body).unwrap_or(log_time),
        };
        let written = self.writer.write_to_known_channel(&header, raw);
        self.mcap_result(written)?;
        self.dirty = true;
        Ok(())
    }

    /// The channel id of `topic`, adding the channel on first use.
    fn channel(
        &mut self,
        topic: &str,
        encoding: &str,
        metadata: BTreeMap<String, String>,
    ) -> Result<u16, RecorderError> {
        if let Some(&id) = self.channels.get(topic) {
            return Ok(id);
        }
        let id = self.writer.add_channel(0, topic, encoding, &metadata);
        let id = self.mcap_result(id)?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    /// Marks the recorder failed on an MCAP error.
    fn mcap_result<T>(&mut self, result: Result<T, McapError>) -> Result<T, RecorderError> {
        result.map_err(|source| {
            self.failed = true;
            RecorderError::Mcap {
                path: self.path.clone(),
                source,
            }
        })
    }

    /// Makes everything appended so far durable: finishes the open chunk, flushes and fsyncs the
    /// file. Returns the highest `S` such that every edge frame `<= S` of this session is durable
    /// (what to acknowledge), or `None` if frame 0 is not. Nothing to write costs nothing.
    pub fn commit(&mut self) -> Result<Option<u64>, RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        if !self.dirty {
            return Ok(self.durable.prefix());
        }
        let flushed = self.writer.flush();
        self.mcap_result(flushed)?;
        if let Err(e) = self.sync.sync_data() {
            self.failed = true;
            return Err(RecorderError::io(&self.path)(e));
        }
        for seq in self.pending.drain(..) {
            self.durable.insert(seq);
        }
        self.dirty = false;
        self.chunks += 1;
        if self.chunks >= CHUNKS_PER_FILE {
            // Everything is durable already; a failure here only fails the recorder.
            if let Err(e) = self.rotate() {
                self.failed = true;
                return Err(e);
            }
        }
        Ok(self.durable.prefix())
    }

    /// Finishes the current file (summary, fsync, session index) and continues in the next.
    fn rotate(&mut self) -> Result<(), RecorderError> {
        let NewFile {
            index: file_index,
            path,
            file,
            writer,
        } = Self::create_file(&self.dir, &self.edge, self.session_id)?;
        let old_writer = std::mem::replace(&mut self.writer, writer);
        let old_sync = std::mem::replace(&mut self.sync, file);
        let old_path = std::mem::replace(&mut self.path, path);
        let old_index = std::mem::replace(&mut self.file_index, file_index);
        self.channels.clear();
        self.chunks = 0;
        let len = finish_file(old_writer, &old_sync, &old_path)?;
        self.covered.insert(old_index, len);
        self.update_index();
        tracing::info!(path = %self.path.display(), previous = %old_path.display(), "recording continues in a new file");
        Ok(())
    }

    /// Writes the session index: the finished files and every seq recorded (all durable: called
    /// right after a commit). A failure is logged: it only costs the next open a read.
    fn update_index(&self) {
        let index = SessionIndex {
            files: self.covered.clone(),
            edge: self.durable.clone(),
            commands: self.commands.clone(),
        };
        if let Err(e) = write_index(&self.dir, &index, self.file_index) {
            tracing::warn!(error = %e, "cannot update the session index");
        }
    }

    /// Commits, then writes the summary and footer so the file is a complete MCAP, and fsyncs
    /// it. Returns the final durable prefix (see [`commit`](Self::commit)).
    pub fn close(mut self) -> Result<Option<u64>, RecorderError> {
        let prefix = self.commit()?;
        let path = self.path.clone();
        let len = finish_file(self.writer, &self.sync, &path)?;
        // Everything the index lists is synced: the earlier files when they were indexed or
        // read, this one just now.
        self.covered.insert(self.file_index, len);
        let index = SessionIndex {
            files: std::mem::take(&mut self.covered),
            edge: std::mem::take(&mut self.durable),
            commands: std::mem::take(&mut self.commands),
        };
        if let Err(e) = write_index(&self.dir, &index, self.file_index) {
            // The recording is complete and durable; only the next open gets slower.
            tracing::warn!(error = %e, "cannot update the session index");
        }
        tracing::info!(path = %path.display(), durable_prefix = ?prefix, "recording closed");
        Ok(prefix)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_protocol::{
        Ack, Command, DeviceStatus, Heartbeat, Hello, ImuSample, LidarRevolution, SensorId,
        StatusEvent, StepperState, TimePing, TimePong,
    };

    #[test]
    fn a_session_recorded_with_protocol_version_1_is_refused_with_one_line_naming_it() {
        let tmp = tempfile::tempdir().unwrap();
        let mut rec = SessionRecorder::open(tmp.path(), "pi", 0x5eed).unwrap();
        for seq in 0..3 {
            let frame = Frame::new(0x5eed, seq, Heartbeat { sent_ns: seq });
            let mut raw = scan3d_protocol::encode(&frame).unwrap();
            // What a version-1 edge sent: the same header with version 1.
            raw[4..6].copy_from_slice(&1u16.to_le_bytes());
            rec.append(&raw, &frame, 1_000 + seq).unwrap();
        }
        rec.close().unwrap();
        let dir = session_dir(tmp.path(), "pi", 0x5eed);
        let mut visited = 0;
        let err = visit_session(&dir, |_| {
            visited += 1;
            Ok(())
        })
        .unwrap_err();
        assert_eq!(visited, 0);
        assert!(matches!(
            err,
            RecorderError::ProtocolVersion {
                version: 1,
                supported: 2,
                ..
            }
        ));
        assert_eq!(
            err.to_string(),
            format!(
                "session {} was recorded with protocol version 1; this build reads version 2",
                dir.display()
            )
        );
        // What calls it says the same.
        let err = read_session(&dir).unwrap_err();
        assert!(matches!(
            err,
            RecorderError::ProtocolVersion { version: 1, .. }
        ));
        let err = summarize_session("pi", 0x5eed, &dir).unwrap_err();
        assert!(matches!(
            err,
            RecorderError::ProtocolVersion { version: 1, .. }
        ));
    }

    #[test]
    fn seq_set_tracks_prefix_and_gaps() {
        let mut set = SeqSet::default();
        assert_eq!(set.prefix(), None);
        assert!(set.insert(1));
        assert_eq!(set.prefix(), None, "0 missing");
        assert!(set.insert(0));
        assert_eq!(set.prefix(), Some(1));
        assert!(!set.insert(1));
        assert!(!set.insert(0));
        assert!(set.insert(5));
        assert!(set.insert(3));
        assert_eq!(set.prefix(), Some(1));
        assert!(set.contains(5) && set.contains(3) && !set.contains(4) && !set.contains(2));
        assert_eq!(set.holes(), vec![2..=2, 4..=4]);
        assert!(set.insert(2));
        assert_eq!(set.prefix(), Some(3));
        assert!(set.insert(4));
        assert_eq!(set.prefix(), Some(5));
        assert_eq!(set.ranges.len(), 1, "merged into one range");
        assert!(set.holes().is_empty());
    }

    #[test]
    fn seq_set_ranges_merge_runs_and_start_with_the_prefix() {
        let mut set = SeqSet::default();
        assert!(set.ranges().is_empty());
        for seq in [3, 4, 7, 9, 10, 11] {
            set.insert(seq);
        }
        assert_eq!(set.ranges(), vec![3..=4, 7..=7, 9..=11]);
        assert_eq!(set.holes(), vec![0..=2, 5..=6, 8..=8]);
        for seq in [0, 1] {
            set.insert(seq);
        }
        assert_eq!(set.ranges(), vec![0..=1, 3..=4, 7..=7, 9..=11]);
        set.insert(2);
        assert_eq!(set.ranges(), vec![0..=4, 7..=7, 9..=11]);
        let mut copy = SeqSet::default();
        for range in set.ranges() {
            assert!(copy.push_range(range));
        }
        assert_eq!(copy, set);
        assert!(!copy.push_range(12..=13), "adjacent to 9..=11");
        assert!(!copy.push_range(5..=6), "out of order");
        let (high, low) = (20, 19);
        assert!(!copy.push_range(high..=low), "empty");
    }

    #[test]
    fn seq_set_memory_grows_with_gaps_not_members() {
        let mut set = SeqSet::default();
        for seq in 1..100_000 {
            set.insert(seq);
        }
        assert_eq!(set.ranges.len(), 1, "0 is missing, one range after it");
        assert_eq!(set.prefix(), None);
    }

    #[test]
    fn seq_set_survives_u64_max() {
        let mut set = SeqSet::default();
        assert!(set.push_range(0..=u64::MAX - 1));
        assert!(set.insert(u64::MAX));
        assert_eq!(set.prefix(), Some(u64::MAX));
        assert!(!set.insert(u64::MAX));
        assert!(!set.insert(7));
        assert!(set.holes().is_empty());
        let mut top = SeqSet::default();
        assert!(top.insert(u64::MAX));
        assert_eq!(top.holes(), vec![0..=u64::MAX - 1]);
    }

    #[test]
    fn topics_follow_the_table() {
        let cases: Vec<(Body, &str)> = vec![
            (Hello::new("pi", "0.1.0", vec![]).into(), "/scan3d/hello"),
            (
                LidarRevolution::new(SensorId::RPLIDAR, 0, 1).into(),
                "/scan3d/lidar/rplidar",
            ),
            (
                LidarRevolution::new(SensorId::SWEEP, 0, 1).into(),
                "/scan3d/lidar/sweep",
            ),
            (
                LidarRevolution::new(SensorId(9), 0, 1).into(),
                "/scan3d/lidar/sensor9",
            ),
            (
                ImuSample {
                    t_ns: 1,
                    accel_mps2: [0.0; 3],
                    gyro_radps: [0.0; 3],
                    mag_ut: [0.0; 3],
                    orientation: None,
                }
                .into(),
                "/scan3d/imu",
            ),
            (
                StepperState {
                    t_ns: 1,
                    commanded_angle_deg: 0.0,
                    step_index: 0,
                    holding: true,
                }
                .into(),
                "/scan3d/stepper",
            ),
            (
                TimePong {
                    t0_ns: 1,
                    t1_ns: 2,
                    t2_ns: 3,
                }
                .into(),
                "/scan3d/timepong",
            ),
            (TimePing { t0_ns: 1 }.into(), "/scan3d/timeping"),
            (
                DeviceStatus {
                    t_ns: 1,
                    sensor: SensorId::IMU,
                    event: StatusEvent::SensorLost,
                    reason: String::new(),
                }
                .into(),
                "/scan3d/status",
            ),
            (Heartbeat { sent_ns: 1 }.into(), "/scan3d/heartbeat"),
            (Ack::UpTo { seq: 1 }.into(), "/scan3d/ack"),
            (Command::StopStaticScan.into(), "/scan3d/command"),
        ];
        for (body, expected) in cases {
            assert_eq!(topic(&body), expected, "{body:?}");
        }
    }

    #[test]
    fn publish_time_is_the_edge_timestamp() {
        let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 100, 200);
        rev.samples.clear();
        assert_eq!(edge_time_ns(&rev.into()), Some(200));
        let pong = TimePong {
            t0_ns: 1,
            t1_ns: 2,
            t2_ns: 3,
        };
        assert_eq!(edge_time_ns(&pong.into()), Some(3));
        assert_eq!(edge_time_ns(&Ack::UpTo { seq: 4 }.into()), None);
    }

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
