//! `scan3d-edge calibrate gyro|mag` against the emulated IMU with known errors, through the
//! edge's own command line, configuration and `SocketI2c` (the path the daemon uses on the
//! rig), the emulator's clock running 5× faster than the wall clock. (The command reads in
//! real time, so how many samples it gets depends on the machine's load: the tests run one at a
//! time and read for a few seconds, enough for a loaded machine's few samples.)
//!
//! The fitted iron and bias must match what the emulator adds ([`ErroneousImu`]), and a
//! magnetometer read with the written calibration must give a field of constant magnitude.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use clap::Parser;
use nalgebra::{Isometry3, Matrix2, Matrix3, UnitQuaternion, Vector3};
use scan3d_edge::calibrate::collect;
use scan3d_edge::cli::{Cli, execute};
use scan3d_edge::clock::{Clock, ScaledClock};
use scan3d_edge::config::EdgeConfig;
use scan3d_edge::i2c_probe::ThreadDelay;
use scan3d_edge::i2c_socket::SocketI2c;
use scan3d_hw_sim::i2c::I2cBus;
use scan3d_hw_sim::i2c_socket::I2cSocketServer;
use scan3d_hw_sim::imu::errors::{ErroneousImu, ImuErrors};
use scan3d_hw_sim::imu::{EarthField, ImuEmulator, MountedImuTruth};
use scan3d_hw_sim::trolley::{BaseMotion, BaseTrajectory};

/// Emulated seconds per wall-clock second.
const TIME_SCALE: f64 = 5.0;

/// One test at a time: they read in real time through sockets, and compete for the cores.
static SERIAL: Mutex<()> = Mutex::new(());

fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// A head turning through every orientation (a tumble about z, y, x at different rates), or
/// about its vertical only.
#[derive(Debug)]
struct Turning {
    rates_rad_s: [f64; 3],
}

impl BaseTrajectory for Turning {
    fn motion_at(&self, t_ns: u64) -> BaseMotion {
        let t = t_ns as f64 * 1e-9;
        let [z, y, x] = self.rates_rad_s.map(|r| r * t);
        BaseMotion {
            pose: Isometry3::from_parts(
                Default::default(),
                UnitQuaternion::from_euler_angles(x, y, z),
            ),
            angular_velocity_rad_s: Vector3::zeros(),
            angular_accel_rad_s2: Vector3::zeros(),
            accel_m_s2: Vector3::zeros(),
        }
    }
}

struct Fixture {
    _dir: tempfile::TempDir,
    config: PathBuf,
    clock: ScaledClock,
    imu: Arc<ErroneousImu>,
    server: Option<I2cSocketServer>,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        if let Some(server) = self.server.take() {
            server.shutdown();
        }
    }
}

/// The emulated IMU on `base` with the default trolley errors (no disturbance), served on a
/// socket, and an edge.toml pointing at it.
fn fixture(base: Arc<dyn BaseTrajectory>) -> Fixture {
    let dir = tempfile::tempdir().expect("temp dir");
    let clock = ScaledClock::new(TIME_SCALE);
    let truth = MountedImuTruth {
        base,
        mount: Isometry3::identity(),
        field: EarthField::default(),
        north_heading_rad: 0.0,
    };
    let imu = Arc::new(ErroneousImu::new(truth, ImuErrors::default()));
    let bus = I2cBus::with_clock(Arc::new(clock));
    bus.attach(Arc::new(Mutex::new(ImuEmulator::new(
        Default::default(),
        imu.clone(),
    ))));
    let socket = dir.path().join("i2c.sock");
    let server = I2cSocketServer::start(&socket, bus).expect("socket server");
    let config = dir.path().join("edge.toml");
    std::fs::write(
        &config,
        format!(
            "device_name = \"cal\"  # kept\n\n[i2c]\nsocket = {:?}\n\n[imu]\nbeta = 0.05\n\n\
             [imu.mount]\nz = 0.1\n",
            socket.display().to_string()
        ),
    )
    .unwrap();
    Fixture {
        _dir: dir,
        config,
        clock,
        imu,
        server: Some(server),
    }
}

