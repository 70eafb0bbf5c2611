//! The map metrics of `scan3d_map::eval` (issue 6) against hand-computed small maps,
//! OctoMap's own confusion counts (research/octomap.md §8.5) and `compare_octrees`' KLD.

mod common;

use std::process::Command;

use common::{octomap_tool, read_octomap_data as read};
use scan3d_map::eval::{EvalError, LeafMap, Role, VoxelBox, compare, evaluate, evaluate_truth};
use scan3d_map::octree::{Key, Octree, OctreeError, Resolution, SensorModel, VoxelMap};

fn load(rel: &str) -> LeafMap {
    LeafMap::read(&read(rel), SensorModel::default()).expect("reads")
}

const C: u16 = 32768;

/// A map at 0.1 m from (key offset from the origin voxel, log-odds) pairs, via the octree
/// module's eager pruning and `.ot` writer, read back by the metrics' reader.
fn map(voxels: &[([u16; 3], f32)]) -> LeafMap {
    let mut m = VoxelMap::new(Resolution::new(0.1).unwrap(), SensorModel::default());
    for &(k, l) in voxels {
        m.set_log_odds(Key([C + k[0], C + k[1], C + k[2]]), l);
    }
    let tree = m.to_octree();
    let from_file = LeafMap::read(&tree.to_ot_bytes(), SensorModel::default()).unwrap();
    assert_eq!(from_file, LeafMap::from_octree(&tree));
    from_file
}

fn p(l: f64) -> f64 {
    1.0 - 1.0 / (1.0 + l.exp())
}

fn kld(pr: f64, pt: f64) -> f64 {
    ((pr / pt).ln() * pr) + ((1.0 - pr) / (1.0 - pt)).ln() * (1.0 - pr)
}

fn close(a: f64, b: f64) {
    assert!((a - b).abs() <= 1e-12 * b.abs().max(1.0), "{a} != {b}");
}

#[test]
fn hand_computed_four_voxel_maps() {
    // x:        0      1      2     3
    // ref:     occ 2  free -1 occ 1  unknown
    // target:  occ 1  occ .5  unk    free -2
    let r = map(&[([0, 0, 0], 2.0), ([1, 0, 0], -1.0), ([2, 0, 0], 1.0)]);
    let t = map(&[([0, 0, 0], 1.0), ([1, 0, 0], 0.5), ([3, 0, 0], -2.0)]);
    let m = evaluate(&r, &t, None).unwrap();
    assert_eq!(m.voxels, 4);
    assert_eq!(m.bbox, VoxelBox::new([C, C, C], [C + 3, C, C]).unwrap());
    assert_eq!(m.confusion, [[1, 0, 1], [1, 0, 0], [0, 1, 0]]);
    let v = 0.001; // m³ per voxel at 0.1 m
    close(m.confusion_m3[0][0], v);
    assert_eq!(
        (m.reference.occupied, m.reference.free, m.reference.unknown),
        (2, 1, 1)
    );
    assert_eq!(
        (m.target.occupied, m.target.free, m.target.unknown),
        (2, 1, 1)
    );
    assert_eq!((m.reference.leaves, m.target.leaves), (3, 3));
    close(m.reference.ratio_occupied, 0.5);
    close(m.reference.ratio_unknown, 0.25);
    // IoU_occ: {x0} / {x0, x1, x2}; free: {} / {x1, x3}; unknown: {} / {x2, x3}.
    close(m.iou.occupied.unwrap(), 1.0 / 3.0);
    close(m.iou.free.unwrap(), 0.0);
    close(m.iou.unknown.unwrap(), 0.0);
    // R_occ + R_free = 0.75 > 0.1: all three terms, with the reference's ratios.
    close(m.iou.weighted, 0.5 / 3.0);
    // C = {x0, x1}.
    let (pr, pt) = ([p(2.0), p(-1.0)], [p(1.0), p(0.5)]);
    let sum = kld(pr[0], pt[0]) + kld(pr[1], pt[1]);
    assert_eq!(m.log_odds.common_voxels, 2);
    close(m.log_odds.sum, sum);
    close(m.log_odds.mean.unwrap(), sum / 2.0);
    let pbar = (pr[0] + pr[1] + pt[0] + pt[1]) / 4.0;
    let (a, b) = ([pr[0] - pbar, pr[1] - pbar], [pt[0] - pbar, pt[1] - pbar]);
    let den = ((a[0] * a[0] + a[1] * a[1]) * (b[0] * b[0] + b[1] * b[1])).sqrt();
    close(
        m.correlation.paper.unwrap(),
        ((a[0] * b[0]).abs() + (a[1] * b[1]).abs()) / den,
    );
    close(
        m.correlation.signed.unwrap(),
        (a[0] * b[0] + a[1] * b[1]) / den,
    );
    close(m.correlation.p_bar.unwrap(), pbar);
    close(m.mean_probability.unwrap(), pbar);
    close(
        m.probability_deviation.unwrap(),
        ((pr[0] - pt[0]).abs() + (pr[1] - pt[1]).abs()) / 2.0,
    );
}

