//! `scan3d-sim demo`: the whole system on one machine.
//!
//! 1. **Streaming.** Both emulated lidars run on real ptys, the edge daemon reads them, and a
//!    server on loopback receives them (real QUIC, mutual TLS, certificates paired in a
//!    temporary directory). The server records the session to `DIR/session/`, and the demo
//!    writes `DIR/scans/*.ply` from what the **server** received. Samples lost must be 0.
//! 2. **The trolley pass** (the paper's §III-B, its map1, [`crate::demo_trolley`]): the rig's
//!    trolley with its erroneous IMU pushed around the room's table through the same
//!    in-process edge daemon and a live server, the pass opened and closed through the server
//!    as `scan3d trolley start --name map1` / `stop` do; the recording goes to
//!    `DIR/moving-sessions/`, map1 to `DIR/clouds/map1.ply` and `DIR/maps/map1.bt` (Table II:
//!    pass-through box only), the trajectory of `base` to `DIR/trajectories/map1.tum` and the
//!    true one to `DIR/truth/trolley.tum` (both edge-clock seconds, room frame).
//! 3. **Static 3D scans** (the paper's §III-A, [`crate::maps`]): `map2`, `map3` and `ref` of
//!    the conference room, each commanded position by position through the server to the edge,
//!    which steps the emulated turntable (PCA9685 on the emulated I2C bus) during the Sweep's
//!    blind sector. Clouds assembled from the recordings go to `DIR/clouds/*.ply|.scans`, with
//!    their accuracy against the true surface; the truth itself goes to `DIR/truth/`.
//! 4. **Maps.** The server runs the live pipeline while the edge scans (Table II filters per
//!    revolution, the OctoMap-identical octree at `--resolution`, 0.05 m); the maps are the live
//!    daemon's, taken with `scan3d snapshot` through its control socket
//!    (`DIR/snapshots/<map>/`, copied to `DIR/maps/{map2,map3,ref}.bt`), with the ground-truth
//!    map `DIR/maps/truth.bt` beside them.
//! 5. **Evaluation** (the paper's §IV): every map (map1, map2, map3) against `ref` and against the truth inside
//!    Table II's pass-through box (the room with its walls), by the very `scan3d report` call
//!    the demo prints ([`report_options`], `scan3d_server::report::ReportOptions`) →
//!    `DIR/report/` (`table.md`, `metrics.json`, `fig11.svg|png`), `scan3d sweep`'s Fig. 12 on
//!    `ref`'s filtered cloud → `fig12.svg|png`, and the differences from the paper's numbers,
//!    explained, with map1's trajectory error and point-to-surface distances beside map2's →
//!    `against-paper.md`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::daemon::DaemonReport;
use scan3d_map::cloud::scans::RevolutionCollector;
use scan3d_protocol::{Body, SensorId};
use scan3d_server::ingest::server::{IngestEvent, IngestStats};
use scan3d_server::pose::timesync::ClockModel;
use scan3d_server::recording::{session_dir, topic};
use scan3d_server::report::{RESOLUTION_SWEEP_M, ReportOptions, opt, write_resolution_sweep};
use scan3d_slam::tum::TrajectoryError;

use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::io;

use crate::demo_trolley::{self, PASS_NAME, PassResult, PassSetup};
use crate::installation::{self, Delivery, EdgeThread, LidarOptions, ServerThread, SimLidars};
use crate::maps::{
    MapPlan, MapResult, MapSetup, PASS_THROUGH_BOX, map_pipeline, paper_maps, scan_map,
};
use crate::noise::RangeNoise;
use crate::trolley::TrolleyPath;
use crate::truth::{Accuracy, GroundTruth, truth_map, write_world_description};
use crate::world::World;

/// Simulated seconds of the trolley's turn in place for `scan3d-edge calibrate mag` before the
/// pass: one turn at 15 °/s on average (30 °/s at most), a slow push by hand; at the pass's
/// time scale a few real seconds.
pub const MAG_TURN_S: f64 = 24.0;

/// Options of `scan3d-sim demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Output directory: the recordings (`session/`, `moving-sessions/`, `static-sessions/`),
    /// `scans/*.ply`, `clouds/`, `trajectories/`, `truth/`, `snapshots/`, `maps/` and `report/`
    /// go below it, replacing those of an earlier run.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Seconds of sensor data the server must receive per lidar.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Simulated seconds per real second (devices and edge clock alike).
    #[arg(long, default_value_t = 10.0)]
    pub time_scale: f64,
    /// Simulated seconds per real second during the trolley pass (at most --time-scale): the
    /// edge stamps samples by their arrival, so a late wake-up of k ms misplaces a sample by
    /// k × scale ms of a moving trolley; ×5 keeps the pass within the two minutes.
    #[arg(long, default_value_t = 5.0)]
    pub pass_time_scale: f64,
    /// Per-byte corruption rate injected on both serial lines (stray bytes and bit flips).
    #[arg(long, default_value_t = 0.0)]
    pub corrupt: f64,
    /// Seed for the world's noise and the fault injection.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Octree resolution of the maps, metres.
    #[arg(long, alias = "res", value_name = "M", default_value_t = 0.05)]
    pub resolution: f64,
    /// Which maps to make (comma-separated among map1, the trolley pass, and the static map2,
    /// map3, ref; empty = none).
    #[arg(long, value_delimiter = ',', default_value = "map1,map2,map3,ref")]
    pub maps: Vec<String>,
}

