//! The edge daemon (`scan3d-edge --config edge.toml`): every configured lidar is acquired on its
//! own thread, its revolutions become frames, and the uplink carries them to the server.
//!
//! ```text
//!  lidar thread ──Acquisition──> worker ──submit──> spool ──Uplink (QUIC)──> server
//!        (serial shell + driver)   (frames, status)        (acks remove frames)
//! ```
//!
//! When the spool is full (server unreachable for long) or cannot write to disk (disk full,
//! I/O errors), a worker stops its lidar, keeps the frames the spool refused, waits for room
//! (the uplink retries the disk with a backoff), then sends the kept frames first and reports
//! `AcquisitionPaused` / `AcquisitionResumed` status frames: nothing is dropped silently. SIGTERM stops the lidars (their STOP commands are sent), lets the uplink
//! drain for a few seconds and leaves the rest in the on-disk spool for the next start.
//!
//! With `[imu]` and `[stepper]`, the I2C bus (rppal on the Pi, any embedded-hal `I2c` in
//! [`run_with_i2c`]) is shared through `embedded-hal-bus` by the IMU thread (Madgwick-fused
//! `Imu` frames at the IMU rate) and the turntable thread. A `StartStaticScan` command from the
//! server makes the Sweep worker run a [`ScanSession`]: one step per revolution while the beam
//! is blocked, every sample decided on the time it has in its revolution frame, and the yaws
//! sent as `StaticScan::Yaws` frames that refer to the Sweep revolution frames by index.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, mpsc::RecvTimeoutError};
use std::thread::JoinHandle;
use std::time::Duration;

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::I2c;
use embedded_hal_bus::i2c::MutexDevice;
use scan3d_protocol::{
    Body, Command, CommandOutcome, CommandReply, DeviceStatus, Hello, LidarRevolution, SensorId,
    SensorInfo, StatusEvent,
};
use scan3d_service::daemon::{self, NotifyState};
use tokio::sync::watch;

use crate::acquisition::{Acquisition, AcquisitionEvent, AcquisitionSummary};
use crate::clock::{ClockDelay, SharedClock};
use crate::config::EdgeConfig;
use crate::drivers::rplidar::Rplidar;
use crate::drivers::sweep::Sweep;
use crate::i2c_socket::SocketI2c;
use crate::imu_worker::{ImuEvent, ImuReport, ImuWorker};
use crate::lidar::{LidarDriver, LidarEvent};
use crate::scan_session::{ScanAction, ScanPosition, ScanSession};
use crate::serial::SerialOptions;
use crate::static_scan::StaticScanConfig;
use crate::timing::{Revolution, TimingConfig};
use crate::trolley_pass::Passes;
use crate::turntable::{Turntable, TurntableJob, TurntableReport};
use crate::uplink::client::{
    ReceivedCommand, SubmitError, Uplink, UplinkConfig, UplinkHandle, UplinkStats,
};
use crate::uplink::tls;

/// What one lidar worker did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LidarReport {
    /// Revolutions handed to the uplink.
    pub revolutions: u64,
    /// Samples in those revolutions.
    pub samples: u64,
    /// Times acquisition paused because the spool was full or could not write to disk.
    pub pauses: u64,
    /// Driver and timing counters of the last acquisition run.
    pub acquisition: AcquisitionSummary,
}

/// What the daemon did, returned when it stops.
#[derive(Debug, Clone, Default)]
pub struct DaemonReport {
    /// Per lidar.
    pub lidars: BTreeMap<SensorId, LidarReport>,
    /// The uplink's counters, if one was configured.
    pub uplink: Option<UplinkStats>,
    /// This boot's session id.
    pub session_id: u64,
    /// The IMU thread's counters, if an IMU was configured.
    pub imu: Option<ImuReport>,
    /// Static scans started.
    pub static_scans: u32,
}

/// The I2C side of the edge: the bus the IMU and the motor HAT share, and the delay that paces
/// their drivers.
pub struct I2cHardware<I, D> {
    /// The bus (rppal's on the Pi; the hw-sim's emulated bus in simulation).
    pub bus: I,
    /// Delay for resets and step pacing (follows the daemon's clock).
    pub delay: D,
}

/// Everything a running daemon shares between its threads.
struct Context {
    clock: SharedClock,
    uplink: Option<UplinkHandle>,
    device_name: String,
    inventory: Mutex<BTreeMap<SensorId, SensorInfo>>,
    stop: AtomicBool,
    /// The configured mounts, sent once per session right after a `Hello` is queued.
    mounts: scan3d_protocol::SensorMounts,
    mounts_sent: AtomicBool,
}

impl Context {
    /// Sends a frame body. Without an uplink, frames are only logged.
    fn submit(&self, body: impl Into<Body>) -> Result<(), SubmitError> {
        match &self.uplink {
            Some(uplink) => uplink.submit(body).map(|_| ()),
            None => Ok(()),
        }
    }

    /// Sends a small, frequent frame (IMU readings) in the uplink's next batch
    /// ([`UplinkHandle::submit_deferred`]).
    fn submit_deferred(&self, body: impl Into<Body>) -> Result<(), SubmitError> {
        match &self.uplink {
            Some(uplink) => uplink.submit_deferred(body).map(|_| ()),
            None => Ok(()),
        }
    }

    fn has_room(&self) -> bool {
        self.uplink.as_ref().is_none_or(UplinkHandle::has_room)
    }

    /// Adds a sensor to the inventory and queues a new hello announcing it.
    fn inventory_insert(&self, info: SensorInfo) {
        self.inventory
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(info.sensor, info);
        self.submit_hello();
    }

    /// Queues a `Hello` and, the first time one is queued in this session, the mounts after
    /// it.
    fn submit_hello(&self) {
        if let Err(e) = self.submit(self.hello()) {
            tracing::warn!(error = %e, "hello not queued");
            return;
        }
        self.submit_mounts_once();
    }

