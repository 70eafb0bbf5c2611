//! Trajectories (`timestamp x y theta` per line) and the relations metric of Kümmerle et al.,
//! "On measuring the accuracy of SLAM algorithms", Autonomous Robots 27(4), 2009: the error of
//! the estimated relative motion between pose pairs against reference motions, as the
//! benchmark's `metricEvaluator` and the team's reference script compute it.

use std::fmt;
use std::io::{self, BufRead, Write};

use serde::{Deserialize, Serialize};

use crate::carmen::LaserScan;
use crate::mapper::ScanResult;
use crate::matcher::Matrix3;
use crate::pose::{Pose2, Velocity2, wrap_angle};
use crate::text::{LineError, LineReader, NextLine, Timestamp, parse_finite};

/// One pose of a trajectory, at the time of the scan it belongs to; the mapper's also carry the
/// velocity and covariance it found (a trajectory read from a file has neither).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryPose {
    pub timestamp: Timestamp,
    pub pose: Pose2,
    /// The velocity at `timestamp`, in the trajectory's frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub velocity: Option<Velocity2>,
    /// The covariance of `pose` over (x, y, θ) (m², m·rad, rad²), as
    /// [`ScanResult::covariance`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance: Option<Matrix3>,
}

impl TrajectoryPose {
    /// A pose at `timestamp`, without velocity or covariance.
    pub fn new(timestamp: Timestamp, pose: Pose2) -> Self {
        Self {
            timestamp,
            pose,
            velocity: None,
            covariance: None,
        }
    }

    /// What the mapper found for one scan: its pose at the scan's reference time, with its
    /// velocity and covariance.
    pub fn of(result: &ScanResult) -> Self {
        Self {
            timestamp: Timestamp::from_seconds(result.time),
            pose: result.pose,
            velocity: Some(result.velocity),
            covariance: Some(result.covariance),
        }
    }
}

/// Poses in file order (the metric sorts by time itself; [`Trajectory::at`] needs time order,
/// which is how the mapper gives them).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Trajectory {
    pub poses: Vec<TrajectoryPose>,
}

impl Trajectory {
    /// The pose and its covariance at `t` (s, the timestamps' clock), between the two poses
    /// around it: see [`Trajectory::pose_at`] for the pose; the covariance is theirs blended
    /// linearly in time. `None` outside the poses' span, or when a pose around `t` has no
    /// covariance (a trajectory read from a file: ask [`Trajectory::pose_at`]).
    pub fn at(&self, t: f64) -> Option<(Pose2, Matrix3)> {
        let (a, b, u) = self.around(t)?;
        let (ca, cb) = (a.covariance?, b.covariance?);
        let covariance = [0, 1, 2].map(|i| [0, 1, 2].map(|j| (1.0 - u) * ca[i][j] + u * cb[i][j]));
        Some((pose_between(a, b, u), covariance))
    }

    /// The pose at `t` (s) between the two poses around it: when both have a velocity, the cubic
    /// Hermite curve through them with those velocities (x, y and the unwrapped heading; a
    /// turning trolley's path is an arc, not the chord), else [`Pose2::interpolate`]. A pose's
    /// own time gives that pose; `None` outside the poses' span (no extrapolation).
    pub fn pose_at(&self, t: f64) -> Option<Pose2> {
        let (a, b, u) = self.around(t)?;
        Some(pose_between(a, b, u))
    }

    /// The poses around `t` (time order assumed) and how far `t` is from the first to the
    /// second, in [0, 1].
    fn around(&self, t: f64) -> Option<(&TrajectoryPose, &TrajectoryPose, f64)> {
        let poses = &self.poses;
        if !t.is_finite() {
            return None;
        }
        let i = poses.partition_point(|p| p.timestamp.seconds < t);
        let b = poses.get(i)?;
        if b.timestamp.seconds == t {
            return Some((b, b, 0.0));
        }
        let a = poses.get(i.checked_sub(1)?)?;
        let span = b.timestamp.seconds - a.timestamp.seconds;
        if span.is_nan() || span <= 0.0 {
            return Some((b, b, 0.0));
        }
        Some((a, b, ((t - a.timestamp.seconds) / span).clamp(0.0, 1.0)))
    }
}

