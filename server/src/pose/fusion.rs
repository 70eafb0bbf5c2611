//! The covariance-intersection yaw fusion's session adapter: a session's IMU samples (the edge's
//! Madgwick quaternion, the gyro, the magnetometer) and the matcher's poses of `base` in, each
//! pose's fused yaw, its variance and the roll and pitch of `base` out (`slam::fusion` does the
//! fusion itself; this joins it to the session's values). Pure: values in, values out.
//!
//! - **Madgwick yaw of `base`.** The edge's quaternion rotates IMU vectors into the earth frame
//!   (NWU); the IMU's mount (`Body::Mounts`, rotation IMU → base `Rz(yaw) Ry(pitch) Rx(roll)`)
//!   turns it into `base`'s: `q_base = q_imu ⊗ q_mount⁻¹`, whose yaw, roll and pitch are
//!   `base`'s. The constant between that yaw and the matcher's frame (magnetic north in the map
//!   plus what the mount leaves) is estimated by [`YawFuser`] over the first seconds.
//! - **Variance.** [`scan3d_slam::fusion::MadgwickVariance`]: the field's magnitude and dip
//!   (the magnetometer against the up axis of the IMU's quaternion) against a reference, the
//!   mean of the first seconds at rest unless configured.
//! - **Time.** Both streams are joined by edge sample time (`t_ns`), never by arrival: the
//!   caller feeds each stream in its own time order, in any interleaving, and says how far the
//!   IMU stream has certainly come ([`PoseFusion::advance_to`]).
//! - **Without Madgwick** (the edge runs no filter: no `orientation`) or when the IMU stops, a
//!   pose is the matcher's alone, logged once per stop; the poses keep coming.
//!
//! For Fig. 5 each pose keeps every source's yaw ([`YawSources`]): the gyro integrated alone
//! (the rate about `base`'s z from the first pose on, no bias correction), Madgwick (aligned),
//! the matcher, the fusion.
//!
//! The edge's Madgwick is used as it comes. Running the filter on the server instead would make
//! replay independent of the edge's filter version and settings and let the variance model
//! know β and the rate for sure; it needs the filter in a crate both may use (it is in
//! `scan3d-edge`, which the server must not depend on): left for later.

use std::collections::VecDeque;

use nalgebra::UnitQuaternion;
use serde::Serialize;

use scan3d_protocol::{ImuSample, SensorId, SensorMounts};
use scan3d_slam::fusion::{
    FusedYaw, FuserConfig, FusionError, FusionNotice, MadgwickUncertainty, MadgwickYaw,
    MagneticField, MatcherOnlyReason, MatcherYaw, YawFuser, YawSource, up_in_sensor_frame,
};
use scan3d_slam::pose::wrap_angle;

/// The MPU-9250's gyro noise density (rad/s/√Hz), as the pose stage's gyro prior takes it.
const GYRO_NOISE_DENSITY: f64 = scan3d_slam::fusion::MPU9250_GYRO_NOISE_DENSITY;

/// The gyro's zero-rate offset never measured (rad/s): the datasheet's ±5 °/s as one σ; the
/// gyro-alone yaw of Fig. 5 is not corrected for it.
const GYRO_BIAS_UNMEASURED: f64 = 5.0 * std::f64::consts::PI / 180.0;

/// IMU history kept for the gyro-alone yaw and the attitude (s behind the newest sample).
const HISTORY_S: f64 = 4.0;

/// Samples kept at most whatever their times (4 s at 1 kHz).
const MAX_HISTORY: usize = 4096;

/// Matcher poses waiting for the IMU at most; beyond, the oldest goes out unfused.
const MAX_PENDING: usize = 1024;

/// The longest IMU gap (s) the gyro-alone yaw integrates over; a longer one stops it.
const GYRO_MAX_GAP_S: f64 = 0.2;

/// A quaternion `[w, x, y, z]`, as the wire carries the edge's orientation.
type Quaternion = [f64; 4];

/// `q` as nalgebra's unit quaternion (normalised).
fn unit(q: Quaternion) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// Roll, pitch, yaw (rad) of `q` read as `Rz(yaw) Ry(pitch) Rx(roll)`.
pub fn euler_from_quaternion(q: Quaternion) -> [f64; 3] {
    let (roll, pitch, yaw) = unit(q).euler_angles();
    [roll, pitch, wrap_angle(yaw)]
}

