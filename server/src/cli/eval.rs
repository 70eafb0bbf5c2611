//! `scan3d eval --reference REF TARGET [--bbox x0,y0,z0,x1,y1,z1] [--truth TRUTH] [--json]`: the
//! paper's map metrics (`scan3d_map::eval`) of one map against a reference, as a table or one
//! JSON object. The form of earlier versions, `scan3d eval REF TARGET`, still works.

use std::io::Write;
use std::path::{Path, PathBuf};

use scan3d_map::eval::Metrics;

use super::parse_bbox;
pub use crate::report::{MetricBox, evaluate_maps, key_box, load_map, opt};

/// Options of `scan3d eval`.
#[derive(Debug, clap::Args)]
pub struct EvalArgs {
    /// The reference map (`.bt` or `.ot`); required.
    #[arg(
        long,
        alias = "ref",
        value_name = "REF",
        required_unless_present = "legacy_target"
    )]
    pub reference: Option<PathBuf>,
    /// The map to score against the reference (`.bt` or `.ot`, same resolution).
    pub target: PathBuf,
    /// `scan3d eval REF TARGET`, the form of earlier versions: then the first path is the
    /// reference and this one the target.
    #[arg(hide = true, conflicts_with = "reference")]
    pub legacy_target: Option<PathBuf>,
    /// The universe box in metres, `x0,y0,z0,x1,y1,z1`: the voxels whose centre is inside.
    /// Default: the smallest key box holding every known voxel of either map.
    #[arg(long, value_parser = parse_bbox, allow_hyphen_values = true)]
    pub bbox: Option<MetricBox>,
    /// A ground-truth map (same resolution): adds precision / recall / F1 / Chamfer.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

impl EvalArgs {
    /// The reference and the target these options name, in either form.
    pub fn maps(&self) -> anyhow::Result<(&Path, &Path)> {
        match (&self.reference, &self.legacy_target) {
            (Some(reference), _) => Ok((reference, &self.target)),
            (None, Some(target)) => Ok((&self.target, target)),
            (None, None) => anyhow::bail!("no reference map: give --reference REF"),
        }
    }
}

/// Runs `scan3d eval`.
pub fn run(args: &EvalArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let (reference_path, target_path) = args.maps()?;
    let reference = load_map(reference_path)?;
    let target = load_map(target_path)?;
    let truth = args.truth.as_deref().map(load_map).transpose()?;
    let bbox = key_box(&reference, args.bbox)?;
    let m = evaluate_maps(&reference, &target, bbox, truth.as_ref())?;
    if args.json {
        serde_json::to_writer_pretty(&mut *out, &m)?;
        writeln!(out)?;
    } else {
        write_table(&m, reference_path, target_path, out)?;
    }
    Ok(())
}

/// Writes the metrics as a readable text table.
pub fn write_table(
    m: &Metrics,
    reference: &Path,
    target: &Path,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    let (lo, hi) = (m.bbox.min, m.bbox.max);
    writeln!(out, "reference {}", reference.display())?;
    writeln!(out, "target    {}", target.display())?;
    writeln!(
        out,
        "resolution {} m; U = keys {lo:?}..={hi:?}: {} voxels",
        m.resolution, m.voxels
    )?;
    writeln!(out)?;
    writeln!(
        out,
        "{:<10} {:>14} {:>14} {:>14} {:>8} {:>8} {:>8} {:>10}",
        "map", "occupied", "free", "unknown", "R_occ", "R_free", "R_no", "leaves"
    )?;
    for (name, c) in [("reference", &m.reference), ("target", &m.target)] {
        writeln!(
            out,
            "{:<10} {:>14} {:>14} {:>14} {:>8.4} {:>8.4} {:>8.4} {:>10}",
            name,
            c.occupied,
            c.free,
            c.unknown,
            c.ratio_occupied,
            c.ratio_free,
            c.ratio_unknown,
            c.leaves
        )?;
    }
    writeln!(out)?;
    writeln!(
        out,
        "confusion (voxels; rows reference, columns target)  {:>14} {:>14} {:>14}",
        "occupied", "free", "unknown"
    )?;
    for (name, row) in ["occupied", "free", "unknown"].iter().zip(&m.confusion) {
        writeln!(
            out,
            "{:>50}  {:>14} {:>14} {:>14}",
            name, row[0], row[1], row[2]
        )?;
    }
    writeln!(out)?;
    let i = &m.iou;
    writeln!(
        out,
        "IoU (eq. M4-M7): occupied {}  free {}  unknown {}  weighted {:.6}",
        opt(i.occupied, 6),
        opt(i.free, 6),
        opt(i.unknown, 6),
        i.weighted
    )?;
    writeln!(
        out,
        "log-odds error (eq. M8, KLD ref||target): sum {:.6}  mean {}  over {} common voxels",
        m.log_odds.sum,
        opt(m.log_odds.mean, 6),
        m.log_odds.common_voxels
    )?;
    writeln!(
        out,
        "correlation (eq. M9): paper {}  signed {}  (p_bar {})",
        opt(m.correlation.paper, 6),
        opt(m.correlation.signed, 6),
        opt(m.correlation.p_bar, 6)
    )?;
    writeln!(
        out,
        "mean probability {}  mean |p_ref - p_target| {}",
        opt(m.mean_probability, 6),
        opt(m.probability_deviation, 6)
    )?;
    if let Some(t) = &m.truth {
        writeln!(out)?;
        writeln!(
            out,
            "against truth: {} target / {} truth occupied voxels in U",
            t.target_occupied, t.truth_occupied
        )?;
        writeln!(
            out,
            "  exact:          precision {}  recall {}  F1 {}",
            opt(t.precision, 4),
            opt(t.recall, 4),
            opt(t.f1, 4)
        )?;
        writeln!(
            out,
            "  1-voxel (26-n): precision {}  recall {}  F1 {}",
            opt(t.precision_tolerant, 4),
            opt(t.recall_tolerant, 4),
            opt(t.f1_tolerant, 4)
        )?;
        writeln!(out, "  Chamfer distance {} m", opt(t.chamfer, 4))?;
    }
    Ok(())
}