#[test]
fn pruned_leaf_counts_all_its_voxels_and_bbox_clips() {
    // The reference is a 2x2x2 free block (one pruned depth-15 leaf), the target one occupied
    // voxel inside it.
    let mut block = Vec::new();
    for z in 0..2 {
        for y in 0..2 {
            for x in 0..2 {
                block.push(([x, y, z], -1.0f32));
            }
        }
    }
    let r = map(&block);
    assert_eq!(r.num_leaves(), 1);
    let t = map(&[([1, 1, 1], 0.5)]);
    let m = evaluate(&r, &t, None).unwrap();
    assert_eq!(m.voxels, 8);
    assert_eq!(m.confusion, [[0, 0, 0], [1, 0, 7], [0, 0, 0]]);
    // R_free = 1 (> 0.1), so the unknown term counts too; every IoU is 0.
    close(m.iou.free.unwrap(), 0.0);
    assert_eq!(m.iou.unknown, Some(0.0));
    assert_eq!(m.iou.occupied, Some(0.0));
    assert_eq!(m.iou.weighted, 0.0);

    // --bbox keeps the voxels whose centre is inside: x centres 0.05 and 0.15, y and z 0.15.
    let b = VoxelBox::from_metric(r.resolution(), [0.0, 0.1, 0.1], [0.2, 0.2, 0.2]).unwrap();
    assert_eq!(
        b,
        VoxelBox::new([C, C + 1, C + 1], [C + 1, C + 1, C + 1]).unwrap()
    );
    let m = evaluate(&r, &t, Some(b)).unwrap();
    assert_eq!(m.voxels, 2);
    assert_eq!(m.confusion, [[0, 0, 0], [1, 0, 1], [0, 0, 0]]);
}

#[test]
fn weighted_iou_ignores_unknown_when_known_share_is_small() {
    // 1 occupied voxel in a box of 2 x 1 x 10 = 20 voxels: R_occ + R_free = 0.1 -> two terms.
    let r = map(&[([0, 0, 0], 1.0), ([1, 0, 9], -1.0)]);
    let t = map(&[([0, 0, 0], 1.0)]);
    let m = evaluate(&r, &t, None).unwrap();
    assert_eq!(m.voxels, 20);
    close(m.reference.ratio_occupied + m.reference.ratio_free, 0.1);
    // IoU_occ 1, IoU_free 0 -> 0.05 * 1 + 0.05 * 0 (the unknown term, 0.9 * 18/19, is left out).
    close(m.iou.weighted, 0.05);
    close(m.iou.unknown.unwrap(), 18.0 / 19.0);
}

#[test]
fn identical_maps_score_perfectly() {
    let a = load("reference/geb079_sim_0.1.ot");
    let m = evaluate(&a, &a, None).unwrap();
    assert_eq!(m.iou.occupied, Some(1.0));
    assert_eq!(m.iou.free, Some(1.0));
    assert_eq!(m.iou.unknown, Some(1.0));
    close(m.iou.weighted, 1.0);
    assert_eq!(m.log_odds.sum, 0.0);
    close(m.correlation.paper.unwrap(), 1.0);
    close(m.correlation.signed.unwrap(), 1.0);
    assert_eq!(m.probability_deviation, Some(0.0));
    assert_eq!(m.confusion[0][1] + m.confusion[1][0], 0);
}

