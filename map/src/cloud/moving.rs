//! 3D assembly along movement (the paper's §III-B): every Sweep sample placed with the pose of
//! `base` at its own sample time.
//!
//! On the trolley nothing turns the Sweep: its scan plane stands across the direction of travel
//! and the trolley's motion sweeps it through the room. A sample of range L at device azimuth α,
//! measured at time t, lands at
//!
//! ```text
//! p = T_room←base(t) · T_base←sweep · (L·cos α, L·sin α, 0)
//! ```
//!
//! with its own sensor origin `o = T_room←base(t) · T_base←sweep · 0`. The beam at azimuth α
//! points along (cos α, sin α, 0) in the Sweep's own frame (counter-clockwise about its spin
//! axis, sensor z), the convention of the emulator's scanner; the mount `T_base←sweep` is the
//! edge's `[sweep.mount]` ([`scan3d_protocol::SensorMount`]: translation, then
//! `R = Rz(yaw) · Ry(pitch) · Rx(roll)`, sensor axes → `base`). The rig's trolley mounts the
//! Sweep with pitch −90°: azimuth 0 up, 90° along `base` +y, spin axis along `base` −x. With a
//! pose that does not change during a revolution this is eq. (1) of
//! [`super::assembly`] (a test holds the two to it); what changes is `t`: at 0.5 m/s a sample
//! placed with the pose of its revolution's start instead of its own lands up to
//! 0.5 m/s × 0.2 s = 10 cm off at the rig's 5 Hz.
//!
//! **Ray bundles.** The octree inserts one [`RayBundle`] at a time, casting every point's
//! free-space ray from the bundle's single origin. Each sample has its own origin, so
//! consecutive samples share a bundle only while their origins stay within
//! [`MovingSettings::max_origin_drift_m`] of the bundle's origin (its first sample's); the points
//! themselves are always exact. The default is a quarter voxel: a ray cast from a start moved by
//! e < resolution/4 ends in the same (exact) voxel and stays within e of the true ray all along,
//! so it can only cross a different voxel where the true ray passes within e of a voxel face —
//! it trades a boundary voxel for its face neighbour and never reaches a voxel the true ray
//! does not touch or border; the occupied (end) updates are unchanged. At the default 5 cm
//! resolution that is 12.5 mm of origin travel: 25 ms at 0.5 m/s, 62 ms at 0.2 m/s, i.e.
//! about 14–34 samples at the Sweep's 550 Hz (26–64 at 1025 Hz), four to eight bundles per
//! 5 Hz revolution (turning moves the mast-mounted origin too and shortens them). A bundle
//! never spans two revolutions.
//!
//! **Poses.** A [`BaseTrajectory`] gives the pose of `base` in the room frame at a sample time
//! (x, y, yaw from the 2D trajectory; roll and pitch when known) and the span of times it
//! knows. A sample outside that span by more than [`MovingSettings::extrapolation_tolerance_ns`]
//! is not placed but counted
//! ([`PlacementCounts::before_span`], [`PlacementCounts::after_span`]): a live
//! stage holds a revolution until [`poses_cover`] says the trajectory reaches its last sample
//! (or its lane's watermark releases it), so nothing is extrapolated beyond the tolerance.
//!
//! **Products.** [`MovingAssembler`] runs each placed revolution's bundles through the
//! per-revolution filters together (as the server's filter stage does for static scans), hands
//! them out for the octree ([`MovingAssembler::take_new`], uncut: the octree applies its own
//! `max_range`) and keeps the pass's cloud with points beyond `max_range_m` cut, as the
//! server's map stage keeps a static scan's cloud.

use std::f64::consts::PI;

use scan3d_protocol::{LidarRevolution, SensorId, SensorMount};

use super::RayBundle;
use super::assembly::cut_range;
use super::filter::{Filter, apply_all};

/// A rigid transform `p ↦ R·p + t`: a rotation, then a translation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigidTransform {
    /// Rotation matrix, row-major.
    pub rotation: [[f64; 3]; 3],
    /// Translation, metres.
    pub translation: [f64; 3],
}

impl RigidTransform {
    /// The identity.
    pub const IDENTITY: RigidTransform = RigidTransform {
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0; 3],
    };

    /// A translation, then `R = Rz(yaw) · Ry(pitch) · Rx(roll)` (radians): the convention of
    /// [`SensorMount`] and of nalgebra's `from_euler_angles`.
    pub fn from_xyz_rpy(translation: [f64; 3], roll: f64, pitch: f64, yaw: f64) -> Self {
        let (sr, cr) = roll.sin_cos();
        let (sp, cp) = pitch.sin_cos();
        let (sy, cy) = yaw.sin_cos();
        RigidTransform {
            rotation: [
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ],
            translation,
        }
    }

    /// A pose on the floor: at (x, y, 0), heading `yaw` (radians, counter-clockwise about z).
    pub fn planar(x: f64, y: f64, yaw: f64) -> Self {
        Self::from_xyz_rpy([x, y, 0.0], 0.0, 0.0, yaw)
    }

    /// A sensor's mount in `base` as the edge sends it (metres and degrees).
    pub fn from_sensor_mount(mount: &SensorMount) -> Self {
        Self::from_xyz_rpy(
            [mount.x_m, mount.y_m, mount.z_m],
            mount.roll_deg.to_radians(),
            mount.pitch_deg.to_radians(),
            mount.yaw_deg.to_radians(),
        )
    }

    /// `self ∘ inner`: first `inner`, then `self` (e.g. `room←base ∘ base←sensor`).
    pub fn compose(&self, inner: &RigidTransform) -> RigidTransform {
        let mut rotation = [[0.0; 3]; 3];
        for (i, row) in rotation.iter_mut().enumerate() {
            for (j, cell) in row.iter_mut().enumerate() {
                *cell = (0..3)
                    .map(|k| self.rotation[i][k] * inner.rotation[k][j])
                    .sum();
            }
        }
        RigidTransform {
            rotation,
            translation: self.transform_point(inner.translation),
        }
    }

    /// `R·v`.
    pub fn rotate(&self, v: [f64; 3]) -> [f64; 3] {
        self.rotation
            .map(|row| row[0] * v[0] + row[1] * v[1] + row[2] * v[2])
    }

    /// `R·p + t`.
    pub fn transform_point(&self, p: [f64; 3]) -> [f64; 3] {
        let r = self.rotate(p);
        [
            r[0] + self.translation[0],
            r[1] + self.translation[1],
            r[2] + self.translation[2],
        ]
    }

    /// Whether every entry is finite.
    pub fn is_finite(&self) -> bool {
        self.rotation.iter().flatten().all(|c| c.is_finite())
            && self.translation.iter().all(|c| c.is_finite())
    }
}

