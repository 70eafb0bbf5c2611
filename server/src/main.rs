//! `scan3d`: the laptop daemon and offline tool.
use clap::Parser;

/// scan3d server and offline tools.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Cli {}

fn main() {
    let _cli = Cli::parse();
}
