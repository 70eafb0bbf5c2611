//! Point clouds: static-scan assembly (eq. 1), per-sensor revolutions ([`scans`]), filters,
//! and the PLY / PCD / `.scans` formats ([`flat`] holds what their readers share, [`io`] picks
//! one by extension).

pub mod assembly;
pub mod filter;
pub mod flat;
pub mod io;
pub mod moving;
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

/// Points seen from one sensor origin (e.g. half a Sweep revolution of a static scan, or one
/// node of a `.graph`), as OctoMap's ray casting needs them: one ray from `origin` to each
/// point. One octree insertion takes one bundle.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RayBundle {
    /// The sensor origin, world frame.
    pub origin: [f64; 3],
    /// The points, world frame.
    pub points: Vec<[f32; 3]>,
}
