//! Byte identity against OctoMap 1.9.7's golden files in `testdata/octomap/reference/`
//! (research/octomap.md; testdata/octomap/README.md): our `.ot` equals `OcTree::write` and our
//! `.bt` equals `OcTree::writeBinary` after inserting the same `.graph` with graph2tree's
//! defaults.

mod common;

use common::{octomap_data as data, octomap_tool, read_octomap_data as read};
use scan3d_map::octree::{Octree, OctreeError, Resolution, SensorModel, VoxelMap, read_graph};

fn build(graph: &str, res: f64) -> Octree {
    let scans = read_graph(&read(graph)).expect("graph parses");
    let mut map = VoxelMap::new(Resolution::new(res).unwrap(), SensorModel::default());
    for s in &scans {
        let st = map.insert_bundle(s, -1.0);
        assert_eq!(st.skipped_nonfinite, 0);
    }
    map.to_octree()
}

/// Compares without dumping megabytes on failure.
fn same(ours: &[u8], theirs: &[u8], what: &str) {
    if ours != theirs {
        let at = ours
            .iter()
            .zip(theirs)
            .position(|(a, b)| a != b)
            .unwrap_or(ours.len().min(theirs.len()));
        panic!(
            "{what}: differs at byte {at} (ours {} bytes, reference {} bytes)",
            ours.len(),
            theirs.len()
        );
    }
}

fn check(graph: &str, stem: &str, res: f64, ot: bool, counts: (usize, u64, u64, u64)) {
    let tree = build(graph, res);
    if ot {
        assert_eq!(
            (
                tree.num_nodes(),
                tree.num_leaves(),
                tree.num_occupied(),
                tree.num_free()
            ),
            counts,
            "{stem} .ot counts"
        );
        same(
            &tree.to_ot_bytes(),
            &read(&format!("reference/{stem}.ot")),
            &format!("{stem}.ot"),
        );
    }
    same(
        &tree.to_bt_bytes(),
        &read(&format!("reference/{stem}.bt")),
        &format!("{stem}.bt"),
    );
}

#[test]
fn spherical_scan_005() {
    check(
        "spherical_scan.graph",
        "spherical_scan_0.05",
        0.05,
        true,
        (23_923, 18_970, 5_285, 13_685),
    );
}

#[test]
fn spherical_scan_01() {
    check(
        "spherical_scan.graph",
        "spherical_scan_0.1",
        0.1,
        true,
        (6_296, 4_926, 1_521, 3_405),
    );
}

#[test]
fn spherical_scan_02() {
    check(
        "spherical_scan.graph",
        "spherical_scan_0.2",
        0.2,
        true,
        (1_598, 1_189, 425, 764),
    );
}

#[test]
fn scan_dat_01() {
    check(
        "derived/scan_dat.graph",
        "scan_dat_0.1",
        0.1,
        true,
        (407_411, 327_452, 23_397, 304_055),
    );
}

#[test]
fn scan_dat_02() {
    check(
        "derived/scan_dat.graph",
        "scan_dat_0.2",
        0.2,
        true,
        (47_107, 37_183, 9_308, 27_875),
    );
}

#[test]
fn geb079_sim_01() {
    check(
        "derived/geb079_sim.graph",
        "geb079_sim_0.1",
        0.1,
        true,
        (582_971, 483_761, 56_040, 427_721),
    );
}

#[test]
fn geb079_sim_02() {
    check(
        "derived/geb079_sim.graph",
        "geb079_sim_0.2",
        0.2,
        true,
        (97_330, 80_911, 17_824, 63_087),
    );
}

#[test]
fn geb079_sim_008_bt() {
    check(
        "derived/geb079_sim.graph",
        "geb079_sim_0.08",
        0.08,
        false,
        (0, 0, 0, 0),
    );
}

#[test]
fn geb079_bt_reads_and_writes_back_identically() {
    let bytes = read("geb079.bt");
    let t = Octree::read_bt(&bytes, SensorModel::default()).unwrap();
    assert_eq!(
        (
            t.num_nodes(),
            t.num_leaves(),
            t.num_occupied(),
            t.num_free()
        ),
        (532_566, 428_144, 143_729, 284_415)
    );
    assert_eq!(t.resolution().meters(), 0.08);
    let (lo, hi) = t.metric_bounds().unwrap();
    let want = ([-8.0, -7.52, -0.32], [30.96, 7.44, 2.8]);
    for i in 0..3 {
        assert!(
            (lo[i] - want.0[i]).abs() < 1e-9 && (hi[i] - want.1[i]).abs() < 1e-9,
            "{lo:?} {hi:?}"
        );
    }
    same(&t.to_bt_bytes(), &bytes, "geb079.bt written back");
    // Root record (research/octomap.md §6.1): `ff ff`, 8 inner children.
    let data_at = bytes.windows(5).position(|w| w == b"data\n").unwrap() + 5;
    assert_eq!(&bytes[data_at..data_at + 2], &[0xff, 0xff]);
}

