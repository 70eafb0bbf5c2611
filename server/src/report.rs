//! The map comparison reports as library functions, for the `scan3d eval` / `report` / `sweep`
//! commands and the simulator's demo: maps read from `.bt`/`.ot` files, scored with the
//! paper's metrics (`scan3d_map::eval`), written as tables, JSON and figures.

use std::fmt::Write as _;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use serde::Serialize;

use scan3d_map::cloud::{RayBundle, io};
use scan3d_map::eval::plot::{Fig11Group, Fig12Row, fig11_png, fig11_svg, fig12_png, fig12_svg};
use scan3d_map::eval::{self, LeafMap, MapSummary, Metrics, Role, VoxelBox, evaluate, summarize};
use scan3d_map::octree::{Resolution, SensorModel, VoxelMap, read_graph};

/// A box in metres, `(min corner, max corner)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricBox {
    /// `x0, y0, z0`.
    pub min: [f64; 3],
    /// `x1, y1, z1`.
    pub max: [f64; 3],
}

/// Parses `x0,y0,z0,x1,y1,z1`.
pub fn parse_bbox(s: &str) -> Result<MetricBox, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("bbox: {e} (want x0,y0,z0,x1,y1,z1 in metres)"))?;
    match v.as_slice() {
        &[x0, y0, z0, x1, y1, z1] => Ok(MetricBox {
            min: [x0, y0, z0],
            max: [x1, y1, z1],
        }),
        _ => Err(format!(
            "bbox: {} numbers given, want 6: x0,y0,z0,x1,y1,z1",
            v.len()
        )),
    }
}

/// Reads a `.bt` / `.ot` map for evaluation (OctoMap's default sensor model).
pub fn load_map(path: &Path) -> anyhow::Result<LeafMap> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    LeafMap::read(&bytes, SensorModel::default())
        .with_context(|| format!("{}", path.display()))
}

/// The key box of a metric box at the reference's resolution.
pub fn key_box(reference: &LeafMap, bbox: Option<MetricBox>) -> anyhow::Result<Option<VoxelBox>> {
    bbox.map(|b| VoxelBox::from_metric(reference.resolution(), b.min, b.max))
        .transpose()
        .context("--bbox")
}

/// All metrics of `target` against `reference`, with the truth scores if `truth` is given.
pub fn evaluate_maps(
    reference: &LeafMap,
    target: &LeafMap,
    bbox: Option<VoxelBox>,
    truth: Option<&LeafMap>,
) -> anyhow::Result<Metrics> {
    let mut m = eval::evaluate(reference, target, bbox)?;
    if let Some(t) = truth {
        eval::check_resolution(reference, t, Role::Truth)?;
        m.truth = Some(eval::evaluate_truth(target, t, m.bbox)?);
    }
    Ok(m)
}

/// A number, or `-` for an undefined one.
pub fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".to_string(), |x| format!("{x:.digits$}"))
}

/// One map of the report.
#[derive(Debug, Serialize)]
struct MapReport {
    name: String,
    path: PathBuf,
    /// Table III's row (whole map).
    summary: MapSummary,
    /// Against the reference.
    metrics: Metrics,
}

/// `metrics.json`.
#[derive(Debug, Serialize)]
struct Report {
    reference: MapReport,
    truth: Option<PathBuf>,
    maps: Vec<MapReport>,
}

fn name_of(path: &Path) -> String {
    path.file_stem().map_or_else(
        || path.display().to_string(),
        |s| s.to_string_lossy().into_owned(),
    )
}

fn pct(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |x| format!("{:.4} %", x * 100.0))
}

