//! The scan3d edge: everything that runs on the Raspberry Pi.
//!
//! - [`clock`]: the edge's monotonic clock, passed in so a simulation can scale time.
//! - [`lidar`]: the sans-I/O driver contract shared by both lidars, and the sample types.
//! - [`drivers`]: RPLidar A1/A2 and Scanse Sweep protocol state machines (bytes in, events out).
//! - [`timing`]: per-sample timestamps from serial arrival times, and revolution assembly.
//! - [`serial`]: the thin I/O shell that runs a driver on a serial port, surviving unplug/replug.
//! - [`probe`], [`i2c_probe`]: the `scan3d-edge probe` wiring checks (lidars; IMU and stepper).
//! - [`config`]: the daemon's TOML configuration (`edge.toml`).
//! - [`static_scan`]: static-scan controller: a step per revolution while blocked, φ per sample.
//! - [`scan_session`]: one static scan as protocol messages and stepper jobs (sans-I/O).
//! - [`i2c_socket`]: I2C over a Unix socket (the simulator's emulated bus), an embedded-hal `I2c`.
//! - [`trolley_pass`]: trolley pass commands as pass markers on the edge's clock (sans-I/O).
//! - [`turntable`], [`imu_worker`]: the stepper and IMU threads on the shared I2C bus.
//! - [`daemon`]: the `scan3d-edge` service: lidar workers, IMU, turntable, uplink.
#![warn(missing_docs)]

pub mod acquisition;
pub mod calibrate;
pub mod cli;
pub mod clock;
pub mod config;
pub mod daemon;
pub mod drivers;
pub mod i2c_probe;
pub mod i2c_socket;
pub mod imu_worker;
pub mod lidar;
pub mod madgwick;
pub mod probe;
pub mod scan_session;
pub mod serial;
pub mod static_scan;
pub mod timing;
pub mod trolley_pass;
pub mod turntable;
pub mod uplink;
