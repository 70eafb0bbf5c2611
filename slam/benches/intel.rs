//! The whole Intel Research Lab log (2,691 s of data, 13,631 scans) through the mapper with
//! odometry, on one core, as `scan3d slam` runs it (a first pass, the odometry calibration, and
//! a second pass when the `ODOM` lines win): real-time factor, time per scan (p50 / p99 / max;
//! over both passes when there are two), peak memory.
//! Cartographer reports 15× real time on this log on a workstation (Hess et al. 2016,
//! Table II); the goal here is ≥ 100×.
//!
//! `cargo bench -p scan3d-slam --bench intel` (add `-- --no-odometry` for the
//! constant-velocity mode, `-- --runs N` for more runs).

use std::io::BufReader;
use std::path::PathBuf;
use std::time::Instant;

use scan3d_slam::carmen::{ReadOptions, read_log};
use scan3d_slam::mapper::MapperConfig;
use scan3d_slam::offline::{RangeLimits, map_log_calibrated};

/// Peak resident set size of this process (kB), from /proc (Linux).
fn peak_rss_kb() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let no_odometry = args.iter().any(|a| a == "--no-odometry");
    let runs: usize = args
        .iter()
        .position(|a| a == "--runs")
        .and_then(|i| args.get(i + 1))
        .and_then(|n| n.parse().ok())
        .unwrap_or(3);
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/slam/intel.clf.gz");
    let file = std::fs::File::open(&path).expect("testdata/slam/intel.clf.gz");
    let before_log = peak_rss_kb();
    let log = read_log(
        BufReader::new(flate2::read::GzDecoder::new(file)),
        &ReadOptions::default(),
    )
    .expect("intel log");
    let after_log = peak_rss_kb();
    let duration = log.scans.last().unwrap().timestamp.seconds - log.scans[0].timestamp.seconds;
    let mut config = MapperConfig::default();
    config.motion.use_odometry = !no_odometry;
    let limits = RangeLimits::for_log(&log, 0.1, None);
    println!(
        "intel: {} scans, {duration:.1} s of data, odometry {}",
        log.scans.len(),
        if no_odometry { "off" } else { "on" }
    );
    for run in 1..=runs {
        let mut per_scan = Vec::with_capacity(log.scans.len());
        let started = Instant::now();
        let mut last = started;
        let result = map_log_calibrated(&log, &config, &limits, |_| {
            let now = Instant::now();
            per_scan.push((now - last).as_secs_f64());
            last = now;
        });
        let elapsed = started.elapsed().as_secs_f64();
        std::hint::black_box(&result.run.trajectory);
        if run == 1 {
            println!("odometry: {:?}", result.odometry);
        }
        per_scan.sort_by(f64::total_cmp);
        let q = |p: f64| per_scan[((per_scan.len() - 1) as f64 * p) as usize] * 1e6;
        println!(
            "run {run}: {elapsed:.3} s = {:.0}× real time ({:.1}× Cartographer's 15×); per scan p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs",
            duration / elapsed,
            duration / elapsed / 15.0,
            q(0.5),
            q(0.99),
            q(1.0)
        );
    }
    if let (Some(a), Some(b), Some(c)) = (before_log, after_log, peak_rss_kb()) {
        println!(
            "peak RSS {:.1} MB (the parsed log {:.1} MB of it; before reading {:.1} MB)",
            c as f64 / 1024.0,
            (b.saturating_sub(a)) as f64 / 1024.0,
            a as f64 / 1024.0
        );
    }
}
