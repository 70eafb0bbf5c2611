//! Point-cloud filters, the PCL pipeline of the paper's Table II (down-sampling, pass-through,
//! Gaussian) plus statistical outlier removal, on clouds that keep each point's sensor origin.
//!
//! Every filter takes `&[RayBundle]` and returns the same bundles (same count, order and
//! origins) with their points filtered, so the result can go straight to octree insertion.
//! Points with a non-finite coordinate are dropped by every filter (as PCL does for non-dense
//! clouds). Results are deterministic: the same input gives the same output bit for bit.
//! Neighbour searches use a k-d tree (`kiddo`), so SOR and Gaussian cost O(n log n), not O(n²).
//!
//! CLI syntax ([`Filter`]'s `FromStr`): `voxel:LEAF`, `box:x0,y0,z0,x1,y1,z1`,
//! `box-out:x0,y0,z0,x1,y1,z1`, `sor:K,ALPHA`, `gauss:SIGMA,RADIUS`.

use std::fmt;
use std::num::NonZeroUsize;
use std::str::FromStr;

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::RayBundle;
use crate::octree::morton;

/// One filter step.
#[derive(Debug, Clone, PartialEq)]
pub enum Filter {
    /// `voxel:LEAF` — `pcl::VoxelGrid` down-sampling with a cubic leaf of `leaf` metres.
    ///
    /// As PCL: the voxel of a point is `floor(p · (1/leaf))` per axis, computed in f32 (PCL's
    /// `inverse_leaf_size_`), so the grid is aligned to multiples of `leaf` from the world
    /// origin (PCL subtracts `floor(min · (1/leaf))` only to make indices non-negative); each
    /// occupied voxel gives one point, the centroid of its members (summed in f64, PCL uses
    /// f32); output in increasing (z, y, x) voxel order, PCL's order.
    ///
    /// Origins: the centroid is computed over the members of *all* bundles (so the density is
    /// PCL's: one point per voxel) and goes to the bundle of the member nearest to the centroid
    /// (ties: the earliest point in bundle order). That member's ray is the observation closest to
    /// the new point, so inserting the centroid from that origin carves almost the same free
    /// space as the original ray did; grouping per (voxel, bundle) instead would keep one point
    /// per voxel *per bundle* and hardly thin clouds made of many overlapping bundles.
    Voxel {
        /// Leaf edge, metres (> 0).
        leaf: f32,
    },
    /// `box:x0,y0,z0,x1,y1,z1` — `pcl::PassThrough` on x, y and z: keep the points with
    /// `min ≤ p ≤ max` on every axis (bounds inclusive, as PCL).
    Box {
        /// Lower corner.
        min: [f64; 3],
        /// Upper corner.
        max: [f64; 3],
    },
    /// `box-out:x0,y0,z0,x1,y1,z1` — the negative pass-through: remove the points inside the
    /// (inclusive) box, keep the rest (the paper cuts out the glass wall this way).
    BoxOut {
        /// Lower corner.
        min: [f64; 3],
        /// Upper corner.
        max: [f64; 3],
    },
    /// `sor:K,ALPHA` — `pcl::StatisticalOutlierRemoval` with `setMeanK(K)` and
    /// `setStddevMulThresh(ALPHA)`.
    ///
    /// As current PCL: each point's mean distance to its `K` nearest neighbours *excluding
    /// itself* (PCL searches `K + 1` and skips the first result, the query point; a duplicate
    /// point at distance 0 can take that place, which changes nothing), fewer if the cloud is
    /// smaller; then `mean` and the sample standard deviation `σ` (divisor n − 1) of those
    /// distances over the cloud; a point is kept iff its distance `≤ mean + ALPHA·σ`. Clouds
    /// of fewer than two points pass unchanged.
    Sor {
        /// Neighbours per point, not counting the point itself.
        k: NonZeroUsize,
        /// Standard-deviation multiplier.
        alpha: f64,
    },
    /// `gauss:SIGMA,RADIUS` — Gaussian smoothing, PCL's `filters::Convolution3D` with a
    /// `GaussianKernel`: each point moves to the Gaussian-weighted mean of the points within
    /// `RADIUS` of it (itself included, bound inclusive), weight `exp(−d² / (2·SIGMA²))`.
    /// The point count and each point's bundle are unchanged; positions are computed in f64.
    Gauss {
        /// Kernel standard deviation, metres (> 0).
        sigma: f64,
        /// Neighbourhood radius, metres (> 0).
        radius: f64,
    },
}