/// What the demo measured.
#[derive(Debug, Clone)]
pub struct DemoReport {
    /// The recorded session's directory.
    pub session_dir: PathBuf,
    /// Frames the server recorded, per MCAP topic.
    pub frames_per_topic: BTreeMap<String, u64>,
    /// Per lidar: emulator → edge → recording accounting.
    pub deliveries: Vec<Delivery>,
    /// The edge daemon's report (CPU time, uplink counters).
    pub edge: DaemonReport,
    /// The server's counters.
    pub server: IngestStats,
    /// The last time-sync clock model.
    pub time_sync: Option<ClockModel>,
    /// How much faster than real time the simulation (and so the edge's clock) ran.
    pub time_scale: f64,
    /// The maps' octree resolution, metres.
    pub resolution: f64,
    /// Seconds of sensor time the server received, per lidar.
    pub sensor_seconds: BTreeMap<SensorId, f64>,
    /// PLY files written from the server's frames.
    pub scans: Vec<PathBuf>,
    /// The trolley pass (map1), when made.
    pub pass: Option<PassResult>,
    /// The static maps made.
    pub maps: Vec<MapResult>,
    /// Ground-truth files written.
    pub truth_files: Vec<PathBuf>,
    /// Occupancy maps written (`DIR/maps/*.bt`).
    pub octrees: Vec<PathBuf>,
    /// The evaluation's `table.md` (Table III and the metrics); without maps, the line saying so.
    pub table: String,
    /// The `scan3d report` command line the evaluation ran (none without maps).
    pub report_command: Option<String>,
    /// `report/against-paper.md`: the differences from the paper's numbers, explained.
    pub against_paper: String,
    /// Wall time of the run.
    pub wall: Duration,
}

impl DemoReport {
    /// Samples that did not make it from the emulators' wire into the recording, over the
    /// recorded span, plus any difference between what the edge sent and what was recorded.
    pub fn samples_lost(&self) -> u64 {
        self.deliveries.iter().map(|d| d.lost()).sum()
    }
}

/// Runs the demo, prints its summary and fails if any sample was lost.
pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let report = run_demo(args)?;
    print!("{}", summary(&report));
    // What the server reported recording, per topic: an independent MCAP reader can check
    // the files against it (`tests/interop/mcap_check.py --expect`).
    let topics = args.out.join("recorded-topics.json");
    let json = serde_json::to_string_pretty(&report.frames_per_topic)?;
    std::fs::write(&topics, json).with_context(|| format!("cannot write {}", topics.display()))?;
    let lost = report.samples_lost();
    anyhow::ensure!(lost == 0 || args.corrupt > 0.0, "{lost} samples lost");
    Ok(())
}