    /// Queues the mounts unless they already were (a refused submit is retried after the
    /// next `Hello`).
    fn submit_mounts_once(&self) {
        if self.mounts_sent.load(Ordering::Acquire) {
            return;
        }
        match self.submit(self.mounts.clone()) {
            Ok(()) => self.mounts_sent.store(true, Ordering::Release),
            Err(e) => tracing::warn!(error = %e, "mounts not queued"),
        }
    }

    fn hello(&self) -> Hello {
        let sensors = self
            .inventory
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .cloned()
            .collect();
        Hello::new(self.device_name.clone(), env!("CARGO_PKG_VERSION"), sensors)
            .with_clock_id(self.clock.clock_id())
    }
}

/// Runs the daemon until `shutdown` turns true. Must be called inside a multi-threaded tokio
/// runtime. `session_id` should be random per boot (the server keys recordings by it).
/// With `[imu]` or `[stepper]` configured, opens the I2C bus: the emulated bus at
/// `[i2c] socket` ([`SocketI2c`]; one that is not there yet is logged and the IMU and the
/// stepper keep retrying), or the Pi's `/dev/i2c-N` through rppal (if it cannot, the lidars
/// still run and the error is logged).
pub async fn run(
    config: EdgeConfig,
    clock: SharedClock,
    session_id: u64,
    shutdown: watch::Receiver<bool>,
) -> anyhow::Result<DaemonReport> {
    let wants_i2c = config.imu.is_some() || config.stepper.is_some();
    if wants_i2c && let Some(socket) = config.i2c.socket.clone() {
        let mut bus = SocketI2c::new(&socket);
        if let Err(e) = bus.connect() {
            tracing::error!(path = %socket.display(), error = %e, "cannot open the I2C socket (is `scan3d-sim rig` running?): the IMU and the stepper retry every second");
        }
        let hardware = I2cHardware {
            bus,
            delay: ClockDelay(clock.clone()),
        };
        return run_with_i2c(config, clock, session_id, shutdown, Some(hardware)).await;
    }
    let i2c = if wants_i2c {
        let bus = config.i2c.bus_number();
        match rppal::i2c::I2c::with_bus(bus) {
            Ok(i2c) => {
                tracing::info!(path = %config.i2c.device_path().display(), "I2C bus opened");
                Some(I2cHardware {
                    bus: i2c,
                    delay: ClockDelay(clock.clone()),
                })
            }
            Err(e) => {
                tracing::error!(path = %config.i2c.device_path().display(), error = %e, "cannot open the I2C bus (enable it with `raspi-config nonint do_i2c 0`; the user needs the i2c group): running without IMU and stepper");
                None
            }
        }
    } else {
        None
    };
    run_with_i2c(config, clock, session_id, shutdown, i2c).await
}

