//! `scan3d map / convert / info` end to end on OctoMap's own data: the files the CLI writes are
//! byte-identical to OctoMap 1.9.7's (`testdata/octomap/reference/`).

mod common;

use common::octomap_data as data;
use common::{arg, run_cli};

#[test]
fn map_writes_octomaps_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let graph = data("spherical_scan.graph");
    for ext in ["bt", "ot"] {
        let out = dir.path().join(format!("m.{ext}"));
        run_cli(&[
            "map",
            arg(&graph),
            "--resolution",
            "0.2",
            "--out",
            arg(&out),
            "--quiet",
        ])
        .unwrap();
        let ours = std::fs::read(&out).unwrap();
        let theirs = std::fs::read(data(&format!("reference/spherical_scan_0.2.{ext}"))).unwrap();
        assert!(ours == theirs, "{ext} differs from OctoMap's");
    }
}

#[test]
fn the_old_spelling_res_still_sets_the_resolution() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.bt");
    let graph = data("spherical_scan.graph");
    run_cli(&[
        "map",
        arg(&graph),
        "--res",
        "0.2",
        "--out",
        arg(&out),
        "--quiet",
    ])
    .unwrap();
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(data("reference/spherical_scan_0.2.bt")).unwrap()
    );
    // It is hidden: the help names the resolution once, as --resolution.
    let help = run_cli(&["map", "--help"]).unwrap_err().to_string();
    assert!(help.contains("--resolution <M>"), "{help}");
    assert!(!help.contains("--res "), "{help}");
}

#[test]
fn convert_ot_to_bt_is_writebinary() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.bt");
    let text = run_cli(&[
        "convert",
        arg(&data("reference/scan_dat_0.2.ot")),
        arg(&out),
    ])
    .unwrap();
    assert!(text.starts_with("wrote "), "{text}");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(data("reference/scan_dat_0.2.bt")).unwrap()
    );
}

#[test]
fn a_cloud_through_ply_keeps_its_origins_and_gives_the_same_map() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("c.ply");
    let ot = dir.path().join("c.ot");
    run_cli(&["convert", arg(&data("spherical_scan.graph")), arg(&ply)]).unwrap();
    run_cli(&[
        "map",
        arg(&ply),
        "--resolution",
        "0.1",
        "--out",
        arg(&ot),
        "--quiet",
    ])
    .unwrap();
    assert_eq!(
        std::fs::read(&ot).unwrap(),
        std::fs::read(data("reference/spherical_scan_0.1.ot")).unwrap()
    );
}

#[test]
fn info_reports_counts_and_bounds() {
    let text = run_cli(&[
        "info",
        "--json",
        arg(&data("reference/spherical_scan_0.1.bt")),
    ])
    .unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(v["resolution"], 0.1);
    assert_eq!(v["nodes"], 6296);
    assert_eq!(v["leaves"], 4926);
    assert_eq!(v["occupied_leaves"], 1521);
    assert_eq!(v["free_leaves"], 3405);
}

#[test]
fn non_finite_points_are_skipped_and_counted_and_filters_apply_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("p.ply");
    std::fs::write(
        &ply,
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
         property float z\nend_header\n1 0 0\nnan 0 0\n2 0 0\n9 0 0\n",
    )
    .unwrap();
    let out = dir.path().join("p.bt");
    let text = run_cli(&[
        "map",
        arg(&ply),
        "--resolution",
        "0.5",
        "--origin",
        "0,0,0",
        "--filter",
        "box-out:8,-1,-1,10,1,1",
        "--out",
        arg(&out),
        "--quiet",
    ])
    .unwrap();
    assert!(
        text.contains("1 scans, 3 points") || text.contains("skipped 1 points"),
        "{text}"
    );
    assert!(text.contains("2 points kept"), "{text}");
    let info = run_cli(&["info", "--json", arg(&out)]).unwrap();
    let v: serde_json::Value = serde_json::from_str(&info).unwrap();
    assert!(v["occupied_leaves"].as_u64().unwrap() >= 2, "{info}");
}

#[test]
fn bad_inputs_give_one_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let truncated = dir.path().join("t.bt");
    let bytes = std::fs::read(data("reference/spherical_scan_0.1.bt")).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let err = run_cli(&["info", arg(&truncated)]).unwrap_err().to_string();
    assert!(err.contains("t.bt"), "{err}");
    // A file that is not OctoMap's: its header line named once, as OctoMap writes it.
    let text = dir.path().join("text.bt");
    std::fs::write(&text, "hello\n").unwrap();
    let err = run_cli(&["info", arg(&text)]).unwrap_err();
    assert_eq!(
        format!("{err:#}"),
        format!(
            "{}: not an OctoMap file: the first line must start with \
             \"# Octomap OcTree binary file\" (.bt) or \"# Octomap OcTree file\" (.ot)",
            text.display()
        )
    );
    let err = run_cli(&["map", "missing.ply", "--resolution", "0.1", "--out", "x.bt"])
        .unwrap_err()
        .to_string();
    assert!(err.contains("missing.ply"), "{err}");
    let err = run_cli(&[
        "map",
        arg(&data("spherical_scan.graph")),
        "--resolution",
        "0.1",
        "--out",
        "x.txt",
    ])
    .unwrap_err()
    .to_string();
    assert!(err.contains("must end in .bt or .ot"), "{err}");
    let err = run_cli(&[
        "convert",
        arg(&data("reference/spherical_scan_0.1.bt")),
        "x.ply",
    ])
    .unwrap_err()
    .to_string();
    assert!(err.contains("between a map and a cloud"), "{err}");
}
