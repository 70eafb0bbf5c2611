//! `scan3d sweep CLOUD --resolution 0.05,0.1,… --out DIR`: Fig. 12 — for each resolution, the octree
//! build time, node count, occupied volume and the time of all metrics (the map against
//! itself, as the paper did), as `sweep.json`, `fig12.svg` and `fig12.png`.

use std::io::Write;
use std::path::PathBuf;

use crate::report::write_resolution_sweep;

/// Options of `scan3d sweep`.
#[derive(Debug, clap::Args)]
pub struct ResolutionSweepArgs {
    /// The point cloud: `.graph` (OctoMap ScanGraph), `.scans`, `.ply` or `.pcd` with origins.
    pub cloud: PathBuf,
    /// Resolutions in metres, comma-separated.
    #[arg(
        long,
        alias = "res",
        value_name = "M,M,…",
        value_delimiter = ',',
        default_value = "0.05,0.1,0.2,0.3,0.4,0.5"
    )]
    pub resolution: Vec<f64>,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Maximum range in metres for insertion (negative: none).
    #[arg(long, value_name = "M", default_value_t = -1.0, allow_hyphen_values = true)]
    pub max_range: f64,
    /// Timing repetitions; the best is kept (the machine may be shared).
    #[arg(long, default_value_t = 3)]
    pub reps: u32,
}

/// Runs `scan3d sweep`.
pub fn run(args: &ResolutionSweepArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let written = write_resolution_sweep(
        &args.cloud,
        &args.resolution,
        args.max_range,
        args.reps,
        &args.out,
        out,
    )?;
    for p in written {
        writeln!(out, "wrote {}", p.display())?;
    }
    Ok(())
}
