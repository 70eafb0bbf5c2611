//! The live pipeline in the daemon at full sensor rates on loopback: an emulated RPLidar
//! (4000 samples/s) and Sweep (1000 samples/s, 2 Hz) stream through the real edge daemon and
//! QUIC into the server, which records and runs the live pipeline (`scan3d serve` with
//! `[pipeline]`, through the rig's `ServerThread`), while a static scan runs at one position of
//! the conference room in real time (time scale 1).
//!
//! `cargo bench -p scan3d-hw-sim --bench live`
//!
//! Prints, from the daemon's own `scan3d status` (asked on its control socket at the end of the
//! scan):
//! - sample-to-voxel latency: how old the newest Sweep sample (its revolution's end, mapped to
//!   server time by the time-sync offset) was when its points reached the octree, p50 / p99 /
//!   max over the scan's insertions. Measured from the revolution's end, so this is the time
//!   beyond the revolution's own duration (goal: p99 ≤ 20 ms);
//! - of which the server's share: from the recorder accepting the frame that carried the
//!   samples to their points in the octree (queue and processing), p50 / p99 / max;
//! - the pipeline worker's CPU time (its thread's clock) against the scan's wall time, and its
//!   octree's memory: the cost of one edge's pipeline;
//! - the largest lag the worker had (frames, ms) and how often it caught up from the recording.
//!
//! The edge, the emulators and the server share this process and the machine's cores with
//! whatever else runs: the load average is printed next to the numbers.

use std::sync::Arc;
use std::time::Instant;

use scan3d_hw_sim::maps::{MapPlan, MapSetup, scan_map};
use scan3d_hw_sim::noise::RangeNoise;
use scan3d_hw_sim::truth::GroundTruth;
use scan3d_hw_sim::world::World;
use scan3d_map::cloud::assembly::Position;

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|text| text.split_whitespace().next().map(str::to_owned))
        .unwrap_or_else(|| "?".into())
}

/// The peak resident set of this process (edge, emulators and server together), MiB.
fn peak_rss_mib() -> String {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or_else(|| "?".into(), |kib| format!("{:.1}", kib / 1024.0))
}

fn main() -> anyhow::Result<()> {
    let work = std::env::temp_dir().join(format!("scan3d-live-bench-{}", std::process::id()));
    let result = run(&work);
    let _ = std::fs::remove_dir_all(&work);
    result
}

fn run(work: &std::path::Path) -> anyhow::Result<()> {
    let world = Arc::new(World::conference_room());
    let truth = GroundTruth::new(&world);
    let clouds = work.join("clouds");
    std::fs::create_dir_all(&clouds)?;
    let setup = MapSetup {
        world: &world,
        truth: &truth,
        work: &work.join("work"),
        data_dir: &work.join("data"),
        clouds_dir: &clouds,
        time_scale: 1.0,
        seed: 7,
        noise: RangeNoise::SWEEP,
        resolution_m: 0.05,
        queue_frames: 256,
        snapshots_dir: &work.join("snapshots"),
        full_rates: true,
    };
    let plan = MapPlan {
        name: "bench",
        positions: vec![Position {
            name: "middle".into(),
            x_m: 4.0,
            y_m: 3.0,
            heading_deg: 0.0,
        }],
        motor_hz: 2,
        max_range_m: 6.0,
    };
    println!(
        "live pipeline bench: RPLidar 4 kHz + Sweep 1 kHz at {} Hz, one static scan in real time, octree {} m, load average {}",
        plan.motor_hz,
        setup.resolution_m,
        load_average()
    );
    let started = Instant::now();
    let result = scan_map(&plan, &setup)?;
    let wall = started.elapsed().as_secs_f64();
    let status = &result.live_status;
    let latency = &status["sample_to_voxel"];
    println!(
        "session: {} frames, {} samples, {} revolutions, {} points, {} occupied / {} free voxels",
        status["frames"],
        status["samples"],
        status["revolutions"],
        status["points"],
        status["occupied_voxels"],
        status["free_voxels"]
    );
    println!(
        "sample-to-voxel latency beyond the revolution (ms, {} insertions): p50 {} p99 {} max {}",
        latency["count"], latency["p50_ms"], latency["p99_ms"], latency["max_ms"]
    );
    let server = &status["accept_to_voxel"];
    println!(
        "of which the server's (recorder accepted the frame -> points in the octree, ms, {} insertions): p50 {} p99 {} max {}",
        server["count"], server["p50_ms"], server["p99_ms"], server["max_ms"]
    );
    println!(
        "time sync at the end: offset {} ns, error bound {} ns",
        status["timesync"]["offset_ns"], status["timesync"]["error_bound_ns"]
    );
    let cpu_ms = status["worker_cpu_ms"].as_f64().unwrap_or(f64::NAN);
    println!(
        "pipeline worker: {cpu_ms} ms CPU over {wall:.1} s wall ({:.2} % of one core), octree {:.1} MiB",
        cpu_ms / 10.0 / wall,
        status["map_memory_bytes"].as_f64().unwrap_or(f64::NAN) / (1 << 20) as f64
    );
    println!(
        "lag: at most {} frames / {} ms; {} catch-ups from the recording, {} queue overflows",
        status["max_lag_frames"],
        status["max_lag_ms"],
        status["catch_ups"],
        status["queue_overflows"]
    );
    println!(
        "process peak RSS (edge + emulators + server + pipeline): {} MiB; load average {}",
        peak_rss_mib(),
        load_average()
    );
    Ok(())
}
