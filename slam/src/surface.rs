//! Where the walls are within a cell: the beam endpoints each cell has seen, as a mean and a
//! scatter, and a refinement of a grid match against them.
//!
//! An occupancy grid puts a wall at the centre of the cell its endpoints fall in, up to half a
//! cell from the true face. Where a wall runs along the cell lattice every endpoint on it is off
//! by the same amount, and a match against the grid inherits that offset; under range noise the
//! wall is stored in whichever cell most endpoints fell in. The mean of the endpoints around a
//! cell is where the wall is, to a fraction of a cell, and their scatter is how far a new
//! endpoint may fall from it. [`refine`] takes a grid match and moves it so that each endpoint is
//! likely under the nearest cell's Gaussian (the Normal Distributions Transform, Biber & Straßer
//! 2003), by Gauss–Newton with the same robust loss and motion prior as the grid matcher.
//!
//! Each cell's Gaussian is fitted to the endpoints of the 3×3 cells around it, not its own alone
//! (as NDT's overlapping cells do). A far wall gets one endpoint every few cells from one
//! revolution; alone, such a cell has no shape, and which cells have one depends on where that
//! revolution's beams happened to fall, so a match against them turns with the beams' azimuths
//! (±0.4° in the simulated room at rest). Pooled, every wall cell is a thin line along the wall,
//! and an endpoint sliding along it costs little.

// 2×2 and 3×3 algebra reads best with explicit indices.
#![allow(clippy::needless_range_loop)]

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use crate::grid::cell_containing;
use crate::matcher::{Fit, Loss, Matrix3, Prior, fill_lower, residual_scale, solve};
use crate::pose::Pose2;

/// How the grid match is refined against the cells' endpoint statistics.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RefineConfig {
    /// Refine every grid match (`false`: the grid match is the pose, as in Hector SLAM).
    pub enabled: bool,
    /// A cell takes part once it has collected this many endpoints.
    pub min_points: u32,
    /// Added to each cell's spread, both ways (m): a wall seen without noise still has a width,
    /// and one endpoint cannot make a cell infinitely sure.
    pub sigma_floor: f64,
    /// Gauss–Newton iterations.
    pub iterations: usize,
    /// Robust loss on each endpoint's Mahalanobis distance to its cell.
    pub loss: Loss,
    /// A refinement that would move the grid match farther than this (m)...
    pub max_translation: f64,
    /// ...or turn it more than this (rad) is not taken: the grid match stands.
    pub max_rotation: f64,
    /// For a scan with per-beam times (a revolution): how far its own velocity may be from the
    /// motion between the previous scan's pose and this one's grid match, one standard
    /// deviation along x and y (m/s)...
    pub velocity_translation_sigma: f64,
    /// ...and in heading (rad/s). The refinement finds the velocity with the pose.
    pub velocity_rotation_sigma: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            min_points: 3,
            sigma_floor: 0.01,
            iterations: 10,
            loss: Loss::Cauchy { c: 2.0 },
            max_translation: 0.05,
            max_rotation: 0.02,
            velocity_translation_sigma: 0.2,
            velocity_rotation_sigma: 0.2,
        }
    }
}

/// The endpoints one cell collected: their count, and sums of their coordinates and products,
/// taken from the cell's lower-left corner so the sums keep their precision anywhere in the map.
#[derive(Debug, Clone, Copy, Default)]
struct Moments {
    count: u32,
    x: f64,
    y: f64,
    xx: f64,
    xy: f64,
    yy: f64,
}

impl Moments {
    /// Adds an endpoint at `(u, v)` from the cell's corner.
    fn add(&mut self, u: f64, v: f64) {
        self.count += 1;
        self.x += u;
        self.y += v;
        self.xx += u * u;
        self.xy += u * v;
        self.yy += v * v;
    }