/// One matcher pose's yaw as the adapter takes it (the session's frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatcherPoseYaw {
    /// The pose's time, edge ns.
    pub t_ns: u64,
    /// Yaw of `base`, rad, counter-clockwise.
    pub yaw: f64,
    /// Its variance, rad².
    pub variance: f64,
}

/// Every source's yaw at one matcher pose (the session's frame, rad and rad²): what Fig. 5 and
/// `yaw_sources.csv` show.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct YawSources {
    /// The pose's time, edge ns.
    pub t_ns: u64,
    /// The matcher's yaw and variance.
    pub matcher: f64,
    /// rad².
    pub matcher_variance: f64,
    /// Madgwick's yaw of `base`, aligned to the matcher's frame (once aligned, with samples).
    pub madgwick: Option<f64>,
    /// Its modelled variance, alignment included.
    pub madgwick_variance: Option<f64>,
    /// The gyro integrated alone from the first pose's matcher yaw (no bias correction).
    pub gyro: Option<f64>,
    /// Its variance: angle random walk plus the unmeasured bias over the time integrated.
    pub gyro_variance: Option<f64>,
    /// The fused yaw (the matcher's when unfused) and its variance.
    pub fused: f64,
    /// rad².
    pub fused_variance: f64,
    /// The weight on the matcher's information, when fused.
    pub omega: Option<f64>,
}

/// Why a pose is the matcher's alone (the status's and the CSV's words).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum UnfusedReason {
    /// The edge sends no Madgwick orientation.
    NoOrientation,
    /// The frames' alignment is still being estimated (the first seconds).
    Aligning,
    /// No Madgwick sample near the pose (the IMU stopped, or a gap).
    NoImuNearby,
    /// The matcher's pose defines the frame (variance 0).
    ExactMatcher,
    /// The field reference is not known yet.
    VarianceUnknown,
}

impl UnfusedReason {
    /// The reason as one word.
    pub fn as_str(&self) -> &'static str {
        match self {
            UnfusedReason::NoOrientation => "no_orientation",
            UnfusedReason::Aligning => "aligning",
            UnfusedReason::NoImuNearby => "no_imu_nearby",
            UnfusedReason::ExactMatcher => "exact_matcher",
            UnfusedReason::VarianceUnknown => "variance_unknown",
        }
    }
}

/// One pose's outcome.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedPoseYaw {
    /// The pose's time, edge ns.
    pub t_ns: u64,
    /// The yaw to report (fused or the matcher's), rad, and its variance, rad².
    pub yaw: f64,
    /// rad².
    pub variance: f64,
    /// The matcher's yaw, to scale the yaw's cross covariances by.
    pub matcher_variance: f64,
    /// Roll and pitch of `base` (rad) from the IMU's quaternion at the pose's time.
    pub roll_pitch: Option<[f64; 2]>,
    /// `None`: fused; else why not.
    pub unfused: Option<UnfusedReason>,
    /// Every source's yaw.
    pub sources: YawSources,
}

/// How many poses were fused and how many not, by reason (`scan3d status`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FusionCounts {
    /// Poses fused.
    pub fused: u64,
    /// Poses that are the matcher's alone.
    pub matcher_only: u64,
    /// ...because the edge sends no Madgwick orientation.
    pub no_orientation: u64,
    /// ...while the alignment was estimated.
    pub aligning: u64,
    /// ...with no IMU sample near.
    pub no_imu_nearby: u64,
    /// ...the frame-defining first pose (or a zero variance).
    pub exact_matcher: u64,
    /// ...before the field reference was known.
    pub variance_unknown: u64,
    /// Times the IMU stopped (each logged once).
    pub imu_stops: u64,
    /// IMU samples ignored (not after the previous one, or a non-finite quaternion).
    pub rejected_samples: u64,
}

