//! The server's mapping pipeline: per session, frames merged by edge sample time go through
//! stages (static-scan assembly by eq. 1, the Table II filters, octree insertion, metrics
//! against a reference), and the products (cloud, octree, metrics) grow as the frames come in.
//!
//! One pipeline, three drivers: `scan3d serve` feeds it live from ingest (through a bounded
//! queue; it catches up from the recording when it falls behind), `scan3d replay` and the
//! offline `scan3d assemble` / `scan3d map` feed it a recorded session frame by frame
//! ([`offline`]). So the live products and the replayed ones are the same bytes.
//!
//! # Sample-time order
//!
//! Frames come in the edge's sequence order, which is not the order of their samples: a Sweep
//! revolution is sent at its end, after the RPLidar revolutions and IMU samples that overlap
//! it. The stages run in **lanes**: a lane is an [`OrderedQueue`] over the streams its first
//! stage names ([`Stage::streams`]) and the stages that follow it (which take what the stage
//! before handed on in the [`StageContext`]). Each lane waits only for its own streams, behind
//! watermarks, so a slow stream never holds a lane that does not take it; a stream silent for
//! longer than [`PipelineSettings::lateness_ms`] of data time is released (logged, counted in
//! [`SessionStatus::stream_releases`]) and the same frames always make the same decisions, live
//! or replayed ([`order`]).
//!
//! # Stages
//!
//! The stages are an ordered list; a [`StageContext`] carries what one stage hands to the next:
//!
//! | stage | lane takes | hands on / keeps |
//! | --- | --- | --- |
//! | [`RevolutionStage`] (optional) | lidar revolutions | per-sensor 2D points, `scans/<lidar>.ply` |
//! | [`PoseStage`], then [`FusionStage`] (with [`Products::trajectory`]) | RPLidar revolutions, IMU samples, pass markers | the poses of `base` in [`StageContext::poses`], handed on to the later lanes that take the Poses stream; `trajectory.tum`, the grid |
//! | [`AssemblyStage`] | Sweep revolutions, static-scan messages (with the pose stage also pass markers and the Poses stream) | the origin groups (one per half revolution) completed by this frame, in [`StageContext::rays`] |
//! | [`MovingStage`] (with [`Products::trajectory`]) | (follows) | each pass's Sweep revolutions, held until the poses cover them, placed sample by sample, in [`StageContext::rays`] tagged with the pass |
//! | [`FilterStage`] | (follows) | the same groups through `revolution_filters` (voxel grid, pass-through) |
//! | [`MapStage`] | (follows) | one octree per session, per named position and per pass (OctoMap's `insertPointCloud`, `max_range` cut), the growing cloud |
//! | [`MetricsStage`] | (follows) | voxel counts and the metrics against the reference, recomputed when the map grew and `status` asks, at most once per [`METRICS_INTERVAL`]; a snapshot's from the octree it wrote |
//!
//! A lane's poses go on to every later lane that takes [`StreamId::Poses`], in order, keyed by
//! their time ([`Stage::on_pose`]), so a Sweep revolution keyed by its end leaves its lane once
//! the poses passed it (or the Poses stream was released by lateness). A lane declares the Poses
//! stream only when the session's `Hello` names an RPLidar and there is a pose stage.
//!
//! [`SessionPipeline::add_stage`] puts a stage at the end: with streams of its own it opens a
//! new lane, without it follows the last stage. Snapshots go through the stages
//! ([`Stage::snapshot`]). The snapshot filters (SOR, Gaussian:
//! they need neighbours across revolutions) only touch the cloud a snapshot writes.
//!
//! # Memory
//!
//! Bounded by the map, not the session: a lane holds at most the frames of its lateness (and
//! [`MAX_QUEUED_FRAMES`]); the assembler forgets the static scans that are over when the next one
//! starts, unless [`Products::static_scans`] asks to keep them, as `scan3d assemble` does; the
//! cloud holds the filtered points (turn it off with [`Products::cloud`] when only the octree is
//! wanted, as `scan3d map` does).

pub mod edge_activity;
pub mod fusion_stage;
pub mod live;
mod metrics;
pub mod moving_stage;
pub mod offline;
pub mod order;
pub mod passes;
pub mod pose_stage;
mod snapshot;
mod stages;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::filter::Filter;
use scan3d_map::eval::{EvalError, LeafMap, Metrics};
use scan3d_map::octree::{OctreeError, Resolution, SensorModel, VoxelMap};
use scan3d_protocol::{Body, Frame};

pub use fusion_stage::{FusedRun, FusionStage, FusionStatus, fuse_session};
pub use metrics::{load_reference, write_metrics_table};
pub use moving_stage::{MovingOptions, MovingScope, MovingStage, PassStatus};
pub use order::{OrderStats, OrderedQueue, Release, StreamId};
pub use pose_stage::{PoseStage, PoseStatus};
pub use snapshot::{Snapshot, SnapshotWriter};
pub use stages::{
    AssemblyStage, FilterStage, MapStage, MetricsStage, PositionMap, RevolutionStage,
};

/// What the pipeline builds and how: the `[pipeline]` section of `server.toml`, or the offline
/// commands' options.
#[derive(Debug, Clone, PartialEq)]
pub struct PipelineSettings {
    /// Voxel edge length of the octrees, metres.
    pub resolution_m: f64,
    /// Rays longer than this are cut (OctoMap's `maxrange`: free up to the cut, no hit);
    /// `None`: no limit.
    pub max_range_m: Option<f64>,
    /// Hit / miss / clamping probabilities of the octree insertion.
    pub sensor: SensorModel,
    /// Applied to each revolution's points before insertion (voxel grid, pass-through box).
    pub revolution_filters: Vec<Filter>,
    /// Applied to the whole cloud when a snapshot is written (statistical outlier removal,
    /// Gaussian), as those need neighbours across revolutions.
    pub snapshot_filters: Vec<Filter>,
    /// A reference map (`.bt` / `.ot`, same resolution) the metrics compare against.
    pub reference: Option<PathBuf>,
    /// A stream that falls this far (ms of edge time) behind the newest one of its lane is no
    /// longer waited for ([`order`]).
    pub lateness_ms: u64,
}

impl Default for PipelineSettings {
    fn default() -> Self {
        PipelineSettings {
            resolution_m: 0.05,
            max_range_m: None,
            sensor: SensorModel::default(),
            revolution_filters: Vec::new(),
            snapshot_filters: Vec::new(),
            reference: None,
            lateness_ms: 1000,
        }
    }
}

