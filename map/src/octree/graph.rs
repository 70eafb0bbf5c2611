//! OctoMap's binary ScanGraph (`.graph`, research/octomap.md §6.3) read into world-frame bundles
//! with OctoMap's own f32 pose transform, so inserting them gives graph2tree's tree.

use super::OctreeError;
use crate::cloud::RayBundle;

/// Bytes of a serialized `Vector3` (i32 count, 3 × f64) and `Quaternion` (i32 count, 4 × f64).
const VEC3_BYTES: usize = 28;
const QUAT_BYTES: usize = 36;
/// A ScanEdge: two u32 ids, a Pose6D, an f64 weight.
const EDGE_BYTES: usize = 8 + VEC3_BYTES + QUAT_BYTES + 8;

struct Reader<'a> {
    rest: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], OctreeError> {
        if self.rest.len() < n {
            return Err(OctreeError::Truncated { what });
        }
        let (head, tail) = self.rest.split_at(n);
        self.rest = tail;
        Ok(head)
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, OctreeError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// `count` f64 values after an i32 element count (ignored, as OctoMap does), cast to f32.
    fn floats<const N: usize>(&mut self, what: &'static str) -> Result<[f32; N], OctreeError> {
        let b = self.take(4 + 8 * N, what)?;
        Ok(std::array::from_fn(|i| {
            let o = 4 + 8 * i;
            let mut a = [0u8; 8];
            a.copy_from_slice(&b[o..o + 8]);
            f64::from_le_bytes(a) as f32
        }))
    }

    /// A u32 count of records of `size` bytes, refused if the remaining bytes cannot hold them.
    fn count(&mut self, size: usize, what: &'static str) -> Result<usize, OctreeError> {
        let n = self.u32(what)? as usize;
        if n.saturating_mul(size) > self.rest.len() {
            return Err(OctreeError::Truncated { what });
        }
        Ok(n)
    }
}

/// Quaternion product (u, x, y, z) in f32, in the operator order of OctoMap's `Quaternion.cpp`.
#[inline]
fn qmul(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[2] * b[3] - b[2] * a[3] + a[0] * b[1] + b[0] * a[1],
        a[3] * b[1] - b[3] * a[1] + a[0] * b[2] + b[0] * a[2],
        a[1] * b[2] - b[1] * a[2] + a[0] * b[3] + b[0] * a[3],
    ]
}

/// OctoMap's `Pose6D::transform`: `q * (0, v) * q⁻¹` (q not re-normalized) plus `t`, all f32.
/// `q` is (w, x, y, z).
pub fn transform_point(t: [f32; 3], q: [f32; 4], v: [f32; 3]) -> [f32; 3] {
    let r = qmul(
        qmul(q, [0.0, v[0], v[1], v[2]]),
        [q[0], -q[1], -q[2], -q[3]],
    );
    [r[1] + t[0], r[2] + t[1], r[3] + t[2]]
}

/// Reads a binary `.graph` into one world-frame bundle per node, exactly as graph2tree (and
/// `octomap_bench -export-scans`) transforms them: points by the node pose in f32, origin =
/// the pose translation. Edges are checked for completeness and ignored.
pub fn read_graph(bytes: &[u8]) -> Result<Vec<RayBundle>, OctreeError> {
    let mut r = Reader { rest: bytes };
    // A node is at least a point count, a pose and an id.
    let nodes = r.count(4 + VEC3_BYTES + QUAT_BYTES + 4, ".graph node count")?;
    let mut bundles = Vec::with_capacity(nodes);
    for _ in 0..nodes {
        let n = r.count(VEC3_BYTES, ".graph point cloud")?;
        let mut local = Vec::with_capacity(n);
        for _ in 0..n {
            local.push(r.floats::<3>(".graph point")?);
        }
        let t = r.floats::<3>(".graph pose translation")?;
        let q = r.floats::<4>(".graph pose rotation")?;
        r.u32(".graph node id")?;
        let points = local
            .into_iter()
            .map(|p| transform_point(t, q, p))
            .collect();
        bundles.push(RayBundle {
            origin: t.map(f64::from),
            points,
        });
    }
    let edges = r.count(EDGE_BYTES, ".graph edge count")?;
    r.take(edges * EDGE_BYTES, ".graph edges")?;
    Ok(bundles)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vec3(out: &mut Vec<u8>, v: [f64; 3]) {
        out.extend_from_slice(&3i32.to_le_bytes());
        v.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
    }

    fn graph(points: &[[f64; 3]], t: [f64; 3], q: [f64; 4]) -> Vec<u8> {
        let mut g = 1u32.to_le_bytes().to_vec();
        g.extend_from_slice(&(points.len() as u32).to_le_bytes());
        points.iter().for_each(|p| vec3(&mut g, *p));
        vec3(&mut g, t);
        g.extend_from_slice(&4i32.to_le_bytes());
        q.iter().for_each(|x| g.extend_from_slice(&x.to_le_bytes()));
        g.extend_from_slice(&7u32.to_le_bytes());
        g.extend_from_slice(&0u32.to_le_bytes());
        g
    }

    #[test]
    fn identity_pose_translates_in_f32() {
        let g = graph(
            &[[1.0, 2.0, 3.0], [0.1, 0.2, 0.3]],
            [1.0, 0.0, -0.5],
            [1.0, 0.0, 0.0, 0.0],
        );
        assert_eq!(g.len(), 4 + 4 + 2 * 28 + 64 + 4 + 4);
        let s = read_graph(&g).unwrap();
        assert_eq!(s.len(), 1);
        assert_eq!(s[0].origin, [1.0, 0.0, -0.5]);
        assert_eq!(s[0].points[0], [2.0, 2.0, 2.5]);
        assert_eq!(s[0].points[1], [0.1f32 + 1.0, 0.2f32, 0.3f32 - 0.5]);
    }

    #[test]
    fn yaw_90_rotates_x_to_y() {
        // q = (cos 45°, 0, 0, sin 45°): x axis -> y axis (up to f32 rounding).
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let g = graph(&[[2.0, 0.0, 0.0]], [0.0; 3], [h, 0.0, 0.0, h]);
        let p = read_graph(&g).unwrap()[0].points[0];
        assert!(
            p[0].abs() < 1e-6 && (p[1] - 2.0).abs() < 1e-6 && p[2] == 0.0,
            "{p:?}"
        );
    }

    #[test]
    fn truncated_and_lying_counts_are_errors() {
        let g = graph(&[[1.0, 2.0, 3.0]], [0.0; 3], [1.0, 0.0, 0.0, 0.0]);
        for cut in [0, 3, 10, g.len() - 1] {
            assert!(
                matches!(read_graph(&g[..cut]), Err(OctreeError::Truncated { .. })),
                "cut {cut}"
            );
        }
        let mut lying = g.clone();
        lying[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            read_graph(&lying).unwrap_err(),
            OctreeError::Truncated {
                what: ".graph point cloud"
            }
        );
    }
}