/// The fusion over one session: feed it the mounts, the IMU samples and the matcher's poses in
/// sample-time order per stream; it returns each pose once it is settled, in pose order.
#[derive(Debug, Clone)]
pub struct PoseFusion {
    fuser: YawFuser,
    /// q_mount⁻¹ (base → IMU).
    mount_inverse: UnitQuaternion<f64>,
    /// `base`'s z axis in the IMU's frame.
    axis: [f64; 3],
    /// The IMU samples of the last [`HISTORY_S`] seconds.
    history: VecDeque<ImuPoint>,
    last_imu_t: Option<f64>,
    orientation_seen: bool,
    /// The first pose's (time, matcher yaw, cumulative gyro integral) the IMU covered: the
    /// gyro-alone yaw starts there.
    gyro_origin: Option<(f64, f64, f64)>,
    pending: VecDeque<MatcherPoseYaw>,
    counts: FusionCounts,
    logged_no_orientation: bool,
}

#[derive(Debug, Clone, Copy)]
struct ImuPoint {
    t: f64,
    cumulative: f64,
    roll_pitch: Option<[f64; 2]>,
}

impl PoseFusion {
    /// A fusion with `config` (refused when the fuser refuses it: a non-finite or non-positive
    /// parameter).
    pub fn new(config: FuserConfig) -> Result<Self, FusionError> {
        Ok(Self {
            fuser: YawFuser::new(config)?,
            mount_inverse: UnitQuaternion::identity(),
            axis: [0.0, 0.0, 1.0],
            history: VecDeque::new(),
            last_imu_t: None,
            orientation_seen: false,
            gyro_origin: None,
            pending: VecDeque::new(),
            counts: FusionCounts::default(),
            logged_no_orientation: false,
        })
    }

    /// The counts so far.
    pub fn counts(&self) -> FusionCounts {
        self.counts
    }

    /// The fuser (its alignment and field reference).
    pub fn fuser(&self) -> &YawFuser {
        &self.fuser
    }

    /// Takes the IMU's mount from the session's mounts (others are ignored).
    pub fn on_mounts(&mut self, mounts: &SensorMounts) {
        if let Some(m) = mounts.sensors.iter().find(|m| m.sensor == SensorId::IMU) {
            let (roll, pitch, yaw) = (
                m.roll_deg.to_radians(),
                m.pitch_deg.to_radians(),
                m.yaw_deg.to_radians(),
            );
            if ![roll, pitch, yaw].iter().all(|v| v.is_finite()) {
                tracing::warn!("the IMU's mount is not finite: the fusion keeps the previous one");
                return;
            }
            self.mount_inverse = UnitQuaternion::from_euler_angles(roll, pitch, yaw).inverse();
            let (sr, cr) = roll.sin_cos();
            let (sp, cp) = pitch.sin_cos();
            self.axis = [-sp, cp * sr, cp * cr];
        }
    }

    /// Takes one IMU sample (edge time order); returns the poses it settles.
    pub fn on_imu(&mut self, sample: &ImuSample) -> Vec<FusedPoseYaw> {
        let t = sample.t_ns as f64 * 1e-9;
        if self.last_imu_t.is_some_and(|last| t <= last) {
            self.counts.rejected_samples += 1;
            return Vec::new();
        }
        let rate: f64 = (0..3)
            .map(|k| self.axis[k] * f64::from(sample.gyro_radps[k]))
            .sum();
        // A sample's rate holds over the time since the previous sample; across a longer gap
        // than GYRO_MAX_GAP_S nothing is integrated (the gyro-alone yaw then misses that turn).
        let cumulative = match (self.history.back(), self.last_imu_t) {
            (Some(p), Some(last)) if t - last <= GYRO_MAX_GAP_S && rate.is_finite() => {
                p.cumulative + rate * (t - last)
            }
            (Some(p), _) => p.cumulative,
            (None, _) => 0.0,
        };
        self.last_imu_t = Some(t);
        let orientation = sample
            .orientation
            .map(|q| q.map(f64::from))
            .filter(|q| q.iter().all(|v| v.is_finite()) && q.iter().any(|v| *v != 0.0));
        let mut roll_pitch = None;
        let mut settled = Vec::new();
        if let Some(q) = orientation {
            self.orientation_seen = true;
            let imu = unit(q);
            let q = [imu.w, imu.i, imu.j, imu.k];
            let (roll, pitch, yaw) = (imu * self.mount_inverse).euler_angles();
            let yaw = wrap_angle(yaw);
            roll_pitch = Some([roll, pitch]);
            let mag = sample.mag_ut.map(f64::from);
            let field = if mag.iter().all(|v| v.is_finite()) {
                MagneticField::from_vectors(mag, up_in_sensor_frame(q))
            } else {
                None
            };
            match self.fuser.push_madgwick(MadgwickYaw {
                time: t,
                yaw,
                uncertainty: MadgwickUncertainty::Field(field),
            }) {
                Ok(out) => settled = out,
                Err(_) => self.counts.rejected_samples += 1,
            }
        }
        // The IMU stream is in time order: no Madgwick sample at or before `t` is to come.
        settled.extend(self.fuser.advance_to(t));
        self.history.push_back(ImuPoint {
            t,
            cumulative,
            roll_pitch,
        });
        while self.history.len() > MAX_HISTORY
            || self.history.front().is_some_and(|p| p.t < t - HISTORY_S)
        {
            self.history.pop_front();
        }
        self.finish(settled)
    }

