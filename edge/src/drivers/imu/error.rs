//! IMU driver errors: every one names the chip and its bus address.

use core::fmt;

use embedded_hal::i2c::ErrorKind;

use super::config::ConfigError;
use super::registers::{ak, mpu};

/// Which of the two dies in the MPU-9250 package an error concerns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Chip {
    /// The accel/gyro die (MPU-6500 part), at 0x68 or 0x69.
    Mpu9250,
    /// The magnetometer die, at 0x0C in bypass mode.
    Ak8963,
}

impl fmt::Display for Chip {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Mpu9250 => "MPU-9250",
            Self::Ak8963 => "AK8963",
        })
    }
}

/// An IMU driver error, generic over the bus error `E`.
///
/// `Display` and `std::error::Error` are written by hand rather than derived: the bus error is
/// only known to implement `embedded_hal::i2c::Error` (not `std::error::Error`), so it is shown
/// through its `kind()` and `Debug` instead of being chained as a source.
#[derive(Debug)]
pub enum Error<E> {
    /// The bus failed on every attempt (NACK, arbitration loss, bus error).
    I2c {
        /// The chip addressed.
        chip: Chip,
        /// Its 7-bit address.
        address: u8,
        /// How many times the transaction was tried.
        attempts: u8,
        /// The bus error of the last attempt.
        source: E,
    },
    /// The identity register holds an unexpected value: wrong device or a clone without
    /// magnetometer.
    WrongChip {
        /// The chip addressed.
        chip: Chip,
        /// Its 7-bit address.
        address: u8,
        /// The value read from WHO_AM_I (MPU) or WIA (AK8963).
        found: u8,
    },
    /// The AK8963 fuse ROM returned 0x00 or 0xFF for a sensitivity adjustment: the read did not
    /// reach the fuse ROM.
    InvalidAsa {
        /// The AK8963's address.
        address: u8,
        /// ASAX, ASAY, ASAZ as read.
        asa: [u8; 3],
    },
    /// The configuration cannot be applied.
    Config(ConfigError),
    /// A FIFO read was asked of a driver whose FIFO is not running (register read mode, or
    /// before a successful `init`).
    FifoOff {
        /// The MPU-9250's address.
        address: u8,
    },
}

impl<E: embedded_hal::i2c::Error> fmt::Display for Error<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::I2c {
                chip,
                address,
                attempts,
                source,
            } => {
                write!(
                    f,
                    "{chip} at I2C address {address:#04x}: bus error after {attempts} attempt(s): "
                )?;
                // `Other` says only "a different error occurred"; the bus error's own words
                // (e.g. the I2C socket's) are the message then.
                match source.kind() {
                    ErrorKind::Other => write!(f, "{source:?}"),
                    kind => write!(f, "{kind} ({source:?})"),
                }
            }
            Self::WrongChip {
                chip: Chip::Mpu9250,
                address,
                found,
            } => {
                write!(
                    f,
                    "MPU-9250 at I2C address {address:#04x}: WHO_AM_I is {found:#04x}, expected \
                     {:#04x} (MPU-9250) or {:#04x} (MPU-9255)",
                    mpu::ID_MPU9250,
                    mpu::ID_MPU9255
                )?;
                if *found == mpu::ID_MPU6500 {
                    f.write_str("; 0x70 is an MPU-6500, which has no magnetometer")?;
                }
                Ok(())
            }
            Self::WrongChip {
                chip: Chip::Ak8963,
                address,
                found,
            } => write!(
                f,
                "AK8963 at I2C address {address:#04x}: WIA is {found:#04x}, expected {:#04x}",
                ak::ID
            ),
            Self::InvalidAsa { address, asa } => write!(
                f,
                "AK8963 at I2C address {address:#04x}: fuse ROM sensitivity adjustment \
                 {asa:02x?} is invalid (0x00 or 0xff)"
            ),
            Self::Config(e) => write!(f, "{e}"),
            Self::FifoOff { address } => write!(
                f,
                "MPU-9250 at I2C address {address:#04x}: FIFO read asked while the FIFO is not \
                 running (read_mode = \"registers\" or not initialised)"
            ),
        }
    }
}

impl<E: embedded_hal::i2c::Error> std::error::Error for Error<E> {}
