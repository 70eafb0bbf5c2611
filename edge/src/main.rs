//! `scan3d-edge`: the Raspberry Pi daemon and its wiring tools.
fn main() {}
