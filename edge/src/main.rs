//! `scan3d-edge`: the Raspberry Pi daemon and its wiring tools.

use std::process::ExitCode;

use clap::Parser;
use scan3d_edge::cli::{Cli, execute};

fn main() -> ExitCode {
    let cli = Cli::parse();
    // The daemon speaks at info (devices opened, the server, what fails); the one-shot tools
    // keep stderr for warnings, their output is on stdout.
    let daemon = cli.command.is_none();
    scan3d_service::daemon::init_logging(if daemon { "info" } else { "warn" });
    let mut stdout = std::io::stdout().lock();
    match execute(cli, &mut stdout) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let error: &(dyn std::error::Error + 'static) = e.as_ref();
            eprintln!(
                "scan3d-edge: {}",
                scan3d_service::report::error_chain(error)
            );
            ExitCode::FAILURE
        }
    }
}
