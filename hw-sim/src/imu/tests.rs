//! Register-level tests (hand-written transactions and expected bytes from
//! research/hardware.md §1) and the edge's driver run against the emulator.

use std::sync::{Arc, Mutex};

use embedded_hal::i2c::{Error as _, ErrorKind, I2c, NoAcknowledgeSource};
use scan3d_edge::clock::Clock;

use super::*;
use crate::i2c::{BusError, I2cBus, SimClock, lock};

const MPU: u8 = 0x68;
const AK: u8 = 0x0C;

/// A truth whose values are a fixed function of time, to see which instant a sample holds.
struct FnTruth(fn(u64) -> TrueImu);

impl ImuTruth for FnTruth {
    fn sample(&self, t_ns: u64) -> TrueImu {
        (self.0)(t_ns)
    }
}

fn fixed_mag(mag_ut: [f64; 3]) -> TrueImu {
    TrueImu {
        accel_m_s2: [0.0, 0.0, STANDARD_GRAVITY],
        gyro_rad_s: [0.0; 3],
        mag_ut,
    }
}

/// No noise, ASA = 128 (factor 1): register values are exact.
fn quiet() -> ImuEmulatorConfig {
    ImuEmulatorConfig {
        mpu: MpuEmulatorConfig {
            accel_sigma_m_s2: [0.0; 3],
            gyro_sigma_rad_s: [0.0; 3],
            ..MpuEmulatorConfig::default()
        },
        ak: AkEmulatorConfig {
            asa: [128; 3],
            mag_sigma_ut: [0.0; 3],
            ..AkEmulatorConfig::default()
        },
    }
}

struct Fixture {
    clock: SimClock,
    bus: I2cBus,
    imu: Arc<Mutex<ImuEmulator>>,
}

fn fixture(config: ImuEmulatorConfig, truth: Arc<dyn ImuTruth>) -> Fixture {
    let clock = SimClock::new();
    let bus = I2cBus::with_clock(clock.shared());
    let imu = Arc::new(Mutex::new(ImuEmulator::new(config, truth)));
    bus.attach(imu.clone());
    Fixture { clock, bus, imu }
}

impl Fixture {
    fn rd(&mut self, address: u8, reg: u8, n: usize) -> Vec<u8> {
        let mut buf = vec![0u8; n];
        self.bus.write_read(address, &[reg], &mut buf).unwrap();
        buf
    }

    fn wr(&mut self, address: u8, reg: u8, value: u8) {
        self.bus.write(address, &[reg, value]).unwrap();
    }

    fn at_ms(&self, ms: u64) {
        self.clock.set_ns(ms * 1_000_000);
    }
}

#[test]
fn reset_values_identity_and_bypass_gating() {
    let mut r = fixture(quiet(), Arc::new(StaticTruth::default()));
    assert_eq!(r.rd(MPU, 0x75, 1), [0x71]);
    assert_eq!(r.rd(MPU, 0x6B, 1), [0x01]);
    assert_eq!(r.rd(MPU, 0x19, 5), [0x00; 5]);
    // The AK8963 is hidden until bypass; unknown addresses NACK too.
    let err = r.bus.write_read(AK, &[0x00], &mut [0]).unwrap_err();
    assert_eq!(err, BusError::AddressNack(AK));
    assert_eq!(
        err.kind(),
        ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address)
    );
    assert_eq!(r.bus.write(0x50, &[0x00]), Err(BusError::AddressNack(0x50)));
    r.wr(MPU, 0x37, 0x02);
    assert_eq!(r.rd(AK, 0x00, 1), [0x48]);
    // I2C master on: the AK8963 is on the MPU's auxiliary bus again.
    r.wr(MPU, 0x6A, 0x20);
    assert_eq!(
        r.bus.write_read(AK, &[0x00], &mut [0]),
        Err(BusError::AddressNack(AK))
    );
    r.wr(MPU, 0x6A, 0x00);
    assert_eq!(r.rd(AK, 0x00, 1), [0x48]);
}

#[test]
fn h_reset_restores_defaults_and_nacks_while_resetting() {
    let mut r = fixture(quiet(), Arc::new(StaticTruth::default()));
    r.wr(MPU, 0x1A, 0x03);
    r.wr(MPU, 0x37, 0x02);
    r.wr(MPU, 0x6B, 0x41); // asleep
    assert_eq!(lock(&r.imu).mpu().peek(0x1A), 0x03);
    assert!(lock(&r.imu).mpu().bypass_enabled());
    r.wr(MPU, 0x6B, 0x80);
    assert_eq!(
        r.bus.write_read(MPU, &[0x75], &mut [0]),
        Err(BusError::AddressNack(MPU))
    );
    r.at_ms(10);
    assert_eq!(r.rd(MPU, 0x1A, 1), [0x00]);
    assert_eq!(r.rd(MPU, 0x6B, 1), [0x01]);
    assert_eq!(r.rd(MPU, 0x37, 1), [0x00]);
    assert!(r.bus.write_read(AK, &[0x00], &mut [0]).is_err());
}

