//! What `scan3d map` and `scan3d convert` report about points they could not use: points a
//! PLY/PCD reader dropped for NaN or infinite values, and degenerate rays the octree skipped.

mod common;

use common::{arg, run_cli};

use std::path::Path;

/// A PCD from the origin with one ordinary point, two non-finite ones and a near-zero one
/// (its ray is degenerate: another voxel, f32 length 0).
fn awkward_pcd(dir: &Path) -> std::path::PathBuf {
    let path = dir.join("awkward.pcd");
    std::fs::write(
        &path,
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 4\nHEIGHT 1\n\
         VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n1 0.5 0.25\nnan 0 0\n-1e-30 -1e-30 0\n0 inf 0\n",
    )
    .unwrap();
    path
}

#[test]
fn map_reports_points_dropped_by_the_reader_and_degenerate_rays_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let pcd = awkward_pcd(dir.path());
    let out = dir.path().join("m.bt");
    let text = run_cli(&[
        "map",
        arg(&pcd),
        "--resolution",
        "0.1",
        "--out",
        arg(&out),
        "--quiet",
    ])
    .unwrap();
    assert!(text.contains("1 scans, 2 points"), "{text}");
    assert!(
        text.contains("dropped 2 points with NaN or infinite coordinates or origins while reading"),
        "{text}"
    );
    assert!(
        text.contains("skipped 1 rays of zero or infinite f32 length"),
        "{text}"
    );
    // Both endpoints are hits in the written map.
    let info = run_cli(&["info", "--json", arg(&out)]).unwrap();
    let v: serde_json::Value = serde_json::from_str(&info).unwrap();
    assert_eq!(v["occupied_leaves"], 2, "{info}");
}

#[test]
fn convert_reports_points_dropped_by_the_reader() {
    let dir = tempfile::tempdir().unwrap();
    let pcd = awkward_pcd(dir.path());
    let ply = dir.path().join("c.ply");
    let text = run_cli(&["convert", arg(&pcd), arg(&ply)]).unwrap();
    assert!(
        text.contains("dropped 2 points with NaN or infinite coordinates or origins while reading"),
        "{text}"
    );
    assert!(text.contains("(1 scans, 2 points)"), "{text}");
}
