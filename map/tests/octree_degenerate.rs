//! Degenerate rays (issue 10, defect 5): a ray whose end is in another voxel than its origin
//! but whose f32 length is 0 (squares underflow) or infinite (squares overflow) made the
//! stepping loop run for ever. Every insertion here runs in a thread with a deadline, so a
//! regression fails instead of hanging, with every kernel.

use std::sync::mpsc;
use std::time::Duration;

use scan3d_map::octree::{InsertStats, Kernel, Resolution, SensorModel, VoxelMap, ray_keys};

const KERNELS: [Kernel; 3] = [Kernel::Scalar, Kernel::Avx2, Kernel::Avx512];

/// Runs `f` on another thread and returns its result, or panics if it takes longer than
/// `secs` (a hang) or panics itself.
fn within<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    match rx.recv_timeout(Duration::from_secs(secs)) {
        Ok(v) => v,
        Err(mpsc::RecvTimeoutError::Timeout) => panic!("did not finish within {secs} s"),
        Err(mpsc::RecvTimeoutError::Disconnected) => panic!("panicked (see above)"),
    }
}

/// Inserts one cloud with `kernel`; returns the stats and the map's `.bt` bytes.
fn insert(
    kernel: Kernel,
    res: f64,
    points: Vec<[f32; 3]>,
    origin: [f32; 3],
    max_range: f64,
) -> (InsertStats, Vec<u8>, VoxelMap) {
    within(20, move || {
        let mut map = VoxelMap::with_kernel(
            Resolution::new(res).unwrap(),
            SensorModel::default(),
            kernel,
        );
        let st = map.insert_point_cloud(&points, origin, max_range);
        let bt = map.to_octree().to_bt_bytes();
        (st, bt, map)
    })
}

#[test]
fn a_near_zero_ray_is_skipped_and_counted_and_its_endpoint_still_hit_with_either_kernel() {
    let end = [-1e-30f32, -1e-30, 0.0];
    for kernel in KERNELS {
        for max_range in [-1.0, 100.0] {
            let (st, _, map) = insert(kernel, 0.1, vec![end], [0.0; 3], max_range);
            assert_eq!(st.points, 1);
            assert_eq!(st.degenerate_rays, 1, "{kernel:?} max range {max_range}");
            assert_eq!((st.skipped_nonfinite, st.out_of_bounds), (0, 0));
            let r = map.resolution();
            let ke = r.coord_to_key(end).unwrap();
            let ko = r.coord_to_key([0.0; 3]).unwrap();
            assert_ne!(ke, ko, "the end lies in another voxel");
            assert_eq!(map.log_odds(ke), Some(map.model().hit));
            assert_eq!(
                map.log_odds(ko),
                None,
                "no ray cast, origin voxel untouched"
            );
            assert_eq!(map.num_voxels(), 1);
            assert_eq!(map.totals().degenerate_rays, 1);
        }
    }
}

#[test]
fn degenerate_rays_among_ordinary_ones_leave_the_ordinary_rays_as_they_were() {
    // Groups of four (the AVX2 lanes) with degenerate rays in various lanes. The ordinary
    // rays go into the positive octant, the degenerate ends lie just below the origin's
    // borders, so their voxels are disjoint and the expected map is easy to state.
    let ordinary: Vec<[f32; 3]> = (0..23)
        .map(|i| {
            let f = i as f32;
            [
                (f * 0.9).sin().abs() * 3.0 + 0.01,
                (f * 0.4).cos().abs() * 2.0 + 0.01,
                f * 0.1 + 0.01,
            ]
        })
        .collect();
    let tiny = [
        [-1e-30f32, -1e-30, 0.0],
        [-1e-25, 0.0, -1e-24],
        [-1e-40, 0.0, 0.0],
    ];
    let mut mixed = ordinary.clone();
    for (n, at) in [0usize, 5, 6, 7, 13, 22].into_iter().enumerate() {
        mixed.insert(at, tiny[n % tiny.len()]);
    }
    for kernel in KERNELS {
        let (st, _, map) = insert(kernel, 0.1, mixed.clone(), [0.0; 3], -1.0);
        let (st0, _, mut plain) = insert(kernel, 0.1, ordinary.clone(), [0.0; 3], -1.0);
        assert_eq!(st.degenerate_rays, 6, "{kernel:?}");
        assert_eq!(st0.degenerate_rays, 0);
        // The same map as the ordinary rays plus the hits of the degenerate endpoints.
        for p in tiny {
            let k = plain.resolution().coord_to_key(p).unwrap();
            plain.update(k, true);
        }
        assert_eq!(
            map.to_octree().to_bt_bytes(),
            plain.to_octree().to_bt_bytes(),
            "{kernel:?}"
        );
    }
}

