//! Yaw fusion by covariance intersection: the IMU's Madgwick yaw and the scan matcher's yaw,
//! fused at each matcher pose as the paper's §III-B does (its eq. 2–3, with eq. 3 corrected).
//!
//! Covariance intersection (CI) is consistent whatever the two errors' correlation, which is
//! unknown here. For two scalars with ω the weight on the matcher's information:
//!
//! - P̂ = 1 / ((1 − ω)/P + ω/Q)  (the paper's eq. 2),
//! - μ̂ = wrap(μ + ω·P̂/Q · wrap(μ′ − μ))  (eq. 3 corrected, in innovation form),
//!
//! with (μ, P) the Madgwick yaw and its variance, (μ′, Q) the matcher's, angles wrapped into
//! (−π, π]. Eq. 3 as printed, μ̂ = P̂((1−ω)P̂⁻¹μ + ωQ⁻¹μ′)⁻¹, is not an angle (its units are
//! 1/rad); the correct μ̂ = P̂((1−ω)P⁻¹μ + ωQ⁻¹μ′) equals the innovation form above, which is
//! the one that wraps safely. How ω is chosen is [`OmegaPolicy`]; the paper bounds it to
//! (0, 0.5), so Madgwick always keeps at least half of the information weight.
//!
//! **Frames.** The matcher's yaw is that of `base` (the mapper is given the RPLidar's mount as
//! its sensor offset, and the server's revolution scans already turn the RPLidar's clockwise
//! angles into counter-clockwise ones), counter-clockwise about up, in the session's (or once a
//! pass anchors it, the room's) frame. The Madgwick yaw is the IMU's, counter-clockwise about
//! up from magnetic north (the edge's filter runs in NWU). Both turn the same way, so they
//! differ by a constant: magnetic north in the map frame plus the IMU's mounting yaw in `base`.
//! [`YawAlignment`] estimates that constant as one (the circular mean of their differences at
//! the start of a run), so neither the mounting yaw nor a handedness flip is applied here; an
//! IMU mounted upside down (its z down) would need its yaw negated before it comes in.
//!
//! **Variances.** The matcher's is its calibrated covariance's yaw term. Madgwick reports none:
//! [`MadgwickNoise`] models it (gyro noise held down by the filter's β, its chatter, a floor for
//! the residual iron, and an inflation while the magnetic field's magnitude or dip leaves its
//! calibrated value, decaying no faster than the filter can correct its heading).
//!
//! **Time.** [`YawFuser`] joins the streams by sample time, never by arrival: the Madgwick yaw
//! is interpolated (on its unwrapped yaw) at each matcher pose's time, and a pose waits until
//! the Madgwick stream has passed its time. With no Madgwick sample within a configured gap
//! around a pose, that pose is the matcher's alone, and the first such pose says so once.
//!
//! Pure code: values in, values out; nothing here reads a clock, a file or a socket.

use std::collections::VecDeque;
use std::f64::consts::{FRAC_PI_2, PI};

use serde::{Deserialize, Serialize};

use crate::pose::wrap_angle;

/// How far ω stays from its bounds 0 and 0.5 (the paper's open interval (0, 0.5)).
pub const OMEGA_EPSILON: f64 = 1e-3;

/// The MPU-9250's gyro rate noise density, 0.01 °/s/√Hz (InvenSense datasheet), in rad/s/√Hz.
pub const MPU9250_GYRO_NOISE_DENSITY: f64 = 0.01 * PI / 180.0;

/// The standard deviation of a yaw known to be nowhere in particular (uniform on the circle):
/// π/√3. Every modelled heading σ is capped here, so a variance stays finite.
pub const UNKNOWN_HEADING_SIGMA: f64 = 1.813_799_364_234_217_8;

/// A yaw and its variance: rad in (−π, π], rad².
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct YawEstimate {
    /// The yaw (rad, counter-clockwise).
    pub mean: f64,
    /// Its variance (rad²).
    pub variance: f64,
}

impl YawEstimate {
    /// A yaw (wrapped into (−π, π]) with its variance.
    pub fn new(mean: f64, variance: f64) -> Self {
        Self {
            mean: wrap_angle(mean),
            variance,
        }
    }
}

/// Why a fusion input was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum FusionError {
    #[error("{what} is not finite ({value})")]
    NotFinite { what: &'static str, value: f64 },
    #[error("{what} must be positive, got {value}")]
    NotPositive { what: &'static str, value: f64 },
    #[error("{what} at {time} s is not after the previous one at {previous} s")]
    OutOfOrder {
        what: &'static str,
        time: f64,
        previous: f64,
    },
}

fn finite(what: &'static str, value: f64) -> Result<f64, FusionError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(FusionError::NotFinite { what, value })
    }
}

fn positive(what: &'static str, value: f64) -> Result<f64, FusionError> {
    if finite(what, value)? > 0.0 {
        Ok(value)
    } else {
        Err(FusionError::NotPositive { what, value })
    }
}

/// How ω, the weight on the matcher's information, is chosen; always clamped to
/// (ε, 0.5 − ε) with ε = [`OMEGA_EPSILON`], the paper's bound.
///
/// The paper says ω is "inversely proportional to P" while its eq. 2 puts ω on the matcher's
/// term: read literally that gives the matcher more weight when Madgwick is *more* certain.
/// The consistent reading, that Madgwick's weight 1 − ω falls as P grows, is fast CI.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OmegaPolicy {
    /// Fast CI (Niehsen, FUSION 2002): weights proportional to each source's information,
    /// ω = (1/Q) / (1/P + 1/Q) = P / (P + Q).
    #[default]
    FastCi,
    /// The paper's sentence read literally: ω = κ / P (κ in rad², > 0).
    Literal { kappa: f64 },
    /// The bound the better source pushes to: 0.5 − ε when the matcher is the more certain
    /// (Q < P), else ε. Scalar CI's own optimum is always a bound.
    Boundary,
}

impl OmegaPolicy {
    /// ω for a Madgwick variance `p` and a matcher variance `q` (both > 0), in (ε, 0.5 − ε).
    pub fn omega(&self, p: f64, q: f64) -> f64 {
        let raw = match *self {
            OmegaPolicy::FastCi => p / (p + q),
            OmegaPolicy::Literal { kappa } => kappa / p,
            OmegaPolicy::Boundary => {
                if q < p {
                    0.5
                } else {
                    0.0
                }
            }
        };
        raw.clamp(OMEGA_EPSILON, 0.5 - OMEGA_EPSILON)
    }
}

/// A covariance intersection of two yaws: the fused yaw and the ω it used.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CiYaw {
    /// The fused yaw (rad, in (−π, π]) and its variance (rad²).
    pub estimate: YawEstimate,
    /// The weight on the matcher's information (1 − ω on Madgwick's).
    pub omega: f64,
}

/// Covariance intersection of the Madgwick yaw (μ, P) and the matcher's (μ′, Q), in the same
/// frame, ω by `policy`: P̂ = 1/((1−ω)/P + ω/Q), μ̂ = wrap(μ + ω·P̂/Q·wrap(μ′ − μ)), so the
/// result lies on the shorter arc between the two. Variances must be positive and finite.
pub fn ci_yaw(
    madgwick: YawEstimate,
    matcher: YawEstimate,
    policy: OmegaPolicy,
) -> Result<CiYaw, FusionError> {
    finite("Madgwick yaw", madgwick.mean)?;
    finite("matcher yaw", matcher.mean)?;
    let p = positive("Madgwick yaw variance", madgwick.variance)?;
    let q = positive("matcher yaw variance", matcher.variance)?;
    if let OmegaPolicy::Literal { kappa } = policy {
        positive("the literal ω rule's κ", kappa)?;
    }
    let omega = policy.omega(p, q);
    let variance = 1.0 / ((1.0 - omega) / p + omega / q);
    let innovation = wrap_angle(matcher.mean - madgwick.mean);
    let mean = wrap_angle(madgwick.mean + omega * variance / q * innovation);
    Ok(CiYaw {
        estimate: YawEstimate { mean, variance },
        omega,
    })
}

/// The constant between the two yaws' frames, estimated from paired samples: the circular mean
/// of wrap(ψ_matcher − ψ_madgwick) (magnetic north in the map frame plus the IMU's mounting yaw
/// in `base`), taken over the first seconds of a run, when the trolley stands at a pass's start.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct YawAlignment {
    sum_cos: f64,
    sum_sin: f64,
    count: usize,
    first_time: Option<f64>,
    last_time: f64,
}

/// A frame alignment: add `offset` to a Madgwick yaw to have it in the matcher's frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AlignmentEstimate {
    /// wrap(ψ_matcher − ψ_madgwick) (rad, in (−π, π]).
    pub offset: f64,
    /// Its variance (rad²), added to every aligned Madgwick yaw's.
    pub variance: f64,
}

