//! Flat voxel storage for insertion: 4×4×4 voxel bricks in a hash map, per-bundle ray marks in a
//! dense window of brick slots, and the OctoMap tree derived on demand.
//!
//! Why this gives OctoMap's tree: with eager pruning OctoMap's tree is, after every update, the
//! canonical prune of its voxel values (a node collapses iff its 8 children are equal leaves),
//! and its early abort at saturation leaves a voxel's value exactly as add-then-clamp would
//! (research/octomap.md §4.3/§4.4). So storing one value per known voxel, applying each bundle's
//! de-duplicated updates per voxel with the same abort rule, and pruning canonically when the
//! tree is needed gives the same nodes, values and bytes.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use super::key::{Key, Resolution, morton};
use super::model::SensorModel;
use super::ray::{BIAS, FIELD, FreeMarks, Kernel, mark_free, pack, ray_length, unpack};
use super::tree::{Octree, TreeBuilder};
use crate::cloud::RayBundle;

/// Bricks are 4×4×4 voxels, i.e. depth-14 nodes; one `u64` holds a bit per voxel.
const BRICK_SHIFT: u32 = 2;
/// Most window cells (16 bytes each) used per bundle for the dense brick lookup; beyond it, a hash map.
const WINDOW_MAX_CELLS: usize = 1 << 20;
/// Largest brick coordinate (14 bits).
const BRICK_MAX: u32 = (1 << (16 - BRICK_SHIFT)) - 1;
const _: () = assert!(
    BIAS.is_multiple_of(4),
    "brick bits of packed keys must not depend on the bias"
);

/// Packed brick coordinates (14 bits per axis).
#[inline]
fn brick_key(k: [u16; 3]) -> u64 {
    u64::from(k[0] >> BRICK_SHIFT)
        | (u64::from(k[1] >> BRICK_SHIFT) << 14)
        | (u64::from(k[2] >> BRICK_SHIFT) << 28)
}

#[inline]
fn brick_coords(bk: u64) -> [u16; 3] {
    [
        (bk & 0x3fff) as u16,
        ((bk >> 14) & 0x3fff) as u16,
        ((bk >> 28) & 0x3fff) as u16,
    ]
}

/// Morton index (0..64) of a voxel inside its brick: bits x0 y0 z0 x1 y1 z1.
#[inline]
fn local_bit(k: [u16; 3]) -> u64 {
    1u64 << morton(k.map(|a| a & 3))
}

/// A cheap multiplicative hasher for packed `u64` keys (bricks here, value pairs in `eval`):
/// the keys are already well spread, so one multiply beats SipHash by far.
#[derive(Default)]
pub(crate) struct U64Hasher(u64);

impl Hasher for U64Hasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }
    #[inline]
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0 ^ v).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
    #[inline]
    fn finish(&self) -> u64 {
        self.0.rotate_left(32)
    }
}

type BrickMap = HashMap<u64, u32, BuildHasherDefault<U64Hasher>>;

/// The values of one brick, in Morton order, and which of them are known.
#[derive(Clone)]
struct Brick {
    values: [f32; 64],
    known: u64,
}

/// Per-bundle scratch: a dense window of bricks around the bundle holding each brick's free and
/// occupied marks (bit per voxel, Morton order), the list of touched cells, and a hash map for
/// the rare keys outside the window.
#[derive(Default)]
struct Scratch {
    /// Per window cell: `[free, occupied]` marks.
    window: Vec<[u64; 2]>,
    /// Cells with a mark, in first-touch order (reset after the bundle).
    touched: Vec<u32>,
    /// Window origin in bricks, and the same in the brick fields of packed keys.
    lo: [u32; 3],
    lo_packed: u64,
    dim: [u32; 3],
    overflow: HashMap<u64, [u64; 2], BuildHasherDefault<U64Hasher>>,
    ends: Vec<([f32; 3], Key, bool)>,
}

/// Brick part of a packed key: each 21-bit field shifted down by 2.
const PACKED_BRICK: u64 = (FIELD >> 2) | ((FIELD >> 2) << 21) | ((FIELD >> 2) << 42);

/// Morton bit index inside a brick of the linear index x + 4y + 16z.
#[cfg(test)]
const LIN_TO_MORTON: [u8; 64] = {
    let mut t = [0u8; 64];
    let mut i = 0;
    while i < 64 {
        let (x, y, z) = (i & 3, (i >> 2) & 3, i >> 4);
        t[i] = morton([x as u16, y as u16, z as u16]) as u8;
        i += 1;
    }
    t
};

