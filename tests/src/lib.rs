//! Test support shared by the scan3d end-to-end tests (the tests themselves live in `tests/`).
//!
//! - [`relay`]: a UDP relay between edge and server that a test can cut and restore, to
//!   simulate a network outage on the QUIC path.
//! - [`operator`]: the operator's flow with the real binaries (pair, serve, `scan3d-sim rig`,
//!   the real `scan3d-edge`), for the rig's end-to-end test and the edge daemon's benchmark.
//! - [`BOX_ROOM`]: a small world of six walls for the static-scan tests.
#![warn(missing_docs)]

pub mod operator;
pub mod relay;

/// A 4 × 3 × 2.5 m room of six walls and nothing else (a hw-sim world file): static scans in
/// it must land on the walls.
pub const BOX_ROOM: &str = r#"
[room]
min = [0.0, 0.0, 0.0]
max = [4.0, 3.0, 2.5]

[[box]]
name = "floor"
min = [-0.1, -0.1, -0.1]
max = [4.1, 3.1, 0.0]

[[box]]
name = "ceiling"
min = [-0.1, -0.1, 2.5]
max = [4.1, 3.1, 2.6]

[[box]]
name = "west"
min = [-0.1, -0.1, 0.0]
max = [0.0, 3.1, 2.5]

[[box]]
name = "east"
min = [4.0, -0.1, 0.0]
max = [4.1, 3.1, 2.5]

[[box]]
name = "south"
min = [-0.1, -0.1, 0.0]
max = [4.1, 0.0, 2.5]

[[box]]
name = "north"
min = [-0.1, 3.0, 0.0]
max = [4.1, 3.1, 2.5]
"#;
