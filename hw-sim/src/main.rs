//! `scan3d-sim`: simulated scan3d hardware. Runs an emulated lidar on a pty until interrupted,
//! or the demo.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Parser, Subcommand, ValueEnum};
use scan3d_hw_sim::demo::{self, DemoArgs};
use scan3d_hw_sim::device::Device;
use scan3d_hw_sim::faults::FaultConfig;
use scan3d_hw_sim::mounts;
use scan3d_hw_sim::pty::{PtyDevice, PtyOptions};
use scan3d_hw_sim::rig::{Head, Rig, RigOptions};
use scan3d_hw_sim::rplidar::{RplidarEmulator, RplidarEmulatorConfig, RplidarModel};
use scan3d_hw_sim::sweep::{SweepEmulator, SweepEmulatorConfig};
use scan3d_hw_sim::trolley::TrolleyPath;
use scan3d_hw_sim::world::World;

/// Simulated scan3d hardware.
#[derive(Debug, Parser)]
#[command(name = "scan3d-sim", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run one emulated device on a pty until interrupted (SIGINT/SIGTERM).
    ///
    /// The device appears as a symlink at --link; its path is printed on stdout once it exists.
    Device {
        #[command(subcommand)]
        device: DeviceCommand,
    },
    /// Run the whole system on this machine: emulated lidars and turntable, the edge daemon,
    /// the server, the paper's static maps and their report.
    Demo(DemoArgs),
    /// Run the whole sensor head in real time for the real scan3d-edge daemon until
    /// interrupted: the RPLidar and the Sweep on ptys (DIR/ttyRPLIDAR, DIR/ttySWEEP), the IMU
    /// and the motor HAT on one I2C bus behind DIR/i2c.sock, and DIR/edge.toml with the edge's
    /// sensor sections (prepend device_name and state_dir, append [uplink]).
    ///
    /// Prints the paths it created on stdout once they exist.
    Rig(RigArgs),
}

#[derive(Debug, Args)]
struct RigArgs {
    /// Directory of the links, the socket and edge.toml (created if missing; stale links and
    /// sockets from an earlier run are replaced).
    #[arg(long, value_name = "DIR")]
    dir: PathBuf,
    /// Where the head stands in the room: X,Y in metres and the heading of its yaw 0 in
    /// degrees (default: the room's centre, heading 0).
    #[arg(long, value_name = "X,Y,HEADING", value_parser = parse_at, conflicts_with = "trolley")]
    at: Option<[f64; 3]>,
    /// Put the head on a pushed trolley following the path in PATH.toml (default: a loop
    /// around the demo room's table): at rest for 20 s, then moving, then at rest at the end
    /// of its path. The path's start replaces --at. Format: docs/simulator.md.
    #[arg(long, value_name = "PATH.toml", num_args = 0..=1)]
    trolley: Option<Option<PathBuf>>,
    /// Write the true trajectory of the head's base to FILE: TUM lines `t x y z qx qy qz qw`
    /// (UNIX seconds, room frame) at 50 Hz, each flushed; with --trolley, a last line
    /// `# end of path` once the trolley rests at the end of its path.
    #[arg(long, value_name = "FILE")]
    truth: Option<PathBuf>,
    /// Seed of the range noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// World file (TOML) instead of the default conference room.
    #[arg(long, value_name = "FILE")]
    world: Option<PathBuf>,
    /// With --trolley: an ideal IMU (white noise only) on a level floor, instead of the
    /// default drifting gyro bias, hard and soft iron, a steel cabinet beside the path and
    /// floor bumps (docs/simulator.md).
    #[arg(long, requires = "trolley")]
    ideal_imu: bool,
}

fn parse_at(s: &str) -> Result<[f64; 3], String> {
    let values: Vec<f64> = s
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("expected X,Y,HEADING (three numbers), got {s:?}"))?;
    match values[..] {
        [x, y, h] if values.iter().all(|v| v.is_finite()) => Ok([x, y, h]),
        _ => Err(format!("expected X,Y,HEADING (three numbers), got {s:?}")),
    }
}

#[derive(Debug, Subcommand)]
enum DeviceCommand {
    /// A Slamtec RPLidar A1/A2 (horizontal, at (4.0, 3.0, 0.4) m in the room).
    Rplidar(RplidarArgs),
    /// A Scanse Sweep (vertical scan plane, at (4.0, 3.0, 1.0) m in the room).
    Sweep(SweepArgs),
}

