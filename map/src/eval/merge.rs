//! The one pass every metric rests on: a merge of two maps' leaves in Morton order.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use serde::Serialize;

use super::leafmap::{LeafMap, split_code};
use super::{EvalError, FREE, OCCUPIED, Role, UNKNOWN, VoxelBox};
use crate::octree::U64Hasher;
use crate::octree::unmorton;

/// Voxels known in both maps that share one (first map, second map) log-odds pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ValuePair {
    /// The first (reference) map's log-odds.
    pub reference: f32,
    /// The second (target) map's log-odds.
    pub target: f32,
    /// How many voxels (in U) carry this pair.
    pub voxels: u64,
}

/// What one merge of two maps found over U.
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    /// `[first map's state][second map's state]` voxel counts (occupied, free, unknown); the
    /// unknown/unknown cell is 0 here (see [`Comparison::confusion_in`]).
    pub confusion: [[u64; 3]; 3],
    /// U: the clip box if one was given, else the smallest key box holding every known voxel
    /// of either map (`None` if both are empty).
    pub universe: Option<VoxelBox>,
    /// The value pairs of the voxels known in both maps, sorted by their bit patterns.
    pub pairs: Vec<ValuePair>,
}

impl Comparison {
    /// The confusion matrix with the unknown/unknown cell filled in as the rest of a
    /// universe of `voxels` voxels.
    pub fn confusion_in(&self, voxels: u64) -> [[u64; 3]; 3] {
        let mut m = self.confusion;
        let known: u64 = m.iter().flatten().sum();
        m[UNKNOWN][UNKNOWN] = voxels.saturating_sub(known);
        m
    }
}

/// Slots of the direct-mapped front of the histogram (a power of two).
const SLOTS: usize = 1024;

/// Voxel counts per packed (first bits, second bits) pair: a direct-mapped table of
/// `(key, count)` in front of a hash map (maps hold few distinct values, so nearly every
/// update is one multiply and one add).
struct Histogram {
    slots: Vec<(u64, u64)>,
    spill: HashMap<u64, u64, BuildHasherDefault<U64Hasher>>,
}

impl Histogram {
    fn new() -> Self {
        Self {
            slots: vec![(0, 0); SLOTS],
            spill: HashMap::default(),
        }
    }

    #[inline]
    fn add(&mut self, key: u64, w: u64) {
        let h = (key.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 54) as usize & (SLOTS - 1);
        if let Some(slot) = self.slots.get_mut(h) {
            if slot.0 == key {
                slot.1 += w;
                return;
            }
            if slot.1 > 0 {
                *self.spill.entry(slot.0).or_insert(0) += slot.1;
            }
            *slot = (key, w);
        }
    }

    fn into_pairs(mut self) -> Vec<ValuePair> {
        for &(k, n) in &self.slots {
            if n > 0 {
                *self.spill.entry(k).or_insert(0) += n;
            }
        }
        let mut keys: Vec<(u64, u64)> = self.spill.into_iter().collect();
        keys.sort_unstable();
        keys.into_iter()
            .map(|(k, voxels)| ValuePair {
                reference: f32::from_bits((k >> 32) as u32),
                target: f32::from_bits(k as u32),
                voxels,
            })
            .collect()
    }
}

/// Voxels of a leaf inside U: `(Morton start, voxel count) -> count in U`.
trait Weight: Copy {
    fn of(self, start: u64, size: u64) -> u64;
}

/// No clipping: the default box holds every known voxel.
#[derive(Clone, Copy)]
struct Whole;

impl Weight for Whole {
    #[inline]
    fn of(self, _: u64, size: u64) -> u64 {
        size
    }
}

/// Clipping to a caller's box.
#[derive(Clone, Copy)]
struct Clip(VoxelBox);

impl Weight for Clip {
    #[inline]
    fn of(self, start: u64, size: u64) -> u64 {
        let lo = unmorton(start);
        let d = (1u32 << (size.trailing_zeros() / 3)) - 1;
        self.0
            .overlap(lo, lo.map(|k| (u32::from(k) + d).min(65535) as u16))
    }
}

