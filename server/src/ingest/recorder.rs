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
//! ```
//!
//! `<edge>` is the edge's name (from its client certificate): ASCII letters, digits, `.`, `_` and
//! `-`, not starting with a dot. Every [`SessionRecorder::open`] starts a **new** file, numbered
//! one past the highest existing one; an existing file is never appended to. A server that
//! crashed leaves its last file without summary and perhaps with a half-written chunk; readers
//! here take every complete chunk of every file and stop at the first damaged record.
//!
//! # Files
//!
//! Standard MCAP (profile `scan3d`), zstd-compressed chunks with CRCs, message indexes and a
//! summary with statistics when the file was closed properly. Chunks are at most about 1 MiB
//! uncompressed, and every commit ends one.
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
//! | `/scan3d/timesync` | [`Body::TimePong`]; `log_time` is the server's receive time t3 | `t2_ns` |
//! | `/scan3d/status` | [`Body::Status`] | `t_ns` |
//! | `/scan3d/heartbeat` | [`Body::Heartbeat`] from the edge | `sent_ns` |
//! | `/scan3d/ack` | [`Body::Ack`] from the edge (it takes an edge sequence number too) | log time |
//! | `/scan3d/command` | [`Body::Command`] the server sent ([`SessionRecorder::append_command`]) | log time |
//! | `/scan3d/static_scan` | [`Body::StaticScan`]: start (position, step, mount), tagged samples, warnings, end | `t_ns` |
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
//! Edge frames and server commands number their frames independently (see [`Frame`]), so the
//! recorder keeps two sets: a frame is a duplicate when its `(session, direction, seq)` is already
//! recorded, durable or buffered. Durable edge sequence numbers are tracked as a contiguous
//! prefix plus the few that arrived past a gap; [`SessionRecorder::commit`] returns the prefix.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

use mcap::records::{MessageHeader, Metadata};
use mcap::sans_io::LinearReaderOptions;
use mcap::{Compression, McapError, WriteOptions, Writer};
use scan3d_protocol::{Body, Direction, Frame, StaticScan, decode};
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
    /// An earlier write or sync failed; the file's state is unknown. Drop this recorder and
    /// [`SessionRecorder::open`] the session again (it continues in a new file).
    #[error("recorder for {0} failed earlier; open the session again")]
    Failed(PathBuf),
}

impl RecorderError {
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
    match body {
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
    }
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
        Body::TimePong(_) => "/scan3d/timesync".into(),
        Body::Ack(_) => "/scan3d/ack".into(),
        Body::Heartbeat(_) => "/scan3d/heartbeat".into(),
        Body::Status(_) => "/scan3d/status".into(),
        Body::Command(_) => "/scan3d/command".into(),
        Body::StaticScan(_) => "/scan3d/static_scan".into(),
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
            StaticScan::Samples(samples) => samples.t_ns,
            StaticScan::Warning(warning) => warning.t_ns,
            StaticScan::Finished(end) => end.t_ns,
        }),
        Body::Hello(_) | Body::TimePing(_) | Body::Ack(_) | Body::Command(_) => None,
    }
}

/// A set of sequence numbers stored as a contiguous prefix `0..=top` plus the ones past a gap.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
struct SeqSet {
    /// Every seq `<= top` is in the set; `None` while 0 is missing.
    top: Option<u64>,
    /// Members above `top + 1` (never contiguous with the prefix).
    above: BTreeSet<u64>,
}

impl SeqSet {
    fn contains(&self, seq: u64) -> bool {
        self.top.is_some_and(|top| seq <= top) || self.above.contains(&seq)
    }

    /// Adds `seq`; `false` if it was already there.
    fn insert(&mut self, seq: u64) -> bool {
        if self.contains(seq) {
            return false;
        }
        let next = match self.top {
            None => Some(0),
            Some(top) => top.checked_add(1),
        };
        if next == Some(seq) {
            self.top = Some(seq);
            while let Some(following) = self.top.and_then(|t| t.checked_add(1)) {
                if !self.above.remove(&following) {
                    break;
                }
                self.top = Some(following);
            }
        } else {
            self.above.insert(seq);
        }
        true
    }

    /// The highest `S` such that every seq `<= S` is in the set.
    fn prefix(&self) -> Option<u64> {
        self.top
    }

    /// Every member as sorted, disjoint, non-adjacent inclusive ranges (the prefix first).
    fn ranges(&self) -> Vec<RangeInclusive<u64>> {
        let mut out: Vec<RangeInclusive<u64>> = Vec::new();
        if let Some(top) = self.top {
            out.push(0..=top);
        }
        for &seq in &self.above {
            match out.last_mut() {
                Some(last) if last.end().checked_add(1) == Some(seq) => {
                    *last = *last.start()..=seq;
                }
                _ => out.push(seq..=seq),
            }
        }
        out
    }
}

