//! MPU-9250 + AK8963 9-axis IMU driver, generic over [`embedded_hal::i2c::I2c`].
//!
//! The MPU-9250 (accel, gyro, temperature) sits at 0x68 or 0x69; its AK8963 magnetometer is put
//! on the host bus at 0x0C by the MPU's bypass mode, so the driver talks to two plain I2C
//! devices (research/hardware.md §1). The driver owns the bus (give it a shared-bus handle from
//! `embedded-hal-bus` to share it with the stepper HAT) and returns it from
//! [`Mpu9250::destroy`]. It does no timing of its own: waits in the init sequence go through
//! the [`DelayNs`] passed in, and the caller polls [`Mpu9250::read`] at the sample rate.
//!
//! - [`Mpu9250::init`]: reset and init sequence (§1.4), AK8963 fuse-ROM sensitivity adjustment,
//!   continuous mode, then the gyro bias estimated at rest.
//! - FIFO mode ([`ReadMode::Fifo`], the default), what a real driver does to spare the bus: after
//!   the init the AK8963 moves behind the MPU's own I2C master, whose SLV0 reads its ST1..ST2
//!   block every sample period; every sample appends accel, temperature, gyro and that block
//!   (22 bytes, [`FifoLayout`]) to the 512-byte FIFO. [`Mpu9250::fifo_count`] and
//!   [`Mpu9250::read_fifo`] then fetch a whole batch in two transactions (about 27 a second at
//!   200 Hz instead of 300); [`FifoClock`] gives each sample its measurement time. Only whole
//!   records are read, so the FIFO stays aligned; an overflow (the chip then drops the oldest
//!   *bytes*, so the content no longer starts at a record), a data read that failed (bytes may
//!   have been popped) or magnetometer status bytes that cannot be ST1/ST2 reset the FIFO and
//!   discard its content: misaligned bytes are never decoded as samples.
//! - [`Mpu9250::read`]: the newest sample from the data registers, in either mode. Register mode
//!   ([`ReadMode::Registers`]): one 14-byte burst (accel, temperature, gyro) and, when a new
//!   field is due, one 8-byte AK8963 read in bypass (ST1, data, ST2): the field comes at 100 Hz
//!   (or 8 Hz), so at 200 Hz every other read skips the AK8963, 1.5 transactions a sample. FIFO
//!   mode: one 22-byte burst of the data registers and EXT_SENS_DATA_00..07 (the master's latest
//!   copy of the AK8963 block), for probes and tests; a field shows at every read until the
//!   master's next copy, so polling faster than the sample rate repeats fields.
//! - Readings are converted to SI units in the accel/gyro frame and calibrated. Every bus
//!   transaction but a FIFO data read (which must not be repeated) is retried
//!   [`ImuConfig::retries`] times before an [`Error`] that names the chip and the address.

mod config;
mod error;
mod fifo;
mod registers;

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;

pub use config::{
    AccelDlpf, AccelRange, ConfigError, GyroDlpf, GyroRange, ImuConfig, MagMode, ReadMode,
};
pub use error::{Chip, Error};
pub use fifo::{
    FIFO_CAPACITY, FifoClock, FifoLayout, MAG_RECORD_LEN, MPU_RECORD_LEN, fifo_read_interval_ns,
};
use registers::{ak, mpu};

/// AK8963 bus address (visible only in bypass mode).
pub const AK8963_ADDRESS: u8 = 0x0C;
/// Standard gravity, for converting g to m/s².
pub const STANDARD_GRAVITY: f32 = 9.80665;
/// AK8963 sensitivity in 16-bit output mode, µT per LSB.
pub const MAG_UT_PER_LSB: f32 = 0.15;

/// Waits of the init sequence (research/hardware.md §1.4).
const RESET_WAIT_MS: u32 = 100;
const SETTLE_WAIT_MS: u32 = 10;
const AK_SOFT_RESET_WAIT_MS: u32 = 1;

