//! `scan3d-sim rig`: the whole sensor head, in real time, for the real `scan3d-edge` daemon.
//!
//! In `DIR`: the RPLidar and the Sweep on ptys (`ttyRPLIDAR`, `ttySWEEP`, their real
//! protocols), the MPU-9250/AK8963 and the PCA9685 motor HAT on one emulated I2C bus behind
//! `i2c.sock` ([`crate::i2c_socket`]), and `edge.toml` with the edge's sensor sections for this
//! head ([`edge_toml`]). Everything runs on one clock at time scale 1.
//!
//! Frames: `room` is the map; `base` is the head's frame on the floor, z up; each sensor's
//! mount pose in `base` is written to `edge.toml` (`[rplidar.mount]`, `[sweep.mount]`,
//! `[imu.mount]`). Two heads:
//!
//! - the static head ([`Head::Static`]): `base` is the turntable's frame (origin on its axis,
//!   x along turntable yaw 0) standing at `--at X,Y,HEADING`; the Sweep on the turntable,
//!   turned when the edge steps the stepper; the RPLidar horizontal on the base;
//! - the trolley ([`Head::Trolley`], `--trolley [PATH.toml]`): `base` is the trolley's frame
//!   (origin at its reference point, x forwards) following a [`TrolleyPath`]; the RPLidar
//!   horizontal at its mount height, the Sweep in the vertical plane across the direction of
//!   travel (spin axis along base −x), no turntable: the trolley's `edge.toml` has no
//!   `[stepper]` (the edge refuses static scans) and no `[static_scan]`.
//!
//! Both lidars cast each ray from the pose of `base` at that sample's time
//! ([`crate::trolley::OnBase`]); the IMU, level on the base, measures the base's true motion
//! ([`MountedImuTruth`]: rates, gravity plus acceleration, the field with magnetic north at
//! [`ROOM_MAGNETIC_NORTH_DEG`]) with the emulator's noise and bias.
//!
//! On the trolley the IMU lies as real ones do unless `--ideal-imu` ([`Rig::start_with_imu`],
//! [`crate::imu::errors`]): a drifting gyro bias, the trolley's hard and soft iron, a steel
//! cabinet beside the path ([`ImuErrors::beside_path`]), and floor bumps that tilt the
//! trolley (its pose, so the lidars and `--truth` see them too). With `--truth FILE` the true
//! errors go to `FILE.imu.toml` ([`imu_truth_toml`]) so a calibration can be checked.
//!
//! `--truth FILE` writes the pose of `base` in `room` as TUM lines ([`TumWriter`]) at
//! [`TRUTH_HZ`], t in UNIX seconds; the trolley's ends with `# end of path` once it rests at
//! the end of its path (it stays at the last pose written).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use scan3d_edge::clock::ScaledClock;
use scan3d_map::cloud::assembly::Position;

use crate::faults::FaultConfig;
use crate::i2c_socket::I2cSocketServer;
use crate::imu::errors::{ErroneousImu, ImuErrors};
use crate::imu::{EarthField, ImuTruth, MountedImuTruth};
use crate::pty::{PtyDevice, PtyHandle, PtyOptions};
use crate::rplidar::{RplidarEmulator, RplidarEmulatorConfig};
use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
use crate::trolley::{BaseTrajectory, BumpyTrolley, OnBase, TROLLEY_CLEARANCE_M, TrolleyPath};
use crate::turntable::TurntableMount;
use crate::turntable_head::{DEMO_MOUNT, head_bus};
use crate::world::World;

/// The RPLidar's link in the rig's directory.
pub const RPLIDAR_LINK: &str = "ttyRPLIDAR";
/// The Sweep's link in the rig's directory.
pub const SWEEP_LINK: &str = "ttySWEEP";
/// The I2C bus's socket in the rig's directory.
pub const I2C_SOCKET: &str = "i2c.sock";
/// The edge's sensor sections for this head, in the rig's directory.
pub const EDGE_TOML: &str = "edge.toml";

