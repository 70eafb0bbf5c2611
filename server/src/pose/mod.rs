//! Pose: where the edge is, and when. The edge clock's mapping to server time ([`timesync`]),
//! and the horizontal lidar's 2D scan matching over a session ([`scan_matching`], on
//! `scan3d-slam`); the covariance-intersection yaw fusion's session adapter ([`fusion`]).

pub mod fusion;
pub mod scan_matching;
pub mod timesync;
