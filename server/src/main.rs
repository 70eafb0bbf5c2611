//! `scan3d`: the laptop daemon and offline tool.

use std::process::ExitCode;

use clap::Parser;
use scan3d_server::cli::{Cli, execute};

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let cli = Cli::parse();
    let mut stdout = std::io::stdout().lock();
    match execute(cli, &mut stdout) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("scan3d: {e:#}");
            ExitCode::FAILURE
        }
    }
}