#[test]
fn burst_read_is_big_endian_and_scaled_by_the_full_scale() {
    let truth = YawRateTruth {
        yaw_rate_rad_s: 10f64.to_radians(),
        ..YawRateTruth::default()
    };
    let mut r = fixture(quiet(), Arc::new(truth));
    r.wr(MPU, 0x1A, 0x03);
    r.wr(MPU, 0x19, 0x04); // 200 Hz
    r.at_ms(5);
    // ±2 g: z = 16384 = 0x4000; 25 °C: (25 − 21)·333.87 = 1335 = 0x0537;
    // ±250 °/s: 10 °/s · 131 = 1310 = 0x051E.
    assert_eq!(
        r.rd(MPU, 0x3B, 14),
        [
            0x00, 0x00, 0x00, 0x00, 0x40, 0x00, 0x05, 0x37, 0x00, 0x00, 0x00, 0x00, 0x05, 0x1E
        ]
    );
    // ±4 g and ±500 °/s: 0x2000 and 655 = 0x028F.
    r.wr(MPU, 0x1C, 0x08);
    r.wr(MPU, 0x1B, 0x08);
    r.at_ms(10);
    let b = r.rd(MPU, 0x3F, 2);
    assert_eq!(b, [0x20, 0x00]);
    assert_eq!(r.rd(MPU, 0x47, 2), [0x02, 0x8F]);
    // A negative rate reads as two's complement: −10 °/s at ±500 °/s = −655 = 0xFD71.
    lock(&r.imu).set_truth(Arc::new(YawRateTruth {
        yaw_rate_rad_s: -(10f64.to_radians()),
        ..YawRateTruth::default()
    }));
    r.at_ms(15);
    assert_eq!(r.rd(MPU, 0x47, 2), [0xFD, 0x71]);
}

#[test]
fn samples_fall_on_the_rate_grid_and_set_raw_data_ready() {
    // Gyro x in °/s equals the time in ms, so a sample shows when it was taken (±250 °/s).
    let truth = FnTruth(|t_ns| TrueImu {
        gyro_rad_s: [(t_ns as f64 / 1e6).to_radians(), 0.0, 0.0],
        ..fixed_mag([0.0; 3])
    });
    let mut r = fixture(quiet(), Arc::new(truth));
    r.wr(MPU, 0x1A, 0x03);
    r.wr(MPU, 0x19, 0x04); // 200 Hz from t = 0
    r.at_ms(12);
    assert_eq!(r.rd(MPU, 0x43, 2), 1310i16.to_be_bytes()); // the 10 ms sample
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x01]);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x00]);
    r.at_ms(14);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x00]);
    r.at_ms(15);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x01]);
    assert_eq!(r.rd(MPU, 0x43, 2), 1965i16.to_be_bytes()); // 15 · 131
    // 100 Hz (SMPLRT_DIV = 9) restarts the grid at 15 ms: next sample at 25 ms.
    r.wr(MPU, 0x19, 0x09);
    r.at_ms(24);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x00]);
    r.at_ms(25);
    assert_eq!(r.rd(MPU, 0x43, 2), 3275i16.to_be_bytes()); // 25 · 131
    // SLEEP freezes the outputs; waking restarts the grid.
    r.wr(MPU, 0x6B, 0x41);
    r.at_ms(60);
    assert_eq!(r.rd(MPU, 0x43, 2), 3275i16.to_be_bytes());
    r.wr(MPU, 0x6B, 0x01);
    r.at_ms(70);
    assert_eq!(r.rd(MPU, 0x43, 2), 9170i16.to_be_bytes()); // 70 · 131
}

#[test]
fn ak8963_fuse_rom_is_readable_only_in_fuse_rom_mode() {
    let mut config = quiet();
    config.ak.asa = [0xB0, 0xB3, 0xA6];
    let mut r = fixture(config, Arc::new(StaticTruth::default()));
    r.wr(MPU, 0x37, 0x02);
    assert_eq!(r.rd(AK, 0x10, 3), [0x00; 3]);
    r.wr(AK, 0x0A, 0x0F);
    assert_eq!(r.rd(AK, 0x10, 3), [0xB0, 0xB3, 0xA6]);
    r.wr(AK, 0x0A, 0x00);
    assert_eq!(r.rd(AK, 0x10, 3), [0x00; 3]);
}

#[test]
fn ak8963_modes_data_layout_and_axis_mapping() {
    // Body field (1.2, 3, 4.8) µT → chip (Hx, Hy, Hz) = (3, 1.2, −4.8) µT
    // = (20, 8, −32) LSB at 0.15 µT/LSB, little-endian.
    let truth = FnTruth(|_| fixed_mag([1.2, 3.0, 4.8]));
    let mut r = fixture(quiet(), Arc::new(truth));
    r.wr(MPU, 0x37, 0x02);
    r.wr(AK, 0x0A, 0x16); // 16-bit, continuous mode 2 (100 Hz), at t = 0
    r.at_ms(9);
    assert_eq!(r.rd(AK, 0x02, 1), [0x00]);
    r.at_ms(10);
    assert_eq!(
        r.rd(AK, 0x02, 8),
        [0x01, 0x14, 0x00, 0x08, 0x00, 0xE0, 0xFF, 0x10]
    );
    // Reading ST2 ended the read: DRDY is clear until the next measurement.
    assert_eq!(r.rd(AK, 0x02, 1), [0x00]);
    // 14-bit output (BIT = 0): 0.6 µT/LSB → (5, 2, −8), BITM clear.
    r.wr(AK, 0x0A, 0x00);
    r.wr(AK, 0x0A, 0x06);
    r.at_ms(20);
    assert_eq!(
        r.rd(AK, 0x02, 8),
        [0x01, 0x05, 0x00, 0x02, 0x00, 0xF8, 0xFF, 0x00]
    );
    // Continuous mode 1 is 8 Hz: nothing before 125 ms.
    r.wr(AK, 0x0A, 0x00);
    r.wr(AK, 0x0A, 0x12);
    r.at_ms(144);
    assert_eq!(r.rd(AK, 0x02, 1), [0x00]);
    r.at_ms(145);
    assert_eq!(r.rd(AK, 0x02, 1), [0x01]);
    // Soft reset: back to power-down, no more measurements.
    r.wr(AK, 0x0B, 0x01);
    assert_eq!(r.rd(AK, 0x0A, 1), [0x00]);
    r.at_ms(400);
    assert_eq!(r.rd(AK, 0x09, 1), [0x00]);
    assert_eq!(r.rd(AK, 0x02, 1), [0x00]);
}

