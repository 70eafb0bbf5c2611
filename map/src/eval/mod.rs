//! The paper's map metrics (§IV, eq. M1–M9, Table III, Fig. 11) between two OctoMap trees,
//! plus a confusion matrix and, against a ground-truth map, precision / recall / F1 / Chamfer.
//!
//! Pure: trees in, numbers out; no I/O. The `scan3d eval | report | sweep` commands are the
//! shells around it, and [`plot`] draws the paper's figures from the numbers.
//!
//! # Definitions (what every number means)
//!
//! Both maps must have the same resolution ([`EvalError::ResolutionMismatch`] otherwise). A
//! *voxel* is a depth-16 OctoMap voxel; a pruned leaf at depth `d` covers all its
//! `8^(16-d)` voxels, with its value.
//!
//! - **Universe U**: all voxels inside a key box B. By default B is the smallest key-aligned
//!   box that holds every known voxel of either map ([`compare`] finds it); a [`VoxelBox`] given
//!   by the caller (`--bbox x0,y0,z0,x1,y1,z1` in metres: the voxels whose *centre* is inside,
//!   [`VoxelBox::from_metric`]) replaces it, and leaves are clipped to it.
//! - **State** of a voxel in a map: *occupied* if its log-odds is `>=` the occupancy threshold
//!   (0, OctoMap's `isNodeOccupied`), *free* if known and below it, *unknown* if no leaf covers it.
//! - **eq. M1–M3**: per map `N_occ`, `N_free` (voxels in U), `N_no = |U| - N_occ - N_free`,
//!   and `R_x = N_x / |U|` ([`MapCounts`]).
//! - **eq. M4–M6**: `IoU_x = |{v ∈ U : ref(v) = x ∧ tar(v) = x}| / |{v ∈ U : ref(v) = x ∨ tar(v) = x}|`,
//!   `None` (JSON null) when the union is empty ([`Iou`]).
//! - **eq. M7**: weighted IoU with the *reference* map's ratios: `R_occ·IoU_occ + R_free·IoU_free`
//!   when `R_occ + R_free <= 0.10`, else that plus `R_no·IoU_no`. A null IoU term has union 0,
//!   hence the reference has no such voxel and its `R` is 0: it adds 0.
//! - **eq. M8** (log-odds error): over C = the voxels known in both maps, `p = 1 - 1/(1 + e^l)`
//!   in f64 from the stored f32 log-odds `l`; per voxel `ln(p_r/p_t)·p_r` if `p_r > 0.9999`,
//!   `ln((1-p_r)/(1-p_t))·(1-p_r)` if `p_r < 0.0001`, else the sum of both. This is the
//!   Bernoulli KL divergence KL(ref‖tar), the quantity OctoMap's `compare_octrees` prints as
//!   `KLD` (it sums over the expanded leaves, i.e. voxels). Reported: the sum (0 for an empty C)
//!   and the mean over C (null for an empty C) ([`LogOddsError`]).
//! - **eq. M9** (correlation): over C with `p̄ = Σ(p_r + p_t) / (2|C|)`: the paper's form
//!   `Σ|(p_r - p̄)(p_t - p̄)| / sqrt(Σ(p_r - p̄)² · Σ(p_t - p̄)²)`, and beside it the ordinary
//!   signed normalised cross-correlation (the same without `|·|`); null when the denominator is
//!   0 (e.g. C empty, or every voxel of one map in C has the same value) ([`Correlation`]).
//! - **Fig. 11's red bars**: mean over C of `(p_r + p_t)/2` (equal to `p̄`), and mean `|p_r - p_t|`.
//! - **Confusion matrix** over U: rows the reference's occupied / free / unknown, columns the
//!   target's, in voxels and in m³ (`voxels · res³`); the unknown/unknown cell is the rest of U.
//! - **Against a truth map** ([`evaluate_truth`]; same resolution; truth voxels outside U are
//!   ignored): precision = |T ∩ G| / |T| and recall = |T ∩ G| / |G| of the target's occupied
//!   voxels T against the truth's G, F1 = 2PR/(P+R); the *tolerant* forms count a target voxel
//!   as correct if a truth voxel is within its 26-neighbourhood (or is itself), and a truth voxel
//!   as found if a target voxel is; Chamfer distance = the mean of (mean distance from each T
//!   centre to the nearest G centre) and (mean distance from each G centre to the nearest T
//!   centre), in metres. Undefined ratios (empty T or G, P + R = 0) are null.
//!
//! # How it is computed
//!
//! Never voxel by voxel (U is huge): both trees' leaves come out in Morton order (OctoMap's
//! preorder), each leaf is a contiguous Morton interval of `8^level` voxels, and two octree
//! intervals are either nested or disjoint. One merge of the two leaf streams counts every
//! leaf fully as "known against unknown" and moves each nested overlap (the smaller leaf's
//! voxels) to its (ref state, target state) cell; the overlaps' value pairs are accumulated in a
//! small histogram keyed by the two f32 bit patterns (maps hold few distinct values), from which
//! eq. M8/M9 are evaluated once per distinct pair.