#[test]
fn ray_keys_refuses_a_degenerate_ray() {
    let r = Resolution::new(0.1).unwrap();
    let ray = within(20, move || {
        let mut keys = Vec::new();
        let ok = ray_keys(&r, [0.0; 3], [-1e-30, -1e-30, 0.0], |k| keys.push(k));
        (ok, keys)
    });
    assert_eq!(ray, (false, vec![]));
    // Huge resolution: coordinates in range whose squares overflow f32 (length +inf).
    let r = Resolution::new(1e20).unwrap();
    let ray = within(20, move || {
        let mut keys = Vec::new();
        let ok = ray_keys(&r, [0.0; 3], [1e24, -1e24, 0.0], |k| keys.push(k));
        (ok, keys)
    });
    assert_eq!(ray, (false, vec![]));
}

/// xorshift64, deterministic.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    /// A coordinate from the awkward set: zeros, tiny, subnormal, huge, infinite, NaN and
    /// ordinary values, of either sign, scaled to the resolution when `scale` is given.
    fn coord(&mut self, scale: f32) -> f32 {
        const AWKWARD: [f32; 14] = [
            0.0,
            1e-30,
            1e-38,
            1e-45, // the smallest subnormal
            1.2e-40,
            f32::MIN_POSITIVE,
            1e-20,
            1e19,
            1e30,
            f32::MAX,
            f32::INFINITY,
            f32::NAN,
            0.05,
            1.0,
        ];
        let v = AWKWARD[(self.next() % AWKWARD.len() as u64) as usize];
        let v = if self.next().is_multiple_of(3) {
            v * scale
        } else {
            v
        };
        if self.next().is_multiple_of(2) { -v } else { v }
    }
}

#[test]
fn any_mix_of_tiny_huge_subnormal_infinite_and_nan_coordinates_finishes_identically_in_both_kernels()
 {
    let mut rng = Rng(0x5eed_0000_dead_beef);
    let mut degenerate = 0;
    // 1e20 m voxels make in-range coordinates whose squares overflow (infinite lengths).
    for res in [0.1, 1.0, 1e-3, 1e20] {
        for case in 0..40 {
            let scale = res as f32;
            let origin = if case % 4 == 0 {
                [0.0; 3]
            } else {
                [0; 3].map(|_| rng.coord(scale))
            };
            let points: Vec<[f32; 3]> = (0..37)
                .map(|i| {
                    let mut p = [0; 3].map(|_| rng.coord(scale));
                    if i % 3 == 0 {
                        // Near the origin: straddling its voxel borders by a hair.
                        for (c, o) in p.iter_mut().zip(origin) {
                            *c = o + *c * 1e-30;
                        }
                    }
                    p
                })
                .collect();
            for max_range in [-1.0, 0.5, 1e30] {
                let (s, b, _) = insert(Kernel::Scalar, res, points.clone(), origin, max_range);
                for kernel in [Kernel::Avx2, Kernel::Avx512] {
                    let (v, bv, _) = insert(kernel, res, points.clone(), origin, max_range);
                    assert_eq!(
                        s, v,
                        "res {res} case {case} max range {max_range} {kernel:?}"
                    );
                    assert_eq!(
                        b, bv,
                        "res {res} case {case} max range {max_range} {kernel:?}"
                    );
                }
                assert_eq!(s.points, 37);
                assert!(s.skipped_nonfinite + s.out_of_bounds <= s.points);
                degenerate += s.degenerate_rays;
            }
            let r = Resolution::new(res).unwrap();
            within(20, move || {
                for p in points {
                    ray_keys(&r, origin, p, |_| {});
                }
            });
        }
    }
    // The generator does reach the case under test.
    assert!(
        degenerate > 20,
        "only {degenerate} degenerate rays generated"
    );
}

#[test]
fn the_default_kernel_follows_scan3d_octree_kernel() {
    // CI runs the golden tests once with SCAN3D_OCTREE_KERNEL=scalar and once without.
    let want = match std::env::var(scan3d_map::octree::KERNEL_ENV).as_deref() {
        Ok("scalar") => Kernel::Scalar,
        Ok("avx2") => Kernel::Avx2,
        _ => Kernel::Avx512,
    };
    assert_eq!(Kernel::from_env(), want);
    let map = VoxelMap::new(Resolution::new(0.1).unwrap(), SensorModel::default());
    assert_eq!(map.kernel(), want);
}