impl AlignmentEstimate {
    /// `madgwick` in the matcher's frame, the alignment's variance added to its own.
    pub fn apply(&self, madgwick: YawEstimate) -> YawEstimate {
        YawEstimate {
            mean: wrap_angle(madgwick.mean + self.offset),
            variance: madgwick.variance + self.variance,
        }
    }
}

impl YawAlignment {
    /// An alignment with no samples yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds the pair (matcher yaw, Madgwick yaw) seen at `time` (s); both rad.
    pub fn add(&mut self, time: f64, matcher_yaw: f64, madgwick_yaw: f64) {
        let (s, c) = wrap_angle(matcher_yaw - madgwick_yaw).sin_cos();
        self.sum_cos += c;
        self.sum_sin += s;
        self.count += 1;
        self.first_time.get_or_insert(time);
        self.last_time = time;
    }

    /// Pairs added.
    pub fn count(&self) -> usize {
        self.count
    }

    /// Time from the first pair to the last (s).
    pub fn span(&self) -> f64 {
        self.first_time.map_or(0.0, |first| self.last_time - first)
    }

    /// The circular mean of the differences and its variance; `None` before any pair or when
    /// they cancel out (no direction). The variance is the pairs' own circular spread,
    /// −2 ln R̄ (R̄ the mean resultant length), *not* divided by their count: pairs a few seconds
    /// apart share most of their errors (Madgwick's moves on its β time scale, its residual iron
    /// at a standing heading not at all), so they are not independent draws.
    pub fn estimate(&self) -> Option<AlignmentEstimate> {
        if self.count == 0 {
            return None;
        }
        let resultant = self.sum_cos.hypot(self.sum_sin) / self.count as f64;
        if resultant < 1e-9 {
            return None;
        }
        Some(AlignmentEstimate {
            offset: wrap_angle(self.sum_sin.atan2(self.sum_cos)),
            variance: (-2.0 * resultant.min(1.0).ln()).max(0.0),
        })
    }
}

/// What a magnetometer reading says beyond its direction: the field's magnitude (any unit, the
/// same as the reference's; µT from the edge) and its dip below the horizontal (rad, positive
/// down, as in the northern hemisphere).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MagneticField {
    /// |B|.
    pub magnitude: f64,
    /// The angle of B below the horizontal plane (rad).
    pub dip: f64,
}

impl MagneticField {
    /// The field's magnitude and dip from the field `field` and the up direction `up`, both in
    /// the sensor frame (`up` of any length; take it from the filter's orientation,
    /// [`up_in_sensor_frame`]: the raw accelerometer also carries the trolley's acceleration).
    /// `None` for a zero or non-finite vector.
    pub fn from_vectors(field: [f64; 3], up: [f64; 3]) -> Option<Self> {
        let magnitude = norm(field);
        let up_norm = norm(up);
        if !(magnitude.is_finite() && up_norm.is_finite() && magnitude > 0.0 && up_norm > 0.0) {
            return None;
        }
        let along_up = (field[0] * up[0] + field[1] * up[1] + field[2] * up[2]) / up_norm;
        let dip = (-along_up / magnitude).clamp(-1.0, 1.0).asin();
        Some(Self { magnitude, dip })
    }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// The earth's up axis in the sensor frame for an orientation `[w, x, y, z]` that rotates
/// sensor vectors into the earth frame (the edge's Madgwick quaternion): the third row of its
/// rotation matrix.
pub fn up_in_sensor_frame(q: [f64; 4]) -> [f64; 3] {
    let [w, x, y, z] = q;
    [
        2.0 * (x * z - w * y),
        2.0 * (w * x + y * z),
        1.0 - 2.0 * (x * x + y * y),
    ]
}

/// The yaw (rad, counter-clockwise about the earth's up axis, in (−π, π]) of an orientation
/// `[w, x, y, z]` (sensor to earth; in the edge's NWU frame it is measured from magnetic north).
pub fn yaw_from_quaternion(q: [f64; 4]) -> f64 {
    let [w, x, y, z] = q;
    wrap_angle((2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z)))
}

/// The constants of the Madgwick yaw variance model ([`MadgwickVariance`]).
///
/// In steady state, with the field as calibrated, the variance is the sum of:
/// - the gyro's angle random walk held down by the filter's correction: each update steps the
///   quaternion by β·Δt along the normalised gradient, i.e. turns the heading back at 2β rad/s
///   whatever the error's size. A random walk of density n pulled back at a constant speed v has
///   the stationary law of a Laplace variable with scale n²/(2v), variance n⁴/(2v²). With the
///   MPU-9250's n and β = 0.1 it is ~1e-14 rad²: the gyro alone is no concern while the
///   magnetometer corrects, and for the same reason a residual gyro bias below 2β leaves no lag;
/// - the chatter of that fixed-size step, uniform within ±2β·Δt: (2β·Δt)²/3;
/// - a floor, `heading_floor²`, for what the filter cannot know: the residual hard and soft iron
///   after calibration (a heading-dependent error) and the magnetometer's noise.
///
/// On top of that comes an inflation σ_d² from the field (see [`MadgwickNoise::disturbance_sigma`]),
/// and while no field reading comes in, the gyro's unaided drift ([`MadgwickNoise::unaided_sigma`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MadgwickNoise {
    /// Gyro rate noise density (rad/s/√Hz); the MPU-9250's by default.
    pub gyro_noise_density: f64,
    /// Gyro bias left after calibration (rad/s), for the drift when the magnetometer is absent.
    pub gyro_bias_residual: f64,
    /// The filter's gain β (rad/s, on the quaternion's rate; the heading turns at 2β).
    pub beta: f64,
    /// The filter's update period (s).
    pub sample_period: f64,
    /// Heading standard deviation (rad) the calibrated magnetometer leaves at rest.
    pub heading_floor: f64,
    /// Relative field change (magnitude error and dip error combined, see
    /// [`MadgwickNoise::disturbance_sigma`]) that counts as noise, not disturbance.
    pub field_tolerance: f64,
    /// How much larger the heading error is taken than the field change a reading reveals (≥ 1).
    pub disturbance_gain: f64,
    /// A field reading older than this (s) means the magnetometer is absent.
    pub field_timeout: f64,
}

impl Default for MadgwickNoise {
    fn default() -> Self {
        Self {
            gyro_noise_density: MPU9250_GYRO_NOISE_DENSITY,
            gyro_bias_residual: 0.05_f64.to_radians(),
            beta: 0.1,
            sample_period: 0.01,
            heading_floor: 1.0_f64.to_radians(),
            field_tolerance: 0.03,
            disturbance_gain: 2.0,
            field_timeout: 0.1,
        }
    }
}

impl MadgwickNoise {
    /// The rate (rad/s) at which the filter turns a heading error away: 2β.
    pub fn correction_rate(&self) -> f64 {
        2.0 * self.beta
    }

    /// The yaw variance (rad²) with the field as calibrated: gyro noise under the correction,
    /// the correction's chatter, and the floor (see the type's doc).
    pub fn steady_variance(&self) -> f64 {
        let n2 = self.gyro_noise_density * self.gyro_noise_density;
        let v = self.correction_rate();
        let random_walk = n2 * n2 / (2.0 * v * v);
        let step = v * self.sample_period;
        random_walk + step * step / 3.0 + self.heading_floor * self.heading_floor
    }

    /// The heading standard deviation (rad) a reading `field` reveals against the calibrated
    /// `reference`. A disturbance δB of relative size ε = |δB|/|B| changes the magnitude by up
    /// to ε and the direction by up to asin ε ≈ ε, so the reading shows one of at least
    /// e = √(e_m² + e_d²) (relative magnitude error, dip error in rad), less `field_tolerance`
    /// for noise. It turns the horizontal field, |B|·cos(dip), by up to e / cos(dip). A part of
    /// δB that turns the horizontal field about the vertical changes neither magnitude nor dip,
    /// so it is invisible here: the estimate is multiplied by `disturbance_gain`.
    /// σ_d = gain · max(0, e − tolerance) / cos(dip_ref), capped at [`UNKNOWN_HEADING_SIGMA`].
    pub fn disturbance_sigma(&self, field: &MagneticField, reference: &MagneticField) -> f64 {
        let magnitude_error = (field.magnitude - reference.magnitude).abs() / reference.magnitude;
        let dip_error = (field.dip - reference.dip).abs();
        let excess = (magnitude_error.hypot(dip_error) - self.field_tolerance).max(0.0);
        // Near a magnetic pole the horizontal field vanishes and the heading with it.
        let horizontal_share = reference.dip.abs().min(FRAC_PI_2).cos().max(0.05);
        (self.disturbance_gain * excess / horizontal_share).min(UNKNOWN_HEADING_SIGMA)
    }