    /// Takes one matcher pose (time order); returns the poses settled.
    pub fn on_pose(&mut self, pose: MatcherPoseYaw) -> Vec<FusedPoseYaw> {
        let time = pose.t_ns as f64 * 1e-9;
        if self.pending.back().is_some_and(|p| p.t_ns >= pose.t_ns) {
            // Out of order: cannot be joined; handed back as the matcher's.
            tracing::warn!(
                t_ns = pose.t_ns,
                "a pose not after the previous one: not fused"
            );
            let out = self.unfused(&pose, UnfusedReason::NoImuNearby);
            return vec![out];
        }
        if self.gyro_origin.is_none()
            && let Some(cumulative) = self.cumulative_at(time)
        {
            self.gyro_origin = Some((time, pose.yaw, cumulative));
        }
        let settled = match self.fuser.push_matcher(MatcherYaw {
            time,
            yaw: pose.yaw,
            variance: pose.variance.max(0.0),
        }) {
            Ok(out) => {
                self.pending.push_back(pose);
                out
            }
            Err(error) => {
                tracing::warn!(%error, "a pose the fuser refused: the matcher's alone");
                return vec![self.unfused(&pose, UnfusedReason::NoImuNearby)];
            }
        };
        let mut out = self.finish(settled);
        while self.pending.len() > MAX_PENDING {
            let oldest = self.pending.pop_front().expect("more than the cap");
            out.push(self.unfused(&oldest, UnfusedReason::NoImuNearby));
        }
        out
    }

    /// Says no IMU sample at or before edge time `t_ns` is still to come (`u64::MAX`: the
    /// stream ended); returns the poses this settles.
    pub fn advance_to(&mut self, t_ns: u64) -> Vec<FusedPoseYaw> {
        let time = if t_ns == u64::MAX {
            f64::INFINITY
        } else {
            t_ns as f64 * 1e-9
        };
        let settled = self.fuser.advance_to(time);
        self.finish(settled)
    }

    /// Matches what the fuser settled with the waiting poses (both in time order).
    fn finish(&mut self, settled: Vec<FusedYaw>) -> Vec<FusedPoseYaw> {
        let mut out = Vec::with_capacity(settled.len());
        for fused in settled {
            // The fuser settles in pose order; drop poses it had already given up on.
            let pose = loop {
                match self.pending.pop_front() {
                    Some(p) if (p.t_ns as f64 * 1e-9) < fused.time => {
                        out.push(self.unfused(&p, UnfusedReason::NoImuNearby));
                    }
                    Some(p) => break Some(p),
                    None => break None,
                }
            };
            let Some(pose) = pose else { continue };
            out.push(self.outcome(&pose, &fused));
        }
        out
    }

