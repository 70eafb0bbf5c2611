//! What the point-cloud readers and writers share: the flat point list PLY and PCD store
//! ([`FlatCloud`]) with its origins, the body [`Encoding`], the [`CloudFormat`]s by extension,
//! and the grouping of flat points into per-origin bundles ([`LoadedBundles`], [`OriginError`]).
//!
//! It sits below [`super::ply`], [`super::pcd`] and [`super::io`]: the readers use these types
//! and never [`super::io`], which picks the format and calls them.

use std::path::Path;

use super::RayBundle;

/// Text or binary body, for the formats that have both (PLY, PCD).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Encoding {
    /// Little-endian binary (PLY `binary_little_endian`, PCD `DATA binary`).
    #[default]
    Binary,
    /// Human-readable text (PLY `ascii`, PCD `DATA ascii`).
    Ascii,
}

/// Where the points of a flat cloud were seen from, as a file states it.
#[derive(Debug, Clone, PartialEq)]
pub enum Origins {
    /// The file says nothing about the sensor origin.
    Unknown,
    /// One origin for the whole cloud (PCD `VIEWPOINT`).
    Viewpoint([f64; 3]),
    /// One origin per point, parallel to [`FlatCloud::points`].
    PerPoint(Vec<[f64; 3]>),
}

/// A flat point list as PLY and PCD store it, with whatever origin information the file had.
#[derive(Debug, Clone, PartialEq)]
pub struct FlatCloud {
    /// The points, in file order.
    pub points: Vec<[f32; 3]>,
    /// Their sensor origins.
    pub origins: Origins,
}

/// Bundles read from a cloud, and how many of the file's points did not make it into them.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadedBundles {
    /// The bundles, in file order.
    pub bundles: Vec<RayBundle>,
    /// Points dropped because a coordinate or their origin was NaN or infinite (PCL marks
    /// "no return" with NaN in organised clouds). `.scans` files keep such points (the octree
    /// skips and counts them), so this is 0 for them.
    pub dropped_nonfinite: u64,
}

/// Why a flat cloud could not be turned into bundles.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OriginError {
    /// No origin in the file and none given by the caller.
    #[error("the cloud has no sensor origin: pass --origin x,y,z")]
    Missing,
    /// Per-point origins whose count differs from the point count.
    #[error("{origins} per-point origins for {points} points")]
    CountMismatch {
        /// Number of origins.
        origins: usize,
        /// Number of points.
        points: usize,
    },
}

impl FlatCloud {
    /// Flattens bundles into a point list with one origin per point (bundle order, then point
    /// order). Empty bundles vanish: a flat cloud cannot carry an origin without a point.
    pub fn from_bundles(bundles: &[RayBundle]) -> Self {
        let total = bundles.iter().map(|s| s.points.len()).sum();
        let mut points = Vec::with_capacity(total);
        let mut origins = Vec::with_capacity(total);
        for bundle in bundles {
            points.extend_from_slice(&bundle.points);
            origins.extend(std::iter::repeat_n(bundle.origin, bundle.points.len()));
        }
        Self {
            points,
            origins: Origins::PerPoint(origins),
        }
    }

    /// Groups the points into bundles, dropping (and counting) points with a non-finite
    /// coordinate or origin (PCL marks "no return" with NaN in organised clouds).
    ///
    /// - Per-point origins: each maximal run of consecutive points with bit-identical origins
    ///   becomes one bundle, in file order (so [`FlatCloud::from_bundles`] round-trips, except
    ///   that adjacent bundles with equal origins merge).
    /// - A cloud-wide viewpoint: one bundle from it, except that an all-zero viewpoint
    ///   (PCL's default, written by every PCL tool whatever the sensor was) yields to
    ///   `default_origin` when one is given.
    /// - No origin: one bundle from `default_origin`, or [`OriginError::Missing`].
    pub fn into_bundles(
        self,
        default_origin: Option<[f64; 3]>,
    ) -> Result<LoadedBundles, OriginError> {
        let total = self.points.len() as u64;
        let bundles = self.into_finite_bundles(default_origin)?;
        let kept: u64 = bundles.iter().map(|s| s.points.len() as u64).sum();
        Ok(LoadedBundles {
            bundles,
            dropped_nonfinite: total - kept,
        })
    }

