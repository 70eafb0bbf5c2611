//! The OctoMap tree as flat preorder arrays (the `.ot` node order): one f32 value and one
//! child mask per node, plus each node's subtree end for random access.

use super::key::{KEY_CENTER, Key, Resolution, TREE_DEPTH};
use super::model::SensorModel;

/// An occupancy octree with OctoMap's structure and values, stored as preorder arrays.
///
/// Made by [`super::VoxelMap::to_octree`], by reading `.bt`/`.ot`, or by
/// [`Octree::to_max_likelihood_pruned`]. Immutable; queries are read-only.
#[derive(Debug, Clone)]
pub struct Octree {
    pub(crate) res: Resolution,
    pub(crate) model: SensorModel,
    /// Log-odds of every node in preorder (inner nodes: max of children).
    pub(crate) values: Vec<f32>,
    /// Child mask of every node (bit i: child i exists).
    pub(crate) masks: Vec<u8>,
    /// Index one past each node's subtree.
    ends: Vec<u32>,
    leaves: u64,
    occupied: u64,
}

/// One leaf as OctoMap's `leaf_iterator` reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Leaf {
    /// Center key (at depth 16 the voxel key itself).
    pub key: Key,
    /// Depth 0..=16; a pruned leaf is shallower than 16.
    pub depth: u8,
    /// Stored log-odds.
    pub log_odds: f32,
}

impl Leaf {
    /// Edge length in metres.
    pub fn size(&self, res: &Resolution) -> f64 {
        res.node_size(self.depth)
    }

    /// Metric center (OctoMap's `keyToCoord(key, depth)`).
    pub fn center(&self, res: &Resolution) -> [f64; 3] {
        self.key.0.map(|k| res.key_to_coord_at_depth(k, self.depth))
    }

    /// Inclusive depth-16 key range `[lo, hi]` per axis covered by this leaf.
    pub fn key_range(&self) -> ([u16; 3], [u16; 3]) {
        let (lo, hi) = node_range(self.key, self.depth);
        (lo.map(|v| v as u16), hi.map(|v| v as u16))
    }
}

/// Inclusive voxel range of the node with center key `c` at `depth`.
#[inline]
fn node_range(c: Key, depth: u8) -> ([u32; 3], [u32; 3]) {
    if depth >= TREE_DEPTH {
        let k = c.0.map(u32::from);
        return (k, k);
    }
    let half = u32::from(KEY_CENTER) >> depth;
    (
        c.0.map(|k| u32::from(k).saturating_sub(half)),
        c.0.map(|k| (u32::from(k) + half - 1).min(65535)),
    )
}

/// Builds preorder arrays node by node; closing a node sets its value to the max of its
/// children, or collapses it when its 8 children are equal leaves (eager pruning).
pub(crate) struct TreeBuilder {
    values: Vec<f32>,
    masks: Vec<u8>,
    stack: Vec<Frame>,
}

struct Frame {
    pos: usize,
    mask: u8,
    max: f32,
    pending: bool,
}

impl TreeBuilder {
    /// A pruning builder (eager-pruning semantics).
    pub(crate) fn with_capacity(n: usize) -> Self {
        Self {
            values: Vec::with_capacity(n),
            masks: Vec::with_capacity(n),
            stack: Vec::new(),
        }
    }

    /// Declares that the next node pushed is child `c` of the open node.
    pub(crate) fn child(&mut self, c: usize) {
        if let Some(f) = self.stack.last_mut() {
            f.mask |= 1 << c;
            f.pending = true;
        }
    }

    fn note_child_value(&mut self, v: f32) {
        if let Some(f) = self.stack.last_mut()
            && f.pending
        {
            f.pending = false;
            if v > f.max {
                f.max = v;
            }
        }
    }

    /// Pushes a leaf.
    pub(crate) fn leaf(&mut self, v: f32) {
        self.values.push(v);
        self.masks.push(0);
        self.note_child_value(v);
    }

    /// Opens an inner node; its children follow until [`TreeBuilder::close`].
    pub(crate) fn open(&mut self) {
        let pos = self.values.len();
        self.values.push(0.0);
        self.masks.push(0);
        self.stack.push(Frame {
            pos,
            mask: 0,
            max: -f32::MAX,
            pending: false,
        });
    }

    /// Closes the open node (prunes or sets max of children). Returns its final value.
    pub(crate) fn close(&mut self) -> f32 {
        let Some(f) = self.stack.pop() else {
            return 0.0;
        };
        let p = f.pos;
        let collapsible = f.mask == 0xff
            && self.values.len() == p + 9
            && self.masks[p + 1..].iter().all(|&m| m == 0)
            && self.values[p + 2..]
                .iter()
                .all(|&v| v == self.values[p + 1]);
        let v = if collapsible {
            let v0 = self.values[p + 1];
            self.values.truncate(p + 1);
            self.masks.truncate(p + 1);
            v0
        } else {
            self.masks[p] = f.mask;
            f.max
        };
        self.values[p] = v;
        self.note_child_value(v);
        v
    }

