//! A whole simulated installation, for the demo and the end-to-end tests: both lidars on ptys,
//! certificates paired in a directory, the server's ingest endpoint and the edge daemon — the
//! same code that runs on the laptop and the Pi, wired over real ptys and real QUIC.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context;
use scan3d_edge::clock::{ClockDelay, SharedClock};
use scan3d_edge::config::{EdgeConfig, RplidarSection, SweepSection, UplinkSection};
use scan3d_edge::daemon::{self, DaemonReport, I2cHardware};
use scan3d_edge::drivers::rplidar::RplidarConfig;
use scan3d_edge::drivers::sweep::SweepConfig;
use scan3d_protocol::{Body, SensorId};
use scan3d_server::ingest::control::{ControlLimits, ControlSocket, EdgeControl, socket_path};
use scan3d_server::ingest::pki::{self, PairRequest};
use scan3d_server::ingest::server::{IngestConfig, IngestEvent, IngestServer, IngestStats};
use scan3d_server::pipeline::live::{LivePipelines, LiveSettings};
use scan3d_server::recording::read_session;
use tokio::sync::{mpsc, oneshot, watch};

use crate::faults::{FaultConfig, SentSample};
use crate::i2c::I2cBus;
use crate::mounts;
use crate::pty::{PtyDevice, PtyHandle, PtyOptions};
use crate::rplidar::{RplidarEmulator, RplidarEmulatorConfig};
use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
use crate::world::World;

/// The simulated edge's name (its certificate's CN).
pub const EDGE_NAME: &str = "sim-edge";

/// How the simulated lidars run.
#[derive(Debug, Clone)]
pub struct LidarOptions {
    /// Simulated seconds per real second.
    pub time_scale: f64,
    /// Per-byte corruption on both lines.
    pub corrupt: f64,
    /// Seed of the world noise and the faults.
    pub seed: u64,
    /// The Sweep's motor settle time (simulated ms).
    pub sweep_settle_ms: u64,
}

impl Default for LidarOptions {
    fn default() -> Self {
        Self {
            time_scale: 10.0,
            corrupt: 0.0,
            seed: 1,
            sweep_settle_ms: 6000,
        }
    }
}

/// An emulated RPLidar A1 (express) and Scanse Sweep on ptys in the default room.
pub struct SimLidars {
    /// The RPLidar's pty.
    pub rplidar: PtyHandle,
    /// The Sweep's pty.
    pub sweep: PtyHandle,
}

impl SimLidars {
    /// Starts both devices with their links in `links_dir`.
    pub fn start(links_dir: &Path, options: &LidarOptions) -> anyhow::Result<Self> {
        std::fs::create_dir_all(links_dir)
            .with_context(|| format!("cannot create {}", links_dir.display()))?;
        let world = Arc::new(World::conference_room());
        let pty = |seed_offset: u64| PtyOptions {
            time_scale: options.time_scale,
            faults: FaultConfig::corrupt(options.corrupt),
            seed: options.seed.wrapping_add(seed_offset),
            epoch: None,
        };
        let sweep = SweepEmulator::new(
            SweepEmulatorConfig {
                settle_ms: options.sweep_settle_ms,
                ..Default::default()
            },
            SweepEmulator::default_scanner(world.clone(), mounts::sweep()),
            options.seed.wrapping_add(1),
        );
        Ok(Self {
            rplidar: spawn_rplidar(links_dir, world.clone(), options)?,
            sweep: PtyDevice::spawn(links_dir.join("sweep"), Box::new(sweep), pty(101))
                .context("cannot start the emulated Sweep")?,
        })
    }

    /// An edge configuration reading these devices (and streaming if `uplink` is given).
    pub fn edge_config(&self, state_dir: &Path, uplink: Option<UplinkSection>) -> EdgeConfig {
        EdgeConfig {
            device_name: EDGE_NAME.into(),
            state_dir: state_dir.to_path_buf(),
            rplidar: Some(RplidarSection {
                path: self.rplidar.link().to_path_buf(),
                driver: RplidarConfig::default(),
                mount: None,
            }),
            sweep: Some(SweepSection {
                path: self.sweep.link().to_path_buf(),
                driver: SweepConfig::default(),
                mount: None,
            }),
            uplink,
            i2c: Default::default(),
            imu: None,
            stepper: None,
            static_scan: Default::default(),
        }
    }

    /// The pty of a lidar.
    pub fn pty(&self, sensor: SensorId) -> &PtyHandle {
        if sensor == SensorId::RPLIDAR {
            &self.rplidar
        } else {
            &self.sweep
        }
    }