/// The bits of a 64-bit set with index bits `i` and `j` exchanged (`i < j`): a delta swap.
const fn swap_index_bits(w: u64, i: u32, j: u32) -> u64 {
    let d = (1u32 << j) - (1u32 << i);
    // Positions whose index has bit i set and bit j clear: the lower of each swapped pair.
    let mut mask = 0u64;
    let mut q = 0;
    while q < 64 {
        if (q >> i) & 1 == 1 && (q >> j) & 1 == 0 {
            mask |= 1 << q;
        }
        q += 1;
    }
    let t = ((w >> d) ^ w) & mask;
    w ^ t ^ (t << d)
}

/// Reorders a brick's marks from linear bit order (x0 x1 y0 y1 z0 z1) to Morton order
/// (x0 y0 z0 x1 y1 z1): three index-bit swaps moving x1 to 3, y0 to 1, y1 to 4 and z0 to 2.
#[inline]
fn to_morton(lin: u64) -> u64 {
    swap_index_bits(swap_index_bits(swap_index_bits(lin, 1, 3), 1, 4), 1, 2)
}

impl Scratch {
    /// Sets the window to the brick box `lo..=hi` (grown by one brick for rays that step a
    /// voxel past their end), shrunk around `center` while too large.
    fn set_window(&mut self, mut lo: [u32; 3], mut hi: [u32; 3], center: [u32; 3]) {
        for i in 0..3 {
            lo[i] = lo[i].saturating_sub(1);
            hi[i] = (hi[i] + 1).min(BRICK_MAX);
        }
        loop {
            let cells: usize = (0..3).map(|i| (hi[i] - lo[i] + 1) as usize).product();
            if cells <= WINDOW_MAX_CELLS {
                break;
            }
            let Some(a) = (0..3).max_by_key(|&i| hi[i] - lo[i]) else {
                break;
            };
            let half = (hi[a] - lo[a]) / 4;
            lo[a] = lo[a].max(center[a].saturating_sub(half));
            hi[a] = hi[a].min(center[a] + half);
        }
        self.lo = lo;
        let bias = BIAS >> BRICK_SHIFT;
        self.lo_packed = (0..3).fold(0, |acc, i| acc | ((u64::from(lo[i]) + bias) << (21 * i)));
        self.dim = [hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1];
        let cells = (self.dim[0] * self.dim[1] * self.dim[2]) as usize;
        if self.window.len() < cells {
            self.window.resize(cells, [0; 2]);
        }
    }

    /// Marks the voxel of a packed key (see `ray::pack`) free (`occ = 0`) or occupied (1).
    /// Marks are in linear order (bit x + 4y + 16z); [`to_morton`] reorders them per brick.
    /// All free marks of a bundle must come before its occupied marks.
    #[inline(always)]
    fn mark(&mut self, k: u64, occ: usize) {
        // Each field is a u16 key plus the bias, give or take the one step a ray may take
        // beyond the key range: the brick and bit extraction below rely on it.
        debug_assert!(
            (0..3)
                .all(|i| (k >> (21 * i)) & FIELD >= BIAS - 1
                    && (k >> (21 * i)) & FIELD <= BIAS + 65_536),
            "packed key {k:#x} has a field outside the biased key range"
        );
        // Window-relative brick coordinates; a field below the window wraps to a huge value.
        let r = ((k >> BRICK_SHIFT) & PACKED_BRICK).wrapping_sub(self.lo_packed);
        let (x, y, z) = (r & 0x1f_ffff, (r >> 21) & 0x1f_ffff, r >> 42);
        let lin = (k & 3) | ((k >> 19) & 0xc) | ((k >> 38) & 0x30);
        let bit = 1u64 << lin;
        let [dx, dy, dz] = self.dim.map(u64::from);
        if (x < dx) & (y < dy) & (z < dz) {
            let cell = x + dx * (y + dy * z);
            if let Some(w) = self.window.get_mut(cell as usize) {
                // Free marks come first, so a cell is new iff its free word is still 0 (and,
                // for an occupied mark, its occupied word too).
                let new = if occ == 0 {
                    w[0] == 0
                } else {
                    w[0] | w[1] == 0
                };
                if new {
                    self.touched.push(cell as u32);
                }
                w[occ & 1] |= bit;
                return;
            }
        }
        self.mark_overflow(k, occ, bit);
    }

