//! The built-in stages of a [`super::SessionPipeline`], in the order they run.

use std::path::{Path, PathBuf};

use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::assembly::{AssembledScan, StaticScanAssembler, cut_range};
use scan3d_map::cloud::filter::{Filter, apply_all};
use scan3d_map::cloud::scans::{RevolutionCollector, SensorTotals};
use scan3d_map::octree::{InsertStats, Resolution, VoxelMap};
use scan3d_protocol::{Body, Frame, SensorId, StaticScan};

use super::{PipelineSettings, Products, Stage, StageContext};

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
    fn on_frame(&mut self, _ctx: &mut StageContext, frame: &Frame) {
        self.collector.on_frame(frame);
    }
}

/// Static-scan assembly by eq. 1: every body goes to the assembler, and the origin groups it
/// completes go on in [`StageContext::rays`].
///
/// Unless asked to keep them, static scans are forgotten once they have finished and their
/// groups were handed on: when the next scan starts and every scan held has ended, the
/// assembler starts afresh, so its memory is bounded by one static scan, not the session.
#[derive(Debug)]
pub struct AssemblyStage {
    assembler: StaticScanAssembler,
    keep: bool,
    /// Orphan samples counted by assemblers already forgotten.
    forgotten_orphans: u64,
    /// Static scans finished and forgotten.
    forgotten_scans: u64,
}

impl AssemblyStage {
    /// A stage that keeps every assembled scan with its points if `keep`.
    pub fn new(keep: bool) -> Self {
        AssemblyStage {
            assembler: StaticScanAssembler::new(),
            keep,
            forgotten_orphans: 0,
            forgotten_scans: 0,
        }
    }

    /// Static-scan samples that could not be placed (their start or revolution never seen).
    pub fn orphan_samples(&self) -> u64 {
        self.forgotten_orphans + self.assembler.orphan_samples()
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
    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
        // Forget the finished scans when the next one starts, not when they finish: the last
        // revolution of a scan and its yaws may still come after its end message.
        let starts = matches!(frame.body, Body::StaticScan(StaticScan::Started(_)));
        if !self.keep && starts && self.assembler.scans().iter().all(|s| s.outcome.is_some()) {
            let done = std::mem::take(&mut self.assembler);
            self.forgotten_orphans += done.orphan_samples();
            self.forgotten_scans += done.scans().len() as u64;
        }
        self.assembler.on_body(&frame.body);
        ctx.rays.extend(self.assembler.take_new());
    }
}

/// The per-revolution filters (`revolution_filters`: voxel grid, pass-through box), applied to
/// the origin groups each frame completed, together (the halves of one revolution).
#[derive(Debug)]
pub struct FilterStage {
    filters: Vec<Filter>,
    failures: u64,
}

impl FilterStage {
    /// A stage applying `filters` in order.
    pub fn new(filters: Vec<Filter>) -> Self {
        FilterStage {
            filters,
            failures: 0,
        }
    }

    /// Origin groups a filter failed on (logged and dropped).
    pub fn failures(&self) -> u64 {
        self.failures
    }
}

impl Stage for FilterStage {
    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
        if self.filters.is_empty() || ctx.rays.is_empty() {
            return;
        }
        let groups: Vec<RayBundle> = ctx
            .rays
            .iter_mut()
            .map(|r| take_rays(&mut r.rays))
            .collect();
        match apply_all(&self.filters, groups) {
            Ok(filtered) => {
                for (new, rays) in ctx.rays.iter_mut().zip(filtered) {
                    new.rays = rays;
                }
            }
            Err(e) => {
                self.failures += ctx.rays.len() as u64;
                tracing::warn!(
                    seq = frame.seq,
                    groups = ctx.rays.len(),
                    "revolution filter failed, its points are dropped: {e}"
                );
                ctx.rays.clear();
            }
        }
    }
}

/// Moves the points out, leaving the origin.
fn take_rays(rays: &mut RayBundle) -> RayBundle {
    RayBundle {
        origin: rays.origin,
        points: std::mem::take(&mut rays.points),
    }
}

/// One named position's octree.
#[derive(Debug)]
pub struct PositionMap {
    /// The position's name.
    pub name: String,
    /// Its octree (`None` when position maps are not kept).
    pub map: Option<VoxelMap>,
    /// Points inserted.
    pub points: u64,
}

/// Octree insertion (OctoMap's `insertPointCloud` from each group's origin, cut at
/// `max_range`) into the session's octree and its position's, and the growing cloud.
#[derive(Debug)]
pub struct MapStage {
    res: Resolution,
    settings: PipelineSettings,
    products: Products,
    session: VoxelMap,
    positions: Vec<PositionMap>,
    /// Filtered points within `max_range` with their origin and position index.
    cloud: Vec<(usize, RayBundle)>,
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
            cloud: Vec::new(),
            points: 0,
        }
    }

    /// The resolution of its octrees.
    pub fn resolution(&self) -> &Resolution {
        &self.res
    }

    /// The session's octree (every position).
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
        let index = position.map(|name| self.positions.iter().position(|p| p.name == name));
        self.cloud
            .iter()
            .filter(|(i, _)| index.is_none_or(|want| want == Some(*i)))
            .map(|(_, rays)| rays.clone())
            .collect()
    }

    fn max_range(&self) -> f64 {
        self.settings.max_range_m.unwrap_or(-1.0)
    }
}

impl Stage for MapStage {
    fn on_frame(&mut self, ctx: &mut StageContext, _frame: &Frame) {
        let max_range = self.max_range();
        for new in &ctx.rays {
            let index = match self.positions.iter().position(|p| p.name == new.position) {
                Some(i) => i,
                None => {
                    self.positions.push(PositionMap {
                        name: new.position.clone(),
                        map: (self.products.octrees && self.products.position_maps)
                            .then(|| VoxelMap::new(self.res, self.settings.sensor)),
                        points: 0,
                    });
                    self.positions.len() - 1
                }
            };
            let n = new.rays.points.len() as u64;
            self.points += n;
            let position = &mut self.positions[index];
            position.points += n;
            if self.products.octrees {
                self.session.insert_bundle(&new.rays, max_range);
                if let Some(map) = &mut position.map {
                    map.insert_bundle(&new.rays, max_range);
                }
            }
            if self.products.cloud {
                let mut rays = new.rays.clone();
                if max_range >= 0.0 {
                    cut_range(std::slice::from_mut(&mut rays), max_range);
                }
                self.cloud.push((index, rays));
            }
        }
    }
}
