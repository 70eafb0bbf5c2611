//! Driver tests against a scripted bus. Expected bytes are written out by hand from
//! research/hardware.md §2 (register map, channel map, coil tables).

use std::collections::HashMap;

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::{ErrorKind, ErrorType, I2c, NoAcknowledgeSource, Operation};

use super::*;

/// Records every transaction; answers reads from `answers` (keyed by the register pointer just
/// written); fails the first `fail` transactions with an address NACK.
#[derive(Default)]
struct ScriptedBus {
    writes: Vec<(u8, Vec<u8>)>,
    reads: Vec<(u8, u8)>,
    answers: HashMap<u8, u8>,
    fail: usize,
}

impl ErrorType for ScriptedBus {
    type Error = ErrorKind;
}

impl I2c for ScriptedBus {
    fn transaction(&mut self, address: u8, ops: &mut [Operation<'_>]) -> Result<(), ErrorKind> {
        if self.fail > 0 {
            self.fail -= 1;
            return Err(ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address));
        }
        let mut pointer = 0;
        for op in ops {
            match op {
                Operation::Write(bytes) => {
                    pointer = bytes.first().copied().unwrap_or(0);
                    if bytes.len() > 1 {
                        self.writes.push((address, bytes.to_vec()));
                    }
                }
                Operation::Read(buf) => {
                    self.reads.push((address, pointer));
                    buf.fill(self.answers.get(&pointer).copied().unwrap_or(0));
                }
            }
        }
        Ok(())
    }
}

/// Counts the delay asked for instead of sleeping.
#[derive(Default)]
struct CountingDelay {
    total_ns: u64,
}

impl DelayNs for CountingDelay {
    fn delay_ns(&mut self, ns: u32) {
        self.total_ns += u64::from(ns);
    }
}

fn initialised_bus() -> ScriptedBus {
    ScriptedBus {
        answers: HashMap::from([(0x00, 0x21), (0xFE, 0x03)]),
        ..ScriptedBus::default()
    }
}

fn hat() -> MotorHat<ScriptedBus> {
    MotorHat::new(initialised_bus(), 0x60, 2)
}

fn stepper(style: StepStyle) -> Stepper {
    Stepper::new(&StepperConfig {
        style,
        ..StepperConfig::default()
    })
    .unwrap()
}

const ON: [u8; 4] = [0x00, 0x10, 0x00, 0x00];
const OFF: [u8; 4] = [0x00, 0x00, 0x00, 0x10];

/// The 25-byte burst for port 1 (channels 8–13 from LED8_ON_L = 0x26) with the six channel
/// values PWMA, AIN2, AIN1, BIN1, BIN2, PWMB.
fn port1_burst(channels: [[u8; 4]; 6]) -> Vec<u8> {
    let mut bytes = vec![0x26];
    for c in channels {
        bytes.extend_from_slice(&c);
    }
    bytes
}

/// Digital coil states (c0 c1 c2 c3) = (AIN2, BIN1, AIN1, BIN2) from the last burst.
fn coils(bus: &ScriptedBus) -> [u8; 4] {
    let (_, last) = bus.writes.last().unwrap();
    let channel = |i: usize| -> u8 {
        match &last[1 + 4 * i..5 + 4 * i] {
            b if b == ON => 1,
            b if b == OFF => 0,
            other => panic!("channel {i} is not digital: {other:02x?}"),
        }
    };
    // Burst order: PWMA(0) AIN2(1) AIN1(2) BIN1(3) BIN2(4) PWMB(5).
    [channel(1), channel(3), channel(2), channel(4)]
}