    /// Adds the endpoints `other` holds, whose corner is `(dx, dy)` from this one's.
    fn merge(&mut self, other: &Moments, dx: f64, dy: f64) {
        let n = f64::from(other.count);
        self.count += other.count;
        self.x += other.x + n * dx;
        self.y += other.y + n * dy;
        self.xx += other.xx + 2.0 * dx * other.x + n * dx * dx;
        self.xy += other.xy + dx * other.y + dy * other.x + n * dx * dy;
        self.yy += other.yy + 2.0 * dy * other.y + n * dy * dy;
    }

    /// The cell's Gaussian in the map frame (its corner at `corner`), once it has `min_points`
    /// endpoints; `floor` (m) is added to the spread both ways.
    fn normal(&self, corner: (f64, f64), min_points: u32, floor: f64) -> Option<Normal> {
        if self.count < min_points {
            return None;
        }
        let n = f64::from(self.count);
        let (u, v) = (self.x / n, self.y / n);
        let floor = floor * floor;
        let a = (self.xx / n - u * u).max(0.0) + floor;
        let b = self.xy / n - u * v;
        let c = (self.yy / n - v * v).max(0.0) + floor;
        let det = a * c - b * b;
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        Some(Normal {
            mean: (u + corner.0, v + corner.1),
            information: [[c / det, -b / det], [-b / det, a / det]],
        })
    }
}

/// A cell's Gaussian: mean (map frame) and inverse covariance, for cells with enough endpoints.
#[derive(Debug, Clone, Copy)]
struct Normal {
    mean: (f64, f64),
    information: [[f64; 2]; 2],
}

#[derive(Debug, Clone, Copy, Default)]
struct Cell {
    moments: Moments,
    normal: Option<Normal>,
}

/// Mixes a packed cell index into a hash: cells are dense integers, so SipHash's protection
/// against chosen keys buys nothing here and costs a third of the lookup.
#[derive(Default)]
struct CellHasher(u64);

impl Hasher for CellHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }

    fn write_u64(&mut self, n: u64) {
        self.0 = (self.0 ^ n)
            .wrapping_mul(0x9e37_79b9_7f4a_7c15)
            .rotate_left(29);
    }
}

fn key((i, j): (i32, i32)) -> u64 {
    (u64::from(i as u32) << 32) | u64::from(j as u32)
}

/// The endpoints of every integrated scan, gathered per cell, as the refinement reads them.
#[derive(Debug, Clone)]
pub struct Surfaces {
    resolution: f64,
    min_points: u32,
    floor: f64,
    cells: HashMap<u64, Cell, BuildHasherDefault<CellHasher>>,
}

impl Surfaces {
    /// No endpoints yet, in cells `resolution` metres wide.
    pub fn new(resolution: f64, config: &RefineConfig) -> Self {
        assert!(
            resolution.is_finite() && resolution > 0.0,
            "cell size must be positive"
        );
        Self {
            resolution,
            min_points: config.min_points.max(1),
            floor: config.sigma_floor.max(0.0),
            cells: HashMap::default(),
        }
    }

    /// Cells that have collected at least one endpoint.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// Whether no endpoint was collected yet.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// Adds the endpoints of one scan taken from `sensor_pose`, given in the sensor frame (as
    /// [`crate::grid::GridPyramid::integrate`] takes them).
    pub fn integrate(&mut self, sensor_pose: &Pose2, hits: &[(f64, f64)]) {
        let mut touched = Vec::with_capacity(hits.len());
        for &(sx, sy) in hits {
            let (x, y) = sensor_pose.transform_point(sx, sy);
            if !(x.is_finite() && y.is_finite()) {
                continue;
            }
            let cell = cell_containing(self.resolution, x, y);
            let corner = (
                f64::from(cell.0) * self.resolution,
                f64::from(cell.1) * self.resolution,
            );
            self.cells
                .entry(key(cell))
                .or_default()
                .moments
                .add(x - corner.0, y - corner.1);
            touched.push(cell);
        }
        // Each cell's Gaussian pools its neighbours' endpoints: refit every cell next to one that
        // changed, once.
        let mut stale: Vec<(i32, i32)> = touched
            .iter()
            .flat_map(|&(i, j)| {
                (-1..=1).flat_map(move |di| (-1..=1).map(move |dj| (i + di, j + dj)))
            })
            .collect();
        stale.sort_unstable();
        stale.dedup();
        for cell in stale {
            self.refit(cell);
        }
    }

