//! Scan-to-map matching by Gauss–Newton on (x, y, ψ), coarse to fine (Hector SLAM, Kohlbrecher
//! et al. 2011), with a robust loss and an optional Gaussian prior on the pose.
//!
//! The cost of a sensor pose ξ is Σᵢ ρ([1 − M(Sᵢ(ξ))]²) / σ² + (ξ − ξₚ)ᵀ Λ (ξ − ξₚ): beam
//! endpoints Sᵢ(ξ) should land where the map M (bilinear occupancy, [`Grid::interpolate`]) is
//! occupied; ρ is the robust loss, σ the spread of a residual and (ξₚ, Λ) the motion prior.
//! Each level of the pyramid, coarsest first, refines the pose the previous one found: the
//! coarse grids are smooth enough to pull a pose in from a few cells away, the fine one is
//! precise. The scan term's Hessian at the pose found, scaled by the spread its residuals were
//! measured at, is what the scan says about the pose ([`Fit`]).

// 3×3 algebra reads best with explicit indices.
#![allow(clippy::needless_range_loop)]

use crate::grid::{Grid, GridPyramid};
use crate::pose::{Pose2, wrap_angle};

/// A 3×3 matrix over (x, y, ψ), row-major.
pub type Matrix3 = [[f64; 3]; 3];

/// The robust loss applied to each endpoint's squared residual.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Loss {
    /// Plain least squares (Hector's).
    Squared,
    /// Quadratic below `delta`, linear above: an endpoint far from any wall pulls with a
    /// bounded force.
    Huber { delta: f64 },
    /// ρ(s) = c² ln(1 + s/c²): outliers (glass, people) fade out instead of pulling.
    Cauchy { c: f64 },
}

impl Loss {
    /// The iteratively-reweighted-least-squares weight for residual `r`.
    pub(crate) fn weight(&self, r: f64) -> f64 {
        match *self {
            Loss::Squared => 1.0,
            Loss::Huber { delta } => {
                let a = r.abs();
                if a <= delta { 1.0 } else { delta / a }
            }
            Loss::Cauchy { c } => 1.0 / (1.0 + (r / c).powi(2)),
        }
    }

    pub(crate) fn cost(&self, r: f64) -> f64 {
        match *self {
            Loss::Squared => r * r,
            Loss::Huber { delta } => {
                let a = r.abs();
                if a <= delta {
                    r * r
                } else {
                    delta * (2.0 * a - delta)
                }
            }
            Loss::Cauchy { c } => c * c * (1.0 + (r / c).powi(2)).ln(),
        }
    }
}

/// How the matcher iterates.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MatchConfig {
    /// Gauss–Newton iterations on each coarse level.
    pub coarse_iterations: usize,
    /// Gauss–Newton iterations on the finest level.
    pub fine_iterations: usize,
    /// Robust loss on each endpoint's residual.
    pub loss: Loss,
    /// Standard deviation of one endpoint's residual 1 − M (occupancy units): weighs the scan
    /// against the prior. (The covariance does not depend on it: its scale is measured from the
    /// residuals, see [`Fit`].)
    pub residual_sigma: f64,
    /// Stop a level's iterations when a step moves less than this (m, and rad).
    pub converged_step: f64,
    /// The scan term is weighed as if the scan had this many endpoints (0: as many as it has),
    /// so that a 360-beam lidar does not weigh twice as much against the motion prior as a
    /// 180-beam one, nor a scan clipped to a short range less than a full one.
    pub reference_endpoints: f64,
}

impl MatchConfig {
    /// The weight of one endpoint's squared residual in the scan term, for a scan of `endpoints`:
    /// one over the residual variance, times [`reference_endpoints`](Self::reference_endpoints)
    /// over `endpoints` when that is set.
    fn endpoint_weight(&self, endpoints: usize) -> f64 {
        let unit = 1.0 / (self.residual_sigma * self.residual_sigma);
        if self.reference_endpoints > 0.0 && endpoints > 0 {
            unit * self.reference_endpoints / endpoints as f64
        } else {
            unit
        }
    }
}

impl Default for MatchConfig {
    fn default() -> Self {
        Self {
            coarse_iterations: 4,
            fine_iterations: 8,
            loss: Loss::Huber { delta: 0.4 },
            residual_sigma: 0.25,
            converged_step: 1e-5,
            reference_endpoints: 180.0,
        }
    }
}

