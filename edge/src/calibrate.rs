//! Field calibration of the IMU (`scan3d-edge calibrate gyro|mag`): the gyro bias at rest and
//! the magnetometer's hard and soft iron from a slow turn.
//!
//! The fits are pure ([`gyro_bias`], [`fit_mag`]: samples in, calibration out; [`MagSettings`]:
//! the `[imu]` values a fit gives); the edges are [`collect`] (readings through the driver on
//! any embedded-hal bus; [`collect_on_clock`] on a simulation's clock) and [`set_imu_keys`]
//! (the `[imu]` keys of an `edge.toml`, the rest of the file kept byte for byte).
//!
//! Magnetometer model: raw = A · m + b with `m` the field at the chip. The fit returns the
//! hard-iron offset `b` and a symmetric soft-iron matrix `S` with m = S · (raw − b) on a sphere
//! of the field's magnitude (the driver's `mag_hard_iron_ut` and `mag_soft_iron`). Two cases:
//! - **3D** (the head tumbled through many orientations): a general ellipsoid fit by linear
//!   least squares; the sphere's radius is `--field-ut` when given, else the geometric mean of
//!   the ellipsoid's semi-axes.
//! - **2D** (a trolley can only turn about its vertical): the samples lie in a plane, so only
//!   the horizontal ellipse is observable. Its centre gives b_x, b_y; its shape the upper-left
//!   2×2 of S (the z row and column stay identity); b_z is the mean of the raw z minus the
//!   true vertical field, which needs the local field (`--field-ut`, and `--inclination-deg` or
//!   the assumption that the field points down, as north of the magnetic equator); without it
//!   b_z is left as configured. A tilt of the hard iron's z into the plane (A's xz, yz terms
//!   times the vertical field) is absorbed into b_x, b_y: the horizontal field, and so the
//!   heading, comes out right, which is what a trolley needs.

use std::fmt::Write as _;
use std::time::{Duration, Instant};

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;
use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, Vector2, Vector3};

use crate::clock::Clock;
use crate::drivers::imu::{ImuConfig, ImuReading, Mpu9250};

/// Default bound of the gyro rate's standard deviation at rest, °/s: about 4× the MPU-9250's
/// white noise at the default 41 Hz filter (0.01 °/s/√Hz · √41 Hz ≈ 0.07 °/s).
pub const DEFAULT_MAX_RATE_STD_DPS: f64 = 0.3;
/// A mean rate above this is not a bias but a turn, °/s (the datasheet's initial ZRO tolerance
/// is ±5 °/s).
pub const MAX_BIAS_DPS: f64 = 5.0;
/// The field may move this far from its mean at rest, µT (AK8963 noise ≈ 0.3 µT σ plus
/// 0.15 µT steps): more means the head turned.
pub const MAX_REST_FIELD_SPREAD_UT: f64 = 3.0;
/// Fewest samples a fit accepts.
pub const MIN_SAMPLES: usize = 50;
/// Fewest of the 36 10° sectors a horizontal turn must cover (300° of 360°).
pub const MIN_CIRCLE_SECTORS: usize = 30;
/// Fewest of the 72 equal-area cells of the sphere a tumble must cover (half the sphere).
pub const MIN_SPHERE_CELLS: usize = 36;
/// Below this ratio of the smallest to the largest spread (standard deviations along the
/// principal axes), the samples lie in a plane: a turn about one axis.
pub const PLANAR_RATIO: f64 = 0.2;
/// A planar turn must be about the chip's z within this angle, degrees.
pub const MAX_TURN_AXIS_TILT_DEG: f64 = 15.0;

/// Why a calibration was refused: one readable line each.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// Not enough samples.
    #[error("only {got} samples (need at least {need}): run it longer")]
    TooFewSamples {
        /// Samples given.
        got: usize,
        /// Samples needed.
        need: usize,
    },
    /// The gyro rate varied more than the noise allows.
    #[error(
        "the head moved during the gyro calibration: the rate on {axis} varied by {std_dps:.3} °/s \
         (σ; at rest it is below {limit_dps} °/s); keep it still and run again"
    )]
    Moved {
        /// Axis name.
        axis: char,
        /// Its rate's standard deviation, °/s.
        std_dps: f64,
        /// The bound, °/s.
        limit_dps: f64,
    },
    /// The mean rate or the field says the head turned.
    #[error("the head turned during the gyro calibration ({0}); keep it still and run again")]
    Turned(String),
    /// The turn did not cover enough of the circle or sphere.
    #[error("{0}")]
    Coverage(String),
    /// The samples lie in a plane that is not the chip's horizontal.
    #[error(
        "the turn was about an axis {tilt_deg:.0}° from the IMU's z: a 2D calibration needs a turn \
         about the vertical with the IMU level (within {MAX_TURN_AXIS_TILT_DEG}°); turn about z, or \
         tumble the head through all orientations"
    )]
    TiltedTurn {
        /// Angle between the turn's axis and the chip's z, degrees.
        tilt_deg: f64,
    },
    /// The fit has no ellipse or ellipsoid (noise only, or inconsistent data).
    #[error("the magnetometer samples do not fit an {0}: is the magnetometer working?")]
    Degenerate(&'static str),
    /// An input given on the command line cannot be used.
    #[error("{0}")]
    BadInput(String),
}

/// The gyro bias measured at rest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GyroCalibration {
    /// Mean rate, rad/s: the bias.
    pub bias_rad_s: [f64; 3],
    /// Standard deviation of the rate per axis, rad/s.
    pub std_rad_s: [f64; 3],
    /// Samples averaged.
    pub samples: usize,
}

