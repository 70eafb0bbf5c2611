//! OctoMap's exact ray stepping (`computeRayKeys`, research/octomap.md §3): a 3D DDA over
//! voxel keys in OctoMap's f32/f64 mix, origin voxel included, end voxel excluded, ties to z then y.
//!
//! **Degenerate rays (a deviation from OctoMap).** A ray whose origin and end keys differ but
//! whose f32 length `(float)sqrt((double)(x²+y²+z²))` is 0 (the squares underflow, e.g. from
//! (0,0,0) to (−1e-30, −1e-30, 0)) or infinite (they overflow, possible only at resolutions
//! above ~1.6e14 m) has no usable direction: OctoMap 1.9.7 fails an assertion there, and with
//! `-DNDEBUG` its loop never ends. Every kernel here refuses such a ray before stepping it, as
//! if `computeRayKeys` had returned false: none of its keys (not even the origin voxel's) is
//! marked, the endpoint still gets its hit like any point whose ray cannot be cast, and
//! insertion counts it ([`crate::octree::InsertStats::degenerate_rays`]). No ray with a finite
//! positive length is affected, so maps stay byte-identical to OctoMap's wherever OctoMap
//! finishes.
//!
//! **Kernels.** With AVX-512F (x86-64), rays are stepped eight per vector, with AVX2 four;
//! otherwise in scalar pairs. [`Kernel`] picks one explicitly (tests run all of them on the
//! same machine, each where the CPU has it); `SCAN3D_OCTREE_KERNEL=scalar` (or `avx2`) forces
//! the narrower kernels process-wide.

use std::hint::select_unpredictable;
use std::sync::OnceLock;

use super::key::{Key, Resolution};

/// Which implementation of the insertion kernels (ray stepping, and point-to-key conversion
/// without a max range) runs. All give exactly the same keys.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kernel {
    /// Portable scalar code (rays stepped in interleaved pairs).
    Scalar,
    /// Four rays (or points) per AVX2 vector where the CPU has AVX2 (checked at each
    /// insertion); the scalar kernels elsewhere.
    Avx2,
    /// Eight rays per AVX-512 vector where the CPU has AVX-512F, points four per AVX2 vector;
    /// [`Kernel::Avx2`]'s kernels on a CPU with AVX2 only, the scalar ones elsewhere.
    Avx512,
}

/// The environment variable that picks the kernels (`SCAN3D_OCTREE_KERNEL=scalar`, `avx2`,
/// `avx512` or `auto`).
pub const KERNEL_ENV: &str = "SCAN3D_OCTREE_KERNEL";

impl Kernel {
    /// The process default: [`Kernel::Scalar`] if `SCAN3D_OCTREE_KERNEL=scalar`,
    /// [`Kernel::Avx2`] if `avx2`, else [`Kernel::Avx512`] (the widest the CPU has; `avx512`
    /// or `auto` say so explicitly). The variable is read once; any other value is reported
    /// with a warning and ignored.
    pub fn from_env() -> Self {
        static KERNEL: OnceLock<Kernel> = OnceLock::new();
        *KERNEL.get_or_init(|| {
            let unknown = |v: &dyn std::fmt::Debug| {
                tracing::warn!(
                    "{KERNEL_ENV}={v:?} is not scalar, avx2, avx512 or auto: using auto"
                );
                Kernel::Avx512
            };
            match std::env::var(KERNEL_ENV) {
                Ok(v) if v.eq_ignore_ascii_case("scalar") => Kernel::Scalar,
                Ok(v) if v.eq_ignore_ascii_case("avx2") => Kernel::Avx2,
                Ok(v) if v.eq_ignore_ascii_case("avx512") || v.eq_ignore_ascii_case("auto") => {
                    Kernel::Avx512
                }
                Err(std::env::VarError::NotPresent) => Kernel::Avx512,
                Ok(v) => unknown(&v),
                Err(std::env::VarError::NotUnicode(v)) => unknown(&v),
            }
        })
    }

    /// Whether this choice runs the AVX2 kernels (points to keys, and rays unless
    /// [`Kernel::uses_avx512`]) on this CPU.
    #[inline]
    pub(crate) fn uses_avx2(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self != Kernel::Scalar {
            return std::arch::is_x86_feature_detected!("avx2");
        }
        false
    }

    /// Whether this choice steps rays with the AVX-512 kernel on this CPU.
    #[inline]
    pub(crate) fn uses_avx512(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self == Kernel::Avx512 {
            return std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("popcnt");
        }
        false
    }
}

impl Default for Kernel {
    /// [`Kernel::from_env`].
    fn default() -> Self {
        Self::from_env()
    }
}

/// The f32 length `computeRayKeys` divides by (`Vector3::norm()`: squares summed in f32, sqrt
/// in f64, cast to float), or `None` when it is 0 or not finite: a degenerate ray (module docs).
#[inline(always)]
pub(crate) fn ray_length(origin: [f32; 3], end: [f32; 3]) -> Option<f32> {
    let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
    let length = f64::from(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() as f32;
    (length > 0.0 && length < f32::INFINITY).then_some(length)
}

/// A ray [`RayStepper::new`] refused: its keys differ but its f32 length is 0 or not finite.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct DegenerateRay;

/// Visits the keys of the ray from `origin` to `end` in order, as `computeRayKeys` would push
/// them. Returns `false` (visiting nothing) when either point is outside the key range, or
/// when the ray is degenerate (module docs; OctoMap asserts there); an origin and end in the
/// same voxel give `true` and no keys.
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
    ray_packed_keyed(res, origin, key_origin, end, key_end, visit).is_ok()
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
) -> Result<(), DegenerateRay> {
    let Some(mut ray) = RayStepper::new(res, origin, key_origin, end, key_end)? else {
        return Ok(());
    };
    visit(pack(key_origin));
    while let Some(k) = ray.step() {
        visit(k);
    }
    Ok(())
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
    /// Steps taken, to catch a ray that would never end (debug builds only).
    #[cfg(debug_assertions)]
    steps: u32,
}

