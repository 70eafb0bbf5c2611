//! The live pose stage: a session's RPLidar revolutions and IMU samples, in sample-time order,
//! through the slam crate's mapper, giving the live 2D trajectory of `base` with each pose's
//! covariance.
//!
//! Between two revolutions the gyro's rate about `base`'s vertical (the IMU's mount rotation
//! from `Body::Mounts` applied to its rate vector, z kept), less its estimated bias, is
//! integrated over the samples whose edge sample time lies between the two revolutions'
//! reference times (the middles of their beams, the times the mapper's poses are for); the
//! increment goes to the mapper as its rotation prior ([`GyroYaw`] says with what variance).
//! Without IMU samples for an interval (no IMU, or it stopped: the ordered queue then releases
//! its stream) the mapper falls back to its constant-velocity prior, logged once per stop.
//!
//! The RPLidar sits at its mount in `base` (the session's `Body::Mounts`; `base` itself without
//! one), so the trajectory is of `base`. It is in the session's own frame (its first pose at the
//! origin) until a pass starts (`Body::Pass`, stamped by the edge when `scan3d trolley start`
//! reached it): the pass says where `base` stood in the room at that edge time, and the whole
//! trajectory, before and after, is reported through that one transform (a later pass's start
//! re-anchors it). A snapshot writes `trajectory.tum` (TUM lines `t x y z qx qy qz qw`, t in
//! UNIX seconds of the server's clock through the session's time-sync models), each pass's
//! `passes/NAME/trajectory.tum` (its poses in [start, stop), by [`super::passes`]' rules), and
//! the scan matcher's grid as map_server `grid.pgm` + `grid.yaml` and `grid.png` (in the
//! session's frame). The snapshot copies what it needs (poses, passes, clock, the grid's cells)
//! while the pipeline is held and renders the files after ([`Stage::snapshot_job`]).

use std::io::Write;

use serde::Serialize;

use std::collections::VecDeque;

use scan3d_protocol::{Body, Frame, ImuSample, LidarRevolution, PassEvent, SensorId, SensorMounts};
use scan3d_slam::grid::MAX_CELLS;
use scan3d_slam::map_image::{Thresholds, write_pgm, write_png_with_trajectory, write_yaml};
use scan3d_slam::mapper::{Mapper, MapperConfig, RotationPrior, ScanResult};
use scan3d_slam::offline::{RangeLimits, raster};
use scan3d_slam::pose::Pose2;
use scan3d_slam::relations::TrajectoryPose;

use super::order::StreamId;
use super::passes::{PassChange, PassSpans};
use super::snapshot::SnapshotWriter;
use super::{BasePose, PipelineError, SnapshotJob, Stage, StageContext};
use crate::pose::scan_matching::revolution_scan;
use crate::pose::timesync::SessionClock;

/// The range limits of the live pose stage: `scan3d slam SESSION_DIR`'s defaults (0.1 m and up),
/// so the offline command gives the poses the live daemon gave.
pub const POSE_RANGE_LIMITS: RangeLimits = RangeLimits {
    min_range: 0.1,
    max_range: None,
    no_return: None,
};

/// The MPU-9250's gyro rate noise spectral density: 0.01 °/s/√Hz (datasheet, PS-MPU-9250A-01
/// §3.1), in rad/s/√Hz. Integrated over `dt` seconds it is an angle random walk of variance
/// `N² · dt` rad².
pub const GYRO_NOISE_DENSITY: f64 = 0.01 * std::f64::consts::PI / 180.0;

/// The gyro's zero-rate offset before it was measured at rest, rad/s: the datasheet's initial
/// tolerance, ±5 °/s, taken as one standard deviation.
pub const GYRO_BIAS_UNMEASURED: f64 = 5.0 * std::f64::consts::PI / 180.0;

/// What a bias measured at rest still misses, rad/s: its drift with temperature and time over a
/// session (0.05 °/s; the rest's own noise, `N / √T`, is added to it).
pub const GYRO_BIAS_DRIFT: f64 = 0.05 * std::f64::consts::PI / 180.0;

/// How long the bias estimate remembers (s of rest): a drifting bias is followed, and its
/// uncertainty from the rest's noise is that of at most this much rest.
pub const GYRO_BIAS_MEMORY_S: f64 = 60.0;

/// The longest gap between IMU samples (and at an interval's ends) still integrated, s: ten
/// samples at the edge's 200 Hz. A longer one and the interval gets no gyro prior.
pub const GYRO_MAX_GAP_S: f64 = 0.05;

