//! `scan3d serve` (being written).

/// Options of `scan3d serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {}

/// Runs `scan3d serve`.
pub fn run(_args: &ServeArgs) -> anyhow::Result<()> {
    anyhow::bail!("scan3d serve is not built yet")
}