mod leafmap;
mod merge;
pub mod plot;
mod truth;

use serde::Serialize;

use crate::octree::Resolution;

pub use leafmap::{LeafMap, MapLeaf};
pub use merge::{Comparison, ValuePair, compare};
pub use truth::{TruthMetrics, evaluate_truth};

/// Index of the occupied state in confusion matrices.
pub const OCCUPIED: usize = 0;
/// Index of the free state in confusion matrices.
pub const FREE: usize = 1;
/// Index of the unknown state in confusion matrices.
pub const UNKNOWN: usize = 2;

/// Threshold of eq. M7: below or at this known share, unknown voxels do not count.
pub const KNOWN_SHARE_THRESHOLD: f64 = 0.10;

/// Which input a problem is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The reference map.
    Reference,
    /// The compared (target) map.
    Target,
    /// The ground-truth map.
    Truth,
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Role::Reference => "reference",
            Role::Target => "target",
            Role::Truth => "truth",
        })
    }
}

/// Why two maps could not be evaluated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum EvalError {
    /// The maps' voxel sizes differ; voxel-wise metrics need equal ones.
    #[error("resolution mismatch: the {role} map has {found} m voxels, expected {expected} m")]
    ResolutionMismatch {
        /// The resolution of the map compared against.
        expected: f64,
        /// The differing map's resolution.
        found: f64,
        /// Which map differs.
        role: Role,
    },
    /// A map has no known voxel at all (nothing to compare, no default box).
    #[error("the {0} map is empty (no known voxel)")]
    EmptyMap(Role),
    /// The bounding box holds no voxel centre.
    #[error("the bounding box holds no voxel centre")]
    EmptyBox,
    /// The bounding box is not `x0 <= x1, y0 <= y1, z0 <= z1` with finite numbers.
    #[error("bad bounding box: {0}")]
    BadBox(String),
    /// A leaf's log-odds is NaN or infinite (a malformed `.ot`).
    #[error("the {role} map holds a non-finite log-odds value {value}")]
    NonFinite {
        /// Which map.
        role: Role,
        /// The value.
        value: f32,
    },
    /// The truth metrics enumerate occupied voxels; this many would not fit in memory.
    #[error(
        "{voxels} occupied voxels in the box, more than the {limit} the truth metrics enumerate"
    )]
    TooManyVoxels {
        /// Occupied voxels of target and truth in U.
        voxels: u64,
        /// The limit.
        limit: u64,
    },
}

/// An inclusive box of depth-16 voxel keys: the universe U.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct VoxelBox {
    /// Smallest key per axis.
    pub min: [u16; 3],
    /// Largest key per axis (inclusive).
    pub max: [u16; 3],
}

impl VoxelBox {
    /// A box from inclusive key bounds; `min <= max` on every axis.
    pub fn new(min: [u16; 3], max: [u16; 3]) -> Result<Self, EvalError> {
        if (0..3).any(|a| min[a] > max[a]) {
            return Err(EvalError::EmptyBox);
        }
        Ok(Self { min, max })
    }