/// How far past the middle of an RPLidar revolution's span the pose lane keys it, ns: three
/// IMU samples at 200 Hz, so the sample at or after the pose's time (the middle of the beams,
/// at or before the span's middle) has been taken when the revolution is matched.
pub const POSE_KEY_MARGIN_NS: u64 = 15_000_000;

/// IMU samples kept waiting for the next revolution at most (20 s at 200 Hz): without
/// revolutions the oldest are dropped.
const GYRO_MAX_SAMPLES: usize = 4096;

/// The gyro's yaw increments between revolutions, for the mapper's rotation prior.
///
/// A sample's rate is taken to hold over the time since the previous sample (the MPU-9250
/// averages over its sample period through its low-pass filter), so the increment over
/// `(a, b]` is `Σ ω_i · |(t_{i−1}, t_i] ∩ (a, b]|` with the sample at or after `b` included for
/// the last piece. Its variance: the angle random walk `N² · Δt` plus the bias's uncertainty
/// carried over the interval, `(σ_b · Δt)²`, with `σ_b` the unmeasured tolerance until the
/// head was seen standing, then `√(N² / T_rest + drift²)`.
///
/// The bias is the mean rate over the intervals in which the mapper held a standing head
/// (`ScanResult::standing`: the matches say it did not move), exponentially forgetting rest
/// older than [`GYRO_BIAS_MEMORY_S`].
#[derive(Debug, Clone)]
pub struct GyroYaw {
    /// `base`'s z axis in the IMU's frame: the z row of the mount's rotation IMU → base.
    axis: [f64; 3],
    /// (edge time s, rate about base z rad/s), time increasing; from the last sample at or
    /// before the previous revolution's time on.
    samples: VecDeque<(f64, f64)>,
    /// The previous revolution's reference time, s.
    from: Option<f64>,
    bias: f64,
    /// Seconds of rest the bias was measured over (at most [`GYRO_BIAS_MEMORY_S`]).
    rest_s: f64,
}

impl Default for GyroYaw {
    fn default() -> Self {
        Self {
            axis: [0.0, 0.0, 1.0],
            samples: VecDeque::new(),
            from: None,
            bias: 0.0,
            rest_s: 0.0,
        }
    }
}

impl GyroYaw {
    /// Sets the IMU's mount: its rotation IMU → base is `Rz(yaw) Ry(pitch) Rx(roll)` (as the
    /// edge's `[imu.mount]` says), whose z row does not depend on the yaw.
    pub fn set_mount(&mut self, roll: f64, pitch: f64) {
        let (sr, cr) = roll.sin_cos();
        let (sp, cp) = pitch.sin_cos();
        self.axis = [-sp, cp * sr, cp * cr];
    }

    /// Takes one gyro reading (rad/s, IMU frame) at edge time `t` (s). Readings not after the
    /// newest one (late or repeated) are ignored.
    pub fn push(&mut self, t: f64, gyro: [f32; 3]) {
        let rate: f64 = (0..3).map(|k| self.axis[k] * f64::from(gyro[k])).sum();
        if !t.is_finite() || !rate.is_finite() || self.samples.back().is_some_and(|s| s.0 >= t) {
            return;
        }
        if self.samples.len() >= GYRO_MAX_SAMPLES {
            self.samples.pop_front();
        }
        self.samples.push_back((t, rate));
    }

    /// The estimated bias, rad/s, and how long a rest it was measured over (s; 0: not yet).
    pub fn bias(&self) -> (f64, f64) {
        (self.bias, self.rest_s)
    }

    /// The bias's standard deviation, rad/s.
    fn bias_sigma(&self) -> f64 {
        if self.rest_s <= 0.0 {
            GYRO_BIAS_UNMEASURED
        } else {
            (GYRO_NOISE_DENSITY.powi(2) / self.rest_s + GYRO_BIAS_DRIFT.powi(2)).sqrt()
        }
    }

    /// The raw integral of the rate over `(a, b]` and the longest gap in it, or `None` when
    /// the samples do not reach `b`.
    fn integrate(&self, a: f64, b: f64) -> Option<(f64, f64)> {
        let mut previous: Option<f64> = None;
        let (mut sum, mut gap) = (0.0, 0.0f64);
        for &(t, rate) in &self.samples {
            let start = previous.unwrap_or(a).max(a);
            let end = t.min(b);
            if end > start {
                sum += rate * (end - start);
                gap = gap.max(end - start);
            }
            if t >= b {
                return Some((sum, gap));
            }
            previous = Some(t);
        }
        None
    }