    /// Refits the Gaussian of `cell`, if it has endpoints, to the endpoints of the 3×3 cells
    /// around it.
    fn refit(&mut self, cell: (i32, i32)) {
        let r = self.resolution;
        let mut pooled = Moments::default();
        for di in -1..=1 {
            for dj in -1..=1 {
                if let Some(c) = self.cells.get(&key((cell.0 + di, cell.1 + dj))) {
                    pooled.merge(&c.moments, f64::from(di) * r, f64::from(dj) * r);
                }
            }
        }
        let corner = (f64::from(cell.0) * r, f64::from(cell.1) * r);
        let normal = pooled.normal(corner, self.min_points, self.floor);
        if let Some(c) = self.cells.get_mut(&key(cell)) {
            c.normal = normal;
        }
    }

    /// The Gaussian nearest to a point (by Mahalanobis distance) among its cell and the eight
    /// around it, with that squared distance.
    fn nearest(&self, x: f64, y: f64) -> Option<(Normal, f64)> {
        let (i, j) = cell_containing(self.resolution, x, y);
        let mut best: Option<(Normal, f64)> = None;
        for di in -1..=1 {
            for dj in -1..=1 {
                let Some(normal) = self
                    .cells
                    .get(&key((i + di, j + dj)))
                    .and_then(|c| c.normal)
                else {
                    continue;
                };
                let d2 = mahalanobis(&normal, x, y);
                if best.is_none_or(|(_, b)| d2 < b) {
                    best = Some((normal, d2));
                }
            }
        }
        best
    }
}

/// The squared Mahalanobis distance of a point from a cell's Gaussian.
fn mahalanobis(normal: &Normal, x: f64, y: f64) -> f64 {
    let (ex, ey) = (x - normal.mean.0, y - normal.mean.1);
    let l = &normal.information;
    ex * (l[0][0] * ex + l[0][1] * ey) + ey * (l[1][0] * ex + l[1][1] * ey)
}

/// A scan taken while the sensor moved (a lidar revolution), for [`refine`]: when each endpoint
/// was seen, relative to the time of the pose being refined, and what the sensor's velocity is
/// thought to be. The refinement then finds the velocity with the pose: endpoint `i` was seen
/// from `pose + offsets[i] · velocity` (x, y and ψ alike, in the map frame; first order over a
/// revolution). A revolution fixes its middle pose best and its velocity a little; the prior
/// on the velocity says how little.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sweep<'a> {
    /// Per endpoint, its time minus the pose's time (s).
    pub offsets: &'a [f64],
    /// The velocity's prior mean: the sensor's x, y (m/s) and ψ (rad/s) rates in the map frame.
    pub velocity: [f64; 3],
    /// The prior's information per component (1/σ²).
    pub information: [f64; 3],
}

impl Sweep<'_> {
    /// Where endpoint `i` was seen from, with the sweep's pose at `pose` and velocity `velocity`.
    fn seen_from(&self, i: usize, pose: &Pose2, velocity: &[f64; 3]) -> (Pose2, f64) {
        let t = self.offsets[i];
        (
            Pose2::new(
                pose.x + t * velocity[0],
                pose.y + t * velocity[1],
                pose.theta + t * velocity[2],
            ),
            t,
        )
    }

    /// The endpoints `points` of this sweep, each seen from its own pose along `velocity`,
    /// placed in the frame of `pose`: the scan de-skewed to the pose's time.
    pub fn place(
        &self,
        points: &[(f64, f64)],
        pose: &Pose2,
        velocity: &[f64; 3],
    ) -> Vec<(f64, f64)> {
        let to_pose = pose.inverse();
        points
            .iter()
            .enumerate()
            .map(|(i, &(x, y))| {
                let (seen, _) = self.seen_from(i, pose, velocity);
                let (mx, my) = seen.transform_point(x, y);
                to_pose.transform_point(mx, my)
            })
            .collect()
    }
}

