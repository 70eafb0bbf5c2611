//! Driver tests against scripted I2C transactions (embedded-hal-mock). The expected register
//! writes are written out by hand from research/hardware.md §1.3-§1.7.

use embedded_hal::i2c::{ErrorKind, NoAcknowledgeSource};
use embedded_hal_mock::eh1::delay::{CheckedDelay, NoopDelay, Transaction as D};
use embedded_hal_mock::eh1::i2c::{Mock, Transaction as T};

use super::*;

const MPU: u8 = 0x68;
const AK: u8 = 0x0C;

/// The §1.4 sequence for the default configuration (200 Hz, ±500 °/s, ±4 g, DLPF 41/44.8 Hz,
/// AK8963 16-bit continuous mode 2), with the given fuse-ROM bytes.
fn default_init_script(asa: [u8; 3]) -> Vec<T> {
    vec![
        T::write_read(MPU, vec![0x75], vec![0x71]),
        T::write(MPU, vec![0x6B, 0x80]),
        T::write(MPU, vec![0x6B, 0x01]),
        T::write(MPU, vec![0x6C, 0x00]),
        T::write(MPU, vec![0x1A, 0x03]),
        T::write(MPU, vec![0x19, 0x04]),
        T::write(MPU, vec![0x1B, 0x08]),
        T::write(MPU, vec![0x1C, 0x08]),
        T::write(MPU, vec![0x1D, 0x03]),
        T::write(MPU, vec![0x6A, 0x00]),
        T::write(MPU, vec![0x37, 0x02]),
        T::write(MPU, vec![0x38, 0x01]),
        T::write_read(AK, vec![0x00], vec![0x48]),
        T::write(AK, vec![0x0B, 0x01]),
        T::write(AK, vec![0x0A, 0x00]),
        T::write(AK, vec![0x0A, 0x0F]),
        T::write_read(AK, vec![0x10], asa.to_vec()),
        T::write(AK, vec![0x0A, 0x00]),
        T::write(AK, vec![0x0A, 0x16]),
    ]
}

/// The default configuration read per sample (data registers, AK8963 in bypass): the scripts
/// below are that path's transactions.
fn registers() -> ImuConfig {
    ImuConfig {
        read_mode: ReadMode::Registers,
        ..ImuConfig::default()
    }
}

fn no_bias_config() -> ImuConfig {
    ImuConfig {
        gyro_bias_samples: 0,
        ..registers()
    }
}

/// A driver initialised with the default config (no bias estimate) and ASA = 128 (factor 1),
/// whose bus then expects `then`.
fn initialised(config: ImuConfig, then: Vec<T>) -> Mpu9250<Mock> {
    let mut script = default_init_script([128, 128, 128]);
    script.extend(then);
    let mut imu = Mpu9250::new(Mock::new(&script), config);
    imu.init(&mut NoopDelay::new()).unwrap();
    imu
}

fn mpu_burst(bytes: [u8; 14]) -> T {
    T::write_read(MPU, vec![0x3B], bytes.to_vec())
}

fn mag_block(bytes: [u8; 8]) -> T {
    T::write_read(AK, vec![0x02], bytes.to_vec())
}

/// ST1 = DRDY, HX = 200, HY = −100, HZ = 400 (little-endian), ST2 = BITM.
const MAG_200_M100_400: [u8; 8] = [0x01, 0xC8, 0x00, 0x9C, 0xFF, 0x90, 0x01, 0x10];

fn assert_close(got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert!((g - w).abs() <= tol, "got {got:?}, want {want:?}");
    }
}

fn finish(imu: Mpu9250<Mock>) {
    imu.destroy().done();
}

#[test]
fn init_writes_the_documented_sequence_with_its_waits() {
    let mut imu = Mpu9250::new(
        Mock::new(&default_init_script([0xB0, 0xA8, 0x80])),
        no_bias_config(),
    );
    let mut delay = CheckedDelay::new(&[
        D::delay_ms(100), // after H_RESET
        D::delay_ms(10),  // after wake
        D::delay_ms(10),  // after bypass
        D::delay_ms(1),   // after AK8963 soft reset
        D::delay_ms(10),  // after power-down
        D::delay_ms(10),  // after leaving fuse-ROM mode
    ]);
    let ids = imu.init(&mut delay).unwrap();
    assert_eq!(
        ids,
        ChipIds {
            who_am_i: 0x71,
            wia: Some(0x48),
            asa: Some([0xB0, 0xA8, 0x80]),
        }
    );
    // 19 register transactions, no retries.
    assert_eq!(imu.stats().transactions, 19);
    assert_eq!(imu.stats().retries, 0);
    delay.done();
    finish(imu);
}

