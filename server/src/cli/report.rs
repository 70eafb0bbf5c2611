//! `scan3d report --reference REF --maps A.bt B.bt … [--truth T] [--bbox …] --out DIR [--json]`:
//! Table III, the metric table, `metrics.json` and a Fig. 11-style chart (`fig11.svg`,
//! `fig11.png`); on stdout the tables, or with `--json` one JSON object.

use std::io::Write;
use std::path::PathBuf;

use super::parse_bbox;
use crate::report::{MetricBox, write_report};

/// Options of `scan3d report`.
#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// The reference map (`.bt` or `.ot`).
    #[arg(long, alias = "ref", value_name = "REF")]
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
    /// Print one JSON object instead of the tables: what `metrics.json` holds (`reference`,
    /// `truth`, `maps`, each map with `name`, `path`, `summary` and `metrics`) and `files`,
    /// the files written.
    #[arg(long)]
    pub json: bool,
}

/// Runs `scan3d report`.
pub fn run(args: &ReportArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let written = write_report(
        &args.reference,
        &args.maps,
        args.truth.as_deref(),
        args.bbox,
        &args.out,
    )?;
    if args.json {
        let mut object = written.metrics;
        let files = written
            .files
            .iter()
            .map(|p| serde_json::Value::String(p.display().to_string()))
            .collect();
        object
            .as_object_mut()
            .ok_or_else(|| anyhow::anyhow!("the report is not a JSON object"))?
            .insert("files".into(), serde_json::Value::Array(files));
        serde_json::to_writer_pretty(&mut *out, &object)?;
        writeln!(out)?;
        return Ok(());
    }
    write!(out, "{}", written.table)?;
    writeln!(out)?;
    for p in written.files {
        writeln!(out, "wrote {}", p.display())?;
    }
    Ok(())
}
