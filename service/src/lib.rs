//! Plumbing shared by the two scan3d daemons, `scan3d-edge` (Raspberry Pi) and `scan3d serve`
//! (laptop), so each is written once:
//!
//! - [`config`]: TOML configuration files whose errors name the file and the line.
//! - [`daemon`]: `tracing` logs for journald, SIGTERM/SIGINT, systemd notification and watchdog.
//! - [`link`]: the QUIC transport settings both ends of the edge↔server link share, and PEM
//!   loading with errors that name the file, and the private-key permission check.
//! - [`report`]: an error and its causes as one line, each cause once.
//!
//! It sits beside `scan3d-protocol` (which stays free of I/O): the edge and the server both
//! depend on it, and it depends on neither.
#![warn(missing_docs)]

pub mod config;
pub mod daemon;
pub mod link;
pub mod report;
