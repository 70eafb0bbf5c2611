//! Ingest: the QUIC server that edges stream to. It records every frame through the
//! [`recording`](crate::recording) layer beneath it and acknowledges what is durable.
//!
//! - [`pki`]: the private CA, server certificate and edge bundles (`scan3d pair`).
//! - [`tls`]: rustls/quinn configuration for mutual TLS, and the edge's identity.
//! - [`server`]: the endpoint, one task per edge connection.
//! - [`acks`]: which acknowledgements to send, from what is durable and what was acknowledged.
//! - [`control`]: operator commands to connected edges, and the local control socket.
//! - [`scan_progress`]: a static scan's progress folded from its messages.

pub mod acks;
pub mod control;
pub mod pki;
pub mod scan_progress;
pub mod server;
pub mod tls;
