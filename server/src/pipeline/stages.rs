//! The built-in stages of a [`super::SessionPipeline`], in the order they run.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::assembly::{AssembledScan, StaticScanAssembler, cut_range};
use scan3d_map::cloud::filter::apply_all as apply_filters;
use scan3d_map::cloud::filter::{Filter, apply_all};
use scan3d_map::cloud::io::Encoding;
use scan3d_map::cloud::ply::write_ply_bundles;
use scan3d_map::cloud::scans::{RevolutionCollector, SensorTotals};
use scan3d_map::eval::{self, LeafMap, Metrics};
use scan3d_map::octree::Octree;
use scan3d_map::octree::{InsertStats, Resolution, VoxelMap};
use scan3d_protocol::{Body, Frame, SensorId, StaticScan};

use super::order::StreamId;
use super::snapshot::SnapshotWriter;
use super::{
    BasePose, METRICS_INTERVAL, NewBundle, PipelineError, PipelineSettings, Products, RaySource,
    SnapshotJob, Stage, StageContext, metrics,
};

/// The 2D revolution collector as a stage: every lidar revolution's samples as points in the
/// sensor's own scan plane, per sensor (`scan3d replay --out`'s `scans/<lidar>.ply`).
#[derive(Debug, Default)]
pub struct RevolutionStage {
    collector: RevolutionCollector,
}

impl RevolutionStage {
    /// An empty collector.
    pub fn new() -> Self {
        Self::default()
    }

    /// Totals per sensor.
    pub fn totals(&self) -> &std::collections::BTreeMap<SensorId, SensorTotals> {
        self.collector.totals()
    }

    /// Writes `dir/<sensor name>.ply` for every sensor seen; returns the files.
    pub fn write_ply_files(&self, dir: &Path) -> std::io::Result<Vec<PathBuf>> {
        self.collector.write_ply_files(dir)
    }
}

impl Stage for RevolutionStage {
    fn name(&self) -> &'static str {
        "revolutions"
    }

    fn streams(&self) -> &'static [StreamId] {
        &[StreamId::Rplidar, StreamId::Sweep, StreamId::OtherLidar]
    }

    fn on_frame(&mut self, _ctx: &mut StageContext, frame: &Frame) {
        self.collector.on_frame(frame);
    }
}

/// Static-scan assembly by eq. 1: every body goes to the assembler, and the origin groups it
/// completes go on in [`StageContext::rays`].
///
/// Unless asked to keep them, static scans are forgotten when the next one starts: the frames
/// come in sample-time order and the edge runs one scan at a time, so everything of the earlier
/// scans has come by then; one whose end message was lost is counted as abandoned (its points
/// were mapped as they came). The assembler's memory is bounded by one static scan.
#[derive(Debug)]
pub struct AssemblyStage {
    assembler: StaticScanAssembler,
    keep: bool,
    /// Whether its lane also takes the pass markers and the poses of `base` (for the moving
    /// stage that follows it).
    poses: bool,
    /// Orphan samples counted by assemblers already forgotten.
    forgotten_orphans: u64,
    /// Static scans forgotten.
    forgotten_scans: u64,
    /// Static scans forgotten without their end message.
    abandoned_scans: u64,
}

impl AssemblyStage {
    /// A stage that keeps every assembled scan with its points if `keep`.
    pub fn new(keep: bool) -> Self {
        Self::with_poses(keep, false)
    }

    /// [`AssemblyStage::new`] whose lane also takes the pass markers and the poses of `base`
    /// if `poses` (the moving stage follows it there).
    pub fn with_poses(keep: bool, poses: bool) -> Self {
        AssemblyStage {
            assembler: StaticScanAssembler::new(),
            keep,
            poses,
            forgotten_orphans: 0,
            forgotten_scans: 0,
            abandoned_scans: 0,
        }
    }

    /// Static-scan samples that could not be placed (their start or revolution never seen).
    pub fn orphan_samples(&self) -> u64 {
        self.forgotten_orphans + self.assembler.orphan_samples()
    }

    /// Static scans forgotten without their end message (it was lost): a later scan started.
    pub fn abandoned_scans(&self) -> u64 {
        self.abandoned_scans
    }

    /// Static scans started so far.
    pub fn static_scans(&self) -> u64 {
        self.forgotten_scans + self.assembler.scans().len() as u64
    }

