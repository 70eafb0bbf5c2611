//! The paper's static maps of the conference room, made through the whole system: for each map
//! a [`TurntableHead`] (Sweep on the turntable, IMU and HAT on I2C), the edge daemon, and the server;
//! at each position the operator's `StartStaticScan` goes server → edge over QUIC, the edge
//! steps the turntable during the blind sector and streams yaw-tagged samples. The server runs
//! the live pipeline as `scan3d serve` does, and the map is the daemon's own: a
//! `scan3d snapshot` request on its control socket once the scans are done writes its octree
//! (`map.bt`, `map.ot`) and filtered cloud. The raw cloud is assembled by eq. (1) from the
//! **recorded session** (the pipeline's offline driver), then scored against the world's true
//! surface.
//!
//! | map | positions | Sweep | range cut |
//! | --- | --- | --- | --- |
//! | `map2` | 1 | 1 Hz | 10 m |
//! | `map3` | 4 | 2 Hz | 6 m |
//! | `ref` | 6 | 2 Hz | 6 m |

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use scan3d_edge::clock::{Clock, ScaledClock, SharedClock};
use scan3d_edge::config::RplidarSection;
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::assembly::{Position, cut_range};
use scan3d_map::cloud::filter::Filter;
use scan3d_map::cloud::io;
use scan3d_protocol::{Body, Command, StaticScan, StaticScanOutcome};
use scan3d_server::ingest::control::{
    ControlRequest, ProductRequest, request, request_products, request_snapshot, socket_path,
};
use scan3d_server::ingest::server::IngestEvent;
use scan3d_server::pipeline::PipelineSettings;
use scan3d_server::pipeline::live::LiveSettings;
use scan3d_server::pipeline::offline::assemble_session;
use scan3d_server::recording::session_dir;
use scan3d_server::report::MetricBox;

use crate::installation::{self, EDGE_NAME, EdgeThread, ServerThread};
use crate::noise::RangeNoise;
use crate::truth::{Accuracy, GroundTruth};
use crate::turntable_head::{TurntableHead, TurntableHeadOptions};
use crate::world::World;

/// One map of the paper's experiment.
#[derive(Debug, Clone, PartialEq)]
pub struct MapPlan {
    /// File stem (`map2`, `map3`, `ref`).
    pub name: &'static str,
    /// Scan positions in the room frame.
    pub positions: Vec<Position>,
    /// Sweep rotation rate, Hz.
    pub motor_hz: u8,
    /// Points farther than this from their sensor origin are cut, metres.
    pub max_range_m: f64,
}

fn at(name: &str, x_m: f64, y_m: f64) -> Position {
    Position {
        name: name.to_owned(),
        x_m,
        y_m,
        heading_deg: 0.0,
    }
}

/// The paper's three static maps (see the module table), positions clear of the furniture.
pub fn paper_maps() -> Vec<MapPlan> {
    vec![
        MapPlan {
            name: "map2",
            positions: vec![at("west", 1.5, 3.0)],
            motor_hz: 1,
            max_range_m: 10.0,
        },
        MapPlan {
            name: "map3",
            positions: vec![
                at("sw", 1.5, 1.2),
                at("se", 6.5, 1.2),
                at("ne", 6.2, 4.6),
                at("nw", 1.5, 4.8),
            ],
            motor_hz: 2,
            max_range_m: 6.0,
        },
        MapPlan {
            name: "ref",
            positions: vec![
                at("sw", 1.2, 1.2),
                at("s", 4.0, 1.0),
                at("se", 6.6, 1.6),
                at("ne", 6.6, 4.2),
                at("n", 4.0, 5.1),
                at("nw", 1.2, 4.6),
            ],
            motor_hz: 2,
            max_range_m: 6.0,
        },
    ]
}