/// The gyro bias from rates taken at rest (rad/s, chip frame), and optionally the fields
/// taken meanwhile (µT) as a second witness of rest. Refuses when the rate varies more than
/// `max_std_rad_s` on any axis, when the mean rate exceeds [`MAX_BIAS_DPS`], or when the field
/// moves more than [`MAX_REST_FIELD_SPREAD_UT`] from its mean.
pub fn gyro_bias(
    rates: &[[f64; 3]],
    fields: &[[f64; 3]],
    max_std_rad_s: f64,
) -> Result<GyroCalibration, CalibrationError> {
    if rates.len() < MIN_SAMPLES {
        return Err(CalibrationError::TooFewSamples {
            got: rates.len(),
            need: MIN_SAMPLES,
        });
    }
    let n = rates.len() as f64;
    let mut mean = [0.0; 3];
    let mut std = [0.0; 3];
    for axis in 0..3 {
        mean[axis] = rates.iter().map(|r| r[axis]).sum::<f64>() / n;
        std[axis] = (rates
            .iter()
            .map(|r| (r[axis] - mean[axis]).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
    }
    for (axis, name) in ['x', 'y', 'z'].into_iter().enumerate() {
        if std[axis].is_nan() || std[axis] > max_std_rad_s {
            return Err(CalibrationError::Moved {
                axis: name,
                std_dps: std[axis].to_degrees(),
                limit_dps: max_std_rad_s.to_degrees(),
            });
        }
        if mean[axis].to_degrees().abs() > MAX_BIAS_DPS {
            return Err(CalibrationError::Turned(format!(
                "mean rate {:.2} °/s on {name}, above the ±{MAX_BIAS_DPS} °/s a bias can be",
                mean[axis].to_degrees()
            )));
        }
    }
    if !fields.is_empty() {
        let m = fields
            .iter()
            .fold(Vector3::zeros(), |s, f| s + Vector3::from(*f))
            / fields.len() as f64;
        let spread = fields
            .iter()
            .map(|f| (Vector3::from(*f) - m).norm())
            .fold(0.0, f64::max);
        if spread > MAX_REST_FIELD_SPREAD_UT {
            return Err(CalibrationError::Turned(format!(
                "the magnetic field moved {spread:.1} µT from its mean, above the \
                 {MAX_REST_FIELD_SPREAD_UT} µT of noise at rest"
            )));
        }
    }
    Ok(GyroCalibration {
        bias_rad_s: mean,
        std_rad_s: std,
        samples: rates.len(),
    })
}

/// Which fit [`fit_mag`] could make.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MagFitKind {
    /// A full ellipsoid: the head was tumbled.
    Ellipsoid,
    /// The horizontal ellipse only: the head turned about its z.
    HorizontalEllipse,
}

/// What the local field is, when known (from a geomagnetic model for the site).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LocalField {
    /// Total intensity, µT.
    pub total_ut: Option<f64>,
    /// Inclination below the horizontal, degrees (negative south of the magnetic equator).
    pub inclination_deg: Option<f64>,
}

/// A fitted magnetometer calibration: m = S · (raw − b).
#[derive(Debug, Clone, PartialEq)]
pub struct MagCalibration {
    /// The fit made.
    pub kind: MagFitKind,
    /// Hard-iron offset b, µT; in 2D, `[2]` is `None` when the local field was not given.
    pub hard_iron_ut: [Option<f64>; 3],
    /// Soft-iron matrix S (row-major, symmetric).
    pub soft_iron: [[f64; 3]; 3],
    /// Radius of the calibrated sphere (3D) or circle (2D, the horizontal field), µT.
    pub radius_ut: f64,
    /// RMS of (|calibrated| − radius) / radius over the samples (horizontal part in 2D).
    pub residual_rms: f64,
    /// How much of the sphere (cells of 72) or circle (10° sectors of 36) the samples cover.
    pub covered: (usize, usize),
    /// The samples used.
    pub samples: usize,
}

/// Fits hard and soft iron to raw fields (µT, chip frame, uncalibrated) from a slow turn:
/// an ellipsoid when the samples fill 3D, a horizontal ellipse when they lie in the chip's
/// horizontal plane (module docs). Refuses too few samples, too little coverage, a planar turn
/// about a tilted axis, and data that fit no ellipse.
pub fn fit_mag(raw: &[[f64; 3]], local: LocalField) -> Result<MagCalibration, CalibrationError> {
    if raw.len() < MIN_SAMPLES {
        return Err(CalibrationError::TooFewSamples {
            got: raw.len(),
            need: MIN_SAMPLES,
        });
    }
    if let Some(total) = local.total_ut
        && !(total.is_finite() && total > 0.0)
    {
        return Err(CalibrationError::BadInput(format!(
            "--field-ut must be a positive number of µT, got {total}"
        )));
    }
    if let Some(i) = local.inclination_deg
        && !(i.is_finite() && i.abs() < 90.0)
    {
        return Err(CalibrationError::BadInput(format!(
            "--inclination-deg must be within ±90°, got {i}"
        )));
    }
    let points: Vec<Vector3<f64>> = raw.iter().map(|r| Vector3::from(*r)).collect();
    let n = points.len() as f64;
    let mean = points.iter().fold(Vector3::zeros(), |s, p| s + p) / n;
    let cov = points.iter().fold(Matrix3::zeros(), |s, p| {
        let d = p - mean;
        s + d * d.transpose()
    }) / n;
    let eigen = cov.symmetric_eigen();
    let (mut lo, mut hi) = (0, 0);
    for i in 0..3 {
        if eigen.eigenvalues[i] < eigen.eigenvalues[lo] {
            lo = i;
        }
        if eigen.eigenvalues[i] > eigen.eigenvalues[hi] {
            hi = i;
        }
    }
    let spread_ratio = (eigen.eigenvalues[lo].max(0.0) / eigen.eigenvalues[hi]).sqrt();
    if !(spread_ratio.is_finite()) || eigen.eigenvalues[hi] <= 0.0 {
        return Err(CalibrationError::Degenerate("ellipse"));
    }
    if spread_ratio < PLANAR_RATIO {
        let normal = eigen.eigenvectors.column(lo);
        let tilt_deg = normal[2].abs().min(1.0).acos().to_degrees();
        if tilt_deg > MAX_TURN_AXIS_TILT_DEG {
            return Err(CalibrationError::TiltedTurn { tilt_deg });
        }
        fit_horizontal(&points, mean, local)
    } else {
        fit_ellipsoid(&points, mean, local)
    }
}