/// What one session's pipeline has done so far (a session's entry in `scan3d status`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SessionStatus {
    /// Frames taken.
    pub frames: u64,
    /// Lidar samples in those frames (both lidars).
    pub samples: u64,
    /// Lidar revolutions in those frames (both lidars).
    pub revolutions: u64,
    /// Occupied voxels (depth 16) of the session's octree (all positions), as of the last
    /// refresh (at most [`METRICS_INTERVAL`] old).
    pub occupied_voxels: u64,
    /// Free voxels of the session's octree, as of the last refresh.
    pub free_voxels: u64,
    /// The latest metrics against the reference, when one is configured and there is a map.
    pub metrics: Option<Metrics>,
    /// Edge sequence numbers skipped over (a gap in the session: frames never received or lost
    /// from the recording); the frames after a gap are processed.
    pub missing_frames: u64,
    /// Frames that arrived with a sequence number already taken (duplicates): skipped.
    pub stale_frames: u64,
    /// Frames that arrived after a later one and filled its gap: taken (and no longer missing).
    pub filled_frames: u64,
    /// Frames the server could not decode (e.g. a body of a newer protocol): skipped.
    pub undecodable_frames: u64,
    /// Static-scan samples that could not be placed (their scan start or revolution was never
    /// seen): skipped.
    pub orphan_samples: u64,
    /// Static scans whose end message never came (lost): forgotten when the next one started.
    pub abandoned_static_scans: u64,
    /// Origin groups a revolution filter failed on (logged; their points are not mapped).
    pub filter_failures: u64,
    /// Points in those groups.
    pub filtered_out_points: u64,
    /// Frames that came after their lane had gone past their sample time (their stream had
    /// been released): processed out of order.
    pub late_frames: u64,
    /// Times a stream fell further than the lateness behind and was no longer waited for.
    pub stream_releases: u64,
    /// Frames waiting in the lanes for a slower stream now.
    pub queued_frames: u64,
    /// Points inserted into the session's octree (after the revolution filters).
    pub points: u64,
    /// Where `base` is now (the live pose stage), once an RPLidar revolution was matched.
    pub pose: Option<PoseStatus>,
    /// The yaw fusion's counts (poses fused, matcher-only and why), with the pose stage.
    pub fusion: Option<FusionStatus>,
    /// Named static-scan positions seen, in first-seen order.
    pub positions: Vec<String>,
    /// Trolley passes seen (assembly along movement, [`MovingStage`]), in first-seen order.
    pub passes: Vec<PassStatus>,
}

/// How often [`SessionPipeline::status`] recomputes voxel counts and metrics at most.
pub const METRICS_INTERVAL: Duration = Duration::from_secs(1);

/// Why a pipeline could not be built or a snapshot written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// The resolution is not a finite positive number.
    #[error("pipeline resolution: {0}")]
    Resolution(#[from] OctreeError),
    /// The max range is NaN or not positive.
    #[error("pipeline max range must be a positive number of metres, got {0}")]
    MaxRange(f64),
    /// The reference map cannot be read.
    #[error("reference map {path}: {reason}")]
    Reference {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The reference map's voxels differ from the pipeline's resolution.
    #[error(
        "reference map {path} has {found} m voxels, the pipeline builds {expected} m ones \
         (metrics need equal resolutions)"
    )]
    ReferenceResolution {
        /// The file.
        path: PathBuf,
        /// The reference's resolution.
        found: f64,
        /// The pipeline's resolution.
        expected: f64,
    },
    /// A snapshot was asked for a position the session has not seen.
    #[error("no static scan at position {name:?} in this session (positions: {known})")]
    UnknownPosition {
        /// The name asked for.
        name: String,
        /// The positions seen, comma-separated.
        known: String,
    },
    /// A snapshot file or directory could not be written.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A snapshot filter failed on the cloud.
    #[error("snapshot filter: {0}")]
    Filter(#[from] scan3d_map::cloud::filter::FilterError),
    /// The metrics could not be computed.
    #[error("metrics: {0}")]
    Metrics(#[from] EvalError),
}

/// Which products a pipeline keeps beyond the session's octree.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Products {
    /// The per-sensor 2D points of every revolution (`scan3d replay --out`'s `scans/*.ply`).
    /// Grows with the session: off by default.
    pub revolution_points: bool,
    /// One octree per named position besides the session's.
    pub position_maps: bool,
    /// The growing world-frame cloud (filtered points with their origins) for `cloud.ply`.
    pub cloud: bool,
    /// Every assembled static scan with its points (`scan3d assemble`): grows with the session.
    pub static_scans: bool,
    /// The session's octree (and the positions' ones with `position_maps`); `scan3d assemble`
    /// needs none.
    pub octrees: bool,
    /// The live 2D trajectory of `base` from the RPLidar's revolutions ([`PoseStage`]):
    /// `trajectory.tum` and the grid in snapshots, the pose in `status`.
    pub trajectory: bool,
}

impl Default for Products {
    /// What the live daemon keeps: octrees per session and position, the cloud and the
    /// trajectory.
    fn default() -> Self {
        Products {
            revolution_points: false,
            position_maps: true,
            cloud: true,
            static_scans: false,
            octrees: true,
            trajectory: true,
        }
    }
}

/// What a frame hands from one stage to the next within a lane.
#[derive(Debug, Default)]
pub struct StageContext {
    /// The frame's key in its lane: its sample time (edge ns; see [`order`]).
    pub key_ns: u64,
    /// `true` when the frame left its lane out of order (its stream had been released).
    pub late: bool,
    /// Origin groups completed by the current frame or pose, world (room) frame, with what they
    /// belong to: one per half revolution of a static scan (the assembly stage), or a bundle of
    /// a pass's Sweep samples placed along the trajectory (the moving stage); later stages
    /// transform or consume them. Emptied after each frame.
    pub rays: Vec<NewBundle>,
    /// Poses of `base` made for the current frame: the pose stage adds the matcher's, a fusion
    /// stage after it in the same lane may replace their yaw and add roll and pitch. The
    /// pipeline hands them, in order, to the lanes that take [`StreamId::Poses`]. Emptied after
    /// each frame.
    pub poses: Vec<BasePose>,
}

/// Points with their sensor origin on their way to the filters and the maps, and what they
/// belong to.
#[derive(Debug, Clone, PartialEq)]
pub struct NewBundle {
    /// The static-scan position or the pass the points were measured in.
    pub source: RaySource,
    /// The points and their origin, world (room) frame.
    pub rays: RayBundle,
}

/// What a [`NewBundle`] belongs to: the map stage keeps a map and a cloud per position and per
/// pass besides the session's.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RaySource {
    /// A static scan at the operator's named position.
    Position(String),
    /// A trolley pass, by its name (the empty name: the whole session placed along the
    /// trajectory, `scan3d assemble --moving` without `--pass`).
    Pass(String),
}

