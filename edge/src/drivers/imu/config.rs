//! IMU configuration (`[imu]` in `edge.toml`): address, rates, ranges, filters, calibration.

use serde::Deserialize;

/// Gyroscope full-scale range (GYRO_CONFIG.GYRO_FS_SEL).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum GyroRange {
    /// ±250 °/s, 131 LSB per °/s.
    #[serde(rename = "250dps")]
    Dps250,
    /// ±500 °/s, 65.5 LSB per °/s.
    #[serde(rename = "500dps")]
    Dps500,
    /// ±1000 °/s, 32.8 LSB per °/s.
    #[serde(rename = "1000dps")]
    Dps1000,
    /// ±2000 °/s, 16.4 LSB per °/s.
    #[serde(rename = "2000dps")]
    Dps2000,
}

impl GyroRange {
    /// The FS_SEL field value (0..=3).
    pub fn fs_sel(self) -> u8 {
        match self {
            Self::Dps250 => 0,
            Self::Dps500 => 1,
            Self::Dps1000 => 2,
            Self::Dps2000 => 3,
        }
    }

    /// Sensitivity in LSB per °/s.
    pub fn lsb_per_dps(self) -> f32 {
        match self {
            Self::Dps250 => 131.0,
            Self::Dps500 => 65.5,
            Self::Dps1000 => 32.8,
            Self::Dps2000 => 16.4,
        }
    }
}

/// Accelerometer full-scale range (ACCEL_CONFIG.ACCEL_FS_SEL).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum AccelRange {
    /// ±2 g, 16384 LSB per g.
    #[serde(rename = "2g")]
    G2,
    /// ±4 g, 8192 LSB per g.
    #[serde(rename = "4g")]
    G4,
    /// ±8 g, 4096 LSB per g.
    #[serde(rename = "8g")]
    G8,
    /// ±16 g, 2048 LSB per g.
    #[serde(rename = "16g")]
    G16,
}

impl AccelRange {
    /// The FS_SEL field value (0..=3).
    pub fn fs_sel(self) -> u8 {
        match self {
            Self::G2 => 0,
            Self::G4 => 1,
            Self::G8 => 2,
            Self::G16 => 3,
        }
    }

    /// Sensitivity in LSB per g.
    pub fn lsb_per_g(self) -> f32 {
        match self {
            Self::G2 => 16384.0,
            Self::G4 => 8192.0,
            Self::G8 => 4096.0,
            Self::G16 => 2048.0,
        }
    }
}

/// Gyro/temperature low-pass filter (CONFIG.DLPF_CFG 1..=6, all with a 1 kHz internal rate so
/// SMPLRT_DIV applies). The name is the bandwidth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum GyroDlpf {
    /// 184 Hz, 2.9 ms delay.
    #[serde(rename = "184hz")]
    Hz184,
    /// 92 Hz, 3.9 ms delay.
    #[serde(rename = "92hz")]
    Hz92,
    /// 41 Hz, 5.9 ms delay.
    #[serde(rename = "41hz")]
    Hz41,
    /// 20 Hz, 9.9 ms delay.
    #[serde(rename = "20hz")]
    Hz20,
    /// 10 Hz, 17.85 ms delay.
    #[serde(rename = "10hz")]
    Hz10,
    /// 5 Hz, 33.48 ms delay.
    #[serde(rename = "5hz")]
    Hz5,
}

impl GyroDlpf {
    /// The DLPF_CFG value written to CONFIG.
    pub fn dlpf_cfg(self) -> u8 {
        match self {
            Self::Hz184 => 1,
            Self::Hz92 => 2,
            Self::Hz41 => 3,
            Self::Hz20 => 4,
            Self::Hz10 => 5,
            Self::Hz5 => 6,
        }
    }
}

/// Accelerometer low-pass filter (ACCEL_CONFIG2.A_DLPF_CFG 1..=6, ACCEL_FCHOICE_B = 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum AccelDlpf {
    /// 218.1 Hz, 1.88 ms delay.
    #[serde(rename = "218hz")]
    Hz218,
    /// 99 Hz, 2.88 ms delay.
    #[serde(rename = "99hz")]
    Hz99,
    /// 44.8 Hz, 4.88 ms delay.
    #[serde(rename = "45hz")]
    Hz45,
    /// 21.2 Hz, 8.87 ms delay.
    #[serde(rename = "21hz")]
    Hz21,
    /// 10.2 Hz, 16.83 ms delay.
    #[serde(rename = "10hz")]
    Hz10,
    /// 5.05 Hz, 32.48 ms delay.
    #[serde(rename = "5hz")]
    Hz5,
}

