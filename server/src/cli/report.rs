//! `scan3d report --ref REF --maps A.bt B.bt … [--truth T] [--bbox …] --out DIR`: Table III,
//! the metric table, `metrics.json` and a Fig. 11-style chart (`fig11.svg`, `fig11.png`).

use std::io::Write;
use std::path::PathBuf;

use crate::report::{MetricBox, parse_bbox, write_report};

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

/// Runs `scan3d report`.
pub fn run(args: &ReportArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let written = write_report(
        &args.reference,
        &args.maps,
        args.truth.as_deref(),
        args.bbox,
        &args.out,
    )?;
    write!(out, "{}", written.table)?;
    writeln!(out)?;
    for p in written.files {
        writeln!(out, "wrote {}", p.display())?;
    }
    Ok(())
}