#[test]
fn init_applies_a_non_default_configuration() {
    let config = ImuConfig {
        address: 0x69,
        sample_rate_hz: 1000,
        gyro_range: GyroRange::Dps2000,
        accel_range: AccelRange::G16,
        gyro_dlpf: GyroDlpf::Hz184,
        accel_dlpf: AccelDlpf::Hz218,
        mag_mode: MagMode::Continuous8Hz,
        gyro_bias_samples: 0,
        ..registers()
    };
    let script = vec![
        T::write_read(0x69, vec![0x75], vec![0x73]), // an MPU-9255 is accepted
        T::write(0x69, vec![0x6B, 0x80]),
        T::write(0x69, vec![0x6B, 0x01]),
        T::write(0x69, vec![0x6C, 0x00]),
        T::write(0x69, vec![0x1A, 0x01]),
        T::write(0x69, vec![0x19, 0x00]),
        T::write(0x69, vec![0x1B, 0x18]),
        T::write(0x69, vec![0x1C, 0x18]),
        T::write(0x69, vec![0x1D, 0x01]),
        T::write(0x69, vec![0x6A, 0x00]),
        T::write(0x69, vec![0x37, 0x02]),
        T::write(0x69, vec![0x38, 0x01]),
        T::write_read(AK, vec![0x00], vec![0x48]),
        T::write(AK, vec![0x0B, 0x01]),
        T::write(AK, vec![0x0A, 0x00]),
        T::write(AK, vec![0x0A, 0x0F]),
        T::write_read(AK, vec![0x10], vec![0x80, 0x80, 0x80]),
        T::write(AK, vec![0x0A, 0x00]),
        T::write(AK, vec![0x0A, 0x12]), // 16-bit, continuous mode 1 (8 Hz)
    ];
    let mut imu = Mpu9250::new(Mock::new(&script), config);
    assert_eq!(imu.init(&mut NoopDelay::new()).unwrap().who_am_i, 0x73);
    finish(imu);
}

#[test]
fn magnetometer_off_skips_the_ak8963_and_accepts_an_mpu6500() {
    let mut script = default_init_script([128; 3]);
    script.truncate(12);
    script[0] = T::write_read(MPU, vec![0x75], vec![0x70]);
    script.push(mpu_burst([0; 14]));
    let config = ImuConfig {
        mag_mode: MagMode::Off,
        ..no_bias_config()
    };
    let mut imu = Mpu9250::new(Mock::new(&script), config);
    let ids = imu.init(&mut NoopDelay::new()).unwrap();
    assert_eq!((ids.who_am_i, ids.wia, ids.asa), (0x70, None, None));
    assert_eq!(imu.read().unwrap().mag_ut, None);
    finish(imu);
}

#[test]
fn read_converts_big_endian_mpu_and_little_endian_ak8963_data() {
    let mut imu = initialised(
        no_bias_config(),
        vec![
            // accel (−4096, 0, 8192) = (−0.5 g, 0, 1 g) at ±4 g; temp 3339 ≈ 31 °C;
            // gyro (655, −655, 0) = (10, −10, 0) °/s at ±500 °/s.
            mpu_burst([
                0xF0, 0x00, 0x00, 0x00, 0x20, 0x00, 0x0D, 0x0B, 0x02, 0x8F, 0xFD, 0x71, 0x00, 0x00,
            ]),
            mag_block(MAG_200_M100_400),
        ],
    );
    let r = imu.read().unwrap();
    assert_close(&r.accel_m_s2, &[-0.5 * 9.80665, 0.0, 9.80665], 1e-5);
    let ten_dps = 10.0f32.to_radians();
    assert_close(&r.gyro_rad_s, &[ten_dps, -ten_dps, 0.0], 1e-6);
    assert_close(&[r.temp_c], &[3339.0 / 333.87 + 21.0], 1e-4);
    // Chip (30, −15, 60) µT → frame (Hy, Hx, −Hz) = (−15, 30, −60) µT.
    assert_close(&r.mag_ut.unwrap(), &[-15.0, 30.0, -60.0], 1e-4);
    assert_eq!(imu.stats().samples, 1);
    assert_eq!(imu.stats().mag_samples, 1);
    finish(imu);
}

