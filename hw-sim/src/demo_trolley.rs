//! The demo's trolley pass, the paper's map1 (§III-B, mapping along movement): the rig's
//! trolley ([`TrolleyHead`]: RPLidar horizontal, Sweep across the direction of travel, the
//! erroneous MPU-9250/AK8963 of [`crate::imu::errors`]) pushed along a [`TrolleyPath`] through
//! the in-process edge daemon to a live server, the pass opened and closed through the
//! server's control socket as `scan3d trolley start --name map1` / `stop` do.
//!
//! Everything runs on one [`ScaledClock`] shared by the emulators and the edge, so an edge
//! sample time *is* the path's time: the truth of `base` at an edge time is exact. The server's
//! time sync cannot map an edge clock running ×10 (it holds skews within ±1000 ppm), so the
//! demo's two trajectories, `trajectories/map1.tum` and `truth/trolley.tum`, are both in
//! edge-clock seconds (the clock the server's own `trajectory.tum` falls back to), room frame.
//!
//! Before the pass the operator calibrates the magnetometer as on a real trolley: the trolley
//! turns once in place, slowly ([`CalibrationTurn`], [`TurnInPlace`]), while
//! `scan3d-edge calibrate mag`'s code reads the emulated chip through the edge's driver
//! ([`calibrate::collect_on_clock`] on the head's clock) and fits the horizontal ellipse
//! ([`calibrate::fit_mag`] with the site's field); the edge then runs with what it found
//! ([`MagSettings`]), never with the emulator's true iron. The gyro bias at rest is the
//! driver's own start-up estimate (the trolley rests after the turn), fresher than a saved
//! `calibrate gyro` bias would be.
//!
//! map1 itself: the live server's snapshot products of the pass (`passes/map1/cloud.ply`,
//! `map.bt`) when the live moving stage makes them; otherwise the recording assembled offline
//! as `scan3d assemble --moving SESSION --pass map1` does (`assemble_moving_sessions`, the
//! same stages; [`MapSource`] says which). Both are scored against the true surface. Table II's
//! filters for point cloud 1: the pass-through box only ([`PASS_THROUGH_BOX`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use nalgebra::Isometry3;
use scan3d_edge::calibrate::{self, LocalField, MagCalibration, MagSettings};
use scan3d_edge::clock::{Clock, ClockDelay, ScaledClock, SharedClock};
use scan3d_edge::config::{EdgeConfig, UplinkSection};
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::filter::Filter;
use scan3d_map::cloud::io;
use scan3d_map::cloud::moving::{PlanarTrajectory, TrajectoryPoint};
use scan3d_protocol::{Body, Command, SensorId};
use scan3d_server::cli::assemble_moving::{assemble_moving_sessions, session_trajectory};
use scan3d_server::ingest::control::{
    CommandRequest, ProductRequest, request_command, request_products, request_snapshot,
    socket_path,
};
use scan3d_server::ingest::server::IngestEvent;
use scan3d_server::pipeline::PassStatus;
use scan3d_server::pipeline::live::LiveSettings;
use scan3d_server::pipeline::{FusedRun, PipelineSettings, fuse_session};
use scan3d_server::recording::session_dir;
use scan3d_server::yaw_plot::{SourceRmse, rmse, write_fig5, yaw_errors};
use scan3d_slam::tum::{TrajectoryError, read_tum, trajectory_error};

use crate::faults::FaultConfig;
use crate::i2c::I2cBus;
use crate::imu::errors::{ErroneousImu, ImuErrors};
use crate::imu::{EarthField, ImuTruth, MountedImuTruth};
use crate::installation::{self, EDGE_NAME, EdgeThread, ServerThread};
use crate::maps::{PASS_THROUGH_BOX, session_status};
use crate::pty::{PtyDevice, PtyHandle, PtyOptions};
use crate::rig::{
    IMU_MOUNT, ROOM_MAGNETIC_NORTH_DEG, TROLLEY_RPLIDAR_MOUNT, TROLLEY_SWEEP_MOUNT, TRUTH_HZ,
    TumWriter, mount_pose, trolley_edge_toml_text,
};
use crate::rplidar::{RplidarEmulator, RplidarEmulatorConfig};
use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
use crate::trolley::{
    BaseTrajectory, BumpyTrolley, OnBase, TROLLEY_CLEARANCE_M, TrolleyPath, TurnInPlace,
};
use crate::truth::{Accuracy, GroundTruth};
use crate::turntable_head::head_bus;
use crate::world::World;

/// The pass's name (`scan3d trolley start --name map1`), the file stem of its products.
pub const PASS_NAME: &str = "map1";

/// Simulated seconds the pass stays open after the trolley has come to rest at its path's end.
const REST_AT_END_S: f64 = 1.0;

/// When the calibration turn starts, simulated s since the head's start (the chip is up).
pub const MAG_TURN_START_S: f64 = 1.0;
/// Simulated seconds at rest between the calibration turn and the daemon's start.
const AFTER_MAG_TURN_S: f64 = 1.0;
/// Most readings a calibration keeps (as the command line).
const MAX_CALIBRATION_SAMPLES: usize = 600_000;

