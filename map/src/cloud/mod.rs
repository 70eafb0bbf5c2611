//! Point clouds: static-scan assembly (eq. 1), per-sensor 2D scans, and PLY / PCD / .scans export.

pub mod assembly;
pub mod filter;
pub mod flat;
pub mod io;
pub mod pcd;
pub mod ply;
pub mod scans;
pub mod scans_file;

/// One point of a cloud with the intensity the sensor reported for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudPoint {
    /// Position in metres (frame given by the cloud's producer).
    pub position: [f32; 3],
    /// Sensor quality / signal strength, as reported.
    pub intensity: f32,
}

/// Points of one revolution with the sensor origin they were seen from, as OctoMap's ray
/// casting needs them.
#[derive(Debug, Clone, PartialEq)]
pub struct RayBundle {
    /// The sensor origin, world frame.
    pub origin: [f64; 3],
    /// The points, world frame.
    pub points: Vec<[f32; 3]>,
}
