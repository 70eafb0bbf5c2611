//! Register-level MPU-9250 (accel/gyro/temperature die) emulator, a pure core: bytes, time and
//! the ground truth in, register bytes out (research/hardware.md §1.3, §1.6, §1.8).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::truth::{ImuTruth, STANDARD_GRAVITY};

const SMPLRT_DIV: u8 = 0x19;
const CONFIG: u8 = 0x1A;
const GYRO_CONFIG: u8 = 0x1B;
const ACCEL_CONFIG: u8 = 0x1C;
const INT_PIN_CFG: u8 = 0x37;
const INT_STATUS: u8 = 0x3A;
const ACCEL_XOUT_H: u8 = 0x3B;
const GYRO_ZOUT_L: u8 = 0x48;
const USER_CTRL: u8 = 0x6A;
const PWR_MGMT_1: u8 = 0x6B;
const WHO_AM_I: u8 = 0x75;

const H_RESET: u8 = 0x80;
const SLEEP: u8 = 0x40;
const BYPASS_EN: u8 = 0x02;
const INT_ANYRD_2CLEAR: u8 = 0x10;
const I2C_MST_EN: u8 = 0x20;
/// USER_CTRL bits that reset something and clear themselves.
const USER_CTRL_SELF_CLEARING: u8 = 0x0F;
const RAW_DATA_RDY: u8 = 0x01;

/// How the emulated MPU-9250 differs from an ideal one.
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(default)]
pub struct MpuEmulatorConfig {
    /// 7-bit address: 0x68 (AD0 low) or 0x69.
    pub address: u8,
    /// WHO_AM_I value: 0x71 for an MPU-9250 (set 0x73 for an MPU-9255, anything else to
    /// inject a wrong chip).
    pub who_am_i: u8,
    /// Accelerometer white noise σ per axis, m/s².
    pub accel_sigma_m_s2: [f64; 3],
    /// Gyro white noise σ per axis, rad/s.
    pub gyro_sigma_rad_s: [f64; 3],
    /// Constant accelerometer bias, m/s².
    pub accel_bias_m_s2: [f64; 3],
    /// Constant gyro bias, rad/s (what the driver's start-up estimate must remove).
    pub gyro_bias_rad_s: [f64; 3],
    /// Die temperature, °C.
    pub temperature_c: f64,
    /// After H_RESET the chip NACKs its address for this long (the driver waits 100 ms).
    pub reset_busy_ns: u64,
    /// Seed of the noise generator.
    pub seed: u64,
}

impl Default for MpuEmulatorConfig {
    /// An MPU-9250 at 0x68 with datasheet-order noise (accel 300 µg/√Hz and gyro
    /// 0.01 °/s/√Hz over a ~45 Hz bandwidth), no bias, 25 °C.
    fn default() -> Self {
        Self {
            address: 0x68,
            who_am_i: 0x71,
            accel_sigma_m_s2: [0.02; 3],
            gyro_sigma_rad_s: [0.0012; 3],
            accel_bias_m_s2: [0.0; 3],
            gyro_bias_rad_s: [0.0; 3],
            temperature_c: 25.0,
            reset_busy_ns: 10_000_000,
            seed: 0x9250,
        }
    }
}

/// The MPU-9250 register file and its sampling state machine.
#[derive(Debug)]
pub struct Mpu9250Emulator {
    config: MpuEmulatorConfig,
    regs: [u8; 128],
    pointer: u8,
    /// The chip NACKs until this time (H_RESET in progress).
    busy_until_ns: u64,
    /// Start of the sampling grid: samples fall at epoch + k·period, k ≥ 1.
    epoch_ns: u64,
    /// Grid index of the sample in the data registers.
    latched: Option<u64>,
    rng: ChaCha8Rng,
}

impl Mpu9250Emulator {
    /// A chip just powered up (reset values) at time 0.
    pub fn new(config: MpuEmulatorConfig) -> Self {
        let rng = ChaCha8Rng::seed_from_u64(config.seed);
        let mut emulator = Self {
            config,
            regs: [0; 128],
            pointer: 0,
            busy_until_ns: 0,
            epoch_ns: 0,
            latched: None,
            rng,
        };
        emulator.reset_registers(0);
        emulator
    }

    /// The configured 7-bit address.
    pub fn address(&self) -> u8 {
        self.config.address
    }

    /// Fault injection: the value WHO_AM_I reads from now on.
    pub fn set_who_am_i(&mut self, value: u8) {
        self.config.who_am_i = value;
        self.regs[usize::from(WHO_AM_I)] = value;
    }

    /// Whether the chip acknowledges its address at `now_ns` (not while H_RESET runs).
    pub fn acknowledges(&self, now_ns: u64) -> bool {
        now_ns >= self.busy_until_ns
    }

    /// Whether the AK8963 is connected to the host bus: INT_PIN_CFG.BYPASS_EN = 1 and
    /// USER_CTRL.I2C_MST_EN = 0.
    pub fn bypass_enabled(&self) -> bool {
        self.reg(INT_PIN_CFG) & BYPASS_EN != 0 && self.reg(USER_CTRL) & I2C_MST_EN == 0
    }

    /// A register's current content, without side effects (for tests and inspection).
    pub fn peek(&self, reg: u8) -> u8 {
        self.reg(reg)
    }

    /// Accel/gyro output period in ns from CONFIG, SMPLRT_DIV and GYRO_CONFIG.FCHOICE_B.
    pub fn sample_period_ns(&self) -> u64 {
        if self.reg(GYRO_CONFIG) & 0x03 != 0 {
            // DLPF bypassed: 32 kHz, SMPLRT_DIV ignored.
            return 31_250;
        }
        let internal_period_ns = match self.reg(CONFIG) & 0x07 {
            0 | 7 => 125_000, // 8 kHz
            _ => 1_000_000,   // 1 kHz
        };
        internal_period_ns * (1 + u64::from(self.reg(SMPLRT_DIV)))
    }