/// More steps than any ray between two in-range keys takes: each step moves one key field by
/// one towards the end voxel (at most 65 535 per axis), plus one past it per axis at the stop
/// rule. Debug builds assert it in every kernel, so a ray that cannot end fails loudly.
// Only `debug_assert!`s read it, which release builds compile out.
#[cfg_attr(not(debug_assertions), allow(dead_code))]
pub(crate) const MAX_RAY_STEPS: u32 = 3 * 65_536 + 3;

impl RayStepper {
    /// The per-ray constants of `computeRayKeys` (steps 4 and 5), `Ok(None)` when the origin
    /// and end keys are equal (an empty ray), or [`DegenerateRay`] when the keys differ but
    /// the f32 length is 0 or not finite (no direction: OctoMap's loop would never end).
    ///
    /// With a finite positive length every `tDelta` is at least `res / (1 + ε)` (each
    /// `|dir[i]| <= 1 + ε`) and each step advances a smallest `tMax`, so the loop ends after
    /// about `3 · length / res` steps at most.
    #[inline(always)]
    pub(crate) fn new(
        res: &Resolution,
        origin: [f32; 3],
        key_origin: Key,
        end: [f32; 3],
        key_end: Key,
    ) -> Result<Option<Self>, DegenerateRay> {
        if key_origin == key_end {
            return Ok(None);
        }
        let length = ray_length(origin, end).ok_or(DegenerateRay)?;
        let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
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
        Ok(Some(Self {
            t,
            d: dt,
            inc,
            k: pack(key_origin),
            end: pack(key_end),
            length: f64::from(length),
            #[cfg(debug_assertions)]
            steps: 0,
        }))
    }

