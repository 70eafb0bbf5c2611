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

/// Reads a `.bt` / `.ot` map for evaluation (OctoMap's default sensor model).
pub fn load_map(path: &Path) -> anyhow::Result<LeafMap> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    LeafMap::read(&bytes, SensorModel::default()).with_context(|| format!("{}", path.display()))
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
    /// Against the reference; null when either map holds no 3D data.
    metrics: Option<Metrics>,
    /// Why there are no metrics: the line the table prints (null when there are).
    no_data: Option<String>,
}

/// `metrics.json`.
#[derive(Debug, Serialize)]
struct Report {
    reference: MapReport,
    truth: Option<MapReport>,
    /// The universe box asked for (`--bbox`), metres; null: each pair's bounding box.
    bbox: Option<[f64; 6]>,
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

/// The line a report prints for a map with no known voxel.
fn no_data_line(path: &Path) -> String {
    format!(
        "no 3D data: {} holds no known voxel (no scan has been inserted into it; for a live \
         session, no static scan has finished)",
        path.display()
    )
}

/// Table III of the paper (§IV): occupied ratio and free ratio in percent, and leaf nodes, as
/// printed there, per map name. The paper does not state the maps' resolution.
pub const PAPER_TABLE_III: [(&str, &str, &str, u64); 4] = [
    ("map1", "13.059 %", "86.941 %", 17140),
    ("map2", "19.061 %", "80.939 %", 18320),
    ("map3", "18.6405 %", "81.3595 %", 20553),
    ("ref", "30.4077 %", "69.5923 %", 22491),
];

/// What the paper says of Fig. 11 per map (§IV): its text gives no bar values, only the ideal
/// (a map against itself) and the order of map1–map3.
pub const PAPER_FIG_11: [(&str, &str); 4] = [
    ("map1", "the worst of map1–map3 (along movement)"),
    ("map2", "the most consistent of map1–map3 (one position)"),
    ("map3", "second of map1–map3 (four positions)"),
    (
        "ref",
        "IoU 1, log-odds 0, correlation 1 (a map against itself)",
    ),
];

fn paper_row(name: &str) -> Option<(&'static str, &'static str, u64)> {
    PAPER_TABLE_III
        .iter()
        .find(|row| row.0 == name)
        .map(|row| (row.1, row.2, row.3))
}

fn paper_fig11(name: &str) -> Option<&'static str> {
    PAPER_FIG_11
        .iter()
        .find(|row| row.0 == name)
        .map(|row| row.1)
}

/// The metric box in the `--bbox` form (`x0,y0,z0,x1,y1,z1`), which parses back to the same box.
impl std::fmt::Display for MetricBox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [x0, y0, z0] = self.min;
        let [x1, y1, z1] = self.max;
        write!(f, "{x0},{y0},{z0},{x1},{y1},{z1}")
    }
}

/// A key box's outer faces in metres and its size, for the footnote.
fn describe_box(b: &VoxelBox, resolution: f64) -> String {
    let r = resolution;
    let lo = b.min.map(|k| (f64::from(k) - 32768.0) * r);
    let hi = b.max.map(|k| (f64::from(k) - 32768.0 + 1.0) * r);
    let n = (0..3)
        .map(|a| u64::from(b.max[a] - b.min[a]) + 1)
        .collect::<Vec<_>>();
    format!(
        "x {:.3}..{:.3}, y {:.3}..{:.3}, z {:.3}..{:.3} m ({} × {} × {} voxels of {r} m)",
        lo[0], hi[0], lo[1], hi[1], lo[2], hi[2], n[0], n[1], n[2]
    )
}

