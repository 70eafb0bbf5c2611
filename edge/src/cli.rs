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
    /// Calibrate the IMU in the field through the daemon's own configuration and bus (stop
    /// the daemon first), then print the `[imu]` keys to paste or write them with --write.
    #[command(subcommand)]
    Calibrate(CalibrateCommand),
}

/// `scan3d-edge calibrate …`
#[derive(Debug, Subcommand)]
pub enum CalibrateCommand {
    /// The gyro bias: keep the head still while it averages the rates; refused if it moved.
    Gyro {
        /// Configuration, output.
        #[command(flatten)]
        common: CalibrateArgs,
        /// Seconds to average.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Refuse when a rate's standard deviation exceeds this, °/s (the head moved).
        #[arg(long, default_value_t = crate::calibrate::DEFAULT_MAX_RATE_STD_DPS)]
        max_rate_std_dps: f64,
    },
    /// The magnetometer's hard and soft iron: turn the head slowly while it records, through
    /// all orientations (a 3D fit), or a trolley about its vertical only, a full turn or more
    /// (a 2D fit of the horizontal ellipse).
    Mag {
        /// Configuration, output.
        #[command(flatten)]
        common: CalibrateArgs,
        /// Seconds to record.
        #[arg(long, default_value_t = 60.0)]
        seconds: f64,
        /// The local field's total intensity, µT (from a geomagnetic model for the site): the
        /// radius of the calibrated sphere; in 2D also what sets the z offset.
        #[arg(long, value_name = "UT")]
        field_ut: Option<f64>,
        /// The local field's inclination, degrees (negative south of the magnetic equator):
        /// with --field-ut, the horizontal and vertical parts for a 2D fit.
        #[arg(long, value_name = "DEG", allow_negative_numbers = true)]
        inclination_deg: Option<f64>,
    },
}

/// Options shared by the calibrations.
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// The daemon's configuration: its `[imu]` settings and the `[i2c]` bus or socket.
    #[arg(long, default_value = "/etc/scan3d/edge.toml")]
    pub config: PathBuf,
    /// Also write the keys into this edge.toml's `[imu]` table (the rest of the file is kept).
    #[arg(long, value_name = "EDGE.toml")]
    pub write: Option<PathBuf>,
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
        Command::Calibrate(command) => run_calibrate(command, out),
        Command::CheckConfig { config: path } => {
            let config = EdgeConfig::load(&path)?;
            print_config(&config, out)?;
            let problems = environment_problems(&config);
            if problems.is_empty() {
                return Ok(());
            }
            // One line per problem, each naming the file.
            let lines: Vec<String> = problems
                .iter()
                .map(|p| format!("{}: {p}", path.display()))
                .collect();
            anyhow::bail!("{}", lines.join("\n"))
        }
    }
}

