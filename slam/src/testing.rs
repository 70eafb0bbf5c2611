//! Scenes for the unit tests: walls as segments, and what a 360° lidar sees of them.

use crate::pose::Pose2;

/// A wall from one end to the other (m).
pub(crate) type Segment = ((f64, f64), (f64, f64));

/// The endpoints (sensor frame) of `beams` beams evenly spread over a full turn from `pose`,
/// each at the nearest of `segments` it meets; beams that meet none are dropped.
pub(crate) fn cast(segments: &[Segment], pose: &Pose2, beams: u32) -> Vec<(f64, f64)> {
    (0..beams)
        .filter_map(|k| {
            let azimuth = std::f64::consts::TAU * f64::from(k) / f64::from(beams);
            cast_beam(segments, pose, azimuth)
        })
        .collect()
}

/// The endpoint (sensor frame) of one beam from `pose` at `azimuth` (rad, sensor frame), at the
/// nearest of `segments` it meets.
pub(crate) fn cast_beam(segments: &[Segment], pose: &Pose2, azimuth: f64) -> Option<(f64, f64)> {
    let (dy, dx) = (pose.theta + azimuth).sin_cos();
    let range = segments
        .iter()
        .filter_map(|&((x1, y1), (x2, y2))| {
            let (ex, ey) = (x2 - x1, y2 - y1);
            let den = dx * ey - dy * ex;
            if den.abs() < 1e-12 {
                return None;
            }
            let (wx, wy) = (x1 - pose.x, y1 - pose.y);
            let t = (wx * ey - wy * ex) / den;
            let u = (wx * dy - wy * dx) / den;
            (t > 0.0 && (0.0..=1.0).contains(&u)).then_some(t)
        })
        .fold(f64::INFINITY, f64::min);
    range
        .is_finite()
        .then(|| (range * azimuth.cos(), range * azimuth.sin()))
}

/// The four walls of an axis-aligned room from `(x0, y0)` to `(x1, y1)`, counter-clockwise.
pub(crate) fn rectangle((x0, y0): (f64, f64), (x1, y1): (f64, f64)) -> [Segment; 4] {
    [
        ((x0, y0), (x1, y0)),
        ((x1, y0), (x1, y1)),
        ((x1, y1), (x0, y1)),
        ((x0, y1), (x0, y0)),
    ]
}
