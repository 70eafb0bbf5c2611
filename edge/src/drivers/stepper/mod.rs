//! Stepper driver for the Adafruit DC & Stepper Motor HAT (PCA9685 at 0x60 driving two TB6612
//! H-bridges), generic over [`embedded_hal::i2c::I2c`] (research/hardware.md §2).
//!
//! - [`MotorHat`]: the PCA9685 layer. It owns the bus ([`MotorHat::destroy`] gives it back),
//!   initialises the chip for 1600 Hz PWM and writes channel bursts with the full-on/off bits.
//! - [`Stepper`]: one motor on port 1 or 2. [`Stepper::step`] writes the coil pattern of the
//!   next phase (full, half or micro steps) in a single 25-byte burst; [`Stepper::hold`] and
//!   [`Stepper::release`] energise or free the coils. It tracks the step index and the commanded
//!   angle of the output shaft (steps per revolution and gear ratio from [`StepperConfig`]) and
//!   refuses to pass the cable-wrap limit; [`Stepper::return_home`] unwinds.
//!
//! The driver never sleeps on its own: the caller paces single steps, or hands a [`DelayNs`] to
//! the paced moves ([`Stepper::run`]). It cannot see whether the rotor followed (a stepper has no
//! feedback); the commanded angle is what it wrote.

mod config;
mod error;
mod pca9685;
#[cfg(test)]
mod tests;

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;

pub use config::{ConfigError, DEFAULT_ADDRESS, Port, StepStyle, StepperConfig};
pub use error::Error;
pub use pca9685::{
    MotorHat, OSCILLATOR_HZ, PWM_FREQUENCY_HZ, Pwm, RESTART_WAIT_US, mode1, mode2, prescale_for,
    reg,
};

/// Which way to turn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Increasing angle (the Adafruit libraries' FORWARD coil order AIN2 → BIN1 → AIN1 → BIN2).
    Forward,
    /// Decreasing angle.
    Backward,
}

impl Direction {
    /// +1 forward, −1 backward.
    pub fn sign(self) -> i64 {
        match self {
            Self::Forward => 1,
            Self::Backward => -1,
        }
    }
}

/// A move of a number of steps in one direction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Move {
    /// Which way.
    pub direction: Direction,
    /// How many steps of the stepper's style.
    pub steps: u64,
}

/// The channel values of one port in channel order: PWMA, AIN2, AIN1, BIN1, BIN2, PWMB
/// (port 1: channels 8–13, port 2: channels 2–7; research/hardware.md §2.3).
pub type CoilOutputs = [Pwm; 6];

/// The coil outputs for step index `position` of `style`.
///
/// Every style counts from the same electrical phase, both coils on with AIN2 and BIN1 (the
/// legacy table's phase 1), so index 0 is one rotor position whatever the style. The field angle
/// advances by 90°/n electrical per index (n = 2 for half steps and, two indices at a time, for
/// full steps; n microsteps otherwise): bridge A carries cos ψ (positive = AIN1, negative =
/// AIN2), bridge B carries −sin ψ (positive = BIN1). Full and half steps drive PWMA/PWMB fully
/// on; microsteps put |current| on PWMA/PWMB as round(4096·sin(iπ/2n)) counts.
pub fn coil_outputs(style: StepStyle, position: i64) -> CoilOutputs {
    let (n, stride, digital) = match style {
        StepStyle::Full => (2i64, 2i64, true),
        StepStyle::Half => (2, 1, true),
        StepStyle::Micro(m) => (i64::from(m.max(2)), 1, false),
    };
    let cycle = 4 * n;
    // Index 0 is ψ = 225° electrical, 5n/2 units of 90°/n.
    let u = (5 * n / 2 + stride * position.rem_euclid(cycle)).rem_euclid(cycle);
    let (quadrant, r) = (u / n, u % n);
    // (sign, sine-table index) of cos ψ and of sin ψ.
    let (cos, sin) = match quadrant {
        0 => ((1, n - r), (1, r)),
        1 => ((-1, r), (1, n - r)),
        2 => ((-1, n - r), (-1, r)),
        _ => ((1, r), (-1, n - r)),
    };
    let amplitude = |index: i64| -> Pwm {
        if index == 0 {
            Pwm::FullOff
        } else if digital || index >= n {
            Pwm::FullOn
        } else {
            let s = (index as f64 * std::f64::consts::PI / (2 * n) as f64).sin();
            Pwm::from_counts((4096.0 * s).round() as u16)
        }
    };
    // Bridge current: (PWM, IN-positive, IN-negative).
    let bridge = |(sign, index): (i64, i64)| -> (Pwm, Pwm, Pwm) {
        if index == 0 {
            (amplitude(0), Pwm::FullOff, Pwm::FullOff)
        } else if sign > 0 {
            (amplitude(index), Pwm::FullOn, Pwm::FullOff)
        } else {
            (amplitude(index), Pwm::FullOff, Pwm::FullOn)
        }
    };
    let (pwma, ain1, ain2) = bridge(cos);
    let (pwmb, bin1, bin2) = bridge((-sin.0, sin.1));
    // A bridge with no current keeps PWM on in the digital styles (as the legacy library does),
    // so the only change between phases is on the direction inputs.
    let pwma = if digital { Pwm::FullOn } else { pwma };
    let pwmb = if digital { Pwm::FullOn } else { pwmb };
    [pwma, ain2, ain1, bin1, bin2, pwmb]
}