/// What a refinement did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refinement {
    /// The refined sensor pose (the start when the refinement was not taken).
    pub pose: Pose2,
    /// With a [`Sweep`], the refined velocity (its prior mean when not taken).
    pub velocity: Option<[f64; 3]>,
    /// Endpoints that had a cell to be matched against, at the refined pose.
    pub matched: usize,
    /// Gauss–Newton iterations run.
    pub iterations: usize,
    /// Whether the refinement was taken.
    pub taken: bool,
    /// What the endpoints alone say about the refined pose (with a sweep, its velocity
    /// marginalised out); `None` when the refinement was not taken.
    pub fit: Option<Fit>,
}

/// The robust cost, Gauss–Newton Hessian and right-hand side at one pose (and velocity): the
/// unknowns are x, y, ψ, then with a sweep the three velocity components.
struct Linearised {
    cost: f64,
    /// Σ wᵢ dᵢ² over the endpoints: their robust-weighted squared Mahalanobis distances.
    weighted: f64,
    hessian: [[f64; 6]; 6],
    gradient: [f64; 6],
    matched: usize,
}

fn linearise(
    surfaces: &Surfaces,
    points: &[(f64, f64)],
    pose: &Pose2,
    sweep: Option<&Sweep>,
    velocity: &[f64; 3],
    prior: Option<&Prior>,
    loss: &Loss,
) -> Linearised {
    let unknowns = if sweep.is_some() { 6 } else { 3 };
    let mut h = [[0.0; 6]; 6];
    let mut g = [0.0; 6];
    let mut cost = 0.0;
    let mut weighted = 0.0;
    let mut matched = 0;
    for (i, &(px, py)) in points.iter().enumerate() {
        let (seen, t) = sweep.map_or((*pose, 0.0), |sweep| sweep.seen_from(i, pose, velocity));
        let (s, c) = seen.theta.sin_cos();
        let (mx, my) = (seen.x + c * px - s * py, seen.y + s * px + c * py);
        let Some((normal, d2)) = surfaces.nearest(mx, my) else {
            continue;
        };
        matched += 1;
        let d = d2.sqrt();
        cost += loss.cost(d);
        let w = loss.weight(d);
        weighted += w * d2;
        let l = &normal.information;
        let e = [normal.mean.0 - mx, normal.mean.1 - my];
        // ∂m/∂ξ, columns x, y, ψ, then the velocity's (the same, times the endpoint's offset).
        let (jx, jy) = (-s * px - c * py, c * px - s * py);
        let jac = [
            [1.0, 0.0, jx, t, 0.0, t * jx],
            [0.0, 1.0, jy, 0.0, t, t * jy],
        ];
        for a in 0..unknowns {
            // Row a of Jᵀ Λ.
            let jl = [
                jac[0][a] * l[0][0] + jac[1][a] * l[1][0],
                jac[0][a] * l[0][1] + jac[1][a] * l[1][1],
            ];
            g[a] += w * (jl[0] * e[0] + jl[1] * e[1]);
            for b in a..unknowns {
                h[a][b] += w * (jl[0] * jac[0][b] + jl[1] * jac[1][b]);
            }
        }
    }
    if let Some(prior) = prior {
        cost += prior.add_to(pose, &mut h, &mut g);
    }
    if let Some(sweep) = sweep {
        for k in 0..3 {
            let e = velocity[k] - sweep.velocity[k];
            cost += sweep.information[k] * e * e;
            g[3 + k] -= sweep.information[k] * e;
            h[3 + k][3 + k] += sweep.information[k];
        }
    }
    fill_lower(&mut h);
    Linearised {
        cost,
        weighted,
        hessian: h,
        gradient: g,
        matched,
    }
}

