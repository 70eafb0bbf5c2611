//! Edge driver cost, measured on realistic byte streams recorded from the emulators.
//!
//! `cargo bench -p scan3d-hw-sim --bench edge_drivers`
//!
//! For each stream (10 s of sensor data, recorded once through an in-memory driver↔emulator
//! pair), a fresh driver decodes the whole recording, best of several runs. Printed:
//! parser throughput in MB/s, and the CPU share of one core that decoding both lidars at full
//! rate needs (RPLidar express 4000 samples/s + Sweep at 1025 samples/s), including revolution
//! assembly and timestamping. The serial reads themselves are measured by the demo
//! (`scan3d-sim demo --time-scale 1`), which runs the same code on real ptys.

use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig, ScanMode};
use scan3d_edge::drivers::sweep::{Sweep, SweepConfig};
use scan3d_edge::lidar::{LidarDriver, LidarEvent};
use scan3d_edge::timing::{RevolutionAssembler, TimingConfig};
use scan3d_hw_sim::device::Device;
use scan3d_hw_sim::mounts;
use scan3d_hw_sim::pair::{Chunk, Pair, replay};
use scan3d_hw_sim::rplidar::{RplidarEmulator, RplidarEmulatorConfig};
use scan3d_hw_sim::sweep::{SweepEmulator, SweepEmulatorConfig};
use scan3d_hw_sim::world::World;

const MS: u64 = 1_000_000;
/// Seconds of streaming recorded per stream.
const SECONDS: u64 = 10;
const RUNS: usize = 7;

struct Stream {
    name: &'static str,
    chunks: Vec<Chunk>,
    make_driver: fn() -> Box<dyn LidarDriver>,
}

impl Stream {
    fn bytes(&self) -> usize {
        self.chunks.iter().map(|(_, b)| b.len()).sum()
    }
    /// Simulated seconds covered by the recording.
    fn seconds(&self) -> f64 {
        match (self.chunks.first(), self.chunks.last()) {
            (Some(first), Some(last)) => (last.0 - first.0) as f64 / 1e9,
            _ => 0.0,
        }
    }
}

fn record<D: LidarDriver, E: Device>(driver: D, device: E, settle_ms: u64) -> Vec<Chunk> {
    // Serial reads of about 2 ms, as a USB adapter with a short latency timer delivers them.
    let mut pair = Pair::new(driver, device, 2 * MS).record();
    pair.run_until((settle_ms + SECONDS * 1000) * MS, |_, _| {});
    pair.recording.take().unwrap_or_default()
}

fn streams() -> Vec<Stream> {
    let world = Arc::new(World::conference_room());
    let rplidar = |mode| {
        let device = RplidarEmulator::new(
            RplidarEmulatorConfig {
                spinup_s: 0.2,
                ..Default::default()
            },
            RplidarEmulator::default_scanner(world.clone(), mounts::rplidar()),
            1,
        );
        record(
            Rplidar::new(RplidarConfig {
                scan_mode: mode,
                ..Default::default()
            }),
            device,
            300,
        )
    };
    let sweep_device = SweepEmulator::new(
        SweepEmulatorConfig {
            settle_ms: 500,
            sample_rate_code: 3,
            ..Default::default()
        },
        SweepEmulator::default_scanner(world.clone(), mounts::sweep()),
        2,
    );
    let sweep_driver = Sweep::new(SweepConfig::default()).expect("valid sweep config");
    vec![
        Stream {
            name: "rplidar standard nodes",
            chunks: rplidar(ScanMode::Standard),
            make_driver: || {
                Box::new(Rplidar::new(RplidarConfig {
                    scan_mode: ScanMode::Standard,
                    ..Default::default()
                }))
            },
        },
        Stream {
            name: "rplidar express capsules",
            chunks: rplidar(ScanMode::Express),
            make_driver: || Box::new(Rplidar::new(RplidarConfig::default())),
        },
        Stream {
            name: "sweep blocks (1025 Hz)",
            chunks: record(sweep_driver, sweep_device, 600),
            make_driver: || Box::new(Sweep::new(SweepConfig::default()).expect("valid config")),
        },
    ]
}

/// Decodes a recording with a fresh driver and assembles revolutions; returns the samples.
fn decode(stream: &Stream) -> u64 {
    let mut driver = (stream.make_driver)();
    let mut assembler = RevolutionAssembler::new(TimingConfig::default());
    let mut samples = 0;
    replay(driver.as_mut(), &stream.chunks, |event| {
        if let LidarEvent::Sample(sample) = event {
            samples += 1;
            black_box(assembler.push(sample));
        }
    });
    samples
}

fn best_of(stream: &Stream) -> (Duration, u64) {
    let mut best = Duration::MAX;
    let mut samples = 0;
    for _ in 0..RUNS {
        let start = Instant::now();
        samples = black_box(decode(black_box(stream)));
        best = best.min(start.elapsed());
    }
    (best, samples)
}

fn main() {
    let streams = streams();
    println!(
        "edge driver benchmark: {SECONDS} s of emulated sensor data per stream, best of {RUNS}"
    );
    println!(
        "{:<26} {:>9} {:>9} {:>10} {:>10} {:>12}",
        "stream", "bytes", "samples", "time", "MB/s", "core share"
    );
    let mut share = std::collections::BTreeMap::new();
    for stream in &streams {
        let (time, samples) = best_of(stream);
        let core_share = time.as_secs_f64() / stream.seconds();
        share.insert(stream.name, core_share);
        println!(
            "{:<26} {:>9} {:>9} {:>8.2}ms {:>10.1} {:>11.4}%",
            stream.name,
            stream.bytes(),
            samples,
            time.as_secs_f64() * 1e3,
            stream.bytes() as f64 / time.as_secs_f64() / 1e6,
            core_share * 100.0
        );
    }
    let both = share
        .get("rplidar express capsules")
        .copied()
        .unwrap_or(0.0)
        + share.get("sweep blocks (1025 Hz)").copied().unwrap_or(0.0);
    println!(
        "both lidars at full rate (express + sweep 1025 Hz), decode + revolution timing: {:.4} % of one core (goal <= 3 %)",
        both * 100.0
    );
}
