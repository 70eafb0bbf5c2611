//! Madgwick orientation filter (MARG and IMU-only), pure and deterministic.
//!
//! The filter fuses a gyroscope (rad/s) with an accelerometer and, optionally, a magnetometer
//! into an attitude quaternion. Each update integrates the gyro rate and then takes one step of
//! fixed length `β` (rad/s) down the normalised gradient of the misfit between the measured
//! directions (gravity, magnetic field) and the ones the current estimate predicts. `β` is the
//! trust in the gyro: Madgwick's report sets β = √(3/4)·ω̃ with ω̃ the gyro's zero-mean error
//! per axis (rad/s); larger β corrects faster but lets accel/mag noise through. Default 0.1, as
//! x-io and ROS `imu_filter_madgwick`.
//!
//! **Conventions** (those of x-io's `MadgwickAHRS.c`, the `ahrs` Python package and the
//! reference vectors in `testdata/madgwick/`):
//! - the quaternion is Hamilton, scalar first, and rotates sensor vectors into the earth frame:
//!   v_earth = q ⊗ v_sensor ⊗ q*;
//! - the earth frame is **NWU**: x = magnetic north (horizontal), y = west, z = up;
//! - the accelerometer reads **+g on the up axis** at rest (a level sensor reads (0, 0, +g));
//! - the magnetic reference is b = (b_x, 0, b_z) in that frame, recomputed every update from the
//!   measured field, so the filter is immune to the local inclination.
//!
//! **The factor 2.** The magnetic rows of the objective are written with 2·b_x and 2·b_z.
//! x-io's published C/C# code stores b_x and b_z in variables named `_2bx`/`_2bz` without
//! doubling them, which halves the predicted field and changes the convergence path (0.06 in a
//! quaternion component on the reference run). This port uses the correct form, as `ahrs` and
//! ROS do, and matches the reference vectors to ~1e-15.
//!
//! Arithmetic is f64 with exact square roots (no "fast inverse square root": it moves outputs by
//! ~3e-3 and x-io's version of it is undefined behaviour on 64-bit Linux).

use nalgebra::{Matrix3, Matrix3x4, Matrix6x4, Quaternion, Rotation3, UnitQuaternion, Vector3};
use serde::Deserialize;

/// Default filter gain β (rad/s), as x-io's `betaDef` and ROS `imu_filter_madgwick`.
pub const DEFAULT_BETA: f64 = 0.1;

/// Below this sine of the angle between the field and gravity the heading of an e-compass is
/// undefined (free fall is caught separately, as a zero accelerometer).
const MIN_FIELD_GRAVITY_SINE: f64 = 1e-6;

/// Why a filter could not be built or reconfigured.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MadgwickError {
    /// β must be finite and non-negative.
    #[error("Madgwick gain beta must be finite and >= 0, got {0}")]
    InvalidGain(f64),
    /// An explicit initial quaternion was zero-length or not finite.
    #[error("initial quaternion [w, x, y, z] = {0:?} is not a finite, non-zero quaternion")]
    InvalidQuaternion([f64; 4]),
    /// The accelerometer read zero or non-finite values, so "up" is unknown.
    #[error("accelerometer reading {0:?} gives no gravity direction")]
    NoGravity([f64; 3]),
    /// The magnetometer read zero, non-finite, or a field (anti)parallel to gravity, so north is
    /// unknown.
    #[error("magnetometer reading {0:?} gives no horizontal field direction")]
    NoHeading([f64; 3]),
}

/// Which correction an update applied (useful to count fallbacks in statistics).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpdateKind {
    /// Gyro + gravity + magnetic field (9-axis).
    Marg,
    /// Gyro + gravity: no usable magnetometer reading (zero or non-finite), or `update_imu`.
    Imu,
    /// Gyro integration only: the accelerometer read zero or non-finite values (or the gradient
    /// vanished because the estimate already explains the measurements exactly).
    GyroOnly,
    /// Nothing changed: the gyro sample or `dt` was not finite, or `dt` was negative.
    Rejected,
}