    /// The voxels whose centre lies in the metric box `[lo, hi]` (inclusive), per axis.
    pub fn from_metric(res: &Resolution, lo: [f64; 3], hi: [f64; 3]) -> Result<Self, EvalError> {
        if !lo.iter().chain(&hi).all(|c| c.is_finite()) || (0..3).any(|a| lo[a] > hi[a]) {
            return Err(EvalError::BadBox(format!(
                "need finite x0 <= x1, y0 <= y1, z0 <= z1, got {lo:?} .. {hi:?}"
            )));
        }
        let center = |k: i64| ((k - 32768) as f64 + 0.5) * res.meters();
        let (mut min, mut max) = ([0u16; 3], [0u16; 3]);
        for a in 0..3 {
            // First key whose centre is >= lo, last whose centre is <= hi, then fix rounding.
            let mut k0 = ((lo[a] / res.meters() - 0.5).ceil() as i64 + 32768).clamp(0, 65536);
            while k0 > 0 && center(k0 - 1) >= lo[a] {
                k0 -= 1;
            }
            while k0 < 65536 && center(k0) < lo[a] {
                k0 += 1;
            }
            let mut k1 = ((hi[a] / res.meters() - 0.5).floor() as i64 + 32768).clamp(-1, 65535);
            while k1 < 65535 && center(k1 + 1) <= hi[a] {
                k1 += 1;
            }
            while k1 >= 0 && center(k1) > hi[a] {
                k1 -= 1;
            }
            if k0 > k1 || k0 > 65535 || k1 < 0 {
                return Err(EvalError::EmptyBox);
            }
            min[a] = k0 as u16;
            max[a] = k1 as u16;
        }
        Ok(Self { min, max })
    }

    /// Number of voxels in the box (`|U|`).
    pub fn voxels(&self) -> u64 {
        (0..3)
            .map(|a| u64::from(self.max[a] - self.min[a]) + 1)
            .product()
    }

    /// Voxels of the inclusive key range `[lo, hi]` that lie inside the box.
    #[inline]
    pub fn overlap(&self, lo: [u16; 3], hi: [u16; 3]) -> u64 {
        let mut n = 1u64;
        for a in 0..3 {
            let l = lo[a].max(self.min[a]);
            let h = hi[a].min(self.max[a]);
            if l > h {
                return 0;
            }
            n *= u64::from(h - l) + 1;
        }
        n
    }

    /// The box's outer faces in metres: `(min corner, max corner)`.
    pub fn metric(&self, res: &Resolution) -> ([f64; 3], [f64; 3]) {
        let r = res.meters();
        (
            self.min.map(|k| (f64::from(k) - 32768.0) * r),
            self.max.map(|k| (f64::from(k) - 32768.0 + 1.0) * r),
        )
    }
}

/// One map's voxel counts inside U (eq. M1–M3) and its whole-tree leaf count.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MapCounts {
    /// Occupied voxels in U (`N_occ`).
    pub occupied: u64,
    /// Free voxels in U (`N_free`).
    pub free: u64,
    /// Unknown voxels in U (`N_no = |U| - N_occ - N_free`).
    pub unknown: u64,
    /// `R_occ = N_occ / |U|`.
    pub ratio_occupied: f64,
    /// `R_free = N_free / |U|`.
    pub ratio_free: f64,
    /// `R_no = N_no / |U|`.
    pub ratio_unknown: f64,
    /// OctoMap leaf count of the whole map (a pruned leaf counts once), as Table III.
    pub leaves: u64,
}

impl MapCounts {
    fn new(occupied: u64, free: u64, universe: u64, leaves: u64) -> Self {
        let unknown = universe - occupied - free;
        let r = |n: u64| n as f64 / universe as f64;
        Self {
            occupied,
            free,
            unknown,
            ratio_occupied: r(occupied),
            ratio_free: r(free),
            ratio_unknown: r(unknown),
            leaves,
        }
    }
}

/// eq. M4–M7.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Iou {
    /// `IoU_occ`, null if neither map has an occupied voxel in U.
    pub occupied: Option<f64>,
    /// `IoU_free`, null if neither map has a free voxel in U.
    pub free: Option<f64>,
    /// `IoU_no`, null if neither map has an unknown voxel in U.
    pub unknown: Option<f64>,
    /// eq. M7 with the reference's ratios.
    pub weighted: f64,
}

/// eq. M8 over the voxels known in both maps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LogOddsError {
    /// Sum over C (`compare_octrees`' KLD); 0 for an empty C.
    pub sum: f64,
    /// Sum / |C|; null for an empty C.
    pub mean: Option<f64>,
    /// |C|.
    pub common_voxels: u64,
}

/// eq. M9 over the voxels known in both maps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Correlation {
    /// The paper's form, `|·|` in the numerator.
    pub paper: Option<f64>,
    /// The ordinary signed normalised cross-correlation.
    pub signed: Option<f64>,
    /// `p̄`, shared by both forms.
    pub p_bar: Option<f64>,
}