    pub(crate) fn finish(self, res: Resolution, model: SensorModel) -> Octree {
        Octree::from_parts(res, model, self.values, self.masks)
    }
}

impl Octree {
    /// Wraps preorder arrays that form a valid tree (every builder and reader guarantees it).
    pub(crate) fn from_parts(
        res: Resolution,
        model: SensorModel,
        values: Vec<f32>,
        masks: Vec<u8>,
    ) -> Self {
        let n = masks.len();
        let mut ends = vec![0u32; n];
        let mut stack: Vec<(usize, u32)> = Vec::with_capacity(17);
        let (mut leaves, mut occupied) = (0u64, 0u64);
        for i in 0..n {
            if masks[i] != 0 {
                stack.push((i, masks[i].count_ones()));
                continue;
            }
            leaves += 1;
            occupied += u64::from(model.is_occupied(values[i]));
            ends[i] = (i + 1) as u32;
            while let Some(top) = stack.last_mut() {
                top.1 -= 1;
                if top.1 > 0 {
                    break;
                }
                ends[top.0] = (i + 1) as u32;
                stack.pop();
            }
        }
        Self::from_arrays(res, model, values, masks, ends, leaves, occupied)
    }

    /// Wraps preorder arrays with their subtree ends and leaf counts already computed (the
    /// `.bt` reader builds them in its single pass).
    pub(crate) fn from_arrays(
        res: Resolution,
        model: SensorModel,
        values: Vec<f32>,
        masks: Vec<u8>,
        ends: Vec<u32>,
        leaves: u64,
        occupied: u64,
    ) -> Self {
        Self {
            res,
            model,
            values,
            masks,
            ends,
            leaves,
            occupied,
        }
    }

    /// An empty tree.
    pub fn empty(res: Resolution, model: SensorModel) -> Self {
        Self::from_parts(res, model, Vec::new(), Vec::new())
    }

    /// Voxel size and key conversions.
    pub fn resolution(&self) -> &Resolution {
        &self.res
    }

    /// The sensor model (clamps and threshold) the tree interprets values with.
    pub fn model(&self) -> &SensorModel {
        &self.model
    }

    /// Number of nodes, root and inner nodes included (OctoMap's `size()`).
    pub fn num_nodes(&self) -> usize {
        self.masks.len()
    }

    /// Number of leaves; a pruned node counts once.
    pub fn num_leaves(&self) -> u64 {
        self.leaves
    }

    /// Leaves with log-odds `>=` the occupancy threshold.
    pub fn num_occupied(&self) -> u64 {
        self.occupied
    }

    /// Leaves below the occupancy threshold.
    pub fn num_free(&self) -> u64 {
        self.leaves - self.occupied
    }

    /// Heap bytes of the node arrays.
    pub fn memory_bytes(&self) -> usize {
        self.values.capacity() * 4 + self.masks.capacity() + self.ends.capacity() * 4
    }

