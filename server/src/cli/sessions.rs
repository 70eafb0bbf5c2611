//! `scan3d sessions` (being written).

use std::io::Write;

/// Options of `scan3d sessions`.
#[derive(Debug, clap::Args)]
pub struct SessionsArgs {}

/// Runs `scan3d sessions`.
pub fn run(_args: &SessionsArgs, _out: &mut dyn Write) -> anyhow::Result<()> {
    anyhow::bail!("scan3d sessions is not built yet")
}
