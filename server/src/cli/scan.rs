//! `scan3d scan --edge NAME --at X,Y[,HEADING] [--name POS] [--wait] [--json]`: starts a static
//! 3D scan on a connected edge through the running server's control socket and reports what
//! the edge did; `--stop` ends one early.
//!
//! The command waits for the edge's answer (its `CommandReply` frame): accepted, refused with
//! the reason (exit status 1), or waiting for the Sweep to stream. `--wait` follows the scan to
//! its end (revolutions, yaw reached, late steps; a progress bar on a terminal, plain lines
//! otherwise) and exits 0 only when it completed. `--json` prints the last status as one JSON
//! object ([`crate::ingest::control::CommandStatus`]).
//!
//! The edge's session holds the scan: a `StaticScan::Started` frame with the position and
//! mount, a `StaticScan::Yaws` per Sweep revolution, then `StaticScan::Finished`;
//! `scan3d assemble SESSION_DIR` turns them into a cloud.

use std::io::Write;
use std::str::FromStr;

use scan3d_protocol::Command;

use super::DataDirArgs;
use crate::ingest::control::{
    CommandRequest, CommandState, CommandStatus, request_command, socket_path,
};

/// A position on the floor as the operator types it: `X,Y` or `X,Y,HEADING` (metres, degrees).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct At {
    /// x, metres.
    pub x_m: f64,
    /// y, metres.
    pub y_m: f64,
    /// Heading φ0 of the turntable's zero, degrees, if given.
    pub heading_deg: Option<f64>,
}

impl FromStr for At {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let values = super::parse_finite_list(text)?;
        match values[..] {
            [x_m, y_m] => Ok(At {
                x_m,
                y_m,
                heading_deg: None,
            }),
            [x_m, y_m, heading] => Ok(At {
                x_m,
                y_m,
                heading_deg: Some(heading),
            }),
            _ => Err(format!(
                "expected X,Y or X,Y,HEADING, got {} values",
                values.len()
            )),
        }
    }
}

/// Options of `scan3d scan`.
#[derive(Debug, clap::Args)]
pub struct ScanArgs {
    /// The edge's name (as in its certificate).
    #[arg(long)]
    pub edge: String,
    /// Where the turntable stands: `X,Y[,HEADING]` in metres and degrees, map frame.
    #[arg(long, value_name = "X,Y[,HEADING]", required_unless_present = "stop")]
    pub at: Option<At>,
    /// The position's name (default `pX_Y`).
    #[arg(long, value_name = "POS")]
    pub name: Option<String>,
    /// Stop the running scan instead (the turntable returns home).
    #[arg(long, conflicts_with_all = ["at", "name", "wait"])]
    pub stop: bool,
    /// Follow the scan to its end (also while the edge waits for the Sweep); exit 0 only if
    /// it completed.
    #[arg(long)]
    pub wait: bool,
    /// Print the last status as JSON.
    #[arg(long)]
    pub json: bool,
    /// Seconds to wait for the edge's answer.
    #[arg(long, value_name = "SECS", default_value_t = 15.0)]
    pub timeout: f64,
    /// Which server.
    #[command(flatten)]
    pub data: DataDirArgs,
}

impl ScanArgs {
    /// The command this invocation sends.
    pub fn command(&self) -> Command {
        match self.at {
            Some(at) if !self.stop => Command::StartStaticScan {
                position: self
                    .name
                    .clone()
                    .unwrap_or_else(|| format!("p{}_{}", at.x_m, at.y_m)),
                x_m: at.x_m,
                y_m: at.y_m,
                heading_deg: at.heading_deg,
            },
            _ => Command::StopStaticScan,
        }
    }
}

/// Runs `scan3d scan`.
pub fn run(args: &ScanArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let (socket, request) = command_request(
        args.command(),
        &args.edge,
        &args.data,
        args.wait,
        args.timeout,
    )?;
    let mut progress = Progress::new(args.wait && !args.json);
    let last = request_command(&socket, &request, &mut |status| {
        if !status.done {
            progress.show(status, out)
        }
    })?;
    progress.finish();
    print_outcome(&last, args.json, out)
}