/// The RPLidar's mount in `base`: horizontal, 0.4 m up, 0.15 m behind the turntable axis.
pub const RPLIDAR_MOUNT: [f64; 6] = [-0.15, 0.0, 0.4, 0.0, 0.0, 0.0];
/// The IMU's mount in `base`: level on the base, 0.1 m up, chip axes = base axes (both heads).
pub const IMU_MOUNT: [f64; 6] = [0.0, -0.1, 0.1, 0.0, 0.0, 0.0];
/// The RPLidar's mount on the trolley: horizontal, 0.4 m up, 0.2 m ahead of the reference
/// point.
pub const TROLLEY_RPLIDAR_MOUNT: [f64; 6] = [0.2, 0.0, 0.4, 0.0, 0.0, 0.0];
/// The Sweep's mount on the trolley: on a mast 0.2 m behind the reference point, optical
/// centre 1 m up, its scan plane the base's y–z plane (across the direction of travel), spin
/// axis along base −x and azimuth 0 up, as on the turntable.
pub const TROLLEY_SWEEP_MOUNT: [f64; 6] = [-0.2, 0.0, 1.0, 0.0, -90.0, 0.0];
/// Where magnetic north lies in the room, degrees counter-clockwise from room x (not 0, so
/// that nothing can assume the map's x points north).
pub const ROOM_MAGNETIC_NORTH_DEG: f64 = 20.0;
/// The Sweep's rotation rate the rig's `edge.toml` asks for, Hz: with 3.6° per revolution a
/// 180° static scan takes 50 revolutions, 10 s, and the two steps (20 ms at 100 steps/s) fit
/// in the 60° blind sector (33 ms at 5 Hz).
pub const SWEEP_MOTOR_HZ: u8 = 5;
/// Full steps (1.8° each) per Sweep revolution in the rig's `[static_scan]`.
pub const STEPS_PER_REVOLUTION: u32 = 2;
/// Truth lines per second.
pub const TRUTH_HZ: f64 = 50.0;

/// What `scan3d-sim rig` runs.
#[derive(Debug, Clone)]
pub struct RigOptions {
    /// Directory of the links, the socket and `edge.toml` (created if missing).
    pub dir: PathBuf,
    /// The head: static or on a trolley.
    pub head: Head,
    /// Where to write the true trajectory of `base` (TUM lines).
    pub truth: Option<PathBuf>,
    /// Seed of the range noise.
    pub seed: u64,
}

/// Which sensor head the rig emulates.
#[derive(Debug, Clone)]
pub enum Head {
    /// The Sweep on the turntable, standing at x, y (m) with the heading of its yaw 0 (deg);
    /// `None` = the room's centre, heading 0.
    Static {
        /// Where `base` stands.
        at: Option<[f64; 3]>,
    },
    /// The head on a trolley pushed along a path.
    Trolley(Arc<TrolleyPath>),
}

/// A running rig; [`Rig::shutdown`] (or drop) stops it and removes its links and socket.
pub struct Rig {
    clock: ScaledClock,
    base: Arc<dyn BaseTrajectory>,
    rplidar: Option<PtyHandle>,
    sweep: Option<PtyHandle>,
    i2c: Option<I2cSocketServer>,
    edge_toml: PathBuf,
    truth: Option<(Arc<AtomicBool>, JoinHandle<()>)>,
    imu_errors: Option<Arc<ErroneousImu>>,
}

/// A pose of `base` in `room` from x, y (m) and heading (deg).
pub fn base_pose(at: [f64; 3]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(at[0], at[1], 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), at[2].to_radians()),
    )
}

/// A mount pose (x, y, z m; roll, pitch, yaw deg, intrinsic Z-Y-X) as an isometry sensor → base.
pub fn mount_pose(m: [f64; 6]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(m[0], m[1], m[2]),
        UnitQuaternion::from_euler_angles(m[3].to_radians(), m[4].to_radians(), m[5].to_radians()),
    )
}

impl Rig {
    /// Starts every device in `world` and writes `edge.toml`. A trolley path that comes
    /// closer than [`TROLLEY_CLEARANCE_M`] to the room's walls or furniture is refused. The
    /// trolley's IMU has the default errors ([`ImuErrors::beside_path`]); the static head's is
    /// ideal.
    pub fn start(world: Arc<World>, options: &RigOptions) -> anyhow::Result<Self> {
        let errors = match &options.head {
            Head::Trolley(path) => Some(ImuErrors::beside_path(path)),
            Head::Static { .. } => None,
        };
        Self::start_with_imu(world, options, errors)
    }