    /// The scans held (all of them when keeping), in start order.
    pub fn scans(&self) -> &[AssembledScan] {
        self.assembler.scans()
    }

    /// The scans held, in start order.
    pub fn into_bundles(self) -> Vec<AssembledScan> {
        self.assembler.finish()
    }
}

impl Stage for AssemblyStage {
    fn name(&self) -> &'static str {
        "assembly"
    }

    fn streams(&self) -> &'static [StreamId] {
        if self.poses {
            &[
                StreamId::Sweep,
                StreamId::StaticScan,
                StreamId::Pass,
                StreamId::Poses,
            ]
        } else {
            &[StreamId::Sweep, StreamId::StaticScan]
        }
    }

    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
        // Forget the earlier scans when the next one starts, not when they finish: the last
        // revolution of a scan and its yaws may still come after its end message.
        let starts = matches!(frame.body, Body::StaticScan(StaticScan::Started(_)));
        if !self.keep && starts && !self.assembler.scans().is_empty() {
            let done = std::mem::take(&mut self.assembler);
            for scan in done.scans().iter().filter(|s| s.outcome.is_none()) {
                self.abandoned_scans += 1;
                tracing::warn!(
                    scan_id = scan.scan_id,
                    position = %scan.position.name,
                    "a static scan never reported its end (the message was lost); its points \
                     were mapped as they came and it is forgotten now that another one started"
                );
            }
            self.forgotten_orphans += done.orphan_samples();
            self.forgotten_scans += done.scans().len() as u64;
        }
        self.assembler.on_body(&frame.body);
        ctx.rays
            .extend(self.assembler.take_new().into_iter().map(|new| NewBundle {
                source: RaySource::Position(new.position),
                rays: new.rays,
            }));
    }
}

/// The per-revolution filters (`revolution_filters`: voxel grid, pass-through box), applied to
/// the origin groups each frame completed, together (the halves of one revolution).
#[derive(Debug)]
pub struct FilterStage {
    filters: Vec<Filter>,
    failures: u64,
    dropped_points: u64,
}

impl FilterStage {
    /// A stage applying `filters` in order.
    pub fn new(filters: Vec<Filter>) -> Self {
        FilterStage {
            filters,
            failures: 0,
            dropped_points: 0,
        }
    }

    /// Origin groups a filter failed on (logged and dropped).
    pub fn failures(&self) -> u64 {
        self.failures
    }

    /// Points in the groups a filter failed on (not mapped).
    pub fn dropped_points(&self) -> u64 {
        self.dropped_points
    }

    /// Filters the groups in `ctx` together; `key_ns` names the frame or pose in the log.
    fn filter(&mut self, ctx: &mut StageContext) {
        if self.filters.is_empty() || ctx.rays.is_empty() {
            return;
        }
        let groups: Vec<RayBundle> = ctx
            .rays
            .iter_mut()
            .map(|r| take_rays(&mut r.rays))
            .collect();
        let dropped: u64 = groups.iter().map(|g| g.points.len() as u64).sum();
        match apply_all(&self.filters, groups) {
            Ok(filtered) => {
                for (new, rays) in ctx.rays.iter_mut().zip(filtered) {
                    new.rays = rays;
                }
            }
            Err(e) => {
                self.failures += ctx.rays.len() as u64;
                // The points were moved out above; count what the groups held.
                self.dropped_points += dropped;
                tracing::warn!(
                    key_ns = ctx.key_ns,
                    groups = ctx.rays.len(),
                    "revolution filter failed, its points are dropped: {e}"
                );
                ctx.rays.clear();
            }
        }
    }
}

impl Stage for FilterStage {
    fn name(&self) -> &'static str {
        "filters"
    }

    fn on_frame(&mut self, ctx: &mut StageContext, _frame: &Frame) {
        self.filter(ctx);
    }

    fn on_pose(&mut self, ctx: &mut StageContext, _pose: &BasePose) {
        self.filter(ctx);
    }

    /// What the stages before it handed on at the session's end (the moving stage's last
    /// revolutions).
    fn flush(&mut self, ctx: &mut StageContext) {
        self.filter(ctx);
    }
}

/// Moves the points out, leaving the origin.
fn take_rays(rays: &mut RayBundle) -> RayBundle {
    RayBundle {
        origin: rays.origin,
        points: std::mem::take(&mut rays.points),
    }
}