    #[cold]
    fn mark_overflow(&mut self, k: u64, occ: usize, bit: u64) {
        self.overflow.entry(brick_key(unpack(k).0)).or_default()[occ & 1] |= bit;
    }

    /// Brick key of a window cell.
    fn cell_brick(&self, cell: u32) -> u64 {
        let [dx, dy, _] = self.dim;
        let (x, y, z) = (cell % dx, (cell / dx) % dy, cell / dx / dy);
        u64::from(self.lo[0] + x)
            | (u64::from(self.lo[1] + y) << 14)
            | (u64::from(self.lo[2] + z) << 28)
    }
}

impl FreeMarks for Scratch {
    fn window(&self) -> (u64, [u32; 3]) {
        (self.lo_packed, self.dim)
    }

    #[inline]
    fn mark_cell(&mut self, cell: u32, bits: u64) {
        debug_assert!(
            u64::from(cell) < self.dim.iter().map(|&d| u64::from(d)).product::<u64>(),
            "cell {cell} outside the window {:?}",
            self.dim
        );
        if let Some(w) = self.window.get_mut(cell as usize) {
            if w[0] == 0 {
                self.touched.push(cell);
            }
            w[0] |= bits;
        }
    }

    #[inline]
    fn mark_key(&mut self, key: u64) {
        self.mark(key, 0);
    }
}

/// What one insertion did with its points.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct InsertStats {
    /// Points given.
    pub points: u64,
    /// Points skipped because a coordinate (or the origin) was NaN or infinite.
    pub skipped_nonfinite: u64,
    /// Points whose endpoint was outside the key range (no hit; their ray is dropped too).
    pub out_of_bounds: u64,
    /// Points beyond the max range (free space up to the cut, no hit).
    pub max_range: u64,
    /// Rays skipped because their f32 length is 0 or not finite although their end lies in
    /// another voxel than the origin (no free space marked; the endpoint still gets its hit).
    /// OctoMap fails an assertion or loops for ever on them (`ray` module docs).
    pub degenerate_rays: u64,
}

impl InsertStats {
    fn add(&mut self, o: &InsertStats) {
        self.points += o.points;
        self.skipped_nonfinite += o.skipped_nonfinite;
        self.out_of_bounds += o.out_of_bounds;
        self.max_range += o.max_range;
        self.degenerate_rays += o.degenerate_rays;
    }
}

/// An occupancy map being built: one f32 log-odds per known voxel, updated with OctoMap's
/// `insertPointCloud` semantics; [`VoxelMap::to_octree`] derives OctoMap's pruned tree.
pub struct VoxelMap {
    res: Resolution,
    model: SensorModel,
    bricks: Vec<Brick>,
    index: BrickMap,
    scratch: Scratch,
    totals: InsertStats,
    kernel: Kernel,
}

impl std::fmt::Debug for VoxelMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VoxelMap")
            .field("resolution", &self.res.meters())
            .field("bricks", &self.bricks.len())
            .field("totals", &self.totals)
            .field("kernel", &self.kernel)
            .finish()
    }
}

/// A copy of the map's voxels (its insertion scratch starts empty): what a snapshot takes so
/// the octree is derived and written without holding the map's owner.
impl Clone for VoxelMap {
    fn clone(&self) -> Self {
        Self {
            res: self.res,
            model: self.model,
            bricks: self.bricks.clone(),
            index: self.index.clone(),
            scratch: Scratch::default(),
            totals: self.totals,
            kernel: self.kernel,
        }
    }
}

impl VoxelMap {
    /// An empty map, inserting with the process's default [`Kernel`] ([`Kernel::from_env`]).
    pub fn new(res: Resolution, model: SensorModel) -> Self {
        Self::with_kernel(res, model, Kernel::from_env())
    }

    /// An empty map inserting with `kernel` (the results are the same; tests compare them).
    pub fn with_kernel(res: Resolution, model: SensorModel, kernel: Kernel) -> Self {
        Self {
            res,
            model,
            bricks: Vec::new(),
            index: BrickMap::default(),
            scratch: Scratch::default(),
            totals: InsertStats::default(),
            kernel,
        }
    }

    /// The kernel insertions use.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// The voxel size and key conversions.
    pub fn resolution(&self) -> &Resolution {
        &self.res
    }

    /// The sensor model used by updates.
    pub fn model(&self) -> &SensorModel {
        &self.model
    }

    /// Sums of the [`InsertStats`] of every insertion so far.
    pub fn totals(&self) -> InsertStats {
        self.totals
    }

