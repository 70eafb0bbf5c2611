//! `scan3d info MAP [--json]`: what an OctoMap `.bt`/`.ot` holds.

use std::io::Write;
use std::path::PathBuf;

use super::map::read_tree;

/// Options of `scan3d info`.
#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// A `.bt` or `.ot` map.
    pub map: PathBuf,
    /// One JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Runs `scan3d info`.
pub fn run(args: &InfoArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let tree = read_tree(&args.map)?;
    let res = tree.resolution().meters();
    let bounds = tree.metric_bounds();
    if args.json {
        let value = serde_json::json!({
            "file": args.map,
            "resolution": res,
            "nodes": tree.num_nodes(),
            "leaves": tree.num_leaves(),
            "occupied_leaves": tree.num_occupied(),
            "free_leaves": tree.num_free(),
            "bbox_min": bounds.map(|b| b.0),
            "bbox_max": bounds.map(|b| b.1),
        });
        writeln!(out, "{value}")?;
        return Ok(());
    }
    writeln!(out, "{}", args.map.display())?;
    writeln!(out, "  resolution  {res} m")?;
    writeln!(out, "  nodes       {}", tree.num_nodes())?;
    writeln!(
        out,
        "  leaves      {} ({} occupied, {} free)",
        tree.num_leaves(),
        tree.num_occupied(),
        tree.num_free()
    )?;
    match bounds {
        Some((min, max)) => writeln!(
            out,
            "  bbox        ({:.3}, {:.3}, {:.3}) .. ({:.3}, {:.3}, {:.3}) m",
            min[0], min[1], min[2], max[0], max[1], max[2]
        )?,
        None => writeln!(out, "  bbox        (empty map)")?,
    }
    Ok(())
}
