//! Scores of a map's occupied voxels against a ground-truth map (beyond the paper).

use std::collections::HashSet;
use std::hash::BuildHasherDefault;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use serde::Serialize;

use super::leafmap::LeafMap;
use super::merge::compare;
use super::{EvalError, OCCUPIED, Role, UNKNOWN, VoxelBox, check_resolution};

/// Most occupied voxels (target + truth, inside U) the tolerant scores and Chamfer distance
/// enumerate (8 bytes each, plus a k-d tree).
pub const MAX_TRUTH_VOXELS: u64 = 20_000_000;

/// The target's occupied voxels against the truth's, inside U (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TruthMetrics {
    /// |T ∩ G| / |T|; null if T is empty.
    pub precision: Option<f64>,
    /// |T ∩ G| / |G|; null if G is empty.
    pub recall: Option<f64>,
    /// 2PR / (P + R); null if undefined or P + R = 0.
    pub f1: Option<f64>,
    /// Share of T with a G voxel in its 26-neighbourhood (or itself).
    pub precision_tolerant: Option<f64>,
    /// Share of G with a T voxel in its 26-neighbourhood (or itself).
    pub recall_tolerant: Option<f64>,
    /// F1 of the tolerant pair.
    pub f1_tolerant: Option<f64>,
    /// Mean of both directions' mean nearest-centre distance, metres; null if T or G is empty.
    pub chamfer: Option<f64>,
    /// |T|: the target's occupied voxels in U.
    pub target_occupied: u64,
    /// |G|: the truth's occupied voxels in U.
    pub truth_occupied: u64,
}

fn ratio(num: u64, den: u64) -> Option<f64> {
    (den > 0).then(|| num as f64 / den as f64)
}

fn f1(p: Option<f64>, r: Option<f64>) -> Option<f64> {
    let (p, r) = (p?, r?);
    (p + r > 0.0).then(|| 2.0 * p * r / (p + r))
}

/// Packs a key as `x | y << 16 | z << 32`.
#[inline]
fn pack(k: [u16; 3]) -> u64 {
    u64::from(k[0]) | (u64::from(k[1]) << 16) | (u64::from(k[2]) << 32)
}

/// Every occupied voxel of `tree` inside `bbox`, packed.
fn occupied_voxels(tree: &LeafMap, bbox: &VoxelBox, capacity: u64) -> Vec<u64> {
    let mut out = Vec::with_capacity(capacity as usize);
    let model = tree.model();
    for leaf in tree.leaves() {
        if !model.is_occupied(leaf.log_odds) {
            continue;
        }
        let (lo, hi) = (leaf.lo, leaf.hi());
        if bbox.overlap(lo, hi) == 0 {
            continue;
        }
        let lo = [0, 1, 2].map(|a| lo[a].max(bbox.min[a]));
        let hi = [0, 1, 2].map(|a| hi[a].min(bbox.max[a]));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    out.push(pack([x, y, z]));
                }
            }
        }
    }
    out
}

type KeySet = HashSet<u64, BuildHasherDefault<std::hash::DefaultHasher>>;

/// How many of `from` have a voxel of `to` among their 27 neighbours (themselves included).
fn tolerant_hits(from: &[u64], to: &KeySet) -> u64 {
    let mut hits = 0u64;
    for &k in from {
        let c = [k & 0xffff, (k >> 16) & 0xffff, k >> 32].map(|v| v as i64);
        let mut found = false;
        'search: for dz in -1..=1i64 {
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    let n = [c[0] + dx, c[1] + dy, c[2] + dz];
                    if n.iter().any(|&v| !(0..=65535).contains(&v)) {
                        continue;
                    }
                    if to.contains(&pack(n.map(|v| v as u16))) {
                        found = true;
                        break 'search;
                    }
                }
            }
        }
        hits += u64::from(found);
    }
    hits
}

/// Mean distance (in voxels) from each of `from` to its nearest voxel of `to` (non-empty).
fn mean_nearest(from: &[u64], to: &[u64]) -> Option<f64> {
    let coords = |k: u64| [k & 0xffff, (k >> 16) & 0xffff, k >> 32].map(|v| v as f64);
    let points: Vec<[f64; 3]> = to.iter().map(|&k| coords(k)).collect();
    let tree = ImmutableKdTree::<f64, 3>::new_from_slice(&points).ok()?;
    let mut sum = 0.0;
    for &k in from {
        let nn = tree
            .query(&coords(k))
            .nearest_one::<SquaredEuclidean<f64>>()
            .execute();
        sum += nn.distance.sqrt();
    }
    Some(sum / from.len() as f64)
}

/// Scores `target`'s occupied voxels against `truth`'s inside `universe` (normally the U of the
/// reference/target evaluation; truth voxels outside it are ignored).
pub fn evaluate_truth(
    target: &LeafMap,
    truth: &LeafMap,
    universe: VoxelBox,
) -> Result<TruthMetrics, EvalError> {
    check_resolution(target, truth, Role::Truth)?;
    if truth.num_leaves() == 0 {
        return Err(EvalError::EmptyMap(Role::Truth));
    }
    let cmp = compare(target, truth, Some(universe), [Role::Target, Role::Truth])?;
    let m = cmp.confusion;
    let tp = m[OCCUPIED][OCCUPIED];
    let target_occupied: u64 = m[OCCUPIED].iter().sum();
    let truth_occupied: u64 = (0..=UNKNOWN).map(|i| m[i][OCCUPIED]).sum();
    let total = target_occupied + truth_occupied;
    if total > MAX_TRUTH_VOXELS {
        return Err(EvalError::TooManyVoxels {
            voxels: total,
            limit: MAX_TRUTH_VOXELS,
        });
    }
    let t = occupied_voxels(target, &universe, target_occupied);
    let g = occupied_voxels(truth, &universe, truth_occupied);
    let set = |v: &[u64]| -> KeySet { v.iter().copied().collect() };
    let (t_set, g_set) = (set(&t), set(&g));
    let precision = ratio(tp, target_occupied);
    let recall = ratio(tp, truth_occupied);
    let precision_tolerant = ratio(tolerant_hits(&t, &g_set), target_occupied);
    let recall_tolerant = ratio(tolerant_hits(&g, &t_set), truth_occupied);
    let chamfer = if t.is_empty() || g.is_empty() {
        None
    } else {
        match (mean_nearest(&t, &g), mean_nearest(&g, &t)) {
            (Some(a), Some(b)) => Some((a + b) / 2.0 * truth.resolution().meters()),
            _ => None,
        }
    };
    Ok(TruthMetrics {
        precision,
        recall,
        f1: f1(precision, recall),
        precision_tolerant,
        recall_tolerant,
        f1_tolerant: f1(precision_tolerant, recall_tolerant),
        chamfer,
        target_occupied,
        truth_occupied,
    })
}
