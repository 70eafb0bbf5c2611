//! `scan3d sweep CLOUD --res 0.05,0.1,… --out DIR`: Fig. 12 — for each resolution, the octree
//! build time, node count, occupied volume and the time of all metrics (the map against
//! itself, as the paper did), as `sweep.json`, `fig12.svg` and `fig12.png`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use serde::Serialize;

use scan3d_map::cloud::{RayBundle, io};
use scan3d_map::eval::plot::{Fig12Row, fig12_png, fig12_svg};
use scan3d_map::eval::{LeafMap, evaluate};
use scan3d_map::octree::{Resolution, SensorModel, VoxelMap, read_graph};

/// Options of `scan3d sweep`.
#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    /// The point cloud: `.graph` (OctoMap ScanGraph), `.scans`, `.ply` or `.pcd` with origins.
    pub cloud: PathBuf,
    /// Resolutions in metres, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.05,0.1,0.2,0.3,0.4,0.5"
    )]
    pub res: Vec<f64>,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Maximum range in metres for insertion (negative: none).
    #[arg(long, default_value_t = -1.0, allow_hyphen_values = true)]
    pub max_range: f64,
    /// Timing repetitions; the best is kept (the machine may be shared).
    #[arg(long, default_value_t = 3)]
    pub reps: u32,
}

/// One resolution of the sweep.
#[derive(Debug, Serialize)]
struct Row {
    resolution: f64,
    /// Insertion of every scan plus deriving the pruned tree, seconds (best of reps).
    build_s: f64,
    nodes: u64,
    leaves: u64,
    occupied_voxels: u64,
    occupied_m3: f64,
    /// Reading the map for evaluation from its `.ot` bytes, seconds.
    load_s: f64,
    /// All metrics of the map against itself, seconds (best of reps).
    eval_s: f64,
}

/// `sweep.json`.
#[derive(Debug, Serialize)]
struct Sweep {
    cloud: PathBuf,
    scans: usize,
    points: usize,
    max_range: f64,
    rows: Vec<Row>,
}

fn load_cloud(path: &Path) -> anyhow::Result<Vec<RayBundle>> {
    let is_graph = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("graph"));
    if is_graph {
        let bytes =
            std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        Ok(read_graph(&bytes).with_context(|| format!("{}", path.display()))?)
    } else {
        Ok(io::load(path, None)?)
    }
}

fn best<T>(reps: u32, mut f: impl FnMut() -> anyhow::Result<T>) -> anyhow::Result<(f64, T)> {
    let mut t_best = f64::MAX;
    let mut out = None;
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        let v = f()?;
        t_best = t_best.min(t.elapsed().as_secs_f64());
        out = Some(v);
    }
    let v = out.ok_or_else(|| anyhow::anyhow!("no repetition ran"))?;
    Ok((t_best, v))
}

/// Runs `scan3d sweep`.
pub fn run(args: &SweepArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    if args.res.is_empty() {
        anyhow::bail!("--res: give at least one resolution");
    }
    let scans = load_cloud(&args.cloud)?;
    let points: usize = scans.iter().map(|s| s.points.len()).sum();
    if points == 0 {
        anyhow::bail!("{}: no points", args.cloud.display());
    }
    writeln!(
        out,
        "{}: {} scans, {points} points",
        args.cloud.display(),
        scans.len()
    )?;
    writeln!(
        out,
        "{:>8} {:>10} {:>10} {:>10} {:>12} {:>10} {:>10}",
        "res [m]", "build [s]", "nodes", "leaves", "occ. [m³]", "load [ms]", "eval [ms]"
    )?;
    let mut rows = Vec::new();
    for &r in &args.res {
        let res = Resolution::new(r).with_context(|| format!("--res {r}"))?;
        let (build_s, tree) = best(args.reps, || {
            let mut map = VoxelMap::new(res, SensorModel::default());
            for s in &scans {
                map.insert_bundle(s, args.max_range);
            }
            Ok(map.to_octree())
        })?;
        let ot = tree.to_ot_bytes();
        let (load_s, map) = best(args.reps, || {
            Ok(LeafMap::read(&ot, SensorModel::default())?)
        })?;
        let (eval_s, _) = best(args.reps, || Ok(evaluate(&map, &map, None)?))?;
        let row = Row {
            resolution: r,
            build_s,
            nodes: tree.num_nodes() as u64,
            leaves: tree.num_leaves(),
            occupied_voxels: map.occupied_voxels(),
            occupied_m3: map.occupied_voxels() as f64 * r * r * r,
            load_s,
            eval_s,
        };
        writeln!(
            out,
            "{:>8} {:>10.4} {:>10} {:>10} {:>12.3} {:>10.2} {:>10.2}",
            r,
            row.build_s,
            row.nodes,
            row.leaves,
            row.occupied_m3,
            row.load_s * 1e3,
            row.eval_s * 1e3
        )?;
        rows.push(row);
    }
    let sweep = Sweep {
        cloud: args.cloud.clone(),
        scans: scans.len(),
        points,
        max_range: args.max_range,
        rows,
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let fig: Vec<Fig12Row> = sweep
        .rows
        .iter()
        .map(|r| Fig12Row {
            resolution: r.resolution,
            build_s: r.build_s,
            eval_s: r.eval_s,
            nodes: r.nodes,
            occupied_m3: r.occupied_m3,
        })
        .collect();
    let json = args.out.join("sweep.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&sweep)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    let svg = args.out.join("fig12.svg");
    std::fs::write(&svg, fig12_svg(&fig)?)
        .with_context(|| format!("cannot write {}", svg.display()))?;
    let png = args.out.join("fig12.png");
    fig12_png(&fig, &png).with_context(|| format!("cannot write {}", png.display()))?;
    for p in [json, svg, png] {
        writeln!(out, "wrote {}", p.display())?;
    }
    Ok(())
}