#[test]
fn init_writes_the_documented_sequence_with_prescale_3() {
    let mut hat = hat();
    let mut delay = CountingDelay::default();
    hat.init(&mut delay).unwrap();
    let bus = hat.destroy();
    let expected: Vec<(u8, Vec<u8>)> = vec![
        (0x60, vec![0x00, 0x31]),                   // MODE1: SLEEP | AI | ALLCALL
        (0x60, vec![0x01, 0x04]),                   // MODE2: OUTDRV
        (0x60, vec![0xFA, 0x00, 0x00, 0x00, 0x10]), // ALL_LED full off
        (0x60, vec![0xFE, 0x03]),                   // PRE_SCALE 3 (1600 Hz asked)
        (0x60, vec![0x00, 0x21]),                   // wake: AI | ALLCALL
        (0x60, vec![0x00, 0xA1]),                   // RESTART
    ];
    assert_eq!(bus.writes, expected);
    assert_eq!(bus.reads, vec![(0x60, 0x00), (0x60, 0xFE)]);
    assert_eq!(delay.total_ns, 500_000);
}

#[test]
fn prescale_follows_the_datasheet_formula_and_range() {
    assert_eq!(prescale_for(1600.0), Some(3));
    assert_eq!(prescale_for(200.0), Some(0x1E)); // the reset value
    assert_eq!(prescale_for(50.0), Some(121));
    assert_eq!(prescale_for(2000.0), None); // would need 2
    assert_eq!(prescale_for(20.0), None); // would need 304
    assert_eq!(prescale_for(0.0), None);
    assert_eq!(prescale_for(f64::NAN), None);
}

#[test]
fn init_reports_a_wrong_readback() {
    let mut bus = initialised_bus();
    bus.answers.insert(0x00, 0x11); // still asleep: not a working PCA9685
    let mut hat = MotorHat::new(bus, 0x60, 0);
    let err = hat.init(&mut CountingDelay::default()).unwrap_err();
    assert!(matches!(
        err,
        Error::Verify {
            address: 0x60,
            register: 0x00,
            expected: 0x21,
            found: 0x11
        }
    ));
}

#[test]
fn bus_errors_are_retried_then_named() {
    let mut bus = initialised_bus();
    bus.fail = 2;
    let mut hat = MotorHat::new(bus, 0x60, 2);
    hat.init(&mut CountingDelay::default()).unwrap();
    assert_eq!(hat.transactions(), 8 + 2);

    let bus = ScriptedBus {
        fail: usize::MAX,
        ..ScriptedBus::default()
    };
    let mut hat = MotorHat::new(bus, 0x61, 2);
    let err = hat.init(&mut CountingDelay::default()).unwrap_err();
    assert!(matches!(
        err,
        Error::I2c {
            address: 0x61,
            attempts: 3,
            ..
        }
    ));
    let text = err.to_string();
    assert!(text.contains("PCA9685") && text.contains("0x61"), "{text}");
}

#[test]
fn full_steps_walk_the_double_coil_phases() {
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Full);
    motor.step(&mut hat, Direction::Forward).unwrap();
    // Phase 3 of the legacy table: BIN1 + AIN1.
    assert_eq!(
        hat.destroy().writes,
        vec![(0x60, port1_burst([ON, OFF, ON, ON, OFF, ON]))]
    );

    // Legacy DOUBLE, forward from phase 1 (1100): 0110, 0011, 1001, 1100.
    let mut hat = MotorHat::new(initialised_bus(), 0x60, 0);
    let mut motor = stepper(StepStyle::Full);
    let mut seen = Vec::new();
    for _ in 0..4 {
        motor.step(&mut hat, Direction::Forward).unwrap();
        seen.push(coils(hat_bus(&hat)));
    }
    assert_eq!(
        seen,
        [[0, 1, 1, 0], [0, 0, 1, 1], [1, 0, 0, 1], [1, 1, 0, 0]]
    );
    assert_eq!(motor.position(), 4);
    motor.step(&mut hat, Direction::Backward).unwrap();
    assert_eq!(coils(hat_bus(&hat)), [1, 0, 0, 1]);
    assert_eq!(motor.position(), 3);
}

/// Borrow the scripted bus inside a hat (tests only).
fn hat_bus(hat: &MotorHat<ScriptedBus>) -> &ScriptedBus {
    hat.bus()
}

