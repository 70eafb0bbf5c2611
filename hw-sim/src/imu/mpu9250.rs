//! Register-level MPU-9250 (accel/gyro/temperature die) emulator, a pure core: bytes, time and
//! the ground truth in, register bytes out (research/hardware.md §1.3, §1.6, §1.8).
//!
//! The chip samples on its own grid (SMPLRT_DIV, CONFIG, GYRO_CONFIG). Idle, only the newest
//! sample matters and it is latched into the data registers when the host reads. Once the FIFO
//! (USER_CTRL.FIFO_EN with FIFO_EN ≠ 0) or the I2C master (USER_CTRL.I2C_MST_EN) runs, every
//! sample instant is played in order before each host transfer: the data registers latch the
//! sample, the master's SLV0 runs its transfer on the auxiliary bus (the AK8963, through
//! [`AuxBus`]) into EXT_SENS_DATA_00.., and the FIFO appends the enabled registers in register
//! order (accel, temperature, gyro x/y/z, SLV0's bytes). With I2C_MST_CTRL.WAIT_FOR_ES the
//! record waits for that sample's external data; without it the record holds the previous
//! instant's. The FIFO ([`Fifo`]) overflows as the chip's does (oldest bytes dropped, or with
//! CONFIG.FIFO_MODE the new ones) and sets INT_STATUS.FIFO_OFLOW_INT; FIFO_COUNTH/L read its
//! byte count big-endian, FIFO_R_W reads pop it without advancing the register pointer (so a
//! burst from 0x74 reads the FIFO). Not modelled: SLV1..4, SLV0's BYTE_SW/REG_DIS/GRP and
//! I2C_SLV0_DLY_EN (SLV0 runs at every sample), the DMP. A host that does not read for long
//! has at most the last [`MAX_CATCH_UP`] instants played (more than fill the FIFO).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::fifo::Fifo;
use super::truth::{ImuTruth, STANDARD_GRAVITY};
use crate::i2c::Nack;

const SMPLRT_DIV: u8 = 0x19;
const CONFIG: u8 = 0x1A;
const GYRO_CONFIG: u8 = 0x1B;
const ACCEL_CONFIG: u8 = 0x1C;
const FIFO_EN: u8 = 0x23;
const I2C_MST_CTRL: u8 = 0x24;
const I2C_SLV0_ADDR: u8 = 0x25;
const I2C_SLV0_REG: u8 = 0x26;
const I2C_SLV0_CTRL: u8 = 0x27;
const I2C_MST_STATUS: u8 = 0x36;
const INT_PIN_CFG: u8 = 0x37;
const INT_STATUS: u8 = 0x3A;
const ACCEL_XOUT_H: u8 = 0x3B;
const TEMP_OUT_H: u8 = 0x41;
const GYRO_XOUT_H: u8 = 0x43;
const GYRO_ZOUT_L: u8 = 0x48;
const EXT_SENS_DATA_00: u8 = 0x49;
const EXT_SENS_DATA_23: u8 = 0x60;
const I2C_SLV0_DO: u8 = 0x63;
const USER_CTRL: u8 = 0x6A;
const PWR_MGMT_1: u8 = 0x6B;
const FIFO_COUNTH: u8 = 0x72;
const FIFO_COUNTL: u8 = 0x73;
const FIFO_R_W: u8 = 0x74;
const WHO_AM_I: u8 = 0x75;

