//! The server's mapping pipeline: per session, frames in sequence order go through stages
//! (static-scan assembly by eq. 1, the Table II filters, octree insertion, metrics against a
//! reference), and the products (cloud, octree, metrics) grow as the frames come in.
//!
//! One pipeline, three drivers: `scan3d serve` feeds it live from ingest (through a bounded
//! queue; it catches up from the recording when it falls behind), `scan3d replay` and the
//! offline `scan3d assemble` / `scan3d map` feed it a recorded session frame by frame
//! ([`offline`]). So the live products and the replayed ones are the same bytes.
//!
//! # Stages
//!
//! A [`Stage`] takes frames and keeps its products. The stages of a [`SessionPipeline`] run in
//! this order for every frame; a [`StageContext`] carries what one stage hands to the next:
//!
//! | stage | takes | hands on / keeps |
//! | --- | --- | --- |
//! | [`RevolutionStage`] (optional) | lidar revolutions | per-sensor 2D points, `scans/<lidar>.ply` |
//! | [`AssemblyStage`] | every body (eq. 1 joins Sweep revolutions and static-scan messages) | the origin groups (one per half revolution) completed by this frame, in [`StageContext::rays`] |
//! | [`FilterStage`] | [`StageContext::rays`] | the same groups through `revolution_filters` (voxel grid, pass-through) |
//! | [`MapStage`] | [`StageContext::rays`] | one octree per session and per named position (OctoMap's `insertPointCloud`, `max_range` cut), the growing cloud |
//!
//! Metrics against the reference are computed from the session's (or a position's) octree when
//! [`SessionPipeline::status`] asks (at most once per [`METRICS_INTERVAL`]) and at every
//! snapshot. The snapshot filters (SOR, Gaussian: they need neighbours across revolutions) only
//! touch the cloud a snapshot writes, never the octree.
//!
//! # Memory
//!
//! Bounded by the map, not the session: no frame is kept; the assembler forgets the static
//! scans that have finished (their rays handed on) when the next one starts, unless
//! [`Products::static_scans`] asks to keep them, as `scan3d assemble` does; the cloud holds the
//! filtered points (turn it off with [`Products::cloud`] when only the octree is wanted, as
//! `scan3d map` does).

pub mod edge_activity;
pub mod live;
mod metrics;
pub mod offline;
mod snapshot;
mod stages;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use scan3d_map::cloud::assembly::NewRays;
use scan3d_map::cloud::filter::Filter;
use scan3d_map::eval::{EvalError, LeafMap, Metrics};
use scan3d_map::octree::{OctreeError, Resolution, SensorModel};
use scan3d_protocol::{Body, Frame};

pub use metrics::{load_reference, write_metrics_table};
pub use snapshot::Snapshot;
pub use stages::{AssemblyStage, FilterStage, MapStage, PositionMap, RevolutionStage};

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
    /// Frames that arrived with a sequence number already passed (duplicates, late resends):
    /// skipped.
    pub stale_frames: u64,
    /// Frames the server could not decode (e.g. a body of a newer protocol): skipped.
    pub undecodable_frames: u64,
    /// Static-scan samples that could not be placed (their scan start or revolution was never
    /// seen): skipped.
    pub orphan_samples: u64,
    /// Points inserted into the session's octree (after the revolution filters).
    pub points: u64,
    /// Named static-scan positions seen, in first-seen order.
    pub positions: Vec<String>,
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
}

impl Default for Products {
    /// What the live daemon keeps: octrees per session and position, and the cloud.
    fn default() -> Self {
        Products {
            revolution_points: false,
            position_maps: true,
            cloud: true,
            static_scans: false,
            octrees: true,
        }
    }
}

/// What a frame hands from one stage to the next.
#[derive(Debug, Default)]
pub struct StageContext {
    /// Origin groups (one per half revolution of a static scan, world frame) completed by the
    /// current frame, with their position; the assembly stage fills it, later stages transform
    /// or consume it. Emptied after each frame.
    pub rays: Vec<NewRays>,
}

/// One stage: takes frames, keeps its products.
pub trait Stage {
    /// Takes one frame of the session (in sequence order) and what the earlier stages handed
    /// on for it in `ctx`.
    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame);
    /// Called when the session's frames end (or before a snapshot): hand on what is pending.
    fn flush(&mut self, ctx: &mut StageContext) {
        let _ = ctx;
    }
}

/// Where the edge's sequence numbers stand.
#[derive(Debug, Default, Clone, Copy)]
struct SeqTrack {
    /// The next edge sequence number expected (`None` before the first frame).
    next: Option<u64>,
    missing: u64,
    stale: u64,
    undecodable: u64,
}

