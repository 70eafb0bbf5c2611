//! A thin PCA9685 layer: the registers the Motor HAT needs, the channel value encoding with the
//! full-on/full-off bits, and [`MotorHat`], which owns the bus (research/hardware.md §2.2).

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;

use super::error::Error;

/// PCA9685 register addresses.
pub mod reg {
    /// Mode register 1 (reset 0x11: SLEEP | ALLCALL).
    pub const MODE1: u8 = 0x00;
    /// Mode register 2 (reset 0x04: OUTDRV).
    pub const MODE2: u8 = 0x01;
    /// LED0_ON_L; channel n's four registers start at `LED0_ON_L + 4n`.
    pub const LED0_ON_L: u8 = 0x06;
    /// ALL_LED_ON_L: the four ALL_LED registers write the same byte to every channel.
    pub const ALL_LED_ON_L: u8 = 0xFA;
    /// The PWM frequency prescaler, writable only while MODE1.SLEEP = 1.
    pub const PRE_SCALE: u8 = 0xFE;
}

/// MODE1 bits.
pub mod mode1 {
    /// Restart the PWM channels after a sleep (reads 1 while a restart is pending).
    pub const RESTART: u8 = 0x80;
    /// Register auto-increment: a burst writes consecutive registers.
    pub const AI: u8 = 0x20;
    /// Low-power mode, oscillator off.
    pub const SLEEP: u8 = 0x10;
    /// Respond to the ALLCALL address.
    pub const ALLCALL: u8 = 0x01;
}

/// MODE2 bits.
pub mod mode2 {
    /// Totem-pole outputs (the HAT's TB6612 inputs need them).
    pub const OUTDRV: u8 = 0x04;
}

/// The PWM frequency the Adafruit libraries use for the Motor HAT.
pub const PWM_FREQUENCY_HZ: f64 = 1600.0;
/// The PCA9685's internal oscillator.
pub const OSCILLATOR_HZ: f64 = 25_000_000.0;
/// Minimum wait between clearing SLEEP and setting RESTART (datasheet 500 µs).
pub const RESTART_WAIT_US: u32 = 500;

/// The PRE_SCALE value for a PWM frequency: `round(25 MHz / (4096 f)) − 1`, or `None` outside
/// the chip's range 3..=255 (about 1526 Hz down to 24 Hz).
///
/// 1600 Hz, what the HAT libraries ask for, gives 3 (the fastest the chip runs: 1525.9 Hz).
pub fn prescale_for(frequency_hz: f64) -> Option<u8> {
    if !(frequency_hz.is_finite() && frequency_hz > 0.0) {
        return None;
    }
    let value = (OSCILLATOR_HZ / (4096.0 * frequency_hz)).round() - 1.0;
    if (3.0..=255.0).contains(&value) {
        Some(value as u8)
    } else {
        None
    }
}

/// What one PWM channel outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pwm {
    /// Always high: LEDn_ON_H bit 4.
    FullOn,
    /// Always low: LEDn_OFF_H bit 4 (takes precedence over full on).
    FullOff,
    /// High for this many of the 4096 counts of each period (1..=4095), starting at count 0.
    Duty(u16),
}

impl Pwm {
    /// A duty of `counts` out of 4096, with 0 and ≥ 4096 mapped to the full-off/full-on bits.
    pub fn from_counts(counts: u16) -> Self {
        match counts {
            0 => Self::FullOff,
            4096.. => Self::FullOn,
            c => Self::Duty(c),
        }
    }

    /// The channel's four registers: ON_L, ON_H, OFF_L, OFF_H.
    pub fn registers(self) -> [u8; 4] {
        match self {
            Self::FullOn => [0x00, 0x10, 0x00, 0x00],
            Self::FullOff => [0x00, 0x00, 0x00, 0x10],
            Self::Duty(c) => [0x00, 0x00, (c & 0xFF) as u8, ((c >> 8) & 0x0F) as u8],
        }
    }
}

/// The Adafruit DC & Stepper Motor HAT: a PCA9685 at `address` on an I2C bus.
///
/// Owns the bus; [`MotorHat::destroy`] gives it back. Holds no stepper state of its own (see
/// [`super::Stepper`]), so one HAT can drive both ports.
#[derive(Debug)]
pub struct MotorHat<I2C> {
    i2c: I2C,
    address: u8,
    retries: u8,
    transactions: u64,
}