/// [`run`] with the I2C bus passed in (the hw-sim's emulated bus, or any embedded-hal bus).
pub async fn run_with_i2c<I, D>(
    mut config: EdgeConfig,
    clock: SharedClock,
    session_id: u64,
    mut shutdown: watch::Receiver<bool>,
    i2c: Option<I2cHardware<I, D>>,
) -> anyhow::Result<DaemonReport>
where
    I: I2c + Send + 'static,
    D: DelayNs + Clone + Send + 'static,
{
    // A configuration built in code (the simulator, tests) gets the checks a file gets.
    config.validate()?;
    config.apply_sweep_mount();
    let (scan_requests_tx, scan_requests) = std::sync::mpsc::channel::<ReceivedCommand>();
    // Where static-scan commands go is known once the stepper and the Sweep are set up; until
    // then the router holds them (the uplink is still connecting).
    let (scan_route_tx, scan_route_rx) = tokio::sync::oneshot::channel::<ScanRoute>();
    let (uplink_task, uplink_stop, uplink_handle) = match &config.uplink {
        Some(section) => {
            let client_config = tls::client_config(&section.pki_dir)?;
            let spool = section.spool_config(config.state_dir.join("spool"))?;
            let uplink_config = UplinkConfig::new(
                section.server.clone(),
                section.tls_name().to_owned(),
                client_config,
                spool,
            );
            let (uplink, handle, commands) = Uplink::new(uplink_config, clock.clone(), session_id)?;
            let (stop_tx, stop_rx) = watch::channel(false);
            let task = tokio::spawn(uplink.run(stop_rx));
            tokio::spawn(route_commands(
                commands,
                scan_route_rx,
                Passes::new(config.rplidar.is_some()),
                handle.clone(),
                clock.clone(),
            ));
            (Some(task), Some(stop_tx), Some(handle))
        }
        None => {
            tracing::warn!("no [uplink] section: acquiring without streaming");
            (None, None, None)
        }
    };
    let context = Arc::new(Context {
        clock: clock.clone(),
        uplink: uplink_handle,
        device_name: config.device_name.clone(),
        inventory: Mutex::new(BTreeMap::new()),
        stop: AtomicBool::new(false),
        mounts: config.sensor_mounts(),
        mounts_sent: AtomicBool::new(false),
    });
    // A spool left full by an earlier run refuses this too; the lidars' Info events send the
    // hello (and the mounts after it) again once there is room.
    context.submit_hello();

    // The IMU and the motor HAT share the bus; embedded-hal-bus's MutexDevice needs the mutex
    // to outlive both threads, so it lives for the rest of the process (one per daemon run).
    let (mut imu_bus, mut hat_bus) = (None, None);
    if let Some(hardware) = i2c {
        let bus: &'static Mutex<I> = Box::leak(Box::new(Mutex::new(hardware.bus)));
        imu_bus = Some((MutexDevice::new(bus), hardware.delay.clone()));
        hat_bus = Some((MutexDevice::new(bus), hardware.delay));
    }
    let imu = match (&config.imu, imu_bus) {
        (Some(section), Some((bus, delay))) => {
            let context = context.clone();
            let mut lost = false;
            Some(ImuWorker::spawn(
                bus,
                delay,
                section.clone(),
                clock.clone(),
                move |event| {
                    let body: Body = match event {
                        ImuEvent::Sample(sample) => {
                            // 200 a second: they go out in the uplink's batches.
                            if let Err(e) = context.submit_deferred(sample) {
                                tracing::debug!(error = %e, "IMU frame not queued");
                            }
                            return;
                        }
                        ImuEvent::Ready(ids) => {
                            tracing::info!(model = "MPU-9250", who_am_i = ids.who_am_i, wia = ?ids.wia, "IMU ready");
                            context.inventory_insert(SensorInfo {
                                sensor: SensorId::IMU,
                                model: "MPU-9250".into(),
                                firmware: String::new(),
                                serial: String::new(),
                            });
                            if !std::mem::take(&mut lost) {
                                return;
                            }
                            status_body(
                                &context,
                                SensorId::IMU,
                                StatusEvent::SensorBack,
                                "answering again",
                            )
                        }
                        ImuEvent::Lost(reason) => {
                            // Once per loss: the worker retries every second while it lasts.
                            if std::mem::replace(&mut lost, true) {
                                tracing::debug!(%reason, "IMU still not answering");
                                return;
                            }
                            tracing::error!(%reason, "IMU lost; retrying every second");
                            status_body(&context, SensorId::IMU, StatusEvent::SensorLost, reason)
                        }
                    };
                    // IMU frames are small and frequent; while the spool is full they are
                    // dropped here (counted by the uplink) rather than pausing the thread.
                    if let Err(e) = context.submit(body) {
                        tracing::debug!(error = %e, "IMU frame not queued");
                    }
                },
            )?)
        }
        _ => None,
    };
    let turntable = match (&config.stepper, hat_bus) {
        (Some(stepper), Some((bus, delay))) => {
            let context = context.clone();
            match Turntable::spawn(bus, delay, stepper, clock.clone(), move |state| {
                if let Err(e) = context.submit(state) {
                    tracing::debug!(error = %e, "stepper state not queued");
                }
            }) {
                Ok(turntable) => Ok(turntable),
                Err(e) => {
                    tracing::error!(error = %e, "stepper unavailable: static scans are off");
                    Err(format!("the stepper is unavailable: {e}"))
                }
            }
        }
        (None, _) => Err("no [stepper] in edge.toml".to_owned()),
        (Some(_), None) => Err("the I2C bus is not open (see the edge's log)".to_owned()),
    };
    // Static scans need the turntable and the Sweep; the reason they are off answers every
    // scan command.
    let (mut scan_hooks, scan_route) = match (turntable, &config.sweep) {
        (Ok(turntable), Some(_)) => (
            Some(ScanHooks::new(
                turntable,
                scan_requests,
                config.static_scan.clone(),
            )),
            ScanRoute::Worker(scan_requests_tx),
        ),
        (Ok(_), None) => {
            tracing::warn!("[stepper] without [sweep]: static scans are off");
            (None, ScanRoute::Off("no [sweep] in edge.toml".to_owned()))
        }
        (Err(why), _) => (None, ScanRoute::Off(why)),
    };
    // No uplink, no commands: nobody listens.
    let _ = scan_route_tx.send(scan_route);

    let mut workers: Vec<(SensorId, JoinHandle<(LidarReport, u32)>)> = Vec::new();
    if let Some(section) = &config.rplidar {
        let driver_config = section.driver.clone();
        let serial = SerialOptions::new(&section.path, section.driver.baud);
        // Nothing waits on the RPLidar within a revolution: half the reads of the Sweep's pace
        // (which the static-scan controller needs), the timing fit is the same. The read that
        // completes a revolution is not paced: the driver's read deadline brings it forward
        // (`LidarDriver::poll_read_deadline`), so the pace does not delay the live pose.
        serial.read_coalesce.set(RPLIDAR_READ_PACE);
        let make: DriverFactory =
            Box::new(move || Ok(Box::new(Rplidar::new(driver_config.clone())) as Box<_>));
        workers.push((
            SensorId::RPLIDAR,
            spawn_worker(SensorId::RPLIDAR, make, serial, context.clone(), None)?,
        ));
    }
    if let Some(section) = &config.sweep {
        let driver_config = section.driver.clone();
        Sweep::new(driver_config.clone())?; // refuse a bad config at start-up, loudly
        let serial = SerialOptions::new(&section.path, 115_200);
        // Faster only while a static scan runs or waits (the Sweep worker sets it).
        serial.read_coalesce.set(SWEEP_IDLE_READ_PACE);
        let make: DriverFactory =
            Box::new(move || Ok(Box::new(Sweep::new(driver_config.clone())?) as Box<_>));
        workers.push((
            SensorId::SWEEP,
            spawn_worker(
                SensorId::SWEEP,
                make,
                serial,
                context.clone(),
                scan_hooks.take(),
            )?,
        ));
    }
    daemon::notify(&[NotifyState::Ready]);
    let watchdog = tokio::spawn(daemon::watchdog());

    while !*shutdown.borrow() {
        if shutdown.changed().await.is_err() {
            break;
        }
    }
    tracing::info!("stopping: lidars first, then the uplink drains");
    daemon::notify(&[NotifyState::Stopping]);
    context.stop.store(true, Ordering::Relaxed);
    let mut report = DaemonReport {
        session_id,
        ..Default::default()
    };
    for (sensor, worker) in workers {
        let lidar = tokio::task::spawn_blocking(move || worker.join()).await;
        match lidar {
            Ok(Ok((lidar, scans))) => {
                report.lidars.insert(sensor, lidar);
                report.static_scans += scans;
            }
            _ => tracing::error!(%sensor, "lidar worker panicked"),
        }
    }
    if let Some(imu) = imu {
        report.imu = Some(tokio::task::spawn_blocking(move || imu.stop()).await?);
    }
    if let Some(stop) = uplink_stop {
        let _ = stop.send(true);
    }
    if let Some(task) = uplink_task {
        report.uplink = task.await.ok();
    }
    watchdog.abort();
    Ok(report)
}

