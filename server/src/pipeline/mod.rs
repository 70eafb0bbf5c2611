//! The server's mapping pipeline: per session, frames in sample-time order go through stages
//! (static-scan assembly by eq. 1, the Table II filters, octree insertion, metrics against a
//! reference), and the products (cloud, octree, metrics) grow as the frames come in.
//!
//! One pipeline, three drivers: `scan3d serve` feeds it live from ingest (through a bounded
//! queue; it catches up from the recording when it falls behind), `scan3d replay` and the
//! offline `scan3d assemble` / `scan3d map` feed it a recorded session frame by frame. So the
//! live products and the replayed ones are the same bytes.

pub mod live;

use std::path::PathBuf;

use serde::Serialize;

use scan3d_map::cloud::filter::Filter;
use scan3d_map::eval::Metrics;
use scan3d_map::octree::SensorModel;

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
    /// Occupied leaves of the session's octree (all positions).
    pub occupied_voxels: u64,
    /// Free leaves of the session's octree.
    pub free_voxels: u64,
    /// The latest metrics against the reference, when one is configured and there is a map.
    pub metrics: Option<Metrics>,
}