impl SeqTrack {
    /// Accounts for edge seq `seq`; `false` if it was already passed (to be skipped).
    fn take(&mut self, seq: u64) -> bool {
        let next = self.next.unwrap_or(0);
        if self.next.is_some() && seq < next {
            self.stale += 1;
            return false;
        }
        if seq > next {
            let gap = seq - next;
            self.missing = self.missing.saturating_add(gap);
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
}

/// Voxel counts and metrics as of the last refresh.
#[derive(Debug, Default)]
struct Refreshed {
    at: Option<Instant>,
    /// Points inserted when it was computed (nothing new since: no recompute).
    points: u64,
    occupied: u64,
    free: u64,
    metrics: Option<Metrics>,
}

/// One session's pipeline: feed its frames in sequence order with [`SessionPipeline::on_frame`],
/// read [`SessionPipeline::status`], write products with [`SessionPipeline::write_snapshot`].
/// `Send`, so a daemon can run it on a worker thread.
pub struct SessionPipeline {
    settings: PipelineSettings,
    products: Products,
    reference: Option<Arc<LeafMap>>,
    revolutions_2d: Option<RevolutionStage>,
    assembly: AssemblyStage,
    filters: FilterStage,
    maps: MapStage,
    /// Stages added with [`SessionPipeline::add_stage`], run after the built-in ones.
    extra: Vec<Box<dyn Stage + Send>>,
    ctx: StageContext,
    seqs: SeqTrack,
    frames: u64,
    samples: u64,
    revolutions: u64,
    refreshed: Refreshed,
}

impl std::fmt::Debug for SessionPipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionPipeline")
            .field("settings", &self.settings)
            .field("products", &self.products)
            .field("frames", &self.frames)
            .field("extra_stages", &self.extra.len())
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
        if let Some(max) = settings.max_range_m
            && (max.is_nan() || max <= 0.0)
        {
            return Err(PipelineError::MaxRange(max));
        }
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
        Ok(SessionPipeline {
            settings: settings.clone(),
            products,
            reference,
            revolutions_2d: products.revolution_points.then(RevolutionStage::new),
            assembly: AssemblyStage::new(products.static_scans),
            filters: FilterStage::new(settings.revolution_filters.clone()),
            maps: MapStage::new(res, settings, products),
            extra: Vec::new(),
            ctx: StageContext::default(),
            seqs: SeqTrack::default(),
            frames: 0,
            samples: 0,
            revolutions: 0,
            refreshed: Refreshed::default(),
        })
    }

    /// The settings it was built with.
    pub fn settings(&self) -> &PipelineSettings {
        &self.settings
    }

    /// Adds a stage that runs after the built-in ones for every later frame.
    pub fn add_stage(&mut self, stage: Box<dyn Stage + Send>) {
        self.extra.push(stage);
    }

    /// Takes the session's next frame. Frames must come in sequence order: one whose edge
    /// sequence number was already passed is skipped and counted
    /// ([`SessionStatus::stale_frames`]); a jump is a gap, counted
    /// ([`SessionStatus::missing_frames`]) and logged, and the frame is processed. Frames the
    /// server made (commands, clock models: their own numbering) are not processed.
    pub fn on_frame(&mut self, frame: &Frame) {
        if frame.body.is_server_made() || !self.seqs.take(frame.seq) {
            return;
        }
        self.frames += 1;
        if let Body::Revolution(rev) = &frame.body {
            self.revolutions += 1;
            self.samples += rev.samples.len() as u64;
        }
        let ctx = &mut self.ctx;
        if let Some(stage) = &mut self.revolutions_2d {
            stage.on_frame(ctx, frame);
        }
        self.assembly.on_frame(ctx, frame);
        self.filters.on_frame(ctx, frame);
        self.maps.on_frame(ctx, frame);
        for stage in &mut self.extra {
            stage.on_frame(ctx, frame);
        }
        ctx.rays.clear();
    }

    /// Takes note of an edge frame the server recorded but could not decode (its seq counts as
    /// received, so it is not a gap): counted in [`SessionStatus::undecodable_frames`].
    pub fn on_undecodable(&mut self, seq: u64) {
        if self.seqs.take(seq) {
            self.seqs.undecodable += 1;
        }
    }

    /// Hands on whatever the stages hold back (nothing today: every origin group is complete
    /// once the body that made it was taken). Call at the end of a session.
    pub fn flush(&mut self) {
        let ctx = &mut self.ctx;
        if let Some(stage) = &mut self.revolutions_2d {
            stage.flush(ctx);
        }
        self.assembly.flush(ctx);
        self.filters.flush(ctx);
        self.maps.flush(ctx);
        for stage in &mut self.extra {
            stage.flush(ctx);
        }
        ctx.rays.clear();
    }