/// One converted IMU sample in the accel/gyro frame (z out of the chip top).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuReading {
    /// Specific force, m/s²; +9.81 on the upward axis at rest.
    pub accel_m_s2: [f32; 3],
    /// Angular rate, rad/s, with the start-up bias removed.
    pub gyro_rad_s: [f32; 3],
    /// Magnetic field, µT, aligned to the accel/gyro frame and calibrated; `None` when the
    /// AK8963 had no new sample, overflowed (sample dropped) or is not used.
    pub mag_ut: Option<[f32; 3]>,
    /// Die temperature, °C.
    pub temp_c: f32,
}

/// What the init sequence found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChipIds {
    /// MPU WHO_AM_I (0x71 or 0x73; 0x70 when the magnetometer is off).
    pub who_am_i: u8,
    /// AK8963 WIA (0x48), `None` when the magnetometer is off.
    pub wia: Option<u8>,
    /// AK8963 fuse-ROM sensitivity adjustment ASAX/Y/Z, `None` when the magnetometer is off.
    pub asa: Option<[u8; 3]>,
}

/// Counters kept by the driver.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ImuStats {
    /// I2C transactions attempted (including retries): divide by time for the bus load.
    pub transactions: u64,
    /// Transactions that failed and were tried again.
    pub retries: u64,
    /// Accel/gyro samples returned by [`Mpu9250::read`].
    pub samples: u64,
    /// Magnetometer samples returned.
    pub mag_samples: u64,
    /// Magnetometer samples dropped because ST2.HOFL (overflow) was set.
    pub mag_overflows: u64,
    /// Reads where ST1.DOR said the AK8963 skipped at least one sample (polled too slowly).
    pub mag_overruns: u64,
    /// FIFO overflows found (samples lost; the FIFO was reset).
    pub fifo_overflows: u64,
    /// FIFO contents discarded because they could not be trusted to start at a record (a
    /// failed data read, impossible magnetometer status bytes); the FIFO was reset.
    pub fifo_discards: u64,
}

/// What one [`Mpu9250::read_fifo`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FifoRead {
    /// Whole records decoded and appended (0 when no sample was due). `restarted`: the FIFO
    /// was reset since the previous batch, so these samples do not follow on from earlier ones
    /// ([`FifoClock::restart`]).
    Samples {
        /// Samples appended.
        samples: usize,
        /// A new stream starts with them.
        restarted: bool,
    },
    /// The FIFO overflowed (its count past the last whole record): the content was discarded
    /// and the FIFO reset; samples were lost.
    Overflow {
        /// The byte count read.
        count: u16,
    },
    /// Magnetometer status bytes where they cannot be (a record boundary lost): the content was
    /// discarded and the FIFO reset.
    Misaligned,
}

/// The FIFO path's state, once [`Mpu9250::init`] started it.
#[derive(Debug, Clone, Copy)]
struct FifoState {
    layout: FifoLayout,
    /// The FIFO must be reset before its content is trusted (a data read failed).
    needs_reset: bool,
    /// It was reset since the last batch handed out.
    restarted: bool,
}

/// What one AK8963 read found.
enum MagRead {
    /// No new field yet (ST1.DRDY clear).
    NotReady,
    /// A new field that overflowed (ST2.HOFL): dropped.
    Overflow,
    /// A new field, µT in the accel/gyro frame, calibrated.
    Field([f32; 3]),
}

/// MPU-9250 + AK8963 driver owning the bus `I2C`.
#[derive(Debug)]
pub struct Mpu9250<I2C> {
    i2c: I2C,
    config: ImuConfig,
    /// Per-chip-axis ASA factor (ASA − 128)/256 + 1, set by `init`.
    asa_factor: [f32; 3],
    gyro_bias_rad_s: [f32; 3],
    stats: ImuStats,
    /// Reads of [`Mpu9250::read`] to skip the AK8963 before its next field is due.
    mag_skip: u32,
    /// Set by `init` in FIFO mode.
    fifo: Option<FifoState>,
    /// Scratch buffer of FIFO reads.
    fifo_bytes: Vec<u8>,
}

