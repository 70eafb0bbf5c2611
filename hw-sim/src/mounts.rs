//! Where the emulated sensors sit in the default room (world frame: metres, z up).
//!
//! One place for the poses so the CLI, the demo and the tests all simulate the same sensor head.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

/// RPLidar position: horizontal scan plane, 0.4 m above the floor in the middle of the room.
pub const RPLIDAR_POSITION_M: [f64; 3] = [4.0, 3.0, 0.4];
/// Sweep position: 1 m above the floor in the middle of the room.
pub const SWEEP_POSITION_M: [f64; 3] = [4.0, 3.0, 1.0];

/// RPLidar pose: sensor axes = world axes (azimuth 0 along +x, counter-clockwise seen from
/// above).
pub fn rplidar() -> Isometry3<f64> {
    let [x, y, z] = RPLIDAR_POSITION_M;
    Isometry3::translation(x, y, z)
}

/// Sweep pose: a vertical scan plane (the x–z plane) with sensor azimuth 0 pointing up (+z) and
/// azimuth 90° along +x; the spin axis (sensor +z) is world +y.
pub fn sweep() -> Isometry3<f64> {
    let [x, y, z] = SWEEP_POSITION_M;
    // Columns: images of the sensor x, y and z axes in the world.
    #[rustfmt::skip]
    let m = Matrix3::new(
        0.0, 1.0, 0.0,
        0.0, 0.0, 1.0,
        1.0, 0.0, 0.0,
    );
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    Isometry3::from_parts(Translation3::new(x, y, z), rotation)
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    #[test]
    fn sweep_azimuth_zero_points_up_and_ninety_along_x() {
        let pose = super::sweep();
        let up = pose.rotation * Vector3::x();
        let along = pose.rotation * Vector3::y();
        assert!((up - Vector3::z()).norm() < 1e-12);
        assert!((along - Vector3::x()).norm() < 1e-12);
    }
}