/// The operator's slow turn in place for `scan3d-edge calibrate mag`, before the pass: one
/// full turn about the trolley's vertical ([`TurnInPlace`]), read for its whole length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibrationTurn {
    /// When it starts, simulated s since the head's start.
    pub start_s: f64,
    /// How long the turn takes, simulated s (its mean rate is 360° over this).
    pub duration_s: f64,
}

impl CalibrationTurn {
    /// A turn of `duration_s` from [`MAG_TURN_START_S`].
    pub fn lasting(duration_s: f64) -> Self {
        Self {
            start_s: MAG_TURN_START_S,
            duration_s,
        }
    }

    /// When it ends, simulated s.
    pub fn end_s(&self) -> f64 {
        self.start_s + self.duration_s
    }
}

/// What the demo's `scan3d-edge calibrate mag` found, beside the emulator's true iron.
#[derive(Debug, Clone, PartialEq)]
pub struct MagCalibrationRun {
    /// The turn read.
    pub turn: CalibrationTurn,
    /// The fit (a horizontal ellipse: the trolley turns about its vertical only).
    pub fit: MagCalibration,
    /// The `[imu]` values the edge runs with.
    pub settings: MagSettings,
    /// Gyro readings taken during the turn (the fields are `fit.samples`).
    pub readings: usize,
    /// The emulator's hard iron b, µT.
    pub true_hard_iron_ut: [f64; 3],
    /// What a turn about z can see of it: b_x, b_y with the soft iron's xz, yz terms times the
    /// vertical field absorbed ([`calibrate`]'s module docs), and b_z.
    pub observable_hard_iron_ut: [f64; 3],
    /// The largest error of the fitted soft iron's xy block against the inverse of the
    /// emulator's.
    pub soft_iron_xy_error: f64,
}

impl MagCalibrationRun {
    /// |fitted − true| hard iron, µT.
    pub fn hard_iron_error_ut(&self) -> f64 {
        distance(self.settings.hard_iron_ut, self.true_hard_iron_ut)
    }

    /// |fitted − observable| hard iron in x, y (the heading's), µT.
    pub fn horizontal_error_ut(&self) -> f64 {
        let [x, y, _] = self.settings.hard_iron_ut;
        let [ox, oy, _] = self.observable_hard_iron_ut;
        distance([x, y, 0.0], [ox, oy, 0.0])
    }

