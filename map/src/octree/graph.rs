//! OctoMap's binary ScanGraph (`.graph`, research/octomap.md §6.3) read into world-frame bundles
//! with OctoMap's own f32 pose transform, so inserting them gives graph2tree's tree.

use std::io::Read;

use super::OctreeError;
use crate::cloud::RayBundle;

/// Bytes of a serialized `Vector3` (i32 count, 3 × f64) and `Quaternion` (i32 count, 4 × f64).
const VEC3_BYTES: usize = 28;
const QUAT_BYTES: usize = 36;
/// A ScanEdge: two u32 ids, a Pose6D, an f64 weight.
const EDGE_BYTES: usize = 8 + VEC3_BYTES + QUAT_BYTES + 8;

/// Points read and parsed per chunk (28 bytes each on disk).
const CHUNK_POINTS: usize = 4096;
/// Points reserved for a node before they are read (192 kB; a hostile count costs no more).
const PREALLOC_POINTS: usize = 1 << 14;

/// The stream being parsed, with the errors named by what was being read.
struct Reader<R> {
    source: R,
}

impl<R: Read> Reader<R> {
    fn exact(&mut self, buf: &mut [u8], what: &'static str) -> Result<(), OctreeError> {
        self.source.read_exact(buf).map_err(|e| match e.kind() {
            std::io::ErrorKind::UnexpectedEof => OctreeError::Truncated { what },
            _ => OctreeError::Read {
                what,
                reason: e.to_string(),
            },
        })
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, OctreeError> {
        let mut b = [0u8; 4];
        self.exact(&mut b, what)?;
        Ok(u32::from_le_bytes(b))
    }

    /// `N` f64 values after an i32 element count (ignored, as OctoMap does), cast to f32.
    fn floats<const N: usize>(&mut self, what: &'static str) -> Result<[f32; N], OctreeError> {
        let mut b = [0u8; 36];
        let b = b
            .get_mut(..4 + 8 * N)
            .ok_or(OctreeError::Truncated { what })?;
        self.exact(b, what)?;
        Ok(floats_at::<N>(b))
    }

    /// `n` serialized `Vector3`s, read and parsed `CHUNK_POINTS` at a time: memory grows with
    /// the points actually read, whatever `n` claims.
    fn points(
        &mut self,
        n: usize,
        out: &mut Vec<[f32; 3]>,
        what: &'static str,
    ) -> Result<(), OctreeError> {
        let mut buf = vec![0u8; VEC3_BYTES * n.min(CHUNK_POINTS)];
        // Bounded: beyond the cap the Vec grows as points actually arrive.
        out.reserve(n.min(PREALLOC_POINTS));
        let mut left = n;
        while left > 0 {
            let k = left.min(CHUNK_POINTS);
            let chunk = buf
                .get_mut(..k * VEC3_BYTES)
                .ok_or(OctreeError::Truncated { what })?;
            self.exact(chunk, what)?;
            out.reserve(k);
            out.extend(chunk.chunks_exact(VEC3_BYTES).map(floats_at::<3>));
            left -= k;
        }
        Ok(())
    }

    /// Reads and drops `n` bytes.
    fn skip(&mut self, n: u64, what: &'static str) -> Result<(), OctreeError> {
        let copied =
            std::io::copy(&mut (&mut self.source).take(n), &mut std::io::sink()).map_err(|e| {
                OctreeError::Read {
                    what,
                    reason: e.to_string(),
                }
            })?;
        if copied < n {
            return Err(OctreeError::Truncated { what });
        }
        Ok(())
    }
}

/// The `N` f64 values after the i32 count at the start of `b`, cast to f32.
#[inline]
fn floats_at<const N: usize>(b: &[u8]) -> [f32; N] {
    std::array::from_fn(|i| {
        let mut a = [0u8; 8];
        if let Some(v) = b.get(4 + 8 * i..12 + 8 * i) {
            a.copy_from_slice(v);
        }
        f64::from_le_bytes(a) as f32
    })
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
#[inline]
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
    read_graph_from(bytes)
}

/// [`read_graph`] from a stream (e.g. a file, which then is never in memory whole: the
/// parse reads it in chunks of a few hundred kB). Counts in the stream are not trusted for
/// allocation; a count larger than the data ends in [`OctreeError::Truncated`].
pub fn read_graph_from(source: impl Read) -> Result<Vec<RayBundle>, OctreeError> {
    let mut bundles = Vec::new();
    visit_graph(source, |bundle| bundles.push(std::mem::take(bundle)))?;
    Ok(bundles)
}

/// [`read_graph_from`] one node at a time: `visit` gets each world-frame bundle as soon as it
/// is read, in file order. The reader reuses the bundle's point buffer for the next node, so a
/// consumer that inserts as it goes holds the map, not the cloud; one that keeps the points
/// takes them (or swaps in a buffer of its own) instead of copying. Returns the node count.
/// An error after some nodes (a truncated file) comes after their visits.
pub fn visit_graph(
    source: impl Read,
    mut visit: impl FnMut(&mut RayBundle),
) -> Result<usize, OctreeError> {
    let mut r = Reader { source };
    let nodes = r.u32(".graph node count")? as usize;
    let mut bundle = RayBundle::default();
    for _ in 0..nodes {
        let n = r.u32(".graph point cloud")? as usize;
        bundle.points.clear();
        r.points(n, &mut bundle.points, ".graph point cloud")?;
        let t = r.floats::<3>(".graph pose translation")?;
        let q = r.floats::<4>(".graph pose rotation")?;
        r.u32(".graph node id")?;
        for p in &mut bundle.points {
            *p = transform_point(t, q, *p);
        }
        bundle.origin = t.map(f64::from);
        visit(&mut bundle);
    }
    let edges = r.u32(".graph edge count")?;
    r.skip(u64::from(edges) * EDGE_BYTES as u64, ".graph edges")?;
    Ok(nodes)
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

    #[test]
    fn a_stream_reads_like_the_bytes_and_a_failing_stream_is_a_read_error() {
        // More points than one chunk, so the chunked parse crosses a boundary.
        let pts: Vec<[f64; 3]> = (0..CHUNK_POINTS + 7)
            .map(|i| [i as f64 * 0.01, 1.0, -(i as f64)])
            .collect();
        let g = graph(&pts, [0.5, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]);
        let from_bytes = read_graph(&g).unwrap();
        assert_eq!(from_bytes[0].points.len(), CHUNK_POINTS + 7);
        assert_eq!(
            from_bytes[0].points[CHUNK_POINTS + 6],
            [
                (((CHUNK_POINTS + 6) as f64 * 0.01) as f32) + 0.5,
                1.0,
                -((CHUNK_POINTS + 6) as f32)
            ]
        );
        assert_eq!(
            read_graph_from(std::io::BufReader::with_capacity(100, &g[..])).unwrap(),
            from_bytes
        );
        struct Failing;
        impl Read for Failing {
            fn read(&mut self, _: &mut [u8]) -> std::io::Result<usize> {
                Err(std::io::Error::other("disk on fire"))
            }
        }
        let e = read_graph_from(Failing).unwrap_err();
        assert_eq!(
            e,
            OctreeError::Read {
                what: ".graph node count",
                reason: "disk on fire".into()
            }
        );
        // A lying edge count: reading stops at the end of the data.
        let mut lying = g.clone();
        let at = lying.len() - 4;
        lying[at..].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            read_graph(&lying).unwrap_err(),
            OctreeError::Truncated {
                what: ".graph edges"
            }
        );
    }
}