    fn into_finite_bundles(
        self,
        default_origin: Option<[f64; 3]>,
    ) -> Result<Vec<RayBundle>, OriginError> {
        let finite3 = |p: &[f32; 3]| p.iter().all(|c| c.is_finite());
        let single = |origin: [f64; 3], points: Vec<[f32; 3]>| {
            let points: Vec<_> = points.into_iter().filter(finite3).collect();
            vec![RayBundle { origin, points }]
        };
        match self.origins {
            Origins::PerPoint(origins) => {
                if origins.len() != self.points.len() {
                    return Err(OriginError::CountMismatch {
                        origins: origins.len(),
                        points: self.points.len(),
                    });
                }
                let mut bundles: Vec<RayBundle> = Vec::new();
                for (p, o) in self.points.into_iter().zip(origins) {
                    // Per-point origins are written as f32 fields (PLY `sx sy sz`, PCD `vp_*`),
                    // so one beyond f32's range is dropped here, counted, like an infinite one,
                    // rather than turned into an infinite origin by the next write.
                    if !finite3(&p) || !o.iter().all(|&c| (c as f32).is_finite()) {
                        continue;
                    }
                    match bundles.last_mut() {
                        Some(last) if same_origin(&last.origin, &o) => last.points.push(p),
                        _ => bundles.push(RayBundle {
                            origin: o,
                            points: vec![p],
                        }),
                    }
                }
                Ok(bundles)
            }
            Origins::Viewpoint(v) => match default_origin {
                Some(d) if v == [0.0; 3] => Ok(single(d, self.points)),
                _ => Ok(single(v, self.points)),
            },
            Origins::Unknown => match default_origin {
                Some(d) => Ok(single(d, self.points)),
                None if self.points.is_empty() => Ok(Vec::new()),
                None => Err(OriginError::Missing),
            },
        }
    }
}

/// Bit-identical origins (so `-0.0` and `0.0` are different bundles, and NaN never matches).
fn same_origin(a: &[f64; 3], b: &[f64; 3]) -> bool {
    a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// The formats [`super::io::load`] and [`super::io::save`] know, by extension (case-insensitive).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CloudFormat {
    /// `.scans`.
    Scans,
    /// `.ply`.
    Ply,
    /// `.pcd`.
    Pcd,
}

impl CloudFormat {
    /// The format named by `path`'s extension, if it is one of ours.
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "scans" => Some(Self::Scans),
            "ply" => Some(Self::Ply),
            "pcd" => Some(Self::Pcd),
            _ => None,
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Two bundles with distinct origins, for the cloud format tests.
    pub(crate) fn two_bundles() -> Vec<RayBundle> {
        vec![
            RayBundle {
                origin: [1.0, 2.0, 0.5],
                points: vec![[1.5, 2.0, 0.25], [0.0, -1.0, 3.0]],
            },
            RayBundle {
                origin: [-4.0, 0.25, 1.0],
                points: vec![[7.0, 8.0, 9.0]],
            },
        ]
    }

    #[test]
    fn flat_round_trip_keeps_bundles_and_origins() {
        let flat = FlatCloud::from_bundles(&two_bundles());
        assert_eq!(flat.points.len(), 3);
        assert_eq!(
            flat.origins,
            Origins::PerPoint(vec![[1.0, 2.0, 0.5], [1.0, 2.0, 0.5], [-4.0, 0.25, 1.0]])
        );
        assert_eq!(flat.into_bundles(None).unwrap().bundles, two_bundles());
    }