#[derive(Debug, Args)]
struct CommonArgs {
    /// Path of the symlink to create (e.g. /tmp/ttyRPLIDAR or /tmp/ttySWEEP); replaced if it
    /// is a stale link.
    #[arg(long, value_name = "PATH")]
    link: PathBuf,
    /// Simulated seconds per real second (also scales the wire rate).
    #[arg(long, default_value_t = 1.0, value_parser = parse_time_scale)]
    time_scale: f64,
    /// Corrupt the output at RATE faults per byte (half stray bytes, half bit flips).
    #[arg(long, value_name = "RATE", default_value_t = 0.0, value_parser = parse_rate)]
    corrupt: f64,
    /// Seed of the noise and fault generators.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// World file (TOML) instead of the default conference room.
    #[arg(long, value_name = "FILE")]
    world: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct RplidarArgs {
    #[command(flatten)]
    common: CommonArgs,
    /// Which model to emulate.
    #[arg(long, value_enum, default_value_t = ModelArg::A1)]
    model: ModelArg,
    /// Line rate: 115200 or 256000.
    #[arg(long, default_value_t = 115_200, value_parser = parse_baud)]
    baud: u32,
}

#[derive(Debug, Args)]
struct SweepArgs {
    #[command(flatten)]
    common: CommonArgs,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ModelArg {
    /// RPLidar A1 (model byte 0x18).
    A1,
    /// RPLidar A2 (model byte 0x28).
    A2,
}

fn parse_time_scale(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got {s:?}")),
    }
}

fn parse_rate(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a probability between 0 and 1, got {s:?}")),
    }
}

fn parse_baud(s: &str) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(b @ (115_200 | 256_000)) => Ok(b),
        _ => Err(format!("expected 115200 or 256000, got {s:?}")),
    }
}

/// Set by SIGINT/SIGTERM.
static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: nix::libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

fn install_signal_handlers() -> anyhow::Result<()> {
    use nix::sys::signal::{SaFlags, SigAction, SigHandler, SigSet, Signal, sigaction};
    let action = SigAction::new(
        SigHandler::Handler(on_signal),
        SaFlags::empty(),
        SigSet::empty(),
    );
    for signal in [Signal::SIGINT, Signal::SIGTERM] {
        // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
        unsafe { sigaction(signal, &action) }
            .with_context(|| format!("cannot install a handler for {signal}"))?;
    }
    Ok(())
}

fn load_world(path: Option<&PathBuf>) -> anyhow::Result<Arc<World>> {
    Ok(Arc::new(match path {
        Some(p) => World::load(p)?,
        None => World::conference_room(),
    }))
}

/// Runs `device` on a pty behind `common.link` until a signal arrives.
fn serve(common: &CommonArgs, device: Box<dyn Device>) -> anyhow::Result<()> {
    install_signal_handlers()?;
    let options = PtyOptions {
        time_scale: common.time_scale,
        faults: FaultConfig::corrupt(common.corrupt),
        seed: common.seed,
        epoch: None,
    };
    let handle = PtyDevice::spawn(common.link.clone(), device, options)?;
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "{}", handle.link().display()).context("cannot write to stdout")?;
    stdout.flush().context("cannot write to stdout")?;
    while !STOP.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(50));
    }
    let stats = handle.stats();
    tracing::info!(
        written = stats.bytes_written,
        dropped_overrun = stats.bytes_dropped_overrun,
        dropped_no_client = stats.bytes_dropped_no_client,
        "stopping"
    );
    handle.shutdown();
    Ok(())
}

/// Runs the rig until a signal arrives.
fn run_rig(args: &RigArgs) -> anyhow::Result<()> {
    install_signal_handlers()?;
    let world = load_world(args.world.as_ref())?;
    let head = match &args.trolley {
        None => Head::Static { at: args.at },
        Some(None) => Head::Trolley(Arc::new(TrolleyPath::demo_room())),
        Some(Some(path)) => Head::Trolley(Arc::new(TrolleyPath::load(path)?)),
    };
    let options = RigOptions {
        dir: args.dir.clone(),
        head,
        truth: args.truth.clone(),
        seed: args.seed,
    };
    let rig = if args.ideal_imu {
        Rig::start_with_imu(world, &options, None)?
    } else {
        Rig::start(world, &options)?
    };
    let mut stdout = std::io::stdout().lock();
    for path in rig.paths() {
        writeln!(stdout, "{}", path.display()).context("cannot write to stdout")?;
    }
    stdout.flush().context("cannot write to stdout")?;
    while !STOP.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(50));
    }
    tracing::info!("stopping");
    rig.shutdown();
    Ok(())
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Demo(args) => demo::run(&args),
        Command::Rig(args) => run_rig(&args),
        Command::Device {
            device: DeviceCommand::Rplidar(args),
        } => {
            let config = RplidarEmulatorConfig {
                model: match args.model {
                    ModelArg::A1 => RplidarModel::A1,
                    ModelArg::A2 => RplidarModel::A2,
                },
                baud: args.baud,
                ..RplidarEmulatorConfig::default()
            };
            config.validate()?;
            let world = load_world(args.common.world.as_ref())?;
            let scanner = RplidarEmulator::default_scanner(world, mounts::rplidar());
            let device = RplidarEmulator::new(config, scanner, args.common.seed);
            serve(&args.common, Box::new(device))
        }
        Command::Device {
            device: DeviceCommand::Sweep(args),
        } => {
            let world = load_world(args.common.world.as_ref())?;
            let scanner = SweepEmulator::default_scanner(world, mounts::sweep());
            let device =
                SweepEmulator::new(SweepEmulatorConfig::default(), scanner, args.common.seed);
            serve(&args.common, Box::new(device))
        }
    }
}