/// Runs `scan3d-edge calibrate ARGS --config CONFIG`: its stdout, or its error line.
fn calibrate(config: &Path, args: &[&str]) -> Result<String, String> {
    let mut argv = vec!["scan3d-edge", "calibrate"];
    argv.extend(args);
    let config = config.display().to_string();
    argv.extend(["--config", &config]);
    let cli = Cli::try_parse_from(argv).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    execute(cli, &mut out).map_err(|e| {
        let error: &(dyn std::error::Error + 'static) = e.as_ref();
        scan3d_service::report::error_chain(error)
    })?;
    Ok(String::from_utf8(out).unwrap())
}

fn floats(value: &toml::Value) -> Vec<f64> {
    value
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_float().unwrap())
        .collect()
}

/// Field magnitudes read with the calibration now in `config`, through the driver.
fn calibrated_fields(config: &Path) -> Vec<Vector3<f64>> {
    let edge = EdgeConfig::load(config).expect("the written edge.toml loads");
    let imu = edge.imu.expect("[imu]");
    let socket = edge.i2c.socket.expect("socket");
    let mut driver = scan3d_edge::drivers::imu::Mpu9250::new(
        SocketI2c::new(socket).with_timeout(Duration::from_secs(10)),
        scan3d_edge::drivers::imu::ImuConfig {
            gyro_bias_samples: 0,
            ..imu.driver
        },
    );
    driver.init(&mut ThreadDelay).expect("init");
    let mut fields = Vec::new();
    for _ in 0..400 {
        if let Some(m) = driver.read().expect("read").mag_ut {
            fields.push(Vector3::from(m.map(f64::from)));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    fields
}

#[test]
fn a_tumble_gives_the_emulator_s_hard_and_soft_iron_and_a_constant_field() {
    let _serial = one_at_a_time();
    let f = fixture(Arc::new(Turning {
        rates_rad_s: [0.7, 0.31, 0.13].map(|r| r * 20.0 / TIME_SCALE),
    }));
    let printed = calibrate(
        &f.config,
        &[
            "mag",
            "--seconds",
            "5",
            "--field-ut",
            "48",
            "--write",
            &f.config.display().to_string(),
        ],
    )
    .expect("calibrate mag");
    eprintln!("{printed}");
    assert!(printed.contains("# 3D fit (ellipsoid)"), "{printed}");
    let table: toml::Table = printed.parse().expect("the output is TOML");
    let hard = Vector3::from_vec(floats(&table["imu"]["mag_hard_iron_ut"]));
    let rows: Vec<Vec<f64>> = table["imu"]["mag_soft_iron"]
        .as_array()
        .unwrap()
        .iter()
        .map(floats)
        .collect();
    let soft = Matrix3::from_fn(|r, c| rows[r][c]);
    let (true_hard, true_soft) = f.imu.expected_calibration().unwrap();
    let (true_hard, true_soft) = (
        Vector3::from(true_hard),
        Matrix3::from_fn(|r, c| true_soft[r][c]),
    );
    let hard_error = (hard - true_hard).norm();
    let soft_error = (soft - true_soft).abs().max();
    eprintln!(
        "3D through the emulator: hard iron {hard:.3?} µT vs true {true_hard:.3?} (|error| \
         {hard_error:.3} µT); soft iron max |error| {soft_error:.4}"
    );
    assert!(hard_error < 1.0, "hard iron {hard} vs {true_hard}");
    // The reference the daemon checks the field against.
    let reference = table["imu"]["mag_field_ut"].as_float().unwrap();
    assert!((reference - 48.0).abs() < 0.5, "mag_field_ut {reference}");
    assert!(soft_error < 0.02, "soft iron {soft} vs {true_soft}");

    // The file was edited in place: the rest kept, the keys now in [imu].
    let written = std::fs::read_to_string(&f.config).unwrap();
    assert!(
        written.starts_with("device_name = \"cal\"  # kept\n"),
        "{written}"
    );
    assert!(
        written.contains("beta = 0.05\nmag_hard_iron_ut = ["),
        "{written}"
    );
    // Read with it, the field's magnitude stays at 48 µT within a few %.
    let fields = calibrated_fields(&f.config);
    assert!(fields.len() > 100, "{} fields", fields.len());
    let off: Vec<f64> = fields.iter().map(|m| m.norm() / 48.0 - 1.0).collect();
    let worst = off.iter().fold(0.0f64, |w, o| w.max(o.abs()));
    let rms = (off.iter().map(|o| o * o).sum::<f64>() / off.len() as f64).sqrt();
    eprintln!(
        "calibrated magnitude: RMS {:.2} %, worst {:.2} % off 48 µT over {} fields",
        rms * 100.0,
        worst * 100.0,
        fields.len()
    );
    assert!(rms < 0.01 && worst < 0.03, "RMS {rms}, worst {worst}");
    // Uncalibrated it is not: the iron makes it vary by more.
    let raw_worst = fields
        .iter()
        .map(|m| {
            let raw = f.imu.apply_iron(*m);
            (raw.norm() / 48.0 - 1.0).abs()
        })
        .fold(0.0, f64::max);
    assert!(raw_worst > 0.1, "raw worst {raw_worst}");
}

#[test]
fn a_trolley_s_turn_about_z_gives_a_2d_calibration_and_a_short_turn_is_refused() {
    let _serial = one_at_a_time();
    let f = fixture(Arc::new(Turning {
        rates_rad_s: [1.0, 0.0, 0.0],
    }));
    // 3 s here is 15 s emulated, 15 rad: more than two turns.
    let printed = calibrate(
        &f.config,
        &[
            "mag",
            "--seconds",
            "3",
            "--field-ut",
            "48",
            "--inclination-deg",
            "60",
            "--write",
            &f.config.display().to_string(),
        ],
    )
    .expect("calibrate mag");
    eprintln!("{printed}");
    assert!(
        printed.contains("# 2D fit (horizontal ellipse"),
        "{printed}"
    );
    let table: toml::Table = printed.parse().unwrap();
    let hard = floats(&table["imu"]["mag_hard_iron_ut"]);
    let rows: Vec<Vec<f64>> = table["imu"]["mag_soft_iron"]
        .as_array()
        .unwrap()
        .iter()
        .map(floats)
        .collect();
    // In 2D: b_xy absorbs A's xz, yz terms times the vertical field, S_xy = (A_xy)⁻¹.
    let a = Matrix3::from_fn(|r, c| f.imu.errors().soft_iron[r][c]);
    let b = f.imu.errors().hard_iron_ut;
    let vertical = EarthField::default().in_level_body(0.0)[2];
    let want_b = [b[0] + a[(0, 2)] * vertical, b[1] + a[(1, 2)] * vertical];
    let want_s = Matrix2::new(a[(0, 0)], a[(0, 1)], a[(1, 0)], a[(1, 1)])
        .try_inverse()
        .unwrap();
    let soft = Matrix2::new(rows[0][0], rows[0][1], rows[1][0], rows[1][1]);
    eprintln!(
        "2D through the emulator: hard iron {hard:.3?} µT vs expected [{:.3}, {:.3}, {:.3}]; \
         soft iron xy max |error| {:.4}",
        want_b[0],
        want_b[1],
        b[2],
        (soft - want_s).abs().max()
    );
    assert!((hard[0] - want_b[0]).abs() < 0.7 && (hard[1] - want_b[1]).abs() < 0.7);
    assert!((hard[2] - b[2]).abs() < 1.5, "b_z {} vs {}", hard[2], b[2]);
    assert!((soft - want_s).abs().max() < 0.02, "{soft} vs {want_s}");
    assert_eq!(rows[2], vec![0.0, 0.0, 1.0]);
    // Read with it: the horizontal field stays at 24 µT within a few %.
    let fields = calibrated_fields(&f.config);
    // (One reading's noise, 0.3 µT σ per axis, is 1.25 % of 24 µT: the worst of 200 is
    // about 3 σ of it.)
    let off: Vec<f64> = fields.iter().map(|m| m.xy().norm() / 24.0 - 1.0).collect();
    let worst = off.iter().fold(0.0f64, |w, o| w.max(o.abs()));
    let rms = (off.iter().map(|o| o * o).sum::<f64>() / off.len() as f64).sqrt();
    eprintln!(
        "calibrated horizontal magnitude: RMS {:.2} %, worst {:.2} % off 24 µT over {} fields",
        rms * 100.0,
        worst * 100.0,
        fields.len()
    );
    assert!(rms < 0.02 && worst < 0.05, "RMS {rms}, worst {worst}");

    // An eighth of a turn (0.08 rad/s for 10 s emulated) is refused, with one line saying how
    // much was covered.
    let slow = fixture(Arc::new(Turning {
        rates_rad_s: [0.08, 0.0, 0.0],
    }));
    let short = calibrate(&slow.config, &["mag", "--seconds", "2"]).unwrap_err();
    assert!(
        short.contains("of the circle (need 300°)") && !short.contains('\n'),
        "{short}"
    );
}

#[test]
fn the_gyro_bias_at_rest_is_the_emulator_s_and_a_turning_head_is_refused() {
    let _serial = one_at_a_time();
    let f = fixture(Arc::new(Isometry3::<f64>::identity()));
    let before = f.clock.now_ns();
    let config = f.config.display().to_string();
    let printed = calibrate(&f.config, &["gyro", "--seconds", "3", "--write", &config])
        .expect("calibrate gyro");
    let after = f.clock.now_ns();
    eprintln!("{printed}");
    let table: toml::Table = printed.parse().unwrap();
    let bias = Vector3::from_vec(floats(&table["imu"]["gyro_bias_rad_s"]));
    let truth = f.imu.gyro_bias_at((before + after) / 2);
    let error_dps = (bias - truth).abs().max().to_degrees();
    eprintln!(
        "gyro bias: fitted {:.4?} °/s vs true {:.4?} °/s (max |error| {error_dps:.4} °/s)",
        bias.map(f64::to_degrees),
        truth.map(f64::to_degrees),
    );
    assert!(error_dps < 0.03, "{bias} vs {truth}");
    // Written, the driver takes it instead of estimating one at start.
    let edge = EdgeConfig::load(&f.config).expect("the written edge.toml loads");
    let saved = edge.imu.expect("[imu]").driver;
    assert_eq!(saved.gyro_bias_rad_s, Some(bias.map(|b| b as f32).into()));
    let mut driver = scan3d_edge::drivers::imu::Mpu9250::new(
        SocketI2c::new(edge.i2c.socket.unwrap()).with_timeout(Duration::from_secs(10)),
        saved.clone(),
    );
    driver.init(&mut ThreadDelay).expect("init");
    assert_eq!(driver.gyro_bias(), saved.gyro_bias_rad_s.unwrap());

    let turning = fixture(Arc::new(Turning {
        rates_rad_s: [0.4, 0.0, 0.0],
    }));
    let refused = calibrate(&turning.config, &["gyro", "--seconds", "2"]).unwrap_err();
    assert!(
        refused.contains("the head turned during the gyro calibration") && !refused.contains('\n'),
        "{refused}"
    );
}

#[test]
fn collect_reads_raw_fields_whatever_the_configured_iron() {
    // The calibration reads through raw_config: a configured iron must not bend the fit.
    let _serial = one_at_a_time();
    let f = fixture(Arc::new(Isometry3::<f64>::identity()));
    let config = scan3d_edge::drivers::imu::ImuConfig {
        mag_hard_iron_ut: [100.0, 100.0, 100.0],
        ..Default::default()
    };
    let socket = EdgeConfig::load(&f.config).unwrap().i2c.socket.unwrap();
    let got = collect(
        SocketI2c::new(socket),
        &mut ThreadDelay,
        &config,
        Duration::from_millis(300),
        1000,
        |_| {},
    )
    .unwrap();
    assert!(!got.fields.is_empty());
    let want = f
        .imu
        .apply_iron(Vector3::from(EarthField::default().in_level_body(0.0)));
    for m in &got.fields {
        assert!((Vector3::from(*m) - want).norm() < 2.0, "{m:?} vs {want}");
    }
}