    /// Number of known voxels.
    pub fn num_voxels(&self) -> u64 {
        self.bricks
            .iter()
            .map(|b| u64::from(b.known.count_ones()))
            .sum()
    }

    /// Approximate heap bytes held (bricks, index, scratch).
    pub fn memory_bytes(&self) -> usize {
        self.bricks.capacity() * std::mem::size_of::<Brick>()
            + self.index.capacity() * (std::mem::size_of::<(u64, u32)>() + 1)
            + self.scratch.window.capacity() * 16
            + self.scratch.touched.capacity() * 4
            + self.scratch.ends.capacity() * std::mem::size_of::<([f32; 3], Key, bool)>()
    }

    fn brick_mut(&mut self, bk: u64) -> &mut Brick {
        let next = self.bricks.len() as u32;
        let i = *self.index.entry(bk).or_insert(next);
        if i == next {
            self.bricks.push(Brick {
                values: [0.0; 64],
                known: 0,
            });
        }
        &mut self.bricks[i as usize]
    }

    /// The log-odds of a voxel, or `None` if unknown.
    pub fn log_odds(&self, key: Key) -> Option<f32> {
        let i = *self.index.get(&brick_key(key.0))?;
        let b = self.bricks.get(i as usize)?;
        let bit = local_bit(key.0);
        (b.known & bit != 0).then(|| b.values[bit.trailing_zeros() as usize])
    }

    /// Sets a voxel's log-odds outright (e.g. a ground-truth map: clamp max for occupied,
    /// clamp min for free), like OctoMap's `setNodeValue` with eager pruning.
    pub fn set_log_odds(&mut self, key: Key, log_odds: f32) {
        let bit = local_bit(key.0);
        let b = self.brick_mut(brick_key(key.0));
        b.values[bit.trailing_zeros() as usize] = log_odds;
        b.known |= bit;
    }

    /// One `updateNode(key, occupied)`: a hit or a miss on a single voxel.
    pub fn update(&mut self, key: Key, occupied: bool) {
        let model = self.model;
        let delta = if occupied { model.hit } else { model.miss };
        let bit = local_bit(key.0);
        let b = self.brick_mut(brick_key(key.0));
        apply(b, bit, delta, &model);
    }

    /// Inserts a bundle given in the world frame (OctoMap's `insertPointCloud` with
    /// `maxrange`, `lazy_eval = false`, `discretize = false`); the origin is cast to f32.
    /// A negative `max_range` means no limit.
    pub fn insert_bundle(&mut self, bundle: &RayBundle, max_range: f64) -> InsertStats {
        let o = bundle.origin.map(|c| c as f32);
        self.insert_point_cloud(&bundle.points, o, max_range)
    }