/// A Gaussian belief about the pose before matching: mean and information (inverse covariance).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prior {
    pub pose: Pose2,
    pub information: Matrix3,
}

impl Prior {
    /// Adds this prior's term at `pose` to a Gauss–Newton system whose upper triangle is
    /// being summed (`gradient` is the right-hand side) and whose first three unknowns are the
    /// pose's x, y and ψ, and returns the term's cost.
    pub(crate) fn add_to<const N: usize>(
        &self,
        pose: &Pose2,
        hessian: &mut [[f64; N]; N],
        gradient: &mut [f64; N],
    ) -> f64 {
        let e = self.error(pose);
        let l = &self.information;
        let mut cost = 0.0;
        for a in 0..3 {
            let le: f64 = (0..3).map(|b| l[a][b] * e[b]).sum();
            gradient[a] -= le;
            cost += e[a] * le;
            for b in a..3 {
                hessian[a][b] += l[a][b];
            }
        }
        cost
    }

    /// The squared Mahalanobis distance of `pose` from the mean, (ξ − ξₚ)ᵀ Λ (ξ − ξₚ): this
    /// prior's cost at `pose`.
    pub(crate) fn squared_distance(&self, pose: &Pose2) -> f64 {
        let e = self.error(pose);
        (0..3)
            .map(|a| {
                (0..3)
                    .map(|b| e[a] * self.information[a][b] * e[b])
                    .sum::<f64>()
            })
            .sum()
    }

    /// `pose − mean` in (x, y, ψ), the heading wrapped.
    fn error(&self, pose: &Pose2) -> [f64; 3] {
        [
            pose.x - self.pose.x,
            pose.y - self.pose.y,
            wrap_angle(pose.theta - self.pose.theta),
        ]
    }
}

/// What a scan says about the pose a match found: the scan term's Gauss–Newton Hessian there, as
/// the match weighed its endpoints, and how far the residuals' measured spread is from the one
/// assumed. The scan alone then puts the pose's covariance at `scale · information⁻¹`
/// ([`Fit::covariance`]): the nonlinear least-squares estimate, independent of the assumed
/// spread. It counts every endpoint as an independent measurement, so it shrinks as one over
/// their number; errors shared by many endpoints (the map's own) are not in it, the mapper adds
/// a floor for them ([`crate::mapper::CovarianceConfig`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fit {
    /// The scan term's Hessian over the sensor's (x, y, ψ), in the match's own units.
    pub information: Matrix3,
    /// Measured over assumed residual variance: Σ wᵢ rᵢ² / (degrees of freedom), rᵢ in the
    /// assumed spreads.
    pub scale: f64,
    /// Endpoints that took part.
    pub endpoints: usize,
}

impl Fit {
    /// The pose covariance from the scan alone, `scale · information⁻¹`, regularised so that a
    /// direction the scan does not constrain (a corridor's axis) gets a huge variance.
    pub fn covariance(&self) -> Matrix3 {
        covariance_of(&self.information).map(|row| row.map(|v| v * self.scale))
    }
}

/// What a match found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    /// The sensor pose that best explains the scan.
    pub pose: Pose2,
    /// What the scan alone says about `pose`, on the finest grid.
    pub fit: Fit,
    /// Covariance of `pose` from the scan alone ([`Fit::covariance`]), for fusing with other pose
    /// sources; very large along directions the scan does not constrain (a corridor's axis).
    pub covariance: Matrix3,
    /// Mean occupancy at the endpoints on the finest grid, in [0, 1]: 1 is a perfect fit.
    pub score: f64,
    /// Gauss–Newton iterations run, over all levels.
    pub iterations: usize,
}