    /// A host write transfer: register pointer, then data with auto-increment.
    pub fn write(&mut self, now_ns: u64, bytes: &[u8]) {
        let Some((&pointer, data)) = bytes.split_first() else {
            return;
        };
        self.pointer = pointer & 0x7F;
        for &value in data {
            self.write_register(now_ns, self.pointer, value);
            self.pointer = (self.pointer + 1) & 0x7F;
        }
    }

    /// A host read transfer from the register pointer, with auto-increment. The data
    /// registers hold the latest sample due at `now_ns`, so a burst never mixes two instants.
    pub fn read(&mut self, now_ns: u64, truth: &dyn ImuTruth, buf: &mut [u8]) {
        self.update(now_ns, truth);
        let any_read_clears = self.reg(INT_PIN_CFG) & INT_ANYRD_2CLEAR != 0;
        for byte in buf.iter_mut() {
            *byte = self.reg(self.pointer);
            if self.pointer == INT_STATUS || any_read_clears {
                self.regs[usize::from(INT_STATUS)] &= !RAW_DATA_RDY;
            }
            self.pointer = (self.pointer + 1) & 0x7F;
        }
    }

    fn reg(&self, reg: u8) -> u8 {
        self.regs[usize::from(reg & 0x7F)]
    }

    fn reset_registers(&mut self, now_ns: u64) {
        self.regs = [0; 128];
        self.regs[usize::from(PWR_MGMT_1)] = 0x01;
        self.regs[usize::from(WHO_AM_I)] = self.config.who_am_i;
        self.restart_sampling(now_ns);
    }

    fn restart_sampling(&mut self, now_ns: u64) {
        self.epoch_ns = now_ns;
        self.latched = None;
    }

    fn write_register(&mut self, now_ns: u64, reg: u8, value: u8) {
        match reg {
            PWR_MGMT_1 if value & H_RESET != 0 => {
                self.reset_registers(now_ns);
                self.busy_until_ns = now_ns.saturating_add(self.config.reset_busy_ns);
            }
            PWR_MGMT_1 => {
                let was_asleep = self.reg(PWR_MGMT_1) & SLEEP != 0;
                self.regs[usize::from(PWR_MGMT_1)] = value;
                if was_asleep && value & SLEEP == 0 {
                    self.restart_sampling(now_ns);
                }
            }
            // Read-only: status, data, identity.
            INT_STATUS | ACCEL_XOUT_H..=GYRO_ZOUT_L | WHO_AM_I => {}
            SMPLRT_DIV | CONFIG | GYRO_CONFIG => {
                self.regs[usize::from(reg)] = value;
                self.restart_sampling(now_ns);
            }
            USER_CTRL => self.regs[usize::from(reg)] = value & !USER_CTRL_SELF_CLEARING,
            _ => self.regs[usize::from(reg & 0x7F)] = value,
        }
    }

    /// Latches the newest sample due at `now_ns` into the data registers (unless asleep).
    fn update(&mut self, now_ns: u64, truth: &dyn ImuTruth) {
        if self.reg(PWR_MGMT_1) & SLEEP != 0 {
            return;
        }
        let period = self.sample_period_ns();
        let k = now_ns.saturating_sub(self.epoch_ns) / period;
        if k == 0 || self.latched == Some(k) {
            return;
        }
        self.latched = Some(k);
        let t_ns = self.epoch_ns + k * period;
        self.latch_sample(t_ns, truth);
        self.regs[usize::from(INT_STATUS)] |= RAW_DATA_RDY;
    }

    fn latch_sample(&mut self, t_ns: u64, truth: &dyn ImuTruth) {
        let true_imu = truth.sample(t_ns);
        let accel_lsb_per_g = 16384.0 / f64::from(1u16 << ((self.reg(ACCEL_CONFIG) >> 3) & 3));
        let gyro_lsb_per_dps = match (self.reg(GYRO_CONFIG) >> 3) & 3 {
            0 => 131.0,
            1 => 65.5,
            2 => 32.8,
            _ => 16.4,
        };
        let mut words = [0i16; 7];
        for axis in 0..3 {
            let accel = true_imu.accel_m_s2[axis]
                + self.config.accel_bias_m_s2[axis]
                + gaussian(&mut self.rng, self.config.accel_sigma_m_s2[axis]);
            words[axis] = quantise(accel / STANDARD_GRAVITY * accel_lsb_per_g);
            let gyro = true_imu.gyro_rad_s[axis]
                + self.config.gyro_bias_rad_s[axis]
                + gaussian(&mut self.rng, self.config.gyro_sigma_rad_s[axis]);
            words[4 + axis] = quantise(gyro.to_degrees() * gyro_lsb_per_dps);
        }
        words[3] = quantise((self.config.temperature_c - 21.0) * 333.87);
        for (i, word) in words.iter().enumerate() {
            let at = usize::from(ACCEL_XOUT_H) + 2 * i;
            self.regs[at..at + 2].copy_from_slice(&word.to_be_bytes());
        }
    }
}

/// Round and saturate to int16, as the ADC does (NaN reads 0).
pub(super) fn quantise(value: f64) -> i16 {
    value
        .round()
        .clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16
}

/// One zero-mean normal draw with standard deviation `sigma`; nothing is drawn (and 0 returned)
/// when σ is zero, negative or not finite.
pub(super) fn gaussian(rng: &mut ChaCha8Rng, sigma: f64) -> f64 {
    if sigma.is_finite() && sigma > 0.0 {
        let z: f64 = rng.sample(StandardNormal);
        z * sigma
    } else {
        0.0
    }
}
