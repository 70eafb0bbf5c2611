//! The scan3d server: ingest, pose, 3D assembly, occupancy octree and map metrics.
//!
//! Stages follow the data flow, one module each (see `ARCHITECTURE.md`); today:
//! - [`ingest`]: QUIC server with mutual TLS, durable MCAP session recordings, time sync.
//! - [`cloud`]: 3D assembly, point-cloud filters and PLY / PCD / `.scans` I/O.
//! - [`octree`]: the OctoMap-compatible occupancy octree.
//! - [`eval`]: the paper's map metrics (IoU, log-odds error, correlation) and truth scores.
//! - [`config`]: the daemon's `server.toml`.
//! - [`cli`]: the `scan3d` subcommands.
#![warn(missing_docs)]

pub mod cli;
pub mod cloud;
pub mod config;
pub mod eval;
pub mod ingest;
pub mod octree;