/// The pose of `base` in the room frame over time, on the samples' clock (edge ns).
pub trait BaseTrajectory {
    /// The first and last sample times (ns) the trajectory knows a pose for; `None` while empty.
    fn span_ns(&self) -> Option<(u64, u64)>;

    /// The pose of `base` in the room frame at `t_ns`. Called for times within
    /// [`BaseTrajectory::span_ns`], or outside it by at most the assembler's extrapolation
    /// tolerance (an implementation extrapolates there, or holds its end pose).
    fn base_pose_at(&self, t_ns: u64) -> RigidTransform;
}

/// A trajectory given by a closure over a known span (synthetic trajectories, adapters).
#[derive(Debug, Clone, Copy)]
pub struct FnTrajectory<F> {
    /// First and last known times, ns.
    pub span_ns: (u64, u64),
    /// The pose of `base` in the room frame at a time, ns.
    pub pose_at: F,
}

impl<F: Fn(u64) -> RigidTransform> BaseTrajectory for FnTrajectory<F> {
    fn span_ns(&self) -> Option<(u64, u64)> {
        Some(self.span_ns)
    }

    fn base_pose_at(&self, t_ns: u64) -> RigidTransform {
        (self.pose_at)(t_ns)
    }
}

/// One pose of a [`PlanarTrajectory`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectoryPoint {
    /// Sample time, ns (the samples' clock).
    pub t_ns: u64,
    /// x of `base` in the room frame, m.
    pub x_m: f64,
    /// y, m.
    pub y_m: f64,
    /// Heading of `base`'s x axis, radians counter-clockwise.
    pub yaw_rad: f64,
    /// Roll of `base`, radians (0 when only the 2D pose is known).
    pub roll_rad: f64,
    /// Pitch of `base`, radians (0 when only the 2D pose is known).
    pub pitch_rad: f64,
}

/// Why a pose cannot join a [`PlanarTrajectory`].
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum TrajectoryError {
    /// Its time is not after the last pose's.
    #[error("pose at {t_ns} ns is not after the last one at {last_ns} ns")]
    NotIncreasing {
        /// The rejected pose's time.
        t_ns: u64,
        /// The last pose's time.
        last_ns: u64,
    },
    /// A coordinate or angle is NaN or infinite.
    #[error("pose at {t_ns} ns has a non-finite value")]
    NotFinite {
        /// The rejected pose's time.
        t_ns: u64,
    },
}

/// Poses of `base` at increasing times, interpolated linearly between neighbours (yaw the
/// short way round) and extrapolated linearly from the end segments.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlanarTrajectory {
    points: Vec<TrajectoryPoint>,
}

impl PlanarTrajectory {
    /// An empty trajectory.
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends a pose; times must increase and values be finite.
    pub fn push(&mut self, point: TrajectoryPoint) -> Result<(), TrajectoryError> {
        let values = [
            point.x_m,
            point.y_m,
            point.yaw_rad,
            point.roll_rad,
            point.pitch_rad,
        ];
        if !values.iter().all(|v| v.is_finite()) {
            return Err(TrajectoryError::NotFinite { t_ns: point.t_ns });
        }
        if let Some(last) = self.points.last()
            && point.t_ns <= last.t_ns
        {
            return Err(TrajectoryError::NotIncreasing {
                t_ns: point.t_ns,
                last_ns: last.t_ns,
            });
        }
        self.points.push(point);
        Ok(())
    }

    /// The poses, in time order.
    pub fn points(&self) -> &[TrajectoryPoint] {
        &self.points
    }

    /// The pose at `t_ns` as (x, y, yaw, roll, pitch); `None` while empty.
    fn interpolate(&self, t_ns: u64) -> Option<[f64; 5]> {
        let (a, b) = match self.points.len() {
            0 => return None,
            1 => (self.points[0], self.points[0]),
            n => {
                // The segment holding t, or the end segment nearest to it.
                let i = self
                    .points
                    .partition_point(|p| p.t_ns <= t_ns)
                    .clamp(1, n - 1);
                (self.points[i - 1], self.points[i])
            }
        };
        let dt = b.t_ns.abs_diff(a.t_ns) as f64;
        let u = if dt > 0.0 {
            (t_ns as f64 - a.t_ns as f64) / dt
        } else {
            0.0
        };
        let lerp = |x: f64, y: f64| x + (y - x) * u;
        Some([
            lerp(a.x_m, b.x_m),
            lerp(a.y_m, b.y_m),
            a.yaw_rad + wrap_pi(b.yaw_rad - a.yaw_rad) * u,
            lerp(a.roll_rad, b.roll_rad),
            lerp(a.pitch_rad, b.pitch_rad),
        ])
    }
}

impl BaseTrajectory for PlanarTrajectory {
    fn span_ns(&self) -> Option<(u64, u64)> {
        Some((self.points.first()?.t_ns, self.points.last()?.t_ns))
    }

    fn base_pose_at(&self, t_ns: u64) -> RigidTransform {
        match self.interpolate(t_ns) {
            Some([x, y, yaw, roll, pitch]) => {
                RigidTransform::from_xyz_rpy([x, y, 0.0], roll, pitch, yaw)
            }
            None => RigidTransform::IDENTITY,
        }
    }
}

/// An angle in (−π, π].
fn wrap_pi(angle: f64) -> f64 {
    let wrapped = (angle + PI).rem_euclid(2.0 * PI) - PI;
    if wrapped <= -PI {
        wrapped + 2.0 * PI
    } else {
        wrapped
    }
}