/// Why a filter string did not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterParseError {
    /// The part before `:` is not a known filter.
    #[error(
        "unknown filter {0:?}: expected voxel:LEAF, box:x0,y0,z0,x1,y1,z1, \
         box-out:x0,y0,z0,x1,y1,z1, sor:K,ALPHA or gauss:SIGMA,RADIUS"
    )]
    UnknownKind(String),
    /// The arguments are missing, of the wrong count or out of range.
    #[error("filter {input:?}: {reason} (expected {usage})")]
    BadArguments {
        /// The whole filter string.
        input: String,
        /// The expected syntax.
        usage: &'static str,
        /// What was wrong.
        reason: String,
    },
}

/// Why a filter could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// A voxel index does not fit in 32 bits (PCL refuses such grids too).
    #[error("voxel leaf {leaf} m is too small for a cloud reaching {coordinate} m")]
    LeafTooSmall {
        /// The leaf size.
        leaf: f32,
        /// The coordinate whose index overflowed.
        coordinate: f32,
    },
    /// More points than a 32-bit index can address.
    #[error("{0} points is more than the neighbour search can index (2^32 - 1)")]
    TooManyPoints(usize),
    /// The k-d tree could not be built.
    #[error("k-d tree construction failed: {0}")]
    KdTree(String),
}

impl FromStr for Filter {
    type Err = FilterParseError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (kind, args) = s.split_once(':').unwrap_or((s, ""));
        let kind = kind.trim();
        let usage = match kind {
            "voxel" => "voxel:LEAF",
            "box" => "box:x0,y0,z0,x1,y1,z1",
            "box-out" => "box-out:x0,y0,z0,x1,y1,z1",
            "sor" => "sor:K,ALPHA",
            "gauss" => "gauss:SIGMA,RADIUS",
            _ => return Err(FilterParseError::UnknownKind(kind.to_owned())),
        };
        let bad = |reason: String| FilterParseError::BadArguments {
            input: s.to_owned(),
            usage,
            reason,
        };
        let parts: Vec<&str> = args.split(',').map(str::trim).collect();
        let expected = match kind {
            "voxel" => 1,
            "box" | "box-out" => 6,
            _ => 2,
        };
        if parts.len() != expected || parts.iter().any(|p| p.is_empty()) {
            return Err(bad(format!("{expected} comma-separated values needed")));
        }
        let num = |t: &str| -> Result<f64, FilterParseError> {
            t.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| bad(format!("{t:?} is not a finite number")))
        };
        let positive = |t: &str| -> Result<f64, FilterParseError> {
            let v = num(t)?;
            if v > 0.0 {
                Ok(v)
            } else {
                Err(bad(format!("{t} must be greater than 0")))
            }
        };
        Ok(match kind {
            "voxel" => {
                let leaf = positive(parts[0])? as f32;
                if !(leaf > 0.0 && leaf.is_finite()) {
                    return Err(bad("leaf is out of f32 range".into()));
                }
                Self::Voxel { leaf }
            }
            "box" | "box-out" => {
                let mut v = [0.0; 6];
                for (out, t) in v.iter_mut().zip(&parts) {
                    *out = num(t)?;
                }
                let (min, max) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
                if min.iter().zip(&max).any(|(a, b)| a > b) {
                    return Err(bad("each of x0, y0, z0 must be ≤ x1, y1, z1".into()));
                }
                if kind == "box" {
                    Self::Box { min, max }
                } else {
                    Self::BoxOut { min, max }
                }
            }
            "sor" => {
                let k = parts[0]
                    .parse::<usize>()
                    .ok()
                    .and_then(NonZeroUsize::new)
                    .ok_or_else(|| bad(format!("K = {:?} must be an integer ≥ 1", parts[0])))?;
                Self::Sor {
                    k,
                    alpha: num(parts[1])?,
                }
            }
            _ => Self::Gauss {
                sigma: positive(parts[0])?,
                radius: positive(parts[1])?,
            },
        })
    }
}

