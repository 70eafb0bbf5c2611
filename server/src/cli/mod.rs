//! The `scan3d` command line, as a library so tests can run it in-process.

use std::io::Write;
use std::path::PathBuf;

use clap::{Parser, Subcommand};

use crate::report::MetricBox;

pub mod assemble;
pub mod assemble_moving;
pub mod convert;
pub mod eval;
pub mod info;
pub mod map;
pub mod pair;
pub mod replay;
pub mod report;
pub mod resolution_sweep;
pub mod scan;
pub mod serve;
pub mod sessions;
pub mod slam;
pub mod snapshot;
pub mod status;
pub mod trolley;

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
    /// Create the CA (first time), a server certificate and an edge bundle; renew or revoke one.
    Pair(pair::PairArgs),
    /// Run the server daemon: accept edges over QUIC and record their sessions.
    Serve(serve::ServeArgs),
    /// What the daemon's live pipeline has built, per connected edge and session.
    Status(status::StatusArgs),
    /// Have the daemon write a session's live octree, cloud and metrics into a directory.
    Snapshot(snapshot::SnapshotArgs),
    /// List the recorded sessions.
    Sessions(sessions::SessionsArgs),
    /// Feed a recorded session back through the server pipeline as if live.
    Replay(replay::ReplayArgs),
    /// Tell a connected edge to make a static 3D scan at a known position (or to stop one).
    Scan(scan::ScanArgs),
    /// Open or close a trolley pass on a connected edge (the head's pose in the room at the start).
    Trolley(trolley::TrolleyArgs),
    /// Turn a session's static scans into one world-frame cloud (eq. 1), or with --moving a
    /// trolley pass's Sweep samples each at its own pose: PLY, PCD or .scans.
    Assemble(assemble::AssembleArgs),
    /// Build an OctoMap-identical occupancy map (.bt/.ot) from a cloud, with filters.
    Map(map::MapArgs),
    /// Convert maps (.bt <-> .ot) or clouds (.graph/.scans/.ply/.pcd -> .scans/.ply/.pcd).
    Convert(convert::ConvertArgs),
    /// Describe a map: resolution, nodes, leaves, occupied/free, bounding box.
    Info(info::InfoArgs),
    /// Score a map against a reference with the paper's metrics (IoU, log-odds, correlation).
    Eval(eval::EvalArgs),
    /// Table III, the metric table, metrics.json and Fig. 11 for several maps against a reference.
    Report(report::ReportArgs),
    /// Fig. 12: build time, nodes, occupied volume and evaluation time against resolution.
    #[command(name = "sweep")]
    ResolutionSweep(resolution_sweep::ResolutionSweepArgs),
    /// 2D scan matching (Hector-style) of a CARMEN log or a session: a trajectory and a map.
    Slam(slam::SlamArgs),
    /// Score a 2D trajectory against reference relations (Kümmerle et al. 2009).
    SlamEval(slam::SlamEvalArgs),
    /// Absolute error of a TUM trajectory (a pass's trajectory.tum) against a reference in the
    /// same frame (the simulator's --truth): position and heading RMSE.
    TrajEval(slam::TrajEvalArgs),
}

/// Where a server keeps its recordings: `--data-dir`, or the `data_dir` of `--config`.
#[derive(Debug, Clone, clap::Args)]
pub struct DataDirArgs {
    /// The server's data directory (sessions under `DIR/sessions`, control socket
    /// `DIR/control.sock`). Without it, the `data_dir` of `--config` is used.
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    /// The server configuration to take `data_dir` from when `--data-dir` is not given.
    #[arg(long, default_value = "/etc/scan3d/server.toml")]
    pub config: PathBuf,
}

impl DataDirArgs {
    /// The data directory these options name.
    pub fn resolve(&self) -> anyhow::Result<PathBuf> {
        match &self.data_dir {
            Some(dir) => Ok(dir.clone()),
            None => Ok(crate::config::ServerConfig::load(&self.config)?.data_dir),
        }
    }
}

/// Comma-separated finite numbers on the command line, as many as given: the one parser behind
/// every `X,Y,...` option, so they all accept and reject the same text.
pub fn parse_finite_list(text: &str) -> Result<Vec<f64>, String> {
    text.split(',')
        .map(|v| {
            v.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("{v:?} is not a finite number"))
        })
        .collect()
}

/// `N` comma-separated finite numbers on the command line; `what` names them in the error.
pub fn parse_finite_numbers<const N: usize>(text: &str, what: &str) -> Result<[f64; N], String> {
    let values = parse_finite_list(text)?;
    let given = values.len();
    <[f64; N]>::try_from(values)
        .map_err(|_| format!("expected {what} ({N} finite numbers), got {given} in {text:?}"))
}

/// Parses `x0,y0,z0,x1,y1,z1` (metres), as `--bbox` takes it.
pub fn parse_bbox(s: &str) -> Result<MetricBox, String> {
    let [x0, y0, z0, x1, y1, z1] = parse_finite_numbers(s, "bbox x0,y0,z0,x1,y1,z1")?;
    Ok(MetricBox {
        min: [x0, y0, z0],
        max: [x1, y1, z1],
    })
}

/// Runs a parsed command line, writing its output to `out`.
pub fn execute(cli: Cli, out: &mut dyn Write) -> anyhow::Result<()> {
    match cli.command {
        Command::Pair(args) => pair::run(&args, out),
        Command::Serve(args) => serve::run(&args),
        Command::Status(args) => status::run(&args, out),
        Command::Snapshot(args) => snapshot::run(&args, out),
        Command::Sessions(args) => sessions::run(&args, out),
        Command::Replay(args) => replay::run(&args, out),
        Command::Scan(args) => scan::run(&args, out),
        Command::Trolley(args) => trolley::run(&args, out),
        Command::Assemble(args) => assemble::run(&args, out),
        Command::Map(args) => map::run(&args, out),
        Command::Convert(args) => convert::run(&args, out),
        Command::Info(args) => info::run(&args, out),
        Command::Eval(args) => eval::run(&args, out),
        Command::Report(args) => report::run(&args, out),
        Command::ResolutionSweep(args) => resolution_sweep::run(&args, out),
        Command::Slam(args) => slam::run(&args, out),
        Command::SlamEval(args) => slam::run_eval(&args, out),
        Command::TrajEval(args) => slam::run_traj_eval(&args, out),
    }
}

#[cfg(test)]
mod tests {
    use super::parse_bbox;
    use crate::report::MetricBox;

    #[test]
    fn a_bbox_needs_six_finite_numbers_and_says_what_it_got() {
        assert_eq!(
            parse_bbox(" -1, -2,0 ,3,4,2.5"),
            Ok(MetricBox {
                min: [-1.0, -2.0, 0.0],
                max: [3.0, 4.0, 2.5],
            })
        );
        assert_eq!(
            parse_bbox("0,0,0,1,1"),
            Err(
                "expected bbox x0,y0,z0,x1,y1,z1 (6 finite numbers), got 5 in \"0,0,0,1,1\"".into()
            )
        );
        // NaN parses as a float; a box with it would select nothing without saying why.
        assert_eq!(
            parse_bbox("0,0,0,1,1,NaN"),
            Err("\"NaN\" is not a finite number".into())
        );
    }
}
