//! Register-level AK8963 magnetometer emulator, a pure core (research/hardware.md §1.5, §1.7,
//! §1.8): mode state machine, fuse ROM, DRDY/DOR, read protection released by ST2, HOFL.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::mpu9250::{gaussian, quantise};
use super::truth::ImuTruth;

const WIA: u8 = 0x00;
const ST1: u8 = 0x02;
const HXL: u8 = 0x03;
const HZH: u8 = 0x08;
const ST2: u8 = 0x09;
const CNTL1: u8 = 0x0A;
const CNTL2: u8 = 0x0B;
const ASAX: u8 = 0x10;
const ASAZ: u8 = 0x12;
/// Registers 0x00..=0x12; the pointer wraps from ASAZ to WIA.
const REGISTER_COUNT: u8 = 0x13;

const DRDY: u8 = 0x01;
const DOR: u8 = 0x02;
const HOFL: u8 = 0x08;
const BITM: u8 = 0x10;
const SRST: u8 = 0x01;
const MODE_CONTINUOUS_1: u8 = 0x02;
const MODE_CONTINUOUS_2: u8 = 0x06;
const MODE_FUSE_ROM: u8 = 0x0F;

/// The measurement range: overflow when |X| + |Y| + |Z| ≥ 4912 µT.
const OVERFLOW_UT: f64 = 4912.0;

/// How the emulated AK8963 differs from an ideal one.
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(default)]
pub struct AkEmulatorConfig {
    /// Fuse-ROM sensitivity adjustment ASAX/Y/Z (real parts ≈ 0xA0..0xB5). The raw output is
    /// divided by (ASA − 128)/256 + 1 so a driver applying the adjustment gets the true field.
    pub asa: [u8; 3],
    /// White noise σ per axis, µT, in the accel/gyro (body) frame.
    pub mag_sigma_ut: [f64; 3],
    /// Hard-iron offset added to the field, µT, body frame (what the driver's calibration
    /// subtracts).
    pub hard_iron_ut: [f64; 3],
    /// Seed of the noise generator.
    pub seed: u64,
}

impl Default for AkEmulatorConfig {
    /// Typical fuse values, 0.3 µT noise, no hard iron.
    fn default() -> Self {
        Self {
            asa: [0xB0, 0xB3, 0xA6],
            mag_sigma_ut: [0.3; 3],
            hard_iron_ut: [0.0; 3],
            seed: 0x8963,
        }
    }
}

/// The AK8963 register file and measurement state machine.
#[derive(Debug)]
pub struct Ak8963Emulator {
    config: AkEmulatorConfig,
    regs: [u8; REGISTER_COUNT as usize],
    pointer: u8,
    /// Start of the measurement grid of the current continuous mode.
    epoch_ns: u64,
    /// Grid index of the last measurement (stored or skipped).
    last_measurement: Option<u64>,
    /// A data register was read and ST2 not yet: new measurements are skipped.
    protected: bool,
    /// Fault injection: this many next measurements report HOFL.
    inject_overflows: u32,
    rng: ChaCha8Rng,
}

impl Ak8963Emulator {
    /// A chip just powered up, in power-down mode.
    pub fn new(config: AkEmulatorConfig) -> Self {
        let rng = ChaCha8Rng::seed_from_u64(config.seed);
        let mut emulator = Self {
            config,
            regs: [0; REGISTER_COUNT as usize],
            pointer: 0,
            epoch_ns: 0,
            last_measurement: None,
            protected: false,
            inject_overflows: 0,
            rng,
        };
        emulator.reset();
        emulator
    }

    /// Fault injection: the next `count` measurements set ST2.HOFL (magnetic overflow).
    pub fn inject_overflows(&mut self, count: u32) {
        self.inject_overflows = count;
    }

    /// A register's current content, without side effects (ASA reads as stored).
    pub fn peek(&self, reg: u8) -> u8 {
        self.regs.get(usize::from(reg)).copied().unwrap_or(0)
    }

    /// Measurement period of the current mode, if it measures continuously.
    pub fn measurement_period_ns(&self) -> Option<u64> {
        match self.peek(CNTL1) & 0x0F {
            MODE_CONTINUOUS_1 => Some(125_000_000),
            MODE_CONTINUOUS_2 => Some(10_000_000),
            _ => None,
        }
    }

    /// A host write transfer: register pointer, then data with auto-increment.
    pub fn write(&mut self, now_ns: u64, truth: &dyn ImuTruth, bytes: &[u8]) {
        self.update(now_ns, truth);
        let Some((&pointer, data)) = bytes.split_first() else {
            return;
        };
        self.pointer = pointer % REGISTER_COUNT;
        for &value in data {
            self.write_register(now_ns, self.pointer, value);
            self.pointer = (self.pointer + 1) % REGISTER_COUNT;
        }
    }

