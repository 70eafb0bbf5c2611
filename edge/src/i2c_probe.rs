//! `scan3d-edge probe imu` and `probe stepper`: the wiring checks for the I2C devices, in the
//! JSON-lines style of the lidar probes.
//!
//! The cores are generic over embedded-hal `I2c` and `DelayNs`, so the same code runs on the
//! Pi's bus (rppal) and on the simulator's register-level emulators in tests.

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;
use nalgebra::Vector3;
use serde::Serialize;

use crate::drivers::imu::{ImuConfig, Mpu9250};
use crate::drivers::stepper::{Direction, MotorHat, Move, Stepper, StepperConfig};
use crate::madgwick::Madgwick;

/// One line of I2C probe output.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum I2cProbeLine {
    /// What the IMU's init sequence found.
    ImuInfo {
        /// MPU-9250 I2C address, e.g. `"0x68"`.
        address: String,
        /// MPU WHO_AM_I, e.g. `"0x71"`.
        who_am_i: String,
        /// AK8963 WIA (`"0x48"`), absent when the magnetometer is off.
        ak8963_wia: Option<String>,
        /// AK8963 fuse-ROM sensitivity adjustment (ASAX/Y/Z).
        asa: Option<[u8; 3]>,
        /// Gyro bias estimated at rest, rad/s.
        gyro_bias_rad_s: [f32; 3],
    },
    /// One converted IMU sample.
    Imu {
        /// Specific force, m/s².
        accel_m_s2: [f32; 3],
        /// Angular rate, rad/s.
        gyro_rad_s: [f32; 3],
        /// Magnetic field, µT (absent when no new magnetometer sample).
        mag_ut: Option<[f32; 3]>,
        /// Die temperature, °C.
        temp_c: f32,
    },
    /// The Madgwick orientation after the samples.
    Orientation {
        /// Quaternion w, x, y, z (sensor → earth, NWU).
        quaternion_wxyz: [f64; 4],
        /// Roll, degrees.
        roll_deg: f64,
        /// Pitch, degrees.
        pitch_deg: f64,
        /// Yaw from magnetic north, counter-clockwise, degrees.
        yaw_deg: f64,
    },
    /// The stepper moved (or came back).
    Stepper {
        /// Motor HAT I2C address, e.g. `"0x60"`.
        address: String,
        /// Steps made by this move (signed: negative = backward).
        steps: i64,
        /// Commanded output-shaft angle after the move, degrees.
        angle_deg: f64,
    },
}

/// Why an I2C probe failed: the driver's error, as text naming the chip and the address.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct I2cProbeError(String);

fn hex(value: u8) -> String {
    format!("0x{value:02x}")
}

/// Initialises the IMU, prints its ids, `samples` readings `period_ms` apart and the
/// orientation Madgwick makes of them; returns the bus.
pub fn probe_imu<I: I2c, D: DelayNs>(
    bus: I,
    delay: &mut D,
    config: ImuConfig,
    samples: usize,
    period_ms: u32,
    mut emit: impl FnMut(&I2cProbeLine),
) -> Result<I, I2cProbeError> {
    let address = config.address;
    let mut imu = Mpu9250::new(bus, config);
    let ids = imu.init(delay).map_err(|e| I2cProbeError(e.to_string()))?;
    emit(&I2cProbeLine::ImuInfo {
        address: hex(address),
        who_am_i: hex(ids.who_am_i),
        ak8963_wia: ids.wia.map(hex),
        asa: ids.asa,
        gyro_bias_rad_s: imu.gyro_bias(),
    });
    let vector = |v: [f32; 3]| Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
    let mut filter: Option<Madgwick> = None;
    let dt_s = f64::from(period_ms) / 1000.0;
    for _ in 0..samples {
        delay.delay_ms(period_ms);
        let reading = imu.read().map_err(|e| I2cProbeError(e.to_string()))?;
        emit(&I2cProbeLine::Imu {
            accel_m_s2: reading.accel_m_s2,
            gyro_rad_s: reading.gyro_rad_s,
            mag_ut: reading.mag_ut,
            temp_c: reading.temp_c,
        });
        let (gyro, accel) = (vector(reading.gyro_rad_s), vector(reading.accel_m_s2));
        match (&mut filter, reading.mag_ut) {
            (Some(filter), Some(mag)) => {
                filter.update_marg(gyro, accel, vector(mag), dt_s);
            }
            (Some(filter), None) => {
                filter.update_imu(gyro, accel, dt_s);
            }
            (None, Some(mag)) => filter = Madgwick::from_accel_mag(0.1, accel, vector(mag)).ok(),
            (None, None) => {}
        }
    }
    if let Some(filter) = &filter {
        let (roll, pitch, yaw) = filter.euler();
        emit(&I2cProbeLine::Orientation {
            quaternion_wxyz: filter.wxyz(),
            roll_deg: roll.to_degrees(),
            pitch_deg: pitch.to_degrees(),
            yaw_deg: yaw.to_degrees(),
        });
    }
    Ok(imu.destroy())
}

/// Initialises the motor HAT, turns the stepper `steps` forward, then back home, and
/// releases the coils; returns the bus.
pub fn probe_stepper<I: I2c, D: DelayNs>(
    bus: I,
    delay: &mut D,
    config: &StepperConfig,
    steps: u64,
    mut emit: impl FnMut(&I2cProbeLine),
) -> Result<I, I2cProbeError> {
    let error = |e: &dyn std::fmt::Display| I2cProbeError(e.to_string());
    let mut stepper = Stepper::new(config).map_err(|e| error(&e))?;
    let mut hat = MotorHat::new(bus, config.address, config.retries);
    hat.init(delay).map_err(|e| error(&e))?;
    let address = hex(config.address);
    let forward = Move {
        direction: Direction::Forward,
        steps,
    };
    stepper
        .run(&mut hat, forward, delay)
        .map_err(|e| error(&e))?;
    emit(&I2cProbeLine::Stepper {
        address: address.clone(),
        steps: i64::try_from(steps).unwrap_or(i64::MAX),
        angle_deg: stepper.commanded_angle_deg(),
    });
    let back = stepper
        .return_home(&mut hat, delay)
        .map_err(|e| error(&e))?;
    stepper.release(&mut hat).map_err(|e| error(&e))?;
    emit(&I2cProbeLine::Stepper {
        address,
        steps: i64::try_from(back.steps).unwrap_or(i64::MAX) * back.direction.sign(),
        angle_deg: stepper.commanded_angle_deg(),
    });
    Ok(hat.destroy())
}

/// `DelayNs` by sleeping the thread: the delay of the real I2C probes.
#[derive(Debug, Default, Clone, Copy)]
pub struct ThreadDelay;

impl DelayNs for ThreadDelay {
    fn delay_ns(&mut self, ns: u32) {
        std::thread::sleep(std::time::Duration::from_nanos(ns.into()));
    }
}
