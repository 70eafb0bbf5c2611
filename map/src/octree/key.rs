//! Voxel keys and metric ↔ key conversion, computed exactly as OctoMap does (research/octomap.md §1).

use super::OctreeError;

/// Depth of the tree: keys have 16 bits per axis and depth-16 nodes are single voxels.
pub const TREE_DEPTH: u8 = 16;
/// Key of the coordinate origin on each axis (`tree_max_val` in OctoMap).
pub const KEY_CENTER: u16 = 32768;

/// A voxel address (x, y, z), 16 bits per axis, `KEY_CENTER` at the metric origin.
///
/// At depth 16 it is the voxel itself; for coarser nodes the tree uses OctoMap's *center* keys.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct Key(pub [u16; 3]);

impl Key {
    /// Index (0..8) of the child containing this depth-16 key below a node at `depth` (< 16):
    /// x in bit 0, y in bit 1, z in bit 2, as OctoMap's `computeChildIdx`.
    #[inline]
    pub fn child_index(self, depth: u8) -> usize {
        let level = 15 - u32::from(depth);
        let b = |k: u16| usize::from((k >> level) & 1);
        b(self.0[0]) | (b(self.0[1]) << 1) | (b(self.0[2]) << 2)
    }

    /// The center key of the child `pos` of a node at `depth` with center key `self`
    /// (OctoMap's `computeChildKey`; at depth 16 the result is the voxel key).
    #[inline]
    pub fn child_center(self, pos: usize, depth: u8) -> Key {
        let off = (u32::from(KEY_CENTER) >> (depth + 1)) as u16;
        let mut out = self.0;
        for (axis, k) in out.iter_mut().enumerate() {
            if pos & (1 << axis) != 0 {
                *k = k.wrapping_add(off);
            } else {
                *k = k.wrapping_sub(off).wrapping_sub(u16::from(off == 0));
            }
        }
        Key(out)
    }
}

/// The voxel edge length and its reciprocal, the pair every OctoMap conversion uses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Resolution {
    res: f64,
    factor: f64,
}

impl Resolution {
    /// A resolution in metres; it must be finite and positive.
    pub fn new(res: f64) -> Result<Self, OctreeError> {
        if !(res.is_finite() && res > 0.0) {
            return Err(OctreeError::BadResolution(res));
        }
        Ok(Self {
            res,
            factor: 1.0 / res,
        })
    }

    /// Voxel edge length in metres.
    #[inline]
    pub fn meters(&self) -> f64 {
        self.res
    }

    /// One axis of `coordToKeyChecked`: `floor(c * (1/res)) + 32768` if that is within 0..65536.
    /// Multiplies by the reciprocal (not a division), like OctoMap.
    #[inline]
    pub fn coord_to_key_axis(&self, c: f64) -> Option<u16> {
        let x = self.factor * c;
        // floor(x) is in -32768..32768 iff x is in [-32768, 32768) (false for NaN). There,
        // truncation corrected downwards is exactly floor, without a libm call.
        if !(-32768.0..32768.0).contains(&x) {
            return None;
        }
        let t = x as i32;
        let f = if f64::from(t) > x { t - 1 } else { t };
        Some((f + 32768) as u16)
    }

    /// The voxel key of an f32 point (widened to f64 first), or `None` outside the key range.
    #[inline]
    pub fn coord_to_key(&self, p: [f32; 3]) -> Option<Key> {
        Some(Key([
            self.coord_to_key_axis(f64::from(p[0]))?,
            self.coord_to_key_axis(f64::from(p[1]))?,
            self.coord_to_key_axis(f64::from(p[2]))?,
        ]))
    }

    /// Voxel center of one depth-16 key axis: `((k - 32768) + 0.5) * res`.
    #[inline]
    pub fn key_to_coord_axis(&self, k: u16) -> f64 {
        (f64::from(i32::from(k) - 32768) + 0.5) * self.res
    }

    /// Voxel center of a depth-16 key.
    #[inline]
    pub fn key_to_coord(&self, k: Key) -> [f64; 3] {
        k.0.map(|a| self.key_to_coord_axis(a))
    }

    /// Center of the node at `depth` containing key axis `k` (OctoMap's `keyToCoord(k, depth)`).
    pub fn key_to_coord_at_depth(&self, k: u16, depth: u8) -> f64 {
        match depth {
            0 => 0.0,
            d if d >= TREE_DEPTH => self.key_to_coord_axis(k),
            d => {
                let div = f64::from(1u32 << (TREE_DEPTH - d));
                (((f64::from(k) - 32768.0) / div).floor() + 0.5) * self.node_size(d)
            }
        }
    }

    /// Edge length of a node at `depth`: `res * 2^(16 - depth)`.
    #[inline]
    pub fn node_size(&self, depth: u8) -> f64 {
        self.res * f64::from(1u32 << (TREE_DEPTH - depth.min(TREE_DEPTH)))
    }
}