/// Symmetric square root of a positive-definite matrix, `None` if not positive definite.
fn sqrt_spd3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let e = m.symmetric_eigen();
    if e.eigenvalues.iter().any(|&l| l.is_nan() || l <= 0.0) {
        return None;
    }
    let d = Matrix3::from_diagonal(&e.eigenvalues.map(f64::sqrt));
    Some(e.eigenvectors * d * e.eigenvectors.transpose())
}

fn sqrt_spd2(m: &Matrix2<f64>) -> Option<Matrix2<f64>> {
    let e = m.symmetric_eigen();
    if e.eigenvalues.iter().any(|&l| l.is_nan() || l <= 0.0) {
        return None;
    }
    let d = Matrix2::from_diagonal(&e.eigenvalues.map(f64::sqrt));
    Some(e.eigenvectors * d * e.eigenvectors.transpose())
}

/// The least-squares circle through the points' x, y (x² + y² + D x + E y + F = 0): centre
/// and radius, `None` for collinear points.
fn fit_circle(points: &[Vector3<f64>]) -> Option<(Vector2<f64>, f64)> {
    let design = DMatrix::from_fn(points.len(), 3, |r, c| match c {
        0 => points[r].x,
        1 => points[r].y,
        _ => 1.0,
    });
    let rhs = DVector::from_fn(points.len(), |r, _| -points[r].xy().norm_squared());
    let p = design.svd(true, true).solve(&rhs, 1e-12).ok()?;
    let centre = Vector2::new(-p[0] / 2.0, -p[1] / 2.0);
    let r2 = centre.norm_squared() - p[2];
    (r2 > 0.0 && r2.is_finite()).then(|| (centre, r2.sqrt()))
}

/// The least-squares sphere through the points (|x|² + D·x + G = 0): centre and radius,
/// `None` for coplanar points.
fn fit_sphere(points: &[Vector3<f64>]) -> Option<(Vector3<f64>, f64)> {
    let design = DMatrix::from_fn(
        points.len(),
        4,
        |r, c| if c < 3 { points[r][c] } else { 1.0 },
    );
    let rhs = DVector::from_fn(points.len(), |r, _| -points[r].norm_squared());
    let p = design.svd(true, true).solve(&rhs, 1e-12).ok()?;
    let centre = Vector3::new(-p[0] / 2.0, -p[1] / 2.0, -p[2] / 2.0);
    let r2 = centre.norm_squared() - p[3];
    (r2 > 0.0 && r2.is_finite()).then(|| (centre, r2.sqrt()))
}

/// Least-squares solution of `design · p = 1`.
fn solve_ones(design: DMatrix<f64>) -> Option<DVector<f64>> {
    let ones = DVector::from_element(design.nrows(), 1.0);
    design.svd(true, true).solve(&ones, 1e-12).ok()
}

fn fit_ellipsoid(
    points: &[Vector3<f64>],
    mean: Vector3<f64>,
    local: LocalField,
) -> Result<MagCalibration, CalibrationError> {
    const SHAPE: &str = "ellipsoid";
    // Centred and scaled for conditioning: u = (x − mean) / scale.
    let scale = (points
        .iter()
        .map(|p| (p - mean).norm_squared())
        .sum::<f64>()
        / points.len() as f64)
        .sqrt();
    if scale.is_nan() || scale <= 0.0 {
        return Err(CalibrationError::Degenerate(SHAPE));
    }
    let design = DMatrix::from_fn(points.len(), 9, |r, c| {
        let u = (points[r] - mean) / scale;
        match c {
            0 => u.x * u.x,
            1 => u.y * u.y,
            2 => u.z * u.z,
            3 => 2.0 * u.x * u.y,
            4 => 2.0 * u.x * u.z,
            5 => 2.0 * u.y * u.z,
            6 => 2.0 * u.x,
            7 => 2.0 * u.y,
            _ => 2.0 * u.z,
        }
    });
    // uᵀ M u + 2 gᵀ u = 1  ⇒  (u − c)ᵀ M (u − c) = 1 + cᵀ M c, c = −M⁻¹ g.
    let ellipsoid = solve_ones(design).and_then(|p| {
        let m = Matrix3::new(p[0], p[3], p[4], p[3], p[1], p[5], p[4], p[5], p[2]);
        let g = Vector3::new(p[6], p[7], p[8]);
        let c = -(m.try_inverse()? * g);
        let k = 1.0 + c.dot(&(m * c));
        let shape = m / (k * scale * scale);
        let unit = sqrt_spd3(&shape)?;
        Some((shape, unit, mean + c * scale))
    });
    // Judged around the ellipsoid, or around the best sphere when a partial turn fits none.
    let (around, unit_around) = match &ellipsoid {
        Some((_, unit, centre)) => (*centre, *unit),
        None => {
            let (centre, radius) = fit_sphere(points).ok_or(CalibrationError::Degenerate(SHAPE))?;
            (centre, Matrix3::identity() / radius)
        }
    };
    let mut cells = [false; 72];
    for p in points {
        let u = (unit_around * (p - around)).normalize();
        let band = (((u.z + 1.0) / 2.0 * 6.0).floor() as usize).min(5);
        let sector = (((u.y.atan2(u.x) + std::f64::consts::PI) / std::f64::consts::TAU * 12.0)
            .floor() as usize)
            .min(11);
        cells[band * 12 + sector] = true;
    }
    let covered = cells.iter().filter(|&&c| c).count();
    if covered < MIN_SPHERE_CELLS {
        return Err(CalibrationError::Coverage(format!(
            "the turn covered {covered} of 72 equal parts of the sphere of directions (need \
             {MIN_SPHERE_CELLS}): tumble the head slowly through all orientations, or, for a \
             trolley, turn it about its vertical only (a 2D calibration)"
        )));
    }
    let (shape, unit, centre) = ellipsoid.ok_or(CalibrationError::Degenerate(SHAPE))?;
    // The semi-axes are 1/√λ: their geometric mean is det(shape)^(−1/6).
    let radius = match local.total_ut {
        Some(total) => total,
        None => shape.determinant().powf(-1.0 / 6.0),
    };
    let soft = unit * radius;
    let sum2: f64 = points
        .iter()
        .map(|p| ((unit * (p - centre)).norm() - 1.0).powi(2))
        .sum();
    Ok(MagCalibration {
        kind: MagFitKind::Ellipsoid,
        hard_iron_ut: [Some(centre.x), Some(centre.y), Some(centre.z)],
        soft_iron: soft.into(),
        radius_ut: radius,
        residual_rms: (sum2 / points.len() as f64).sqrt(),
        covered: (covered, 72),
        samples: points.len(),
    })
}

