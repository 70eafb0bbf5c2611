//! `scan3d-sim demo`: emulated lidars on ptys, read through the edge drivers.

use std::path::PathBuf;

/// Options of `scan3d-sim demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
}

/// Runs the demo.
pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    anyhow::bail!("demo not built yet (output would go to {})", args.out.display())
}