#[test]
fn ak8963_overrun_and_read_protection() {
    // Field along body x (= chip y) equal to the time in ms, in µT.
    let truth = FnTruth(|t_ns| fixed_mag([t_ns as f64 / 1e6, 0.0, 0.0]));
    let mut r = fixture(quiet(), Arc::new(truth));
    r.wr(MPU, 0x37, 0x02);
    r.wr(AK, 0x0A, 0x16);
    r.at_ms(30);
    // Three measurements, none read: DRDY and DOR.
    assert_eq!(r.rd(AK, 0x02, 1), [0x03]);
    assert_eq!(r.rd(AK, 0x09, 1), [0x10]);
    assert_eq!(r.rd(AK, 0x02, 1), [0x00]);
    r.at_ms(40);
    // Data read without ST2: 40 µT on chip y = 267 LSB (0x010B).
    assert_eq!(r.rd(AK, 0x05, 2), [0x0B, 0x01]);
    r.at_ms(50);
    // Protected: the 50 ms measurement was skipped (DOR), the data still read 40 µT.
    assert_eq!(r.rd(AK, 0x02, 1), [0x03]);
    assert_eq!(r.rd(AK, 0x05, 2), [0x0B, 0x01]);
    assert_eq!(r.rd(AK, 0x09, 1), [0x10]);
    r.at_ms(60);
    // 60 µT = 400 LSB = 0x0190.
    assert_eq!(r.rd(AK, 0x02, 8), [0x01, 0, 0, 0x90, 0x01, 0, 0, 0x10]);
}

#[test]
fn ak8963_overflow_from_the_field_and_by_injection() {
    let mut r = fixture(
        quiet(),
        Arc::new(FnTruth(|_| fixed_mag([3000.0, 2000.0, 0.0]))),
    );
    r.wr(MPU, 0x37, 0x02);
    r.wr(AK, 0x0A, 0x16);
    r.at_ms(10);
    assert_eq!(r.rd(AK, 0x09, 1), [0x18]); // HOFL | BITM
    lock(&r.imu).set_truth(Arc::new(StaticTruth::default()));
    lock(&r.imu).ak_mut().inject_overflows(1);
    r.at_ms(20);
    assert_eq!(r.rd(AK, 0x09, 1), [0x18]);
    r.at_ms(30);
    assert_eq!(r.rd(AK, 0x09, 1), [0x10]);
}

#[test]
fn injected_nacks_fail_whole_transactions() {
    let mut r = fixture(quiet(), Arc::new(StaticTruth::default()));
    lock(&r.imu).nack_next(2);
    for _ in 0..2 {
        let err = r.bus.write_read(MPU, &[0x75], &mut [0]).unwrap_err();
        assert_eq!(
            err.kind(),
            ErrorKind::NoAcknowledge(NoAcknowledgeSource::Data)
        );
    }
    assert_eq!(r.rd(MPU, 0x75, 1), [0x71]);
    lock(&r.imu).mpu_mut().set_who_am_i(0x70);
    assert_eq!(r.rd(MPU, 0x75, 1), [0x70]);
}

/// Gyro z in °/s at ±500 °/s (65.5 LSB per °/s) reads the sample's time in ms as LSB, so a
/// FIFO record shows which instant it holds.
fn time_in_gyro_z() -> FnTruth {
    FnTruth(|t_ns| TrueImu {
        gyro_rad_s: [0.0, 0.0, (t_ns as f64 / 1e6 / 65.5).to_radians()],
        ..fixed_mag([1.2, 3.0, 4.8])
    })
}

/// What the chip holds for one sample of [`time_in_gyro_z`] at `t_ms` (±4 g, ±500 °/s, 25 °C):
/// accel, temperature, gyro, big-endian, in register order.
fn mpu_record(t_ms: i16) -> Vec<u8> {
    let mut record = vec![0, 0, 0, 0, 0x20, 0x00, 0x05, 0x37, 0, 0, 0, 0];
    record.extend_from_slice(&t_ms.to_be_bytes());
    record
}

/// 200 Hz from t = 0, ±4 g, ±500 °/s, DLPF 41 Hz.
fn at_200_hz(r: &mut Fixture) {
    r.wr(MPU, 0x1A, 0x03);
    r.wr(MPU, 0x19, 0x04);
    r.wr(MPU, 0x1B, 0x08);
    r.wr(MPU, 0x1C, 0x08);
}

