//! OctoMap's exact ray stepping (`computeRayKeys`, research/octomap.md §3): a 3D DDA over
//! voxel keys in OctoMap's f32/f64 mix, origin voxel included, end voxel excluded, ties to z then y.

use std::hint::select_unpredictable;

use super::key::{Key, Resolution};

/// Visits the keys of the ray from `origin` to `end` in order, as `computeRayKeys` would push
/// them. Returns `false` (visiting nothing) when either point is outside the key range; an
/// origin and end in the same voxel give `true` and no keys.
#[inline]
pub fn ray_keys(
    res: &Resolution,
    origin: [f32; 3],
    end: [f32; 3],
    mut visit: impl FnMut(Key),
) -> bool {
    ray_packed(res, origin, end, |k| visit(unpack(k)))
}

/// Packs a key into the stepping loop's 21-bit biased fields.
#[inline]
pub(crate) fn pack(k: Key) -> u64 {
    (0..3).fold(0u64, |acc, i| {
        acc | ((u64::from(k.0[i]) + BIAS) << (21 * i))
    })
}

/// The u16 key of packed fields (wrapping like OctoMap's u16 keys).
#[inline]
pub(crate) fn unpack(k: u64) -> Key {
    Key([0, 1, 2].map(|i| ((k >> (21 * i)) & FIELD).wrapping_sub(BIAS) as u16))
}

/// [`ray_keys`] with keys in the packed form of [`pack`].
#[inline(always)]
pub(crate) fn ray_packed(
    res: &Resolution,
    origin: [f32; 3],
    end: [f32; 3],
    visit: impl FnMut(u64),
) -> bool {
    let (Some(key_origin), Some(key_end)) = (res.coord_to_key(origin), res.coord_to_key(end))
    else {
        return false;
    };
    ray_packed_keyed(res, origin, key_origin, end, key_end, visit);
    true
}

/// The stepping of [`ray_packed`] once both keys are known to be in range.
#[inline(always)]
pub(crate) fn ray_packed_keyed(
    res: &Resolution,
    origin: [f32; 3],
    key_origin: Key,
    end: [f32; 3],
    key_end: Key,
    mut visit: impl FnMut(u64),
) {
    let Some(mut ray) = RayStepper::new(res, origin, key_origin, end, key_end) else {
        return;
    };
    visit(pack(key_origin));
    while let Some(k) = ray.step() {
        visit(k);
    }
}

/// One ray of OctoMap's stepping loop as a resumable state, so that several rays can be
/// stepped interleaved (their dependency chains then overlap in the CPU).
///
/// [`RayStepper::step`] yields the keys after the origin key, which the caller handles.
#[derive(Clone, Copy)]
pub(crate) struct RayStepper {
    t: [f64; 3],
    d: [f64; 3],
    inc: [u64; 3],
    k: u64,
    end: u64,
    length: f64,
}

