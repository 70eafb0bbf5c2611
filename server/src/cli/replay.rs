//! `scan3d replay` (being written).

use std::io::Write;

/// Options of `scan3d replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {}

/// Runs `scan3d replay`.
pub fn run(_args: &ReplayArgs, _out: &mut dyn Write) -> anyhow::Result<()> {
    anyhow::bail!("scan3d replay is not built yet")
}
