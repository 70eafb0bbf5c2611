//! 3D assembly of static scans at known positions: the paper's eq. (1) with the mount geometry.
//!
//! The Sweep spins in a vertical plane on a turntable. θ is its beam azimuth in that plane,
//! with θ = 0 pointing up (z = L·cos θ), so θ ≈ π points down into the base, where the beam is
//! blocked. φ is the turntable's yaw. For a sample (L, θ) taken at yaw φ at the position
//! (x_p, y_p), eq. (1) gives
//!
//! ```text
//! x = x_p − L·sin θ·sin φ
//! y = y_p + L·sin θ·cos φ
//! z =       L·cos θ
//! ```
//!
//! Samples with θ ∈ (0, π) use the yaw in effect during the first half of the revolution;
//! the stepper turns by δφ while the beam crosses the blocked sector, so samples with
//! θ ∈ (π, 2π) use φ + δφ. Which yaw applies is decided when the sample is tagged on the edge;
//! here every sample carries its own φ.
//!
//! Beyond the paper, [`MountGeometry`] places the Sweep's optical centre relative to the
//! turntable axis (its offset beside the axis and its height) and the azimuth at which the
//! device reports 0; [`Position`] adds a heading φ0 so several positions can be spliced in
//! one world frame.

use std::io::{self, Write};

use serde::{Deserialize, Serialize};

pub use super::OriginScan;

/// How the Sweep sits on the turntable.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MountGeometry {
    /// Distance of the Sweep's optical centre from the turntable axis, along the scan plane's
    /// normal (+ = towards yaw direction φ), metres.
    pub axis_offset_m: f64,
    /// Height of the optical centre above the floor, metres.
    pub height_m: f64,
    /// The device azimuth that points straight up (θ = 0 of eq. (1)), degrees.
    pub azimuth_zero_deg: f64,
}

impl Default for MountGeometry {
    fn default() -> Self {
        Self {
            axis_offset_m: 0.0,
            height_m: 0.0,
            azimuth_zero_deg: 0.0,
        }
    }
}

/// A scan position on the floor, in the global frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Position {
    /// The operator's name for it (e.g. `"door"`).
    pub name: String,
    /// x_p, metres.
    pub x_m: f64,
    /// y_p, metres.
    pub y_m: f64,
    /// φ0: the turntable yaw 0 expressed in the global frame, degrees.
    pub heading_deg: f64,
}

/// One Sweep sample of a static scan, with the turntable yaw it was taken at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticSample {
    /// Range L, metres (`0.0` = no return: skipped).
    pub range_m: f64,
    /// Device azimuth, degrees (counter-clockwise, as the Sweep reports it).
    pub azimuth_deg: f64,
    /// Turntable yaw φ in effect for this sample, degrees (relative to the position's heading).
    pub yaw_deg: f64,
}

/// The sensor origin (optical centre) at yaw `yaw_deg` for `position`.
pub fn sensor_origin(position: &Position, mount: &MountGeometry, yaw_deg: f64) -> [f64; 3] {
    let phi = (position.heading_deg + yaw_deg).to_radians();
    [
        position.x_m + mount.axis_offset_m * phi.cos(),
        position.y_m + mount.axis_offset_m * phi.sin(),
        mount.height_m,
    ]
}

/// Eq. (1): the world point of one sample, or `None` for a sample without return.
pub fn static_point(
    position: &Position,
    mount: &MountGeometry,
    sample: &StaticSample,
) -> Option<[f64; 3]> {
    if !(sample.range_m.is_finite() && sample.range_m > 0.0) {
        return None;
    }
    let theta = (sample.azimuth_deg - mount.azimuth_zero_deg).to_radians();
    let phi = (position.heading_deg + sample.yaw_deg).to_radians();
    let [ox, oy, oz] = sensor_origin(position, mount, sample.yaw_deg);
    let l = sample.range_m;
    Some([
        ox - l * theta.sin() * phi.sin(),
        oy + l * theta.sin() * phi.cos(),
        oz + l * theta.cos(),
    ])
}

/// Writes `.scans` (`research/octomap.md` §6.5): for each scan `u32 n; f64 ox, oy, oz;
/// n × (f32 x, f32 y, f32 z)`, little-endian, read until end of file.
pub fn write_scans<W: Write>(mut out: W, scans: &[OriginScan]) -> io::Result<()> {
    for scan in scans {
        let n = u32::try_from(scan.points.len()).map_err(|_| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                "more than 2^32 points in one scan",
            )
        })?;
        out.write_all(&n.to_le_bytes())?;
        for c in scan.origin {
            out.write_all(&c.to_le_bytes())?;
        }
        for p in &scan.points {
            for c in p {
                out.write_all(&c.to_le_bytes())?;
            }
        }
    }
    out.flush()
}

