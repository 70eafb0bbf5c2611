//! The `scan3d-edge` command line, as a library so tests can run it in-process.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;

use clap::{Args, Parser, Subcommand, ValueEnum};

use crate::clock::{Clock, MonotonicClock, ScaledClock};
use crate::config::EdgeConfig;
use crate::daemon;
use crate::drivers::imu::ImuConfig;
use crate::drivers::rplidar::{Rplidar, RplidarConfig, ScanMode};
use crate::drivers::stepper::StepperConfig;
use crate::drivers::sweep::{Sweep, SweepConfig};
use crate::i2c_probe::{ThreadDelay, probe_imu, probe_stepper};
use crate::lidar::LidarDriver;
use crate::probe::{self, ProbeLine, ProbeOptions};

/// scan3d edge daemon and wiring tools (Raspberry Pi side).
#[derive(Debug, Parser)]
#[command(name = "scan3d-edge", version, about)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Cli {
    /// Run the daemon with this configuration (the default when no subcommand is given).
    #[arg(long, global = false, default_value = "/etc/scan3d/edge.toml")]
    pub config: PathBuf,
    /// A one-shot tool instead of the daemon.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// `scan3d-edge` subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Talk to one device (a lidar, the IMU or the stepper) and print what it answers as JSON
    /// lines.
    #[command(subcommand)]
    Probe(ProbeCommand),
    /// Parse and validate an edge.toml, then print what it configures.
    CheckConfig {
        /// The configuration file.
        #[arg(long, default_value = "/etc/scan3d/edge.toml")]
        config: PathBuf,
    },
}

/// `scan3d-edge probe …`
#[derive(Debug, Subcommand)]
pub enum ProbeCommand {
    /// Probe a Slamtec RPLidar A1/A2: its info, health and a few revolutions.
    Rplidar {
        /// Serial device (e.g. /dev/rplidar or /dev/ttyUSB0).
        path: PathBuf,
        /// Baud rate: 115200 (A1, A2M4–M8) or 256000 (A2M7, A2M12).
        #[arg(long, default_value_t = 115_200)]
        baud: u32,
        /// Scan mode.
        #[arg(long, value_enum, default_value_t = ProbeScanMode::Express)]
        mode: ProbeScanMode,
        /// Revolutions, timeout, time scale.
        #[command(flatten)]
        common: ProbeArgs,
    },
    /// Probe the IMU (MPU-9250 + AK8963) on an I2C bus: chip ids, a few samples, the orientation.
    Imu {
        /// I2C bus number (/dev/i2c-N; the Pi's header is bus 1).
        #[arg(long, default_value_t = 1)]
        bus: u8,
        /// MPU-9250 address: 0x68 (AD0 low) or 0x69.
        #[arg(long, default_value = "0x68", value_parser = parse_i2c_address)]
        address: u8,
        /// Samples to print.
        #[arg(long, default_value_t = 20)]
        samples: usize,
    },
    /// Turn the stepper on the motor HAT forward, then back home, and release it.
    Stepper {
        /// I2C bus number (/dev/i2c-N; the Pi's header is bus 1).
        #[arg(long, default_value_t = 1)]
        bus: u8,
        /// Motor HAT address.
        #[arg(long, default_value = "0x60", value_parser = parse_i2c_address)]
        address: u8,
        /// Steps forward before coming back.
        #[arg(long, default_value_t = 50)]
        steps: u64,
    },
    /// Probe a Scanse Sweep: its info and a few revolutions.
    Sweep {
        /// Serial device (e.g. /dev/sweep or /dev/ttyUSB1).
        path: PathBuf,
        /// Revolutions, timeout, time scale.
        #[command(flatten)]
        common: ProbeArgs,
    },
}

