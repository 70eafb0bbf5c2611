//! The live driver of the pipeline (`scan3d serve`): ingest hands every frame the recorder
//! accepted to [`LivePipelines`], which queues it for its session's worker, one thread per
//! session owning a [`SessionPipeline`].
//!
//! Ingest never waits for processing: each session's queue is bounded
//! ([`LiveSettings::queue_frames`]) and filled with `try_send`. A frame that finds the queue full
//! is not dropped silently: its seq is noted as owed, and the worker reads it back from the
//! session's recording once committed (`visit_session`) — the recording is the source of truth,
//! the queue only a fast path. The same happens when frames arrive out of sequence (resends
//! after a reconnect, a gap, a session already recorded before this daemon started): the worker
//! catches up from the recording, in the recording's order, skipping the seqs it already
//! processed, so the live products are those of a replay of the recording. [`Sequencer`] is the
//! pure core of that decision; the worker's lag (frames and ms) is reported in
//! [`StatusReport`].
//!
//! The worker never lends its pipeline for heavy work: it publishes what `status` shows
//! between frames (recomputing the metrics itself, at most once per
//! [`super::METRICS_INTERVAL`], while status is asked or once idle), and a snapshot holds the
//! pipeline only to copy what it writes ([`SessionPipeline::prepare_snapshot`]). A worker that
//! has taken no frame for [`LiveSettings::retire_after`] writes its products to disk and exits,
//! freeing its maps; the session is then served from those files, until a frame of it starts a
//! new worker that rebuilds it from the recording.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use scan3d_protocol::{Body, Frame, SensorId, StaticScan};
use serde::Serialize;

use super::edge_activity::{EdgeActivity, SensorStatus};
use super::{
    PipelineError, PipelineSettings, PreparedSnapshot, Products, SessionPipeline, SessionStatus,
    Snapshot, SnapshotWriter, load_reference,
};
use crate::ingest::control::{ControlReply, LiveProducts, ProductRequest};
use crate::ingest::scan_progress::ScanProgress;
use crate::ingest::server::{IngestEvent, IngestSink, unix_now_ns};
use crate::recording::{ReadPosition, SeqRanges, SessionReader, SessionRecord, session_dir};
use scan3d_map::eval::LeafMap;
use scan3d_map::octree::Resolution;
use scan3d_protocol::ClockModel;

/// How the live driver runs: the `[pipeline]` section of `server.toml` beyond the pipeline's
/// own settings.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveSettings {
    /// What each session's pipeline builds.
    pub pipeline: PipelineSettings,
    /// Frames each session's queue holds; more make the worker catch up from the recording.
    pub queue_frames: usize,
    /// Write every session's products into `data_dir/snapshots/<edge>/<session>/` this often
    /// (when something changed); `None`: only on request.
    pub snapshot_every: Option<Duration>,
    /// The server's data directory (recordings under `sessions/`, periodic snapshots under
    /// `snapshots/`).
    pub data_dir: PathBuf,
    /// How often a worker that owes frames looks for them in the recording (they appear there
    /// when ingest commits, every `commit_interval`).
    pub catch_up_retry: Duration,
    /// An owed frame not found in the recording for this long is given up (logged and counted
    /// in the status): the recorder lost it, and the edge will resend it if it was never
    /// acknowledged.
    pub give_up_after: Duration,
    /// How long a snapshot request waits for its session's worker to catch up.
    pub snapshot_wait: Duration,
    /// A session's worker that has taken no frame for this long writes its products into
    /// `data_dir/retired/<edge>/<session>/` and exits, freeing its maps; `status` and
    /// `snapshot` serve the session from there until a frame of it comes again. `None`: never.
    pub retire_after: Option<Duration>,
    /// How long shutdown waits, in all, for the workers to finish what they were given.
    pub shutdown_wait: Duration,
    /// How often a worker that owes nothing reads on through its recording (taking any frame
    /// committed there before its queue hands it over), so that a later catch-up starts where
    /// that read ended instead of at the start of the file holding the first frame owed: a
    /// catch-up then reads at most this much data beyond what is owed. `None`: never.
    pub read_on_every: Option<Duration>,
}

impl LiveSettings {
    /// Live settings with the defaults beyond `pipeline` and `data_dir`.
    pub fn new(pipeline: PipelineSettings, data_dir: PathBuf) -> Self {
        LiveSettings {
            pipeline,
            queue_frames: 256,
            snapshot_every: None,
            data_dir,
            catch_up_retry: Duration::from_millis(50),
            give_up_after: Duration::from_secs(30),
            snapshot_wait: Duration::from_secs(20),
            retire_after: Some(Duration::from_secs(60)),
            shutdown_wait: Duration::from_secs(35),
            read_on_every: Some(Duration::from_secs(5)),
        }
    }
}

/// What a frame offered from the queue means to the worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offer {
    /// The next frame in sequence: process it now.
    Process,
    /// Already processed (from the recording): nothing to do.
    Skip,
    /// Out of sequence, or behind frames the worker still owes: it is read back from the
    /// recording, in the recording's order.
    Owe,
}

/// Which seqs of one session the worker has processed and which it owes (accepted by the
/// recorder, not yet processed): the pure core of the live driver's ordering.
///
/// The queue's frames are processed as they come while they follow each other (seq = last + 1,
/// the first being 0); anything else, and everything after it until the debt is paid, is owed
/// and taken from the recording with [`Sequencer::from_recording`]. So the frames go through
/// the pipeline in the recording's order whatever the queue did.
#[derive(Debug, Clone, Default)]
pub struct Sequencer {
    done: SeqRanges,
    owed: BTreeSet<u64>,
}

impl Sequencer {
    /// A frame from the queue.
    pub fn offer(&mut self, seq: u64) -> Offer {
        if self.done.contains(seq) {
            return Offer::Skip;
        }
        let next = match self.done.last() {
            None => 0,
            Some(last) => last.saturating_add(1),
        };
        if self.owed.is_empty() && seq == next {
            self.done.insert(seq);
            Offer::Process
        } else {
            self.owed.insert(seq);
            Offer::Owe
        }
    }

    /// The smallest sequence number not processed yet: a catch-up reads the recording from
    /// there, so its cost follows what is owed, not the session's length.
    pub fn resume_from(&self) -> u64 {
        self.done.prefix().map_or(0, |last| last.saturating_add(1))
    }

    /// A frame the queue had no room for.
    pub fn owe(&mut self, seq: u64) {
        if !self.done.contains(seq) {
            self.owed.insert(seq);
        }
    }

    /// A frame read back from the recording, in recording order: whether to process it.
    pub fn from_recording(&mut self, seq: u64) -> bool {
        self.owed.remove(&seq);
        self.done.insert(seq)
    }

    /// Frames owed.
    pub fn owed(&self) -> usize {
        self.owed.len()
    }

    /// Counts every seq before `seq` as processed (a worker that took them from its queue):
    /// the next catch-up reads from `seq`.
    pub fn processed_before(&mut self, seq: u64) {
        if let Some(last) = seq.checked_sub(1) {
            self.done.insert_range(0, last);
            self.owed.retain(|&owed| owed >= seq);
        }
    }

    /// Gives up the owed frames (they never reached the recording); returns them.
    pub fn forgive(&mut self) -> Vec<u64> {
        std::mem::take(&mut self.owed).into_iter().collect()
    }
}

/// One catch-up of a session's worker, run by the daemon's own code ([`WorkerRun`]'s
/// catch-up) outside the daemon: the catch-up benchmark's entry point. The worker is built as
/// if it had processed every frame before `owed_from` from its queue and owed the rest.
pub struct CatchUpProbe {
    run: WorkerRun,
}

impl CatchUpProbe {
    /// A worker of `edge`'s session `session_id` (recorded under `settings.data_dir`), its
    /// pipeline built, owing every frame from `owed_from` on.
    pub fn new(
        settings: &LiveSettings,
        edge: &str,
        session_id: u64,
        owed_from: u64,
    ) -> Result<Self, PipelineError> {
        let pipeline = SessionPipeline::new(&settings.pipeline)?;
        let (_queue, frames) = std::sync::mpsc::sync_channel(1);
        let mut run = WorkerRun::new(
            Arc::new(WorkerShared::new(edge, session_id)),
            frames,
            settings,
        );
        *lock(&run.shared.pipeline) = Slot::Running(Box::new(pipeline));
        run.sequencer.processed_before(owed_from);
        Ok(CatchUpProbe { run })
    }

