//! Device drivers.
//!
//! - [`rplidar`], [`sweep`]: sans-I/O lidar protocol drivers (bytes in,
//!   [`crate::lidar::LidarEvent`]s out).
//! - [`imu`], [`stepper`]: I2C drivers generic over `embedded_hal::i2c::I2c` (MPU-9250/AK8963,
//!   PCA9685 motor HAT).

pub mod imu;
pub mod rplidar;
pub mod stepper;
pub mod sweep;