    /// One iteration of the loop: the next key, or `None` when the ray is done (it reached
    /// the end key, or every `tMax` is beyond the length). Branch-free in the axis choice
    /// (ties: z, then y).
    #[inline(always)]
    pub(crate) fn step(&mut self) -> Option<u64> {
        #[cfg(debug_assertions)]
        {
            self.steps += 1;
            debug_assert!(self.steps <= MAX_RAY_STEPS, "a ray that does not end");
        }
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

/// Where [`mark_free`] puts the keys of rays: a dense window of 4×4×4-voxel bricks (one
/// 64-bit word of free marks per brick, bit `x + 4y + 16z` of the voxel inside the brick),
/// plus a way to mark keys outside it.
pub(crate) trait FreeMarks {
    /// The window's lowest brick in the brick fields of packed keys (each 21-bit field of a
    /// packed key shifted down by 2), and its size in bricks per axis. Cell `x + dx(y + dy z)`
    /// is the brick at window-relative coordinates (x, y, z).
    fn window(&self) -> (u64, [u32; 3]);
    /// ORs `bits` into the free word of window cell `cell` (always inside the window).
    fn mark_cell(&mut self, cell: u32, bits: u64);
    /// Marks one packed key free, wherever it is.
    fn mark_key(&mut self, key: u64);
}

/// Marks free every key of the rays from `origin` to each of `ends` (end point and its key)
/// after the origin key, which the caller marks. With [`Kernel::Avx2`] on an AVX2 CPU, rays
/// go four at a time, one per lane, from setup to end, and each lane gathers its marks per
/// brick before writing them (a ray crosses several voxels of a brick in a row); otherwise
/// rays step in scalar pairs. Both mark exactly the keys of `computeRayKeys`
/// ([`RayStepper::step`]) and skip degenerate rays; returns how many were skipped.
#[inline]
pub(crate) fn mark_free(
    kernel: Kernel,
    res: &Resolution,
    origin: [f32; 3],
    key_origin: Key,
    ends: impl Iterator<Item = ([f32; 3], Key)>,
    marks: &mut impl FreeMarks,
) -> u64 {
    if kernel.uses_avx512() {
        // SAFETY: `uses_avx512` checked that the CPU supports AVX-512F, the only requirement
        // of `avx512::mark_free`'s `#[target_feature]`.
        #[cfg(target_arch = "x86_64")]
        return unsafe { avx512::mark_free(res, origin, key_origin, ends, marks) };
    }
    if kernel.uses_avx2() {
        // SAFETY: `uses_avx2` checked that the CPU supports AVX2, the only requirement of
        // `avx2::mark_free`'s `#[target_feature]`.
        #[cfg(target_arch = "x86_64")]
        return unsafe { avx2::mark_free(res, origin, key_origin, ends, marks) };
    }
    let mut degenerate = 0;
    let rays = ends.filter_map(|(end, key_end)| {
        RayStepper::new(res, origin, key_origin, end, key_end)
            .inspect_err(|_| degenerate += 1)
            .ok()
            .flatten()
    });
    step_rays_pairs(rays, |_, k| marks.mark_key(k));
    degenerate
}

/// Steps every ray of `rays` and calls `visit(n, key)` with the ray's position `n` in `rays`
/// and each packed key after its origin key, in order per ray. Rays go in pairs, interleaved,
/// so that their loop-carried dependency chains overlap.
pub(crate) fn step_rays_pairs(
    rays: impl Iterator<Item = RayStepper>,
    mut visit: impl FnMut(usize, u64),
) {
    let mut rays = rays.enumerate();
    while let Some((na, mut a)) = rays.next() {
        let Some((nb, mut b)) = rays.next() else {
            while let Some(k) = a.step() {
                visit(na, k);
            }
            break;
        };
        loop {
            match (a.step(), b.step()) {
                (Some(ka), Some(kb)) => {
                    visit(na, ka);
                    visit(nb, kb);
                }
                (Some(ka), None) => {
                    visit(na, ka);
                    while let Some(k) = a.step() {
                        visit(na, k);
                    }
                    break;
                }
                (None, Some(kb)) => {
                    visit(nb, kb);
                    while let Some(k) = b.step() {
                        visit(nb, k);
                    }
                    break;
                }
                (None, None) => break,
            }
        }
    }
}

/// Four rays per AVX2 vector, one per lane, set up and stepped together until all four end.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{FIELD, FreeMarks, Key, Resolution, pack};

    /// Brick part of a packed key (see `voxels`): each 21-bit field shifted down by 2.
    const PACKED_BRICK: i64 = ((FIELD >> 2) | ((FIELD >> 2) << 21) | ((FIELD >> 2) << 42)) as i64;
    /// Capacity of the buffer of gathered (cell, marks) pairs written in batches.
    const PENDING: usize = 256;

    /// Per 4-bit lane mask, the 32-bit permutation moving the 64-bit lanes set in the mask to
    /// the front, in order.
    const COMPRESS: [[i32; 8]; 16] = {
        let mut t = [[0i32; 8]; 16];
        let mut m = 0;
        while m < 16 {
            let mut j = 0;
            let mut l = 0;
            while l < 4 {
                if m & (1 << l) != 0 {
                    t[m][2 * j] = 2 * l;
                    t[m][2 * j + 1] = 2 * l + 1;
                    j += 1;
                }
                l += 1;
            }
            m += 1;
        }
        t
    };

    #[target_feature(enable = "avx2")]
    fn epi_lanes(v: __m256i) -> [u64; 4] {
        [
            _mm256_extract_epi64::<0>(v) as u64,
            _mm256_extract_epi64::<1>(v) as u64,
            _mm256_extract_epi64::<2>(v) as u64,
            _mm256_extract_epi64::<3>(v) as u64,
        ]
    }

    /// Gathered marks waiting to be written, appended without branches.
    struct Pending {
        cell: [u64; PENDING],
        bits: [u64; PENDING],
        n: usize,
    }

    impl Pending {
        /// Appends the lanes of `cell`/`bits` whose bit is set in `lanes`: they are moved to
        /// the front (a permutation from [`COMPRESS`]) and all four stored with one vector
        /// store each, so the only serial dependency is the count. Needs `n <= PENDING - 4`.
        #[target_feature(enable = "avx2")]
        fn push(&mut self, cell: __m256i, bits: __m256i, lanes: u32) {
            debug_assert!(lanes < 16, "lane mask {lanes:#x} has more than 4 lanes");
            // Otherwise the checked slices below are None and the marks would be lost.
            debug_assert!(
                self.n + 4 <= PENDING,
                "pending buffer not drained: {} of {PENDING}",
                self.n
            );
            let p = COMPRESS[(lanes & 15) as usize];
            let idx = _mm256_setr_epi32(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]);
            let n = self.n;
            if let (Some(c), Some(b)) = (self.cell.get_mut(n..n + 4), self.bits.get_mut(n..n + 4)) {
                // SAFETY: `c` and `b` are 4 u64s each, the 32 bytes the unaligned stores write.
                unsafe {
                    _mm256_storeu_si256(
                        c.as_mut_ptr().cast(),
                        _mm256_permutevar8x32_epi32(cell, idx),
                    );
                    _mm256_storeu_si256(
                        b.as_mut_ptr().cast(),
                        _mm256_permutevar8x32_epi32(bits, idx),
                    );
                }
                self.n = n + lanes.count_ones() as usize;
            }
        }

        fn drain(&mut self, marks: &mut impl FreeMarks) {
            let (_, [dx, dy, dz]) = marks.window();
            let cells = u64::from(dx) * u64::from(dy) * u64::from(dz);
            for (&c, &b) in self.cell.iter().zip(&self.bits).take(self.n) {
                // Only lanes inside the window (with marks) are pushed: the vector cell index
                // (32-bit multiplies) must then be a cell of the window.
                debug_assert!(c < cells, "cell {c} outside a window of {cells} cells");
                debug_assert!(b != 0, "a pending entry without marks");
                marks.mark_cell(c as u32, b);
            }
            self.n = 0;
        }
    }

    // The unaligned stores of `Pending::push` write four u64s: 32 bytes, one __m256i.
    const _: () = assert!(size_of::<[u64; 4]>() == size_of::<__m256i>());

