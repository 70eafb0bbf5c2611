//! Stepper driver errors: bus failures name the chip and its address.

use core::fmt;

use super::config::ConfigError;

/// A Motor HAT / stepper error, generic over the bus error `E`.
///
/// `Display` and `std::error::Error` are written by hand: the bus error is only known to
/// implement `embedded_hal::i2c::Error`, so it is shown through `kind()` and `Debug`.
#[derive(Debug)]
pub enum Error<E> {
    /// The bus failed on every attempt (NACK, arbitration loss, bus error).
    I2c {
        /// The PCA9685's 7-bit address.
        address: u8,
        /// How many times the transaction was tried.
        attempts: u8,
        /// The bus error of the last attempt.
        source: E,
    },
    /// A register read back after initialisation does not hold what was written: not a
    /// PCA9685, or the chip ignored the write.
    Verify {
        /// The PCA9685's 7-bit address.
        address: u8,
        /// The register read back.
        register: u8,
        /// The value written.
        expected: u8,
        /// The value read.
        found: u8,
    },
    /// The step would turn the output shaft past the cable-wrap limit; nothing was written.
    WrapLimit {
        /// The angle the step would reach, in degrees from home.
        target_deg: f64,
        /// The configured limit, in degrees either side of home.
        limit_deg: f64,
    },
    /// The configuration cannot be applied.
    Config(ConfigError),
}

impl<E: embedded_hal::i2c::Error> fmt::Display for Error<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::I2c {
                address,
                attempts,
                source,
            } => write!(
                f,
                "PCA9685 (Motor HAT) at I2C address {address:#04x}: bus error after {attempts} \
                 attempt(s): {} ({source:?})",
                source.kind()
            ),
            Self::Verify {
                address,
                register,
                expected,
                found,
            } => write!(
                f,
                "PCA9685 (Motor HAT) at I2C address {address:#04x}: register {register:#04x} \
                 reads {found:#04x}, expected {expected:#04x}"
            ),
            Self::WrapLimit {
                target_deg,
                limit_deg,
            } => write!(
                f,
                "stepper: a step to {target_deg:.3}° would pass the cable-wrap limit of \
                 ±{limit_deg}°"
            ),
            Self::Config(e) => write!(f, "{e}"),
        }
    }
}

impl<E: embedded_hal::i2c::Error> std::error::Error for Error<E> {}

impl<E> From<ConfigError> for Error<E> {
    fn from(e: ConfigError) -> Self {
        Self::Config(e)
    }
}