/// The Gauss–Newton step of `at` over its first `unknowns` unknowns.
fn step(at: &Linearised, unknowns: usize) -> Option<[f64; 6]> {
    if unknowns == 3 {
        let h: Matrix3 = [0, 1, 2].map(|a| [at.hessian[a][0], at.hessian[a][1], at.hessian[a][2]]);
        let s = solve(&h, &[at.gradient[0], at.gradient[1], at.gradient[2]])?;
        return Some([s[0], s[1], s[2], 0.0, 0.0, 0.0]);
    }
    let h = nalgebra::Matrix6::from_fn(|a, b| at.hessian[a][b]);
    let s = h
        .cholesky()?
        .solve(&nalgebra::Vector6::from_column_slice(&at.gradient));
    Some([s[0], s[1], s[2], s[3], s[4], s[5]])
}

/// Moves `start` (a sensor pose from the grid matcher) so that `points` (endpoints in the
/// sensor frame) fit the cells' Gaussians best, under `prior`; with a `sweep`, each endpoint
/// is seen from its own pose along the sweep's velocity, which is refined too. The start stands
/// (`taken` is false) when fewer than a tenth of the endpoints, or fewer than 10, have a cell
/// to match, or when the refined pose is farther from it than the configured bounds: the
/// refinement corrects within a cell, it does not relocalise.
pub fn refine(
    surfaces: &Surfaces,
    points: &[(f64, f64)],
    start: Pose2,
    sweep: Option<&Sweep>,
    prior: Option<&Prior>,
    config: &RefineConfig,
) -> Refinement {
    assert!(
        sweep.is_none_or(|s| s.offsets.len() == points.len()),
        "one sweep offset per point"
    );
    let unknowns = if sweep.is_some() { 6 } else { 3 };
    let enough = (points.len() / 10).max(10);
    let mut pose = start;
    let mut velocity = sweep.map_or([0.0; 3], |s| s.velocity);
    let at_pose = |pose: &Pose2, velocity: &[f64; 3]| {
        linearise(surfaces, points, pose, sweep, velocity, prior, &config.loss)
    };
    let mut iterations = 0;
    let mut at = at_pose(&pose, &velocity);
    let refused = |matched, iterations| Refinement {
        pose: start,
        velocity: sweep.map(|s| s.velocity),
        matched,
        iterations,
        taken: false,
        fit: None,
    };
    if at.matched < enough {
        return refused(at.matched, 0);
    }
    while iterations < config.iterations {
        iterations += 1;
        let Some(step) = step(&at, unknowns) else {
            break;
        };
        let mut accepted = None;
        for fraction in [1.0, 0.5, 0.25] {
            let candidate = Pose2::new(
                pose.x + fraction * step[0],
                pose.y + fraction * step[1],
                pose.theta + fraction * step[2],
            );
            let moved = [0, 1, 2].map(|k| velocity[k] + fraction * step[3 + k]);
            let next = at_pose(&candidate, &moved);
            if next.matched >= enough && next.cost < at.cost {
                accepted = Some((candidate, moved, next, fraction));
                break;
            }
        }
        let Some((candidate, moved, next, fraction)) = accepted else {
            break;
        };
        pose = candidate;
        velocity = moved;
        at = next;
        if fraction * step[0].hypot(step[1]) < 1e-6 && (fraction * step[2]).abs() < 1e-7 {
            break;
        }
    }
    let moved = start.between(&pose);
    if moved.x.hypot(moved.y) > config.max_translation || moved.theta.abs() > config.max_rotation {
        return refused(at.matched, iterations);
    }
    let scan_only = linearise(
        surfaces,
        points,
        &pose,
        sweep,
        &velocity,
        None,
        &config.loss,
    );
    Refinement {
        pose,
        velocity: sweep.map(|_| velocity),
        matched: at.matched,
        iterations,
        taken: true,
        fit: Some(fit_of(&scan_only, sweep)),
    }
}