#[test]
fn a_field_along_the_ak8963_x_axis_is_the_drivers_y() {
    // HX = 1000 LSB, HY = HZ = 0.
    let mut imu = initialised(
        no_bias_config(),
        vec![
            mpu_burst([0; 14]),
            mag_block([0x01, 0xE8, 0x03, 0, 0, 0, 0, 0x10]),
        ],
    );
    assert_close(
        &imu.read().unwrap().mag_ut.unwrap(),
        &[0.0, 150.0, 0.0],
        1e-4,
    );
    finish(imu);
}

#[test]
fn sensitivity_adjustment_applies_per_chip_axis_before_the_remap() {
    // ASAX = 0xB0 (factor 1.1875), ASAY = 0x80 (1), ASAZ = 0x40 (0.75).
    let mut script = default_init_script([0xB0, 0x80, 0x40]);
    script.push(mpu_burst([0; 14]));
    script.push(mag_block(MAG_200_M100_400));
    let mut imu = Mpu9250::new(Mock::new(&script), no_bias_config());
    imu.init(&mut NoopDelay::new()).unwrap();
    // Hx = 200·1.1875·0.15 = 35.625, Hy = −15, Hz = 400·0.75·0.15 = 45.
    assert_close(
        &imu.read().unwrap().mag_ut.unwrap(),
        &[-15.0, 35.625, -45.0],
        1e-4,
    );
    finish(imu);
}

#[test]
fn hard_and_soft_iron_calibration_from_config() {
    let config = ImuConfig {
        mag_hard_iron_ut: [5.0, 10.0, -20.0],
        mag_soft_iron: [[2.0, 0.0, 0.0], [0.0, 1.0, 1.0], [0.0, 0.0, 0.5]],
        ..no_bias_config()
    };
    let mut imu = initialised(
        config,
        vec![mpu_burst([0; 14]), mag_block(MAG_200_M100_400)],
    );
    // raw (−15, 30, −60) − (5, 10, −20) = (−20, 20, −40); S· = (−40, −20, −20).
    assert_close(
        &imu.read().unwrap().mag_ut.unwrap(),
        &[-40.0, -20.0, -20.0],
        1e-4,
    );
    finish(imu);
}

#[test]
fn no_new_field_overflow_and_overrun() {
    let mut imu = initialised(
        no_bias_config(),
        vec![
            mpu_burst([0; 14]),
            // DRDY clear: no new field.
            mag_block([0x00, 0xC8, 0x00, 0, 0, 0, 0, 0x10]),
            mpu_burst([0; 14]),
            // DRDY with HOFL: dropped and counted.
            mag_block([0x01, 0xFF, 0x7F, 0, 0, 0, 0, 0x18]),
            // The chip's next field is 10 ms away: at 200 Hz this read skips the AK8963.
            mpu_burst([0; 14]),
            mpu_burst([0; 14]),
            // DRDY with DOR: kept, overrun counted.
            mag_block([0x03, 0xC8, 0x00, 0, 0, 0, 0, 0x10]),
        ],
    );
    assert_eq!(imu.read().unwrap().mag_ut, None);
    assert_eq!(imu.read().unwrap().mag_ut, None);
    assert_eq!(imu.read().unwrap().mag_ut, None);
    assert_close(
        &imu.read().unwrap().mag_ut.unwrap(),
        &[0.0, 30.0, 0.0],
        1e-4,
    );
    let stats = imu.stats();
    assert_eq!(
        (
            stats.samples,
            stats.mag_samples,
            stats.mag_overflows,
            stats.mag_overruns
        ),
        (4, 1, 1, 1)
    );
    finish(imu);
}