#[test]
fn fifo_holds_every_sample_in_register_order_and_pops_on_read() {
    let mut r = fixture(quiet(), Arc::new(time_in_gyro_z()));
    at_200_hz(&mut r);
    r.wr(MPU, 0x23, 0xF8); // temperature, gyro x/y/z, accel
    r.wr(MPU, 0x6A, 0x40); // FIFO on
    r.at_ms(26);
    // Five samples (5 … 25 ms) of 14 bytes: 70 = 0x0046, big-endian.
    assert_eq!(r.rd(MPU, 0x72, 2), [0x00, 0x46]);
    let want: Vec<u8> = [5, 10, 15, 20, 25]
        .into_iter()
        .flat_map(mpu_record)
        .collect();
    assert_eq!(lock(&r.imu).mpu().fifo_contents(), want);
    // A burst from FIFO_R_W stays there: 20 bytes pop 20 bytes.
    assert_eq!(r.rd(MPU, 0x74, 20), want[..20]);
    assert_eq!(r.rd(MPU, 0x72, 2), [0x00, 50]);
    assert_eq!(r.rd(MPU, 0x74, 50), want[20..]);
    // Empty: a read repeats the last byte, the count stays 0.
    assert_eq!(r.rd(MPU, 0x74, 2), [want[69]; 2]);
    assert_eq!(r.rd(MPU, 0x72, 2), [0, 0]);
    // Accel only: 6 bytes a sample; the count passes 255 (0x0102 = 258 after 43 samples).
    r.wr(MPU, 0x23, 0x08);
    r.at_ms(26 + 43 * 5);
    assert_eq!(r.rd(MPU, 0x72, 2), [0x01, 0x02]);
    // FIFO_RST empties it and clears itself.
    r.wr(MPU, 0x6A, 0x44);
    assert_eq!(r.rd(MPU, 0x72, 2), [0, 0]);
    assert_eq!(r.rd(MPU, 0x6A, 1), [0x40]);
    // USER_CTRL.FIFO_EN off: nothing more is written.
    r.wr(MPU, 0x6A, 0x00);
    r.at_ms(400);
    assert_eq!(r.rd(MPU, 0x72, 2), [0, 0]);
}

#[test]
fn fifo_overflow_drops_the_oldest_bytes_and_sets_fifo_oflow_int() {
    let mut r = fixture(quiet(), Arc::new(time_in_gyro_z()));
    at_200_hz(&mut r);
    r.wr(MPU, 0x23, 0xF8);
    r.wr(MPU, 0x6A, 0x40);
    r.at_ms(36 * 5);
    // 36 records of 14 bytes = 504: full to the last whole record, no overflow.
    assert_eq!(r.rd(MPU, 0x72, 2), [0x01, 0xF8]);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x01]);
    r.at_ms(37 * 5);
    // The 37th needs 518 bytes: the 6 oldest are dropped, the FIFO starts 6 bytes into the
    // 5 ms record, and the overflow flag is up until INT_STATUS is read.
    assert_eq!(r.rd(MPU, 0x72, 2), [0x02, 0x00]);
    let contents = lock(&r.imu).mpu().fifo_contents();
    assert_eq!(contents[..8], mpu_record(5)[6..]);
    assert_eq!(contents[8..22], mpu_record(10));
    assert_eq!(contents[498..], mpu_record(185));
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x11]);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x00]);

    // CONFIG.FIFO_MODE = 1: a full FIFO keeps its old bytes (the grid restarts with CONFIG).
    r.wr(MPU, 0x6A, 0x44);
    r.wr(MPU, 0x1A, 0x43);
    r.at_ms(185 + 37 * 5);
    // (The chip plays the instants due when the host next talks to it.)
    assert_eq!(r.rd(MPU, 0x72, 2), [0x02, 0x00]);
    let contents = lock(&r.imu).mpu().fifo_contents();
    assert_eq!(contents[..14], mpu_record(190));
    // The 37th record was cut after 8 bytes.
    assert_eq!(contents[504..], mpu_record(185 + 37 * 5)[..8]);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x11]);

    // A host that does not read for a minute: the FIFO is full and flagged, not stalled.
    r.wr(MPU, 0x1A, 0x03);
    r.wr(MPU, 0x6A, 0x44);
    r.at_ms(60_000);
    assert_eq!(r.rd(MPU, 0x72, 2), [0x02, 0x00]);
    assert_eq!(r.rd(MPU, 0x3A, 1), [0x11]);
    // H_RESET empties the FIFO.
    r.wr(MPU, 0x6B, 0x80);
    r.at_ms(60_010);
    assert_eq!(r.rd(MPU, 0x72, 2), [0, 0]);
}

