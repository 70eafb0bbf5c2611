//! `.bt` (binary max-likelihood) and `.ot` (full) OcTree files, byte-compatible with OctoMap
//! (research/octomap.md §6.1/§6.2). Pure: bytes in, bytes out. Reading walks the node stream
//! with [`super::walk`], the walker `eval::LeafMap` uses too.

use super::OctreeError;
use super::key::{Resolution, TREE_DEPTH};
use super::model::SensorModel;
use super::tree::Octree;
use super::walk::{NodeVisitor, walk_bt, walk_ot};

/// First line of a `.bt` file.
pub(crate) const BT_MAGIC: &str = "# Octomap OcTree binary file";
/// First line of an `.ot` file.
pub(crate) const OT_MAGIC: &str = "# Octomap OcTree file";
/// The file extension a header line belongs to: `.bt` or `.ot`.
pub(crate) fn extension_of(magic: &str) -> &'static str {
    if magic == BT_MAGIC { ".bt" } else { ".ot" }
}

/// Which reader a file's first line asks for: `Ok(true)` for `.bt`, `Ok(false)` for `.ot`.
pub(crate) fn is_binary(bytes: &[u8]) -> Result<bool, OctreeError> {
    if bytes.starts_with(BT_MAGIC.as_bytes()) {
        Ok(true)
    } else if bytes.starts_with(OT_MAGIC.as_bytes()) {
        Ok(false)
    } else {
        Err(OctreeError::NotOctoMap)
    }
}

const COMMENT: &str =
    "\n# (feel free to add / change comments, but leave the first line as it is!)\n#\n";

/// The resolution as C++ `ostream << double` prints it (6 significant digits, `%g` style),
/// e.g. `0.05`, `0.1`, `1e-05`.
pub fn format_resolution(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let sci = format!("{v:.5e}");
    let (mant, exp) = sci.split_once('e').unwrap_or((&sci, "0"));
    let exp: i32 = exp.parse().unwrap_or(0);
    let trim = |s: &str| -> String {
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s.to_string()
        }
    };
    if !(-4..6).contains(&exp) {
        let sign = if exp < 0 { '-' } else { '+' };
        format!("{}e{}{:02}", trim(mant), sign, exp.abs())
    } else {
        trim(&format!("{:.*}", (5 - exp) as usize, v))
    }
}

fn header(magic: &str, nodes: usize, res: f64) -> Vec<u8> {
    format!(
        "{magic}{COMMENT}id OcTree\nsize {nodes}\nres {}\ndata\n",
        format_resolution(res)
    )
    .into_bytes()
}

/// Fields of an OctoMap header.
pub(crate) struct Header {
    /// Node count (OctoMap's `size`).
    pub(crate) size: u64,
    /// Voxel size.
    pub(crate) res: Resolution,
}