/// The [`Fit`] of a refinement from its scan-only linearisation: with a sweep, the velocity
/// (under its own prior, which is part of the model) is marginalised out of the Hessian, the
/// Schur complement Hₚₚ − Hₚᵥ Hᵥᵥ⁻¹ Hᵥₚ. Each endpoint is two observations (its Mahalanobis
/// distance is over x and y).
fn fit_of(scan_only: &Linearised, sweep: Option<&Sweep>) -> Fit {
    let h = &scan_only.hessian;
    let pose_block: Matrix3 = [0, 1, 2].map(|a| [h[a][0], h[a][1], h[a][2]]);
    let information = match sweep {
        None => pose_block,
        Some(_) => {
            let hpp = nalgebra::Matrix3::from_fn(|a, b| h[a][b]);
            let hpv = nalgebra::Matrix3::from_fn(|a, b| h[a][3 + b]);
            let hvv = nalgebra::Matrix3::from_fn(|a, b| h[3 + a][3 + b]);
            match hvv.try_inverse() {
                Some(inverse) => {
                    let m = hpp - hpv * inverse * hpv.transpose();
                    [0, 1, 2].map(|a| [m[(a, 0)], m[(a, 1)], m[(a, 2)]])
                }
                None => pose_block,
            }
        }
    };
    let unknowns = if sweep.is_some() { 6.0 } else { 3.0 };
    Fit {
        information,
        scale: residual_scale(scan_only.weighted, 2.0 * scan_only.matched as f64, unknowns),
        endpoints: scan_only.matched,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{GridPyramid, UpdateModel};
    use crate::matcher::{MatchConfig, match_scan};
    use crate::pose::wrap_angle;
    use crate::testing::{Segment, cast, cast_beam, rectangle};

    #[test]
    fn a_cell_holds_the_mean_and_spread_of_its_endpoints() {
        let mut surfaces = Surfaces::new(0.05, &RefineConfig::default());
        // A wall along y = 0.013, inside the cells' row 0: an endpoint every centimetre.
        let wall: Vec<_> = (0..5)
            .map(|k| (0.005 + 0.01 * f64::from(k), 0.013))
            .collect();
        surfaces.integrate(&Pose2::default(), &wall);
        let (normal, _) = surfaces.nearest(0.02, 0.013).expect("five endpoints");
        assert!((normal.mean.0 - 0.025).abs() < 1e-12, "{normal:?}");
        assert!((normal.mean.1 - 0.013).abs() < 1e-12, "{normal:?}");
        // Across the wall the spread is the floor's alone: 1 cm off is one standard deviation.
        assert!((mahalanobis(&normal, 0.025, 0.023) - 1.0).abs() < 1e-9);
        // Along it the endpoints' own variance (2·10⁻⁴ m²) adds to the floor's.
        assert!((mahalanobis(&normal, 0.035, 0.013) - 1e-4 / 3e-4).abs() < 1e-9);
        // Two endpoints are fewer than `min_points`: no Gaussian there.
        surfaces.integrate(&Pose2::default(), &[(1.0, 1.0), (1.01, 1.0)]);
        assert!(surfaces.nearest(1.0, 1.0).is_none());
        assert_eq!(surfaces.len(), 2);
    }

    #[test]
    fn a_cell_pools_the_endpoints_of_its_neighbours_into_a_line() {
        let mut surfaces = Surfaces::new(0.05, &RefineConfig::default());
        // One endpoint per cell along y = 0.02, as a far wall gives from one revolution.
        let wall: Vec<_> = (0..5)
            .map(|k| (0.025 + 0.05 * f64::from(k), 0.02))
            .collect();
        surfaces.integrate(&Pose2::default(), &wall);
        // The middle cell fits its own endpoint and its two neighbours': mean on the wall...
        let (normal, _) = surfaces
            .nearest(0.125, 0.02)
            .expect("three pooled endpoints");
        assert!((normal.mean.0 - 0.125).abs() < 1e-12, "{normal:?}");
        assert!((normal.mean.1 - 0.02).abs() < 1e-12, "{normal:?}");
        // ...1 cm off the wall is one standard deviation (the floor's); along it the endpoints'
        // own spread, (0.05² · 2/3) m², adds to the floor's, so one endpoint spacing is 1.2.
        assert!((mahalanobis(&normal, 0.125, 0.03) - 1.0).abs() < 1e-9);
        let along = 0.05f64.powi(2) / (0.05f64.powi(2) * 2.0 / 3.0 + 1e-4);
        assert!((mahalanobis(&normal, 0.175, 0.02) - along).abs() < 1e-9);
        // The end cells pool two endpoints, fewer than `min_points`: no Gaussian of their own.
        let end = surfaces.cells.get(&key((0, 0))).expect("an endpoint");
        assert!(end.normal.is_none());
    }

    /// A 6 m × 4 m room and a pillar, every wall a third of a 5 cm cell off the lattice, so a
    /// grid stores each one a sixth of a cell from where it is.
    fn walls() -> Vec<Segment> {
        let mut walls = rectangle((-3.0167, -2.0333), (2.9833, 1.9667)).to_vec();
        walls.extend(rectangle((1.0167, 0.5167), (1.4167, 0.9167)));
        walls
    }

    /// The room mapped from a few poses along a drive, into a grid and its surfaces.
    fn mapped() -> (GridPyramid, Surfaces) {
        let mut grid = GridPyramid::new(0.05, 2, &UpdateModel::default());
        let mut surfaces = Surfaces::new(0.05, &RefineConfig::default());
        for k in 0..8 {
            let k = f64::from(k);
            let pose = Pose2::new(-1.0 + 0.25 * k, -0.4 + 0.05 * k, 0.1 * k);
            let scan = cast(&walls(), &pose, 720);
            grid.integrate(&pose, &scan, &[]);
            surfaces.integrate(&pose, &scan);
        }
        (grid, surfaces)
    }

    fn error(pose: &Pose2, truth: &Pose2) -> (f64, f64) {
        (
            (pose.x - truth.x).hypot(pose.y - truth.y),
            wrap_angle(pose.theta - truth.theta).abs(),
        )
    }

    #[test]
    fn refinement_takes_a_grid_match_to_the_walls_inside_the_cells() {
        let (grid, surfaces) = mapped();
        let truth = Pose2::new(0.12, 0.07, 0.3);
        let scan = cast(&walls(), &truth, 360);
        let start = Pose2::new(0.15, 0.05, 0.32);
        let matched = match_scan(&grid, &scan, start, None, &MatchConfig::default());
        let refined = refine(
            &surfaces,
            &scan,
            matched.pose,
            None,
            None,
            &RefineConfig::default(),
        );
        assert!(refined.taken && refined.matched > 300, "{refined:?}");
        let (grid_t, grid_r) = error(&matched.pose, &truth);
        let (t, r) = error(&refined.pose, &truth);
        assert!(
            t < 1e-3 && r < 0.02f64.to_radians(),
            "refined {:.2} mm {:.4}°, grid {:.2} mm {:.4}°",
            t * 1e3,
            r.to_degrees(),
            grid_t * 1e3,
            grid_r.to_degrees()
        );
        assert!(t < grid_t / 3.0, "refined {t} m vs grid {grid_t} m");
    }

    #[test]
    fn a_sweep_refinement_finds_the_velocity_a_revolution_was_taken_at() {
        let (_, surfaces) = mapped();
        // One revolution of 720 beams in 0.18 s, turning at 0.6 rad/s and moving at 0.4 m/s;
        // its middle pose is the truth, each beam is cast from where the sensor was at its time.
        let truth = Pose2::new(0.12, 0.07, 0.3);
        let velocity = [0.4 * 0.3f64.cos(), 0.4 * 0.3f64.sin(), 0.6];
        let period = 0.18;
        let mut points = Vec::new();
        let mut offsets = Vec::new();
        for k in 0..720 {
            let t = period * (f64::from(k) / 720.0 - 0.5);
            let seen = Pose2::new(
                truth.x + t * velocity[0],
                truth.y + t * velocity[1],
                truth.theta + t * velocity[2],
            );
            // Clockwise, as the RPLidar turns.
            let azimuth = -std::f64::consts::TAU * f64::from(k) / 720.0;
            if let Some(point) = cast_beam(&walls(), &seen, azimuth) {
                points.push(point);
                offsets.push(t);
            }
        }
        // The prior: standing still, loosely.
        let sweep = Sweep {
            offsets: &offsets,
            velocity: [0.0; 3],
            information: [25.0, 25.0, 25.0],
        };
        let start = Pose2::new(0.13, 0.06, 0.31);
        let config = RefineConfig {
            iterations: 30,
            ..RefineConfig::default()
        };
        let moving = refine(&surfaces, &points, start, Some(&sweep), None, &config);
        let rigid = refine(&surfaces, &points, start, None, None, &config);
        assert!(moving.taken && rigid.taken, "{moving:?} {rigid:?}");
        let found = moving.velocity.expect("a sweep's velocity");
        let (t, r) = error(&moving.pose, &truth);
        let (rigid_t, rigid_r) = error(&rigid.pose, &truth);
        assert!(
            t < 1e-3 && r < 0.02f64.to_radians(),
            "sweep {:.2} mm {:.4}°, rigid {:.2} mm {:.4}°",
            t * 1e3,
            r.to_degrees(),
            rigid_t * 1e3,
            rigid_r.to_degrees()
        );
        // Matched rigidly about its middle, the revolution's 6° turn bends it symmetrically and
        // the heading comes out right, but the bent scan sits 5 mm off.
        assert!(
            rigid_t > 10.0 * t,
            "sweep {t} m {r} rad, rigid {rigid_t} m {rigid_r} rad"
        );
        assert!((found[2] - velocity[2]).abs() < 0.05, "{found:?}");
        assert!(
            (found[0] - velocity[0]).hypot(found[1] - velocity[1]) < 0.05,
            "{found:?}"
        );
        // Placed at the middle pose with that velocity, the beams fit the walls again.
        let placed = sweep.place(&points, &moving.pose, &found);
        let again = refine(&surfaces, &placed, moving.pose, None, None, &config);
        assert!(error(&again.pose, &moving.pose).0 < 1e-3, "{again:?}");
    }

    #[test]
    fn a_refinement_past_its_bounds_or_without_cells_leaves_the_start() {
        let (_, surfaces) = mapped();
        let truth = Pose2::new(0.12, 0.07, 0.3);
        let scan = cast(&walls(), &truth, 360);
        let start = Pose2::new(0.125, 0.07, 0.3);
        let config = RefineConfig {
            max_translation: 0.002,
            ..RefineConfig::default()
        };
        let refused = refine(&surfaces, &scan, start, None, None, &config);
        assert!(!refused.taken && refused.pose == start, "{refused:?}");
        let taken = refine(
            &surfaces,
            &scan,
            start,
            None,
            None,
            &RefineConfig::default(),
        );
        assert!(
            taken.taken && error(&taken.pose, &truth).0 < 1e-3,
            "{taken:?}"
        );

        let empty = Surfaces::new(0.05, &RefineConfig::default());
        let alone = refine(&empty, &scan, start, None, None, &RefineConfig::default());
        assert!(!alone.taken && alone.pose == start && alone.matched == 0);
    }
}