impl RayStepper {
    /// The per-ray constants of `computeRayKeys` (steps 4 and 5), or `None` when the origin
    /// and end keys are equal (an empty ray).
    #[inline(always)]
    pub(crate) fn new(
        res: &Resolution,
        origin: [f32; 3],
        key_origin: Key,
        end: [f32; 3],
        key_end: Key,
    ) -> Option<Self> {
        if key_origin == key_end {
            return None;
        }
        let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        // Vector3::norm(): squares summed in f32, sqrt in f64, then cast to float.
        let length = f64::from(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() as f32;
        let dir = [d[0] / length, d[1] / length, d[2] / length];

        let r = res.meters();
        let mut t = [f64::MAX; 3];
        let mut dt = [f64::MAX; 3];
        let mut inc = [0u64; 3];
        for i in 0..3 {
            let step: i32 = if dir[i] > 0.0 {
                1
            } else if dir[i] < 0.0 {
                -1
            } else {
                0
            };
            if step != 0 {
                let half = (f64::from(step) * r * 0.5) as f32;
                let border = res.key_to_coord_axis(key_origin.0[i]) + f64::from(half);
                t[i] = (border - f64::from(origin[i])) / f64::from(dir[i]);
                dt[i] = r / f64::from(dir[i].abs());
            }
            // The three keys live in one u64 as 21-bit fields biased by 2^17, so a step is
            // one add and the end test one compare; keys wrap to u16 like OctoMap's on unpack.
            inc[i] = (i64::from(step) << (21 * i)) as u64;
        }
        Some(Self {
            t,
            d: dt,
            inc,
            k: pack(key_origin),
            end: pack(key_end),
            length: f64::from(length),
        })
    }

    /// One iteration of the loop: the next key, or `None` when the ray is done (it reached
    /// the end key, or every `tMax` is beyond the length). Branch-free in the axis choice
    /// (ties: z, then y).
    #[inline(always)]
    pub(crate) fn step(&mut self) -> Option<u64> {
        let [t0, t1, t2] = self.t;
        let x_lt_y = t0 < t1;
        let cx = x_lt_y & (t0 < t2);
        let cy = !x_lt_y & (t1 < t2);
        let cz = !(cx | cy);
        // Selects, not branches: the axis choice is unpredictable.
        let t0 = t0 + select_unpredictable(cx, self.d[0], 0.0);
        let t1 = t1 + select_unpredictable(cy, self.d[1], 0.0);
        let t2 = t2 + select_unpredictable(cz, self.d[2], 0.0);
        self.t = [t0, t1, t2];
        let inc = select_unpredictable(cy, self.inc[1], self.inc[2]);
        self.k = self
            .k
            .wrapping_add(select_unpredictable(cx, self.inc[0], inc));
        // std::min(std::min(t0, t1), t2)
        let m = if t1 < t0 { t1 } else { t0 };
        let m = if t2 < m { t2 } else { m };
        if (self.k == self.end) | (m > self.length) {
            return None;
        }
        Some(self.k)
    }
}

/// Bias and mask of the packed 21-bit key fields of the stepping loop.
pub(crate) const BIAS: u64 = 1 << 17;
pub(crate) const FIELD: u64 = (1 << 21) - 1;

#[cfg(test)]
mod tests {
    use super::*;

