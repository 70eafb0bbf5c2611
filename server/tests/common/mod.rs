//! What the server's integration tests share: the map crate's test data helpers (the vendored
//! OctoMap data and OctoMap's tools, re-exported) and an in-process `scan3d` runner.
//!
//! Each test file includes it as `mod common;`; not every target uses every item.
#![allow(dead_code)]

use std::path::Path;

#[path = "../../../map/tests/common/mod.rs"]
mod testdata;

#[allow(unused_imports)]
pub use testdata::*;

/// Runs `scan3d ARGS…` in process, as the binary's `main` would, and returns what it printed.
pub fn run_cli(args: &[&str]) -> anyhow::Result<String> {
    use clap::Parser;
    let cli = scan3d_server::cli::Cli::try_parse_from(
        std::iter::once("scan3d").chain(args.iter().copied()),
    )?;
    let mut out = Vec::new();
    scan3d_server::cli::execute(cli, &mut out)?;
    Ok(String::from_utf8(out)?)
}

/// `path` as a CLI argument.
pub fn arg(path: &Path) -> &str {
    path.to_str().expect("utf-8 path")
}
