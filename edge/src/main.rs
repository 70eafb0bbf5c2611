//! `scan3d-edge`: the Raspberry Pi daemon and its wiring tools.

use std::process::ExitCode;

use clap::Parser;
use scan3d_edge::cli::{Cli, execute};

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .init();
    let cli = Cli::parse();
    let mut stdout = std::io::stdout().lock();
    match execute(cli, &mut stdout) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("scan3d-edge: {e:#}");
            ExitCode::FAILURE
        }
    }
}