/// `[imu.madgwick]`-style configuration: the gain and how to initialise.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MadgwickConfig {
    /// Filter gain β (rad/s); see the module docs. Default 0.1.
    pub beta: f64,
    /// Explicit start orientation `[w, x, y, z]` (normalised on use). When absent the filter
    /// starts from the first accelerometer + magnetometer pair (an e-compass), which avoids
    /// the many seconds β needs to remove a large initial heading error.
    pub initial_orientation: Option<[f64; 4]>,
}

impl Default for MadgwickConfig {
    fn default() -> Self {
        Self {
            beta: DEFAULT_BETA,
            initial_orientation: None,
        }
    }
}

impl MadgwickConfig {
    /// Builds the filter: from `initial_orientation` if configured, otherwise from this first
    /// `accel` + `mag` pair (see [`orientation_from_accel_mag`]).
    pub fn start(&self, accel: Vector3<f64>, mag: Vector3<f64>) -> Result<Madgwick, MadgwickError> {
        match self.initial_orientation {
            Some(wxyz) => Madgwick::new(self.beta, unit_from_wxyz(wxyz)?),
            None => Madgwick::from_accel_mag(self.beta, accel, mag),
        }
    }
}

/// Normalises a `[w, x, y, z]` quaternion, refusing zero-length or non-finite ones.
fn unit_from_wxyz(wxyz: [f64; 4]) -> Result<UnitQuaternion<f64>, MadgwickError> {
    let [w, x, y, z] = wxyz;
    let q = Quaternion::new(w, x, y, z);
    let norm = q.norm();
    if !norm.is_finite() || norm <= f64::MIN_POSITIVE {
        return Err(MadgwickError::InvalidQuaternion(wxyz));
    }
    Ok(UnitQuaternion::new_unchecked(q / norm))
}

/// The attitude of a static sensor from one accelerometer + magnetometer pair (an e-compass,
/// TRIAD style, in the filter's NWU earth frame).
///
/// Up = â, east = (m̂ × â)/|m̂ × â|, north = up × east, west = −east; the rotation whose rows are
/// north, west, up (each in sensor coordinates) maps sensor vectors into the earth frame, and
/// its quaternion is returned with w ≥ 0. Units of `accel` and `mag` do not matter. Heading is
/// magnetic (no declination). Fails on free fall, on a missing field and on a field along
/// gravity (at a magnetic pole, or with a badly calibrated magnetometer).
pub fn orientation_from_accel_mag(
    accel: Vector3<f64>,
    mag: Vector3<f64>,
) -> Result<UnitQuaternion<f64>, MadgwickError> {
    let up = normalised(accel).ok_or(MadgwickError::NoGravity(accel.into()))?;
    let field = normalised(mag).ok_or(MadgwickError::NoHeading(mag.into()))?;
    let east = field.cross(&up);
    let sine = east.norm();
    if sine.is_nan() || sine < MIN_FIELD_GRAVITY_SINE {
        return Err(MadgwickError::NoHeading(mag.into()));
    }
    let east = east / sine;
    let north = up.cross(&east);
    let west = -east;
    let earth_from_sensor =
        Matrix3::from_rows(&[north.transpose(), west.transpose(), up.transpose()]);
    let q =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(earth_from_sensor));
    Ok(if q.w < 0.0 {
        UnitQuaternion::new_unchecked(-q.into_inner())
    } else {
        q
    })
}

/// `v / |v|`, or `None` when `v` is zero or not finite.
fn normalised(v: Vector3<f64>) -> Option<Vector3<f64>> {
    let norm = v.norm();
    (norm.is_finite() && norm > 0.0).then(|| v / norm)
}

/// The Madgwick filter state: the current orientation and the gain.
///
/// Pure: every update takes the sample and its time step and returns which correction it
/// applied; no clocks, no I/O. Not-finite inputs never poison the state (see [`UpdateKind`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Madgwick {
    /// Unit quaternion, earth-from-sensor (see the module docs).
    q: Quaternion<f64>,
    /// Gain β, rad/s.
    beta: f64,
}

