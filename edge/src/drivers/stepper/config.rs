//! Stepper configuration (`[stepper]` in `edge.toml`): HAT address, port, step style, motor and
//! gearing, cable-wrap limit and speed.

use serde::Deserialize;

/// Default PCA9685 address of the Motor HAT (no address jumpers bridged).
pub const DEFAULT_ADDRESS: u8 = 0x60;

/// Which stepper terminals of the HAT the motor is wired to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "u8")]
pub enum Port {
    /// Stepper 1: terminals M1 + M2, PCA9685 channels 8–13.
    One,
    /// Stepper 2: terminals M3 + M4, PCA9685 channels 2–7.
    Two,
}

impl Port {
    /// The first of the port's six consecutive PCA9685 channels (PWMA).
    pub fn first_channel(self) -> u8 {
        match self {
            Self::One => 8,
            Self::Two => 2,
        }
    }
}

impl TryFrom<u8> for Port {
    type Error = ConfigError;

    fn try_from(value: u8) -> Result<Self, Self::Error> {
        match value {
            1 => Ok(Self::One),
            2 => Ok(Self::Two),
            other => Err(ConfigError::Port(other)),
        }
    }
}

/// How the coils are driven, which sets the step size.
///
/// In TOML: `style = "full"`, `style = "half"` or `style = { micro = 16 }`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StepStyle {
    /// Full steps with both coils on (the legacy library's DOUBLE): most torque.
    Full,
    /// Half steps alternating one and two coils (INTERLEAVE): twice the resolution.
    Half,
    /// `n` microsteps per full step, coil currents on a sine table through PWMA/PWMB
    /// (`n` even, 2..=64).
    Micro(u8),
}

impl StepStyle {
    /// Steps of this style per full step.
    pub fn steps_per_full_step(self) -> u32 {
        match self {
            Self::Full => 1,
            Self::Half => 2,
            Self::Micro(n) => u32::from(n),
        }
    }
}

/// Why a stepper configuration was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// The HAT has stepper ports 1 and 2 only.
    #[error("stepper port {0} does not exist (the HAT has ports 1 and 2)")]
    Port(u8),
    /// The address is outside the HAT's jumper range 0x60–0x7F or is the ALLCALL address 0x70.
    #[error("Motor HAT address {0:#04x} is invalid (0x60–0x7f, not the ALLCALL address 0x70)")]
    Address(u8),
    /// Microsteps must be even and 2..=64.
    #[error("{0} microsteps per full step is invalid (even, 2–64)")]
    Microsteps(u8),
    /// A numeric setting is zero, negative or not finite.
    #[error("stepper setting `{0}` must be positive and finite")]
    NotPositive(&'static str),
}

/// Settings of one stepper on a Motor HAT.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StepperConfig {
    /// PCA9685 address of the HAT (default 0x60).
    pub address: u8,
    /// Which stepper port the motor is wired to (1 or 2; default 1).
    pub port: Port,
    /// Step style (default full steps).
    pub style: StepStyle,
    /// Full steps per motor revolution (default 200, a 1.8° NEMA-17).
    pub steps_per_rev: u32,
    /// Motor revolutions per revolution of the output shaft (default 1, direct drive).
    pub gear_ratio: f64,
    /// The output shaft never goes further than this from home, in degrees (default 180), so
    /// the cables through the turntable never wind up.
    pub wrap_limit_deg: f64,
    /// Speed for paced moves, in full steps per second of the motor (default 100).
    pub full_steps_per_sec: f64,
    /// Extra attempts for a failed bus transaction before giving up (default 2).
    pub retries: u8,
}

impl Default for StepperConfig {
    fn default() -> Self {
        Self {
            address: DEFAULT_ADDRESS,
            port: Port::One,
            style: StepStyle::Full,
            steps_per_rev: 200,
            gear_ratio: 1.0,
            wrap_limit_deg: 180.0,
            full_steps_per_sec: 100.0,
            retries: 2,
        }
    }
}

impl StepperConfig {
    /// Checks every setting; the driver only accepts a validated configuration.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(0x60..=0x7F).contains(&self.address) || self.address == 0x70 {
            return Err(ConfigError::Address(self.address));
        }
        if let StepStyle::Micro(n) = self.style
            && (!(2..=64).contains(&n) || n % 2 != 0)
        {
            return Err(ConfigError::Microsteps(n));
        }
        if self.steps_per_rev == 0 {
            return Err(ConfigError::NotPositive("steps_per_rev"));
        }
        for (name, value) in [
            ("gear_ratio", self.gear_ratio),
            ("wrap_limit_deg", self.wrap_limit_deg),
            ("full_steps_per_sec", self.full_steps_per_sec),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(ConfigError::NotPositive(name));
            }
        }
        Ok(())
    }
}
