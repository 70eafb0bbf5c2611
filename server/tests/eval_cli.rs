//! `scan3d eval | report | sweep` (issue 6), run in-process on OctoMap's data.

mod common;

use common::run_cli;

fn data(rel: &str) -> String {
    common::octomap_data(rel).to_string_lossy().into_owned()
}

#[test]
fn eval_json_has_every_key_and_octomaps_counts() {
    let out = run_cli(&[
        "eval",
        "--reference",
        &data("geb079.bt"),
        &data("reference/geb079_sim_0.08.bt"),
        "--truth",
        &data("geb079.bt"),
        "--json",
    ])
    .unwrap();
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    for k in [
        "resolution",
        "voxels",
        "ref",
        "target",
        "confusion",
        "confusion_m3",
        "iou",
        "log_odds",
        "correlation",
        "mean_probability",
        "probability_deviation",
        "truth",
    ] {
        assert!(v.get(k).is_some(), "missing {k}");
    }
    for k in [
        "occupied",
        "free",
        "unknown",
        "ratio_occupied",
        "ratio_free",
        "ratio_unknown",
        "leaves",
    ] {
        assert!(
            v["ref"].get(k).is_some() && v["target"].get(k).is_some(),
            "{k}"
        );
    }
    assert_eq!(v["resolution"], 0.08);
    assert_eq!(v["confusion"][0], serde_json::json!([50949, 14, 134710]));
    assert_eq!(v["confusion"][1], serde_json::json!([92, 569046, 381621]));
    assert_eq!(v["ref"]["leaves"], 428144);
    assert_eq!(v["target"]["leaves"], 439443);
    let m3 = v["confusion_m3"][0][0].as_f64().unwrap();
    assert!((m3 - 50949.0 * 0.08f64.powi(3)).abs() < 1e-9);
    for k in ["occupied", "free", "unknown", "weighted"] {
        assert!(v["iou"][k].is_number(), "iou.{k}");
    }
    for k in ["sum", "mean", "common_voxels"] {
        assert!(v["log_odds"][k].is_number(), "log_odds.{k}");
    }
    for k in ["paper", "signed", "p_bar"] {
        assert!(v["correlation"][k].is_number(), "correlation.{k}");
    }
    // The target scored against the reference map as truth: its occupied voxels in U.
    let t = &v["truth"];
    assert_eq!(t["target_occupied"], 50949 + 92 + 28);
    assert_eq!(t["truth_occupied"], 50949 + 14 + 134710);
    assert_eq!(
        t["precision"].as_f64().unwrap(),
        50949.0 / (50949.0 + 92.0 + 28.0)
    );
    for k in [
        "recall",
        "f1",
        "precision_tolerant",
        "recall_tolerant",
        "f1_tolerant",
        "chamfer",
    ] {
        assert!(t[k].is_number(), "truth.{k}");
    }
}

#[test]
fn eval_table_and_errors() {
    let ot = data("reference/geb079_sim_0.1.ot");
    let bt = data("reference/geb079_sim_0.1.bt");
    let out = run_cli(&["eval", "--reference", &ot, &bt]).unwrap();
    assert!(out.contains("sum 85865.52"), "{out}");
    assert!(out.contains("over 556561 common voxels"), "{out}");
    assert!(
        out.starts_with(&format!("reference {ot}\ntarget    {bt}\n")),
        "{out}"
    );
    // The hidden `--ref` and the form of earlier versions (`eval REF TARGET`) give the same.
    assert_eq!(run_cli(&["eval", "--ref", &ot, &bt]).unwrap(), out);
    assert_eq!(run_cli(&["eval", &ot, &bt]).unwrap(), out);
    // Three maps, or a reference both ways, are refused by the parser.
    assert!(run_cli(&["eval", "--reference", &ot, &bt, &bt]).is_err());
    assert!(run_cli(&["eval", &bt]).is_err());
    let e = run_cli(&[
        "eval",
        "--reference",
        &ot,
        &data("reference/geb079_sim_0.2.bt"),
    ])
    .unwrap_err();
    assert!(e.to_string().contains("resolution mismatch"), "{e}");
    let text = data("mapcoll.txt");
    let e = run_cli(&["eval", "--reference", &ot, &text]).unwrap_err();
    assert_eq!(
        format!("{e:#}"),
        format!(
            "{text}: not an OctoMap file: the first line must start with \
             \"# Octomap OcTree binary file\" (.bt) or \"# Octomap OcTree file\" (.ot)"
        )
    );
    let e = run_cli(&["eval", "--reference", &ot, &ot, "--bbox", "1,2,3"]).unwrap_err();
    assert!(
        e.to_string()
            .contains("(6 finite numbers), got 3 in \"1,2,3\""),
        "{e}"
    );
    let e = run_cli(&[
        "eval",
        "--reference",
        &ot,
        &ot,
        "--bbox",
        "0,0,0,0.01,0.01,0.01",
    ])
    .unwrap_err();
    assert!(format!("{e:#}").contains("no voxel centre"), "{e:#}");
    // A box: only the voxels whose centre is inside count.
    let out = run_cli(&[
        "eval",
        "--reference",
        &ot,
        &ot,
        "--bbox",
        "-0.2,-0.2,-0.2,0.2,0.2,0.2",
        "--json",
    ])
    .unwrap();
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["voxels"], 64);
}