/// Options shared by the two lidar probes.
#[derive(Debug, Args)]
pub struct ProbeArgs {
    /// Full revolutions to print before stopping the device.
    #[arg(long, default_value_t = 3)]
    pub revolutions: usize,
    /// Give up after this many seconds (device time).
    #[arg(long, default_value_t = 30)]
    pub timeout: u64,
    /// Run the edge clock this many times faster than real time (only for a simulated device
    /// started with the same `--time-scale`).
    #[arg(long, default_value_t = 1.0)]
    pub time_scale: f64,
}

/// RPLidar scan modes selectable from the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ProbeScanMode {
    /// 5-byte nodes, ~2000 samples/s.
    Standard,
    /// Legacy express capsules, ~4000 samples/s.
    Express,
}

/// Runs a parsed command line, writing its output to `out`.
pub fn execute(cli: Cli, out: &mut dyn Write) -> anyhow::Result<()> {
    let Some(command) = cli.command else {
        return run_daemon(&cli.config);
    };
    match command {
        Command::Probe(ProbeCommand::Rplidar {
            path,
            baud,
            mode,
            common,
        }) => {
            let config = RplidarConfig {
                baud,
                scan_mode: match mode {
                    ProbeScanMode::Standard => ScanMode::Standard,
                    ProbeScanMode::Express => ScanMode::Express,
                },
                ..RplidarConfig::default()
            };
            run_probe(&mut Rplidar::new(config), path, baud, &common, out)
        }
        Command::Probe(ProbeCommand::Imu {
            bus,
            address,
            samples,
        }) => {
            let config = ImuConfig {
                address,
                ..ImuConfig::default()
            };
            let period_ms = 1000 / u32::from(config.sample_rate_hz.max(1));
            let mut emit = json_lines(out);
            probe_imu(
                open_i2c(bus)?,
                &mut ThreadDelay,
                config,
                samples,
                period_ms.max(1),
                |l| emit.write(l),
            )?;
            emit.finish()
        }
        Command::Probe(ProbeCommand::Stepper {
            bus,
            address,
            steps,
        }) => {
            let config = StepperConfig {
                address,
                ..StepperConfig::default()
            };
            let mut emit = json_lines(out);
            probe_stepper(open_i2c(bus)?, &mut ThreadDelay, &config, steps, |l| {
                emit.write(l)
            })?;
            emit.finish()
        }
        Command::Probe(ProbeCommand::Sweep { path, common }) => {
            let mut driver = Sweep::new(SweepConfig::default())?;
            run_probe(&mut driver, path, 115_200, &common, out)
        }
        Command::CheckConfig { config } => {
            let config = EdgeConfig::load(&config)?;
            writeln!(out, "device {}", config.device_name)?;
            if let Some(r) = &config.rplidar {
                writeln!(
                    out,
                    "rplidar {} at {} baud, {:?} scan",
                    r.path.display(),
                    r.driver.baud,
                    r.driver.scan_mode
                )?;
            }
            if let Some(s) = &config.sweep {
                writeln!(out, "sweep {}", s.path.display())?;
            }
            if let Some(u) = &config.uplink {
                writeln!(
                    out,
                    "uplink to {} (TLS name {}), spool {} MiB in memory, {} MiB on disk",
                    u.server,
                    u.tls_name(),
                    u.spool_memory_mb,
                    u.spool_disk_mb
                )?;
            }
            Ok(())
        }
    }
}

fn run_probe(
    driver: &mut dyn LidarDriver,
    path: PathBuf,
    baud: u32,
    common: &ProbeArgs,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    anyhow::ensure!(common.revolutions > 0, "--revolutions must be at least 1");
    anyhow::ensure!(
        common.time_scale.is_finite() && common.time_scale > 0.0,
        "--time-scale must be a positive number"
    );
    let clock: Arc<dyn Clock> = if common.time_scale == 1.0 {
        Arc::new(MonotonicClock::new())
    } else {
        Arc::new(ScaledClock::new(common.time_scale))
    };
    let options = ProbeOptions {
        path,
        baud,
        revolutions: common.revolutions,
        deadline_ns: common.timeout.saturating_mul(1_000_000_000),
    };
    let mut emit = json_lines(out);
    probe::run(driver, &options, clock, |line: &ProbeLine| emit.write(line))?;
    emit.finish()
}

