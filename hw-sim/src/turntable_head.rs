//! The paper's 3D scanner in simulation: the emulated Sweep on the emulated turntable, and the
//! IMU and motor HAT on one emulated I2C bus — everything the edge daemon drives for a static
//! scan, on one shared world clock.
//!
//! ```text
//!  world clock ─┬─> Sweep emulator (pty) ── pose from ──> TurntableMount ── rotor angle ─┐
//!               └─> I2C bus: MPU-9250 + AK8963 (0x68, 0x0C), PCA9685 HAT (0x60) ─ rotor ─┘
//! ```
//!
//! The operator carries the head from position to position ([`TurntableHead::move_to`]); the edge
//! daemon sees a Sweep on a serial port and chips on a bus, exactly as on the Pi.

use std::path::Path;
use std::sync::{Arc, Mutex, RwLock};

use anyhow::Context;
use nalgebra::Isometry3;
use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::config::{EdgeConfig, ImuSection, SweepSection, UplinkSection};
use scan3d_edge::drivers::stepper::{Port, StepperConfig};
use scan3d_edge::drivers::sweep::SweepConfig;
use scan3d_edge::static_scan::{MountConfig, StaticScanConfig};
use scan3d_map::cloud::assembly::{MountGeometry, Position};

use crate::faults::FaultConfig;
use crate::i2c::{BusStats, I2cBus};
use crate::imu::{ImuEmulator, ImuTruth, StaticTruth};
use crate::installation::EDGE_NAME;
use crate::noise::RangeNoise;
use crate::pty::{PtyDevice, PtyHandle, PtyOptions};
use crate::stepper::{Pca9685Emulator, Turntable};
use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
use crate::turntable::TurntableMount;
use crate::world::{PoseSource, Scanner, World};

/// How the Sweep sits on the demo turntable: 5 cm beside the axis, optical centre 1 m up.
pub const DEMO_MOUNT: MountGeometry = MountGeometry {
    axis_offset_m: 0.05,
    height_m: 1.0,
    azimuth_zero_deg: 0.0,
};

/// Settings of a [`TurntableHead`].
#[derive(Debug, Clone)]
pub struct TurntableHeadOptions {
    /// Simulated seconds per real second.
    pub time_scale: f64,
    /// The Sweep's rotation rate, Hz (the edge sets it at start-up).
    pub motor_hz: u8,
    /// Seed of the world noise.
    pub seed: u64,
    /// The Sweep's motor settle time, simulated ms.
    pub sweep_settle_ms: u64,
    /// The Sweep's range noise.
    pub noise: RangeNoise,
}

/// The head's I2C bus on `clock`: the PCA9685 motor HAT (its port 1 turns the turntable) and
/// the MPU-9250/AK8963 measuring `imu`. Returns the bus, the HAT and the turntable it drives.
pub fn head_bus(
    clock: SharedClock,
    imu: Arc<dyn ImuTruth>,
) -> (I2cBus, Arc<Mutex<Pca9685Emulator>>, Turntable) {
    let bus = I2cBus::with_clock(clock);
    let hat = Arc::new(Mutex::new(Pca9685Emulator::motor_hat()));
    let turntable = hat
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .turntable(Port::One);
    bus.attach(hat.clone());
    bus.attach(Arc::new(Mutex::new(ImuEmulator::new(
        Default::default(),
        imu,
    ))));
    (bus, hat, turntable)
}

/// A movable [`TurntableMount`]: the operator may carry the head between scans.
#[derive(Debug, Clone)]
struct CarriedMount(Arc<RwLock<TurntableMount>>);

impl PoseSource for CarriedMount {
    fn pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        self.0
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .pose_at(t_ns)
    }
}

/// The emulated scanner: Sweep on a pty, turntable and IMU on an I2C bus, one world clock.
pub struct TurntableHead {
    world_clock: ScaledClock,
    sweep: PtyHandle,
    mount: CarriedMount,
    bus: I2cBus,
    hat: Arc<Mutex<Pca9685Emulator>>,
    motor_hz: u8,
}

