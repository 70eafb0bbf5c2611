//! Ground-truth motion for the IMU emulators: what a perfect IMU would measure at time t.
//!
//! Frames: the body frame is the MPU-9250's accel/gyro frame (z out of the chip top). The Earth
//! frame is the one Madgwick's filter uses: x towards magnetic north (horizontal), y west,
//! z up; gravity's specific-force reference is (0, 0, +1 g) and the field is
//! (B cos I, 0, −B sin I) in the northern hemisphere.

/// Standard gravity, m/s².
pub const STANDARD_GRAVITY: f64 = 9.80665;

/// What an ideal IMU measures at one instant, all in the body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueImu {
    /// Specific force (acceleration minus gravity), m/s²: (0, 0, +9.81) when level and still.
    pub accel_m_s2: [f64; 3],
    /// Body angular rate, rad/s.
    pub gyro_rad_s: [f64; 3],
    /// Magnetic field, µT.
    pub mag_ut: [f64; 3],
}

/// A source of ground truth; a pure function of time so samples are reproducible.
pub trait ImuTruth: Send + Sync {
    /// The true measurements at `t_ns` (simulated nanoseconds).
    fn sample(&self, t_ns: u64) -> TrueImu;
}

/// The Earth's field at the site.
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct EarthField {
    /// Total intensity, µT.
    pub total_ut: f64,
    /// Inclination (dip) below the horizontal, degrees (positive in the northern hemisphere).
    pub inclination_deg: f64,
}

impl Default for EarthField {
    /// 48 µT at 60° inclination (central Europe / northern China).
    fn default() -> Self {
        Self {
            total_ut: 48.0,
            inclination_deg: 60.0,
        }
    }
}

impl EarthField {
    /// The field in the body frame of a level IMU whose x axis points `heading_rad` from
    /// magnetic north, counter-clockwise seen from above (towards west).
    pub fn in_level_body(&self, heading_rad: f64) -> [f64; 3] {
        let incl = self.inclination_deg.to_radians();
        let horizontal = self.total_ut * incl.cos();
        let down = self.total_ut * incl.sin();
        let (s, c) = heading_rad.sin_cos();
        // Body = Rz(heading)ᵀ · (horizontal, 0, −down).
        [horizontal * c, -horizontal * s, -down]
    }
}

/// A still, level IMU at a fixed heading.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StaticTruth {
    /// Heading of the body x axis from magnetic north, counter-clockwise, radians.
    pub heading_rad: f64,
    /// The site's field.
    pub field: EarthField,
}

impl ImuTruth for StaticTruth {
    fn sample(&self, _t_ns: u64) -> TrueImu {
        TrueImu {
            accel_m_s2: [0.0, 0.0, STANDARD_GRAVITY],
            gyro_rad_s: [0.0; 3],
            mag_ut: self.field.in_level_body(self.heading_rad),
        }
    }
}

/// A level IMU turning about the vertical at a constant rate (a turntable).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct YawRateTruth {
    /// Heading at t = 0, radians.
    pub heading0_rad: f64,
    /// Yaw rate, rad/s (positive counter-clockwise seen from above).
    pub yaw_rate_rad_s: f64,
    /// The site's field.
    pub field: EarthField,
}

impl YawRateTruth {
    /// The heading at `t_ns`.
    pub fn heading_at(&self, t_ns: u64) -> f64 {
        self.heading0_rad + self.yaw_rate_rad_s * (t_ns as f64 * 1e-9)
    }
}

impl ImuTruth for YawRateTruth {
    fn sample(&self, t_ns: u64) -> TrueImu {
        TrueImu {
            accel_m_s2: [0.0, 0.0, STANDARD_GRAVITY],
            gyro_rad_s: [0.0, 0.0, self.yaw_rate_rad_s],
            mag_ut: self.field.in_level_body(self.heading_at(t_ns)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
    }

    #[test]
    fn earth_field_components() {
        let f = EarthField::default();
        // 48 µT at 60°: horizontal 24 µT, vertical 41.569 µT downwards (−z).
        assert!(close(
            f.in_level_body(0.0),
            [24.0, 0.0, -41.569_219_381_653_05]
        ));
        // Body x turned 90° towards west: north is now along body −y.
        assert!(close(
            f.in_level_body(std::f64::consts::FRAC_PI_2),
            [0.0, -24.0, -41.569_219_381_653_05]
        ));
    }

    #[test]
    fn yaw_rate_truth_turns_the_field() {
        let t = YawRateTruth {
            heading0_rad: 0.0,
            yaw_rate_rad_s: std::f64::consts::PI,
            field: EarthField::default(),
        };
        let s = t.sample(500_000_000);
        assert!(close(s.gyro_rad_s, [0.0, 0.0, std::f64::consts::PI]));
        assert!(close(s.mag_ut, [0.0, -24.0, -41.569_219_381_653_05]));
        assert!(close(s.accel_m_s2, [0.0, 0.0, 9.80665]));
    }
}