#[test]
fn half_steps_walk_all_eight_phases() {
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Half);
    let mut seen = Vec::new();
    for _ in 0..8 {
        motor.step(&mut hat, Direction::Forward).unwrap();
        seen.push(coils(hat_bus(&hat)));
    }
    // Legacy phases 2, 3, 4, 5, 6, 7, 0, 1.
    assert_eq!(
        seen,
        [
            [0, 1, 0, 0],
            [0, 1, 1, 0],
            [0, 0, 1, 0],
            [0, 0, 1, 1],
            [0, 0, 0, 1],
            [1, 0, 0, 1],
            [1, 0, 0, 0],
            [1, 1, 0, 0],
        ]
    );
    // Single-coil phases keep PWMA and PWMB on (phase 0: AIN2 only).
    let (_, last) = &hat_bus(&hat).writes[6];
    assert_eq!(last, &port1_burst([ON, ON, OFF, OFF, OFF, ON]));
}

#[test]
fn microsteps_put_the_sine_table_on_pwma_and_pwmb() {
    // round(4096 sin(iπ/16)), i = 0..8; 0 → full off, 4096 → full on.
    let table: [u16; 9] = [0, 799, 1567, 2276, 2896, 3406, 3784, 4017, 4096];
    let pwm = |c: u16| -> [u8; 4] {
        match c {
            0 => OFF,
            4096 => ON,
            c => [0x00, 0x00, (c & 0xFF) as u8, (c >> 8) as u8],
        }
    };
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Micro(8));
    motor.hold(&mut hat).unwrap();
    for k in 0..=4usize {
        if k > 0 {
            motor.step(&mut hat, Direction::Forward).unwrap();
        }
        // From both coils at 45° (AIN2 + BIN1) to BIN1 alone: A fades, B grows.
        let a = table[4 - k];
        let b = table[4 + k];
        let ain2 = if a == 0 { OFF } else { ON };
        let expected = port1_burst([pwm(a), ain2, OFF, ON, OFF, pwm(b)]);
        let (_, last) = hat_bus(&hat).writes.last().unwrap();
        assert_eq!(last, &expected, "microstep {k}");
    }
    // One more: into the AIN1 quadrant.
    motor.step(&mut hat, Direction::Forward).unwrap();
    let (_, last) = hat_bus(&hat).writes.last().unwrap();
    assert_eq!(last, &port1_burst([pwm(799), OFF, ON, ON, OFF, pwm(4017)]));
}

#[test]
fn port_two_uses_channels_2_to_7() {
    let mut hat = hat();
    let mut motor = Stepper::new(&StepperConfig {
        port: Port::Two,
        ..StepperConfig::default()
    })
    .unwrap();
    motor.hold(&mut hat).unwrap();
    let mut expected = vec![0x0E]; // LED2_ON_L
    for c in [ON, ON, OFF, ON, OFF, ON] {
        expected.extend_from_slice(&c);
    }
    assert_eq!(hat.destroy().writes, vec![(0x60, expected)]);
}

#[test]
fn hold_and_release() {
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Full);
    motor.step(&mut hat, Direction::Forward).unwrap();
    motor.release(&mut hat).unwrap();
    assert!(!motor.is_energised());
    motor.hold(&mut hat).unwrap();
    assert!(motor.is_energised());
    assert_eq!(motor.position(), 1);
    let writes = hat.destroy().writes;
    assert_eq!(writes[1].1, port1_burst([OFF; 6]));
    assert_eq!(writes[2].1, writes[0].1);
}

