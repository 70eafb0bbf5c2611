//! The reference map and the metrics against it, as `scan3d eval --reference REF map.bt` computes them.

use std::io::Write;
use std::path::Path;

use scan3d_map::eval::{LeafMap, Metrics};
use scan3d_map::octree::{Octree, Resolution, SensorModel};

use super::PipelineError;

/// Reads the reference map (`.bt` / `.ot`, OctoMap's default sensor model, as `scan3d eval`
/// does) and checks that its voxels are `res`.
pub fn load_reference(path: &Path, res: &Resolution) -> Result<LeafMap, PipelineError> {
    let unreadable = |reason: String| PipelineError::Reference {
        path: path.to_path_buf(),
        reason,
    };
    let bytes = std::fs::read(path).map_err(|e| unreadable(e.to_string()))?;
    let reference =
        LeafMap::read(&bytes, SensorModel::default()).map_err(|e| unreadable(e.to_string()))?;
    check_resolution(&reference, res, path)?;
    Ok(reference)
}

/// Checks that the reference read from `path` has voxels of `res` (within 1e-9 m).
pub(super) fn check_resolution(
    reference: &LeafMap,
    res: &Resolution,
    path: &Path,
) -> Result<(), PipelineError> {
    let (found, expected) = (reference.resolution().meters(), res.meters());
    if (found - expected).abs() > 1e-9 {
        return Err(PipelineError::ReferenceResolution {
            path: path.to_path_buf(),
            found,
            expected,
        });
    }
    Ok(())
}

/// The metrics' view of `tree` as its `.bt` file holds it (max-likelihood values), so the
/// pipeline's metrics equal `scan3d eval --reference REF map.bt`.
pub(super) fn leaf_map(tree: &Octree) -> LeafMap {
    leaf_map_of_bt(tree, &tree.to_bt_bytes())
}

/// [`leaf_map`] when `bt`, the tree's `.bt` bytes, are already written.
pub(super) fn leaf_map_of_bt(tree: &Octree, bt: &[u8]) -> LeafMap {
    // The writer's own output always reads back; the tree's leaves are the fallback that cannot
    // happen rather than a panic in the daemon.
    LeafMap::read_bt(bt, SensorModel::default()).unwrap_or_else(|e| {
        tracing::error!("the octree's own .bt did not read back: {e}");
        LeafMap::from_octree(tree)
    })
}

/// Writes the main metrics as a short text table (`metrics.txt` of a snapshot; `scan3d eval`
/// prints the full one from `metrics.json`'s numbers).
pub fn write_metrics_table(m: &Metrics, out: &mut dyn Write) -> std::io::Result<()> {
    let opt = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |x| format!("{x:.6}"));
    writeln!(
        out,
        "resolution {} m; U = keys {:?}..={:?}: {} voxels",
        m.resolution, m.bbox.min, m.bbox.max, m.voxels
    )?;
    writeln!(
        out,
        "{:<10} {:>14} {:>14} {:>14} {:>10}",
        "map", "occupied", "free", "unknown", "leaves"
    )?;
    for (name, c) in [("reference", &m.reference), ("target", &m.target)] {
        writeln!(
            out,
            "{:<10} {:>14} {:>14} {:>14} {:>10}",
            name, c.occupied, c.free, c.unknown, c.leaves
        )?;
    }
    writeln!(
        out,
        "IoU (eq. M4-M7): occupied {}  free {}  unknown {}  weighted {:.6}",
        opt(m.iou.occupied),
        opt(m.iou.free),
        opt(m.iou.unknown),
        m.iou.weighted
    )?;
    writeln!(
        out,
        "log-odds error (eq. M8): sum {:.6}  mean {}  over {} common voxels",
        m.log_odds.sum,
        opt(m.log_odds.mean),
        m.log_odds.common_voxels
    )?;
    writeln!(
        out,
        "correlation (eq. M9): paper {}  signed {}",
        opt(m.correlation.paper),
        opt(m.correlation.signed)
    )
}
