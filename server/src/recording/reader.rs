//! The reader: walks a session's MCAP files in recording order and hands on each record once
//! (each frame's `(session, direction, seq)` once, each undecodable seq once), with a report of
//! what could not be read. [`SessionReader`] is the whole view (frames, undecodable frames,
//! server-made records) and can start at an edge sequence number, skipping the files the
//! session index shows to lie wholly before it; [`visit_session`] and [`visit_session_items`]
//! are the frame views the offline commands and the pipeline use.

use std::collections::HashMap;
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

use scan3d_protocol::{Body, Frame, PROTOCOL_VERSION};
use serde::Serialize;

use super::index::read_index;
use super::seq_ranges::SeqRanges;
use super::server_record::{RecordedServerRecord, ServerRecord};
use super::undecodable::UndecodableFrame;
use super::walker::{ChannelInfo, Item, scan_file};
use super::{RecorderError, session_files};

/// Deduplication key of a recorded frame: edge frames and server-originated ones number
/// separately.
fn dedup_key(frame: &Frame) -> (u64, bool) {
    (frame.session_id, server_originated(&frame.body))
}

/// Whether the server made this body (a command it sent; a clock model in a recording made
/// before server-made records): numbered in the server's sequence, not the edge's.
pub(crate) fn server_originated(body: &Body) -> bool {
    body.is_server_made()
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
    /// Number of MCAP files in the directory.
    pub files: usize,
    /// Files not read: before the position the read resumed at
    /// ([`SessionReader::resume_at`]), or shown by the session index to hold only edge seqs
    /// below the one it started at ([`SessionReader::from_seq`]). The other fields describe
    /// the files read.
    pub files_skipped: usize,
    /// Files that end early (a crash cut them short; read up to their last complete chunk).
    pub incomplete_files: usize,
    /// Messages that are neither decodable `scan3d-frame`s nor server-made records this
    /// build knows (skipped).
    pub skipped_messages: u64,
    /// Frames the server received but could not decode, recorded raw on
    /// [`UNDECODABLE_TOPIC`](super::UNDECODABLE_TOPIC) (each seq once; not visited as frames).
    pub undecodable_frames: u64,
    /// Total size of the files in bytes.
    pub bytes: u64,
    /// Damaged stretches skipped (empty when everything recorded was read). A file cut short
    /// by a crash is not a loss: what it lacks was never acknowledged.
    pub losses: Vec<Loss>,
    /// Where the read ended, to resume there later ([`SessionReader::resume_at`]); `None`
    /// when there was no file to read.
    #[serde(skip)]
    pub end: Option<ReadPosition>,
    /// Edge sequence numbers below the highest one read (and not below the one the read
    /// started at) that are in no file read, as ranges. With
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

/// Where a read of a session ended: the last file read and the offset in it where the next
/// read resumes (past its last complete chunk), or past it when it was finished. Recordings
/// only grow, so a read resumed here ([`SessionReader::resume_at`]) hands on exactly what was
/// recorded since, reading nothing twice.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadPosition {
    /// The file's number.
    file: u64,
    /// Where in it to resume (0: from its start).
    offset: u64,
    /// The file was finished (summary and end magic): resume with the next one.
    finished: bool,
    /// The channels the file declared before `offset`.
    channels: HashMap<u16, ChannelInfo>,
}

impl ReadPosition {
    /// The number of the file the read ended in.
    pub fn file(&self) -> u64 {
        self.file
    }

    /// The offset in it where the next read starts (its length when it was finished).
    pub fn offset(&self) -> u64 {
        self.offset
    }
}

/// Results of [`visit_files`].
pub(crate) struct DirScan {
    pub(crate) report: SessionReport,
    /// `(index, length read)` of each file.
    pub(crate) lengths: Vec<(u64, u64)>,
}