impl<I2C: I2c> Mpu9250<I2C> {
    /// Wraps the bus; no bus access until [`Mpu9250::init`].
    pub fn new(i2c: I2C, config: ImuConfig) -> Self {
        Self {
            i2c,
            config,
            asa_factor: [1.0; 3],
            gyro_bias_rad_s: [0.0; 3],
            stats: ImuStats::default(),
            mag_skip: 0,
            fifo: None,
            fifo_bytes: Vec::new(),
        }
    }

    /// Gives the bus back.
    pub fn destroy(self) -> I2C {
        self.i2c
    }

    /// The configuration in use.
    pub fn config(&self) -> &ImuConfig {
        &self.config
    }

    /// The driver's counters.
    pub fn stats(&self) -> ImuStats {
        self.stats
    }

    /// The gyro bias subtracted from every reading, rad/s.
    pub fn gyro_bias(&self) -> [f32; 3] {
        self.gyro_bias_rad_s
    }

    /// Replaces the gyro bias (e.g. one saved from an earlier calibration).
    pub fn set_gyro_bias(&mut self, bias_rad_s: [f32; 3]) {
        self.gyro_bias_rad_s = bias_rad_s;
    }

    /// Runs the reset and init sequence of research/hardware.md §1.4, then takes the saved
    /// [`ImuConfig::gyro_bias_rad_s`] or (if [`ImuConfig::gyro_bias_samples`] > 0) estimates the
    /// gyro bias; the device must be at rest.
    /// In FIFO mode it then hands the AK8963 to the I2C master and starts the FIFO.
    pub fn init<D: DelayNs>(&mut self, delay: &mut D) -> Result<ChipIds, Error<I2C::Error>> {
        self.config.validate().map_err(Error::Config)?;
        self.fifo = None;
        let mag_on = self.config.mag_mode != MagMode::Off;

        // 1. Identity.
        let who_am_i = self.read_reg(Chip::Mpu9250, mpu::WHO_AM_I)?;
        let accepted = matches!(who_am_i, mpu::ID_MPU9250 | mpu::ID_MPU9255)
            || (!mag_on && who_am_i == mpu::ID_MPU6500);
        if !accepted {
            return Err(Error::WrongChip {
                chip: Chip::Mpu9250,
                address: self.config.address,
                found: who_am_i,
            });
        }
        // 2-3. Reset, wake with the auto-selected PLL clock, all axes on.
        self.write_reg(Chip::Mpu9250, mpu::PWR_MGMT_1, mpu::H_RESET)?;
        delay.delay_ms(RESET_WAIT_MS);
        self.write_reg(Chip::Mpu9250, mpu::PWR_MGMT_1, mpu::CLKSEL_AUTO)?;
        delay.delay_ms(SETTLE_WAIT_MS);
        self.write_reg(Chip::Mpu9250, mpu::PWR_MGMT_2, 0x00)?;
        // 4. Filters, rate, full scales.
        let c = &self.config;
        let writes = [
            (mpu::CONFIG, c.gyro_dlpf.dlpf_cfg()),
            (mpu::SMPLRT_DIV, c.smplrt_div()),
            (mpu::GYRO_CONFIG, c.gyro_range.fs_sel() << 3),
            (mpu::ACCEL_CONFIG, c.accel_range.fs_sel() << 3),
            (mpu::ACCEL_CONFIG2, c.accel_dlpf.a_dlpf_cfg()),
            // 5. I2C master off and bypass on, so the AK8963 appears at 0x0C.
            (mpu::USER_CTRL, 0x00),
            (mpu::INT_PIN_CFG, mpu::BYPASS_EN),
            (mpu::INT_ENABLE, mpu::RAW_RDY_EN),
        ];
        for (reg, value) in writes {
            self.write_reg(Chip::Mpu9250, reg, value)?;
        }
        delay.delay_ms(SETTLE_WAIT_MS);

        let (wia, asa) = if mag_on {
            let (wia, asa) = self.init_ak8963(delay)?;
            (Some(wia), Some(asa))
        } else {
            (None, None)
        };

        if let Some(saved) = self.config.gyro_bias_rad_s {
            self.gyro_bias_rad_s = saved;
        } else if self.config.gyro_bias_samples > 0 {
            self.estimate_gyro_bias(delay, self.config.gyro_bias_samples)?;
        }
        self.mag_skip = 0;
        if self.config.read_mode == ReadMode::Fifo {
            self.start_fifo(delay)?;
        }
        Ok(ChipIds { who_am_i, wia, asa })
    }