    /// One line: the fitted hard-iron offset and its error against the emulator's true iron.
    pub fn summary(&self) -> String {
        let [x, y, z] = self.settings.hard_iron_ut;
        let [tx, ty, tz] = self.true_hard_iron_ut;
        format!(
            "magnetometer calibrated by scan3d-edge calibrate mag's code over a {:.0} s turn in \
             place ({} fields, {}° covered, residual {:.2} %): hard iron ({x:.2}, {y:.2}, {z:.2}) \
             µT vs the emulator's true ({tx:.2}, {ty:.2}, {tz:.2}): |error| {:.2} µT; x, y {:.2} \
             µT off what a turn about z can see, z {:+.2} µT (from the site's vertical field); \
             soft iron xy max error {:.4}",
            self.turn.duration_s,
            self.fit.samples,
            self.fit.covered.0 * 10,
            self.fit.residual_rms * 100.0,
            self.hard_iron_error_ut(),
            self.horizontal_error_ut(),
            z - tz,
            self.soft_iron_xy_error
        )
    }
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The rig's trolley for the in-process edge: the lidars on ptys and the IMU on an I2C bus
/// handed to the edge directly, all on one time-scaled clock (the rig's are at ×1).
pub struct TrolleyHead {
    clock: ScaledClock,
    path: Arc<TrolleyPath>,
    base: Arc<BumpyTrolley>,
    rplidar: PtyHandle,
    sweep: PtyHandle,
    bus: I2cBus,
    imu: Arc<ErroneousImu>,
}

impl TrolleyHead {
    /// Starts the trolley on `path` in `world` at `time_scale`, links in `links_dir`, with the
    /// IMU's default errors ([`ImuErrors::beside_path`]: drifting gyro bias, hard and soft
    /// iron, the cabinet beside the path, floor bumps that tilt the trolley), turning once in
    /// place during `turn` (which must end before the path's rest does). A path closer than
    /// [`TROLLEY_CLEARANCE_M`] to the room is refused.
    pub fn start(
        links_dir: &Path,
        world: Arc<World>,
        path: Arc<TrolleyPath>,
        turn: Option<CalibrationTurn>,
        time_scale: f64,
        seed: u64,
    ) -> anyhow::Result<Self> {
        if let Some(turn) = turn {
            anyhow::ensure!(
                turn.start_s >= 0.0 && turn.duration_s > 0.0 && turn.end_s() < path.rest_s(),
                "the calibration turn ({:.1}–{:.1} s) must lie within the path's rest (0–{:.1} s)",
                turn.start_s,
                turn.end_s(),
                path.rest_s()
            );
        }
        let clearance = path.clearance(&world);
        anyhow::ensure!(
            clearance.distance_m >= TROLLEY_CLEARANCE_M,
            "the trolley's path passes {:.2} m from {}: it needs {TROLLEY_CLEARANCE_M} m",
            clearance.distance_m,
            clearance.what
        );
        std::fs::create_dir_all(links_dir)
            .with_context(|| format!("cannot create {}", links_dir.display()))?;
        let errors = ImuErrors::beside_path(&path);
        let base = Arc::new(BumpyTrolley::new(path.clone(), &errors.floor_bumps));
        let clock = ScaledClock::new(time_scale);
        let mut dyn_base: Arc<dyn BaseTrajectory> = base.clone();
        if let Some(turn) = turn {
            dyn_base = Arc::new(TurnInPlace {
                base: dyn_base,
                start_s: turn.start_s,
                duration_s: turn.duration_s,
                angle_rad: std::f64::consts::TAU,
            });
        }
        let truth = MountedImuTruth {
            base: dyn_base.clone(),
            mount: mount_pose(IMU_MOUNT),
            field: EarthField::default(),
            north_heading_rad: ROOM_MAGNETIC_NORTH_DEG.to_radians(),
        };
        let imu = Arc::new(ErroneousImu::new(truth, errors));
        let imu_truth: Arc<dyn ImuTruth> = imu.clone();
        let (bus, _hat, _turntable) = head_bus(Arc::new(clock), imu_truth);
        let pty = |seed: u64| PtyOptions {
            time_scale,
            faults: FaultConfig::default(),
            seed,
            epoch: Some(clock.epoch()),
        };
        let on_base = |mount: [f64; 6]| OnBase {
            base: dyn_base.clone(),
            mount: mount_pose(mount),
        };
        let rplidar = RplidarEmulator::new(
            RplidarEmulatorConfig::default(),
            RplidarEmulator::default_scanner(world.clone(), Isometry3::identity()),
            seed,
        )
        .with_pose_source(on_base(TROLLEY_RPLIDAR_MOUNT));
        let rplidar = PtyDevice::spawn(links_dir.join("rplidar"), Box::new(rplidar), pty(seed))
            .context("cannot start the trolley's RPLidar")?;
        let sweep = SweepEmulator::new(
            SweepEmulatorConfig::default(),
            SweepEmulator::default_scanner(world, crate::mounts::sweep()),
            seed.wrapping_add(1),
        )
        .with_pose_source(on_base(TROLLEY_SWEEP_MOUNT));
        let sweep = PtyDevice::spawn(
            links_dir.join("sweep"),
            Box::new(sweep),
            pty(seed.wrapping_add(101)),
        )
        .context("cannot start the trolley's Sweep")?;
        Ok(Self {
            clock,
            path,
            base,
            rplidar,
            sweep,
            bus,
            imu,
        })
    }

    /// The clock of the emulators, to be the edge's too (edge time = path time).
    pub fn clock(&self) -> ScaledClock {
        self.clock
    }

    /// The path the trolley follows.
    pub fn path(&self) -> &Arc<TrolleyPath> {
        &self.path
    }

    /// The edge's handle on the I2C bus (the erroneous IMU).
    pub fn bus(&self) -> I2cBus {
        self.bus.clone()
    }

    /// The IMU's errors as emulated.
    pub fn imu(&self) -> &ErroneousImu {
        &self.imu
    }

    /// The true pose of `base` in `room` at edge time `t_ns` (floor bumps included).
    pub fn base_pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        self.base.motion_at(t_ns).pose
    }

    /// Calibrates the magnetometer as `scan3d-edge calibrate mag --field-ut F
    /// --inclination-deg I` does (the site's field from a model: the emulator's Earth field),
    /// reading through the edge's driver with `config`'s `[imu]` for the whole of `turn`: waits
    /// for the turn's start, reads on the head's clock, fits. Refused as the command refuses
    /// (too little of the circle, a tilted turn, too few fields).
    pub fn calibrate_mag(
        &self,
        config: &EdgeConfig,
        turn: CalibrationTurn,
    ) -> anyhow::Result<MagCalibrationRun> {
        let imu = config
            .imu
            .as_ref()
            .context("the trolley's edge.toml has no [imu]")?;
        let start_ns = (turn.start_s * 1e9) as u64;
        let now_ns = self.clock.now_ns();
        if start_ns > now_ns {
            std::thread::sleep(self.clock.real_duration(start_ns - now_ns));
        }
        let shared: SharedClock = Arc::new(self.clock);
        let collected = calibrate::collect_on_clock(
            self.bus(),
            &mut ClockDelay(shared),
            &imu.driver,
            &self.clock,
            (turn.duration_s * 1e9) as u64,
            MAX_CALIBRATION_SAMPLES,
            |_| {},
        )
        .context("scan3d-edge calibrate mag: reading the IMU")?;
        let field = EarthField::default();
        let local = LocalField {
            total_ut: Some(field.total_ut),
            inclination_deg: Some(field.inclination_deg),
        };
        let fit = calibrate::fit_mag(&collected.fields, local)
            .context("scan3d-edge calibrate mag over the demo's turn")?;
        let settings = MagSettings::from_fit(
            &fit,
            &collected.fields,
            f64::from(imu.driver.mag_hard_iron_ut[2]),
        );
        let errors = self.imu.errors();
        let a = nalgebra::Matrix3::from_fn(|r, c| errors.soft_iron[r][c]);
        let b = errors.hard_iron_ut;
        let vertical_ut = field.in_level_body(0.0)[2];
        let observable_hard_iron_ut = [
            b[0] + a[(0, 2)] * vertical_ut,
            b[1] + a[(1, 2)] * vertical_ut,
            b[2],
        ];
        let soft_xy = a.fixed_view::<2, 2>(0, 0).into_owned().try_inverse();
        let soft_iron_xy_error = soft_xy.map_or(f64::NAN, |want| {
            let got = nalgebra::Matrix2::from_fn(|r, c| settings.soft_iron[r][c]);
            (got - want).abs().max()
        });
        Ok(MagCalibrationRun {
            turn,
            fit,
            settings,
            readings: collected.rates.len(),
            true_hard_iron_ut: b,
            observable_hard_iron_ut,
            soft_iron_xy_error,
        })
    }