/// Matches `points` (beam endpoints in the sensor frame, m) against the pyramid, starting at the
/// sensor pose `start`.
pub fn match_scan(
    pyramid: &GridPyramid,
    points: &[(f64, f64)],
    start: Pose2,
    prior: Option<&Prior>,
    config: &MatchConfig,
) -> Match {
    let mut pose = start;
    let mut iterations = 0;
    let levels = pyramid.levels();
    for (level, grid) in levels.iter().enumerate().rev() {
        let budget = if level == 0 {
            config.fine_iterations
        } else {
            config.coarse_iterations
        };
        for _ in 0..budget {
            iterations += 1;
            let normal = normal_equations(grid, points, &pose, prior, config);
            let Some(step) = solve(&normal.hessian, &normal.gradient) else {
                break;
            };
            let candidate = Pose2::new(pose.x + step[0], pose.y + step[1], pose.theta + step[2]);
            let new_cost = cost(grid, points, &candidate, prior, config);
            if new_cost > normal.cost {
                // Gauss–Newton overshot (the map is only piecewise smooth): try half the step once.
                let half = Pose2::new(
                    pose.x + 0.5 * step[0],
                    pose.y + 0.5 * step[1],
                    pose.theta + 0.5 * step[2],
                );
                if cost(grid, points, &half, prior, config) < normal.cost {
                    pose = half;
                }
                break;
            }
            pose = candidate;
            if step[0].hypot(step[1]) < config.converged_step
                && step[2].abs() < config.converged_step
            {
                break;
            }
        }
    }
    let finest = &levels[0];
    let fit = grid_fit(finest, points, &pose, config);
    Match {
        pose,
        fit,
        covariance: fit.covariance(),
        score: score(finest, points, &pose),
        iterations,
    }
}

/// A brute-force window searched around a start pose before Gauss–Newton (correlative
/// matching, Olson 2009): it finds a turn that a poor prediction missed, which the local
/// Gauss–Newton cannot pull in from more than a few cells away.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SearchWindow {
    /// Half-width of the heading window (rad); 0 turns the search off.
    pub angle: f64,
    /// Heading step (rad).
    pub angle_step: f64,
    /// Half-width of the translation window (m), searched in steps of the grid's cells.
    pub translation: f64,
    /// How much a candidate's distance from the start costs, in mean occupancy per unit of the
    /// prior's squared Mahalanobis distance (0: the window is flat). Along a corridor, where the
    /// map cannot tell candidates apart, the one the prediction supports wins.
    pub prior_weight: f64,
    /// The window also reaches this many of the prediction's standard deviations (0: fixed),
    /// up to `max_angle` and `max_translation`: after a long interval without odometry the
    /// robot may have turned and moved farther than the fixed window.
    pub sigmas: f64,
    /// Largest heading half-width when the window grows with the prediction (rad); its step
    /// grows in proportion, so a search costs at most as much as the fixed window's.
    pub max_angle: f64,
    /// Largest translation half-width when the window grows with the prediction (m).
    pub max_translation: f64,
}

impl SearchWindow {
    /// This window widened to `sigmas` of a prediction with standard deviations `translation`
    /// (m) and `rotation` (rad), within the largest half-widths.
    pub fn around(&self, translation: f64, rotation: f64) -> SearchWindow {
        if self.sigmas <= 0.0 || self.angle <= 0.0 {
            return *self;
        }
        let angle = (self.sigmas * rotation).clamp(self.angle, self.max_angle.max(self.angle));
        let reach = (self.sigmas * translation)
            .clamp(self.translation, self.max_translation.max(self.translation));
        SearchWindow {
            angle,
            angle_step: self.angle_step * angle / self.angle,
            translation: reach,
            ..*self
        }
    }
}

impl Default for SearchWindow {
    fn default() -> Self {
        Self {
            angle: 0.35,
            angle_step: 0.01,
            translation: 0.2,
            prior_weight: 0.01,
            sigmas: 1.0,
            max_angle: std::f64::consts::PI,
            max_translation: 0.5,
        }
    }
}

