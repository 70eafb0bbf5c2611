//! `scan3d pair` (being written).

use std::io::Write;

/// Options of `scan3d pair`.
#[derive(Debug, clap::Args)]
pub struct PairArgs {}

/// Runs `scan3d pair`.
pub fn run(_args: &PairArgs, _out: &mut dyn Write) -> anyhow::Result<()> {
    anyhow::bail!("scan3d pair is not built yet")
}
