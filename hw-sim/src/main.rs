//! `scan3d-sim`: simulated scan3d hardware.
fn main() {}