    /// FIFO mode: the AK8963 read by SLV0 of the MPU's I2C master at every sample (ST1..ST2
    /// into EXT_SENS_DATA_00..07, WAIT_FOR_ES so a record carries its own sample's copy), then
    /// the FIFO reset and on. The AK8963 leaves the host bus (bypass off).
    fn start_fifo<D: DelayNs>(&mut self, delay: &mut D) -> Result<(), Error<I2C::Error>> {
        let layout = FifoLayout {
            mag: self.config.mag_mode != MagMode::Off,
        };
        self.write_reg(Chip::Mpu9250, mpu::USER_CTRL, 0x00)?;
        self.write_reg(Chip::Mpu9250, mpu::FIFO_EN, 0x00)?;
        if layout.mag {
            let writes = [
                (mpu::INT_PIN_CFG, 0x00),
                (
                    mpu::I2C_MST_CTRL,
                    mpu::WAIT_FOR_ES | mpu::I2C_MST_CLK_400KHZ,
                ),
                (mpu::I2C_SLV0_ADDR, mpu::SLV_READ | AK8963_ADDRESS),
                (mpu::I2C_SLV0_REG, ak::ST1),
                (mpu::I2C_SLV0_CTRL, mpu::SLV_EN | MAG_RECORD_LEN as u8),
                (mpu::USER_CTRL, mpu::USER_I2C_MST_EN),
            ];
            for (reg, value) in writes {
                self.write_reg(Chip::Mpu9250, reg, value)?;
            }
            // A few master cycles, so EXT_SENS_DATA holds an AK8963 block before any record.
            delay.delay_ms(SETTLE_WAIT_MS);
        }
        self.write_reg(Chip::Mpu9250, mpu::FIFO_EN, layout.fifo_en())?;
        self.fifo = Some(FifoState {
            layout,
            needs_reset: false,
            restarted: true,
        });
        self.reset_fifo()
    }

    /// Empties the FIFO (USER_CTRL.FIFO_RST, the master and the FIFO left on).
    fn reset_fifo(&mut self) -> Result<(), Error<I2C::Error>> {
        let Some(state) = self.fifo else {
            return Ok(());
        };
        let master = if state.layout.mag {
            mpu::USER_I2C_MST_EN
        } else {
            0
        };
        self.write_reg(
            Chip::Mpu9250,
            mpu::USER_CTRL,
            master | mpu::USER_FIFO_EN | mpu::USER_FIFO_RST,
        )?;
        self.fifo = Some(FifoState {
            needs_reset: false,
            restarted: true,
            ..state
        });
        Ok(())
    }

    /// The FIFO's record layout, once `init` started the FIFO (FIFO mode).
    pub fn fifo_layout(&self) -> Option<FifoLayout> {
        self.fifo.map(|state| state.layout)
    }

    /// FIFO mode: the FIFO's byte count (FIFO_COUNTH/L, one transaction; a reset owed from a
    /// failed data read goes first). Pass it to [`Mpu9250::read_fifo`]; the time this returns
    /// is an upper bound of the newest counted sample's measurement time ([`FifoClock`]).
    pub fn fifo_count(&mut self) -> Result<u16, Error<I2C::Error>> {
        let state = self.fifo.ok_or(Error::FifoOff {
            address: self.config.address,
        })?;
        if state.needs_reset {
            self.reset_fifo()?;
        }
        let mut count = [0u8; 2];
        self.read_regs(Chip::Mpu9250, mpu::FIFO_COUNTH, &mut count)?;
        Ok(u16::from_be_bytes(count) & 0x1FFF)
    }