/// A pose of `base` at one sample time, as the pose lane hands it on (see
/// [`StageContext::poses`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BasePose {
    /// Its time: the reference time of the RPLidar revolution it was matched from, edge ns.
    pub t_ns: u64,
    /// x, y (m) and yaw (rad, counter-clockwise) of `base` in the session's own frame.
    pub pose: scan3d_slam::pose::Pose2,
    /// Covariance over (x, y, yaw), row-major, m² / m·rad / rad².
    pub covariance: [f64; 9],
    /// Roll and pitch of `base`, rad, when an attitude source gave them (the fusion stage);
    /// `None`: taken as level.
    pub roll_pitch: Option<[f64; 2]>,
    /// The session's frame → the room frame (a pass start anchored it) when this pose was
    /// made; `None` before any pass. A consumer places with the anchor of the newest pose it
    /// uses.
    pub room_from_session: Option<scan3d_slam::pose::Pose2>,
}

impl BasePose {
    /// The pose in the room frame (the session's own when not anchored).
    pub fn in_room(&self) -> scan3d_slam::pose::Pose2 {
        match &self.room_from_session {
            Some(anchor) => anchor.compose(&self.pose),
            None => self.pose,
        }
    }
}

/// One stage: takes frames in sample-time order, keeps its products.
pub trait Stage: std::any::Any + Send {
    /// The stage's name in logs and status.
    fn name(&self) -> &'static str {
        std::any::type_name::<Self>()
    }
    /// The streams it takes, in sample-time order: it opens a lane of its own. Empty (the
    /// default): it follows the stage before it and takes what that one handed on.
    fn streams(&self) -> &'static [StreamId] {
        &[]
    }
    /// The time its lane orders `frame` by, given the pipeline's (`default_ns`: a revolution's
    /// end, a sample's time). Only the first stage of a lane is asked; a stage that needs a
    /// revolution before the other streams reach its end (the pose stage: its pose is for the
    /// middle of the beams) keys it earlier, so it leaves sooner.
    fn key_ns(&self, frame: &Frame, default_ns: u64) -> u64 {
        let _ = frame;
        default_ns
    }
    /// Takes one frame and what the earlier stages of its lane handed on for it in `ctx`.
    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame);
    /// Takes one pose of `base` handed on by an earlier lane, in sample-time order among the
    /// frames, when the lane takes [`StreamId::Poses`] (the default does nothing). Rays a
    /// stage completes with it go on in `ctx` as for a frame.
    fn on_pose(&mut self, ctx: &mut StageContext, pose: &BasePose) {
        let _ = (ctx, pose);
    }
    /// Called when the session's frames end (or before a snapshot): hand on what is pending.
    fn flush(&mut self, ctx: &mut StageContext) {
        let _ = ctx;
    }
    /// Adds the stage's products to a snapshot being written (in `out.snapshot.dir`).
    fn snapshot(&mut self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        let _ = out;
        Ok(())
    }
    /// Takes what this stage's part of a snapshot of the session (`position` `None`) or of one
    /// position needs (shared handles or plain copies, no heavy work) and returns the job that
    /// writes it later, after the pipeline is released ([`SessionPipeline::prepare_snapshot`]).
    /// `None` (the default): the stage writes in [`Stage::snapshot`] while the pipeline is
    /// held, adding files only.
    fn snapshot_job(&self, position: Option<&str>) -> Option<SnapshotJob> {
        let _ = position;
        None
    }
}

/// A stage's part of a snapshot, taken while the pipeline is held and written after
/// ([`Stage::snapshot_job`]).
pub type SnapshotJob = Box<dyn FnOnce(&mut SnapshotWriter) -> Result<(), PipelineError> + Send>;

/// A snapshot taken from a pipeline and not written yet ([`SessionPipeline::prepare_snapshot`]):
/// owns what it needs, so the heavy work (the octree derived, the snapshot filters, the files)
/// runs without the pipeline.
pub struct PreparedSnapshot {
    dir: PathBuf,
    position: Option<String>,
    parts: Vec<SnapshotPart>,
}

/// One stage's part of a [`PreparedSnapshot`].
enum SnapshotPart {
    /// To be written.
    Job(SnapshotJob),
    /// Written already (a stage without [`Stage::snapshot_job`]): its files, in order.
    Written(Vec<PathBuf>),
}

impl PreparedSnapshot {
    /// Writes the stages' parts in order (each file through a temporary name and a rename).
    pub fn write(self) -> Result<Snapshot, PipelineError> {
        let mut writer = SnapshotWriter::new(&self.dir, self.position.as_deref());
        for part in self.parts {
            match part {
                SnapshotPart::Job(job) => job(&mut writer)?,
                SnapshotPart::Written(files) => writer.snapshot.files.extend(files),
            }
        }
        Ok(writer.snapshot)
    }
}

/// Frames a lane holds at most before it releases its slowest stream.
pub const MAX_QUEUED_FRAMES: usize = 20_000;

/// Where a frame goes in the sample-time order: its stream and time, or `None` for frames the
/// stages never see (time pings, acks).
fn stream_of(body: &Body) -> Option<(StreamId, Option<u64>)> {
    use scan3d_protocol::{SensorId, StaticScan};
    Some(match body {
        Body::Revolution(rev) => {
            let stream = match rev.sensor {
                SensorId::RPLIDAR => StreamId::Rplidar,
                SensorId::SWEEP => StreamId::Sweep,
                _ => StreamId::OtherLidar,
            };
            (stream, Some(rev.t1_ns))
        }
        Body::Imu(sample) => (StreamId::Imu, Some(sample.t_ns)),
        Body::Stepper(state) => (StreamId::Stepper, Some(state.t_ns)),
        Body::StaticScan(message) => {
            let t = match message {
                StaticScan::Started(start) => start.t_ns,
                StaticScan::Yaws(yaws) => yaws.revolution_t0_ns,
                StaticScan::Warning(warning) => warning.t_ns,
                StaticScan::Finished(end) => end.t_ns,
            };
            (StreamId::StaticScan, Some(t))
        }
        Body::Pass(marker) => (StreamId::Pass, Some(marker.t_ns)),
        Body::Hello(_)
        | Body::Mounts(_)
        | Body::Status(_)
        | Body::CommandReply(_)
        | Body::Command(_) => (StreamId::Edge, None),
        Body::Heartbeat(_)
        | Body::TimePing(_)
        | Body::TimePong(_)
        | Body::Ack(_)
        | Body::ClockModel(_) => return None,
    })
}

/// The continuous streams a `Hello`'s sensors promise.
fn declared_streams(hello: &scan3d_protocol::Hello) -> Vec<StreamId> {
    use scan3d_protocol::SensorId;
    hello
        .sensors
        .iter()
        .filter_map(|info| match info.sensor {
            SensorId::RPLIDAR => Some(StreamId::Rplidar),
            SensorId::SWEEP => Some(StreamId::Sweep),
            SensorId::IMU => Some(StreamId::Imu),
            _ => None,
        })
        .collect()
}