    /// The edge's configuration for this trolley: the rig's trolley `edge.toml`
    /// ([`trolley_edge_toml_text`]: the mounts, no stepper) with these links, the I2C bus
    /// handed over in-process, and `mag` (what [`TrolleyHead::calibrate_mag`] found) as its
    /// magnetometer's calibration, when given.
    pub fn edge_config(
        &self,
        state_dir: &Path,
        uplink: Option<UplinkSection>,
        mag: Option<&MagSettings>,
    ) -> anyhow::Result<EdgeConfig> {
        let text = format!(
            "device_name = {EDGE_NAME:?}\nstate_dir = {:?}\n{}",
            state_dir.display().to_string(),
            trolley_edge_toml_text(
                self.rplidar.link(),
                self.sweep.link(),
                Path::new("in-process")
            )
        );
        let mut config = EdgeConfig::from_toml_str(&text, Path::new("edge.toml"))
            .context("the trolley's edge.toml")?;
        config.i2c = Default::default();
        config.uplink = uplink;
        // What `scan3d-edge calibrate mag --write edge.toml` put there. Uncalibrated, the
        // trolley's hard and soft iron turn Madgwick's yaw by tens of degrees.
        if let (Some(imu), Some(mag)) = (config.imu.as_mut(), mag) {
            mag.apply(&mut imu.driver);
        }
        Ok(config)
    }

    /// Stops the emulators and removes their links.
    pub fn shutdown(self) {
        self.rplidar.shutdown();
        self.sweep.shutdown();
    }
}

/// Where and how the pass is made.
#[derive(Debug, Clone)]
pub struct PassSetup<'a> {
    /// The simulated room.
    pub world: &'a Arc<World>,
    /// Its true surface, for scoring.
    pub truth: &'a GroundTruth,
    /// The trolley's path ([`TrolleyPath::demo_room`] in the demo).
    pub path: Arc<TrolleyPath>,
    /// Scratch space (certificates, links, edge state).
    pub work: &'a Path,
    /// The server's data directory: the pass's recording goes below it.
    pub data_dir: &'a Path,
    /// The demo's output directory: `clouds/`, `maps/`, `trajectories/`, `truth/` below it.
    pub out: &'a Path,
    /// The live snapshot goes to `snapshots_dir/map1/`.
    pub snapshots_dir: &'a Path,
    /// Simulated seconds per real second.
    pub time_scale: f64,
    /// World noise seed.
    pub seed: u64,
    /// Octree resolution, metres.
    pub resolution_m: f64,
    /// The live pipeline's queue per session.
    pub queue_frames: usize,
    /// Simulated seconds of the magnetometer's calibration turn before the pass (the path's
    /// rest is lengthened by it, [`CalibrationTurn`]).
    pub mag_turn_s: f64,
}

/// Which products map1 is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapSource {
    /// The live server's snapshot of the pass (`passes/map1/cloud.ply`, `map.bt`).
    Live,
    /// The recorded session assembled offline along the pose stage's trajectory.
    Offline,
}

impl std::fmt::Display for MapSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            MapSource::Live => "the live server's snapshot of the pass (passes/map1/)",
            MapSource::Offline => {
                "the recorded pass assembled offline (as scan3d assemble --moving --pass map1)"
            }
        })
    }
}