impl fmt::Display for Filter {
    /// The CLI form, which parses back to the same filter.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let corners = |f: &mut fmt::Formatter<'_>, name, min: &[f64; 3], max: &[f64; 3]| {
            write!(
                f,
                "{name}:{},{},{},{},{},{}",
                min[0], min[1], min[2], max[0], max[1], max[2]
            )
        };
        match self {
            Self::Voxel { leaf } => write!(f, "voxel:{leaf}"),
            Self::Box { min, max } => corners(f, "box", min, max),
            Self::BoxOut { min, max } => corners(f, "box-out", min, max),
            Self::Sor { k, alpha } => write!(f, "sor:{k},{alpha}"),
            Self::Gauss { sigma, radius } => write!(f, "gauss:{sigma},{radius}"),
        }
    }
}

impl Filter {
    /// Runs this filter; the output has the input's bundles and origins, in order.
    pub fn apply(&self, bundles: &[RayBundle]) -> Result<Vec<RayBundle>, FilterError> {
        match self {
            Self::Voxel { leaf } => voxel_grid(bundles, *leaf),
            Self::Box { min, max } => Ok(pass_through(bundles, min, max, true)),
            Self::BoxOut { min, max } => Ok(pass_through(bundles, min, max, false)),
            Self::Sor { k, alpha } => statistical_outlier_removal(bundles, *k, *alpha),
            Self::Gauss { sigma, radius } => gaussian(bundles, *sigma, *radius),
        }
    }
}

/// Runs `filters` one after the other, in order.
pub fn apply_all(
    filters: &[Filter],
    bundles: Vec<RayBundle>,
) -> Result<Vec<RayBundle>, FilterError> {
    filters.iter().try_fold(bundles, |s, f| f.apply(&s))
}

fn finite(p: &[f32; 3]) -> bool {
    p.iter().all(|c| c.is_finite())
}

/// Empty bundles with the input's origins, to be refilled.
fn empty_like(bundles: &[RayBundle]) -> Vec<RayBundle> {
    bundles
        .iter()
        .map(|s| RayBundle {
            origin: s.origin,
            points: Vec::new(),
        })
        .collect()
}

/// All finite points in bundle order with the index of their bundle.
struct Flat {
    points: Vec<[f32; 3]>,
    bundle: Vec<u32>,
}

fn flatten(bundles: &[RayBundle]) -> Result<Flat, FilterError> {
    let total: usize = bundles.iter().map(|s| s.points.len()).sum();
    if u32::try_from(total).is_err() || u32::try_from(bundles.len()).is_err() {
        return Err(FilterError::TooManyPoints(total));
    }
    let mut flat = Flat {
        points: Vec::with_capacity(total),
        bundle: Vec::with_capacity(total),
    };
    for (si, s) in bundles.iter().enumerate() {
        for p in s.points.iter().filter(|p| finite(p)) {
            flat.points.push(*p);
            flat.bundle.push(si as u32);
        }
    }
    Ok(flat)
}