/// One named position's (or pass's) octree.
#[derive(Debug)]
pub struct PositionMap {
    /// The position's (or pass's) name.
    pub name: String,
    /// Its octree (`None` when position maps, or octrees, are not kept).
    pub map: Option<VoxelMap>,
    /// Points inserted.
    pub points: u64,
}

/// Which part of the session a bundle of the cloud belongs to: an index into the positions or
/// into the passes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Part {
    Position(usize),
    Pass(usize),
}

/// Octree insertion (OctoMap's `insertPointCloud` from each group's origin, cut at
/// `max_range`) into the session's octree and its position's or pass's, and the growing cloud.
/// A pass's octree is kept whenever octrees are (a pass is the product of a trolley run, as a
/// position's is of a static scan, but there are few passes), a position's with
/// [`Products::position_maps`].
#[derive(Debug)]
pub struct MapStage {
    res: Resolution,
    settings: PipelineSettings,
    products: Products,
    session: VoxelMap,
    positions: Vec<PositionMap>,
    passes: Vec<PositionMap>,
    /// Filtered points within `max_range` with their origin and part (shared, so a snapshot
    /// takes the cloud without copying it).
    cloud: Vec<(Part, Arc<RayBundle>)>,
    points: u64,
}

impl MapStage {
    /// An empty stage at resolution `res` keeping `products`.
    pub fn new(res: Resolution, settings: &PipelineSettings, products: Products) -> Self {
        MapStage {
            res,
            settings: settings.clone(),
            products,
            session: VoxelMap::new(res, settings.sensor),
            positions: Vec::new(),
            passes: Vec::new(),
            cloud: Vec::new(),
            points: 0,
        }
    }

    /// The resolution of its octrees.
    pub fn resolution(&self) -> &Resolution {
        &self.res
    }

    /// The session's octree (every position and pass).
    pub fn session_map(&self) -> &VoxelMap {
        &self.session
    }

    /// The position called `name`, if seen.
    pub fn position(&self, name: &str) -> Option<&PositionMap> {
        self.positions.iter().find(|p| p.name == name)
    }

    /// Names of the positions seen, in first-seen order.
    pub fn positions(&self) -> Vec<String> {
        self.positions.iter().map(|p| p.name.clone()).collect()
    }

    /// The pass called `name`, if any of its points was mapped (or its map seeded).
    pub fn pass(&self, name: &str) -> Option<&PositionMap> {
        self.passes.iter().find(|p| p.name == name)
    }

    /// Names of the passes mapped, in first-seen order.
    pub fn passes(&self) -> Vec<String> {
        self.passes.iter().map(|p| p.name.clone()).collect()
    }

    /// Takes pass `name`'s octree out (offline assembly hands it to the next session's
    /// pipeline, [`MapStage::seed_pass`]).
    pub fn take_pass_map(&mut self, name: &str) -> Option<VoxelMap> {
        self.passes
            .iter_mut()
            .find(|p| p.name == name)
            .and_then(|p| p.map.take())
    }

    /// Starts pass `name`'s octree from `map` (its points count from zero).
    pub fn seed_pass(&mut self, name: &str, map: VoxelMap) {
        let index = self.pass_index(name);
        self.passes[index].map = Some(map);
    }

    /// Points inserted into the session's octree.
    pub fn points(&self) -> u64 {
        self.points
    }

    /// Sums of the session octree's insertions.
    pub fn insert_stats(&self) -> InsertStats {
        self.session.totals()
    }

    /// The cloud of the session (`None`) or of one position, as origin groups in insertion
    /// order (empty when the cloud is not kept).
    pub fn cloud(&self, position: Option<&str>) -> Vec<RayBundle> {
        self.shared_cloud(position)
            .into_iter()
            .map(Arc::unwrap_or_clone)
            .collect()
    }

    /// The cloud of pass `name`, as origin groups in insertion order (empty when the cloud is
    /// not kept or the pass is unknown).
    pub fn pass_cloud(&self, name: &str) -> Vec<RayBundle> {
        self.shared_pass_cloud(name)
            .into_iter()
            .map(Arc::unwrap_or_clone)
            .collect()
    }

    /// [`MapStage::cloud`] as shared handles (no point is copied).
    fn shared_cloud(&self, position: Option<&str>) -> Vec<Arc<RayBundle>> {
        let part = match position {
            None => None,
            Some(name) => match self.positions.iter().position(|p| p.name == name) {
                Some(i) => Some(Part::Position(i)),
                None => return Vec::new(),
            },
        };
        self.parts_cloud(part)
    }

