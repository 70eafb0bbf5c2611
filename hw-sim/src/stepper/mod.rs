//! Register-level emulator of the Adafruit Motor HAT: a PCA9685 PWM chip whose channels drive
//! two TB6612 bridges and stepper rotors (research/hardware.md §2.2–2.5).
//!
//! [`Pca9685Emulator`] keeps the PCA9685 register file with its reset values and semantics:
//! MODE1 sleep / restart / auto-increment, PRE_SCALE writable only in sleep (minimum 3), LEDn
//! ON/OFF with the full-on and full-off bits, the write-only ALL_LED registers, the ALLCALL and
//! sub-addresses, and the general-call software reset. Outputs change at the end of each write
//! transfer (MODE2.OCH = 0: on STOP) or after every byte (OCH = 1); each change is decoded into
//! a coil field angle per stepper port and handed to that port's [`Rotor`], which turns it into
//! steps taken or lost (see [`rotor`]).
//!
//! It is an [`I2cDevice`] (put it on an [`crate::i2c::I2cBus`] next to the IMU) and also an
//! [`I2c`] on its own. Time is pushed in ([`I2cDevice::set_time_ns`]); read the rotor through the
//! [`Turntable`] handle from [`Pca9685Emulator::turntable`] while a driver owns the bus.

pub mod rotor;
#[cfg(test)]
mod tests;

use embedded_hal::i2c::{ErrorType, I2c, Operation, SevenBitAddress};
use scan3d_edge::drivers::stepper::Port;

use crate::i2c::{BusError, I2cDevice, Nack, run_transaction};
pub use rotor::{Rotor, RotorConfig, RotorCounters, RotorMove, Turntable};

/// Register addresses, from the datasheet map in research/hardware.md §2.2.
mod regs {
    pub(super) const MODE1: u8 = 0x00;
    pub(super) const MODE2: u8 = 0x01;
    pub(super) const SUBADR1: u8 = 0x02;
    pub(super) const SUBADR2: u8 = 0x03;
    pub(super) const SUBADR3: u8 = 0x04;
    pub(super) const ALLCALLADR: u8 = 0x05;
    pub(super) const LED0_ON_L: u8 = 0x06;
    pub(super) const LED15_OFF_H: u8 = 0x45;
    pub(super) const ALL_LED_ON_L: u8 = 0xFA;
    pub(super) const ALL_LED_OFF_H: u8 = 0xFD;
    pub(super) const PRE_SCALE: u8 = 0xFE;
    pub(super) const TEST_MODE: u8 = 0xFF;

    pub(super) const RESTART: u8 = 0x80;
    pub(super) const EXTCLK: u8 = 0x40;
    pub(super) const AI: u8 = 0x20;
    pub(super) const SLEEP: u8 = 0x10;
    pub(super) const SUB1: u8 = 0x08;
    pub(super) const SUB2: u8 = 0x04;
    pub(super) const SUB3: u8 = 0x02;
    pub(super) const ALLCALL: u8 = 0x01;

    pub(super) const INVRT: u8 = 0x10;
    pub(super) const OCH: u8 = 0x08;

    /// Bit 4 of LEDn_ON_H / LEDn_OFF_H.
    pub(super) const FULL: u8 = 0x10;
}

/// The general-call address; data byte 0x06 after it is the software reset.
const GENERAL_CALL: u8 = 0x00;
const SWRST: u8 = 0x06;
/// The oscillator needs this long after SLEEP is cleared before RESTART may be set.
const OSCILLATOR_SETTLE_NS: u64 = 500_000;
const OSCILLATOR_HZ: f64 = 25_000_000.0;

/// Something a host did that the datasheet forbids or that the chip ignores.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Violation {
    /// PRE_SCALE written while awake: ignored by the chip.
    PrescaleWhileAwake {
        /// The value written.
        value: u8,
    },
    /// RESTART set less than 500 µs after SLEEP was cleared: ignored.
    RestartTooSoon {
        /// How long after the wake-up.
        after_ns: u64,
    },
    /// A write to a reserved register (0x46–0xF9) or TestMode (0xFF): ignored.
    Reserved {
        /// The register.
        register: u8,
    },
}

