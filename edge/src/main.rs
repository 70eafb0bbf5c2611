//! `scan3d-edge`: the Raspberry Pi daemon and its wiring tools.

use std::process::ExitCode;

use clap::Parser;
use scan3d_edge::cli::{Cli, execute};

fn main() -> ExitCode {
    scan3d_service::daemon::init_logging("warn");
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