    /// The rotation prior from the previous revolution's time to `to` (s): `None` for the
    /// first revolution, or when the samples do not cover the interval within
    /// [`GYRO_MAX_GAP_S`].
    pub fn prior(&self, to: f64) -> Option<RotationPrior> {
        let from = self.from?;
        let dt = to - from;
        if dt <= 0.0 {
            return None;
        }
        // The first sample must be close enough after `from` (a sample before it covers it).
        let first = self.samples.front()?.0;
        if first > from + GYRO_MAX_GAP_S {
            return None;
        }
        let (sum, gap) = self.integrate(from, to)?;
        if gap > GYRO_MAX_GAP_S {
            return None;
        }
        let sigma_b = self.bias_sigma();
        Some(RotationPrior {
            increment: sum - self.bias * dt,
            variance: GYRO_NOISE_DENSITY.powi(2) * dt + (sigma_b * dt).powi(2),
        })
    }

    /// The revolution at reference time `time` (s) was matched; `standing`: the mapper held
    /// the head still, so the rate since the previous revolution was the bias.
    pub fn revolution(&mut self, time: f64, standing: bool) {
        if let Some(from) = self.from
            && standing
            && time > from
            && let Some((sum, gap)) = self.integrate(from, time)
            && gap <= GYRO_MAX_GAP_S
        {
            let dt = time - from;
            let rest = (self.rest_s + dt).min(GYRO_BIAS_MEMORY_S);
            self.bias += (sum / dt - self.bias) * dt / rest;
            self.rest_s = rest;
        }
        // Keep the last sample at or before `time`: it bounds the next interval's first piece.
        while self.samples.len() > 1 && self.samples[1].0 <= time {
            self.samples.pop_front();
        }
        self.from = Some(time);
    }
}

/// A session's poses from its RPLidar revolutions and IMU samples: the mapper, the lidar's
/// mount, the gyro. Live ([`PoseStage`]) and offline (`scan3d slam`) alike.
#[derive(Debug, Clone)]
pub struct PoseTracker {
    mapper: Mapper,
    limits: RangeLimits,
    /// The RPLidar's pose in `base` (x, y, yaw).
    mount: Pose2,
    /// A mount that `Body::Mounts` does not replace.
    fixed_mount: bool,
    gyro: GyroYaw,
    /// Whether IMU samples came at all, and whether the last revolution had none to go by.
    imu_seen: bool,
    falling_back: bool,
    /// Revolutions matched with a gyro prior, and without one although IMU samples came.
    gyro_priors: u64,
    gyro_fallbacks: u64,
}

impl PoseTracker {
    /// A tracker matching with `config` and `limits`, the lidar at `mount` in `base` until a
    /// `Body::Mounts` says otherwise (`fixed`: it never does).
    pub fn new(config: MapperConfig, limits: RangeLimits, mount: Pose2, fixed: bool) -> Self {
        Self {
            mapper: Mapper::new(config),
            limits,
            mount,
            fixed_mount: fixed,
            gyro: GyroYaw::default(),
            imu_seen: false,
            falling_back: false,
            gyro_priors: 0,
            gyro_fallbacks: 0,
        }
    }

    /// The mapper (its map, its configuration).
    pub fn mapper(&self) -> &Mapper {
        &self.mapper
    }

    /// The gyro integration (its bias).
    pub fn gyro(&self) -> &GyroYaw {
        &self.gyro
    }

    /// Revolutions matched with the gyro's prior, and revolutions that had to do without one
    /// after IMU samples had come (they stopped, or a gap).
    pub fn gyro_counts(&self) -> (u64, u64) {
        (self.gyro_priors, self.gyro_fallbacks)
    }

    /// Takes the sensors' mounts: the RPLidar's (unless fixed) and the IMU's rotation.
    pub fn on_mounts(&mut self, mounts: &SensorMounts) {
        for m in &mounts.sensors {
            if m.sensor == SensorId::RPLIDAR && !self.fixed_mount {
                self.mount = Pose2::new(m.x_m, m.y_m, m.yaw_deg.to_radians());
            } else if m.sensor == SensorId::IMU {
                self.gyro
                    .set_mount(m.roll_deg.to_radians(), m.pitch_deg.to_radians());
            }
        }
    }

    /// Takes one IMU sample.
    pub fn on_imu(&mut self, sample: &ImuSample) {
        self.imu_seen = true;
        self.gyro.push(sample.t_ns as f64 * 1e-9, sample.gyro_radps);
    }

