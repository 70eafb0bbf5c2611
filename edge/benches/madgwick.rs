//! Madgwick filter cost: nanoseconds per MARG update and per IMU-only update.
//!
//! Run with `cargo bench -p scan3d-edge --bench madgwick` (release). Plain `main`, no harness:
//! each figure is the best of several runs of 1 000 000 updates over a table of varying,
//! realistic samples (a sensor turning and nodding), with the inputs passed through
//! `black_box` so nothing is hoisted out of the loop. Goal: ≤ 100 ns per update.

use std::hint::black_box;
use std::time::Instant;

use nalgebra::{UnitQuaternion, Vector3};
use scan3d_edge::madgwick::Madgwick;

const UPDATES: usize = 1_000_000;
const RUNS: usize = 15;
const TABLE: usize = 1024;
const DT: f64 = 0.005;
const GOAL_NS: f64 = 100.0;

/// One IMU sample: gyro (rad/s), accel (m/s²), mag (µT).
struct Sample {
    gyro: Vector3<f64>,
    accel: Vector3<f64>,
    mag: Vector3<f64>,
}

/// Samples of a sensor yawing at 0.5 rad/s while rolling ±0.3 rad, with small deterministic
/// perturbations so consecutive updates differ.
fn samples() -> Vec<Sample> {
    let earth_field = Vector3::new(25.0, 0.0, -43.3);
    let gravity = Vector3::new(0.0, 0.0, 9.80665);
    (0..TABLE)
        .map(|k| {
            let t = k as f64 * DT;
            let roll = 0.3 * (1.3 * t).sin();
            let truth = UnitQuaternion::from_euler_angles(roll, 0.1 * (0.7 * t).cos(), 0.5 * t);
            let wobble = 1e-3 * ((k * 7919) % 101) as f64;
            Sample {
                gyro: Vector3::new(0.39 * (1.3 * t).cos() + wobble, 0.02 - wobble, 0.5),
                accel: truth.inverse_transform_vector(&gravity) + Vector3::repeat(wobble),
                mag: truth.inverse_transform_vector(&earth_field) - Vector3::repeat(wobble),
            }
        })
        .collect()
}

/// Best nanoseconds per update over `RUNS` runs of `UPDATES` calls to `step`.
fn best_ns(table: &[Sample], mut step: impl FnMut(&mut Madgwick, &Sample)) -> (f64, [f64; 4]) {
    let mut best = f64::INFINITY;
    let mut last = [0.0; 4];
    for _ in 0..RUNS {
        let mut filter = match Madgwick::new(0.1, UnitQuaternion::identity()) {
            Ok(filter) => filter,
            Err(e) => panic!("filter: {e}"),
        };
        let start = Instant::now();
        for sample in table.iter().cycle().take(UPDATES) {
            step(&mut filter, black_box(sample));
        }
        let elapsed = start.elapsed();
        last = black_box(filter.wxyz());
        best = best.min(elapsed.as_nanos() as f64 / UPDATES as f64);
    }
    (best, last)
}

fn main() {
    let table = samples();
    let (marg, q_marg) = best_ns(&table, |f, s| {
        black_box(f.update_marg(s.gyro, s.accel, s.mag, black_box(DT)));
    });
    let (imu, q_imu) = best_ns(&table, |f, s| {
        black_box(f.update_imu(s.gyro, s.accel, black_box(DT)));
    });
    println!("madgwick: best of {RUNS} runs x {UPDATES} updates, goal <= {GOAL_NS} ns per update");
    println!(
        "  MARG update: {marg:7.1} ns per update ({}; final q {q_marg:.4?})",
        verdict(marg)
    );
    println!(
        "  IMU update:  {imu:7.1} ns per update ({}; final q {q_imu:.4?})",
        verdict(imu)
    );
}

fn verdict(ns: f64) -> &'static str {
    if ns <= GOAL_NS {
        "meets goal"
    } else {
        "OVER goal"
    }
}
