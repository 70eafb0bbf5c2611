//! The session pipeline's costs at the demo's size (the simulator's 8 × 6 × 3 m conference room,
//! six static-scan positions, 0.05 m voxels, the Sweep at 2 Hz: 500 samples per revolution,
//! 100 revolutions per position):
//!
//! - **throughput**: lidar samples per second through assembly (eq. 1) and octree insertion,
//!   with only the session's octree (`scan3d map SESSION_DIR`) and with everything the live
//!   daemon keeps (octrees per session and position, the cloud);
//! - **metrics update**: what one `status()` refresh costs against a reference of the same
//!   room (the octree derived, its `.bt` view, every metric; goal ≤ 50 ms).
//!
//! `cargo bench -p scan3d-server --bench pipeline` (add `-- --quick` for a smaller run).

#[path = "../tests/pipeline_support/mod.rs"]
mod support;

use std::time::{Duration, Instant};

use scan3d_map::eval::{LeafMap, evaluate};
use scan3d_map::octree::SensorModel;
use scan3d_protocol::{Body, Frame, SensorId};
use scan3d_server::pipeline::offline::MAP_ONLY;
use scan3d_server::pipeline::{PipelineSettings, Products, SessionPipeline};
use support::{DEMO_ROOM, SessionBuilder, position};

/// The demo's reference map positions (hw-sim `maps::paper_maps`, map `ref`).
fn positions() -> Vec<scan3d_map::cloud::assembly::Position> {
    vec![
        position("sw", 1.2, 1.2, 0.0),
        position("s", 4.0, 1.0, 0.0),
        position("se", 6.6, 1.6, 0.0),
        position("ne", 6.6, 4.2, 0.0),
        position("n", 4.0, 5.1, 0.0),
        position("nw", 1.2, 4.6, 0.0),
    ]
}

fn session(revolutions: u32, samples: u32, heading_deg: f64) -> Vec<Frame> {
    let mut s = SessionBuilder::in_room(1, DEMO_ROOM);
    for mut p in positions() {
        p.heading_deg = heading_deg;
        s.rplidar_revolutions(5, 400);
        s.static_scan(&p, revolutions, samples);
    }
    s.frames().cloned().collect()
}

/// Samples of the static scans' Sweep revolutions (the ones assembled and inserted).
fn sweep_samples(frames: &[Frame]) -> u64 {
    frames
        .iter()
        .map(|f| match &f.body {
            Body::Revolution(r) if r.sensor == SensorId::SWEEP => r.samples.len() as u64,
            _ => 0,
        })
        .sum()
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let (revolutions, samples) = if quick { (25, 250) } else { (100, 500) };
    let settings = PipelineSettings {
        resolution_m: 0.05,
        max_range_m: Some(6.0),
        ..PipelineSettings::default()
    };
    let frames = session(revolutions, samples, 0.0);
    let total = sweep_samples(&frames);
    println!(
        "session: {} frames, {total} Sweep samples in static scans (6 positions × {revolutions} revolutions × {samples} samples; RPLidar revolutions between)",
        frames.len()
    );

    let mut built = None;
    for (name, products) in [
        ("octree only", MAP_ONLY),
        ("live products", Products::default()),
    ] {
        let mut times = Vec::new();
        for _ in 0..3 {
            let mut pipeline = SessionPipeline::with_products(&settings, products).unwrap();
            let t = Instant::now();
            for f in &frames {
                pipeline.on_frame(f);
            }
            times.push(t.elapsed());
            built = Some(pipeline);
        }
        let t = median(times);
        println!(
            "throughput ({name}): {:.0} Sweep samples/s ({:.1} ms for the session, median of 3)",
            total as f64 / t.as_secs_f64(),
            t.as_secs_f64() * 1e3
        );
    }
    let pipeline = built.unwrap();
    let map = pipeline.maps().session_map();
    let tree = map.to_octree();
    println!(
        "map: {} known voxels, octree {} nodes / {} leaves, {:.1} MB in memory",
        map.num_voxels(),
        tree.num_nodes(),
        tree.num_leaves(),
        map.memory_bytes() as f64 / 1e6
    );

    // The reference: the same room scanned from the same positions turned by 1°.
    let dir = std::env::temp_dir().join(format!("scan3d-pipeline-bench-{}", std::process::id()));
    let reference = {
        let mut p = SessionPipeline::with_products(&settings, MAP_ONLY).unwrap();
        for f in &session(revolutions, samples, 1.0) {
            p.on_frame(f);
        }
        p.write_snapshot(&dir, None).unwrap();
        dir.join("map.bt")
    };
    let with_reference = PipelineSettings {
        reference: Some(reference),
        ..settings.clone()
    };
    let mut live = SessionPipeline::new(&with_reference).unwrap();
    let split = frames.len() - 40;
    for f in &frames[..split] {
        live.on_frame(f);
    }
    let start = Instant::now();
    let mut times = Vec::new();
    for (i, f) in frames[split..].iter().enumerate() {
        // One more frame, then a status a second later: every call refreshes.
        live.on_frame(f);
        let now = start + Duration::from_secs(2 * (i as u64 + 1));
        let t = Instant::now();
        let status = live.status_at(now);
        times.push(t.elapsed());
        assert!(status.metrics.is_some(), "metrics against the reference");
    }
    let status = live.status_at(start + Duration::from_secs(10_000));
    let m = status.metrics.unwrap();
    times.sort();
    println!(
        "metrics update (status refresh, {} refreshes): median {:.1} ms, max {:.1} ms (goal ≤ 50 ms); \
         |U| = {} voxels, IoU occupied {:.3}, weighted {:.3}",
        times.len(),
        times[times.len() / 2].as_secs_f64() * 1e3,
        times[times.len() - 1].as_secs_f64() * 1e3,
        m.voxels,
        m.iou.occupied.unwrap_or(f64::NAN),
        m.iou.weighted
    );
    // Where a refresh's time goes.
    let reference_map = live.reference().unwrap();
    let t = Instant::now();
    let tree = live.maps().session_map().to_octree();
    let t_tree = t.elapsed();
    let t = Instant::now();
    let bt = tree.to_bt_bytes();
    let t_bt = t.elapsed();
    let t = Instant::now();
    let leaves = LeafMap::read_bt(&bt, SensorModel::default()).unwrap();
    let t_read = t.elapsed();
    let t = Instant::now();
    evaluate(reference_map, &leaves, None).unwrap();
    let t_eval = t.elapsed();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "  of which: octree derived {:.1} ms, .bt written {:.1} ms ({} bytes), .bt read {:.1} ms, metrics {:.1} ms",
        ms(t_tree),
        ms(t_bt),
        bt.len(),
        ms(t_read),
        ms(t_eval)
    );
    let t = Instant::now();
    let snap = live.write_snapshot(&dir.join("snapshot"), None).unwrap();
    println!(
        "snapshot (map.bt, map.ot, cloud.ply of {} points, metrics): {:.1} ms",
        snap.points,
        t.elapsed().as_secs_f64() * 1e3
    );
    let _ = std::fs::remove_dir_all(&dir);
}