/// An emulated PCA9685 on a Motor HAT, with a rotor model on each stepper port.
#[derive(Debug)]
pub struct Pca9685Emulator {
    address: u8,
    regs: [u8; 256],
    pointer: u8,
    now_ns: u64,
    /// When SLEEP was last cleared; `None` while asleep.
    awake_since_ns: Option<u64>,
    restart_pending: bool,
    violations: Vec<Violation>,
    /// Port 1 (channels 8–13), port 2 (channels 2–7).
    turntables: [Turntable; 2],
}

impl Pca9685Emulator {
    /// A chip at `address` in its power-on state, both ports with `rotor` motors at rest.
    pub fn new(address: u8, rotor: RotorConfig) -> Self {
        let mut emulator = Self {
            address,
            regs: [0; 256],
            pointer: 0,
            now_ns: 0,
            awake_since_ns: None,
            restart_pending: false,
            violations: Vec::new(),
            turntables: [Turntable::new(rotor.clone()), Turntable::new(rotor)],
        };
        emulator.reset();
        emulator
    }

    /// The Motor HAT at its default address 0x60 with 200-step motors.
    pub fn motor_hat() -> Self {
        Self::new(0x60, RotorConfig::default())
    }

    /// Sets the simulated time in nanoseconds (an earlier time than the current one is
    /// ignored). On an [`crate::i2c::I2cBus`] with a clock the bus does this itself.
    pub fn set_time_ns(&mut self, now_ns: u64) {
        self.now_ns = self.now_ns.max(now_ns);
    }

    /// The shared rotor handle of a port.
    pub fn turntable(&self, port: Port) -> Turntable {
        self.turntables[port_index(port)].clone()
    }

    /// A port's shaft angle once any move in progress has finished, degrees from power-up.
    pub fn rotor_angle_deg(&self, port: Port) -> f64 {
        self.turntables[port_index(port)].angle_deg()
    }

    /// Coil changes the port's rotor followed.
    pub fn steps_taken(&self, port: Port) -> u64 {
        self.turntables[port_index(port)].counters().steps_taken
    }

    /// Coil changes the port's rotor did not follow (too fast or skipped phases).
    pub fn steps_lost(&self, port: Port) -> u64 {
        self.turntables[port_index(port)].counters().steps_lost
    }

    /// A register as the host would read it (MODE1 with the RESTART bit; write-only and
    /// reserved registers read 0).
    pub fn register(&self, register: u8) -> u8 {
        match register {
            regs::MODE1 => {
                self.regs[0]
                    | if self.restart_pending {
                        regs::RESTART
                    } else {
                        0
                    }
            }
            regs::ALL_LED_ON_L..=regs::ALL_LED_OFF_H | regs::TEST_MODE => 0,
            r if r > regs::LED15_OFF_H && r < regs::ALL_LED_ON_L => 0,
            r => self.regs[usize::from(r)],
        }
    }

    /// Whether MODE1.SLEEP is set (oscillator off, outputs off).
    pub fn is_sleeping(&self) -> bool {
        self.regs[usize::from(regs::MODE1)] & regs::SLEEP != 0
    }

    /// The PWM frequency set by PRE_SCALE: 25 MHz / (4096 × (PRE_SCALE + 1)).
    pub fn pwm_frequency_hz(&self) -> f64 {
        OSCILLATOR_HZ / (4096.0 * (f64::from(self.regs[usize::from(regs::PRE_SCALE)]) + 1.0))
    }