/// Checks `command` and `timeout` here (the server checks too; here gives the reason without a
/// round trip) and makes the control socket's request for `edge`, following it if `follow`.
pub(crate) fn command_request(
    command: Command,
    edge: &str,
    data: &DataDirArgs,
    follow: bool,
    timeout: f64,
) -> anyhow::Result<(std::path::PathBuf, CommandRequest)> {
    command
        .validate()
        .map_err(|e| anyhow::anyhow!("invalid command: {e}"))?;
    if !(timeout.is_finite() && timeout > 0.0) {
        anyhow::bail!("--timeout {timeout} is not a positive number of seconds");
    }
    let socket = socket_path(&data.resolve()?);
    let request = CommandRequest {
        edge: edge.to_owned(),
        command,
        follow,
        reply_timeout_s: Some(timeout),
    };
    Ok((socket, request))
}

/// Prints a command's last status (JSON, or its detail line when it succeeded) and fails with
/// the detail when it did not.
pub(crate) fn print_outcome(
    last: &CommandStatus,
    json: bool,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    if json {
        writeln!(out, "{}", serde_json::to_string_pretty(last)?)?;
    } else if last.ok {
        writeln!(out, "{}", last.detail)?;
    }
    if !last.ok {
        anyhow::bail!("{}", last.detail);
    }
    Ok(())
}

/// How `--wait` shows a scan under way: a bar on a terminal (stderr), a line per change on
/// stdout otherwise.
struct Progress {
    enabled: bool,
    bar: Option<indicatif::ProgressBar>,
    last_line: Option<(CommandState, u32)>,
}

