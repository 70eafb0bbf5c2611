//! The uplink: frames to the server over QUIC with mutual TLS, nothing lost.
//!
//! - [`client`]: the QUIC connection task and the producers' handle.
//! - [`spool`]: every frame stays here (memory, spilling to disk) until the server acknowledges it.
//! - [`timesync`]: answers the server's time-sync pings (QUIC datagrams, never spooled).
//! - [`tls`]: the edge bundle → quinn client configuration.

pub mod client;
pub mod spool;
pub mod timesync;
pub mod tls;