    /// Inserts points seen from `origin` (all world frame). Per bundle each voxel gets one update:
    /// a hit if some point ends in it, else a miss if some ray crosses it (origin voxel
    /// included, end voxel excluded). Points beyond `max_range` (if `>= 0`) free space up to
    /// the cut and make no hit. Non-finite points are skipped and counted; so are degenerate
    /// rays (see [`InsertStats::degenerate_rays`]).
    pub fn insert_point_cloud(
        &mut self,
        points: &[[f32; 3]],
        origin: [f32; 3],
        max_range: f64,
    ) -> InsertStats {
        let mut stats = InsertStats {
            points: points.len() as u64,
            ..InsertStats::default()
        };
        if !origin.iter().all(|c| c.is_finite()) {
            stats.skipped_nonfinite = stats.points;
            self.totals.add(&stats);
            return stats;
        }
        let res = self.res;
        let origin_key = res.coord_to_key(origin);

        // Pass 1: ray ends (cut at max range) and the brick box of everything the rays reach.
        let mut ends = std::mem::take(&mut self.scratch.ends);
        ends.clear();
        let (mut lo, mut hi) = ([u32::MAX; 3], [0u32; 3]);
        if let Some(k) = origin_key {
            grow(&mut lo, &mut hi, k);
        }
        #[cfg(target_arch = "x86_64")]
        let fast = max_range < 0.0 && self.kernel.uses_avx2();
        let mut i = 0;
        while i < points.len() {
            #[cfg(target_arch = "x86_64")]
            if fast {
                // SAFETY: the CPU supports AVX2 (`uses_avx2` checked it), the only requirement
                // of `avx2::unlimited_ends`'s `#[target_feature]`.
                i += unsafe {
                    avx2::unlimited_ends(
                        &res,
                        points.get(i..).unwrap_or(&[]),
                        &mut ends,
                        &mut lo,
                        &mut hi,
                    )
                };
            }
            // A group the fast path left (a point out of range, or the last few), or all
            // points without it.
            let stop = (i + 4).min(points.len());
            for p in points.get(i..stop).unwrap_or(&[]) {
                push_end(
                    &res, origin, max_range, p, &mut ends, &mut stats, &mut lo, &mut hi,
                );
            }
            i = stop;
        }

        // Pass 2: mark free keys along rays and occupied endpoints, per brick.
        if lo[0] <= hi[0] {
            let center = origin_key.map_or(lo, |k| k.0.map(|a| u32::from(a >> BRICK_SHIFT)));
            self.scratch.set_window(lo, hi, center);
            if let Some(key_origin) = origin_key {
                stats.degenerate_rays = mark_rays(
                    self.kernel,
                    &mut self.scratch,
                    &res,
                    origin,
                    key_origin,
                    &ends,
                );
            }
            for &(_, key_end, hit) in &ends {
                if hit {
                    self.scratch.mark(pack(key_end), 1);
                }
            }
        }
        self.scratch.ends = ends;

        // Pass 3: one update per marked voxel; occupied wins over free.
        let model = self.model;
        let touched = std::mem::take(&mut self.scratch.touched);
        for &cell in &touched {
            let bk = self.scratch.cell_brick(cell);
            let [free, occ] = self
                .scratch
                .window
                .get_mut(cell as usize)
                .map_or([0; 2], std::mem::take)
                .map(to_morton);
            let b = self.brick_mut(bk);
            apply(b, free & !occ, model.miss, &model);
            apply(b, occ, model.hit, &model);
        }
        self.scratch.touched = touched;
        self.scratch.touched.clear();
        let overflow = std::mem::take(&mut self.scratch.overflow);
        for (&bk, marks) in &overflow {
            let [free, occ] = marks.map(to_morton);
            let b = self.brick_mut(bk);
            apply(b, free & !occ, model.miss, &model);
            apply(b, occ, model.hit, &model);
        }
        self.scratch.overflow = overflow;
        self.scratch.overflow.clear();
        self.totals.add(&stats);
        stats
    }

    /// Derives OctoMap's eagerly pruned tree: the tree `OcTree::write` would save after the
    /// same updates (inner value = max of children, 8 equal leaves collapse).
    pub fn to_octree(&self) -> Octree {
        let mut order: Vec<(u64, u32)> = self
            .index
            .iter()
            .filter(|(_, i)| self.bricks.get(**i as usize).is_some_and(|b| b.known != 0))
            .map(|(bk, i)| (morton(brick_coords(*bk)), *i))
            .collect();
        order.sort_unstable();
        let mut tb = TreeBuilder::with_capacity(order.len() * 4);
        if !order.is_empty() {
            self.build(&mut tb, 0, &order);
        }
        tb.finish(self.res, self.model)
    }

    fn build(&self, tb: &mut TreeBuilder, depth: u8, items: &[(u64, u32)]) {
        tb.open();
        if depth < 14 {
            let shift = 3 * u32::from(13 - depth);
            let mut rest = items;
            while let Some(first) = rest.first() {
                let c = (first.0 >> shift) & 7;
                let n = rest
                    .iter()
                    .take_while(|it| (it.0 >> shift) & 7 == c)
                    .count();
                let (group, tail) = rest.split_at(n);
                tb.child(c as usize);
                self.build(tb, depth + 1, group);
                rest = tail;
            }
        } else if let Some(b) = items.first().and_then(|it| self.bricks.get(it.1 as usize)) {
            for c15 in 0..8 {
                let known = (b.known >> (8 * c15)) & 0xff;
                if known == 0 {
                    continue;
                }
                tb.child(c15);
                tb.open();
                for c16 in 0..8 {
                    if known & (1 << c16) != 0 {
                        tb.child(c16);
                        tb.leaf(b.values[8 * c15 + c16]);
                    }
                }
                tb.close();
            }
        }
        tb.close();
    }
}

/// Widens the brick box `lo..=hi` to the brick of `k`.
#[inline]
fn grow(lo: &mut [u32; 3], hi: &mut [u32; 3], k: Key) {
    for i in 0..3 {
        let b = u32::from(k.0[i] >> BRICK_SHIFT);
        lo[i] = lo[i].min(b);
        hi[i] = hi[i].max(b);
    }
}