    #[target_feature(enable = "avx2")]
    pub(super) fn mark_free(
        res: &Resolution,
        origin: [f32; 3],
        key_origin: Key,
        ends: impl Iterator<Item = ([f32; 3], Key)>,
        marks: &mut impl FreeMarks,
    ) -> u64 {
        let mut ends = ends;
        let mut degenerate = 0u64;
        // Per-axis setup constants shared by all rays (computeRayKeys step 5): the origin
        // voxel's borders on either side, `keyToCoord + (float)(±res/2)`, minus the origin.
        let r = res.meters();
        let half = f64::from((r * 0.5) as f32);
        let num = [0, 1, 2].map(|i| {
            let c = res.key_to_coord_axis(key_origin.0[i]);
            let o = f64::from(origin[i]);
            (
                _mm256_set1_pd((c + half) - o),
                _mm256_set1_pd((c + -half) - o),
            )
        });
        let o4 = [0, 1, 2].map(|i| _mm_set1_ps(origin[i]));
        let rv = _mm256_set1_pd(r);
        let max = _mm256_set1_pd(f64::MAX);
        let k0 = _mm256_set1_epi64x(pack(key_origin) as i64);

        let (lo, dim) = marks.window();
        // The cell index `x + dx (y + dy z)` is computed with 32-bit multiplies (mul_epu32) and
        // stored as u32: the window must have fewer than 2^32 cells, and its brick fields must
        // be those of packed keys (each 21-bit field, bias included, shifted down by 2).
        debug_assert!(
            dim.iter().map(|&d| u64::from(d)).product::<u64>() < 1 << 32,
            "window {dim:?} too large for u32 cells"
        );
        debug_assert!(
            lo & !(PACKED_BRICK as u64) == 0,
            "window origin {lo:#x} is not in packed brick fields"
        );
        let lo = _mm256_set1_epi64x(lo as i64);
        let [dx, dy, dz] = dim.map(|d| _mm256_set1_epi64x(i64::from(d)));
        let brick = _mm256_set1_epi64x(PACKED_BRICK);
        let field = _mm256_set1_epi64x(FIELD as i64);
        let one = _mm256_set1_epi64x(1);
        let zero = _mm256_setzero_si256();
        let mut pending = Pending {
            cell: [0; PENDING],
            bits: [0; PENDING],
            n: 0,
        };
        loop {
            // Four rays; lanes without one (or with an empty ray) start dead.
            let mut e = [[0f32; 4]; 3];
            let mut end = [0u64; 4];
            let mut live = 0u32;
            let mut any = false;
            for l in 0..4 {
                if let Some((p, k)) = ends.next() {
                    any = true;
                    for i in 0..3 {
                        e[i][l] = p[i];
                    }
                    end[l] = pack(k);
                    live |= u32::from(k != key_origin) << l;
                } else {
                    for i in 0..3 {
                        e[i][l] = origin[i];
                    }
                }
            }
            if !any {
                break;
            }
            if live == 0 {
                continue;
            }
            // computeRayKeys steps 4-5 in every lane, in the same f32/f64 operations.
            let d = [0, 1, 2]
                .map(|i| _mm_sub_ps(_mm_setr_ps(e[i][0], e[i][1], e[i][2], e[i][3]), o4[i]));
            let len2 = _mm_add_ps(
                _mm_add_ps(_mm_mul_ps(d[0], d[0]), _mm_mul_ps(d[1], d[1])),
                _mm_mul_ps(d[2], d[2]),
            );
            let length = _mm256_cvtps_pd(_mm256_cvtpd_ps(_mm256_sqrt_pd(_mm256_cvtps_pd(len2))));
            let length32 = _mm256_cvtpd_ps(length);
            // Degenerate rays (f32 length 0 or infinite, `ray_length`) would never end: their
            // lanes start dead and are counted. NaN cannot occur (finite coordinates).
            let usable = _mm_movemask_ps(_mm_and_ps(
                _mm_cmpgt_ps(length32, _mm_setzero_ps()),
                _mm_cmplt_ps(length32, _mm_set1_ps(f32::INFINITY)),
            )) as u32;
            degenerate += u64::from((live & !usable).count_ones());
            live &= usable;
            if live == 0 {
                continue;
            }
            let mut t = [max; 3];
            let mut dt = [max; 3];
            let mut inc = [zero; 3];
            for i in 0..3 {
                let dir = _mm256_cvtps_pd(_mm_div_ps(d[i], length32));
                let pos = _mm256_cmp_pd::<_CMP_GT_OQ>(dir, _mm256_setzero_pd());
                let neg = _mm256_cmp_pd::<_CMP_LT_OQ>(dir, _mm256_setzero_pd());
                let moving = _mm256_or_pd(pos, neg);
                let n = _mm256_blendv_pd(num[i].1, num[i].0, pos);
                let absdir = _mm256_andnot_pd(_mm256_set1_pd(-0.0), dir);
                t[i] = _mm256_blendv_pd(max, _mm256_div_pd(n, dir), moving);
                dt[i] = _mm256_blendv_pd(max, _mm256_div_pd(rv, absdir), moving);
                let unit = _mm256_set1_epi64x(1i64 << (21 * i));
                // +unit where dir > 0, -unit where dir < 0.
                inc[i] = _mm256_sub_epi64(
                    _mm256_and_si256(_mm256_castpd_si256(pos), unit),
                    _mm256_and_si256(_mm256_castpd_si256(neg), unit),
                );
            }
            let end =
                _mm256_setr_epi64x(end[0] as i64, end[1] as i64, end[2] as i64, end[3] as i64);
            let mut live_v = _mm256_setr_epi64x(
                -i64::from(live & 1),
                -i64::from((live >> 1) & 1),
                -i64::from((live >> 2) & 1),
                -i64::from((live >> 3) & 1),
            );
            let [mut t0, mut t1, mut t2] = t;
            let mut k = k0;
            // Per lane: the window cell being gathered and its marks so far (0: none).
            let mut cur_cell = _mm256_set1_epi64x(-1);
            let mut cur_bits = zero;
            #[cfg(debug_assertions)]
            let mut steps = 0u32;
            loop {
                #[cfg(debug_assertions)]
                {
                    steps += 1;
                    debug_assert!(steps <= super::MAX_RAY_STEPS, "a ray that does not end");
                }
                // RayStepper::step in every lane: the axis of the smallest t (ties: z, then y).
                let c01 = _mm256_cmp_pd::<_CMP_LT_OQ>(t0, t1);
                let cx = _mm256_and_pd(c01, _mm256_cmp_pd::<_CMP_LT_OQ>(t0, t2));
                let cy = _mm256_andnot_pd(c01, _mm256_cmp_pd::<_CMP_LT_OQ>(t1, t2));
                let cxy = _mm256_or_pd(cx, cy);
                t0 = _mm256_add_pd(t0, _mm256_and_pd(cx, dt[0]));
                t1 = _mm256_add_pd(t1, _mm256_and_pd(cy, dt[1]));
                t2 = _mm256_add_pd(t2, _mm256_andnot_pd(cxy, dt[2]));
                let (ix, iy, ixy) = (
                    _mm256_castpd_si256(cx),
                    _mm256_castpd_si256(cy),
                    _mm256_castpd_si256(cxy),
                );
                let step = _mm256_or_si256(
                    _mm256_or_si256(_mm256_and_si256(ix, inc[0]), _mm256_and_si256(iy, inc[1])),
                    _mm256_andnot_si256(ixy, inc[2]),
                );
                k = _mm256_add_epi64(k, step);
                // min_pd(a, b) is `a < b ? a : b`, i.e. std::min(std::min(t0, t1), t2).
                let m = _mm256_min_pd(t2, _mm256_min_pd(t1, t0));
                let done = _mm256_or_si256(
                    _mm256_cmpeq_epi64(k, end),
                    _mm256_castpd_si256(_mm256_cmp_pd::<_CMP_GT_OQ>(m, length)),
                );
                // Lanes with a key to mark this step; a lane once done stays done.
                live_v = _mm256_andnot_si256(done, live_v);
                let go = live_v;

                // The key's window cell and its bit in the brick (as `voxels::Scratch::mark`);
                // a field below the window wraps to a huge value and fails its test.
                let r = _mm256_sub_epi64(_mm256_and_si256(_mm256_srli_epi64::<2>(k), brick), lo);
                let x = _mm256_and_si256(r, field);
                let y = _mm256_and_si256(_mm256_srli_epi64::<21>(r), field);
                let z = _mm256_srli_epi64::<42>(r);
                let inside = _mm256_and_si256(
                    _mm256_and_si256(_mm256_cmpgt_epi64(dx, x), _mm256_cmpgt_epi64(dy, y)),
                    _mm256_cmpgt_epi64(dz, z),
                );
                let cell = _mm256_add_epi64(
                    x,
                    _mm256_mul_epu32(dx, _mm256_add_epi64(y, _mm256_mul_epu32(dy, z))),
                );
                let lin = _mm256_or_si256(
                    _mm256_or_si256(
                        _mm256_and_si256(k, _mm256_set1_epi64x(3)),
                        _mm256_and_si256(_mm256_srli_epi64::<19>(k), _mm256_set1_epi64x(0xc)),
                    ),
                    _mm256_and_si256(_mm256_srli_epi64::<38>(k), _mm256_set1_epi64x(0x30)),
                );
                let bit = _mm256_sllv_epi64(one, lin);
                let fast = _mm256_and_si256(go, inside);
                let same = _mm256_cmpeq_epi64(cell, cur_cell);
                // A lane leaving its cell writes the marks gathered there.
                let flush = _mm256_andnot_si256(
                    _mm256_or_si256(same, _mm256_cmpeq_epi64(cur_bits, zero)),
                    fast,
                );
                pending.push(
                    cur_cell,
                    cur_bits,
                    _mm256_movemask_pd(_mm256_castsi256_pd(flush)) as u32,
                );
                let gathered = _mm256_or_si256(_mm256_and_si256(same, cur_bits), bit);
                cur_bits = _mm256_blendv_epi8(cur_bits, gathered, fast);
                cur_cell = _mm256_blendv_epi8(cur_cell, cell, fast);
                let slow = _mm256_movemask_pd(_mm256_castsi256_pd(_mm256_andnot_si256(inside, go)));
                if slow != 0 {
                    let kk = epi_lanes(k);
                    for (l, &key) in kk.iter().enumerate() {
                        if slow & (1 << l) != 0 {
                            marks.mark_key(key);
                        }
                    }
                }
                if pending.n > PENDING - 8 {
                    pending.drain(marks);
                }
                if _mm256_testz_si256(go, go) != 0 {
                    break;
                }
            }
            let rest = _mm256_xor_si256(_mm256_cmpeq_epi64(cur_bits, zero), _mm256_set1_epi64x(-1));
            pending.push(
                cur_cell,
                cur_bits,
                _mm256_movemask_pd(_mm256_castsi256_pd(rest)) as u32,
            );
            if pending.n > PENDING - 8 {
                pending.drain(marks);
            }
        }
        pending.drain(marks);
        degenerate
    }
}