/// Prints every section of a configuration, one or two lines each (`check-config`).
fn print_config(config: &EdgeConfig, out: &mut dyn Write) -> std::io::Result<()> {
    let mount = |mount: &Option<crate::config::Mount>| match mount {
        Some(m) => format!(
            "mount x {} y {} z {} m, roll {} pitch {} yaw {} deg",
            m.x, m.y, m.z, m.roll, m.pitch, m.yaw
        ),
        None => "no mount".to_owned(),
    };
    writeln!(out, "device {}", config.device_name)?;
    writeln!(out, "state_dir {}", config.state_dir.display())?;
    match &config.rplidar {
        Some(r) => writeln!(
            out,
            "rplidar {} at {} baud, {:?} scan; {}; {:?}",
            r.path.display(),
            r.driver.baud,
            r.driver.scan_mode,
            mount(&r.mount),
            r.driver
        )?,
        None => writeln!(out, "rplidar: not configured")?,
    }
    match &config.sweep {
        Some(s) => writeln!(
            out,
            "sweep {}; {}; {:?}",
            s.path.display(),
            mount(&s.mount),
            s.driver
        )?,
        None => writeln!(out, "sweep: not configured")?,
    }
    match &config.uplink {
        Some(u) => writeln!(
            out,
            "uplink to {} (TLS name {}), bundle {}, spool {} MiB in memory, {} MiB on disk",
            u.server,
            u.tls_name(),
            u.pki_dir.display(),
            u.spool_memory_mb,
            u.spool_disk_mb
        )?,
        None => writeln!(out, "uplink: not configured (acquiring without streaming)")?,
    }
    let i2c_used = config.imu.is_some() || config.stepper.is_some();
    writeln!(
        out,
        "i2c {} ({}){}",
        config.i2c.device_path().display(),
        if config.i2c.socket.is_some() {
            "emulated bus socket"
        } else {
            "rppal"
        },
        if i2c_used { "" } else { ", unused" }
    )?;
    match &config.imu {
        Some(imu) => writeln!(
            out,
            "imu address {:#04x}, beta {}, initial orientation {:?}; {}; {:?}",
            imu.driver.address,
            imu.beta,
            imu.initial_orientation_wxyz,
            mount(&imu.mount),
            imu.driver
        )?,
        None => writeln!(out, "imu: not configured")?,
    }
    match &config.stepper {
        Some(stepper) => writeln!(out, "stepper {stepper:?}")?,
        None => writeln!(out, "stepper: not configured (no static scans)")?,
    }
    let scan = &config.static_scan;
    writeln!(
        out,
        "static_scan blocked sector {} deg, {} step(s) per Sweep revolution, total {} deg, \
         azimuth zero {} deg, mount axis offset {} m height {} m; {:?}",
        scan.blocked_sector_deg,
        scan.steps_per_revolution_of_sweep,
        scan.total_sweep_deg,
        scan.azimuth_zero_deg,
        scan.mount.axis_offset_m,
        scan.mount.height_m,
        scan
    )
}

/// What `check-config` finds wrong outside the file: serial paths that are missing or not
/// character devices, an I2C bus or socket that is not there, PKI files that do not load, a
/// `device_name` other than the certificate's. One line per problem.
pub fn environment_problems(config: &EdgeConfig) -> Vec<String> {
    use crate::serial::{OpenFailure, PathKind};
    let mut problems = Vec::new();
    let lidars = [
        ("rplidar", config.rplidar.as_ref().map(|s| &s.path)),
        ("sweep", config.sweep.as_ref().map(|s| &s.path)),
    ];
    for (section, path) in lidars {
        let Some(path) = path else { continue };
        match PathKind::of(path) {
            PathKind::CharDevice => {}
            PathKind::Missing => problems.push(format!(
                "[{section}] {}",
                OpenFailure::Missing.message(path, "")
            )),
            PathKind::Other(what) => problems.push(format!(
                "[{section}] {}",
                OpenFailure::NotSerial(what).message(path, "")
            )),
            PathKind::Unknown => problems.push(format!(
                "[{section}] {} cannot be examined (permission denied on a directory?)",
                path.display()
            )),
        }
    }
    if config.imu.is_some() || config.stepper.is_some() {
        problems.extend(i2c_problem(&config.i2c));
    }
    if let Some(uplink) = &config.uplink {
        if let Err(e) = crate::uplink::tls::client_config(&uplink.pki_dir) {
            problems.push(format!(
                "[uplink] {}",
                scan3d_service::report::error_chain(&e)
            ));
        } else {
            let cert = uplink.pki_dir.join(crate::uplink::tls::BUNDLE_CERT);
            match certificate_name(&cert) {
                Ok(name) if name == config.device_name => {}
                Ok(name) => problems.push(format!(
                    "device_name {:?} differs from the name in {} ({name:?}): the server records \
                     this edge under {name:?}; set device_name = {name:?}, or pair again with \
                     `scan3d pair --edge {}`",
                    config.device_name,
                    cert.display(),
                    config.device_name
                )),
                Err(e) => problems.push(format!("[uplink] {}: {e}", cert.display())),
            }
        }
    }
    problems
}