#[test]
fn ot_reads_and_writes_back_identically() {
    for stem in ["spherical_scan_0.05", "scan_dat_0.2", "geb079_sim_0.2"] {
        let bytes = read(&format!("reference/{stem}.ot"));
        let t = Octree::read_ot(&bytes, SensorModel::default()).unwrap();
        same(&t.to_ot_bytes(), &bytes, stem);
        // And the .bt made from the read .ot is OctoMap's writeBinary of the same tree.
        same(
            &t.to_bt_bytes(),
            &read(&format!("reference/{stem}.bt")),
            stem,
        );
    }
}

#[test]
fn truncated_reference_files_are_typed_errors() {
    let model = SensorModel::default();
    let bt = read("reference/spherical_scan_0.1.bt");
    let ot = read("reference/spherical_scan_0.1.ot");
    let graph = read("spherical_scan.graph");
    for frac in [0.5, 0.9, 0.999] {
        let cut = |b: &[u8]| b[..(b.len() as f64 * frac) as usize].to_vec();
        assert!(matches!(
            Octree::read_bt(&cut(&bt), model),
            Err(OctreeError::Truncated { .. })
        ));
        assert!(matches!(
            Octree::read_ot(&cut(&ot), model),
            Err(OctreeError::Truncated { .. })
        ));
        assert!(matches!(
            read_graph(&cut(&graph)),
            Err(OctreeError::Truncated { .. })
        ));
    }
    assert!(Octree::read_bt(&bt[..bt.len() - 1], model).is_err());
    assert!(Octree::read(&ot[..40], model).is_err());
}

#[test]
fn ground_truth_from_voxel_states_writes_readable_bt() {
    // Rebuild geb079.bt voxel by voxel from its leaves (clamp max occupied, clamp min free):
    // the derived tree written as .bt is the original file.
    let bytes = read("geb079.bt");
    let model = SensorModel::default();
    let t = Octree::read_bt(&bytes, model).unwrap();
    let mut gt = VoxelMap::new(*t.resolution(), model);
    let mut voxels = 0u64;
    t.for_each_voxel_in_box(
        scan3d_map::octree::Key([0; 3]),
        scan3d_map::octree::Key([65535; 3]),
        |k, v| {
            voxels += 1;
            gt.set_log_odds(
                k,
                if model.is_occupied(v) {
                    model.clamp_max
                } else {
                    model.clamp_min
                },
            );
        },
    );
    assert_eq!(gt.num_voxels(), voxels);
    let rebuilt = gt.to_octree();
    assert_eq!(
        rebuilt.search(scan3d_map::octree::Key([32768; 3])),
        t.search(scan3d_map::octree::Key([32768; 3]))
    );
    same(&rebuilt.to_bt_bytes(), &bytes, "geb079 rebuilt from voxels");
}

#[test]
fn bt_read_equals_octomaps_read_bt_written_as_ot() {
    // OctoMap's own `convert_octree in.bt out.ot` (readBinary then write) shows the tree
    // OctoMap reads from a .bt: leaf clamps, inner max, root clamp max. Skipped without it,
    // unless SCAN3D_REQUIRE_OCTOMAP=1.
    let Some(tool) = octomap_tool("convert_octree") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    for stem in [
        "geb079",
        "reference/geb079_sim_0.08",
        "reference/spherical_scan_0.05",
    ] {
        let bt = data(&format!("{stem}.bt"));
        let out = dir.path().join("out.ot");
        let ok = std::process::Command::new(&tool)
            .arg(&bt)
            .arg(&out)
            .output()
            .unwrap()
            .status
            .success();
        assert!(ok, "convert_octree {stem}");
        let t = Octree::read_bt(&std::fs::read(&bt).unwrap(), SensorModel::default()).unwrap();
        same(&t.to_ot_bytes(), &std::fs::read(&out).unwrap(), stem);
    }
}

#[test]
fn a_missing_octomap_tool_fails_when_required_and_is_a_notice_otherwise() {
    // Runs the convert_octree comparison above in a child of this test binary with an empty
    // PATH, so the tool cannot be found, with and without SCAN3D_REQUIRE_OCTOMAP=1.
    let run = |required: bool| {
        let mut cmd = std::process::Command::new(std::env::current_exe().unwrap());
        cmd.args([
            "bt_read_equals_octomaps_read_bt_written_as_ot",
            "--exact",
            "--nocapture",
        ])
        .env("PATH", "")
        .env_remove(common::REQUIRE_OCTOMAP);
        if required {
            cmd.env(common::REQUIRE_OCTOMAP, "1");
        }
        let out = cmd.output().unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        (out.status.success(), text)
    };
    let (ok, text) = run(true);
    assert!(
        !ok,
        "passed although the tool is required and missing:\n{text}"
    );
    assert!(
        text.contains("SCAN3D_REQUIRE_OCTOMAP=1 but OctoMap's `convert_octree` is not on PATH"),
        "{text}"
    );
    assert!(text.contains("1 failed"), "{text}");
    let (ok, text) = run(false);
    assert!(ok, "{text}");
    assert!(
        text.contains("skipped the comparison with OctoMap: OctoMap's `convert_octree`"),
        "{text}"
    );
}