    /// Leaves in OctoMap's order (depth-first, children 0..7, i.e. Morton order).
    pub fn leaves(&self) -> Leaves<'_> {
        Leaves {
            tree: self,
            i: 0,
            stack: Vec::with_capacity(17),
        }
    }

    /// Log-odds at a depth-16 voxel: the voxel's own node or the pruned leaf covering it;
    /// `None` if unknown (OctoMap's `search`).
    pub fn search(&self, key: Key) -> Option<f32> {
        let mut i = 0usize;
        for depth in 0..TREE_DEPTH {
            let m = *self.masks.get(i)?;
            if m == 0 {
                return self.values.get(i).copied();
            }
            let pos = key.child_index(depth);
            if m & (1 << pos) == 0 {
                return None;
            }
            let mut c = i + 1;
            for _ in 0..(m & ((1u8 << pos) - 1)).count_ones() {
                c = *self.ends.get(c)? as usize;
            }
            i = c;
        }
        self.values.get(i).copied()
    }

    /// Metric bounding box `(min, max)` of all leaves, or `None` for an empty tree
    /// (OctoMap's `getMetricMin/Max`).
    pub fn metric_bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let mut lo = [f64::MAX; 3];
        let mut hi = [-f64::MAX; 3];
        let mut any = false;
        for leaf in self.leaves() {
            any = true;
            let s = leaf.size(&self.res);
            let c = leaf.center(&self.res);
            for i in 0..3 {
                let a = c[i] - s / 2.0;
                lo[i] = lo[i].min(a);
                hi[i] = hi[i].max(a + s);
            }
        }
        any.then_some((lo, hi))
    }

    /// Calls `f(voxel key, log-odds)` for every depth-16 voxel inside the inclusive key box
    /// `[min, max]` that a leaf covers (pruned leaves are clipped to the box), in tree order.
    pub fn for_each_voxel_in_box(&self, min: Key, max: Key, mut f: impl FnMut(Key, f32)) {
        if self.masks.is_empty() {
            return;
        }
        let (bmin, bmax) = (min.0.map(u32::from), max.0.map(u32::from));
        // (node index, center key, depth)
        let mut stack = vec![(0usize, Key([KEY_CENTER; 3]), 0u8)];
        while let Some((i, key, depth)) = stack.pop() {
            let (lo, hi) = node_range(key, depth);
            if (0..3).any(|a| hi[a] < bmin[a] || lo[a] > bmax[a]) {
                continue;
            }
            let (Some(&m), Some(&v)) = (self.masks.get(i), self.values.get(i)) else {
                continue;
            };
            if m == 0 {
                let lo = [0, 1, 2].map(|a| lo[a].max(bmin[a]));
                let hi = [0, 1, 2].map(|a| hi[a].min(bmax[a]));
                for z in lo[2]..=hi[2] {
                    for y in lo[1]..=hi[1] {
                        for x in lo[0]..=hi[0] {
                            f(Key([x as u16, y as u16, z as u16]), v);
                        }
                    }
                }
                continue;
            }
            // Push children in reverse so they pop in ascending order.
            let mut kids = [(0usize, 0usize); 8];
            let mut n = 0;
            let mut c = i + 1;
            for pos in 0..8 {
                if m & (1 << pos) != 0 {
                    kids[n] = (pos, c);
                    n += 1;
                    c = self.ends.get(c).map_or(c, |&e| e as usize);
                }
            }
            for &(pos, c) in kids[..n].iter().rev() {
                stack.push((c, key.child_center(pos, depth), depth + 1));
            }
        }
    }

    /// What OctoMap's `writeBinary` does to a tree before writing: `toMaxLikelihood()` (every
    /// node to clamp max if occupied, else clamp min), then `prune()` level by level from
    /// depth 15 up, stopping at the first level that prunes nothing.
    pub fn to_max_likelihood_pruned(&self) -> Octree {
        let mut values: Vec<f32> = self
            .values
            .iter()
            .map(|&v| self.model.max_likelihood(v))
            .collect();
        let mut masks = self.masks.clone();
        for depth in (1..TREE_DEPTH).rev() {
            if prune_level(&mut values, &mut masks, depth) == 0 {
                break;
            }
        }
        Octree::from_parts(self.res, self.model, values, masks)
    }

    /// Index one past the subtree of node `i`.
    pub(crate) fn subtree_end(&self, i: usize) -> usize {
        self.ends.get(i).map_or(i + 1, |&e| e as usize)
    }
}

/// One pass of OctoMap's `pruneRecurs` at `depth`: collapses every node there whose 8
/// children are leaves with equal values (f32 `==`). Returns how many were pruned.
fn prune_level(values: &mut Vec<f32>, masks: &mut Vec<u8>, depth: u8) -> usize {
    let n = masks.len();
    let mut stack: Vec<(u8, u32)> = Vec::with_capacity(17);
    let (mut r, mut w, mut pruned) = (0usize, 0usize, 0usize);
    while r < n {
        let d = if r == 0 {
            0
        } else {
            let Some(top) = stack.last_mut() else { break };
            let d = top.0 + 1;
            top.1 -= 1;
            if top.1 == 0 {
                stack.pop();
            }
            d
        };
        let m = masks[r];
        if d == depth
            && m == 0xff
            && r + 8 < n
            && masks[r + 1..=r + 8].iter().all(|&c| c == 0)
            && values[r + 2..=r + 8].iter().all(|&v| v == values[r + 1])
        {
            values[w] = values[r + 1];
            masks[w] = 0;
            r += 9;
            pruned += 1;
        } else {
            values[w] = values[r];
            masks[w] = m;
            r += 1;
            if m != 0 {
                stack.push((d, m.count_ones()));
            }
        }
        w += 1;
    }
    values.truncate(w);
    masks.truncate(w);
    pruned
}

/// Iterator over [`Leaf`]s, see [`Octree::leaves`].
#[derive(Debug)]
pub struct Leaves<'a> {
    tree: &'a Octree,
    i: usize,
    /// (center key, depth, children not yet visited)
    stack: Vec<(Key, u8, u8)>,
}