/// Whether the I2C bus device or socket is there.
fn i2c_problem(i2c: &crate::config::I2cSection) -> Option<String> {
    use std::os::unix::fs::FileTypeExt;
    let path = i2c.device_path();
    let meta = std::fs::metadata(&path);
    match (&i2c.socket, meta) {
        (Some(_), Ok(meta)) if meta.file_type().is_socket() => None,
        (Some(_), Ok(_)) => Some(format!("[i2c] {} is not a Unix socket", path.display())),
        (Some(_), Err(e)) => Some(format!(
            "[i2c] socket {}: {e} (is `scan3d-sim rig` running? the edge waits for it)",
            path.display()
        )),
        (None, Ok(meta)) if meta.file_type().is_char_device() => None,
        (None, Ok(_)) => Some(format!(
            "[i2c] {} is not a character device",
            path.display()
        )),
        (None, Err(e)) => Some(format!(
            "[i2c] {}: {e} (enable I2C with `raspi-config nonint do_i2c 0`)",
            path.display()
        )),
    }
}

/// The common name of the first certificate in a PEM file: the name the server records the
/// edge under.
pub fn certificate_name(path: &std::path::Path) -> Result<String, String> {
    let certs = scan3d_service::link::read_certs(path).map_err(|e| e.to_string())?;
    let (_, cert) = x509_parser::parse_x509_certificate(&certs[0])
        .map_err(|e| format!("not a certificate: {e}"))?;
    let cn = cert
        .subject()
        .iter_common_name()
        .next()
        .ok_or("the certificate has no common name")?;
    cn.as_str()
        .map(str::to_owned)
        .map_err(|e| format!("common name: {e}"))
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

/// Most samples a calibration keeps (10 minutes at 1 kHz).
const MAX_CALIBRATION_SAMPLES: usize = 600_000;

/// `scan3d-edge calibrate gyro|mag`: reads the IMU through the configured bus, fits, prints
/// the `[imu]` keys (and writes them with `--write`).
fn run_calibrate(command: CalibrateCommand, out: &mut dyn Write) -> anyhow::Result<()> {
    use crate::calibrate::{self, LocalField, MagFitKind};
    let (common, seconds) = match &command {
        CalibrateCommand::Gyro {
            common, seconds, ..
        }
        | CalibrateCommand::Mag {
            common, seconds, ..
        } => (common, *seconds),
    };
    anyhow::ensure!(
        seconds.is_finite() && seconds > 0.0 && seconds <= 600.0,
        "--seconds must be within (0, 600], got {seconds}"
    );
    let config = EdgeConfig::load(&common.config)?;
    let Some(imu) = &config.imu else {
        anyhow::bail!(
            "{} has no [imu] section: nothing to calibrate",
            common.config.display()
        );
    };
    let duration = std::time::Duration::from_secs_f64(seconds);
    let progress = |s: u64| eprintln!("scan3d-edge calibrate: {s} s of {seconds} s");
    let collected = match &config.i2c.socket {
        Some(socket) => {
            let mut bus = crate::i2c_socket::SocketI2c::new(socket);
            bus.connect().map_err(|e| {
                anyhow::anyhow!(
                    "cannot open the I2C socket {}: {e} (is `scan3d-sim rig` running?)",
                    socket.display()
                )
            })?;
            calibrate::collect(
                bus,
                &mut ThreadDelay,
                &imu.driver,
                duration,
                MAX_CALIBRATION_SAMPLES,
                progress,
            )?
        }
        None => calibrate::collect(
            open_i2c(config.i2c.bus_number())?,
            &mut ThreadDelay,
            &imu.driver,
            duration,
            MAX_CALIBRATION_SAMPLES,
            progress,
        )?,
    };
    let (comments, keys): (Vec<String>, Vec<(&str, String)>) = match command {
        CalibrateCommand::Gyro {
            max_rate_std_dps, ..
        } => {
            let fit = calibrate::gyro_bias(
                &collected.rates,
                &collected.fields,
                max_rate_std_dps.to_radians(),
            )?;
            let dps = fit.bias_rad_s.map(f64::to_degrees);
            let std = fit.std_rad_s.map(f64::to_degrees);
            (
                vec![
                    format!(
                        "gyro bias at rest from {} samples over {seconds} s: ({:.3}, {:.3}, {:.3}) °/s, \
                         rate σ ({:.3}, {:.3}, {:.3}) °/s",
                        fit.samples, dps[0], dps[1], dps[2], std[0], std[1], std[2]
                    ),
                    "the driver uses it instead of estimating the bias at rest at every start \
                     (remove the key to go back to that)"
                        .to_owned(),
                ],
                vec![(GYRO_BIAS_KEY, calibrate::toml_array(&fit.bias_rad_s))],
            )
        }
        CalibrateCommand::Mag {
            field_ut,
            inclination_deg,
            ..
        } => {
            let local = LocalField {
                total_ut: field_ut,
                inclination_deg,
            };
            let fit = calibrate::fit_mag(&collected.fields, local)?;
            let configured_z = f64::from(imu.driver.mag_hard_iron_ut[2]);
            let settings = calibrate::MagSettings::from_fit(&fit, &collected.fields, configured_z);
            let mut comments = vec![match fit.kind {
                MagFitKind::Ellipsoid => format!(
                    "3D fit (ellipsoid) of {} fields covering {} of {} parts of the sphere; \
                     calibrated radius {:.1} µT, residual {:.2} %",
                    fit.samples,
                    fit.covered.0,
                    fit.covered.1,
                    fit.radius_ut,
                    fit.residual_rms * 100.0
                ),
                MagFitKind::HorizontalEllipse => format!(
                    "2D fit (horizontal ellipse: the head turned about its z only) of {} fields \
                     covering {}° of the circle; horizontal field {:.1} µT, residual {:.2} %; the \
                     z row of the soft iron is left at identity",
                    fit.samples,
                    fit.covered.0 * 10,
                    fit.radius_ut,
                    fit.residual_rms * 100.0
                ),
            }];
            let reference = settings.field_ut;
            comments.push(format!(
                "mag_field_ut: the calibrated field's magnitude ({reference:.1} µT), which the \
                 daemon warns about leaving by more than mag_field_tolerance"
            ));
            if fit.hard_iron_ut[2].is_none() {
                comments.push(format!(
                    "the z offset cannot be seen in a turn about z: kept at {configured_z} µT \
                     (pass --field-ut and --inclination-deg of the site to set it)"
                ));
            }
            (
                comments,
                vec![
                    (
                        "mag_hard_iron_ut",
                        calibrate::toml_array(&settings.hard_iron_ut),
                    ),
                    ("mag_soft_iron", calibrate::toml_matrix(&settings.soft_iron)),
                    ("mag_field_ut", format!("{reference:.3}")),
                ],
            )
        }
    };
    for line in &comments {
        writeln!(out, "# {line}")?;
    }
    writeln!(out, "[imu]")?;
    for (key, value) in &keys {
        writeln!(out, "{key} = {value}")?;
    }
    if let Some(path) = &common.write {
        write_imu_keys(path, &keys)?;
        let names: Vec<&str> = keys.iter().map(|(k, _)| *k).collect();
        writeln!(
            out,
            "# wrote {} to [imu] of {}",
            names.join(", "),
            path.display()
        )?;
    }
    Ok(())
}

/// The `[imu]` key of a saved gyro bias.
const GYRO_BIAS_KEY: &str = "gyro_bias_rad_s";

/// Sets `keys` in the `[imu]` table of the file at `path` (created if missing), checking that
/// the table still loads, and replaces the file in one rename.
fn write_imu_keys(path: &std::path::Path, keys: &[(&str, String)]) -> anyhow::Result<()> {
    use anyhow::Context;
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    };
    let edited = crate::calibrate::set_imu_keys(&text, keys)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let table: toml::Table = edited.parse().context("the edited file is not TOML")?;
    if let Some(toml::Value::Table(imu)) = table.get("imu") {
        crate::config::ImuSection::try_from(imu.clone())
            .map_err(|e| anyhow::anyhow!("{}: not written: {e}", path.display()))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".calibrate.tmp");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, edited).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot replace {}", path.display()))?;
    Ok(())
}