fn pass_through(
    bundles: &[RayBundle],
    min: &[f64; 3],
    max: &[f64; 3],
    keep_inside: bool,
) -> Vec<RayBundle> {
    let inside = |p: &[f32; 3]| {
        (0..3).all(|a| {
            let c = f64::from(p[a]);
            min[a] <= c && c <= max[a]
        })
    };
    bundles
        .iter()
        .map(|s| RayBundle {
            origin: s.origin,
            points: s
                .points
                .iter()
                .filter(|p| finite(p) && inside(p) == keep_inside)
                .copied()
                .collect(),
        })
        .collect()
}

fn voxel_grid(bundles: &[RayBundle], leaf: f32) -> Result<Vec<RayBundle>, FilterError> {
    let flat = flatten(bundles)?;
    let inverse = 1.0f32 / leaf;
    // (k, j, i, flat index): sorting gives PCL's (z, y, x) voxel order, members in bundle order.
    let mut cells: Vec<([i32; 3], u32)> = Vec::with_capacity(flat.points.len());
    for (idx, p) in flat.points.iter().enumerate() {
        let mut kji = [0i32; 3];
        for (axis, out) in [2, 1, 0].into_iter().zip(kji.iter_mut()) {
            let v = (p[axis] * inverse).floor();
            if !(v >= i32::MIN as f32 && v < i32::MAX as f32) {
                return Err(FilterError::LeafTooSmall {
                    leaf,
                    coordinate: p[axis],
                });
            }
            *out = v as i32;
        }
        cells.push((kji, idx as u32));
    }
    cells.sort_unstable();
    let mut out = empty_like(bundles);
    for group in cells.chunk_by(|a, b| a.0 == b.0) {
        let mut sum = [0.0f64; 3];
        for &(_, idx) in group {
            let p = flat.points[idx as usize];
            for (s, c) in sum.iter_mut().zip(p) {
                *s += f64::from(c);
            }
        }
        let n = group.len() as f64;
        let centroid = sum.map(|s| s / n);
        let d2 = |idx: u32| {
            let p = flat.points[idx as usize];
            (0..3)
                .map(|a| (f64::from(p[a]) - centroid[a]).powi(2))
                .sum::<f64>()
        };
        // `group` is never empty (chunk_by); min_by keeps the first of equal distances.
        let nearest = group
            .iter()
            .map(|&(_, idx)| (d2(idx), idx))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(0, |(_, idx)| idx);
        let bundle = flat.bundle[nearest as usize] as usize;
        out[bundle].points.push(centroid.map(|c| c as f32));
    }
    Ok(out)
}

/// A k-d tree over `points` reordered along a Morton (Z-order) curve, with the permutation:
/// `points[order[j]]` is the tree's item `j`. Querying in that order keeps consecutive
/// queries in neighbouring tree leaves, which on millions of points is several times faster
/// than file order (cache misses dominate). Pure function of the input, so deterministic.
struct SpatialIndex {
    tree: ImmutableKdTree<f32, 3>,
    sorted: Vec<[f32; 3]>,
    order: Vec<u32>,
}

impl SpatialIndex {
    fn new(points: &[[f32; 3]]) -> Result<Self, FilterError> {
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for p in points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let scale = (0..3)
            .map(|a| 1023.0 / f64::from(hi[a] - lo[a]).max(1e-9))
            .collect::<Vec<_>>();
        // 10 bits per axis: the order only needs to be local, not exact.
        let quantised = |p: &[f32; 3]| {
            morton(
                [0, 1, 2].map(|a| (f64::from(p[a] - lo[a]) * scale[a]).clamp(0.0, 1023.0) as u16),
            )
        };
        let mut keyed: Vec<(u64, u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (quantised(p), i as u32))
            .collect();
        keyed.sort_unstable();
        let order: Vec<u32> = keyed.into_iter().map(|(_, i)| i).collect();
        let sorted: Vec<[f32; 3]> = order.iter().map(|&i| points[i as usize]).collect();
        let tree = ImmutableKdTree::new_from_slice(&sorted)
            .map_err(|e| FilterError::KdTree(e.to_string()))?;
        Ok(Self {
            tree,
            sorted,
            order,
        })
    }