    /// The heading standard deviation (rad) after `seconds` of gyro integration alone: the
    /// angle random walk and the residual bias, √(n²·t + (b·t)²), capped at
    /// [`UNKNOWN_HEADING_SIGMA`].
    pub fn unaided_sigma(&self, seconds: f64) -> f64 {
        let t = seconds.max(0.0);
        let n = self.gyro_noise_density;
        let drift = self.gyro_bias_residual * t;
        (n * n * t + drift * drift)
            .sqrt()
            .min(UNKNOWN_HEADING_SIGMA)
    }
}

/// The Madgwick yaw variance over a run, reading by reading: [`MadgwickNoise::steady_variance`]
/// plus σ², where σ is the heading error the filter may still carry. A disturbed reading raises
/// σ to [`MadgwickNoise::disturbance_sigma`] at once; afterwards σ falls no faster than the filter
/// corrects, 2β rad/s (after a 20° disturbance the yaw needs ~1.7 s to come back at β = 0.1).
/// Without field readings σ grows as the gyro's unaided drift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MadgwickVariance {
    noise: MadgwickNoise,
    reference: MagneticField,
    /// σ (rad) at `sigma_time`.
    sigma: f64,
    sigma_time: f64,
    last_field_time: Option<f64>,
}

impl MadgwickVariance {
    /// The model with its constants and the calibrated field (`reference`: magnitude > 0).
    pub fn new(noise: MadgwickNoise, reference: MagneticField) -> Self {
        Self {
            noise,
            reference,
            sigma: 0.0,
            sigma_time: 0.0,
            last_field_time: None,
        }
    }

    /// The calibrated field the readings are compared with.
    pub fn reference(&self) -> &MagneticField {
        &self.reference
    }

    /// σ at `time` with the field present: the last one, corrected away at 2β since.
    fn decayed(&self, time: f64) -> f64 {
        (self.sigma - self.noise.correction_rate() * (time - self.sigma_time).max(0.0)).max(0.0)
    }

    /// σ at `time` given when the field was last read.
    fn sigma_at(&self, time: f64) -> f64 {
        match self.last_field_time {
            None => UNKNOWN_HEADING_SIGMA,
            Some(last) if time - last > self.noise.field_timeout => self
                .decayed(last)
                .max(self.noise.unaided_sigma(time - last)),
            Some(_) => self.decayed(time),
        }
    }

    /// Takes the filter's state at `time` (s, increasing) with the field read then, if any
    /// (the magnetometer runs slower than the gyro), and returns the yaw variance (rad²).
    /// Before any field reading the yaw is unknown: [`UNKNOWN_HEADING_SIGMA`]².
    pub fn update(&mut self, time: f64, field: Option<&MagneticField>) -> f64 {
        if let Some(field) = field {
            let carried = match self.last_field_time {
                None => 0.0,
                Some(_) => self.sigma_at(time),
            };
            self.sigma = carried.max(self.noise.disturbance_sigma(field, &self.reference));
            self.sigma_time = time;
            self.last_field_time = Some(time);
        }
        let sigma = self.sigma_at(time);
        self.noise.steady_variance() + sigma * sigma
    }
}

/// How a Madgwick sample's variance is known.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MadgwickUncertainty {
    /// Given by the caller (rad², > 0).
    Variance(f64),
    /// From the model ([`MadgwickVariance`]), with the field read at this sample, if any.
    Field(Option<MagneticField>),
}

/// One Madgwick output: its sample time, its yaw (counter-clockwise about up from magnetic
/// north, rad) and how its variance is known.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MadgwickYaw {
    /// Sample time (s), on the matcher's clock (the edge's monotonic clock).
    pub time: f64,
    /// Yaw (rad).
    pub yaw: f64,
    /// Its variance, or the field that gives it.
    pub uncertainty: MadgwickUncertainty,
}

/// One matcher pose's yaw: that of `base`, counter-clockwise, in the map frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatcherYaw {
    /// The time the pose is for (s, `ScanResult::time`).
    pub time: f64,
    /// Yaw (rad).
    pub yaw: f64,
    /// Its variance (rad², ≥ 0; 0 for the pose that defines the map frame).
    pub variance: f64,
}

/// Why a matcher pose came out unfused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum MatcherOnlyReason {
    /// The frame alignment is still being estimated (the first seconds).
    Aligning,
    /// No Madgwick sample within the configured gap on both sides of the pose's time.
    NoMadgwickWithinGap,
    /// The matcher's variance is 0 (the pose that defines the map frame): nothing to add.
    ExactMatcher,
    /// The Madgwick variance model has no calibrated field yet (first seconds).
    MadgwickVarianceUnknown,
}

/// Where a fused yaw came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum YawSource {
    /// Covariance intersection of the matcher's yaw and `madgwick` (aligned, interpolated at the
    /// pose's time) with weight `omega` on the matcher.
    Fused { omega: f64, madgwick: YawEstimate },
    /// The matcher's yaw alone.
    MatcherOnly(MatcherOnlyReason),
}

/// A change of the fuser's state worth one log line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FusionNotice {
    /// The frame alignment is estimated; fusion starts with this pose.
    Aligned(AlignmentEstimate),
    /// No Madgwick sample near this pose: the matcher alone from here on, until [`Self::Resumed`].
    FallingBack,
    /// Madgwick samples are back: fused again from this pose.
    Resumed,
}

/// The yaw at one matcher pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedYaw {
    /// The matcher pose's time (s).
    pub time: f64,
    /// The yaw of `base` in the map frame and its variance.
    pub estimate: YawEstimate,
    /// Fused, or the matcher's alone and why.
    pub source: YawSource,
    /// Set on the pose where the fuser's state changed, so the caller logs each change once.
    pub notice: Option<FusionNotice>,
}

/// The [`YawFuser`]'s parameters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FuserConfig {
    /// How ω is chosen.
    pub policy: OmegaPolicy,
    /// A matcher pose is fused only with Madgwick samples at most this far (s) before and after
    /// its time (the filter runs at 100–200 Hz; 0.1 s is 10–20 samples lost).
    pub max_gap: f64,
    /// Madgwick samples kept this long (s) behind the newest (matcher poses lag the IMU by about
    /// half a revolution, 0.1 s at 5.5 Hz).
    pub history: f64,
    /// The frame alignment averages the pairs over this long (s) from the first.
    pub alignment_duration: f64,
    /// ...and over at least this many pairs.
    pub alignment_min_pairs: usize,
    /// The Madgwick variance model's constants.
    pub noise: MadgwickNoise,
    /// The calibrated field; `None`: the mean of the readings over the first
    /// `alignment_duration` seconds of Madgwick samples (the trolley standing).
    pub field_reference: Option<MagneticField>,
    /// Innovation gate (standard deviations; 0: off). When the two yaws differ by more than
    /// this many σ of their combined variance, √(P + Q), the Madgwick variance is raised until
    /// they differ by exactly that many: an error the field model cannot see (iron that turns
    /// the horizontal field without changing its magnitude or dip, an uncalibrated
    /// magnetometer) then no longer pulls the fused yaw. The matcher's variance is the
    /// calibrated one, so it is the Madgwick variance that is taken as wrong.
    pub innovation_gate: f64,
}

impl Default for FuserConfig {
    fn default() -> Self {
        Self {
            policy: OmegaPolicy::default(),
            max_gap: 0.1,
            history: 2.0,
            alignment_duration: 2.0,
            alignment_min_pairs: 5,
            noise: MadgwickNoise::default(),
            field_reference: None,
            innovation_gate: 3.0,
        }
    }
}

/// Madgwick samples kept at most (2 s at 2 kHz), whatever `history` says.
const MAX_BUFFERED_SAMPLES: usize = 4096;
/// Matcher poses waiting at most (three minutes at 5.5 Hz); beyond, the oldest goes out unfused.
const MAX_PENDING_POSES: usize = 1024;

#[derive(Debug, Clone, Copy)]
struct Buffered {
    time: f64,
    /// Yaw unwrapped along the stream (rad).
    yaw: f64,
    variance: Option<f64>,
    field: Option<MagneticField>,
}

/// The field's mean over the first seconds, for a reference nobody configured.
#[derive(Debug, Clone, Copy, Default)]
struct FieldMean {
    first_time: Option<f64>,
    sum_magnitude: f64,
    sum_dip: f64,
    count: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Starting,
    Fusing,
    FallenBack,
}

enum Bracket {
    Found(Buffered, Buffered),
    Never,
    Wait,
}

/// Fuses the Madgwick yaw with the matcher's at each matcher pose, streams joined by sample time.
///
/// Feed it both streams as they come ([`YawFuser::push_madgwick`], [`YawFuser::push_matcher`],
/// each in its own time order, in any interleaving) and, if the caller knows it, how far the
/// Madgwick stream has certainly come ([`YawFuser::advance_to`]: a pipeline ordered by sample
/// time knows it from every frame it releases). Each call returns the poses it could settle, in
/// time order: a pose waits until Madgwick samples bracket its time, or until it is clear none
/// will within [`FuserConfig::max_gap`] (then the matcher's yaw alone, see [`YawSource`]).
#[derive(Debug, Clone)]
pub struct YawFuser {
    config: FuserConfig,
    samples: VecDeque<Buffered>,
    /// The last Madgwick sample's time, raw yaw and unwrapped yaw.
    last_sample: Option<(f64, f64, f64)>,
    watermark: f64,
    pending: VecDeque<MatcherYaw>,
    last_matcher_time: Option<f64>,
    alignment: YawAlignment,
    aligned: Option<AlignmentEstimate>,
    field_mean: FieldMean,
    variance_model: Option<MadgwickVariance>,
    mode: Mode,
}