/// What a lane's queue orders: the session's frames and the poses of `base` an earlier lane
/// handed on ([`StreamId::Poses`], keyed by their time).
#[derive(Debug, Clone)]
enum LaneItem {
    Frame(Arc<Frame>),
    Pose(BasePose),
}

/// A lane: the stages after one that names streams, and the queue that orders its frames.
struct Lane {
    streams: &'static [StreamId],
    queue: OrderedQueue<LaneItem>,
    /// Indices into [`SessionPipeline::stages`], in order.
    stages: Vec<usize>,
}

impl Lane {
    fn new(streams: &'static [StreamId], lateness_ns: u64) -> Self {
        Lane {
            streams,
            queue: OrderedQueue::new(lateness_ns, MAX_QUEUED_FRAMES),
            stages: Vec::new(),
        }
    }

    fn takes(&self, stream: StreamId) -> bool {
        // Untimed frames (hello, status) go to every lane, in their place among its frames.
        stream == StreamId::Edge || self.streams.contains(&stream)
    }
}

/// Where the edge's sequence numbers stand: the received set's newest, and the gaps below it
/// (at most [`MAX_GAPS`] ranges, the oldest forgotten), so a frame that arrives after a later
/// one fills its gap instead of being taken for a duplicate.
#[derive(Debug, Default, Clone)]
struct SeqTrack {
    /// The next edge sequence number expected (`None` before the first frame).
    next: Option<u64>,
    /// Sequence numbers not received below `next`: start → end (exclusive).
    gaps: std::collections::BTreeMap<u64, u64>,
    missing: u64,
    stale: u64,
    undecodable: u64,
    filled: u64,
}

/// Gaps remembered at most (a hostile edge cannot grow them without bound).
const MAX_GAPS: usize = 1024;

impl SeqTrack {
    /// Accounts for edge seq `seq`; `false` if it was already taken (to be skipped).
    fn take(&mut self, seq: u64) -> bool {
        let next = self.next.unwrap_or(0);
        if self.next.is_some() && seq < next {
            return self.fill(seq);
        }
        if seq > next {
            let gap = seq - next;
            self.missing = self.missing.saturating_add(gap);
            self.gaps.insert(next, seq);
            if self.gaps.len() > MAX_GAPS {
                self.gaps.pop_first();
            }
            tracing::warn!(
                from = next,
                to = seq - 1,
                frames = gap,
                "gap in the session's sequence numbers; going on after it"
            );
        }
        self.next = Some(seq.saturating_add(1));
        true
    }

    /// A frame below `next`: taken if it fills a gap, else stale.
    fn fill(&mut self, seq: u64) -> bool {
        let Some((&start, &end)) = self.gaps.range(..=seq).next_back() else {
            self.stale += 1;
            return false;
        };
        if seq >= end {
            self.stale += 1;
            return false;
        }
        self.gaps.remove(&start);
        if start < seq {
            self.gaps.insert(start, seq);
        }
        if seq + 1 < end {
            self.gaps.insert(seq + 1, end);
        }
        self.missing -= 1;
        self.filled += 1;
        true
    }
}

/// One session's pipeline: feed its frames in sequence order with [`SessionPipeline::on_frame`],
/// read [`SessionPipeline::status`], write products with [`SessionPipeline::write_snapshot`].
/// `Send`, so a daemon can run it on a worker thread.
pub struct SessionPipeline {
    settings: PipelineSettings,
    products: Products,
    reference: Option<Arc<LeafMap>>,
    /// Every stage, in order.
    stages: Vec<Box<dyn Stage>>,
    lanes: Vec<Lane>,
    /// Indices of the built-in stages in `stages`.
    builtin: Builtin,
    ctx: StageContext,
    seqs: SeqTrack,
    frames: u64,
    samples: u64,
    revolutions: u64,
    released: Vec<Release>,
}

#[derive(Debug, Clone, Copy)]
struct Builtin {
    revolutions: Option<usize>,
    pose: Option<usize>,
    moving: Option<usize>,
    assembly: usize,
    filters: usize,
    maps: usize,
    metrics: usize,
}

impl std::fmt::Debug for SessionPipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionPipeline")
            .field("settings", &self.settings)
            .field("products", &self.products)
            .field("frames", &self.frames)
            .field(
                "stages",
                &self.stages.iter().map(|s| s.name()).collect::<Vec<_>>(),
            )
            .finish_non_exhaustive()
    }
}

impl SessionPipeline {
    /// A pipeline keeping the live daemon's [`Products`]; loads the reference map and checks
    /// that its resolution is the pipeline's.
    pub fn new(settings: &PipelineSettings) -> Result<Self, PipelineError> {
        Self::with_products(settings, Products::default())
    }

    /// A pipeline keeping `products`.
    pub fn with_products(
        settings: &PipelineSettings,
        products: Products,
    ) -> Result<Self, PipelineError> {
        let res = Resolution::new(settings.resolution_m)?;
        let reference = match &settings.reference {
            Some(path) => Some(Arc::new(load_reference(path, &res)?)),
            None => None,
        };
        Self::with_reference(settings, products, reference)
    }

    /// A pipeline keeping `products` that compares against `reference` (loaded once with
    /// [`load_reference`] and shared by every session) instead of reading `settings.reference`.
    pub fn with_reference(
        settings: &PipelineSettings,
        products: Products,
        reference: Option<Arc<LeafMap>>,
    ) -> Result<Self, PipelineError> {
        let res = Resolution::new(settings.resolution_m)?;
        if let Some(max) = settings.max_range_m
            && (max.is_nan() || max <= 0.0)
        {
            return Err(PipelineError::MaxRange(max));
        }
        if let Some(reference) = &reference {
            let path = settings
                .reference
                .as_deref()
                .unwrap_or(Path::new("(shared)"));
            metrics::check_resolution(reference, &res, path)?;
        }
        let mut pipeline = SessionPipeline {
            settings: settings.clone(),
            products,
            reference: reference.clone(),
            stages: Vec::new(),
            lanes: Vec::new(),
            builtin: Builtin {
                revolutions: None,
                pose: None,
                moving: None,
                assembly: 0,
                filters: 0,
                maps: 0,
                metrics: 0,
            },
            ctx: StageContext::default(),
            seqs: SeqTrack::default(),
            frames: 0,
            samples: 0,
            revolutions: 0,
            released: Vec::new(),
        };
        if products.revolution_points {
            pipeline.builtin.revolutions =
                Some(pipeline.push_stage(Box::new(RevolutionStage::new())));
        }
        if products.trajectory {
            let stage = PoseStage::new(
                scan3d_slam::mapper::MapperConfig::default(),
                scan3d_slam::pose::Pose2::default(),
            );
            pipeline.builtin.pose = Some(pipeline.push_stage(Box::new(stage)));
            let fusion = FusionStage::new(scan3d_slam::fusion::FuserConfig::default())
                .expect("the default fusion config is valid");
            pipeline.push_stage(Box::new(fusion));
        }
        // With poses (the pose stage), the assembly lane also takes the pass markers and the
        // poses, and the moving stage places the passes' Sweep samples in it.
        pipeline.builtin.assembly = pipeline.push_stage(Box::new(AssemblyStage::with_poses(
            products.static_scans,
            products.trajectory,
        )));
        if products.trajectory {
            let stage = MovingStage::new(res, MovingOptions::default());
            pipeline.builtin.moving = Some(pipeline.push_stage(Box::new(stage)));
        }
        pipeline.builtin.filters = pipeline.push_stage(Box::new(FilterStage::new(
            settings.revolution_filters.clone(),
        )));
        pipeline.builtin.maps =
            pipeline.push_stage(Box::new(MapStage::new(res, settings, products)));
        pipeline.builtin.metrics = pipeline.push_stage(Box::new(MetricsStage::new(reference)));
        Ok(pipeline)
    }