/// How long the RPLidar's reads let bytes gather ([`SerialOptions::read_coalesce`]; the read
/// that completes an express revolution comes at the driver's deadline instead), and the
/// Sweep's while no static scan runs or waits.
const RPLIDAR_READ_PACE: Duration = Duration::from_millis(20);
const SWEEP_IDLE_READ_PACE: Duration = Duration::from_millis(20);

/// The Sweep's read pace while a static scan runs or waits: the controller decides each
/// step on samples that are at most this old (an FTDI adapter's latency timer is 16 ms).
const SWEEP_SCAN_READ_PACE: Duration = Duration::from_millis(10);

/// Makes a fresh driver for each acquisition run (after a pause the handshake starts over).
type DriverFactory = Box<dyn Fn() -> anyhow::Result<Box<dyn LidarDriver + Send>> + Send>;

fn spawn_worker(
    sensor: SensorId,
    make_driver: DriverFactory,
    serial: SerialOptions,
    context: Arc<Context>,
    mut scan: Option<ScanHooks>,
) -> std::io::Result<JoinHandle<(LidarReport, u32)>> {
    std::thread::Builder::new()
        .name(format!("{sensor} worker"))
        .spawn(move || {
            let report = lidar_worker(sensor, make_driver.as_ref(), serial, &context, &mut scan);
            let started = scan.as_mut().map_or(0, |hooks| {
                hooks.shut_down(&context);
                hooks.started
            });
            (report, started)
        })
}

/// Where the server's static-scan commands go: the Sweep worker's [`ScanHooks`], or nowhere,
/// with the reason static scans are off (which the edge's refusal carries).
enum ScanRoute {
    /// The Sweep worker with a turntable takes them.
    Worker(std::sync::mpsc::Sender<ReceivedCommand>),
    /// Static scans are off, for this reason.
    Off(String),
}

/// The refusal of `command` that the router gives itself (without asking the Sweep worker):
/// commands this edge does not support, and scan commands when static scans are off.
fn route_refusal(command: &Command, route: &ScanRoute) -> Option<String> {
    match (command, route) {
        (Command::SetMotorSpeed { .. }, _) => {
            Some("SetMotorSpeed is not supported: set motor_hz in edge.toml".to_owned())
        }
        // The router answers these itself (`Passes`) before asking for a route.
        (Command::StartPass { .. } | Command::StopPass, _) => None,
        (_, ScanRoute::Worker(_)) => None,
        (Command::StopStaticScan, ScanRoute::Off(why)) => Some(format!(
            "no static scan is running (static scans are off: {why})"
        )),
        (Command::StartStaticScan { .. }, ScanRoute::Off(why)) => {
            Some(format!("static scans are off: {why}"))
        }
    }
}

/// Routes the server's commands: scan commands to the Sweep worker (which replies), the rest
/// refused here with a [`CommandReply`]. Waits for the route first (the commands queue).
async fn route_commands(
    mut commands: tokio::sync::mpsc::UnboundedReceiver<ReceivedCommand>,
    route: tokio::sync::oneshot::Receiver<ScanRoute>,
    mut passes: Passes,
    uplink: UplinkHandle,
    clock: SharedClock,
) {
    let route = route
        .await
        .unwrap_or_else(|_| ScanRoute::Off("the edge daemon is stopping".to_owned()));
    while let Some(received) = commands.recv().await {
        // Trolley passes are the router's own: a reply and a pass marker on the edge's clock.
        if let Some(bodies) = passes.on_command(received.seq, &received.command, clock.now_ns()) {
            tracing::info!(command = ?received.command, running = ?passes.running(), "trolley pass command");
            for body in bodies {
                if let Err(e) = uplink.submit(body) {
                    tracing::warn!(error = %e, "trolley pass frame not queued");
                }
            }
            continue;
        }
        let refusal = match route_refusal(&received.command, &route) {
            Some(reason) => Some(reason),
            None => match &route {
                ScanRoute::Worker(worker) => worker
                    .send(received.clone())
                    .err()
                    .map(|_| "the Sweep worker has stopped".to_owned()),
                ScanRoute::Off(_) => None,
            },
        };
        if let Some(reason) = refusal {
            tracing::warn!(command = ?received.command, %reason, "command refused");
            let reply = CommandReply {
                command_seq: received.seq,
                t_ns: clock.now_ns(),
                outcome: CommandOutcome::Refused { reason },
            };
            if let Err(e) = uplink.submit(reply) {
                tracing::warn!(error = %e, "command reply not queued");
            }
        }
    }
}

/// How long after its last sample the Sweep still counts as streaming (a revolution takes at
/// most 1 s at the slowest rate).
const SWEEP_STREAMING_NS: u64 = 2_000_000_000;

/// What the Sweep worker needs to run static scans.
struct ScanHooks {
    turntable: Turntable,
    requests: std::sync::mpsc::Receiver<ReceivedCommand>,
    config: StaticScanConfig,
    session: Option<ScanSession>,
    /// A start that waits for the Sweep to stream: its command's seq and position.
    pending: Option<(u64, ScanPosition)>,
    /// Edge time of the Sweep's latest sample.
    last_sample_ns: Option<u64>,
    /// Scans started (the next scan's id).
    started: u32,
}

/// A reply to the command carried by server frame `seq`.
fn reply(seq: u64, t_ns: u64, outcome: CommandOutcome) -> Body {
    CommandReply {
        command_seq: seq,
        t_ns,
        outcome,
    }
    .into()
}