/// What the pass produced.
#[derive(Debug, Clone)]
pub struct PassResult {
    /// The path the trolley followed (the setup's, its rest lengthened by the calibration
    /// turn).
    pub path: Arc<TrolleyPath>,
    /// The magnetometer's calibration the edge ran with.
    pub mag_calibration: MagCalibrationRun,
    /// The recorded session.
    pub session_dir: PathBuf,
    /// The pass's span, edge ns (its start and stop markers).
    pub span_ns: (u64, u64),
    /// Which products map1 is.
    pub source: MapSource,
    /// map1's cloud (Table II: pass-through box only), with per-bundle origins.
    pub cloud: Vec<RayBundle>,
    /// The offline assembly's counts of the pass.
    pub totals: PassStatus,
    /// map1's points against the true surface.
    pub accuracy: Option<Accuracy>,
    /// The offline assembly's points against the true surface (map1's when offline).
    pub offline_accuracy: Option<Accuracy>,
    /// The live snapshot's points against the true surface, when it made them.
    pub live_accuracy: Option<Accuracy>,
    /// The pose stage's (scan matcher's) trajectory of `base` against the truth.
    pub matcher_error: Option<TrajectoryError>,
    /// The CI-fused trajectory against the truth (`None` when the fusion gave none).
    pub fused_error: Option<TrajectoryError>,
    /// Why there is no fused trajectory, when there is none.
    pub fusion_failure: Option<String>,
    /// The yaw RMSE of each source (gyro alone, Madgwick, matcher, CI fusion) against the
    /// truth, as Fig. 5 draws them.
    pub yaw_rmse: Vec<SourceRmse>,
    /// `report/fig5.svg|png` when written.
    pub fig5: Vec<PathBuf>,
    /// Files written: `clouds/map1.ply|.scans`, `maps/map1.bt`, `trajectories/map1.tum`,
    /// `truth/trolley.tum`.
    pub files: Vec<PathBuf>,
    /// `maps/map1.bt`.
    pub octree: PathBuf,
    /// `trajectories/map1.tum`.
    pub trajectory_file: PathBuf,
    /// `truth/trolley.tum`.
    pub truth_file: PathBuf,
    /// Where the live daemon's snapshot of the session went.
    pub snapshot_dir: PathBuf,
    /// The session's line of `scan3d status` before the snapshot.
    pub live_status: serde_json::Value,
    /// Edge frames of the IMU the server recorded during the pass's session.
    pub imu_frames: u64,
    /// Real seconds the pass took, from the server's start to the written files.
    pub wall_s: f64,
}

impl PassResult {
    /// Number of points in map1's cloud.
    pub fn points(&self) -> usize {
        self.cloud.iter().map(|b| b.points.len()).sum()
    }
}

/// The live server's `[pipeline]` for map1: Table II's filter for point cloud 1 (the
/// pass-through box only, no down-sampling, no Gaussian), octrees at `resolution_m`.
pub fn map1_pipeline(resolution_m: f64) -> PipelineSettings {
    PipelineSettings {
        resolution_m,
        max_range_m: None,
        revolution_filters: vec![map1_filter()],
        snapshot_filters: Vec::new(),
        ..PipelineSettings::default()
    }
}

/// Table II's filter for point cloud 1: the pass-through box.
pub fn map1_filter() -> Filter {
    Filter::Box {
        min: PASS_THROUGH_BOX.min,
        max: PASS_THROUGH_BOX.max,
    }
}