/// Spreads the low 16 bits of `v` so that bit i lands at bit 3i: one axis of a [`morton`]
/// code. The one bit interleaving of the crate (octree bricks, eval's leaf intervals, the
/// filters' point order all use it).
#[inline]
pub(crate) const fn spread3(v: u64) -> u64 {
    let mut x = v & 0xffff;
    x = (x | (x << 16)) & 0x0000_ff00_00ff;
    x = (x | (x << 8)) & 0x00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x0c30_c30c_30c3;
    (x | (x << 2)) & 0x2492_4924_9249
}

/// Inverse of [`spread3`]: gathers bits 0, 3, 6, … into the low 16 bits.
#[inline]
pub(crate) const fn compact3(v: u64) -> u16 {
    let mut x = v & 0x2492_4924_9249;
    x = (x ^ (x >> 2)) & 0x0c30_c30c_30c3;
    x = (x ^ (x >> 4)) & 0x00f0_0f00_f00f;
    x = (x ^ (x >> 8)) & 0x0000_ff00_00ff;
    x = (x ^ (x >> 16)) & 0xffff;
    x as u16
}

/// Morton code of three 16-bit coordinates, x in the lowest bit: OctoMap's child order
/// (child index = x | y << 1 | z << 2), so preorder is Morton order.
#[inline]
pub(crate) const fn morton(k: [u16; 3]) -> u64 {
    spread3(k[0] as u64) | (spread3(k[1] as u64) << 1) | (spread3(k[2] as u64) << 2)
}

/// The coordinates of a [`morton`] code.
#[inline]
pub(crate) const fn unmorton(m: u64) -> [u16; 3] {
    [compact3(m), compact3(m >> 1), compact3(m >> 2)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn multiplies_by_reciprocal_not_divides() {
        // research/octomap.md §1: 1.75f at res 0.07 -> 1.75 * 14.285714285714285 = 25.0 -> 32768 + 25.
        let r = Resolution::new(0.07).unwrap();
        assert_eq!(r.coord_to_key_axis(f64::from(1.75f32)), Some(32768 + 25));
        assert_eq!((1.75f64 / 0.07).floor(), 24.0);
    }

    #[test]
    fn negative_coordinates_floor_and_range_is_checked() {
        let r = Resolution::new(0.1).unwrap();
        assert_eq!(r.coord_to_key_axis(f64::from(-0.05f32)), Some(32767));
        assert_eq!(r.coord_to_key_axis(0.0), Some(32768));
        // -0.2f is -0.200000003: floor(-2.00000003) = -3.
        assert_eq!(r.coord_to_key_axis(f64::from(-0.2f32)), Some(32768 - 3));
        assert_eq!(r.coord_to_key_axis(-3276.8), Some(0));
        assert_eq!(r.coord_to_key_axis(3276.7), Some(65535));
        assert_eq!(r.coord_to_key_axis(3276.8), None);
        assert_eq!(r.coord_to_key_axis(-3276.81), None);
        assert_eq!(r.coord_to_key_axis(f64::NAN), None);
        assert_eq!(r.coord_to_key_axis(1e300), None);
    }

    #[test]
    fn centers_at_depths() {
        let r = Resolution::new(0.1).unwrap();
        assert_eq!(r.key_to_coord_axis(32768), 0.05);
        assert_eq!(r.key_to_coord_axis(32767), -0.05);
        assert_eq!(r.key_to_coord_at_depth(40000, 0), 0.0);
        // depth 15: pairs of voxels, (floor(1/2) + 0.5) * 0.2 = 0.1 for key 32769.
        assert!((r.key_to_coord_at_depth(32769, 15) - 0.1).abs() < 1e-12);
        assert!((r.key_to_coord_at_depth(32767, 15) + 0.1).abs() < 1e-12);
        assert_eq!(r.node_size(0), 0.1 * 65536.0);
    }

    #[test]
    fn child_keys_and_indices() {
        let root = Key([KEY_CENTER; 3]);
        assert_eq!(root.child_center(0, 0), Key([16384; 3]));
        assert_eq!(root.child_center(7, 0), Key([49152; 3]));
        let d15 = Key([100, 200, 300]);
        assert_eq!(d15.child_center(0b101, 15), Key([100, 199, 300]));
        let voxel = Key([0b1, 0b10, 0b100]);
        assert_eq!(voxel.child_index(15), 0b001);
        assert_eq!(voxel.child_index(14), 0b010);
        assert_eq!(voxel.child_index(13), 0b100);
    }

    #[test]
    fn morton_puts_x_lowest_and_round_trips() {
        assert_eq!(morton([1, 0, 0]), 1);
        assert_eq!(morton([0, 1, 0]), 2);
        assert_eq!(morton([0, 0, 1]), 4);
        assert_eq!(morton([2, 0, 0]), 8);
        assert_eq!(morton([0xffff, 0, 0xffff]), 0o5555_5555_5555_5555);
        assert_eq!(morton([0xffff; 3]), (1 << 48) - 1);
        for k in [
            [0, 0, 0],
            [1, 2, 3],
            [32768, 32767, 65535],
            [0xabcd, 0x1234, 0x8001],
        ] {
            assert_eq!(unmorton(morton(k)), k);
        }
        assert_eq!(spread3(0x1_0001), 1, "only the low 16 bits count");
    }
}