/// Parses the text header the way `AbstractOcTree::readHeader` does; returns the data after
/// the `data` line.
pub(crate) fn parse_header<'a>(
    bytes: &'a [u8],
    magic: &'static str,
) -> Result<(Header, &'a [u8]), OctreeError> {
    if !bytes.starts_with(magic.as_bytes()) {
        return Err(OctreeError::BadMagic { expected: magic });
    }
    let mut p = bytes
        .iter()
        .position(|&b| b == b'\n')
        .map_or(bytes.len(), |i| i + 1);
    let skip_line = |p: &mut usize| {
        *p = bytes[*p..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| *p + i + 1);
    };
    let token = |p: &mut usize| -> &'a [u8] {
        while *p < bytes.len() && bytes[*p].is_ascii_whitespace() {
            *p += 1;
        }
        let start = *p;
        while *p < bytes.len() && !bytes[*p].is_ascii_whitespace() {
            *p += 1;
        }
        &bytes[start..*p]
    };
    let text = |t: &[u8]| String::from_utf8_lossy(t).into_owned();
    let (mut id, mut size, mut res) = (None, None, None);
    loop {
        let t = token(&mut p);
        match t {
            b"" => return Err(OctreeError::BadHeader("no `data` line".into())),
            b"data" => {
                skip_line(&mut p);
                break;
            }
            b"id" => id = Some(text(token(&mut p))),
            b"size" => {
                let v = text(token(&mut p));
                size = Some(
                    v.parse::<u64>()
                        .map_err(|_| OctreeError::BadHeader(format!("size {v:?}")))?,
                );
            }
            b"res" => {
                let v = text(token(&mut p));
                res = Some(
                    v.parse::<f64>()
                        .map_err(|_| OctreeError::BadHeader(format!("res {v:?}")))?,
                );
            }
            _ => skip_line(&mut p),
        }
    }
    match id.as_deref() {
        Some("OcTree") | Some("1") => {}
        Some(other) => return Err(OctreeError::UnsupportedTreeType(other.into())),
        None => return Err(OctreeError::BadHeader("no id".into())),
    }
    let res = Resolution::new(res.ok_or_else(|| OctreeError::BadHeader("no res".into()))?)?;
    let size = size.unwrap_or(0);
    // Node indices (subtree ends) are u32 in `Octree`.
    if size > u64::from(u32::MAX) {
        return Err(OctreeError::TooManyNodes(size));
    }
    Ok((Header { size, res }, &bytes[p.min(bytes.len())..]))
}

/// Builds an [`Octree`]'s preorder arrays (values, child masks, subtree ends) and leaf counts
/// from a walk, in one pass.
struct TreeReader {
    model: SensorModel,
    /// `.bt`: inner values are the max of their children, the root's is clamp max.
    derive_inner: bool,
    values: Vec<f32>,
    masks: Vec<u8>,
    ends: Vec<u32>,
    /// Per open inner node (index = its depth): its index and the max of its children so far.
    open: [(u32, f32); TREE_DEPTH as usize],
    leaves: u64,
    occupied: u64,
}

impl TreeReader {
    fn new(capacity: usize, model: SensorModel, derive_inner: bool) -> Self {
        Self {
            model,
            derive_inner,
            values: Vec::with_capacity(capacity),
            masks: Vec::with_capacity(capacity),
            ends: Vec::with_capacity(capacity),
            open: [(0, 0.0); TREE_DEPTH as usize],
            leaves: 0,
            occupied: 0,
        }
    }

    /// Raises the running max of the inner node at `depth - 1` (the parent of a node at
    /// `depth`) to `value`.
    #[inline]
    fn raise_parent(&mut self, depth: u32, value: f32) {
        if let Some(parent) = (depth as usize)
            .checked_sub(1)
            .and_then(|p| self.open.get_mut(p))
        {
            parent.1 = parent.1.max(value);
        }
    }

    fn finish(mut self, res: Resolution) -> Octree {
        if self.derive_inner {
            // The root keeps clamp max (OctoMap never recomputes it after reading).
            if let Some(root) = self.values.first_mut() {
                *root = self.model.clamp_max;
            }
        }
        Octree::from_arrays(
            res,
            self.model,
            self.values,
            self.masks,
            self.ends,
            self.leaves,
            self.occupied,
        )
    }
}

impl NodeVisitor for TreeReader {
    #[inline]
    fn inner(&mut self, depth: u32, mask: u8, value: f32) {
        let n = self.values.len() as u32;
        self.values.push(value);
        self.masks.push(mask);
        self.ends.push(0);
        if let Some(o) = self.open.get_mut(depth as usize) {
            *o = (n, -f32::MAX);
        }
    }

    #[inline]
    fn leaf(&mut self, depth: u32, _first: u64, value: f32) {
        let n = self.values.len() as u32;
        self.values.push(value);
        self.masks.push(0);
        self.ends.push(n + 1);
        self.leaves += 1;
        self.occupied += u64::from(self.model.is_occupied(value));
        self.raise_parent(depth, value);
    }

