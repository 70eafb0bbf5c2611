//! `scan3d report --ref REF --maps A.bt B.bt … [--truth T] [--bbox …] --out DIR`: Table III,
//! the metric table, `metrics.json` and a Fig. 11-style chart (`fig11.svg`, `fig11.png`).

use std::fmt::Write as _;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;

use super::eval::{MetricBox, evaluate_maps, key_box, load_map, opt, parse_bbox};
use scan3d_map::eval::plot::{Fig11Group, fig11_png, fig11_svg};
use scan3d_map::eval::{MapSummary, Metrics, summarize};

/// Options of `scan3d report`.
#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// The reference map (`.bt` or `.ot`).
    #[arg(long = "ref", value_name = "REF")]
    pub reference: PathBuf,
    /// The maps to score against the reference (same resolution).
    #[arg(long, num_args = 1.., required = true)]
    pub maps: Vec<PathBuf>,
    /// A ground-truth map: adds precision / recall / F1 / Chamfer per map.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// The universe box in metres, `x0,y0,z0,x1,y1,z1` (default: per pair, the bounding box).
    #[arg(long, value_parser = parse_bbox, allow_hyphen_values = true)]
    pub bbox: Option<MetricBox>,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
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

/// Runs `scan3d report`.
pub fn run(args: &ReportArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let reference = load_map(&args.reference)?;
    let truth = args.truth.as_deref().map(load_map).transpose()?;
    let bbox = key_box(&reference, args.bbox)?;
    let mut maps = Vec::new();
    for path in &args.maps {
        let map = load_map(path)?;
        let metrics = evaluate_maps(&reference, &map, bbox, truth.as_ref())
            .with_context(|| format!("{} against {}", path.display(), args.reference.display()))?;
        maps.push(MapReport {
            name: name_of(path),
            path: path.clone(),
            summary: summarize(&map),
            metrics,
        });
    }
    let report = Report {
        reference: MapReport {
            name: name_of(&args.reference),
            path: args.reference.clone(),
            summary: summarize(&reference),
            metrics: evaluate_maps(&reference, &reference, bbox, truth.as_ref())?,
        },
        truth: args.truth.clone(),
        maps,
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let write = |name: &str, bytes: &[u8]| -> anyhow::Result<PathBuf> {
        let p = args.out.join(name);
        std::fs::write(&p, bytes).with_context(|| format!("cannot write {}", p.display()))?;
        Ok(p)
    };
    let table = table_md(&report);
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
    let png = args.out.join("fig11.png");
    fig11_png(&groups, &png).with_context(|| format!("cannot write {}", png.display()))?;
    written.push(png);
    write!(out, "{table}")?;
    writeln!(out)?;
    for p in written {
        writeln!(out, "wrote {}", p.display())?;
    }
    Ok(())
}