/// Every metric of one target map against a reference (the `scan3d eval --json` object).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Metrics {
    /// Voxel edge length in metres.
    pub resolution: f64,
    /// `|U|`.
    pub voxels: u64,
    /// The key box U.
    pub bbox: VoxelBox,
    /// Reference counts.
    #[serde(rename = "ref")]
    pub reference: MapCounts,
    /// Target counts.
    pub target: MapCounts,
    /// `[ref state][target state]` voxel counts (occupied, free, unknown).
    pub confusion: [[u64; 3]; 3],
    /// The same in m³.
    pub confusion_m3: [[f64; 3]; 3],
    /// eq. M4–M7.
    pub iou: Iou,
    /// eq. M8.
    pub log_odds: LogOddsError,
    /// eq. M9.
    pub correlation: Correlation,
    /// Mean over C of `(p_r + p_t) / 2` (Fig. 11's red bar).
    pub mean_probability: Option<f64>,
    /// Mean over C of `|p_r - p_t|` (Fig. 11's deviation bar).
    pub probability_deviation: Option<f64>,
    /// Scores against a ground-truth map, if one was given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthMetrics>,
}

/// OctoMap's occupancy probability of a log-odds value: `1 - 1/(1 + e^l)` in f64.
#[inline]
pub fn probability(log_odds: f32) -> f64 {
    1.0 - 1.0 / (1.0 + f64::from(log_odds).exp())
}

/// One voxel's eq. M8 term, exactly as `compare_octrees` computes it.
#[inline]
pub fn kld_term(p_ref: f64, p_tar: f64) -> f64 {
    let occ = (p_ref / p_tar).ln() * p_ref;
    let free = ((1.0 - p_ref) / (1.0 - p_tar)).ln() * (1.0 - p_ref);
    if p_ref < 0.0001 {
        free
    } else if p_ref > 0.9999 {
        occ
    } else {
        occ + free
    }
}

/// Checks that `other` (playing `role`) has the voxel size of `base` (`|a - b| <= 1e-9` m).
pub fn check_resolution(base: &LeafMap, other: &LeafMap, role: Role) -> Result<(), EvalError> {
    let (a, b) = (base.resolution().meters(), other.resolution().meters());
    if (a - b).abs() > 1e-9 {
        return Err(EvalError::ResolutionMismatch {
            expected: a,
            found: b,
            role,
        });
    }
    Ok(())
}

/// All metrics of `target` against `reference` over U (`bbox`, or the default box).
pub fn evaluate(
    reference: &LeafMap,
    target: &LeafMap,
    bbox: Option<VoxelBox>,
) -> Result<Metrics, EvalError> {
    check_resolution(reference, target, Role::Target)?;
    if reference.num_leaves() == 0 {
        return Err(EvalError::EmptyMap(Role::Reference));
    }
    if target.num_leaves() == 0 {
        return Err(EvalError::EmptyMap(Role::Target));
    }
    let cmp = compare(reference, target, bbox, [Role::Reference, Role::Target])?;
    let bbox = cmp.universe.ok_or(EvalError::EmptyBox)?;
    Ok(metrics_from(&cmp, bbox, reference, target))
}

fn metrics_from(
    cmp: &Comparison,
    bbox: VoxelBox,
    reference: &LeafMap,
    target: &LeafMap,
) -> Metrics {
    let res = reference.resolution().meters();
    let universe = bbox.voxels();
    let m = cmp.confusion_in(universe);
    let row = |i: usize| m[i][OCCUPIED] + m[i][FREE] + m[i][UNKNOWN];
    let col = |j: usize| m[OCCUPIED][j] + m[FREE][j] + m[UNKNOWN][j];
    let ref_counts = MapCounts::new(row(OCCUPIED), row(FREE), universe, reference.num_leaves());
    let tar_counts = MapCounts::new(col(OCCUPIED), col(FREE), universe, target.num_leaves());
    let iou_of = |x: usize| {
        let union = row(x) + col(x) - m[x][x];
        (union > 0).then(|| m[x][x] as f64 / union as f64)
    };
    let iou_occ = iou_of(OCCUPIED);
    let iou_free = iou_of(FREE);
    let iou_no = iou_of(UNKNOWN);
    let term = |r: f64, iou: Option<f64>| r * iou.unwrap_or(0.0);
    let mut weighted =
        term(ref_counts.ratio_occupied, iou_occ) + term(ref_counts.ratio_free, iou_free);
    if ref_counts.ratio_occupied + ref_counts.ratio_free > KNOWN_SHARE_THRESHOLD {
        weighted += term(ref_counts.ratio_unknown, iou_no);
    }
    let values = PairStats::of(&cmp.pairs);
    let vol = res * res * res;
    Metrics {
        resolution: res,
        voxels: universe,
        bbox,
        reference: ref_counts,
        target: tar_counts,
        confusion: m,
        confusion_m3: m.map(|r| r.map(|n| n as f64 * vol)),
        iou: Iou {
            occupied: iou_occ,
            free: iou_free,
            unknown: iou_no,
            weighted,
        },
        log_odds: LogOddsError {
            sum: values.kld_sum,
            mean: values.mean(values.kld_sum),
            common_voxels: values.common,
        },
        correlation: Correlation {
            paper: values.correlation_paper,
            signed: values.correlation_signed,
            p_bar: values.p_bar,
        },
        mean_probability: values.p_bar,
        probability_deviation: values.mean(values.abs_diff_sum),
        truth: None,
    }
}