/// Table III (as the paper has it) and the metric table, in Markdown.
fn table_md(r: &Report) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# Map comparison against `{}`\n",
        r.reference.path.display()
    );
    let _ = writeln!(
        s,
        "## Table III: proportion (occupied and free as shares of each map's known voxels)\n"
    );
    let _ = writeln!(s, "| | Occupied Ratio | Free Ratio | Leaf nodes number |");
    let _ = writeln!(s, "|---|---:|---:|---:|");
    for m in r.maps.iter().chain(std::iter::once(&r.reference)) {
        let label = if std::ptr::eq(m, &r.reference) {
            "ref"
        } else {
            &m.name
        };
        let _ = writeln!(
            s,
            "| **{label}** | {} | {} | {} |",
            pct(m.summary.occupied_share),
            pct(m.summary.free_share),
            m.summary.leaves
        );
    }
    let _ = writeln!(
        s,
        "\n## Metrics against the reference (eq. M4–M9, Fig. 11)\n"
    );
    let truth = r.truth.is_some();
    let _ = write!(
        s,
        "| map | IoU occ | IoU free | IoU unknown | IoU weighted | log-odds mean | log-odds sum | correlation (paper) | correlation (signed) | mean p | mean \\|Δp\\| | common voxels |"
    );
    if truth {
        let _ = write!(
            s,
            " precision | recall | F1 | precision ±1 | recall ±1 | F1 ±1 | Chamfer [m] |"
        );
    }
    let _ = writeln!(s);
    let cols = 12 + if truth { 7 } else { 0 };
    let _ = writeln!(s, "|---{}|", "|---:".repeat(cols - 1));
    for m in r.maps.iter().chain(std::iter::once(&r.reference)) {
        let label = if std::ptr::eq(m, &r.reference) {
            "ref (itself)"
        } else {
            &m.name
        };
        let x = &m.metrics;
        let _ = write!(
            s,
            "| **{label}** | {} | {} | {} | {:.4} | {} | {:.4} | {} | {} | {} | {} | {} |",
            opt(x.iou.occupied, 4),
            opt(x.iou.free, 4),
            opt(x.iou.unknown, 4),
            x.iou.weighted,
            opt(x.log_odds.mean, 5),
            x.log_odds.sum,
            opt(x.correlation.paper, 4),
            opt(x.correlation.signed, 4),
            opt(x.mean_probability, 4),
            opt(x.probability_deviation, 4),
            x.log_odds.common_voxels
        );
        if truth {
            match &x.truth {
                Some(t) => {
                    let _ = write!(
                        s,
                        " {} | {} | {} | {} | {} | {} | {} |",
                        opt(t.precision, 4),
                        opt(t.recall, 4),
                        opt(t.f1, 4),
                        opt(t.precision_tolerant, 4),
                        opt(t.recall_tolerant, 4),
                        opt(t.f1_tolerant, 4),
                        opt(t.chamfer, 4)
                    );
                }
                None => {
                    let _ = write!(s, "{}", " - |".repeat(7));
                }
            }
        }
        let _ = writeln!(s);
    }
    let _ = writeln!(
        s,
        "\nU is each pair's box (the bounding box of both maps' known voxels unless `--bbox`); \
         the log-odds error is KL(ref‖map) per common voxel (OctoMap's `compare_octrees` KLD)."
    );
    s
}

/// What [`write_report`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct WrittenReport {
    /// `table.md`: Table III and the metric table, in Markdown.
    pub table: String,
    /// The files written: `table.md`, `metrics.json`, `fig11.svg`, `fig11.png`.
    pub files: Vec<PathBuf>,
    /// What `metrics.json` holds: the reference, the truth and every map with its metrics.
    pub metrics: serde_json::Value,
}