fn fit_horizontal(
    points: &[Vector3<f64>],
    mean: Vector3<f64>,
    local: LocalField,
) -> Result<MagCalibration, CalibrationError> {
    const SHAPE: &str = "ellipse";
    let mean2 = Vector2::new(mean.x, mean.y);
    let scale = (points
        .iter()
        .map(|p| (p.xy() - mean2).norm_squared())
        .sum::<f64>()
        / points.len() as f64)
        .sqrt();
    if scale.is_nan() || scale <= 0.0 {
        return Err(CalibrationError::Degenerate(SHAPE));
    }
    let design = DMatrix::from_fn(points.len(), 5, |r, c| {
        let u = (points[r].xy() - mean2) / scale;
        match c {
            0 => u.x * u.x,
            1 => u.y * u.y,
            2 => 2.0 * u.x * u.y,
            3 => 2.0 * u.x,
            _ => 2.0 * u.y,
        }
    });
    let ellipse = solve_ones(design).and_then(|p| {
        let m = Matrix2::new(p[0], p[2], p[2], p[1]);
        let g = Vector2::new(p[3], p[4]);
        let c = -(m.try_inverse()? * g);
        let k = 1.0 + c.dot(&(m * c));
        let shape = m / (k * scale * scale);
        let unit = sqrt_spd2(&shape)?;
        Some((shape, unit, mean2 + c * scale))
    });
    // The coverage is judged around the ellipse, or (when a short arc fits none) around the
    // best circle, so a short turn is told as such.
    let (around, unit_around) = match &ellipse {
        Some((_, unit, centre)) => (*centre, *unit),
        None => {
            let (centre, radius) = fit_circle(points).ok_or(CalibrationError::Degenerate(SHAPE))?;
            (centre, Matrix2::identity() / radius)
        }
    };
    let mut sectors = [false; 36];
    for p in points {
        let d = unit_around * (p.xy() - around);
        let sector = (((d.y.atan2(d.x) + std::f64::consts::PI) / std::f64::consts::TAU * 36.0)
            .floor() as usize)
            .min(35);
        sectors[sector] = true;
    }
    let covered = sectors.iter().filter(|&&s| s).count();
    if covered < MIN_CIRCLE_SECTORS {
        return Err(CalibrationError::Coverage(format!(
            "the turn covered {}° of the circle (need {}°): turn the trolley slowly through at \
             least one full turn about its vertical",
            covered * 10,
            MIN_CIRCLE_SECTORS * 10
        )));
    }
    let (shape, unit, centre) = ellipse.ok_or(CalibrationError::Degenerate(SHAPE))?;
    let horizontal = match (local.total_ut, local.inclination_deg) {
        (Some(total), Some(incl)) => total * incl.to_radians().cos(),
        // The semi-axes' geometric mean: det(shape)^(−1/4).
        _ => shape.determinant().powf(-0.25),
    };
    // The true vertical field at a level chip (z up): −H·tan(I), or −√(F² − H²) with the
    // field pointing down when only F is known.
    let vertical = match (local.total_ut, local.inclination_deg) {
        (_, Some(incl)) => Some(-horizontal * incl.to_radians().tan()),
        (Some(total), None) if total > horizontal => {
            Some(-(total * total - horizontal * horizontal).sqrt())
        }
        (Some(total), None) => {
            return Err(CalibrationError::BadInput(format!(
                "--field-ut {total} µT is below the horizontal field measured ({horizontal:.1} µT)"
            )));
        }
        (None, None) => None,
    };
    let mean_z = points.iter().map(|p| p.z).sum::<f64>() / points.len() as f64;
    let soft2 = unit * horizontal;
    let sum2: f64 = points
        .iter()
        .map(|p| ((unit * (p.xy() - centre)).norm() - 1.0).powi(2))
        .sum();
    let soft = [
        [soft2[(0, 0)], soft2[(0, 1)], 0.0],
        [soft2[(1, 0)], soft2[(1, 1)], 0.0],
        [0.0, 0.0, 1.0],
    ];
    Ok(MagCalibration {
        kind: MagFitKind::HorizontalEllipse,
        hard_iron_ut: [Some(centre.x), Some(centre.y), vertical.map(|v| mean_z - v)],
        soft_iron: soft,
        radius_ut: horizontal,
        residual_rms: (sum2 / points.len() as f64).sqrt(),
        covered: (covered, 36),
        samples: points.len(),
    })
}

/// The median magnitude of the calibrated fields S · (raw − b), µT: the reference the daemon
/// compares the field with (`mag_field_ut`). `None` without samples.
pub fn calibrated_magnitude(
    raw: &[[f64; 3]],
    hard_iron_ut: [f64; 3],
    soft_iron: &[[f64; 3]; 3],
) -> Option<f64> {
    let s = Matrix3::from_fn(|r, c| soft_iron[r][c]);
    let b = Vector3::from(hard_iron_ut);
    let mut norms: Vec<f64> = raw
        .iter()
        .map(|m| (s * (Vector3::from(*m) - b)).norm())
        .filter(|n| n.is_finite())
        .collect();
    norms.sort_by(f64::total_cmp);
    norms.get(norms.len() / 2).copied()
}

