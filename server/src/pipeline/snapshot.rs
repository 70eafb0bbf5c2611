//! Writing a session's (or one position's) products into a directory.

use std::path::{Path, PathBuf};

use serde::Serialize;

use scan3d_map::cloud::filter::apply_all;
use scan3d_map::cloud::io::Encoding;
use scan3d_map::cloud::ply::write_ply_bundles;
use scan3d_map::eval::{self, Metrics};
use scan3d_map::octree::{Octree, VoxelMap};

use super::{PipelineError, SessionPipeline, metrics};

/// What [`SessionPipeline::write_snapshot`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Snapshot {
    /// The directory.
    pub dir: PathBuf,
    /// The position it is of (`None`: the whole session).
    pub position: Option<String>,
    /// The files written, in order: `map.bt`, `map.ot`, `cloud.ply`, then `metrics.json` and
    /// `metrics.txt` when there were metrics.
    pub files: Vec<PathBuf>,
    /// Nodes of the octree (OctoMap's count, root included; 0 for an empty map).
    pub nodes: u64,
    /// Occupied voxels (depth 16) of the `.bt`.
    pub occupied_voxels: u64,
    /// Free voxels of the `.bt`.
    pub free_voxels: u64,
    /// Points in `cloud.ply` (after the snapshot filters).
    pub points: u64,
    /// The metrics against the reference (`None` without a reference or without 3D data).
    pub metrics: Option<Metrics>,
}

pub(super) fn write(
    pipeline: &mut SessionPipeline,
    dir: &Path,
    position: Option<&str>,
) -> Result<Snapshot, PipelineError> {
    let maps = pipeline.maps();
    let map: Option<&VoxelMap> = match position {
        None => Some(maps.session_map()),
        Some(name) => match maps.position(name) {
            Some(p) => p.map.as_ref(),
            None => {
                return Err(PipelineError::UnknownPosition {
                    name: name.to_string(),
                    known: maps.positions().join(", "),
                });
            }
        },
    };
    let res = *maps.resolution();
    let model = pipeline.settings().sensor;
    let tree = map.map_or_else(|| Octree::empty(res, model), VoxelMap::to_octree);
    let bt = tree.to_bt_bytes();
    let leaves = metrics::leaf_map_of_bt(&tree, &bt);
    let mut cloud = maps.cloud(position);
    if !pipeline.settings().snapshot_filters.is_empty() && !cloud.is_empty() {
        cloud = apply_all(&pipeline.settings().snapshot_filters, cloud)?;
    }
    let mut ply = Vec::new();
    write_ply_bundles(&mut ply, &cloud, Encoding::Binary).map_err(|source| {
        PipelineError::Write {
            path: dir.join("cloud.ply"),
            source,
        }
    })?;
    let metrics = match pipeline.reference() {
        Some(reference) if leaves.num_leaves() > 0 => {
            Some(eval::evaluate(reference, &leaves, None)?)
        }
        _ => None,
    };
    std::fs::create_dir_all(dir).map_err(|source| PipelineError::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut files = Vec::new();
    write_file(dir, "map.bt", &bt, &mut files)?;
    write_file(dir, "map.ot", &tree.to_ot_bytes(), &mut files)?;
    write_file(dir, "cloud.ply", &ply, &mut files)?;
    if let Some(m) = &metrics {
        let mut json = serde_json::to_vec_pretty(m).map_err(|e| PipelineError::Write {
            path: dir.join("metrics.json"),
            source: e.into(),
        })?;
        json.push(b'\n');
        write_file(dir, "metrics.json", &json, &mut files)?;
        let mut text = Vec::new();
        metrics::write_metrics_table(m, &mut text).map_err(|source| PipelineError::Write {
            path: dir.join("metrics.txt"),
            source,
        })?;
        write_file(dir, "metrics.txt", &text, &mut files)?;
    }
    Ok(Snapshot {
        dir: dir.to_path_buf(),
        position: position.map(str::to_string),
        files,
        nodes: tree.num_nodes() as u64,
        occupied_voxels: leaves.occupied_voxels(),
        free_voxels: leaves.free_voxels(),
        points: cloud.iter().map(|c| c.points.len() as u64).sum(),
        metrics,
    })
}

/// Writes `dir/name` through a temporary file and a rename, so readers never see half of it.
fn write_file(
    dir: &Path,
    name: &str,
    bytes: &[u8],
    files: &mut Vec<PathBuf>,
) -> Result<(), PipelineError> {
    let path = dir.join(name);
    let tmp = dir.join(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, &path))
        .map_err(|source| {
            let _ = std::fs::remove_file(&tmp);
            PipelineError::Write {
                path: path.clone(),
                source,
            }
        })?;
    files.push(path);
    Ok(())
}
