//! A map as the metrics see it: its leaves as Morton intervals in preorder, read straight from
//! `.bt`/`.ot` bytes or taken from an [`Octree`].
//!
//! Why not just [`Octree`]: the metrics only need each leaf's first voxel, size and value in
//! Morton order, and `Octree::leaves()` costs ~14 ns per leaf (64 ms for the 4.4 M leaves of the
//! geb079_sim 0.05 m pair, more than the whole 50 ms budget). Reading the files' preorder
//! streams directly into two flat arrays costs a few ns per node. The readers share the header
//! parser and the preorder walk (`octree::walk`) with `Octree::read_bt`/`read_ot`, so they
//! accept exactly the same files (the tests also compare the two on every reference file) and
//! return the same [`OctreeError`]s.

use super::VoxelBox;
use crate::octree::{
    BT_MAGIC, Header, NodeVisitor, OT_MAGIC, Octree, OctreeError, Resolution, SensorModel,
    TREE_DEPTH, compact3, morton, parse_header, spread3, unmorton, walk_bt, walk_ot,
};

/// Bits of a packed code that hold the Morton index of the leaf's first voxel.
const MORTON_BITS: u32 = 48;
const MORTON_MASK: u64 = (1 << MORTON_BITS) - 1;

/// One leaf: the first voxel of its cube, the cube's level (edge `2^level` voxels,
/// `level = 16 - depth`) and its log-odds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapLeaf {
    /// Smallest voxel key of the cube.
    pub lo: [u16; 3],
    /// `16 - depth`: the cube has `8^level` voxels.
    pub level: u8,
    /// Stored log-odds.
    pub log_odds: f32,
}

impl MapLeaf {
    /// Largest voxel key of the cube (inclusive).
    pub fn hi(&self) -> [u16; 3] {
        let d = (1u32 << self.level) - 1;
        self.lo.map(|k| (u32::from(k) + d).min(65535) as u16)
    }
}

/// A map's leaves in Morton order as flat arrays, plus what the metrics need to know about it.
#[derive(Debug, Clone, PartialEq)]
pub struct LeafMap {
    res: Resolution,
    model: SensorModel,
    /// Per leaf: Morton index of its first voxel (bits 0..48) | level << 48.
    codes: Vec<u64>,
    values: Vec<f32>,
    nodes: u64,
    bounds: Option<VoxelBox>,
    /// The first NaN / infinite log-odds, if any (the metrics refuse such a map).
    non_finite: Option<f32>,
    /// Occupied and free voxels of the whole map.
    known: [u64; 2],
}

/// Spread (Morton-masked) x coordinate bits; `<< 1` for y, `<< 2` for z.
const AXIS: u64 = spread3(0xffff);

/// Collects leaves in preorder and, on the way, the bounds, voxel totals and any non-finite
/// value (one pass instead of three over the arrays afterwards).
struct Builder {
    codes: Vec<u64>,
    values: Vec<f32>,
    threshold: f32,
    /// Spread coordinates: smallest first voxel and largest last voxel per axis.
    lo: [u64; 3],
    hi: [u64; 3],
    known: [u64; 2],
    non_finite: Option<f32>,
}

impl Builder {
    fn new(capacity: usize, model: &SensorModel) -> Self {
        Self {
            codes: Vec::with_capacity(capacity),
            values: Vec::with_capacity(capacity),
            threshold: model.occupancy_threshold,
            lo: [u64::MAX; 3],
            hi: [0; 3],
            known: [0; 2],
            non_finite: None,
        }
    }

    /// A leaf whose first voxel has Morton index `m`, with `8^level` voxels.
    #[inline(always)]
    fn push_leaf(&mut self, m: u64, level: u32, value: f32) {
        self.codes.push(m | (u64::from(level) << MORTON_BITS));
        self.values.push(value);
        // Spread coordinates compare like the coordinates, and a leaf's first voxel is
        // aligned to its size, so its last voxel is `m | (8^level - 1)`: no decoding needed.
        let size = 1u64 << (3 * level);
        let last = m | (size - 1);
        for a in 0..3 {
            self.lo[a] = self.lo[a].min(m & (AXIS << a));
            self.hi[a] = self.hi[a].max(last & (AXIS << a));
        }
        self.known[usize::from(value < self.threshold)] += size;
        if !value.is_finite() && self.non_finite.is_none() {
            self.non_finite = Some(value);
        }
    }

    fn finish(self, res: Resolution, model: SensorModel, nodes: u64) -> LeafMap {
        let bounds = (!self.codes.is_empty()).then(|| VoxelBox {
            min: [0, 1, 2].map(|a| compact3(self.lo[a] >> a)),
            max: [0, 1, 2].map(|a| compact3(self.hi[a] >> a)),
        });
        LeafMap {
            res,
            model,
            codes: self.codes,
            values: self.values,
            nodes,
            bounds,
            non_finite: self.non_finite,
            known: self.known,
        }
    }
}