/// Runs the trolley pass through the whole system and writes map1's files (module docs).
pub fn run_pass(setup: &PassSetup<'_>) -> anyhow::Result<PassResult> {
    let started = Instant::now();
    let work = setup.work.join(PASS_NAME);
    let pki = work.join("pki");
    let bundle = installation::pair_certificates(&pki)?;
    let live = LiveSettings {
        queue_frames: setup.queue_frames,
        ..LiveSettings::new(
            map1_pipeline(setup.resolution_m),
            setup.data_dir.to_path_buf(),
        )
    };
    let mut server =
        ServerThread::start_live(installation::ingest_config(&pki, setup.data_dir, 0), live)?;
    let socket = socket_path(setup.data_dir);
    // The path waits for the operator's calibration turn, then rests as long as it said.
    let turn = CalibrationTurn::lasting(setup.mag_turn_s);
    let path = Arc::new(
        setup
            .path
            .with_rest_s(setup.path.rest_s() + turn.end_s() + AFTER_MAG_TURN_S),
    );
    let head = TrolleyHead::start(
        &work.join("links"),
        setup.world.clone(),
        path.clone(),
        Some(turn),
        setup.time_scale,
        setup.seed,
    )?;
    let clock = head.clock();
    let shared: SharedClock = Arc::new(clock);
    let state_dir = work.join("edge-state");
    let uplink = Some(installation::uplink_section(server.addr(), &bundle));
    // `scan3d-edge calibrate mag` with the daemon stopped, its keys written to edge.toml, then
    // the daemon started with them.
    let uncalibrated = head.edge_config(&state_dir, uplink.clone(), None)?;
    let mag_calibration = head.calibrate_mag(&uncalibrated, turn)?;
    tracing::info!("{}", mag_calibration.summary());
    let config = head.edge_config(&state_dir, uplink, Some(&mag_calibration.settings))?;
    let session_id = rand::random::<u64>();
    let edge = EdgeThread::start_with_i2c(config, shared, session_id, Some(head.bus()))?;
    let now_s = || clock.now_ns() as f64 * 1e-9;
    let mut imu_frames = 0u64;

    // Both lidars streaming while the trolley still rests at its start.
    let (mut rplidar, mut sweep) = (false, false);
    let ready_by =
        Instant::now() + Duration::from_secs_f64(path.rest_s() / setup.time_scale + 30.0);
    wait_for(&mut server, ready_by, &mut imu_frames, |body| {
        if let Body::Revolution(rev) = body {
            rplidar |= rev.sensor == SensorId::RPLIDAR;
            sweep |= rev.sensor == SensorId::SWEEP;
        }
        rplidar && sweep
    })
    .context("the trolley's lidars never streamed")?;
    anyhow::ensure!(
        now_s() < path.rest_s(),
        "the lidars streamed only at {:.1} s, after the trolley set off at {:.1} s: a longer \
         rest_s (or a smaller --time-scale) is needed",
        now_s(),
        path.rest_s()
    );
    // What the operator types: `scan3d trolley start --edge sim-edge --at X,Y,HEADING --name map1`.
    let [x_m, y_m, heading_deg] = path.start_pose();
    let start = pass_command(
        &socket,
        Command::StartPass {
            name: Some(PASS_NAME.into()),
            x_m,
            y_m,
            heading_deg,
        },
    )
    .context("scan3d trolley start")?;
    // The trolley is pushed along its path, then rests at its end.
    let end_s = path.end_of_path_s() + REST_AT_END_S;
    let moving_by =
        Instant::now() + Duration::from_secs_f64((end_s - now_s()) / setup.time_scale + 60.0);
    while now_s() < end_s {
        anyhow::ensure!(Instant::now() < moving_by, "the pass never reached its end");
        drain(&mut server, &mut imu_frames);
        std::thread::sleep(Duration::from_millis(20));
    }
    let stop = pass_command(&socket, Command::StopPass).context("scan3d trolley stop")?;
    let span_ns = (start, stop);
    edge.stop()?;
    drain(&mut server, &mut imu_frames);
    let session_hex = format!("{session_id:016x}");
    let status = request_products(&socket, &ProductRequest::Status)?;
    anyhow::ensure!(status.ok, "scan3d status: {}", status.detail);
    let live_status = session_status(status.data.as_ref(), &session_hex)
        .with_context(|| format!("scan3d status has no line for session {session_hex}"))?;
    let snapshot_dir = setup.snapshots_dir.join(PASS_NAME);
    request_snapshot(&socket, EDGE_NAME, Some(&session_hex), None, &snapshot_dir)
        .context("scan3d snapshot of the pass")?;
    server.stop();
    let truth_poses = truth_lines(&head, span_ns);
    let base = head.base.clone();
    let base_poses = move |t_ns: u64| base.motion_at(t_ns).pose;
    head.shutdown();

    let session = session_dir(setup.data_dir, EDGE_NAME, session_id);
    // The CI yaw fusion of the recorded session (the pose lane's fusion stage, offline): the
    // trajectory written as map1's, when it gives one; the matcher's is the same run's yaw.
    let (fused, fusion_failure) = match fuse_session(&session) {
        Ok(run) if !run.trajectory.is_empty() => (Some(run), None),
        Ok(_) => (None, Some("the fusion gave no pose".to_string())),
        Err(e) => (None, Some(format!("{e:#}"))),
    };
    let matcher = match &fused {
        Some(run) => matcher_trajectory(run),
        None => {
            tracing::warn!(
                "no fused trajectory, map1's is the matcher's: {}",
                fusion_failure.as_deref().unwrap_or_default()
            );
            let tracked = session_trajectory(&session, false)?;
            anyhow::ensure!(
                tracked.anchored,
                "{}: the pass start did not anchor the trajectory in the room",
                session.display()
            );
            tracked.trajectory
        }
    };
    let placing = fused
        .as_ref()
        .map_or_else(|| matcher.clone(), fused_trajectory);
    let live_dir = snapshot_dir.join("passes").join(PASS_NAME);
    let (live_cloud, live_map) = (live_dir.join("cloud.ply"), live_dir.join("map.bt"));
    let score = |cloud: &[RayBundle]| {
        setup.truth.accuracy(
            cloud
                .iter()
                .flat_map(|b| b.points.iter().map(|p| p.map(f64::from))),
        )
    };
    // The offline assembly always, so that both are measured when the live one exists: the
    // server's own (`scan3d assemble --moving SESSION --pass map1`, the live pipeline's stages).
    let offline = assemble_moving_sessions(
        std::slice::from_ref(&session),
        &map1_pipeline(setup.resolution_m),
        Some(PASS_NAME),
        false,
        true,
    )
    .context("scan3d assemble --moving of the pass")?;
    let totals = offline
        .sessions
        .first()
        .and_then(|s| s.placed.clone())
        .context("the offline assembly placed nothing of the pass")?;
    let offline_cloud = offline.cloud;
    let offline_tree = offline.octree;
    let offline_accuracy = score(&offline_cloud);
    let (source, cloud, live_accuracy) = if live_cloud.is_file() && live_map.is_file() {
        let cloud = io::load(&live_cloud, None)?;
        let accuracy = score(&cloud);
        (MapSource::Live, cloud, accuracy)
    } else {
        (MapSource::Offline, offline_cloud, None)
    };
    let accuracy = match source {
        MapSource::Live => live_accuracy,
        MapSource::Offline => offline_accuracy,
    };

    // Files.
    let mut files = Vec::new();
    for dir in ["clouds", "maps", "trajectories", "truth"] {
        let dir = setup.out.join(dir);
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
    }
    for ext in ["ply", "scans"] {
        let path = setup.out.join("clouds").join(format!("{PASS_NAME}.{ext}"));
        io::save(&path, &cloud)?;
        files.push(path);
    }
    let octree = setup.out.join("maps").join(format!("{PASS_NAME}.bt"));
    match source {
        MapSource::Live => {
            std::fs::copy(&live_map, &octree).with_context(|| {
                format!("cannot copy {} to {}", live_map.display(), octree.display())
            })?;
        }
        MapSource::Offline => {
            let tree = offline_tree.context("the offline assembly made no octree")?;
            std::fs::write(&octree, tree.to_bt_bytes())
                .with_context(|| format!("cannot write {}", octree.display()))?;
        }
    }
    files.push(octree.clone());
    let matcher_tum = trajectory_tum(&matcher, span_ns);
    let estimate = trajectory_tum(&placing, span_ns);
    let trajectory_file = setup
        .out
        .join("trajectories")
        .join(format!("{PASS_NAME}.tum"));
    std::fs::write(&trajectory_file, &estimate)
        .with_context(|| format!("cannot write {}", trajectory_file.display()))?;
    files.push(trajectory_file.clone());
    let truth_file = setup.out.join("truth").join("trolley.tum");
    std::fs::write(&truth_file, &truth_poses)
        .with_context(|| format!("cannot write {}", truth_file.display()))?;
    files.push(truth_file.clone());
    let matcher_error = tum_error(&matcher_tum, &truth_poses)?;
    let fused_error = match fused {
        Some(_) => tum_error(&estimate, &truth_poses)?,
        None => None,
    };
    let (mut yaw_rmse, mut fig5) = (Vec::new(), Vec::new());
    if let Some(run) = &fused {
        let run = on_edge_clock(run);
        let truth_yaw = truth_yaw_at_poses(&run, span_ns, |t_ns| yaw_of(&base_poses(t_ns)));
        yaw_rmse = rmse(&yaw_errors(&run, &truth_yaw), 0.0);
        match write_fig5(&run, &truth_yaw, &setup.out.join("report")) {
            Ok(written) => fig5 = written,
            Err(e) => tracing::warn!("no Fig. 5: {e:#}"),
        }
    }
    Ok(PassResult {
        path,
        mag_calibration,
        session_dir: session,
        span_ns,
        source,
        cloud,
        totals,
        accuracy,
        offline_accuracy,
        live_accuracy,
        matcher_error,
        fused_error,
        fusion_failure,
        yaw_rmse,
        fig5,
        files,
        octree,
        trajectory_file,
        truth_file,
        snapshot_dir,
        live_status,
        imu_frames,
        wall_s: started.elapsed().as_secs_f64(),
    })
}

