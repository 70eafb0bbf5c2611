//! The simulated world: a conference room with ground truth and ray intersection.

use nalgebra::{Point3, Unit, Vector3};
use rand::Rng;

/// The simulated environment (being written; the signature of [`World::cast`] is fixed).
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
