//! Simulated scan3d hardware, so everything runs and is tested without a Pi.
//!
//! - [`world`]: a conference room with ground truth, ray intersection and a glass wall.
//! - [`noise`]: per-sensor range noise models.
//! - [`device`]: the sans-I/O emulator contract (host bytes in, paced wire units out).
//! - [`rplidar`], [`sweep`]: the two lidar emulators speaking the real wire protocols.
//! - [`i2c`]: a simulated I2C bus dispatching to register-level chip emulators.
//! - [`i2c_socket`]: that bus behind a Unix socket, for the real edge daemon.
//! - [`faults`]: stray bytes, bit flips and dropped bytes, with a log of what was really sent.
//! - [`mounts`]: where the emulated sensors sit in the room.
//! - [`truth`]: ground truth for scoring clouds: surface samples, exact distances, the world file.
//! - [`turntable`]: the Sweep on the stepper's turntable, its scan plane following the rotor.
//! - [`fleet`]: synthetic edges (own certificate, spool and session each) for load and soak runs.
//! - [`pair`]: a driver wired straight to an emulator in memory (deterministic tests, benches).
//! - [`pty`]: runs an emulator on a Linux pty behind a symlink, paced at the wire rate.
//! - [`rig`]: `scan3d-sim rig`, the whole sensor head in real time for the real edge daemon.
//! - [`trolley`]: the rig's pushed trolley: a path through the room and its exact kinematics.
//! - [`installation`]: a whole installation in-process (lidars, certificates, server, edge daemon)
//!   for the demo and tests.
//! - [`turntable_head`]: the paper's scanner in-process: Sweep on the turntable, IMU and motor HAT
//!   on I2C.
//! - [`maps`]: the paper's static maps through the whole system, scored against ground truth.
//! - [`demo`]: the README's demo.
//! - [`clock`]: a drifting edge clock and delay model driving the real time-sync exchange.
#![warn(missing_docs)]

pub mod clock;
pub mod demo;
pub mod demo_trolley;
pub mod device;
pub mod faults;
pub mod fleet;
pub mod i2c;
pub mod i2c_socket;
pub mod imu;
pub mod installation;
pub mod maps;
pub mod mounts;
pub mod noise;
pub mod pair;
pub mod pty;
pub mod rig;
pub mod rplidar;
pub mod stepper;
pub mod sweep;
pub mod trolley;
pub mod truth;
pub mod turntable;
pub mod turntable_head;
pub mod world;