    /// The duty cycle a channel (0..=15) outputs now, in [0, 1]: 0 while asleep, full off
    /// before full on, then ((OFF − ON) mod 4096) / 4096, inverted by MODE2.INVRT.
    pub fn channel_duty(&self, channel: u8) -> f64 {
        if channel > 15 || self.is_sleeping() {
            return 0.0;
        }
        let base = usize::from(regs::LED0_ON_L) + 4 * usize::from(channel);
        let r = |i: usize| u16::from(self.regs[base + i]);
        let duty = if r(3) & u16::from(regs::FULL) != 0 {
            0.0
        } else if r(1) & u16::from(regs::FULL) != 0 {
            1.0
        } else {
            let on = r(0) | ((r(1) & 0x0F) << 8);
            let off = r(2) | ((r(3) & 0x0F) << 8);
            f64::from(off.wrapping_sub(on) & 0x0FFF) / 4096.0
        };
        if self.regs[usize::from(regs::MODE2)] & regs::INVRT != 0 {
            1.0 - duty
        } else {
            duty
        }
    }

    /// Forbidden or ignored host actions seen so far.
    pub fn violations(&self) -> &[Violation] {
        &self.violations
    }

    /// Power-on values of every register (the rotors keep their position).
    fn reset(&mut self) {
        self.regs = [0; 256];
        self.regs[usize::from(regs::MODE1)] = regs::SLEEP | regs::ALLCALL;
        self.regs[usize::from(regs::MODE2)] = 0x04;
        self.regs[usize::from(regs::SUBADR1)] = 0xE2;
        self.regs[usize::from(regs::SUBADR2)] = 0xE4;
        self.regs[usize::from(regs::SUBADR3)] = 0xE8;
        self.regs[usize::from(regs::ALLCALLADR)] = 0xE0;
        for channel in 0..16 {
            self.regs[usize::from(regs::LED0_ON_L) + 4 * channel + 3] = regs::FULL;
        }
        self.regs[usize::from(regs::PRE_SCALE)] = 0x1E;
        self.pointer = 0;
        self.awake_since_ns = None;
        self.restart_pending = false;
        self.update_outputs();
    }

    fn auto_increment(&self) -> bool {
        self.regs[usize::from(regs::MODE1)] & regs::AI != 0
    }

    /// The register after `r` in an auto-increment burst: LED15_OFF_H and 0xFF roll over to
    /// MODE1.
    fn next_register(r: u8) -> u8 {
        match r {
            regs::LED15_OFF_H | 0xFF => regs::MODE1,
            r => r + 1,
        }
    }

    /// One data byte written to `register`. Returns whether a PWM register changed.
    fn write_register(&mut self, register: u8, value: u8) -> bool {
        match register {
            regs::MODE1 => {
                self.write_mode1(value);
                false
            }
            regs::MODE2 => {
                self.regs[usize::from(regs::MODE2)] = value & 0x1F;
                false
            }
            regs::SUBADR1..=regs::ALLCALLADR => {
                self.regs[usize::from(register)] = value;
                false
            }
            regs::LED0_ON_L..=regs::LED15_OFF_H => {
                self.regs[usize::from(register)] = value;
                true
            }
            regs::ALL_LED_ON_L..=regs::ALL_LED_OFF_H => {
                let k = usize::from(register - regs::ALL_LED_ON_L);
                for channel in 0..16 {
                    self.regs[usize::from(regs::LED0_ON_L) + 4 * channel + k] = value;
                }
                true
            }
            regs::PRE_SCALE => {
                if self.is_sleeping() {
                    self.regs[usize::from(regs::PRE_SCALE)] = value.max(3);
                } else {
                    self.violations
                        .push(Violation::PrescaleWhileAwake { value });
                }
                false
            }
            register => {
                self.violations.push(Violation::Reserved { register });
                false
            }
        }
    }

    fn write_mode1(&mut self, value: u8) {
        let old = self.regs[usize::from(regs::MODE1)];
        let was_sleeping = old & regs::SLEEP != 0;
        let sleeping = value & regs::SLEEP != 0;
        if !was_sleeping && sleeping {
            // PWM was running: the chip remembers to restart it.
            self.restart_pending = true;
            self.awake_since_ns = None;
        } else if was_sleeping && !sleeping {
            self.awake_since_ns = Some(self.now_ns);
        }
        if value & regs::RESTART != 0
            && !sleeping
            && self.restart_pending
            && let Some(since) = self.awake_since_ns
        {
            let after_ns = self.now_ns.saturating_sub(since);
            if after_ns >= OSCILLATOR_SETTLE_NS {
                self.restart_pending = false;
            } else {
                self.violations.push(Violation::RestartTooSoon { after_ns });
            }
        }
        // EXTCLK is sticky until reset; RESTART is reported from `restart_pending`.
        self.regs[usize::from(regs::MODE1)] = (value & !regs::RESTART) | (old & regs::EXTCLK);
        self.update_outputs();
    }

