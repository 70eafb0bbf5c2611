//! Time-sync error in the simulator: mapped minus true server time of edge sample times, under
//! the issue's delay model (1 ms + Exp(2 ms) out, 1 ms + Exp(0.5 ms) back, a ping a second,
//! ±100 ppm skew), without and with a fixed path asymmetry A. Samples every 10 ms, scored from
//! 30 s into each 90 s run, 20 seeds per row.
//!
//! `cargo bench -p scan3d-hw-sim --bench timesync`

use std::time::Instant;

use scan3d_hw_sim::clock::{SyncOutcome, SyncScenario, run};

const SEEDS: u64 = 20;

fn main() {
    println!("time-sync error |mapped - true| over {SEEDS} seeds × 90 s, scored after 30 s");
    println!(
        "{:<28} {:>9} {:>9} {:>9} {:>9} {:>10} {:>11} {:>8}",
        "scenario", "samples", "p50 µs", "p99 µs", "max µs", "bound ok", "bound p50", "ms/run"
    );
    for (name, skew_ppm, asymmetry_ms) in [
        ("skew +100 ppm, A = 0", 100.0, 0.0),
        ("skew -100 ppm, A = 0", -100.0, 0.0),
        ("skew +100 ppm, A = 2 ms", 100.0, 2.0),
        ("skew -100 ppm, A = 5 ms", -100.0, 5.0),
    ] {
        let started = Instant::now();
        let mut all = SyncOutcome::default();
        for seed in 0..SEEDS {
            let outcome = run(&SyncScenario::issue(seed, skew_ppm, asymmetry_ms * 1e6));
            all.errors_ns.extend(outcome.errors_ns);
            all.within_bound += outcome.within_bound;
            all.bounds_ns.extend(outcome.bounds_ns);
        }
        let per_run_ms = started.elapsed().as_secs_f64() * 1e3 / SEEDS as f64;
        println!(
            "{:<28} {:>9} {:>9.1} {:>9.1} {:>9.1} {:>9.2}% {:>8.1} µs {:>8.2}",
            name,
            all.errors_ns.len(),
            all.abs_error_quantile_ns(0.5) as f64 / 1e3,
            all.abs_error_quantile_ns(0.99) as f64 / 1e3,
            all.max_abs_error_ns() as f64 / 1e3,
            all.bound_coverage() * 100.0,
            median(&mut all.bounds_ns) as f64 / 1e3,
            per_run_ms
        );
    }
}

fn median(values: &mut [u64]) -> u64 {
    values.sort_unstable();
    values.get(values.len() / 2).copied().unwrap_or(0)
}