    /// Evaluates `f(point, &tree, &sorted_points)` for every point, in Morton order, and
    /// returns the results in the original point order.
    fn map<T: Clone + Default>(
        &self,
        f: impl Fn(&[f32; 3], &ImmutableKdTree<f32, 3>, &[[f32; 3]]) -> T,
    ) -> Vec<T> {
        let mut out = vec![T::default(); self.sorted.len()];
        for (p, &i) in self.sorted.iter().zip(&self.order) {
            out[i as usize] = f(p, &self.tree, &self.sorted);
        }
        out
    }
}

fn statistical_outlier_removal(
    bundles: &[RayBundle],
    k: NonZeroUsize,
    alpha: f64,
) -> Result<Vec<RayBundle>, FilterError> {
    let flat = flatten(bundles)?;
    let n = flat.points.len();
    let mut out = empty_like(bundles);
    if n < 2 {
        for (p, s) in flat.points.iter().zip(&flat.bundle) {
            out[*s as usize].points.push(*p);
        }
        return Ok(out);
    }
    let index = SpatialIndex::new(&flat.points)?;
    let searched = k.saturating_add(1);
    let mean_distances: Vec<f64> = index.map(|p, tree, _| {
        let hits = tree
            .query(p)
            .nearest_n::<SquaredEuclidean<f32>>(searched)
            .execute();
        // The first hit (distance 0) is the query point itself; n ≥ 2 so there are more.
        let neighbours = hits.len().saturating_sub(1).max(1);
        let sum: f64 = hits
            .iter()
            .skip(1)
            .map(|h| f64::from(h.distance).sqrt())
            .sum();
        sum / neighbours as f64
    });
    let count = n as f64;
    let sum: f64 = mean_distances.iter().sum();
    let sq_sum: f64 = mean_distances.iter().map(|d| d * d).sum();
    let mean = sum / count;
    let variance = ((sq_sum - sum * sum / count) / (count - 1.0)).max(0.0);
    let threshold = mean + alpha * variance.sqrt();
    for ((p, s), d) in flat.points.iter().zip(&flat.bundle).zip(&mean_distances) {
        if *d <= threshold {
            out[*s as usize].points.push(*p);
        }
    }
    Ok(out)
}

