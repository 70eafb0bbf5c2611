//! The one preorder walk over the node streams of OctoMap's `.bt` and `.ot` files
//! (research/octomap.md §6.1/§6.2), with a [`NodeVisitor`] for what to build.
//!
//! Both formats list nodes depth first, children in order 0..7 (x lowest), so preorder is
//! Morton order and the walk can hand each leaf the Morton index of its first voxel for free.
//! The walk owns everything the two readers of the crate (`Octree::read_bt`/`read_ot` and
//! `eval::LeafMap::read_bt`/`read_ot`) must agree on: the record layout, the node count check
//! against the header, the depth limit and the truncation errors. It is generic over the
//! visitor, so each reader compiles to its own loop (the eval bench's ≥ 100 M nodes/s).

use super::OctreeError;
use super::key::TREE_DEPTH;

/// Open inner nodes while walking: depths 0..16 (a depth-16 node is a voxel, never inner).
const DEPTHS: usize = TREE_DEPTH as usize + 1;

/// What a walk reports, in file (preorder) order. Depth 0 is the root, 16 a single voxel.
pub(crate) trait NodeVisitor {
    /// An inner node at `depth` opens; the children in `mask` (bit i: child i) follow.
    /// `value` is the stored log-odds in an `.ot`; a `.bt` stores none and passes NaN.
    fn inner(&mut self, depth: u32, mask: u8, value: f32);
    /// A leaf at `depth` whose cube starts at the voxel of Morton index `first`
    /// (`crate::octree::key::morton`; the cube holds `8^(16 - depth)` voxels).
    fn leaf(&mut self, depth: u32, first: u64, value: f32);
    /// The inner node opened last at `depth` has had all its children. A `.bt` inner node
    /// whose record lists no child (OctoMap never writes one) opens and closes at once.
    fn close(&mut self, depth: u32);
}

/// Child mask (bit i: child i exists) of a `.bt` record's eight 2-bit codes.
#[inline]
fn child_mask(codes: u16) -> u8 {
    const NIBBLE: [u8; 256] = {
        let mut t = [0u8; 256];
        let mut i = 0;
        while i < 256 {
            let mut m = 0;
            let mut c = 0;
            while c < 4 {
                if (i >> (2 * c)) & 3 != 0 {
                    m |= 1 << c;
                }
                c += 1;
            }
            t[i] = m;
            i += 1;
        }
        t
    };
    let [lo, hi] = codes.to_le_bytes();
    NIBBLE[usize::from(lo)] | (NIBBLE[usize::from(hi)] << 4)
}

/// The node count check once the root has closed.
#[inline]
fn all_read(size: u64, read: u64) -> Result<(), OctreeError> {
    if read == size {
        Ok(())
    } else {
        Err(OctreeError::SizeMismatch { header: size, read })
    }
}

/// Walks the data of a `.bt` file whose header says `size` nodes: per inner node a 2-byte
/// record of eight 2-bit child codes (0 absent, 1 free leaf, 2 occupied leaf, 3 inner).
/// Leaves get `leaf_values[0]` (free) or `[1]` (occupied): the file stores no values.
pub(crate) fn walk_bt(
    data: &[u8],
    size: u64,
    leaf_values: [f32; 2],
    visitor: &mut impl NodeVisitor,
) -> Result<(), OctreeError> {
    if size == 0 {
        return Ok(());
    }
    let mut records = data.chunks_exact(2);
    let mut record = || -> Result<u16, OctreeError> {
        records
            .next()
            .map(|r| u16::from(r[0]) | (u16::from(r[1]) << 8))
            .ok_or(OctreeError::Truncated {
                what: ".bt node record",
            })
    };
    // Per open inner node (index = its depth): the child codes not yet read and the Morton
    // index of its first voxel.
    let mut codes = [0u16; DEPTHS];
    let mut bases = [0u64; DEPTHS];
    codes[0] = record()?;
    visitor.inner(0, child_mask(codes[0]), f32::NAN);
    let mut d = 0usize;
    let mut read = 1u64;
    loop {
        while codes[d] == 0 {
            visitor.close(d as u32);
            if d == 0 {
                return all_read(size, read);
            }
            d -= 1;
        }
        let c = codes[d].trailing_zeros() / 2;
        let code = (codes[d] >> (2 * c)) & 3;
        codes[d] &= !(3 << (2 * c));
        // Children of a depth-d node are at depth d + 1, i.e. cubes of 8^(15 - d) voxels.
        let level = 15 - d as u32;
        let base = bases[d] | (u64::from(c) << (3 * level));
        if read >= size {
            return Err(OctreeError::SizeMismatch {
                header: size,
                read: read + 1,
            });
        }
        read += 1;
        match code {
            1 | 2 => visitor.leaf(d as u32 + 1, base, leaf_values[usize::from(code == 2)]),
            _ => {
                if level == 0 {
                    return Err(OctreeError::TooDeep);
                }
                let r = record()?;
                d += 1;
                codes[d] = r;
                bases[d] = base;
                visitor.inner(d as u32, child_mask(r), f32::NAN);
            }
        }
    }
}