    /// Reads the recording from the first frame owed and processes it all, as the worker
    /// does; returns the frames put through the pipeline.
    pub fn catch_up(&mut self) -> u64 {
        let before = self.run.processed;
        self.run.catch_up();
        self.run.processed - before
    }

    /// The worker's periodic read on through the recording while it owes nothing
    /// ([`LiveSettings::read_on_every`]): the next catch-up starts where it ended. Returns the
    /// frames put through the pipeline (those recorded and not counted as processed).
    pub fn read_on(&mut self) -> u64 {
        let before = self.run.processed;
        self.run.read_recording();
        self.run.processed - before
    }
}

/// One session's line in `scan3d status`: the pipeline's counters, the worker's lag and the
/// edge's time sync.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LiveSessionStatus {
    /// The session id, 16 hex digits (its directory's name).
    pub id: String,
    /// The session's worker was retired (no frame for `retire_after`): the numbers are its
    /// last, and snapshots are served from the products it wrote.
    pub retired: bool,
    /// What the pipeline has built (frames, samples, revolutions, voxels, metrics, positions).
    #[serde(flatten)]
    pub pipeline: SessionStatus,
    /// How long the oldest frame not yet processed has waited, ms (0 when caught up).
    pub lag_ms: u64,
    /// Frames accepted by the recorder and not yet processed.
    pub lag_frames: u64,
    /// The largest `lag_frames` seen.
    pub max_lag_frames: u64,
    /// The largest `lag_ms` seen.
    pub max_lag_ms: u64,
    /// Times the worker read frames back from the recording.
    pub catch_ups: u64,
    /// Frames that found the queue full (each read back from the recording).
    pub queue_overflows: u64,
    /// Owed frames never found in the recording, given up after `give_up_after`.
    pub abandoned: u64,
    /// The edge's clock against the server's, latest estimate.
    pub timesync: Option<TimeSyncStatus>,
    /// CPU time the session's worker thread has used, ms (processing and catching up).
    pub worker_cpu_ms: u64,
    /// Memory of the session's octree (all positions' points in one), bytes.
    pub map_memory_bytes: u64,
    /// How old the newest Sweep sample was when its points reached the octree, over the last
    /// [`LATENCY_WINDOW`] insertions (needs a time-sync estimate).
    pub sample_to_voxel: Option<LatencySummary>,
    /// From the recorder's acceptance of a frame to its points in the octree (the server's
    /// share of [`sample_to_voxel`](Self::sample_to_voxel): queue and processing), frames from
    /// the queue only, over the last [`LATENCY_WINDOW`] insertions.
    pub accept_to_voxel: Option<LatencySummary>,
    /// How long after the end of an RPLidar revolution (its last sample, mapped to server time
    /// by the clock model) the pose matched from it was made, over the last
    /// [`LATENCY_WINDOW`] poses (needs a time-sync estimate): the edge's read and send,
    /// transport, queue, the pose lane's wait for the IMU, and the matcher.
    pub revolution_to_pose: Option<LatencySummary>,
    /// From the recorder's acceptance of an RPLidar revolution to the pose matched from it (the
    /// server's share of [`revolution_to_pose`](Self::revolution_to_pose): queue, the wait for
    /// the IMU, the matcher), revolutions from the queue only.
    pub accept_to_pose: Option<LatencySummary>,
}

/// Insertions [`LiveSessionStatus::sample_to_voxel`] summarises.
pub const LATENCY_WINDOW: usize = 4096;

/// Percentiles of a latency, ms.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LatencySummary {
    /// Insertions measured.
    pub count: usize,
    /// Median, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Largest, ms.
    pub max_ms: f64,
}

impl LatencySummary {
    /// The summary of `latencies_ns` (`None` if empty).
    pub fn of(latencies_ns: &[i64]) -> Option<Self> {
        let mut sorted = latencies_ns.to_vec();
        sorted.sort_unstable();
        let at = |q: f64| {
            let i = ((sorted.len() as f64 - 1.0) * q).round() as usize;
            sorted[i.min(sorted.len() - 1)] as f64 / 1e6
        };
        (!sorted.is_empty()).then(|| LatencySummary {
            count: sorted.len(),
            p50_ms: at(0.5),
            p99_ms: at(0.99),
            max_ms: at(1.0),
        })
    }
}

/// A time-sync estimate as `scan3d status` shows it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TimeSyncStatus {
    /// Edge clock minus server clock, ns.
    pub offset_ns: i64,
    /// Edge clock rate error against the server's, parts per million.
    pub skew_ppm: Option<f64>,
    /// Bound on the offset's error, ns.
    pub error_bound_ns: u64,
}

/// One edge in `scan3d status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EdgeStatus {
    /// The edge's name (its certificate's).
    pub name: String,
    /// Whether it is connected now.
    pub connected: bool,
    /// Its sensors: kind, state, data rate, age of the last data.
    pub sensors: Vec<SensorStatus>,
    /// Its static scans since the daemon started (the newest 64), oldest first.
    pub static_scans: Vec<StaticScanStatus>,
    /// Its sessions the daemon has seen since it started, oldest first.
    pub sessions: Vec<LiveSessionStatus>,
}

/// One static scan in `scan3d status`: its session and progress (position, revolutions, yaw
/// reached, late steps, outcome).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StaticScanStatus {
    /// The session (16 hex digits).
    pub session: String,
    /// Its progress.
    #[serde(flatten)]
    pub progress: ScanProgress,
}

/// The answer to `scan3d status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StatusReport {
    /// Every edge connected now or with a session since the daemon started, by name.
    pub edges: Vec<EdgeStatus>,
}

/// Why a snapshot could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// No session of that edge (or not that one) since the daemon started.
    #[error(
        "no live session{} of edge {edge:?} (known: {known})",
        session.map_or_else(String::new, |id| format!(" {id:016x}"))
    )]
    NoSession {
        /// The edge asked for.
        edge: String,
        /// The session asked for; `None`: any (the latest).
        session: Option<u64>,
        /// The sessions there are, as `edge/session`.
        known: String,
    },
    /// `--session` is not 16 hex digits.
    #[error("session {0:?} is not a session id (16 hex digits)")]
    BadSession(String),
    /// The pipeline could not write (unwritable directory, ...).
    #[error("snapshot of {edge}/{session:016x} into {}: {source}", dir.display())]
    Write {
        /// The edge.
        edge: String,
        /// The session.
        session: u64,
        /// Where it was to go.
        dir: PathBuf,
        /// Why it failed.
        source: PipelineError,
    },
    /// The session's pipeline is not running.
    #[error("session {edge}/{session:016x} has no live products: {reason}")]
    NotRunning {
        /// The edge.
        edge: String,
        /// The session.
        session: u64,
        /// Why.
        reason: String,
    },
    /// The session's worker did not catch up in time.
    #[error(
        "session {edge}/{session:016x} is {lag_frames} frames behind after {waited:?}; try again"
    )]
    Behind {
        /// The edge.
        edge: String,
        /// The session.
        session: u64,
        /// Frames still to process.
        lag_frames: u64,
        /// How long the request waited.
        waited: Duration,
    },
}

/// The live pipelines of every session; cheap to clone. Ingest feeds it
/// ([`IngestSink`]), the control socket asks it for status and snapshots ([`LiveProducts`]).
#[derive(Clone)]
pub struct LivePipelines {
    inner: Arc<Inner>,
}

struct Inner {
    settings: LiveSettings,
    /// The reference map, loaded once for every session.
    reference: Option<Arc<LeafMap>>,
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    /// By `(edge, session)`, in order of first frame.
    workers: Vec<Worker>,
    connected: BTreeSet<String>,
    timesync: HashMap<(String, u64), TimeSyncStatus>,
    /// Per edge: its sensors and static scans, from the frames recorded.
    activity: HashMap<String, EdgeActivity>,
    /// Threads of retired workers, joined at shutdown (finished ones are joined as new ones
    /// come).
    exited: Vec<JoinHandle<()>>,
}