    /// Decodes both ports' coil currents and hands them to the rotors.
    fn update_outputs(&mut self) {
        for (index, first) in [(0usize, 8u8), (1, 2)] {
            let d = |i: u8| self.channel_duty(first + i);
            // Channel order from the port's first channel: PWMA, AIN2, AIN1, BIN1, BIN2, PWMB.
            let current_a = d(0) * (d(2) - d(1));
            let current_b = d(5) * (d(3) - d(4));
            let field = if current_a.hypot(current_b) < 1e-9 {
                None
            } else {
                // θe = atan2(I_B, I_A); forward (AIN2 → BIN1 → AIN1 → BIN2) is −θe.
                Some((-current_b.atan2(current_a).to_degrees()).rem_euclid(360.0))
            };
            self.turntables[index].drive(self.now_ns, field);
        }
    }

    fn is_own_address(&self, address: u8) -> bool {
        let mode1 = self.regs[usize::from(regs::MODE1)];
        let matches =
            |bit: u8, reg: u8| mode1 & bit != 0 && address == self.regs[usize::from(reg)] >> 1;
        address == self.address
            || matches(regs::ALLCALL, regs::ALLCALLADR)
            || matches(regs::SUB1, regs::SUBADR1)
            || matches(regs::SUB2, regs::SUBADR2)
            || matches(regs::SUB3, regs::SUBADR3)
    }
}

fn port_index(port: Port) -> usize {
    match port {
        Port::One => 0,
        Port::Two => 1,
    }
}

impl I2cDevice for Pca9685Emulator {
    fn address(&self) -> u8 {
        self.address
    }

    fn responds_to(&self, address: u8) -> bool {
        address == GENERAL_CALL || self.is_own_address(address)
    }

    fn write(&mut self, address: u8, bytes: &[u8]) -> Result<(), Nack> {
        if address == GENERAL_CALL {
            return match bytes {
                [] => Ok(()),
                [SWRST] => {
                    self.reset();
                    Ok(())
                }
                _ => Err(Nack),
            };
        }
        let Some((&pointer, data)) = bytes.split_first() else {
            return Ok(());
        };
        self.pointer = pointer;
        let mut pwm_written = false;
        for &value in data {
            let changed = self.write_register(self.pointer, value);
            pwm_written |= changed;
            if changed && self.regs[usize::from(regs::MODE2)] & regs::OCH != 0 {
                self.update_outputs();
            }
            if self.auto_increment() {
                self.pointer = Self::next_register(self.pointer);
            }
        }
        if pwm_written {
            // OCH = 0: outputs change on STOP, which also clears a pending restart.
            if self.regs[usize::from(regs::MODE2)] & regs::OCH == 0 {
                self.restart_pending = false;
            }
            self.update_outputs();
        }
        Ok(())
    }

    fn read(&mut self, address: u8, buf: &mut [u8]) -> Result<(), Nack> {
        if address == GENERAL_CALL {
            return Err(Nack);
        }
        for byte in buf {
            *byte = self.register(self.pointer);
            if self.auto_increment() {
                self.pointer = Self::next_register(self.pointer);
            }
        }
        Ok(())
    }

    fn set_time_ns(&mut self, now_ns: u64) {
        Pca9685Emulator::set_time_ns(self, now_ns);
    }
}

impl ErrorType for Pca9685Emulator {
    type Error = BusError;
}

impl I2c<SevenBitAddress> for Pca9685Emulator {
    fn transaction(
        &mut self,
        address: u8,
        operations: &mut [Operation<'_>],
    ) -> Result<(), Self::Error> {
        if !self.responds_to(address) {
            return Err(BusError::AddressNack(address));
        }
        run_transaction(&mut [self], address, operations)
    }
}