#[test]
fn geb079_confusion_equals_octomaps_counts() {
    // research/octomap.md §8.5, octomap_bench cmp geb079.bt reference/geb079_sim_0.08.bt.
    let a = load("geb079.bt");
    let b = load("reference/geb079_sim_0.08.bt");
    let m = evaluate(&a, &b, None).unwrap();
    let c = m.confusion;
    assert_eq!(c[0], [50_949, 14, 134_710]);
    assert_eq!(c[1], [92, 569_046, 381_621]);
    assert_eq!([c[2][0], c[2][1]], [28, 351_370]);
    assert_eq!(c.iter().flatten().sum::<u64>(), m.voxels);
    assert_eq!((m.reference.leaves, m.target.leaves), (428_144, 439_443));
    assert!((m.iou.occupied.unwrap() - 0.274).abs() < 5e-4);
}

#[test]
fn log_odds_sum_equals_compare_octrees_kld() {
    // compare_octrees geb079_sim_0.1.ot (full) against its max-likelihood .ot printed
    // "Expanded num. leafs: 556561" and "KLD: 85865.5" (research/octomap.md §8.5).
    let ot_bytes = read("reference/geb079_sim_0.1.ot");
    let ot = LeafMap::read(&ot_bytes, SensorModel::default()).unwrap();
    let bt = load("reference/geb079_sim_0.1.bt");
    let tree = Octree::read(&ot_bytes, SensorModel::default()).unwrap();
    let ml_tree = tree.to_max_likelihood_pruned();
    let ml = LeafMap::from_octree(&ml_tree);
    for target in [&bt, &ml] {
        let m = evaluate(&ot, target, None).unwrap();
        assert_eq!(m.log_odds.common_voxels, 556_561);
        assert_eq!(format!("{:.1}", m.log_odds.sum), "85865.5");
    }
    // Live, when Debian's octomap-tools is installed (required in CI): the same to its 6 digits.
    let Some(compare_octrees) = octomap_tool("compare_octrees") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("full.ot"), dir.path().join("ml.ot"));
    std::fs::write(&a, &ot_bytes).unwrap();
    std::fs::write(&b, ml_tree.to_ot_bytes()).unwrap();
    let out = Command::new(&compare_octrees)
        .arg(&a)
        .arg(&b)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let kld: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("KLD: "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no KLD in compare_octrees output: {text}"));
    let ours = evaluate(&ot, &ml, None).unwrap().log_odds.sum;
    assert!(
        ((ours - kld) / kld).abs() < 5e-6,
        "ours {ours} vs compare_octrees {kld}"
    );
}

#[test]
fn fast_reader_equals_octree_reader_on_every_reference_file() {
    for f in [
        "geb079.bt",
        "reference/geb079_sim_0.08.bt",
        "reference/geb079_sim_0.1.bt",
        "reference/geb079_sim_0.1.ot",
        "reference/geb079_sim_0.2.ot",
        "reference/scan_dat_0.2.bt",
        "reference/spherical_scan_0.05.ot",
    ] {
        let bytes = read(f);
        let tree = Octree::read(&bytes, SensorModel::default()).unwrap();
        let fast = LeafMap::read(&bytes, SensorModel::default()).unwrap();
        assert_eq!(fast, LeafMap::from_octree(&tree), "{f}");
        assert_eq!(fast.num_nodes(), tree.num_nodes() as u64, "{f}");
        assert_eq!(fast.num_leaves(), tree.num_leaves(), "{f}");
    }
}

#[test]
fn malformed_files_are_clear_errors() {
    let m = SensorModel::default();
    let ot = read("reference/spherical_scan_0.2.ot");
    let bt = read("reference/spherical_scan_0.2.bt");
    // Cut anywhere in the data: an error (never a panic), of the octree reader's kind.
    for bytes in [&ot, &bt] {
        let header_end = bytes.windows(5).position(|w| w == b"data\n").unwrap() + 5;
        for cut in (header_end..bytes.len()).step_by(97) {
            let cut_bytes = &bytes[..cut];
            let ours = LeafMap::read(cut_bytes, m).unwrap_err();
            let theirs = Octree::read(cut_bytes, m).unwrap_err();
            assert_eq!(
                std::mem::discriminant(&ours),
                std::mem::discriminant(&theirs),
                "cut at {cut}: {ours} vs {theirs}"
            );
        }
    }
    assert!(matches!(
        LeafMap::read(b"hello", m),
        Err(OctreeError::NotOctoMap)
    ));
    let no_res = b"# Octomap OcTree file\nid OcTree\nsize 1\ndata\n\0\0\0\0\0";
    assert!(matches!(
        LeafMap::read(no_res, m),
        Err(OctreeError::BadHeader(_))
    ));
    // A child mask below depth 16: every node claims child 0.
    let mut deep = b"# Octomap OcTree file\nid OcTree\nsize 20\nres 0.1\ndata\n".to_vec();
    for _ in 0..20 {
        deep.extend_from_slice(&[0, 0, 0, 0, 1]);
    }
    assert_eq!(LeafMap::read(&deep, m).unwrap_err(), OctreeError::TooDeep);
    // A NaN log-odds is refused by the metrics.
    let mut nan = b"# Octomap OcTree file\nid OcTree\nsize 1\nres 0.1\ndata\n".to_vec();
    nan.extend_from_slice(&f32::NAN.to_le_bytes());
    nan.push(0);
    let nan = LeafMap::read(&nan, m).unwrap();
    let good = map(&[([0, 0, 0], 1.0)]);
    assert!(matches!(
        evaluate(&good, &nan, None),
        Err(EvalError::NonFinite {
            role: Role::Target,
            ..
        })
    ));
}

