//! `scan3d-edge probe imu` / `probe stepper` cores against the register-level emulators on the
//! simulated I2C bus (the same code runs on the Pi's bus through rppal).

use std::sync::{Arc, Mutex};

use scan3d_edge::drivers::imu::ImuConfig;
use scan3d_edge::drivers::stepper::{Port, StepperConfig};
use scan3d_edge::i2c_probe::{I2cProbeLine, probe_imu, probe_stepper};
use scan3d_hw_sim::i2c::{I2cBus, SimClock};
use scan3d_hw_sim::imu::{ImuEmulator, StaticTruth};
use scan3d_hw_sim::stepper::Pca9685Emulator;

#[test]
fn the_imu_probe_reports_ids_samples_and_a_level_orientation() {
    let clock = SimClock::new();
    let bus = I2cBus::with_clock(clock.shared());
    // Still and level, heading 30° from magnetic north (counter-clockwise).
    let truth = StaticTruth {
        heading_rad: 30f64.to_radians(),
        ..Default::default()
    };
    bus.attach(Arc::new(Mutex::new(ImuEmulator::new(
        Default::default(),
        Arc::new(truth),
    ))));
    let mut lines = Vec::new();
    probe_imu(bus, &mut clock.clone(), ImuConfig::default(), 200, 5, |l| {
        lines.push(l.clone())
    })
    .expect("probe");
    assert!(matches!(
        &lines[0],
        I2cProbeLine::ImuInfo { who_am_i, ak8963_wia: Some(wia), .. } if who_am_i == "0x71" && wia == "0x48"
    ));
    let samples = lines
        .iter()
        .filter(|l| matches!(l, I2cProbeLine::Imu { .. }))
        .count();
    assert_eq!(samples, 200);
    match lines.last() {
        Some(I2cProbeLine::Orientation {
            roll_deg,
            pitch_deg,
            yaw_deg,
            ..
        }) => {
            assert!(
                roll_deg.abs() < 2.0 && pitch_deg.abs() < 2.0,
                "{roll_deg} {pitch_deg}"
            );
            assert!((yaw_deg - 30.0).abs() < 3.0, "yaw {yaw_deg}");
        }
        other => panic!("expected an orientation last, got {other:?}"),
    }
}

#[test]
fn the_stepper_probe_moves_and_comes_back() {
    let clock = SimClock::new();
    let bus = I2cBus::with_clock(clock.shared());
    let hat = Arc::new(Mutex::new(Pca9685Emulator::motor_hat()));
    let table = hat.lock().expect("lock").turntable(Port::One);
    bus.attach(hat.clone());
    let mut lines = Vec::new();
    let config = StepperConfig::default();
    probe_stepper(bus, &mut clock.clone(), &config, 50, |l| {
        lines.push(l.clone())
    })
    .expect("probe");
    assert_eq!(lines.len(), 2);
    assert!(
        matches!(&lines[0], I2cProbeLine::Stepper { steps: 50, angle_deg, .. } if (angle_deg - 90.0).abs() < 1e-9)
    );
    assert!(
        matches!(&lines[1], I2cProbeLine::Stepper { steps: -50, angle_deg, .. } if angle_deg.abs() < 1e-9)
    );
    // The emulated rotor really went there and back (no step lost at the default rate).
    let history = table.history();
    let max = history.iter().map(|(_, a)| *a).fold(f64::MIN, f64::max);
    assert!((max - 90.0).abs() < 1e-6, "rotor reached {max}°");
    assert!(table.angle_deg().abs() < 1e-9);
}