/// The fused run's trajectory as the assembler's (x, y, fused yaw; roll and pitch from the
/// IMU's attitude), edge ns; a pose not after the one before is skipped.
pub fn fused_trajectory(run: &FusedRun) -> PlanarTrajectory {
    let mut trajectory = PlanarTrajectory::new();
    for p in &run.trajectory {
        let _ = trajectory.push(TrajectoryPoint {
            t_ns: p.t_ns,
            x_m: p.x,
            y_m: p.y,
            yaw_rad: p.yaw,
            roll_rad: p.roll,
            pitch_rad: p.pitch,
        });
    }
    trajectory
}

/// The fused run's trajectory with the matcher's yaw instead of the fused one (x and y are the
/// matcher's in both): the scan matcher alone, from the same run of the pose stage (the fused
/// yaw where the run has no source row at a pose's time).
pub fn matcher_trajectory(run: &FusedRun) -> PlanarTrajectory {
    let yaw: std::collections::HashMap<u64, f64> = run
        .sources
        .iter()
        .map(|s| (s.yaws.t_ns, s.yaws.matcher))
        .collect();
    let mut trajectory = PlanarTrajectory::new();
    for p in &run.trajectory {
        let _ = trajectory.push(TrajectoryPoint {
            t_ns: p.t_ns,
            x_m: p.x,
            y_m: p.y,
            yaw_rad: yaw.get(&p.t_ns).copied().unwrap_or(p.yaw),
            roll_rad: 0.0,
            pitch_rad: 0.0,
        });
    }
    trajectory
}

/// The yaw about z (ZYX) of a pose, rad.
fn yaw_of(pose: &Isometry3<f64>) -> f64 {
    pose.rotation.euler_angles().2
}