struct Worker {
    edge: String,
    session_id: u64,
    queue: Option<SyncSender<Queued>>,
    shared: Arc<WorkerShared>,
    thread: Option<JoinHandle<()>>,
}

struct Queued {
    frame: Frame,
    accepted_at: Instant,
}

/// A session's pipeline: built on the worker's thread (loading the reference map there, not on
/// ingest's task).
enum Slot {
    Starting,
    Running(Box<SessionPipeline>),
    Failed(String),
    /// The worker wrote its products and exited ([`LiveSettings::retire_after`]).
    Retired(Arc<RetiredProducts>),
}

/// What a retired worker left on disk: the snapshot of its session and of each named position,
/// served (copied) by later snapshot requests.
#[derive(Debug)]
struct RetiredProducts {
    session: Snapshot,
    positions: Vec<Snapshot>,
}

impl RetiredProducts {
    /// Copies the products of the session (`position` `None`) or of one position into `dir`.
    fn copy_into(&self, dir: &Path, position: Option<&str>) -> Result<Snapshot, PipelineError> {
        let written = match position {
            None => &self.session,
            Some(name) => self
                .positions
                .iter()
                .find(|p| p.position.as_deref() == Some(name))
                .ok_or_else(|| PipelineError::UnknownPosition {
                    name: name.to_owned(),
                    known: self
                        .positions
                        .iter()
                        .filter_map(|p| p.position.clone())
                        .collect::<Vec<_>>()
                        .join(", "),
                })?,
        };
        std::fs::create_dir_all(dir).map_err(|source| PipelineError::Write {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut writer = SnapshotWriter::new(dir, position);
        for file in &written.files {
            let relative = file.strip_prefix(&written.dir).unwrap_or(file);
            writer.copy_file(relative, file)?;
        }
        Ok(Snapshot {
            dir: dir.to_path_buf(),
            files: writer.snapshot.files,
            ..written.clone()
        })
    }
}

/// What a worker last published for `status` ([`WorkerRun::publish`]): computed on the
/// worker's thread, so a status request never waits for the pipeline.
#[derive(Debug)]
struct Published {
    pipeline: SessionStatus,
    map_memory_bytes: u64,
}

/// For this long after a status request, a worker refreshes its metrics as often as
/// [`super::METRICS_INTERVAL`] allows while frames come (when idle it does anyway).
const STATUS_INTEREST: Duration = Duration::from_secs(10);

impl Slot {
    fn running(&mut self) -> Option<&mut SessionPipeline> {
        match self {
            Slot::Running(pipeline) => Some(pipeline),
            Slot::Starting | Slot::Failed(_) | Slot::Retired(_) => None,
        }
    }
}

/// What a worker shares with ingest (counters) and the control socket (pipeline, progress).
struct WorkerShared {
    edge: String,
    session_id: u64,
    /// Frames handed to the driver.
    accepted: AtomicU64,
    /// Of those, frames that found the queue full.
    overflowed: AtomicU64,
    /// Their seqs, for the worker to read back.
    missed: Mutex<Vec<u64>>,
    /// When each frame now in the queue was accepted, oldest first (the lag is the front's age).
    waiting: Mutex<std::collections::VecDeque<Instant>>,
    pipeline: Mutex<Slot>,
    progress: Mutex<Progress>,
    /// The session's latest edge → server clock model (time sync).
    clock: Mutex<Option<ClockModel>>,
    /// Every model of the session so far (the snapshot's trajectory is stamped through them).
    clock_models: Mutex<crate::pose::timesync::SessionClock>,
    /// Sample-to-voxel latencies, ns, the last [`LATENCY_WINDOW`].
    latencies: Mutex<std::collections::VecDeque<i64>>,
    /// Accept-to-voxel latencies, ns, the last [`LATENCY_WINDOW`].
    server_latencies: Mutex<std::collections::VecDeque<i64>>,
    /// Revolution-to-pose latencies, ns, the last [`LATENCY_WINDOW`].
    pose_latencies: Mutex<std::collections::VecDeque<i64>>,
    /// Accept-to-pose latencies, ns, the last [`LATENCY_WINDOW`].
    pose_server_latencies: Mutex<std::collections::VecDeque<i64>>,
    /// What `status` shows of the pipeline (`None` until it is built).
    published: Mutex<Option<Arc<Published>>>,
    /// When `status` last asked.
    status_asked: Mutex<Option<Instant>>,
    /// Whether the worker is retired. Ingest counts a frame in `accepted` before it looks here
    /// and the worker retires only with every accepted frame taken, both under this lock: a
    /// frame is either taken by the worker or revives the session.
    retired: Mutex<bool>,
}

/// Appends `latency_ns` to a window of at most [`LATENCY_WINDOW`].
fn push_latency(window: &Mutex<std::collections::VecDeque<i64>>, latency_ns: i64) {
    let mut window = lock(window);
    if window.len() == LATENCY_WINDOW {
        window.pop_front();
    }
    window.push_back(latency_ns);
}

#[derive(Debug, Default)]
struct Progress {
    /// Frames taken out of the queue.
    received: u64,
    owed: u64,
    behind_since: Option<Instant>,
    max_lag_frames: u64,
    max_lag_ms: u64,
    catch_ups: u64,
    abandoned: u64,
    /// The worker thread's CPU time, ns.
    cpu_ns: u64,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

impl WorkerShared {
    /// The shared state of a new worker of `edge`'s session `session_id`.
    fn new(edge: &str, session_id: u64) -> Self {
        WorkerShared {
            edge: edge.to_owned(),
            session_id,
            accepted: AtomicU64::new(0),
            overflowed: AtomicU64::new(0),
            missed: Mutex::new(Vec::new()),
            waiting: Mutex::new(std::collections::VecDeque::new()),
            pipeline: Mutex::new(Slot::Starting),
            progress: Mutex::new(Progress::default()),
            clock: Mutex::new(None),
            clock_models: Mutex::new(crate::pose::timesync::SessionClock::new()),
            latencies: Mutex::new(std::collections::VecDeque::with_capacity(LATENCY_WINDOW)),
            server_latencies: Mutex::new(std::collections::VecDeque::with_capacity(LATENCY_WINDOW)),
            pose_latencies: Mutex::new(std::collections::VecDeque::with_capacity(LATENCY_WINDOW)),
            pose_server_latencies: Mutex::new(std::collections::VecDeque::with_capacity(
                LATENCY_WINDOW,
            )),
            published: Mutex::new(None),
            status_asked: Mutex::new(None),
            retired: Mutex::new(false),
        }
    }

    /// A new worker's shared state for the session `self` retired from: the time sync and the
    /// last status carry over.
    fn revived(&self) -> Self {
        let shared = WorkerShared::new(&self.edge, self.session_id);
        *lock(&shared.clock) = *lock(&self.clock);
        *lock(&shared.clock_models) = lock(&self.clock_models).clone();
        *lock(&shared.published) = lock(&self.published).clone();
        shared
    }

    /// `(lag_frames, lag_ms)` now.
    fn lag(&self) -> (u64, u64) {
        let accepted = self.accepted.load(Ordering::Acquire);
        let overflowed = self.overflowed.load(Ordering::Acquire);
        let missed = lock(&self.missed).len() as u64;
        let progress = lock(&self.progress);
        let queued = accepted.saturating_sub(overflowed + progress.received);
        let frames = queued + progress.owed + missed;
        let behind = progress
            .behind_since
            .map_or(Duration::ZERO, |since| since.elapsed());
        drop(progress);
        let oldest_waiting = lock(&self.waiting)
            .front()
            .map_or(Duration::ZERO, Instant::elapsed);
        let ms = if frames == 0 {
            0
        } else {
            behind.max(oldest_waiting).as_millis() as u64
        };
        (frames, ms)
    }

    fn note_lag(&self) {
        let (frames, ms) = self.lag();
        let mut progress = lock(&self.progress);
        progress.max_lag_frames = progress.max_lag_frames.max(frames);
        progress.max_lag_ms = progress.max_lag_ms.max(ms);
    }

    /// After a catch-up that began owing at `owed_since`: the oldest owed frame waited at least
    /// that long before it was processed (or given up), so the largest lag is at least that,
    /// although the lag is 0 again once the catch-up is over.
    fn note_caught_up(&self, owed_since: Instant) {
        let waited = owed_since.elapsed().as_millis() as u64;
        let mut progress = lock(&self.progress);
        progress.max_lag_ms = progress.max_lag_ms.max(waited);
    }
}

impl LivePipelines {
    /// Checks the settings by building one pipeline (a reference map that cannot be read or
    /// has another resolution fails here, at start) and makes an empty driver.
    pub fn new(settings: LiveSettings) -> Result<Self, PipelineError> {
        let res = Resolution::new(settings.pipeline.resolution_m)?;
        let reference = match &settings.pipeline.reference {
            Some(path) => Some(Arc::new(load_reference(path, &res)?)),
            None => None,
        };
        SessionPipeline::with_reference(
            &settings.pipeline,
            Products::default(),
            reference.clone(),
        )?;
        Ok(LivePipelines {
            inner: Arc::new(Inner {
                settings,
                reference,
                state: Mutex::new(State::default()),
            }),
        })
    }

    /// Takes one event from ingest; never blocks on processing.
    pub fn on_event(&self, event: IngestEvent) {
        match event {
            IngestEvent::Frame { edge, frame } => self.on_frame(&edge, frame),
            IngestEvent::Connected { edge, .. } => {
                lock(&self.inner.state).connected.insert(edge);
            }
            IngestEvent::Disconnected { edge, .. } => {
                lock(&self.inner.state).connected.remove(&edge);
            }
            IngestEvent::TimeSync {
                edge,
                session_id,
                model,
            } => {
                let status = TimeSyncStatus {
                    offset_ns: model.offset_ns,
                    skew_ppm: Some(model.skew_ppm),
                    error_bound_ns: model.error_bound_ns,
                };
                let mut state = lock(&self.inner.state);
                if let Some(worker) = state
                    .workers
                    .iter()
                    .find(|w| w.edge == edge && w.session_id == session_id)
                {
                    *lock(&worker.shared.clock) = Some(model);
                    lock(&worker.shared.clock_models).push(model);
                }
                state.timesync.insert((edge, session_id), status);
            }
        }
    }

    fn on_frame(&self, edge: &str, frame: Frame) {
        let (queue, shared) = {
            let mut state = lock(&self.inner.state);
            match state.activity.get_mut(edge) {
                Some(activity) => activity.on_body(frame.session_id, &frame.body, Instant::now()),
                None => {
                    let mut activity = EdgeActivity::default();
                    activity.on_body(frame.session_id, &frame.body, Instant::now());
                    state.activity.insert(edge.to_owned(), activity);
                }
            }
            let index = match state
                .workers
                .iter()
                .position(|w| w.edge == edge && w.session_id == frame.session_id)
            {
                Some(index) => index,
                None => match self.spawn(edge, WorkerShared::new(edge, frame.session_id)) {
                    Ok(worker) => {
                        state.workers.push(worker);
                        state.workers.len() - 1
                    }
                    Err(e) => {
                        tracing::error!(%edge, session = format!("{:016x}", frame.session_id), error = %e,
                            "cannot start the session's pipeline; the session is recorded only");
                        return;
                    }
                },
            };
            // Counted before the retired check (see `WorkerShared::retired`).
            let shared = state.workers[index].shared.clone();
            shared.accepted.fetch_add(1, Ordering::AcqRel);
            if *lock(&shared.retired) {
                shared.accepted.fetch_sub(1, Ordering::AcqRel);
                // A frame of a retired session: a new worker rebuilds it from the recording
                // (its first frame is out of sequence, so it catches up from the start).
                match self.spawn(edge, shared.revived()) {
                    Ok(worker) => {
                        tracing::info!(%edge, session = format!("{:016x}", frame.session_id),
                            "a frame of a retired session; its pipeline is rebuilt from the recording");
                        let old = std::mem::replace(&mut state.workers[index], worker);
                        state.exited.retain(|thread| !thread.is_finished());
                        state.exited.extend(old.thread);
                        state.workers[index]
                            .shared
                            .accepted
                            .fetch_add(1, Ordering::AcqRel);
                    }
                    Err(e) => {
                        tracing::error!(%edge, session = format!("{:016x}", frame.session_id), error = %e,
                            "cannot restart the retired session's pipeline; the frame is recorded only");
                        return;
                    }
                }
            }
            let worker = &state.workers[index];
            (worker.queue.clone(), worker.shared.clone())
        };
        let Some(queue) = queue else { return };
        let seq = frame.seq;
        let accepted_at = Instant::now();
        let queued = Queued { frame, accepted_at };
        // Listed before the send, so the worker never takes a frame that is not listed.
        lock(&shared.waiting).push_back(accepted_at);
        let sent = queue.try_send(queued);
        if sent.is_err() {
            lock(&shared.waiting).pop_back();
        }
        match sent {
            Ok(()) => {}
            // The worker is gone (its pipeline could not be built, logged): recording only.
            Err(TrySendError::Disconnected(_)) => {
                shared.accepted.fetch_sub(1, Ordering::AcqRel);
            }
            Err(TrySendError::Full(_)) => {
                lock(&shared.missed).push(seq);
                shared.overflowed.fetch_add(1, Ordering::AcqRel);
            }
        }
    }

    fn spawn(&self, edge: &str, shared: WorkerShared) -> std::io::Result<Worker> {
        // The pipeline itself is built on the worker's thread.
        let settings = &self.inner.settings;
        let session_id = shared.session_id;
        let shared = Arc::new(shared);
        let (queue, frames) = std::sync::mpsc::sync_channel(settings.queue_frames.max(1));
        let mut run = WorkerRun::new(shared.clone(), frames, settings);
        run.reference = self.inner.reference.clone();
        let thread = std::thread::Builder::new()
            .name(format!("pipeline {edge}/{session_id:016x}"))
            .spawn(move || run.run())?;
        tracing::info!(%edge, session = format!("{session_id:016x}"), "live pipeline started");
        Ok(Worker {
            edge: edge.to_owned(),
            session_id,
            queue: Some(queue),
            shared,
            thread: Some(thread),
        })
    }

    /// Every edge and session: counters, lag, time sync, metrics.
    pub fn status(&self) -> StatusReport {
        let now = Instant::now();
        let (workers, connected, timesync, activity) = {
            let state = lock(&self.inner.state);
            let workers: Vec<Arc<WorkerShared>> =
                state.workers.iter().map(|w| w.shared.clone()).collect();
            let activity: HashMap<String, (Vec<SensorStatus>, Vec<StaticScanStatus>)> = state
                .activity
                .iter()
                .map(|(edge, activity)| {
                    let scans = activity
                        .scans()
                        .into_iter()
                        .map(|(session, progress)| StaticScanStatus {
                            session: format!("{session:016x}"),
                            progress,
                        })
                        .collect();
                    let sensors = activity.sensors(now, state.connected.contains(edge));
                    (edge.clone(), (sensors, scans))
                })
                .collect();
            (
                workers,
                state.connected.clone(),
                state.timesync.clone(),
                activity,
            )
        };
        let edge_status = |name: &str, connected: bool| {
            let (sensors, static_scans) = activity.get(name).cloned().unwrap_or_default();
            EdgeStatus {
                name: name.to_owned(),
                connected,
                sensors,
                static_scans,
                sessions: Vec::new(),
            }
        };
        let mut edges: Vec<EdgeStatus> = connected
            .iter()
            .map(|name| edge_status(name, true))
            .collect();
        for shared in workers {
            // Not built yet (a few ms) or failed (logged): no line.
            let Some(published) = lock(&shared.published).clone() else {
                continue;
            };
            *lock(&shared.status_asked) = Some(now);
            let retired = *lock(&shared.retired);
            let (lag_frames, lag_ms) = shared.lag();
            let progress = lock(&shared.progress);
            let session = LiveSessionStatus {
                id: format!("{:016x}", shared.session_id),
                retired,
                pipeline: published.pipeline.clone(),
                lag_ms,
                lag_frames,
                max_lag_frames: progress.max_lag_frames.max(lag_frames),
                max_lag_ms: progress.max_lag_ms.max(lag_ms),
                catch_ups: progress.catch_ups,
                queue_overflows: shared.overflowed.load(Ordering::Acquire),
                abandoned: progress.abandoned,
                worker_cpu_ms: progress.cpu_ns / 1_000_000,
                map_memory_bytes: published.map_memory_bytes,
                timesync: timesync
                    .get(&(shared.edge.clone(), shared.session_id))
                    .copied(),
                sample_to_voxel: LatencySummary::of(lock(&shared.latencies).make_contiguous()),
                accept_to_voxel: LatencySummary::of(
                    lock(&shared.server_latencies).make_contiguous(),
                ),
                revolution_to_pose: LatencySummary::of(
                    lock(&shared.pose_latencies).make_contiguous(),
                ),
                accept_to_pose: LatencySummary::of(
                    lock(&shared.pose_server_latencies).make_contiguous(),
                ),
            };
            match edges.iter_mut().find(|e| e.name == shared.edge) {
                Some(edge) => edge.sessions.push(session),
                None => edges.push(EdgeStatus {
                    sessions: vec![session],
                    ..edge_status(&shared.edge, connected.contains(&shared.edge))
                }),
            }
        }
        edges.sort_by(|a, b| a.name.cmp(&b.name));
        StatusReport { edges }
    }

    /// Writes the products of `edge`'s session (`session`, 16 hex digits, or its latest) into
    /// `dir`, once the session's worker has caught up with what was accepted so far.
    pub fn snapshot(
        &self,
        edge: &str,
        session: Option<&str>,
        position: Option<&str>,
        dir: &Path,
    ) -> Result<(u64, Snapshot), LiveError> {
        let wanted = session
            .map(|s| u64::from_str_radix(s, 16).map_err(|_| LiveError::BadSession(s.to_owned())))
            .transpose()?;
        let shared = {
            let state = lock(&self.inner.state);
            let found = state
                .workers
                .iter()
                .rev()
                .find(|w| w.edge == edge && wanted.is_none_or(|id| id == w.session_id));
            match found {
                Some(worker) => worker.shared.clone(),
                None => {
                    let known: Vec<String> = state
                        .workers
                        .iter()
                        .map(|w| format!("{}/{:016x}", w.edge, w.session_id))
                        .collect();
                    return Err(LiveError::NoSession {
                        edge: edge.to_owned(),
                        session: wanted,
                        known: if known.is_empty() {
                            "none".into()
                        } else {
                            known.join(", ")
                        },
                    });
                }
            }
        };
        if let Slot::Failed(reason) = &*lock(&shared.pipeline) {
            return Err(LiveError::NotRunning {
                edge: edge.to_owned(),
                session: shared.session_id,
                reason: reason.clone(),
            });
        }
        let started = Instant::now();
        loop {
            let (lag_frames, _) = shared.lag();
            if lag_frames == 0 {
                break;
            }
            let waited = started.elapsed();
            if waited >= self.inner.settings.snapshot_wait {
                return Err(LiveError::Behind {
                    edge: edge.to_owned(),
                    session: shared.session_id,
                    lag_frames,
                    waited,
                });
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let not_running = |reason: String| LiveError::NotRunning {
            edge: edge.to_owned(),
            session: shared.session_id,
            reason,
        };
        let failed = |source| LiveError::Write {
            edge: edge.to_owned(),
            session: shared.session_id,
            dir: dir.to_path_buf(),
            source,
        };
        // Only the copies are taken under the pipeline; the files are written without it.
        let prepared = {
            let mut slot = lock(&shared.pipeline);
            match &mut *slot {
                Slot::Running(pipeline) => {
                    pipeline.set_clock(lock(&shared.clock_models).clone());
                    pipeline.prepare_snapshot(dir, position).map_err(failed)?
                }
                Slot::Retired(products) => {
                    let products = Arc::clone(products);
                    drop(slot);
                    let snapshot = products.copy_into(dir, position).map_err(failed)?;
                    return Ok((shared.session_id, snapshot));
                }
                Slot::Starting => return Err(not_running("its pipeline is still starting".into())),
                Slot::Failed(reason) => return Err(not_running(reason.clone())),
            }
        };
        let snapshot = prepared.write().map_err(failed)?;
        Ok((shared.session_id, snapshot))
    }

    /// Stops every worker after it has processed what it was given (and read back what it
    /// owes, within `give_up_after`).
    pub fn shutdown(&self) {
        let (workers, mut threads) = {
            let mut state = lock(&self.inner.state);
            (
                std::mem::take(&mut state.workers),
                std::mem::take(&mut state.exited),
            )
        };
        // Every worker is told at once (its queue closes); then one deadline for them all.
        for mut worker in workers {
            worker.queue = None;
            threads.extend(worker.thread.take());
        }
        let deadline = Instant::now() + self.inner.settings.shutdown_wait;
        while threads.iter().any(|thread| !thread.is_finished()) && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(10));
        }
        let (finished, running): (Vec<_>, Vec<_>) =
            threads.into_iter().partition(JoinHandle::is_finished);
        for thread in finished {
            let _ = thread.join();
        }
        if !running.is_empty() {
            tracing::warn!(workers = running.len(), waited = ?self.inner.settings.shutdown_wait,
                "session workers still catching up at shutdown; left to end with the process");
        }
    }
}

impl IngestSink for LivePipelines {
    fn on_event(&self, event: IngestEvent) {
        LivePipelines::on_event(self, event);
    }
}

impl LiveProducts for LivePipelines {
    fn answer(&self, request: &ProductRequest) -> ControlReply {
        match request {
            ProductRequest::Status => {
                let status = self.status();
                ControlReply {
                    ok: true,
                    detail: format!("{} edge(s)", status.edges.len()),
                    data: serde_json::to_value(&status).ok(),
                }
            }
            ProductRequest::Snapshot {
                edge,
                session,
                position,
                out,
            } => match self.snapshot(edge, session.as_deref(), position.as_deref(), out) {
                Ok((session_id, snapshot)) => ControlReply {
                    ok: true,
                    detail: format!(
                        "wrote the products of {edge}/{session_id:016x} into {}",
                        out.display()
                    ),
                    data: serde_json::to_value(&snapshot).ok(),
                },
                Err(e) => ControlReply {
                    ok: false,
                    detail: e.to_string(),
                    data: None,
                },
            },
        }
    }
}

/// The calling thread's CPU time, ns (0 if the clock cannot be read, which Linux never does).
fn thread_cpu_ns() -> u64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map(|t| u64::try_from(Duration::from(t).as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// A worker thread's state.
struct WorkerRun {
    shared: Arc<WorkerShared>,
    frames: Receiver<Queued>,
    sequencer: Sequencer,
    session_dir: PathBuf,
    snapshot_dir: PathBuf,
    settings: LiveSettings,
    /// The reference map shared by every session (`None`: none configured, or a pipeline
    /// built alone that reads its own).
    reference: Option<Arc<LeafMap>>,
    /// Frames processed since the last periodic snapshot.
    changed: bool,
    last_snapshot: Instant,
    /// `(start, end)` edge times (ns) of the latest Sweep revolutions processed, oldest first.
    recent_sweeps: std::collections::VecDeque<(u64, u64)>,
    /// `(start, end)` edge times (ns) of the latest RPLidar revolutions processed, oldest first.
    recent_rplidar: std::collections::VecDeque<RecentRevolution>,
    /// Frames put through the pipeline.
    processed: u64,
    /// Frames taken from the queue since the last [`WorkerRun::publish`] (they count in the
    /// lag until their effect is published).
    taken: u64,
    /// When the worker last took or processed a frame (the retirement clock).
    last_activity: Instant,
    /// Where the last catch-up's read of the recording ended: every record before it is
    /// processed, so the next catch-up reads on from there, not from the start of the file
    /// holding the first frame owed.
    read_to: Option<ReadPosition>,
    /// When the worker last read the recording.
    last_read: Instant,
}

impl WorkerRun {
    /// A worker taking `shared`'s session's frames from `frames`.
    fn new(shared: Arc<WorkerShared>, frames: Receiver<Queued>, settings: &LiveSettings) -> Self {
        let (edge, session_id) = (&shared.edge, shared.session_id);
        WorkerRun {
            session_dir: session_dir(&settings.data_dir, edge, session_id),
            snapshot_dir: settings
                .data_dir
                .join("snapshots")
                .join(edge)
                .join(format!("{session_id:016x}")),
            shared,
            frames,
            sequencer: Sequencer::default(),
            settings: settings.clone(),
            reference: None,
            changed: false,
            last_snapshot: Instant::now(),
            recent_sweeps: std::collections::VecDeque::with_capacity(RECENT_SWEEPS),
            recent_rplidar: std::collections::VecDeque::with_capacity(RECENT_SWEEPS),
            processed: 0,
            taken: 0,
            last_activity: Instant::now(),
            read_to: None,
            last_read: Instant::now(),
        }
    }
}

/// Sweep revolutions [`WorkerRun`] remembers to date the static-scan samples that refer to them.
const RECENT_SWEEPS: usize = 16;

/// An RPLidar revolution the worker processed lately: its span on the edge clock, and when the
/// recorder accepted it (`None`: read from the recording), for the pose latencies.
struct RecentRevolution {
    t0_ns: u64,
    t1_ns: u64,
    accepted_at: Option<Instant>,
}

/// Whether [`WorkerRun::publish`] recomputes the metrics first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Refresh {
    /// No: the counters only.
    No,
    /// If the map grew and the last computation is [`super::METRICS_INTERVAL`] old.
    Due,
    /// If the map grew.
    Now,
}

impl WorkerRun {
    fn run(mut self) {
        let built = match &self.reference {
            Some(reference) => SessionPipeline::with_reference(
                &self.settings.pipeline,
                Products::default(),
                Some(Arc::clone(reference)),
            ),
            None => SessionPipeline::new(&self.settings.pipeline),
        };
        match built {
            Ok(pipeline) => *lock(&self.shared.pipeline) = Slot::Running(Box::new(pipeline)),
            Err(e) => {
                tracing::error!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
                    error = %e, "cannot build the session's pipeline; the session is recorded only");
                *lock(&self.shared.pipeline) = Slot::Failed(e.to_string());
                *lock(&self.shared.published) = None;
                return;
            }
        }
        self.publish(Refresh::No);
        let mut owed_since: Option<Instant> = None;
        let mut last_catch_up: Option<Instant> = None;
        let mut open = true;
        loop {
            for seq in std::mem::take(&mut *lock(&self.shared.missed)) {
                self.sequencer.owe(seq);
            }
            let due = last_catch_up.is_none_or(|at| at.elapsed() >= self.settings.catch_up_retry);
            if self.sequencer.owed() > 0 && due {
                let since = *owed_since.get_or_insert_with(Instant::now);
                self.set_owed(Some(since));
                self.shared.note_lag();
                last_catch_up = Some(Instant::now());
                self.catch_up();
                self.shared.note_caught_up(since);
                if self.sequencer.owed() == 0 {
                    owed_since = None;
                } else if since.elapsed() >= self.settings.give_up_after {
                    let lost = self.sequencer.forgive();
                    tracing::error!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
                        frames = lost.len(), first = lost.first().copied(), last = lost.last().copied(),
                        "accepted frames never appeared in the recording; the live products lack them");
                    lock(&self.shared.progress).abandoned += lost.len() as u64;
                    owed_since = None;
                }
            } else if self.sequencer.owed() > 0 {
                owed_since.get_or_insert_with(Instant::now);
            }
            self.set_owed(owed_since);
            if !open && self.sequencer.owed() == 0 {
                break;
            }
            if self.sequencer.owed() == 0
                && self
                    .settings
                    .read_on_every
                    .is_some_and(|every| self.last_read.elapsed() >= every)
            {
                self.read_recording();
            }
            if open
                && self.sequencer.owed() == 0
                && self
                    .settings
                    .retire_after
                    .is_some_and(|after| self.last_activity.elapsed() >= after)
            {
                if self.retire() {
                    return;
                }
                // A frame came meanwhile, or the products could not be written: go on, and try
                // again after another idle period.
                self.last_activity = Instant::now();
            }
            let wait = if self.sequencer.owed() > 0 || !open {
                self.settings.catch_up_retry
            } else {
                let mut wait = self.settings.catch_up_retry;
                if let Some(every) = self.settings.snapshot_every {
                    wait = wait.min(every.saturating_sub(self.last_snapshot.elapsed()));
                }
                if let Some(after) = self.settings.retire_after {
                    wait = wait.min(after.saturating_sub(self.last_activity.elapsed()));
                }
                wait
            };
            let mut idle = false;
            if open {
                match self.frames.recv_timeout(wait) {
                    Ok(queued) => {
                        self.take(queued);
                        while let Ok(queued) = self.frames.try_recv() {
                            self.take(queued);
                        }
                    }
                    Err(RecvTimeoutError::Timeout) => idle = true,
                    Err(RecvTimeoutError::Disconnected) => open = false,
                }
            } else {
                std::thread::sleep(wait);
            }
            // While frames come, the metrics are recomputed only for someone who asks; idle,
            // the worker brings them up to date once.
            let asked =
                lock(&self.shared.status_asked).is_some_and(|at| at.elapsed() < STATUS_INTEREST);
            self.publish(if idle || asked {
                Refresh::Due
            } else {
                Refresh::No
            });
            self.periodic_snapshot();
            lock(&self.shared.progress).cpu_ns = thread_cpu_ns();
        }
        self.publish(Refresh::Now);
        self.periodic_snapshot_now();
    }

    /// Publishes what `status` shows (the pipeline's counters, refreshed as `refresh` says)
    /// and counts the frames taken since the last time as received.
    fn publish(&mut self, refresh: Refresh) {
        let published = {
            let mut slot = lock(&self.shared.pipeline);
            let Some(pipeline) = slot.running() else {
                return;
            };
            match refresh {
                Refresh::No => {}
                Refresh::Due => pipeline.refresh_metrics(Instant::now(), false),
                Refresh::Now => pipeline.refresh_metrics(Instant::now(), true),
            }
            Published {
                pipeline: pipeline.current_status(),
                map_memory_bytes: pipeline.maps().session_map().memory_bytes() as u64,
            }
        };
        *lock(&self.shared.published) = Some(Arc::new(published));
        lock(&self.shared.progress).received += std::mem::take(&mut self.taken);
        self.shared.note_lag();
    }

    /// Where a retired worker leaves its products: `data_dir/retired/<edge>/<session>/`.
    fn retired_dir(&self) -> PathBuf {
        self.settings
            .data_dir
            .join("retired")
            .join(&self.shared.edge)
            .join(format!("{:016x}", self.shared.session_id))
    }

    /// Writes the products (the session's and each position's, under
    /// [`WorkerRun::retired_dir`]; positions in `positions/<n>/` by first-seen order) and the
    /// final status, then frees the pipeline, unless a frame came meanwhile. Returns whether
    /// the worker is retired (and must exit).
    fn retire(&mut self) -> bool {
        let dir = self.retired_dir();
        let prepared = {
            let mut slot = lock(&self.shared.pipeline);
            let Some(pipeline) = slot.running() else {
                return false;
            };
            pipeline.set_clock(lock(&self.shared.clock_models).clone());
            let positions = pipeline.positions();
            let mut prepared = vec![pipeline.prepare_snapshot(&dir, None)];
            for (index, name) in positions.iter().enumerate() {
                let position_dir = dir.join("positions").join(index.to_string());
                prepared.push(pipeline.prepare_snapshot(&position_dir, Some(name)));
            }
            prepared
        };
        let written: Result<Vec<Snapshot>, PipelineError> = prepared
            .into_iter()
            .map(|prepared| prepared.and_then(PreparedSnapshot::write))
            .collect();
        let mut written = match written {
            Ok(written) => written,
            Err(e) => {
                tracing::error!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
                    dir = %dir.display(), error = %e, "cannot write the idle session's products; its worker stays");
                return false;
            }
        };
        self.publish(Refresh::Now);
        self.periodic_snapshot_now();
        let session = written.remove(0);
        let products = RetiredProducts {
            session,
            positions: written,
        };
        let mut retired = lock(&self.shared.retired);
        let accepted = self.shared.accepted.load(Ordering::Acquire);
        let overflowed = self.shared.overflowed.load(Ordering::Acquire);
        let received = lock(&self.shared.progress).received;
        if accepted != overflowed + received || !lock(&self.shared.missed).is_empty() {
            return false;
        }
        *retired = true;
        let pipeline = std::mem::replace(
            &mut *lock(&self.shared.pipeline),
            Slot::Retired(Arc::new(products)),
        );
        drop(retired);
        // Its maps and cloud are freed here, with no lock held.
        drop(pipeline);
        tracing::info!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
            dir = %dir.display(), idle = ?self.last_activity.elapsed(),
            "idle session retired: its products are on disk and its maps freed");
        true
    }

