//! Emulator tests (register semantics, rotor model) and the edge stepper driver run against it.
//! Register values and coil patterns are written out by hand from research/hardware.md §2.

use std::sync::{Arc, Mutex};

use embedded_hal::i2c::I2c;
use scan3d_edge::clock::Clock;
use scan3d_edge::drivers::stepper::{
    Direction, MotorHat, Move, Port, StepStyle, Stepper, StepperConfig,
};

use super::{Pca9685Emulator, RotorCounters, Turntable, Violation};
use crate::i2c::{I2cBus, SimClock, lock};

const HAT: u8 = 0x60;

fn read(emu: &mut Pca9685Emulator, register: u8) -> u8 {
    let mut value = [0u8];
    emu.write_read(HAT, &[register], &mut value).unwrap();
    value[0]
}

/// Writes one port's six channels (PWMA, AIN2, AIN1, BIN1, BIN2, PWMB) as digital levels
/// (1 = full on, 0 = full off) in one auto-increment burst at `now_ns`.
fn set_port1(emu: &mut Pca9685Emulator, now_ns: u64, levels: [u8; 6]) {
    emu.set_time_ns(now_ns);
    let mut bytes = vec![0x26]; // LED8_ON_L
    for level in levels {
        bytes.extend_from_slice(if level == 1 {
            &[0x00, 0x10, 0x00, 0x00]
        } else {
            &[0x00, 0x00, 0x00, 0x10]
        });
    }
    emu.write(HAT, &bytes).unwrap();
}

/// An emulator woken with auto-increment (MODE1 = AI | ALLCALL), time 0.
fn awake() -> Pca9685Emulator {
    let mut emu = Pca9685Emulator::motor_hat();
    emu.write(HAT, &[0x00, 0x21]).unwrap();
    emu
}

#[test]
fn power_on_register_values() {
    let mut emu = Pca9685Emulator::motor_hat();
    assert_eq!(read(&mut emu, 0x00), 0x11); // MODE1: SLEEP | ALLCALL
    assert_eq!(read(&mut emu, 0x01), 0x04); // MODE2: OUTDRV
    assert_eq!(read(&mut emu, 0x02), 0xE2);
    assert_eq!(read(&mut emu, 0x05), 0xE0); // ALLCALLADR
    assert_eq!(read(&mut emu, 0x09), 0x10); // LED0_OFF_H: full off
    assert_eq!(read(&mut emu, 0x45), 0x10); // LED15_OFF_H
    assert_eq!(read(&mut emu, 0xFE), 0x1E); // PRE_SCALE
    assert!((emu.pwm_frequency_hz() - 25e6 / (4096.0 * 31.0)).abs() < 1e-9);
    // AI = 0: a 2-byte read repeats MODE1.
    let mut two = [0u8; 2];
    emu.write_read(HAT, &[0x00], &mut two).unwrap();
    assert_eq!(two, [0x11, 0x11]);
}

#[test]
fn auto_increment_decides_where_burst_bytes_go() {
    let mut emu = Pca9685Emulator::motor_hat();
    // AI = 0: all four data bytes land in LED0_ON_L.
    emu.write(HAT, &[0x06, 0x01, 0x02, 0x03, 0x04]).unwrap();
    assert_eq!(
        [emu.register(0x06), emu.register(0x07), emu.register(0x08)],
        [0x04, 0x00, 0x00]
    );
    emu.write(HAT, &[0x00, 0x31]).unwrap(); // AI on, still asleep
    emu.write(HAT, &[0x06, 0x01, 0x02, 0x03, 0x04]).unwrap();
    let mut four = [0u8; 4];
    emu.write_read(HAT, &[0x06], &mut four).unwrap();
    assert_eq!(four, [0x01, 0x02, 0x03, 0x04]);
    // LED15_OFF_H rolls over to MODE1.
    emu.write(HAT, &[0x45, 0x10, 0x35]).unwrap();
    assert_eq!(emu.register(0x00), 0x35);
}

#[test]
fn prescale_is_writable_only_asleep_and_at_least_3() {
    let mut emu = Pca9685Emulator::motor_hat();
    emu.write(HAT, &[0xFE, 0x05]).unwrap();
    assert_eq!(read(&mut emu, 0xFE), 0x05);
    emu.write(HAT, &[0xFE, 0x01]).unwrap();
    assert_eq!(read(&mut emu, 0xFE), 0x03);
    emu.write(HAT, &[0x00, 0x01]).unwrap(); // wake
    emu.write(HAT, &[0xFE, 0x79]).unwrap();
    assert_eq!(read(&mut emu, 0xFE), 0x03);
    assert_eq!(
        emu.violations(),
        &[Violation::PrescaleWhileAwake { value: 0x79 }]
    );
    assert!((emu.pwm_frequency_hz() - 1_525.878_906_25).abs() < 1e-6);
}

