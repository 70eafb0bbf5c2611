//! Sans-I/O lidar protocol drivers: bytes in, [`crate::lidar::LidarEvent`]s out.

pub mod rplidar;
pub mod sweep;