/// Runs the demo and returns what it measured (for tests and the CLI).
pub fn run_demo(args: &DemoArgs) -> anyhow::Result<DemoReport> {
    anyhow::ensure!(args.seconds > 0.0, "--seconds must be positive");
    anyhow::ensure!(
        args.time_scale > 0.0 && args.time_scale.is_finite(),
        "--time-scale must be positive"
    );
    anyhow::ensure!(
        args.pass_time_scale > 0.0 && args.pass_time_scale.is_finite(),
        "--pass-time-scale must be positive"
    );
    anyhow::ensure!(
        (0.0..=0.1).contains(&args.corrupt),
        "--corrupt must be within 0..=0.1"
    );
    let with_pass = args.maps.iter().any(|name| name == PASS_NAME);
    let plans: Vec<MapPlan> = args
        .maps
        .iter()
        .filter(|name| !name.is_empty() && name.as_str() != PASS_NAME)
        .map(|name| {
            paper_maps()
                .into_iter()
                .find(|plan| plan.name == name)
                .ok_or_else(|| anyhow::anyhow!("unknown map {name:?} (map1, map2, map3, ref)"))
        })
        .collect::<anyhow::Result<_>>()?;
    let started = Instant::now();
    let data_dir = args.out.join("session");
    let scans_dir = args.out.join("scans");
    for dir in [
        &data_dir,
        &scans_dir,
        &args.out.join("clouds"),
        &args.out.join("truth"),
        &args.out.join("maps"),
        &args.out.join("snapshots"),
        &args.out.join("static-sessions"),
        &args.out.join("moving-sessions"),
        &args.out.join("trajectories"),
    ] {
        // Each run starts afresh: an old recording would mix two runs' sessions.
        if dir.exists() {
            std::fs::remove_dir_all(dir)
                .with_context(|| format!("cannot clear {}", dir.display()))?;
        }
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let work = std::env::temp_dir().join(format!("scan3d-demo-{}", std::process::id()));
    let result = run_in(args, &work, &data_dir, &scans_dir, started).and_then(|mut report| {
        let world = Arc::new(World::conference_room());
        let truth = GroundTruth::new(&world);
        report.truth_files = write_truth(&world, &truth, &args.out.join("truth"))?;
        let setup = MapSetup {
            world: &world,
            truth: &truth,
            work: &work,
            data_dir: &args.out.join("static-sessions"),
            clouds_dir: &args.out.join("clouds"),
            time_scale: args.time_scale,
            seed: args.seed,
            noise: RangeNoise::SWEEP,
            resolution_m: args.resolution,
            queue_frames: 256,
            snapshots_dir: &args.out.join("snapshots"),
            full_rates: false,
        };
        if with_pass {
            let path = Arc::new(TrolleyPath::demo_room());
            println!(
                "trolley pass: {PASS_NAME} (the magnetometer calibrated over a {MAG_TURN_S:.0} s \
                 turn in place, then {:.1} m around the table in {:.0} s after {:.0} s at rest, \
                 erroneous IMU; time x{}) ...",
                path.length_m(),
                path.motion_s(),
                path.rest_s(),
                args.pass_time_scale.min(args.time_scale)
            );
            let pass = demo_trolley::run_pass(&PassSetup {
                world: &world,
                truth: &truth,
                path,
                work: &work,
                data_dir: &args.out.join("moving-sessions"),
                out: &args.out,
                snapshots_dir: &args.out.join("snapshots"),
                time_scale: args.pass_time_scale.min(args.time_scale),
                seed: args.seed,
                resolution_m: args.resolution,
                queue_frames: 256,
                mag_turn_s: MAG_TURN_S,
            })?;
            report.truth_files.push(pass.truth_file.clone());
            report.octrees.push(pass.octree.clone());
            report.pass = Some(pass);
        }
        for plan in &plans {
            println!(
                "static scans: {} ({} position(s), Sweep {} Hz) ...",
                plan.name,
                plan.positions.len(),
                plan.motor_hz
            );
            report.maps.push(scan_map(plan, &setup)?);
        }
        let maps_dir = args.out.join("maps");
        for result in &report.maps {
            // The live daemon's map, named after the plan for the report.
            let live = result.snapshot_dir.join("map.bt");
            let path = maps_dir.join(format!("{}.bt", result.plan.name));
            std::fs::copy(&live, &path)
                .with_context(|| format!("cannot copy {} to {}", live.display(), path.display()))?;
            report.octrees.push(path);
        }
        if !report.maps.is_empty() || report.pass.is_some() {
            let tree = truth_map(&world, &truth, args.resolution)?.to_octree();
            let path = maps_dir.join("truth.bt");
            std::fs::write(&path, tree.to_bt_bytes())
                .with_context(|| format!("cannot write {}", path.display()))?;
            report.octrees.push(path);
            let evaluation = evaluate_maps(&args.out, report.pass.as_ref(), &report.maps)?;
            report.report_command = Some(evaluation.command);
            report.table = evaluation.table;
            report.against_paper = evaluation.against_paper;
        } else {
            let dir = args.out.join("report");
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create {}", dir.display()))?;
            let path = dir.join("table.md");
            std::fs::write(&path, format!("{NO_MAPS}\n"))
                .with_context(|| format!("cannot write {}", path.display()))?;
            report.table = NO_MAPS.to_string();
        }
        report.wall = started.elapsed();
        Ok(report)
    });
    let _ = std::fs::remove_dir_all(&work);
    result
}

/// The `scan3d report` the demo runs: the maps `names` (`DIR/maps/<name>.bt`) against `ref`
/// (or the first map when `ref` is not among them) and the truth map, inside Table II's
/// pass-through box (the room with its walls, [`PASS_THROUGH_BOX`]), into `DIR/report/`.
pub fn report_options(out: &Path, names: &[&str]) -> ReportOptions {
    let map_path = |name: &str| out.join("maps").join(format!("{name}.bt"));
    let reference = if names.contains(&"ref") {
        map_path("ref")
    } else {
        map_path(names.first().copied().unwrap_or("ref"))
    };
    let maps: Vec<PathBuf> = names
        .iter()
        .map(|name| map_path(name))
        .filter(|path| *path != reference || names.len() == 1)
        .collect();
    ReportOptions {
        reference,
        maps,
        truth: Some(map_path("truth")),
        bbox: Some(PASS_THROUGH_BOX),
        out: out.join("report"),
    }
}

/// What the demo's evaluation produced.
struct Evaluation {
    command: String,
    table: String,
    against_paper: String,
}

/// Scores the maps (map1 first when the pass ran) as `scan3d report` does ([`report_options`],
/// the same library call), makes `scan3d sweep`'s Fig. 12 from `ref`'s filtered cloud (the live
/// snapshot's) and writes `DIR/report/against-paper.md`.
fn evaluate_maps(
    out: &Path,
    pass: Option<&PassResult>,
    maps: &[MapResult],
) -> anyhow::Result<Evaluation> {
    let names: Vec<&str> = pass
        .map(|_| PASS_NAME)
        .into_iter()
        .chain(maps.iter().map(|m| m.plan.name))
        .collect();
    let options = report_options(out, &names);
    let written = options.write()?;
    // The live daemon's filtered cloud of `ref`.
    let cloud = out.join("snapshots/ref/cloud.ply");
    let mut sweep = None;
    if cloud.exists() {
        write_resolution_sweep(
            &cloud,
            &RESOLUTION_SWEEP_M,
            -1.0,
            1,
            &options.out,
            &mut std::io::sink(),
        )?;
        let path = options.out.join("sweep.json");
        let bytes =
            std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
        sweep = Some(serde_json::from_slice(&bytes)?);
    }
    let map1 = pass.map(|pass| Map1Notes {
        source: pass.source.to_string(),
        points: pass.points(),
        offline_accuracy: pass.offline_accuracy,
        live_accuracy: pass.live_accuracy,
        map2_accuracy: maps
            .iter()
            .find(|m| m.plan.name == "map2")
            .and_then(|m| m.accuracy),
        matcher: pass.matcher_error.clone(),
        fused: pass.fused_error.clone(),
        fusion_failure: pass.fusion_failure.clone(),
        yaw_rmse: pass
            .yaw_rmse
            .iter()
            .map(|r| (r.label.clone(), r.rmse_deg, r.poses))
            .collect(),
    });
    let against_paper = against_paper(&written.metrics, sweep.as_ref(), map1.as_ref());
    let path = options.out.join("against-paper.md");
    std::fs::write(&path, &against_paper)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(Evaluation {
        command: options.command_line(),
        table: written.table,
        against_paper,
    })
}

/// What `against-paper.md` says of map1 beyond the report's metrics: its points against the
/// true surface beside map2's, and the trajectory of `base` against the truth.
#[derive(Debug, Clone, Default)]
pub struct Map1Notes {
    /// Which products map1 is ([`demo_trolley::MapSource`], as text).
    pub source: String,
    /// Points in map1's cloud.
    pub points: usize,
    /// The offline assembly's point-to-surface distances.
    pub offline_accuracy: Option<Accuracy>,
    /// The live snapshot's, when the live server made map1.
    pub live_accuracy: Option<Accuracy>,
    /// map2's, for the goal (map1's mean ≤ 1.5 × map2's).
    pub map2_accuracy: Option<Accuracy>,
    /// The scan matcher's trajectory (the pose stage's) against the truth.
    pub matcher: Option<TrajectoryError>,
    /// The CI-fused trajectory against the truth; `None` when not made.
    pub fused: Option<TrajectoryError>,
    /// Why there is no fused trajectory, when there is none.
    pub fusion_failure: Option<String>,
    /// Fig. 5's sources' yaw RMSE against the truth: (source, degrees, poses).
    pub yaw_rmse: Vec<(String, f64, usize)>,
}

/// The demo's goal for map1's mean point-to-surface distance, as a multiple of map2's.
pub const MAP1_SURFACE_GOAL_RATIO: f64 = 1.5;
/// The demo's goal for the trajectory's position RMSE, metres.
pub const ATE_POSITION_GOAL_M: f64 = 0.03;
/// The demo's goal for the trajectory's heading RMSE, degrees.
pub const ATE_HEADING_GOAL_DEG: f64 = 0.5;

/// One line on a trajectory error against the demo's goals.
fn ate_text(label: &str, e: &TrajectoryError) -> String {
    let met = |ok: bool| if ok { "met" } else { "missed" };
    format!(
        "{label}: position RMSE {:.2} cm (max {:.2} cm, goal ≤ {} cm: {}), heading RMSE {:.3}° \
         (max {:.3}°, goal ≤ {}°: {}), {} poses",
        e.position_rmse_m * 100.0,
        e.position_max_m * 100.0,
        ATE_POSITION_GOAL_M * 100.0,
        met(e.position_rmse_m <= ATE_POSITION_GOAL_M),
        e.heading_rmse_deg,
        e.heading_max_deg,
        ATE_HEADING_GOAL_DEG,
        met(e.heading_rmse_deg <= ATE_HEADING_GOAL_DEG),
        e.compared
    )
}

/// map1's sentences of `against-paper.md`.
fn map1_text(s: &mut String, notes: &Map1Notes, metrics: &serde_json::Value) {
    let f = |v: &serde_json::Value| v.as_f64();
    let _ = writeln!(
        s,
        "- map1 is the trolley pass ({}), {} points.",
        notes.source, notes.points
    );
    let mm = |a: &Accuracy| format!("mean {:.1} mm, p95 {:.1} mm", a.mean_m * 1e3, a.p95_m * 1e3);
    for (how, accuracy) in [
        ("offline", &notes.offline_accuracy),
        ("live", &notes.live_accuracy),
    ] {
        match (accuracy, &notes.map2_accuracy) {
            (Some(m1), Some(m2)) => {
                let ratio = m1.mean_m / m2.mean_m;
                let _ = writeln!(
                    s,
                    "- map1 ({how}) against the true surface: {} (map2: {}); map1's mean is \
                     {ratio:.2} × map2's (goal ≤ {MAP1_SURFACE_GOAL_RATIO}: {}).",
                    mm(m1),
                    mm(m2),
                    if ratio <= MAP1_SURFACE_GOAL_RATIO {
                        "met"
                    } else {
                        "missed"
                    }
                );
            }
            (Some(m1), None) => {
                let _ = writeln!(
                    s,
                    "- map1 ({how}) against the true surface: {} (map2 not made in this run).",
                    mm(m1)
                );
            }
            (None, _) => {
                let _ = writeln!(s, "- map1 ({how}): not made or no point to score.");
            }
        }
    }
    let _ = writeln!(
        s,
        "- Trajectory of `base` (`trajectories/map1.tum` against `truth/trolley.tum`, edge-clock \
         seconds, room frame, no alignment fitted: the pass's start anchors it)."
    );
    match &notes.matcher {
        Some(e) => {
            let _ = writeln!(s, "  - {}", ate_text("scan matcher (pose stage)", e));
        }
        None => {
            let _ = writeln!(s, "  - scan matcher: no pose within the truth's span.");
        }
    }
    match &notes.fused {
        Some(e) => {
            let _ = writeln!(s, "  - {}", ate_text("matcher + CI yaw fusion", e));
        }
        None => {
            let _ = writeln!(
                s,
                "  - matcher + CI yaw fusion: not made in this run ({}; \
                 `trajectories/map1.tum` is the matcher's).",
                notes.fusion_failure.as_deref().unwrap_or("no fused pose")
            );
        }
    }
    if !notes.yaw_rmse.is_empty() {
        let list = notes
            .yaw_rmse
            .iter()
            .map(|(label, deg, poses)| format!("{label} {deg:.3}° ({poses} poses)"))
            .collect::<Vec<_>>()
            .join(", ");
        let _ = writeln!(
            s,
            "- Fig. 5 (`report/fig5.svg|png`), yaw RMSE against the truth over the pass: {list}."
        );
        let fused = notes.yaw_rmse.iter().find(|r| r.0 == "CI fusion");
        if let Some((_, f, _)) = fused {
            let ratios = notes
                .yaw_rmse
                .iter()
                .filter(|r| r.0 != "CI fusion" && r.1.is_finite() && r.1 > 0.0)
                .map(|(label, deg, _)| format!("{:.2} of {label}'s", f / deg))
                .collect::<Vec<_>>()
                .join(", ");
            let _ = writeln!(
                s,
                "  The fused yaw error is {ratios}; the paper says the fusion halves the \
                 deviation of a single source (covariance intersection of two sources cannot \
                 reach half of the better one)."
            );
        }
    }
    let map = |name: &str| {
        metrics["maps"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|m| m["name"] == name)
    };
    if let Some(m1) = map(PASS_NAME) {
        let occupied = f(&m1["summary"]["occupied_share"]);
        let leaves = m1["summary"]["leaves"].as_u64();
        if let (Some(o), Some(leaves)) = (occupied, leaves) {
            let _ = writeln!(
                s,
                "- Table III, map1: {:.2} % occupied and {leaves} leaves here against 13.059 % and \
                 17140 in the paper: as for ref, the leaves follow this run's voxel size and \
                 the share the simulated room; the paper calls its map1 \"very sparse\", this \
                 one is the Sweep's plane swept at 5 Hz along the whole path.",
                o * 100.0
            );
        }
        let iou = |name: &str| map(name).and_then(|m| f(&m["metrics"]["iou"]["weighted"]));
        if let Some(i1) = iou(PASS_NAME) {
            let others: Vec<(&str, f64)> = ["map2", "map3"]
                .into_iter()
                .filter_map(|n| iou(n).map(|i| (n, i)))
                .collect();
            let worst = others.iter().all(|(_, i)| i1 <= *i);
            let list = others
                .iter()
                .map(|(n, i)| format!("{n} {i:.4}"))
                .collect::<Vec<_>>()
                .join(", ");
            let _ = writeln!(
                s,
                "- Fig. 11, map1: IoU {i1:.4} ({list}): {}",
                if others.is_empty() {
                    "no static map to order it against".to_string()
                } else if worst {
                    "the worst, as in the paper".to_string()
                } else {
                    "not the worst, unlike the paper (which calls its map1 sparse, its octomap \
                     with many defects)"
                        .to_string()
                }
            );
        }
    }
}

/// One sentence per difference between this run and the paper's Table III, Fig. 11 and
/// Fig. 12 that the simulation explains, from `scan3d report`'s `metrics.json` and
/// `scan3d sweep`'s `sweep.json` values, with map1's notes when the pass ran.
pub fn against_paper(
    metrics: &serde_json::Value,
    sweep: Option<&serde_json::Value>,
    map1: Option<&Map1Notes>,
) -> String {
    let mut s = String::from("## Against the paper\n\n");
    let f = |v: &serde_json::Value| v.as_f64();
    let map = |name: &str| {
        metrics["maps"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|m| m["name"] == name)
    };
    let reference = &metrics["reference"];
    let resolution = f(&reference["metrics"]["resolution"]);
    let res_text = resolution.map_or_else(|| "?".into(), |r| format!("{r}"));
    if let Some(leaves) = reference["summary"]["leaves"].as_u64() {
        let _ = writeln!(
            s,
            "- Leaf nodes: ref has {leaves} here against 22491 in the paper: this run's voxels are \
             {res_text} m, and a surface takes about four times the leaves per halving of the \
             voxel edge; the paper does not state its maps' resolution."
        );
    }
    let occupied = f(&reference["summary"]["occupied_share"]);
    let truth_occupied = f(&metrics["truth"]["summary"]["occupied_share"]);
    if let (Some(o), Some(t)) = (occupied, truth_occupied) {
        let _ = writeln!(
            s,
            "- Occupied ratio: ref {:.2} % here against 30.4077 % in the paper: the true map of \
             the simulated room at {res_text} m is itself {:.2} % occupied (one layer of wall, \
             floor and ceiling voxels around 8 × 6 × 3 m of free air, one table, chairs and \
             boxes), so the share follows from the room and the voxel size, not from the scanner.",
            o * 100.0,
            t * 100.0
        );
    }
    let iou = |name: &str| map(name).and_then(|m| f(&m["metrics"]["iou"]["weighted"]));
    let common =
        |name: &str| map(name).and_then(|m| m["metrics"]["log_odds"]["common_voxels"].as_u64());
    let ref_known = reference["metrics"]["log_odds"]["common_voxels"].as_u64();
    if let (Some(i2), Some(i3), Some(c2), Some(c3), Some(known)) = (
        iou("map2"),
        iou("map3"),
        common("map2"),
        common("map3"),
        ref_known,
    ) {
        let share = |c: u64| c as f64 / known.max(1) as f64 * 100.0;
        if i2 < i3 {
            let _ = writeln!(
                s,
                "- Order of Fig. 11: map3 (IoU {i3:.4}) scores above map2 ({i2:.4}) here, the \
                 reverse of the paper's order: from its one position map2 knows {:.0} % of the \
                 voxels ref knows, map3 from four positions {:.0} %; in the simulation every \
                 position sees the same room with the same Sweep noise, so the metrics follow \
                 coverage.",
                share(c2),
                share(c3)
            );
        } else {
            let _ = writeln!(
                s,
                "- Order of Fig. 11: map2 (IoU {i2:.4}) scores at or above map3 ({i3:.4}), as in \
                 the paper (map2 knows {:.0} % of the voxels ref knows, map3 {:.0} %).",
                share(c2),
                share(c3)
            );
        }
    }
    if let Some(i) = f(&reference["metrics"]["iou"]["weighted"]) {
        let _ = writeln!(
            s,
            "- ref against itself: IoU {i:.4}, log-odds {}, correlation {}, as the paper's ideal \
             (1, 0, 1).",
            opt(f(&reference["metrics"]["log_odds"]["mean"]), 5),
            opt(f(&reference["metrics"]["correlation"]["paper"]), 4)
        );
    }
    match map1 {
        Some(notes) => map1_text(&mut s, notes, metrics),
        None => {
            let _ = writeln!(
                s,
                "- map1 (mapping along movement) is not made: this run made no trolley pass."
            );
        }
    }
    let row = sweep.and_then(|sw| {
        sw["rows"]
            .as_array()?
            .iter()
            .find(|r| f(&r["resolution"]).is_some_and(|x| (x - 0.2).abs() < 1e-9))
            .cloned()
    });
    if let Some(row) = row {
        let _ = writeln!(
            s,
            "- Fig. 12 at 0.20 m: ref has {} nodes and its evaluation took {:.1} ms here, against \
             9979 nodes and 75 ms in the paper: the node count follows the simulated room's size \
             and what the six positions reach, and the time is this machine's, not the paper's \
             laptop.",
            row["nodes"].as_u64().unwrap_or(0),
            f(&row["eval_s"]).unwrap_or(f64::NAN) * 1e3
        );
    }
    s
}

/// The line the demo writes as its report when it made no static map.
pub const NO_MAPS: &str =
    "no 3D data: this run made no static map (--maps was empty), so there is nothing to score";

/// Writes the ground truth for evaluation: the world description (`world.toml`, loadable with
/// `World::load`) and the true surface sampled every 2 cm (`surface.ply`).
fn write_truth(world: &World, truth: &GroundTruth, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let world_file = dir.join("world.toml");
    write_world_description(world, &world_file)?;
    let surface = dir.join("surface.ply");
    let points: Vec<[f32; 3]> = truth
        .sample(0.02)
        .iter()
        .map(|p| p.point.map(|c| c as f32))
        .collect();
    io::save(
        &surface,
        &[RayBundle {
            origin: [0.0; 3],
            points,
        }],
    )?;
    Ok(vec![world_file, surface])
}

fn run_in(
    args: &DemoArgs,
    work: &Path,
    data_dir: &Path,
    scans_dir: &Path,
    started: Instant,
) -> anyhow::Result<DemoReport> {
    println!(
        "scan3d demo: conference room 8 x 6 x 3 m; RPLidar A1 (express) + Scanse Sweep on ptys -> edge daemon -> QUIC (mutual TLS) -> server; time x{}",
        args.time_scale
    );
    let pki = work.join("pki");
    let bundle = installation::pair_certificates(&pki)?;
    let mut server = ServerThread::start(installation::ingest_config(&pki, data_dir, 0))?;
    let options = LidarOptions {
        time_scale: args.time_scale,
        corrupt: args.corrupt,
        seed: args.seed,
        sweep_settle_ms: 6000,
    };
    let lidars = SimLidars::start(&work.join("links"), &options)?;
    let clock: SharedClock = Arc::new(ScaledClock::new(args.time_scale));
    let config = lidars.edge_config(
        &work.join("edge-state"),
        Some(installation::uplink_section(server.addr(), &bundle)),
    );
    let session_id = rand::random::<u64>();
    let edge = EdgeThread::start(config, clock.clone(), session_id)?;

    let mut received = Received::default();
    let deadline_ns = clock.now_ns() + ((args.seconds + 40.0) * 1e9) as u64;
    while !received.has_seconds(args.seconds) {
        if clock.now_ns() > deadline_ns {
            anyhow::bail!(
                "timed out: the server received {:.1} s of rplidar and {:.1} s of sweep data",
                received.seconds(SensorId::RPLIDAR),
                received.seconds(SensorId::SWEEP)
            );
        }
        received.drain(&mut server);
        std::thread::sleep(Duration::from_millis(10));
    }
    // The edge stops its lidars, then drains its spool until the server has acknowledged all.
    // Frames are reported when recorded, before they are acknowledged: once the edge has
    // stopped (everything acknowledged), every frame's event is already queued.
    let edge_report = edge.stop()?;
    received.drain(&mut server);
    let server_stats = server.stop();
    let session = session_dir(data_dir, installation::EDGE_NAME, session_id);
    let deliveries = installation::account(&session, &lidars, Some(&edge_report))?;
    lidars.shutdown();
    let scans = received
        .scans
        .write_ply_files(scans_dir)
        .context("cannot write the scans")?;
    let sensor_seconds = [SensorId::RPLIDAR, SensorId::SWEEP]
        .map(|s| (s, received.seconds(s)))
        .into();
    Ok(DemoReport {
        sensor_seconds,
        session_dir: session,
        frames_per_topic: received.frames_per_topic,
        deliveries,
        edge: edge_report,
        server: server_stats,
        time_sync: received.time_sync,
        time_scale: args.time_scale,
        resolution: args.resolution,
        scans,
        pass: None,
        maps: Vec::new(),
        truth_files: Vec::new(),
        octrees: Vec::new(),
        table: String::new(),
        report_command: None,
        against_paper: String::new(),
        wall: started.elapsed(),
    })
}

/// What the server reported while the demo ran.
#[derive(Default)]
struct Received {
    scans: RevolutionCollector,
    frames_per_topic: BTreeMap<String, u64>,
    sensor_ns: BTreeMap<SensorId, u64>,
    time_sync: Option<ClockModel>,
}

impl Received {
    fn drain(&mut self, server: &mut ServerThread) {
        while let Ok(event) = server.events.try_recv() {
            match event {
                IngestEvent::Frame { frame, .. } => {
                    *self.frames_per_topic.entry(topic(&frame.body)).or_default() += 1;
                    if let Body::Revolution(rev) = &frame.body {
                        *self.sensor_ns.entry(rev.sensor).or_default() +=
                            rev.t1_ns.saturating_sub(rev.t0_ns);
                    }
                    self.scans.on_frame(&frame);
                }
                IngestEvent::TimeSync { model, .. } => self.time_sync = Some(model),
                IngestEvent::Connected { .. } | IngestEvent::Disconnected { .. } => {}
            }
        }
    }

    fn seconds(&self, sensor: SensorId) -> f64 {
        self.sensor_ns.get(&sensor).copied().unwrap_or(0) as f64 / 1e9
    }

    fn has_seconds(&self, seconds: f64) -> bool {
        [SensorId::RPLIDAR, SensorId::SWEEP]
            .iter()
            .all(|&s| self.seconds(s) >= seconds)
    }
}

/// The trolley pass's lines of the summary.
fn pass_summary(s: &mut String, pass: &PassResult) {
    let _ = writeln!(
        s,
        "trolley pass {PASS_NAME} (§III-B): {:.1} m in {:.1} s of edge time, {} IMU frames, \
         recorded in {}",
        pass.path.length_m(),
        (pass.span_ns.1.saturating_sub(pass.span_ns.0)) as f64 * 1e-9,
        pass.imu_frames,
        pass.session_dir.display()
    );
    let _ = writeln!(s, "  {}", pass.mag_calibration.summary());
    let _ = writeln!(s, "  map1 is {}", pass.source);
    let totals = &pass.totals;
    let _ = writeln!(
        s,
        "  offline assembly (scan3d assemble --moving --pass {PASS_NAME}): {} Sweep revolutions, \
         {} samples placed, {} unplaced, {} points after the pass-through box",
        totals.revolutions, totals.samples, totals.unplaced_samples, totals.points
    );
    let mm = |a: &Option<Accuracy>| {
        a.map_or_else(
            || "-".to_string(),
            |a| format!("mean {:.1} mm, p95 {:.1} mm", a.mean_m * 1e3, a.p95_m * 1e3),
        )
    };
    let _ = writeln!(
        s,
        "  against the true surface: offline {}; live {}",
        mm(&pass.offline_accuracy),
        mm(&pass.live_accuracy)
    );
    match &pass.accuracy {
        Some(a) => {
            let _ = writeln!(
                s,
                "  {} points; against the true surface: mean {:.1} mm, p95 {:.1} mm",
                pass.points(),
                a.mean_m * 1e3,
                a.p95_m * 1e3
            );
        }
        None => {
            let _ = writeln!(s, "  no point to score");
        }
    }
    if let Some(e) = &pass.matcher_error {
        let _ = writeln!(s, "  {}", ate_text("trajectory (scan matcher)", e));
    }
    match (&pass.fused_error, &pass.fusion_failure) {
        (Some(e), _) => {
            let _ = writeln!(s, "  {}", ate_text("trajectory (matcher + CI fusion)", e));
        }
        (None, Some(why)) => {
            let _ = writeln!(s, "  no fused trajectory: {why}");
        }
        (None, None) => {}
    }
    for r in &pass.yaw_rmse {
        let _ = writeln!(
            s,
            "  yaw RMSE, {}: {:.3}° ({} poses)",
            r.label, r.rmse_deg, r.poses
        );
    }
    for file in &pass.fig5 {
        let _ = writeln!(s, "  wrote {}", file.display());
    }
    let _ = writeln!(s, "  pass wall time {:.1} s", pass.wall_s);
    // The octree and the truth are listed with the other maps and truth files.
    for file in pass
        .files
        .iter()
        .filter(|f| **f != pass.octree && **f != pass.truth_file)
    {
        let _ = writeln!(s, "  wrote {}", file.display());
    }
}

/// The human-readable summary printed at the end of the demo.
pub fn summary(report: &DemoReport) -> String {
    let mut s = String::new();
    let frames: u64 = report.frames_per_topic.values().sum();
    let _ = writeln!(
        s,
        "server recorded {frames} frames ({} duplicates ignored) in {}",
        report.server.duplicates,
        report.session_dir.display()
    );
    for (topic, count) in &report.frames_per_topic {
        let _ = writeln!(s, "  {topic:<24} {count:>6}");
    }
    let _ = writeln!(
        s,
        "{:<8} {:>6} {:>14} {:>12} {:>12} {:>6} {:>9}",
        "lidar", "revs", "sent (span)", "edge sent", "recorded", "lost", "edge CPU"
    );
    let mut core_share = 0.0;
    for d in &report.deliveries {
        let lidar = report
            .edge
            .lidars
            .get(&d.sensor)
            .copied()
            .unwrap_or_default();
        let seconds = report.sensor_seconds.get(&d.sensor).copied().unwrap_or(0.0);
        let share = if seconds > 0.0 {
            lidar.acquisition.cpu_time.as_secs_f64() / seconds
        } else {
            0.0
        };
        core_share += share;
        let lost = d.lost();
        let _ = writeln!(
            s,
            "{:<8} {:>6} {:>14} {:>12} {:>12} {:>6} {:>8.2}%",
            d.sensor.to_string(),
            d.revolutions,
            d.sent_in_span,
            d.edge_samples,
            d.recorded_samples,
            lost,
            share * 100.0
        );
    }
    let _ = writeln!(s, "samples lost: {} (must be 0)", report.samples_lost());
    if let Some(sync) = &report.time_sync {
        let _ = writeln!(
            s,
            "time sync: edge clock - server clock = {:.3} s, skew {:.1} ppm, error bound {:.3} ms, round trip {:.3} ms",
            sync.offset_ns as f64 / 1e9,
            sync.skew_ppm,
            sync.error_bound_ns as f64 / 1e6,
            sync.min_delay_ns as f64 / 1e6
        );
        if report.time_scale != 1.0 {
            let _ = writeln!(
                s,
                "  (the simulated edge clock runs x{} against the server's, far outside the ±200 ppm of real \
                 crystals the estimator allows: skew and bound are only meaningful with --time-scale 1)",
                report.time_scale
            );
        }
    }
    if let Some(uplink) = &report.edge.uplink {
        let _ = writeln!(
            s,
            "uplink: {} frames submitted, {} sent, {} acks, {} connection(s)",
            uplink.submitted, uplink.frames_sent, uplink.acks, uplink.connections
        );
    }
    for path in &report.scans {
        let _ = writeln!(s, "wrote {}", path.display());
    }
    let _ = writeln!(
        s,
        "edge CPU for both lidars at full rate: {:.2} % of one core (acquisition threads)",
        core_share * 100.0,
    );
    if let Some(pass) = &report.pass {
        pass_summary(&mut s, pass);
    }
    if !report.maps.is_empty() {
        let _ = writeln!(
            s,
            "static 3D scans (eq. 1), accuracy = point-to-true-surface distance:"
        );
        let _ = writeln!(
            s,
            "{:<5} {:>4} {:>5} {:>9} {:>10} {:>9} {:>9} {:>8} {:>7}",
            "map", "pos", "Hz", "points", "scan s", "mean mm", "p95 mm", "warnings", "I2C/s"
        );
        for m in &report.maps {
            let mean_scan = m.scan_seconds.iter().sum::<f64>() / m.scan_seconds.len().max(1) as f64;
            let (mean, p95) = m
                .accuracy
                .map_or((f64::NAN, f64::NAN), |a| (a.mean_m * 1e3, a.p95_m * 1e3));
            let _ = writeln!(
                s,
                "{:<5} {:>4} {:>5} {:>9} {:>10.1} {:>9.1} {:>9.1} {:>8} {:>7.0}",
                m.plan.name,
                m.plan.positions.len(),
                m.plan.motor_hz,
                m.points(),
                mean_scan,
                mean,
                p95,
                m.warnings,
                m.i2c_per_s
            );
            let pipeline = map_pipeline(&m.plan, report.resolution);
            let filters = |list: &[scan3d_map::cloud::filter::Filter]| {
                list.iter()
                    .map(|f| format!(" --filter {f}"))
                    .collect::<String>()
            };
            let _ = writeln!(
                s,
                "  map made by the live pipeline with --resolution {} --max-range {}{}{}",
                pipeline.resolution_m,
                pipeline.max_range_m.unwrap_or(-1.0),
                filters(&pipeline.revolution_filters),
                filters(&pipeline.snapshot_filters).replace("--filter", "--snapshot-filter")
            );
            for file in &m.files {
                let _ = writeln!(s, "  wrote {}", file.display());
            }
        }
    }
    for file in &report.truth_files {
        let _ = writeln!(s, "wrote {}", file.display());
    }
    for file in &report.octrees {
        let _ = writeln!(s, "wrote {}", file.display());
    }
    if let Some(command) = &report.report_command {
        let _ = writeln!(
            s,
            "\nscored with (run it by hand for the same table):\n  {command}"
        );
    }
    if !report.table.is_empty() {
        let _ = writeln!(s, "\n{}", report.table.trim_end());
    }
    if !report.against_paper.is_empty() {
        let _ = writeln!(s, "\n{}", report.against_paper.trim_end());
    }
    let _ = writeln!(s, "wall time {:.1} s", report.wall.as_secs_f64());
    s
}