impl Madgwick {
    /// A filter starting at `initial` (earth-from-sensor, NWU) with gain `beta` (rad/s).
    pub fn new(beta: f64, initial: UnitQuaternion<f64>) -> Result<Self, MadgwickError> {
        check_gain(beta)?;
        Ok(Self {
            q: initial.into_inner(),
            beta,
        })
    }

    /// A filter starting from the e-compass attitude of the first `accel` + `mag` pair
    /// ([`orientation_from_accel_mag`]).
    pub fn from_accel_mag(
        beta: f64,
        accel: Vector3<f64>,
        mag: Vector3<f64>,
    ) -> Result<Self, MadgwickError> {
        Self::new(beta, orientation_from_accel_mag(accel, mag)?)
    }

    /// The gain β (rad/s).
    pub fn beta(&self) -> f64 {
        self.beta
    }

    /// Changes β, e.g. a high gain while settling and a low one afterwards.
    pub fn set_beta(&mut self, beta: f64) -> Result<(), MadgwickError> {
        check_gain(beta)?;
        self.beta = beta;
        Ok(())
    }

    /// The current orientation (rotates sensor vectors into the NWU earth frame).
    pub fn quaternion(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::new_unchecked(self.q)
    }

    /// The current orientation as raw `[w, x, y, z]` (for frames on the wire).
    pub fn wxyz(&self) -> [f64; 4] {
        [self.q.w, self.q.i, self.q.j, self.q.k]
    }

    /// `(roll, pitch, yaw)` in radians, Z-Y-X (yaw about earth z, then pitch, then roll);
    /// yaw is counter-clockwise from magnetic north, in (−π, π].
    pub fn euler(&self) -> (f64, f64, f64) {
        self.quaternion().euler_angles()
    }

    /// One 9-axis update: `gyro` in rad/s, `accel` and `mag` in any units (only directions are
    /// used), `dt_s` the time since the previous sample.
    ///
    /// A zero or non-finite `mag` falls back to [`Madgwick::update_imu`]; a zero or
    /// non-finite `accel` skips the correction (gyro integration only), as x-io does.
    pub fn update_marg(
        &mut self,
        gyro: Vector3<f64>,
        accel: Vector3<f64>,
        mag: Vector3<f64>,
        dt_s: f64,
    ) -> UpdateKind {
        if !gyro_step_valid(&gyro, dt_s) {
            return UpdateKind::Rejected;
        }
        let Some(m) = normalised(mag) else {
            return self.update_imu(gyro, accel, dt_s);
        };
        let Some(a) = normalised(accel) else {
            return self.integrate(gyro, None, dt_s);
        };
        let q = self.q;
        let (q0, q1, q2, q3) = (q.w, q.i, q.j, q.k);

        // Earth-frame direction of the measured field, h = q ⊗ m ⊗ q*; the reference keeps its
        // horizontal magnitude on north and its vertical part on up.
        // Expanded as h = m + 2w(u × m) + 2u × (u × m) with q = (w, u), which is cheaper than
        // two quaternion products.
        let u = q.imag();
        let t = u.cross(&m) * 2.0;
        let h = m + t * q0 + u.cross(&t);
        let bx = (h.x * h.x + h.y * h.y).sqrt();
        let bz = h.z;
        let (bx2, bz2) = (2.0 * bx, 2.0 * bz);

        // Objective f (predicted minus measured directions) and its Jacobian ∂f/∂q.
        let f = nalgebra::Vector6::new(
            2.0 * (q1 * q3 - q0 * q2) - a.x,
            2.0 * (q0 * q1 + q2 * q3) - a.y,
            2.0 * (0.5 - q1 * q1 - q2 * q2) - a.z,
            bx2 * (0.5 - q2 * q2 - q3 * q3) + bz2 * (q1 * q3 - q0 * q2) - m.x,
            bx2 * (q1 * q2 - q0 * q3) + bz2 * (q0 * q1 + q2 * q3) - m.y,
            bx2 * (q0 * q2 + q1 * q3) + bz2 * (0.5 - q1 * q1 - q2 * q2) - m.z,
        );
        #[rustfmt::skip]
        let j = Matrix6x4::new(
            -2.0 * q2, 2.0 * q3, -2.0 * q0, 2.0 * q1,
            2.0 * q1, 2.0 * q0, 2.0 * q3, 2.0 * q2,
            0.0, -4.0 * q1, -4.0 * q2, 0.0,
            -bz2 * q2, bz2 * q3, -2.0 * bx2 * q2 - bz2 * q0, -2.0 * bx2 * q3 + bz2 * q1,
            -bx2 * q3 + bz2 * q1, bx2 * q2 + bz2 * q0, bx2 * q1 + bz2 * q3, -bx2 * q0 + bz2 * q2,
            bx2 * q2, bx2 * q3 - 2.0 * bz2 * q1, bx2 * q0 - 2.0 * bz2 * q2, bx2 * q1,
        );
        let gradient = j.tr_mul(&f);
        match self.integrate(gyro, Some(gradient), dt_s) {
            UpdateKind::Imu => UpdateKind::Marg,
            other => other,
        }
    }