impl AccelDlpf {
    /// The A_DLPF_CFG value written to ACCEL_CONFIG2.
    pub fn a_dlpf_cfg(self) -> u8 {
        match self {
            Self::Hz218 => 1,
            Self::Hz99 => 2,
            Self::Hz45 => 3,
            Self::Hz21 => 4,
            Self::Hz10 => 5,
            Self::Hz5 => 6,
        }
    }
}

/// AK8963 measurement mode (always with 16-bit output, 0.15 µT/LSB).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum MagMode {
    /// Continuous measurement mode 2: 100 Hz (the default).
    #[serde(rename = "100hz")]
    Continuous100Hz,
    /// Continuous measurement mode 1: 8 Hz.
    #[serde(rename = "8hz")]
    Continuous8Hz,
    /// Magnetometer not used: no AK8963 access at all, readings carry no field (IMU-only
    /// fusion). This also accepts an MPU-6500 (WHO_AM_I 0x70), which has no magnetometer.
    #[serde(rename = "off")]
    Off,
}

/// How the driver gets samples off the chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum ReadMode {
    /// The chip's FIFO (the default): every sample period the MPU appends accel, temperature,
    /// gyro and (through its I2C master reading the AK8963) ST1..ST2 of the magnetometer; the
    /// host reads the count and the records every [`ImuConfig::fifo_read_interval_ms`], two bus
    /// transactions for a batch of samples.
    #[serde(rename = "fifo")]
    Fifo,
    /// One data-register burst per sample and the AK8963 in bypass mode (1.5 bus transactions
    /// a sample at 200 Hz): the caller polls [`super::Mpu9250::read`] at the sample rate.
    #[serde(rename = "registers")]
    Registers,
}

/// Everything the driver needs to set up and calibrate an MPU-9250 + AK8963.
///
/// Every field has a default, so an empty `[imu]` table is a working configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImuConfig {
    /// MPU-9250 7-bit address: 0x68 (AD0 low, default) or 0x69.
    pub address: u8,
    /// Accel/gyro output rate in Hz (4..=1000). SMPLRT_DIV = round(1000 / rate) − 1, so the
    /// rate actually used is [`ImuConfig::effective_sample_rate_hz`]. Default 200.
    pub sample_rate_hz: u16,
    /// Gyro full scale. Default ±500 °/s.
    pub gyro_range: GyroRange,
    /// Accel full scale. Default ±4 g.
    pub accel_range: AccelRange,
    /// Gyro low-pass filter. Default 41 Hz.
    pub gyro_dlpf: GyroDlpf,
    /// Accel low-pass filter. Default 44.8 Hz.
    pub accel_dlpf: AccelDlpf,
    /// Magnetometer mode. Default continuous 100 Hz.
    pub mag_mode: MagMode,
    /// Samples averaged at start-up (device at rest) to estimate the gyro bias; 0 disables the
    /// estimate. Default 200 (1 s at 200 Hz).
    pub gyro_bias_samples: u16,
    /// A saved gyro bias in rad/s (`scan3d-edge calibrate gyro`), subtracted from every
    /// reading instead of the start-up estimate: for a head that cannot rest at start. Unset
    /// by default (the estimate at rest is better when possible: the bias changes from one
    /// power-up to the next).
    pub gyro_bias_rad_s: Option<[f32; 3]>,
    /// The calibrated field's magnitude, µT (`scan3d-edge calibrate mag` writes it): the daemon
    /// warns, at most once a minute, when the field read leaves it by more than
    /// `mag_field_tolerance` (steel nearby, or a calibration out of date). Unset: no check.
    pub mag_field_ut: Option<f32>,
    /// The fraction of `mag_field_ut` the field may depart from it. Default 0.1.
    pub mag_field_tolerance: f32,
    /// Magnetometer hard-iron offset in µT, in the accel/gyro frame; subtracted first.
    pub mag_hard_iron_ut: [f32; 3],
    /// Magnetometer soft-iron matrix (row-major), applied after the hard-iron offset:
    /// m = S · (m_raw − hard_iron). Default identity.
    pub mag_soft_iron: [[f32; 3]; 3],
    /// Extra attempts for a failed I2C transaction (NACK, bus error) before giving up.
    /// Default 3.
    pub retries: u8,
    /// How samples are read: `"fifo"` (default) or `"registers"` ([`ReadMode`]).
    pub read_mode: ReadMode,
    /// In FIFO mode, the longest time between two FIFO reads, ms (1..=1000; default 40). Shorter
    /// at high sample rates, so that the FIFO is never more than half full
    /// ([`super::fifo_read_interval_ns`]).
    pub fifo_read_interval_ms: u16,
}

