//! What a live worker's catch-up costs per frame as the session grows: sessions of 1 k, 10 k
//! and 100 k frames (the edge's mix: RPLidar revolutions at 10 Hz, Sweep revolutions at 2 Hz,
//! IMU samples at 200 Hz, after a `Hello`) are written with the real recorder, committed every
//! 100 ms of data as ingest does, the recorder left open as in a live session; then a worker
//! that processed everything but the last `--owed` frames from its queue catches up from the
//! recording through the daemon's own catch-up ([`CatchUpProbe`]). The cost per caught-up frame
//! should not grow with the session (the ratio 100k / 1k near 1). The read alone is timed too:
//! the files before the one holding the first frame owed are skipped through the session
//! index, but that file is read from its start (at most `CHUNKS_PER_FILE` commits).
//!
//! `cargo bench -p scan3d-server --bench catch_up` (`-- --lengths 1000,10000 --runs 5` …).

#[path = "../tests/pipeline_support/mod.rs"]
mod support;

use std::path::Path;
use std::time::{Duration, Instant};

use clap::Parser;
use scan3d_protocol::{
    Body, Frame, Hello, ImuSample, LidarRevolution, SensorId, SensorInfo, encode,
};
use scan3d_server::pipeline::PipelineSettings;
use scan3d_server::pipeline::live::{CatchUpProbe, LiveSettings};
use scan3d_server::recording::{SessionReader, SessionRecorder};
use support::{DEMO_ROOM, range_to_walls};

#[derive(Parser, Debug)]
#[command(about = "live catch-up cost per frame against the session's length")]
struct Args {
    /// Session lengths, frames.
    #[arg(long, value_delimiter = ',', default_values_t = [1_000u64, 10_000, 100_000])]
    lengths: Vec<u64>,
    /// Frames owed at the end of each session (what the catch-up reads back).
    #[arg(long, default_value_t = 1_000)]
    owed: u64,
    /// Catch-ups measured per length (the median is printed).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Ignored (cargo bench passes it).
    #[arg(long, hide = true)]
    bench: bool,
}

const EDGE: &str = "bench-edge";
const SESSION: u64 = 0x20;
/// Edge time between IMU samples (200 Hz).
const IMU_PERIOD_NS: u64 = 5_000_000;
/// Frames per commit: 100 ms of the mix (ingest's default commit interval).
const FRAMES_PER_COMMIT: u64 = 21;

/// A revolution of `sensor` over `t0..t1` seen from the middle of the demo room, `samples`
/// ranges ray-cast against its walls (every 17th a dropout, as the RPLidar reports them).
fn revolution(sensor: SensorId, t0: u64, t1: u64, samples: u64) -> LidarRevolution {
    let mut rev = LidarRevolution::new(sensor, t0, t1);
    for i in 0..samples {
        let angle = 360.0 * i as f64 / samples as f64;
        let a = (-angle).to_radians();
        let (dir, origin) = if sensor == SensorId::SWEEP {
            // The Sweep turns in a vertical plane.
            ([a.cos(), 0.0, a.sin()], [4.0, 3.0, 1.0])
        } else {
            ([a.cos(), a.sin(), 0.0], [4.0, 3.0, 0.2])
        };
        let range = if i % 17 == 0 {
            0.0
        } else {
            range_to_walls(DEMO_ROOM, origin, dir) as f32
        };
        rev.push(angle as f32, range, 40, t0 + i * (t1 - t0) / samples)
            .expect("sample time within the revolution");
    }
    rev
}

/// The session's frames in the order the edge sends them (each at its end time).
fn frames(count: u64) -> Vec<Frame> {
    let sensor = |sensor, model: &str| SensorInfo {
        sensor,
        model: model.into(),
        firmware: String::new(),
        serial: String::new(),
    };
    let hello = Hello::new(
        "bench-edge",
        "0.0.0",
        vec![
            sensor(SensorId::RPLIDAR, "A1"),
            sensor(SensorId::SWEEP, "Sweep"),
            sensor(SensorId::IMU, "MPU-9250"),
        ],
    );
    let mut out = Vec::with_capacity(count as usize);
    out.push(Frame::new(SESSION, 0, Body::Hello(hello)));
    let start = 1_000_000_000u64;
    let mut tick = 1u64;
    while (out.len() as u64) < count {
        let t = start + tick * IMU_PERIOD_NS;
        let body = Body::Imu(ImuSample {
            t_ns: t,
            accel_mps2: [0.0, 0.0, 9.81],
            gyro_radps: [0.0; 3],
            mag_ut: if tick.is_multiple_of(2) {
                [20.0, 0.0, -40.0]
            } else {
                [f32::NAN; 3]
            },
            orientation: Some([1.0, 0.0, 0.0, 0.0]),
        });
        let mut bodies = vec![body];
        // An RPLidar revolution every 100 ms, a Sweep one every 500 ms, sent at their end.
        if tick.is_multiple_of(20) {
            bodies.push(Body::Revolution(revolution(
                SensorId::RPLIDAR,
                t - 100_000_000,
                t,
                360,
            )));
        }
        if tick.is_multiple_of(100) {
            bodies.push(Body::Revolution(revolution(
                SensorId::SWEEP,
                t - 500_000_000,
                t,
                500,
            )));
        }
        for body in bodies {
            if (out.len() as u64) < count {
                let seq = out.len() as u64;
                out.push(Frame::new(SESSION, seq, body));
            }
        }
        tick += 1;
    }
    out
}