#[test]
fn i2c_master_slv0_copies_the_ak8963_into_ext_sens_data_and_the_fifo() {
    // Body field (1.2, 3, 4.8) µT: the AK8963 block is [DRDY, 20, 0, 8, 0, −32 (LE), BITM].
    let block = [0x01, 0x14, 0x00, 0x08, 0x00, 0xE0, 0xFF, 0x10];
    let mut r = fixture(quiet(), Arc::new(time_in_gyro_z()));
    at_200_hz(&mut r);
    r.wr(MPU, 0x37, 0x02);
    r.wr(AK, 0x0A, 0x16); // continuous 100 Hz from t = 0, in bypass
    r.wr(MPU, 0x37, 0x00);
    r.wr(MPU, 0x24, 0x4D); // WAIT_FOR_ES, 400 kHz
    r.wr(MPU, 0x25, 0x8C); // SLV0 reads 0x0C
    r.wr(MPU, 0x26, 0x02); // from ST1
    r.wr(MPU, 0x27, 0x88); // 8 bytes
    r.wr(MPU, 0x23, 0xF9); // … and SLV0's bytes to the FIFO
    r.wr(MPU, 0x6A, 0x60); // FIFO and master on
    assert!(r.bus.write_read(AK, &[0x00], &mut [0]).is_err());
    r.at_ms(21);
    // Samples at 5, 10, 15, 20 ms; the AK8963 measures at 10 and 20 ms. The master reads ST1..ST2
    // at every sample, so DRDY shows at 10 and 20 ms only (the read of ST2 clears it).
    let not_ready = [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x10];
    let mut want = Vec::new();
    for (t_ms, ext) in [(5, not_ready), (10, block), (15, block), (20, block)] {
        want.extend(mpu_record(t_ms));
        let mut ext = ext;
        if t_ms == 15 {
            ext[0] = 0x00; // the 10 ms field again, DRDY clear
        }
        want.extend(ext);
    }
    assert_eq!(r.rd(MPU, 0x72, 2), [0x00, 88]);
    assert_eq!(lock(&r.imu).mpu().fifo_contents(), want);
    // EXT_SENS_DATA_00..07 hold the last copy; reading them does not touch the AK8963.
    assert_eq!(r.rd(MPU, 0x49, 8), block);
    assert_eq!(r.rd(MPU, 0x36, 1), [0x00]);
    // A 22-byte burst from ACCEL_XOUT_H reads the newest sample and the copy together.
    let burst = r.rd(MPU, 0x3B, 22);
    assert_eq!(burst[..14], mpu_record(20));
    assert_eq!(burst[14..], block);

    // Without WAIT_FOR_ES a record carries the copy the master made at the previous sample.
    r.wr(MPU, 0x6A, 0x64);
    r.wr(MPU, 0x24, 0x0D);
    r.at_ms(31);
    assert_eq!(r.rd(MPU, 0x72, 2), [0x00, 44]);
    let contents = lock(&r.imu).mpu().fifo_contents();
    let mut no_new_field = block;
    no_new_field[0] = 0x00;
    // The 25 ms record: the copy made at 20 ms (DRDY); the 30 ms record: the one made at 25 ms
    // (no new field); the 30 ms field came after its record.
    assert_eq!(contents[14..22], block);
    assert_eq!(contents[36..44], no_new_field);
    assert_eq!(r.rd(MPU, 0x49, 8), block);

    // SLV0 addressing nobody: I2C_SLV0_NACK, EXT_SENS_DATA kept.
    r.wr(MPU, 0x25, 0x8D);
    r.at_ms(36);
    assert_eq!(r.rd(MPU, 0x36, 1), [0x01]);
    assert_eq!(r.rd(MPU, 0x49, 8), block);
}

mod with_driver {
    use scan3d_edge::drivers::imu::{
        Chip, Error, FifoClock, FifoRead, ImuConfig, ImuReading, Mpu9250, ReadMode,
        fifo_read_interval_ns,
    };

    use super::*;

    /// The per-sample path: data registers and the AK8963 in bypass.
    fn registers() -> ImuConfig {
        ImuConfig {
            read_mode: ReadMode::Registers,
            ..ImuConfig::default()
        }
    }

    fn started(config: ImuEmulatorConfig, truth: Arc<dyn ImuTruth>) -> (Fixture, Mpu9250<I2cBus>) {
        started_with(config, truth, registers())
    }

    fn started_with(
        config: ImuEmulatorConfig,
        truth: Arc<dyn ImuTruth>,
        driver: ImuConfig,
    ) -> (Fixture, Mpu9250<I2cBus>) {
        let r = fixture(config, truth);
        let mut imu = Mpu9250::new(r.bus.clone(), driver);
        let mut delay = r.clock.clone();
        imu.init(&mut delay).unwrap();
        (r, imu)
    }

    /// FIFO batches every `interval_ns` for `ms`: each sample with the time of the count read.
    fn run_fifo(
        r: &Fixture,
        imu: &mut Mpu9250<I2cBus>,
        interval_ns: u64,
        ms: u64,
    ) -> Vec<(ImuReading, u64)> {
        let end = r.clock.now_ns() + ms * 1_000_000;
        let mut out = Vec::new();
        let mut readings = Vec::new();
        while r.clock.now_ns() + interval_ns <= end {
            r.clock.advance_ns(interval_ns);
            let count = imu.fifo_count().unwrap();
            readings.clear();
            match imu.read_fifo(count, &mut readings).unwrap() {
                FifoRead::Samples { samples, .. } => assert_eq!(samples, readings.len()),
                other => panic!("{other:?} at {} ns", r.clock.now_ns()),
            }
            out.extend(readings.iter().map(|&reading| (reading, r.clock.now_ns())));
        }
        out
    }

    /// Reads for `ms` milliseconds at the 200 Hz sample rate.
    fn run(r: &Fixture, imu: &mut Mpu9250<I2cBus>, ms: u64) -> Vec<ImuReading> {
        (0..ms / 5)
            .map(|_| {
                r.clock.advance_ns(5_000_000);
                imu.read().unwrap()
            })
            .collect()
    }

    fn within(got: [f32; 3], want: [f64; 3], tol: f64) -> bool {
        got.iter()
            .zip(want)
            .all(|(g, w)| (f64::from(*g) - w).abs() <= tol)
    }

    #[test]
    fn readings_match_the_truth_within_noise_and_the_gyro_bias_is_removed() {
        let mut config = ImuEmulatorConfig::default();
        config.mpu.gyro_bias_rad_s = [0.01, -0.02, 0.005];
        let truth = StaticTruth {
            heading_rad: 30f64.to_radians(),
            field: EarthField::default(),
        };
        let (r, mut imu) = started(config, Arc::new(truth));
        // Bias from 200 samples: error ≈ σ/√200 ≈ 0.0001 rad/s, plus half an LSB.
        let lsb_gyro = 1f64.to_radians() / 65.5;
        assert!(
            within(imu.gyro_bias(), [0.01, -0.02, 0.005], 0.0005 + lsb_gyro),
            "bias {:?}",
            imu.gyro_bias()
        );
        let readings = run(&r, &mut imu, 1000);
        let lsb_accel = 9.80665 / 8192.0;
        let field = truth.field.in_level_body(truth.heading_rad);
        let mut mags = 0;
        for reading in &readings {
            assert!(within(
                reading.accel_m_s2,
                [0.0, 0.0, 9.80665],
                5.0 * 0.02 + lsb_accel
            ));
            assert!(
                within(reading.gyro_rad_s, [0.0; 3], 5.0 * 0.0012 + 2.0 * lsb_gyro),
                "{:?}",
                reading.gyro_rad_s
            );
            assert!((reading.temp_c - 25.0).abs() < 0.01);
            if let Some(m) = reading.mag_ut {
                mags += 1;
                // 5σ plus one LSB (0.15 µT × ASA ≈ 0.18 µT).
                assert!(within(m, field, 5.0 * 0.3 + 0.2), "{m:?} vs {field:?}");
            }
        }
        // 1 s at 100 Hz.
        assert!((99..=101).contains(&mags), "{mags} field samples");
        let mean_gz = readings
            .iter()
            .map(|r| f64::from(r.gyro_rad_s[2]))
            .sum::<f64>()
            / 200.0;
        assert!(mean_gz.abs() < 0.0005, "residual gyro z bias {mean_gz}");
    }