impl ScanHooks {
    fn new(
        turntable: Turntable,
        requests: std::sync::mpsc::Receiver<ReceivedCommand>,
        config: StaticScanConfig,
    ) -> Self {
        ScanHooks {
            turntable,
            requests,
            config,
            session: None,
            pending: None,
            last_sample_ns: None,
            started: 0,
        }
    }

    /// Whether the Sweep worker needs every sample as it arrives: while a scan runs or waits
    /// for the Sweep. Otherwise the revolutions are enough ([`ScanHooks::on_revolution`]) and
    /// the Sweep's thread does not wake the worker for each read.
    fn wants_samples(&self) -> bool {
        self.session.is_some() || self.pending.is_some()
    }

    /// A Sweep revolution: the Sweep streams (when samples are not forwarded, this is how the
    /// worker knows).
    fn on_revolution(&mut self, rev: &Revolution) {
        let last = rev.samples.last().map_or(rev.t1_ns, |s| s.t_ns);
        self.last_sample_ns = Some(self.last_sample_ns.map_or(last, |t| t.max(last)));
    }

    /// Whether the Sweep sent a sample within [`SWEEP_STREAMING_NS`] of `now_ns`.
    fn streaming(&self, now_ns: u64) -> bool {
        self.last_sample_ns
            .is_some_and(|t| now_ns.saturating_sub(t) <= SWEEP_STREAMING_NS)
    }

    /// Starts a scan at `position` for the command of `seq`; the reply goes to `bodies`.
    fn start(
        &mut self,
        seq: u64,
        position: ScanPosition,
        now_ns: u64,
        actions: &mut Vec<ScanAction>,
    ) {
        tracing::info!(scan = self.started, position = %position.name, x_m = position.x_m, y_m = position.y_m, "static scan starts");
        match ScanSession::start(
            self.started,
            position,
            &self.config,
            (
                self.turntable.step_angle_deg(),
                self.turntable.step_rate_hz(),
            ),
            now_ns,
        ) {
            Ok((session, started)) => {
                actions.push(ScanAction::Send(reply(
                    seq,
                    now_ns,
                    CommandOutcome::Accepted {
                        scan_id: Some(self.started),
                    },
                )));
                self.session = Some(session);
                self.started += 1;
                actions.push(started);
            }
            Err(e) => {
                tracing::error!(error = %e, "static scan refused");
                actions.push(ScanAction::Send(reply(
                    seq,
                    now_ns,
                    CommandOutcome::Refused {
                        reason: format!("static scan refused: {e}"),
                    },
                )));
            }
        }
    }

    /// Handles commands and stepper reports; frames to send go to `bodies`.
    fn poll(&mut self, context: &Context, bodies: &mut Vec<Body>) {
        let mut actions = Vec::new();
        while let Ok(ReceivedCommand { seq, command }) = self.requests.try_recv() {
            let now = context.clock.now_ns();
            let refuse = |reason: String| {
                tracing::warn!(%reason, "command refused");
                ScanAction::Send(reply(seq, now, CommandOutcome::Refused { reason }))
            };
            match command {
                Command::StartStaticScan {
                    position,
                    x_m,
                    y_m,
                    heading_deg,
                } => {
                    let position = ScanPosition {
                        name: position,
                        x_m,
                        y_m,
                        heading_deg: heading_deg.unwrap_or(0.0),
                    };
                    if let Some(session) = &self.session {
                        actions.push(refuse(format!(
                            "static scan {} is running; stop it first (scan3d scan --stop)",
                            session.scan_id()
                        )));
                    } else if let Some((_, waiting)) = &self.pending {
                        actions.push(refuse(format!(
                            "a static scan at {:?} is waiting for the Sweep; stop it first (scan3d scan --stop)",
                            waiting.name
                        )));
                    } else if self.streaming(now) {
                        self.start(seq, position, now, &mut actions);
                    } else {
                        tracing::info!(position = %position.name, "static scan waits for the Sweep to stream");
                        self.pending = Some((seq, position));
                        actions.push(ScanAction::Send(reply(
                            seq,
                            now,
                            CommandOutcome::Waiting {
                                reason: "waiting for the Sweep to stream".to_owned(),
                            },
                        )));
                    }
                }
                Command::StopStaticScan => {
                    if let Some(session) = &mut self.session {
                        let scan_id = session.scan_id();
                        tracing::info!(scan = scan_id, "static scan stopped by the server");
                        actions.push(ScanAction::Send(reply(
                            seq,
                            now,
                            CommandOutcome::Accepted {
                                scan_id: Some(scan_id),
                            },
                        )));
                        session.stop(now, &mut actions);
                    } else if let Some((waiting_seq, position)) = self.pending.take() {
                        tracing::info!(position = %position.name, "static scan cancelled before the Sweep streamed");
                        actions.push(ScanAction::Send(reply(
                            waiting_seq,
                            now,
                            CommandOutcome::Refused {
                                reason: "stopped before the Sweep streamed".to_owned(),
                            },
                        )));
                        actions.push(ScanAction::Send(reply(
                            seq,
                            now,
                            CommandOutcome::Accepted { scan_id: None },
                        )));
                    } else {
                        actions.push(refuse("no static scan is running".to_owned()));
                    }
                }
                Command::SetMotorSpeed { .. } => actions.push(refuse(
                    "SetMotorSpeed is not supported: set motor_hz in edge.toml".to_owned(),
                )),
                // The router keeps trolley passes (`Passes`); none reach the Sweep worker.
                Command::StartPass { .. } | Command::StopPass => actions.push(refuse(
                    "not a static-scan command: trolley passes are the router's".to_owned(),
                )),
            }
        }
        while let Some(report) = self.turntable.try_report() {
            match (report, &mut self.session) {
                (TurntableReport::Moved { t_ns }, Some(session)) => {
                    session.on_step_done(t_ns, &mut actions)
                }
                (
                    TurntableReport::Failed {
                        t_ns,
                        steps_done,
                        error,
                    },
                    Some(session),
                ) => {
                    tracing::error!(%error, "stepper move failed");
                    session.on_step_failed(t_ns, steps_done, &mut actions);
                }
                (TurntableReport::Home(Ok(())), _) => tracing::info!("turntable home"),
                (TurntableReport::Home(Err(e)), _) => {
                    tracing::error!(error = %e, "turntable could not return home")
                }
                (report, None) => tracing::debug!(?report, "stepper report after the scan"),
            }
        }
        self.carry_out(actions, bodies);
    }

