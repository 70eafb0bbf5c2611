//! Listing and summaries: what each recording directory holds, for `scan3d sessions`.

use std::collections::BTreeMap;
use std::fs;
use std::io;
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

use scan3d_protocol::Body;
use serde::Serialize;

use super::reader::{Loss, SessionReader, SessionRecord};
use super::{RecorderError, session_files};

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
    /// Records the server made (clock models, …) per topic; not counted in `frames`.
    pub server_records_per_topic: BTreeMap<String, u64>,
    /// Messages that are neither decodable `scan3d-frame`s nor server-made records this
    /// build knows (skipped).
    pub skipped_messages: u64,
    /// Frames the server received but could not decode, recorded raw on
    /// [`UNDECODABLE_TOPIC`](super::UNDECODABLE_TOPIC) (each seq once; not counted in
    /// `frames`).
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
    /// Damaged stretches skipped, and the seqs they probably held (see
    /// [`SessionReport`](super::SessionReport)).
    pub losses: Vec<Loss>,
    /// See [`SessionReport::missing_seqs`](super::SessionReport::missing_seqs).
    pub missing_seqs: Vec<RangeInclusive<u64>>,
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
    let mut server_records_per_topic: BTreeMap<String, u64> = BTreeMap::new();
    let report = SessionReader::new(session_dir).visit(|record| {
        let recorded = match record {
            SessionRecord::Frame(recorded) => recorded,
            SessionRecord::Server(server) => {
                *server_records_per_topic.entry(server.topic).or_default() += 1;
                return Ok(());
            }
            SessionRecord::Undecodable(_) => return Ok(()),
        };
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
        server_records_per_topic,
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