impl<I2C: I2c> MotorHat<I2C> {
    /// A HAT at `address` (writes nothing yet); failed transactions are tried `retries` more
    /// times.
    pub fn new(i2c: I2C, address: u8, retries: u8) -> Self {
        Self {
            i2c,
            address,
            retries,
            transactions: 0,
        }
    }

    /// The PCA9685's 7-bit address.
    pub fn address(&self) -> u8 {
        self.address
    }

    /// I2C transactions attempted so far (including retries), for the bus-load figure.
    pub fn transactions(&self) -> u64 {
        self.transactions
    }

    /// Initialises the chip for the HAT: every channel full off, totem-pole outputs, register
    /// auto-increment, PWM at 1600 Hz (PRE_SCALE 3, 1525.9 Hz in fact), then restart.
    ///
    /// The sequence (research/hardware.md §2.2): MODE1 ← SLEEP|AI|ALLCALL; MODE2 ← OUTDRV;
    /// ALL_LED ← full off; PRE_SCALE ← 3 (only accepted asleep); MODE1 ← AI|ALLCALL (wake);
    /// wait 500 µs for the oscillator; MODE1 ← RESTART|AI|ALLCALL. MODE1 and PRE_SCALE are then
    /// read back.
    pub fn init<D: DelayNs>(&mut self, delay: &mut D) -> Result<(), Error<I2C::Error>> {
        let prescale = prescale_for(PWM_FREQUENCY_HZ).unwrap_or(3);
        let awake = mode1::AI | mode1::ALLCALL;
        self.write(&[reg::MODE1, awake | mode1::SLEEP])?;
        self.write(&[reg::MODE2, mode2::OUTDRV])?;
        let mut all_off = [reg::ALL_LED_ON_L, 0, 0, 0, 0];
        all_off[1..].copy_from_slice(&Pwm::FullOff.registers());
        self.write(&all_off)?;
        self.write(&[reg::PRE_SCALE, prescale])?;
        self.write(&[reg::MODE1, awake])?;
        delay.delay_us(RESTART_WAIT_US);
        self.write(&[reg::MODE1, awake | mode1::RESTART])?;
        self.verify(reg::MODE1, awake)?;
        self.verify(reg::PRE_SCALE, prescale)
    }

    /// Sets consecutive channels `first`, `first + 1`, … in one auto-increment burst (needs
    /// [`MotorHat::init`] first), so all of them change together at the I2C STOP.
    pub fn set_channels(&mut self, first: u8, values: &[Pwm]) -> Result<(), Error<I2C::Error>> {
        let mut bytes = Vec::with_capacity(1 + 4 * values.len());
        bytes.push(reg::LED0_ON_L.wrapping_add(first.wrapping_mul(4)));
        for value in values {
            bytes.extend_from_slice(&value.registers());
        }
        self.write(&bytes)
    }

    /// The bus, for inspecting a simulated one.
    pub fn bus(&self) -> &I2C {
        &self.i2c
    }

    /// Gives the bus back.
    pub fn destroy(self) -> I2C {
        self.i2c
    }

    fn verify(&mut self, register: u8, expected: u8) -> Result<(), Error<I2C::Error>> {
        let found = self.read_register(register)?;
        if found == expected {
            Ok(())
        } else {
            Err(Error::Verify {
                address: self.address,
                register,
                expected,
                found,
            })
        }
    }

    fn read_register(&mut self, register: u8) -> Result<u8, Error<I2C::Error>> {
        let mut value = [0u8];
        self.retry(|i2c, address| i2c.write_read(address, &[register], &mut value))?;
        let [value] = value;
        Ok(value)
    }

    fn write(&mut self, bytes: &[u8]) -> Result<(), Error<I2C::Error>> {
        self.retry(|i2c, address| i2c.write(address, bytes))
    }

    fn retry(
        &mut self,
        mut transfer: impl FnMut(&mut I2C, u8) -> Result<(), I2C::Error>,
    ) -> Result<(), Error<I2C::Error>> {
        let attempts = self.retries.saturating_add(1);
        let mut attempt = 0u8;
        loop {
            attempt += 1;
            self.transactions += 1;
            match transfer(&mut self.i2c, self.address) {
                Ok(()) => return Ok(()),
                Err(source) if attempt >= attempts => {
                    return Err(Error::I2c {
                        address: self.address,
                        attempts,
                        source,
                    });
                }
                Err(_) => {}
            }
        }
    }
}