    #[inline]
    fn close(&mut self, depth: u32) {
        let Some(&(node, max)) = self.open.get(depth as usize) else {
            return;
        };
        let end = self.values.len() as u32;
        if let Some(e) = self.ends.get_mut(node as usize) {
            *e = end;
        }
        if self.derive_inner
            && let Some(v) = self.values.get_mut(node as usize)
        {
            *v = max;
        }
        if end == node + 1 {
            // An inner-node code whose record lists no child is a childless node, a leaf
            // (OctoMap's getNumLeafNodes counts it) of value -FLT_MAX (getMaxChildLogOdds of
            // no children); a childless root is a leaf at clamp max. OctoMap never writes
            // one; a hand-made `.bt` can hold it.
            let v = if depth == 0 {
                self.model.clamp_max
            } else {
                max
            };
            self.leaves += 1;
            self.occupied += u64::from(self.model.is_occupied(v));
        }
        self.raise_parent(depth, max);
    }
}

impl Octree {
    /// Reads a `.bt` or `.ot` file, chosen by its first line. `model` gives the clamps that
    /// `.bt` leaves take and the occupancy threshold (files do not store them).
    pub fn read(bytes: &[u8], model: SensorModel) -> Result<Octree, OctreeError> {
        if is_binary(bytes)? {
            Self::read_bt(bytes, model)
        } else {
            Self::read_ot(bytes, model)
        }
    }

    /// Reads a `.bt` file like `OcTree::readBinary`: free leaves get clamp min, occupied ones
    /// clamp max, inner nodes the max of their children, and the root keeps clamp max.
    pub fn read_bt(bytes: &[u8], model: SensorModel) -> Result<Octree, OctreeError> {
        let (h, data) = parse_header(bytes, BT_MAGIC)?;
        // Each data byte describes at most 4 nodes: no allocation beyond what the file holds.
        let cap = (h.size as usize).min(data.len().saturating_mul(4) + 1);
        let mut tree = TreeReader::new(cap, model, true);
        walk_bt(data, h.size, [model.clamp_min, model.clamp_max], &mut tree)?;
        Ok(tree.finish(h.res))
    }

    /// Reads an `.ot` file (`AbstractOcTree::read` of an `OcTree`): values as stored.
    pub fn read_ot(bytes: &[u8], model: SensorModel) -> Result<Octree, OctreeError> {
        let (h, data) = parse_header(bytes, OT_MAGIC)?;
        let cap = (h.size as usize).min(data.len() / 5 + 1);
        let mut tree = TreeReader::new(cap, model, false);
        walk_ot(data, h.size, &mut tree)?;
        Ok(tree.finish(h.res))
    }

    /// The `.ot` file of this tree as it is (`OcTree::write`).
    pub fn to_ot_bytes(&self) -> Vec<u8> {
        let mut out = header(OT_MAGIC, self.num_nodes(), self.res.meters());
        out.reserve(self.num_nodes() * 5);
        for (v, m) in self.values.iter().zip(&self.masks) {
            out.extend_from_slice(&v.to_le_bytes());
            out.push(*m);
        }
        out
    }

    /// The `.bt` file OctoMap's `writeBinary` makes: max-likelihood, prune, then write; the
    /// bytes of `self.to_max_likelihood_pruned().to_bt_bytes_const()` without building that
    /// tree. One pass finds what the level-by-level prune collapses (under a full bottom-up
    /// prune, with the number of collapses per depth: the prune stops at the deepest depth
    /// with none), a second writes the codes of the pruned tree.
    pub fn to_bt_bytes(&self) -> Vec<u8> {
        let mut ml = vec![f32::NAN; self.num_nodes()];
        let mut collapses = [0usize; TREE_DEPTH as usize];
        self.ml_collapse(0, 0, &mut ml, &mut collapses);
        // `to_max_likelihood_pruned` prunes depth 15, 14, … and stops at the first depth that
        // prunes nothing: nodes deeper than it collapse, it and the ones above do not.
        let stop = (1..TREE_DEPTH)
            .rev()
            .find(|&d| collapses[usize::from(d)] == 0)
            .unwrap_or(0);
        // Each collapse drops its 8 children (already leaves: deeper collapses dropped theirs).
        let dropped = 8 * collapses
            .get(usize::from(stop) + 1..)
            .map_or(0, |c| c.iter().sum::<usize>());
        self.bt_bytes(stop, &ml, self.num_nodes().saturating_sub(dropped))
    }