    fn outcome(&mut self, pose: &MatcherPoseYaw, fused: &FusedYaw) -> FusedPoseYaw {
        match fused.notice {
            Some(FusionNotice::Aligned(a)) => tracing::info!(
                offset_deg = a.offset.to_degrees(),
                sigma_deg = a.variance.sqrt().to_degrees(),
                "yaw fusion: Madgwick aligned with the matcher's frame, fusing from here"
            ),
            Some(FusionNotice::FallingBack) if self.orientation_seen => {
                self.counts.imu_stops += 1;
                tracing::warn!(
                    at_s = fused.time,
                    "yaw fusion: no Madgwick sample near the pose (the IMU stopped?): the \
                     matcher's yaw alone until it comes back"
                );
            }
            Some(FusionNotice::Resumed) => {
                tracing::info!(
                    at_s = fused.time,
                    "yaw fusion: Madgwick samples again, fusing"
                )
            }
            _ => {}
        }
        match fused.source {
            YawSource::Fused { omega, madgwick } => {
                self.counts.fused += 1;
                let mut sources = self.sources(pose);
                sources.madgwick = Some(madgwick.mean);
                sources.madgwick_variance = Some(madgwick.variance);
                sources.fused = fused.estimate.mean;
                sources.fused_variance = fused.estimate.variance;
                sources.omega = Some(omega);
                FusedPoseYaw {
                    t_ns: pose.t_ns,
                    yaw: fused.estimate.mean,
                    variance: fused.estimate.variance,
                    matcher_variance: pose.variance,
                    roll_pitch: self.roll_pitch_at(fused.time),
                    unfused: None,
                    sources,
                }
            }
            YawSource::MatcherOnly(reason) => {
                let reason = match reason {
                    _ if !self.orientation_seen => UnfusedReason::NoOrientation,
                    MatcherOnlyReason::Aligning => UnfusedReason::Aligning,
                    MatcherOnlyReason::NoMadgwickWithinGap => UnfusedReason::NoImuNearby,
                    MatcherOnlyReason::ExactMatcher => UnfusedReason::ExactMatcher,
                    MatcherOnlyReason::MadgwickVarianceUnknown => UnfusedReason::VarianceUnknown,
                };
                self.unfused(pose, reason)
            }
        }
    }

    fn unfused(&mut self, pose: &MatcherPoseYaw, reason: UnfusedReason) -> FusedPoseYaw {
        self.counts.matcher_only += 1;
        match reason {
            UnfusedReason::NoOrientation => {
                self.counts.no_orientation += 1;
                if !self.logged_no_orientation {
                    self.logged_no_orientation = true;
                    tracing::warn!(
                        "yaw fusion: the edge sends no Madgwick orientation: the matcher's yaw \
                         alone"
                    );
                }
            }
            UnfusedReason::Aligning => self.counts.aligning += 1,
            UnfusedReason::NoImuNearby => self.counts.no_imu_nearby += 1,
            UnfusedReason::ExactMatcher => self.counts.exact_matcher += 1,
            UnfusedReason::VarianceUnknown => self.counts.variance_unknown += 1,
        }
        let time = pose.t_ns as f64 * 1e-9;
        FusedPoseYaw {
            t_ns: pose.t_ns,
            yaw: pose.yaw,
            variance: pose.variance,
            matcher_variance: pose.variance,
            roll_pitch: self.roll_pitch_at(time),
            unfused: Some(reason),
            sources: self.sources(pose),
        }
    }

    /// The sources known without the fuser: the matcher's and the gyro's.
    fn sources(&self, pose: &MatcherPoseYaw) -> YawSources {
        let time = pose.t_ns as f64 * 1e-9;
        let gyro = self.gyro_at(time);
        YawSources {
            t_ns: pose.t_ns,
            matcher: pose.yaw,
            matcher_variance: pose.variance,
            madgwick: None,
            madgwick_variance: None,
            gyro: gyro.map(|g| g.0),
            gyro_variance: gyro.map(|g| g.1),
            fused: pose.yaw,
            fused_variance: pose.variance,
            omega: None,
        }
    }

    /// The cumulative gyro integral at `time`, linear between samples, if the history covers it.
    fn cumulative_at(&self, time: f64) -> Option<f64> {
        let i = self.history.partition_point(|p| p.t <= time);
        let before = self.history.get(i.checked_sub(1)?)?;
        let Some(after) = self.history.get(i) else {
            return (time - before.t <= GYRO_MAX_GAP_S).then_some(before.cumulative);
        };
        let u = (time - before.t) / (after.t - before.t);
        Some(before.cumulative + u * (after.cumulative - before.cumulative))
    }

    /// The gyro-alone yaw at `time` and its variance, from the first pose's matcher yaw on.
    fn gyro_at(&self, time: f64) -> Option<(f64, f64)> {
        let (t0, yaw0, origin) = self.gyro_origin?;
        let now = self.cumulative_at(time)?;
        let dt = (time - t0).max(0.0);
        let variance = GYRO_NOISE_DENSITY.powi(2) * dt + (GYRO_BIAS_UNMEASURED * dt).powi(2);
        Some((wrap_angle(yaw0 + now - origin), variance))
    }