/// Only the leaves matter to the metrics; inner nodes carry nothing they use.
impl NodeVisitor for Builder {
    #[inline(always)]
    fn inner(&mut self, _depth: u32, _mask: u8, _value: f32) {}

    #[inline(always)]
    fn leaf(&mut self, depth: u32, first: u64, value: f32) {
        self.push_leaf(first, u32::from(TREE_DEPTH).saturating_sub(depth), value);
    }

    #[inline(always)]
    fn close(&mut self, _depth: u32) {}
}

impl LeafMap {
    /// The leaves of an in-memory tree (through `Octree::leaves`).
    pub fn from_octree(tree: &Octree) -> Self {
        let mut b = Builder::new(tree.num_leaves() as usize, tree.model());
        for leaf in tree.leaves() {
            let level = u32::from(TREE_DEPTH - leaf.depth.min(TREE_DEPTH));
            b.push_leaf(morton(leaf.key_range().0), level, leaf.log_odds);
        }
        b.finish(*tree.resolution(), *tree.model(), tree.num_nodes() as u64)
    }

    /// Reads a `.bt` or `.ot` file, chosen by its first line, like `Octree::read`: `.bt`
    /// leaves take `model`'s clamps, and `model`'s threshold decides occupied / free.
    pub fn read(bytes: &[u8], model: SensorModel) -> Result<Self, OctreeError> {
        if crate::octree::is_binary(bytes)? {
            Self::read_bt(bytes, model)
        } else {
            Self::read_ot(bytes, model)
        }
    }

    /// Reads a `.bt` file (2-bit child codes per inner node in preorder).
    pub fn read_bt(bytes: &[u8], model: SensorModel) -> Result<Self, OctreeError> {
        let (Header { size, res }, data) = parse_header(bytes, BT_MAGIC)?;
        // Each data byte describes at most 4 nodes.
        let cap = (size as usize).min(data.len().saturating_mul(4) + 1);
        let mut b = Builder::new(cap, &model);
        walk_bt(data, size, [model.clamp_min, model.clamp_max], &mut b)?;
        Ok(b.finish(res, model, size))
    }

    /// Reads an `.ot` file (f32 log-odds and child mask per node, in preorder).
    pub fn read_ot(bytes: &[u8], model: SensorModel) -> Result<Self, OctreeError> {
        let (Header { size, res }, data) = parse_header(bytes, OT_MAGIC)?;
        let mut b = Builder::new((size as usize).min(data.len() / 5 + 1), &model);
        walk_ot(data, size, &mut b)?;
        Ok(b.finish(res, model, size))
    }

    /// Voxel size and key conversions.
    pub fn resolution(&self) -> &Resolution {
        &self.res
    }

    /// The sensor model whose threshold decides occupied / free.
    pub fn model(&self) -> &SensorModel {
        &self.model
    }

    /// OctoMap's leaf count (a pruned leaf counts once).
    pub fn num_leaves(&self) -> u64 {
        self.codes.len() as u64
    }

    /// OctoMap's node count (root and inner nodes included).
    pub fn num_nodes(&self) -> u64 {
        self.nodes
    }

    /// The smallest key box holding every known voxel, `None` for an empty map.
    pub fn bounds(&self) -> Option<VoxelBox> {
        self.bounds
    }

    /// Occupied voxels of the whole map (a pruned leaf counts all its voxels).
    pub fn occupied_voxels(&self) -> u64 {
        self.known[0]
    }

    /// Free voxels of the whole map.
    pub fn free_voxels(&self) -> u64 {
        self.known[1]
    }

    /// The first NaN or infinite log-odds in the map, if any.
    pub fn non_finite(&self) -> Option<f32> {
        self.non_finite
    }

    /// The leaves in Morton (OctoMap preorder) order.
    pub fn leaves(&self) -> impl Iterator<Item = MapLeaf> + '_ {
        self.codes.iter().zip(&self.values).map(|(&c, &v)| MapLeaf {
            lo: unmorton(c & MORTON_MASK),
            level: (c >> MORTON_BITS) as u8,
            log_odds: v,
        })
    }

    /// Raw packed codes (Morton start | level << 48) and values, for the merge.
    pub(super) fn raw(&self) -> (&[u64], &[f32]) {
        (&self.codes, &self.values)
    }
}

/// Splits a packed code into (Morton start, voxel count).
#[inline]
pub(super) fn split_code(c: u64) -> (u64, u64) {
    (c & MORTON_MASK, 1u64 << (3 * (c >> MORTON_BITS)))
}