/// The pose in `window` around `start` whose endpoints land on the most occupancy in `grid`
/// (the caller passes a coarse level: smooth, and cheap to search).
///
/// With `information` (the prediction's, over x, y and ψ) each candidate's mean occupancy is
/// lowered by [`SearchWindow::prior_weight`] times its squared Mahalanobis distance from `start`.
pub fn search(
    grid: &Grid,
    points: &[(f64, f64)],
    start: Pose2,
    window: &SearchWindow,
    information: Option<&Matrix3>,
) -> Pose2 {
    if window.angle <= 0.0 || window.angle_step <= 0.0 || points.is_empty() {
        return start;
    }
    let steps = (window.angle / window.angle_step).ceil().min(1000.0) as i32;
    let cells = (window.translation / grid.resolution())
        .floor()
        .clamp(0.0, 20.0) as i32;
    // Every other endpoint is enough to rank candidates.
    let sample: Vec<(f64, f64)> = points.iter().step_by(2).copied().collect();
    // (score, distance from the start in search steps, pose)
    let mut best = (f64::NEG_INFINITY, f64::INFINITY, start);
    for a in -steps..=steps {
        let theta = start.theta + f64::from(a) * window.angle_step;
        let (s, c) = theta.sin_cos();
        let rotated: Vec<(f64, f64)> = sample
            .iter()
            .map(|&(x, y)| (c * x - s * y, s * x + c * y))
            .collect();
        for i in -cells..=cells {
            for j in -cells..=cells {
                let x = start.x + f64::from(i) * grid.resolution();
                let y = start.y + f64::from(j) * grid.resolution();
                let occupancy: f64 = rotated
                    .iter()
                    .map(|&(rx, ry)| grid.interpolate(x + rx, y + ry).value)
                    .sum();
                let mut score = occupancy / sample.len() as f64;
                if let Some(&information) = information.filter(|_| window.prior_weight > 0.0) {
                    let prediction = Prior {
                        pose: start,
                        information,
                    };
                    let distance = prediction.squared_distance(&Pose2::new(x, y, theta));
                    score -= window.prior_weight * distance;
                }
                // Ties (within rounding) go to the candidate nearest the start, counted in
                // search steps: where the map cannot tell candidates apart (along a corridor,
                // on an empty map) the prediction stands.
                let steps_away = f64::from(i).hypot(f64::from(j)).hypot(f64::from(a));
                let tied = (score - best.0).abs() <= 1e-9;
                if score > best.0 + 1e-9 || (tied && steps_away < best.1) {
                    best = (score.max(best.0), steps_away, Pose2::new(x, y, theta));
                }
            }
        }
    }
    best.2
}

/// Mean interpolated occupancy at the endpoints placed at `pose`.
pub fn score(grid: &Grid, points: &[(f64, f64)], pose: &Pose2) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let sum: f64 = points
        .iter()
        .map(|&(x, y)| {
            let (mx, my) = pose.transform_point(x, y);
            grid.interpolate(mx, my).value
        })
        .sum();
    sum / points.len() as f64
}

/// The scan term's [`Fit`] at `pose` on `grid`.
fn grid_fit(grid: &Grid, points: &[(f64, f64)], pose: &Pose2, config: &MatchConfig) -> Fit {
    // What the scan says, endpoint by endpoint: not reweighed to a reference count.
    let config = &MatchConfig {
        reference_endpoints: 0.0,
        ..*config
    };
    let scan_only = normal_equations(grid, points, pose, None, config);
    let scale = 1.0 / (config.residual_sigma * config.residual_sigma);
    let weighted: f64 = points
        .iter()
        .map(|&(x, y)| {
            let (mx, my) = pose.transform_point(x, y);
            let r = 1.0 - grid.interpolate(mx, my).value;
            config.loss.weight(r) * r * r * scale
        })
        .sum();
    Fit {
        information: scan_only.hessian,
        scale: residual_scale(weighted, points.len() as f64, 3.0),
        endpoints: points.len(),
    }
}

/// The measured over assumed residual variance of a fit: `weighted` (Σ wᵢ rᵢ², rᵢ in assumed
/// spreads) over the degrees of freedom, `observations` minus the `unknowns`; 1 (the assumed
/// spread) when there are too few observations to say.
pub(crate) fn residual_scale(weighted: f64, observations: f64, unknowns: f64) -> f64 {
    let dof = observations - unknowns;
    if dof < 1.0 || !weighted.is_finite() {
        1.0
    } else {
        weighted / dof
    }
}

struct Normal {
    hessian: Matrix3,
    /// Right-hand side: the step solves hessian · step = gradient.
    gradient: [f64; 3],
    cost: f64,
}