/// The pose a fraction `u` of the way from `a` to `b`: Hermite with both velocities, else the
/// SE(2) interpolation.
fn pose_between(a: &TrajectoryPose, b: &TrajectoryPose, u: f64) -> Pose2 {
    let (Some(va), Some(vb)) = (a.velocity, b.velocity) else {
        return a.pose.interpolate(&b.pose, u);
    };
    let span = b.timestamp.seconds - a.timestamp.seconds;
    let (u2, u3) = (u * u, u * u * u);
    let (h10, h01, h11) = (u3 - 2.0 * u2 + u, -2.0 * u3 + 3.0 * u2, u3 - u2);
    let h00 = 1.0 - h01;
    let curve = |p0: f64, v0: f64, p1: f64, v1: f64| {
        h00 * p0 + h10 * span * v0 + h01 * p1 + h11 * span * v1
    };
    let turn = wrap_angle(b.pose.theta - a.pose.theta);
    Pose2::new(
        curve(a.pose.x, va.x, b.pose.x, vb.x),
        curve(a.pose.y, va.y, b.pose.y, vb.y),
        a.pose.theta + curve(0.0, va.theta, turn, vb.theta),
    )
}

impl Trajectory {
    /// Pairs each scan's timestamp (its text kept) with the pose estimated for it.
    ///
    /// # Panics
    /// If `poses` is not one per scan — a caller's bug, not bad input.
    pub fn from_scans(scans: &[LaserScan], poses: &[Pose2]) -> Self {
        assert_eq!(scans.len(), poses.len(), "one pose per scan");
        Self {
            poses: scans
                .iter()
                .zip(poses)
                .map(|(scan, &pose)| TrajectoryPose::new(scan.timestamp.clone(), pose))
                .collect(),
        }
    }
}

/// Reads a trajectory: `timestamp x y theta` per line (θ in rad; spaces or commas between
/// fields, extra columns ignored), blank lines and `#` comments skipped — what the reference
/// script accepts.
pub fn read_trajectory(reader: impl BufRead) -> Result<Trajectory, LineError> {
    let mut lines = LineReader::new(reader);
    let mut poses = Vec::new();
    loop {
        let (line, text) = match lines.next_line()? {
            NextLine::Line(line, text) => (line, text),
            NextLine::TooLong(e) => return Err(e),
            NextLine::End => break,
        };
        let text = text.replace(',', " ");
        let fields: Vec<&str> = text.split_ascii_whitespace().collect();
        if fields.is_empty() || fields[0].starts_with('#') {
            continue;
        }
        let parse = || -> Result<TrajectoryPose, String> {
            if fields.len() < 4 {
                return Err(format!(
                    "expected \"timestamp x y theta\", found {} field(s)",
                    fields.len()
                ));
            }
            Ok(TrajectoryPose::new(
                Timestamp::parse(fields[0], "the timestamp")?,
                Pose2::new(
                    parse_finite(fields[1], "x")?,
                    parse_finite(fields[2], "y")?,
                    parse_finite(fields[3], "theta")?,
                ),
            ))
        };
        poses.push(parse().map_err(|what| LineError { line, what })?);
    }
    Ok(Trajectory { poses })
}

/// Writes one `timestamp x y theta` line per pose: the timestamp text as it was read, x, y (m)
/// and θ (rad) with six decimals (µm / µrad, as the reference script writes them).
pub fn write_trajectory(trajectory: &Trajectory, mut out: impl Write) -> io::Result<()> {
    for p in &trajectory.poses {
        writeln!(
            out,
            "{} {:.6} {:.6} {:.6}",
            p.timestamp.text, p.pose.x, p.pose.y, p.pose.theta
        )?;
    }
    Ok(())
}

/// One reference relation: the robot's motion from its pose at `t1` to its pose at `t2`,
/// expressed in the frame of the pose at `t1`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Relation {
    /// 1-based line number in the relations file.
    pub line: usize,
    pub t1: Timestamp,
    pub t2: Timestamp,
    /// x, y and yaw of the reference motion (z, roll, pitch are 0 in 2D and not kept).
    pub motion: Pose2,
}

/// A benchmark's relations file, in file order.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Relations {
    pub relations: Vec<Relation>,
}

/// Reads a relations file: `t1 t2 x y z roll pitch yaw` per line (m, rad), blank lines and
/// `#` comments skipped.
pub fn read_relations(reader: impl BufRead) -> Result<Relations, LineError> {
    let mut lines = LineReader::new(reader);
    let mut relations = Vec::new();
    loop {
        let (line, text) = match lines.next_line()? {
            NextLine::Line(line, text) => (line, text),
            NextLine::TooLong(e) => return Err(e),
            NextLine::End => break,
        };
        let fields: Vec<&str> = text.split_ascii_whitespace().collect();
        if fields.is_empty() || fields[0].starts_with('#') {
            continue;
        }
        let parse = || -> Result<Relation, String> {
            if fields.len() < 8 {
                return Err(format!(
                    "expected \"t1 t2 x y z roll pitch yaw\", found {} field(s)",
                    fields.len()
                ));
            }
            let v = |i: usize, what: &str| parse_finite(fields[i], what);
            for (i, what) in [(4, "z"), (5, "roll"), (6, "pitch")] {
                v(i, what)?;
            }
            Ok(Relation {
                line,
                t1: Timestamp::parse(fields[0], "t1")?,
                t2: Timestamp::parse(fields[1], "t2")?,
                motion: Pose2::new(v(2, "x")?, v(3, "y")?, v(7, "yaw")?),
            })
        };
        relations.push(parse().map_err(|what| LineError { line, what })?);
    }
    Ok(Relations { relations })
}