    /// A line-by-line transcription of OctoMap's `computeRayKeys` loop, to check the packed,
    /// branch-free loop against.
    fn reference(res: &Resolution, origin: [f32; 3], end: [f32; 3]) -> Option<Vec<Key>> {
        let ko = res.coord_to_key(origin)?;
        let ke = res.coord_to_key(end)?;
        let mut ray = Vec::new();
        if ko == ke {
            return Some(ray);
        }
        ray.push(ko);
        let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        let length = f64::from(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() as f32;
        let dir = d.map(|c| c / length);
        let r = res.meters();
        let (mut step, mut t_max, mut t_delta) = ([0i32; 3], [f64::MAX; 3], [f64::MAX; 3]);
        for i in 0..3 {
            step[i] = if dir[i] > 0.0 {
                1
            } else if dir[i] < 0.0 {
                -1
            } else {
                0
            };
            if step[i] != 0 {
                let mut border = res.key_to_coord_axis(ko.0[i]);
                border += f64::from((f64::from(step[i]) * r * 0.5) as f32);
                t_max[i] = (border - f64::from(origin[i])) / f64::from(dir[i]);
                t_delta[i] = r / f64::from(dir[i].abs());
            }
        }
        let mut key = ko.0;
        loop {
            let dim = if t_max[0] < t_max[1] {
                if t_max[0] < t_max[2] { 0 } else { 2 }
            } else if t_max[1] < t_max[2] {
                1
            } else {
                2
            };
            key[dim] = key[dim].wrapping_add(step[dim] as u16);
            t_max[dim] += t_delta[dim];
            if key == ke.0 {
                break;
            }
            if t_max[0].min(t_max[1]).min(t_max[2]) > f64::from(length) {
                break;
            }
            ray.push(Key(key));
        }
        Some(ray)
    }

    #[test]
    fn fast_loop_equals_the_transcription_on_many_rays() {
        // Deterministic pseudo-random rays, many from voxel centers and on grid lines (ties).
        let mut s = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for res in [0.05, 0.1, 0.07, 0.2, 1.0] {
            let r = Resolution::new(res).unwrap();
            for i in 0..20_000 {
                let mut pt = |grid: bool| {
                    [0; 3].map(|_| {
                        let v = (rnd() % 4000) as f32 / 100.0 - 20.0;
                        if grid {
                            (v * 4.0).round() / 4.0 * res as f32
                        } else {
                            v
                        }
                    })
                };
                let (o, e) = (pt(i % 3 == 0), pt(i % 5 == 0));
                let mut fast = Vec::new();
                let ok = ray_keys(&r, o, e, |k| fast.push(k));
                assert_eq!(
                    reference(&r, o, e),
                    ok.then_some(fast),
                    "res {res} {o:?} -> {e:?}"
                );
            }
        }
    }

    fn keys(res: f64, o: [f32; 3], e: [f32; 3]) -> Option<Vec<[i32; 3]>> {
        let r = Resolution::new(res).unwrap();
        let mut v = Vec::new();
        ray_keys(&r, o, e, |k| v.push(k.0.map(|a| i32::from(a) - 32768))).then_some(v)
    }

    #[test]
    fn probe_example_from_the_notes() {
        // research/octomap.md §3: 15 keys, the last (9,3,-2); the end voxel (10,3,-3) excluded.
        let v = keys(0.1, [0.05, 0.05, 0.05], [1.0, 0.33, -0.2]).unwrap();
        assert_eq!(v.len(), 15);
        assert_eq!(v[0], [0, 0, 0]);
        assert_eq!(v[14], [9, 3, -2]);
        assert!(!v.contains(&[10, 3, -3]));
        // Each step moves one voxel along one axis.
        for w in v.windows(2) {
            let d: i32 = (0..3).map(|i| (w[1][i] - w[0][i]).abs()).sum();
            assert_eq!(d, 1);
        }
    }

    #[test]
    fn exact_diagonal_ties_go_to_z_then_y() {
        // From a voxel center along (1,1,1): all three borders are hit at the same t.
        let v = keys(0.1, [0.05, 0.05, 0.05], [0.35, 0.35, 0.35]).unwrap();
        assert_eq!(&v[..4], &[[0, 0, 0], [0, 0, 1], [0, 1, 1], [1, 1, 1]]);
        assert_eq!(&v[4..7], &[[1, 1, 2], [1, 2, 2], [2, 2, 2]]);
        // Tie between x and y only (z constant): y first.
        let v = keys(0.5, [0.25, 0.25, 0.25], [1.25, 1.25, 0.25]).unwrap();
        assert_eq!(v, vec![[0, 0, 0], [0, 1, 0], [1, 1, 0], [1, 2, 0]]);
    }

    #[test]
    fn same_voxel_and_out_of_bounds() {
        assert_eq!(
            keys(0.1, [0.01, 0.01, 0.01], [0.09, 0.02, 0.03]),
            Some(vec![])
        );
        assert_eq!(keys(0.1, [0.0, 0.0, 0.0], [4000.0, 0.0, 0.0]), None);
        assert_eq!(keys(0.1, [-4000.0, 0.0, 0.0], [0.0, 0.0, 0.0]), None);
        // Axis-aligned: origin voxel in, end voxel out.
        assert_eq!(
            keys(1.0, [0.5, 0.5, 0.5], [3.5, 0.5, 0.5]),
            Some(vec![[0, 0, 0], [1, 0, 0], [2, 0, 0]])
        );
        assert_eq!(
            keys(1.0, [0.5, 0.5, 0.5], [-1.5, 0.5, 0.5]),
            Some(vec![[0, 0, 0], [-1, 0, 0]])
        );
    }
}