/// eq. M8/M9 and the Fig. 11 means from the value-pair histogram of C.
struct PairStats {
    common: u64,
    kld_sum: f64,
    abs_diff_sum: f64,
    p_bar: Option<f64>,
    correlation_paper: Option<f64>,
    correlation_signed: Option<f64>,
}

impl PairStats {
    fn of(pairs: &[ValuePair]) -> Self {
        let probs: Vec<(f64, f64, f64)> = pairs
            .iter()
            .map(|p| {
                (
                    probability(p.reference),
                    probability(p.target),
                    p.voxels as f64,
                )
            })
            .collect();
        let common: u64 = pairs.iter().map(|p| p.voxels).sum();
        let (mut kld_sum, mut abs_diff_sum, mut p_sum) = (0.0, 0.0, 0.0);
        for &(pr, pt, w) in &probs {
            kld_sum += w * kld_term(pr, pt);
            abs_diff_sum += w * (pr - pt).abs();
            p_sum += w * (pr + pt);
        }
        let p_bar = (common > 0).then(|| p_sum / (2.0 * common as f64));
        let (mut num_abs, mut num, mut dr, mut dt) = (0.0, 0.0, 0.0, 0.0);
        if let Some(pb) = p_bar {
            for &(pr, pt, w) in &probs {
                let (a, b) = (pr - pb, pt - pb);
                num_abs += w * (a * b).abs();
                num += w * a * b;
                dr += w * a * a;
                dt += w * b * b;
            }
        }
        let den = (dr * dt).sqrt();
        let ok = den > 0.0 && den.is_finite();
        Self {
            common,
            kld_sum,
            abs_diff_sum,
            p_bar,
            correlation_paper: ok.then(|| num_abs / den),
            correlation_signed: ok.then(|| num / den),
        }
    }

    fn mean(&self, sum: f64) -> Option<f64> {
        (self.common > 0).then(|| sum / self.common as f64)
    }
}

/// A whole map's voxel counts and tree size (Table III; no box).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MapSummary {
    /// Occupied voxels.
    pub occupied_voxels: u64,
    /// Free voxels.
    pub free_voxels: u64,
    /// Occupied share of the known voxels (Table III's "Occupied Ratio"); null if none known.
    pub occupied_share: Option<f64>,
    /// Free share of the known voxels (Table III's "Free Ratio"); null if none known.
    pub free_share: Option<f64>,
    /// OctoMap leaves (a pruned leaf counts once).
    pub leaves: u64,
    /// OctoMap nodes (root and inner nodes included).
    pub nodes: u64,
}

/// Table III's row for one map: its occupied and free voxels as shares of its known voxels.
pub fn summarize(tree: &LeafMap) -> MapSummary {
    let (mut occ, mut free) = (0u64, 0u64);
    let model = tree.model();
    for leaf in tree.leaves() {
        let n = 1u64 << (3 * u32::from(leaf.level));
        if model.is_occupied(leaf.log_odds) {
            occ += n;
        } else {
            free += n;
        }
    }
    let known = occ + free;
    let share = |n: u64| (known > 0).then(|| n as f64 / known as f64);
    MapSummary {
        occupied_voxels: occ,
        free_voxels: free,
        occupied_share: share(occ),
        free_share: share(free),
        leaves: tree.num_leaves(),
        nodes: tree.num_nodes(),
    }
}