/// How the error of one relation is measured.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Formula {
    /// As `metricEvaluator` (Kümmerle et al. 2009): ‖t(δ) − t(δ*)‖ and |wrap(θ − θ*)|, i.e.
    /// the translation of δ⁻¹ ⊕ δ*. The published tables use it.
    #[default]
    Kummerle,
    /// As Cartographer's `compute_relations_metrics`: the translation of δ ⊕ δ*⁻¹,
    /// ‖t(δ) − R(θ − θ*) t(δ*)‖; a few percent apart from Kümmerle's on the benchmark logs.
    Cartographer,
}

impl std::str::FromStr for Formula {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "kummerle" => Ok(Self::Kummerle),
            "cartographer" => Ok(Self::Cartographer),
            _ => Err(format!("unknown formula {s:?} (kummerle or cartographer)")),
        }
    }
}

impl fmt::Display for Formula {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Kummerle => "kummerle",
            Self::Cartographer => "cartographer",
        })
    }
}

/// Relations shorter than this (|t2 − t1|, s) are "short": mostly odometry-scale motion.
pub const SHORT_RELATION_S: f64 = 5.0;
/// Relations longer than this (|t2 − t1|, s) are "long": the loop-closing ones.
pub const LONG_RELATION_S: f64 = 60.0;

/// How a trajectory is matched to the relations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvalOptions {
    /// Largest |time difference| (s) between a relation end and its pose for the relation to
    /// count (the script's `--max-dt`, default 1 ms; `f64::INFINITY` keeps all).
    pub max_dt: f64,
    pub formula: Formula,
    /// SE(2)-interpolate between the two poses around each relation end instead of taking
    /// the nearest pose (the distance to the nearest pose is still held against `max_dt`).
    pub interpolate: bool,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            max_dt: 1e-3,
            formula: Formula::Kummerle,
            interpolate: false,
        }
    }
}

/// Mean and population standard deviation (the script's, and numpy's default ddof = 0).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MeanStd {
    pub mean: f64,
    pub std: f64,
}

impl MeanStd {
    /// NaN ± NaN for no values.
    fn of(values: impl Iterator<Item = f64> + Clone) -> Self {
        let n = values.clone().count() as f64;
        let mean = values.clone().sum::<f64>() / n;
        let var = values.map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
        Self {
            mean,
            std: var.sqrt(),
        }
    }
}

/// Error statistics over a set of relations, in the published tables' units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ErrorStats {
    /// Relations in these statistics.
    pub used: usize,
    pub abs_trans_m: MeanStd,
    pub sq_trans_m2: MeanStd,
    pub abs_rot_deg: MeanStd,
    pub sq_rot_deg2: MeanStd,
    pub max_trans_m: f64,
    pub max_rot_deg: f64,
    /// Kümmerle's ε = mean(trans² + rot²), rot in rad (m² + rad²).
    pub kummerle_eps: f64,
}

impl ErrorStats {
    fn of<'a>(errors: impl Iterator<Item = &'a RelationError> + Clone) -> Self {
        let trans = errors.clone().map(|e| e.trans_m);
        let rot = errors.clone().map(|e| e.rot_deg);
        let n = errors.clone().count();
        let max = |v: &mut dyn Iterator<Item = f64>| v.reduce(f64::max).unwrap_or(f64::NAN);
        Self {
            used: n,
            abs_trans_m: MeanStd::of(trans.clone()),
            sq_trans_m2: MeanStd::of(trans.clone().map(|x| x * x)),
            abs_rot_deg: MeanStd::of(rot.clone()),
            sq_rot_deg2: MeanStd::of(rot.clone().map(|x| x * x)),
            max_trans_m: max(&mut trans.clone()),
            max_rot_deg: max(&mut rot.clone()),
            kummerle_eps: errors
                .map(|e| e.trans_m * e.trans_m + e.rot_rad * e.rot_rad)
                .sum::<f64>()
                / n as f64,
        }
    }
}