    /// The settings it was built with.
    pub fn settings(&self) -> &PipelineSettings {
        &self.settings
    }

    /// Adds a stage after the others: with streams of its own ([`Stage::streams`]) it opens a
    /// lane that takes them in sample-time order; without, it follows the last stage.
    pub fn add_stage(&mut self, stage: Box<dyn Stage>) {
        self.push_stage(stage);
    }

    fn push_stage(&mut self, stage: Box<dyn Stage>) -> usize {
        let streams = stage.streams();
        if !streams.is_empty() || self.lanes.is_empty() {
            let lateness_ns = self.settings.lateness_ms.saturating_mul(1_000_000);
            self.lanes.push(Lane::new(streams, lateness_ns));
        }
        let index = self.stages.len();
        self.stages.push(stage);
        self.lanes.last_mut().expect("a lane").stages.push(index);
        index
    }

    /// Takes the session's next frame, in sequence order as the edge sent it. A frame whose edge
    /// sequence number was already taken is skipped and counted
    /// ([`SessionStatus::stale_frames`]); a jump is a gap, counted
    /// ([`SessionStatus::missing_frames`]) and logged, and a frame that fills a gap later is
    /// taken. Frames the server made (commands, clock models: their own numbering) are not
    /// processed. Each lane that takes the frame's stream queues it and runs what can leave.
    pub fn on_frame(&mut self, frame: &Frame) {
        if frame.body.is_server_made() || !self.seqs.take(frame.seq) {
            return;
        }
        self.frames += 1;
        if let Body::Revolution(rev) = &frame.body {
            self.revolutions += 1;
            self.samples += rev.samples.len() as u64;
        }
        if let Body::Hello(hello) = &frame.body {
            let mut streams = declared_streams(hello);
            // Poses come only from a pose stage fed by an RPLidar: a session without one (static
            // scans only) never waits for them.
            if self.builtin.pose.is_some() && streams.contains(&StreamId::Rplidar) {
                streams.push(StreamId::Poses);
            }
            for stream in streams {
                for lane in self
                    .lanes
                    .iter_mut()
                    .filter(|l| l.streams.contains(&stream))
                {
                    lane.queue.declare(stream);
                }
            }
        }
        let Some((stream, t_ns)) = stream_of(&frame.body) else {
            if let Body::Heartbeat(heartbeat) = &frame.body {
                for index in 0..self.lanes.len() {
                    self.lanes[index].queue.observe(heartbeat.sent_ns);
                    self.poll_lane(index);
                }
            }
            return;
        };
        if !self.lanes.iter().any(|lane| lane.takes(stream)) {
            return;
        }
        let frame = Arc::new(frame.clone());
        for index in 0..self.lanes.len() {
            if !self.lanes[index].takes(stream) {
                continue;
            }
            let lane = &self.lanes[index];
            // An untimed frame takes its place at the lane's newest time.
            let t = match t_ns {
                Some(t) => self.stages[lane.stages[0]].key_ns(&frame, t),
                None => lane.queue.frontier_ns().unwrap_or(0),
            };
            self.push_item(index, stream, t, LaneItem::Frame(Arc::clone(&frame)));
        }
    }

    /// Queues one item in lane `index` and runs what leaves.
    fn push_item(&mut self, index: usize, stream: StreamId, t_ns: u64, item: LaneItem) {
        let mut out = Vec::new();
        let mut releases = Vec::new();
        self.lanes[index]
            .queue
            .push(stream, t_ns, item, &mut out, &mut releases);
        self.note_releases(index, releases);
        self.run_lane(index, out);
    }

    /// Hands the poses lane `from` made to every later lane that takes [`StreamId::Poses`], in
    /// order, keyed by their time.
    fn hand_on_poses(&mut self, from: usize, poses: Vec<BasePose>) {
        if poses.is_empty() {
            return;
        }
        for index in from + 1..self.lanes.len() {
            if !self.lanes[index].streams.contains(&StreamId::Poses) {
                continue;
            }
            for pose in &poses {
                self.push_item(index, StreamId::Poses, pose.t_ns, LaneItem::Pose(*pose));
            }
        }
    }

    fn poll_lane(&mut self, index: usize) {
        let mut out = Vec::new();
        let mut releases = Vec::new();
        self.lanes[index].queue.poll(&mut out, &mut releases);
        self.note_releases(index, releases);
        self.run_lane(index, out);
    }

    fn note_releases(&mut self, lane: usize, releases: Vec<Release>) {
        for release in releases {
            tracing::warn!(
                lane = self.stages[self.lanes[lane].stages[0]].name(),
                stream = release.stream.name(),
                watermark_ns = release.watermark_ns,
                frontier_ns = release.frontier_ns,
                cause = ?release.cause,
                "a stream fell behind the others and is no longer waited for"
            );
            self.released.push(release);
        }
    }

    /// Runs the lane's stages on the frames and poses that left its queue; the poses they made
    /// go on to the later lanes that take them.
    fn run_lane(&mut self, index: usize, out: Vec<order::Ordered<LaneItem>>) {
        for ordered in out {
            let ctx = &mut self.ctx;
            ctx.key_ns = ordered.key_ns;
            ctx.late = ordered.late;
            for &stage in &self.lanes[index].stages {
                match &ordered.item {
                    LaneItem::Frame(frame) => self.stages[stage].on_frame(ctx, frame),
                    LaneItem::Pose(pose) => self.stages[stage].on_pose(ctx, pose),
                }
            }
            ctx.rays.clear();
            let poses = std::mem::take(&mut ctx.poses);
            self.hand_on_poses(index, poses);
        }
    }