/// Pass 1 for one point: its ray end (cut at `max_range` if `>= 0`), key and whether it is
/// a hit, pushed to `ends` with the brick box grown; or counted as skipped.
#[allow(clippy::too_many_arguments)]
#[inline]
fn push_end(
    res: &Resolution,
    origin: [f32; 3],
    max_range: f64,
    p: &[f32; 3],
    ends: &mut Vec<([f32; 3], Key, bool)>,
    stats: &mut InsertStats,
    lo: &mut [u32; 3],
    hi: &mut [u32; 3],
) {
    if !p.iter().all(|c| c.is_finite()) {
        stats.skipped_nonfinite += 1;
        return;
    }
    let d = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
    let norm = || f64::from(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let (end, hit) = if max_range < 0.0 || norm() <= max_range {
        (*p, true)
    } else {
        let norm = norm();
        stats.max_range += 1;
        // Vector3::normalized() divides by (float)norm; new_end = origin + dir * (float)maxrange.
        let n = norm as f32;
        let dir = if norm > 0.0 {
            [d[0] / n, d[1] / n, d[2] / n]
        } else {
            d
        };
        let mr = max_range as f32;
        (
            [
                origin[0] + dir[0] * mr,
                origin[1] + dir[1] * mr,
                origin[2] + dir[2] * mr,
            ],
            false,
        )
    };
    match res.coord_to_key(end) {
        Some(k) => {
            grow(lo, hi, k);
            ends.push((end, k, hit));
        }
        None => stats.out_of_bounds += u64::from(hit),
    }
}

/// Pass 1 without a max range, four points per AVX2 vector.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{BRICK_SHIFT, Key, Resolution};

    #[target_feature(enable = "avx2")]
    fn lanes(v: __m128i) -> [u32; 4] {
        [
            _mm_extract_epi32::<0>(v) as u32,
            _mm_extract_epi32::<1>(v) as u32,
            _mm_extract_epi32::<2>(v) as u32,
            _mm_extract_epi32::<3>(v) as u32,
        ]
    }

    /// Pushes the ends (hits) of the leading groups of four points whose keys are all in range,
    /// as `push_end` with no max range would (a key in range implies finite coordinates),
    /// growing `lo..=hi`; returns how many points it took (a multiple of 4). The key is
    /// `coord_to_key_axis`'s: `floor(c * (1/res)) + 32768` for `c * (1/res)` in [-2^15, 2^15).
    #[target_feature(enable = "avx2")]
    pub(super) fn unlimited_ends(
        res: &Resolution,
        points: &[[f32; 3]],
        ends: &mut Vec<([f32; 3], Key, bool)>,
        lo: &mut [u32; 3],
        hi: &mut [u32; 3],
    ) -> usize {
        let factor = _mm256_set1_pd(1.0 / res.meters());
        let (min, max) = (_mm256_set1_pd(-32768.0), _mm256_set1_pd(32768.0));
        let bias = _mm_set1_epi32(32768);
        let mut kmin = [_mm_set1_epi32(-1); 3];
        let mut kmax = [_mm_setzero_si128(); 3];
        let mut taken = 0;
        'groups: for g in points.chunks_exact(4) {
            let mut keys = [[0u32; 4]; 3];
            for a in 0..3 {
                let c = _mm_setr_ps(g[0][a], g[1][a], g[2][a], g[3][a]);
                let x = _mm256_mul_pd(factor, _mm256_cvtps_pd(c));
                let inside = _mm256_and_pd(
                    _mm256_cmp_pd::<_CMP_GE_OQ>(x, min),
                    _mm256_cmp_pd::<_CMP_LT_OQ>(x, max),
                );
                if _mm256_movemask_pd(inside) != 15 {
                    break 'groups;
                }
                let k = _mm_add_epi32(_mm256_cvttpd_epi32(_mm256_floor_pd(x)), bias);
                kmin[a] = _mm_min_epu32(kmin[a], k);
                kmax[a] = _mm_max_epu32(kmax[a], k);
                keys[a] = lanes(k);
            }
            for (l, p) in g.iter().enumerate() {
                // In range (checked above), so each key fits its u16.
                debug_assert!(keys.iter().all(|k| k[l] <= 0xffff), "key {keys:?} lane {l}");
                let k = Key([keys[0][l] as u16, keys[1][l] as u16, keys[2][l] as u16]);
                ends.push((*p, k, true));
            }
            taken += 4;
        }
        if taken > 0 {
            for a in 0..3 {
                let (m, n) = (lanes(kmin[a]), lanes(kmax[a]));
                lo[a] = lo[a].min(m[0].min(m[1]).min(m[2]).min(m[3]) >> BRICK_SHIFT);
                hi[a] = hi[a].max(n[0].max(n[1]).max(n[2]).max(n[3]) >> BRICK_SHIFT);
            }
        }
        taken
    }
}