/// The daemon's check of the calibrated field (`mag_field_ut`, `mag_field_tolerance`): a
/// warning line when the magnitude leaves the reference by more than the tolerance, at most
/// once per [`FieldMonitor::INTERVAL_NS`].
#[derive(Debug, Clone, PartialEq)]
pub struct FieldMonitor {
    reference_ut: f64,
    tolerance: f64,
    last_warning_ns: Option<u64>,
}

impl FieldMonitor {
    /// Least time between two warnings, ns (a minute).
    pub const INTERVAL_NS: u64 = 60_000_000_000;

    /// A monitor for the configured reference; `None` when there is none (or it is not a
    /// positive number).
    pub fn from_config(config: &ImuConfig) -> Option<Self> {
        let reference = f64::from(config.mag_field_ut?);
        let tolerance = f64::from(config.mag_field_tolerance);
        (reference > 0.0 && tolerance > 0.0 && reference.is_finite() && tolerance.is_finite())
            .then_some(Self {
                reference_ut: reference,
                tolerance,
                last_warning_ns: None,
            })
    }

    /// Checks one calibrated field (µT) read at `t_ns`: the warning to log, if any.
    pub fn check(&mut self, t_ns: u64, field_ut: [f32; 3]) -> Option<String> {
        let magnitude = Vector3::from(field_ut.map(f64::from)).norm();
        let off = magnitude / self.reference_ut - 1.0;
        if off.is_nan() || off.abs() <= self.tolerance {
            return None;
        }
        if let Some(last) = self.last_warning_ns
            && t_ns.saturating_sub(last) < Self::INTERVAL_NS
        {
            return None;
        }
        self.last_warning_ns = Some(t_ns);
        Some(format!(
            "the magnetic field reads {magnitude:.1} µT, {:+.0} % off its calibrated {:.1} µT \
             (tolerance {:.0} %): steel nearby or a calibration out of date (`scan3d-edge \
             calibrate mag`); the heading may be off",
            off * 100.0,
            self.reference_ut,
            self.tolerance * 100.0
        ))
    }
}

/// Readings taken for a calibration, through the driver.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Collected {
    /// Gyro rates, rad/s, chip frame, no bias removed.
    pub rates: Vec<[f64; 3]>,
    /// Fields, µT, chip frame, no iron removed (the driver's ASA adjustment and axis
    /// alignment applied).
    pub fields: Vec<[f64; 3]>,
}

/// The driver configuration a calibration reads with: `config` with no gyro bias removed and
/// no iron applied, so the readings are what the fits need.
pub fn raw_config(config: &ImuConfig) -> ImuConfig {
    ImuConfig {
        gyro_bias_samples: 0,
        gyro_bias_rad_s: None,
        mag_field_ut: None,
        mag_hard_iron_ut: [0.0; 3],
        mag_soft_iron: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        ..config.clone()
    }
}

/// Initialises the IMU on `bus` with [`raw_config`] of `config` and reads it for `duration`
/// (wall clock) at its sample rate; `progress` is called about once a second with the seconds
/// elapsed. At most `max_samples` readings are kept. (The command line's reading:
/// [`collect_on_clock`] on the wall clock.)
pub fn collect<I: I2c, D: DelayNs>(
    bus: I,
    delay: &mut D,
    config: &ImuConfig,
    duration: Duration,
    max_samples: usize,
    progress: impl FnMut(u64),
) -> anyhow::Result<Collected> {
    let wall = WallClock(Instant::now());
    let duration_ns = u64::try_from(duration.as_nanos()).unwrap_or(u64::MAX);
    collect_on_clock(
        bus,
        delay,
        config,
        &wall,
        duration_ns,
        max_samples,
        progress,
    )
}

/// The wall clock since an instant, for [`collect`].
struct WallClock(Instant);

impl Clock for WallClock {
    fn now_ns(&self) -> u64 {
        u64::try_from(self.0.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }
}

/// [`collect`] on `clock`'s time: reads for `duration_ns` of it, one reading per sample period
/// of it (a simulation's scaled clock reads a simulated turn in a fraction of the real time;
/// `delay` should wait on the same clock). `progress` gets the clock's whole seconds elapsed.
pub fn collect_on_clock<I: I2c, D: DelayNs>(
    bus: I,
    delay: &mut D,
    config: &ImuConfig,
    clock: &dyn Clock,
    duration_ns: u64,
    max_samples: usize,
    mut progress: impl FnMut(u64),
) -> anyhow::Result<Collected> {
    let mut imu = Mpu9250::new(bus, raw_config(config));
    imu.init(delay)
        .map_err(|e| anyhow::anyhow!("IMU init failed: {e}"))?;
    imu.set_gyro_bias([0.0; 3]);
    let period_ns = u64::from(config.sample_period_ns()).max(1);
    let start_ns = clock.now_ns();
    let elapsed_ns = || clock.now_ns().saturating_sub(start_ns);
    let mut next_ns = 0u64;
    let mut reported = 0;
    let mut out = Collected::default();
    while elapsed_ns() < duration_ns && out.rates.len() < max_samples {
        let reading: ImuReading = imu
            .read()
            .map_err(|e| anyhow::anyhow!("IMU read failed: {e}"))?;
        out.rates.push(reading.gyro_rad_s.map(f64::from));
        if let Some(mag) = reading.mag_ut {
            out.fields.push(mag.map(f64::from));
        }
        let seconds = elapsed_ns() / 1_000_000_000;
        if seconds > reported {
            reported = seconds;
            progress(seconds);
        }
        next_ns += period_ns;
        let now_ns = elapsed_ns();
        if next_ns > now_ns {
            std::thread::sleep(clock.real_duration(next_ns - now_ns));
        } else {
            next_ns = now_ns;
        }
    }
    Ok(out)
}

/// The `[imu]` settings a magnetometer fit gives, as `scan3d-edge calibrate mag` writes them.
#[derive(Debug, Clone, PartialEq)]
pub struct MagSettings {
    /// `mag_hard_iron_ut`: the fit's offset; a z the fit could not see (a 2D fit without the
    /// local field) is the configured one.
    pub hard_iron_ut: [f64; 3],
    /// `mag_soft_iron`.
    pub soft_iron: [[f64; 3]; 3],
    /// `mag_field_ut`: the calibrated fields' median magnitude, the daemon's reference.
    pub field_ut: f64,
}

impl MagSettings {
    /// The settings from `fit` of the raw `fields` it was fitted to, keeping `configured_z_ut`
    /// where the fit has no z offset.
    pub fn from_fit(fit: &MagCalibration, fields: &[[f64; 3]], configured_z_ut: f64) -> Self {
        let hard_iron_ut = [
            fit.hard_iron_ut[0].unwrap_or_default(),
            fit.hard_iron_ut[1].unwrap_or_default(),
            fit.hard_iron_ut[2].unwrap_or(configured_z_ut),
        ];
        let field_ut =
            calibrated_magnitude(fields, hard_iron_ut, &fit.soft_iron).unwrap_or(fit.radius_ut);
        Self {
            hard_iron_ut,
            soft_iron: fit.soft_iron,
            field_ut,
        }
    }

