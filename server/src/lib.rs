//! The scan3d server: ingest, pose, 3D assembly, occupancy octree and map metrics.
//!
//! Stages follow the data flow, one module each (see `ARCHITECTURE.md`); today:
//! - [`cloud`]: point-cloud types and PLY export.
#![warn(missing_docs)]

pub mod cloud;