    /// A Sweep sample: the Sweep streams, so a waiting scan starts (at this sample), and a
    /// running one decides on it.
    fn on_sample(&mut self, sample: &crate::timing::StampedSample, bodies: &mut Vec<Body>) {
        let mut actions = Vec::new();
        self.last_sample_ns = Some(sample.sample.t_ns);
        if self.session.is_none()
            && let Some((seq, position)) = self.pending.take()
        {
            self.start(seq, position, sample.sample.t_ns, &mut actions);
        }
        if let Some(session) = &mut self.session {
            session.on_sample(sample, &mut actions);
        }
        self.carry_out(actions, bodies);
    }

    /// Ends a running scan (Sweep lost, acquisition paused, daemon stopping). A scan waiting
    /// for the Sweep keeps waiting.
    fn stop(&mut self, context: &Context, why: &str, bodies: &mut Vec<Body>) {
        let mut actions = Vec::new();
        if let Some(session) = &mut self.session {
            tracing::warn!(scan = session.scan_id(), why, "static scan stopped");
            session.stop(context.clock.now_ns(), &mut actions);
        }
        self.carry_out(actions, bodies);
    }

    fn carry_out(&mut self, actions: Vec<ScanAction>, bodies: &mut Vec<Body>) {
        for action in actions {
            match action {
                ScanAction::Send(body) => bodies.push(body),
                ScanAction::Step(command) => {
                    if !self.turntable.submit(TurntableJob::Move(command.as_move())) {
                        tracing::error!("turntable thread gone");
                    }
                }
                ScanAction::ReturnHome => {
                    self.turntable.submit(TurntableJob::Home);
                }
            }
        }
        if self.session.as_ref().is_some_and(ScanSession::is_over) {
            self.session = None;
        }
    }

    /// At daemon stop: ends a running scan, refuses a waiting one, and waits (bounded) for the
    /// way home.
    fn shut_down(&mut self, context: &Context) {
        let mut bodies = Vec::new();
        let running = self.session.is_some();
        self.stop(context, "daemon stopping", &mut bodies);
        if let Some((seq, _)) = self.pending.take() {
            bodies.push(reply(
                seq,
                context.clock.now_ns(),
                CommandOutcome::Refused {
                    reason: "the edge daemon is stopping".to_owned(),
                },
            ));
        }
        for body in bodies {
            if let Err(e) = context.submit(body) {
                tracing::warn!(error = %e, "static scan frame not queued at shutdown");
            }
        }
        if running {
            while let Some(report) = self.turntable.wait_report(Duration::from_secs(30)) {
                if matches!(report, TurntableReport::Home(_)) {
                    break;
                }
            }
        }
    }
}

/// Why a worker paused acquisition.
#[derive(Debug, Clone, PartialEq, Eq)]
enum PauseCause {
    /// The spool reached its limits (the server is unreachable or too slow).
    SpoolFull,
    /// The spool cannot write to disk (disk full, I/O error).
    Unwritable(String),
}

impl PauseCause {
    /// The reason sent in the `AcquisitionPaused` status.
    fn reason(&self) -> String {
        match self {
            PauseCause::SpoolFull => "spool full".into(),
            PauseCause::Unwritable(reason) => format!("spool cannot write to disk: {reason}"),
        }
    }
}

/// Submits the frames an earlier pause kept (`refused`), then `bodies`, in order, until the
/// spool refuses one for lack of room or a writable disk: that frame and every later one stay
/// in `refused`, to go first after the pause. Returns why it must pause, if it must. Only a
/// frame that can never be queued (over the size limit) is dropped, with an error.
fn submit_in_order(
    sensor: SensorId,
    submit: &mut dyn FnMut(Body) -> Result<(), SubmitError>,
    refused: &mut Vec<Body>,
    bodies: &mut Vec<Body>,
) -> Option<PauseCause> {
    let mut pause = None;
    for body in std::mem::take(refused).into_iter().chain(bodies.drain(..)) {
        if pause.is_some() {
            refused.push(body);
            continue;
        }
        match submit(body.clone()) {
            Ok(()) => {}
            Err(SubmitError::Full) => {
                refused.push(body);
                pause = Some(PauseCause::SpoolFull);
            }
            Err(SubmitError::Unwritable { reason }) => {
                refused.push(body);
                pause = Some(PauseCause::Unwritable(reason));
            }
            Err(e) => tracing::error!(%sensor, error = %e, "frame not queued"),
        }
    }
    pause
}