    /// FIFO mode: reads the whole records among the `count` bytes [`Mpu9250::fifo_count`] gave
    /// (one transaction, not retried: a failed read may have popped bytes, so the FIFO is
    /// reset instead) and appends them to `out`, oldest first. An overflow or a content that
    /// cannot be aligned resets the FIFO and decodes nothing.
    pub fn read_fifo(
        &mut self,
        count: u16,
        out: &mut Vec<ImuReading>,
    ) -> Result<FifoRead, Error<I2C::Error>> {
        let state = self.fifo.ok_or(Error::FifoOff {
            address: self.config.address,
        })?;
        let layout = state.layout;
        let record_len = layout.record_len();
        let count_bytes = usize::from(count);
        if count_bytes > layout.capacity_records() * record_len {
            self.stats.fifo_overflows += 1;
            self.reset_fifo()?;
            return Ok(FifoRead::Overflow { count });
        }
        let records = count_bytes / record_len;
        if records > 0 {
            let mut bytes = std::mem::take(&mut self.fifo_bytes);
            bytes.clear();
            bytes.resize(records * record_len, 0);
            let address = self.config.address;
            let result = self.attempt(Chip::Mpu9250, 1, |i2c| {
                i2c.write_read(address, &[mpu::FIFO_R_W], &mut bytes)
            });
            if let Err(e) = result {
                self.fifo_bytes = bytes;
                self.stats.fifo_discards += 1;
                if let Some(state) = &mut self.fifo {
                    state.needs_reset = true;
                }
                // Reset now if the bus lets us; otherwise `fifo_count` does it first.
                let _ = self.reset_fifo();
                return Err(e);
            }
            let aligned = !layout.mag
                || bytes
                    .chunks_exact(record_len)
                    .all(|record| plausible_mag_status(&record[MPU_RECORD_LEN..]));
            if !aligned {
                self.fifo_bytes = bytes;
                self.stats.fifo_discards += 1;
                self.reset_fifo()?;
                return Ok(FifoRead::Misaligned);
            }
            out.reserve(records);
            for record in bytes.chunks_exact(record_len) {
                let (mpu_bytes, mag_bytes) = record.split_at(MPU_RECORD_LEN);
                let raw = RawMpu::from_be_bytes(mpu_bytes);
                let mag_ut = match <[u8; MAG_RECORD_LEN]>::try_from(mag_bytes) {
                    Ok(block) => match self.decode_mag(block) {
                        MagRead::Field(field) => Some(field),
                        MagRead::NotReady | MagRead::Overflow => None,
                    },
                    Err(_) => None,
                };
                let reading = self.convert(&raw, mag_ut);
                out.push(reading);
            }
            self.fifo_bytes = bytes;
        }
        let restarted = if records > 0 {
            self.fifo
                .as_mut()
                .is_some_and(|state| std::mem::take(&mut state.restarted))
        } else {
            false
        };
        Ok(FifoRead::Samples {
            samples: records,
            restarted,
        })
    }