impl TurntableHead {
    /// Starts the devices in `world`, the Sweep's link in `links_dir`, the head at `start`.
    pub fn start(
        links_dir: &Path,
        world: Arc<World>,
        start: Position,
        options: &TurntableHeadOptions,
    ) -> anyhow::Result<Self> {
        std::fs::create_dir_all(links_dir)
            .with_context(|| format!("cannot create {}", links_dir.display()))?;
        let world_clock = ScaledClock::new(options.time_scale);
        let (bus, hat, turntable) =
            head_bus(Arc::new(world_clock), Arc::new(StaticTruth::default()));
        let mount = CarriedMount(Arc::new(RwLock::new(TurntableMount::new(
            turntable, start, DEMO_MOUNT,
        ))));
        let sweep = SweepEmulator::new(
            SweepEmulatorConfig {
                settle_ms: options.sweep_settle_ms,
                ..Default::default()
            },
            Scanner {
                noise: options.noise,
                ..SweepEmulator::default_scanner(world, crate::mounts::sweep())
            },
            options.seed,
        )
        .with_pose_source(mount.clone());
        let pty = PtyOptions {
            time_scale: options.time_scale,
            faults: FaultConfig::default(),
            seed: options.seed,
            epoch: Some(world_clock.epoch()),
        };
        let sweep = PtyDevice::spawn(links_dir.join("sweep"), Box::new(sweep), pty)
            .context("cannot start the emulated Sweep")?;
        Ok(Self {
            world_clock,
            sweep,
            mount,
            bus,
            hat,
            motor_hz: options.motor_hz,
        })
    }

    /// The operator carries the turntable to `position` (between scans).
    pub fn move_to(&self, position: Position) {
        self.mount
            .0
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .position = position;
    }

    /// The edge's handle on the I2C bus (another handle to the same emulated bus).
    pub fn bus(&self) -> I2cBus {
        self.bus.clone()
    }

    /// Transactions on the bus so far.
    pub fn bus_stats(&self) -> BusStats {
        self.bus.stats()
    }

    /// The rotor angle now, degrees (0 = home).
    pub fn rotor_deg(&self) -> f64 {
        let now = scan3d_edge::clock::Clock::now_ns(&self.world_clock);
        self.mount
            .0
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .yaw_deg_at(now)
    }

    /// Steps the emulated rotor lost (driven faster than it can follow).
    pub fn steps_lost(&self) -> u64 {
        self.hat
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .steps_lost(Port::One)
    }

    /// The edge configuration for this head: the Sweep at `motor_hz`, the IMU, the stepper on
    /// port 1, static scans with the demo mount.
    pub fn edge_config(&self, state_dir: &Path, uplink: Option<UplinkSection>) -> EdgeConfig {
        EdgeConfig {
            device_name: EDGE_NAME.into(),
            state_dir: state_dir.to_path_buf(),
            rplidar: None,
            sweep: Some(SweepSection {
                path: self.sweep.link().to_path_buf(),
                driver: SweepConfig {
                    motor_hz: Some(self.motor_hz),
                    ..Default::default()
                },
                mount: None,
            }),
            uplink,
            i2c: Default::default(),
            imu: Some(ImuSection {
                driver: Default::default(),
                beta: 0.1,
                initial_orientation_wxyz: None,
                mount: None,
            }),
            stepper: Some(StepperConfig::default()),
            static_scan: StaticScanConfig {
                azimuth_zero_deg: DEMO_MOUNT.azimuth_zero_deg,
                mount: MountConfig {
                    axis_offset_m: DEMO_MOUNT.axis_offset_m,
                    height_m: DEMO_MOUNT.height_m,
                },
                ..Default::default()
            },
        }
    }

    /// Stops the Sweep emulator and removes its link.
    pub fn shutdown(self) {
        self.sweep.shutdown();
    }
}