impl Progress {
    fn new(enabled: bool) -> Self {
        use std::io::IsTerminal;
        let bar = (enabled && std::io::stderr().is_terminal()).then(|| {
            let bar = indicatif::ProgressBar::new(1000);
            bar.set_style(
                indicatif::ProgressStyle::with_template("{bar:30} {percent:>3}% {msg}")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
            bar
        });
        Progress {
            enabled,
            bar,
            last_line: None,
        }
    }

    fn show(&mut self, status: &CommandStatus, out: &mut dyn Write) {
        if !self.enabled {
            return;
        }
        let revolutions = status.progress.as_ref().map_or(0, |p| p.revolutions);
        match &self.bar {
            Some(bar) => {
                let fraction = status.progress.as_ref().map_or(0.0, |p| p.fraction());
                bar.set_position((fraction * 1000.0).round() as u64);
                bar.set_message(status.detail.clone());
            }
            None => {
                // Keep-alive repeats change nothing: one line per state or revolution.
                let key = (status.state, revolutions);
                if self.last_line != Some(key) {
                    self.last_line = Some(key);
                    let _ = writeln!(out, "{}", status.detail);
                }
            }
        }
    }

    fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_parse() {
        assert_eq!(
            "1.5,-2".parse::<At>(),
            Ok(At {
                x_m: 1.5,
                y_m: -2.0,
                heading_deg: None
            })
        );
        assert_eq!(
            "0,0,90".parse::<At>(),
            Ok(At {
                x_m: 0.0,
                y_m: 0.0,
                heading_deg: Some(90.0)
            })
        );
        assert!("1".parse::<At>().is_err());
        assert!("1,2,3,4".parse::<At>().is_err());
        assert_eq!(
            "1,x".parse::<At>(),
            Err("\"x\" is not a finite number".to_string())
        );
        assert!("1,nan".parse::<At>().is_err());
    }

    /// A control socket in `dir` with edge `pi` connected, whose connection task is scripted:
    /// each command is answered by `answer(seq, command)`'s frames.
    fn scripted_edge(
        dir: &std::path::Path,
        answer: impl Fn(u64, &Command) -> Vec<scan3d_protocol::Body> + Send + 'static,
    ) -> (tokio::runtime::Runtime, std::path::PathBuf) {
        use crate::ingest::control::{ControlLimits, ControlSocket, EdgeControl, SentCommand};
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let control = EdgeControl::default();
        let mut commands = control.register("pi");
        let socket = runtime.block_on(async {
            ControlSocket::bind(socket_path(dir), ControlLimits::default())
                .await
                .unwrap()
        });
        let path = socket.path().to_path_buf();
        runtime.spawn(socket.serve(control.clone()));
        runtime.spawn(async move {
            let mut seq = 0;
            while let Some(queued) = commands.recv().await {
                if let Some(sent) = queued.sent {
                    let _ = sent.send(SentCommand { session_id: 1, seq });
                }
                for (i, body) in answer(seq, &queued.command).into_iter().enumerate() {
                    control.publish("pi", &scan3d_protocol::Frame::new(1, 100 + i as u64, body));
                }
                seq += 1;
            }
        });
        (runtime, path)
    }

    fn run_cli(dir: &std::path::Path, args: &[&str]) -> (anyhow::Result<()>, String) {
        use clap::Parser;
        let dir = dir.to_str().unwrap();
        let mut argv = vec!["scan3d", "scan", "--edge", "pi", "--data-dir", dir];
        argv.extend_from_slice(args);
        let cli = crate::cli::Cli::try_parse_from(argv).unwrap();
        let mut out = Vec::new();
        let result = crate::cli::execute(cli, &mut out);
        (result, String::from_utf8(out).unwrap())
    }

    #[test]
    fn wait_follows_the_scan_to_its_end_and_a_refusal_is_an_error_with_the_edges_reason() {
        use scan3d_protocol::{
            CommandOutcome, CommandReply, StaticScan, StaticScanEnd, StaticScanOutcome,
            StaticScanYaws, YawRun,
        };
        let dir = tempfile::tempdir().unwrap();
        let (_runtime, _socket) = scripted_edge(dir.path(), |seq, command| {
            let reply = |outcome| {
                CommandReply {
                    command_seq: seq,
                    t_ns: 1,
                    outcome,
                }
                .into()
            };
            match command {
                Command::StopStaticScan => vec![reply(CommandOutcome::Refused {
                    reason: "no static scan is running".into(),
                })],
                _ => {
                    let yaws = |yaw_deg| {
                        StaticScan::Yaws(StaticScanYaws {
                            scan_id: 0,
                            revolution_t0_ns: 0,
                            runs: vec![YawRun {
                                first_index: 0,
                                count: 1,
                                yaw_deg,
                            }],
                        })
                        .into()
                    };
                    vec![
                        reply(CommandOutcome::Accepted { scan_id: Some(0) }),
                        yaws(90.0),
                        yaws(180.0),
                        StaticScan::Finished(StaticScanEnd {
                            scan_id: 0,
                            t_ns: 2,
                            outcome: StaticScanOutcome::Completed,
                            yaw_deg: 180.0,
                            revolutions: 2,
                            tagged: 2,
                            blocked: 0,
                            untrusted: 0,
                            late_steps: 0,
                            failed_steps: 0,
                        })
                        .into(),
                    ]
                }
            }
        });
        let (result, out) = run_cli(dir.path(), &["--at", "1,2", "--name", "door", "--wait"]);
        result.unwrap();
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(
            lines.last().copied(),
            Some(
                "static scan 0 at \"\": 2 revolutions, yaw 180.0° of 0.0°, 0 late steps, 0 failed steps — completed"
            ),
            "{out}"
        );
        assert!(lines.len() >= 2, "progress lines before the end: {out}");
        let (result, out) = run_cli(dir.path(), &["--at", "1,2", "--json"]);
        result.unwrap();
        let status: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(status["state"], "accepted");
        assert_eq!(status["scan_id"], 0);
        let (result, out) = run_cli(dir.path(), &["--stop"]);
        assert_eq!(
            result.unwrap_err().to_string(),
            "edge pi refused: no static scan is running"
        );
        assert_eq!(out, "", "a refusal prints nothing on stdout");
        let (result, out) = run_cli(dir.path(), &["--stop", "--json"]);
        assert!(result.is_err());
        let status: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(
            (status["state"].as_str(), status["ok"].as_bool()),
            (Some("refused"), Some(false))
        );
        // An edge that never answers: bounded, with the reason.
        std::fs::create_dir(dir.path().join("silent")).unwrap();
        let (_silent_runtime, _) = scripted_edge(&dir.path().join("silent"), |_, _| Vec::new());
        let (result, _) = run_cli(&dir.path().join("silent"), &["--stop", "--timeout", "0.5"]);
        let err = result.unwrap_err().to_string();
        assert!(
            err.starts_with("edge pi did not answer: no answer within 0.5 s"),
            "{err}"
        );
    }

    #[test]
    fn an_invalid_command_is_refused_before_the_server_is_asked() {
        use clap::Parser;
        let long = "p".repeat(300);
        let cli = crate::cli::Cli::try_parse_from([
            "scan3d",
            "scan",
            "--edge",
            "pi",
            "--at",
            "1,2",
            "--name",
            &long,
            "--data-dir",
            "/nonexistent/scan3d-data",
        ])
        .unwrap();
        let err = crate::cli::execute(cli, &mut Vec::new()).unwrap_err();
        assert_eq!(
            err.to_string(),
            "invalid command: position name of 300 bytes: must be 1 to 256 bytes"
        );
    }
}