    fn roll_pitch_at(&self, time: f64) -> Option<[f64; 2]> {
        let i = self.history.partition_point(|p| p.t <= time);
        let near = [i.checked_sub(1), Some(i)]
            .into_iter()
            .flatten()
            .filter_map(|j| self.history.get(j))
            .filter(|p| (p.t - time).abs() <= GYRO_MAX_GAP_S)
            .min_by(|a, b| (a.t - time).abs().total_cmp(&(b.t - time).abs()))?;
        near.roll_pitch
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_protocol::SensorMount;

    /// The earth's field (µT) and dip (rad).
    const FIELD: f64 = 50.0;
    const DIP: f64 = 1.0;

    /// `v` (earth frame) in the frame `q` rotates into the earth.
    fn to_sensor(q: Quaternion, v: [f64; 3]) -> [f64; 3] {
        unit(q)
            .inverse_transform_vector(&nalgebra::Vector3::from(v))
            .into()
    }

    /// The rotation `Rz(yaw) Ry(pitch) Rx(roll)` as `[w, x, y, z]`.
    fn quat_from_euler(roll: f64, pitch: f64, yaw: f64) -> Quaternion {
        let q = UnitQuaternion::from_euler_angles(roll, pitch, yaw);
        [q.w, q.i, q.j, q.k]
    }

    fn quat_mul(a: Quaternion, b: Quaternion) -> Quaternion {
        let q = unit(a) * unit(b);
        [q.w, q.i, q.j, q.k]
    }

    fn noise(seed: u64, k: u64) -> f64 {
        let mut x = seed ^ k.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0x2545_f491_4f6c_dd1d;
        let mut sum = 0.0;
        for _ in 0..4 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            sum += (x % 10_000) as f64 / 10_000.0 - 0.5;
        }
        sum * 3f64.sqrt()
    }

    fn true_yaw(t: f64) -> f64 {
        if t < 3.0 { 0.2 } else { 0.2 + 0.3 * (t - 3.0) }
    }

    /// The IMU sample at edge time `t_ns` of a level IMU (no mount) whose Madgwick yaw is off
    /// by `error`, in a field scaled by `field_scale`.
    fn imu(t_ns: u64, error: f64, field_scale: f64, orientation: bool) -> ImuSample {
        let t = t_ns as f64 * 1e-9;
        let truth = quat_from_euler(0.0, 0.0, true_yaw(t));
        let reported = quat_from_euler(0.0, 0.0, true_yaw(t) + error);
        let b = FIELD * field_scale;
        let mag = to_sensor(truth, [b * DIP.cos(), 0.0, -b * DIP.sin()]);
        ImuSample {
            t_ns,
            accel_mps2: [0.0, 0.0, 9.81],
            gyro_radps: [0.0, 0.0, 0.3 * f32::from(u8::from(t >= 3.0))],
            mag_ut: mag.map(|v| v as f32),
            orientation: orientation.then(|| reported.map(|v| v as f32)),
        }
    }

    /// One stream item as it arrives: an IMU sample or a matcher pose.
    #[derive(Clone, Copy)]
    enum Item {
        Imu(ImuSample),
        Pose(MatcherPoseYaw),
    }

    /// 20 s: IMU at 200 Hz, matcher poses at 5.5 Hz with σ = 1° noise (as bad as Madgwick, so
    /// the fusion listens to both); Madgwick off by 20° in a field 20 % stronger in `disturbed`
    /// seconds. Returns the items in sample-time order and the true yaw per pose.
    fn run(seed: u64, disturbed: Option<(f64, f64)>, orientation: bool) -> (Vec<Item>, Vec<f64>) {
        let mut items = Vec::new();
        let mut truth = Vec::new();
        let pose_period = 181_818_182u64;
        let mut next_pose = 500_000_000u64;
        for k in 0..4000u64 {
            let t_ns = 100_000_000 + k * 5_000_000;
            let t = t_ns as f64 * 1e-9;
            let inside = disturbed.is_some_and(|(a, b)| t >= a && t < b);
            // Madgwick's error: 1°, a new draw every 180 ms (about one per pose).
            let error = 1f64.to_radians() * noise(seed, k / 36)
                + if inside { 20f64.to_radians() } else { 0.0 };
            items.push(Item::Imu(imu(
                t_ns,
                error,
                if inside { 1.2 } else { 1.0 },
                orientation,
            )));
            // A pose is known once its revolution ends, half a revolution after its time.
            while next_pose + pose_period / 2 <= t_ns {
                let tp = next_pose as f64 * 1e-9;
                truth.push(true_yaw(tp));
                items.push(Item::Pose(MatcherPoseYaw {
                    t_ns: next_pose,
                    yaw: wrap_angle(true_yaw(tp) + 1f64.to_radians() * noise(seed + 99, next_pose)),
                    variance: 1f64.to_radians().powi(2),
                }));
                next_pose += pose_period;
            }
        }
        (items, truth)
    }

