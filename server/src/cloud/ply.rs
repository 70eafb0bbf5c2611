//! Binary little-endian PLY export, the format every point-cloud viewer opens
//! (MeshLab, CloudCompare, Open3D, PCL's `pcl_viewer`).

use std::io::{self, Write};

use super::CloudPoint;

/// Writes `points` as a binary little-endian PLY with `float x, y, z, intensity` per vertex.
pub fn write_ply<W: Write>(mut out: W, points: &[CloudPoint]) -> io::Result<()> {
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment scan3d\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty float intensity\n\
         end_header\n",
        points.len()
    )?;
    let mut body = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in p.position.iter().chain(std::iter::once(&p.intensity)) {
            body.extend_from_slice(&v.to_le_bytes());
        }
    }
    out.write_all(&body)?;
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_body_are_exact() {
        let points = [
            CloudPoint {
                position: [1.0, -2.0, 0.5],
                intensity: 47.0,
            },
            CloudPoint {
                position: [0.0, 0.0, 0.0],
                intensity: 0.0,
            },
        ];
        let mut bytes = Vec::new();
        write_ply(&mut bytes, &points).unwrap();
        let header = "ply\nformat binary_little_endian 1.0\ncomment scan3d\nelement vertex 2\n\
                      property float x\nproperty float y\nproperty float z\n\
                      property float intensity\nend_header\n";
        assert_eq!(&bytes[..header.len()], header.as_bytes());
        let body = &bytes[header.len()..];
        assert_eq!(body.len(), 32);
        assert_eq!(&body[..4], &[0x00, 0x00, 0x80, 0x3f]); // 1.0f32 LE
        assert_eq!(&body[4..8], &[0x00, 0x00, 0x00, 0xc0]); // -2.0
        assert_eq!(&body[12..16], &[0x00, 0x00, 0x3c, 0x42]); // 47.0
    }
}