/// One sample placed in the room frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedSample {
    /// Sample time, ns.
    pub t_ns: u64,
    /// The Sweep's optical centre at that time, room frame.
    pub origin: [f64; 3],
    /// The measured point, room frame.
    pub point: [f64; 3],
}

/// How many of one revolution's samples were placed, and why the others were not.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PlacementCounts {
    /// Samples placed.
    pub placed: u64,
    /// Samples without a return (range 0 or not finite): nothing to place.
    pub no_return: u64,
    /// Samples earlier than the trajectory's first pose by more than the tolerance: never
    /// placed (the trajectory does not grow backwards).
    pub before_span: u64,
    /// Samples later than the trajectory's last pose by more than the tolerance (or with no
    /// trajectory yet): not placed; a live stage waits for the poses instead ([`poses_cover`]).
    pub after_span: u64,
}

/// One revolution's samples placed, and how many were not.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Placement {
    /// The samples placed, in the revolution's order.
    pub samples: Vec<PlacedSample>,
    /// What was placed and what was not.
    pub counts: PlacementCounts,
}

/// Whether `trajectory` already knows the pose at every sample time of `rev`: a live stage
/// holds a revolution until this is true (or its watermark releases it) before placing it.
pub fn poses_cover(rev: &LidarRevolution, trajectory: &(impl BaseTrajectory + ?Sized)) -> bool {
    let last = rev.sample_times_ns().max().unwrap_or(rev.t0_ns);
    trajectory.span_ns().is_some_and(|(_, end)| end >= last)
}

/// Places each sample of one Sweep revolution with the pose of `base` at the sample's own
/// time and the Sweep's mount `base←sweep`; samples outside the trajectory's span by more than
/// `tolerance_ns` are counted, not placed.
pub fn place_revolution(
    rev: &LidarRevolution,
    trajectory: &(impl BaseTrajectory + ?Sized),
    mount: &RigidTransform,
    tolerance_ns: u64,
) -> Placement {
    let mut placement = Placement::default();
    let span = trajectory.span_ns();
    for (sample, t_ns) in rev.samples.iter().zip(rev.sample_times_ns()) {
        let range = f64::from(sample.range_m);
        if !(range.is_finite() && range > 0.0) {
            placement.counts.no_return += 1;
            continue;
        }
        match span {
            Some((first, _)) if t_ns < first.saturating_sub(tolerance_ns) => {
                placement.counts.before_span += 1;
                continue;
            }
            Some((_, last)) if t_ns <= last.saturating_add(tolerance_ns) => {}
            _ => {
                placement.counts.after_span += 1;
                continue;
            }
        }
        let sensor = trajectory.base_pose_at(t_ns).compose(mount);
        let alpha = f64::from(sample.angle_deg).to_radians();
        let beam = [range * alpha.cos(), range * alpha.sin(), 0.0];
        placement.samples.push(PlacedSample {
            t_ns,
            origin: sensor.translation,
            point: sensor.transform_point(beam),
        });
    }
    placement.counts.placed = placement.samples.len() as u64;
    placement
}

/// Groups consecutive placed samples into ray bundles: a bundle's origin is its first
/// sample's, and a sample whose own origin lies farther than `max_drift_m` from it opens the
/// next bundle (see the [module docs](self) for why a quarter voxel is enough).
pub fn bundle_by_origin(samples: &[PlacedSample], max_drift_m: f64) -> Vec<RayBundle> {
    let mut bundles: Vec<RayBundle> = Vec::new();
    for sample in samples {
        let point = sample.point.map(|c| c as f32);
        match bundles.last_mut() {
            Some(bundle) if distance(bundle.origin, sample.origin) <= max_drift_m => {
                bundle.points.push(point);
            }
            _ => bundles.push(RayBundle {
                origin: sample.origin,
                points: vec![point],
            }),
        }
    }
    bundles
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// How far a sample's own origin may drift from its bundle's, as a fraction of the voxel edge.
pub const DEFAULT_DRIFT_FRACTION: f64 = 0.25;

/// Default [`MovingSettings::extrapolation_tolerance_ns`]: 50 ms, to place the last samples of
/// a pass, measured after the last RPLidar pose. Extrapolating t = 50 ms from an end segment of
/// Δ = 100 ms (one pose per 10 Hz RPLidar revolution) errs by a·t·(Δ + t)/2 ≈ 2 mm at a pushed
/// trolley's 0.5 m/s² — a sixth of the default bundle drift.
pub const DEFAULT_EXTRAPOLATION_TOLERANCE_NS: u64 = 50_000_000;

/// How a [`MovingAssembler`] groups, limits and filters.
#[derive(Debug, Clone, PartialEq)]
pub struct MovingSettings {
    /// Largest distance of a sample's own origin from its bundle's origin, metres
    /// (default: [`DEFAULT_DRIFT_FRACTION`] of the octree's resolution).
    pub max_origin_drift_m: f64,
    /// How far outside the trajectory's span a sample is still placed (extrapolated), ns.
    pub extrapolation_tolerance_ns: u64,
    /// The kept cloud drops points farther than this from their origin (the octree's
    /// `max_range` applies to the bundles handed out); `None`: no limit.
    pub max_range_m: Option<f64>,
    /// Applied to each revolution's bundles together, in order (voxel grid, pass-through).
    pub filters: Vec<Filter>,
    /// Whether to keep the pass's cloud ([`MovingAssembler::cloud`]); a live map that keeps its
    /// own may turn it off.
    pub keep_cloud: bool,
}

impl MovingSettings {
    /// The defaults for an octree of `resolution_m`: bundles drift at most a quarter voxel,
    /// 50 ms of extrapolation, no range limit, no filters, the cloud kept.
    pub fn for_resolution(resolution_m: f64) -> Self {
        MovingSettings {
            max_origin_drift_m: resolution_m * DEFAULT_DRIFT_FRACTION,
            extrapolation_tolerance_ns: DEFAULT_EXTRAPOLATION_TOLERANCE_NS,
            max_range_m: None,
            filters: Vec::new(),
            keep_cloud: true,
        }
    }
}

/// Why a [`MovingAssembler`] cannot be made.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum MovingSettingsError {
    /// The origin drift is not a finite number ≥ 0.
    #[error("max_origin_drift_m = {0} is not a finite number >= 0")]
    Drift(f64),
    /// The range limit is not a finite number ≥ 0.
    #[error("max_range_m = {0} is not a finite number >= 0")]
    Range(f64),
    /// The mount has a non-finite entry.
    #[error("the Sweep's mount has a non-finite value")]
    Mount,
}