    /// Takes note of an edge frame the server recorded but could not decode (its seq counts as
    /// received, so it is not a gap): counted in [`SessionStatus::undecodable_frames`].
    pub fn on_undecodable(&mut self, seq: u64) {
        if self.seqs.take(seq) {
            self.seqs.undecodable += 1;
        }
    }

    /// Lets every queued frame through in sample-time order and hands on whatever the stages
    /// hold back. Call at the end of a session (a snapshot of a live session does not: it shows
    /// what has left the queues).
    pub fn flush(&mut self) {
        for index in 0..self.lanes.len() {
            let mut out = Vec::new();
            self.lanes[index].queue.flush(&mut out);
            self.run_lane(index, out);
            let ctx = &mut self.ctx;
            for &stage in &self.lanes[index].stages {
                self.stages[stage].flush(ctx);
            }
            ctx.rays.clear();
            let poses = std::mem::take(&mut ctx.poses);
            self.hand_on_poses(index, poses);
        }
    }

    /// What the pipeline has done; voxel counts and metrics are recomputed when the map grew,
    /// at most once per [`METRICS_INTERVAL`] (cheap otherwise).
    pub fn status(&mut self) -> SessionStatus {
        self.status_at(Instant::now())
    }

    /// [`SessionPipeline::status`] with the caller's clock.
    pub fn status_at(&mut self, now: Instant) -> SessionStatus {
        self.refresh_metrics(now, false);
        self.current_status()
    }

    /// Recomputes the voxel counts and metrics if the map grew: at most once per
    /// [`METRICS_INTERVAL`] at `now`, or however recent the last computation with `always`.
    /// The heavy part of a status (the octree derived, its `.bt` view, the metrics).
    pub fn refresh_metrics(&mut self, now: Instant, always: bool) {
        let (maps, metrics) = (self.builtin.maps, self.builtin.metrics);
        let (low, high) = self.stages.split_at_mut(metrics);
        let maps: &dyn std::any::Any = low[maps].as_ref();
        let metrics: &mut dyn std::any::Any = high[0].as_mut();
        if let (Some(maps), Some(metrics)) = (
            maps.downcast_ref::<MapStage>(),
            metrics.downcast_mut::<MetricsStage>(),
        ) {
            if always {
                metrics.refresh_now(maps, now);
            } else {
                metrics.refresh(maps, now);
            }
        }
    }

    /// What the pipeline has done, with the voxel counts and metrics as last computed
    /// ([`SessionPipeline::refresh_metrics`]): cheap.
    pub fn current_status(&self) -> SessionStatus {
        let metrics = self.metrics_stage();
        let filters = self.filters_stage();
        let mut order = OrderStats::default();
        for lane in &self.lanes {
            let stats = lane.queue.stats();
            order.late += stats.late;
            order.releases += stats.releases;
            order.queued += stats.queued;
        }
        SessionStatus {
            frames: self.frames,
            samples: self.samples,
            revolutions: self.revolutions,
            occupied_voxels: metrics.occupied_voxels(),
            free_voxels: metrics.free_voxels(),
            metrics: metrics.metrics().cloned(),
            missing_frames: self.seqs.missing,
            stale_frames: self.seqs.stale,
            filled_frames: self.seqs.filled,
            undecodable_frames: self.seqs.undecodable,
            orphan_samples: self.assembly().orphan_samples(),
            abandoned_static_scans: self.assembly().abandoned_scans(),
            filter_failures: filters.failures(),
            filtered_out_points: filters.dropped_points(),
            points: self.maps().points(),
            positions: self.positions(),
            passes: self.passes(),
            pose: self.pose().and_then(PoseStage::status),
            fusion: self.fusion().map(FusionStage::status),
            late_frames: order.late,
            stream_releases: order.releases,
            queued_frames: order.queued,
        }
    }

    /// The trolley passes seen, in first-seen order: what the moving stage placed and holds,
    /// and the points the map stage took for each (empty without the moving stage).
    pub fn passes(&self) -> Vec<PassStatus> {
        let Some(moving) = self.moving() else {
            return Vec::new();
        };
        let maps = self.maps();
        moving
            .passes()
            .into_iter()
            .map(|mut pass| {
                pass.points = maps.pass(&pass.name).map_or(0, |p| p.points);
                pass
            })
            .collect()
    }

    /// The streams released so far (a stream fell too far behind), in order.
    pub fn releases(&self) -> &[Release] {
        &self.released
    }

    /// Named static-scan positions seen, in first-seen order.
    pub fn positions(&self) -> Vec<String> {
        self.maps().positions().to_vec()
    }

    /// Writes the current products into `dir` (created if missing): `map.bt`, `map.ot`,
    /// `cloud.ply` (the cloud through the snapshot filters) and, with a reference, `metrics.json`
    /// and `metrics.txt`; of the whole session, or of one `position`; then what the other
    /// stages write ([`Stage::snapshot`]; the pose stage: `trajectory.tum`, each pass's
    /// `passes/NAME/trajectory.tum`, `grid.pgm`, `grid.yaml`, `grid.png`). With no 3D data yet the `.bt`/`.ot` are valid empty
    /// trees and the PLY has no vertex (no metrics then). Each file is written under a
    /// temporary name and renamed, so a reader never sees half a file.
    pub fn write_snapshot(
        &mut self,
        dir: &Path,
        position: Option<&str>,
    ) -> Result<Snapshot, PipelineError> {
        self.prepare_snapshot(dir, position)?.write()
    }

    /// The first half of [`SessionPipeline::write_snapshot`]: checks `position`, creates `dir`
    /// and takes from each stage what its part needs ([`Stage::snapshot_job`]); the returned
    /// [`PreparedSnapshot`] writes the same bytes later, without the pipeline, so a daemon holds
    /// its pipeline only for the copies.
    pub fn prepare_snapshot(
        &mut self,
        dir: &Path,
        position: Option<&str>,
    ) -> Result<PreparedSnapshot, PipelineError> {
        let maps = self.maps();
        if let Some(name) = position
            && maps.position(name).is_none()
        {
            return Err(PipelineError::UnknownPosition {
                name: name.to_string(),
                known: maps.positions().join(", "),
            });
        }
        std::fs::create_dir_all(dir).map_err(|source| PipelineError::Write {
            path: dir.to_path_buf(),
            source,
        })?;
        // The map's files first (map.bt, map.ot, cloud.ply, metrics), then the others' in order.
        let (maps, metrics) = (self.builtin.maps, self.builtin.metrics);
        let order = [maps, metrics]
            .into_iter()
            .chain((0..self.stages.len()).filter(|&i| i != maps && i != metrics));
        let mut parts = Vec::with_capacity(self.stages.len());
        for index in order {
            let part = match self.stages[index].snapshot_job(position) {
                Some(job) => SnapshotPart::Job(job),
                None => {
                    let mut writer = SnapshotWriter::new(dir, position);
                    self.stages[index].snapshot(&mut writer)?;
                    SnapshotPart::Written(writer.snapshot.files)
                }
            };
            parts.push(part);
        }
        Ok(PreparedSnapshot {
            dir: dir.to_path_buf(),
            position: position.map(str::to_owned),
            parts,
        })
    }

