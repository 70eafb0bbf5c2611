//! The simulated world: a conference room with ground truth and ray intersection.
//! (being written; the signatures of [`World::cast`] and [`Scanner`] are fixed)

use std::sync::Arc;

use nalgebra::{Isometry3, Point3, Unit, Vector3};
use rand::Rng;

use crate::noise::RangeNoise;

/// The simulated environment.
#[derive(Debug, Clone, Default)]
pub struct World {}

impl World {
    /// The default room: about 8 × 6 × 3 m with a door, a table, chairs/boxes and a glass wall.
    pub fn conference_room() -> Self {
        Self {}
    }

    /// Distance along the ray to the first surface that returns the beam, if any within
    /// `max_range_m`. Glass returns are random (pass through or reflect), drawn from `rng`.
    pub fn cast<R: Rng + ?Sized>(
        &self,
        _origin: &Point3<f64>,
        _dir: &Unit<Vector3<f64>>,
        _max_range_m: f64,
        _rng: &mut R,
    ) -> Option<f64> {
        None
    }
}

/// A 2D lidar placed in the world: what one beam at a given azimuth measures.
#[derive(Debug, Clone)]
pub struct Scanner {
    /// The world the beam travels in.
    pub world: Arc<World>,
    /// Sensor frame → world frame. In the sensor frame the beam at azimuth α (radians,
    /// counter-clockwise about +z) points along (cos α, sin α, 0).
    pub pose: Isometry3<f64>,
    /// Range noise added to true ranges.
    pub noise: RangeNoise,
    /// Shortest range the sensor reports, metres (closer → no return).
    pub min_range_m: f64,
    /// Longest range the sensor reports, metres (farther → no return).
    pub max_range_m: f64,
}

impl Scanner {
    /// Noisy range measured at azimuth `azimuth_rad` (sensor frame, counter-clockwise),
    /// or `None` for no return.
    pub fn measure<R: Rng + ?Sized>(&self, azimuth_rad: f64, rng: &mut R) -> Option<f64> {
        let dir = Unit::new_normalize(
            self.pose.rotation * Vector3::new(azimuth_rad.cos(), azimuth_rad.sin(), 0.0),
        );
        let origin = Point3::from(self.pose.translation.vector);
        let range = self.world.cast(&origin, &dir, self.max_range_m, rng)?;
        let noisy = self.noise.apply(range, rng);
        (noisy >= self.min_range_m && noisy <= self.max_range_m).then_some(noisy)
    }
}