#[test]
fn commanded_angle_follows_steps_per_rev_and_gear_ratio() {
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Full);
    assert_eq!(motor.step_angle_deg(), 1.8);
    for _ in 0..5 {
        motor.step(&mut hat, Direction::Forward).unwrap();
    }
    assert!((motor.commanded_angle_deg() - 9.0).abs() < 1e-12);

    let geared = Stepper::new(&StepperConfig {
        style: StepStyle::Half,
        gear_ratio: 3.0,
        ..StepperConfig::default()
    })
    .unwrap();
    assert!((geared.step_angle_deg() - 0.3).abs() < 1e-12);
    assert_eq!(geared.steps_per_output_rev(), 1200.0);
    // 100 full steps/s in half steps: 5 ms per half step.
    assert_eq!(geared.step_period_ns(), 5_000_000);
}

#[test]
fn the_wrap_limit_stops_steps_without_writing() {
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Full);
    let mut delay = CountingDelay::default();
    motor
        .run(
            &mut hat,
            Move {
                direction: Direction::Forward,
                steps: 100,
            },
            &mut delay,
        )
        .unwrap();
    assert!((motor.commanded_angle_deg() - 180.0).abs() < 1e-9);
    let writes_before = hat_bus(&hat).writes.len();
    let err = motor.step(&mut hat, Direction::Forward).unwrap_err();
    assert!(matches!(err, Error::WrapLimit { limit_deg, .. } if limit_deg == 180.0));
    assert_eq!(hat_bus(&hat).writes.len(), writes_before);
    assert_eq!(motor.position(), 100);
}

#[test]
fn return_home_goes_back_the_way_it_came() {
    let mut hat = hat();
    let mut motor = stepper(StepStyle::Full);
    let mut delay = CountingDelay::default();
    let forward = Move {
        direction: Direction::Forward,
        steps: 100,
    };
    motor.run(&mut hat, forward, &mut delay).unwrap();
    // At +180°: the only way that never passes ±180° is backward.
    let mv = motor.home_move();
    assert_eq!(
        mv,
        Move {
            direction: Direction::Backward,
            steps: 100
        }
    );
    let mut delay = CountingDelay::default();
    assert_eq!(motor.return_home(&mut hat, &mut delay).unwrap(), mv);
    assert_eq!(motor.position(), 0);
    assert_eq!(delay.total_ns, 100 * 10_000_000); // 100 full steps/s
    // Back at home the coils show index 0 again: AIN2 + BIN1.
    assert_eq!(coils(hat_bus(&hat)), [1, 1, 0, 0]);

    for _ in 0..37 {
        motor.step(&mut hat, Direction::Backward).unwrap();
    }
    assert_eq!(
        motor.home_move(),
        Move {
            direction: Direction::Forward,
            steps: 37
        }
    );
}

#[test]
fn config_from_toml_with_defaults_and_validation() {
    let config: StepperConfig = toml::from_str("").unwrap();
    assert_eq!(config, StepperConfig::default());
    assert_eq!(config.address, 0x60);
    assert_eq!(config.steps_per_rev, 200);

    let config: StepperConfig = toml::from_str(
        "port = 2\nstyle = { micro = 16 }\ngear_ratio = 4.5\nwrap_limit_deg = 200.0\n",
    )
    .unwrap();
    assert_eq!(config.port, Port::Two);
    assert_eq!(config.style, StepStyle::Micro(16));
    assert_eq!(config.gear_ratio, 4.5);
    assert!(toml::from_str::<StepperConfig>("port = 3").is_err());
    assert!(toml::from_str::<StepperConfig>("speed = 3").is_err());
    let config: StepperConfig = toml::from_str("style = \"half\"").unwrap();
    assert_eq!(config.style, StepStyle::Half);

    let bad = |c: StepperConfig| Stepper::new(&c).unwrap_err();
    let d = StepperConfig::default;
    assert_eq!(
        bad(StepperConfig {
            style: StepStyle::Micro(7),
            ..d()
        }),
        ConfigError::Microsteps(7)
    );
    assert_eq!(
        bad(StepperConfig {
            address: 0x70,
            ..d()
        }),
        ConfigError::Address(0x70)
    );
    assert_eq!(
        bad(StepperConfig {
            gear_ratio: 0.0,
            ..d()
        }),
        ConfigError::NotPositive("gear_ratio")
    );
}