    #[test]
    fn a_constant_yaw_rate_and_the_turning_field() {
        let truth = YawRateTruth {
            heading0_rad: 0.0,
            yaw_rate_rad_s: 20f64.to_radians(),
            field: EarthField::default(),
        };
        let mut config = quiet();
        config.ak.asa = [0xB0, 0xB3, 0xA6];
        // At rest during the bias estimate is not possible on a turning table; skip it.
        let r = fixture(config, Arc::new(truth));
        let mut imu = Mpu9250::new(
            r.bus.clone(),
            ImuConfig {
                gyro_bias_samples: 0,
                ..registers()
            },
        );
        imu.init(&mut r.clock.clone()).unwrap();
        let mut mags = 0;
        for _ in 0..100 {
            let reading = run(&r, &mut imu, 5)[0];
            let lsb = 1f64.to_radians() / 65.5;
            assert!(within(
                reading.gyro_rad_s,
                [0.0, 0.0, 20f64.to_radians()],
                lsb
            ));
            if let Some(m) = reading.mag_ut {
                // The field turns 0.2° per 10 ms measurement period (0.08 µT at 24 µT).
                let want = truth
                    .field
                    .in_level_body(truth.heading_at(r.clock.now_ns()));
                assert!(within(m, want, 0.1 + 0.2), "{m:?} vs {want:?}");
                mags += 1;
            }
        }
        assert_eq!(mags, 50);
    }

    #[test]
    fn a_field_along_the_ak8963_x_axis_is_the_drivers_y() {
        let truth = FnTruth(|_| fixed_mag([0.0, 40.0, 0.0]));
        let (r, mut imu) = started(quiet(), Arc::new(truth));
        r.clock.advance_ns(10_000_000);
        // The chip's own registers: HX = 40 / 0.15 = 267 LSB, HY = HZ = 0.
        let mut block = [0u8; 8];
        r.bus.clone().write_read(AK, &[0x02], &mut block).unwrap();
        assert_eq!(block[1..7], [0x0B, 0x01, 0, 0, 0, 0]);
        let m = run(&r, &mut imu, 20)
            .into_iter()
            .find_map(|reading| reading.mag_ut)
            .unwrap();
        assert!(within(m, [0.0, 40.0, 0.0], 0.08), "{m:?}");
    }

    #[test]
    fn wrong_who_am_i_is_a_clear_error() {
        let r = fixture(quiet(), Arc::new(StaticTruth::default()));
        lock(&r.imu).mpu_mut().set_who_am_i(0x70);
        let mut imu = Mpu9250::new(r.bus.clone(), ImuConfig::default());
        let err = imu.init(&mut r.clock.clone()).unwrap_err();
        assert!(matches!(
            err,
            Error::WrongChip {
                chip: Chip::Mpu9250,
                address: 0x68,
                found: 0x70
            }
        ));
        assert_eq!(
            err.to_string(),
            "MPU-9250 at I2C address 0x68: WHO_AM_I is 0x70, expected 0x71 (MPU-9250) or 0x73 \
             (MPU-9255); 0x70 is an MPU-6500, which has no magnetometer"
        );
    }

    #[test]
    fn nacks_are_retried_then_reported_with_chip_and_address() {
        let (r, mut imu) = started(quiet(), Arc::new(StaticTruth::default()));
        let before = imu.stats();
        lock(&r.imu).nack_next(3);
        r.clock.advance_ns(5_000_000);
        imu.read().unwrap();
        assert_eq!(imu.stats().retries - before.retries, 3);

        lock(&r.imu).nack_next(4);
        let err = imu.read().unwrap_err();
        assert!(matches!(
            err,
            Error::I2c {
                chip: Chip::Mpu9250,
                address: 0x68,
                attempts: 4,
                source: BusError::DataNack(0x68),
            }
        ));
        assert!(
            err.to_string()
                .starts_with("MPU-9250 at I2C address 0x68: bus error after 4 attempt(s): "),
            "{err}"
        );

        // The I2C master switched on behind the driver's back hides the AK8963 (asked only when
        // its next field is due: at most every other read at 200 Hz).
        r.bus.clone().write(MPU, &[0x6A, 0x20]).unwrap();
        r.clock.advance_ns(20_000_000);
        let err = (0..3)
            .find_map(|_| imu.read().err())
            .expect("the AK8963 read fails within three reads");
        assert!(matches!(
            err,
            Error::I2c {
                chip: Chip::Ak8963,
                address: 0x0C,
                attempts: 4,
                source: BusError::AddressNack(0x0C),
            }
        ));
        assert!(err.to_string().starts_with("AK8963 at I2C address 0x0c"));
    }