impl Iterator for Leaves<'_> {
    type Item = Leaf;

    fn next(&mut self) -> Option<Leaf> {
        loop {
            let i = self.i;
            let (&m, &v) = (self.tree.masks.get(i)?, self.tree.values.get(i)?);
            let (key, depth) = if i == 0 {
                (Key([KEY_CENTER; 3]), 0)
            } else {
                let top = self.stack.last_mut()?;
                let pos = top.2.trailing_zeros() as usize;
                top.2 &= top.2 - 1;
                let out = (top.0.child_center(pos, top.1), top.1 + 1);
                if top.2 == 0 {
                    self.stack.pop();
                }
                out
            };
            self.i += 1;
            if m != 0 {
                self.stack.push((key, depth, m));
                continue;
            }
            return Some(Leaf {
                key,
                depth,
                log_odds: v,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::VoxelMap;

    fn res() -> Resolution {
        Resolution::new(0.1).unwrap()
    }

    #[test]
    fn eight_equal_voxels_collapse_and_inner_is_max() {
        let mut m = VoxelMap::new(res(), SensorModel::default());
        // 8 voxels of one depth-15 node, all equal -> one leaf at depth 15.
        for i in 0..8u16 {
            m.set_log_odds(
                Key([32768 + (i & 1), 32768 + ((i >> 1) & 1), 32768 + (i >> 2)]),
                -2.0,
            );
        }
        let t = m.to_octree();
        assert_eq!((t.num_nodes(), t.num_leaves()), (16, 1));
        let l: Vec<Leaf> = t.leaves().collect();
        assert_eq!(l[0].depth, 15);
        assert_eq!(l[0].key, Key([32769; 3]));
        assert_eq!(l[0].key_range(), ([32768; 3], [32769; 3]));
        assert_eq!(t.search(Key([32769, 32768, 32769])), Some(-2.0));
        assert_eq!(t.search(Key([32770, 32768, 32768])), None);
        // One differing voxel: no collapse; parents carry the max.
        m.set_log_odds(Key([32768; 3]), 1.5);
        let t = m.to_octree();
        assert_eq!(
            (t.num_nodes(), t.num_leaves(), t.num_occupied()),
            (24, 8, 1)
        );
        assert!(t.values[..16].iter().all(|&v| v == 1.5));
        let depths: Vec<u8> = t.leaves().map(|l| l.depth).collect();
        assert_eq!(depths, vec![16; 8]);
        let mut seen = Vec::new();
        t.for_each_voxel_in_box(Key([32768; 3]), Key([32768, 32769, 32768]), |k, v| {
            seen.push((k, v))
        });
        assert_eq!(
            seen,
            vec![(Key([32768; 3]), 1.5), (Key([32768, 32769, 32768]), -2.0)]
        );
    }

    #[test]
    fn pruned_leaves_are_clipped_to_the_box() {
        let mut m = VoxelMap::new(res(), SensorModel::default());
        // A full depth-14 node (4x4x4 voxels) of equal values collapses to one leaf.
        for x in 0..4 {
            for y in 0..4 {
                for z in 0..4 {
                    m.set_log_odds(Key([32768 + x, 32768 + y, 32768 + z]), 3.5);
                }
            }
        }
        let t = m.to_octree();
        assert_eq!(t.num_leaves(), 1);
        assert_eq!(t.leaves().next().map(|l| l.depth), Some(14));
        let mut n = 0;
        t.for_each_voxel_in_box(
            Key([32767, 32769, 32770]),
            Key([32768, 32770, 40000]),
            |k, _| {
                n += 1;
                assert!(
                    k.0[0] == 32768
                        && (32769..=32770).contains(&k.0[1])
                        && (32770..=32771).contains(&k.0[2])
                );
            },
        );
        assert_eq!(n, 4);
        let (lo, hi) = t.metric_bounds().unwrap();
        assert!((lo[0] - 0.0).abs() < 1e-12 && (hi[2] - 0.4).abs() < 1e-12);
    }

    #[test]
    fn max_likelihood_prune_merges_differing_occupied_leaves() {
        let mut m = VoxelMap::new(res(), SensorModel::default());
        for i in 0..8u16 {
            let v = if i == 0 { 0.5 } else { 1.0 };
            m.set_log_odds(
                Key([32768 + (i & 1), 32768 + ((i >> 1) & 1), 32768 + (i >> 2)]),
                v,
            );
        }
        let t = m.to_octree();
        assert_eq!(t.num_leaves(), 8);
        let ml = t.to_max_likelihood_pruned();
        assert_eq!(
            (ml.num_nodes(), ml.num_leaves(), ml.num_occupied()),
            (16, 1, 1)
        );
        assert_eq!(ml.values[15], SensorModel::default().clamp_max);
    }
}
