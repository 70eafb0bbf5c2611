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

/// A quaternion `[w, x, y, z]`.
type Quaternion = [f64; 4];

fn quat_mul(a: Quaternion, b: Quaternion) -> Quaternion {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

/// The rotation `Rz(yaw) Ry(pitch) Rx(roll)` as a quaternion.
fn quat_from_euler(roll: f64, pitch: f64, yaw: f64) -> Quaternion {
    let (sr, cr) = (roll / 2.0).sin_cos();
    let (sp, cp) = (pitch / 2.0).sin_cos();
    let (sy, cy) = (yaw / 2.0).sin_cos();
    [
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]
}

/// Roll, pitch, yaw (rad) of `q` read as `Rz(yaw) Ry(pitch) Rx(roll)`.
pub fn euler_from_quaternion(q: Quaternion) -> [f64; 3] {
    let [w, x, y, z] = q;
    let roll = (2.0 * (w * x + y * z)).atan2(1.0 - 2.0 * (x * x + y * y));
    let pitch = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0).asin();
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z));
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
    mount_inverse: Quaternion,
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
            mount_inverse: [1.0, 0.0, 0.0, 0.0],
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
            let q = quat_from_euler(roll, pitch, yaw);
            self.mount_inverse = [q[0], -q[1], -q[2], -q[3]];
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
            let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            let q = q.map(|v| v / norm);
            let base = quat_mul(q, self.mount_inverse);
            let [roll, pitch, yaw] = euler_from_quaternion(base);
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
