//! OctoMap's exact ray stepping (`computeRayKeys`, research/octomap.md §3): a 3D DDA over
//! voxel keys in OctoMap's f32/f64 mix, origin voxel included, end voxel excluded, ties to z then y.

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
    let (Some(key_origin), Some(key_end)) = (res.coord_to_key(origin), res.coord_to_key(end))
    else {
        return false;
    };
    if key_origin == key_end {
        return true;
    }
    visit(key_origin);

    let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
    // Vector3::norm(): squares summed in f32, sqrt in f64, then cast to float.
    let length = f64::from(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() as f32;
    let dir = [d[0] / length, d[1] / length, d[2] / length];

    let r = res.meters();
    let mut step = [0i32; 3];
    let mut t_max = [f64::MAX; 3];
    let mut t_delta = [f64::MAX; 3];
    for i in 0..3 {
        step[i] = if dir[i] > 0.0 {
            1
        } else if dir[i] < 0.0 {
            -1
        } else {
            0
        };
        if step[i] != 0 {
            let half = (f64::from(step[i]) * r * 0.5) as f32;
            let border = res.key_to_coord_axis(key_origin.0[i]) + f64::from(half);
            t_max[i] = (border - f64::from(origin[i])) / f64::from(dir[i]);
            t_delta[i] = r / f64::from(dir[i].abs());
        }
    }

    let length = f64::from(length);
    let mut key = key_origin.0;
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
        if key == key_end.0 {
            break;
        }
        if t_max[0].min(t_max[1]).min(t_max[2]) > length {
            break;
        }
        visit(Key(key));
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

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