fn main() {
    let cli = Cli::parse();
    // The demo prints its own summary; devices log their plugging and client connections.
    let default_level = match cli.command {
        Command::Demo(_) => "warn",
        Command::Device { .. } | Command::Rig(_) => "info",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level)),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    if let Err(e) = run(cli) {
        eprintln!("scan3d-sim: error: {}", one_line(&e));
        std::process::exit(1);
    }
}

/// The error and its causes on one line, skipping causes whose text the message already holds
/// (many error types print their source themselves).
fn one_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if !line.contains(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
    }
    line
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Vector3};

    use super::*;

    #[test]
    fn rplidar_pose_is_horizontal() {
        let pose = mounts::rplidar();
        assert!((pose.rotation * Vector3::x() - Vector3::x()).norm() < 1e-12);
        assert_eq!(pose * Point3::origin(), Point3::new(4.0, 3.0, 0.4));
    }

    #[test]
    fn error_line_does_not_repeat_causes() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "gone");
        let e = anyhow::Error::new(io)
            .context("cannot read x: gone")
            .context("starting");
        assert_eq!(one_line(&e), "starting: cannot read x: gone");
    }

    #[test]
    fn cli_parses_and_rejects() {
        <Cli as clap::CommandFactory>::command().debug_assert();
        let ok = Cli::try_parse_from([
            "scan3d-sim",
            "device",
            "rplidar",
            "--link",
            "/tmp/x",
            "--model",
            "a2",
            "--baud",
            "256000",
            "--corrupt",
            "0.001",
        ]);
        assert!(ok.is_ok());
        let rig = Cli::try_parse_from(["scan3d-sim", "rig", "--dir", "/tmp/r", "--at", "1.5,3,90"]);
        assert!(matches!(
            rig,
            Ok(Cli {
                command: Command::Rig(RigArgs {
                    at: Some([1.5, 3.0, 90.0]),
                    ..
                })
            })
        ));
        assert!(
            Cli::try_parse_from(["scan3d-sim", "rig", "--dir", "/tmp/r", "--at", "1.5,3"]).is_err()
        );
        let trolley = |args: &[&str]| {
            let mut all = vec!["scan3d-sim", "rig", "--dir", "/tmp/r"];
            all.extend(args);
            match Cli::try_parse_from(all) {
                Ok(Cli {
                    command: Command::Rig(args),
                }) => Ok(args.trolley),
                Ok(other) => panic!("{other:?}"),
                Err(e) => Err(e.kind()),
            }
        };
        assert_eq!(trolley(&[]), Ok(None));
        assert_eq!(trolley(&["--trolley"]), Ok(Some(None)));
        assert_eq!(
            trolley(&["--trolley", "p.toml", "--truth", "t.tum"]),
            Ok(Some(Some(PathBuf::from("p.toml"))))
        );
        assert_eq!(
            trolley(&["--trolley", "--at", "1,2,3"]),
            Err(clap::error::ErrorKind::ArgumentConflict)
        );
        for bad in [
            [
                "scan3d-sim",
                "device",
                "rplidar",
                "--link",
                "/tmp/x",
                "--baud",
                "9600",
            ],
            [
                "scan3d-sim",
                "device",
                "rplidar",
                "--link",
                "/tmp/x",
                "--corrupt",
                "2",
            ],
            [
                "scan3d-sim",
                "device",
                "sweep",
                "--link",
                "/tmp/x",
                "--time-scale",
                "0",
            ],
        ] {
            assert!(Cli::try_parse_from(bad).is_err(), "{bad:?}");
        }
    }
}
