//! Register-level MPU-9250 + AK8963 emulator, driven by a ground-truth motion.
//!
//! [`ImuEmulator`] is the MPU-9250 package as the host bus sees it: the accel/gyro die
//! ([`Mpu9250Emulator`], 0x68/0x69) and the magnetometer die ([`Ak8963Emulator`], 0x0C, which
//! acknowledges only while the MPU's bypass is on). It implements [`crate::i2c::I2cDevice`], so
//! it sits on the shared simulated [`crate::i2c::I2cBus`] (an `embedded_hal::i2c::I2c`) next to
//! the motor HAT, and the edge's real driver runs against it unchanged. Unknown addresses, the
//! AK8963 without bypass and the MPU during H_RESET NACK their address.
//!
//! The MPU's I2C master reaches the AK8963 over the package's auxiliary bus ([`AuxBus`]): with
//! USER_CTRL.I2C_MST_EN the host no longer sees 0x0C, and SLV0 copies the AK8963's registers
//! into EXT_SENS_DATA and the FIFO at the sample rate (see [`Mpu9250Emulator`]).
//!
//! Values come from an [`ImuTruth`] sampled on the chips' own sampling grids (set by
//! SMPLRT_DIV/CONFIG and the AK8963 mode), plus per-axis noise and constant biases, quantised
//! at the configured full scale. Time is pushed in by the bus (from a
//! [`scan3d_edge::clock::Clock`], e.g. [`crate::i2c::SimClock`]); the chip cores take `now_ns`
//! and never read a clock.
//!
//! Fault injection: [`ImuEmulator::nack_next`] (data NACK on the next transfers),
//! [`Mpu9250Emulator::set_who_am_i`] (wrong chip), [`Ak8963Emulator::inject_overflows`] (HOFL).

mod ak8963;
pub mod errors;
mod fifo;
mod mpu9250;
mod truth;

use std::sync::Arc;

pub use ak8963::{Ak8963Emulator, AkEmulatorConfig};
pub use fifo::{FIFO_CAPACITY, Fifo};
pub use mpu9250::{AuxBus, MAX_CATCH_UP, Mpu9250Emulator, MpuEmulatorConfig};
pub use truth::{
    EarthField, ImuTruth, MountedImuTruth, STANDARD_GRAVITY, StaticTruth, TrueImu, YawRateTruth,
};

use crate::i2c::{I2cDevice, Nack};

/// The AK8963's address in bypass mode.
pub const AK8963_ADDRESS: u8 = 0x0C;

/// Configuration of both dies.
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(default)]
pub struct ImuEmulatorConfig {
    /// The accel/gyro die.
    pub mpu: MpuEmulatorConfig,
    /// The magnetometer die.
    pub ak: AkEmulatorConfig,
}

/// The MPU-9250 package on a simulated I2C bus: MPU-9250 + AK8963 sharing one ground truth.
pub struct ImuEmulator {
    mpu: Mpu9250Emulator,
    ak: Ak8963Emulator,
    truth: Arc<dyn ImuTruth>,
    now_ns: u64,
    nacks_pending: u32,
}

impl std::fmt::Debug for ImuEmulator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ImuEmulator")
            .field("mpu", &self.mpu)
            .field("ak", &self.ak)
            .field("now_ns", &self.now_ns)
            .field("nacks_pending", &self.nacks_pending)
            .finish_non_exhaustive()
    }
}

impl ImuEmulator {
    /// Both dies just powered up (reset values), measuring `truth`.
    pub fn new(config: ImuEmulatorConfig, truth: Arc<dyn ImuTruth>) -> Self {
        Self {
            mpu: Mpu9250Emulator::new(config.mpu),
            ak: Ak8963Emulator::new(config.ak),
            truth,
            now_ns: 0,
            nacks_pending: 0,
        }
    }

    /// The accel/gyro die.
    pub fn mpu(&self) -> &Mpu9250Emulator {
        &self.mpu
    }

    /// The accel/gyro die, for fault injection.
    pub fn mpu_mut(&mut self) -> &mut Mpu9250Emulator {
        &mut self.mpu
    }

    /// The magnetometer die.
    pub fn ak(&self) -> &Ak8963Emulator {
        &self.ak
    }

    /// The magnetometer die, for fault injection.
    pub fn ak_mut(&mut self) -> &mut Ak8963Emulator {
        &mut self.ak
    }

    /// Replaces the ground truth (e.g. when the emulated IMU is moved to another sensor head).
    pub fn set_truth(&mut self, truth: Arc<dyn ImuTruth>) {
        self.truth = truth;
    }

    /// Fault injection: the next `count` transfers to either die are not acknowledged (a data
    /// NACK, the whole transaction fails).
    pub fn nack_next(&mut self, count: u32) {
        self.nacks_pending = count;
    }

    fn take_injected_nack(&mut self) -> Result<(), Nack> {
        if self.nacks_pending > 0 {
            self.nacks_pending -= 1;
            Err(Nack)
        } else {
            Ok(())
        }
    }
}

impl I2cDevice for ImuEmulator {
    fn address(&self) -> u8 {
        self.mpu.address()
    }

    fn responds_to(&self, address: u8) -> bool {
        (address == self.mpu.address() && self.mpu.acknowledges(self.now_ns))
            || (address == AK8963_ADDRESS && self.mpu.bypass_enabled())
    }

    fn write(&mut self, address: u8, bytes: &[u8]) -> Result<(), Nack> {
        self.take_injected_nack()?;
        let truth = self.truth.as_ref();
        if address == AK8963_ADDRESS {
            self.ak.write(self.now_ns, truth, bytes);
        } else {
            let mut aux = AkOnAuxBus {
                ak: &mut self.ak,
                truth,
            };
            self.mpu.write(self.now_ns, truth, &mut aux, bytes);
        }
        Ok(())
    }

    fn read(&mut self, address: u8, buf: &mut [u8]) -> Result<(), Nack> {
        self.take_injected_nack()?;
        let truth = self.truth.as_ref();
        if address == AK8963_ADDRESS {
            self.ak.read(self.now_ns, truth, buf);
        } else {
            let mut aux = AkOnAuxBus {
                ak: &mut self.ak,
                truth,
            };
            self.mpu.read(self.now_ns, truth, &mut aux, buf);
        }
        Ok(())
    }

    fn set_time_ns(&mut self, now_ns: u64) {
        self.now_ns = now_ns;
    }
}

/// The package's auxiliary bus as the MPU's I2C master drives it: the AK8963 at 0x0C, nothing
/// else (other addresses NACK).
struct AkOnAuxBus<'a> {
    ak: &'a mut Ak8963Emulator,
    truth: &'a dyn ImuTruth,
}

impl AuxBus for AkOnAuxBus<'_> {
    fn read(&mut self, t_ns: u64, address: u8, reg: u8, buf: &mut [u8]) -> Result<(), Nack> {
        if address != AK8963_ADDRESS {
            return Err(Nack);
        }
        self.ak.write(t_ns, self.truth, &[reg]);
        self.ak.read(t_ns, self.truth, buf);
        Ok(())
    }

    fn write(&mut self, t_ns: u64, address: u8, reg: u8, value: u8) -> Result<(), Nack> {
        if address != AK8963_ADDRESS {
            return Err(Nack);
        }
        self.ak.write(t_ns, self.truth, &[reg, value]);
        Ok(())
    }
}

#[cfg(test)]
mod tests;
