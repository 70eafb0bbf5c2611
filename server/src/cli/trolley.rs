//! `scan3d trolley start --edge NAME --at X,Y,HEADING [--name NAME] [--json]` and
//! `scan3d trolley stop --edge NAME [--json]`: open and close a trolley pass on a connected edge
//! through the running server's control socket.
//!
//! `start` says where `base` stands in the room when the pass opens (metres and degrees, parsed
//! as `scan3d scan --at` does, the heading required): the server anchors the session's
//! trajectory there. The edge stamps the start and the stop on its own clock and streams them
//! back as `Body::Pass` markers (recorded on `/scan3d/pass`), so a pass begins and ends at an
//! edge sample time, live and in replay alike. Without `--name` the edge names the pass
//! `pass-N`, N counting from 1 in its session.
//!
//! Refused, with one line and exit status 1: an edge that is not connected, an edge whose
//! `Hello` lists no RPLidar (the server checks before sending), a start while a pass runs and a
//! stop while none does (the edge's reasons).

use std::io::Write;

use scan3d_protocol::Command;

use super::DataDirArgs;
use super::scan::{At, command_request, print_outcome};
use crate::ingest::control::request_command;

/// Options of `scan3d trolley`.
#[derive(Debug, clap::Args)]
pub struct TrolleyArgs {
    /// Start or stop a pass.
    #[command(subcommand)]
    pub action: TrolleyAction,
}

/// `scan3d trolley` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum TrolleyAction {
    /// Open a pass: the head stands at `--at` in the room now.
    Start(StartArgs),
    /// Close the running pass.
    Stop(StopArgs),
}

/// Options of `scan3d trolley start`.
#[derive(Debug, clap::Args)]
pub struct StartArgs {
    /// Where `base` stands: `X,Y,HEADING` in metres and degrees, room frame.
    #[arg(long, value_name = "X,Y,HEADING")]
    pub at: At,
    /// The pass's name (default: the edge's `pass-N`).
    #[arg(long, value_name = "NAME")]
    pub name: Option<String>,
    /// Which edge, answer format, server.
    #[command(flatten)]
    pub common: CommonArgs,
}

/// Options of `scan3d trolley stop`.
#[derive(Debug, clap::Args)]
pub struct StopArgs {
    /// Which edge, answer format, server.
    #[command(flatten)]
    pub common: CommonArgs,
}

/// What `start` and `stop` share.
#[derive(Debug, clap::Args)]
pub struct CommonArgs {
    /// The edge's name (as in its certificate).
    #[arg(long)]
    pub edge: String,
    /// Print the edge's answer as JSON.
    #[arg(long)]
    pub json: bool,
    /// Seconds to wait for the edge's answer.
    #[arg(long, value_name = "SECS", default_value_t = 15.0)]
    pub timeout: f64,
    /// Which server.
    #[command(flatten)]
    pub data: DataDirArgs,
}

impl TrolleyArgs {
    /// The command this invocation sends, or why it cannot be sent.
    pub fn command(&self) -> anyhow::Result<Command> {
        Ok(match &self.action {
            TrolleyAction::Start(start) => {
                let Some(heading_deg) = start.at.heading_deg else {
                    anyhow::bail!(
                        "--at needs X,Y,HEADING for a pass (the heading anchors the trajectory)"
                    );
                };
                Command::StartPass {
                    name: start.name.clone(),
                    x_m: start.at.x_m,
                    y_m: start.at.y_m,
                    heading_deg,
                }
            }
            TrolleyAction::Stop(_) => Command::StopPass,
        })
    }

    fn common(&self) -> &CommonArgs {
        match &self.action {
            TrolleyAction::Start(start) => &start.common,
            TrolleyAction::Stop(stop) => &stop.common,
        }
    }
}

/// Runs `scan3d trolley`.
pub fn run(args: &TrolleyArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let common = args.common();
    let (socket, request) = command_request(
        args.command()?,
        &common.edge,
        &common.data,
        false,
        common.timeout,
    )?;
    let last = request_command(&socket, &request, &mut |_| {})?;
    print_outcome(&last, common.json, out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::control::socket_path;
    use clap::Parser;

    fn parse(args: &[&str]) -> Result<TrolleyArgs, String> {
        let mut argv = vec!["scan3d", "trolley"];
        argv.extend_from_slice(args);
        match crate::cli::Cli::try_parse_from(argv) {
            Ok(crate::cli::Cli {
                command: crate::cli::Command::Trolley(args),
            }) => Ok(args),
            Ok(other) => Err(format!("{other:?}")),
            Err(e) => Err(e.to_string()),
        }
    }

    #[test]
    fn start_and_stop_make_the_pass_commands() {
        let start = parse(&[
            "start",
            "--edge",
            "pi",
            "--at",
            "1.5,-2,90",
            "--name",
            "hall",
        ]);
        assert_eq!(
            start.unwrap().command().unwrap(),
            Command::StartPass {
                name: Some("hall".into()),
                x_m: 1.5,
                y_m: -2.0,
                heading_deg: 90.0
            }
        );
        let unnamed = parse(&["start", "--edge", "pi", "--at", "0,0,0"]).unwrap();
        assert!(matches!(
            unnamed.command().unwrap(),
            Command::StartPass { name: None, .. }
        ));
        let stop = parse(&["stop", "--edge", "pi", "--json"]).unwrap();
        assert_eq!(stop.command().unwrap(), Command::StopPass);
        assert!(stop.common().json);
    }

    #[test]
    fn a_start_needs_a_finite_x_y_and_heading() {
        let no_heading = parse(&["start", "--edge", "pi", "--at", "1,2"]).unwrap();
        assert_eq!(
            no_heading.command().unwrap_err().to_string(),
            "--at needs X,Y,HEADING for a pass (the heading anchors the trajectory)"
        );
        let message = parse(&["start", "--edge", "pi", "--at", "1,nan,0"]).unwrap_err();
        assert!(
            message.contains("\"nan\" is not a finite number"),
            "{message}"
        );
        assert!(parse(&["start", "--edge", "pi"]).is_err());
        assert!(parse(&["stop"]).is_err());
    }

    #[test]
    fn a_not_connected_edge_is_one_error_line() {
        let dir = tempfile::tempdir().unwrap();
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        use crate::ingest::control::{ControlLimits, ControlSocket, EdgeControl};
        let socket = runtime.block_on(async {
            ControlSocket::bind(socket_path(dir.path()), ControlLimits::default())
                .await
                .unwrap()
        });
        runtime.spawn(socket.serve(EdgeControl::default()));
        let argv = [
            "scan3d",
            "trolley",
            "stop",
            "--edge",
            "pi",
            "--data-dir",
            dir.path().to_str().unwrap(),
        ];
        let cli = crate::cli::Cli::try_parse_from(argv).unwrap();
        let mut out = Vec::new();
        let error = crate::cli::execute(cli, &mut out).unwrap_err().to_string();
        assert_eq!(error, "edge \"pi\" is not connected (connected: none)");
        assert!(out.is_empty());
    }
}