/// The error of one relation that was used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RelationError {
    pub t1: Timestamp,
    pub t2: Timestamp,
    pub trans_m: f64,
    pub rot_deg: f64,
    pub rot_rad: f64,
}

/// What [`evaluate`] found: the script's summary, plus the short / long relation split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Relations in the file.
    pub relations: usize,
    /// Relations with both ends ≤ 1 ms from their pose (whatever `max_dt` is).
    pub matched_within_1ms: usize,
    /// Relations with both ends ≤ 10 µs from their pose: exact matches, not a neighbour scan.
    pub matched_within_10us: usize,
    pub formula: Formula,
    pub max_dt_s: f64,
    /// The largest end-to-pose time difference among the relations used (s).
    pub max_dt_used_s: f64,
    /// Statistics over every relation used (the numbers to publish).
    #[serde(flatten)]
    pub all: ErrorStats,
    /// Over the used relations with |t2 − t1| < [`SHORT_RELATION_S`].
    pub short: ErrorStats,
    /// Over the used relations with |t2 − t1| > [`LONG_RELATION_S`].
    pub long: ErrorStats,
    /// Each used relation's error, in file order (for `slam-eval --worst`; not in the JSON).
    #[serde(skip)]
    pub per_relation: Vec<RelationError>,
}

/// Scores `trajectory` against `relations`: each relation end is matched to the pose nearest
/// in time (or interpolated), the relation counts when both ends are within `max_dt`, and the
/// estimated motion δ = x(t1)⁻¹ ⊕ x(t2) is compared with the reference by `formula`. This is
/// `slam_relations_eval.py`'s computation, step for step.
pub fn evaluate(
    trajectory: &Trajectory,
    relations: &Relations,
    options: &EvalOptions,
) -> EvalReport {
    let mut poses: Vec<(f64, Pose2)> = trajectory
        .poses
        .iter()
        .map(|p| (p.timestamp.seconds, p.pose))
        .collect();
    poses.sort_by(|a, b| a.0.total_cmp(&b.0));
    let look = |t: f64| {
        if options.interpolate {
            interpolated(&poses, t)
        } else {
            nearest(&poses, t)
        }
    };
    let (mut n_ms, mut n_exact, mut worst_dt) = (0, 0, 0.0_f64);
    let mut used = Vec::new();
    let mut spans = Vec::new();
    for rel in &relations.relations {
        let (Some((d1, p1)), Some((d2, p2))) = (look(rel.t1.seconds), look(rel.t2.seconds)) else {
            continue;
        };
        let dt = d1.max(d2);
        n_ms += usize::from(dt <= 1e-3);
        n_exact += usize::from(dt <= 1e-5);
        if dt > options.max_dt {
            continue;
        }
        worst_dt = worst_dt.max(dt);
        let (trans_m, rot_rad) = relation_error(&p1.between(&p2), &rel.motion, options.formula);
        used.push(RelationError {
            t1: rel.t1.clone(),
            t2: rel.t2.clone(),
            trans_m,
            rot_deg: rot_rad.to_degrees(),
            rot_rad,
        });
        spans.push((rel.t2.seconds - rel.t1.seconds).abs());
    }
    let subset = |keep: fn(f64) -> bool| {
        ErrorStats::of(
            used.iter()
                .zip(&spans)
                .filter(move |(_, s)| keep(**s))
                .map(|(e, _)| e),
        )
    };
    EvalReport {
        relations: relations.relations.len(),
        matched_within_1ms: n_ms,
        matched_within_10us: n_exact,
        formula: options.formula,
        max_dt_s: options.max_dt,
        max_dt_used_s: worst_dt,
        all: ErrorStats::of(used.iter()),
        short: subset(|s| s < SHORT_RELATION_S),
        long: subset(|s| s > LONG_RELATION_S),
        per_relation: used,
    }
}

/// Translational (m) and rotational (rad) error of an estimated motion against the reference.
pub fn relation_error(estimate: &Pose2, reference: &Pose2, formula: Formula) -> (f64, f64) {
    let e = match formula {
        Formula::Kummerle => estimate.between(reference),
        Formula::Cartographer => estimate.compose(&reference.inverse()),
    };
    (e.x.hypot(e.y), wrap_angle(e.theta).abs())
}

