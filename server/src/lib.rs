//! The scan3d server: ingest, pose, 3D assembly, occupancy octree and map metrics.
//!
//! Stages follow the data flow, one module each (see `ARCHITECTURE.md`); today:
//! - [`recording`]: durable MCAP session recordings (writer, reader, index, server-made
//!   records), beneath ingest, pose and pipeline.
//! - [`ingest`]: QUIC server with mutual TLS; records through [`recording`].
//! - [`pose`]: the edge clock's mapping to server time (time sync); scan matching comes here.
//! - [`pipeline`]: per session, frames through assembly, filters, octree and metrics.
//! - the octree, clouds and metrics are the pure `scan3d-map` crate, used here.
//! - [`report`]: map comparison reports (Table III, metrics, Fig. 11/12) from map files.
//! - [`config`]: the daemon's `server.toml`.
//! - [`yaw_plot`]: the paper's Fig. 5 (yaw error per source against time) from a fused run.
//! - [`cli`]: the `scan3d` subcommands.
#![warn(missing_docs)]

pub mod cli;
pub mod config;
pub mod ingest;
pub mod pipeline;
pub mod pose;
pub mod recording;
pub mod report;
pub mod yaw_plot;