/// The run with every time in edge-clock seconds: the server's time sync cannot map an edge
/// clock running ×10 (its `t_s` would jump between models), and the truth is on the edge's.
pub fn on_edge_clock(run: &FusedRun) -> FusedRun {
    let mut run = run.clone();
    for s in &mut run.sources {
        s.t_s = s.yaws.t_ns as f64 * 1e-9;
    }
    for p in &mut run.trajectory {
        p.t_s = p.t_ns as f64 * 1e-9;
    }
    run.on_server_clock = false;
    run
}

/// The true yaw at each of the run's poses within `span_ns` as (ns on the run's `t_s` clock,
/// rad), time increasing: Fig. 5's truth.
fn truth_yaw_at_poses(
    run: &FusedRun,
    span_ns: (u64, u64),
    yaw_at: impl Fn(u64) -> f64,
) -> Vec<(u64, f64)> {
    let mut truth: Vec<(u64, f64)> = Vec::new();
    for s in &run.sources {
        if s.yaws.t_ns < span_ns.0 || s.yaws.t_ns > span_ns.1 {
            continue;
        }
        let t = (s.t_s * 1e9).round().max(0.0) as u64;
        if truth.last().is_none_or(|last| t > last.0) {
            truth.push((t, yaw_at(s.yaws.t_ns)));
        }
    }
    truth
}

/// The absolute trajectory error of TUM text `estimate` against TUM text `truth` (same clock,
/// same frame, no alignment: [`trajectory_error`]).
pub fn tum_error(estimate: &[u8], truth: &[u8]) -> anyhow::Result<Option<TrajectoryError>> {
    let estimate = read_tum(estimate).map_err(|e| anyhow::anyhow!("estimate: {e}"))?;
    let truth = read_tum(truth).map_err(|e| anyhow::anyhow!("truth: {e}"))?;
    Ok(trajectory_error(&estimate, &truth, None, None))
}

/// `trajectory`'s poses within `span_ns` as TUM text, t in edge-clock seconds (a comment says
/// so), z 0 and the yaw as a rotation about z (the pose stage's own `trajectory.tum` lines).
pub fn trajectory_tum(trajectory: &PlanarTrajectory, span_ns: (u64, u64)) -> Vec<u8> {
    let mut text = String::from("# t: edge clock seconds; pose of base in the room frame\n");
    for p in trajectory.points() {
        if p.t_ns < span_ns.0 || p.t_ns > span_ns.1 {
            continue;
        }
        let (qz, qw) = ((p.yaw_rad / 2.0).sin(), (p.yaw_rad / 2.0).cos());
        text.push_str(&format!(
            "{:.9} {:.6} {:.6} 0 0 0 {qz:.9} {qw:.9}\n",
            p.t_ns as f64 * 1e-9,
            p.x_m,
            p.y_m
        ));
    }
    text.into_bytes()
}

/// The true pose of `base` at [`TRUTH_HZ`] over `span_ns` as TUM text, t in edge-clock
/// seconds (the head's clock is the edge's).
fn truth_lines(head: &TrolleyHead, span_ns: (u64, u64)) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(b"# t: edge clock seconds; true pose of base in the room frame\n");
    let mut writer = TumWriter::new(&mut out);
    let step_ns = (1e9 / TRUTH_HZ) as u64;
    let mut t_ns = span_ns.0;
    while t_ns <= span_ns.1 {
        // Writing to a Vec cannot fail.
        let _ = writer.pose(t_ns as f64 * 1e-9, &head.base_pose_at(t_ns));
        t_ns += step_ns;
    }
    out
}

/// Sends a pass command as `scan3d trolley start|stop` does; returns the edge time of the
/// marker the edge answered with.
fn pass_command(socket: &Path, command: Command) -> anyhow::Result<u64> {
    let request = CommandRequest {
        edge: EDGE_NAME.into(),
        command,
        follow: false,
        reply_timeout_s: Some(30.0),
    };
    let status = request_command(socket, &request, &mut |_| {})?;
    anyhow::ensure!(status.ok, "{}", status.detail);
    let marker = status
        .pass
        .with_context(|| format!("the edge answered without a pass marker: {}", status.detail))?;
    Ok(marker.t_ns)
}

/// Waits until the server records a frame whose body satisfies `done`, counting IMU frames.
fn wait_for(
    server: &mut ServerThread,
    deadline: Instant,
    imu_frames: &mut u64,
    mut done: impl FnMut(&Body) -> bool,
) -> anyhow::Result<()> {
    loop {
        while let Ok(event) = server.events.try_recv() {
            let IngestEvent::Frame { frame, .. } = event else {
                continue;
            };
            if matches!(frame.body, Body::Imu(_)) {
                *imu_frames += 1;
            }
            if done(&frame.body) {
                return Ok(());
            }
        }
        anyhow::ensure!(Instant::now() < deadline, "timed out");
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn drain(server: &mut ServerThread, imu_frames: &mut u64) {
    while let Ok(event) = server.events.try_recv() {
        if let IngestEvent::Frame { frame, .. } = event
            && matches!(frame.body, Body::Imu(_))
        {
            *imu_frames += 1;
        }
    }
}