    #[test]
    fn magnetometer_overflow_drops_the_sample_and_counts_it() {
        let (r, mut imu) = started(quiet(), Arc::new(StaticTruth::default()));
        run(&r, &mut imu, 20); // drain what accumulated during the bias estimate
        let before = imu.stats();
        lock(&r.imu).ak_mut().inject_overflows(3);
        let readings = run(&r, &mut imu, 100);
        let stats = imu.stats();
        assert_eq!(stats.mag_overflows - before.mag_overflows, 3);
        // 10 measurements in 100 ms: 3 dropped, 7 delivered.
        assert_eq!(stats.mag_samples - before.mag_samples, 7);
        assert_eq!(readings.iter().filter(|r| r.mag_ut.is_some()).count(), 7);
    }

    #[test]
    fn fifo_batches_carry_the_same_samples_and_rates_in_few_transactions() {
        let mut config = ImuEmulatorConfig::default();
        config.mpu.gyro_bias_rad_s = [0.01, -0.02, 0.005];
        let truth = StaticTruth {
            heading_rad: 30f64.to_radians(),
            field: EarthField::default(),
        };
        let (r, mut imu) = started_with(config, Arc::new(truth), ImuConfig::default());
        // The host bus no longer sees the AK8963: the MPU's master reads it.
        assert!(r.bus.clone().write_read(AK, &[0x00], &mut [0]).is_err());
        let lsb_gyro = 1f64.to_radians() / 65.5;
        assert!(
            within(imu.gyro_bias(), [0.01, -0.02, 0.005], 0.0005 + lsb_gyro),
            "bias {:?}",
            imu.gyro_bias()
        );
        let interval = fifo_read_interval_ns(40, 5_000_000, imu.fifo_layout().unwrap());
        run_fifo(&r, &mut imu, interval, 100); // past the start
        let before = r.bus.stats();
        let t0 = r.clock.now_ns();
        let readings = run_fifo(&r, &mut imu, interval, 10_000);
        let seconds = (r.clock.now_ns() - t0) as f64 / 1e9;
        let after = r.bus.stats();
        let per_second = (after.transactions - before.transactions) as f64 / seconds;
        let rate = readings.len() as f64 / seconds;
        let mags = readings.iter().filter(|(r, _)| r.mag_ut.is_some()).count();
        println!(
            "IMU FIFO at 200 Hz: {per_second:.1} I2C transactions/s, {rate:.1} samples/s, {:.1} \
             field samples/s",
            mags as f64 / seconds
        );
        // Two transactions (count, records) per batch of 7 or 8 samples.
        assert!(
            (per_second - 2e9 / interval as f64).abs() < 0.5,
            "{per_second}"
        );
        assert!((rate - 200.0).abs() < 1.0, "{rate} samples/s");
        assert!((mags as f64 / seconds - 100.0).abs() < 1.0, "{mags} fields");
        let field = truth.field.in_level_body(truth.heading_rad);
        let lsb_accel = 9.80665 / 8192.0;
        for (reading, _) in &readings {
            assert!(within(
                reading.accel_m_s2,
                [0.0, 0.0, 9.80665],
                5.0 * 0.02 + lsb_accel
            ));
            assert!(within(
                reading.gyro_rad_s,
                [0.0; 3],
                5.0 * 0.0012 + 2.0 * lsb_gyro
            ));
            assert!((reading.temp_c - 25.0).abs() < 0.01);
            if let Some(m) = reading.mag_ut {
                assert!(within(m, field, 5.0 * 0.3 + 0.2), "{m:?} vs {field:?}");
            }
        }
        // Fields every other sample, as the AK8963 measures at half the rate.
        assert!(
            readings
                .windows(2)
                .all(|w| w[0].0.mag_ut.is_some() != w[1].0.mag_ut.is_some())
        );
        let stats = imu.stats();
        assert_eq!((stats.fifo_overflows, stats.fifo_discards), (0, 0));
        // The probe's single read works in FIFO mode too: data registers + the master's copy.
        let reading = imu.read().unwrap();
        assert!(within(reading.accel_m_s2, [0.0, 0.0, 9.80665], 0.2));
    }

    #[test]
    fn fifo_samples_are_stamped_with_their_measurement_times() {
        // Gyro z in °/s is 0.5 × (the time in ms, modulo 400): the reading says when it was
        // measured, to 1/65.5/0.5 ≈ 0.03 ms.
        let truth = FnTruth(|t_ns| TrueImu {
            gyro_rad_s: [
                0.0,
                0.0,
                (0.5 * ((t_ns / 1000) % 400_000) as f64 / 1000.0).to_radians(),
            ],
            ..fixed_mag([20.0, 0.0, -40.0])
        });
        let driver = ImuConfig {
            gyro_bias_samples: 0,
            ..ImuConfig::default()
        };
        let (r, mut imu) = started_with(quiet(), Arc::new(truth), driver);
        let interval = fifo_read_interval_ns(40, 5_000_000, imu.fifo_layout().unwrap());
        let mut clock = FifoClock::new(5_000_000);
        let mut times = Vec::new();
        let mut worst_ms: f64 = 0.0;
        let mut stamped = 0;
        for batch in 0..200 {
            // A host that wakes a little late, by 0 to 2.9 ms.
            r.clock.advance_ns(interval + (batch * 7919 % 30) * 100_000);
            let count = imu.fifo_count().unwrap();
            let counted = r.clock.now_ns();
            let mut readings = Vec::new();
            let FifoRead::Samples { samples, restarted } =
                imu.read_fifo(count, &mut readings).unwrap()
            else {
                panic!("no samples");
            };
            assert_eq!(restarted, batch == 0);
            times.clear();
            clock.stamp(counted, samples, &mut times);
            for (reading, &t) in readings.iter().zip(&times) {
                assert!(t <= counted);
                let measured_ms = f64::from(reading.gyro_rad_s[2]).to_degrees() / 0.5;
                let stamped_ms = (t % 400_000_000) as f64 / 1e6;
                let mut error = stamped_ms - measured_ms;
                if error.abs() > 200.0 {
                    error -= 400.0 * error.signum(); // across the wrap
                }
                if batch >= 20 {
                    worst_ms = worst_ms.max(error.abs());
                    stamped += 1;
                }
            }
        }
        println!("FIFO stamps after the first 20 batches: worst error {worst_ms:.3} ms");
        assert!(stamped > 1000);
        assert!(worst_ms < 1.0, "worst stamp error {worst_ms} ms");
    }