/// Writes a binary PCD (v0.7, `x y z` as `F 4`), the format PCL tools and viewers read.
pub fn write_pcd<W: Write>(mut out: W, points: &[[f32; 3]]) -> io::Result<()> {
    write!(
        out,
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n\
         TYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n\
         DATA binary\n",
        n = points.len()
    )?;
    let mut body = Vec::with_capacity(points.len() * 12);
    for p in points {
        for c in p {
            body.extend_from_slice(&c.to_le_bytes());
        }
    }
    out.write_all(&body)?;
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at_origin() -> Position {
        Position {
            name: "p".into(),
            x_m: 0.0,
            y_m: 0.0,
            heading_deg: 0.0,
        }
    }

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
    }

    fn point(position: &Position, range: f64, azimuth: f64, yaw: f64) -> [f64; 3] {
        let sample = StaticSample {
            range_m: range,
            azimuth_deg: azimuth,
            yaw_deg: yaw,
        };
        static_point(position, &MountGeometry::default(), &sample).expect("a return")
    }

    #[test]
    fn equation_one_by_hand() {
        let p = Position {
            name: "a".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 0.0,
        };
        // θ = 0: straight up.
        assert!(close(point(&p, 2.0, 0.0, 30.0), [1.0, 2.0, 2.0]));
        // θ = 90°, φ = 0: along +y.
        assert!(close(point(&p, 2.0, 90.0, 0.0), [1.0, 4.0, 0.0]));
        // θ = 90°, φ = 90°: along −x.
        assert!(close(point(&p, 2.0, 90.0, 90.0), [-1.0, 2.0, 0.0]));
        // θ = 270° (second half): the opposite side of the same plane.
        assert!(close(point(&p, 2.0, 270.0, 0.0), [1.0, 0.0, 0.0]));
    }

    #[test]
    fn the_second_half_revolution_uses_phi_plus_delta_phi() {
        // The beam at θ = 90° before the step and θ = 270° after a 1.8° step sees two points
        // whose planes differ by exactly δφ.
        let p = at_origin();
        let first = point(&p, 1.0, 90.0, 0.0);
        let second = point(&p, 1.0, 270.0, 1.8);
        let angle_first = first[1].atan2(first[0]).to_degrees();
        let angle_second = (-second[1]).atan2(-second[0]).to_degrees();
        assert!(
            (angle_second - angle_first - 1.8).abs() < 1e-9,
            "{angle_first} {angle_second}"
        );
    }

    #[test]
    fn mount_geometry_and_heading_move_the_origin() {
        let mount = MountGeometry {
            axis_offset_m: 0.1,
            height_m: 1.0,
            azimuth_zero_deg: 180.0,
        };
        let p = Position {
            name: "b".into(),
            x_m: 3.0,
            y_m: 0.0,
            heading_deg: 90.0,
        };
        assert!(close(sensor_origin(&p, &mount, 0.0), [3.0, 0.1, 1.0]));
        // Device azimuth 180° is "up" on this mount.
        let s = StaticSample {
            range_m: 1.5,
            azimuth_deg: 180.0,
            yaw_deg: 0.0,
        };
        assert!(close(
            static_point(&p, &mount, &s).unwrap(),
            [3.0, 0.1, 2.5]
        ));
        let none = StaticSample { range_m: 0.0, ..s };
        assert_eq!(static_point(&p, &mount, &none), None);
    }

    #[test]
    fn scans_and_pcd_bytes_are_exact() {
        let scans = [OriginScan {
            origin: [1.0, 2.0, 3.0],
            points: vec![[0.5, -1.0, 2.0]],
        }];
        let mut bytes = Vec::new();
        write_scans(&mut bytes, &scans).unwrap();
        assert_eq!(bytes.len(), 4 + 24 + 12);
        assert_eq!(&bytes[..4], &1u32.to_le_bytes());
        assert_eq!(&bytes[4..12], &1.0f64.to_le_bytes());
        assert_eq!(&bytes[28..32], &0.5f32.to_le_bytes());
        let mut pcd = Vec::new();
        write_pcd(&mut pcd, &[[1.0, 2.0, 3.0]]).unwrap();
        let text = String::from_utf8_lossy(&pcd);
        assert!(text.contains("POINTS 1\nDATA binary\n"), "{text}");
        assert_eq!(&pcd[pcd.len() - 12..pcd.len() - 8], &1.0f32.to_le_bytes());
    }
}