    /// Matches one RPLidar revolution (other sensors' are not taken: `None`).
    pub fn on_revolution(&mut self, revolution: &LidarRevolution) -> Option<ScanResult> {
        if revolution.sensor != SensorId::RPLIDAR {
            return None;
        }
        let mut scan = revolution_scan(revolution, &self.limits, &self.mount);
        let reference = scan.reference_time();
        scan.rotation = self.gyro.prior(reference);
        if scan.rotation.is_some() {
            self.gyro_priors += 1;
            if self.falling_back {
                tracing::info!("IMU samples again: the pose stage takes the gyro's turn again");
                self.falling_back = false;
            }
        } else if self.imu_seen && self.mapper_started() {
            self.gyro_fallbacks += 1;
            if !self.falling_back {
                tracing::warn!(
                    at_s = reference,
                    "no IMU samples between two revolutions: the pose stage falls back to the \
                     constant-velocity prior"
                );
                self.falling_back = true;
            }
        }
        let refused = self.mapper.refused_integrations();
        let result = self.mapper.add_scan(&scan);
        if refused == 0 && self.mapper.refused_integrations() > 0 {
            tracing::warn!(
                at_s = reference,
                cells = MAX_CELLS,
                "the map reached its size limit: revolutions beyond it are matched but not \
                 mapped, and where the map has nothing the pose follows the prior alone"
            );
        }
        self.gyro.revolution(result.time, result.standing);
        Some(result)
    }

    fn mapper_started(&self) -> bool {
        self.gyro.from.is_some()
    }
}

/// Where `base` is now, for `scan3d status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PoseStatus {
    /// x in the room frame (the session's own before a pass anchors it), m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading of `base`'s x axis, degrees.
    pub yaw_deg: f64,
    /// Covariance over (x, y, yaw), row-major, m² / m·rad / rad².
    pub covariance: [f64; 9],
    /// Length of the path so far, m.
    pub path_m: f64,
    /// Revolutions matched.
    pub revolutions: u64,
    /// Whether the trajectory is anchored in the room (a pass started).
    pub anchored: bool,
}

/// The live 2D trajectory of `base` from the RPLidar's revolutions.
pub struct PoseStage {
    tracker: PoseTracker,
    /// Poses in the session's frame, edge clock seconds.
    poses: Vec<TrajectoryPose>,
    path_m: f64,
    /// Session frame → room frame, once anchored.
    anchor: Option<Pose2>,
    /// The passes; this stage logs the markers it ignores (the others after it do not).
    passes: PassSpans,
    clock: SessionClock,
}

impl std::fmt::Debug for PoseStage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PoseStage")
            .field("poses", &self.poses.len())
            .field("path_m", &self.path_m)
            .field("anchor", &self.anchor)
            .finish_non_exhaustive()
    }
}

impl PoseStage {
    /// A stage matching with `config` and [`POSE_RANGE_LIMITS`], the lidar at `mount` in `base`.
    pub fn new(config: MapperConfig, mount: Pose2) -> Self {
        PoseStage {
            tracker: PoseTracker::new(config, POSE_RANGE_LIMITS, mount, false),
            poses: Vec::new(),
            path_m: 0.0,
            anchor: None,
            passes: PassSpans::logging(),
            clock: SessionClock::new(),
        }
    }

    /// The trajectory so far, in the session's frame (edge clock seconds).
    pub fn poses(&self) -> &[TrajectoryPose] {
        &self.poses
    }

    /// The mapper, the mount and the gyro behind the poses.
    pub fn tracker(&self) -> &PoseTracker {
        &self.tracker
    }

    /// Says that `base` stood at `room` (room frame) at edge time `t_ns`: the whole trajectory
    /// is reported in the room frame from now on. The pose at `t_ns` is the one of the newest
    /// revolution at or before it (the first one if none).
    /// The newest pose at or before it is carried to `t_ns` with its velocity.
    pub fn anchor(&mut self, t_ns: u64, room: Pose2) {
        let t = t_ns as f64 * 1e-9;
        let at = match self.poses.iter().rev().find(|p| p.timestamp.seconds <= t) {
            Some(p) => {
                let dt = t - p.timestamp.seconds;
                let v = p.velocity.unwrap_or_default();
                Pose2 {
                    x: p.pose.x + v.x * dt,
                    y: p.pose.y + v.y * dt,
                    theta: p.pose.theta + v.theta * dt,
                }
            }
            None => self.poses.first().map_or_else(Pose2::default, |p| p.pose),
        };
        self.anchor = Some(room.compose(&at.inverse()));
    }

    /// Names of the passes seen, each once, in the order of their first start.
    pub fn passes(&self) -> Vec<String> {
        self.passes.names()
    }

    /// The passes seen as (name, start, stop) in edge ns (stop `None` while open), in start
    /// order: the spans assembly along movement keeps for `--pass NAME`.
    pub fn pass_spans(&self) -> Vec<(String, u64, Option<u64>)> {
        self.passes.as_tuples()
    }