/// `scan3d report`: every map of `maps` against `reference` (and `truth`), inside `bbox`:
/// Table III, the metric table, `metrics.json` and Fig. 11 into `out_dir` (created if missing).
pub fn write_report(
    reference_path: &Path,
    maps_paths: &[PathBuf],
    truth_path: Option<&Path>,
    bbox: Option<MetricBox>,
    out_dir: &Path,
) -> anyhow::Result<WrittenReport> {
    let reference = load_map(reference_path)?;
    let truth = truth_path.map(load_map).transpose()?;
    let bbox = key_box(&reference, bbox)?;
    let mut maps = Vec::new();
    for path in maps_paths {
        let map = load_map(path)?;
        let metrics = evaluate_maps(&reference, &map, bbox, truth.as_ref())
            .with_context(|| format!("{} against {}", path.display(), reference_path.display()))?;
        maps.push(MapReport {
            name: name_of(path),
            path: path.clone(),
            summary: summarize(&map),
            metrics,
        });
    }
    let report = Report {
        reference: MapReport {
            name: name_of(reference_path),
            path: reference_path.to_path_buf(),
            summary: summarize(&reference),
            metrics: evaluate_maps(&reference, &reference, bbox, truth.as_ref())?,
        },
        truth: truth_path.map(Path::to_path_buf),
        maps,
    };
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("cannot create {}", out_dir.display()))?;
    let write = |name: &str, bytes: &[u8]| -> anyhow::Result<PathBuf> {
        let p = out_dir.join(name);
        std::fs::write(&p, bytes).with_context(|| format!("cannot write {}", p.display()))?;
        Ok(p)
    };
    let table = table_md(&report);
    let metrics = serde_json::to_value(&report)?;
    let mut written = vec![
        write("table.md", table.as_bytes())?,
        write("metrics.json", &serde_json::to_vec_pretty(&report)?)?,
    ];
    let groups: Vec<Fig11Group> = report
        .maps
        .iter()
        .map(|m| (m.name.clone(), &m.metrics))
        .chain(std::iter::once((
            "ref (itself)".to_string(),
            &report.reference.metrics,
        )))
        .map(|(label, m)| Fig11Group {
            label,
            iou: m.iou.weighted,
            log_odds_mean: m.log_odds.mean,
            correlation: m.correlation.paper,
            mean_probability: m.mean_probability,
            deviation: m.probability_deviation,
        })
        .collect();
    written.push(write("fig11.svg", fig11_svg(&groups)?.as_bytes())?);
    let png = out_dir.join("fig11.png");
    fig11_png(&groups, &png).with_context(|| format!("cannot write {}", png.display()))?;
    written.push(png);
    Ok(WrittenReport {
        table,
        files: written,
        metrics,
    })
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

/// The resolutions of `scan3d sweep` by default (Fig. 12's), metres.
pub const RESOLUTION_SWEEP_M: [f64; 6] = [0.05, 0.1, 0.2, 0.3, 0.4, 0.5];

/// `scan3d sweep`: Fig. 12 for `cloud_path` at each of `resolutions` (`max_range` cuts rays,
/// negative: none; timings the best of `reps`): `sweep.json`, `fig12.svg`, `fig12.png` into
/// `out_dir`, a line per resolution to `out`. Returns the files written.
pub fn write_resolution_sweep(
    cloud_path: &Path,
    resolutions: &[f64],
    max_range: f64,
    reps: u32,
    out_dir: &Path,
    out: &mut dyn Write,
) -> anyhow::Result<Vec<PathBuf>> {
    if resolutions.is_empty() {
        anyhow::bail!("--resolution: give at least one resolution");
    }
    let scans = load_cloud(cloud_path)?;
    let points: usize = scans.iter().map(|s| s.points.len()).sum();
    if points == 0 {
        anyhow::bail!("{}: no points", cloud_path.display());
    }
    writeln!(
        out,
        "{}: {} scans, {points} points",
        cloud_path.display(),
        scans.len()
    )?;
    writeln!(
        out,
        "{:>8} {:>10} {:>10} {:>10} {:>12} {:>10} {:>10}",
        "res [m]", "build [s]", "nodes", "leaves", "occ. [m³]", "load [ms]", "eval [ms]"
    )?;
    let mut rows = Vec::new();
    for &r in resolutions {
        let res = Resolution::new(r).with_context(|| format!("--resolution {r}"))?;
        let (build_s, tree) = best(reps, || {
            let mut map = VoxelMap::new(res, SensorModel::default());
            for s in &scans {
                map.insert_bundle(s, max_range);
            }
            Ok(map.to_octree())
        })?;
        let ot = tree.to_ot_bytes();
        let (load_s, map) = best(reps, || Ok(LeafMap::read(&ot, SensorModel::default())?))?;
        let (eval_s, _) = best(reps, || Ok(evaluate(&map, &map, None)?))?;
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
        cloud: cloud_path.to_path_buf(),
        scans: scans.len(),
        points,
        max_range,
        rows,
    };
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("cannot create {}", out_dir.display()))?;
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
    let json = out_dir.join("sweep.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&sweep)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    let svg = out_dir.join("fig12.svg");
    std::fs::write(&svg, fig12_svg(&fig)?)
        .with_context(|| format!("cannot write {}", svg.display()))?;
    let png = out_dir.join("fig12.png");
    fig12_png(&fig, &png).with_context(|| format!("cannot write {}", png.display()))?;
    Ok(vec![json, svg, png])
}