    /// One 6-axis update (no magnetometer): heading then follows the gyro alone and drifts.
    /// `gyro` in rad/s, `accel` in any units; a zero or non-finite `accel` skips the correction.
    pub fn update_imu(&mut self, gyro: Vector3<f64>, accel: Vector3<f64>, dt_s: f64) -> UpdateKind {
        if !gyro_step_valid(&gyro, dt_s) {
            return UpdateKind::Rejected;
        }
        let Some(a) = normalised(accel) else {
            return self.integrate(gyro, None, dt_s);
        };
        let q = self.q;
        let (q0, q1, q2, q3) = (q.w, q.i, q.j, q.k);
        let f = Vector3::new(
            2.0 * (q1 * q3 - q0 * q2) - a.x,
            2.0 * (q0 * q1 + q2 * q3) - a.y,
            2.0 * (0.5 - q1 * q1 - q2 * q2) - a.z,
        );
        #[rustfmt::skip]
        let j = Matrix3x4::new(
            -2.0 * q2, 2.0 * q3, -2.0 * q0, 2.0 * q1,
            2.0 * q1, 2.0 * q0, 2.0 * q3, 2.0 * q2,
            0.0, -4.0 * q1, -4.0 * q2, 0.0,
        );
        let gradient = j.tr_mul(&f);
        self.integrate(gyro, Some(gradient), dt_s)
    }

    /// q̇ = ½ q ⊗ (0, ω) − β ∇/|∇|, then q ← normalise(q + q̇ Δt). Returns `Imu` when the
    /// gradient step was taken, `GyroOnly` when there was none (or it vanished: an exactly
    /// consistent estimate, where x-io would divide by zero).
    fn integrate(
        &mut self,
        gyro: Vector3<f64>,
        gradient: Option<nalgebra::Vector4<f64>>,
        dt_s: f64,
    ) -> UpdateKind {
        let mut q_dot = self.q * Quaternion::from_imag(gyro) * 0.5;
        let mut kind = UpdateKind::GyroOnly;
        if let Some(g) = gradient {
            let norm = g.norm();
            if norm > 0.0 && norm.is_finite() {
                let [s0, s1, s2, s3]: [f64; 4] = g.into();
                q_dot -= Quaternion::new(s0, s1, s2, s3) * (self.beta / norm);
                kind = UpdateKind::Imu;
            }
        }
        let next = self.q + q_dot * dt_s;
        let norm = next.norm();
        if !norm.is_finite() || norm <= f64::MIN_POSITIVE {
            return UpdateKind::Rejected;
        }
        self.q = next / norm;
        kind
    }
}

/// A gyro step can only be integrated with finite rates and a finite, non-negative `dt`.
fn gyro_step_valid(gyro: &Vector3<f64>, dt_s: f64) -> bool {
    gyro.iter().all(|w| w.is_finite()) && dt_s.is_finite() && dt_s >= 0.0
}