fn gaussian(bundles: &[RayBundle], sigma: f64, radius: f64) -> Result<Vec<RayBundle>, FilterError> {
    let flat = flatten(bundles)?;
    let mut out = empty_like(bundles);
    if flat.points.is_empty() {
        return Ok(out);
    }
    let index = SpatialIndex::new(&flat.points)?;
    let r2 = (radius * radius) as f32;
    let inv_two_sigma2 = 1.0 / (2.0 * sigma * sigma);
    let moved: Vec<[f32; 3]> = index.map(|p, tree, sorted| {
        let hits = tree
            .query(p)
            .within::<SquaredEuclidean<f32>>(r2)
            .unsorted()
            .execute();
        let (mut acc, mut total) = ([0.0f64; 3], 0.0f64);
        for h in &hits {
            let q = sorted.get(h.item as usize).copied().unwrap_or(*p);
            let w = (-f64::from(h.distance) * inv_two_sigma2).exp();
            for (a, c) in acc.iter_mut().zip(q) {
                *a += w * f64::from(c);
            }
            total += w;
        }
        // The point itself is always a hit with weight 1, so `total ≥ 1`.
        if total > 0.0 {
            acc.map(|a| (a / total) as f32)
        } else {
            *p
        }
    });
    for (p, s) in moved.into_iter().zip(&flat.bundle) {
        out[*s as usize].points.push(p);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bundle(origin: [f64; 3], points: &[[f32; 3]]) -> RayBundle {
        RayBundle {
            origin,
            points: points.to_vec(),
        }
    }

    fn close(a: [f32; 3], b: [f32; 3], tol: f32) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    const A: [f64; 3] = [0.0, 0.0, 1.0];
    const B: [f64; 3] = [5.0, 5.0, 1.0];

    #[test]
    fn parse_and_display() {
        let cases = [
            ("voxel:0.05", Filter::Voxel { leaf: 0.05 }),
            (
                "box:-1,-2,-3,1,2,3",
                Filter::Box {
                    min: [-1.0, -2.0, -3.0],
                    max: [1.0, 2.0, 3.0],
                },
            ),
            (
                "box-out:0,0,0,0.5,0.5,2.5",
                Filter::BoxOut {
                    min: [0.0; 3],
                    max: [0.5, 0.5, 2.5],
                },
            ),
            (
                "sor:8,1.5",
                Filter::Sor {
                    k: NonZeroUsize::new(8).unwrap(),
                    alpha: 1.5,
                },
            ),
            (
                "gauss:0.02,0.06",
                Filter::Gauss {
                    sigma: 0.02,
                    radius: 0.06,
                },
            ),
        ];
        for (text, filter) in cases {
            assert_eq!(text.parse::<Filter>().unwrap(), filter, "{text}");
            assert_eq!(filter.to_string(), text);
        }
        assert_eq!(
            " sor: 3 , -0.5".parse::<Filter>().unwrap(),
            Filter::Sor {
                k: NonZeroUsize::new(3).unwrap(),
                alpha: -0.5
            }
        );
    }

    #[test]
    fn parse_errors_are_clear() {
        let err = |s: &str| s.parse::<Filter>().unwrap_err();
        assert_eq!(
            err("median:3"),
            FilterParseError::UnknownKind("median".into())
        );
        for bad in [
            "voxel",
            "voxel:",
            "voxel:0",
            "voxel:-1",
            "voxel:nan",
            "voxel:1e60",
            "voxel:1,2",
            "box:0,0,0,1,1",
            "box:1,0,0,0,1,1",
            "box-out:0,0,0,1,1,x",
            "sor:0,1",
            "sor:2.5,1",
            "sor:3,inf",
            "gauss:0,1",
            "gauss:1",
        ] {
            let e = err(bad);
            assert!(
                matches!(e, FilterParseError::BadArguments { .. }),
                "{bad}: {e}"
            );
            assert!(e.to_string().contains("expected"), "{bad}: {e}");
        }
    }

    #[test]
    fn voxel_centroid_goes_to_nearest_members_bundle() {
        let bundles = [
            bundle(
                A,
                &[
                    [0.1, 0.1, 0.1],
                    [0.3, 0.5, 0.9],
                    [1.5, -0.5, 0.0],
                    [-0.2, 0.0, 0.0],
                ],
            ),
            bundle(B, &[[0.5, 0.2, 0.2], [f32::NAN, 0.0, 0.0]]),
        ];
        let out = Filter::Voxel { leaf: 1.0 }.apply(&bundles).unwrap();
        assert_eq!(out.len(), 2);
        assert_eq!((out[0].origin, out[1].origin), (A, B));
        // Voxel (0,0,0): centroid (0.3, 0.26667, 0.4); squared distances to its members
        // 0.1578, 0.3044, 0.0844 → the B point is nearest.
        assert_eq!(out[1].points.len(), 1);
        assert!(
            close(out[1].points[0], [0.3, 0.266_666_67, 0.4], 1e-6),
            "{:?}",
            out[1]
        );
        // Voxel (1,-1,0) sorts before (-1,0,0) in (z, y, x) order; singletons are unchanged.
        assert_eq!(out[0].points, vec![[1.5, -0.5, 0.0], [-0.2, 0.0, 0.0]]);
    }

    #[test]
    fn voxel_grid_is_anchored_at_world_multiples_like_pcl() {
        // floor((p - min)/leaf) would merge 0.9 and 1.1; PCL's floor(p/leaf) does not.
        let bundles = [bundle(
            A,
            &[[0.9, 0.0, 0.0], [1.1, 0.0, 0.0], [1.7, 0.0, 0.0]],
        )];
        let out = Filter::Voxel { leaf: 1.0 }.apply(&bundles).unwrap();
        assert_eq!(out[0].points.len(), 2);
        assert_eq!(out[0].points[0], [0.9, 0.0, 0.0]);
        assert!(close(out[0].points[1], [1.4, 0.0, 0.0], 1e-6));
        let far = [bundle(A, &[[1e6, 0.0, 0.0]])];
        assert!(matches!(
            Filter::Voxel { leaf: 1e-4 }.apply(&far),
            Err(FilterError::LeafTooSmall { .. })
        ));
    }

    fn grid(n: i32, spacing: f32) -> Vec<[f32; 3]> {
        let mut g = Vec::new();
        for y in 0..n {
            for x in 0..n {
                g.push([x as f32 * spacing, y as f32 * spacing, 0.0]);
            }
        }
        g
    }

    #[test]
    fn box_keep_and_remove_counts() {
        // 5 × 5 grid at 0..4; the box [1, 3] × [1, 3] × [0, 0] holds 9 (its edges inclusive).
        let bundles = [
            bundle(A, &grid(5, 1.0)[..10]),
            bundle(B, &grid(5, 1.0)[10..]),
        ];
        let (min, max) = ([1.0, 1.0, 0.0], [3.0, 3.0, 0.0]);
        let kept = Filter::Box { min, max }.apply(&bundles).unwrap();
        let removed = Filter::BoxOut { min, max }.apply(&bundles).unwrap();
        let counts = |s: &[RayBundle]| s.iter().map(|s| s.points.len()).collect::<Vec<_>>();
        // Rows y = 0, 1 are bundle A: row 1 has x = 1..3 inside. Rows 2..4 are bundle B: 6 inside.
        assert_eq!(counts(&kept), vec![3, 6]);
        assert_eq!(counts(&removed), vec![7, 9]);
        assert_eq!(
            kept[0].points,
            vec![[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [3.0, 1.0, 0.0]]
        );
        assert_eq!((removed[0].origin, removed[1].origin), (A, B));
    }

    #[test]
    fn sor_removes_planted_outlier_and_keeps_grid() {
        let mut b = vec![[2.0, 2.0, 10.0]];
        b.extend_from_slice(&grid(5, 1.0)[20..]);
        let bundles = [bundle(A, &grid(5, 1.0)[..20]), bundle(B, &b)];
        let f: Filter = "sor:4,1".parse().unwrap();
        let out = f.apply(&bundles).unwrap();
        assert_eq!(out[0].points, grid(5, 1.0)[..20].to_vec());
        assert_eq!(out[1].points, grid(5, 1.0)[20..].to_vec());
        assert_eq!(out[1].origin, B);
    }

    #[test]
    fn sor_k_excludes_the_point_itself() {
        // k = 1: mean distances 1, 1, 2 → mean 4/3, σ = √(1/3); ALPHA 0 keeps d ≤ 4/3.
        // (Counting the point itself, every distance would be 0 and all three kept.)
        let bundles = [bundle(
            A,
            &[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]],
        )];
        let out = "sor:1,0"
            .parse::<Filter>()
            .unwrap()
            .apply(&bundles)
            .unwrap();
        assert_eq!(out[0].points, vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]);
        // ALPHA 1: threshold 4/3 + 0.577 = 1.91 < 2 still removes it; ALPHA 2 (2.49) keeps it.
        let out = "sor:1,2"
            .parse::<Filter>()
            .unwrap()
            .apply(&bundles)
            .unwrap();
        assert_eq!(out[0].points.len(), 3);
        // Duplicates and tiny clouds do not break it.
        let dup = [bundle(A, &[[1.0, 1.0, 1.0]; 50])];
        assert_eq!(
            "sor:8,1".parse::<Filter>().unwrap().apply(&dup).unwrap()[0]
                .points
                .len(),
            50
        );
        let one = [bundle(A, &[[1.0, 1.0, 1.0]])];
        assert_eq!(
            "sor:8,1".parse::<Filter>().unwrap().apply(&one).unwrap(),
            one.to_vec()
        );
    }

    #[test]
    fn gaussian_two_points_by_hand() {
        // d = 1, σ = 1: w = e^-0.5 = 0.606531; x0' = w / (1 + w), x1' = 1 / (1 + w).
        let bundles = [bundle(A, &[[0.0, 0.0, 0.0]]), bundle(B, &[[1.0, 0.0, 0.0]])];
        let out = "gauss:1,1"
            .parse::<Filter>()
            .unwrap()
            .apply(&bundles)
            .unwrap();
        assert!(
            close(out[0].points[0], [0.377_541, 0.0, 0.0], 1e-6),
            "{out:?}"
        );
        assert!(
            close(out[1].points[0], [0.622_459, 0.0, 0.0], 1e-6),
            "{out:?}"
        );
        // Radius below the distance: nothing moves.
        let out = "gauss:1,0.5"
            .parse::<Filter>()
            .unwrap()
            .apply(&bundles)
            .unwrap();
        assert_eq!(out, bundles.to_vec());
    }

    #[test]
    fn gaussian_flattens_a_noisy_plane_and_keeps_points() {
        // 20 × 20 plane, spacing 0.1, z = ±0.01 in a checkerboard.
        let mut noisy = grid(20, 0.1);
        for (i, p) in noisy.iter_mut().enumerate() {
            p[2] = if (i % 20 + i / 20) % 2 == 0 {
                0.01
            } else {
                -0.01
            };
        }
        let bundles = [bundle(A, &noisy[..200]), bundle(B, &noisy[200..])];
        let out = "gauss:0.1,0.25"
            .parse::<Filter>()
            .unwrap()
            .apply(&bundles)
            .unwrap();
        assert_eq!((out[0].points.len(), out[1].points.len()), (200, 200));
        assert_eq!((out[0].origin, out[1].origin), (A, B));
        let spread = |s: &[RayBundle]| {
            let z = s.iter().flat_map(|s| s.points.iter().map(|p| p[2]));
            let (lo, hi) = z.fold((f32::MAX, f32::MIN), |(lo, hi), z| (lo.min(z), hi.max(z)));
            hi - lo
        };
        assert!((spread(&bundles) - 0.02).abs() < 1e-6);
        assert!(spread(&out) < 0.01, "{}", spread(&out));
        // x, y stay near the grid (interior points barely move in the plane).
        assert!(close(out[0].points[21], noisy[21], 0.02));
    }

    #[test]
    fn apply_all_runs_in_order_and_is_deterministic() {
        let mut pts = grid(30, 0.0625);
        pts.push([0.7, 0.7, 5.0]);
        let bundles = vec![bundle(A, &pts[..450]), bundle(B, &pts[450..])];
        let filters: Vec<Filter> = [
            "box:-1,-1,-1,2,2,2",
            "voxel:0.125",
            "sor:4,1",
            "gauss:0.05,0.1",
        ]
        .iter()
        .map(|s| s.parse().unwrap())
        .collect();
        let a = apply_all(&filters, bundles.clone()).unwrap();
        let b = apply_all(&filters, bundles).unwrap();
        assert_eq!(a, b);
        // The box cuts the outlier; 30 × 30 at 1/16 m over 1/8 m leaves gives a 15 × 15 grid
        // of spacing s; SOR (k = 4) then sees interior points at s, border ones at 1.104 s and
        // corners at 1.354 s: mean 1.030 s, σ 0.062 s, so mean + σ = 1.092 s drops the border
        // ring and keeps the 13 × 13 interior.
        assert_eq!(a.iter().map(|s| s.points.len()).sum::<usize>(), 169);
        assert_eq!((a[0].origin, a[1].origin), (A, B));
    }
}