    /// Whether a pass start anchored the trajectory in the room frame.
    pub fn anchored(&self) -> bool {
        self.anchor.is_some()
    }

    /// The trajectory so far as (edge ns, pose of `base`) in the reported frame (the room's
    /// once anchored, see [`PoseStage::anchored`]): what the Sweep's samples are placed with.
    pub fn room_poses(&self) -> Vec<(u64, Pose2)> {
        self.poses
            .iter()
            .map(|p| (edge_ns(p.timestamp.seconds), self.reported(&p.pose)))
            .collect()
    }

    /// A pass marker: a start ([`PassSpans`]' rules) anchors the trajectory in the room.
    fn on_pass(&mut self, t_ns: u64, event: &PassEvent) {
        if let PassChange::Started { room, .. } = self.passes.apply(t_ns, event) {
            self.anchor(t_ns, room);
        }
    }

    /// The time-sync models the snapshot maps edge times with.
    pub fn set_clock(&mut self, clock: SessionClock) {
        self.clock = clock;
    }

    /// A pose of the session's frame in the reported frame (the room's once anchored).
    fn reported(&self, pose: &Pose2) -> Pose2 {
        reported(self.anchor, pose)
    }

    /// Where `base` is now; `None` before the first revolution.
    pub fn status(&self) -> Option<PoseStatus> {
        let last = self.poses.last()?;
        let pose = self.reported(&last.pose);
        let mut covariance = last.covariance.unwrap_or([[0.0; 3]; 3]);
        if let Some(anchor) = self.anchor {
            covariance = rotate_covariance(&covariance, anchor.theta);
        }
        Some(PoseStatus {
            x: pose.x,
            y: pose.y,
            yaw_deg: pose.theta.to_degrees(),
            covariance: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| covariance[k / 3][k % 3]),
            path_m: self.path_m,
            revolutions: self.poses.len() as u64,
            anchored: self.anchor.is_some(),
        })
    }

    /// Writes the trajectory as TUM lines: t in UNIX seconds of the server's clock when a
    /// time-sync model covers the session, else in edge-clock seconds (said in a comment).
    pub fn write_tum(&self, out: &mut dyn Write) -> std::io::Result<()> {
        write_matcher_tum(out, &self.clock, self.anchor, &self.poses, |_| true)
    }

    /// What the stage's part of a session snapshot needs, copied (`None` for a position's
    /// snapshot, or before the first pose): the heavy work is [`PoseSnapshot::write`]'s.
    fn take_snapshot(&self, position: Option<&str>) -> Option<PoseSnapshot> {
        if position.is_some() || self.poses.is_empty() {
            return None;
        }
        Some(PoseSnapshot {
            poses: self.poses.clone(),
            anchor: self.anchor,
            passes: self.passes.clone(),
            clock: self.clock.clone(),
            grid: self.tracker.mapper().map().finest().clone(),
        })
    }
}

/// A pose of the session's frame in the reported frame: the room's through `anchor` once a
/// pass anchored the trajectory, else the session's own.
fn reported(anchor: Option<Pose2>, pose: &Pose2) -> Pose2 {
    anchor.map_or(*pose, |a| a.compose(pose))
}

/// An edge time in seconds as edge ns (as the poses handed on carry it; negative as 0).
pub(crate) fn edge_ns(edge_s: f64) -> u64 {
    (edge_s * 1e9).round().max(0.0) as u64
}

/// Writes the matcher's `poses` (session frame) whose edge ns `keep` takes as TUM lines, in the
/// reported frame of `anchor` ([`write_tum`]).
fn write_matcher_tum(
    out: &mut dyn Write,
    clock: &SessionClock,
    anchor: Option<Pose2>,
    poses: &[TrajectoryPose],
    keep: impl Fn(u64) -> bool,
) -> std::io::Result<()> {
    let poses = poses
        .iter()
        .filter(|p| keep(edge_ns(p.timestamp.seconds)))
        .map(|p| (p.timestamp.seconds, reported(anchor, &p.pose), None));
    write_tum(out, clock, poses)
}

/// The pose stage's part of a session snapshot, copied while the pipeline is held (the poses,
/// the passes, the clock and the matcher's finest grid: a copy of its cells) so that the TUM
/// files, the grid's raster and its PGM and PNG are made after the pipeline is released.
struct PoseSnapshot {
    poses: Vec<TrajectoryPose>,
    anchor: Option<Pose2>,
    passes: PassSpans,
    clock: SessionClock,
    grid: scan3d_slam::grid::Grid,
}