    /// What the pipeline has done; voxel counts and metrics are recomputed when the map grew,
    /// at most once per [`METRICS_INTERVAL`] (cheap otherwise).
    pub fn status(&mut self) -> SessionStatus {
        self.status_at(Instant::now())
    }

    /// [`SessionPipeline::status`] with the caller's clock.
    pub fn status_at(&mut self, now: Instant) -> SessionStatus {
        let due = self
            .refreshed
            .at
            .is_none_or(|at| now.saturating_duration_since(at) >= METRICS_INTERVAL);
        if due && self.refreshed.points != self.maps.points() {
            self.refresh(now);
        }
        SessionStatus {
            frames: self.frames,
            samples: self.samples,
            revolutions: self.revolutions,
            occupied_voxels: self.refreshed.occupied,
            free_voxels: self.refreshed.free,
            metrics: self.refreshed.metrics.clone(),
            missing_frames: self.seqs.missing,
            stale_frames: self.seqs.stale,
            undecodable_frames: self.seqs.undecodable,
            orphan_samples: self.assembly.orphan_samples(),
            points: self.maps.points(),
            positions: self.positions(),
        }
    }

    fn refresh(&mut self, now: Instant) {
        let leaves = metrics::leaf_map(&self.maps.session_map().to_octree());
        self.refreshed.occupied = leaves.occupied_voxels();
        self.refreshed.free = leaves.free_voxels();
        self.refreshed.metrics = self.reference.as_ref().and_then(|reference| {
            scan3d_map::eval::evaluate(reference, &leaves, None)
                .inspect_err(|e| tracing::debug!("no metrics yet: {e}"))
                .ok()
        });
        self.refreshed.points = self.maps.points();
        self.refreshed.at = Some(now);
    }

    /// Named static-scan positions seen, in first-seen order.
    pub fn positions(&self) -> Vec<String> {
        self.maps.positions().to_vec()
    }

    /// Writes the current products into `dir` (created if missing): `map.bt`, `map.ot`,
    /// `cloud.ply` (the cloud through the snapshot filters) and, with a reference, `metrics.json`
    /// and `metrics.txt`; of the whole session, or of one `position`. With no 3D data yet the
    /// `.bt`/`.ot` are valid empty trees and the PLY has no vertex (no metrics then). Each file
    /// is written under a temporary name and renamed, so a reader never sees half a file.
    pub fn write_snapshot(
        &mut self,
        dir: &Path,
        position: Option<&str>,
    ) -> Result<Snapshot, PipelineError> {
        snapshot::write(self, dir, position)
    }

    /// The session's octree stage (its maps and cloud).
    pub fn maps(&self) -> &MapStage {
        &self.maps
    }

    /// The assembly stage (its static scans, when [`Products::static_scans`] keeps them).
    pub fn assembly(&self) -> &AssemblyStage {
        &self.assembly
    }

    /// The 2D revolution collector, when [`Products::revolution_points`] is on.
    pub fn revolution_points(&self) -> Option<&RevolutionStage> {
        self.revolutions_2d.as_ref()
    }

    /// The reference map, when one is configured.
    pub fn reference(&self) -> Option<&LeafMap> {
        self.reference.as_deref()
    }

    /// Takes the assembly stage's static scans (with [`Products::static_scans`]), in start order.
    pub fn into_static_scans(self) -> Vec<scan3d_map::cloud::assembly::AssembledScan> {
        self.assembly.into_bundles()
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

    fn heartbeat(seq: u64) -> Frame {
        Frame::new(1, seq, Heartbeat { sent_ns: seq })
    }

    #[test]
    fn sequence_numbers_count_gaps_stale_frames_and_undecodable_ones() {
        let mut p = SessionPipeline::new(&PipelineSettings::default()).unwrap();
        p.on_frame(&heartbeat(0));
        p.on_frame(&heartbeat(1));
        p.on_frame(&heartbeat(5)); // 2, 3, 4 missing
        p.on_frame(&heartbeat(3)); // late: skipped
        p.on_undecodable(6);
        p.on_frame(&heartbeat(7));
        p.on_frame(&heartbeat(7)); // duplicate: skipped
        let s = p.status();
        assert_eq!(
            (
                s.frames,
                s.missing_frames,
                s.stale_frames,
                s.undecodable_frames
            ),
            (4, 3, 2, 1)
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
