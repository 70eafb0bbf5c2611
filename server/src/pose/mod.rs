//! Pose: where the edge is, and when. Today the edge clock's mapping to server time
//! ([`timesync`]); the 2D scan matcher and the covariance-intersection fusion of the next issues
//! come here too.

pub mod timesync;