    /// A host read transfer from the register pointer, with auto-increment.
    pub fn read(&mut self, now_ns: u64, truth: &dyn ImuTruth, buf: &mut [u8]) {
        self.update(now_ns, truth);
        let fuse_rom = self.peek(CNTL1) & 0x0F == MODE_FUSE_ROM;
        for byte in buf.iter_mut() {
            let reg = self.pointer;
            *byte = match reg {
                ASAX..=ASAZ if !fuse_rom => 0x00,
                _ => self.peek(reg),
            };
            match reg {
                HXL..=HZH => self.protected = true,
                ST2 => {
                    // End of a data read: release the protection, clear DRDY and DOR.
                    self.protected = false;
                    self.regs[usize::from(ST1)] = 0;
                }
                _ => {}
            }
            self.pointer = (self.pointer + 1) % REGISTER_COUNT;
        }
    }

    fn reset(&mut self) {
        self.regs = [0; REGISTER_COUNT as usize];
        self.regs[usize::from(WIA)] = 0x48;
        self.regs[usize::from(ASAX)..].copy_from_slice(&self.config.asa);
        self.protected = false;
        self.last_measurement = None;
    }

    fn write_register(&mut self, now_ns: u64, reg: u8, value: u8) {
        match reg {
            CNTL1 => {
                self.regs[usize::from(CNTL1)] = value & 0x1F;
                self.epoch_ns = now_ns;
                self.last_measurement = None;
                let bitm = if value & BITM != 0 { BITM } else { 0 };
                self.regs[usize::from(ST2)] = (self.peek(ST2) & !BITM) | bitm;
            }
            CNTL2 if value & SRST != 0 => self.reset(),
            // Writable control registers (ASTC, TS1/TS2, I2CDIS) are stored; the rest is
            // read-only.
            0x0C..=0x0F => self.regs[usize::from(reg)] = value,
            _ => {}
        }
    }

    /// Performs the measurements due by `now_ns` in continuous mode.
    fn update(&mut self, now_ns: u64, truth: &dyn ImuTruth) {
        let Some(period) = self.measurement_period_ns() else {
            return;
        };
        let k = now_ns.saturating_sub(self.epoch_ns) / period;
        let last = self.last_measurement.unwrap_or(0);
        if k <= last {
            return;
        }
        self.last_measurement = Some(k);
        let st1 = self.peek(ST1);
        if self.protected {
            // Data are being read: the new measurement is skipped.
            self.regs[usize::from(ST1)] = st1 | DOR;
            return;
        }
        let overrun = st1 & DRDY != 0 || k - last >= 2;
        self.regs[usize::from(ST1)] = DRDY | if overrun { DOR } else { 0 };
        self.measure(self.epoch_ns + k * period, truth);
    }

    fn measure(&mut self, t_ns: u64, truth: &dyn ImuTruth) {
        let body = truth.sample(t_ns).mag_ut;
        let mut m = [0.0; 3];
        for axis in 0..3 {
            m[axis] = body[axis]
                + self.config.hard_iron_ut[axis]
                + gaussian(&mut self.rng, self.config.mag_sigma_ut[axis]);
        }
        // Body (accel/gyro) frame to chip axes: Hx = m_y, Hy = m_x, Hz = −m_z (§1.7).
        let chip = [m[1], m[0], -m[2]];
        let sixteen_bit = self.peek(CNTL1) & BITM != 0;
        let (ut_per_lsb, limit) = if sixteen_bit {
            (0.15, 32760.0)
        } else {
            (0.6, 8190.0)
        };
        let injected = self.inject_overflows > 0;
        self.inject_overflows = self.inject_overflows.saturating_sub(1);
        let overflow = injected || chip.iter().map(|h| h.abs()).sum::<f64>() >= OVERFLOW_UT;
        for (axis, h) in chip.iter().enumerate() {
            let asa = (f64::from(self.config.asa[axis]) - 128.0) / 256.0 + 1.0;
            let raw = quantise((h / (asa * ut_per_lsb)).clamp(-limit, limit));
            let at = usize::from(HXL) + 2 * axis;
            self.regs[at..at + 2].copy_from_slice(&raw.to_le_bytes());
        }
        let bitm = self.peek(ST2) & BITM;
        self.regs[usize::from(ST2)] = bitm | if overflow { HOFL } else { 0 };
    }
}