impl Default for ImuConfig {
    fn default() -> Self {
        Self {
            address: 0x68,
            sample_rate_hz: 200,
            gyro_range: GyroRange::Dps500,
            accel_range: AccelRange::G4,
            gyro_dlpf: GyroDlpf::Hz41,
            accel_dlpf: AccelDlpf::Hz45,
            mag_mode: MagMode::Continuous100Hz,
            gyro_bias_samples: 200,
            gyro_bias_rad_s: None,
            mag_field_ut: None,
            mag_field_tolerance: 0.1,
            mag_hard_iron_ut: [0.0; 3],
            mag_soft_iron: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            retries: 3,
            read_mode: ReadMode::Fifo,
            fifo_read_interval_ms: 40,
        }
    }
}

/// A configuration value the driver cannot use.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// The MPU-9250 only answers at 0x68 or 0x69.
    #[error("IMU address {0:#04x} is not an MPU-9250 address (0x68 or 0x69)")]
    Address(u8),
    /// The sample rate is outside what SMPLRT_DIV can produce from 1 kHz.
    #[error("IMU sample rate {0} Hz is outside 4..=1000 Hz")]
    SampleRate(u16),
    /// A calibration value is NaN or infinite.
    #[error("IMU calibration (magnetometer iron or gyro bias) contains a non-finite value")]
    NonFiniteCalibration,
    /// `mag_field_ut` or `mag_field_tolerance` is not a positive number.
    #[error("IMU mag_field_ut and mag_field_tolerance must be positive numbers")]
    MagFieldCheck,
    /// The FIFO read interval is outside 1..=1000 ms.
    #[error("IMU fifo_read_interval_ms {0} is outside 1..=1000")]
    FifoReadInterval(u16),
}