    fn set_owed(&self, since: Option<Instant>) {
        let mut progress = lock(&self.shared.progress);
        progress.owed = self.sequencer.owed() as u64;
        progress.behind_since = since;
    }

    /// A frame from the queue.
    fn take(&mut self, queued: Queued) {
        lock(&self.shared.waiting).pop_front();
        self.taken += 1;
        self.last_activity = Instant::now();
        match self.sequencer.offer(queued.frame.seq) {
            Offer::Process => self.process(&queued.frame, Some(queued.accepted_at)),
            Offer::Skip => {}
            Offer::Owe => {
                lock(&self.shared.progress).owed = self.sequencer.owed() as u64;
            }
        }
    }

    /// Puts one frame through the pipeline; `accepted_at`: when the recorder accepted it, for
    /// a frame from the queue.
    fn process(&mut self, frame: &Frame, accepted_at: Option<Instant>) {
        if frame.body.is_server_made() {
            return;
        }
        if let Body::Revolution(rev) = &frame.body
            && rev.sensor == SensorId::SWEEP
        {
            if self.recent_sweeps.len() == RECENT_SWEEPS {
                self.recent_sweeps.pop_front();
            }
            self.recent_sweeps.push_back((rev.t0_ns, rev.t1_ns));
        }
        if let Body::Revolution(rev) = &frame.body
            && rev.sensor == SensorId::RPLIDAR
        {
            if self.recent_rplidar.len() == RECENT_SWEEPS {
                self.recent_rplidar.pop_front();
            }
            self.recent_rplidar.push_back(RecentRevolution {
                t0_ns: rev.t0_ns,
                t1_ns: rev.t1_ns,
                accepted_at,
            });
        }
        let (grew, new_pose_s) = {
            let mut slot = lock(&self.shared.pipeline);
            let Some(pipeline) = slot.running() else {
                return;
            };
            let before = pipeline.maps().points();
            let poses_before = pipeline.pose().map_or(0, |stage| stage.poses().len());
            pipeline.on_frame(frame);
            let newest_pose = pipeline
                .pose()
                .filter(|stage| stage.poses().len() > poses_before)
                .and_then(|stage| stage.poses().last())
                .map(|pose| pose.timestamp.seconds);
            (pipeline.maps().points() > before, newest_pose)
        };
        self.changed = true;
        self.processed += 1;
        // Sample-to-voxel latency: the age of the newest sample whose points this frame put into
        // the octree (the end of its Sweep revolution, mapped to server time by the session's
        // clock model; the server's time-sync clock is UNIX time at start plus monotonic time).
        let clock = *lock(&self.shared.clock);
        if grew && let (Some(edge_ns), Some(clock)) = (self.newest_inserted_ns(frame), clock) {
            let sample_server_ns = i128::from(clock.to_server_ns(edge_ns));
            let latency = i128::from(unix_now_ns()) - sample_server_ns;
            let latency = latency.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
            push_latency(&self.shared.latencies, latency);
        }
        if grew && let Some(accepted_at) = accepted_at {
            let latency = i64::try_from(accepted_at.elapsed().as_nanos()).unwrap_or(i64::MAX);
            push_latency(&self.shared.server_latencies, latency);
        }
        // Revolution-to-pose latency, for frames from the queue only (a catch-up's are as old
        // as the gap it fills): from the end of the revolution the newest pose was matched
        // from (the one whose span holds the pose's time) to now.
        if let (Some(pose_s), Some(clock), Some(_)) = (new_pose_s, clock, accepted_at) {
            let pose_ns = super::pose_stage::edge_ns(pose_s);
            if let Some(revolution) = self
                .recent_rplidar
                .iter()
                .rev()
                .find(|r| r.t0_ns <= pose_ns && pose_ns <= r.t1_ns)
            {
                let end_server_ns = clock.to_server_ns(revolution.t1_ns);
                let latency = i128::from(unix_now_ns()) - i128::from(end_server_ns);
                let latency = latency.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
                push_latency(&self.shared.pose_latencies, latency);
                if let Some(accepted_at) = revolution.accepted_at {
                    let latency =
                        i64::try_from(accepted_at.elapsed().as_nanos()).unwrap_or(i64::MAX);
                    push_latency(&self.shared.pose_server_latencies, latency);
                }
            }
        }
    }

