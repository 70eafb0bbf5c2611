//! `scan3d`: the laptop daemon and offline tool.

use std::process::ExitCode;

use clap::Parser;
use scan3d_server::cli::{Cli, execute};

fn main() -> ExitCode {
    scan3d_service::daemon::init_logging("info");
    let cli = Cli::parse();
    let mut stdout = std::io::stdout().lock();
    match execute(cli, &mut stdout) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let error: &(dyn std::error::Error + 'static) = e.as_ref();
            eprintln!("scan3d: {}", scan3d_service::report::error_chain(error));
            ExitCode::FAILURE
        }
    }
}
