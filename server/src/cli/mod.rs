//! The `scan3d` command line, as a library so tests can run it in-process.

use std::io::Write;

use clap::{Parser, Subcommand};

pub mod pair;
pub mod replay;
pub mod serve;
pub mod sessions;

/// scan3d server and offline tools (laptop side).
#[derive(Debug, Parser)]
#[command(name = "scan3d", version, about)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// `scan3d` subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Create the CA (first time), a server certificate and an edge bundle.
    Pair(pair::PairArgs),
    /// Run the server daemon: accept edges over QUIC and record their sessions.
    Serve(serve::ServeArgs),
    /// List the recorded sessions.
    Sessions(sessions::SessionsArgs),
    /// Feed a recorded session back through the server pipeline as if live.
    Replay(replay::ReplayArgs),
}

/// Runs a parsed command line, writing its output to `out`.
pub fn execute(cli: Cli, out: &mut dyn Write) -> anyhow::Result<()> {
    match cli.command {
        Command::Pair(args) => pair::run(&args, out),
        Command::Serve(args) => serve::run(&args),
        Command::Sessions(args) => sessions::run(&args, out),
        Command::Replay(args) => replay::run(&args, out),
    }
}