    /// [`Rig::start`] with the IMU's errors given: `None` is an ideal IMU (the emulators'
    /// white noise only) and, on the trolley, a level floor. On the trolley, the errors'
    /// [`ImuErrors::floor_bumps`] tilt its trajectory.
    pub fn start_with_imu(
        world: Arc<World>,
        options: &RigOptions,
        imu_errors: Option<ImuErrors>,
    ) -> anyhow::Result<Self> {
        let dir = &options.dir;
        let (base, at): (Arc<dyn BaseTrajectory>, [f64; 3]) = match &options.head {
            Head::Static { at } => {
                let at = at.unwrap_or_else(|| {
                    let room = world.room();
                    [
                        (room.min.x + room.max.x) / 2.0,
                        (room.min.y + room.max.y) / 2.0,
                        0.0,
                    ]
                });
                (Arc::new(base_pose(at)), at)
            }
            Head::Trolley(path) => {
                let clearance = path.clearance(&world);
                if clearance.distance_m < TROLLEY_CLEARANCE_M {
                    anyhow::bail!(
                        "the trolley's path passes {:.2} m from {} at ({:.2}, {:.2}): the \
                         trolley needs {TROLLEY_CLEARANCE_M} m (see docs/simulator.md for the \
                         path file)",
                        clearance.distance_m,
                        clearance.what,
                        clearance.at[0],
                        clearance.at[1]
                    );
                }
                let base: Arc<dyn BaseTrajectory> = match &imu_errors {
                    Some(errors) => Arc::new(BumpyTrolley::new(path.clone(), &errors.floor_bumps)),
                    None => path.clone(),
                };
                (base, path.start_pose())
            }
        };
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let clock = ScaledClock::new(1.0);
        let imu = MountedImuTruth {
            base: base.clone(),
            mount: mount_pose(IMU_MOUNT),
            field: EarthField::default(),
            north_heading_rad: ROOM_MAGNETIC_NORTH_DEG.to_radians(),
        };
        let imu_errors = imu_errors.map(|errors| Arc::new(ErroneousImu::new(imu.clone(), errors)));
        let imu_truth: Arc<dyn ImuTruth> = match &imu_errors {
            Some(erroneous) => erroneous.clone(),
            None => Arc::new(imu),
        };
        let (bus, _hat, turntable) = head_bus(Arc::new(clock), imu_truth);
        let pty = |seed: u64| PtyOptions {
            time_scale: 1.0,
            faults: FaultConfig::default(),
            seed,
            epoch: Some(clock.epoch()),
        };
        let on_base = |mount: [f64; 6]| OnBase {
            base: base.clone(),
            mount: mount_pose(mount),
        };
        let trolley = matches!(options.head, Head::Trolley(_));
        let rplidar_mount = if trolley {
            TROLLEY_RPLIDAR_MOUNT
        } else {
            RPLIDAR_MOUNT
        };
        let rplidar = RplidarEmulator::new(
            RplidarEmulatorConfig::default(),
            RplidarEmulator::default_scanner(world.clone(), Isometry3::identity()),
            options.seed,
        )
        .with_pose_source(on_base(rplidar_mount));
        let rplidar =
            PtyDevice::spawn(dir.join(RPLIDAR_LINK), Box::new(rplidar), pty(options.seed))
                .context("cannot start the emulated RPLidar")?;
        let sweep = SweepEmulator::new(
            SweepEmulatorConfig::default(),
            SweepEmulator::default_scanner(world, crate::mounts::sweep()),
            options.seed.wrapping_add(1),
        );
        let sweep = if trolley {
            sweep.with_pose_source(on_base(TROLLEY_SWEEP_MOUNT))
        } else {
            let position = Position {
                name: "rig".into(),
                x_m: at[0],
                y_m: at[1],
                heading_deg: at[2],
            };
            sweep.with_pose_source(TurntableMount::new(turntable, position, DEMO_MOUNT))
        };
        let sweep = PtyDevice::spawn(
            dir.join(SWEEP_LINK),
            Box::new(sweep),
            pty(options.seed.wrapping_add(101)),
        )
        .context("cannot start the emulated Sweep")?;
        let i2c = I2cSocketServer::start(&dir.join(I2C_SOCKET), bus)?;
        let edge_toml = dir.join(EDGE_TOML);
        let text = if trolley {
            trolley_edge_toml_text(rplidar.link(), sweep.link(), i2c.path())
        } else {
            edge_toml_text(rplidar.link(), sweep.link(), i2c.path())
        };
        std::fs::write(&edge_toml, text)
            .with_context(|| format!("cannot write {}", edge_toml.display()))?;
        let end_of_path_s = match &options.head {
            Head::Trolley(path) => Some(path.end_of_path_s()),
            Head::Static { .. } => None,
        };
        let truth = match &options.truth {
            Some(path) => Some(start_truth(path, clock, base.clone(), end_of_path_s)?),
            None => None,
        };
        if let (Some(truth), Some(erroneous)) = (&options.truth, &imu_errors) {
            let mut name = truth.clone().into_os_string();
            name.push(".imu.toml");
            let path = PathBuf::from(name);
            std::fs::write(&path, imu_truth_toml(erroneous))
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
        match &options.head {
            Head::Static { .. } => tracing::info!(
                rplidar = %rplidar.link().display(),
                sweep = %sweep.link().display(),
                i2c = %i2c.path().display(),
                x = at[0], y = at[1], heading_deg = at[2],
                "rig running: static head"
            ),
            Head::Trolley(path) => tracing::info!(
                rplidar = %rplidar.link().display(),
                sweep = %sweep.link().display(),
                i2c = %i2c.path().display(),
                x = at[0], y = at[1], heading_deg = at[2],
                rest_s = path.rest_s(),
                motion_s = format_args!("{:.1}", path.motion_s()),
                length_m = format_args!("{:.2}", path.length_m()),
                "rig running: trolley (at rest until rest_s, then moving for motion_s)"
            ),
        }
        Ok(Self {
            clock,
            base,
            rplidar: Some(rplidar),
            sweep: Some(sweep),
            i2c: Some(i2c),
            edge_toml,
            truth,
            imu_errors,
        })
    }

    /// The IMU's errors as emulated (the true iron, bias and disturbance), `None` when ideal.
    pub fn imu_errors(&self) -> Option<&ErroneousImu> {
        self.imu_errors.as_deref()
    }

    /// The rig's clock: every emulator's time base (its `now_ns` is the time since the rig's
    /// start, the `t` of [`TrolleyPath::state_at`] in nanoseconds).
    pub fn clock(&self) -> ScaledClock {
        self.clock
    }

    /// The true pose of `base` in `room` at `t_ns` on [`Rig::clock`].
    pub fn base_pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        self.base.motion_at(t_ns).pose
    }