fn normal_equations(
    grid: &Grid,
    points: &[(f64, f64)],
    pose: &Pose2,
    prior: Option<&Prior>,
    config: &MatchConfig,
) -> Normal {
    let (s, c) = pose.theta.sin_cos();
    let scale = config.endpoint_weight(points.len());
    let mut h = [[0.0; 3]; 3];
    let mut g = [0.0; 3];
    let mut total = 0.0;
    for &(px, py) in points {
        let mx = pose.x + c * px - s * py;
        let my = pose.y + s * px + c * py;
        let sample = grid.interpolate(mx, my);
        let r = 1.0 - sample.value;
        let (gx, gy) = sample.gradient;
        // ∂M/∂ξ = ∇M · ∂S/∂ξ, ∂S/∂ψ = (−s·px − c·py, c·px − s·py).
        let j = [gx, gy, gx * (-s * px - c * py) + gy * (c * px - s * py)];
        let w = config.loss.weight(r) * scale;
        total += config.loss.cost(r) * scale;
        for a in 0..3 {
            g[a] += w * j[a] * r;
            for b in a..3 {
                h[a][b] += w * j[a] * j[b];
            }
        }
    }
    if let Some(prior) = prior {
        total += prior.add_to(pose, &mut h, &mut g);
    }
    fill_lower(&mut h);
    Normal {
        hessian: h,
        gradient: g,
        cost: total,
    }
}

fn cost(
    grid: &Grid,
    points: &[(f64, f64)],
    pose: &Pose2,
    prior: Option<&Prior>,
    config: &MatchConfig,
) -> f64 {
    let scale = config.endpoint_weight(points.len());
    let mut total: f64 = points
        .iter()
        .map(|&(x, y)| {
            let (mx, my) = pose.transform_point(x, y);
            config.loss.cost(1.0 - grid.interpolate(mx, my).value) * scale
        })
        .sum();
    if let Some(prior) = prior {
        total += prior.squared_distance(pose);
    }
    total
}

/// The inverse of a scan Hessian, regularised so that a direction the scan does not constrain
/// (a corridor's axis, an empty scan) gets a huge variance instead of no answer.
pub(crate) fn covariance_of(hessian: &Matrix3) -> Matrix3 {
    let largest = (0..3).map(|a| hessian[a][a]).fold(0.0f64, f64::max);
    let lambda = (1e-9 * largest).max(1e-12);
    let mut regularised = *hessian;
    for (a, row) in regularised.iter_mut().enumerate() {
        row[a] += lambda;
    }
    invert(&regularised).unwrap_or([
        [1.0 / lambda, 0.0, 0.0],
        [0.0, 1.0 / lambda, 0.0],
        [0.0, 0.0, 1.0 / lambda],
    ])
}

/// Copies the upper triangle of a symmetric matrix, summed alone, into its lower one.
pub(crate) fn fill_lower<const N: usize>(m: &mut [[f64; N]; N]) {
    for a in 0..N {
        for b in 0..a {
            m[a][b] = m[b][a];
        }
    }
}

/// The determinant-checked inverse of a symmetric 3×3 matrix.
pub fn invert(m: &Matrix3) -> Option<Matrix3> {
    let [[a, b, c], [d, e, f], [g, h, i]] = *m;
    let co = [
        [e * i - f * h, c * h - b * i, b * f - c * e],
        [f * g - d * i, a * i - c * g, c * d - a * f],
        [d * h - e * g, b * g - a * h, a * e - b * d],
    ];
    let det = a * co[0][0] + b * co[1][0] + c * co[2][0];
    let scale = m.iter().flatten().fold(0.0f64, |acc, v| acc.max(v.abs()));
    if !det.is_finite() || det.abs() <= 1e-12 * scale.powi(3) || scale == 0.0 {
        return None;
    }
    Some(co.map(|row| row.map(|v| v / det)))
}