/// What one map run produced.
#[derive(Debug, Clone)]
pub struct MapResult {
    /// The plan.
    pub plan: MapPlan,
    /// The cloud with its sensor origins (after the range cut).
    pub cloud: Vec<RayBundle>,
    /// Files written (`.ply`, `.scans`).
    pub files: Vec<PathBuf>,
    /// Accuracy against the true surface.
    pub accuracy: Option<Accuracy>,
    /// Per position: simulated seconds from command to `Finished`.
    pub scan_seconds: Vec<f64>,
    /// Warnings the edge reported (late / failed steps, missed sectors).
    pub warnings: usize,
    /// Points cut by the range limit.
    pub cut: usize,
    /// Steps the emulated rotor lost (driven faster than it follows): must be 0.
    pub steps_lost: u64,
    /// The IMU frames seen while scanning.
    pub imu: ImuSeen,
    /// I2C transactions per simulated second during the map.
    pub i2c_per_s: f64,
    /// The recorded session.
    pub session_dir: PathBuf,
    /// Where the live daemon's snapshot of the session went (`map.bt`, `map.ot`, `cloud.ply`).
    pub snapshot_dir: PathBuf,
    /// The session's line of `scan3d status` (JSON) just before the snapshot: frames, voxels,
    /// the pipeline's lag.
    pub live_status: serde_json::Value,
}

impl MapResult {
    /// Number of points.
    pub fn points(&self) -> usize {
        self.cloud.iter().map(|s| s.points.len()).sum()
    }
}

/// The IMU stream the server recorded during a map.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ImuSeen {
    /// `Imu` frames recorded.
    pub frames: u64,
    /// The last Madgwick orientation `[w, x, y, z]` the edge sent.
    pub last_orientation: Option<[f32; 4]>,
}

/// Where and how maps are made.
#[derive(Debug, Clone, Copy)]
pub struct MapSetup<'a> {
    /// The simulated room.
    pub world: &'a Arc<World>,
    /// Its true surface, for scoring.
    pub truth: &'a GroundTruth,
    /// Scratch space (certificates, pty links, edge state).
    pub work: &'a Path,
    /// The server's data directory (recordings).
    pub data_dir: &'a Path,
    /// Where the clouds go.
    pub clouds_dir: &'a Path,
    /// Simulated seconds per real second.
    pub time_scale: f64,
    /// World noise seed.
    pub seed: u64,
    /// The Sweep's range noise ([`RangeNoise::SWEEP`] for the paper's device).
    pub noise: RangeNoise,
    /// Octree resolution of the live daemon's maps, metres.
    pub resolution_m: f64,
    /// The live pipeline's queue per session (`[pipeline] queue_frames`).
    pub queue_frames: usize,
    /// The live snapshots go to `snapshots_dir/<map>/`.
    pub snapshots_dir: &'a Path,
    /// Both lidars at their full rates, as in the field: an RPLidar (4 kHz) streams beside the
    /// Sweep, which samples at 1 kHz (the live pipeline benchmark); otherwise the Sweep alone at
    /// its power-on rate.
    pub full_rates: bool,
}