const H_RESET: u8 = 0x80;
const SLEEP: u8 = 0x40;
const BYPASS_EN: u8 = 0x02;
const INT_ANYRD_2CLEAR: u8 = 0x10;
/// CONFIG.FIFO_MODE: a full FIFO keeps its bytes and drops new ones.
const FIFO_MODE: u8 = 0x40;
/// USER_CTRL.FIFO_EN: records are written to the FIFO.
const USER_FIFO_EN: u8 = 0x40;
const I2C_MST_EN: u8 = 0x20;
/// USER_CTRL.FIFO_RST: empties the FIFO (self-clearing).
const FIFO_RST: u8 = 0x04;
/// USER_CTRL bits that reset something and clear themselves.
const USER_CTRL_SELF_CLEARING: u8 = 0x0F;
/// INT_STATUS bits.
const RAW_DATA_RDY: u8 = 0x01;
const FIFO_OFLOW_INT: u8 = 0x10;
/// FIFO_EN bits, in the order their registers land in a record.
const FIFO_TEMP: u8 = 0x80;
const FIFO_GYRO_X: u8 = 0x40;
const FIFO_GYRO_Y: u8 = 0x20;
const FIFO_GYRO_Z: u8 = 0x10;
const FIFO_ACCEL: u8 = 0x08;
const FIFO_SLV0: u8 = 0x01;
/// I2C_MST_CTRL.WAIT_FOR_ES: a sample waits for its external sensor data.
const WAIT_FOR_ES: u8 = 0x40;
/// I2C_SLVx_ADDR bit 7: the slave transfer is a read.
const SLV_READ: u8 = 0x80;
/// I2C_SLVx_CTRL bit 7: the slave is enabled; [3:0] its length.
const SLV_EN: u8 = 0x80;
const SLV_LEN: u8 = 0x0F;
/// I2C_MST_STATUS.I2C_SLV0_NACK.
const SLV0_NACK: u8 = 0x01;

/// Sample instants played at most per host transfer (see the module doc): more than any record
/// layout needs to fill the 512-byte FIFO.
pub const MAX_CATCH_UP: u64 = 1024;