    /// Steps 6-10: identity, soft reset, fuse-ROM ASA, continuous 16-bit mode.
    fn init_ak8963<D: DelayNs>(
        &mut self,
        delay: &mut D,
    ) -> Result<(u8, [u8; 3]), Error<I2C::Error>> {
        let wia = self.read_reg(Chip::Ak8963, ak::WIA)?;
        if wia != ak::ID {
            return Err(Error::WrongChip {
                chip: Chip::Ak8963,
                address: AK8963_ADDRESS,
                found: wia,
            });
        }
        self.write_reg(Chip::Ak8963, ak::CNTL2, ak::SRST)?;
        delay.delay_ms(AK_SOFT_RESET_WAIT_MS);
        self.write_reg(Chip::Ak8963, ak::CNTL1, ak::MODE_POWER_DOWN)?;
        delay.delay_ms(SETTLE_WAIT_MS);
        self.write_reg(Chip::Ak8963, ak::CNTL1, ak::MODE_FUSE_ROM)?;
        let mut asa = [0u8; 3];
        self.read_regs(Chip::Ak8963, ak::ASAX, &mut asa)?;
        self.write_reg(Chip::Ak8963, ak::CNTL1, ak::MODE_POWER_DOWN)?;
        delay.delay_ms(SETTLE_WAIT_MS);
        if asa.iter().any(|&a| a == 0x00 || a == 0xFF) {
            return Err(Error::InvalidAsa {
                address: AK8963_ADDRESS,
                asa,
            });
        }
        self.asa_factor = asa.map(|a| (f32::from(a) - 128.0) / 256.0 + 1.0);
        let mode = match self.config.mag_mode {
            MagMode::Continuous8Hz => ak::MODE_CONTINUOUS_1,
            _ => ak::MODE_CONTINUOUS_2,
        };
        self.write_reg(Chip::Ak8963, ak::CNTL1, ak::BIT_16 | mode)?;
        Ok((wia, asa))
    }

    /// Averages `samples` gyro readings taken one sample period apart (device at rest) and
    /// makes the mean the bias subtracted from every later reading. Returns it, rad/s.
    pub fn estimate_gyro_bias<D: DelayNs>(
        &mut self,
        delay: &mut D,
        samples: u16,
    ) -> Result<[f32; 3], Error<I2C::Error>> {
        let mut sum = [0.0f64; 3];
        let scale = self.gyro_scale();
        for _ in 0..samples {
            delay.delay_ns(self.config.sample_period_ns());
            let raw = self.read_mpu_raw()?;
            for (s, r) in sum.iter_mut().zip(raw.gyro) {
                *s += f64::from(r);
            }
        }
        if samples > 0 {
            let n = f64::from(samples);
            self.gyro_bias_rad_s = sum.map(|s| (s / n) as f32 * scale);
        }
        Ok(self.gyro_bias_rad_s)
    }

    /// Reads the newest sample: accel, temperature and gyro always; the magnetic field when the
    /// AK8963 has a new one (call at the accel/gyro rate; the field comes at 100 Hz). Register
    /// mode: after a field was read, the AK8963 is not asked again until its next one is due
    /// (every other read at 200 Hz); when it had none yet, it is asked again at the next read.
    /// FIFO mode: one burst of the data registers and the master's copy of the AK8963 block.
    pub fn read(&mut self) -> Result<ImuReading, Error<I2C::Error>> {
        if let Some(state) = self.fifo
            && state.layout.mag
        {
            let mut b = [0u8; MPU_RECORD_LEN + MAG_RECORD_LEN];
            self.read_regs(Chip::Mpu9250, mpu::ACCEL_XOUT_H, &mut b)?;
            let (mpu_bytes, mag_bytes) = b.split_at(MPU_RECORD_LEN);
            let raw = RawMpu::from_be_bytes(mpu_bytes);
            let mut block = [0u8; MAG_RECORD_LEN];
            block.copy_from_slice(mag_bytes);
            let mag_ut = match self.decode_mag(block) {
                MagRead::Field(field) => Some(field),
                MagRead::NotReady | MagRead::Overflow => None,
            };
            return Ok(self.convert(&raw, mag_ut));
        }
        let raw = self.read_mpu_raw()?;
        let mag_ut = if self.config.mag_mode == MagMode::Off || self.fifo.is_some() {
            None
        } else if self.mag_skip > 0 {
            self.mag_skip -= 1;
            None
        } else {
            match self.read_mag()? {
                MagRead::NotReady => None,
                MagRead::Overflow => {
                    self.mag_skip = self.reads_per_field().saturating_sub(1);
                    None
                }
                MagRead::Field(field) => {
                    self.mag_skip = self.reads_per_field().saturating_sub(1);
                    Some(field)
                }
            }
        };
        Ok(self.convert(&raw, mag_ut))
    }