/// The pose nearest in time to `t` among time-sorted poses and its distance (s); of two
/// equally near, the earlier (as the script's bisect).
fn nearest(poses: &[(f64, Pose2)], t: f64) -> Option<(f64, Pose2)> {
    let i = poses.partition_point(|p| p.0 < t);
    let before = i.checked_sub(1).map(|j| poses[j]);
    let after = poses.get(i).copied();
    match (before, after) {
        (Some(b), Some(a)) if (a.0 - t).abs() < (b.0 - t).abs() => Some(((a.0 - t).abs(), a.1)),
        (Some(b), _) => Some(((b.0 - t).abs(), b.1)),
        (None, Some(a)) => Some(((a.0 - t).abs(), a.1)),
        (None, None) => None,
    }
}

/// The SE(2) interpolation at `t` between the poses around it, with the distance to the
/// nearer of them; the nearest pose outside the trajectory's span.
fn interpolated(poses: &[(f64, Pose2)], t: f64) -> Option<(f64, Pose2)> {
    let i = poses.partition_point(|p| p.0 < t);
    if poses.get(i).is_some_and(|p| p.0 == t) {
        return Some((0.0, poses[i].1));
    }
    if i == 0 || i == poses.len() {
        return nearest(poses, t);
    }
    let ((t0, a), (t1, b)) = (poses[i - 1], poses[i]);
    let p = a.interpolate(&b, (t - t0) / (t1 - t0));
    Some(((t - t0).min(t1 - t), p))
}