    /// Everything a device put on the wire so far.
    pub fn sent(&self, sensor: SensorId) -> Vec<SentSample> {
        self.pty(sensor).sent_log().snapshot()
    }

    /// Stops both devices and removes their links.
    pub fn shutdown(self) {
        self.rplidar.shutdown();
        self.sweep.shutdown();
    }
}

/// An emulated RPLidar A1 (express) in `world` on a pty linked at `links_dir/rplidar`.
pub fn spawn_rplidar(
    links_dir: &Path,
    world: Arc<World>,
    options: &LidarOptions,
) -> anyhow::Result<PtyHandle> {
    let rplidar = RplidarEmulator::new(
        RplidarEmulatorConfig::default(),
        RplidarEmulator::default_scanner(world, mounts::rplidar()),
        options.seed,
    );
    let pty = PtyOptions {
        time_scale: options.time_scale,
        faults: FaultConfig::corrupt(options.corrupt),
        seed: options.seed.wrapping_add(100),
        epoch: None,
    };
    PtyDevice::spawn(links_dir.join("rplidar"), Box::new(rplidar), pty)
        .context("cannot start the emulated RPLidar")
}

/// Pairs a CA, a `localhost` server certificate and the [`EDGE_NAME`] bundle in `pki_dir`.
pub fn pair_certificates(pki_dir: &Path) -> anyhow::Result<PathBuf> {
    let outcome = pki::pair(&PairRequest {
        dir: pki_dir.to_path_buf(),
        edge: EDGE_NAME.into(),
        server_names: Vec::new(),
        force: true,
    })?;
    Ok(outcome.edge_dir)
}

/// The `[uplink]` section pointing the edge at `server` with the bundle in `bundle_dir`.
pub fn uplink_section(server: std::net::SocketAddr, bundle_dir: &Path) -> UplinkSection {
    UplinkSection {
        server: server.to_string(),
        server_name: Some("localhost".into()),
        pki_dir: bundle_dir.to_path_buf(),
        spool_memory_mb: 8,
        spool_disk_mb: 256,
    }
}

/// An ingest configuration on loopback port `port` (0 = any) recording under `data_dir`.
pub fn ingest_config(pki_dir: &Path, data_dir: &Path, port: u16) -> IngestConfig {
    IngestConfig {
        listen: std::net::SocketAddr::from(([127, 0, 0, 1], port)),
        pki_dir: pki_dir.to_path_buf(),
        data_dir: data_dir.to_path_buf(),
        commit_interval: Duration::from_millis(50),
        time_sync_interval: Duration::from_millis(500),
        max_connections: 8,
        limits: Default::default(),
    }
}

/// The ingest server on its own thread and runtime, as `scan3d serve` runs it.
pub struct ServerThread {
    addr: std::net::SocketAddr,
    control: EdgeControl,
    live: Option<LivePipelines>,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<JoinHandle<IngestStats>>,
    /// Everything the server reports (recorded frames, connections, time sync).
    pub events: mpsc::UnboundedReceiver<IngestEvent>,
}

impl ServerThread {
    /// Binds and starts serving, with the operator's control socket in the data directory
    /// (`data_dir/control.sock`, as `scan3d serve` has it); records only.
    pub fn start(config: IngestConfig) -> anyhow::Result<Self> {
        Self::start_with(config, None)
    }

    /// [`ServerThread::start`] with the live pipeline, as `scan3d serve` runs with `[pipeline]`:
    /// the control socket also answers `scan3d status` and `scan3d snapshot`.
    pub fn start_live(config: IngestConfig, live: LiveSettings) -> anyhow::Result<Self> {
        Self::start_with(config, Some(live))
    }