    #[test]
    fn origin_rules() {
        let pts = vec![[1.0, 1.0, 1.0], [f32::NAN, 0.0, 0.0]];
        let unknown = FlatCloud {
            points: pts.clone(),
            origins: Origins::Unknown,
        };
        assert_eq!(
            unknown.clone().into_bundles(None),
            Err(OriginError::Missing)
        );
        assert!(OriginError::Missing.to_string().contains("--origin"));
        let got = unknown.into_bundles(Some([0.0, 0.0, 2.0])).unwrap();
        assert_eq!(got.dropped_nonfinite, 1);
        assert_eq!(
            got.bundles,
            vec![RayBundle {
                origin: [0.0, 0.0, 2.0],
                points: vec![[1.0, 1.0, 1.0]] // NaN point dropped
            }]
        );
        let zero_vp = FlatCloud {
            points: pts.clone(),
            origins: Origins::Viewpoint([0.0; 3]),
        };
        assert_eq!(
            zero_vp.clone().into_bundles(None).unwrap().bundles[0].origin,
            [0.0; 3]
        );
        assert_eq!(
            zero_vp.into_bundles(Some([5.0, 0.0, 0.0])).unwrap().bundles[0].origin,
            [5.0, 0.0, 0.0]
        );
        let vp = FlatCloud {
            points: pts,
            origins: Origins::Viewpoint([1.0, 0.0, 0.0]),
        };
        assert_eq!(
            vp.into_bundles(Some([5.0, 0.0, 0.0])).unwrap().bundles[0].origin,
            [1.0, 0.0, 0.0]
        );
        let bad = FlatCloud {
            points: vec![[0.0; 3]],
            origins: Origins::PerPoint(vec![]),
        };
        assert_eq!(
            bad.into_bundles(None),
            Err(OriginError::CountMismatch {
                origins: 0,
                points: 1
            })
        );
    }

    #[test]
    fn nonfinite_points_and_origins_are_dropped_and_counted() {
        let flat = FlatCloud {
            points: vec![
                [1.0, 0.0, 0.0],
                [f32::NAN, 0.0, 0.0],
                [2.0, 0.0, 0.0],
                [0.0, f32::NEG_INFINITY, 0.0],
                [3.0, 0.0, 0.0],
            ],
            origins: Origins::PerPoint(vec![
                [0.0; 3],
                [0.0; 3],
                [0.0, f64::NAN, 0.0],
                [0.0; 3],
                [0.0; 3],
            ]),
        };
        let got = flat.into_bundles(None).unwrap();
        assert_eq!(got.dropped_nonfinite, 3);
        assert_eq!(
            got.bundles,
            vec![RayBundle {
                origin: [0.0; 3],
                points: vec![[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]
            }]
        );
    }

    #[test]
    fn a_per_point_origin_beyond_f32_is_dropped_at_read_not_lost_by_the_next_write() {
        // Found by fuzz/fuzz_targets/pcd.rs (fuzz/regressions/pcd/): a finite f64 origin of
        // 1e39 was kept, then written to an f32 `vp_x` as inf, and its point vanished on re-read.
        let flat = FlatCloud {
            points: vec![[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]],
            origins: Origins::PerPoint(vec![[0.0; 3], [1e39, 0.0, 0.0], [0.5, 0.0, 0.0]]),
        };
        let got = flat.into_bundles(None).unwrap();
        assert_eq!(got.dropped_nonfinite, 1);
        let kept: Vec<_> = got.bundles.iter().flat_map(|s| s.points.clone()).collect();
        assert_eq!(kept, vec![[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]);
        let mut pcd = Vec::new();
        crate::cloud::pcd::write_pcd_bundles(&mut pcd, &got.bundles, Encoding::Binary).unwrap();
        let back = crate::cloud::pcd::parse_pcd(&pcd)
            .unwrap()
            .into_bundles(None)
            .unwrap();
        assert_eq!(back.dropped_nonfinite, 0);
        assert_eq!(back.bundles, got.bundles);
    }
}
