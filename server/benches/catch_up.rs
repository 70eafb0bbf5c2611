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

/// Records `frames` (the session's from its `first`th on) with the real recorder, committing
/// every [`FRAMES_PER_COMMIT`] of the session, as ingest does; the recorder stays open (a live
/// session's last file has no summary yet).
fn record(recorder: &mut SessionRecorder, frames: &[Frame], first: usize) {
    for (n, frame) in frames.iter().enumerate() {
        let n = (first + n) as u64;
        let raw = encode(frame).expect("encode");
        recorder.append(&raw, frame, 1_000 + n).expect("append");
        if n % FRAMES_PER_COMMIT == FRAMES_PER_COMMIT - 1 {
            recorder.commit().expect("commit");
        }
    }
    recorder.commit().expect("commit");
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

/// Microseconds per caught-up frame.
fn per_frame(time: Duration, frames: u64) -> f64 {
    time.as_secs_f64() * 1e6 / frames.max(1) as f64
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
        "cold: the worker's first read of the recording; after read-on: the worker read on through the recording just before the gap (it does every read_on_every while it owes nothing)"
    );
    println!(
        "{:>10} {:>6} {:>10} {:>14} {:>13} {:>16} {:>15}",
        "frames",
        "files",
        "caught up",
        "cold µs/frame",
        "cold read ms",
        "read-on µs/frame",
        "read-on read ms"
    );
    let mut rows = Vec::new();
    for &length in &args.lengths {
        let data = tempfile::tempdir().expect("temporary directory");
        settings.data_dir = data.path().to_path_buf();
        let frames = frames(length);
        let owed_from = length.saturating_sub(args.owed);
        let split = owed_from as usize;
        let mut recorder =
            SessionRecorder::open(data.path(), EDGE, SESSION).expect("open the recorder");
        record(&mut recorder, &frames[..split], 0);
        // Workers that processed everything recorded so far and read on through it.
        let runs = args.runs.max(1);
        let mut followers: Vec<CatchUpProbe> = (0..runs)
            .map(|_| {
                let mut probe = CatchUpProbe::new(&settings, EDGE, SESSION, owed_from)
                    .expect("build the pipeline");
                assert_eq!(probe.read_on(), 0, "nothing before the gap is owed");
                probe
            })
            .collect();
        // The same, counting the gap's frames as processed too: their read alone.
        let mut readers: Vec<CatchUpProbe> = (0..runs)
            .map(|_| {
                let mut probe = CatchUpProbe::new(&settings, EDGE, SESSION, length)
                    .expect("build the pipeline");
                assert_eq!(probe.read_on(), 0, "nothing is owed");
                probe
            })
            .collect();
        record(&mut recorder, &frames[split..], split);
        let files = std::fs::read_dir(recorder.session_dir())
            .expect("session directory")
            .filter_map(Result::ok)
            .filter(|e| e.path().extension().is_some_and(|x| x == "mcap"))
            .count();
        let (mut cold, mut reads, mut warm, mut warm_reads) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut caught_up = 0;
        for (follower, reader) in followers.iter_mut().zip(&mut readers) {
            let mut probe =
                CatchUpProbe::new(&settings, EDGE, SESSION, owed_from).expect("build the pipeline");
            let started = Instant::now();
            caught_up = probe.catch_up();
            cold.push(started.elapsed());
            // The reading share alone: the same read, nothing processed.
            let started = Instant::now();
            let report = SessionReader::new(recorder.session_dir())
                .from_seq(owed_from)
                .visit(|_| Ok(()))
                .expect("read the recording");
            assert!(report.losses.is_empty(), "{:?}", report.loss_line());
            reads.push(started.elapsed());
            let started = Instant::now();
            assert_eq!(follower.catch_up(), caught_up, "the same frames caught up");
            warm.push(started.elapsed());
            let started = Instant::now();
            assert_eq!(reader.read_on(), 0, "the gap counted as processed");
            warm_reads.push(started.elapsed());
        }
        let (cold, read, warm, warm_read) = (
            median(cold),
            median(reads),
            median(warm),
            median(warm_reads),
        );
        let row = (
            length,
            per_frame(cold, caught_up),
            per_frame(warm, caught_up),
        );
        println!(
            "{length:>10} {files:>6} {caught_up:>10} {:>14.1} {:>13.1} {:>16.1} {:>15.1}",
            row.1,
            read.as_secs_f64() * 1e3,
            row.2,
            warm_read.as_secs_f64() * 1e3
        );
        rows.push(row);
        drop(recorder);
    }
    if let (Some(&(first_len, first_cold, first_warm)), Some(&(last_len, last_cold, last_warm))) =
        (rows.first(), rows.last())
        && rows.len() > 1
    {
        println!(
            "ratio {}k / {}k per caught-up frame: {:.2} cold, {:.2} after read-on",
            last_len / 1000,
            first_len / 1000,
            last_cold / first_cold,
            last_warm / first_warm
        );
    }
}