    fn start_with(config: IngestConfig, live: Option<LiveSettings>) -> anyhow::Result<Self> {
        std::fs::create_dir_all(&config.data_dir)?;
        let socket_file = socket_path(&config.data_dir);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        let live = live
            .map(LivePipelines::new)
            .transpose()
            .map_err(|e| anyhow::anyhow!("[pipeline]: {e}"))?;
        let mut server = runtime.block_on(async { IngestServer::bind(config) })?;
        let mut socket = runtime.block_on(ControlSocket::bind(
            socket_file.clone(),
            ControlLimits::default(),
        ))?;
        if let Some(live) = &live {
            server = server.with_sink(Arc::new(live.clone()));
            socket = socket.with_live(Arc::new(live.clone()));
        }
        let addr = server.local_addr()?;
        let control = server.control();
        let (events_tx, events) = mpsc::unbounded_channel();
        let (stop, stopped) = oneshot::channel::<()>();
        let socket_control = control.clone();
        let thread = std::thread::Builder::new()
            .name("ingest server".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let control = tokio::spawn(socket.serve(socket_control));
                    let stats = server
                        .run(Some(events_tx), async {
                            let _ = stopped.await;
                        })
                        .await;
                    control.abort();
                    let _ = std::fs::remove_file(&socket_file);
                    stats
                })
            })?;
        Ok(Self {
            addr,
            control,
            live,
            stop: Some(stop),
            thread: Some(thread),
            events,
        })
    }

    /// The live pipeline, when started with [`ServerThread::start_live`].
    pub fn live(&self) -> Option<&LivePipelines> {
        self.live.as_ref()
    }

    /// Where edges connect.
    pub fn addr(&self) -> std::net::SocketAddr {
        self.addr
    }

    /// Sends commands to connected edges, as `scan3d scan` does through the control socket.
    pub fn control(&self) -> &EdgeControl {
        &self.control
    }

    /// Shuts down cleanly (commits, closes recordings) and returns the server's counters.
    pub fn stop(mut self) -> IngestStats {
        self.shutdown()
    }

    fn shutdown(&mut self) -> IngestStats {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let stats = self
            .thread
            .take()
            .and_then(|t| t.join().ok())
            .unwrap_or_default();
        if let Some(live) = &self.live {
            live.shutdown();
        }
        stats
    }
}

impl Drop for ServerThread {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The edge daemon on its own thread and runtime, as `scan3d-edge` runs it.
pub struct EdgeThread {
    stop: watch::Sender<bool>,
    thread: Option<JoinHandle<anyhow::Result<DaemonReport>>>,
}

impl EdgeThread {
    /// Starts the daemon with `config` on `clock` (no I2C devices).
    pub fn start(config: EdgeConfig, clock: SharedClock, session_id: u64) -> anyhow::Result<Self> {
        Self::start_with_i2c::<I2cBus>(config, clock.clone(), session_id, None)
    }

    /// Starts the daemon with the emulated I2C bus (IMU, motor HAT) of `i2c`.
    pub fn start_with_i2c<I: embedded_hal::i2c::I2c + Send + 'static>(
        config: EdgeConfig,
        clock: SharedClock,
        session_id: u64,
        i2c: Option<I>,
    ) -> anyhow::Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        let (stop, stopped) = watch::channel(false);
        let hardware = i2c.map(|bus| I2cHardware {
            bus,
            delay: ClockDelay(clock.clone()),
        });
        let thread = std::thread::Builder::new()
            .name("edge daemon".into())
            .spawn(move || {
                runtime.block_on(daemon::run_with_i2c(
                    config, clock, session_id, stopped, hardware,
                ))
            })?;
        Ok(Self {
            stop,
            thread: Some(thread),
        })
    }

    /// Stops the daemon as SIGTERM would and returns its report.
    pub fn stop(mut self) -> anyhow::Result<DaemonReport> {
        let _ = self.stop.send(true);
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => anyhow::bail!("the edge daemon panicked"),
            None => anyhow::bail!("the edge daemon was already stopped"),
        }
    }
}

impl Drop for EdgeThread {
    fn drop(&mut self) {
        let _ = self.stop.send(true);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Exactly-once accounting of one lidar's samples from emulator to recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Delivery {
    /// The lidar.
    pub sensor: SensorId,
    /// Revolution frames in the recording.
    pub revolutions: u64,
    /// Samples in those frames.
    pub recorded_samples: u64,
    /// Samples the edge daemon handed to its uplink.
    pub edge_samples: u64,
    /// Samples the emulator sent between the first and the last recorded sample.
    pub sent_in_span: u64,
    /// Of those, samples that are not in the recording.
    pub missing_in_span: u64,
    /// Recorded samples that match nothing the emulator sent (must be 0).
    pub unexplained: u64,
    /// Bytes the emulator's pty dropped because the reader fell behind (a UART overrun): their
    /// samples were never sent, so they are not counted as missing.
    pub overrun_bytes: u64,
    /// Wire units those bytes made up. A dropped express capsule also makes the capsule before
    /// it undecodable (capsules decode in pairs), so each can cost up to one more unit.
    pub overrun_units: u64,
}

impl Delivery {
    /// Most samples an overrun can take beyond its own: one neighbouring express capsule
    /// (32 samples) per dropped unit. Zero on a line that never overran.
    pub fn overrun_allowance(&self) -> u64 {
        self.overrun_units * 32
    }