/// Records `frames` under `data_dir` with the real recorder, committing every
/// [`FRAMES_PER_COMMIT`]; returns the recorder still open (a live session's last file has no
/// summary yet).
fn record(data_dir: &Path, frames: &[Frame]) -> SessionRecorder {
    let mut recorder = SessionRecorder::open(data_dir, EDGE, SESSION).expect("open the recorder");
    for (n, frame) in frames.iter().enumerate() {
        let raw = encode(frame).expect("encode");
        recorder
            .append(&raw, frame, 1_000 + n as u64)
            .expect("append");
        if n as u64 % FRAMES_PER_COMMIT == FRAMES_PER_COMMIT - 1 {
            recorder.commit().expect("commit");
        }
    }
    recorder.commit().expect("commit");
    recorder
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn main() {
    let args = Args::parse();
    let mut settings = LiveSettings::new(
        PipelineSettings {
            resolution_m: 0.05,
            max_range_m: Some(8.0),
            ..PipelineSettings::default()
        },
        std::path::PathBuf::new(),
    );
    println!(
        "catch-up of the last {} frames (median of {} runs; frames: RPLidar 10 Hz × 360, Sweep 2 Hz × 500, IMU 200 Hz; commit every {FRAMES_PER_COMMIT} frames)",
        args.owed, args.runs
    );
    println!(
        "{:>10} {:>6} {:>10} {:>12} {:>14} {:>10} {:>14}",
        "frames", "files", "caught up", "catch-up ms", "µs per frame", "read ms", "read µs/frame"
    );
    let mut per_frame = Vec::new();
    for &length in &args.lengths {
        let data = tempfile::tempdir().expect("temporary directory");
        settings.data_dir = data.path().to_path_buf();
        let frames = frames(length);
        let recorder = record(data.path(), &frames);
        let files = std::fs::read_dir(recorder.session_dir())
            .expect("session directory")
            .filter_map(Result::ok)
            .filter(|e| e.path().extension().is_some_and(|x| x == "mcap"))
            .count();
        let owed_from = length.saturating_sub(args.owed);
        let mut times = Vec::with_capacity(args.runs);
        let mut reads = Vec::with_capacity(args.runs);
        let mut caught_up = 0;
        for _ in 0..args.runs.max(1) {
            let mut probe =
                CatchUpProbe::new(&settings, EDGE, SESSION, owed_from).expect("build the pipeline");
            let started = Instant::now();
            caught_up = probe.catch_up();
            times.push(started.elapsed());
            // The reading share alone: the same read, nothing processed.
            let started = Instant::now();
            let report = SessionReader::new(recorder.session_dir())
                .from_seq(owed_from)
                .visit(|_| Ok(()))
                .expect("read the recording");
            assert!(report.losses.is_empty(), "{:?}", report.loss_line());
            reads.push(started.elapsed());
        }
        let (time, read) = (median(times), median(reads));
        let per = |d: Duration| d.as_secs_f64() * 1e6 / caught_up.max(1) as f64;
        let us = per(time);
        per_frame.push((length, us, per(read)));
        println!(
            "{length:>10} {files:>6} {caught_up:>10} {:>12.1} {us:>14.1} {:>10.1} {:>14.1}",
            time.as_secs_f64() * 1e3,
            read.as_secs_f64() * 1e3,
            per(read)
        );
        drop(recorder);
    }
    if let (Some(&(first_len, first, first_read)), Some(&(last_len, last, last_read))) =
        (per_frame.first(), per_frame.last())
        && per_frame.len() > 1
    {
        println!(
            "ratio {}k / {}k: {:.2} per caught-up frame ({:.2} for the read alone)",
            last_len / 1000,
            first_len / 1000,
            last / first,
            last_read / first_read
        );
    }
}