    fn stage<T: 'static>(&self, index: usize) -> &T {
        let stage: &dyn std::any::Any = self.stages[index].as_ref();
        stage
            .downcast_ref::<T>()
            .expect("a built-in stage at its index")
    }

    /// The session's octree stage (its maps and cloud).
    pub fn maps(&self) -> &MapStage {
        self.stage(self.builtin.maps)
    }

    /// The assembly stage (its static scans, when [`Products::static_scans`] keeps them).
    pub fn assembly(&self) -> &AssemblyStage {
        self.stage(self.builtin.assembly)
    }

    fn filters_stage(&self) -> &FilterStage {
        self.stage(self.builtin.filters)
    }

    fn metrics_stage(&self) -> &MetricsStage {
        self.stage(self.builtin.metrics)
    }

    /// The pose stage, when [`Products::trajectory`] is on.
    pub fn pose(&self) -> Option<&PoseStage> {
        self.builtin.pose.map(|index| self.stage(index))
    }

    /// The moving stage (assembly along movement), when [`Products::trajectory`] is on.
    pub fn moving(&self) -> Option<&MovingStage> {
        self.builtin.moving.map(|index| self.stage(index))
    }

    /// The moving stage to configure ([`MovingStage::set_options`]) before the first frame.
    pub fn moving_mut(&mut self) -> Option<&mut MovingStage> {
        let index = self.builtin.moving?;
        let stage: &mut dyn std::any::Any = self.stages[index].as_mut();
        stage.downcast_mut::<MovingStage>()
    }

    /// Starts pass `name`'s octree from `map` instead of an empty one (before the first
    /// frame): `scan3d assemble --moving` over several sessions grows one octree across them,
    /// the same as inserting all their bundles in order.
    pub fn seed_pass_map(&mut self, name: &str, map: VoxelMap) {
        let index = self.builtin.maps;
        let stage: &mut dyn std::any::Any = self.stages[index].as_mut();
        if let Some(maps) = stage.downcast_mut::<MapStage>() {
            maps.seed_pass(name, map);
        }
    }

    /// Takes the map stage out of the pipeline (its octrees and clouds), leaving an empty one.
    pub fn take_maps(&mut self) -> MapStage {
        let index = self.builtin.maps;
        let res = *self.maps().resolution();
        let stage: &mut dyn std::any::Any = self.stages[index].as_mut();
        let maps = stage
            .downcast_mut::<MapStage>()
            .expect("the map stage at its index");
        std::mem::replace(maps, MapStage::new(res, &self.settings, self.products))
    }

    fn pose_mut(&mut self) -> Option<&mut PoseStage> {
        let index = self.builtin.pose?;
        let stage: &mut dyn std::any::Any = self.stages[index].as_mut();
        stage.downcast_mut::<PoseStage>()
    }

    /// The session's time-sync models (recorded, or as the live server made them): the
    /// snapshot's trajectory is stamped on the server's clock through them.
    pub fn set_clock(&mut self, clock: crate::pose::timesync::SessionClock) {
        for stage in &mut self.stages {
            let stage: &mut dyn std::any::Any = stage.as_mut();
            if let Some(fusion) = stage.downcast_mut::<FusionStage>() {
                fusion.set_clock(clock.clone());
            }
        }
        if let Some(pose) = self.pose_mut() {
            pose.set_clock(clock);
        }
    }

    /// The yaw fusion stage (after the pose stage, with [`Products::trajectory`]).
    pub fn fusion(&self) -> Option<&FusionStage> {
        self.stages.iter().find_map(|stage| {
            let stage: &dyn std::any::Any = stage.as_ref();
            stage.downcast_ref::<FusionStage>()
        })
    }

    /// The 2D revolution collector, when [`Products::revolution_points`] is on.
    pub fn revolution_points(&self) -> Option<&RevolutionStage> {
        self.builtin.revolutions.map(|index| self.stage(index))
    }

    /// The reference map, when one is configured.
    pub fn reference(&self) -> Option<&LeafMap> {
        self.reference.as_deref()
    }

    /// Takes the assembly stage's static scans (with [`Products::static_scans`]), in start order.
    pub fn into_static_scans(mut self) -> Vec<scan3d_map::cloud::assembly::AssembledScan> {
        let assembly: &mut dyn std::any::Any = self.stages[self.builtin.assembly].as_mut();
        let assembly = assembly
            .downcast_mut::<AssemblyStage>()
            .expect("the assembly stage at its index");
        std::mem::replace(assembly, AssemblyStage::new(false)).into_bundles()
    }
}