/// The MPU-9250's auxiliary I2C bus as its I2C master sees it (the AK8963 sits on it).
pub trait AuxBus {
    /// Reads `buf.len()` bytes from register `reg` of `address`, at emulated time `t_ns`.
    fn read(&mut self, t_ns: u64, address: u8, reg: u8, buf: &mut [u8]) -> Result<(), Nack>;
    /// Writes `value` to register `reg` of `address`, at emulated time `t_ns`.
    fn write(&mut self, t_ns: u64, address: u8, reg: u8, value: u8) -> Result<(), Nack>;
}

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
    /// Grid index of the last sample instant played (0: none yet).
    played: u64,
    fifo: Fifo,
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
            played: 0,
            fifo: Fifo::default(),
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

    /// A register's current content, without side effects (for tests and inspection; FIFO_R_W
    /// is not popped, FIFO_COUNTH/L give the count).
    pub fn peek(&self, reg: u8) -> u8 {
        let [high, low] = (self.fifo.len() as u16).to_be_bytes();
        match reg & 0x7F {
            FIFO_COUNTH => high,
            FIFO_COUNTL => low,
            other => self.reg(other),
        }
    }

    /// The FIFO's bytes, oldest first, without popping them (for tests and inspection).
    pub fn fifo_contents(&self) -> Vec<u8> {
        self.fifo.contents()
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

    /// A host write transfer: register pointer, then data with auto-increment (a write to
    /// FIFO_R_W pushes a byte and keeps the pointer there). The sample instants due by `now_ns`
    /// are played first, with the registers as they were.
    pub fn write(&mut self, now_ns: u64, truth: &dyn ImuTruth, aux: &mut dyn AuxBus, bytes: &[u8]) {
        self.update(now_ns, truth, aux);
        let Some((&pointer, data)) = bytes.split_first() else {
            return;
        };
        self.pointer = pointer & 0x7F;
        for &value in data {
            self.write_register(now_ns, self.pointer, value);
            if self.pointer != FIFO_R_W {
                self.pointer = (self.pointer + 1) & 0x7F;
            }
        }
    }

    /// A host read transfer from the register pointer, with auto-increment, except at FIFO_R_W
    /// where every byte pops the FIFO. The data registers hold the latest sample due at
    /// `now_ns`, so a burst never mixes two instants.
    pub fn read(
        &mut self,
        now_ns: u64,
        truth: &dyn ImuTruth,
        aux: &mut dyn AuxBus,
        buf: &mut [u8],
    ) {
        self.update(now_ns, truth, aux);
        let any_read_clears = self.reg(INT_PIN_CFG) & INT_ANYRD_2CLEAR != 0;
        let [count_high, count_low] = (self.fifo.len() as u16).to_be_bytes();
        for byte in buf.iter_mut() {
            *byte = match self.pointer {
                FIFO_COUNTH => count_high,
                FIFO_COUNTL => count_low,
                FIFO_R_W => self.fifo.pop(),
                reg => self.reg(reg),
            };
            if self.pointer == INT_STATUS || any_read_clears {
                self.regs[usize::from(INT_STATUS)] &= !(RAW_DATA_RDY | FIFO_OFLOW_INT);
            }
            if self.pointer != FIFO_R_W {
                self.pointer = (self.pointer + 1) & 0x7F;
            }
        }
    }

    fn reg(&self, reg: u8) -> u8 {
        self.regs[usize::from(reg & 0x7F)]
    }

    fn reset_registers(&mut self, now_ns: u64) {
        self.regs = [0; 128];
        self.regs[usize::from(PWR_MGMT_1)] = 0x01;
        self.regs[usize::from(WHO_AM_I)] = self.config.who_am_i;
        self.fifo.reset();
        self.restart_sampling(now_ns);
    }

    fn restart_sampling(&mut self, now_ns: u64) {
        self.epoch_ns = now_ns;
        self.played = 0;
    }

    /// Records go to the FIFO: USER_CTRL.FIFO_EN and at least one FIFO_EN source.
    fn fifo_writing(&self) -> bool {
        self.reg(USER_CTRL) & USER_FIFO_EN != 0 && self.reg(FIFO_EN) != 0
    }

    fn master_enabled(&self) -> bool {
        self.reg(USER_CTRL) & I2C_MST_EN != 0
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
            // Read-only: status, data, external sensor data, FIFO count, identity.
            I2C_MST_STATUS
            | INT_STATUS
            | ACCEL_XOUT_H..=GYRO_ZOUT_L
            | EXT_SENS_DATA_00..=EXT_SENS_DATA_23
            | FIFO_COUNTH
            | FIFO_COUNTL
            | WHO_AM_I => {}
            SMPLRT_DIV | CONFIG | GYRO_CONFIG => {
                self.regs[usize::from(reg)] = value;
                self.restart_sampling(now_ns);
            }
            USER_CTRL => {
                if value & FIFO_RST != 0 {
                    self.fifo.reset();
                }
                self.regs[usize::from(reg)] = value & !USER_CTRL_SELF_CLEARING;
            }
            FIFO_R_W => self.push_fifo(&[value]),
            _ => self.regs[usize::from(reg & 0x7F)] = value,
        }
    }

    /// Plays the sample instants due by `now_ns` (unless asleep): every one while the FIFO or
    /// the I2C master runs, else only the newest, latched into the data registers.
    fn update(&mut self, now_ns: u64, truth: &dyn ImuTruth, aux: &mut dyn AuxBus) {
        if self.reg(PWR_MGMT_1) & SLEEP != 0 {
            return;
        }
        let period = self.sample_period_ns();
        let due = now_ns.saturating_sub(self.epoch_ns) / period;
        if due <= self.played {
            return;
        }
        if self.fifo_writing() || self.master_enabled() {
            let first = self.played + 1;
            let keep_old = self.reg(CONFIG) & FIFO_MODE != 0;
            let played = if due - first < MAX_CATCH_UP {
                first..=due
            } else if keep_old {
                // The first instants fill the FIFO and it keeps them; the newest still latches.
                first..=first + MAX_CATCH_UP - 1
            } else {
                due + 1 - MAX_CATCH_UP..=due
            };
            let last = *played.end();
            for k in played {
                self.play_instant(self.epoch_ns + k * period, truth, aux);
            }
            if last != due {
                self.latch_sample(self.epoch_ns + due * period, truth);
            }
        } else {
            self.latch_sample(self.epoch_ns + due * period, truth);
        }
        self.played = due;
        self.regs[usize::from(INT_STATUS)] |= RAW_DATA_RDY;
    }

    /// One sample instant with the FIFO or the master running: latch, the SLV0 transfer, the
    /// FIFO record (after the transfer with WAIT_FOR_ES, before it otherwise).
    fn play_instant(&mut self, t_ns: u64, truth: &dyn ImuTruth, aux: &mut dyn AuxBus) {
        self.latch_sample(t_ns, truth);
        let wait_for_external = self.reg(I2C_MST_CTRL) & WAIT_FOR_ES != 0;
        if wait_for_external {
            self.run_slave0(t_ns, aux);
        }
        if self.fifo_writing() {
            let record = self.fifo_record();
            self.push_fifo(&record);
        }
        if !wait_for_external {
            self.run_slave0(t_ns, aux);
        }
    }

    /// SLV0's transfer on the auxiliary bus, if the master and SLV0 are enabled: a read of
    /// LENGTH bytes from SLV0_REG into EXT_SENS_DATA_00.., or a write of SLV0_DO. A NACK sets
    /// I2C_MST_STATUS.I2C_SLV0_NACK and leaves EXT_SENS_DATA as it was.
    fn run_slave0(&mut self, t_ns: u64, aux: &mut dyn AuxBus) {
        let ctrl = self.reg(I2C_SLV0_CTRL);
        if !self.master_enabled() || ctrl & SLV_EN == 0 {
            return;
        }
        let address = self.reg(I2C_SLV0_ADDR);
        let reg = self.reg(I2C_SLV0_REG);
        let result = if address & SLV_READ != 0 {
            let len = usize::from(ctrl & SLV_LEN);
            let mut buf = [0u8; 16];
            let result = aux.read(t_ns, address & 0x7F, reg, &mut buf[..len]);
            if result.is_ok() {
                let at = usize::from(EXT_SENS_DATA_00);
                self.regs[at..at + len].copy_from_slice(&buf[..len]);
            }
            result
        } else {
            aux.write(t_ns, address & 0x7F, reg, self.reg(I2C_SLV0_DO))
        };
        let status = &mut self.regs[usize::from(I2C_MST_STATUS)];
        match result {
            Ok(()) => *status &= !SLV0_NACK,
            Err(Nack) => *status |= SLV0_NACK,
        }
    }

    /// The enabled FIFO_EN sources in register order: accel, temperature, gyro x, y, z, then
    /// SLV0's LENGTH bytes of EXT_SENS_DATA.
    fn fifo_record(&self) -> Vec<u8> {
        let enabled = self.reg(FIFO_EN);
        let sources = [
            (FIFO_ACCEL, ACCEL_XOUT_H, 6),
            (FIFO_TEMP, TEMP_OUT_H, 2),
            (FIFO_GYRO_X, GYRO_XOUT_H, 2),
            (FIFO_GYRO_Y, GYRO_XOUT_H + 2, 2),
            (FIFO_GYRO_Z, GYRO_XOUT_H + 4, 2),
            (
                FIFO_SLV0,
                EXT_SENS_DATA_00,
                usize::from(self.reg(I2C_SLV0_CTRL) & SLV_LEN),
            ),
        ];
        let mut record = Vec::with_capacity(30);
        for (bit, first, len) in sources {
            if enabled & bit != 0 {
                let at = usize::from(first);
                record.extend_from_slice(&self.regs[at..at + len]);
            }
        }
        record
    }

    fn push_fifo(&mut self, bytes: &[u8]) {
        let keep_old = self.reg(CONFIG) & FIFO_MODE != 0;
        if self.fifo.push(bytes, keep_old) {
            self.regs[usize::from(INT_STATUS)] |= FIFO_OFLOW_INT;
        }
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
