//! The uplink: frames to the server over QUIC with mutual TLS, nothing lost.
//!
//! - [`spool`]: every frame stays here (memory, spilling to disk) until the server acknowledges it.
//! - [`tls`]: the edge bundle → quinn client configuration.

pub mod spool;
pub mod tls;