// The daemon runs each session's pipeline on a worker thread.
const _: fn() = || {
    fn is_send<T: Send>() {}
    is_send::<SessionPipeline>();
};

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_protocol::{Command, Heartbeat, LidarRevolution, SensorId};
    use std::sync::Arc;

    fn heartbeat(seq: u64) -> Frame {
        Frame::new(1, seq, Heartbeat { sent_ns: seq })
    }

    #[test]
    fn sequence_numbers_count_gaps_stale_frames_and_undecodable_ones() {
        let mut p = SessionPipeline::new(&PipelineSettings::default()).unwrap();
        p.on_frame(&heartbeat(0));
        p.on_frame(&heartbeat(1));
        p.on_frame(&heartbeat(5)); // 2, 3, 4 missing
        p.on_frame(&heartbeat(3)); // after a later one: fills its gap
        p.on_frame(&heartbeat(3)); // now a duplicate: skipped
        p.on_undecodable(6);
        p.on_frame(&heartbeat(7));
        p.on_frame(&heartbeat(7)); // duplicate: skipped
        let s = p.status();
        assert_eq!(
            (
                s.frames,
                s.missing_frames,
                s.filled_frames,
                s.stale_frames,
                s.undecodable_frames
            ),
            (5, 2, 1, 2, 1)
        );
    }

    /// Sample times of the revolutions handed to [`Order`], and whether each came late.
    type Seen = Arc<std::sync::Mutex<Vec<(u64, bool)>>>;

    /// Records the sample times of the revolutions it is handed, in its own lane.
    struct Order(Seen);

    impl Stage for Order {
        fn name(&self) -> &'static str {
            "order"
        }

        fn streams(&self) -> &'static [StreamId] {
            &[StreamId::Rplidar, StreamId::Sweep]
        }

        fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
            if let Body::Revolution(rev) = &frame.body {
                self.0.lock().unwrap().push((rev.t1_ns, ctx.late));
            }
        }
    }

    fn revolution(seq: u64, sensor: SensorId, t1_ms: u64) -> Frame {
        let t1 = t1_ms * 1_000_000;
        let mut rev = LidarRevolution::new(sensor, t1 - 100_000_000, t1);
        rev.push(0.0, 1.0, 10, t1 - 50_000_000).unwrap();
        Frame::new(1, seq, rev)
    }

    fn ordered_pipeline() -> (SessionPipeline, Seen) {
        let seen = Arc::new(std::sync::Mutex::new(Vec::new()));
        // Without the pose stage: its poses would make the assembly lane release the Sweep too.
        let products = Products {
            trajectory: false,
            ..Products::default()
        };
        let mut p = SessionPipeline::with_products(&PipelineSettings::default(), products).unwrap();
        p.add_stage(Box::new(Order(Arc::clone(&seen))));
        (p, seen)
    }

    #[test]
    fn a_stage_sees_the_streams_it_takes_in_sample_time_order_not_arrival_order() {
        let (mut p, seen) = ordered_pipeline();
        // The Sweep revolution ending at 250 ms is sent after the RPLidar one ending at 300 ms.
        p.on_frame(&revolution(0, SensorId::RPLIDAR, 100));
        p.on_frame(&revolution(1, SensorId::SWEEP, 150));
        p.on_frame(&revolution(2, SensorId::RPLIDAR, 200));
        p.on_frame(&revolution(3, SensorId::RPLIDAR, 300));
        p.on_frame(&revolution(4, SensorId::SWEEP, 250));
        p.on_frame(&revolution(5, SensorId::SWEEP, 450));
        let times: Vec<u64> = seen
            .lock()
            .unwrap()
            .iter()
            .map(|(t, _)| t / 1_000_000)
            .collect();
        assert_eq!(
            times,
            [100, 150, 200, 250, 300],
            "450 waits for the RPLidar"
        );
        p.flush();
        assert_eq!(seen.lock().unwrap().len(), 6);
        assert_eq!(p.status().queued_frames, 0);
    }

    #[test]
    fn a_stream_that_stops_is_released_after_the_lateness_and_the_others_go_on() {
        let (mut p, seen) = ordered_pipeline();
        p.on_frame(&revolution(0, SensorId::SWEEP, 100));
        for i in 1..=20u64 {
            p.on_frame(&revolution(i, SensorId::RPLIDAR, 100 + 100 * i));
        }
        // Released once 1000 ms (the default lateness) behind: the RPLidar up to then is through.
        let status = p.status();
        assert_eq!(status.stream_releases, 1);
        assert!(
            seen.lock().unwrap().len() >= 19,
            "{:?}",
            seen.lock().unwrap()
        );
        // The Sweep comes back with an old revolution: handed on at once, marked late.
        p.on_frame(&revolution(21, SensorId::SWEEP, 600));
        assert_eq!(seen.lock().unwrap().last(), Some(&(600_000_000, true)));
        assert_eq!(p.status().late_frames, 1);
        assert_eq!(p.releases().len(), 1);
    }

    #[test]
    fn a_lost_frame_that_arrives_after_a_later_one_is_mapped_not_dropped() {
        let products = Products {
            revolution_points: true,
            ..Products::default()
        };
        let mut p = SessionPipeline::with_products(&PipelineSettings::default(), products).unwrap();
        p.on_frame(&revolution(0, SensorId::RPLIDAR, 100));
        p.on_frame(&revolution(2, SensorId::RPLIDAR, 300));
        p.on_frame(&revolution(1, SensorId::RPLIDAR, 200));
        p.flush();
        let totals = p.revolution_points().unwrap().totals()[&SensorId::RPLIDAR];
        assert_eq!(totals.revolutions, 3);
        let s = p.status();
        assert_eq!(
            (s.missing_frames, s.filled_frames, s.stale_frames),
            (0, 1, 0)
        );
    }

    #[test]
    fn a_session_that_starts_late_counts_the_frames_before_it_as_missing() {
        let mut p = SessionPipeline::new(&PipelineSettings::default()).unwrap();
        p.on_frame(&heartbeat(4));
        assert_eq!(p.status().missing_frames, 4);
    }

    #[test]
    fn server_commands_and_clock_models_have_their_own_numbers_and_are_not_processed() {
        let mut p = SessionPipeline::new(&PipelineSettings::default()).unwrap();
        p.on_frame(&heartbeat(0));
        p.on_frame(&Frame::new(1, 0, Command::StopStaticScan));
        // A recorded clock model numbered 5 in the server's sequence is no jump in the edge's.
        let model = scan3d_protocol::ClockModel {
            offset_ns: 1,
            skew_ppm: 0.0,
            error_bound_ns: 1,
            skew_bound_ppm: 0.0,
            ref_edge_ns: 0,
            fit_from_edge_ns: 0,
            fit_to_edge_ns: 0,
            valid_from_edge_ns: 0,
            min_delay_ns: 1,
            exchanges: 1,
        };
        p.on_frame(&Frame::new(1, 5, Body::ClockModel(model)));
        p.on_frame(&heartbeat(1));
        let s = p.status();
        assert_eq!((s.frames, s.stale_frames, s.missing_frames), (2, 0, 0));
    }

    #[test]
    fn revolutions_and_their_samples_are_counted_for_both_lidars() {
        let mut p = SessionPipeline::new(&PipelineSettings::default()).unwrap();
        for (seq, sensor, n) in [(0, SensorId::RPLIDAR, 3), (1, SensorId::SWEEP, 2)] {
            let mut rev = LidarRevolution::new(sensor, 0, 1_000);
            for i in 0..n {
                rev.push(i as f32, 1.0, 10, i).unwrap();
            }
            p.on_frame(&Frame::new(1, seq, rev));
        }
        let s = p.status();
        assert_eq!((s.revolutions, s.samples, s.points), (2, 5, 0));
    }

    #[test]
    fn bad_settings_are_refused_with_what_is_wrong() {
        let bad_res = PipelineSettings {
            resolution_m: 0.0,
            ..PipelineSettings::default()
        };
        let err = SessionPipeline::new(&bad_res).unwrap_err();
        assert!(err.to_string().contains("resolution"), "{err}");
        let bad_range = PipelineSettings {
            max_range_m: Some(f64::NAN),
            ..PipelineSettings::default()
        };
        let err = SessionPipeline::new(&bad_range).unwrap_err();
        assert!(matches!(err, PipelineError::MaxRange(_)), "{err}");
    }
}