impl ImuConfig {
    /// Checks the values the hardware cannot accept.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !matches!(self.address, 0x68 | 0x69) {
            return Err(ConfigError::Address(self.address));
        }
        if !(4..=1000).contains(&self.sample_rate_hz) {
            return Err(ConfigError::SampleRate(self.sample_rate_hz));
        }
        let finite = self.mag_hard_iron_ut.iter().all(|v| v.is_finite())
            && self.mag_soft_iron.iter().flatten().all(|v| v.is_finite())
            && self.gyro_bias_rad_s.iter().flatten().all(|v| v.is_finite());
        if !finite {
            return Err(ConfigError::NonFiniteCalibration);
        }
        let positive = |v: f32| v.is_finite() && v > 0.0;
        if !positive(self.mag_field_tolerance) || !self.mag_field_ut.is_none_or(positive) {
            return Err(ConfigError::MagFieldCheck);
        }
        if !(1..=1000).contains(&self.fifo_read_interval_ms) {
            return Err(ConfigError::FifoReadInterval(self.fifo_read_interval_ms));
        }
        Ok(())
    }

    /// The SMPLRT_DIV value for [`ImuConfig::sample_rate_hz`] (1 kHz internal rate).
    pub fn smplrt_div(&self) -> u8 {
        let rate = u32::from(self.sample_rate_hz.clamp(4, 1000));
        // round(1000 / rate) − 1, in integers; ≤ 249 for rate ≥ 4.
        let div = (2000 + rate) / (2 * rate) - 1;
        u8::try_from(div).unwrap_or(u8::MAX)
    }

    /// The accel/gyro output rate really produced: 1000 / (1 + SMPLRT_DIV) Hz.
    pub fn effective_sample_rate_hz(&self) -> f32 {
        1000.0 / (1.0 + f32::from(self.smplrt_div()))
    }

    /// Nanoseconds between two accel/gyro samples at the effective rate.
    pub fn sample_period_ns(&self) -> u32 {
        (1 + u32::from(self.smplrt_div())) * 1_000_000
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smplrt_div_for_common_rates() {
        let with_rate = |sample_rate_hz| ImuConfig {
            sample_rate_hz,
            ..ImuConfig::default()
        };
        assert_eq!(with_rate(1000).smplrt_div(), 0);
        assert_eq!(with_rate(500).smplrt_div(), 1);
        assert_eq!(with_rate(200).smplrt_div(), 4);
        assert_eq!(with_rate(100).smplrt_div(), 9);
        assert_eq!(with_rate(4).smplrt_div(), 249);
        // 300 Hz is not reachable: 1000/3 ≈ 333 Hz is the nearest.
        assert_eq!(with_rate(300).smplrt_div(), 2);
        assert_eq!(with_rate(200).sample_period_ns(), 5_000_000);
    }

    #[test]
    fn empty_table_gives_defaults_and_names_parse() {
        let config: ImuConfig = toml::from_str("").unwrap();
        assert_eq!(config, ImuConfig::default());
        let config: ImuConfig = toml::from_str(
            "address = 0x69\nsample_rate_hz = 500\ngyro_range = \"2000dps\"\n\
             accel_range = \"16g\"\ngyro_dlpf = \"184hz\"\naccel_dlpf = \"99hz\"\n\
             mag_mode = \"8hz\"\nmag_hard_iron_ut = [1.0, -2.0, 3.5]\n\
             read_mode = \"registers\"\nfifo_read_interval_ms = 25\n\
             gyro_bias_rad_s = [0.01, -0.02, 0.005]\n",
        )
        .unwrap();
        assert_eq!(config.address, 0x69);
        assert_eq!(config.gyro_range, GyroRange::Dps2000);
        assert_eq!(config.accel_range, AccelRange::G16);
        assert_eq!(config.gyro_dlpf, GyroDlpf::Hz184);
        assert_eq!(config.accel_dlpf, AccelDlpf::Hz99);
        assert_eq!(config.mag_mode, MagMode::Continuous8Hz);
        assert_eq!(config.mag_hard_iron_ut, [1.0, -2.0, 3.5]);
        assert_eq!(config.read_mode, ReadMode::Registers);
        assert_eq!(config.fifo_read_interval_ms, 25);
        assert_eq!(config.gyro_bias_rad_s, Some([0.01, -0.02, 0.005]));
        assert_eq!(config.mag_field_ut, None);
        assert_eq!(config.mag_field_tolerance, 0.1);
        assert!(toml::from_str::<ImuConfig>("adress = 0x68").is_err());
    }

    #[test]
    fn validate_rejects_bad_values() {
        let bad = |c: ImuConfig| c.validate().unwrap_err();
        assert_eq!(
            bad(ImuConfig {
                address: 0x0C,
                ..ImuConfig::default()
            }),
            ConfigError::Address(0x0C)
        );
        assert_eq!(
            bad(ImuConfig {
                sample_rate_hz: 2000,
                ..ImuConfig::default()
            }),
            ConfigError::SampleRate(2000)
        );
        assert_eq!(
            bad(ImuConfig {
                mag_hard_iron_ut: [0.0, f32::NAN, 0.0],
                ..ImuConfig::default()
            }),
            ConfigError::NonFiniteCalibration
        );
        assert_eq!(
            bad(ImuConfig {
                gyro_bias_rad_s: Some([0.0, 0.0, f32::INFINITY]),
                ..ImuConfig::default()
            }),
            ConfigError::NonFiniteCalibration
        );
        assert_eq!(
            bad(ImuConfig {
                mag_field_ut: Some(0.0),
                ..ImuConfig::default()
            }),
            ConfigError::MagFieldCheck
        );
        assert_eq!(
            bad(ImuConfig {
                fifo_read_interval_ms: 0,
                ..ImuConfig::default()
            }),
            ConfigError::FifoReadInterval(0)
        );
        assert!(ImuConfig::default().validate().is_ok());
    }
}