/// Eight rays per AVX-512 vector, one per lane: [`avx2`]'s kernel with mask registers for the
/// lane choices and a compress for the gathered marks.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    use super::{FIELD, FreeMarks, Key, Resolution, pack};

    /// Brick part of a packed key (see `voxels`): each 21-bit field shifted down by 2.
    const PACKED_BRICK: i64 = ((FIELD >> 2) | ((FIELD >> 2) << 21) | ((FIELD >> 2) << 42)) as i64;
    /// Capacity of the buffers (entries).
    const PENDING: usize = 512;
    /// Steps of eight lanes between two emptyings of the buffers: each step adds at most
    /// eight entries to each, and a batch's end eight more to the gathered marks.
    const CHUNK_STEPS: usize = 31;
    /// Entries a buffer may hold at the start of a chunk so that the chunk and the batch's
    /// final push fit.
    const ROOM: usize = PENDING - 8 * (CHUNK_STEPS + 1);

    /// `K` parallel arrays of u64 entries: a push appends the lanes set in a mask,
    /// compressed to the front with one vector store per array; emptied in batches.
    struct Compressed<const K: usize> {
        entries: [[u64; PENDING]; K],
        n: usize,
    }

    impl<const K: usize> Compressed<K> {
        fn new() -> Self {
            Self {
                entries: [[0; PENDING]; K],
                n: 0,
            }
        }

        /// Appends the lanes of `values` (one vector per array) set in `lanes`. Needs
        /// `n <= PENDING - 8`.
        #[target_feature(enable = "avx512f,popcnt")]
        fn push(&mut self, values: [__m512i; K], lanes: __mmask8) {
            debug_assert!(
                self.n + 8 <= PENDING,
                "buffer not emptied: {} of {PENDING}",
                self.n
            );
            let n = self.n;
            if n + 8 > PENDING {
                return;
            }
            for (array, v) in self.entries.iter_mut().zip(values) {
                if let Some(to) = array.get_mut(n..n + 8) {
                    // SAFETY: `to` is 8 u64s, the 64 bytes the unaligned store writes.
                    unsafe {
                        _mm512_storeu_si512(
                            to.as_mut_ptr().cast(),
                            _mm512_maskz_compress_epi64(lanes, v),
                        );
                    }
                }
            }
            self.n = n + lanes.count_ones() as usize;
        }

        /// Whether fewer than a chunk's worth of entries are free.
        fn is_full(&self) -> bool {
            self.n > ROOM
        }

        /// Hands every entry (one value per array) to `f`, in order, and empties the buffer.
        fn drain(&mut self, mut f: impl FnMut([u64; K])) {
            for i in 0..self.n {
                f(std::array::from_fn(|a| self.entries[a][i]));
            }
            self.n = 0;
        }
    }

    /// Gathered marks: (window cell, free marks).
    type Pending = Compressed<2>;
    /// Packed keys outside the window, marked one by one.
    type Outside = Compressed<1>;

    /// Writes the gathered marks and the keys outside the window out.
    fn empty(pending: &mut Pending, outside: &mut Outside, marks: &mut impl FreeMarks) {
        let (_, [dx, dy, dz]) = marks.window();
        let cells = u64::from(dx) * u64::from(dy) * u64::from(dz);
        pending.drain(|[c, b]| {
            debug_assert!(c < cells, "cell {c} outside a window of {cells} cells");
            debug_assert!(b != 0, "a pending entry without marks");
            marks.mark_cell(c as u32, b);
        });
        outside.drain(|[k]| marks.mark_key(k));
    }

    /// [`empty`] when either buffer has less than a chunk's worth of room.
    fn make_room(pending: &mut Pending, outside: &mut Outside, marks: &mut impl FreeMarks) {
        if pending.is_full() || outside.is_full() {
            empty(pending, outside, marks);
        }
    }

    const _: () = assert!(size_of::<[u64; 8]>() == size_of::<__m512i>());

    /// [`super::avx2::mark_free`] eight lanes wide: the same operations per lane, so the same
    /// keys; see there for the steps.
    #[target_feature(enable = "avx512f,popcnt")]
    pub(super) fn mark_free(
        res: &Resolution,
        origin: [f32; 3],
        key_origin: Key,
        ends: impl Iterator<Item = ([f32; 3], Key)>,
        marks: &mut impl FreeMarks,
    ) -> u64 {
        let mut ends = ends;
        let mut degenerate = 0u64;
        let r = res.meters();
        let half = f64::from((r * 0.5) as f32);
        let num = [0, 1, 2].map(|i| {
            let c = res.key_to_coord_axis(key_origin.0[i]);
            let o = f64::from(origin[i]);
            (
                _mm512_set1_pd((c + half) - o),
                _mm512_set1_pd((c + -half) - o),
            )
        });
        let o8 = [0, 1, 2].map(|i| _mm256_set1_ps(origin[i]));
        let rv = _mm512_set1_pd(r);
        let max = _mm512_set1_pd(f64::MAX);
        let zero_pd = _mm512_setzero_pd();
        let k0 = _mm512_set1_epi64(pack(key_origin) as i64);

        let (lo, dim) = marks.window();
        debug_assert!(
            dim.iter().map(|&d| u64::from(d)).product::<u64>() < 1 << 32,
            "window {dim:?} too large for u32 cells"
        );
        debug_assert!(
            lo & !(PACKED_BRICK as u64) == 0,
            "window origin {lo:#x} is not in packed brick fields"
        );
        let window = Window {
            lo: _mm512_set1_epi64(lo as i64),
            dim: dim.map(|d| _mm512_set1_epi64(i64::from(d))),
            brick: _mm512_set1_epi64(PACKED_BRICK),
            field: _mm512_set1_epi64(FIELD as i64),
        };
        let zero = _mm512_setzero_si512();
        let mut pending = Pending::new();
        let mut outside = Outside::new();
        loop {
            let mut e = [[0f32; 8]; 3];
            let mut end = [0i64; 8];
            let mut live: u8 = 0;
            let mut any = false;
            for l in 0..8 {
                if let Some((p, k)) = ends.next() {
                    any = true;
                    for i in 0..3 {
                        e[i][l] = p[i];
                    }
                    end[l] = pack(k) as i64;
                    live |= u8::from(k != key_origin) << l;
                } else {
                    for i in 0..3 {
                        e[i][l] = origin[i];
                    }
                }
            }
            if !any {
                break;
            }
            if live == 0 {
                continue;
            }
            let d = [0, 1, 2].map(|i| {
                // SAFETY: `e[i]` is 8 f32s, the 32 bytes the unaligned load reads.
                _mm256_sub_ps(unsafe { _mm256_loadu_ps(e[i].as_ptr()) }, o8[i])
            });
            let len2 = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(d[0], d[0]), _mm256_mul_ps(d[1], d[1])),
                _mm256_mul_ps(d[2], d[2]),
            );
            let length32 = _mm512_cvtpd_ps(_mm512_sqrt_pd(_mm512_cvtps_pd(len2)));
            let length = _mm512_cvtps_pd(length32);
            let usable = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(length, zero_pd)
                & _mm512_cmp_pd_mask::<_CMP_LT_OQ>(length, _mm512_set1_pd(f64::INFINITY));
            degenerate += u64::from((live & !usable).count_ones());
            live &= usable;
            if live == 0 {
                continue;
            }
            let mut t = [max; 3];
            let mut dt = [max; 3];
            let mut inc = [zero; 3];
            for i in 0..3 {
                let dir = _mm512_cvtps_pd(_mm256_div_ps(d[i], length32));
                let pos = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(dir, zero_pd);
                let neg = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(dir, zero_pd);
                let moving = pos | neg;
                let n = _mm512_mask_blend_pd(pos, num[i].1, num[i].0);
                t[i] = _mm512_mask_div_pd(max, moving, n, dir);
                dt[i] = _mm512_mask_div_pd(max, moving, rv, _mm512_abs_pd(dir));
                let unit = _mm512_set1_epi64(1i64 << (21 * i));
                inc[i] = _mm512_mask_sub_epi64(_mm512_maskz_mov_epi64(pos, unit), neg, zero, unit);
            }
            // SAFETY: `end` is 8 i64s, the 64 bytes the unaligned load reads.
            let end = unsafe { _mm512_loadu_si512(end.as_ptr().cast()) };
            let mut rays = Rays {
                t,
                dt,
                inc,
                k: k0,
                end,
                length,
                cur_cell: _mm512_set1_epi64(-1),
                cur_bits: zero,
                live,
                #[cfg(debug_assertions)]
                steps: 0,
            };
            // Steps run in chunks with no call inside (`step_chunk`), and the buffers are
            // emptied between chunks: so the stepping state stays in registers, where a call
            // in the loop would spill all of it at every step.
            while step_chunk(&mut rays, &window, &mut pending, &mut outside) {
                make_room(&mut pending, &mut outside, marks);
            }
            make_room(&mut pending, &mut outside, marks);
            pending.push(
                [rays.cur_cell, rays.cur_bits],
                _mm512_test_epi64_mask(rays.cur_bits, rays.cur_bits),
            );
            make_room(&mut pending, &mut outside, marks);
        }
        empty(&mut pending, &mut outside, marks);
        degenerate
    }

    /// Eight rays being stepped, one per lane.
    struct Rays {
        t: [__m512d; 3],
        dt: [__m512d; 3],
        inc: [__m512i; 3],
        /// The current packed key.
        k: __m512i,
        end: __m512i,
        length: __m512d,
        /// The brick cell whose marks are being gathered (−1 before the first), and the marks.
        cur_cell: __m512i,
        cur_bits: __m512i,
        /// Lanes whose ray has not ended.
        live: __mmask8,
        #[cfg(debug_assertions)]
        steps: u32,
    }

    /// The window of bricks as vectors, and the constants of the cell arithmetic.
    struct Window {
        lo: __m512i,
        dim: [__m512i; 3],
        brick: __m512i,
        field: __m512i,
    }

    /// Up to [`CHUNK_STEPS`] steps of `rays`, their marks gathered into `pending` (inside the
    /// window) and `outside`, each of which must have room for them ([`make_room`]). Returns
    /// whether a ray is still live. Not inlined, and calls nothing: the state lives in
    /// registers for the chunk.
    #[inline(never)]
    #[target_feature(enable = "avx512f,popcnt")]
    fn step_chunk(
        rays: &mut Rays,
        window: &Window,
        pending: &mut Pending,
        outside: &mut Outside,
    ) -> bool {
        let Rays {
            t: [mut t0, mut t1, mut t2],
            dt,
            inc,
            mut k,
            end,
            length,
            mut cur_cell,
            mut cur_bits,
            mut live,
            ..
        } = *rays;
        let Window {
            lo,
            dim: [dx, dy, dz],
            brick,
            field,
        } = *window;
        let one = _mm512_set1_epi64(1);
        for _ in 0..CHUNK_STEPS {
            #[cfg(debug_assertions)]
            {
                rays.steps += 1;
                debug_assert!(
                    rays.steps <= super::MAX_RAY_STEPS,
                    "a ray that does not end"
                );
            }
            // The axis of the smallest t (ties: z, then y).
            let c01 = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(t0, t1);
            let cx = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(c01, t0, t2);
            let cy = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(!c01, t1, t2);
            let cz = !(cx | cy);
            t0 = _mm512_mask_add_pd(t0, cx, t0, dt[0]);
            t1 = _mm512_mask_add_pd(t1, cy, t1, dt[1]);
            t2 = _mm512_mask_add_pd(t2, cz, t2, dt[2]);
            let step =
                _mm512_mask_blend_epi64(cx, _mm512_mask_blend_epi64(cy, inc[2], inc[1]), inc[0]);
            k = _mm512_add_epi64(k, step);
            let m = _mm512_min_pd(t2, _mm512_min_pd(t1, t0));
            let done =
                _mm512_cmpeq_epi64_mask(k, end) | _mm512_cmp_pd_mask::<_CMP_GT_OQ>(m, length);
            live &= !done;
            let go = live;

            let r = _mm512_sub_epi64(_mm512_and_si512(_mm512_srli_epi64::<2>(k), brick), lo);
            let x = _mm512_and_si512(r, field);
            let y = _mm512_and_si512(_mm512_srli_epi64::<21>(r), field);
            let z = _mm512_srli_epi64::<42>(r);
            let inside = _mm512_mask_cmplt_epu64_mask(
                _mm512_mask_cmplt_epu64_mask(_mm512_cmplt_epu64_mask(x, dx), y, dy),
                z,
                dz,
            );
            let cell = _mm512_add_epi64(
                x,
                _mm512_mul_epu32(dx, _mm512_add_epi64(y, _mm512_mul_epu32(dy, z))),
            );
            let lin = _mm512_or_si512(
                _mm512_or_si512(
                    _mm512_and_si512(k, _mm512_set1_epi64(3)),
                    _mm512_and_si512(_mm512_srli_epi64::<19>(k), _mm512_set1_epi64(0xc)),
                ),
                _mm512_and_si512(_mm512_srli_epi64::<38>(k), _mm512_set1_epi64(0x30)),
            );
            let bit = _mm512_sllv_epi64(one, lin);
            let fast = go & inside;
            let same = _mm512_cmpeq_epi64_mask(cell, cur_cell);
            let flush = fast & !same & _mm512_test_epi64_mask(cur_bits, cur_bits);
            pending.push([cur_cell, cur_bits], flush);
            let gathered = _mm512_mask_or_epi64(bit, same, cur_bits, bit);
            cur_bits = _mm512_mask_mov_epi64(cur_bits, fast, gathered);
            cur_cell = _mm512_mask_mov_epi64(cur_cell, fast, cell);
            let slow = go & !inside;
            if slow != 0 {
                outside.push([k], slow);
            }
            if go == 0 {
                break;
            }
        }
        rays.t = [t0, t1, t2];
        rays.k = k;
        rays.cur_cell = cur_cell;
        rays.cur_bits = cur_bits;
        rays.live = live;
        live != 0
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

    /// Every key of every ray through `step` (origin key first), grouped by ray.
    fn batched(
        r: &Resolution,
        origin: [f32; 3],
        ends: &[[f32; 3]],
        step: fn(std::vec::IntoIter<RayStepper>, &mut dyn FnMut(usize, u64)),
    ) -> Vec<Option<Vec<Key>>> {
        let ko = r.coord_to_key(origin);
        let mut out: Vec<Option<Vec<Key>>> = Vec::new();
        let mut which = Vec::new();
        let mut steppers = Vec::new();
        for &e in ends {
            match (ko, r.coord_to_key(e)) {
                (Some(ko), Some(ke)) => {
                    let s = RayStepper::new(r, origin, ko, e, ke).expect("not degenerate");
                    out.push(Some(if s.is_some() { vec![ko] } else { vec![] }));
                    if let Some(s) = s {
                        which.push(out.len() - 1);
                        steppers.push(s);
                    }
                }
                _ => out.push(None),
            }
        }
        step(steppers.into_iter(), &mut |n, k| {
            if let Some(Some(v)) = out.get_mut(which[n]) {
                v.push(unpack(k));
            }
        });
        out
    }

    /// Records marked keys; cells are decoded back to keys.
    struct TestMarks {
        lo_packed: u64,
        lo: [u32; 3],
        dim: [u32; 3],
        keys: Vec<Key>,
    }

    impl FreeMarks for TestMarks {
        fn window(&self) -> (u64, [u32; 3]) {
            (self.lo_packed, self.dim)
        }
        fn mark_cell(&mut self, cell: u32, bits: u64) {
            let [dx, dy, _] = self.dim;
            let c = [cell % dx, (cell / dx) % dy, cell / dx / dy];
            for lin in (0..64).filter(|l| bits & (1 << l) != 0) {
                let v = [lin & 3, (lin >> 2) & 3, lin >> 4];
                self.keys.push(Key(
                    [0, 1, 2].map(|i| (((self.lo[i] + c[i]) << 2) + v[i]) as u16)
                ));
            }
        }
        fn mark_key(&mut self, key: u64) {
            self.keys.push(unpack(key));
        }
    }

    #[test]
    fn batched_stepping_equals_the_transcription() {
        // Bundles of rays from one origin (as one insertion takes them): random lengths from 0 to ~40 m, many
        // ends and origins on voxel borders (ties, the length stop rule), for every kernel.
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for res in [0.05, 0.1, 0.07, 0.2, 1.0] {
            let r = Resolution::new(res).unwrap();
            for bundle in 0..16 {
                let mut pt = |grid: bool, scale: u64| {
                    [0; 3].map(|_| {
                        let v = (rnd() % (2 * scale)) as f32 / 100.0 - scale as f32 / 100.0;
                        if grid {
                            (v / res as f32).round() * res as f32
                        } else {
                            v
                        }
                    })
                };
                let origin = pt(bundle % 4 == 0, 500);
                let ends: Vec<[f32; 3]> = (0..1500)
                    .map(|i| {
                        let scale = [5, 100, 1000, 4000][i % 4];
                        let e = pt(i % 3 == 0, scale);
                        [origin[0] + e[0], origin[1] + e[1], origin[2] + e[2]]
                    })
                    .collect();
                let want: Vec<_> = ends.iter().map(|&e| reference(&r, origin, e)).collect();
                assert_eq!(
                    batched(&r, origin, &ends, |rays, visit| step_rays_pairs(
                        rays, visit
                    )),
                    want,
                    "res {res}: pairs"
                );
                // The marks of all rays (origin keys aside) as sets, with windows that hold
                // all, some or none of the keys.
                let mut all: Vec<Key> = want
                    .iter()
                    .flatten()
                    .flat_map(|v| v.iter().skip(1))
                    .copied()
                    .collect();
                all.sort_unstable();
                all.dedup();
                let Some(ko) = r.coord_to_key(origin) else {
                    continue;
                };
                for (kernel, (half, shift)) in [Kernel::Scalar, Kernel::Avx2, Kernel::Avx512]
                    .into_iter()
                    .flat_map(|k| [(50u32, 0i64), (3, 0), (2, 5), (1, 40_000)].map(|w| (k, w)))
                {
                    let b = ko.0.map(|a| i64::from(a >> 2) + shift - i64::from(half));
                    let lo = b.map(|c| c.clamp(0, 1 << 14) as u64 + (BIAS >> 2));
                    let mut sink = TestMarks {
                        lo_packed: lo[0] | (lo[1] << 21) | (lo[2] << 42),
                        lo: b.map(|c| c.clamp(0, 1 << 14) as u32),
                        dim: [2 * half + 1; 3],
                        keys: Vec::new(),
                    };
                    let keyed = ends.iter().filter_map(|&e| Some((e, r.coord_to_key(e)?)));
                    assert_eq!(mark_free(kernel, &r, origin, ko, keyed, &mut sink), 0);
                    sink.keys.sort_unstable();
                    sink.keys.dedup();
                    // Window cells fit u32 as in `voxels` (at most 2^20 cells).
                    assert!(
                        sink.keys == all,
                        "res {res}, {kernel:?}: window ±{half} shifted {shift}: {} keys marked, {} expected, first difference {:?}",
                        sink.keys.len(),
                        all.len(),
                        sink.keys.iter().zip(&all).find(|(a, b)| a != b)
                    );
                }
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