/// β must be a finite, non-negative rate.
fn check_gain(beta: f64) -> Result<(), MadgwickError> {
    if beta.is_finite() && beta >= 0.0 {
        Ok(())
    } else {
        Err(MadgwickError::InvalidGain(beta))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    /// The reference vectors vendored in the repository (testdata/madgwick/README.md).
    const DATA_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/madgwick/");
    const G: f64 = 9.80665;
    /// The reference data's earth field: 50 µT, 60° inclination (down), NWU.
    const M_EARTH: [f64; 3] = [25.0, 0.0, -43.30127018922193];

    /// Parses a reference CSV into its header and rows of f64 (the files are written with
    /// Python `repr`, so parsing gives back the exact doubles).
    fn read_csv(name: &str) -> (Vec<String>, Vec<Vec<f64>>) {
        let path = format!("{DATA_DIR}{name}");
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
        let mut lines = text.lines();
        let header: Vec<String> = lines
            .next()
            .expect("header")
            .split(',')
            .map(str::to_owned)
            .collect();
        let rows = lines
            .filter(|l| !l.is_empty())
            .map(|l| {
                l.split(',')
                    .map(|v| v.parse::<f64>().expect("number"))
                    .collect::<Vec<_>>()
            })
            .collect();
        (header, rows)
    }

    fn column(header: &[String], name: &str) -> usize {
        header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("no column {name}"))
    }

    fn vec3(row: &[f64], first: usize) -> Vector3<f64> {
        Vector3::new(row[first], row[first + 1], row[first + 2])
    }

    /// Largest component difference, treating q and −q as equal.
    fn quat_diff(a: [f64; 4], b: [f64; 4]) -> f64 {
        let same = (0..4).map(|i| (a[i] - b[i]).abs()).fold(0.0, f64::max);
        let flipped = (0..4).map(|i| (a[i] + b[i]).abs()).fold(0.0, f64::max);
        same.min(flipped)
    }

    /// Replays a reference file from q = (1, 0, 0, 0), β = 0.1, dt = 0.01 and returns the
    /// largest deviation over all rows.
    fn replay(name: &str, marg: bool) -> f64 {
        let (header, rows) = read_csv(name);
        assert_eq!(rows.len(), 1000, "{name}: expected 1000 rows");
        let (g, a, qw) = (
            column(&header, "gx_rad_s"),
            column(&header, "ax_m_s2"),
            column(&header, "qw"),
        );
        let mut filter = Madgwick::new(0.1, UnitQuaternion::identity()).expect("filter");
        let mut worst: f64 = 0.0;
        for row in &rows {
            let kind = if marg {
                let m = column(&header, "mx_uT");
                filter.update_marg(vec3(row, g), vec3(row, a), vec3(row, m), 0.01)
            } else {
                filter.update_imu(vec3(row, g), vec3(row, a), 0.01)
            };
            assert_eq!(
                kind,
                if marg {
                    UpdateKind::Marg
                } else {
                    UpdateKind::Imu
                }
            );
            let expected = [row[qw], row[qw + 1], row[qw + 2], row[qw + 3]];
            worst = worst.max(quat_diff(filter.wxyz(), expected));
        }
        worst
    }

    #[test]
    fn marg_matches_reference_file() {
        let worst = replay("reference.csv", true);
        println!("MARG max |Δq| vs reference.csv: {worst:e}");
        assert!(worst <= 1e-9, "MARG deviates by {worst:e}");
    }

    #[test]
    fn imu_matches_reference_file() {
        let worst = replay("reference_imu.csv", false);
        println!("IMU max |Δq| vs reference_imu.csv: {worst:e}");
        assert!(worst <= 1e-9, "IMU deviates by {worst:e}");
    }

    /// Sensor readings of a still sensor at `truth`: gravity (+g up) and the earth field.
    fn still_readings(truth: &UnitQuaternion<f64>) -> (Vector3<f64>, Vector3<f64>) {
        let accel = truth.inverse_transform_vector(&Vector3::new(0.0, 0.0, G));
        let mag = truth.inverse_transform_vector(&Vector3::from(M_EARTH));
        (accel, mag)
    }

    #[test]
    fn still_marg_converges_from_a_tilted_start() {
        let truth = UnitQuaternion::from_euler_angles(0.35, -0.2, 1.0);
        let (accel, mag) = still_readings(&truth);
        let start = UnitQuaternion::from_euler_angles(-0.3, 0.25, 0.6);
        let mut filter = Madgwick::new(0.1, start).expect("filter");
        assert!(filter.quaternion().angle_to(&truth) > 0.5);
        for _ in 0..3000 {
            assert_eq!(
                filter.update_marg(Vector3::zeros(), accel, mag, 0.01),
                UpdateKind::Marg
            );
        }
        // Steady-state chatter is about β·dt = 1e-3 rad.
        let error = filter.quaternion().angle_to(&truth);
        assert!(error < 3e-3, "attitude error {error} rad");
        let up = filter.quaternion().transform_vector(&accel.normalize());
        assert!((up - Vector3::z()).norm() < 3e-3, "gravity maps to {up}");
    }

    #[test]
    fn still_imu_aligns_gravity_from_a_tilted_start() {
        let truth = UnitQuaternion::from_euler_angles(-0.4, 0.3, 2.0);
        let (accel, _) = still_readings(&truth);
        let mut filter = Madgwick::new(0.1, UnitQuaternion::identity()).expect("filter");
        for _ in 0..2000 {
            assert_eq!(
                filter.update_imu(Vector3::zeros(), accel, 0.01),
                UpdateKind::Imu
            );
        }
        let up = filter.quaternion().transform_vector(&accel.normalize());
        assert!((up - Vector3::z()).norm() < 3e-3, "gravity maps to {up}");
        let (roll, pitch, _) = filter.euler();
        // Roll and pitch are observable without a magnetometer; compare tilt through the
        // truth's own angles (yaw differs, but Z-Y-X roll/pitch do not depend on it).
        assert!((roll - -0.4).abs() < 3e-3, "roll {roll}");
        assert!((pitch - 0.3).abs() < 3e-3, "pitch {pitch}");
    }

    #[test]
    fn constant_yaw_rate_integrates_to_omega_t() {
        for omega in [0.25, -0.3] {
            let mut filter = Madgwick::new(0.1, UnitQuaternion::identity()).expect("filter");
            for _ in 0..1000 {
                // Level: the gradient is exactly zero, so only the gyro acts.
                filter.update_imu(
                    Vector3::new(0.0, 0.0, omega),
                    Vector3::new(0.0, 0.0, G),
                    0.01,
                );
            }
            let (roll, pitch, yaw) = filter.euler();
            // Each first-order step q + ½q⊗ω·dt, renormalised, turns by exactly
            // 2·atan(ω·dt/2) = ω·dt − (ω·dt)³/12 + …: 1.3e-6 rad short of ω·T after 10 s.
            let stepped = 1000.0 * 2.0 * (omega * 0.01 / 2.0).atan();
            assert!((yaw - stepped).abs() < 1e-12, "yaw {yaw} for ω = {omega}");
            assert!(
                (yaw - omega * 10.0).abs() < 3e-6,
                "yaw {yaw} for ω = {omega}"
            );
            assert!(roll.abs() < 1e-12 && pitch.abs() < 1e-12);
        }
    }

    #[test]
    fn yaw_rate_on_a_tilted_marg_tracks_the_truth() {
        // Rotation about earth up at 0.4 rad/s with a 0.2 rad roll, started at the truth.
        let omega = 0.4;
        let roll = 0.2;
        let truth_at = |t: f64| {
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), omega * t)
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), roll)
        };
        let gyro = Vector3::new(0.0, omega * roll.sin(), omega * roll.cos());
        let mut filter = Madgwick::new(0.1, truth_at(0.0)).expect("filter");
        for k in 1..=700 {
            let (accel, mag) = still_readings(&truth_at(k as f64 * 0.01));
            filter.update_marg(gyro, accel, mag, 0.01);
        }
        // The estimate leads the truth by about ω·dt (README: 0.3° at 0.5 rad/s).
        let error = filter.quaternion().angle_to(&truth_at(7.0));
        assert!(error < 2.0 * omega * 0.01, "error {error} rad");
        let (_, _, yaw) = filter.euler();
        assert!((yaw - 2.8).abs() < 0.05, "yaw {yaw}");
    }

    #[test]
    fn ecompass_known_poses() {
        let level_north = orientation_from_accel_mag(
            Vector3::new(0.0, 0.0, G),
            Vector3::new(25.0, 0.0, -43.30127018922193),
        )
        .expect("pose");
        assert!(level_north.angle() < 1e-12, "{level_north}");

        // Sensor turned +90° about up (x points west): north is along sensor −y.
        let facing_west = orientation_from_accel_mag(
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.0, -25.0, -43.3),
        )
        .expect("pose");
        let (roll, pitch, yaw) = Madgwick::new(0.1, facing_west).expect("f").euler();
        assert!(roll.abs() < 1e-12 && pitch.abs() < 1e-12);
        assert!((yaw - FRAC_PI_2).abs() < 1e-12, "yaw {yaw}");
        assert!(facing_west.w >= 0.0);

        // Facing south: north along sensor −x; yaw ±π.
        let facing_south =
            orientation_from_accel_mag(Vector3::new(0.0, 0.0, G), Vector3::new(-25.0, 0.0, -43.3))
                .expect("pose");
        let (_, _, yaw) = Madgwick::new(0.1, facing_south).expect("f").euler();
        assert!((yaw.abs() - PI).abs() < 1e-12, "yaw {yaw}");

        // Rolled +90° about north: the sensor reads an earth vector v as (v_x, v_z, −v_y).
        let rolled =
            orientation_from_accel_mag(Vector3::new(0.0, G, 0.0), Vector3::new(25.0, -43.3, 0.0))
                .expect("pose");
        let expected = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2);
        assert!(rolled.angle_to(&expected) < 1e-12, "{rolled}");

        // A general pose, readings made by nalgebra from the truth; units do not matter.
        let truth = UnitQuaternion::from_euler_angles(0.3, -0.4, 2.0);
        let (accel, mag) = still_readings(&truth);
        let found = orientation_from_accel_mag(accel / G, mag * 1e-6).expect("pose");
        assert!(found.angle_to(&truth) < 1e-12, "{found} vs {truth}");
    }

    #[test]
    fn ecompass_refuses_degenerate_readings() {
        let up = Vector3::new(0.0, 0.0, G);
        assert_eq!(
            orientation_from_accel_mag(Vector3::zeros(), Vector3::from(M_EARTH)),
            Err(MadgwickError::NoGravity([0.0; 3]))
        );
        assert_eq!(
            orientation_from_accel_mag(up, Vector3::zeros()),
            Err(MadgwickError::NoHeading([0.0; 3]))
        );
        assert_eq!(
            orientation_from_accel_mag(up, Vector3::new(0.0, 0.0, -40.0)),
            Err(MadgwickError::NoHeading([0.0, 0.0, -40.0]))
        );
        assert!(matches!(
            orientation_from_accel_mag(Vector3::new(f64::NAN, 0.0, 1.0), Vector3::from(M_EARTH)),
            Err(MadgwickError::NoGravity(_))
        ));
    }

    #[test]
    fn zero_mag_falls_back_to_imu_update() {
        let start = UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3);
        let gyro = Vector3::new(0.01, -0.02, 0.3);
        let accel = Vector3::new(0.5, -0.3, 9.7);
        let mut marg = Madgwick::new(0.1, start).expect("filter");
        let mut imu = marg.clone();
        assert_eq!(
            marg.update_marg(gyro, accel, Vector3::zeros(), 0.01),
            UpdateKind::Imu
        );
        assert_eq!(imu.update_imu(gyro, accel, 0.01), UpdateKind::Imu);
        assert_eq!(marg, imu);
        assert_ne!(marg.quaternion(), start);
        // A non-finite field is treated the same way.
        let mut nan_mag = Madgwick::new(0.1, start).expect("filter");
        let nan = Vector3::new(f64::NAN, 1.0, 1.0);
        assert_eq!(nan_mag.update_marg(gyro, accel, nan, 0.01), UpdateKind::Imu);
        assert_eq!(nan_mag, imu);
    }

    #[test]
    fn zero_accel_integrates_the_gyro_only() {
        // From identity, ω = (0, 0, 1) rad/s, dt = 0.1: q + ½ q⊗ω dt = (1, 0, 0, 0.05).
        let n = 1.0025_f64.sqrt();
        let expected = [1.0 / n, 0.0, 0.0, 0.05 / n];
        let gyro = Vector3::new(0.0, 0.0, 1.0);
        let mut marg = Madgwick::new(0.1, UnitQuaternion::identity()).expect("filter");
        let kind = marg.update_marg(gyro, Vector3::zeros(), Vector3::from(M_EARTH), 0.1);
        assert_eq!(kind, UpdateKind::GyroOnly);
        assert!(
            quat_diff(marg.wxyz(), expected) < 1e-15,
            "{:?}",
            marg.wxyz()
        );
        let mut imu = Madgwick::new(0.1, UnitQuaternion::identity()).expect("filter");
        assert_eq!(
            imu.update_imu(gyro, Vector3::zeros(), 0.1),
            UpdateKind::GyroOnly
        );
        assert!(quat_diff(imu.wxyz(), expected) < 1e-15, "{:?}", imu.wxyz());
    }

    #[test]
    fn non_finite_gyro_or_dt_leaves_the_state_alone() {
        let start = UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3);
        let mut filter = Madgwick::new(0.1, start).expect("filter");
        let accel = Vector3::new(0.0, 0.0, G);
        let mag = Vector3::from(M_EARTH);
        let nan_gyro = Vector3::new(f64::NAN, 0.0, 0.0);
        assert_eq!(
            filter.update_marg(nan_gyro, accel, mag, 0.01),
            UpdateKind::Rejected
        );
        assert_eq!(
            filter.update_imu(Vector3::zeros(), accel, f64::INFINITY),
            UpdateKind::Rejected
        );
        assert_eq!(
            filter.update_imu(Vector3::zeros(), accel, -0.01),
            UpdateKind::Rejected
        );
        assert_eq!(filter.quaternion(), start);
    }

    #[test]
    fn gain_is_validated() {
        let id = UnitQuaternion::identity();
        assert_eq!(
            Madgwick::new(-0.1, id),
            Err(MadgwickError::InvalidGain(-0.1))
        );
        assert!(Madgwick::new(f64::NAN, id).is_err());
        let mut filter = Madgwick::new(0.0, id).expect("β = 0 is pure gyro integration");
        assert_eq!(
            filter.set_beta(f64::INFINITY),
            Err(MadgwickError::InvalidGain(f64::INFINITY))
        );
        filter.set_beta(0.05).expect("valid gain");
        assert_eq!(filter.beta(), 0.05);
    }

    #[test]
    fn config_parses_and_starts_the_filter() {
        let default: MadgwickConfig = toml::from_str("").expect("empty config");
        assert_eq!(default.beta, 0.1);
        assert_eq!(default.initial_orientation, None);

        // Without an explicit start the first pair decides: sensor facing west.
        let accel = Vector3::new(0.0, 0.0, G);
        let mag = Vector3::new(0.0, -25.0, -43.3);
        let filter = default.start(accel, mag).expect("start");
        assert!((filter.euler().2 - FRAC_PI_2).abs() < 1e-12);

        // An explicit start wins over the readings and is normalised: (0, 0, 0, 2) is yaw π.
        let cfg: MadgwickConfig =
            toml::from_str("beta = 0.033\ninitial_orientation = [0.0, 0.0, 0.0, 2.0]")
                .expect("config");
        let filter = cfg.start(accel, mag).expect("start");
        assert_eq!(filter.beta(), 0.033);
        assert_eq!(filter.wxyz(), [0.0, 0.0, 0.0, 1.0]);

        let zero: MadgwickConfig =
            toml::from_str("initial_orientation = [0.0, 0.0, 0.0, 0.0]").expect("config");
        assert_eq!(
            zero.start(accel, mag),
            Err(MadgwickError::InvalidQuaternion([0.0; 4]))
        );
        assert!(toml::from_str::<MadgwickConfig>("gain = 0.1").is_err());
    }
}