/// Acquires one lidar until the daemon stops, pausing while the spool has no room.
fn lidar_worker(
    sensor: SensorId,
    make_driver: &dyn Fn() -> anyhow::Result<Box<dyn LidarDriver + Send>>,
    serial: SerialOptions,
    context: &Context,
    scan: &mut Option<ScanHooks>,
) -> LidarReport {
    let mut report = LidarReport::default();
    // Frames refused by a full or unwritable spool are kept and sent first after resuming.
    let mut refused: Vec<Body> = Vec::new();
    let mut lost = false;
    while !context.stop.load(Ordering::Relaxed) {
        let driver = match make_driver() {
            Ok(driver) => driver,
            Err(e) => {
                tracing::error!(%sensor, error = %e, "cannot create the driver");
                return report;
            }
        };
        let (acquisition, events) = Acquisition::spawn(
            driver,
            serial.clone(),
            context.clock.clone(),
            TimingConfig::default(),
            scan.as_ref().is_some_and(ScanHooks::wants_samples),
        );
        let mut pause: Option<PauseCause> = None;
        let mut bodies: Vec<Body> = Vec::new();
        while pause.is_none() && !context.stop.load(Ordering::Relaxed) {
            if let Some(hooks) = scan.as_mut() {
                hooks.poll(context, &mut bodies);
            }
            let event = match events.recv_timeout(Duration::from_millis(100)) {
                Ok(event) => Some(event),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => break,
            };
            let body: Option<Body> = match event {
                None => None,
                Some(event) => match event {
                    AcquisitionEvent::Samples(samples) => {
                        if let Some(hooks) = scan.as_mut() {
                            for sample in &samples {
                                hooks.on_sample(sample, &mut bodies);
                            }
                        }
                        None
                    }
                    AcquisitionEvent::Revolution(rev) => {
                        if let Some(hooks) = scan.as_mut() {
                            hooks.on_revolution(&rev);
                        }
                        report.revolutions += 1;
                        report.samples += rev.samples.len() as u64;
                        Some(revolution_frame(sensor, &rev).into())
                    }
                    AcquisitionEvent::Driver(LidarEvent::Info(info)) => {
                        tracing::info!(%sensor, path = %serial.path.display(), model = %info.model, firmware = %info.firmware, serial = %info.serial, "lidar identified");
                        let entry = SensorInfo {
                            sensor,
                            model: info.model,
                            firmware: info.firmware,
                            serial: info.serial,
                        };
                        context
                            .inventory
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .insert(sensor, entry);
                        Some(context.hello().into())
                    }
                    AcquisitionEvent::Lost(reason) => {
                        lost = true;
                        tracing::warn!(%sensor, %reason, "lidar lost");
                        if let Some(hooks) = scan.as_mut() {
                            hooks.stop(context, "Sweep lost", &mut bodies);
                        }
                        Some(status_body(
                            context,
                            sensor,
                            StatusEvent::SensorLost,
                            reason,
                        ))
                    }
                    AcquisitionEvent::Driver(LidarEvent::Scanning { .. }) if lost => {
                        lost = false;
                        tracing::info!(%sensor, "lidar back");
                        Some(status_body(
                            context,
                            sensor,
                            StatusEvent::SensorBack,
                            "scanning again",
                        ))
                    }
                    AcquisitionEvent::Driver(LidarEvent::Failed(error)) => {
                        tracing::error!(%sensor, %error, "lidar driver gave up; retrying");
                        if let Some(hooks) = scan.as_mut() {
                            hooks.stop(context, "Sweep driver failed", &mut bodies);
                        }
                        Some(status_body(
                            context,
                            sensor,
                            StatusEvent::SensorLost,
                            error.to_string(),
                        ))
                    }
                    AcquisitionEvent::Driver(LidarEvent::Warning(text)) => {
                        tracing::warn!(%sensor, "{text}");
                        None
                    }
                    AcquisitionEvent::Opened | AcquisitionEvent::Driver(_) => None,
                },
            };
            bodies.extend(body);
            if let Some(hooks) = scan.as_ref() {
                let wanted = hooks.wants_samples();
                acquisition.forward_samples(wanted);
                serial.read_coalesce.set(if wanted {
                    SWEEP_SCAN_READ_PACE
                } else {
                    SWEEP_IDLE_READ_PACE
                });
            }
            pause = submit_in_order(
                sensor,
                // At once: the server matches the live pose of the head from each RPLidar
                // revolution as it comes (the IMU readings read so far, deferred, ride in the
                // same write), and builds a static scan's live map from the Sweep's.
                &mut |body| context.submit(body),
                &mut refused,
                &mut bodies,
            );
        }
        if let Some(cause) = &pause
            && let Some(hooks) = scan.as_mut()
        {
            // The Sweep stops while paused: a scan cannot go on without it.
            hooks.stop(context, &cause.reason(), &mut refused);
        }
        match acquisition.stop() {
            Ok(summary) => report.acquisition = summary,
            Err(e) => tracing::warn!(%sensor, error = %e, "acquisition ended with an error"),
        }
        if let Some(cause) = pause {
            report.pauses += 1;
            let paused_at = context.clock.now_ns();
            match &cause {
                PauseCause::SpoolFull => {
                    tracing::warn!(%sensor, "spool full (server unreachable or too slow): acquisition paused")
                }
                PauseCause::Unwritable(reason) => {
                    tracing::warn!(%sensor, %reason, "spool cannot write to disk: acquisition paused, retrying the disk")
                }
            }
            while !context.has_room() && !context.stop.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(100));
            }
            let resumed_at = context.clock.now_ns();
            tracing::info!(%sensor, paused_s = (resumed_at - paused_at) as f64 / 1e9, "acquisition resumes");
            let pause = DeviceStatus {
                t_ns: paused_at,
                sensor,
                event: StatusEvent::AcquisitionPaused,
                reason: cause.reason(),
            };
            let resume = DeviceStatus {
                t_ns: resumed_at,
                sensor,
                event: StatusEvent::AcquisitionResumed,
                reason: match cause {
                    PauseCause::SpoolFull => "spool has room again".into(),
                    PauseCause::Unwritable(_) => "spool writes to disk again".into(),
                },
            };
            // Queued behind the frames the pause kept; they all go out when acquisition resumes.
            refused.extend([pause.into(), resume.into()]);
        }
    }
    if !refused.is_empty() {
        submit_in_order(
            sensor,
            &mut |body| context.submit(body),
            &mut refused,
            &mut Vec::new(),
        );
        if !refused.is_empty() {
            tracing::error!(%sensor, frames = refused.len(), "frames lost at shutdown: the spool had no room for them");
        }
    }
    report
}