#[test]
fn full_on_full_off_and_counted_duties() {
    let mut emu = awake();
    // ch0: ON_H full-on and OFF_H full-off both set: off wins.
    emu.write(HAT, &[0x06, 0x00, 0x10, 0x00, 0x10]).unwrap();
    assert_eq!(emu.channel_duty(0), 0.0);
    emu.write(HAT, &[0x06, 0x00, 0x10, 0x00, 0x00]).unwrap();
    assert_eq!(emu.channel_duty(0), 1.0);
    // ON = 0, OFF = 0x800: half.
    emu.write(HAT, &[0x06, 0x00, 0x00, 0x00, 0x08]).unwrap();
    assert_eq!(emu.channel_duty(0), 0.5);
    // ON = 4000 (0xFA0), OFF = 100 (0x064): wraps, 196 counts.
    emu.write(HAT, &[0x06, 0xA0, 0x0F, 0x64, 0x00]).unwrap();
    assert_eq!(emu.channel_duty(0), 196.0 / 4096.0);
    // INVRT.
    emu.write(HAT, &[0x01, 0x14]).unwrap();
    assert_eq!(emu.channel_duty(0), 1.0 - 196.0 / 4096.0);
    // Asleep: outputs off.
    emu.write(HAT, &[0x01, 0x04]).unwrap();
    emu.write(HAT, &[0x00, 0x31]).unwrap();
    assert_eq!(emu.channel_duty(0), 0.0);
}

#[test]
fn all_led_writes_every_channel_and_reads_zero() {
    let mut emu = awake();
    emu.write(HAT, &[0xFA, 0x00, 0x10, 0x00, 0x00]).unwrap();
    for channel in 0..16 {
        assert_eq!(emu.channel_duty(channel), 1.0, "channel {channel}");
    }
    assert_eq!(read(&mut emu, 0x07 + 4 * 15), 0x10);
    assert_eq!(read(&mut emu, 0xFB), 0x00);
}

#[test]
fn restart_needs_500_us_after_wake() {
    let mut emu = awake();
    emu.write(HAT, &[0x00, 0x31]).unwrap(); // sleep while running
    assert_eq!(read(&mut emu, 0x00), 0xB1); // RESTART reads 1
    emu.set_time_ns(1_000_000);
    emu.write(HAT, &[0x00, 0x21]).unwrap(); // wake at 1 ms
    emu.set_time_ns(1_100_000);
    emu.write(HAT, &[0x00, 0xA1]).unwrap(); // 100 µs later: too soon
    assert_eq!(read(&mut emu, 0x00), 0xA1);
    assert_eq!(
        emu.violations(),
        &[Violation::RestartTooSoon { after_ns: 100_000 }]
    );
    emu.set_time_ns(1_500_000);
    emu.write(HAT, &[0x00, 0xA1]).unwrap();
    assert_eq!(read(&mut emu, 0x00), 0x21);
}

#[test]
fn allcall_and_general_call_reset_on_a_shared_bus() {
    let emu = Arc::new(Mutex::new(Pca9685Emulator::motor_hat()));
    let mut bus = I2cBus::new();
    bus.attach(emu.clone());
    bus.write(0x70, &[0x00, 0x21]).unwrap(); // ALLCALL 0xE0 >> 1
    assert_eq!(lock(&emu).register(0x00), 0x20 | 0x01);
    bus.write(0x60, &[0x00, 0x20]).unwrap(); // ALLCALL bit cleared
    assert!(bus.write(0x70, &[0x00, 0x21]).is_err());
    bus.write(0x60, &[0xFE]).unwrap();
    assert!(bus.write(0x00, &[0x07]).is_err()); // general call, not SWRST
    bus.write(0x00, &[0x06]).unwrap(); // SWRST
    assert_eq!(lock(&emu).register(0x00), 0x11);
    assert!(bus.write(0x41, &[0x00]).is_err());
}

