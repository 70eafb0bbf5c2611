//! The paper's static maps of the conference room, made through the whole system: for each map
//! a [`ScanRig`] (Sweep on the turntable, IMU and HAT on I2C), the edge daemon, and the server;
//! at each position the operator's `StartStaticScan` goes server → edge over QUIC, the edge
//! steps the turntable during the blind sector and streams yaw-tagged samples, and the cloud is
//! assembled by eq. (1) from the **recorded session** (`scan3d assemble`'s code), then scored
//! against the world's true surface.
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
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::assembly::{Position, cut_range};
use scan3d_map::cloud::filter::{Filter, apply_all};
use scan3d_map::cloud::io;
use scan3d_map::octree::{Octree, Resolution, SensorModel, VoxelMap};
use scan3d_protocol::{Body, StaticScan, StaticScanOutcome};
use scan3d_server::cli::DataDirArgs;
use scan3d_server::cli::assemble::assemble_session;
use scan3d_server::cli::scan::{At, ScanArgs};
use scan3d_server::ingest::recorder::session_dir;
use scan3d_server::ingest::server::IngestEvent;

use crate::noise::RangeNoise;
use crate::rig::{self, EDGE_NAME, EdgeThread, ServerThread};
use crate::static_rig::{ScanRig, ScanRigOptions};
use crate::truth::{Accuracy, GroundTruth};
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
}

/// Runs one map: starts a server, the rig and the edge, scans every position, assembles the
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
    } = *setup;
    let first = plan
        .positions
        .first()
        .context("a map needs at least one position")?;
    let work = work.join(plan.name);
    let pki = work.join("pki");
    let bundle = rig::pair_certificates(&pki)?;
    let mut server = ServerThread::start(rig::ingest_config(&pki, data_dir, 0))?;
    let rig = ScanRig::start(
        &work.join("links"),
        world.clone(),
        first.clone(),
        &ScanRigOptions {
            time_scale,
            motor_hz: plan.motor_hz,
            seed,
            sweep_settle_ms: 3000,
            noise,
        },
    )?;
    let clock = ScaledClock::new(time_scale);
    let shared: SharedClock = Arc::new(clock);
    let config = rig.edge_config(
        &work.join("edge-state"),
        Some(rig::uplink_section(server.addr(), &bundle)),
    );
    let session_id = rand::random::<u64>();
    let edge = EdgeThread::start_with_i2c(config, shared, session_id, Some(rig.bus()))?;
    let bus_start = (rig.bus_stats().transactions, clock.now_ns());

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
        rig.move_to(position.clone());
        // What the operator types: `scan3d scan --edge sim-edge --at X,Y,HEADING --name POS`,
        // through the server's control socket.
        let scan = ScanArgs {
            edge: EDGE_NAME.into(),
            at: Some(At {
                x_m: position.x_m,
                y_m: position.y_m,
                heading_deg: Some(position.heading_deg),
            }),
            name: Some(position.name.clone()),
            stop: false,
            data: DataDirArgs {
                data_dir: Some(data_dir.to_path_buf()),
                config: PathBuf::from("/nonexistent/server.toml"),
            },
        };
        let started = clock.now_ns();
        scan3d_server::cli::scan::run(&scan, &mut std::io::sink())
            .with_context(|| format!("scan3d scan at {}", position.name))?;
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
        while rig.rotor_deg().abs() > 1e-6 && Instant::now() < home_by {
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    let (transactions, bus_ns) = (
        rig.bus_stats().transactions - bus_start.0,
        clock.now_ns() - bus_start.1,
    );
    let steps_lost = rig.steps_lost();
    edge.stop()?;
    drain(&mut server);
    server.stop();
    rig.shutdown();

    let session = session_dir(data_dir, EDGE_NAME, session_id);
    let assembled = assemble_session(&session)?;
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
    })
}

/// The paper's Table II filters for a map of the conference room: down-sampling and a
/// pass-through box that keeps the room and cuts the glass wall (y ≥ 5.9 m) and what was seen
/// through it or the doorway away; `ref` is also Gaussian-smoothed.
pub fn table_ii_filters(name: &str) -> Vec<Filter> {
    let mut filters = vec![
        Filter::Voxel { leaf: 0.02 },
        Filter::Box {
            min: [-0.2, -0.2, -0.2],
            max: [8.05, 5.9, 3.2],
        },
    ];
    if name == "ref" {
        filters.push(Filter::Gauss {
            sigma: 0.02,
            radius: 0.05,
        });
    }
    filters
}

/// Filters a map's cloud (Table II) and inserts it, each half revolution from its own sensor
/// origin, into an OctoMap-identical occupancy map at `resolution`.
pub fn build_map(
    name: &str,
    cloud: &[RayBundle],
    resolution: f64,
) -> anyhow::Result<(Vec<RayBundle>, Octree)> {
    let filtered = apply_all(&table_ii_filters(name), cloud.to_vec())?;
    let mut map = VoxelMap::new(Resolution::new(resolution)?, SensorModel::default());
    for scan in &filtered {
        map.insert_bundle(scan, -1.0);
    }
    Ok((filtered, map.to_octree()))
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