impl PoseSnapshot {
    /// Writes `trajectory.tum`, each pass's `passes/NAME/trajectory.tum` (the poses in the
    /// pass's spans, [`PassSpans`]' rules), and `grid.pgm`, `grid.yaml`, `grid.png` once a cell
    /// of the grid was hit.
    fn write(self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        let (clock, anchor, poses) = (&self.clock, self.anchor, &self.poses[..]);
        out.render("trajectory.tum", |tum| {
            write_matcher_tum(tum, clock, anchor, poses, |_| true)
        })?;
        for name in self.passes.names() {
            let subdir = std::path::Path::new("passes").join(path_safe(&name));
            let covers = |t_ns| self.passes.covers(&name, t_ns);
            out.render_in(&subdir, "trajectory.tum", |tum| {
                write_matcher_tum(tum, clock, anchor, poses, covers)
            })?;
        }
        let Ok(raster) = raster(&self.grid) else {
            // No cell was ever hit: no grid to write.
            return Ok(());
        };
        let thresholds = Thresholds::default();
        out.render("grid.pgm", |pgm| write_pgm(&raster, &thresholds, pgm))?;
        out.render("grid.yaml", |yaml| write_yaml(&raster, "grid.pgm", yaml))?;
        let session_poses: Vec<Pose2> = poses.iter().map(|p| p.pose).collect();
        out.render("grid.png", |png| {
            write_png_with_trajectory(&raster, &thresholds, &session_poses, png)
        })
    }
}

/// Writes poses `(edge s, pose in the reported frame, roll and pitch if known)` as TUM lines
/// `t x y z qx qy qz qw` (z 0; the quaternion
/// `Rz(yaw) Ry(pitch) Rx(roll)`, level without roll and pitch): t in UNIX seconds of the
/// server's clock when a time-sync model covers the session (`clock`), else in edge-clock
/// seconds (said in a comment). The pose stage's `trajectory.tum` and the fusion stage's
/// `trajectory_fused.tum` alike.
pub fn write_tum(
    out: &mut dyn Write,
    clock: &SessionClock,
    poses: impl Iterator<Item = (f64, Pose2, Option<[f64; 2]>)>,
) -> std::io::Result<()> {
    let on_server = !clock.models().is_empty();
    if !on_server {
        writeln!(
            out,
            "# t: edge clock seconds (no time-sync model in this session)"
        )?;
    }
    for (edge_s, pose, roll_pitch) in poses {
        let t = tum_time(clock, edge_s);
        let [roll, pitch] = roll_pitch.unwrap_or([0.0, 0.0]);
        let (sr, cr) = (roll / 2.0).sin_cos();
        let (sp, cp) = (pitch / 2.0).sin_cos();
        let (sy, cy) = (pose.theta / 2.0).sin_cos();
        let (qx, qy) = (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy);
        let (qz, qw) = (cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy);
        if roll_pitch.is_some() {
            writeln!(
                out,
                "{t:.6} {:.6} {:.6} 0 {qx:.9} {qy:.9} {qz:.9} {qw:.9}",
                pose.x, pose.y
            )?;
        } else {
            writeln!(
                out,
                "{t:.6} {:.6} {:.6} 0 0 0 {qz:.9} {qw:.9}",
                pose.x, pose.y
            )?;
        }
    }
    Ok(())
}

/// A trajectory file's time for edge time `edge_s`: UNIX seconds of the server's clock through
/// the session's time-sync models when one covers it, else the edge's seconds.
pub fn tum_time(clock: &SessionClock, edge_s: f64) -> f64 {
    if clock.models().is_empty() {
        return edge_s;
    }
    clock
        .to_server_ns(edge_ns(edge_s))
        .map_or(edge_s, |ns| ns as f64 * 1e-9)
}

/// A pass name as one path component: letters, digits, `.`, `_` and `-` kept, anything else
/// `_`, and never `.` or `..` alone.
pub(crate) fn path_safe(name: &str) -> String {
    let safe: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            }
        })
        .collect();
    if safe.is_empty() || safe.chars().all(|c| c == '.') {
        format!("_{safe}")
    } else {
        safe
    }
}

/// Σ' = R Σ Rᵀ for a rotation of the frame by `theta` (x, y rotate; yaw does not).
fn rotate_covariance(c: &[[f64; 3]; 3], theta: f64) -> [[f64; 3]; 3] {
    let (s, co) = theta.sin_cos();
    let r = [[co, -s, 0.0], [s, co, 0.0], [0.0, 0.0, 1.0]];
    let mut rc = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            rc[i][j] = (0..3).map(|k| r[i][k] * c[k][j]).sum();
        }
    }
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = (0..3).map(|k| rc[i][k] * r[j][k]).sum();
        }
    }
    out
}