/// Runs one map: starts a server, the turntable head and the edge, scans every position, assembles the
/// recording and writes `clouds_dir/<name>.ply` and `.scans`.
pub fn scan_map(plan: &MapPlan, setup: &MapSetup<'_>) -> anyhow::Result<MapResult> {
    let MapSetup {
        world,
        truth,
        work,
        data_dir,
        clouds_dir,
        time_scale,
        seed,
        noise,
        resolution_m,
        queue_frames,
        snapshots_dir,
        full_rates,
    } = *setup;
    let first = plan
        .positions
        .first()
        .context("a map needs at least one position")?;
    let work = work.join(plan.name);
    let pki = work.join("pki");
    let bundle = installation::pair_certificates(&pki)?;
    let live = LiveSettings {
        queue_frames,
        ..LiveSettings::new(map_pipeline(plan, resolution_m), data_dir.to_path_buf())
    };
    let mut server =
        ServerThread::start_live(installation::ingest_config(&pki, data_dir, 0), live)?;
    let socket = socket_path(data_dir);
    let head = TurntableHead::start(
        &work.join("links"),
        world.clone(),
        first.clone(),
        &TurntableHeadOptions {
            time_scale,
            motor_hz: plan.motor_hz,
            seed,
            sweep_settle_ms: 3000,
            noise,
        },
    )?;
    let clock = ScaledClock::new(time_scale);
    let shared: SharedClock = Arc::new(clock);
    let mut config = head.edge_config(
        &work.join("edge-state"),
        Some(installation::uplink_section(server.addr(), &bundle)),
    );
    let rplidar = if full_rates {
        let options = installation::LidarOptions {
            time_scale,
            seed,
            ..Default::default()
        };
        let pty = installation::spawn_rplidar(&work.join("links"), world.clone(), &options)?;
        config.rplidar = Some(RplidarSection {
            path: pty.link().to_path_buf(),
            driver: Default::default(),
            mount: None,
        });
        if let Some(sweep) = &mut config.sweep {
            sweep.driver.sample_rate_code = Some(3);
        }
        Some(pty)
    } else {
        None
    };
    let session_id = rand::random::<u64>();
    let edge = EdgeThread::start_with_i2c(config, shared, session_id, Some(head.bus()))?;
    let bus_start = (head.bus_stats().transactions, clock.now_ns());

    // Scanning: the server has the Sweep's revolutions at the planned rate.
    let ready_by = Instant::now() + Duration::from_secs_f64(60.0 / time_scale + 20.0);
    let mut imu = ImuSeen::default();
    wait_for(&mut server, ready_by, &mut imu, |body| {
        matches!(body, Body::Revolution(rev) if rev.sensor == scan3d_protocol::SensorId::SWEEP
            && rev.t1_ns.saturating_sub(rev.t0_ns) > (0.8e9 / f64::from(plan.motor_hz)) as u64)
    })
    .context("the Sweep never reached its scan rate")?;

    let mut scan_seconds = Vec::new();
    let mut warnings = 0;
    for position in &plan.positions {
        head.move_to(position.clone());
        // What the operator types: `scan3d scan --edge sim-edge --at X,Y,HEADING --name POS`,
        // through the server's control socket.
        let command = ControlRequest {
            edge: EDGE_NAME.into(),
            command: Command::StartStaticScan {
                position: position.name.clone(),
                x_m: position.x_m,
                y_m: position.y_m,
                heading_deg: Some(position.heading_deg),
            },
        };
        let started = clock.now_ns();
        let reply = request(&socket, &command)
            .with_context(|| format!("scan3d scan at {}", position.name))?;
        anyhow::ensure!(
            reply.ok,
            "scan3d scan at {}: {}",
            position.name,
            reply.detail
        );
        // 100 revolutions plus the way home; generous for a loaded machine.
        let sim_budget = 130.0 / f64::from(plan.motor_hz) + 10.0;
        let deadline = Instant::now() + Duration::from_secs_f64(sim_budget / time_scale + 30.0);
        let mut outcome = None;
        wait_for(&mut server, deadline, &mut imu, |body| match body {
            Body::StaticScan(StaticScan::Warning(_)) => {
                warnings += 1;
                false
            }
            Body::StaticScan(StaticScan::Finished(end)) => {
                outcome = Some(end.outcome);
                true
            }
            _ => false,
        })
        .with_context(|| {
            format!(
                "{}: the scan at {} never finished",
                plan.name, position.name
            )
        })?;
        anyhow::ensure!(
            outcome == Some(StaticScanOutcome::Completed),
            "{}: the scan at {} ended {outcome:?}",
            plan.name,
            position.name
        );
        scan_seconds.push(clock.now_ns().saturating_sub(started) as f64 / 1e9);
        // The turntable goes home before the operator carries it on.
        let home_by = Instant::now() + Duration::from_secs(10);
        while head.rotor_deg().abs() > 1e-6 && Instant::now() < home_by {
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    let (transactions, bus_ns) = (
        head.bus_stats().transactions - bus_start.0,
        clock.now_ns() - bus_start.1,
    );
    let steps_lost = head.steps_lost();
    // Everything the edge sent is acknowledged once it has stopped.
    edge.stop()?;
    drain(&mut server);
    // The map is the live daemon's: `scan3d status`, then `scan3d snapshot` of this session.
    let session_hex = format!("{session_id:016x}");
    let status = request_products(&socket, &ProductRequest::Status)?;
    anyhow::ensure!(status.ok, "scan3d status: {}", status.detail);
    let snapshot_dir = snapshots_dir.join(plan.name);
    let snapshot = request_snapshot(&socket, EDGE_NAME, Some(&session_hex), None, &snapshot_dir)
        .with_context(|| format!("scan3d snapshot of {}", plan.name))?;
    tracing::info!(map = plan.name, detail = %snapshot.detail, "live snapshot");
    let live_status = session_status(status.data.as_ref(), &session_hex)
        .with_context(|| format!("scan3d status has no line for session {session_hex}"))?;
    server.stop();
    head.shutdown();
    if let Some(pty) = rplidar {
        pty.shutdown();
    }

    let session = session_dir(data_dir, EDGE_NAME, session_id);
    let assembled = assemble_session(&session, false)?;
    let mut cloud: Vec<RayBundle> = assembled.into_iter().flat_map(|scan| scan.scans).collect();
    let cut = cut_range(&mut cloud, plan.max_range_m);
    let accuracy = truth.accuracy(
        cloud
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.map(f64::from))),
    );
    let mut files = Vec::new();
    for ext in ["ply", "scans"] {
        let path = clouds_dir.join(format!("{}.{ext}", plan.name));
        io::save(&path, &cloud)?;
        files.push(path);
    }
    Ok(MapResult {
        plan: plan.clone(),
        cloud,
        files,
        accuracy,
        scan_seconds,
        warnings,
        cut,
        steps_lost,
        imu,
        i2c_per_s: transactions as f64 / (bus_ns.max(1) as f64 / 1e9),
        session_dir: session,
        snapshot_dir,
        live_status,
    })
}