#[test]
fn rotor_decodes_phases_and_loses_fast_or_skipped_changes() {
    let mut emu = awake();
    let table = emu.turntable(Port::One);
    // Legacy phase 1 (AIN2 + BIN1) is where the rotor rests at power-up.
    set_port1(&mut emu, 0, [1, 1, 0, 1, 0, 1]);
    assert!(table.is_holding());
    assert_eq!(table.counters(), RotorCounters::default());
    // Phase 2 (BIN1): a half step forward, 0.9°, taking 1 ms at 1000 half steps/s.
    set_port1(&mut emu, 10_000_000, [1, 0, 0, 1, 0, 1]);
    assert!((table.angle_deg() - 0.9).abs() < 1e-9);
    assert!((table.angle_deg_at(10_500_000) - 0.45).abs() < 1e-9);
    // Phase 3 only 0.5 ms later: too fast, lost.
    set_port1(&mut emu, 10_500_000, [1, 0, 1, 1, 0, 1]);
    assert!((table.angle_deg() - 0.9).abs() < 1e-9);
    // Phase 6 (BIN2), from phase 2: 180° electrical, skipped phases, lost.
    set_port1(&mut emu, 20_000_000, [1, 0, 0, 0, 1, 1]);
    // Phase 1 again, from phase 2: a half step backward.
    set_port1(&mut emu, 30_000_000, [1, 1, 0, 1, 0, 1]);
    assert!(table.angle_deg().abs() < 1e-9);
    assert_eq!(
        table.counters(),
        RotorCounters {
            steps_taken: 2,
            steps_lost: 2,
            lost_too_fast: 1,
            lost_skipped: 1,
        }
    );
    assert_eq!(emu.steps_lost(Port::One), 2);
    assert_eq!(table.history().len(), 4);
    // Released: no torque; port 2 never moved.
    set_port1(&mut emu, 40_000_000, [0; 6]);
    assert!(!table.is_holding());
    assert_eq!(emu.steps_taken(Port::Two), 0);
}

/// The edge driver on a simulated bus with the emulator, paced on simulated time.
struct Fixture {
    clock: SimClock,
    emu: Arc<Mutex<Pca9685Emulator>>,
    table: Turntable,
    hat: MotorHat<I2cBus>,
    motor: Stepper,
}

fn fixture(config: StepperConfig) -> Fixture {
    let clock = SimClock::new();
    let emu = Arc::new(Mutex::new(Pca9685Emulator::motor_hat()));
    let table = lock(&emu).turntable(config.port);
    let bus = I2cBus::with_clock(clock.shared());
    bus.attach(emu.clone());
    let mut hat = MotorHat::new(bus, config.address, config.retries);
    hat.init(&mut clock.clone()).unwrap();
    let motor = Stepper::new(&config).unwrap();
    Fixture {
        clock,
        emu,
        table,
        hat,
        motor,
    }
}

fn one_turn(style: StepStyle) -> StepperConfig {
    StepperConfig {
        style,
        wrap_limit_deg: 360.0,
        ..StepperConfig::default()
    }
}

impl Fixture {
    fn run(&mut self, direction: Direction, steps: u64) {
        self.motor
            .run(
                &mut self.hat,
                Move { direction, steps },
                &mut self.clock.clone(),
            )
            .unwrap();
    }
}

#[test]
fn driver_init_leaves_the_chip_at_1600_hz_with_everything_off() {
    let r = fixture(StepperConfig::default());
    let emu = lock(&r.emu);
    assert_eq!(emu.register(0x00), 0x21); // awake, AI, ALLCALL, no restart pending
    assert_eq!(emu.register(0x01), 0x04);
    assert_eq!(emu.register(0xFE), 0x03);
    assert!((emu.pwm_frequency_hz() - 1_525.878_906_25).abs() < 1e-6);
    for channel in 0..16 {
        assert_eq!(emu.channel_duty(channel), 0.0);
    }
    assert!(emu.violations().is_empty());
    assert_eq!(r.clock.now_ns(), 500_000);
}

#[test]
fn full_steps_one_revolution() {
    let mut r = fixture(one_turn(StepStyle::Full));
    r.motor.hold(&mut r.hat).unwrap();
    r.run(Direction::Forward, 200);
    assert!((r.table.angle_deg() - 360.0).abs() < 1e-9);
    assert_eq!(r.table.counters().steps_taken, 200);
    assert_eq!(r.table.counters().steps_lost, 0);
    assert!((r.motor.commanded_angle_deg() - r.table.angle_deg()).abs() < 1e-9);
}

#[test]
fn half_steps_one_revolution() {
    let mut r = fixture(one_turn(StepStyle::Half));
    r.run(Direction::Forward, 400);
    assert!((r.table.angle_deg() - 360.0).abs() < 1e-9);
    assert_eq!(r.table.counters().steps_taken, 400);
    assert_eq!(r.table.counters().steps_lost, 0);
}