/// Deduplication key of a recorded frame: edge frames and server commands number separately.
fn dedup_key(frame: &Frame) -> (u64, bool) {
    (frame.session_id, matches!(frame.body, Body::Command(_)))
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
    /// Total size of the files in bytes.
    pub bytes: u64,
}

/// How reading one file ended.
#[derive(Debug, Default)]
struct FileScan {
    /// It ended at the end magic (closed properly) rather than at a damaged record.
    complete: bool,
    /// Messages skipped because they are not decodable frames.
    skipped: u64,
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

/// Reads every message of one file that lies in a complete, CRC-checked chunk, stopping quietly
/// at the first damaged or missing record (a file cut short by a crash).
fn scan_file(
    path: &Path,
    visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
) -> Result<FileScan, RecorderError> {
    let file = File::open(path).map_err(RecorderError::io(path))?;
    let options = LinearReaderOptions::default()
        .with_prevalidate_chunk_crcs(true)
        .with_record_length_limit(RECORD_LENGTH_LIMIT);
    let mut reader = mcap::sans_io::MessageReader::new_with_options(options);
    let mut source = BufReader::with_capacity(64 * 1024, file);
    let mut scan = FileScan::default();
    while let Some(event) = reader.next_event() {
        match event {
            Ok(mcap::sans_io::MessageReadEvent::ReadRequest(need)) => {
                let read = loop {
                    match source.read(reader.insert(need)) {
                        Ok(n) => break n,
                        Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                        Err(e) => return Err(RecorderError::io(path)(e)),
                    }
                };
                reader.notify_read(read);
            }
            Ok(mcap::sans_io::MessageReadEvent::Message(message)) => {
                if message.channel.message_encoding == UNDECODABLE_ENCODING {
                    match parse_undecodable(message.log_time, &message.data) {
                        Some(undecodable) => visit(Item::Undecodable(undecodable))?,
                        None => scan.skipped += 1,
                    }
                    continue;
                }
                if message.channel.message_encoding != MESSAGE_ENCODING {
                    scan.skipped += 1;
                    continue;
                }
                match decode(&message.data) {
                    Ok((frame, used)) if used == message.data.len() => {
                        visit(Item::Frame(RecordedFrame {
                            topic: message.channel.topic.clone(),
                            log_time_ns: message.log_time,
                            raw: message.data.into_owned(),
                            frame,
                        }))?
                    }
                    Ok(_) => {
                        tracing::warn!(path = %path.display(), "message with bytes after its frame skipped");
                        scan.skipped += 1;
                    }
                    Err(e) => {
                        tracing::warn!(path = %path.display(), error = %e, "undecodable message skipped");
                        scan.skipped += 1;
                    }
                }
            }
            Err(e) => {
                tracing::info!(path = %path.display(), reason = %e, "recording ends early (cut short?); read up to its last complete chunk");
                return Ok(scan);
            }
        }
    }
    scan.complete = true;
    Ok(scan)
}

/// Per-file results of [`visit_files`].
struct DirScan {
    files: usize,
    incomplete_files: usize,
    skipped: u64,
    bytes: u64,
}

/// One record read back from a session file.
#[derive(Debug)]
enum Item {
    Frame(RecordedFrame),
    Undecodable(UndecodableFrame),
}

/// Visits every item of the session's files, each frame `(session, direction, seq)` and each
/// undecodable seq once.
fn visit_files(
    dir: &Path,
    visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
) -> Result<DirScan, RecorderError> {
    let files = session_files(dir)?;
    let mut seen: HashMap<(u64, bool), SeqSet> = HashMap::new();
    let mut undecodable_seen = SeqSet::default();
    let mut out = DirScan {
        files: files.len(),
        incomplete_files: 0,
        skipped: 0,
        bytes: 0,
    };
    for (_, path) in &files {
        out.bytes += fs::metadata(path).map_err(RecorderError::io(path))?.len();
        let scan = scan_file(path, &mut |item| {
            let first = match &item {
                Item::Frame(recorded) => seen
                    .entry(dedup_key(&recorded.frame))
                    .or_default()
                    .insert(recorded.frame.seq),
                Item::Undecodable(undecodable) => undecodable_seen.insert(undecodable.seq),
            };
            if first { visit(item) } else { Ok(()) }
        })?;
        if !scan.complete {
            out.incomplete_files += 1;
        }
        out.skipped += scan.skipped;
    }
    Ok(out)
}

/// Calls `visit` for every frame of a session directory, file by file in order, each
/// `(session, direction, seq)` once. Files cut short are read up to their last complete chunk.
/// Streaming: memory does not grow with the recording.
pub fn visit_session(
    session_dir: &Path,
    mut visit: impl FnMut(RecordedFrame) -> Result<(), RecorderError>,
) -> Result<(), RecorderError> {
    visit_files(session_dir, &mut |item| match item {
        Item::Frame(recorded) => visit(recorded),
        Item::Undecodable(_) => Ok(()),
    })
    .map(|_| ())
}

/// All frames of a session directory in recording order, duplicates removed (see
/// [`visit_session`]).
pub fn read_session(session_dir: &Path) -> Result<Vec<RecordedFrame>, RecorderError> {
    let mut frames = Vec::new();
    visit_session(session_dir, |frame| {
        frames.push(frame);
        Ok(())
    })?;
    Ok(frames)
}

/// Summarises one session directory (see [`SessionSummary`]).
pub fn summarize_session(
    edge: &str,
    session_id: u64,
    session_dir: &Path,
) -> Result<SessionSummary, RecorderError> {
    let mut summary = SessionSummary {
        edge: edge.to_string(),
        session_id,
        dir: session_dir.to_path_buf(),
        files: 0,
        incomplete_files: 0,
        frames: 0,
        frames_per_topic: BTreeMap::new(),
        skipped_messages: 0,
        undecodable_frames: 0,
        first_log_time_ns: None,
        last_log_time_ns: None,
        bytes: 0,
    };
    let scan = visit_files(session_dir, &mut |item| {
        let recorded = match item {
            Item::Frame(recorded) => recorded,
            Item::Undecodable(_) => {
                summary.undecodable_frames += 1;
                return Ok(());
            }
        };
        summary.frames += 1;
        *summary.frames_per_topic.entry(recorded.topic).or_default() += 1;
        let t = recorded.log_time_ns;
        summary.first_log_time_ns = Some(summary.first_log_time_ns.map_or(t, |f| f.min(t)));
        summary.last_log_time_ns = Some(summary.last_log_time_ns.map_or(t, |l| l.max(t)));
        Ok(())
    })?;
    summary.files = scan.files;
    summary.incomplete_files = scan.incomplete_files;
    summary.skipped_messages = scan.skipped;
    summary.bytes = scan.bytes;
    Ok(summary)
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

/// Records one edge session into a new MCAP file of its directory, acknowledging only what is
/// synced to disk.
///
/// Not thread-safe by design: one recorder per edge connection task. After any error from
/// [`append`](Self::append) or [`commit`](Self::commit) the recorder refuses further work
/// ([`RecorderError::Failed`]); open the session again to continue in a new file.
/// Dropping it without [`close`](Self::close) lets the MCAP writer finish the file best-effort
/// (no fsync); a crash leaves the file without summary, which the readers tolerate.
pub struct SessionRecorder {
    edge: String,
    session_id: u64,
    dir: PathBuf,
    path: PathBuf,
    writer: Writer<BufWriter<File>>,
    /// Second handle on the file, to fsync what the writer flushed.
    sync: File,
    channels: HashMap<String, u16>,
    /// Edge seqs recorded (durable or buffered): the duplicate check.
    seen: SeqSet,
    /// Edge seqs synced to disk: what may be acknowledged.
    durable: SeqSet,
    /// Server command seqs recorded.
    commands: SeqSet,
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

impl SessionRecorder {
    /// Opens the recording of `edge`'s session `session_id` under `data_dir`: creates the
    /// directory, reads the files earlier server runs left (tolerating a cut-short last chunk)
    /// to learn which frames are already durable, and starts the next-numbered file.
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

        let mut seen = SeqSet::default();
        let mut commands = SeqSet::default();
        visit_files(&dir, &mut |item| {
            match item {
                Item::Frame(recorded) if recorded.frame.session_id == session_id => {
                    if matches!(recorded.frame.body, Body::Command(_)) {
                        commands.insert(recorded.frame.seq);
                    } else {
                        seen.insert(recorded.frame.seq);
                    }
                }
                Item::Frame(_) => {}
                Item::Undecodable(undecodable) => {
                    seen.insert(undecodable.seq);
                }
            }
            Ok(())
        })?;
        let files = session_files(&dir)?;
        // What an earlier run wrote but did not sync may still sit in the page cache: sync it
        // before counting it as durable.
        for (_, path) in &files {
            File::open(path)
                .and_then(|f| f.sync_all())
                .map_err(RecorderError::io(path))?;
        }
        let index = files.last().map_or(0, |(last, _)| last.saturating_add(1));
        let path = dir.join(format!("{index:04}.mcap"));
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(RecorderError::io(&path))?;
        let sync = file.try_clone().map_err(RecorderError::io(&path))?;
        sync_dir(&dir)?;

        let mcap_err = |source| RecorderError::Mcap {
            path: path.clone(),
            source,
        };
        let options = WriteOptions::new()
            .compression(Some(Compression::Zstd))
            .compression_threads(0)
            .chunk_size(Some(CHUNK_SIZE))
            .profile(PROFILE)
            .library(format!("scan3d-server {}", env!("CARGO_PKG_VERSION")));
        let mut writer = options
            .create(BufWriter::with_capacity(64 * 1024, file))
            .map_err(mcap_err)?;
        let metadata = Metadata {
            name: SESSION_METADATA.to_string(),
            metadata: BTreeMap::from([
                ("edge".to_string(), edge.to_string()),
                ("session_id".to_string(), format!("{session_id:016x}")),
                ("file_index".to_string(), index.to_string()),
                (
                    "recorder".to_string(),
                    format!("scan3d-server {}", env!("CARGO_PKG_VERSION")),
                ),
            ]),
        };
        writer.write_metadata(&metadata).map_err(mcap_err)?;
        tracing::info!(
            path = %path.display(),
            durable_prefix = ?seen.prefix(),
            "recording session"
        );
        Ok(SessionRecorder {
            edge: edge.to_string(),
            session_id,
            dir,
            path,
            writer,
            sync,
            channels: HashMap::new(),
            durable: seen.clone(),
            seen,
            commands,
            pending: Vec::new(),
            dirty: false,
            failed: false,
        })
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
        self.check(frame)?;
        if !matches!(frame.body, Body::Command(_)) {
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
        Ok(self.durable.prefix())
    }

    /// Commits, then writes the summary and footer so the file is a complete MCAP, and fsyncs
    /// it. Returns the final durable prefix (see [`commit`](Self::commit)).
    pub fn close(mut self) -> Result<Option<u64>, RecorderError> {
        let prefix = self.commit()?;
        let path = self.path.clone();
        let mcap_err = |source| RecorderError::Mcap {
            path: path.clone(),
            source,
        };
        self.writer.finish().map_err(mcap_err)?;
        let mut inner = self.writer.into_inner();
        inner.flush().map_err(RecorderError::io(&path))?;
        self.sync.sync_data().map_err(RecorderError::io(&path))?;
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
        assert!(set.insert(2));
        assert_eq!(set.prefix(), Some(3));
        assert!(set.insert(4));
        assert_eq!(set.prefix(), Some(5));
        assert!(set.above.is_empty());
    }

    #[test]
    fn seq_set_ranges_merge_runs_and_start_with_the_prefix() {
        let mut set = SeqSet::default();
        assert!(set.ranges().is_empty());
        for seq in [3, 4, 7, 9, 10, 11] {
            set.insert(seq);
        }
        assert_eq!(set.ranges(), vec![3..=4, 7..=7, 9..=11]);
        for seq in [0, 1] {
            set.insert(seq);
        }
        assert_eq!(set.ranges(), vec![0..=1, 3..=4, 7..=7, 9..=11]);
        set.insert(2);
        assert_eq!(set.ranges(), vec![0..=4, 7..=7, 9..=11]);
    }

    #[test]
    fn undecodable_messages_round_trip_and_cut_long_reasons_at_a_char_boundary() {
        let data = undecodable_message(u64::MAX - 3, "bad", b"\x00\x01");
        let back = parse_undecodable(7, &data).expect("parse");
        assert_eq!(
            back,
            UndecodableFrame {
                log_time_ns: 7,
                seq: u64::MAX - 3,
                reason: "bad".into(),
                raw: vec![0, 1],
            }
        );
        let long = "é".repeat(UNDECODABLE_REASON_LIMIT);
        let back = parse_undecodable(0, &undecodable_message(1, &long, b"x")).expect("parse");
        assert!(back.reason.len() <= UNDECODABLE_REASON_LIMIT);
        assert_eq!(back.reason.len() % 2, 0, "no half character");
        assert_eq!(back.raw, b"x");
        assert!(parse_undecodable(0, b"S3DP....").is_none());
        assert!(parse_undecodable(0, &data[..10]).is_none());
    }

    #[test]
    fn seq_set_survives_u64_max() {
        let mut set = SeqSet {
            top: Some(u64::MAX - 1),
            above: BTreeSet::new(),
        };
        assert!(set.insert(u64::MAX));
        assert_eq!(set.prefix(), Some(u64::MAX));
        assert!(!set.insert(u64::MAX));
        assert!(!set.insert(7));
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
                "/scan3d/timesync",
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