    /// The `.bt` encoding of this tree as it is (`writeBinaryConst`): the root's record, then
    /// each inner node's 2-byte child codes in preorder (0 absent, 1 free, 2 occupied, 3 inner).
    pub fn to_bt_bytes_const(&self) -> Vec<u8> {
        self.bt_bytes(TREE_DEPTH, &self.values, self.num_nodes())
    }

    /// The header and the codes of the tree pruned below `stop` (nothing pruned at
    /// [`TREE_DEPTH`]), leaves valued by `values`; `nodes` is that tree's node count.
    fn bt_bytes(&self, stop: u8, values: &[f32], nodes: usize) -> Vec<u8> {
        let mut out = header(BT_MAGIC, nodes, self.res.meters());
        if nodes > 0 {
            out.reserve(nodes / 3 + 2);
            let written = self.write_bt_codes(0, 0, stop, values, &mut out);
            debug_assert_eq!(written, nodes, "the .bt header's node count");
        }
        out
    }

    /// The max-likelihood value node `i` (at `depth`) has after a full bottom-up prune into
    /// `ml[i]`: its own for a leaf, its children's when all 8 are leaves of one value (a
    /// collapse, counted at `depth`), NaN while it stays inner. Returns `ml[i]`.
    fn ml_collapse(&self, i: usize, depth: u8, ml: &mut [f32], collapses: &mut [usize]) -> f32 {
        let m = self.masks.get(i).copied().unwrap_or(0);
        let value = if m == 0 {
            self.model
                .max_likelihood(self.values.get(i).copied().unwrap_or(f32::NAN))
        } else {
            let mut c = i + 1;
            let mut first = None;
            let mut equal = m == 0xff;
            for _ in 0..m.count_ones() {
                let v = self.ml_collapse(c, depth + 1, ml, collapses);
                equal &= first.is_none_or(|f| f == v);
                first.get_or_insert(v);
                c = self.subtree_end(c);
            }
            match first {
                Some(v) if equal && !v.is_nan() && depth > 0 => {
                    if let Some(n) = collapses.get_mut(usize::from(depth)) {
                        *n += 1;
                    }
                    v
                }
                _ => f32::NAN,
            }
        };
        if let Some(slot) = ml.get_mut(i) {
            *slot = value;
        }
        value
    }

    /// Whether node `i` at `depth` is a leaf of the tree pruned below `stop` (see
    /// [`Octree::to_bt_bytes`]), with its value in `values`.
    fn pruned_leaf(&self, i: usize, depth: u8, stop: u8, values: &[f32]) -> Option<f32> {
        let v = values.get(i).copied().unwrap_or(f32::NAN);
        let leaf = self.masks.get(i).is_none_or(|&m| m == 0) || (depth > stop && !v.is_nan());
        leaf.then_some(v)
    }