    /// Edge time of the newest sample `frame` inserted: the end of the Sweep revolution its
    /// static-scan yaws refer to, else of the latest Sweep revolution.
    fn newest_inserted_ns(&self, frame: &Frame) -> Option<u64> {
        let latest = self.recent_sweeps.back().map(|&(_, t1)| t1);
        match &frame.body {
            Body::StaticScan(StaticScan::Yaws(yaws)) => self
                .recent_sweeps
                .iter()
                .rev()
                .find(|&&(t0, _)| t0 == yaws.revolution_t0_ns)
                .map(|&(_, t1)| t1)
                .or(latest),
            Body::Revolution(rev) if rev.sensor == SensorId::SWEEP => Some(rev.t1_ns),
            _ => latest,
        }
    }

    /// Reads the recording and processes, in its order, every frame not processed yet.
    fn catch_up(&mut self) {
        lock(&self.shared.progress).catch_ups += 1;
        self.read_recording();
    }

    /// Reads the recording on from where the last read ended (or from the file holding the
    /// first frame not processed) and processes, in its order, every frame not processed yet.
    fn read_recording(&mut self) {
        self.last_read = Instant::now();
        let processed = self.processed;
        let session_dir = self.session_dir.clone();
        let from = self.sequencer.resume_from();
        let mut reader = SessionReader::new(&session_dir).from_seq(from);
        if let Some(position) = self.read_to.clone() {
            reader = reader.resume_at(position);
        }
        let visited = reader.visit(|record| {
            match record {
                // Server-made frames (commands) number separately; no map data.
                SessionRecord::Frame(recorded) => {
                    if !recorded.frame.body.is_server_made()
                        && self.sequencer.from_recording(recorded.frame.seq)
                    {
                        self.process(&recorded.frame, None);
                    }
                }
                // Recorded raw (a body this server cannot decode): its seq is no gap.
                SessionRecord::Undecodable(frame) => {
                    if self.sequencer.from_recording(frame.seq)
                        && let Some(pipeline) = lock(&self.shared.pipeline).running()
                    {
                        pipeline.on_undecodable(frame.seq);
                    }
                }
                // Clock models and other server records reach the worker through ingest.
                SessionRecord::Server(_) => {}
            }
            Ok(())
        });
        if self.processed > processed {
            self.last_activity = Instant::now();
        }
        match visited {
            Ok(report) => {
                self.read_to.clone_from(&report.end);
                if let Some(line) = report.loss_line() {
                    tracing::warn!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
                        "{line}; catching up from what is readable");
                }
            }
            Err(e) => {
                tracing::warn!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
                    error = %e, "cannot read the recording to catch up; retrying");
            }
        }
    }

    fn periodic_snapshot(&mut self) {
        if let Some(every) = self.settings.snapshot_every
            && self.last_snapshot.elapsed() >= every
        {
            self.periodic_snapshot_now();
        }
    }

    fn periodic_snapshot_now(&mut self) {
        if self.settings.snapshot_every.is_none() || !self.changed {
            return;
        }
        self.last_snapshot = Instant::now();
        self.changed = false;
        let prepared = {
            let mut slot = lock(&self.shared.pipeline);
            let Some(pipeline) = slot.running() else {
                return;
            };
            pipeline.set_clock(lock(&self.shared.clock_models).clone());
            pipeline.prepare_snapshot(&self.snapshot_dir, None)
        };
        if let Err(e) = prepared.and_then(PreparedSnapshot::write) {
            tracing::error!(edge = %self.shared.edge, session = format!("{:016x}", self.shared.session_id),
                dir = %self.snapshot_dir.display(), error = %e, "periodic snapshot failed; recording goes on");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_snapshot_of_an_edge_without_a_session_names_it_and_what_there_is() {
        let data = tempfile::tempdir().unwrap();
        let settings = LiveSettings::new(PipelineSettings::default(), data.path().to_path_buf());
        let live = LivePipelines::new(settings).unwrap();
        let out = data.path().join("snap");
        let any = live.snapshot("pi-01", None, None, &out).unwrap_err();
        assert_eq!(
            any.to_string(),
            "no live session of edge \"pi-01\" (known: none)"
        );
        let one = live
            .snapshot("pi-01", Some("00000000000000ab"), None, &out)
            .unwrap_err();
        assert_eq!(
            one.to_string(),
            "no live session 00000000000000ab of edge \"pi-01\" (known: none)"
        );
    }

    #[test]
    fn the_lag_is_the_age_of_the_oldest_frame_still_waiting() {
        let now = Instant::now();
        let ago = |s| now.checked_sub(Duration::from_secs(s)).expect("uptime");
        // Three frames accepted, one taken at once (it waited 0 ms); two wait, since 3 s and 1 s.
        let shared = WorkerShared::new("e", 1);
        shared.accepted.store(3, Ordering::Release);
        *lock(&shared.waiting) = [ago(3), ago(1)].into();
        lock(&shared.progress).received = 1;
        let (frames, ms) = shared.lag();
        assert_eq!(frames, 2);
        assert!((3_000..60_000).contains(&ms), "{ms} ms");
        lock(&shared.waiting).clear();
        shared.progress.lock().unwrap().received = 3;
        assert_eq!(shared.lag(), (0, 0));
    }

    #[test]
    fn the_largest_lag_keeps_a_catch_up_that_is_over() {
        let shared = WorkerShared::new("e", 1);
        // Frames owed since 4 s ago were caught up just now: nothing waits any more...
        let since = Instant::now()
            .checked_sub(Duration::from_secs(4))
            .expect("uptime");
        shared.note_caught_up(since);
        shared.note_lag();
        assert_eq!(shared.lag(), (0, 0));
        // ...but the oldest of them waited 4 s.
        let max = lock(&shared.progress).max_lag_ms;
        assert!((4_000..60_000).contains(&max), "{max} ms");
    }

    #[test]
    fn latency_percentiles_come_from_the_sorted_window() {
        let latencies: Vec<i64> = (1..=100).rev().map(|ms| ms * 1_000_000).collect();
        let summary = LatencySummary::of(&latencies).unwrap();
        assert_eq!(summary.count, 100);
        assert_eq!(summary.p50_ms, 51.0);
        assert_eq!(summary.p99_ms, 99.0);
        assert_eq!(summary.max_ms, 100.0);
        assert_eq!(LatencySummary::of(&[]), None);
    }

    #[test]
    fn frames_in_sequence_are_processed_as_they_come() {
        let mut sequencer = Sequencer::default();
        for seq in 0..5 {
            assert_eq!(sequencer.offer(seq), Offer::Process);
        }
        assert_eq!(sequencer.owed(), 0);
    }

    #[test]
    fn a_catch_up_reads_from_the_first_frame_not_processed() {
        let mut sequencer = Sequencer::default();
        assert_eq!(sequencer.resume_from(), 0);
        for seq in 0..5 {
            sequencer.offer(seq);
        }
        assert_eq!(sequencer.resume_from(), 5);
        sequencer.owe(5);
        assert_eq!(sequencer.offer(6), Offer::Owe);
        assert_eq!(sequencer.resume_from(), 5, "5 and 6 are owed");
        assert!(sequencer.from_recording(5) && sequencer.from_recording(6));
        assert_eq!(sequencer.resume_from(), 7);
    }

    #[test]
    fn frames_counted_as_processed_are_not_read_back() {
        let mut sequencer = Sequencer::default();
        sequencer.owe(3);
        sequencer.owe(7);
        sequencer.processed_before(5);
        assert_eq!(sequencer.resume_from(), 5);
        assert_eq!(sequencer.owed(), 1, "3 is done, 7 still owed");
        assert!(!sequencer.from_recording(4));
        assert!(sequencer.from_recording(5));
    }

    #[test]
    fn a_frame_after_an_overflow_is_owed_until_the_recording_gives_both_in_its_order() {
        let mut sequencer = Sequencer::default();
        assert_eq!(sequencer.offer(0), Offer::Process);
        sequencer.owe(1);
        // 2 follows 1, which is owed: it must wait behind it.
        assert_eq!(sequencer.offer(2), Offer::Owe);
        assert_eq!(sequencer.owed(), 2);
        // The recording, in its order: 0 was processed, 1 and 2 are taken, 3 as well (committed
        // before its queue entry was read).
        let taken: Vec<u64> = (0..4)
            .filter(|&seq| sequencer.from_recording(seq))
            .collect();
        assert_eq!(taken, [1, 2, 3]);
        assert_eq!(sequencer.owed(), 0);
        // 3's queue entry arrives late: already done. 4 is next in sequence.
        assert_eq!(sequencer.offer(3), Offer::Skip);
        assert_eq!(sequencer.offer(4), Offer::Process);
    }

    #[test]
    fn a_resend_after_a_gap_is_read_back_in_recording_order() {
        let mut sequencer = Sequencer::default();
        for seq in [0, 1, 2] {
            assert_eq!(sequencer.offer(seq), Offer::Process);
        }
        // 3 was lost on the way (it comes again after a reconnect); 4 and 5 come first.
        assert_eq!(sequencer.offer(4), Offer::Owe);
        assert_eq!(sequencer.offer(5), Offer::Owe);
        // The recording holds 0, 1, 2, 4, 5 so far.
        let taken: Vec<u64> = [0, 1, 2, 4, 5]
            .into_iter()
            .filter(|&seq| sequencer.from_recording(seq))
            .collect();
        assert_eq!(taken, [4, 5]);
        // Then the resend: out of sequence again, read back after 5 as the recording has it.
        assert_eq!(sequencer.offer(3), Offer::Owe);
        let taken: Vec<u64> = [0, 1, 2, 4, 5, 3, 6]
            .into_iter()
            .filter(|&seq| sequencer.from_recording(seq))
            .collect();
        assert_eq!(taken, [3, 6]);
        assert_eq!(sequencer.offer(7), Offer::Process);
    }

    #[test]
    fn a_session_recorded_before_the_daemon_started_is_read_from_its_beginning() {
        let mut sequencer = Sequencer::default();
        // The first frame this daemon sees is 120: 0..120 are in the recording already.
        assert_eq!(sequencer.offer(120), Offer::Owe);
        let taken = (0..=120)
            .filter(|&seq| sequencer.from_recording(seq))
            .count();
        assert_eq!(taken, 121);
        assert_eq!(sequencer.offer(121), Offer::Process);
    }

    #[test]
    fn owed_frames_that_never_reach_the_recording_are_given_up_once() {
        let mut sequencer = Sequencer::default();
        assert_eq!(sequencer.offer(0), Offer::Process);
        sequencer.owe(1);
        sequencer.owe(2);
        assert!(!sequencer.from_recording(0));
        assert_eq!(sequencer.forgive(), [1, 2]);
        assert_eq!(sequencer.owed(), 0);
        // A frame owed but already done (a late overflow report) is not owed.
        sequencer.owe(0);
        assert_eq!(sequencer.owed(), 0);
    }
}