    /// Feeds `items` in order (advancing the IMU stream with each sample: in order within it).
    fn feed(items: &[Item]) -> (Vec<FusedPoseYaw>, FusionCounts) {
        feed_with(items, FuserConfig::default())
    }

    fn feed_with(items: &[Item], config: FuserConfig) -> (Vec<FusedPoseYaw>, FusionCounts) {
        let mut fusion = PoseFusion::new(config).expect("valid");
        let mut out = Vec::new();
        for item in items {
            match item {
                Item::Imu(sample) => out.extend(fusion.on_imu(sample)),
                Item::Pose(pose) => out.extend(fusion.on_pose(*pose)),
            }
        }
        out.extend(fusion.advance_to(u64::MAX));
        (out, fusion.counts())
    }

    fn error_deg(out: &FusedPoseYaw, truth: f64) -> f64 {
        wrap_angle(out.yaw - truth).to_degrees()
    }

    #[test]
    fn a_disturbed_field_keeps_the_fusion_off_the_madgwick_yaw() {
        let (items, truth) = run(3, Some((8.0, 12.0)), true);
        // Without the innovation gate: the field model alone must see the disturbance.
        let config = FuserConfig {
            innovation_gate: 0.0,
            ..FuserConfig::default()
        };
        let (out, counts) = feed_with(&items, config);
        assert_eq!(out.len(), truth.len());
        assert!(counts.fused > 80, "{counts:?}");
        let during: Vec<(f64, f64)> = out
            .iter()
            .zip(&truth)
            .filter(|(o, _)| (8.2..12.0).contains(&(o.t_ns as f64 * 1e-9)))
            .map(|(o, t)| {
                (
                    error_deg(o, *t),
                    wrap_angle(o.sources.madgwick.unwrap() - t).to_degrees(),
                )
            })
            .collect();
        let fused_worst = during.iter().fold(0.0f64, |m, e| m.max(e.0.abs()));
        let madgwick_worst = during.iter().fold(0.0f64, |m, e| m.max(e.1.abs()));
        println!("disturbed: worst fused {fused_worst:.2}°, Madgwick {madgwick_worst:.2}°");
        assert!(madgwick_worst > 18.0);
        // The matcher's own noise is 1° (3.5° at worst over 20 poses); half of Madgwick's 20°
        // would be 10°.
        assert!(fused_worst < 4.0, "{fused_worst}");
    }

    #[test]
    fn the_fusion_beats_either_source_when_they_are_alike() {
        for seed in [1, 2, 3] {
            let (items, truth) = run(seed, None, true);
            let (out, _) = feed(&items);
            let fused: Vec<_> = out
                .iter()
                .zip(&truth)
                .filter(|(o, _)| o.unfused.is_none())
                .collect();
            let rms = |f: &dyn Fn(&FusedPoseYaw, f64) -> f64| {
                (fused.iter().map(|(o, t)| f(o, **t).powi(2)).sum::<f64>() / fused.len() as f64)
                    .sqrt()
            };
            let f = rms(&|o, t| error_deg(o, t));
            let m = rms(&|o, t| wrap_angle(o.sources.matcher - t).to_degrees());
            let g = rms(&|o, t| wrap_angle(o.sources.madgwick.unwrap() - t).to_degrees());
            println!("seed {seed}: fused {f:.3}°, matcher {m:.3}°, Madgwick {g:.3}°");
            assert!(f <= m.min(g), "seed {seed}: {f} vs {m}, {g}");
        }
    }