    /// The paths the rig created: the two links, the socket, `edge.toml`.
    pub fn paths(&self) -> Vec<PathBuf> {
        let mut paths = Vec::new();
        paths.extend(self.rplidar.as_ref().map(|p| p.link().to_path_buf()));
        paths.extend(self.sweep.as_ref().map(|p| p.link().to_path_buf()));
        paths.extend(self.i2c.as_ref().map(|s| s.path().to_path_buf()));
        paths.push(self.edge_toml.clone());
        paths
    }

    /// Stops every device and removes the links and the socket (`edge.toml` stays).
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        if let Some((stop, thread)) = self.truth.take() {
            stop.store(true, Ordering::SeqCst);
            let _ = thread.join();
        }
        if let Some(i2c) = self.i2c.take() {
            i2c.shutdown();
        }
        for pty in [self.rplidar.take(), self.sweep.take()]
            .into_iter()
            .flatten()
        {
            pty.shutdown();
        }
    }
}

impl Drop for Rig {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The edge's sensor sections for the static head whose devices are at these paths. An
/// operator prepends `device_name` and `state_dir` and appends `[uplink]`.
pub fn edge_toml_text(rplidar: &Path, sweep: &Path, i2c_socket: &Path) -> String {
    let mount = mount_text;
    // The Sweep on the turntable as eq. (1) has it: spin axis along base -x, azimuth 0 up.
    let sweep_mount = [
        DEMO_MOUNT.axis_offset_m,
        0.0,
        DEMO_MOUNT.height_m,
        0.0,
        -90.0,
        0.0,
    ];
    format!(
        "# The sensor head of `scan3d-sim rig` (generated). Prepend device_name and state_dir,\n\
         # append [uplink].\n\n\
         [rplidar]\npath = {rplidar:?}\n\n[rplidar.mount]\n{rplidar_mount}\n\
         [sweep]\npath = {sweep:?}\nmotor_hz = {SWEEP_MOTOR_HZ}\n\n[sweep.mount]\n{sweep_mount}\n\
         [i2c]\nsocket = {i2c_socket:?}\n\n\
         [imu]\n\n[imu.mount]\n{imu_mount}\n\
         [stepper]\n\n\
         [static_scan]\nsteps_per_revolution_of_sweep = {STEPS_PER_REVOLUTION}\n",
        rplidar = rplidar.display().to_string(),
        sweep = sweep.display().to_string(),
        i2c_socket = i2c_socket.display().to_string(),
        rplidar_mount = mount(RPLIDAR_MOUNT),
        sweep_mount = mount(sweep_mount),
        imu_mount = mount(IMU_MOUNT),
    )
}

/// The edge's sensor sections for the trolley whose devices are at these paths: the lidars and
/// the IMU with their mounts on the trolley, no `[stepper]` (no turntable: the edge refuses
/// static scans) and no `[static_scan]`. An operator prepends `device_name` and `state_dir` and
/// appends `[uplink]`.
pub fn trolley_edge_toml_text(rplidar: &Path, sweep: &Path, i2c_socket: &Path) -> String {
    format!(
        "# The sensor head of `scan3d-sim rig --trolley` (generated): the head on a pushed\n\
         # trolley, no turntable (so no [stepper] and no [static_scan]: the edge refuses static\n\
         # scans). Prepend device_name and state_dir, append [uplink].\n\n\
         [rplidar]\npath = {rplidar:?}\n\n[rplidar.mount]\n{rplidar_mount}\n\
         [sweep]\npath = {sweep:?}\nmotor_hz = {SWEEP_MOTOR_HZ}\n\n[sweep.mount]\n{sweep_mount}\n\
         [i2c]\nsocket = {i2c_socket:?}\n\n\
         [imu]\n\n[imu.mount]\n{imu_mount}",
        rplidar = rplidar.display().to_string(),
        sweep = sweep.display().to_string(),
        i2c_socket = i2c_socket.display().to_string(),
        rplidar_mount = mount_text(TROLLEY_RPLIDAR_MOUNT),
        sweep_mount = mount_text(TROLLEY_SWEEP_MOUNT),
        imu_mount = mount_text(IMU_MOUNT),
    )
}

/// A `[*.mount]` section's keys.
fn mount_text(m: [f64; 6]) -> String {
    format!(
        "x = {:?}\ny = {:?}\nz = {:?}\nroll = {:?}\npitch = {:?}\nyaw = {:?}\n",
        m[0], m[1], m[2], m[3], m[4], m[5]
    )
}

/// The true IMU errors as TOML (`--truth FILE` writes them to `FILE.imu.toml`): the
/// `[imu]` keys a perfect `scan3d-edge calibrate mag` would write (`mag_hard_iron_ut`,
/// `mag_soft_iron` = A⁻¹), the turn-on gyro bias, then the configured errors.
pub fn imu_truth_toml(imu: &ErroneousImu) -> String {
    #[derive(serde::Serialize)]
    struct Calibration {
        mag_hard_iron_ut: Option<[f64; 3]>,
        mag_soft_iron: Option<[[f64; 3]; 3]>,
        gyro_bias_at_start_rad_s: [f64; 3],
    }
    #[derive(serde::Serialize)]
    struct File<'a> {
        calibration: Calibration,
        errors: &'a ImuErrors,
    }
    let expected = imu.expected_calibration();
    let file = File {
        calibration: Calibration {
            mag_hard_iron_ut: expected.map(|e| e.0),
            mag_soft_iron: expected.map(|e| e.1),
            gyro_bias_at_start_rad_s: imu.gyro_bias_at(0).into(),
        },
        errors: imu.errors(),
    };
    format!(
        "# The rig's true IMU errors (generated). [calibration]: what a perfect calibration \
         finds;\n# [errors]: what the emulator adds.\n\n{}",
        toml::to_string(&file).unwrap_or_default()
    )
}