    fn shared_pass_cloud(&self, name: &str) -> Vec<Arc<RayBundle>> {
        match self.passes.iter().position(|p| p.name == name) {
            Some(i) => self.parts_cloud(Some(Part::Pass(i))),
            None => Vec::new(),
        }
    }

    /// The cloud's bundles of `part` (all with `None`).
    fn parts_cloud(&self, part: Option<Part>) -> Vec<Arc<RayBundle>> {
        self.cloud
            .iter()
            .filter(|(p, _)| part.is_none_or(|want| want == *p))
            .map(|(_, rays)| Arc::clone(rays))
            .collect()
    }

    /// What a snapshot of the session (`position` `None`) or of one position needs: a copy of
    /// its octree's voxels and the cloud's handles, taken while the pipeline is held; the
    /// octree is derived, filtered and written later ([`MapSnapshot::write`]). A session's
    /// snapshot also takes each named pass's.
    fn take_snapshot(&self, position: Option<&str>) -> (MapSnapshot, Vec<(String, MapSnapshot)>) {
        let map = match position {
            None => Some(&self.session),
            Some(name) => self.position(name).and_then(|p| p.map.as_ref()),
        };
        let whole = MapSnapshot {
            map: map.cloned(),
            cloud: self.shared_cloud(position),
            res: self.res,
            settings: self.settings.clone(),
        };
        let passes = match position {
            Some(_) => Vec::new(),
            None => self
                .passes
                .iter()
                .filter(|pass| !pass.name.is_empty())
                .map(|pass| {
                    let taken = MapSnapshot {
                        map: pass.map.clone(),
                        cloud: self.shared_pass_cloud(&pass.name),
                        res: self.res,
                        settings: self.settings.clone(),
                    };
                    (pass.name.clone(), taken)
                })
                .collect(),
        };
        (whole, passes)
    }

    fn max_range(&self) -> f64 {
        self.settings.max_range_m.unwrap_or(-1.0)
    }

    fn position_index(&mut self, name: &str) -> usize {
        match self.positions.iter().position(|p| p.name == name) {
            Some(i) => i,
            None => {
                self.positions.push(PositionMap {
                    name: name.to_string(),
                    map: (self.products.octrees && self.products.position_maps)
                        .then(|| VoxelMap::new(self.res, self.settings.sensor)),
                    points: 0,
                });
                self.positions.len() - 1
            }
        }
    }

    fn pass_index(&mut self, name: &str) -> usize {
        match self.passes.iter().position(|p| p.name == name) {
            Some(i) => i,
            None => {
                self.passes.push(PositionMap {
                    name: name.to_string(),
                    map: self
                        .products
                        .octrees
                        .then(|| VoxelMap::new(self.res, self.settings.sensor)),
                    points: 0,
                });
                self.passes.len() - 1
            }
        }
    }

    /// Inserts the groups in `ctx` into the session's octree and their part's, and keeps them
    /// in the cloud.
    fn insert(&mut self, ctx: &StageContext) {
        let max_range = self.max_range();
        for new in &ctx.rays {
            let part = match &new.source {
                RaySource::Position(name) => Part::Position(self.position_index(name)),
                RaySource::Pass(name) => Part::Pass(self.pass_index(name)),
            };
            let n = new.rays.points.len() as u64;
            self.points += n;
            let part_map = match part {
                Part::Position(i) => &mut self.positions[i],
                Part::Pass(i) => &mut self.passes[i],
            };
            part_map.points += n;
            if self.products.octrees {
                self.session.insert_bundle(&new.rays, max_range);
                if let Some(map) = &mut part_map.map {
                    map.insert_bundle(&new.rays, max_range);
                }
            }
            if self.products.cloud {
                let mut rays = new.rays.clone();
                if max_range >= 0.0 {
                    cut_range(std::slice::from_mut(&mut rays), max_range);
                }
                self.cloud.push((part, Arc::new(rays)));
            }
        }
    }
}