/// What a [`MovingAssembler`] has placed and dropped so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MovingTotals {
    /// Sweep revolutions taken.
    pub revolutions: u64,
    /// Samples placed.
    pub placed: u64,
    /// Samples without a return.
    pub no_return: u64,
    /// Samples before the trajectory's span (beyond the tolerance), not placed.
    pub before_span: u64,
    /// Samples after the trajectory's span (beyond the tolerance), not placed.
    pub after_span: u64,
    /// Points the filters removed.
    pub filtered_out: u64,
    /// Revolutions a filter failed on (their points dropped, logged).
    pub filter_failures: u64,
    /// Points dropped from the kept cloud by the range limit.
    pub range_cut: u64,
}

/// Assembles a pass: each Sweep revolution placed along the trajectory, filtered, handed out as
/// ray bundles for the octree and kept as the pass's cloud (see the [module docs](self)).
#[derive(Debug)]
pub struct MovingAssembler {
    mount: RigidTransform,
    settings: MovingSettings,
    cloud: Vec<RayBundle>,
    new: Vec<RayBundle>,
    totals: MovingTotals,
}

impl MovingAssembler {
    /// An assembler for a Sweep mounted at `mount` (`base←sweep`).
    pub fn new(
        mount: RigidTransform,
        settings: MovingSettings,
    ) -> Result<Self, MovingSettingsError> {
        let drift = settings.max_origin_drift_m;
        if !(drift.is_finite() && drift >= 0.0) {
            return Err(MovingSettingsError::Drift(drift));
        }
        if let Some(range) = settings.max_range_m
            && !(range.is_finite() && range >= 0.0)
        {
            return Err(MovingSettingsError::Range(range));
        }
        if !mount.is_finite() {
            return Err(MovingSettingsError::Mount);
        }
        Ok(MovingAssembler {
            mount,
            settings,
            cloud: Vec::new(),
            new: Vec::new(),
            totals: MovingTotals::default(),
        })
    }

    /// Places one revolution along `trajectory` (other sensors' revolutions are ignored and
    /// give an empty placement's counts); returns its counts. Samples outside the trajectory's
    /// span are counted and dropped: call once [`poses_cover`] holds or the stage gives up
    /// waiting.
    pub fn add_revolution(
        &mut self,
        rev: &LidarRevolution,
        trajectory: &(impl BaseTrajectory + ?Sized),
    ) -> PlacementCounts {
        if rev.sensor != SensorId::SWEEP {
            return PlacementCounts::default();
        }
        let placement = place_revolution(
            rev,
            trajectory,
            &self.mount,
            self.settings.extrapolation_tolerance_ns,
        );
        let counts = placement.counts;
        let totals = &mut self.totals;
        totals.revolutions += 1;
        totals.placed += counts.placed;
        totals.no_return += counts.no_return;
        totals.before_span += counts.before_span;
        totals.after_span += counts.after_span;
        let bundles = bundle_by_origin(&placement.samples, self.settings.max_origin_drift_m);
        let bundles = match apply_all(&self.settings.filters, bundles) {
            Ok(filtered) => filtered,
            Err(e) => {
                totals.filter_failures += 1;
                totals.filtered_out += counts.placed;
                tracing::warn!(
                    t0_ns = rev.t0_ns,
                    points = counts.placed,
                    "revolution filter failed, the revolution's points are dropped: {e}"
                );
                return counts;
            }
        };
        let kept: u64 = bundles.iter().map(|b| b.points.len() as u64).sum();
        totals.filtered_out += counts.placed.saturating_sub(kept);
        let bundles: Vec<RayBundle> = bundles
            .into_iter()
            .filter(|b| !b.points.is_empty())
            .collect();
        if self.settings.keep_cloud {
            let mut cut = bundles.clone();
            if let Some(max_range) = self.settings.max_range_m {
                totals.range_cut += cut_range(&mut cut, max_range) as u64;
            }
            self.cloud
                .extend(cut.into_iter().filter(|b| !b.points.is_empty()));
        }
        self.new.extend(bundles);
        counts
    }

    /// The bundles completed since the last call, for octree insertion (filtered, not cut by
    /// range: the octree's `max_range` keeps their free space up to the limit).
    pub fn take_new(&mut self) -> Vec<RayBundle> {
        std::mem::take(&mut self.new)
    }

    /// The pass's cloud so far (filtered, range-cut), one bundle per origin.
    pub fn cloud(&self) -> &[RayBundle] {
        &self.cloud
    }

    /// The pass's cloud.
    pub fn finish(self) -> Vec<RayBundle> {
        self.cloud
    }

    /// What was placed and dropped so far.
    pub fn totals(&self) -> MovingTotals {
        self.totals
    }