/// Visits every item of the given files, each frame `(session, direction, seq)` and each
/// undecodable seq once, with the number of the file it is in. Edge items (edge frames and
/// undecodable frames) with a seq below `from_seq` are read but not visited, and the report's
/// missing seqs start at `from_seq`. `resume`: where in the first file to start (a position an
/// earlier read ended at, in that file).
pub(crate) fn visit_files(
    files: &[(u64, PathBuf)],
    from_seq: u64,
    resume: Option<&ReadPosition>,
    visit: &mut dyn FnMut(u64, Item) -> Result<(), RecorderError>,
) -> Result<DirScan, RecorderError> {
    let mut seen: HashMap<(u64, bool), SeqRanges> = HashMap::new();
    let mut edge_seqs = SeqRanges::default();
    let mut undecodable_seen = SeqRanges::default();
    let mut out = DirScan {
        report: SessionReport {
            files: files.len(),
            ..SessionReport::default()
        },
        lengths: Vec::with_capacity(files.len()),
    };
    for (position, (index, path)) in files.iter().enumerate() {
        let start = resume
            .filter(|at| position == 0 && at.file == *index && !at.finished)
            .map(|at| (at.offset, at.channels.clone()));
        let scan = scan_file(path, start, &mut |item| {
            let first = match &item {
                Item::Frame(recorded) => seen
                    .entry(dedup_key(&recorded.frame))
                    .or_default()
                    .insert(recorded.frame.seq),
                Item::Undecodable(undecodable) => undecodable_seen.insert(undecodable.seq),
                Item::Record(_) | Item::OtherVersion(_) => true,
            };
            let edge_seq = match &item {
                Item::Frame(recorded) if !server_originated(&recorded.frame.body) => {
                    Some(recorded.frame.seq)
                }
                Item::Frame(_) | Item::Record(_) | Item::OtherVersion(_) => None,
                Item::Undecodable(undecodable) => Some(undecodable.seq),
            };
            if let Some(seq) = edge_seq {
                edge_seqs.insert(seq);
            }
            if first && edge_seq.is_none_or(|seq| seq >= from_seq) {
                visit(*index, item)
            } else {
                Ok(())
            }
        })?;
        let report = &mut out.report;
        report.bytes += scan.len;
        if !scan.complete {
            report.incomplete_files += 1;
        }
        report.skipped_messages += scan.skipped;
        report.losses.extend(scan.losses);
        out.lengths.push((*index, scan.len));
        report.end = Some(ReadPosition {
            file: *index,
            offset: scan.end,
            finished: scan.complete,
            channels: scan.channels,
        });
    }
    out.report.undecodable_frames = undecodable_seen.len();
    out.report.missing_seqs = match edge_seqs.last() {
        Some(last) if last >= from_seq => edge_seqs.missing_in(from_seq, last),
        _ => Vec::new(),
    };
    Ok(out)
}

/// One record of a session, as [`SessionReader`] hands it on.
#[derive(Debug, Clone, PartialEq)]
pub enum SessionRecord {
    /// A wire frame: one the edge sent, or a command the server sent it.
    Frame(RecordedFrame),
    /// An edge frame the server recorded without being able to decode it (its seq was
    /// received, so it is no gap).
    Undecodable(UndecodableFrame),
    /// A record the server made (a clock model, …). A clock model that an older server
    /// recorded as a wire frame (`Body::ClockModel`) comes here too, never as a frame.
    Server(RecordedServerRecord),
}

/// Reads a session directory's records in recording order: file by file, each frame
/// `(session, direction, seq)` and each undecodable seq once, server-made records as written.
/// Files cut short are read up to their last complete chunk; damaged chunks are skipped and
/// reported in the returned [`SessionReport`] (check [`SessionReport::losses`]). Streaming:
/// memory does not grow with the recording. A session recorded with another protocol version
/// fails with [`RecorderError::ProtocolVersion`] at its first such frame.
///
/// [`from_seq`](Self::from_seq) starts the read at an edge sequence number: the leading files
/// that the session index (`recorded.idx`) shows to hold only edge seqs below it are not read
/// at all (nor their commands and server-made records), and in the files read, edge frames and
/// undecodable frames below it are not handed on. So a reader catching up from the seq it is
/// owed costs what the files from that seq on cost, not what the whole session does.
///
/// [`resume_at`](Self::resume_at) starts where an earlier read ended
/// ([`SessionReport::end`]): nothing before that point is read again, so a reader that
/// follows a recording as it grows (a live worker catching up) reads each byte once. Records
/// recorded before the position are not handed on again; a duplicate recorded after it (which
/// the recorder does not write) would be.
#[derive(Debug, Clone)]
pub struct SessionReader {
    dir: PathBuf,
    from_seq: u64,
    resume: Option<ReadPosition>,
}