    #[test]
    fn the_join_is_by_edge_sample_time_whatever_the_clocks_and_the_arrival() {
        let (items, _) = run(4, None, true);
        let (in_order, _) = feed(&items);
        // The server sees the edge's clock offset by 3 s and 80 ppm fast, the IMU in batches of
        // 40 samples, the poses 50–150 ms late: arrival order by server time.
        let arrival = |item: &Item| -> f64 {
            let (t, delay) = match item {
                Item::Imu(s) => {
                    let batch_end = (s.t_ns / 200_000_000 + 1) * 200_000_000;
                    (batch_end as f64 * 1e-9, 0.01)
                }
                // Jitter below the poses' period: a stream keeps its own order.
                Item::Pose(p) => (
                    p.t_ns as f64 * 1e-9,
                    0.05 + 0.1 * (noise(8, p.t_ns) + 1.8) / 3.6,
                ),
            };
            3.0 + t * (1.0 + 80e-6) + delay
        };
        let mut arrived = items.clone();
        arrived.sort_by(|a, b| arrival(a).total_cmp(&arrival(b)));
        let moved = arrived
            .iter()
            .zip(&items)
            .filter(|(a, b)| std::mem::discriminant(*a) != std::mem::discriminant(*b))
            .count();
        assert!(moved > 100, "the arrival order differs ({moved})");
        let (late, _) = feed(&arrived);
        assert_eq!(late.len(), in_order.len());
        for (a, b) in late.iter().zip(&in_order) {
            assert_eq!(a, b);
        }
    }

    #[test]
    fn without_orientation_or_after_the_imu_stops_the_pose_is_the_matchers() {
        let (items, truth) = run(5, None, false);
        let (out, counts) = feed(&items);
        assert_eq!(out.len(), truth.len());
        assert!(
            out.iter()
                .all(|o| o.unfused == Some(UnfusedReason::NoOrientation))
        );
        assert_eq!(counts.no_orientation as usize, truth.len());
        assert!(
            out.iter().all(|o| o.sources.gyro.is_some()),
            "the gyro still integrates"
        );

        let (items, truth) = run(5, None, true);
        let cut = items
            .iter()
            .position(|i| matches!(i, Item::Imu(s) if s.t_ns >= 10_000_000_000))
            .unwrap();
        let kept: Vec<Item> = items
            .iter()
            .enumerate()
            .filter(|(k, i)| *k < cut || matches!(i, Item::Pose(_)))
            .map(|(_, i)| *i)
            .collect();
        let (out, counts) = feed(&kept);
        assert_eq!(out.len(), truth.len(), "every pose comes out");
        assert_eq!(counts.imu_stops, 1);
        for o in &out {
            if o.t_ns as f64 * 1e-9 > 10.2 {
                assert_eq!(o.unfused, Some(UnfusedReason::NoImuNearby));
            }
        }
    }

    #[test]
    fn the_madgwick_attitude_of_base_goes_through_the_imus_mount() {
        let mut fusion = PoseFusion::new(FuserConfig::default()).expect("valid");
        // IMU upside down, turned 90° on base; base pitched 5° nose down at yaw 30°.
        fusion.on_mounts(&SensorMounts {
            sensors: vec![SensorMount {
                sensor: SensorId::IMU,
                x_m: 0.0,
                y_m: 0.0,
                z_m: 0.0,
                roll_deg: 180.0,
                pitch_deg: 0.0,
                yaw_deg: 90.0,
            }],
        });
        let base = quat_from_euler(0.0, 5f64.to_radians(), 30f64.to_radians());
        let mount = quat_from_euler(PI_, 0.0, std::f64::consts::FRAC_PI_2);
        let q = quat_mul(base, mount);
        for k in 0..100u64 {
            let mut sample = imu(1_000_000_000 + k * 5_000_000, 0.0, 1.0, true);
            sample.orientation = Some(q.map(|v| v as f32));
            fusion.on_imu(&sample);
        }
        let rp = fusion.roll_pitch_at(1.2).expect("covered");
        assert!(
            rp[0].abs() < 1e-5 && (rp[1] - 5f64.to_radians()).abs() < 1e-5,
            "{rp:?}"
        );
    }

    const PI_: f64 = std::f64::consts::PI;
}