impl YawFuser {
    /// A fuser that estimates the frame alignment over its first seconds; refuses a config
    /// with a non-finite value, or a non-positive κ, gap, history, alignment duration, β,
    /// sample period or field timeout.
    pub fn new(config: FuserConfig) -> Result<Self, FusionError> {
        if let OmegaPolicy::Literal { kappa } = config.policy {
            positive("the literal ω rule's κ", kappa)?;
        }
        positive("max_gap", config.max_gap)?;
        positive("history", config.history)?;
        positive("alignment_duration", config.alignment_duration)?;
        if finite("innovation_gate", config.innovation_gate)? < 0.0 {
            return Err(FusionError::NotPositive {
                what: "innovation_gate",
                value: config.innovation_gate,
            });
        }
        let noise = &config.noise;
        positive("noise.beta", noise.beta)?;
        positive("noise.sample_period", noise.sample_period)?;
        positive("noise.field_timeout", noise.field_timeout)?;
        for (what, value) in [
            ("noise.gyro_noise_density", noise.gyro_noise_density),
            ("noise.gyro_bias_residual", noise.gyro_bias_residual),
            ("noise.heading_floor", noise.heading_floor),
            ("noise.field_tolerance", noise.field_tolerance),
            ("noise.disturbance_gain", noise.disturbance_gain),
        ] {
            if finite(what, value)? < 0.0 {
                return Err(FusionError::NotPositive { what, value });
            }
        }
        if let Some(reference) = config.field_reference {
            positive("the reference field's magnitude", reference.magnitude)?;
            finite("the reference field's dip", reference.dip)?;
        }
        Ok(Self {
            config,
            samples: VecDeque::new(),
            last_sample: None,
            watermark: f64::NEG_INFINITY,
            pending: VecDeque::new(),
            last_matcher_time: None,
            alignment: YawAlignment::new(),
            aligned: None,
            field_mean: FieldMean::default(),
            variance_model: config
                .field_reference
                .map(|reference| MadgwickVariance::new(config.noise, reference)),
            mode: Mode::Starting,
        })
    }

    /// A fuser with a known frame alignment (fuses from the first pose).
    pub fn with_alignment(
        config: FuserConfig,
        alignment: AlignmentEstimate,
    ) -> Result<Self, FusionError> {
        finite("the alignment's offset", alignment.offset)?;
        if finite("the alignment's variance", alignment.variance)? < 0.0 {
            return Err(FusionError::NotPositive {
                what: "the alignment's variance",
                value: alignment.variance,
            });
        }
        let mut fuser = Self::new(config)?;
        fuser.aligned = Some(alignment);
        Ok(fuser)
    }

    /// The frame alignment, once estimated (or given).
    pub fn alignment(&self) -> Option<AlignmentEstimate> {
        self.aligned
    }

    /// The calibrated field the variance model compares readings with, once known.
    pub fn field_reference(&self) -> Option<MagneticField> {
        self.variance_model.map(|model| *model.reference())
    }

    /// Takes one Madgwick sample (times strictly increasing); returns the poses it settles.
    pub fn push_madgwick(&mut self, sample: MadgwickYaw) -> Result<Vec<FusedYaw>, FusionError> {
        let time = finite("Madgwick sample time", sample.time)?;
        let raw = finite("Madgwick yaw", sample.yaw)?;
        let (given, field) = match sample.uncertainty {
            MadgwickUncertainty::Variance(v) => (Some(positive("Madgwick yaw variance", v)?), None),
            MadgwickUncertainty::Field(field) => {
                if let Some(f) = field {
                    positive("field magnitude", f.magnitude)?;
                    finite("field dip", f.dip)?;
                }
                (None, field)
            }
        };
        if let Some((previous, _, _)) = self.last_sample
            && time <= previous
        {
            return Err(FusionError::OutOfOrder {
                what: "Madgwick sample",
                time,
                previous,
            });
        }
        let yaw = match self.last_sample {
            Some((_, last_raw, last_unwrapped)) => last_unwrapped + wrap_angle(raw - last_raw),
            None => raw,
        };
        self.last_sample = Some((time, raw, yaw));
        let is_field_sample = matches!(sample.uncertainty, MadgwickUncertainty::Field(_));
        let variance = match (given, &mut self.variance_model) {
            (Some(v), _) => Some(v),
            (None, Some(model)) => Some(model.update(time, field.as_ref())),
            (None, None) => None,
        };
        self.samples.push_back(Buffered {
            time,
            yaw,
            variance,
            field,
        });
        if is_field_sample && self.variance_model.is_none() {
            self.learn_field_reference(time, field);
        }
        self.prune();
        Ok(self.settle())
    }

    /// Takes one matcher pose (times strictly increasing); returns the poses it settles.
    pub fn push_matcher(&mut self, pose: MatcherYaw) -> Result<Vec<FusedYaw>, FusionError> {
        let time = finite("matcher pose time", pose.time)?;
        finite("matcher yaw", pose.yaw)?;
        if finite("matcher yaw variance", pose.variance)? < 0.0 {
            return Err(FusionError::NotPositive {
                what: "matcher yaw variance",
                value: pose.variance,
            });
        }
        if let Some(previous) = self.last_matcher_time
            && time <= previous
        {
            return Err(FusionError::OutOfOrder {
                what: "matcher pose",
                time,
                previous,
            });
        }
        self.last_matcher_time = Some(time);
        self.pending.push_back(pose);
        let mut settled = Vec::new();
        while self.pending.len() > MAX_PENDING_POSES {
            let oldest = self.pending.pop_front().expect("more than the cap");
            settled.push(self.unfused(&oldest, MatcherOnlyReason::NoMadgwickWithinGap));
        }
        settled.extend(self.settle());
        Ok(settled)
    }

    /// Says that no Madgwick sample at or before `time` (s) is still to come (`f64::INFINITY`:
    /// the stream has ended); returns the poses this settles (those left without a Madgwick
    /// sample within the gap).
    pub fn advance_to(&mut self, time: f64) -> Vec<FusedYaw> {
        if time > self.watermark {
            self.watermark = time;
        }
        self.settle()
    }

    /// Mean field over the first `alignment_duration` seconds of samples; the reference is fixed
    /// with the first sample past them, and the samples kept so far get their variances.
    fn learn_field_reference(&mut self, time: f64, field: Option<MagneticField>) {
        let first = *self.field_mean.first_time.get_or_insert(time);
        if time - first <= self.config.alignment_duration {
            if let Some(f) = field {
                self.field_mean.sum_magnitude += f.magnitude;
                self.field_mean.sum_dip += f.dip;
                self.field_mean.count += 1;
            }
            return;
        }
        if self.field_mean.count == 0 {
            return;
        }
        let n = self.field_mean.count as f64;
        let reference = MagneticField {
            magnitude: self.field_mean.sum_magnitude / n,
            dip: self.field_mean.sum_dip / n,
        };
        let mut model = MadgwickVariance::new(self.config.noise, reference);
        for sample in self.samples.iter_mut() {
            if sample.variance.is_none() {
                sample.variance = Some(model.update(sample.time, sample.field.as_ref()));
            }
        }
        self.variance_model = Some(model);
    }

    fn prune(&mut self) {
        let Some(newest) = self.samples.back().map(|s| s.time) else {
            return;
        };
        let cutoff = newest - self.config.history;
        while self.samples.len() > MAX_BUFFERED_SAMPLES
            || self.samples.front().is_some_and(|s| s.time < cutoff)
        {
            self.samples.pop_front();
        }
    }

    /// The Madgwick samples around `time`, if they are (or will be) there.
    fn bracket(&self, time: f64) -> Bracket {
        let gap = self.config.max_gap;
        let i = self.samples.partition_point(|s| s.time <= time);
        let before = i.checked_sub(1).map(|j| self.samples[j]);
        let after = match before {
            Some(b) if b.time == time => Some(b),
            _ => self.samples.get(i).copied(),
        };
        match (before, after) {
            (Some(b), Some(a)) if time - b.time <= gap && a.time - time <= gap => {
                Bracket::Found(b, a)
            }
            (_, Some(_)) => Bracket::Never,
            (_, None) => {
                let horizon = self
                    .last_sample
                    .map_or(self.watermark, |(t, _, _)| t.max(self.watermark));
                if horizon >= time + gap {
                    Bracket::Never
                } else {
                    Bracket::Wait
                }
            }
        }
    }