    /// One sample in SI units, the gyro bias removed (counted in [`ImuStats::samples`]).
    fn convert(&mut self, raw: &RawMpu, mag_ut: Option<[f32; 3]>) -> ImuReading {
        self.stats.samples += 1;
        let accel_scale = STANDARD_GRAVITY / self.config.accel_range.lsb_per_g();
        let gyro_scale = self.gyro_scale();
        let mut gyro_rad_s = raw.gyro.map(|g| f32::from(g) * gyro_scale);
        for (g, b) in gyro_rad_s.iter_mut().zip(self.gyro_bias_rad_s) {
            *g -= b;
        }
        ImuReading {
            accel_m_s2: raw.accel.map(|a| f32::from(a) * accel_scale),
            gyro_rad_s,
            mag_ut,
            temp_c: f32::from(raw.temp) / 333.87 + 21.0,
        }
    }

    /// rad/s per gyro LSB at the configured full scale.
    fn gyro_scale(&self) -> f32 {
        (core::f32::consts::PI / 180.0) / self.config.gyro_range.lsb_per_dps()
    }

    /// One 14-byte burst from ACCEL_XOUT_H: accel xyz, temperature, gyro xyz, big-endian.
    fn read_mpu_raw(&mut self) -> Result<RawMpu, Error<I2C::Error>> {
        let mut b = [0u8; MPU_RECORD_LEN];
        self.read_regs(Chip::Mpu9250, mpu::ACCEL_XOUT_H, &mut b)?;
        Ok(RawMpu::from_be_bytes(&b))
    }

    /// Accel/gyro reads per magnetometer field: the whole reads that fit in one field period
    /// (2 at 200 Hz with the field at 100 Hz; at least 1).
    fn reads_per_field(&self) -> u32 {
        let field_hz = match self.config.mag_mode {
            MagMode::Continuous8Hz => 8.0,
            _ => 100.0,
        };
        ((self.config.effective_sample_rate_hz() / field_hz).floor() as u32).max(1)
    }

    /// One 8-byte read from ST1 (ST1, HXL..HZH little-endian, ST2). Reading ST2 releases the
    /// AK8963's data protection, so this is also the "end of read" the chip waits for.
    fn read_mag(&mut self) -> Result<MagRead, Error<I2C::Error>> {
        let mut b = [0u8; MAG_RECORD_LEN];
        self.read_regs(Chip::Ak8963, ak::ST1, &mut b)?;
        Ok(self.decode_mag(b))
    }

    /// An AK8963 block (ST1, HXL..HZH little-endian, ST2), from the bus or the FIFO.
    fn decode_mag(&mut self, block: [u8; MAG_RECORD_LEN]) -> MagRead {
        let [st1, xl, xh, yl, yh, zl, zh, st2] = block;
        if st1 & ak::ST1_DRDY == 0 {
            return MagRead::NotReady;
        }
        if st1 & ak::ST1_DOR != 0 {
            self.stats.mag_overruns += 1;
        }
        if st2 & ak::ST2_HOFL != 0 {
            self.stats.mag_overflows += 1;
            return MagRead::Overflow;
        }
        self.stats.mag_samples += 1;
        let chip = [
            i16::from_le_bytes([xl, xh]),
            i16::from_le_bytes([yl, yh]),
            i16::from_le_bytes([zl, zh]),
        ];
        // Sensitivity adjustment per chip axis, before the remap (§1.5).
        let mut h = [0.0f32; 3];
        for ((h, raw), asa) in h.iter_mut().zip(chip).zip(self.asa_factor) {
            *h = f32::from(raw) * asa * MAG_UT_PER_LSB;
        }
        let [hx, hy, hz] = h;
        // Chip axes to the accel/gyro frame: x ← Hy, y ← Hx, z ← −Hz (§1.7).
        let aligned = [hy, hx, -hz];
        MagRead::Field(self.calibrate_mag(aligned))
    }

