//! Rigid 2D poses: (x, y, θ) with composition and inverse, the SE(2) algebra that trajectories,
//! relations and the scan matcher share.

use serde::{Deserialize, Serialize};

/// A rigid 2D transform: translation (m) and heading θ (rad, counter-clockwise, kept in (−π, π]).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose2 {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

impl Pose2 {
    /// The pose at (x, y) with heading `theta`, wrapped into (−π, π].
    pub fn new(x: f64, y: f64, theta: f64) -> Self {
        Self {
            x,
            y,
            theta: wrap_angle(theta),
        }
    }

    /// `self ⊕ other`: `other` expressed in the frame of `self`, brought to the outer frame.
    pub fn compose(&self, other: &Pose2) -> Pose2 {
        let (s, c) = self.theta.sin_cos();
        Pose2::new(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            self.theta + other.theta,
        )
    }

    /// The inverse transform: `p.inverse().compose(&p)` is the identity.
    pub fn inverse(&self) -> Pose2 {
        let (s, c) = self.theta.sin_cos();
        Pose2::new(
            -c * self.x - s * self.y,
            s * self.x - c * self.y,
            -self.theta,
        )
    }

    /// `self⁻¹ ⊕ other`: the motion from `self` to `other`, in the frame of `self`.
    pub fn between(&self, other: &Pose2) -> Pose2 {
        self.inverse().compose(other)
    }

    /// The pose a fraction `u` of the way from `self` to `other` (0: `self`, 1: `other`): the
    /// motion between them scaled by `u`, x, y and θ alike, in the frame of `self`. It is the
    /// SE(2) geodesic to first order (exact for a pure rotation or translation), which is what
    /// trajectories, the relations metric and odometry tracks interpolate with.
    pub fn interpolate(&self, other: &Pose2, u: f64) -> Pose2 {
        let d = self.between(other);
        self.compose(&Pose2::new(u * d.x, u * d.y, u * d.theta))
    }

    /// A point given in this pose's frame, expressed in the outer frame.
    pub fn transform_point(&self, x: f64, y: f64) -> (f64, f64) {
        let (s, c) = self.theta.sin_cos();
        (self.x + c * x - s * y, self.y + s * x + c * y)
    }
}

/// A rigid 2D velocity in the outer (map) frame: the rates of x and y (m/s) and of θ (rad/s,
/// counter-clockwise).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Velocity2 {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

/// `angle` wrapped into (−π, π].
pub fn wrap_angle(angle: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    // Angles already in range come back bit for bit (a logged −0.002458 stays −0.002458).
    if angle > -PI && angle <= PI {
        return angle;
    }
    let wrapped = angle.rem_euclid(TAU);
    if wrapped > PI { wrapped - TAU } else { wrapped }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Pose2, b: &Pose2) -> bool {
        (a.x - b.x).abs() < 1e-12
            && (a.y - b.y).abs() < 1e-12
            && wrap_angle(a.theta - b.theta).abs() < 1e-12
    }

    #[test]
    fn a_pose_composed_with_its_inverse_is_the_identity() {
        let p = Pose2::new(1.5, -2.0, 2.9);
        assert!(close(&p.compose(&p.inverse()), &Pose2::default()));
        assert!(close(&p.inverse().compose(&p), &Pose2::default()));
    }

    #[test]
    fn between_gives_the_motion_in_the_first_frame() {
        // Facing +y at (1, 0); the point (1, 1) is one metre straight ahead.
        let a = Pose2::new(1.0, 0.0, std::f64::consts::FRAC_PI_2);
        let b = Pose2::new(1.0, 1.0, std::f64::consts::PI);
        assert!(close(
            &a.between(&b),
            &Pose2::new(1.0, 0.0, std::f64::consts::FRAC_PI_2)
        ));
        assert!(close(&a.compose(&a.between(&b)), &b));
    }

    #[test]
    fn interpolation_scales_the_motion_between_two_poses() {
        let a = Pose2::new(1.0, 2.0, 3.0);
        let b = Pose2::new(1.5, 1.0, -2.9);
        assert!(close(&a.interpolate(&b, 0.0), &a));
        assert!(close(&a.interpolate(&b, 1.0), &b));
        // Across the ±π seam the heading takes the short way: 3.0 to −2.9 is +0.383 rad.
        let half = a.interpolate(&b, 0.5);
        assert!((wrap_angle(half.theta - 3.0) - 0.5 * wrap_angle(-2.9 - 3.0)).abs() < 1e-12);
        // A pure translation is interpolated exactly.
        let c = Pose2::new(3.0, 6.0, 3.0);
        assert!(close(&a.interpolate(&c, 0.25), &Pose2::new(1.5, 3.0, 3.0)));
    }

    #[test]
    fn angles_wrap_into_the_half_open_interval() {
        use std::f64::consts::PI;
        assert_eq!(wrap_angle(PI), PI);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-15);
        assert!((wrap_angle(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
    }
}