/// Walks the data of an `.ot` file whose header says `size` nodes: per node its f32 log-odds
/// (little-endian) and a child mask byte (0: a leaf).
pub(crate) fn walk_ot(
    data: &[u8],
    size: u64,
    visitor: &mut impl NodeVisitor,
) -> Result<(), OctreeError> {
    if size == 0 {
        return Ok(());
    }
    let mut nodes = data.chunks_exact(5);
    let mut node = || -> Result<(f32, u8), OctreeError> {
        nodes
            .next()
            .map(|c| (f32::from_le_bytes([c[0], c[1], c[2], c[3]]), c[4]))
            .ok_or(OctreeError::Truncated { what: ".ot node" })
    };
    // Per open inner node (index = its depth): the child mask not yet read and the Morton
    // index of its first voxel.
    let mut masks = [0u8; DEPTHS];
    let mut bases = [0u64; DEPTHS];
    let (v, m) = node()?;
    if m == 0 {
        visitor.leaf(0, 0, v);
        return all_read(size, 1);
    }
    visitor.inner(0, m, v);
    masks[0] = m;
    let mut d = 0usize;
    let mut read = 1u64;
    loop {
        while masks[d] == 0 {
            visitor.close(d as u32);
            if d == 0 {
                return all_read(size, read);
            }
            d -= 1;
        }
        let c = masks[d].trailing_zeros();
        masks[d] &= masks[d] - 1;
        let level = 15 - d as u32;
        let base = bases[d] | (u64::from(c) << (3 * level));
        if read >= size {
            return Err(OctreeError::SizeMismatch {
                header: size,
                read: read + 1,
            });
        }
        let (v, m) = node()?;
        read += 1;
        if m == 0 {
            visitor.leaf(d as u32 + 1, base, v);
        } else {
            if level == 0 {
                return Err(OctreeError::TooDeep);
            }
            d += 1;
            masks[d] = m;
            bases[d] = base;
            visitor.inner(d as u32, m, v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Records every event as text.
    #[derive(Default)]
    struct Log(Vec<String>);

    impl NodeVisitor for Log {
        fn inner(&mut self, depth: u32, mask: u8, value: f32) {
            self.0.push(format!("inner {depth} {mask:#04x} {value}"));
        }
        fn leaf(&mut self, depth: u32, first: u64, value: f32) {
            self.0.push(format!("leaf {depth} {first:#x} {value}"));
        }
        fn close(&mut self, depth: u32) {
            self.0.push(format!("close {depth}"));
        }
    }

    #[test]
    fn a_bt_stream_is_reported_in_preorder_with_morton_starts_and_leaf_values() {
        // Root: child 0 inner (code 3), child 7 occupied (2). Child 0: child 1 free (1).
        let data = [0x03, 0x80, 0x04, 0x00];
        let mut log = Log::default();
        walk_bt(&data, 4, [-2.0, 3.5], &mut log).unwrap();
        assert_eq!(
            log.0,
            [
                "inner 0 0x81 NaN",
                "inner 1 0x02 NaN",
                // Child 1 of child 0: x bit at level 14, Morton 1 << 42.
                "leaf 2 0x40000000000 -2",
                "close 1",
                // Child 7 of the root: Morton 7 << 45.
                "leaf 1 0xe00000000000 3.5",
                "close 0",
            ]
        );
    }

    #[test]
    fn an_ot_stream_is_reported_with_its_stored_values() {
        let mut data = Vec::new();
        for (v, m) in [(1.5f32, 0x10u8), (0.25, 0)] {
            data.extend_from_slice(&v.to_le_bytes());
            data.push(m);
        }
        let mut log = Log::default();
        walk_ot(&data, 2, &mut log).unwrap();
        assert_eq!(
            log.0,
            ["inner 0 0x10 1.5", "leaf 1 0x800000000000 0.25", "close 0"]
        );
        let mut log = Log::default();
        walk_ot(&data[5..], 1, &mut log).unwrap();
        assert_eq!(log.0, ["leaf 0 0x0 0.25"], "a root leaf");
    }

    #[test]
    fn counts_depths_and_truncation_are_checked_the_same_way_in_both_formats() {
        let mut log = Log::default();
        let bt = [0x03, 0x80, 0x04, 0x00];
        assert_eq!(
            walk_bt(&bt, 3, [0.0; 2], &mut log),
            Err(OctreeError::SizeMismatch { header: 3, read: 4 })
        );
        assert_eq!(
            walk_bt(&bt, 5, [0.0; 2], &mut log),
            Err(OctreeError::SizeMismatch { header: 5, read: 4 })
        );
        assert_eq!(
            walk_bt(&bt[..3], 4, [0.0; 2], &mut log),
            Err(OctreeError::Truncated {
                what: ".bt node record"
            })
        );
        let deep = [0x03, 0x00].repeat(17);
        assert_eq!(
            walk_bt(&deep, 100, [0.0; 2], &mut log),
            Err(OctreeError::TooDeep)
        );
        let mut deep_ot = Vec::new();
        for _ in 0..17 {
            deep_ot.extend_from_slice(&0f32.to_le_bytes());
            deep_ot.push(1);
        }
        assert_eq!(walk_ot(&deep_ot, 100, &mut log), Err(OctreeError::TooDeep));
        assert_eq!(
            walk_ot(&deep_ot[..7], 100, &mut log),
            Err(OctreeError::Truncated { what: ".ot node" })
        );
        let mut empty = Log::default();
        walk_bt(&[], 0, [0.0; 2], &mut empty).unwrap();
        walk_ot(&[], 0, &mut empty).unwrap();
        assert!(empty.0.is_empty(), "size 0: no nodes");
    }
}