    /// Appends the `.bt` records of node `i`'s pruned subtree (the root's even if it is a
    /// leaf) and returns how many nodes that subtree has.
    fn write_bt_codes(
        &self,
        i: usize,
        depth: u8,
        stop: u8,
        values: &[f32],
        out: &mut Vec<u8>,
    ) -> usize {
        if self.pruned_leaf(i, depth, stop, values).is_some() {
            if i == 0 {
                out.extend_from_slice(&[0, 0]);
            }
            return 1;
        }
        let m = self.masks.get(i).copied().unwrap_or(0);
        let mut codes = 0u16;
        let mut c = i + 1;
        for pos in (0..8).filter(|pos| m & (1 << pos) != 0) {
            let code = match self.pruned_leaf(c, depth + 1, stop, values) {
                Some(v) if self.model.is_occupied(v) => 2,
                Some(_) => 1,
                None => 3,
            };
            codes |= code << (2 * pos);
            c = self.subtree_end(c);
        }
        out.extend_from_slice(&codes.to_le_bytes());
        let mut nodes = 1;
        let mut c = i + 1;
        for _ in 0..m.count_ones() {
            nodes += self.write_bt_codes(c, depth + 1, stop, values, out);
            c = self.subtree_end(c);
        }
        nodes
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::{Key, VoxelMap};

    /// The one-pass `.bt` writer against the tree `to_max_likelihood_pruned` builds.
    fn bt_both_ways(m: &VoxelMap) -> (Vec<u8>, Vec<u8>) {
        let t = m.to_octree();
        (
            t.to_bt_bytes(),
            t.to_max_likelihood_pruned().to_bt_bytes_const(),
        )
    }

    #[test]
    fn bt_writer_prunes_exactly_like_the_max_likelihood_tree() {
        let model = SensorModel::default();
        let res = Resolution::new(0.1).unwrap();
        // Empty, one voxel, and one bundle of rays (free space with occupied ends).
        let mut m = VoxelMap::new(res, model);
        let (a, b) = bt_both_ways(&m);
        assert_eq!(a, b);
        m.update(Key([32768; 3]), true);
        let (a, b) = bt_both_ways(&m);
        assert_eq!(a, b);
        let pts: Vec<[f32; 3]> = (0..2000)
            .map(|i| {
                let a = i as f32 * 0.0031;
                [6.0 * a.cos(), 6.0 * a.sin(), (i % 17) as f32 * 0.1 - 0.8]
            })
            .collect();
        m.insert_point_cloud(&pts, [0.05, 0.05, 0.05], -1.0);
        let (a, b) = bt_both_ways(&m);
        assert_eq!(a, b);

        // The stop rule: eight sibling bricks (depth-14 leaves), each uniform but each of another
        // occupied log-odds. Max-likelihood makes them equal, but depth 15 has nothing to prune,
        // so OctoMap's level-by-level prune stops there and they stay eight leaves.
        let mut m = VoxelMap::new(res, model);
        for b in 0..8u16 {
            let base = [b & 1, (b >> 1) & 1, b >> 2].map(|o| 32768 + 4 * o);
            for v in 0..64u16 {
                let k = [v & 3, (v >> 2) & 3, v >> 4];
                m.set_log_odds(
                    Key([0, 1, 2].map(|i| base[i] + k[i])),
                    0.5 + f32::from(b) * 0.1,
                );
            }
        }
        let (a, b) = bt_both_ways(&m);
        assert_eq!(a, b);
        let unpruned = m.to_octree().to_max_likelihood_pruned();
        assert_eq!(unpruned.num_leaves(), 8);
        // Eight voxels elsewhere of two occupied log-odds: depth 15 prunes them into one leaf,
        // depth 14 then has nothing to prune, so the bricks still stay apart.
        for v in 0..8u16 {
            let k = Key([40000 + (v & 1), 40000 + ((v >> 1) & 1), 40000 + (v >> 2)]);
            m.set_log_odds(k, if v == 0 { 0.7 } else { 0.9 });
        }
        let (a, b) = bt_both_ways(&m);
        assert_eq!(a, b);
        let pruned = m.to_octree().to_max_likelihood_pruned();
        assert_eq!(pruned.num_leaves(), 8 + 1);
    }

    #[test]
    fn resolution_prints_like_cpp_ostream() {
        assert_eq!(format_resolution(0.05), "0.05");
        assert_eq!(format_resolution(0.1), "0.1");
        assert_eq!(format_resolution(0.08), "0.08");
        assert_eq!(format_resolution(1.0), "1");
        assert_eq!(format_resolution(0.123456789), "0.123457");
        assert_eq!(format_resolution(0.00001), "1e-05");
        assert_eq!(format_resolution(1234567.0), "1.23457e+06");
        assert_eq!(format_resolution(0.0001), "0.0001");
    }

    fn small_tree() -> Octree {
        let model = SensorModel::default();
        let mut m = VoxelMap::new(Resolution::new(0.1).unwrap(), model);
        m.set_log_odds(Key([32768; 3]), model.clamp_max);
        m.set_log_odds(Key([32767, 32768, 32768]), model.clamp_min);
        m.to_octree()
    }

    #[test]
    fn bt_bytes_by_hand() {
        // Voxel A (32768,32768,32768) occupied, B (32767,32768,32768) free. At the root (key
        // bit 15) A is child 7 and B child 6, both inner: byte1 = 0b1111_0000. Below, B's x bits
        // are all 1 and y, z all 0: child 1 at every level; A takes child 0 at every level.
        // 1 + 2 * 16 nodes, 1 + 2 * 15 records.
        let bt = small_tree().to_bt_bytes();
        let head = b"# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the first line as it is!)\n#\nid OcTree\nsize 33\nres 0.1\ndata\n";
        assert!(
            bt.starts_with(head),
            "{}",
            String::from_utf8_lossy(&bt[..head.len()])
        );
        let data = &bt[head.len()..];
        assert_eq!(data.len(), 2 * 31, "{data:02x?}");
        assert_eq!(&data[..2], &[0x00, 0xf0]);
        for r in 1..15 {
            assert_eq!(
                &data[2 * r..2 * r + 2],
                &[0x0c, 0x00],
                "B record {r}: child 1 inner {data:02x?}"
            );
        }
        assert_eq!(
            &data[30..32],
            &[0x04, 0x00],
            "B depth 15: child 1 free leaf"
        );
        for r in 16..30 {
            assert_eq!(
                &data[2 * r..2 * r + 2],
                &[0x03, 0x00],
                "A record {r}: child 0 inner"
            );
        }
        assert_eq!(
            &data[60..62],
            &[0x02, 0x00],
            "A depth 15: child 0 occupied leaf"
        );
        let t = Octree::read_bt(&bt, SensorModel::default()).unwrap();
        assert_eq!(
            (t.num_nodes(), t.num_leaves(), t.num_occupied()),
            (33, 2, 1)
        );
        assert_eq!(t.to_bt_bytes(), bt);
    }

    #[test]
    fn childless_nodes_of_a_hand_made_bt_are_counted_as_the_leaves_they_are() {
        // Found by fuzz/fuzz_targets/bt.rs (fuzz/regressions/bt/): an inner-node code whose
        // record lists no child made a node that `leaves()` yields but `num_leaves` missed.
        let model = SensorModel::default();
        let head = |size: u32| {
            format!("# Octomap OcTree binary file\nid OcTree\nsize {size}\nres 0.1\ndata\n")
                .into_bytes()
        };
        // Root: child 0 inner (code 3), child 1 occupied (code 2); child 0's record: nothing.
        let mut bt = head(3);
        bt.extend_from_slice(&[0x0b, 0x00, 0x00, 0x00]);
        let t = Octree::read_bt(&bt, model).unwrap();
        assert_eq!(t.leaves().count(), 2);
        assert_eq!((t.num_nodes(), t.num_leaves(), t.num_occupied()), (3, 2, 1));
        let childless = t.leaves().find(|l| l.log_odds != model.clamp_max).unwrap();
        assert_eq!(
            childless.log_odds,
            -f32::MAX,
            "getMaxChildLogOdds of no children"
        );
        // A root record without children: the root alone is the one leaf, at clamp max.
        let mut bt = head(1);
        bt.extend_from_slice(&[0x00, 0x00]);
        let t = Octree::read_bt(&bt, model).unwrap();
        assert_eq!(t.leaves().count(), 1);
        assert_eq!((t.num_nodes(), t.num_leaves(), t.num_occupied()), (1, 1, 1));
    }

    #[test]
    fn ot_roundtrip_and_truncation() {
        let t = small_tree();
        let ot = t.to_ot_bytes();
        let back = Octree::read_ot(&ot, SensorModel::default()).unwrap();
        assert_eq!(back.to_ot_bytes(), ot);
        for cut in [ot.len() - 1, ot.len() - 5, ot.len() - 100, 20] {
            assert!(
                Octree::read(&ot[..cut], SensorModel::default()).is_err(),
                "cut {cut}"
            );
        }
        let bt = t.to_bt_bytes();
        assert_eq!(
            Octree::read(&bt[..bt.len() - 1], SensorModel::default()).unwrap_err(),
            OctreeError::Truncated {
                what: ".bt node record"
            }
        );
    }

    #[test]
    fn lying_sizes_and_bad_headers_are_errors() {
        let model = SensorModel::default();
        let ot = small_tree().to_ot_bytes();
        let pos = ot.windows(8).position(|w| w == b"size 33\n").unwrap();
        let mut lying = ot[..pos].to_vec();
        lying.extend_from_slice(b"size 4000000000\n");
        lying.extend_from_slice(&ot[pos + 8..]);
        assert_eq!(
            Octree::read_ot(&lying, model).unwrap_err(),
            OctreeError::SizeMismatch {
                header: 4_000_000_000,
                read: 33
            }
        );
        assert_eq!(
            Octree::read(b"hello", model).unwrap_err().to_string(),
            "not an OctoMap file: the first line must start with \"# Octomap OcTree binary file\" (.bt) or \"# Octomap OcTree file\" (.ot)"
        );
        assert_eq!(
            Octree::read_bt(b"# Octomap OcTree file\n", model)
                .unwrap_err()
                .to_string(),
            "not an OctoMap .bt file: the first line must start with \"# Octomap OcTree binary file\""
        );
        assert_eq!(
            Octree::read_ot(b"hello", model).unwrap_err().to_string(),
            "not an OctoMap .ot file: the first line must start with \"# Octomap OcTree file\""
        );
        assert!(matches!(
            Octree::read(
                b"# Octomap OcTree file\nid ColorOcTree\nres 0.1\nsize 1\ndata\n",
                model
            ),
            Err(OctreeError::UnsupportedTreeType(_))
        ));
        assert!(matches!(
            Octree::read(b"# Octomap OcTree file\nid OcTree\nres -1\ndata\n", model),
            Err(OctreeError::BadResolution(_))
        ));
        assert!(matches!(
            Octree::read(b"# Octomap OcTree file\nid OcTree\nres 0.1\n", model),
            Err(OctreeError::BadHeader(_))
        ));
        // 17 nested inner nodes.
        let mut deep =
            b"# Octomap OcTree binary file\nid OcTree\nsize 100\nres 0.1\ndata\n".to_vec();
        for _ in 0..17 {
            deep.extend_from_slice(&[0x03, 0x00]);
        }
        assert_eq!(
            Octree::read(&deep, model).unwrap_err(),
            OctreeError::TooDeep
        );
        // Empty tree.
        let e = Octree::read(
            b"# Octomap OcTree binary file\nid OcTree\nsize 0\nres 0.2\ndata\n",
            model,
        )
        .unwrap();
        assert_eq!(e.num_nodes(), 0);
        assert!(e.to_bt_bytes().ends_with(b"size 0\nres 0.2\ndata\n"));
    }
}