    /// `config` with these settings, as the daemon loads them from the written `edge.toml`.
    pub fn apply(&self, config: &mut ImuConfig) {
        config.mag_hard_iron_ut = self.hard_iron_ut.map(|v| v as f32);
        config.mag_soft_iron = self.soft_iron.map(|row| row.map(|v| v as f32));
        config.mag_field_ut = Some(self.field_ut as f32);
    }
}

/// A TOML value for a float array, with enough digits.
pub fn toml_array(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|v| format!("{v:.6}")).collect();
    format!("[{}]", items.join(", "))
}

/// A TOML value for a 3×3 matrix, row-major.
pub fn toml_matrix(m: &[[f64; 3]; 3]) -> String {
    let rows: Vec<String> = m.iter().map(|r| toml_array(r)).collect();
    format!("[{}]", rows.join(", "))
}

/// `text` (an `edge.toml`) with the keys `keys` (name, TOML value text) set in its `[imu]`
/// table: an existing key's line (and the continuation lines of a multi-line array) is
/// replaced, a missing key is inserted after the table's last key, and a missing `[imu]` table
/// is appended. Everything else is kept as it was. The result is parsed back and the keys
/// checked; a file this cannot edit safely (e.g. `[imu]` written as an inline table or dotted
/// keys) is refused with the reason.
pub fn set_imu_keys(text: &str, keys: &[(&str, String)]) -> Result<String, String> {
    let lines: Vec<&str> = text.split_inclusive('\n').collect();
    let header = lines.iter().position(|l| {
        let t = l.split('#').next().unwrap_or("");
        t.replace([' ', '\t', '\n', '\r'], "") == "[imu]"
    });
    let mut out: Vec<String> = lines.iter().map(|l| (*l).to_owned()).collect();
    match header {
        None => {
            let mut tail = String::new();
            if !text.is_empty() && !text.ends_with('\n') {
                tail.push('\n');
            }
            tail.push_str("\n[imu]\n");
            for (key, value) in keys {
                let _ = writeln!(tail, "{key} = {value}");
            }
            out.push(tail);
        }
        Some(h) => {
            // Walk the table's lines up to the next header; a key's value may continue over
            // several lines (a multi-line array) until its brackets balance.
            let mut removed_at: Vec<(usize, &str)> = Vec::new();
            let mut last_key_line = h;
            let mut i = h + 1;
            while i < lines.len() {
                let t = lines[i].trim_start();
                if t.starts_with('[') {
                    break;
                }
                let mut span = 1;
                if !t.starts_with('#') && t.contains('=') {
                    let key = t.split(['=', ' ', '\t']).next().unwrap_or("");
                    let mut depth: i64 = 0;
                    let mut j = i;
                    loop {
                        let body = lines[j].split('#').next().unwrap_or("");
                        depth += body.matches('[').count() as i64;
                        depth -= body.matches(']').count() as i64;
                        if depth <= 0 || j + 1 >= lines.len() {
                            break;
                        }
                        j += 1;
                    }
                    span = j - i + 1;
                    if let Some((name, _)) = keys.iter().find(|(k, _)| *k == key) {
                        removed_at.push((i, name));
                        for line in out.iter_mut().skip(i).take(span) {
                            line.clear();
                        }
                    }
                    last_key_line = j;
                }
                i += span;
            }
            for (key, value) in keys {
                let line = format!("{key} = {value}\n");
                match removed_at.iter().find(|(_, k)| k == key) {
                    Some((at, _)) => out[*at] = line,
                    None => {
                        let at = last_key_line;
                        if !out[at].is_empty() && !out[at].ends_with('\n') {
                            out[at].push('\n');
                        }
                        out[at].push_str(&line);
                    }
                }
            }
        }
    }
    let result: String = out.concat();
    // Parse back: the file is still TOML and holds exactly the values written.
    let table: toml::Table = result
        .parse()
        .map_err(|e| format!("the edited file would not be valid TOML: {e}"))?;
    let imu = table
        .get("imu")
        .and_then(|v| v.as_table())
        .ok_or("the edited file has no [imu] table")?;
    for (key, value) in keys {
        let want: toml::Table = format!("v = {value}")
            .parse()
            .map_err(|e| format!("bad value for {key}: {e}"))?;
        if imu.get(*key) != want.get("v") {
            return Err(format!(
                "could not set imu.{key} safely in this file; add `{key} = {value}` to [imu] by hand"
            ));
        }
    }
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    use rand::{Rng, SeedableRng};

    /// Normal draws (Box–Muller) from a seeded generator.
    struct Gauss(rand::rngs::StdRng, f64);

    impl Gauss {
        fn new(seed: u64, sigma: f64) -> Self {
            Self(rand::rngs::StdRng::seed_from_u64(seed), sigma)
        }
        fn sample(&mut self) -> f64 {
            let u1: f64 = self.0.random::<f64>().max(1e-300);
            let u2: f64 = self.0.random();
            self.1 * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        }
    }

    /// Raw fields for the true field `field` seen in orientations `rotations`, through
    /// raw = A·m + b plus noise.
    fn raw_fields(
        a: Matrix3<f64>,
        b: Vector3<f64>,
        field: Vector3<f64>,
        rotations: impl Iterator<Item = nalgebra::Rotation3<f64>>,
        sigma: f64,
    ) -> Vec<[f64; 3]> {
        let mut noise = Gauss::new(7, sigma);
        rotations
            .map(|r| {
                let m = r.inverse() * field;
                let n = Vector3::from_fn(|_, _| noise.sample());
                (a * m + b + n).into()
            })
            .collect()
    }

    fn true_iron() -> (Matrix3<f64>, Vector3<f64>) {
        (
            Matrix3::new(1.06, 0.03, -0.02, 0.03, 0.95, 0.01, -0.02, 0.01, 1.02),
            Vector3::new(15.0, -8.0, 5.0),
        )
    }

    fn field() -> Vector3<f64> {
        // 48 µT at 60° inclination, north along x (z up, so the field points to −z).
        Vector3::new(24.0, 0.0, -41.569_219_381_653_05)
    }

    #[test]
    fn a_tumble_gives_the_hard_iron_and_the_inverse_soft_iron() {
        let (a, b) = true_iron();
        let rotations = (0..3000).map(|k| {
            let t = f64::from(k) * 0.05;
            nalgebra::Rotation3::from_euler_angles(0.7 * t, 0.31 * t, 0.13 * t)
        });
        let raw = raw_fields(a, b, field(), rotations, 0.3);
        let local = LocalField {
            total_ut: Some(48.0),
            inclination_deg: None,
        };
        let fit = fit_mag(&raw, local).unwrap();
        assert_eq!(fit.kind, MagFitKind::Ellipsoid);
        let s = Matrix3::from_fn(|r, c| fit.soft_iron[r][c]);
        let want = a.try_inverse().unwrap();
        let hard = Vector3::from(fit.hard_iron_ut.map(Option::unwrap));
        assert!((hard - b).norm() < 0.2, "{hard} vs {b}");
        assert!((s - want).abs().max() < 0.005, "{s} vs {want}");
        assert!(fit.residual_rms < 0.02, "{}", fit.residual_rms);
        // Without the field's magnitude, the sphere's radius is the semi-axes' mean: the
        // matrix is the same up to that scale.
        let free = fit_mag(&raw, LocalField::default()).unwrap();
        let mean_radius = 48.0 * a.determinant().cbrt();
        assert!(
            (free.radius_ut - mean_radius).abs() < 0.2,
            "{}",
            free.radius_ut
        );
        let ratio = free.soft_iron[1][1] / fit.soft_iron[1][1];
        assert!((ratio - free.radius_ut / 48.0).abs() < 1e-9);
        eprintln!(
            "3D fit: hard iron {hard:.3?} (true {b:.3?}), soft iron max |error| {:.4}, residual \
             {:.4}, {} of 72 cells",
            (s - want).abs().max(),
            fit.residual_rms,
            fit.covered.0
        );
    }

    #[test]
    fn a_turn_about_z_gives_the_horizontal_ellipse_and_z_from_the_local_field() {
        let (a, b) = true_iron();
        let rotations = (0..1000)
            .map(|k| nalgebra::Rotation3::from_euler_angles(0.0, 0.0, f64::from(k) * 0.01));
        let raw = raw_fields(a, b, field(), rotations, 0.3);
        let local = LocalField {
            total_ut: Some(48.0),
            inclination_deg: Some(60.0),
        };
        let fit = fit_mag(&raw, local).unwrap();
        assert_eq!(fit.kind, MagFitKind::HorizontalEllipse);
        // The xy offset absorbs A's xz, yz terms times the vertical field.
        let vz = field().z;
        let want_b = [b.x + a[(0, 2)] * vz, b.y + a[(1, 2)] * vz];
        let got = fit.hard_iron_ut;
        assert!(
            (got[0].unwrap() - want_b[0]).abs() < 0.2,
            "{got:?} vs {want_b:?}"
        );
        assert!(
            (got[1].unwrap() - want_b[1]).abs() < 0.2,
            "{got:?} vs {want_b:?}"
        );
        // b_z from the mean z and the true vertical: off by (A_zz − 1)·vz.
        assert!((got[2].unwrap() - b.z).abs() < 1.0, "{got:?}");
        let want_s = a
            .fixed_view::<2, 2>(0, 0)
            .into_owned()
            .try_inverse()
            .unwrap();
        for r in 0..2 {
            for c in 0..2 {
                assert!(
                    (fit.soft_iron[r][c] - want_s[(r, c)]).abs() < 0.01,
                    "{fit:?}"
                );
            }
        }
        assert_eq!(fit.soft_iron[2], [0.0, 0.0, 1.0]);
        // Without the local field, z is not determined.
        let free = fit_mag(&raw, LocalField::default()).unwrap();
        assert_eq!(free.hard_iron_ut[2], None);
        // A quarter turn is refused, saying how much it covered.
        let quarter = fit_mag(&raw[..160], local).unwrap_err();
        // (Judged around the ellipse a short arc fits, which is not the true one: more than
        // the 92° turned, still far from enough.)
        let CalibrationError::Coverage(message) = &quarter else {
            panic!("{quarter}")
        };
        let degrees: usize = message["the turn covered ".len()..]
            .split('°')
            .next()
            .and_then(|d| d.parse().ok())
            .expect(message);
        assert!((90..=180).contains(&degrees), "{message}");
        // Half a sphere's worth of a tumble is not enough either.
        let cap = (0..400).map(|k| {
            let t = f64::from(k) * 0.01;
            nalgebra::Rotation3::from_euler_angles(0.3 * t.sin(), 0.3 * t.cos(), t)
        });
        let cap = fit_mag(&raw_fields(a, b, field(), cap, 0.3), local).unwrap_err();
        assert!(matches!(&cap, CalibrationError::Coverage(_)), "{cap}");
        // A turn about a tilted axis is refused.
        // m = Rx(−0.5)·Rz(−θ)·F: a circle whose plane is tilted 0.5 rad from the chip's xy.
        let tilted = (0..1000).map(|k| {
            nalgebra::Rotation3::from_euler_angles(0.0, 0.0, f64::from(k) * 0.01)
                * nalgebra::Rotation3::from_euler_angles(0.5, 0.0, 0.0)
        });
        let tilted = fit_mag(&raw_fields(a, b, field(), tilted, 0.3), local);
        assert!(
            matches!(tilted, Err(CalibrationError::TiltedTurn { .. })),
            "{tilted:?}"
        );
    }

    #[test]
    fn the_gyro_bias_is_the_mean_at_rest_and_motion_is_refused() {
        let mut noise = Gauss::new(3, 0.0012);
        let bias = [0.01, -0.02, 0.005];
        let rates: Vec<[f64; 3]> = (0..2000)
            .map(|_| bias.map(|b| b + noise.sample()))
            .collect();
        let fields = vec![[24.0, 0.0, -41.6]; 100];
        let fit = gyro_bias(&rates, &fields, DEFAULT_MAX_RATE_STD_DPS.to_radians()).unwrap();
        for (got, want) in fit.bias_rad_s.iter().zip(bias) {
            assert!((got - want).abs() < 1e-4, "{got} vs {want}");
        }
        // A push: the rate varies.
        let pushed: Vec<[f64; 3]> = rates
            .iter()
            .enumerate()
            .map(|(i, r)| [r[0], r[1], r[2] + 0.1 * (i as f64 * 0.05).sin()])
            .collect();
        let refused = gyro_bias(&pushed, &fields, DEFAULT_MAX_RATE_STD_DPS.to_radians());
        let message = refused.unwrap_err().to_string();
        assert!(
            message.starts_with("the head moved") && message.contains(" z "),
            "{message}"
        );
        // A steady turn: the rate is steady, the field is not.
        let turning: Vec<[f64; 3]> = (0..100)
            .map(|k| {
                let h = f64::from(k) * 0.01;
                [24.0 * h.cos(), -24.0 * h.sin(), -41.6]
            })
            .collect();
        let message = gyro_bias(&rates, &turning, DEFAULT_MAX_RATE_STD_DPS.to_radians())
            .unwrap_err()
            .to_string();
        assert!(message.contains("magnetic field moved"), "{message}");
        assert!(matches!(
            gyro_bias(&rates[..10], &[], 1.0),
            Err(CalibrationError::TooFewSamples { got: 10, .. })
        ));
    }

    #[test]
    fn the_field_monitor_warns_off_its_reference_at_most_once_a_minute() {
        let config = ImuConfig {
            mag_field_ut: Some(48.0),
            ..ImuConfig::default()
        };
        let mut monitor = FieldMonitor::from_config(&config).unwrap();
        assert_eq!(monitor.check(0, [24.0, 0.0, -41.6]), None);
        let disturbed = [30.0, 0.0, -41.6]; // 51.3 µT: +7 %, within 10 %
        assert_eq!(monitor.check(1, disturbed), None);
        let far = [40.0, 0.0, -41.6]; // 57.7 µT: +20 %
        let line = monitor.check(2, far).expect("a warning");
        assert!(
            line.contains("57.7 µT, +20 % off its calibrated 48.0 µT"),
            "{line}"
        );
        assert_eq!(monitor.check(59_000_000_000, far), None);
        assert!(monitor.check(62_000_000_001, far).is_some());
        assert!(FieldMonitor::from_config(&ImuConfig::default()).is_none());
        let raw = [[25.0, 1.0, -40.6], [23.0, 1.0, -40.6], [24.0, 1.0, -40.6]];
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let median = calibrated_magnitude(&raw, [0.0, 1.0, 1.0], &identity).unwrap();
        assert!((median - (24.0f64.powi(2) + 41.6f64.powi(2)).sqrt()).abs() < 1e-9);
    }

    #[test]
    fn imu_keys_are_set_in_place_and_the_rest_of_the_file_is_kept() {
        let text = "device_name = \"t\"  # the name\n\n[i2c]\nsocket = \"/x\"\n\n[imu]\n\
                    # calibration\nbeta = 0.05\nmag_soft_iron = [\n  [1.0, 0.0, 0.0],\n  [0.0, 1.0, 0.0],\n  [0.0, 0.0, 1.0],\n]\n\n\
                    [imu.mount]\nz = 0.1\n";
        let keys = [
            ("mag_hard_iron_ut", toml_array(&[1.0, 2.0, 3.0])),
            (
                "mag_soft_iron",
                toml_matrix(&[[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            ),
        ];
        let out = set_imu_keys(text, &keys).unwrap();
        assert!(out.starts_with("device_name = \"t\"  # the name\n\n[i2c]\nsocket = \"/x\"\n\n[imu]\n# calibration\nbeta = 0.05\n"), "{out}");
        assert!(out.contains("\n[imu.mount]\nz = 0.1\n"), "{out}");
        assert_eq!(out.matches("mag_soft_iron").count(), 1, "{out}");
        let table: toml::Table = out.parse().unwrap();
        assert_eq!(table["imu"]["mag_hard_iron_ut"][2].as_float(), Some(3.0));
        assert_eq!(table["imu"]["mag_soft_iron"][0][0].as_float(), Some(2.0));
        assert_eq!(table["imu"]["beta"].as_float(), Some(0.05));
        // Again: replaced, not added twice.
        let twice = set_imu_keys(&out, &keys).unwrap();
        assert_eq!(twice, out);
        // No [imu]: appended.
        let appended = set_imu_keys("device_name = \"t\"", &keys[..1]).unwrap();
        assert_eq!(
            appended,
            "device_name = \"t\"\n\n[imu]\nmag_hard_iron_ut = [1.000000, 2.000000, 3.000000]\n"
        );
        // An inline [imu] cannot be edited safely.
        let inline = set_imu_keys("imu = { beta = 0.1 }\n", &keys).unwrap_err();
        assert!(inline.contains("valid TOML"), "{inline}");
    }
}