    /// Samples lost on the way from the emulator's wire to the recording that no overrun
    /// explains, plus any difference between what the edge sent and what was recorded: 0 on
    /// a correct system.
    pub fn lost(&self) -> u64 {
        self.missing_in_span
            .saturating_sub(self.overrun_allowance())
            + self.unexplained
            + self.edge_samples.abs_diff(self.recorded_samples)
    }
}

/// Compares a session recording with what the emulators sent and the edge submitted.
///
/// Every recorded sample must match, in order, one the emulator sent; everything the emulator
/// sent between the first and last recorded sample must be recorded (a clean line loses
/// nothing); and the recording must hold exactly the samples the edge submitted — one more
/// would be a duplicate, one less a loss.
pub fn account(
    session_dir: &Path,
    lidars: &SimLidars,
    daemon: Option<&DaemonReport>,
) -> anyhow::Result<Vec<Delivery>> {
    let frames = read_session(session_dir)?;
    let mut out = Vec::new();
    for sensor in [SensorId::RPLIDAR, SensorId::SWEEP] {
        let revolutions: Vec<_> = frames
            .iter()
            .filter_map(|f| match &f.frame.body {
                Body::Revolution(rev) if rev.sensor == sensor => Some(rev),
                _ => None,
            })
            .collect();
        let recorded: Vec<(f32, f32, u8)> = revolutions
            .iter()
            .flat_map(|r| {
                r.samples
                    .iter()
                    .map(|s| (s.angle_deg, s.range_m, s.quality))
            })
            .collect();
        let sent = lidars.sent(sensor);
        let mut delivery = Delivery {
            sensor,
            revolutions: revolutions.len() as u64,
            recorded_samples: recorded.len() as u64,
            edge_samples: daemon
                .and_then(|d| d.lidars.get(&sensor))
                .map_or(0, |l| l.samples),
            sent_in_span: 0,
            missing_in_span: 0,
            unexplained: 0,
            overrun_bytes: lidars.pty(sensor).stats().bytes_dropped_overrun,
            overrun_units: lidars.pty(sensor).stats().units_dropped_overrun,
        };
        let same = |r: &(f32, f32, u8), s: &SentSample| {
            (r.0 - s.sample.angle_deg).abs() < 0.05
                && (r.1 - s.sample.range_m).abs() < 0.0005
                && r.2 == s.sample.quality
        };
        let (matched, unexplained) = match_in_order(&recorded, &sent, same);
        delivery.unexplained = unexplained.len() as u64;
        for &i in unexplained.iter().take(3) {
            tracing::warn!(%sensor, sample = ?recorded[i], "recorded sample matches nothing sent");
        }
        if let (Some(&first), Some(&last)) = (matched.first(), matched.last()) {
            delivery.sent_in_span = (last - first + 1) as u64;
            delivery.missing_in_span = delivery.sent_in_span - matched.len() as u64;
        }
        out.push(delivery);
    }
    Ok(out)
}

/// Matches `decoded` samples, in order, to entries of a device's sent log.
///
/// Returns the log index of every matched sample and the indices (into `decoded`) of those that
/// match nothing. Each sample is looked for within [`MATCH_WINDOW`] entries after the previous
/// match; only the first sample, or one confirmed by the [`MATCH_CONFIRM`] samples after it, may
/// match farther ahead. Noisy ranges repeat by chance a revolution later, so an unbounded greedy
/// search would jump there on one unmatched sample and misalign everything after it.
pub fn match_in_order<R>(
    decoded: &[R],
    sent: &[SentSample],
    same: impl Fn(&R, &SentSample) -> bool,
) -> (Vec<usize>, Vec<usize>) {
    let mut matched = Vec::with_capacity(decoded.len());
    let mut unexplained = Vec::new();
    let mut cursor = 0;
    for (i, sample) in decoded.iter().enumerate() {
        let window_end = if matched.is_empty() {
            sent.len()
        } else {
            (cursor + MATCH_WINDOW).min(sent.len())
        };
        let near = sent[cursor..window_end]
            .iter()
            .position(|s| same(sample, s))
            .map(|o| cursor + o);
        let found = near.or_else(|| {
            // Farther ahead only with confirmation: the next samples must follow in order.
            (window_end..sent.len()).find(|&k| {
                same(sample, &sent[k])
                    && (1..=MATCH_CONFIRM).all(|d| match (decoded.get(i + d), sent.get(k + d)) {
                        (Some(next), Some(entry)) => same(next, entry),
                        (None, _) => true,
                        (Some(_), None) => false,
                    })
            })
        });
        match found {
            Some(k) => {
                matched.push(k);
                cursor = k + 1;
            }
            None => unexplained.push(i),
        }
    }
    (matched, unexplained)
}

/// How far after the previous match a sample is looked for without confirmation (well under
/// one revolution of either lidar).
pub const MATCH_WINDOW: usize = 64;
/// Consecutive samples that must confirm a match farther than [`MATCH_WINDOW`] ahead.
pub const MATCH_CONFIRM: usize = 3;