impl SessionReader {
    /// A reader of the session directory `session_dir`, from its start.
    pub fn new(session_dir: &Path) -> Self {
        SessionReader {
            dir: session_dir.to_path_buf(),
            from_seq: 0,
            resume: None,
        }
    }

    /// Starts the read where an earlier read of this session ended (see the type's
    /// documentation).
    pub fn resume_at(mut self, position: ReadPosition) -> Self {
        self.resume = Some(position);
        self
    }

    /// Starts the read at edge sequence number `seq` (see the type's documentation).
    pub fn from_seq(mut self, seq: u64) -> Self {
        self.from_seq = seq;
        self
    }

    /// The session directory.
    pub fn session_dir(&self) -> &Path {
        &self.dir
    }

    /// The files to read, and how many leading files are skipped (before the resume
    /// position, or shown by the index to lie before `from_seq`).
    fn files(&self) -> Result<(Vec<(u64, PathBuf)>, usize), RecorderError> {
        let mut files = session_files(&self.dir)?;
        let mut skipped = 0;
        if let Some(at) = &self.resume {
            let before = files
                .iter()
                .take_while(|(number, _)| *number < at.file || (*number == at.file && at.finished))
                .count();
            files.drain(..before);
            skipped += before;
        }
        if self.from_seq == 0 {
            return Ok((files, skipped));
        }
        let Some(index) = read_index(&self.dir) else {
            return Ok((files, 0));
        };
        let mut skip = 0;
        for (number, path) in &files {
            let Some(entry) = index.files.get(number) else {
                break;
            };
            // Only a file that is exactly as the index saw it, with its seqs listed.
            let len = std::fs::metadata(path)
                .map_err(RecorderError::io(path))?
                .len();
            let before = entry.len == len
                && entry
                    .edge
                    .as_ref()
                    .is_some_and(|edge| edge.last().is_none_or(|last| last < self.from_seq));
            if !before {
                break;
            }
            skip += 1;
        }
        files.drain(..skip);
        Ok((files, skipped + skip))
    }

    /// Calls `visit` for every record (see the type's documentation).
    pub fn visit(
        &self,
        mut visit: impl FnMut(SessionRecord) -> Result<(), RecorderError>,
    ) -> Result<SessionReport, RecorderError> {
        let (files, skipped) = self.files()?;
        let resume = self.resume.as_ref();
        let scan = visit_files(&files, self.from_seq, resume, &mut |_, item| match item {
            Item::Frame(recorded) => match recorded.frame.body {
                // A clock model an older server recorded as a wire frame.
                Body::ClockModel(model) => visit(SessionRecord::Server(RecordedServerRecord {
                    topic: recorded.topic,
                    log_time_ns: recorded.log_time_ns,
                    record: ServerRecord::ClockModel(model),
                })),
                _ => visit(SessionRecord::Frame(recorded)),
            },
            Item::Undecodable(undecodable) => visit(SessionRecord::Undecodable(undecodable)),
            Item::Record(record) => visit(SessionRecord::Server(record)),
            Item::OtherVersion(version) => Err(RecorderError::ProtocolVersion {
                dir: self.dir.clone(),
                version,
                supported: PROTOCOL_VERSION,
            }),
        })?;
        let mut report = scan.report;
        report.files += skipped;
        report.files_skipped = skipped;
        // Nothing read: the position stays where it was.
        if report.end.is_none() {
            report.end = self.resume.clone();
        }
        Ok(report)
    }
}

