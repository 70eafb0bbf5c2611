//! The demo's report can be checked by hand: the `scan3d report` command line the demo prints,
//! run through the real `scan3d` CLI, writes the very table and `metrics.json` the demo's own
//! scoring wrote; the box it scores in holds the walls; the differences from the paper are
//! explained from the numbers.

use std::path::{Path, PathBuf};

use clap::Parser;
use scan3d_hw_sim::demo::{Map1Notes, against_paper, report_options};
use scan3d_hw_sim::maps::PASS_THROUGH_BOX;
use scan3d_hw_sim::truth::{GroundTruth, truth_map};
use scan3d_hw_sim::world::World;
use scan3d_map::cloud::RayBundle;
use scan3d_map::octree::{Resolution, SensorModel, VoxelMap};
use scan3d_server::report::MetricBox;

/// A scratch directory removed when dropped; its name holds a space and a quote, so the
/// printed command must quote it.
struct Scratch(PathBuf);

impl Scratch {
    fn new(tag: &str) -> Self {
        let dir = std::env::temp_dir().join(format!(
            "scan3d demo-report {tag} it's {}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("maps")).unwrap();
        Self(dir)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Splits a command line as a POSIX shell does for plain words and single-quoted ones.
fn shell_split(line: &str) -> Vec<String> {
    let mut words = Vec::new();
    let mut word: Option<String> = None;
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        match c {
            ' ' => words.extend(word.take()),
            '\'' => {
                let w = word.get_or_insert_with(String::new);
                for q in chars.by_ref() {
                    if q == '\'' {
                        break;
                    }
                    w.push(q);
                }
            }
            '\\' => {
                let w = word.get_or_insert_with(String::new);
                w.extend(chars.next());
            }
            c => word.get_or_insert_with(String::new).push(c),
        }
    }
    words.extend(word);
    words
}

/// A map of the simulated room as scanned from `origins`: rays to the true surface (sampled
/// every `spacing` m) inserted with OctoMap's sensor model.
fn scanned(truth: &GroundTruth, origins: &[[f64; 3]], spacing: f64, res: f64) -> Vec<u8> {
    let mut map = VoxelMap::new(Resolution::new(res).unwrap(), SensorModel::default());
    let points: Vec<[f32; 3]> = truth
        .sample(spacing)
        .iter()
        .map(|p| p.point.map(|c| c as f32))
        .filter(|p| p[1] < 5.9)
        .collect();
    for origin in origins {
        map.insert_bundle(
            &RayBundle {
                origin: *origin,
                points: points.clone(),
            },
            6.0,
        );
    }
    map.to_octree().to_bt_bytes()
}

fn write(path: &Path, bytes: &[u8]) {
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn the_printed_report_command_gives_the_demos_table() {
    let scratch = Scratch::new("same");
    let out = &scratch.0;
    let res = 0.1;
    let world = World::conference_room();
    let truth = GroundTruth::new(&world);
    let maps = out.join("maps");
    write(
        &maps.join("truth.bt"),
        &truth_map(&world, &truth, res)
            .unwrap()
            .to_octree()
            .to_bt_bytes(),
    );
    // map1: the Sweep's plane swept along a line through the room (origins every 0.5 m).
    let along: Vec<[f64; 3]> = (0..10)
        .map(|k| [1.6 + 0.5 * f64::from(k), 0.85, 1.0])
        .collect();
    write(&maps.join("map1.bt"), &scanned(&truth, &along, 0.2, res));
    write(
        &maps.join("map2.bt"),
        &scanned(&truth, &[[1.5, 3.0, 1.0]], 0.12, res),
    );
    write(
        &maps.join("map3.bt"),
        &scanned(&truth, &[[1.5, 1.2, 1.0], [6.5, 4.6, 1.0]], 0.12, res),
    );
    write(
        &maps.join("ref.bt"),
        &scanned(
            &truth,
            &[
                [1.2, 1.2, 1.0],
                [6.6, 1.6, 1.0],
                [6.6, 4.2, 1.0],
                [1.2, 4.6, 1.0],
            ],
            0.08,
            res,
        ),
    );

    // The demo's path: its options, the library call.
    let options = report_options(out, &["map1", "map2", "map3", "ref"]);
    assert_eq!(options.bbox, Some(PASS_THROUGH_BOX));
    let demo = options.write().unwrap();
    let demo_json = std::fs::read(out.join("report/metrics.json")).unwrap();
    assert_eq!(
        std::fs::read_to_string(out.join("report/table.md")).unwrap(),
        demo.table
    );

    // The printed line spells out every option, then runs through the real CLI as typed.
    let line = options.command_line();
    for option in [
        "--reference",
        "--maps",
        "--truth",
        "--bbox -0.2,-0.2,-0.2,8.05,5.9,3.2",
        "--out",
    ] {
        assert!(line.contains(option), "{option} missing from {line}");
    }
    let words = shell_split(&line);
    assert_eq!(words[0], "scan3d");
    std::fs::remove_dir_all(out.join("report")).unwrap();
    let cli = scan3d_server::cli::Cli::try_parse_from(&words).unwrap();
    let mut printed = Vec::new();
    scan3d_server::cli::execute(cli, &mut printed).unwrap();
    let by_hand = std::fs::read_to_string(out.join("report/table.md")).unwrap();
    assert_eq!(by_hand, demo.table);
    assert_eq!(
        std::fs::read(out.join("report/metrics.json")).unwrap(),
        demo_json
    );
    assert!(String::from_utf8(printed).unwrap().contains(&demo.table));

    // The footnote names the box used; the paper's Table III stands beside this run's.
    assert!(
        demo.table
            .contains("U is the same box for every pair, `--bbox -0.2,-0.2,-0.2,8.05,5.9,3.2`"),
        "{}",
        demo.table
    );
    assert!(
        demo.table.contains("| 30.4077 % | 69.5923 % | 22491 |"),
        "{}",
        demo.table
    );
    assert!(demo.table.contains("| 19.061 % | 80.939 % | 18320 |"));
    assert!(demo.table.contains("## Fig. 11 beside the paper"));
    // Four rows in Table III, map1 first, each beside the paper's; three maps in Fig. 11
    // beside ref against itself.
    let table_iii: Vec<&str> = demo
        .table
        .lines()
        .skip_while(|l| !l.starts_with("## Table III"))
        .filter(|l| l.starts_with("| **"))
        .take_while(|l| !l.starts_with("| **truth"))
        .collect();
    let labels: Vec<&str> = table_iii
        .iter()
        .map(|l| l.split("**").nth(1).unwrap())
        .collect();
    assert_eq!(labels, ["map1", "map2", "map3", "ref"], "{}", demo.table);
    assert!(
        table_iii[0].ends_with("| 13.059 % | 86.941 % | 17140 |"),
        "{}",
        table_iii[0]
    );
    let fig11: Vec<&str> = demo
        .table
        .lines()
        .skip_while(|l| !l.starts_with("## Fig. 11 beside the paper"))
        .filter(|l| l.starts_with("| **"))
        .collect();
    assert_eq!(fig11.len(), 4, "{}", demo.table);
    assert!(fig11[0].starts_with("| **map1** |") && fig11[0].contains("the worst of map1–map3"));
    let drawn: Vec<&str> = demo.metrics["maps"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|m| !m["metrics"].is_null())
        .map(|m| m["name"].as_str().unwrap())
        .collect();
    assert_eq!(drawn, ["map1", "map2", "map3"]);
    // Scored against the truth too.
    assert!(demo.metrics["maps"][0]["metrics"]["truth"]["f1"].is_number());

    // Scored without the box (what a reader would type without the printed line), the
    // numbers differ: the box is part of the result.
    let mut unboxed = options.clone();
    unboxed.bbox = None;
    unboxed.out = out.join("unboxed");
    let other = unboxed.write().unwrap();
    assert_ne!(other.table, demo.table);
    assert!(other.table.contains("U is each pair's own box"));

    // The differences from the paper, one sentence each, from the numbers.
    let notes = against_paper(&demo.metrics, None, None);
    assert!(notes.contains("Leaf nodes: ref has"), "{notes}");
    assert!(notes.contains("Occupied ratio: ref"), "{notes}");
    assert!(notes.contains("Order of Fig. 11"), "{notes}");
    assert!(notes.contains("as the paper's ideal (1, 0, 1)"), "{notes}");
    assert!(notes.contains("map1 (mapping along movement) is not made"));

    // With the pass: map1's surface distances beside map2's against the goal, and the
    // trajectory error against the truth, from the numbers given.
    let accuracy = |mean_m: f64, p95_m: f64| scan3d_hw_sim::truth::Accuracy {
        points: 1000,
        mean_m,
        p95_m,
        max_m: 0.1,
    };
    let error = scan3d_slam::tum::TrajectoryError {
        compared: 800,
        outside: 0,
        position_rmse_m: 0.0123,
        position_max_m: 0.04,
        heading_rmse_deg: 0.61,
        heading_max_deg: 1.5,
    };
    let map1 = Map1Notes {
        source: "offline".into(),
        points: 1000,
        offline_accuracy: Some(accuracy(0.018, 0.05)),
        live_accuracy: None,
        map2_accuracy: Some(accuracy(0.010, 0.03)),
        matcher: Some(error),
        fused: None,
        fusion_failure: Some("no IMU".into()),
        yaw_rmse: vec![
            ("gyro integration alone".into(), 2.0, 100),
            ("matcher alone".into(), 0.5, 100),
            ("CI fusion".into(), 0.4, 100),
        ],
    };
    let notes = against_paper(&demo.metrics, None, Some(&map1));
    assert!(!notes.contains("is not made"), "{notes}");
    assert!(
        notes.contains("map1 (offline) against the true surface: mean 18.0 mm, p95 50.0 mm (map2: mean 10.0 mm, p95 30.0 mm); map1's mean is 1.80 × map2's (goal ≤ 1.5: missed)"),
        "{notes}"
    );
    assert!(
        notes.contains("scan matcher (pose stage): position RMSE 1.23 cm (max 4.00 cm, goal ≤ 3 cm: met), heading RMSE 0.610° (max 1.500°, goal ≤ 0.5°: missed)"),
        "{notes}"
    );
    assert!(notes.contains("map1 (live): not made"), "{notes}");
    assert!(notes.contains("not made in this run (no IMU;"), "{notes}");
    assert!(
        notes.contains(
            "The fused yaw error is 0.20 of gyro integration alone's, 0.80 of matcher alone's"
        ),
        "{notes}"
    );
    assert!(notes.contains("Table III, map1:"), "{notes}");
    assert!(notes.contains("Fig. 11, map1: IoU"), "{notes}");
}

#[test]
fn the_scoring_box_holds_every_wall_of_the_room() {
    // The truth map's occupied voxels are the walls' inner faces; scored inside the demo's box,
    // the truth against itself keeps every one of them below the glass cut (y <= 5.9 m).
    let world = World::conference_room();
    let truth = GroundTruth::new(&world);
    for res in [0.05, 0.1] {
        let scratch = Scratch::new(&format!("box {res}"));
        let maps = scratch.0.join("maps");
        let tree = truth_map(&world, &truth, res).unwrap().to_octree();
        write(&maps.join("truth.bt"), &tree.to_bt_bytes());
        write(&maps.join("ref.bt"), &tree.to_bt_bytes());
        let options = report_options(&scratch.0, &["ref"]);
        let written = options.write().unwrap();
        let t = &written.metrics["reference"]["metrics"]["truth"];
        // A box 10 m larger on every side, with the same cut before the glass, holds no truth
        // voxel more.
        let mut larger = options.clone();
        larger.bbox = Some(MetricBox {
            min: PASS_THROUGH_BOX.min.map(|c| c - 10.0),
            max: [
                PASS_THROUGH_BOX.max[0] + 10.0,
                PASS_THROUGH_BOX.max[1],
                PASS_THROUGH_BOX.max[2] + 10.0,
            ],
        });
        larger.out = scratch.0.join("larger");
        let wide = larger.write().unwrap();
        let w = &wide.metrics["reference"]["metrics"]["truth"];
        assert!(t["truth_occupied"].as_u64().unwrap() > 0);
        assert_eq!(t["truth_occupied"], w["truth_occupied"], "at {res} m");
        assert_eq!(t["precision_tolerant"], 1.0);
    }
}