impl Stage for PoseStage {
    fn name(&self) -> &'static str {
        "pose"
    }

    fn streams(&self) -> &'static [StreamId] {
        &[StreamId::Rplidar, StreamId::Imu, StreamId::Pass]
    }

    /// An RPLidar revolution is keyed at the middle of its span plus [`POSE_KEY_MARGIN_NS`]
    /// (at most its end): its pose is for the middle of its beams, and the gyro's prior needs
    /// the IMU only a sample past that, so the revolution need not wait until the IMU has
    /// reached its end (the edge reads the IMU's FIFO in batches, ~37 ms apart).
    fn key_ns(&self, frame: &Frame, default_ns: u64) -> u64 {
        match &frame.body {
            Body::Revolution(rev) if rev.sensor == scan3d_protocol::SensorId::RPLIDAR => {
                let middle = rev.t0_ns + rev.t1_ns.saturating_sub(rev.t0_ns) / 2;
                middle.saturating_add(POSE_KEY_MARGIN_NS).min(default_ns)
            }
            _ => default_ns,
        }
    }

    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
        let revolution = match &frame.body {
            Body::Revolution(revolution) => revolution,
            Body::Imu(sample) => {
                self.tracker.on_imu(sample);
                return;
            }
            Body::Mounts(mounts) => {
                self.tracker.on_mounts(mounts);
                return;
            }
            Body::Pass(marker) => {
                self.on_pass(marker.t_ns, &marker.event);
                return;
            }
            _ => return,
        };
        let Some(result) = self.tracker.on_revolution(revolution) else {
            return;
        };
        if let Some(previous) = self.poses.last() {
            let (dx, dy) = (
                result.pose.x - previous.pose.x,
                result.pose.y - previous.pose.y,
            );
            self.path_m += dx.hypot(dy);
        }
        self.poses.push(TrajectoryPose::of(&result));
        ctx.poses.push(BasePose {
            t_ns: edge_ns(result.time),
            pose: result.pose,
            covariance: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| result.covariance[k / 3][k % 3]),
            roll_pitch: None,
            room_from_session: self.anchor,
        });
    }

    fn snapshot(&mut self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        let position = out.snapshot.position.clone();
        self.take_snapshot(position.as_deref())
            .map_or(Ok(()), |snapshot| snapshot.write(out))
    }

    /// The poses, passes, clock and grid copied; the files made and written after.
    fn snapshot_job(&self, position: Option<&str>) -> Option<SnapshotJob> {
        let snapshot = self.take_snapshot(position)?;
        Some(Box::new(move |out: &mut SnapshotWriter| {
            snapshot.write(out)
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_rplidar_revolution_is_keyed_past_its_middle_and_others_as_given() {
        let stage = PoseStage::new(MapperConfig::default(), Pose2::default());
        let frame = |rev: scan3d_protocol::LidarRevolution| Frame::new(1, 0, rev);
        let ms = 1_000_000;
        // 180 ms: middle at 90 ms, keyed 15 ms past it.
        let long = scan3d_protocol::LidarRevolution::new(SensorId::RPLIDAR, 1000 * ms, 1180 * ms);
        assert_eq!(stage.key_ns(&frame(long), 1180 * ms), 1105 * ms);
        // 20 ms: the margin would pass the end, so the end.
        let short = scan3d_protocol::LidarRevolution::new(SensorId::RPLIDAR, 1000 * ms, 1020 * ms);
        assert_eq!(stage.key_ns(&frame(short), 1020 * ms), 1020 * ms);
        // Not an RPLidar revolution: the pipeline's key.
        let sweep = scan3d_protocol::LidarRevolution::new(SensorId::SWEEP, 1000 * ms, 1180 * ms);
        assert_eq!(stage.key_ns(&frame(sweep), 1180 * ms), 1180 * ms);
    }

    #[test]
    fn an_anchor_carries_the_whole_trajectory_into_the_room_frame() {
        let mut stage = PoseStage::new(MapperConfig::default(), Pose2::default());
        for (i, x) in [0.0, 0.5, 1.0].into_iter().enumerate() {
            stage.poses.push(TrajectoryPose::new(
                scan3d_slam::text::Timestamp::from_seconds(i as f64),
                Pose2 {
                    x,
                    y: 0.0,
                    theta: 0.0,
                },
            ));
        }
        // At t = 1 s base stood at (2, 3) facing +y.
        stage.anchor(
            1_000_000_000,
            Pose2 {
                x: 2.0,
                y: 3.0,
                theta: std::f64::consts::FRAC_PI_2,
            },
        );
        let now = stage.status().expect("a pose");
        assert!(
            (now.x - 2.0).abs() < 1e-9 && (now.y - 3.5).abs() < 1e-9,
            "{now:?}"
        );
        assert!((now.yaw_deg - 90.0).abs() < 1e-9);
        let mut tum = Vec::new();
        stage.write_tum(&mut tum).unwrap();
        let text = String::from_utf8(tum).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[0].starts_with("# t: edge clock"));
        assert_eq!(
            lines[1],
            "0.000000 2.000000 2.500000 0 0 0 0.707106781 0.707106781"
        );
    }

    #[test]
    fn a_snapshot_job_owns_a_copy_and_a_positions_snapshot_has_no_part() {
        let mut stage = PoseStage::new(MapperConfig::default(), Pose2::default());
        let pose = |t: f64| {
            TrajectoryPose::new(
                scan3d_slam::text::Timestamp::from_seconds(t),
                Pose2::default(),
            )
        };
        assert!(stage.snapshot_job(None).is_none(), "no pose yet: no part");
        stage.poses.extend([pose(1.0), pose(2.0)]);
        assert!(stage.snapshot_job(Some("p1")).is_none());
        let job = stage.snapshot_job(None).expect("a part");
        // Poses after the job was taken are not in its files.
        stage.poses.push(pose(3.0));
        let tmp = tempfile::tempdir().unwrap();
        let mut out = SnapshotWriter::new(tmp.path(), None);
        job(&mut out).unwrap();
        let tum = std::fs::read_to_string(tmp.path().join("trajectory.tum")).unwrap();
        let times: Vec<&str> = tum
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split(' ').next().unwrap())
            .collect();
        assert_eq!(times, ["1.000000", "2.000000"]);
        // No revolution was matched: no grid.
        assert_eq!(out.snapshot.files, [tmp.path().join("trajectory.tum")]);
    }

    #[test]
    fn the_gyros_turn_between_two_revolutions_is_its_rate_over_their_times_less_the_bias() {
        // Mounted upside down (roll 180°): the IMU's z reads the opposite of base's.
        let mut gyro = GyroYaw::default();
        gyro.set_mount(std::f64::consts::PI, 0.0);
        // 200 Hz from t = 0.9 s, turning at 0.5 rad/s about base z.
        for k in 0..100 {
            gyro.push(0.9 + 0.005 * f64::from(k), [0.0, 0.0, -0.5]);
        }
        assert_eq!(gyro.prior(1.0), None, "no revolution before");
        gyro.revolution(1.0, false);
        let prior = gyro.prior(1.2).expect("covered");
        assert!((prior.increment - 0.1).abs() < 1e-9, "{prior:?}");
        // Unmeasured bias: (5 °/s · 0.2 s)² dominates the noise density's N² · 0.2 s.
        let want = (GYRO_BIAS_UNMEASURED * 0.2).powi(2) + GYRO_NOISE_DENSITY.powi(2) * 0.2;
        assert!((prior.variance - want).abs() < 1e-12, "{prior:?}");
        // Not covered: the samples end at 1.395 s.
        assert_eq!(gyro.prior(1.5), None);
        // Standing from 1.0 to 1.2 s at a reading of 0.5 rad/s: that is the bias now.
        gyro.revolution(1.2, true);
        let (bias, rest) = gyro.bias();
        assert!((bias - 0.5).abs() < 1e-9 && (rest - 0.2).abs() < 1e-9);
        let prior = gyro.prior(1.3).expect("covered");
        assert!(prior.increment.abs() < 1e-9, "{prior:?}");
        assert!(prior.variance < want / 100.0, "{prior:?}");
    }

    #[test]
    fn a_gap_in_the_imu_samples_leaves_the_interval_without_a_prior() {
        let mut gyro = GyroYaw::default();
        for k in 0..10 {
            gyro.push(1.0 + 0.005 * f64::from(k), [0.0, 0.0, 1.0]);
        }
        for k in 0..10 {
            gyro.push(1.2 + 0.005 * f64::from(k), [0.0, 0.0, 1.0]);
        }
        gyro.revolution(1.0, false);
        assert!(gyro.prior(1.04).is_some());
        assert_eq!(gyro.prior(1.22), None, "150 ms without a sample");
    }

    #[test]
    fn a_rotated_frame_rotates_the_position_covariance_and_keeps_the_yaw_variance() {
        let c = [[4.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.01]];
        let r = rotate_covariance(&c, std::f64::consts::FRAC_PI_2);
        assert!((r[0][0] - 1.0).abs() < 1e-12 && (r[1][1] - 4.0).abs() < 1e-12);
        assert!((r[2][2] - 0.01).abs() < 1e-15);
    }
}
