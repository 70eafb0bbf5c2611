//! Ground-truth motion for the IMU emulators: what a perfect IMU would measure at time t.
//!
//! Frames: the body frame is the MPU-9250's accel/gyro frame (z out of the chip top). The Earth
//! frame is the one Madgwick's filter uses: x towards magnetic north (horizontal), y west,
//! z up; gravity's specific-force reference is (0, 0, +1 g) and the field is
//! (B cos I, 0, −B sin I) in the northern hemisphere.

use std::sync::Arc;

use nalgebra::{Isometry3, Vector3};

use crate::trolley::BaseTrajectory;

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

/// An IMU mounted on a moving `base` (the trolley, or a standing head): what it measures is
/// the base's true motion seen from the chip.
///
/// - gyro: the base's angular velocity in the chip frame;
/// - accelerometer: the specific force at the chip, in the chip frame: gravity's reaction
///   (+g up) plus the chip's acceleration, which is the base's plus the tangential (α × r) and
///   centripetal (ω × (ω × r)) terms of the lever arm r from the base's origin to the chip;
/// - magnetometer: the site's field in the chip frame, magnetic north lying
///   `north_heading_rad` counter-clockwise from room x.
#[derive(Debug, Clone)]
pub struct MountedImuTruth {
    /// How `base` moves (ns since the rig's start).
    pub base: Arc<dyn BaseTrajectory>,
    /// The chip's mount on `base` (chip → base).
    pub mount: Isometry3<f64>,
    /// The site's field.
    pub field: EarthField,
    /// Direction of magnetic north in the room: radians counter-clockwise from room x.
    pub north_heading_rad: f64,
}

impl MountedImuTruth {
    /// The field in the room frame (x, y horizontal, z up).
    pub fn field_in_room(&self) -> Vector3<f64> {
        let incl = self.field.inclination_deg.to_radians();
        let horizontal = self.field.total_ut * incl.cos();
        let down = self.field.total_ut * incl.sin();
        let (s, c) = self.north_heading_rad.sin_cos();
        Vector3::new(horizontal * c, horizontal * s, -down)
    }
}

impl ImuTruth for MountedImuTruth {
    fn sample(&self, t_ns: u64) -> TrueImu {
        let m = self.base.motion_at(t_ns);
        let chip = m.pose * self.mount;
        let to_chip = chip.rotation.inverse();
        let r = m.pose.rotation * self.mount.translation.vector;
        let w = m.angular_velocity_rad_s;
        let a = m.accel_m_s2 + m.angular_accel_rad_s2.cross(&r) + w.cross(&w.cross(&r));
        let specific = a + Vector3::new(0.0, 0.0, STANDARD_GRAVITY);
        let v = |x: Vector3<f64>| [x.x, x.y, x.z];
        TrueImu {
            accel_m_s2: v(to_chip * specific),
            gyro_rad_s: v(to_chip * w),
            mag_ut: v(to_chip * self.field_in_room()),
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
    fn an_imu_on_the_trolley_feels_gravity_the_lever_arm_s_acceleration_and_the_turned_field() {
        use crate::trolley::TrolleyPath;
        let path = Arc::new(TrolleyPath::demo_room());
        let mount = Isometry3::translation(0.1, -0.2, 0.3);
        let truth = MountedImuTruth {
            base: path.clone(),
            mount,
            field: EarthField::default(),
            north_heading_rad: 20f64.to_radians(),
        };
        // At rest at the start (heading 0): gravity, no rate, the field 20° to the left.
        let rest = truth.sample(1_000_000_000);
        assert!(close(rest.accel_m_s2, [0.0, 0.0, STANDARD_GRAVITY]));
        assert!(close(rest.gyro_rad_s, [0.0; 3]));
        let level = EarthField::default().in_level_body(-20f64.to_radians());
        assert!(close(rest.mag_ut, level), "{:?} vs {level:?}", rest.mag_ut);
        // Through the first turn: the chip's acceleration is the second difference of its
        // position in the room, seen in the chip's frame; the gyro is the yaw rate.
        let chip_at = |t: f64| (path.pose_at_s(t) * mount).translation.vector;
        let h = 1e-3;
        let mut turned = false;
        for k in 0..400 {
            let t = 35.0 + k as f64 * 0.05;
            let st = path.state_at(t);
            turned |= st.yaw_rate_rad_s.abs() > 0.3;
            let a = (chip_at(t + h) - 2.0 * chip_at(t) + chip_at(t - h)) / (h * h);
            let want = (path.pose_at_s(t) * mount).rotation.inverse()
                * (a + Vector3::new(0.0, 0.0, STANDARD_GRAVITY));
            let got = truth.sample((t * 1e9).round() as u64);
            for i in 0..3 {
                assert!(
                    (got.accel_m_s2[i] - want[i]).abs() < 1e-3,
                    "t {t}: {:?} vs {want:?}",
                    got.accel_m_s2
                );
            }
            assert!(
                (got.gyro_rad_s[2] - st.yaw_rate_rad_s).abs() < 1e-6,
                "t {t}"
            );
            let heading = st.heading_rad - 20f64.to_radians();
            assert!(close(
                got.mag_ut,
                EarthField::default().in_level_body(heading)
            ));
        }
        assert!(turned, "no turn between 35 and 55 s");
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