/// Occupied and free voxels of one map inside U.
fn known_in<W: Weight>(map: &LeafMap, w: W) -> [u64; 2] {
    let (codes, values) = map.raw();
    let t = map.model().occupancy_threshold;
    let mut known = [0u64; 2];
    for (&c, &v) in codes.iter().zip(values) {
        let (start, size) = split_code(c);
        known[usize::from(v < t)] += w.of(start, size);
    }
    known
}

/// The nested overlaps of the two leaf lists, into the histogram.
fn overlaps<W: Weight>(a: &LeafMap, b: &LeafMap, w: W, hist: &mut Histogram) {
    let (ca, va) = a.raw();
    let (cb, vb) = b.raw();
    let (na, nb) = (ca.len().min(va.len()), cb.len().min(vb.len()));
    let (ca, va, cb, vb) = (&ca[..na], &va[..na], &cb[..nb], &vb[..nb]);
    let (mut i, mut j) = (0usize, 0usize);
    while i < na && j < nb {
        let (sa, za) = split_code(ca[i]);
        let (sb, zb) = split_code(cb[j]);
        if sa + za <= sb {
            i += 1;
        } else if sb + zb <= sa {
            j += 1;
        } else {
            // Octree intervals overlap only when nested: the smaller one is the overlap.
            let n = if za <= zb { w.of(sa, za) } else { w.of(sb, zb) };
            if n > 0 {
                hist.add(
                    (u64::from(va[i].to_bits()) << 32) | u64::from(vb[j].to_bits()),
                    n,
                );
            }
            i += usize::from(za <= zb);
            j += usize::from(zb <= za);
        }
    }
}

/// Merges the leaves of `a` and `b` (`roles` name them in errors): the confusion matrix over
/// U (without unknown/unknown) and the value pairs of the voxels known in both.
///
/// With `clip`, U is that box and leaves are clipped to it; without, U is the bounding box of
/// every known voxel of either map. Time is linear in the two leaf counts.
pub fn compare(
    a: &LeafMap,
    b: &LeafMap,
    clip: Option<VoxelBox>,
    roles: [Role; 2],
) -> Result<Comparison, EvalError> {
    for (map, role) in [(a, roles[0]), (b, roles[1])] {
        if let Some(value) = map.non_finite() {
            return Err(EvalError::NonFinite { role, value });
        }
    }
    let mut hist = Histogram::new();
    let (ka, kb) = match clip {
        None => {
            overlaps(a, b, Whole, &mut hist);
            (
                [a.occupied_voxels(), a.free_voxels()],
                [b.occupied_voxels(), b.free_voxels()],
            )
        }
        Some(c) => {
            overlaps(a, b, Clip(c), &mut hist);
            (known_in(a, Clip(c)), known_in(b, Clip(c)))
        }
    };
    let pairs = hist.into_pairs();
    let (ta, tb) = (a.model().occupancy_threshold, b.model().occupancy_threshold);
    let state = |v: f32, t: f32| if v >= t { OCCUPIED } else { FREE };
    let mut m = [[0u64; 3]; 3];
    for p in &pairs {
        m[state(p.reference, ta)][state(p.target, tb)] += p.voxels;
    }
    for s in [OCCUPIED, FREE] {
        m[s][UNKNOWN] = ka[s].saturating_sub(m[s][OCCUPIED] + m[s][FREE]);
        m[UNKNOWN][s] = kb[s].saturating_sub(m[OCCUPIED][s] + m[FREE][s]);
    }
    let universe = match clip {
        Some(c) => Some(c),
        None => match (a.bounds(), b.bounds()) {
            (Some(p), Some(q)) => Some(VoxelBox {
                min: [0, 1, 2].map(|i| p.min[i].min(q.min[i])),
                max: [0, 1, 2].map(|i| p.max[i].max(q.max[i])),
            }),
            (p, q) => p.or(q),
        },
    };
    Ok(Comparison {
        confusion: m,
        universe,
        pairs,
    })
}
