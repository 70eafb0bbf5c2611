//! 2D SLAM for scan3d, as pure code: scans and poses in, poses and maps out.
//!
//! - [`pose`]: the rigid 2D transform every other module speaks.
//! - [`carmen`]: the CARMEN laser logs of the classic SLAM benchmarks (`FLASER`, `ROBOTLASER1`,
//!   `ODOM`).
//! - [`relations`]: trajectories (`timestamp x y theta`) and the Kümmerle et al. (2009)
//!   relations metric that scores them.
//! - [`grid`]: occupancy grids that grow as the robot explores, read as a continuous function.
//! - [`matcher`]: Gauss–Newton scan-to-map matching, coarse to fine, with a robust loss.
//! - [`surface`]: the endpoints each cell has seen, and a sub-cell refinement of a grid match.
//! - [`mapper`]: the incremental front end (motion prior, de-skew, map-update rule).
//! - [`reentry`]: a scan returning to a place mapped long ago, fitted to the old map there.
//! - [`odometry`]: which odometry a log's scans get, and how late its laser stamps run.
//! - [`odometry_agreement`]: how well the odometry has agreed with the scans lately.
//! - [`offline`]: the mapper over a whole log, and its grid as a raster.
//! - [`map_image`]: occupancy rasters as ROS `map_server` PGM + YAML and as PNG.
//! - [`text`]: what those text formats share: [`text::Timestamp`] (kept as written, so a
//!   trajectory writes the log's timestamps back exactly), the line-numbered [`text::LineError`].
//!
//! Nothing here opens a file or a socket: readers take `BufRead`/`&str`, writers return bytes or
//! take `Write`.

pub mod carmen;
pub mod fusion;
pub mod grid;
pub mod map_image;
pub mod mapper;
pub mod matcher;
pub mod odometry;
pub mod odometry_agreement;
pub mod odometry_bias;
pub mod offline;
pub mod pose;
pub mod reentry;
pub mod relations;
pub mod surface;
pub mod text;
pub mod tum;

#[cfg(test)]
mod testing;