/// Table III (as the paper has it) and the metric table, in Markdown.
fn table_md(r: &Report) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# Map comparison against `{}`\n",
        r.reference.path.display()
    );
    let rows: Vec<(&str, &MapReport)> = r
        .maps
        .iter()
        .map(|m| (m.name.as_str(), m))
        .chain(std::iter::once(("ref", &r.reference)))
        .chain(r.truth.iter().map(|t| ("truth", t)))
        .collect();
    let any_paper = rows.iter().any(|(label, _)| paper_row(label).is_some());
    let _ = writeln!(
        s,
        "## Table III: proportion (occupied and free as shares of each map's known voxels)\n"
    );
    if any_paper {
        let _ = writeln!(
            s,
            "| | Occupied Ratio | Free Ratio | Leaf nodes number | paper: Occupied Ratio | paper: Free Ratio | paper: Leaf nodes number |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|");
    } else {
        let _ = writeln!(s, "| | Occupied Ratio | Free Ratio | Leaf nodes number |");
        let _ = writeln!(s, "|---|---:|---:|---:|");
    }
    for (label, m) in &rows {
        let _ = write!(
            s,
            "| **{label}** | {} | {} | {} |",
            pct(m.summary.occupied_share),
            pct(m.summary.free_share),
            m.summary.leaves
        );
        if any_paper {
            match paper_row(label) {
                Some((occ, free, leaves)) => {
                    let _ = write!(s, " {occ} | {free} | {leaves} |");
                }
                None => {
                    let _ = write!(s, " - | - | - |");
                }
            }
        }
        let _ = writeln!(s);
    }
    if any_paper {
        let _ = writeln!(
            s,
            "\npaper: the paper's Table III for the map of the same name (its text does not state \
             the maps' resolution); this run's maps are at {} m.",
            r.reference.resolution_text()
        );
    }
    for (_, m) in &rows {
        if m.summary.occupied_voxels + m.summary.free_voxels == 0 {
            let _ = writeln!(s, "\n{}", no_data_line(&m.path));
        }
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
    let scored: Vec<(String, &str, &MapReport)> = r
        .maps
        .iter()
        .map(|m| (m.name.clone(), m.name.as_str(), m))
        .chain(std::iter::once((
            "ref (itself)".to_string(),
            "ref",
            &r.reference,
        )))
        .collect();
    for (label, _, m) in &scored {
        let Some(x) = &m.metrics else {
            let why = m.no_data.as_deref().unwrap_or("no metrics");
            let _ = writeln!(s, "| **{label}** | {why} |{}", " |".repeat(cols - 1));
            continue;
        };
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
    if scored
        .iter()
        .any(|(_, key, m)| m.metrics.is_some() && paper_fig11(key).is_some())
    {
        let _ = writeln!(s, "\n## Fig. 11 beside the paper\n");
        let _ = writeln!(
            s,
            "| map | IoU weighted | log-odds mean | correlation (paper) | mean p ± mean \\|Δp\\| | paper (§IV, Fig. 11) |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---|");
        for (label, key, m) in &scored {
            let (Some(x), Some(paper)) = (&m.metrics, paper_fig11(key)) else {
                continue;
            };
            let _ = writeln!(
                s,
                "| **{label}** | {:.4} | {} | {} | {} ± {} | {paper} |",
                x.iou.weighted,
                opt(x.log_odds.mean, 5),
                opt(x.correlation.paper, 4),
                opt(x.mean_probability, 4),
                opt(x.probability_deviation, 4),
            );
        }
        let _ = writeln!(
            s,
            "\nThe paper's text gives no bar heights for Fig. 11, only the ideal and the order above."
        );
    }
    let _ = writeln!(s);
    match r.bbox {
        Some(b) => {
            let used = scored
                .iter()
                .find_map(|(_, _, m)| m.metrics.as_ref())
                .map(|x| format!(": {}", describe_box(&x.bbox, x.resolution)))
                .unwrap_or_default();
            let _ = writeln!(
                s,
                "U is the same box for every pair, `--bbox {}`: the voxels whose centre lies in it{used}.",
                MetricBox {
                    min: [b[0], b[1], b[2]],
                    max: [b[3], b[4], b[5]],
                }
            );
        }
        None => {
            let _ = writeln!(
                s,
                "U is each pair's own box, the bounding box of both maps' known voxels (no `--bbox`):"
            );
            for (label, _, m) in &scored {
                if let Some(x) = &m.metrics {
                    let _ = writeln!(s, "- {label}: {}", describe_box(&x.bbox, x.resolution));
                }
            }
        }
    }
    let _ = writeln!(
        s,
        "The log-odds error is KL(ref‖map) per common voxel (OctoMap's `compare_octrees` KLD); \
         precision … Chamfer are against the truth map{}.",
        r.truth
            .as_ref()
            .map(|t| format!(" `{}`", t.path.display()))
            .unwrap_or_default()
    );
    s
}

impl MapReport {
    fn resolution_text(&self) -> String {
        self.metrics
            .as_ref()
            .map_or_else(|| "?".into(), |m| m.resolution.to_string())
    }
}

/// What [`write_report`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct WrittenReport {
    /// `table.md`: Table III and the metric table, in Markdown.
    pub table: String,
    /// The files written: `table.md`, `metrics.json`, and `fig11.svg`, `fig11.png` when some
    /// map has metrics.
    pub files: Vec<PathBuf>,
    /// What `metrics.json` holds: the reference, the truth and every map with its metrics.
    pub metrics: serde_json::Value,
}