/// Writes poses as TUM lines `t x y z qx qy qz qw`, each flushed.
pub struct TumWriter<W: Write> {
    out: W,
}

impl<W: Write> TumWriter<W> {
    /// A writer onto `out`.
    pub fn new(out: W) -> Self {
        Self { out }
    }

    /// One line: `t` in seconds, the pose's translation and its rotation as a unit quaternion.
    pub fn pose(&mut self, t_s: f64, pose: &Isometry3<f64>) -> std::io::Result<()> {
        let p = pose.translation.vector;
        let q = pose.rotation.quaternion();
        writeln!(
            self.out,
            "{t_s:.6} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
            p.x, p.y, p.z, q.i, q.j, q.k, q.w
        )?;
        self.out.flush()
    }

    /// The last line once `base` rests at the end of its path.
    pub fn end_of_path(&mut self) -> std::io::Result<()> {
        writeln!(self.out, "# end of path")?;
        self.out.flush()
    }
}

fn unix_now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// The truth of `base`: its pose at [`TRUTH_HZ`] (t: UNIX time now, pose: at the rig clock's
/// now) until stopped or, when `end_of_path_s` is given, until the rig clock passes it: then
/// `# end of path` and the thread ends.
fn start_truth(
    path: &Path,
    clock: ScaledClock,
    base: Arc<dyn BaseTrajectory>,
    end_of_path_s: Option<f64>,
) -> anyhow::Result<(Arc<AtomicBool>, JoinHandle<()>)> {
    let file = std::fs::File::create(path)
        .with_context(|| format!("cannot create the truth file {}", path.display()))?;
    let mut writer = TumWriter::new(std::io::BufWriter::new(file));
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let path = path.to_path_buf();
    let thread = std::thread::Builder::new()
        .name("rig-truth".into())
        .spawn(move || {
            let period = Duration::from_secs_f64(1.0 / TRUTH_HZ);
            let mut next = std::time::Instant::now();
            while !flag.load(Ordering::SeqCst) {
                let t_ns = scan3d_edge::clock::Clock::now_ns(&clock);
                let ended = end_of_path_s.is_some_and(|end| t_ns as f64 * 1e-9 >= end);
                let written = writer
                    .pose(unix_now_s(), &base.motion_at(t_ns).pose)
                    .and_then(|()| if ended { writer.end_of_path() } else { Ok(()) });
                if let Err(e) = written {
                    tracing::error!(path = %path.display(), "cannot write the truth: {e}");
                    return;
                }
                if ended {
                    tracing::info!(path = %path.display(), "the trolley rests at the end of its path");
                    return;
                }
                next += period;
                if let Some(wait) = next.checked_duration_since(std::time::Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
        })
        .context("cannot start the truth thread")?;
    Ok((stop, thread))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tum_lines_carry_the_pose_and_the_end() {
        let mut out = Vec::new();
        let mut writer = TumWriter::new(&mut out);
        writer
            .pose(1_700_000_000.25, &base_pose([1.5, 3.0, 90.0]))
            .unwrap();
        writer.end_of_path().unwrap();
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2);
        let v: Vec<f64> = lines[0].split(' ').map(|f| f.parse().unwrap()).collect();
        assert_eq!(v.len(), 8);
        assert_eq!(v[0], 1_700_000_000.25);
        assert_eq!(&v[1..4], &[1.5, 3.0, 0.0]);
        let h = std::f64::consts::FRAC_PI_4;
        let expected = [0.0, 0.0, h.sin(), h.cos()];
        for (got, want) in v[4..].iter().zip(expected) {
            assert!((got - want).abs() < 1e-8, "{v:?}");
        }
        assert_eq!(lines[1], "# end of path");
    }

    #[test]
    fn the_trolley_s_edge_toml_has_its_mounts_and_no_turntable() {
        let text = trolley_edge_toml_text(Path::new("/r"), Path::new("/s"), Path::new("/i"));
        let table: toml::Table = text.parse().unwrap();
        assert!(!table.contains_key("stepper"), "{text}");
        assert!(!table.contains_key("static_scan"), "{text}");
        assert_eq!(table["imu"]["mount"]["z"].as_float(), Some(IMU_MOUNT[2]));
        assert_eq!(table["rplidar"]["mount"]["z"].as_float(), Some(0.4));
        let m = &table["sweep"]["mount"];
        let get = |k: &str| m[k].as_float().unwrap();
        let mount = mount_pose([
            get("x"),
            get("y"),
            get("z"),
            get("roll"),
            get("pitch"),
            get("yaw"),
        ]);
        // Spin axis along the direction of travel, so the scan plane is across it.
        let spin = mount.rotation * Vector3::z();
        assert!((spin + Vector3::x()).norm() < 1e-12, "{spin}");
        let config = scan3d_edge::config::EdgeConfig::from_toml_str(
            &format!("device_name = \"t\"\n{text}"),
            Path::new("edge.toml"),
        )
        .expect("the edge accepts it");
        assert!(config.stepper.is_none() && config.imu.is_some());
    }

    #[test]
    fn the_true_imu_errors_file_holds_the_calibration_that_undoes_them() {
        let path = Arc::new(TrolleyPath::demo_room());
        let truth = MountedImuTruth {
            base: path.clone(),
            mount: mount_pose(IMU_MOUNT),
            field: EarthField::default(),
            north_heading_rad: 0.0,
        };
        let imu = ErroneousImu::new(truth, ImuErrors::beside_path(&path));
        let table: toml::Table = imu_truth_toml(&imu).parse().expect("valid TOML");
        let hard = table["calibration"]["mag_hard_iron_ut"].as_array().unwrap();
        assert_eq!(hard[0].as_float(), Some(15.0));
        let soft = table["calibration"]["mag_soft_iron"].as_array().unwrap();
        // S = A⁻¹: S₀₀ below 1 since A₀₀ = 1.06.
        let s00 = soft[0].as_array().unwrap()[0].as_float().unwrap();
        assert!(s00 > 0.9 && s00 < 0.95, "{s00}");
        let errors: ImuErrors = table["errors"].clone().try_into().expect("errors");
        assert_eq!(&errors, imu.errors());
        // The cabinet beside the path: a few µT at the closest point, nothing at the start.
        let strongest = (0..2000)
            .map(|k| imu.disturbance_at(k * 50_000_000).norm())
            .fold(0.0, f64::max);
        eprintln!("the cabinet's field at the chip: at most {strongest:.2} µT along the path");
        assert!((1.0..10.0).contains(&strongest), "{strongest}");
        assert!(imu.disturbance_at(0).norm() < 0.5);
    }

    #[test]
    fn the_sweep_mount_is_the_demo_turntable() {
        let text = edge_toml_text(Path::new("/r"), Path::new("/s"), Path::new("/i"));
        let table: toml::Table = text.parse().unwrap();
        let mount = &table["sweep"]["mount"];
        assert_eq!(mount["x"].as_float(), Some(DEMO_MOUNT.axis_offset_m));
        assert_eq!(mount["pitch"].as_float(), Some(-90.0));
        assert_eq!(table["i2c"]["socket"].as_str(), Some("/i"));
        assert_eq!(table["rplidar"]["path"].as_str(), Some("/r"));
        // The mount rotation maps the Sweep's spin axis (z) to base -x.
        let spin = mount_pose([0.05, 0.0, 1.0, 0.0, -90.0, 0.0]).rotation * Vector3::z();
        assert!((spin + Vector3::x()).norm() < 1e-12);
    }
}