pub(crate) fn solve(h: &Matrix3, g: &[f64; 3]) -> Option<[f64; 3]> {
    let inv = invert(h)?;
    Some([0, 1, 2].map(|a| (0..3).map(|b| inv[a][b] * g[b]).sum()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::UpdateModel;
    use crate::testing::{cast, rectangle};

    /// A 6 m × 4 m room with a pillar, as beam endpoints seen from `pose` (every 1°).
    fn room_scan(pose: &Pose2) -> Vec<(f64, f64)> {
        // Walls on cell centres of the 5 cm grid, so the map has no half-cell bias to test.
        let mut walls = rectangle((-3.025, -2.025), (3.025, 2.025)).to_vec();
        walls.extend(rectangle((1.025, 0.525), (1.425, 0.925)));
        cast(&walls, pose, 360)
    }

    fn mapped_room() -> GridPyramid {
        let mut p = GridPyramid::new(0.05, 3, &UpdateModel::default());
        let pose = Pose2::new(-0.5, -0.3, 0.2);
        let scan = room_scan(&pose);
        for _ in 0..3 {
            p.integrate(&pose, &scan, &[]);
        }
        p
    }

    #[test]
    fn a_scan_from_a_displaced_pose_is_matched_back_to_where_it_was_taken() {
        let map = mapped_room();
        let truth = Pose2::new(-0.2, 0.1, 0.35);
        let scan = room_scan(&truth);
        let start = Pose2::new(-0.05, 0.22, 0.25);
        let m = match_scan(&map, &scan, start, None, &MatchConfig::default());
        assert!(
            (m.pose.x - truth.x).abs() < 0.01 && (m.pose.y - truth.y).abs() < 0.01,
            "{:?} vs {truth:?}",
            m.pose
        );
        assert!(
            wrap_angle(m.pose.theta - truth.theta).abs() < 0.2f64.to_radians(),
            "{m:?}"
        );
        assert!(m.score > 0.7, "{m:?}");
    }

    #[test]
    fn a_strong_prior_holds_the_pose_and_a_weak_one_lets_the_scan_decide() {
        let map = mapped_room();
        let truth = Pose2::new(-0.2, 0.1, 0.35);
        let scan = room_scan(&truth);
        let held = Pose2::new(-0.1, 0.1, 0.35);
        let info = |w: f64| [[w, 0.0, 0.0], [0.0, w, 0.0], [0.0, 0.0, w]];
        let strong = Prior {
            pose: held,
            information: info(1e9),
        };
        let m = match_scan(&map, &scan, held, Some(&strong), &MatchConfig::default());
        assert!((m.pose.x - held.x).abs() < 1e-3, "{m:?}");
        let weak = Prior {
            pose: held,
            information: info(1e-3),
        };
        let m = match_scan(&map, &scan, held, Some(&weak), &MatchConfig::default());
        assert!((m.pose.x - truth.x).abs() < 0.01, "{m:?}");
    }

    #[test]
    fn the_covariance_is_largest_along_a_corridor() {
        // Two long parallel walls along x: the scan pins y and ψ, not x.
        let (p, walls) = corridor();
        let near: Vec<(f64, f64)> = walls
            .iter()
            .copied()
            .filter(|(x, _)| x.abs() < 4.0)
            .collect();
        let m = match_scan(&p, &near, Pose2::default(), None, &MatchConfig::default());
        assert!(
            m.covariance[0][0] > 100.0 * m.covariance[1][1],
            "{:?}",
            m.covariance
        );
    }

    /// Two long parallel walls along x, 2.05 m apart, mapped from the origin.
    fn corridor() -> (GridPyramid, Vec<(f64, f64)>) {
        let mut p = GridPyramid::new(0.05, 2, &UpdateModel::default());
        let walls: Vec<(f64, f64)> = (0..400)
            .flat_map(|k| {
                let x = -10.025 + 0.05 * f64::from(k);
                [(x, 1.025), (x, -1.025)]
            })
            .collect();
        p.integrate(&Pose2::default(), &walls, &[]);
        (p, walls)
    }

    #[test]
    fn the_window_search_breaks_ties_nearest_the_start() {
        let (map, walls) = corridor();
        let window = SearchWindow::default();
        // On an empty map every candidate ties: the start stands.
        let empty = GridPyramid::new(0.05, 2, &UpdateModel::default());
        let start = Pose2::new(0.3, -0.2, 0.1);
        assert_eq!(
            search(&empty.levels()[1], &walls, start, &window, None),
            start
        );
        // Seen from 0.1 m off the corridor's axis, the scan pins y and the heading, not x: the
        // search corrects y and keeps x where the prediction put it (not the window's corner).
        let near: Vec<(f64, f64)> = walls
            .iter()
            .filter(|(x, _)| x.abs() < 4.0)
            .map(|&(x, y)| (x, y - 0.1))
            .collect();
        let found = search(
            &map.levels()[1],
            &near,
            Pose2::new(0.0, 0.0, 0.0),
            &window,
            None,
        );
        assert_eq!(found.x, 0.0, "{found:?}");
        assert!((found.y - 0.1).abs() < 0.051, "{found:?}");
        assert!(found.theta.abs() < 0.011, "{found:?}");
    }

    #[test]
    fn the_scan_weighs_the_same_against_the_prior_whatever_its_endpoint_count() {
        let map = mapped_room();
        let truth = Pose2::new(-0.2, 0.1, 0.35);
        let scan = room_scan(&truth);
        let twice: Vec<(f64, f64)> = scan.iter().flat_map(|&p| [p, p]).collect();
        let held = Pose2::new(-0.17, 0.1, 0.35);
        // A prior (σ 5 mm) that holds the pose against the scan: with a weak one both matches
        // reach the truth, and the weighing cannot show.
        let prior = Prior {
            pose: held,
            information: [[4e4, 0.0, 0.0], [0.0, 4e4, 0.0], [0.0, 0.0, 4e4]],
        };
        let normalised = MatchConfig {
            reference_endpoints: 180.0,
            ..MatchConfig::default()
        };
        let once = match_scan(&map, &scan, held, Some(&prior), &normalised);
        let doubled = match_scan(&map, &twice, held, Some(&prior), &normalised);
        assert!(
            (once.pose.x - doubled.pose.x).abs() < 1e-9
                && (once.pose.theta - doubled.pose.theta).abs() < 1e-9,
            "{:?} vs {:?}",
            once.pose,
            doubled.pose
        );
        // Counted endpoint by endpoint, the doubled scan pulls harder against the prior.
        let plain = MatchConfig {
            reference_endpoints: 0.0,
            ..MatchConfig::default()
        };
        let once = match_scan(&map, &scan, held, Some(&prior), &plain);
        let doubled = match_scan(&map, &twice, held, Some(&prior), &plain);
        assert!(
            (doubled.pose.x - held.x).abs() > (once.pose.x - held.x).abs() + 1e-4,
            "{:?} vs {:?}",
            once.pose,
            doubled.pose
        );
        // What the scan says about the pose does not depend on the reweighing.
        let fit = match_scan(&map, &scan, truth, None, &normalised).covariance;
        let unweighed = match_scan(&map, &scan, truth, None, &plain).covariance;
        assert!((fit[0][0] / unweighed[0][0] - 1.0).abs() < 1e-9);
    }

    #[test]
    fn the_prior_weight_trades_the_maps_evidence_against_the_distance_from_the_prediction() {
        let map = mapped_room();
        let truth = Pose2::new(-0.2, 0.1, 0.35);
        let scan = room_scan(&truth);
        let start = Pose2::new(-0.05, 0.1, 0.45);
        let information = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 1e4]];
        let grid = &map.levels()[1];
        let flat = SearchWindow {
            prior_weight: 0.0,
            ..SearchWindow::default()
        };
        let found = search(grid, &scan, start, &flat, Some(&information));
        assert!((found.x - truth.x).abs() < 0.051 && (found.theta - truth.theta).abs() < 0.011);
        let weighed = SearchWindow {
            prior_weight: 1.0,
            ..flat
        };
        assert_eq!(
            search(grid, &scan, start, &weighed, Some(&information)),
            start
        );
    }

    #[test]
    fn a_window_grows_with_the_prediction_within_its_limits() {
        let fixed = SearchWindow {
            sigmas: 0.0,
            ..SearchWindow::default()
        };
        assert_eq!(
            fixed.around(5.0, 5.0),
            fixed,
            "sigmas 0: the window is fixed"
        );
        let growing = SearchWindow {
            sigmas: 3.0,
            max_angle: 1.4,
            max_translation: 0.5,
            ..fixed
        };
        // A sure prediction keeps the fixed window.
        assert_eq!(growing.around(0.01, 0.01), growing);
        let wide = growing.around(0.1, 0.2);
        assert!((wide.angle - 0.6).abs() < 1e-12 && (wide.translation - 0.3).abs() < 1e-12);
        // The heading step grows with the window: as many headings as the fixed window's.
        assert!((wide.angle / wide.angle_step - fixed.angle / fixed.angle_step).abs() < 1e-9);
        let capped = growing.around(10.0, 10.0);
        assert_eq!((capped.angle, capped.translation), (1.4, 0.5));
    }

    #[test]
    fn inverting_a_singular_matrix_gives_none() {
        assert!(invert(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]).is_none());
        let m = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let inv = invert(&m).expect("invertible");
        for a in 0..3 {
            for b in 0..3 {
                let v: f64 = (0..3).map(|k| m[a][k] * inv[k][b]).sum();
                assert!((v - if a == b { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
}