    #[test]
    fn an_overflow_is_counted_reset_and_nothing_misaligned_is_decoded() {
        let (r, mut imu) = started_with(
            quiet(),
            Arc::new(StaticTruth::default()),
            ImuConfig {
                gyro_bias_samples: 0,
                ..ImuConfig::default()
            },
        );
        let interval = fifo_read_interval_ns(40, 5_000_000, imu.fifo_layout().unwrap());
        run_fifo(&r, &mut imu, interval, 100);
        // 200 ms unread: 40 records of 22 bytes do not fit in 512.
        r.clock.advance_ns(200_000_000);
        let count = imu.fifo_count().unwrap();
        assert_eq!(count, 512);
        let mut readings = Vec::new();
        assert_eq!(
            imu.read_fifo(count, &mut readings).unwrap(),
            FifoRead::Overflow { count: 512 }
        );
        assert!(readings.is_empty());
        assert_eq!(imu.stats().fifo_overflows, 1);
        // The FIFO was reset: the next batch is a new stream of whole, sane samples.
        r.clock.advance_ns(interval);
        let count = imu.fifo_count().unwrap();
        assert!(matches!(
            imu.read_fifo(count, &mut readings).unwrap(),
            FifoRead::Samples {
                samples: 7..=8,
                restarted: true
            }
        ));
        for reading in &readings {
            assert!(within(reading.accel_m_s2, [0.0, 0.0, 9.80665], 0.01));
            assert!(within(reading.gyro_rad_s, [0.0; 3], 0.001));
        }
    }

    #[test]
    fn a_fifo_that_lost_its_record_boundary_is_discarded_not_decoded() {
        let (r, mut imu) = started_with(
            quiet(),
            Arc::new(StaticTruth::default()),
            ImuConfig {
                gyro_bias_samples: 0,
                ..ImuConfig::default()
            },
        );
        let interval = fifo_read_interval_ns(40, 5_000_000, imu.fifo_layout().unwrap());
        run_fifo(&r, &mut imu, interval, 100);
        // Someone else pops 5 bytes: the records now start 5 bytes late.
        r.clock.advance_ns(interval);
        r.bus.clone().write_read(MPU, &[0x74], &mut [0; 5]).unwrap();
        let count = imu.fifo_count().unwrap();
        let mut readings = Vec::new();
        assert_eq!(
            imu.read_fifo(count, &mut readings).unwrap(),
            FifoRead::Misaligned
        );
        assert!(readings.is_empty());
        assert_eq!(imu.stats().fifo_discards, 1);
        assert_eq!(lock(&r.imu).mpu().peek(0x73), 0);

        // A failed data read is not retried (it may have popped bytes): the FIFO is reset.
        r.clock.advance_ns(interval);
        let count = imu.fifo_count().unwrap();
        lock(&r.imu).nack_next(1);
        assert!(imu.read_fifo(count, &mut readings).is_err());
        assert_eq!(imu.stats().fifo_discards, 2);
        r.clock.advance_ns(interval);
        let count = imu.fifo_count().unwrap();
        assert!(matches!(
            imu.read_fifo(count, &mut readings).unwrap(),
            FifoRead::Samples {
                samples: 7..=8,
                restarted: true
            }
        ));
        assert!(
            readings
                .iter()
                .all(|r| within(r.accel_m_s2, [0.0, 0.0, 9.80665], 0.01))
        );
    }

    #[test]
    fn i2c_transactions_per_second_at_the_default_rates() {
        let (r, mut imu) = started(
            ImuEmulatorConfig::default(),
            Arc::new(StaticTruth::default()),
        );
        run(&r, &mut imu, 20); // drain what accumulated during the bias estimate
        let before = r.bus.stats();
        let t0 = r.clock.now_ns();
        let readings = run(&r, &mut imu, 10_000);
        let seconds = (r.clock.now_ns() - t0) as f64 / 1e9;
        let after = r.bus.stats();
        let per_second = (after.transactions - before.transactions) as f64 / seconds;
        let bytes_read = (after.bytes_read - before.bytes_read) as f64 / seconds;
        let mags = readings.iter().filter(|r| r.mag_ut.is_some()).count();
        println!(
            "IMU at 200 Hz accel/gyro + 100 Hz mag: {per_second} I2C transactions/s, \
             {bytes_read} data bytes read/s, {} field samples/s",
            mags as f64 / seconds
        );
        // One 14-byte MPU burst per sample, and one 8-byte AK8963 block per field sample: the
        // magnetometer is read only when its next field is due.
        assert_eq!(per_second, 300.0);
        assert_eq!(bytes_read, 200.0 * 14.0 + 100.0 * 8.0);
        assert_eq!(mags, 1000);
        assert_eq!(imu.stats().mag_overflows, 0);
    }
}