/// Marks the free keys of all rays from `origin` to `ends` (origin voxel included once, if
/// some ray is cast); returns the number of degenerate rays skipped.
fn mark_rays(
    kernel: Kernel,
    scratch: &mut Scratch,
    res: &Resolution,
    origin: [f32; 3],
    key_origin: Key,
    ends: &[([f32; 3], Key, bool)],
) -> u64 {
    // Usually decided by the first end. A degenerate ray marks nothing, not even the origin.
    if ends
        .iter()
        .any(|e| e.1 != key_origin && ray_length(origin, e.0).is_some())
    {
        scratch.mark(pack(key_origin), 0);
    }
    mark_free(
        kernel,
        res,
        origin,
        key_origin,
        ends.iter().map(|e| (e.0, e.1)),
        scratch,
    )
}

/// Applies `delta` to the voxels of `bits` in brick `b`: the early abort for known voxels,
/// add-then-clamp from 0.0 for new ones.
#[inline]
fn apply(b: &mut Brick, mut bits: u64, delta: f32, model: &SensorModel) {
    while bits != 0 {
        let i = bits.trailing_zeros() as usize;
        let bit = bits & bits.wrapping_neg();
        bits ^= bit;
        let v = &mut b.values[i];
        *v = if b.known & bit != 0 {
            model.update(*v, delta)
        } else {
            model.add_clamped(0.0, delta)
        };
        b.known |= bit;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::ray_keys;

    fn map(res: f64) -> VoxelMap {
        VoxelMap::new(Resolution::new(res).unwrap(), SensorModel::default())
    }

    #[test]
    fn local_bits_are_morton_order() {
        assert_eq!(local_bit([0, 0, 0]), 1);
        assert_eq!(local_bit([1, 0, 0]), 1 << 1);
        assert_eq!(local_bit([0, 0, 1]), 1 << 4);
        assert_eq!(local_bit([2, 0, 0]), 1 << 8);
        assert_eq!(local_bit([3, 3, 3]), 1 << 63);
        assert_eq!(brick_coords(brick_key([65535, 4, 9])), [16383, 1, 2]);
        for lin in 0..64u16 {
            let k = [100 + (lin & 3), 200 + ((lin >> 2) & 3), 300 + (lin >> 4)];
            assert_eq!(local_bit(k), 1 << LIN_TO_MORTON[usize::from(lin)]);
            let p = pack(Key(k));
            assert_eq!(
                (p & 3) | ((p >> 19) & 0xc) | ((p >> 38) & 0x30),
                u64::from(lin)
            );
        }
    }

    #[test]
    fn to_morton_moves_each_linear_bit_to_its_morton_bit() {
        for (lin, &m) in LIN_TO_MORTON.iter().enumerate() {
            assert_eq!(to_morton(1 << lin), 1 << m, "bit {lin}");
        }
        let mut w = 0x0123_4567_89ab_cdefu64;
        for _ in 0..100 {
            let by_bits = (0..64)
                .filter(|l| w & (1 << l) != 0)
                .fold(0u64, |m, l| m | (1 << LIN_TO_MORTON[l]));
            assert_eq!(to_morton(w), by_bits);
            w = w.rotate_left(7).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }

    #[test]
    fn occupied_wins_and_one_update_per_bundle() {
        // res 1: origin voxel 0; ray A ends in voxel 3 (passes 0,1,2), ray B ends in voxel 1.
        let mut m = map(1.0);
        let model = *m.model();
        let st = m.insert_point_cloud(
            &[[3.5, 0.5, 0.5], [1.5, 0.5, 0.5], [3.6, 0.5, 0.5]],
            [0.5, 0.5, 0.5],
            -1.0,
        );
        assert_eq!(st.points, 3);
        let k = |x: u16| Key([32768 + x, 32768, 32768]);
        assert_eq!(m.log_odds(k(0)), Some(model.miss));
        assert_eq!(
            m.log_odds(k(1)),
            Some(model.hit),
            "hit by B, crossed by A: one hit only"
        );
        assert_eq!(
            m.log_odds(k(2)),
            Some(model.miss),
            "crossed twice, one miss"
        );
        assert_eq!(m.log_odds(k(3)), Some(model.hit), "two endpoints, one hit");
        assert_eq!(m.log_odds(k(4)), None);
        assert_eq!(m.num_voxels(), 4);
    }

    #[test]
    fn max_range_frees_up_to_the_cut_without_a_hit_and_nonfinite_is_counted() {
        let mut m = map(1.0);
        let st = m.insert_point_cloud(
            &[
                [10.5, 0.5, 0.5],
                [f32::NAN, 0.0, 0.0],
                [0.0, f32::INFINITY, 0.0],
            ],
            [0.5, 0.5, 0.5],
            3.0,
        );
        assert_eq!((st.max_range, st.skipped_nonfinite), (1, 2));
        // Cut end at x = 3.5: voxels 0, 1, 2 free; voxel 3 (the cut end) not touched; no hit.
        let k = |x: u16| Key([32768 + x, 32768, 32768]);
        assert!((0..3).all(|x| m.log_odds(k(x)) == Some(m.model().miss)));
        assert_eq!(m.log_odds(k(3)), None);
        assert_eq!(m.totals().skipped_nonfinite, 2);
    }

    #[test]
    fn unlimited_range_equals_a_range_beyond_every_point() {
        // No max range takes the four-point path; a huge one the per-point path. Out-of-range
        // and non-finite points sit at various places in groups of four, and a tail of three.
        let mut pts: Vec<[f32; 3]> = (0..39)
            .map(|i| {
                let f = i as f32;
                [
                    (f * 0.37).sin() * 9.0,
                    (f * 0.71).cos() * 7.0,
                    f * 0.05 - 1.0,
                ]
            })
            .collect();
        pts[5] = [5000.0, 0.0, 0.0];
        pts[10] = [0.0, f32::NAN, 0.0];
        pts[15] = [0.0, 0.0, -f32::INFINITY];
        pts[36] = [0.0, -5000.0, 0.0];
        let mut bytes = Vec::new();
        for kernel in [Kernel::Scalar, Kernel::Avx2, Kernel::Avx512] {
            let new = || {
                VoxelMap::with_kernel(
                    Resolution::new(0.1).unwrap(),
                    SensorModel::default(),
                    kernel,
                )
            };
            let (mut a, mut b) = (new(), new());
            let sa = a.insert_point_cloud(&pts, [0.3, -0.2, 0.1], -1.0);
            let sb = b.insert_point_cloud(&pts, [0.3, -0.2, 0.1], 1e30);
            assert_eq!((sa.out_of_bounds, sa.skipped_nonfinite), (2, 2));
            assert_eq!(sa, sb);
            assert!(a.num_voxels() > 100);
            assert_eq!(a.to_octree().to_bt_bytes(), b.to_octree().to_bt_bytes());
            bytes.push(a.to_octree().to_ot_bytes());
        }
        assert_eq!(bytes[0], bytes[1], "scalar and AVX2 kernels differ");
        assert_eq!(bytes[0], bytes[2], "scalar and AVX-512 kernels differ");
    }

    #[test]
    fn out_of_bounds_endpoints_drop_the_ray() {
        let mut m = map(0.1);
        let st = m.insert_point_cloud(&[[5000.0, 0.0, 0.0]], [0.0, 0.0, 0.0], -1.0);
        assert_eq!(st.out_of_bounds, 1);
        assert_eq!(m.num_voxels(), 0);
        assert_eq!(m.to_octree().num_nodes(), 0);
    }

    #[test]
    fn a_huge_bundle_box_falls_back_beyond_the_window() {
        // Rays 3000 m long at 0.1 m: the brick box exceeds the window, the far part is hashed.
        let mut m = map(0.1);
        let pts = [
            [3000.0f32, 3000.0, 3000.0],
            [-3000.0, -3000.0, -3000.0],
            [3000.0, -3000.0, 5.0],
        ];
        m.insert_point_cloud(&pts, [0.0, 0.0, 0.0], -1.0);
        let r = *m.resolution();
        for p in pts {
            assert_eq!(m.log_odds(r.coord_to_key(p).unwrap()), Some(m.model().hit));
        }
        let mut n = 0;
        ray_keys(&r, [0.0; 3], pts[0], |k| {
            n += 1;
            assert_eq!(m.log_odds(k), Some(m.model().miss));
        });
        assert!(n > 80_000);
    }
}