/// Calls `visit` for every frame of a session directory (see [`SessionReader`]): the frames
/// the edge sent and the commands the server sent, not undecodable frames (counted in the
/// report) nor server-made records.
pub fn visit_session(
    session_dir: &Path,
    mut visit: impl FnMut(RecordedFrame) -> Result<(), RecorderError>,
) -> Result<SessionReport, RecorderError> {
    SessionReader::new(session_dir).visit(|record| match record {
        SessionRecord::Frame(recorded) => visit(recorded),
        SessionRecord::Undecodable(_) | SessionRecord::Server(_) => Ok(()),
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

/// One item of a session for [`visit_session_items`]: a frame, or an edge frame the server
/// recorded without being able to decode it (its seq was received, so it is no gap). The
/// view of a reader that follows sequence numbers; [`SessionRecord`] is the whole one.
#[derive(Debug)]
pub enum SessionItem {
    /// A decoded frame.
    Frame(RecordedFrame),
    /// A frame recorded on [`UNDECODABLE_TOPIC`](super::UNDECODABLE_TOPIC).
    Undecodable(UndecodableFrame),
}

/// [`visit_session`], visiting the undecodable frames too (in recording order, each seq once),
/// for readers that tell a gap in the sequence numbers from a frame they cannot read.
pub fn visit_session_items(
    session_dir: &Path,
    mut visit: impl FnMut(SessionItem) -> Result<(), RecorderError>,
) -> Result<SessionReport, RecorderError> {
    SessionReader::new(session_dir).visit(|record| match record {
        SessionRecord::Frame(recorded) => visit(SessionItem::Frame(recorded)),
        SessionRecord::Undecodable(undecodable) => visit(SessionItem::Undecodable(undecodable)),
        SessionRecord::Server(_) => Ok(()),
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::fs;

    use scan3d_protocol::{ClockModel, Command, Frame, Heartbeat, encode};

    use super::*;
    use crate::recording::{SessionRecorder, read_session, session_dir, summarize_session};

    const T0: u64 = 1_767_225_600_000_000_000;

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

    /// A recording made by a protocol-2 server before server-made records (see
    /// `testdata/recordings/README.md`).
    fn legacy_data_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../testdata/recordings/protocol2-clock-models")
    }

    const LEGACY_SESSION: u64 = 0x4ec6_5dd8_064d_310b;

    #[test]
    fn a_recording_with_clock_models_as_wire_frames_reads_them_back_as_server_records() {
        let dir = session_dir(&legacy_data_dir(), "sim-edge", LEGACY_SESSION);
        let mut frames = Vec::new();
        let mut models = Vec::new();
        let report = SessionReader::new(&dir)
            .visit(|record| {
                match record {
                    SessionRecord::Frame(recorded) => frames.push(recorded),
                    SessionRecord::Server(server) => {
                        assert_eq!(server.topic, "/scan3d/timesync");
                        let ServerRecord::ClockModel(model) = server.record;
                        models.push(model);
                    }
                    SessionRecord::Undecodable(u) => panic!("undecodable {u:?}"),
                }
                Ok(())
            })
            .expect("read");
        assert_eq!(report.loss_line(), None);
        assert!(report.missing_seqs.is_empty(), "{report:?}");
        assert_eq!(frames.len(), 45);
        assert!(
            frames
                .iter()
                .all(|f| !f.frame.body.is_server_made()
                    && !matches!(f.frame.body, Body::ClockModel(_))),
            "no clock model (nor any server frame) comes out as a frame"
        );
        assert_eq!(models.len(), 2);
        assert!(
            models
                .iter()
                .all(|m| m.exchanges > 0 && m.error_bound_ns > 0)
        );
        assert!(models[0].valid_from_edge_ns < models[1].valid_from_edge_ns);
        // The frame views agree.
        assert_eq!(read_session(&dir).expect("frames").len(), 45);
        let summary = summarize_session("sim-edge", LEGACY_SESSION, &dir).expect("summary");
        assert_eq!(summary.frames, 45);
        assert_eq!(
            summary.server_records_per_topic,
            BTreeMap::from([("/scan3d/timesync".to_string(), 2)])
        );

        // A recorder reopening it (a copy) numbers new commands above the old clock models'
        // server seqs (1 and 9), and its new models are server-made records.
        let tmp = tempfile::tempdir().expect("tempdir");
        let copy = session_dir(tmp.path(), "sim-edge", LEGACY_SESSION);
        fs::create_dir_all(&copy).expect("mkdir");
        for name in ["0000.mcap", "recorded.idx"] {
            fs::copy(dir.join(name), copy.join(name)).expect("copy");
        }
        let mut rec = SessionRecorder::open(tmp.path(), "sim-edge", LEGACY_SESSION).expect("open");
        assert_eq!(rec.next_command_seq(), 10);
        assert_eq!(rec.durable_ranges(), vec![0..=44]);
        let newer = ClockModel {
            valid_from_edge_ns: models[1].valid_from_edge_ns + 1_000_000_000,
            ..models[1]
        };
        rec.append_record(&ServerRecord::ClockModel(newer), T0)
            .expect("record");
        rec.close().expect("close");
        let mut read_back = Vec::new();
        let _ = SessionReader::new(&copy)
            .visit(|record| {
                if let SessionRecord::Server(server) = record {
                    read_back.push(server.record);
                }
                Ok(())
            })
            .expect("read");
        assert_eq!(
            read_back,
            [models[0], models[1], newer]
                .map(ServerRecord::ClockModel)
                .to_vec()
        );
    }

    fn heartbeat(rec: &mut SessionRecorder, seq: u64) {
        let frame = Frame::new(rec.session_id(), seq, Heartbeat { sent_ns: seq });
        rec.append(&encode(&frame).unwrap(), &frame, T0 + seq)
            .unwrap();
    }

    fn model(valid_from_edge_ns: u64) -> ServerRecord {
        ServerRecord::ClockModel(ClockModel {
            offset_ns: 3_000_000_000,
            skew_ppm: -12.5,
            error_bound_ns: 90_000,
            skew_bound_ppm: 0.5,
            ref_edge_ns: valid_from_edge_ns - 500,
            fit_from_edge_ns: valid_from_edge_ns - 1_000,
            fit_to_edge_ns: valid_from_edge_ns,
            valid_from_edge_ns,
            min_delay_ns: 180_000,
            exchanges: 7,
        })
    }

    /// What a read hands on, in order: edge seqs as `E<seq>`, commands as `C<seq>`, records as
    /// `R<edge time>`.
    fn trace(reader: &SessionReader) -> (Vec<String>, SessionReport) {
        let mut seen = Vec::new();
        let report = reader
            .visit(|record| {
                seen.push(match record {
                    SessionRecord::Frame(f) if f.frame.body.is_server_made() => {
                        format!("C{}", f.frame.seq)
                    }
                    SessionRecord::Frame(f) => format!("E{}", f.frame.seq),
                    SessionRecord::Undecodable(u) => format!("E{}", u.seq),
                    SessionRecord::Server(s) => format!("R{}", s.record.edge_time_ns().unwrap()),
                });
                Ok(())
            })
            .expect("read");
        (seen, report)
    }

    #[test]
    fn a_reader_from_a_seq_skips_the_files_the_index_shows_wholly_before_it() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let id = 0x5eed;
        // File 0: edge 0..10 and a record; file 1: edge 10..20, a command, a record; file 2
        // (a crash: not indexed): edge 20..25.
        let mut rec = SessionRecorder::open(tmp.path(), "pi", id).unwrap();
        for seq in 0..10 {
            heartbeat(&mut rec, seq);
        }
        rec.append_record(&model(100_000), T0).unwrap();
        rec.close().unwrap();
        let mut rec = SessionRecorder::open(tmp.path(), "pi", id).unwrap();
        for seq in 10..15 {
            heartbeat(&mut rec, seq);
        }
        let command = Frame::new(id, rec.next_command_seq(), Command::StopStaticScan);
        rec.append_command(&encode(&command).unwrap(), &command, T0)
            .unwrap();
        rec.append_record(&model(200_000), T0).unwrap();
        for seq in 15..20 {
            heartbeat(&mut rec, seq);
        }
        rec.close().unwrap();
        let mut rec = SessionRecorder::open(tmp.path(), "pi", id).unwrap();
        rec.append_undecodable(20, b"junk", "test", T0).unwrap();
        for seq in 21..25 {
            heartbeat(&mut rec, seq);
        }
        rec.commit().unwrap();
        std::mem::forget(rec);
        let dir = session_dir(tmp.path(), "pi", id);
        let index = fs::read_to_string(dir.join("recorded.idx")).unwrap();
        assert!(index.starts_with("scan3d-recorded-index 2\n"), "{index}");
        assert!(
            index.contains("\nfile 0 ") && index.contains(" 0-9\nfile 1 "),
            "{index}"
        );
        assert!(
            index.contains(" 10-19\nedge 0-19\ncommands 0-0\n"),
            "{index}"
        );

        let edges = |from: u64, to: u64| (from..to).map(|s| format!("E{s}"));
        let all: Vec<String> = edges(0, 10)
            .chain(["R100000".into()])
            .chain(edges(10, 15))
            .chain(["C0".into(), "R200000".into()])
            .chain(edges(15, 25))
            .collect();
        let (seen, report) = trace(&SessionReader::new(&dir));
        assert_eq!(seen, all);
        assert_eq!((report.files, report.files_skipped), (3, 0));
        assert_eq!(report.undecodable_frames, 1);

        // From 12: file 0 is skipped (its record with it); in file 1, edge frames below 12
        // are not handed on, its command and record are.
        let (seen, report) = trace(&SessionReader::new(&dir).from_seq(12));
        assert_eq!(seen, all[13..].to_vec());
        assert_eq!(seen[0], "E12");
        assert_eq!((report.files, report.files_skipped), (3, 1));
        assert!(report.missing_seqs.is_empty());
        // Past every indexed file: only the unindexed one is read.
        let (seen, report) = trace(&SessionReader::new(&dir).from_seq(23));
        assert_eq!(seen, vec!["E23", "E24"]);
        assert_eq!(report.files_skipped, 2);
        assert_eq!(
            report.bytes,
            fs::metadata(dir.join("0002.mcap")).unwrap().len()
        );

        // Without the index (or with a file changed since), nothing is skipped and the read
        // hands on the same records.
        let saved = fs::read(dir.join("recorded.idx")).unwrap();
        fs::remove_file(dir.join("recorded.idx")).unwrap();
        let (seen, report) = trace(&SessionReader::new(&dir).from_seq(12));
        let expected: Vec<String> = std::iter::once("R100000".to_string())
            .chain(all[13..].iter().cloned())
            .collect();
        assert_eq!(seen, expected);
        assert_eq!(report.files_skipped, 0);
        fs::write(dir.join("recorded.idx"), saved).unwrap();
        let mut file0 = fs::OpenOptions::new()
            .append(true)
            .open(dir.join("0000.mcap"))
            .unwrap();
        std::io::Write::write_all(&mut file0, b"x").unwrap();
        let (_, report) = trace(&SessionReader::new(&dir).from_seq(12));
        assert_eq!(report.files_skipped, 0, "file 0 is no longer as indexed");
    }

    #[test]
    fn a_read_resumed_where_the_last_one_ended_hands_on_only_what_was_recorded_since() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let id = 0xfeed;
        let dir = session_dir(tmp.path(), "pi", id);
        let mut rec = SessionRecorder::open(tmp.path(), "pi", id).unwrap();
        for seq in 0..5 {
            heartbeat(&mut rec, seq);
        }
        rec.append_record(&model(100_000), T0).unwrap();
        rec.commit().unwrap();
        // A live reader follows the file being written.
        let (seen, report) = trace(&SessionReader::new(&dir));
        assert_eq!(seen, ["E0", "E1", "E2", "E3", "E4", "R100000"]);
        let at = report.end.expect("a position");
        assert_eq!(at.file(), 0);
        assert_eq!(
            at.offset(),
            fs::metadata(dir.join("0000.mcap")).unwrap().len(),
            "past the last complete chunk"
        );
        // Nothing new: nothing handed on, the position stays.
        let (seen, report) = trace(&SessionReader::new(&dir).resume_at(at.clone()));
        assert!(seen.is_empty(), "{seen:?}");
        assert_eq!(report.end.as_ref(), Some(&at));
        for seq in 5..8 {
            heartbeat(&mut rec, seq);
        }
        rec.commit().unwrap();
        let (seen, report) = trace(&SessionReader::new(&dir).resume_at(at));
        assert_eq!(seen, ["E5", "E6", "E7"], "only what was recorded since");
        // Frames recorded in the same file (its channels declared before the position) and,
        // after a close, in the next file.
        rec.close().unwrap();
        let at = report.end.expect("a position");
        let (seen, report) = trace(&SessionReader::new(&dir).resume_at(at));
        assert!(seen.is_empty(), "the close adds no record: {seen:?}");
        let at = report.end.expect("a position");
        let mut rec = SessionRecorder::open(tmp.path(), "pi", id).unwrap();
        for seq in 8..10 {
            heartbeat(&mut rec, seq);
        }
        rec.append_record(&model(200_000), T0).unwrap();
        rec.close().unwrap();
        let (seen, report) = trace(&SessionReader::new(&dir).resume_at(at));
        assert_eq!(seen, ["E8", "E9", "R200000"]);
        assert_eq!((report.files, report.files_skipped), (2, 1));
        let end = report.end.expect("a position");
        assert_eq!(end.file(), 1);
        // The whole read hands on the same records in the same order.
        let (all, _) = trace(&SessionReader::new(&dir));
        assert_eq!(all.len(), 5 + 1 + 3 + 2 + 1);
    }
}
