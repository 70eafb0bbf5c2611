//! scan3d's maps, with no network and no async: what a user needs to build, read, write and
//! score an occupancy map without the daemon.
//!
//! - [`octree`]: the occupancy octree, byte-identical to OctoMap's `.bt` / `.ot` files.
//! - [`cloud`]: static-scan assembly (the paper's eq. 1), point-cloud filters (Table II) and
//!   PLY / PCD / `.scans` I/O.
//! - [`eval`]: the paper's map metrics (occupancy ratios, IoU, log-odds error, correlation) and
//!   point-to-surface scores.
//!
//! The server's pipeline stages and the offline commands are thin layers over this crate.
#![warn(missing_docs)]

pub mod cloud;
pub mod eval;
pub mod octree;