#[test]
fn at_200_hz_the_ak8963_is_read_every_other_sample_once_it_delivered_a_field() {
    let field = mag_block(MAG_200_M100_400);
    let mut imu = initialised(
        no_bias_config(),
        vec![
            // A field: the next one is due in 10 ms, two samples on.
            mpu_burst([0; 14]),
            field.clone(),
            mpu_burst([0; 14]),
            mpu_burst([0; 14]),
            // Not there yet (DRDY clear): asked again at the next sample.
            mag_block([0x00, 0, 0, 0, 0, 0, 0, 0x10]),
            mpu_burst([0; 14]),
            field,
            mpu_burst([0; 14]),
        ],
    );
    let before = imu.stats().transactions;
    let fields: Vec<bool> = (0..5)
        .map(|_| imu.read().unwrap().mag_ut.is_some())
        .collect();
    assert_eq!(fields, [true, false, false, true, false]);
    assert_eq!(
        imu.stats().transactions - before,
        8,
        "5 bursts and 3 AK8963 reads"
    );
    assert_eq!(imu.stats().mag_samples, 2);
    finish(imu);
}

#[test]
fn gyro_bias_is_averaged_at_start_up_and_removed() {
    let gyro = |x: i16, y: i16, z: i16| {
        let mut b = [0u8; 14];
        b[8..10].copy_from_slice(&x.to_be_bytes());
        b[10..12].copy_from_slice(&y.to_be_bytes());
        b[12..14].copy_from_slice(&z.to_be_bytes());
        mpu_burst(b)
    };
    let mut script = default_init_script([128; 3]);
    script.extend([
        gyro(100, -50, 10),
        gyro(102, -52, 12),
        gyro(101, -51, 11),
        mag_block([0; 8]),
        gyro(101 + 655, -51, 11),
        mag_block([0; 8]),
    ]);
    let config = ImuConfig {
        gyro_bias_samples: 2,
        ..registers()
    };
    let mut imu = Mpu9250::new(Mock::new(&script), config);
    let mut delay = CheckedDelay::new(&[
        D::delay_ms(100),
        D::delay_ms(10),
        D::delay_ms(10),
        D::delay_ms(1),
        D::delay_ms(10),
        D::delay_ms(10),
        // One sample period (200 Hz) before each bias sample.
        D::delay_ns(5_000_000),
        D::delay_ns(5_000_000),
    ]);
    imu.init(&mut delay).unwrap();
    let lsb = 1.0f32.to_radians() / 65.5;
    assert_close(
        &imu.gyro_bias(),
        &[101.0 * lsb, -51.0 * lsb, 11.0 * lsb],
        1e-7,
    );
    assert_close(&imu.read().unwrap().gyro_rad_s, &[0.0; 3], 1e-7);
    assert_close(
        &imu.read().unwrap().gyro_rad_s,
        &[10.0f32.to_radians(), 0.0, 0.0],
        1e-6,
    );
    delay.done();
    finish(imu);
}

#[test]
fn wrong_who_am_i_names_the_chip_and_address() {
    for (found, extra) in [(0x68u8, None), (0x70, Some("MPU-6500"))] {
        let script = [T::write_read(MPU, vec![0x75], vec![found])];
        let mut imu = Mpu9250::new(Mock::new(&script), no_bias_config());
        let err = imu.init(&mut NoopDelay::new()).unwrap_err();
        assert!(matches!(
            err,
            Error::WrongChip {
                chip: Chip::Mpu9250,
                address: 0x68,
                found: f,
            } if f == found
        ));
        let text = err.to_string();
        assert!(
            text.starts_with("MPU-9250 at I2C address 0x68: WHO_AM_I is"),
            "{text}"
        );
        assert!(text.contains(&format!("{found:#04x}")), "{text}");
        if let Some(extra) = extra {
            assert!(text.contains(extra), "{text}");
        }
        finish(imu);
    }
}

#[test]
fn wrong_wia_names_the_ak8963() {
    let mut script = default_init_script([128; 3]);
    script.truncate(13);
    script[12] = T::write_read(AK, vec![0x00], vec![0xFF]);
    let mut imu = Mpu9250::new(Mock::new(&script), no_bias_config());
    let err = imu.init(&mut NoopDelay::new()).unwrap_err();
    assert_eq!(
        err.to_string(),
        "AK8963 at I2C address 0x0c: WIA is 0xff, expected 0x48"
    );
    finish(imu);
}