/// `scan3d-edge --config edge.toml`: runs the daemon until SIGTERM or SIGINT.
fn run_daemon(config_path: &std::path::Path) -> anyhow::Result<()> {
    let config = EdgeConfig::load(config_path)?;
    // One worker: the async side is the uplink (QUIC, acks, pongs) and a few control tasks,
    // all light; a second worker only added wake-ups handing tasks between the two threads.
    // Named for `top -H` and the edge_daemon benchmark's per-thread table.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("uplink")
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
        tracing::info!(config = %config_path.display(), device = %config.device_name, session = format!("{session_id:016x}"), version = env!("CARGO_PKG_VERSION"), "edge daemon starting");
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

    /// Runs `check-config`: what it printed, and its error (one line per problem).
    fn check_config(path: PathBuf) -> (String, Result<(), String>) {
        let cli = Cli::parse_from(
            ["scan3d-edge", "check-config", "--config"]
                .map(Into::into)
                .into_iter()
                .chain([path.into_os_string()]),
        );
        let mut out = Vec::new();
        let result = execute(cli, &mut out).map_err(|e| {
            let error: &(dyn std::error::Error + 'static) = e.as_ref();
            scan3d_service::report::error_chain(error)
        });
        (String::from_utf8(out).unwrap(), result)
    }

    const SECTIONS: [&str; 9] = [
        "device ",
        "state_dir ",
        "rplidar",
        "sweep",
        "uplink",
        "i2c ",
        "imu",
        "stepper",
        "static_scan ",
    ];

    #[test]
    fn check_config_prints_every_section_of_the_shipped_example_and_refuses_what_the_daemon_cannot_use()
     {
        let shipped = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/edge.toml"));
        let (printed, _) = check_config(shipped);
        assert!(printed.starts_with("device edge-pi-01\n"), "{printed}");
        let lines: Vec<&str> = printed.lines().collect();
        for (line, section) in lines.iter().zip(SECTIONS) {
            assert!(
                line.starts_with(section),
                "{line:?} is not {section:?}:\n{printed}"
            );
        }
        assert_eq!(lines.len(), SECTIONS.len(), "{printed}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("edge.toml");
        std::fs::write(&path, "device_name = \"t\"\n[stepper]\nsteps_per_rev = 0\n").unwrap();
        let message = check_config(path).1.unwrap_err();
        assert!(
            message.contains("line 3: `stepper.steps_per_rev` = 0"),
            "{message}"
        );
    }

    /// A bundle as `scan3d pair` writes it, for an edge named `name`.
    fn write_bundle(dir: &std::path::Path, name: &str) {
        use rcgen::{
            BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer,
            KeyPair,
        };
        use std::os::unix::fs::PermissionsExt;
        let ca_key = KeyPair::generate().unwrap();
        let mut ca_params = CertificateParams::default();
        ca_params.distinguished_name.push(DnType::CommonName, "ca");
        ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        let ca = ca_params.self_signed(&ca_key).unwrap();
        let issuer = Issuer::new(ca_params, ca_key);
        let key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(vec![name.to_owned()]).unwrap();
        params.distinguished_name.push(DnType::CommonName, name);
        params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
        let cert = params.signed_by(&key, &issuer).unwrap();
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("edge.pem"), cert.pem()).unwrap();
        std::fs::write(dir.join("ca.pem"), ca.pem()).unwrap();
        let key_path = dir.join("edge.key");
        std::fs::write(&key_path, key.serialize_pem()).unwrap();
        std::fs::set_permissions(&key_path, std::fs::Permissions::from_mode(0o600)).unwrap();
    }

    /// An edge.toml in `dir` for the devices given, the bundle in `dir/pki`.
    fn write_config(
        dir: &std::path::Path,
        name: &str,
        rplidar: &str,
        sweep: &str,
        i2c: &str,
    ) -> PathBuf {
        let path = dir.join("edge.toml");
        let text = format!(
            "device_name = \"{name}\"\nstate_dir = \"{state}\"\n\
             [rplidar]\npath = \"{rplidar}\"\n[rplidar.mount]\nz = 0.4\n\
             [sweep]\npath = \"{sweep}\"\n[sweep.mount]\nz = 1.0\npitch = -90.0\n\
             [i2c]\n{i2c}\n[imu]\n[imu.mount]\nz = 0.2\n[stepper]\n\
             [uplink]\nserver = \"localhost:4433\"\npki_dir = \"{pki}\"\n",
            state = dir.join("state").display(),
            pki = dir.join("pki").display(),
        );
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn check_config_accepts_present_devices_and_a_matching_bundle() {
        let dir = tempfile::tempdir().unwrap();
        write_bundle(&dir.path().join("pki"), "pi-01");
        let socket = dir.path().join("i2c.sock");
        let _listener = std::os::unix::net::UnixListener::bind(&socket).unwrap();
        let i2c = format!("socket = \"{}\"", socket.display());
        let path = write_config(dir.path(), "pi-01", "/dev/null", "/dev/null", &i2c);
        let (printed, result) = check_config(path);
        assert_eq!(result, Ok(()), "{printed}");
        for section in SECTIONS {
            assert!(
                printed.lines().any(|l| l.starts_with(section)),
                "{section} missing:\n{printed}"
            );
        }
        assert!(printed.contains("emulated bus socket"), "{printed}");
        assert!(
            printed.contains("mount x 0 y 0 z 1 m, roll 0 pitch -90 yaw 0 deg"),
            "{printed}"
        );
    }

    #[test]
    fn check_config_reports_every_problem_on_its_own_line() {
        let dir = tempfile::tempdir().unwrap();
        write_bundle(&dir.path().join("pki"), "pi-01");
        let file = dir.path().join("ttyFILE");
        std::fs::write(&file, "").unwrap();
        let gone = dir.path().join("ttyGONE");
        let socket = dir.path().join("i2c.sock");
        let i2c = format!("socket = \"{}\"", socket.display());
        let path = write_config(
            dir.path(),
            "pi-02",
            &gone.display().to_string(),
            &file.display().to_string(),
            &i2c,
        );
        let (_, result) = check_config(path.clone());
        let message = result.unwrap_err();
        let lines: Vec<&str> = message.lines().collect();
        assert_eq!(lines.len(), 4, "{message}");
        for line in &lines {
            assert!(line.starts_with(&format!("{}: ", path.display())), "{line}");
        }
        assert!(
            lines[0].contains("[rplidar]") && lines[0].contains("does not exist"),
            "{message}"
        );
        assert!(
            lines[1].contains("is not a serial device (a regular file)"),
            "{message}"
        );
        assert!(
            lines[2].contains("[i2c] socket") && lines[2].contains("i2c.sock"),
            "{message}"
        );
        assert!(
            lines[3].contains("\"pi-02\" differs")
                && lines[3].contains("records this edge under \"pi-01\""),
            "{message}"
        );
        assert!(!message.contains("typewriter"), "{message}");

        // A missing bundle: its file named, its cause once.
        std::fs::remove_dir_all(dir.path().join("pki")).unwrap();
        let message = check_config(path).1.unwrap_err();
        let pki = message
            .lines()
            .find(|l| l.contains("[uplink]"))
            .expect(&message);
        assert!(pki.contains("ca.pem"), "{pki}");
        assert_eq!(pki.matches("No such file").count(), 1, "{pki}");
    }

    #[test]
    fn check_config_refuses_a_bus_and_a_socket_together_at_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = write_config(
            dir.path(),
            "pi-01",
            "/dev/null",
            "/dev/null",
            "bus = 1\nsocket = \"/x\"",
        );
        let message = check_config(path).1.unwrap_err();
        assert!(message.contains("line 14: `i2c.socket`"), "{message}");
        assert!(message.contains("not both"), "{message}");
    }
}