/// `scan3d-edge --config edge.toml`: runs the daemon until SIGTERM or SIGINT.
fn run_daemon(config_path: &std::path::Path) -> anyhow::Result<()> {
    let config = EdgeConfig::load(config_path)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        tokio::spawn(async move {
            scan3d_service::daemon::wait_for_termination().await;
            let _ = stop_tx.send(true);
        });
        let clock: Arc<dyn Clock> = Arc::new(MonotonicClock::new());
        let session_id = rand::random::<u64>();
        tracing::info!(device = %config.device_name, session = format!("{session_id:016x}"), "edge daemon starting");
        let report = daemon::run(config, clock, session_id, stop_rx).await?;
        for (sensor, lidar) in &report.lidars {
            tracing::info!(%sensor, revolutions = lidar.revolutions, samples = lidar.samples, pauses = lidar.pauses, "lidar summary");
        }
        if let Some(uplink) = &report.uplink {
            tracing::info!(submitted = uplink.submitted, sent = uplink.frames_sent, acks = uplink.acks, connections = uplink.connections, "uplink summary");
        }
        Ok(())
    })
}

/// Opens `/dev/i2c-N` through rppal, with a hint when it is not there.
fn open_i2c(bus: u8) -> anyhow::Result<rppal::i2c::I2c> {
    rppal::i2c::I2c::with_bus(bus).map_err(|e| {
        anyhow::anyhow!(
            "cannot open I2C bus {bus} (/dev/i2c-{bus}): {e} (enable I2C with `raspi-config nonint do_i2c 0` and add the user to the i2c group)"
        )
    })
}

fn parse_i2c_address(text: &str) -> Result<u8, String> {
    let digits = text.strip_prefix("0x").or_else(|| text.strip_prefix("0X"));
    let value = match digits {
        Some(hex) => u8::from_str_radix(hex, 16),
        None => text.parse::<u8>(),
    };
    match value {
        Ok(address) if address <= 0x7f => Ok(address),
        _ => Err(format!(
            "expected a 7-bit I2C address such as 0x68, got {text:?}"
        )),
    }
}

/// Writes serialisable lines as JSON, one per line, remembering the first write error.
struct JsonLines<'a> {
    out: &'a mut dyn Write,
    error: Option<std::io::Error>,
}

fn json_lines(out: &mut dyn Write) -> JsonLines<'_> {
    JsonLines { out, error: None }
}

impl JsonLines<'_> {
    fn write(&mut self, line: &impl serde::Serialize) {
        if self.error.is_none() {
            let result = serde_json::to_string(line)
                .map_err(std::io::Error::other)
                .and_then(|json| writeln!(self.out, "{json}"))
                .and_then(|()| self.out.flush());
            self.error = result.err();
        }
    }

    fn finish(self) -> anyhow::Result<()> {
        match self.error {
            Some(e) => Err(e.into()),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_config(path: PathBuf) -> anyhow::Result<String> {
        let cli = Cli::parse_from(
            ["scan3d-edge", "check-config", "--config"]
                .map(Into::into)
                .into_iter()
                .chain([path.into_os_string()]),
        );
        let mut out = Vec::new();
        execute(cli, &mut out)?;
        Ok(String::from_utf8(out)?)
    }

    #[test]
    fn check_config_passes_the_shipped_example_and_refuses_what_the_daemon_cannot_use() {
        let shipped = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/edge.toml"));
        let printed = check_config(shipped).unwrap();
        assert!(printed.starts_with("device edge-pi-01\n"), "{printed}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("edge.toml");
        std::fs::write(&path, "device_name = \"t\"\n[stepper]\nsteps_per_rev = 0\n").unwrap();
        let message = format!("{:#}", check_config(path).unwrap_err());
        assert!(
            message.contains("line 3: `stepper.steps_per_rev` = 0"),
            "{message}"
        );
    }
}
