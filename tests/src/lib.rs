//! Test support shared by the scan3d end-to-end tests (the tests themselves live in `tests/`).
//!
//! - [`relay`]: a UDP relay between edge and server that a test can cut and restore, to
//!   simulate a network outage on the QUIC path.
#![warn(missing_docs)]

pub mod relay;