#[test]
fn invalid_fuse_rom_is_an_error() {
    let mut script = default_init_script([0xFF, 0x80, 0x80]);
    script.truncate(18);
    let mut imu = Mpu9250::new(Mock::new(&script), no_bias_config());
    let err = imu.init(&mut NoopDelay::new()).unwrap_err();
    assert!(matches!(
        err,
        Error::InvalidAsa {
            address: 0x0C,
            asa: [0xFF, 0x80, 0x80]
        }
    ));
    finish(imu);
}

#[test]
fn a_nack_is_retried_then_succeeds() {
    let nack = ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address);
    let mut imu = initialised(
        no_bias_config(),
        vec![
            T::write_read(MPU, vec![0x3B], vec![0; 14]).with_error(nack),
            T::write_read(MPU, vec![0x3B], vec![0; 14]).with_error(ErrorKind::Bus),
            mpu_burst([0; 14]),
            mag_block([0; 8]),
        ],
    );
    let before = imu.stats().transactions;
    imu.read().unwrap();
    assert_eq!(imu.stats().retries, 2);
    assert_eq!(imu.stats().transactions - before, 4);
    finish(imu);
}

#[test]
fn persistent_nack_fails_after_the_retries_naming_chip_and_address() {
    let nack = ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address);
    let failing = T::write_read(AK, vec![0x02], vec![0; 8]).with_error(nack);
    let config = ImuConfig {
        retries: 2,
        ..no_bias_config()
    };
    let mut imu = initialised(
        config,
        vec![
            mpu_burst([0; 14]),
            failing.clone(),
            failing.clone(),
            failing,
        ],
    );
    let err = imu.read().unwrap_err();
    assert!(matches!(
        err,
        Error::I2c {
            chip: Chip::Ak8963,
            address: 0x0C,
            attempts: 3,
            source: ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address),
        }
    ));
    let text = err.to_string();
    assert!(
        text.starts_with("AK8963 at I2C address 0x0c: bus error after 3 attempt(s): "),
        "{text}"
    );
    assert!(text.contains("acknowledge"), "{text}");
    finish(imu);
}

#[test]
fn invalid_config_is_rejected_before_any_bus_access() {
    let config = ImuConfig {
        address: 0x0C,
        ..registers()
    };
    let mut imu = Mpu9250::new(Mock::new(&[]), config);
    let err = imu.init(&mut NoopDelay::new()).unwrap_err();
    assert!(matches!(err, Error::Config(ConfigError::Address(0x0C))));
    finish(imu);
}

/// The FIFO start after the §1.4 sequence: the AK8963 behind the I2C master's SLV0 (ST1..ST2,
/// 8 bytes, every sample, WAIT_FOR_ES, 400 kHz), then the FIFO reset and on with temperature,
/// gyro, accel and SLV0.
fn fifo_start_script() -> Vec<T> {
    vec![
        T::write(MPU, vec![0x6A, 0x00]),
        T::write(MPU, vec![0x23, 0x00]),
        T::write(MPU, vec![0x37, 0x00]),
        T::write(MPU, vec![0x24, 0x4D]),
        T::write(MPU, vec![0x25, 0x8C]),
        T::write(MPU, vec![0x26, 0x02]),
        T::write(MPU, vec![0x27, 0x88]),
        T::write(MPU, vec![0x6A, 0x20]),
        T::write(MPU, vec![0x23, 0xF9]),
        T::write(MPU, vec![0x6A, 0x64]),
    ]
}

fn fifo_initialised(then: Vec<T>) -> Mpu9250<Mock> {
    let mut script = default_init_script([128, 128, 128]);
    script.extend(fifo_start_script());
    script.extend(then);
    let config = ImuConfig {
        gyro_bias_samples: 0,
        ..ImuConfig::default()
    };
    let mut imu = Mpu9250::new(Mock::new(&script), config);
    imu.init(&mut NoopDelay::new()).unwrap();
    imu
}

/// One 22-byte FIFO record: accel (0, 0, 1 g), temperature 25 °C, gyro z = `gz` LSB, then the
/// AK8963 block.
fn fifo_record(gz: i16, mag: [u8; 8]) -> Vec<u8> {
    let mut record = vec![0, 0, 0, 0, 0x20, 0x00, 0x05, 0x37, 0, 0, 0, 0];
    record.extend_from_slice(&gz.to_be_bytes());
    record.extend_from_slice(&mag);
    record
}