#[test]
fn resolution_mismatch_and_empty_maps_are_errors() {
    let a = load("reference/geb079_sim_0.1.bt");
    let b = load("reference/geb079_sim_0.2.bt");
    let e = evaluate(&a, &b, None).unwrap_err();
    assert_eq!(
        e,
        EvalError::ResolutionMismatch {
            expected: 0.1,
            found: 0.2,
            role: Role::Target
        }
    );
    assert!(e.to_string().contains("resolution mismatch"));
    let empty = LeafMap::from_octree(&Octree::empty(
        Resolution::new(0.1).unwrap(),
        SensorModel::default(),
    ));
    assert_eq!(
        evaluate(&empty, &a, None).unwrap_err(),
        EvalError::EmptyMap(Role::Reference)
    );
    assert_eq!(
        evaluate(&a, &empty, None).unwrap_err(),
        EvalError::EmptyMap(Role::Target)
    );
    assert_eq!(
        VoxelBox::from_metric(a.resolution(), [0.01, 0.0, 0.0], [0.04, 1.0, 1.0]).unwrap_err(),
        EvalError::EmptyBox
    );
}

#[test]
fn truth_scores_hand_computed() {
    // Along x: target occupied {0, 1, 9}, truth occupied {0, 5} and 20 (outside U = x 0..=9).
    let t = map(&[
        ([0, 0, 0], 1.0),
        ([1, 0, 0], 1.0),
        ([9, 0, 0], 1.0),
        ([4, 0, 0], -1.0),
    ]);
    let g = map(&[
        ([0, 0, 0], 3.5),
        ([5, 0, 0], 3.5),
        ([20, 0, 0], 3.5),
        ([1, 0, 0], -2.0),
    ]);
    let u = VoxelBox::new([C, C, C], [C + 9, C, C]).unwrap();
    let s = evaluate_truth(&t, &g, u).unwrap();
    assert_eq!((s.target_occupied, s.truth_occupied), (3, 2));
    close(s.precision.unwrap(), 1.0 / 3.0);
    close(s.recall.unwrap(), 0.5);
    close(s.f1.unwrap(), 0.4);
    close(s.precision_tolerant.unwrap(), 2.0 / 3.0);
    close(s.recall_tolerant.unwrap(), 0.5);
    close(s.f1_tolerant.unwrap(), 4.0 / 7.0);
    // T -> G: 0, 1, 4 voxels (mean 5/3); G -> T: 0, 4 (mean 2); at 0.1 m.
    close(s.chamfer.unwrap(), (5.0 / 3.0 + 2.0) / 2.0 * 0.1);
    // Against itself: perfect.
    let s = evaluate_truth(&g, &g, u).unwrap();
    assert_eq!(
        (s.precision, s.recall, s.f1),
        (Some(1.0), Some(1.0), Some(1.0))
    );
    assert_eq!(s.chamfer, Some(0.0));
}

#[test]
fn compare_is_symmetric_in_its_confusion() {
    let a = load("geb079.bt");
    let b = load("reference/geb079_sim_0.08.bt");
    let ab = compare(&a, &b, None, [Role::Reference, Role::Target]).unwrap();
    let ba = compare(&b, &a, None, [Role::Reference, Role::Target]).unwrap();
    for i in 0..3 {
        for j in 0..3 {
            assert_eq!(ab.confusion[i][j], ba.confusion[j][i]);
        }
    }
    assert_eq!(ab.universe, ba.universe);
}