#[test]
fn microsteps_one_revolution_and_a_fraction_of_a_step() {
    let mut r = fixture(one_turn(StepStyle::Micro(16)));
    r.run(Direction::Forward, 3);
    // 3/16 of 1.8°.
    // (PWM duties are rounded to 1/4096, so the field angle is within a few thousandths.)
    assert!((r.table.angle_deg() - 0.3375).abs() < 1e-3);
    r.run(Direction::Forward, 3200 - 3);
    assert!((r.table.angle_deg() - 360.0).abs() < 1e-6);
    assert_eq!(r.table.counters().steps_taken, 3200);
    assert_eq!(r.table.counters().steps_lost, 0);
}

#[test]
fn backward_turns_the_other_way_and_port_two_is_independent() {
    let mut r = fixture(StepperConfig {
        port: Port::Two,
        ..StepperConfig::default()
    });
    r.run(Direction::Backward, 50);
    assert!((r.table.angle_deg() + 90.0).abs() < 1e-9);
    assert_eq!(lock(&r.emu).steps_taken(Port::One), 0);
}

#[test]
fn release_frees_and_hold_keeps_the_position() {
    let mut r = fixture(StepperConfig::default());
    r.run(Direction::Forward, 10);
    r.motor.release(&mut r.hat).unwrap();
    assert!(!r.table.is_holding());
    r.clock.advance_ns(1_000_000_000);
    r.motor.hold(&mut r.hat).unwrap();
    assert!(r.table.is_holding());
    assert!((r.table.angle_deg() - 18.0).abs() < 1e-9);
    r.run(Direction::Forward, 1);
    assert!((r.table.angle_deg() - 19.8).abs() < 1e-9);
    assert_eq!(r.table.counters().steps_taken, 11);
}

#[test]
fn return_home_unwinds_within_the_wrap_limit() {
    let mut r = fixture(StepperConfig::default()); // limit ±180°
    r.run(Direction::Forward, 100);
    assert!((r.table.angle_deg() - 180.0).abs() < 1e-9);
    assert!(r.motor.step(&mut r.hat, Direction::Forward).is_err());
    let mv = r
        .motor
        .return_home(&mut r.hat, &mut r.clock.clone())
        .unwrap();
    assert_eq!(mv.direction, Direction::Backward);
    assert!(r.table.angle_deg().abs() < 1e-9);
    let (min, max) = r
        .table
        .history()
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), &(_, a)| {
            (lo.min(a), hi.max(a))
        });
    assert!(min > -1e-9 && max < 180.0 + 1e-9, "{min} {max}");
    assert_eq!(r.table.counters().steps_lost, 0);
}

#[test]
fn stepping_at_the_rate_limit_keeps_every_step() {
    // 500 full steps/s = 1000 half steps/s: each step starts as the last one ends.
    let mut r = fixture(StepperConfig {
        full_steps_per_sec: 500.0,
        ..one_turn(StepStyle::Full)
    });
    r.run(Direction::Forward, 200);
    assert_eq!(r.table.counters().steps_lost, 0);
    assert!((r.table.angle_deg() - 360.0).abs() < 1e-9);
}

#[test]
fn overspeed_loses_steps_and_commanded_differs_from_actual() {
    let mut r = fixture(StepperConfig {
        full_steps_per_sec: 800.0,
        ..one_turn(StepStyle::Full)
    });
    r.run(Direction::Forward, 200);
    let lost = r.table.counters().steps_lost;
    assert!(lost > 0);
    assert_eq!(lock(&r.emu).steps_lost(Port::One), lost);
    assert!((r.motor.commanded_angle_deg() - 360.0).abs() < 1e-9);
    assert!(
        (r.motor.commanded_angle_deg() - r.table.angle_deg()).abs() >= 1.8,
        "rotor at {}",
        r.table.angle_deg()
    );
}

#[test]
fn the_turntable_angle_is_interpolated_during_a_step() {
    let mut r = fixture(StepperConfig::default());
    r.motor.hold(&mut r.hat).unwrap();
    r.clock.set_ns(10_000_000);
    r.motor.step(&mut r.hat, Direction::Forward).unwrap();
    // A full step (90° electrical) takes 2 ms at 1000 half steps/s.
    assert_eq!(r.table.angle_deg_at(9_000_000), 0.0);
    assert!((r.table.angle_deg_at(11_000_000) - 0.9).abs() < 1e-9);
    assert!((r.table.angle_deg_at(12_000_000) - 1.8).abs() < 1e-9);
    assert_eq!(
        r.table.history(),
        vec![(10_000_000, 0.0), (12_000_000, 1.8)]
    );
}