/// ST1 clear (no new field), ST2 = BITM.
const MAG_NOT_READY: [u8; 8] = [0, 0, 0, 0, 0, 0, 0, 0x10];

#[test]
fn fifo_mode_starts_the_master_and_the_fifo_after_the_init_sequence() {
    let imu = fifo_initialised(vec![]);
    assert_eq!(imu.fifo_layout(), Some(FifoLayout { mag: true }));
    assert_eq!(imu.stats().transactions, 19 + 10);
    // Register mode has no FIFO to read.
    let mut registers_only = Mpu9250::new(Mock::new(&[]), registers());
    assert!(matches!(
        registers_only.fifo_count(),
        Err(Error::FifoOff { address: 0x68 })
    ));
    registers_only.destroy().done();
    finish(imu);
}

#[test]
fn a_fifo_batch_is_two_transactions_of_whole_records() {
    let records: Vec<u8> = [
        fifo_record(655, MAG_NOT_READY),
        fifo_record(-655, MAG_200_M100_400),
    ]
    .concat();
    let mut imu = fifo_initialised(vec![
        // 44 bytes and 10 of a record being written: only the whole records are read.
        T::write_read(MPU, vec![0x72], vec![0x00, 54]),
        T::write_read(MPU, vec![0x74], records),
    ]);
    let count = imu.fifo_count().unwrap();
    assert_eq!(count, 54);
    let mut readings = Vec::new();
    assert_eq!(
        imu.read_fifo(count, &mut readings).unwrap(),
        FifoRead::Samples {
            samples: 2,
            restarted: true
        }
    );
    let ten_dps = 10.0f32.to_radians();
    assert_close(&readings[0].gyro_rad_s, &[0.0, 0.0, ten_dps], 1e-6);
    assert_close(&readings[1].gyro_rad_s, &[0.0, 0.0, -ten_dps], 1e-6);
    assert_close(&readings[0].accel_m_s2, &[0.0, 0.0, 9.80665], 1e-5);
    assert_eq!(readings[0].mag_ut, None);
    assert_close(&readings[1].mag_ut.unwrap(), &[-15.0, 30.0, -60.0], 1e-4);
    assert_close(&[readings[1].temp_c], &[25.0], 0.01);
    finish(imu);
}

#[test]
fn a_fifo_overflow_or_misaligned_content_resets_the_fifo_and_decodes_nothing() {
    let mut misaligned = fifo_record(0, MAG_NOT_READY);
    misaligned[21] = 0x20; // an accel byte where ST2 should be
    let mut imu = fifo_initialised(vec![
        // Past the last whole record (23 × 22 = 506): the chip dropped bytes.
        T::write_read(MPU, vec![0x72], vec![0x02, 0x00]),
        T::write(MPU, vec![0x6A, 0x64]),
        T::write_read(MPU, vec![0x72], vec![0x00, 22]),
        T::write_read(MPU, vec![0x74], misaligned),
        T::write(MPU, vec![0x6A, 0x64]),
        // A data read that fails is not retried: the FIFO is reset instead.
        T::write_read(MPU, vec![0x72], vec![0x00, 22]),
        T::write_read(MPU, vec![0x74], vec![0; 22])
            .with_error(ErrorKind::NoAcknowledge(NoAcknowledgeSource::Data)),
        T::write(MPU, vec![0x6A, 0x64]),
    ]);
    let mut readings = Vec::new();
    let count = imu.fifo_count().unwrap();
    assert_eq!(
        imu.read_fifo(count, &mut readings).unwrap(),
        FifoRead::Overflow { count: 512 }
    );
    let count = imu.fifo_count().unwrap();
    assert_eq!(
        imu.read_fifo(count, &mut readings).unwrap(),
        FifoRead::Misaligned
    );
    let count = imu.fifo_count().unwrap();
    let err = imu.read_fifo(count, &mut readings).unwrap_err();
    assert!(matches!(err, Error::I2c { attempts: 1, .. }), "{err}");
    assert!(readings.is_empty());
    let stats = imu.stats();
    assert_eq!((stats.fifo_overflows, stats.fifo_discards), (1, 2));
    finish(imu);
}