fn status_body(
    context: &Context,
    sensor: SensorId,
    event: StatusEvent,
    reason: impl Into<String>,
) -> Body {
    DeviceStatus {
        t_ns: context.clock.now_ns(),
        sensor,
        event,
        reason: reason.into(),
    }
    .into()
}

/// The protocol frame of a timestamped revolution. Its base time is the revolution's `t0_ns`,
/// the first sample's time (sample times only go forwards), which names it for the static-scan
/// yaws; a sample more than 4.29 s after it (only the tail of a stalled revolution can be) is
/// dropped, so the indices of the others stay.
pub fn revolution_frame(sensor: SensorId, rev: &Revolution) -> LidarRevolution {
    let t0 = rev.t0_ns;
    let mut frame = LidarRevolution::new(sensor, t0, rev.t1_ns.max(t0));
    for s in &rev.samples {
        if frame
            .push(s.angle_deg, s.range_m, s.quality, s.t_ns)
            .is_err()
        {
            tracing::warn!(%sensor, "sample more than 4.29 s after its revolution start; dropped from the frame");
        }
    }
    frame
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicU64;

    use scan3d_protocol::{Frame, Heartbeat, decode};

    use super::*;
    use crate::clock::Clock;
    use crate::uplink::client::unused_client_config;
    use crate::uplink::spool::{SpoolConfig, StorageFaults};

    /// A clock the test moves by hand.
    #[derive(Default)]
    struct ManualClock(AtomicU64);

    impl Clock for ManualClock {
        fn now_ns(&self) -> u64 {
            self.0.load(Ordering::Relaxed)
        }
    }

    fn heartbeat(n: u64) -> Body {
        Heartbeat { sent_ns: n }.into()
    }

    #[test]
    fn the_router_refuses_what_the_sweep_worker_cannot_do_with_the_reason() {
        let start = Command::StartStaticScan {
            position: "p".into(),
            x_m: 0.0,
            y_m: 0.0,
            heading_deg: None,
        };
        let off = ScanRoute::Off("no [stepper] in edge.toml".into());
        assert_eq!(
            route_refusal(&start, &off).as_deref(),
            Some("static scans are off: no [stepper] in edge.toml")
        );
        assert_eq!(
            route_refusal(&Command::StopStaticScan, &off).as_deref(),
            Some("no static scan is running (static scans are off: no [stepper] in edge.toml)")
        );
        let (tx, _rx) = std::sync::mpsc::channel();
        let worker = ScanRoute::Worker(tx);
        assert_eq!(route_refusal(&start, &worker), None);
        assert_eq!(route_refusal(&Command::StopStaticScan, &worker), None);
        let speed = Command::SetMotorSpeed {
            sensor: SensorId::SWEEP,
            hz: 2.0,
        };
        for route in [&off, &worker] {
            assert!(
                route_refusal(&speed, route).is_some_and(|r| r.contains("not supported")),
                "SetMotorSpeed is refused whatever the route"
            );
        }
    }

    #[test]
    fn a_disk_write_failure_pauses_keeps_every_frame_and_resumes_once_writes_succeed() {
        let dir = tempfile::tempdir().unwrap();
        let faults = StorageFaults::default();
        let mut spool = SpoolConfig::new(dir.path());
        // Two 14-byte heartbeats fit in memory; the third makes the oldest spill to disk, and
        // memory stays above the 75 % resume mark until that spill succeeds.
        spool.memory_limit_bytes = 30;
        spool.faults = faults.clone();
        let clock = Arc::new(ManualClock::default());
        let config = UplinkConfig::new(
            "localhost:1".into(),
            "localhost".into(),
            unused_client_config(),
            spool,
        );
        let (_uplink, handle, _commands) = Uplink::new(config, clock.clone(), 7).unwrap();
        let mut submit = |body: Body| handle.submit(body).map(|_| ());
        let mut refused = Vec::new();

        faults.set_disk_full(true);
        let mut bodies: Vec<Body> = (0..10).map(heartbeat).collect();
        let pause = submit_in_order(SensorId::RPLIDAR, &mut submit, &mut refused, &mut bodies);
        assert!(
            matches!(&pause, Some(PauseCause::Unwritable(reason)) if reason.contains("No space left")),
            "{pause:?}"
        );
        let kept = refused.len();
        assert!(kept > 0 && kept < 10, "{kept} frames kept");
        assert!(!handle.has_room(), "paused while the disk is full");
        let stats = handle.stats();
        assert_eq!(stats.storage_episodes, 1);

        // Retries back off while the disk stays full; the episode is counted once.
        for step in 1..=5 {
            clock.0.store(step * 1_000_000_000, Ordering::Relaxed);
            assert!(!handle.has_room());
        }
        assert_eq!(handle.stats().storage_episodes, 1);

        faults.set_disk_full(false);
        clock.0.store(20_000_000_000, Ordering::Relaxed);
        assert!(
            handle.has_room(),
            "resumes once the disk takes writes again"
        );
        let mut bodies: Vec<Body> = (10..15).map(heartbeat).collect();
        let pause = submit_in_order(SensorId::RPLIDAR, &mut submit, &mut refused, &mut bodies);
        assert_eq!(pause, None);
        assert!(refused.is_empty());
        assert_eq!(handle.stats().storage_episodes, 1);

        let delivered: Vec<(u64, Body)> = handle
            .drain_unsent()
            .into_iter()
            .map(|frame| {
                let (decoded, _): (Frame, _) = decode(&frame.bytes).unwrap();
                (frame.seq, decoded.body)
            })
            .collect();
        let expected: Vec<(u64, Body)> = (0..15).map(|n| (n, heartbeat(n))).collect();
        assert_eq!(delivered, expected, "every frame, once, in order");
    }
}