    fn settle(&mut self) -> Vec<FusedYaw> {
        let mut settled = Vec::new();
        while let Some(&pose) = self.pending.front() {
            let out = match self.bracket(pose.time) {
                Bracket::Wait => break,
                Bracket::Never => self.unfused(&pose, MatcherOnlyReason::NoMadgwickWithinGap),
                Bracket::Found(before, after) => self.fuse(&pose, &before, &after),
            };
            self.pending.pop_front();
            settled.push(out);
        }
        settled
    }

    fn unfused(&mut self, pose: &MatcherYaw, reason: MatcherOnlyReason) -> FusedYaw {
        let notice = match reason {
            MatcherOnlyReason::NoMadgwickWithinGap if self.mode != Mode::FallenBack => {
                self.mode = Mode::FallenBack;
                Some(FusionNotice::FallingBack)
            }
            _ => None,
        };
        FusedYaw {
            time: pose.time,
            estimate: YawEstimate::new(pose.yaw, pose.variance),
            source: YawSource::MatcherOnly(reason),
            notice,
        }
    }

    fn fuse(&mut self, pose: &MatcherYaw, before: &Buffered, after: &Buffered) -> FusedYaw {
        let u = if after.time > before.time {
            (pose.time - before.time) / (after.time - before.time)
        } else {
            0.0
        };
        let yaw = wrap_angle(before.yaw + u * (after.yaw - before.yaw));
        let mut notice = None;
        let alignment = match self.aligned {
            Some(a) => a,
            None => {
                self.alignment.add(pose.time, pose.yaw, yaw);
                let ready = self.alignment.span() >= self.config.alignment_duration
                    && self.alignment.count() >= self.config.alignment_min_pairs;
                match self.alignment.estimate().filter(|_| ready) {
                    Some(a) => {
                        self.aligned = Some(a);
                        notice = Some(FusionNotice::Aligned(a));
                        a
                    }
                    None => return self.unfused(pose, MatcherOnlyReason::Aligning),
                }
            }
        };
        let with_notice = |mut out: FusedYaw| {
            out.notice = out.notice.or(notice);
            out
        };
        let (Some(vb), Some(va)) = (before.variance, after.variance) else {
            return with_notice(self.unfused(pose, MatcherOnlyReason::MadgwickVarianceUnknown));
        };
        if pose.variance == 0.0 {
            return with_notice(self.unfused(pose, MatcherOnlyReason::ExactMatcher));
        }
        let mut madgwick = alignment.apply(YawEstimate::new(yaw, vb + u * (va - vb)));
        let matcher = YawEstimate::new(pose.yaw, pose.variance);
        let gate = self.config.innovation_gate;
        if gate > 0.0 {
            let innovation = wrap_angle(matcher.mean - madgwick.mean);
            let needed = innovation * innovation / (gate * gate) - matcher.variance;
            madgwick.variance = madgwick
                .variance
                .max(needed)
                .min(UNKNOWN_HEADING_SIGMA * UNKNOWN_HEADING_SIGMA);
        }
        let fused = match ci_yaw(madgwick, matcher, self.config.policy) {
            Ok(fused) => fused,
            // Cannot happen: the inputs and the config's κ were checked on the way in.
            Err(_) => {
                return with_notice(self.unfused(pose, MatcherOnlyReason::MadgwickVarianceUnknown));
            }
        };
        if notice.is_none() && self.mode == Mode::FallenBack {
            notice = Some(FusionNotice::Resumed);
        }
        self.mode = Mode::Fusing;
        FusedYaw {
            time: pose.time,
            estimate: fused.estimate,
            source: YawSource::Fused {
                omega: fused.omega,
                madgwick,
            },
            notice,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn deg(x: f64) -> f64 {
        x.to_radians()
    }

    fn deg2(x: f64) -> f64 {
        x * (PI / 180.0) * (PI / 180.0)
    }

    fn yaw_deg(mean: f64, variance_deg2: f64) -> YawEstimate {
        YawEstimate::new(deg(mean), deg2(variance_deg2))
    }

    /// The paper's eq. 3 exactly as printed, μ̂ = P̂((1−ω)P̂⁻¹μ + ωQ⁻¹μ′)⁻¹: the misprint the
    /// module corrects, kept only to pin down what "as printed" gives.
    fn paper_eq3_as_printed(mu: f64, p: f64, mu_prime: f64, q: f64, omega: f64) -> f64 {
        let p_hat = 1.0 / ((1.0 - omega) / p + omega / q);
        p_hat / ((1.0 - omega) / p_hat * mu + omega / q * mu_prime)
    }

    #[test]
    fn the_literal_rule_reproduces_the_research_vector() {
        // μ = 10°, P = 4 deg², μ′ = 14°, Q = 1 deg², ω = 0.3 (κ = 0.3·P).
        let p = deg2(4.0);
        let fused = ci_yaw(
            yaw_deg(10.0, 4.0),
            yaw_deg(14.0, 1.0),
            OmegaPolicy::Literal { kappa: 0.3 * p },
        )
        .expect("valid");
        assert!((fused.omega - 0.3).abs() < 1e-12);
        assert!((fused.estimate.variance / deg2(1.0) - 2.105263).abs() < 1e-6);
        assert!((fused.estimate.mean.to_degrees() - 12.526316).abs() < 1e-6);
    }

    #[test]
    fn fast_ci_clamps_omega_below_one_half() {
        // ω = P/(P+Q) = 0.8, clamped to 0.5 − ε. At ω = 0.5 exactly the research vector is
        // P̂ = 1.6, μ̂ = 13.2; ε = 1e-3 moves that to 1.60064 and 13.19488.
        let fused =
            ci_yaw(yaw_deg(10.0, 4.0), yaw_deg(14.0, 1.0), OmegaPolicy::FastCi).expect("valid");
        assert_eq!(fused.omega, 0.5 - OMEGA_EPSILON);
        let variance = fused.estimate.variance / deg2(1.0);
        let mean = fused.estimate.mean.to_degrees();
        assert!(
            (variance - 1.0 / (0.501 / 4.0 + 0.499)).abs() < 1e-9,
            "{variance}"
        );
        assert!(
            (mean - (10.0 + 0.499 * variance * 4.0)).abs() < 1e-9,
            "{mean}"
        );
        assert!((variance - 1.6).abs() < 1e-2 && (mean - 13.2).abs() < 1e-2);
    }

    #[test]
    fn the_boundary_rule_pushes_omega_to_the_better_source() {
        let matcher_better = ci_yaw(
            yaw_deg(10.0, 4.0),
            yaw_deg(14.0, 1.0),
            OmegaPolicy::Boundary,
        );
        assert_eq!(matcher_better.expect("valid").omega, 0.5 - OMEGA_EPSILON);
        let madgwick_better = ci_yaw(
            yaw_deg(10.0, 1.0),
            yaw_deg(14.0, 4.0),
            OmegaPolicy::Boundary,
        );
        assert_eq!(madgwick_better.expect("valid").omega, OMEGA_EPSILON);
    }

    #[test]
    fn fusion_across_the_seam_lands_on_it_not_opposite() {
        // μ = 179°, μ′ = −179°, P = Q: the naive average is 0°, the right answer ±180°.
        let fused = ci_yaw(
            yaw_deg(179.0, 1.0),
            yaw_deg(-179.0, 1.0),
            OmegaPolicy::Boundary,
        )
        .expect("valid");
        // Boundary with P = Q gives ε; take ω near 0.5 through a literal κ.
        assert!((fused.estimate.mean.abs() - deg(179.0)).abs() < deg(0.01));
        let fused = ci_yaw(
            yaw_deg(179.0, 1.0),
            yaw_deg(-179.0, 1.0),
            OmegaPolicy::Literal { kappa: 1.0 },
        )
        .expect("valid");
        assert_eq!(fused.omega, 0.5 - OMEGA_EPSILON);
        assert!(
            (fused.estimate.mean.abs() - PI).abs() < deg(0.01),
            "{}",
            fused.estimate.mean
        );
        assert!((fused.estimate.variance / deg2(1.0) - 1.0).abs() < 1e-9);
        assert!(fused.estimate.mean > -PI && fused.estimate.mean <= PI);
    }

    #[test]
    fn eq3_as_printed_is_not_an_angle() {
        let printed = paper_eq3_as_printed(10.0, 4.0, 14.0, 1.0, 0.3);
        assert!((printed - 0.2798).abs() < 1e-4, "{printed}");
        let fused = ci_yaw(
            yaw_deg(10.0, 4.0),
            yaw_deg(14.0, 1.0),
            OmegaPolicy::Literal {
                kappa: 0.3 * deg2(4.0),
            },
        )
        .expect("valid");
        assert!((fused.estimate.mean.to_degrees() - printed).abs() > 12.0);
    }

    #[test]
    fn a_bad_config_is_refused_with_its_field() {
        let bad_beta = FuserConfig {
            noise: MadgwickNoise {
                beta: 0.0,
                ..MadgwickNoise::default()
            },
            ..FuserConfig::default()
        };
        let error = YawFuser::new(bad_beta).expect_err("β = 0");
        assert_eq!(error.to_string(), "noise.beta must be positive, got 0");
        let bad_gap = FuserConfig {
            max_gap: f64::NAN,
            ..FuserConfig::default()
        };
        assert!(YawFuser::new(bad_gap).is_err());
    }

    #[test]
    fn bad_inputs_are_refused() {
        let good = yaw_deg(0.0, 1.0);
        assert!(ci_yaw(yaw_deg(0.0, 0.0), good, OmegaPolicy::FastCi).is_err());
        assert!(ci_yaw(good, YawEstimate::new(f64::NAN, 1.0), OmegaPolicy::FastCi).is_err());
        assert!(ci_yaw(good, good, OmegaPolicy::Literal { kappa: -1.0 }).is_err());
    }

    fn any_policy() -> impl Strategy<Value = OmegaPolicy> {
        prop_oneof![
            Just(OmegaPolicy::FastCi),
            Just(OmegaPolicy::Boundary),
            (1e-8..1.0f64).prop_map(|kappa| OmegaPolicy::Literal { kappa }),
        ]
    }

    proptest! {
        #[test]
        fn the_fused_variance_is_within_the_weighted_bound(
            mu in -PI..PI, p in 1e-8..10.0f64, mu2 in -PI..PI, q in 1e-8..10.0f64,
            policy in any_policy(),
        ) {
            let fused = ci_yaw(YawEstimate::new(mu, p), YawEstimate::new(mu2, q), policy).unwrap();
            let w = fused.omega;
            let bound = (p / (1.0 - w)).min(q / w);
            prop_assert!(fused.estimate.variance <= bound * (1.0 + 1e-12));
            prop_assert!(fused.estimate.variance <= p.max(q) * (1.0 + 1e-12));
            prop_assert!(fused.estimate.variance > 0.0);
        }

        #[test]
        fn the_fused_yaw_lies_between_the_inputs_on_the_circle(
            mu in -PI..PI, p in 1e-8..10.0f64, delta in -(PI - 1e-3)..(PI - 1e-3), q in 1e-8..10.0f64,
            policy in any_policy(),
        ) {
            let mu2 = wrap_angle(mu + delta);
            let fused = ci_yaw(YawEstimate::new(mu, p), YawEstimate::new(mu2, q), policy).unwrap();
            let from_madgwick = wrap_angle(fused.estimate.mean - mu);
            let to_matcher = wrap_angle(mu2 - fused.estimate.mean);
            prop_assert!(from_madgwick * delta >= 0.0);
            prop_assert!(to_matcher * delta >= -1e-12);
            prop_assert!((from_madgwick + to_matcher - delta).abs() < 1e-9);
        }

        #[test]
        fn rotating_both_inputs_rotates_the_result(
            mu in -PI..PI, p in 1e-8..10.0f64, mu2 in -PI..PI, q in 1e-8..10.0f64,
            turn in -10.0..10.0f64, policy in any_policy(),
        ) {
            let fused = ci_yaw(YawEstimate::new(mu, p), YawEstimate::new(mu2, q), policy).unwrap();
            let turned = ci_yaw(
                YawEstimate::new(mu + turn, p),
                YawEstimate::new(mu2 + turn, q),
                policy,
            )
            .unwrap();
            prop_assert!(wrap_angle(turned.estimate.mean - fused.estimate.mean - turn).abs() < 1e-9);
            prop_assert_eq!(turned.estimate.variance, fused.estimate.variance);
            prop_assert_eq!(turned.omega, fused.omega);
        }
    }

    #[test]
    fn the_alignment_is_a_circular_mean_across_the_seam() {
        let mut alignment = YawAlignment::new();
        assert!(alignment.estimate().is_none());
        // Offsets of 179° and −179° (the matcher at 170°, Madgwick at −9° and at −11° written
        // as 349°): their mean is 180°, not 0°.
        alignment.add(0.0, deg(170.0), deg(-9.0));
        alignment.add(0.5, deg(170.0), deg(-11.0) + 2.0 * PI);
        let estimate = alignment.estimate().expect("two pairs");
        assert!(
            (estimate.offset.abs() - PI).abs() < 1e-9,
            "{}",
            estimate.offset
        );
        // Two pairs 2° apart: −2 ln cos 1° ≈ (1°)².
        assert!(
            (estimate.variance / deg2(1.0) - 1.0).abs() < 1e-3,
            "{}",
            estimate.variance
        );
        assert!((alignment.span() - 0.5).abs() < 1e-12);
        let aligned = estimate.apply(yaw_deg(-10.0, 2.0));
        assert!((aligned.mean - deg(170.0)).abs() < 1e-9);
        assert!((aligned.variance / deg2(1.0) - 3.0).abs() < 1e-3);
    }

    const EARTH: MagneticField = MagneticField {
        magnitude: 50.0,
        dip: 1.047_197_551_196_597_6, // 60°
    };

    #[test]
    fn the_steady_variance_is_finite_and_positive_and_the_gyro_term_negligible() {
        let noise = MadgwickNoise::default();
        let steady = noise.steady_variance();
        assert!(steady.is_finite() && steady > 0.0);
        assert!((UNKNOWN_HEADING_SIGMA - PI / 3f64.sqrt()).abs() < 1e-15);
        let without_floor = MadgwickNoise {
            heading_floor: 0.0,
            ..noise
        };
        // Chatter at β = 0.1, 100 Hz: ±0.115°, variance (2e-3)²/3.
        assert!((without_floor.steady_variance() - 4e-6 / 3.0).abs() < 1e-10);
        assert!((steady - without_floor.steady_variance() - deg2(1.0)).abs() < 1e-15);
    }

    #[test]
    fn the_disturbance_sigma_grows_with_the_field_error() {
        let noise = MadgwickNoise::default();
        let sigma = |magnitude_error: f64, dip_error_deg: f64| {
            noise.disturbance_sigma(
                &MagneticField {
                    magnitude: EARTH.magnitude * (1.0 + magnitude_error),
                    dip: EARTH.dip + deg(dip_error_deg),
                },
                &EARTH,
            )
        };
        // Within the tolerance: no inflation.
        assert_eq!(sigma(0.0, 0.0), 0.0);
        assert_eq!(sigma(0.02, 1.0), 0.0);
        let mut previous = 0.0;
        for k in 1..=40 {
            let e = 0.01 * f64::from(k);
            let by_magnitude = sigma(e, 0.0);
            let by_dip = sigma(0.0, e.to_degrees());
            let by_both = sigma(e, e.to_degrees());
            for s in [by_magnitude, by_dip, by_both] {
                assert!((0.0..=UNKNOWN_HEADING_SIGMA).contains(&s));
            }
            assert!(by_magnitude >= previous && by_both >= by_magnitude);
            if e > noise.field_tolerance + 0.005 {
                assert!(by_magnitude > previous, "not growing at {e}");
            }
            previous = by_magnitude;
        }
        // A 10 % magnitude error at 60° dip: 2 · (0.10 − 0.03) / cos 60° = 0.28 rad.
        assert!((sigma(0.10, 0.0) - 0.28).abs() < 1e-9);
        // Losing the magnetometer: the gyro alone drifts, monotonically.
        let mut last = 0.0;
        for t in [0.0, 0.1, 1.0, 10.0, 100.0] {
            let s = noise.unaided_sigma(t);
            assert!(s >= last && s.is_finite());
            last = s;
        }
        assert!((noise.unaided_sigma(10.0) - deg(0.5)).abs() < deg(0.01));
    }

    #[test]
    fn a_disturbance_raises_the_variance_at_once_and_lets_it_fall_at_the_correction_rate() {
        let noise = MadgwickNoise::default();
        let mut model = MadgwickVariance::new(noise, EARTH);
        let steady = noise.steady_variance();
        assert!((model.update(0.0, Some(&EARTH)) - steady).abs() < 1e-15);
        let disturbed = MagneticField {
            magnitude: 44.2,
            dip: deg(53.0),
        };
        let high = model.update(1.0, Some(&disturbed));
        assert!(high > steady + deg2(100.0), "{high}");
        // Still disturbed: as high. Back to normal: falling at 2β = 0.2 rad/s, not at once.
        assert_eq!(model.update(1.5, Some(&disturbed)), high);
        let sigma0 = (high - steady).sqrt();
        let mut previous = high;
        for k in 1..=80 {
            // Field readings 0.05 s apart, within the 0.1 s that counts as present.
            let t = 1.5 + 0.05 * f64::from(k);
            let v = model.update(t, Some(&EARTH));
            let expected = (sigma0 - 0.2 * (t - 1.5)).max(0.0);
            assert!((v - steady - expected * expected).abs() < 1e-12, "at {t}");
            assert!(v <= previous);
            previous = v;
        }
        assert!((previous - steady).abs() < 1e-15);
        // Gyro samples without a field in between do not count as absence (100 Hz field).
        assert!((model.update(5.55, None) - steady).abs() < 1e-15);
        // The magnetometer gone for 10 s: the gyro's drift.
        let gone = model.update(15.5, None);
        assert!((gone - steady - noise.unaided_sigma(10.0).powi(2)).abs() < 1e-15);
    }

    #[test]
    fn the_field_is_read_against_the_up_axis() {
        // NWU, level sensor: north 25 µT, down 43.3 µT → 50 µT at 60°.
        let field = MagneticField::from_vectors([25.0, 0.0, -43.301_270_189], [0.0, 0.0, 9.8])
            .expect("valid");
        assert!((field.magnitude - 50.0).abs() < 1e-6);
        assert!((field.dip - deg(60.0)).abs() < 1e-9);
        // The same field seen by a sensor rolled 90° about x: the up axis in its frame is the
        // filter quaternion's third row.
        let half = FRAC_PI_2 / 2.0;
        let q = [half.cos(), half.sin(), 0.0, 0.0];
        let up = up_in_sensor_frame(q);
        assert!((up[0]).abs() < 1e-12 && (up[1] - 1.0).abs() < 1e-12 && up[2].abs() < 1e-12);
        let rolled = MagneticField::from_vectors([25.0, -43.301_270_189, 0.0], up).expect("ok");
        assert!((rolled.dip - deg(60.0)).abs() < 1e-9);
        assert!(MagneticField::from_vectors([0.0; 3], up).is_none());
        // Yaw: 90° about z is facing west in NWU, +90°.
        let q = [half.cos(), 0.0, 0.0, half.sin()];
        assert!((yaw_from_quaternion(q) - FRAC_PI_2).abs() < 1e-12);
    }

    /// The truth of the synthetic runs: standing for 3 s, then turning back and forth while
    /// going round (≈ 1.3 turns in a minute, so both yaws cross ±180°).
    fn true_yaw(t: f64) -> f64 {
        let s = (t - 3.0).max(0.0);
        0.6 * (0.15 * s).sin() + 0.14 * s
    }

    /// Magnetic north in the map frame (the alignment to find).
    const NORTH_IN_MAP: f64 = 2.5;
    const MATCHER_RATE: f64 = 5.5;
    const IMU_RATE: f64 = 100.0;
    const RUN_SECONDS: f64 = 60.0;

    /// A metal object near the path between `start` and `end` (s): its field, fading in and
    /// out over a second, adds (0, 9.1, 8) µT in NWU, turning the horizontal field by −20°,
    /// shrinking |B| by 12 % and the dip by 7°.
    #[derive(Clone, Copy)]
    struct Disturbance {
        start: f64,
        end: f64,
    }

    impl Disturbance {
        fn strength(&self, t: f64) -> f64 {
            ((t - self.start).min(self.end - t)).clamp(0.0, 1.0)
        }
    }

    struct Run {
        madgwick: Vec<MadgwickYaw>,
        matcher: Vec<MatcherYaw>,
    }

    /// A run: the Madgwick filter's yaw as its fixed-step correction makes it (the gyro
    /// integrated with noise and bias, turned towards the magnetometer's heading by at most
    /// 2β·Δt per update; the heading has 1.4° of noise per reading and a residual-iron error of
    /// 0.8°·sin ψ), and the matcher's at 5.5 Hz with 0.3° of noise per pose and a slow drift
    /// (0.02° per pose as a random walk), its variance (0.3°)² (drift not included, as the
    /// mapper's). The first matcher pose defines the map frame (error 0, variance 0).
    fn synthetic_run(seed: u64, disturbance: Option<Disturbance>, imu_until: f64) -> Run {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let unit = Normal::new(0.0, 1.0).expect("σ = 1");
        let noise = MadgwickNoise::default();
        let dt = 1.0 / IMU_RATE;
        let earth = [25.0, 0.0, -43.301_270_189];
        let mut madgwick = Vec::new();
        let mut filter_yaw = -NORTH_IN_MAP;
        let mut previous_truth = true_yaw(0.0);
        let bias = deg(0.05);
        for k in 0..(RUN_SECONDS * IMU_RATE) as usize {
            let t = k as f64 * dt;
            if t >= imu_until {
                break;
            }
            let truth = true_yaw(t);
            let gyro_step = truth - previous_truth
                + bias * dt
                + noise.gyro_noise_density * dt.sqrt() * unit.sample(&mut rng);
            previous_truth = truth;
            let strength = disturbance.map_or(0.0, |d| d.strength(t));
            let delta = [0.0, 9.1 * strength, 8.0 * strength];
            let b = [
                earth[0] + delta[0],
                earth[1] + delta[1],
                earth[2] + delta[2],
            ];
            let heading_error = -(b[1]).atan2(b[0]);
            let magnetic_yaw = truth - NORTH_IN_MAP;
            let measured = magnetic_yaw
                + heading_error
                + deg(0.8) * magnetic_yaw.sin()
                + deg(1.4) * unit.sample(&mut rng);
            let predicted = filter_yaw + gyro_step;
            let step = noise.correction_rate() * dt;
            filter_yaw = predicted + wrap_angle(measured - predicted).clamp(-step, step);
            let magnitude = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
            let field = MagneticField {
                magnitude: magnitude + 0.6 * unit.sample(&mut rng),
                dip: (-b[2]).atan2(b[0].hypot(b[1])) + deg(0.5) * unit.sample(&mut rng),
            };
            madgwick.push(MadgwickYaw {
                time: t,
                yaw: wrap_angle(filter_yaw),
                uncertainty: MadgwickUncertainty::Field(Some(field)),
            });
        }
        let mut matcher = Vec::new();
        let mut drift = 0.0;
        for k in 0..(RUN_SECONDS * MATCHER_RATE) as usize {
            let t = 0.05 + k as f64 / MATCHER_RATE;
            let (error, variance) = if k == 0 {
                (0.0, 0.0)
            } else {
                drift += deg(0.02) * unit.sample(&mut rng);
                (drift + deg(0.3) * unit.sample(&mut rng), deg2(0.09))
            };
            matcher.push(MatcherYaw {
                time: t,
                yaw: wrap_angle(true_yaw(t) + error),
                variance,
            });
        }
        Run { madgwick, matcher }
    }

    /// Both streams in sample-time order (as the pipeline releases them), each matcher pose
    /// released with its revolution's end, 0.09 s after its time; the pipeline's watermark
    /// follows every frame.
    fn run_fuser(run: &Run, config: FuserConfig) -> Vec<FusedYaw> {
        let mut fuser = YawFuser::new(config).expect("valid config");
        let mut out = Vec::new();
        let (mut i, mut j) = (0, 0);
        let release = |pose: &MatcherYaw| pose.time + 0.09;
        while i < run.madgwick.len() || j < run.matcher.len() {
            let take_imu = match (run.madgwick.get(i), run.matcher.get(j)) {
                (Some(s), Some(p)) => s.time <= release(p),
                (Some(_), None) => true,
                _ => false,
            };
            if take_imu {
                let sample = run.madgwick[i];
                out.extend(fuser.push_madgwick(sample).expect("valid sample"));
                out.extend(fuser.advance_to(sample.time));
                i += 1;
            } else {
                let pose = run.matcher[j];
                out.extend(fuser.advance_to(release(&pose)));
                out.extend(fuser.push_matcher(pose).expect("valid pose"));
                j += 1;
            }
        }
        out.extend(fuser.advance_to(f64::INFINITY));
        out
    }

    fn rms(errors: &[f64]) -> f64 {
        (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt()
    }

    /// Per fused pose: (time, fused error, aligned Madgwick error, matcher error), rad.
    fn errors(run: &Run, fused: &[FusedYaw]) -> Vec<(f64, f64, f64, f64)> {
        fused
            .iter()
            .filter_map(|f| {
                let YawSource::Fused { madgwick, .. } = f.source else {
                    return None;
                };
                let truth = true_yaw(f.time);
                let matcher = run.matcher.iter().find(|p| p.time == f.time)?;
                Some((
                    f.time,
                    wrap_angle(f.estimate.mean - truth),
                    wrap_angle(madgwick.mean - truth),
                    wrap_angle(matcher.yaw - truth),
                ))
            })
            .collect()
    }

    #[test]
    fn the_fused_yaw_is_no_worse_than_the_better_source() {
        for seed in [1, 2, 3] {
            let run = synthetic_run(seed, None, f64::INFINITY);
            let fused = run_fuser(&run, FuserConfig::default());
            assert_eq!(fused.len(), run.matcher.len(), "every pose comes out once");
            let aligned = fused.iter().find_map(|f| match f.notice {
                Some(FusionNotice::Aligned(a)) => Some(a),
                _ => None,
            });
            let aligned = aligned.expect("aligned within the run");
            assert!(wrap_angle(aligned.offset - NORTH_IN_MAP).abs() < deg(2.0));
            let e = errors(&run, &fused);
            assert!(e.len() > 300, "{} fused of {}", e.len(), fused.len());
            let fused_rms = rms(&e.iter().map(|x| x.1).collect::<Vec<_>>());
            let madgwick_rms = rms(&e.iter().map(|x| x.2).collect::<Vec<_>>());
            let matcher_rms = rms(&e.iter().map(|x| x.3).collect::<Vec<_>>());
            println!(
                "seed {seed}: yaw RMSE fused {:.3}°, Madgwick {:.3}°, matcher {:.3}°; \
                 fused/Madgwick {:.2}, fused/matcher {:.2} (alignment {:.2}° off)",
                fused_rms.to_degrees(),
                madgwick_rms.to_degrees(),
                matcher_rms.to_degrees(),
                fused_rms / madgwick_rms,
                fused_rms / matcher_rms,
                wrap_angle(aligned.offset - NORTH_IN_MAP).to_degrees(),
            );
            assert!(fused_rms <= madgwick_rms.min(matcher_rms), "seed {seed}");
        }
    }

    #[test]
    fn a_magnetic_disturbance_does_not_pull_the_fused_yaw() {
        let disturbance = Disturbance {
            start: 25.0,
            end: 37.0,
        };
        let run = synthetic_run(7, Some(disturbance), f64::INFINITY);
        // Over the stretch and the filter's recovery after it: the worst |yaw error| of the
        // fused yaw, Madgwick and the matcher, and the worst pull of the fused yaw away from
        // the matcher's.
        let stretch_worst = |config: FuserConfig| {
            let fused = run_fuser(&run, config);
            let e = errors(&run, &fused);
            let stretch: Vec<_> = e
                .iter()
                .filter(|x| x.0 >= disturbance.start && x.0 <= disturbance.end + 3.0)
                .collect();
            assert!(stretch.len() > 50);
            let worst = |pick: fn(&(f64, f64, f64, f64)) -> f64| {
                stretch.iter().map(|x| pick(x).abs()).fold(0.0, f64::max)
            };
            (
                worst(|x| x.1),
                worst(|x| x.2),
                worst(|x| x.3),
                worst(|x| wrap_angle(x.1 - x.3)),
            )
        };
        let (fused_max, madgwick_max, matcher_max, pull) = stretch_worst(FuserConfig::default());
        // The same run with the variance model blind to the field.
        let blind = FuserConfig {
            noise: MadgwickNoise {
                disturbance_gain: 0.0,
                ..MadgwickNoise::default()
            },
            // Without the gate either: the model alone is what this compares.
            innovation_gate: 0.0,
            ..FuserConfig::default()
        };
        let (blind_max, _, _, blind_pull) = stretch_worst(blind);
        println!(
            "disturbed stretch: max |yaw error| fused {:.3}°, Madgwick {:.3}°, matcher {:.3}°; \
             max pull from the matcher {:.3}° (variance model blind to the field: error {:.3}°, \
             pull {:.3}°)",
            fused_max.to_degrees(),
            madgwick_max.to_degrees(),
            matcher_max.to_degrees(),
            pull.to_degrees(),
            blind_max.to_degrees(),
            blind_pull.to_degrees(),
        );
        assert!(madgwick_max > deg(18.0), "the disturbance is real");
        assert!(fused_max < deg(2.0), "the fusion followed it");
        assert!(
            pull < deg(0.5) && pull < blind_pull / 3.0,
            "the field did not count"
        );
    }

    #[test]
    fn the_innovation_gate_keeps_an_error_the_model_cannot_see_out() {
        // Madgwick 30° off while its variance says 1°: iron the field model cannot see.
        let fuse = |gate: f64| {
            let config = FuserConfig {
                innovation_gate: gate,
                ..FuserConfig::default()
            };
            let alignment = AlignmentEstimate {
                offset: 0.0,
                variance: 0.0,
            };
            let mut fuser = YawFuser::with_alignment(config, alignment).expect("valid");
            for k in 0..20 {
                let sample = MadgwickYaw {
                    time: 0.01 * f64::from(k),
                    yaw: deg(30.0),
                    uncertainty: MadgwickUncertainty::Variance(deg2(1.0)),
                };
                fuser.push_madgwick(sample).expect("valid");
            }
            let pose = MatcherYaw {
                time: 0.1,
                yaw: 0.0,
                variance: deg2(0.5),
            };
            let mut out = fuser.push_matcher(pose).expect("valid");
            out.pop().expect("settled").estimate.mean.to_degrees()
        };
        let ungated = fuse(0.0);
        let gated = fuse(3.0);
        assert!(ungated > 5.0, "{ungated}");
        // Raised until the innovation is 3σ: Madgwick's variance (30/3)² − 0.25 ≈ 100 deg²,
        // which leaves it 0.15° of pull (ω stays below 0.5).
        assert!(gated.abs() < 0.3, "{gated}");
    }

    #[test]
    fn when_the_imu_stops_the_matcher_goes_on_alone_and_says_so_once() {
        let run = synthetic_run(11, None, 30.0);
        let fused = run_fuser(&run, FuserConfig::default());
        assert_eq!(fused.len(), run.matcher.len());
        let notices: Vec<_> = fused
            .iter()
            .filter_map(|f| f.notice.map(|n| (f.time, n)))
            .collect();
        assert_eq!(notices.len(), 2, "{notices:?}");
        assert!(matches!(notices[0].1, FusionNotice::Aligned(_)));
        assert_eq!(notices[1].1, FusionNotice::FallingBack);
        assert!(
            notices[1].0 > 29.9 && notices[1].0 < 30.2,
            "{}",
            notices[1].0
        );
        for (f, pose) in fused.iter().zip(&run.matcher) {
            assert_eq!(f.time, pose.time);
            if f.time > 30.0 {
                assert_eq!(
                    f.source,
                    YawSource::MatcherOnly(MatcherOnlyReason::NoMadgwickWithinGap)
                );
                assert_eq!(f.estimate.mean, pose.yaw);
            }
        }
    }

    #[test]
    fn the_streams_are_joined_by_sample_time_not_by_arrival() {
        let run = synthetic_run(5, None, f64::INFINITY);
        let in_time_order = run_fuser(&run, FuserConfig::default());
        // Every matcher pose first, then the IMU: each pose waits for its samples.
        let mut fuser = YawFuser::new(FuserConfig::default()).expect("valid config");
        let mut late_imu = Vec::new();
        for pose in &run.matcher {
            late_imu.extend(fuser.push_matcher(*pose).expect("valid"));
        }
        assert!(
            late_imu.is_empty(),
            "nothing settles before the IMU's samples"
        );
        for sample in &run.madgwick {
            late_imu.extend(fuser.push_madgwick(*sample).expect("valid"));
        }
        late_imu.extend(fuser.advance_to(f64::INFINITY));
        assert_eq!(late_imu, in_time_order);
    }

    #[test]
    fn the_madgwick_yaw_is_interpolated_at_the_pose_time_across_the_seam() {
        let config = FuserConfig {
            policy: OmegaPolicy::Literal { kappa: 1.0 },
            ..FuserConfig::default()
        };
        let identity = AlignmentEstimate {
            offset: 0.0,
            variance: 0.0,
        };
        let mut fuser = YawFuser::with_alignment(config, identity).expect("valid config");
        let sample = |time: f64, yaw: f64| MadgwickYaw {
            time,
            yaw: deg(yaw),
            uncertainty: MadgwickUncertainty::Variance(deg2(1.0)),
        };
        fuser.push_madgwick(sample(0.0, 178.0)).expect("valid");
        let pose = MatcherYaw {
            time: 0.05,
            yaw: deg(-180.0),
            variance: deg2(1.0),
        };
        assert!(fuser.push_matcher(pose).expect("valid").is_empty());
        let out = fuser.push_madgwick(sample(0.1, -178.0)).expect("valid");
        assert_eq!(out.len(), 1);
        let YawSource::Fused { madgwick, omega } = out[0].source else {
            panic!("not fused: {:?}", out[0].source);
        };
        // Halfway from 178° to −178° the short way is 180°, not 0°.
        assert!((madgwick.mean.abs() - PI).abs() < 1e-9, "{}", madgwick.mean);
        assert!((out[0].estimate.mean.abs() - PI).abs() < 1e-9);
        assert_eq!(omega, 0.5 - OMEGA_EPSILON);
        // Out of order or non-finite: refused with the reason.
        assert!(matches!(
            fuser.push_madgwick(sample(0.1, 0.0)),
            Err(FusionError::OutOfOrder { .. })
        ));
        assert!(
            fuser
                .push_matcher(MatcherYaw {
                    time: f64::NAN,
                    ..pose
                })
                .is_err()
        );
    }
}