    /// m = S · (m_raw − hard_iron).
    fn calibrate_mag(&self, m: [f32; 3]) -> [f32; 3] {
        let mut d = m;
        for (d, h) in d.iter_mut().zip(self.config.mag_hard_iron_ut) {
            *d -= h;
        }
        self.config
            .mag_soft_iron
            .map(|row| row.iter().zip(d).map(|(s, v)| s * v).sum())
    }

    fn address(&self, chip: Chip) -> u8 {
        match chip {
            Chip::Mpu9250 => self.config.address,
            Chip::Ak8963 => AK8963_ADDRESS,
        }
    }

    fn read_reg(&mut self, chip: Chip, reg: u8) -> Result<u8, Error<I2C::Error>> {
        let mut b = [0u8; 1];
        self.read_regs(chip, reg, &mut b)?;
        Ok(b[0])
    }

    fn read_regs(&mut self, chip: Chip, reg: u8, buf: &mut [u8]) -> Result<(), Error<I2C::Error>> {
        let address = self.address(chip);
        self.retrying(chip, |i2c| i2c.write_read(address, &[reg], buf))
    }

    fn write_reg(&mut self, chip: Chip, reg: u8, value: u8) -> Result<(), Error<I2C::Error>> {
        let address = self.address(chip);
        self.retrying(chip, |i2c| i2c.write(address, &[reg, value]))
    }

    /// Runs one transaction, retrying it up to `config.retries` times.
    fn retrying(
        &mut self,
        chip: Chip,
        transaction: impl FnMut(&mut I2C) -> Result<(), I2C::Error>,
    ) -> Result<(), Error<I2C::Error>> {
        let attempts = self.config.retries.saturating_add(1);
        self.attempt(chip, attempts, transaction)
    }

    /// Runs one transaction, at most `attempts` times (at least once).
    fn attempt(
        &mut self,
        chip: Chip,
        attempts: u8,
        mut transaction: impl FnMut(&mut I2C) -> Result<(), I2C::Error>,
    ) -> Result<(), Error<I2C::Error>> {
        let mut attempt = 0u8;
        loop {
            attempt += 1;
            self.stats.transactions += 1;
            match transaction(&mut self.i2c) {
                Ok(()) => return Ok(()),
                Err(source) if attempt >= attempts => {
                    return Err(Error::I2c {
                        chip,
                        address: self.address(chip),
                        attempts: attempt,
                        source,
                    });
                }
                Err(_) => self.stats.retries += 1,
            }
        }
    }
}

/// The 14-byte burst decoded, still in LSB.
struct RawMpu {
    accel: [i16; 3],
    temp: i16,
    gyro: [i16; 3],
}

impl RawMpu {
    /// Accel xyz, temperature, gyro xyz, int16 big-endian: the data registers from
    /// ACCEL_XOUT_H, or the first 14 bytes of a FIFO record (`bytes` has at least 14).
    fn from_be_bytes(bytes: &[u8]) -> Self {
        let word = |i: usize| i16::from_be_bytes([bytes[2 * i], bytes[2 * i + 1]]);
        Self {
            accel: [word(0), word(1), word(2)],
            temp: word(3),
            gyro: [word(4), word(5), word(6)],
        }
    }
}

/// Whether an 8-byte block can be the AK8963's ST1..ST2 in 16-bit mode: ST1 holds only DRDY and
/// DOR, ST2 has BITM set and nothing but HOFL beside it. A FIFO read that lost its record
/// boundary puts accel or gyro bytes here, which pass this only by chance.
fn plausible_mag_status(block: &[u8]) -> bool {
    let (Some(&st1), Some(&st2)) = (block.first(), block.get(MAG_RECORD_LEN - 1)) else {
        return false;
    };
    st1 & !(ak::ST1_DRDY | ak::ST1_DOR) == 0 && st2 & !ak::ST2_HOFL == ak::ST2_BITM
}

#[cfg(test)]
mod tests;