impl Stage for MapStage {
    fn name(&self) -> &'static str {
        "map"
    }

    fn snapshot(&mut self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        let position = out.snapshot.position.clone();
        let (whole, passes) = self.take_snapshot(position.as_deref());
        write_map_snapshot(whole, passes, out)
    }

    fn snapshot_job(&self, position: Option<&str>) -> Option<SnapshotJob> {
        let (whole, passes) = self.take_snapshot(position);
        Some(Box::new(move |out: &mut SnapshotWriter| {
            write_map_snapshot(whole, passes, out)
        }))
    }

    fn on_frame(&mut self, ctx: &mut StageContext, _frame: &Frame) {
        self.insert(ctx);
    }

    fn on_pose(&mut self, ctx: &mut StageContext, _pose: &BasePose) {
        self.insert(ctx);
    }

    /// What the stages before it handed on at the session's end (the moving stage's last
    /// revolutions).
    fn flush(&mut self, ctx: &mut StageContext) {
        self.insert(ctx);
    }
}

/// Writes the session's (or position's) map files, then each pass's `passes/NAME/map.bt` and
/// `passes/NAME/cloud.ply` (beside the pose stage's `passes/NAME/trajectory.tum`).
fn write_map_snapshot(
    whole: MapSnapshot,
    passes: Vec<(String, MapSnapshot)>,
    out: &mut SnapshotWriter,
) -> Result<(), PipelineError> {
    whole.write(out)?;
    // The whole map's numbers and leaves (for the metrics) stay those of the session.
    for (name, pass) in passes {
        let subdir = Path::new("passes").join(super::pose_stage::path_safe(&name));
        let (bt, ply) = pass.bytes(&out.snapshot.dir.join(&subdir))?;
        out.write_file_in(&subdir, "map.bt", &bt)?;
        out.write_file_in(&subdir, "cloud.ply", &ply)?;
    }
    Ok(())
}

/// A map's part of a snapshot, taken by [`MapStage::take_snapshot`].
struct MapSnapshot {
    map: Option<VoxelMap>,
    cloud: Vec<Arc<RayBundle>>,
    res: Resolution,
    settings: PipelineSettings,
}

impl MapSnapshot {
    /// The `.bt` and the binary PLY (through the snapshot filters) of a pass's part; `dir`
    /// names the files in errors.
    fn bytes(self, dir: &Path) -> Result<(Vec<u8>, Vec<u8>), PipelineError> {
        let tree = self.map.map_or_else(
            || Octree::empty(self.res, self.settings.sensor),
            |m| m.to_octree(),
        );
        let mut cloud: Vec<RayBundle> = self.cloud.into_iter().map(Arc::unwrap_or_clone).collect();
        if !self.settings.snapshot_filters.is_empty() && !cloud.is_empty() {
            cloud = apply_filters(&self.settings.snapshot_filters, cloud)?;
        }
        let mut ply = Vec::new();
        write_ply_bundles(&mut ply, &cloud, Encoding::Binary).map_err(|source| {
            PipelineError::Write {
                path: dir.join("cloud.ply"),
                source,
            }
        })?;
        Ok((tree.to_bt_bytes(), ply))
    }

    /// Writes `map.bt`, `map.ot` and `cloud.ply` (through the snapshot filters) and hands the
    /// `.bt`'s leaves on to the metrics.
    fn write(self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        let tree = self.map.map_or_else(
            || Octree::empty(self.res, self.settings.sensor),
            |m| m.to_octree(),
        );
        let bt = tree.to_bt_bytes();
        let leaves = metrics::leaf_map_of_bt(&tree, &bt);
        let mut cloud: Vec<RayBundle> = self.cloud.into_iter().map(Arc::unwrap_or_clone).collect();
        if !self.settings.snapshot_filters.is_empty() && !cloud.is_empty() {
            cloud = apply_filters(&self.settings.snapshot_filters, cloud)?;
        }
        let mut ply = Vec::new();
        write_ply_bundles(&mut ply, &cloud, Encoding::Binary).map_err(|source| {
            PipelineError::Write {
                path: out.snapshot.dir.join("cloud.ply"),
                source,
            }
        })?;
        out.write_file("map.bt", &bt)?;
        out.write_file("map.ot", &tree.to_ot_bytes())?;
        out.write_file("cloud.ply", &ply)?;
        out.snapshot.nodes = tree.num_nodes() as u64;
        out.snapshot.occupied_voxels = leaves.occupied_voxels();
        out.snapshot.free_voxels = leaves.free_voxels();
        out.snapshot.points = cloud.iter().map(|c| c.points.len() as u64).sum();
        out.leaves = Some(leaves);
        Ok(())
    }
}