/// One stepper motor on a [`MotorHat`] port: the step index, the style and the geometry.
///
/// The step index counts steps of the configured style from home (0); the commanded angle of
/// the output shaft is `index × 360° / (steps_per_rev × steps per full step × gear_ratio)`.
#[derive(Debug, Clone)]
pub struct Stepper {
    port: Port,
    style: StepStyle,
    steps_per_output_rev: f64,
    wrap_limit_deg: f64,
    step_period_ns: u32,
    position: i64,
    energised: bool,
}

impl Stepper {
    /// A stepper at home (index 0), coils assumed off, from a validated `config`.
    pub fn new(config: &StepperConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        let per_full = f64::from(config.style.steps_per_full_step());
        let step_rate = config.full_steps_per_sec * per_full;
        Ok(Self {
            port: config.port,
            style: config.style,
            steps_per_output_rev: f64::from(config.steps_per_rev) * per_full * config.gear_ratio,
            wrap_limit_deg: config.wrap_limit_deg,
            step_period_ns: (1e9 / step_rate).round().clamp(1.0, f64::from(u32::MAX)) as u32,
            position: 0,
            energised: false,
        })
    }

    /// The HAT port.
    pub fn port(&self) -> Port {
        self.port
    }

    /// The step style.
    pub fn style(&self) -> StepStyle {
        self.style
    }

    /// The step index: steps of the style from home, positive forward.
    pub fn position(&self) -> i64 {
        self.position
    }

    /// Whether the coils are energised (holding torque).
    pub fn is_energised(&self) -> bool {
        self.energised
    }

    /// Output-shaft degrees per step.
    pub fn step_angle_deg(&self) -> f64 {
        360.0 / self.steps_per_output_rev
    }

    /// Steps of the style per output-shaft revolution (motor steps × gear ratio).
    pub fn steps_per_output_rev(&self) -> f64 {
        self.steps_per_output_rev
    }

    /// The commanded angle of the output shaft, degrees from home (not wrapped).
    pub fn commanded_angle_deg(&self) -> f64 {
        self.position as f64 * self.step_angle_deg()
    }

    /// The pause between steps of a paced move, from `full_steps_per_sec`.
    pub fn step_period_ns(&self) -> u32 {
        self.step_period_ns
    }

    /// The coil outputs of the current step index.
    pub fn outputs(&self) -> CoilOutputs {
        coil_outputs(self.style, self.position)
    }

    /// Makes the current step index home (angle 0).
    pub fn set_home(&mut self) {
        self.position = 0;
    }

    /// Moves one step: writes exactly the coil pattern of the next phase.
    ///
    /// Refuses (writing nothing) a step past the cable-wrap limit. On a bus error the index is
    /// unchanged, so the commanded angle always matches the last pattern written.
    pub fn step<I2C: I2c>(
        &mut self,
        hat: &mut MotorHat<I2C>,
        direction: Direction,
    ) -> Result<(), Error<I2C::Error>> {
        let target = self.position.saturating_add(direction.sign());
        let target_deg = target as f64 * self.step_angle_deg();
        if target_deg.abs() > self.wrap_limit_deg + 1e-9 {
            return Err(Error::WrapLimit {
                target_deg,
                limit_deg: self.wrap_limit_deg,
            });
        }
        hat.set_channels(self.port.first_channel(), &coil_outputs(self.style, target))?;
        self.position = target;
        self.energised = true;
        Ok(())
    }

    /// Energises the coils at the current step index (holding torque, no motion).
    pub fn hold<I2C: I2c>(&mut self, hat: &mut MotorHat<I2C>) -> Result<(), Error<I2C::Error>> {
        hat.set_channels(self.port.first_channel(), &self.outputs())?;
        self.energised = true;
        Ok(())
    }

    /// Turns all six channels of the port fully off: no current, no holding torque.
    ///
    /// The index is kept; a later [`Stepper::hold`] or step re-energises the same phase.
    pub fn release<I2C: I2c>(&mut self, hat: &mut MotorHat<I2C>) -> Result<(), Error<I2C::Error>> {
        hat.set_channels(self.port.first_channel(), &[Pwm::FullOff; 6])?;
        self.energised = false;
        Ok(())
    }

    /// Steps `mv.steps` times, pausing [`Stepper::step_period_ns`] after each step.
    ///
    /// Stops at the first error; the index then reflects the steps done.
    pub fn run<I2C: I2c, D: DelayNs>(
        &mut self,
        hat: &mut MotorHat<I2C>,
        mv: Move,
        delay: &mut D,
    ) -> Result<(), Error<I2C::Error>> {
        for _ in 0..mv.steps {
            self.step(hat, mv.direction)?;
            delay.delay_ns(self.step_period_ns);
        }
        Ok(())
    }

    /// The move back to home.
    ///
    /// The cables twist with the unwrapped angle, which [`Stepper::step`] keeps within
    /// ±`wrap_limit_deg`; the way home that never crosses the limit is straight back through
    /// the angles already passed, so the move is always −index (e.g. from +180° it turns
    /// backward 180°, never forward "the other way round").
    pub fn home_move(&self) -> Move {
        Move {
            direction: if self.position > 0 {
                Direction::Backward
            } else {
                Direction::Forward
            },
            steps: self.position.unsigned_abs(),
        }
    }

    /// Runs [`Stepper::home_move`] paced by `delay`, and returns the move made.
    pub fn return_home<I2C: I2c, D: DelayNs>(
        &mut self,
        hat: &mut MotorHat<I2C>,
        delay: &mut D,
    ) -> Result<Move, Error<I2C::Error>> {
        let mv = self.home_move();
        self.run(hat, mv, delay)?;
        Ok(mv)
    }
}