#[test]
fn report_writes_tables_json_and_figure() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("report");
    let out = run_cli(&[
        "report",
        "--reference",
        &data("reference/geb079_sim_0.1.ot"),
        "--maps",
        &data("reference/geb079_sim_0.1.bt"),
        &data("reference/geb079_sim_0.1.ot"),
        "--out",
        out_dir.to_str().unwrap(),
    ])
    .unwrap();
    assert!(out.contains("wrote"));
    let table = std::fs::read_to_string(out_dir.join("table.md")).unwrap();
    assert!(table.contains("Table III"));
    // geb079_sim at 0.1: 56 040 occupied of 483 761 leaves (.ot); the share is in voxels.
    assert!(table.contains("| 483761 |"), "{table}");
    assert!(table.contains("| 252824 |"), "{table}");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(json["maps"].as_array().unwrap().len(), 2);
    assert_eq!(json["maps"][1]["metrics"]["log_odds"]["sum"], 0.0);
    let svg = std::fs::read_to_string(out_dir.join("fig11.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("Fig. 11"));
    let png = std::fs::read(out_dir.join("fig11.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");

    // --json: metrics.json's object and the files written, nothing else on stdout; the
    // hidden --ref still names the reference.
    let json_dir = dir.path().join("report-json");
    let printed = run_cli(&[
        "report",
        "--ref",
        &data("reference/geb079_sim_0.1.ot"),
        "--maps",
        &data("reference/geb079_sim_0.1.bt"),
        &data("reference/geb079_sim_0.1.ot"),
        "--out",
        json_dir.to_str().unwrap(),
        "--json",
    ])
    .unwrap();
    let mut printed: serde_json::Value = serde_json::from_str(&printed).unwrap();
    let files = printed
        .as_object_mut()
        .unwrap()
        .remove("files")
        .expect("files");
    let names: Vec<&str> = files
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap().rsplit('/').next().unwrap())
        .collect();
    assert_eq!(
        names,
        ["table.md", "metrics.json", "fig11.svg", "fig11.png"]
    );
    let file: serde_json::Value =
        serde_json::from_slice(&std::fs::read(json_dir.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(printed, file);
    assert_eq!(printed["maps"][0]["name"], "geb079_sim_0.1");
    let weighted = printed["maps"][0]["metrics"]["iou"]["weighted"]
        .as_f64()
        .unwrap();
    assert!(weighted > 0.0 && weighted <= 1.0, "{weighted}");
}

#[test]
fn sweep_writes_fig12_with_octomaps_node_counts() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("sweep");
    run_cli(&[
        "sweep",
        &data("spherical_scan.graph"),
        "--resolution",
        "0.1,0.2",
        "--reps",
        "1",
        "--out",
        out_dir.to_str().unwrap(),
    ])
    .unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("sweep.json")).unwrap()).unwrap();
    let rows = json["rows"].as_array().unwrap();
    // research/octomap.md §8.1: spherical_scan has 6 296 nodes at 0.1 m and 1 598 at 0.2 m.
    assert_eq!(rows[0]["nodes"], 6296);
    assert_eq!(rows[1]["nodes"], 1598);
    assert_eq!(rows[1]["leaves"], 1189);
    assert_eq!(json["points"], 10201);
    // 425 occupied leaves at 0.2 m, all single voxels of 0.008 m³ (none pruned).
    let v = rows[1]["occupied_m3"].as_f64().unwrap();
    assert!((v - 425.0 * 0.008).abs() < 1e-9, "{v}");
    let png = std::fs::read(out_dir.join("fig12.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    assert!(
        std::fs::read_to_string(out_dir.join("fig12.svg"))
            .unwrap()
            .contains("Fig. 12")
    );
    let e = run_cli(&[
        "sweep",
        &data("mapcoll.txt"),
        "--out",
        out_dir.to_str().unwrap(),
    ])
    .unwrap_err();
    assert!(!e.to_string().is_empty());
}