/// Voxel counts and the metrics against the reference: recomputed from the session's octree
/// when the map grew, at most once per [`METRICS_INTERVAL`]; a snapshot's metrics come from the
/// octree it wrote.
#[derive(Debug)]
pub struct MetricsStage {
    reference: Option<Arc<LeafMap>>,
    /// When last computed.
    at: Option<Instant>,
    /// Points inserted when it was computed (nothing new since: no recompute).
    points: u64,
    occupied: u64,
    free: u64,
    metrics: Option<Metrics>,
}

impl MetricsStage {
    /// A stage comparing against `reference`, if any.
    pub fn new(reference: Option<Arc<LeafMap>>) -> Self {
        MetricsStage {
            reference,
            at: None,
            points: 0,
            occupied: 0,
            free: 0,
            metrics: None,
        }
    }

    /// Occupied voxels (depth 16) of the session's octree as last computed.
    pub fn occupied_voxels(&self) -> u64 {
        self.occupied
    }

    /// Free voxels of the session's octree as last computed.
    pub fn free_voxels(&self) -> u64 {
        self.free
    }

    /// The metrics as last computed (a reference is configured and there is a map).
    pub fn metrics(&self) -> Option<&Metrics> {
        self.metrics.as_ref()
    }

    /// Recomputes from `maps` if the map grew and the last computation is [`METRICS_INTERVAL`]
    /// old at `now`.
    pub fn refresh(&mut self, maps: &MapStage, now: Instant) {
        let due = self
            .at
            .is_none_or(|at| now.saturating_duration_since(at) >= METRICS_INTERVAL);
        if due {
            self.refresh_now(maps, now);
        }
    }

    /// Recomputes from `maps` if the map grew, however recent the last computation (a worker
    /// about to be retired reports its final numbers).
    pub fn refresh_now(&mut self, maps: &MapStage, now: Instant) {
        if self.points == maps.points() {
            return;
        }
        let leaves = metrics::leaf_map(&maps.session_map().to_octree());
        self.occupied = leaves.occupied_voxels();
        self.free = leaves.free_voxels();
        self.metrics = self.evaluate(&leaves);
        self.points = maps.points();
        self.at = Some(now);
    }

    fn evaluate(&self, leaves: &LeafMap) -> Option<Metrics> {
        let reference = self.reference.as_ref()?;
        eval::evaluate(reference, leaves, None)
            .inspect_err(|e| tracing::debug!("no metrics yet: {e}"))
            .ok()
    }
}

impl Stage for MetricsStage {
    fn name(&self) -> &'static str {
        "metrics"
    }

    /// Nothing per frame: the numbers are computed from the map when asked
    /// ([`MetricsStage::refresh`]) and for each snapshot.
    fn on_frame(&mut self, _ctx: &mut StageContext, _frame: &Frame) {}

    fn snapshot(&mut self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        write_metrics(self.reference.as_deref(), out)
    }

    fn snapshot_job(&self, _position: Option<&str>) -> Option<SnapshotJob> {
        let reference = self.reference.clone();
        Some(Box::new(move |out: &mut SnapshotWriter| {
            write_metrics(reference.as_deref(), out)
        }))
    }
}

/// Writes `metrics.json` and `metrics.txt` of the leaves the map's part of the snapshot handed
/// on, against `reference` (nothing without a reference or without 3D data).
fn write_metrics(
    reference: Option<&LeafMap>,
    out: &mut SnapshotWriter,
) -> Result<(), PipelineError> {
    let Some(leaves) = &out.leaves else {
        return Ok(());
    };
    let Some(reference) = reference else {
        return Ok(());
    };
    if leaves.num_leaves() == 0 {
        return Ok(());
    }
    let m = eval::evaluate(reference, leaves, None)?;
    let mut json = serde_json::to_vec_pretty(&m).map_err(|e| PipelineError::Write {
        path: out.snapshot.dir.join("metrics.json"),
        source: e.into(),
    })?;
    json.push(b'\n');
    out.write_file("metrics.json", &json)?;
    let mut text = Vec::new();
    metrics::write_metrics_table(&m, &mut text).map_err(|source| PipelineError::Write {
        path: out.snapshot.dir.join("metrics.txt"),
        source,
    })?;
    out.write_file("metrics.txt", &text)?;
    out.snapshot.metrics = Some(m);
    Ok(())
}