impl fmt::Display for EvalReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let a = &self.all;
        writeln!(f, "relations in file          : {}", self.relations)?;
        writeln!(
            f,
            "matched (both ends <= 1 ms): {}   (<= 10 us: {})",
            self.matched_within_1ms, self.matched_within_10us
        )?;
        writeln!(f, "error formula              : {}", self.formula)?;
        writeln!(
            f,
            "used in statistics         : {} (largest |dt| used {:.6} s)",
            a.used, self.max_dt_used_s
        )?;
        writeln!(
            f,
            "Absolute translational (m) : {:.4} +- {:.4}   (max {:.4})",
            a.abs_trans_m.mean, a.abs_trans_m.std, a.max_trans_m
        )?;
        writeln!(
            f,
            "Squared translational (m2) : {:.4} +- {:.4}",
            a.sq_trans_m2.mean, a.sq_trans_m2.std
        )?;
        writeln!(
            f,
            "Absolute rotational (deg)  : {:.3} +- {:.3}   (max {:.3})",
            a.abs_rot_deg.mean, a.abs_rot_deg.std, a.max_rot_deg
        )?;
        writeln!(
            f,
            "Squared rotational (deg2)  : {:.3} +- {:.3}",
            a.sq_rot_deg2.mean, a.sq_rot_deg2.std
        )?;
        writeln!(
            f,
            "Kummerle eps = mean(t^2 + r^2) [m^2 + rad^2]: {:.6}",
            a.kummerle_eps
        )?;
        for (name, s) in [
            ("short (< 5 s) ", &self.short),
            ("long (> 60 s) ", &self.long),
        ] {
            writeln!(
                f,
                "{name}{:>5} used : {:.4} +- {:.4} m, {:.3} +- {:.3} deg",
                s.used,
                s.abs_trans_m.mean,
                s.abs_trans_m.std,
                s.abs_rot_deg.mean,
                s.abs_rot_deg.std
            )?;
        }
        if a.used > self.matched_within_10us {
            writeln!(
                f,
                "WARNING: {} relation(s) used a pose more than 10 us from the relation time; logs such as\n\
                 \x20        Intel have scans < 1 ms apart, so such a match may be the neighbouring scan.\n\
                 \x20        Write all 6 decimals of the laser timestamps, or use a max dt of 1e-5 s.",
                a.used - self.matched_within_10us
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose_at(t: f64, x: f64, y: f64, theta: f64) -> TrajectoryPose {
        TrajectoryPose::new(Timestamp::from_seconds(t), Pose2::new(x, y, theta))
    }

    /// Driving a circle of radius 2 m at 1 m/s (0.5 rad/s) counter-clockwise from (2, 0) facing
    /// +y: the pose and velocity at `t`.
    fn on_circle(t: f64) -> (Pose2, Velocity2) {
        let a = 0.5 * t;
        (
            Pose2::new(
                2.0 * a.cos(),
                2.0 * a.sin(),
                a + std::f64::consts::FRAC_PI_2,
            ),
            Velocity2 {
                x: -a.sin(),
                y: a.cos(),
                theta: 0.5,
            },
        )
    }

    #[test]
    fn a_trajectory_is_asked_between_its_poses_along_their_velocities() {
        let diagonal = |v: f64| [[v, 0.0, 0.0], [0.0, v, 0.0], [0.0, 0.0, v]];
        let poses = [0.0, 1.0, 2.0]
            .map(|t| {
                let (pose, velocity) = on_circle(t);
                TrajectoryPose {
                    timestamp: Timestamp::from_seconds(10.0 + t),
                    pose,
                    velocity: Some(velocity),
                    covariance: Some(diagonal(1e-4 * (1.0 + t))),
                }
            })
            .to_vec();
        let trajectory = Trajectory { poses };
        // A pose's own time gives it exactly.
        let (pose, covariance) = trajectory.at(11.0).expect("inside");
        assert_eq!(pose, on_circle(1.0).0);
        assert_eq!(covariance, diagonal(2e-4));
        // Between poses the curve follows the arc (the chord misses it by 6 cm halfway).
        let (pose, covariance) = trajectory.at(11.5).expect("inside");
        let truth = on_circle(1.5).0;
        assert!(
            (pose.x - truth.x).hypot(pose.y - truth.y) < 1e-3
                && wrap_angle(pose.theta - truth.theta).abs() < 1e-3,
            "{pose:?} vs {truth:?}"
        );
        assert!((covariance[0][0] - 2.5e-4).abs() < 1e-15);
        let chord = trajectory.poses[1]
            .pose
            .interpolate(&trajectory.poses[2].pose, 0.5);
        assert!((chord.x - truth.x).hypot(chord.y - truth.y) > 0.05);
        // Nothing outside the span, nor at a time that is not a number.
        assert!(trajectory.at(9.999).is_none() && trajectory.at(12.001).is_none());
        assert!(trajectory.at(f64::NAN).is_none());
        // Read from a file, a trajectory has poses but no covariance.
        let mut text = Vec::new();
        write_trajectory(&trajectory, &mut text).expect("written");
        let read = read_trajectory(&text[..]).expect("read");
        assert!(read.at(11.5).is_none());
        let plain = read.pose_at(11.5).expect("inside");
        assert!((plain.x - chord.x).abs() < 1e-6 && (plain.y - chord.y).abs() < 1e-6);
    }

    fn relation(t1: f64, t2: f64, motion: Pose2) -> Relation {
        Relation {
            line: 0,
            t1: Timestamp::from_seconds(t1),
            t2: Timestamp::from_seconds(t2),
            motion,
        }
    }

    /// A 4 m square walked counter-clockwise, a pose every metre, one per second from t = 100.
    fn square() -> Trajectory {
        use std::f64::consts::FRAC_PI_2;
        let mut poses = Vec::new();
        let mut p = Pose2::default();
        for i in 0..16 {
            poses.push(TrajectoryPose::new(
                Timestamp::from_seconds(100.0 + i as f64),
                p,
            ));
            let turn = if i % 4 == 3 { FRAC_PI_2 } else { 0.0 };
            p = p.compose(&Pose2::new(1.0, 0.0, turn));
        }
        Trajectory { poses }
    }

    /// Relations between every pose pair of `truth`, exact.
    fn all_pairs(truth: &Trajectory) -> Relations {
        let mut relations = Vec::new();
        for (i, a) in truth.poses.iter().enumerate() {
            for b in &truth.poses[i + 1..] {
                relations.push(relation(
                    a.timestamp.seconds,
                    b.timestamp.seconds,
                    a.pose.between(&b.pose),
                ));
            }
        }
        Relations { relations }
    }

    #[test]
    fn the_exact_trajectory_scores_zero_and_a_moved_copy_too() {
        let truth = square();
        let rels = all_pairs(&truth);
        let report = evaluate(&truth, &rels, &EvalOptions::default());
        assert_eq!((report.all.used, report.matched_within_10us), (120, 120));
        assert!(report.all.abs_trans_m.mean < 1e-12 && report.all.abs_rot_deg.mean < 1e-12);
        let g = Pose2::new(5.0, -3.0, 1.2);
        let moved = Trajectory {
            poses: truth
                .poses
                .iter()
                .map(|p| TrajectoryPose::new(p.timestamp.clone(), g.compose(&p.pose)))
                .collect(),
        };
        let report = evaluate(&moved, &rels, &EvalOptions::default());
        assert!(report.all.abs_trans_m.mean < 1e-12 && report.all.abs_rot_deg.mean < 1e-12);
    }

    #[test]
    fn one_perturbed_pose_of_a_square_gives_the_known_errors() {
        let truth = square();
        let rels = all_pairs(&truth);
        let mut est = truth.clone();
        // Pose 5 (on the second side, heading +y) pushed 0.1 m along its own x and turned 2°.
        let bump = Pose2::new(0.1, 0.0, 2f64.to_radians());
        est.poses[5].pose = est.poses[5].pose.compose(&bump);
        let report = evaluate(&est, &rels, &EvalOptions::default());
        // 15 of the 120 relations touch pose 5; each errs 2° in rotation. In translation the
        // relations *from* pose 5 see the rotated frame: error = |R(−2°)(t* − 0.1 x̂) − t*|;
        // those *to* pose 5 err exactly 0.1 m.
        assert_eq!(report.all.used, 120);
        let expected_rot = 15.0 * 2.0 / 120.0;
        assert!((report.all.abs_rot_deg.mean - expected_rot).abs() < 1e-9);
        let mut trans = 0.0;
        for r in &rels.relations {
            let (i, j) = (
                (r.t1.seconds - 100.0) as usize,
                (r.t2.seconds - 100.0) as usize,
            );
            trans += if j == 5 {
                0.1
            } else if i == 5 {
                let t = r.motion;
                let c = bump.inverse().compose(&t);
                (c.x - t.x).hypot(c.y - t.y)
            } else {
                0.0
            };
        }
        assert!((report.all.abs_trans_m.mean - trans / 120.0).abs() < 1e-12);
        assert!((report.all.max_rot_deg - 2.0).abs() < 1e-9);
        let error_of = |t1: f64, t2: f64| {
            let e = report
                .per_relation
                .iter()
                .find(|e| e.t1.seconds == t1 && e.t2.seconds == t2)
                .unwrap();
            (e.trans_m, e.rot_deg)
        };
        // 4 → 5: the pose is 0.1 m further along, turned 2°.
        let (t, r) = error_of(104.0, 105.0);
        assert!((t - 0.1).abs() < 1e-12 && (r - 2.0).abs() < 1e-9);
        // 5 → 6: the next pose, 1 m ahead of the true pose 5, seen from the bumped one is
        // R(−2°)·(0.9, 0): |(0.9 cos 2° − 1, −0.9 sin 2°)| = 0.10534…
        let (t, r) = error_of(105.0, 106.0);
        assert!((t - 0.10533997990140151).abs() < 1e-12 && (r - 2.0).abs() < 1e-9);
        let (t, r) = error_of(104.0, 106.0);
        assert!(t < 1e-12 && r < 1e-12, "4 → 6 does not touch pose 5");
        let sq = report.all.sq_rot_deg2.mean;
        assert!((sq - 15.0 * 4.0 / 120.0).abs() < 1e-9, "{sq}");
    }

    #[test]
    fn the_cartographer_formula_rotates_the_reference_translation() {
        let (est, reference) = (Pose2::new(1.0, 0.0, 0.1), Pose2::new(1.0, 0.0, 0.0));
        let (tk, rk) = relation_error(&est, &reference, Formula::Kummerle);
        let (tc, rc) = relation_error(&est, &reference, Formula::Cartographer);
        assert!(tk.abs() < 1e-15 && (tc - 2.0 * 0.05f64.sin()).abs() < 1e-15);
        assert!((rk - 0.1).abs() < 1e-15 && (rc - 0.1).abs() < 1e-15);
    }

    #[test]
    fn a_trajectory_missing_a_scan_matches_its_neighbour_within_max_dt_and_says_so() {
        // Scans at 10.0000, 10.0004 and 12.0; the relation ends at 10.0004 and 12.0.
        let full = Trajectory {
            poses: vec![
                pose_at(10.0, 0.0, 0.0, 0.0),
                pose_at(10.0004, 0.01, 0.0, 0.0),
                pose_at(12.0, 1.01, 0.0, 0.0),
            ],
        };
        let rels = Relations {
            relations: vec![relation(10.0004, 12.0, Pose2::new(1.0, 0.0, 0.0))],
        };
        let exact = evaluate(&full, &rels, &EvalOptions::default());
        assert_eq!((exact.all.used, exact.matched_within_10us), (1, 1));
        assert!(exact.all.abs_trans_m.mean < 1e-12);
        // Without the 10.0004 scan the nearest pose is 0.4 ms away: within the default 1 ms,
        // so the script (and this) uses it — the neighbour's 1 cm shows up as error — but the
        // 10 µs count and the warning say so; with max_dt = 10 µs it is left out.
        let mut skipped = full.clone();
        skipped.poses.remove(1);
        let report = evaluate(&skipped, &rels, &EvalOptions::default());
        assert_eq!((report.all.used, report.matched_within_1ms), (1, 1));
        assert_eq!(report.matched_within_10us, 0);
        assert!((report.all.abs_trans_m.mean - 0.01).abs() < 1e-9);
        assert!((report.max_dt_used_s - 0.0004).abs() < 1e-9);
        assert!(
            report
                .to_string()
                .contains("WARNING: 1 relation(s) used a pose more than 10 us")
        );
        let strict = EvalOptions {
            max_dt: 1e-5,
            ..EvalOptions::default()
        };
        let report = evaluate(&skipped, &rels, &strict);
        assert_eq!((report.all.used, report.matched_within_1ms), (0, 1));
        assert!(report.all.abs_trans_m.mean.is_nan());
        // 2 ms away is unmatched even at the default.
        skipped.poses[0].timestamp = Timestamp::from_seconds(9.9984);
        let report = evaluate(&skipped, &rels, &EvalOptions::default());
        assert_eq!((report.all.used, report.matched_within_1ms), (0, 0));
    }

    #[test]
    fn interpolation_gives_the_pose_between_two_scans() {
        let line = Trajectory {
            poses: vec![
                pose_at(0.0, 0.0, 0.0, 0.0),
                pose_at(1.0, 1.0, 0.0, 0.0),
                pose_at(2.0, 2.0, 0.0, 0.0),
            ],
        };
        let rels = Relations {
            relations: vec![relation(0.0, 1.5, Pose2::new(1.5, 0.0, 0.0))],
        };
        let options = EvalOptions {
            max_dt: f64::INFINITY,
            interpolate: true,
            ..EvalOptions::default()
        };
        let report = evaluate(&line, &rels, &options);
        assert!(report.all.abs_trans_m.mean < 1e-12);
        assert_eq!(report.max_dt_used_s, 0.5);
        let nearest = evaluate(
            &line,
            &rels,
            &EvalOptions {
                interpolate: false,
                ..options
            },
        );
        assert!((nearest.all.abs_trans_m.mean - 0.5).abs() < 1e-12);
    }

    #[test]
    fn a_trajectory_round_trips_with_its_timestamp_text() {
        let text = "# timestamp x y theta\n976052857.337530 1.000000 -2.500000 0.100000\n\
                    70.2899, 3.0, 4.0, -0.5, extra\n";
        let traj = read_trajectory(text.as_bytes()).unwrap();
        assert_eq!(traj.poses.len(), 2);
        assert_eq!(traj.poses[0].timestamp.text, "976052857.337530");
        assert_eq!(traj.poses[1].pose, Pose2::new(3.0, 4.0, -0.5));
        let mut out = Vec::new();
        write_trajectory(&traj, &mut out).unwrap();
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "976052857.337530 1.000000 -2.500000 0.100000\n70.2899 3.000000 4.000000 -0.500000\n"
        );
    }

    #[test]
    fn malformed_trajectory_and_relation_lines_name_the_line_and_the_field() {
        let err = read_trajectory("1.0 2.0 3.0 0.0\n\n2.0 2.0 3.0\n".as_bytes()).unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 3: expected \"timestamp x y theta\", found 3 field(s)"
        );
        let err = read_trajectory("1.0 2.0 nan 0.0\n".as_bytes()).unwrap_err();
        assert_eq!(err.to_string(), "line 1: y is not finite: \"nan\"");
        let err = read_relations("1 2 0.1 0 0 0 0 0\n1 2 0.1 0 0 0 0\n".as_bytes()).unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 2: expected \"t1 t2 x y z roll pitch yaw\", found 7 field(s)"
        );
        let err = read_relations("1 2 0.1 0 0 0 0 yaw\n".as_bytes()).unwrap_err();
        assert_eq!(err.to_string(), "line 1: yaw is not a number: \"yaw\"");
        let rels =
            read_relations("# c\n976052857.337530 976052859.1 0.5 0 0 0 0 0.25\n".as_bytes())
                .unwrap();
        assert_eq!(rels.relations[0].line, 2);
        assert_eq!(rels.relations[0].t1.text, "976052857.337530");
        assert_eq!(rels.relations[0].motion, Pose2::new(0.5, 0.0, 0.25));
    }

    #[test]
    fn the_report_serialises_with_the_scripts_keys() {
        let truth = square();
        let report = evaluate(&truth, &all_pairs(&truth), &EvalOptions::default());
        let json = serde_json::to_value(&report).unwrap();
        for key in [
            "relations",
            "matched_within_1ms",
            "matched_within_10us",
            "used",
            "abs_trans_m",
            "sq_rot_deg2",
            "kummerle_eps",
            "short",
            "long",
        ] {
            assert!(json.get(key).is_some(), "{key} missing from {json}");
        }
        assert_eq!(json["formula"], "kummerle");
        assert_eq!(json["used"], 120);
        assert!(json.get("per_relation").is_none());
    }
}