/// Everything `scan3d report` is given: the one description of a report that the command line
/// and the simulator's demo both build, so their tables cannot differ.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportOptions {
    /// The reference map (`--reference`).
    pub reference: PathBuf,
    /// The maps scored against it (`--maps`).
    pub maps: Vec<PathBuf>,
    /// The ground-truth map (`--truth`).
    pub truth: Option<PathBuf>,
    /// The universe box (`--bbox`); `None`: each pair's bounding box.
    pub bbox: Option<MetricBox>,
    /// The output directory (`--out`).
    pub out: PathBuf,
}

/// `s` as one shell word: as is when it holds only safe characters, else single-quoted.
pub fn shell_word(s: &str) -> String {
    let safe = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-./,:=+@%".contains(c));
    if safe {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', "'\\''"))
    }
}

impl ReportOptions {
    /// The `scan3d report` command line that makes this report, every option spelled out.
    pub fn command_line(&self) -> String {
        let word = |p: &Path| shell_word(&p.display().to_string());
        let mut line = format!("scan3d report --reference {}", word(&self.reference));
        line.push_str(" --maps");
        for m in &self.maps {
            line.push(' ');
            line.push_str(&word(m));
        }
        if let Some(t) = &self.truth {
            line.push_str(&format!(" --truth {}", word(t)));
        }
        if let Some(b) = self.bbox {
            line.push_str(&format!(" --bbox {b}"));
        }
        line.push_str(&format!(" --out {}", word(&self.out)));
        line
    }

    /// Scores every map against the reference (and the truth) inside the box and writes
    /// `table.md`, `metrics.json` and Fig. 11 into `out` (created if missing). A map with no
    /// known voxel is reported with a line saying so, not scored.
    pub fn write(&self) -> anyhow::Result<WrittenReport> {
        let reference = load_map(&self.reference)?;
        let truth = self.truth.as_deref().map(load_map).transpose()?;
        let bbox = key_box(&reference, self.bbox)?;
        let empty = |m: &LeafMap| {
            let s = summarize(m);
            s.occupied_voxels + s.free_voxels == 0
        };
        let reference_empty = empty(&reference);
        let score = |path: &Path,
                     map: &LeafMap|
         -> anyhow::Result<(Option<Metrics>, Option<String>)> {
            if reference_empty {
                return Ok((None, Some(no_data_line(&self.reference))));
            }
            if empty(map) {
                return Ok((None, Some(no_data_line(path))));
            }
            let m = evaluate_maps(&reference, map, bbox, truth.as_ref()).with_context(|| {
                format!("{} against {}", path.display(), self.reference.display())
            })?;
            Ok((Some(m), None))
        };
        let mut maps = Vec::new();
        for path in &self.maps {
            let map = load_map(path)?;
            let (metrics, no_data) = score(path, &map)?;
            maps.push(MapReport {
                name: name_of(path),
                path: path.clone(),
                summary: summarize(&map),
                metrics,
                no_data,
            });
        }
        let (metrics, no_data) = score(&self.reference, &reference)?;
        let report = Report {
            reference: MapReport {
                name: name_of(&self.reference),
                path: self.reference.clone(),
                summary: summarize(&reference),
                metrics,
                no_data,
            },
            truth: self
                .truth
                .as_ref()
                .zip(truth.as_ref())
                .map(|(path, t)| MapReport {
                    name: name_of(path),
                    path: path.clone(),
                    summary: summarize(t),
                    metrics: None,
                    no_data: None,
                }),
            bbox: self
                .bbox
                .map(|b| [b.min[0], b.min[1], b.min[2], b.max[0], b.max[1], b.max[2]]),
            maps,
        };
        let out_dir = &self.out;
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
            .filter_map(|(label, m)| {
                let m = m.as_ref()?;
                Some(Fig11Group {
                    label,
                    iou: m.iou.weighted,
                    log_odds_mean: m.log_odds.mean,
                    correlation: m.correlation.paper,
                    mean_probability: m.mean_probability,
                    deviation: m.probability_deviation,
                })
            })
            .collect();
        // Without any scored map there is no figure; the table says why.
        if !groups.is_empty() {
            written.push(write("fig11.svg", fig11_svg(&groups)?.as_bytes())?);
            let png = out_dir.join("fig11.png");
            fig11_png(&groups, &png).with_context(|| format!("cannot write {}", png.display()))?;
            written.push(png);
        }
        Ok(WrittenReport {
            table,
            files: written,
            metrics,
        })
    }
}

