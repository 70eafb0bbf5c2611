//! The scan3d server: ingest, pose, 3D assembly, occupancy octree and map metrics.
//!
//! Stages arrive with later issues; the crate exists so the workspace has its final shape.
#![warn(missing_docs)]