    /// The settings in use.
    pub fn settings(&self) -> &MovingSettings {
        &self.settings
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::FRAC_PI_2;

    use scan3d_protocol::{Body, MountInfo, StaticScan, StaticScanStart, StaticScanYaws, YawRun};

    use super::*;
    use crate::cloud::assembly::StaticScanAssembler;

    /// The rig's Sweep on the trolley: 0.2 m behind the reference point, 1 m up, pitch −90°.
    fn trolley_mount() -> RigidTransform {
        RigidTransform::from_sensor_mount(&SensorMount {
            sensor: SensorId::SWEEP,
            x_m: -0.2,
            y_m: 0.0,
            z_m: 1.0,
            roll_deg: 0.0,
            pitch_deg: -90.0,
            yaw_deg: 0.0,
        })
    }

    /// The room: walls at x = 0 and 8, y = 0 and 6, floor z = 0, ceiling z = 3.
    const ROOM_MIN: [f64; 3] = [0.0, 0.0, 0.0];
    const ROOM_MAX: [f64; 3] = [8.0, 6.0, 3.0];

    /// Range from `origin` (inside the room) along the unit `direction` to the first wall.
    fn cast(origin: [f64; 3], direction: [f64; 3]) -> f64 {
        (0..3)
            .filter_map(|i| {
                let d = direction[i];
                if d > 1e-12 {
                    Some((ROOM_MAX[i] - origin[i]) / d)
                } else if d < -1e-12 {
                    Some((ROOM_MIN[i] - origin[i]) / d)
                } else {
                    None
                }
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Distance of `p` to the nearest of the room's six planes.
    fn off_the_walls(p: [f64; 3]) -> f64 {
        (0..3)
            .flat_map(|i| [(p[i] - ROOM_MIN[i]).abs(), (p[i] - ROOM_MAX[i]).abs()])
            .fold(f64::INFINITY, f64::min)
    }

    const T0_NS: u64 = 1_000_000_000;
    const SPEED_M_S: f64 = 0.5;
    /// The rig's Sweep: 5 Hz, 550 samples/s → 110 samples per revolution.
    const SAMPLES_PER_REVOLUTION: u64 = 110;
    const SAMPLE_PERIOD_NS: u64 = 1_000_000_000 / 550;

    fn seconds(t_ns: u64) -> f64 {
        (t_ns as f64 - T0_NS as f64) * 1e-9
    }

    /// Along y = 3 at 0.5 m/s, heading +x.
    fn straight(t_ns: u64) -> RigidTransform {
        RigidTransform::planar(1.0 + SPEED_M_S * seconds(t_ns), 3.0, 0.0)
    }

    /// A left turn on a circle of 1.5 m about (4, 3) at 0.5 m/s, with a small roll and pitch
    /// from floor bumps.
    fn turning(t_ns: u64) -> RigidTransform {
        let s = seconds(t_ns);
        let angle = SPEED_M_S / 1.5 * s;
        RigidTransform::from_xyz_rpy(
            [4.0 + 1.5 * angle.cos(), 3.0 + 1.5 * angle.sin(), 0.0],
            0.02 * (7.0 * s).sin(),
            0.015 * (5.0 * s).cos(),
            angle + FRAC_PI_2,
        )
    }

    /// One Sweep revolution starting at `t0_ns`, each sample's range cast from the true pose of
    /// the Sweep at its own time.
    fn revolution_from(truth: impl Fn(u64) -> RigidTransform, t0_ns: u64) -> LidarRevolution {
        let n = SAMPLES_PER_REVOLUTION;
        let mut rev = LidarRevolution::new(SensorId::SWEEP, t0_ns, t0_ns + n * SAMPLE_PERIOD_NS);
        for k in 0..n {
            let t = t0_ns + k * SAMPLE_PERIOD_NS;
            let azimuth = (k as f64 * 360.0 / n as f64) as f32;
            let sensor = truth(t).compose(&trolley_mount());
            let a = f64::from(azimuth).to_radians();
            let range = cast(sensor.translation, sensor.rotate([a.cos(), a.sin(), 0.0]));
            rev.push(azimuth, range as f32, 100, t).unwrap();
        }
        rev
    }

    /// The exact wall point of each sample, from its true pose.
    fn truth_points(truth: impl Fn(u64) -> RigidTransform, rev: &LidarRevolution) -> Vec<[f64; 3]> {
        rev.samples
            .iter()
            .zip(rev.sample_times_ns())
            .map(|(s, t)| {
                let sensor = truth(t).compose(&trolley_mount());
                let a = f64::from(s.angle_deg).to_radians();
                let d = sensor.rotate([a.cos(), a.sin(), 0.0]);
                let l = cast(sensor.translation, d);
                std::array::from_fn(|i| sensor.translation[i] + l * d[i])
            })
            .collect()
    }

    fn known(pose: fn(u64) -> RigidTransform) -> FnTrajectory<fn(u64) -> RigidTransform> {
        FnTrajectory {
            span_ns: (0, u64::MAX),
            pose_at: pose,
        }
    }

    fn distance3(a: [f64; 3], b: [f64; 3]) -> f64 {
        distance(a, b)
    }

    #[test]
    fn the_trolley_mount_puts_azimuth_zero_up_and_ninety_to_the_left_with_the_spin_axis_backwards()
    {
        let mount = trolley_mount();
        let close = |a: [f64; 3], b: [f64; 3]| distance3(a, b) < 1e-12;
        assert!(close(mount.rotate([1.0, 0.0, 0.0]), [0.0, 0.0, 1.0]));
        assert!(close(mount.rotate([0.0, 1.0, 0.0]), [0.0, 1.0, 0.0]));
        assert!(close(mount.rotate([0.0, 0.0, 1.0]), [-1.0, 0.0, 0.0]));
        assert!(close(mount.translation, [-0.2, 0.0, 1.0]));
        // R = Rz(yaw)·Ry(pitch)·Rx(roll): composing the three single rotations gives the same.
        let (roll, pitch, yaw) = (0.3, -0.7, 2.1);
        let composed = RigidTransform::from_xyz_rpy([0.0; 3], 0.0, 0.0, yaw)
            .compose(&RigidTransform::from_xyz_rpy([0.0; 3], 0.0, pitch, 0.0))
            .compose(&RigidTransform::from_xyz_rpy([0.0; 3], roll, 0.0, 0.0));
        let direct = RigidTransform::from_xyz_rpy([0.0; 3], roll, pitch, yaw);
        for (a, b) in composed
            .rotation
            .iter()
            .flatten()
            .zip(direct.rotation.iter().flatten())
        {
            assert!((a - b).abs() < 1e-12);
        }
        // Rx(roll) turns y towards z.
        let rolled = RigidTransform::from_xyz_rpy([0.0; 3], FRAC_PI_2, 0.0, 0.0);
        assert!(close(rolled.rotate([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]));
    }

    /// Places one revolution of `truth` both ways and returns (worst error with each sample's own
    /// pose, the naive placements with the revolution's start pose, the true points).
    fn own_time_and_naive(
        truth: fn(u64) -> RigidTransform,
    ) -> (f64, Vec<PlacedSample>, Vec<[f64; 3]>) {
        let t0 = T0_NS + 300_000_000;
        let rev = revolution_from(truth, t0);
        let exact = truth_points(truth, &rev);
        let placed = place_revolution(&rev, &known(truth), &trolley_mount(), 0);
        assert_eq!(placed.counts.placed, SAMPLES_PER_REVOLUTION);
        let mut worst: f64 = 0.0;
        for (p, want) in placed.samples.iter().zip(&exact) {
            worst = worst.max(distance3(p.point, *want));
            assert!(
                off_the_walls(p.point) < 1e-5,
                "{:?} is off the walls",
                p.point
            );
            let sensor_origin = truth(p.t_ns).compose(&trolley_mount()).translation;
            assert!(distance3(p.origin, sensor_origin) < 1e-12);
        }
        let start = FnTrajectory {
            span_ns: (0, u64::MAX),
            pose_at: move |_| truth(t0),
        };
        let naive = place_revolution(&rev, &start, &trolley_mount(), 0).samples;
        (worst, naive, exact)
    }

    #[test]
    fn moving_samples_placed_at_their_own_time_land_on_the_walls_on_a_straight_line() {
        let (worst, naive, exact) = own_time_and_naive(straight);
        assert!(worst < 1e-5, "worst {worst} m");
        // The naive way: every point is off by speed × (t − t0), along the direction of travel.
        let t0 = naive[0].t_ns;
        let mut naive_worst: f64 = 0.0;
        for (p, want) in naive.iter().zip(&exact) {
            let lag = SPEED_M_S * (p.t_ns - t0) as f64 * 1e-9;
            assert!((want[0] - p.point[0] - lag).abs() < 1e-5, "{p:?} {want:?}");
            assert!((want[1] - p.point[1]).abs() < 1e-5);
            assert!((want[2] - p.point[2]).abs() < 1e-5);
            naive_worst = naive_worst.max(distance3(p.point, *want));
        }
        // 109 sample periods of 1/550 s at 0.5 m/s: 9.9 cm.
        assert!(
            (naive_worst - 0.5 * 109.0 / 550.0).abs() < 1e-5,
            "{naive_worst}"
        );
    }

    #[test]
    fn moving_samples_placed_at_their_own_time_land_on_the_walls_in_a_turn() {
        let (worst, naive, exact) = own_time_and_naive(turning);
        assert!(worst < 1e-5, "worst {worst} m");
        let naive_worst = naive
            .iter()
            .zip(&exact)
            .map(|(p, want)| distance3(p.point, *want))
            .fold(0.0, f64::max);
        // The Sweep moves ≈ 10 cm and turns ≈ 3.8° in the revolution: the naive way is off by
        // centimetres.
        assert!(naive_worst > 0.05, "naive worst {naive_worst} m");
    }

    #[test]
    fn moving_bundles_split_when_the_origin_drifts_a_quarter_voxel() {
        let rev = revolution_from(straight, T0_NS);
        let placed = place_revolution(&rev, &known(straight), &trolley_mount(), 0);
        let drift = 0.05 * DEFAULT_DRIFT_FRACTION;
        let bundles = bundle_by_origin(&placed.samples, drift);
        // The origin moves 0.5/550 m per sample: 14 samples span 13 × 0.91 mm = 11.8 mm ≤ 12.5 mm,
        // the 15th would be 12.7 mm away.
        let sizes: Vec<usize> = bundles.iter().map(|b| b.points.len()).collect();
        assert_eq!(sizes, [14, 14, 14, 14, 14, 14, 14, 12]);
        // Each bundle's origin is its first sample's, every member's within the drift, and the
        // sample opening the next bundle is beyond it.
        let mut next = 0;
        for bundle in &bundles {
            let members = &placed.samples[next..next + bundle.points.len()];
            assert_eq!(bundle.origin, members[0].origin);
            assert!(
                members
                    .iter()
                    .all(|s| distance3(s.origin, bundle.origin) <= drift)
            );
            for (point, sample) in bundle.points.iter().zip(members) {
                assert_eq!(*point, sample.point.map(|c| c as f32));
            }
            next += members.len();
            if let Some(opening) = placed.samples.get(next) {
                assert!(distance3(opening.origin, bundle.origin) > drift);
            }
        }
        // At 0.2 m/s: 35 samples per bundle, four bundles per revolution.
        let slow = |t_ns| RigidTransform::planar(1.0 + 0.2 * seconds(t_ns), 3.0, 0.0);
        let rev = revolution_from(slow, T0_NS);
        let trajectory = FnTrajectory {
            span_ns: (0, u64::MAX),
            pose_at: slow,
        };
        let placed = place_revolution(&rev, &trajectory, &trolley_mount(), 0);
        let sizes: Vec<usize> = bundle_by_origin(&placed.samples, drift)
            .iter()
            .map(|b| b.points.len())
            .collect();
        assert_eq!(sizes, [35, 35, 35, 5]);
        // Standing still: one bundle per revolution.
        let still = |_| RigidTransform::planar(4.0, 3.0, 0.3);
        let rev = revolution_from(still, T0_NS);
        let trajectory = FnTrajectory {
            span_ns: (0, u64::MAX),
            pose_at: still,
        };
        let placed = place_revolution(&rev, &trajectory, &trolley_mount(), 0);
        assert_eq!(bundle_by_origin(&placed.samples, drift).len(), 1);
        // The assembler groups the same way and hands each bundle out once.
        let mut assembler =
            MovingAssembler::new(trolley_mount(), MovingSettings::for_resolution(0.05)).unwrap();
        let rev = revolution_from(straight, T0_NS);
        let counts = assembler.add_revolution(&rev, &known(straight));
        assert_eq!(counts.placed, SAMPLES_PER_REVOLUTION);
        assert_eq!(assembler.take_new().len(), 8);
        assert!(assembler.take_new().is_empty());
        assert_eq!(assembler.cloud().len(), 8);
    }

    /// The straight line sampled like the pose stage's output: one pose every 100 ms over
    /// `[T0, T0 + 100 ms × (n − 1)]`.
    fn rplidar_poses(n: u64) -> PlanarTrajectory {
        let mut trajectory = PlanarTrajectory::new();
        for k in 0..n {
            let t_ns = T0_NS + k * 100_000_000;
            trajectory
                .push(TrajectoryPoint {
                    t_ns,
                    x_m: 1.0 + SPEED_M_S * seconds(t_ns),
                    y_m: 3.0,
                    yaw_rad: 0.0,
                    roll_rad: 0.0,
                    pitch_rad: 0.0,
                })
                .unwrap();
        }
        trajectory
    }

    #[test]
    fn moving_samples_outside_the_trajectory_span_are_counted_not_placed() {
        let n = SAMPLES_PER_REVOLUTION;
        // Poses over [T0, T0 + 100 ms]; the revolution runs over [T0 − 50 ms, T0 + 150 ms].
        let trajectory = rplidar_poses(2);
        let rev = revolution_from(straight, T0_NS - 50_000_000);
        let before = (0..n).filter(|k| k * SAMPLE_PERIOD_NS < 50_000_000).count() as u64;
        let after = (0..n)
            .filter(|k| k * SAMPLE_PERIOD_NS > 150_000_000)
            .count() as u64;
        assert!(!poses_cover(&rev, &trajectory));
        let strict = place_revolution(&rev, &trajectory, &trolley_mount(), 0);
        assert_eq!(strict.counts.before_span, before);
        assert_eq!(strict.counts.after_span, after);
        assert_eq!(strict.counts.placed, n - before - after);
        assert!(
            strict
                .samples
                .iter()
                .all(|s| (T0_NS..=T0_NS + 100_000_000).contains(&s.t_ns))
        );
        // Within the tolerance the samples are placed, extrapolated (exact on a straight line).
        let tolerant = place_revolution(&rev, &trajectory, &trolley_mount(), 20_000_000);
        let far_before = (0..n).filter(|k| k * SAMPLE_PERIOD_NS < 30_000_000).count() as u64;
        let far_after = (0..n)
            .filter(|k| k * SAMPLE_PERIOD_NS > 170_000_000)
            .count() as u64;
        assert_eq!(tolerant.counts.before_span, far_before);
        assert_eq!(tolerant.counts.after_span, far_after);
        let exact = truth_points(straight, &rev);
        let first = usize::try_from(far_before).unwrap();
        for (p, want) in tolerant.samples.iter().zip(&exact[first..]) {
            assert!(distance3(p.point, *want) < 1e-5, "{p:?} {want:?}");
        }
        // Once the poses reach the revolution's last sample, everything is placed.
        let later = rplidar_poses(3);
        let earlier_start = revolution_from(straight, T0_NS);
        assert!(poses_cover(&earlier_start, &later));
        let all = place_revolution(&earlier_start, &later, &trolley_mount(), 0);
        assert_eq!(all.counts.placed, n);
        // No trajectory yet: nothing placed, everything waits.
        let none = place_revolution(&rev, &PlanarTrajectory::new(), &trolley_mount(), 1_000);
        assert_eq!((none.counts.placed, none.counts.after_span), (0, n));
        assert!(!poses_cover(&rev, &PlanarTrajectory::new()));
        // The assembler adds them up.
        let mut assembler =
            MovingAssembler::new(trolley_mount(), MovingSettings::for_resolution(0.05)).unwrap();
        assembler.add_revolution(&rev, &trajectory);
        let totals = assembler.totals();
        let tolerance = DEFAULT_EXTRAPOLATION_TOLERANCE_NS;
        assert_eq!(tolerance, 50_000_000);
        let edge_before = (0..n)
            .filter(|k| k * SAMPLE_PERIOD_NS + tolerance < 50_000_000)
            .count();
        assert_eq!(totals.before_span, edge_before as u64);
        assert_eq!(
            totals.placed + totals.before_span + totals.after_span + totals.no_return,
            n
        );
    }

    #[test]
    fn planar_trajectory_interpolates_yaw_the_short_way_and_refuses_bad_poses() {
        let mut trajectory = PlanarTrajectory::new();
        let pose = |t_ns, yaw_rad| TrajectoryPoint {
            t_ns,
            x_m: 0.0,
            y_m: 0.0,
            yaw_rad,
            roll_rad: 0.0,
            pitch_rad: 0.0,
        };
        trajectory.push(pose(100, 3.1)).unwrap();
        trajectory.push(pose(200, -3.1)).unwrap();
        let mid = trajectory.base_pose_at(150);
        // Half way from 3.1 to −3.1 the short way is π, pointing along −x.
        let heading = mid.rotate([1.0, 0.0, 0.0]);
        assert!((heading[0] + 1.0).abs() < 1e-9, "{heading:?}");
        assert_eq!(
            trajectory.push(pose(200, 0.0)),
            Err(TrajectoryError::NotIncreasing {
                t_ns: 200,
                last_ns: 200
            })
        );
        assert_eq!(
            trajectory.push(pose(300, f64::NAN)),
            Err(TrajectoryError::NotFinite { t_ns: 300 })
        );
        assert_eq!(trajectory.span_ns(), Some((100, 200)));
    }

    #[test]
    fn moving_assembler_applies_the_range_cut_to_its_cloud_and_the_filters_to_both() {
        let rev = revolution_from(straight, T0_NS);
        let settings = MovingSettings {
            max_range_m: Some(2.5),
            ..MovingSettings::for_resolution(0.05)
        };
        let mut assembler = MovingAssembler::new(trolley_mount(), settings).unwrap();
        assembler.add_revolution(&rev, &known(straight));
        let new = assembler.take_new();
        let all: usize = new.iter().map(|b| b.points.len()).sum();
        assert_eq!(
            all as u64, SAMPLES_PER_REVOLUTION,
            "the octree's bundles are not cut"
        );
        let cloud: usize = assembler.cloud().iter().map(|b| b.points.len()).sum();
        let far = new
            .iter()
            .flat_map(|b| {
                b.points
                    .iter()
                    .map(move |p| distance3(p.map(f64::from), b.origin))
            })
            .filter(|d| *d > 2.5)
            .count();
        assert!(far > 0 && far < all, "{far} of {all} beyond 2.5 m");
        assert_eq!(cloud, all - far);
        assert_eq!(assembler.totals().range_cut, far as u64);
        // A pass-through box keeping the floor's neighbourhood only, applied before both.
        let settings = MovingSettings {
            filters: vec!["box:-10,-10,-0.5,10,10,0.5".parse().unwrap()],
            ..MovingSettings::for_resolution(0.05)
        };
        let mut assembler = MovingAssembler::new(trolley_mount(), settings).unwrap();
        assembler.add_revolution(&rev, &known(straight));
        let new = assembler.take_new();
        assert!(new.iter().flat_map(|b| &b.points).all(|p| p[2] <= 0.5));
        let kept: usize = new.iter().map(|b| b.points.len()).sum();
        assert!(kept > 0 && (kept as u64) < SAMPLES_PER_REVOLUTION);
        assert_eq!(
            assembler.totals().filtered_out,
            SAMPLES_PER_REVOLUTION - kept as u64
        );
        // Other sensors' revolutions are not Sweep samples.
        let mut rplidar = rev.clone();
        rplidar.sensor = SensorId::RPLIDAR;
        assert_eq!(
            assembler.add_revolution(&rplidar, &known(straight)),
            PlacementCounts::default()
        );
        // Settings that cannot work are refused.
        let bad = MovingSettings {
            max_origin_drift_m: f64::NAN,
            ..MovingSettings::for_resolution(0.05)
        };
        assert!(MovingAssembler::new(trolley_mount(), bad).is_err());
        let mut mount = trolley_mount();
        mount.translation[2] = f64::INFINITY;
        assert_eq!(
            MovingAssembler::new(mount, MovingSettings::for_resolution(0.05)).err(),
            Some(MovingSettingsError::Mount)
        );
    }

    /// splitmix64: a seeded stream of uniform numbers for the property test.
    struct Random(u64);

    impl Random {
        fn next(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            (z ^ (z >> 31)) as f64 / u64::MAX as f64
        }

        fn within(&mut self, lo: f64, hi: f64) -> f64 {
            lo + (hi - lo) * self.next()
        }
    }

    #[test]
    fn moving_assembly_with_a_constant_trajectory_is_the_static_equation_one() {
        let mut random = Random(21);
        for case in 0..300 {
            let (x, y) = (random.within(-5.0, 5.0), random.within(-5.0, 5.0));
            let heading = random.within(-180.0, 180.0);
            let mount = MountInfo {
                axis_offset_m: random.within(-0.2, 0.2),
                height_m: random.within(0.0, 2.0),
                azimuth_zero_deg: random.within(0.0, 360.0),
            };
            let yaw = random.within(0.0, 180.0) as f32;
            let t0 = 1_000 + case * 1_000_000_000;
            let mut rev = LidarRevolution::new(SensorId::SWEEP, t0, t0 + 200_000_000);
            for k in 0..40u64 {
                let range = if random.next() < 0.1 {
                    0.0
                } else {
                    random.within(0.1, 10.0)
                };
                let azimuth = random.within(0.0, 360.0);
                rev.push(azimuth as f32, range as f32, 50, t0 + k * 5_000_000)
                    .unwrap();
            }
            // The reference: the static path, fed the frames of a one-run static scan.
            let mut reference = StaticScanAssembler::new();
            reference.on_body(&Body::StaticScan(StaticScan::Started(StaticScanStart {
                scan_id: 0,
                t_ns: t0,
                position: "p".into(),
                x_m: x,
                y_m: y,
                heading_deg: heading,
                step_deg: 1.8,
                total_deg: 180.0,
                blocked_sector_deg: 0.0,
                mount,
            })));
            reference.on_body(&Body::StaticScan(StaticScan::Yaws(StaticScanYaws {
                scan_id: 0,
                revolution_t0_ns: t0,
                runs: vec![YawRun {
                    first_index: 0,
                    count: 40,
                    yaw_deg: yaw,
                }],
            })));
            reference.on_body(&Body::Revolution(rev.clone()));
            let scan = &reference.scans()[0];
            // The same as a pose of `base` (the turntable's yaw folded into its heading) and a
            // mount: optical centre at (offset, 0, height), Ry(−90°) standing the plane up,
            // Rz(−azimuth_zero) turning the device's azimuth into θ.
            let phi = (heading + f64::from(yaw)).to_radians();
            let still = move |_| RigidTransform::planar(x, y, phi);
            let sweep = RigidTransform::from_xyz_rpy(
                [mount.axis_offset_m, 0.0, mount.height_m],
                0.0,
                -FRAC_PI_2,
                0.0,
            )
            .compose(&RigidTransform::from_xyz_rpy(
                [0.0; 3],
                0.0,
                0.0,
                -mount.azimuth_zero_deg.to_radians(),
            ));
            let trajectory = FnTrajectory {
                span_ns: (t0, t0 + 200_000_000),
                pose_at: still,
            };
            let mut assembler =
                MovingAssembler::new(sweep, MovingSettings::for_resolution(0.05)).unwrap();
            let counts = assembler.add_revolution(&rev, &trajectory);
            assert_eq!(counts.no_return, scan.no_return, "case {case}");
            let moving = assembler.take_new();
            assert_eq!(moving.len(), scan.scans.len(), "case {case}");
            for (got, want) in moving.iter().zip(&scan.scans) {
                assert!(distance3(got.origin, want.origin) < 1e-9, "case {case}");
                assert_eq!(got.points.len(), want.points.len(), "case {case}");
                for (p, q) in got.points.iter().zip(&want.points) {
                    let d = distance3(p.map(f64::from), q.map(f64::from));
                    assert!(d < 1e-5, "case {case}: {p:?} against eq. 1's {q:?}");
                }
            }
        }
    }
}