/// `scan3d report`: every map of `maps` against `reference` (and `truth`), inside `bbox`:
/// Table III, the metric table, `metrics.json` and Fig. 11 into `out_dir` (created if missing).
/// The same as [`ReportOptions::write`].
pub fn write_report(
    reference_path: &Path,
    maps_paths: &[PathBuf],
    truth_path: Option<&Path>,
    bbox: Option<MetricBox>,
    out_dir: &Path,
) -> anyhow::Result<WrittenReport> {
    ReportOptions {
        reference: reference_path.to_path_buf(),
        maps: maps_paths.to_vec(),
        truth: truth_path.map(Path::to_path_buf),
        bbox,
        out: out_dir.to_path_buf(),
    }
    .write()
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

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_map::cloud::RayBundle;

    fn map_bytes(points: &[[f32; 3]]) -> Vec<u8> {
        let mut map = VoxelMap::new(Resolution::new(0.1).unwrap(), SensorModel::default());
        if !points.is_empty() {
            map.insert_bundle(
                &RayBundle {
                    origin: [0.0; 3],
                    points: points.to_vec(),
                },
                -1.0,
            );
        }
        map.to_octree().to_bt_bytes()
    }

    #[test]
    fn a_map_without_3d_data_is_reported_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let (reference, empty) = (dir.path().join("ref.bt"), dir.path().join("map2.bt"));
        std::fs::write(&reference, map_bytes(&[[1.0, 0.5, 0.2], [0.8, -0.4, 0.3]])).unwrap();
        std::fs::write(&empty, map_bytes(&[])).unwrap();
        let options = ReportOptions {
            reference: reference.clone(),
            maps: vec![empty.clone()],
            truth: None,
            bbox: None,
            out: dir.path().join("report"),
        };
        let written = options.write().unwrap();
        let line = format!("no 3D data: {} holds no known voxel", empty.display());
        assert!(written.table.contains(&line), "{}", written.table);
        assert_eq!(
            written.metrics["maps"][0]["metrics"],
            serde_json::Value::Null
        );
        assert!(
            written.metrics["maps"][0]["no_data"]
                .as_str()
                .unwrap()
                .starts_with("no 3D data")
        );
        // The reference against itself is still scored and drawn.
        assert_eq!(
            written.metrics["reference"]["metrics"]["iou"]["occupied"],
            1.0
        );
        assert!(written.files.iter().any(|f| f.ends_with("fig11.png")));

        // An empty reference: nothing is scored, every row says why, no figure.
        let options = ReportOptions {
            reference: empty.clone(),
            maps: vec![reference.clone()],
            out: dir.path().join("report-empty"),
            ..options
        };
        let written = options.write().unwrap();
        assert_eq!(
            written.table.matches("no 3D data").count(),
            // Table III's line for the reference, and both metric rows.
            3,
            "{}",
            written.table
        );
        let names: Vec<_> = written
            .files
            .iter()
            .map(|f| f.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["table.md", "metrics.json"]);
        let on_disk = std::fs::read_to_string(dir.path().join("report-empty/table.md")).unwrap();
        assert_eq!(on_disk, written.table);
    }

    #[test]
    fn the_command_line_quotes_what_the_shell_would_split() {
        let options = ReportOptions {
            reference: "/tmp/a b/ref.bt".into(),
            maps: vec!["m.bt".into(), "it's.bt".into()],
            truth: Some("t.bt".into()),
            bbox: Some(MetricBox {
                min: [-0.2, -0.2, -0.2],
                max: [8.05, 5.9, 3.2],
            }),
            out: "out".into(),
        };
        assert_eq!(
            options.command_line(),
            "scan3d report --reference '/tmp/a b/ref.bt' --maps m.bt 'it'\\''s.bt' --truth t.bt \
             --bbox -0.2,-0.2,-0.2,8.05,5.9,3.2 --out out"
        );
        assert_eq!(
            crate::cli::parse_bbox(&options.bbox.unwrap().to_string()),
            Ok(options.bbox.unwrap())
        );
    }
}