/// The line of session `id` in a `scan3d status` report.
pub fn session_status(report: Option<&serde_json::Value>, id: &str) -> Option<serde_json::Value> {
    report?["edges"]
        .as_array()?
        .iter()
        .flat_map(|edge| edge["sessions"].as_array().into_iter().flatten())
        .find(|session| session["id"] == id)
        .cloned()
}

/// The pass-through box of Table II for the conference room, metres: the room with its walls,
/// floor and ceiling (they lie just outside the 8 × 6 × 3 m interior), cut at y = 5.9 m before
/// the glass wall. The maps hold nothing outside it, and the demo scores them inside it.
pub const PASS_THROUGH_BOX: MetricBox = MetricBox {
    min: [-0.2, -0.2, -0.2],
    max: [8.05, 5.9, 3.2],
};

/// The paper's Table II filters for a map of the conference room: down-sampling and a
/// pass-through box that keeps the room and cuts the glass wall (y ≥ 5.9 m) and what was seen
/// through it or the doorway away, per revolution; `ref`'s cloud is also Gaussian-smoothed
/// when a snapshot is written (it needs neighbours across revolutions).
pub fn table_ii_filters(name: &str) -> (Vec<Filter>, Vec<Filter>) {
    let revolution = vec![
        Filter::Voxel { leaf: 0.02 },
        Filter::Box {
            min: PASS_THROUGH_BOX.min,
            max: PASS_THROUGH_BOX.max,
        },
    ];
    let snapshot = if name == "ref" {
        vec![Filter::Gauss {
            sigma: 0.02,
            radius: 0.05,
        }]
    } else {
        Vec::new()
    };
    (revolution, snapshot)
}

/// The live daemon's `[pipeline]` for a map: Table II filters, the plan's range cut, octrees at
/// `resolution_m` with OctoMap's sensor model.
pub fn map_pipeline(plan: &MapPlan, resolution_m: f64) -> PipelineSettings {
    let (revolution_filters, snapshot_filters) = table_ii_filters(plan.name);
    PipelineSettings {
        resolution_m,
        max_range_m: Some(plan.max_range_m),
        revolution_filters,
        snapshot_filters,
        ..PipelineSettings::default()
    }
}

/// Waits until the server records a frame whose body satisfies `done`.
fn wait_for(
    server: &mut ServerThread,
    deadline: Instant,
    imu: &mut ImuSeen,
    mut done: impl FnMut(&Body) -> bool,
) -> anyhow::Result<()> {
    loop {
        while let Ok(event) = server.events.try_recv() {
            let IngestEvent::Frame { frame, .. } = event else {
                continue;
            };
            if let Body::Imu(sample) = &frame.body {
                imu.frames += 1;
                imu.last_orientation = sample.orientation.or(imu.last_orientation);
            }
            if done(&frame.body) {
                return Ok(());
            }
        }
        anyhow::ensure!(Instant::now() < deadline, "timed out");
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn drain(server: &mut ServerThread) {
    while server.events.try_recv().is_ok() {}
}
