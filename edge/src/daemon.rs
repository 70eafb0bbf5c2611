//! The edge daemon (`scan3d-edge --config edge.toml`): every configured lidar is acquired on its
//! own thread, its revolutions become frames, and the uplink carries them to the server.
//!
//! ```text
//!  lidar thread ──Acquisition──> worker ──submit──> spool ──Uplink (QUIC)──> server
//!        (serial shell + driver)   (frames, status)        (acks remove frames)
//! ```
//!
//! When the spool is full (server unreachable for long), a worker stops its lidar, waits for
//! room, then reports `AcquisitionPaused` / `AcquisitionResumed` status frames: nothing is
//! dropped silently. SIGTERM stops the lidars (their STOP commands are sent), lets the uplink
//! drain for a few seconds and leaves the rest in the on-disk spool for the next start.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, mpsc::RecvTimeoutError};
use std::thread::JoinHandle;
use std::time::Duration;

use scan3d_protocol::{
    Body, DeviceStatus, Hello, LidarRevolution, SensorId, SensorInfo, StatusEvent,
};
use scan3d_service::daemon::{self, NotifyState};
use tokio::sync::watch;

use crate::acquisition::{Acquisition, AcquisitionEvent, AcquisitionSummary};
use crate::clock::SharedClock;
use crate::config::EdgeConfig;
use crate::drivers::rplidar::Rplidar;
use crate::drivers::sweep::Sweep;
use crate::lidar::{LidarDriver, LidarEvent};
use crate::serial::SerialOptions;
use crate::timing::{Revolution, TimingConfig};
use crate::uplink::client::{SubmitError, Uplink, UplinkConfig, UplinkHandle, UplinkStats};
use crate::uplink::spool::SpoolConfig;
use crate::uplink::tls;

/// What one lidar worker did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LidarReport {
    /// Revolutions handed to the uplink.
    pub revolutions: u64,
    /// Samples in those revolutions.
    pub samples: u64,
    /// Times acquisition paused because the spool was full.
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
}

/// Everything a running daemon shares between its threads.
struct Context {
    clock: SharedClock,
    uplink: Option<UplinkHandle>,
    device_name: String,
    inventory: Mutex<BTreeMap<SensorId, SensorInfo>>,
    stop: AtomicBool,
}

impl Context {
    /// Sends a frame body. Without an uplink, frames are only logged.
    fn submit(&self, body: impl Into<Body>) -> Result<(), SubmitError> {
        match &self.uplink {
            Some(uplink) => uplink.submit(body).map(|_| ()),
            None => Ok(()),
        }
    }

    fn has_room(&self) -> bool {
        self.uplink.as_ref().is_none_or(UplinkHandle::has_room)
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
    }
}

/// Runs the daemon until `shutdown` turns true. Must be called inside a multi-threaded tokio
/// runtime. `session_id` should be random per boot (the server keys recordings by it).
pub async fn run(
    config: EdgeConfig,
    clock: SharedClock,
    session_id: u64,
    mut shutdown: watch::Receiver<bool>,
) -> anyhow::Result<DaemonReport> {
    let (uplink_task, uplink_stop, uplink_handle) = match &config.uplink {
        Some(section) => {
            let client_config = tls::client_config(&section.pki_dir)?;
            let mut spool = SpoolConfig::new(config.state_dir.join("spool"));
            spool.memory_limit_bytes =
                usize::try_from(section.spool_memory_mb << 20).unwrap_or(usize::MAX);
            spool.disk_limit_bytes = section.spool_disk_mb << 20;
            let uplink_config = UplinkConfig::new(
                section.server.clone(),
                section.tls_name().to_owned(),
                client_config,
                spool,
            );
            let (uplink, handle, mut commands) =
                Uplink::new(uplink_config, clock.clone(), session_id)?;
            let (stop_tx, stop_rx) = watch::channel(false);
            let task = tokio::spawn(uplink.run(stop_rx));
            tokio::spawn(async move {
                while let Some(command) = commands.recv().await {
                    tracing::warn!(
                        ?command,
                        "this edge build does not act on server commands yet"
                    );
                }
            });
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
    });
    // A spool left full by an earlier run refuses this too; the lidars' Info events send the
    // hello again once there is room.
    if let Err(e) = context.submit(context.hello()) {
        tracing::warn!(error = %e, "hello not queued");
    }

    let mut workers: Vec<(SensorId, JoinHandle<LidarReport>)> = Vec::new();
    if let Some(section) = &config.rplidar {
        let driver_config = section.driver.clone();
        let serial = SerialOptions::new(&section.path, section.driver.baud);
        let make: DriverFactory =
            Box::new(move || Ok(Box::new(Rplidar::new(driver_config.clone())) as Box<_>));
        workers.push((
            SensorId::RPLIDAR,
            spawn_worker(SensorId::RPLIDAR, make, serial, context.clone())?,
        ));
    }
    if let Some(section) = &config.sweep {
        let driver_config = section.driver.clone();
        Sweep::new(driver_config.clone())?; // refuse a bad config at start-up, loudly
        let serial = SerialOptions::new(&section.path, 115_200);
        let make: DriverFactory =
            Box::new(move || Ok(Box::new(Sweep::new(driver_config.clone())?) as Box<_>));
        workers.push((
            SensorId::SWEEP,
            spawn_worker(SensorId::SWEEP, make, serial, context.clone())?,
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
            Ok(Ok(lidar)) => {
                report.lidars.insert(sensor, lidar);
            }
            _ => tracing::error!(%sensor, "lidar worker panicked"),
        }
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

/// Makes a fresh driver for each acquisition run (after a pause the handshake starts over).
type DriverFactory = Box<dyn Fn() -> anyhow::Result<Box<dyn LidarDriver + Send>> + Send>;

fn spawn_worker(
    sensor: SensorId,
    make_driver: DriverFactory,
    serial: SerialOptions,
    context: Arc<Context>,
) -> std::io::Result<JoinHandle<LidarReport>> {
    std::thread::Builder::new()
        .name(format!("{sensor} worker"))
        .spawn(move || lidar_worker(sensor, make_driver.as_ref(), serial, &context))
}

/// Acquires one lidar until the daemon stops, pausing while the spool is full.
fn lidar_worker(
    sensor: SensorId,
    make_driver: &dyn Fn() -> anyhow::Result<Box<dyn LidarDriver + Send>>,
    serial: SerialOptions,
    context: &Context,
) -> LidarReport {
    let mut report = LidarReport::default();
    // A frame refused by a full spool is kept and sent first after resuming.
    let mut refused: Option<Body> = None;
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
        );
        let mut full = false;
        while !full && !context.stop.load(Ordering::Relaxed) {
            let event = match events.recv_timeout(Duration::from_millis(100)) {
                Ok(event) => event,
                Err(RecvTimeoutError::Timeout) => continue,
                Err(RecvTimeoutError::Disconnected) => break,
            };
            let body: Body = match event {
                AcquisitionEvent::Revolution(rev) => {
                    report.revolutions += 1;
                    report.samples += rev.samples.len() as u64;
                    revolution_frame(sensor, &rev).into()
                }
                AcquisitionEvent::Driver(LidarEvent::Info(info)) => {
                    tracing::info!(%sensor, model = %info.model, firmware = %info.firmware, serial = %info.serial, "lidar identified");
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
                    context.hello().into()
                }
                AcquisitionEvent::Lost(reason) => {
                    lost = true;
                    tracing::warn!(%sensor, %reason, "lidar lost");
                    status_body(context, sensor, StatusEvent::SensorLost, reason)
                }
                AcquisitionEvent::Driver(LidarEvent::Scanning { .. }) if lost => {
                    lost = false;
                    tracing::info!(%sensor, "lidar back");
                    status_body(context, sensor, StatusEvent::SensorBack, "scanning again")
                }
                AcquisitionEvent::Driver(LidarEvent::Failed(error)) => {
                    tracing::error!(%sensor, %error, "lidar driver gave up; retrying");
                    status_body(context, sensor, StatusEvent::SensorLost, error.to_string())
                }
                AcquisitionEvent::Driver(LidarEvent::Warning(text)) => {
                    tracing::warn!(%sensor, "{text}");
                    continue;
                }
                AcquisitionEvent::Opened | AcquisitionEvent::Driver(_) => continue,
            };
            for body in refused.take().into_iter().chain(std::iter::once(body)) {
                match context.submit(body.clone()) {
                    Ok(()) => {}
                    Err(SubmitError::Full) => {
                        refused = Some(body);
                        full = true;
                    }
                    Err(e) => tracing::error!(%sensor, error = %e, "frame not queued"),
                }
            }
        }
        match acquisition.stop() {
            Ok(summary) => report.acquisition = summary,
            Err(e) => tracing::warn!(%sensor, error = %e, "acquisition ended with an error"),
        }
        if full {
            report.pauses += 1;
            let paused_at = context.clock.now_ns();
            tracing::warn!(%sensor, "spool full (server unreachable or too slow): acquisition paused");
            while !context.has_room() && !context.stop.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(100));
            }
            let resumed_at = context.clock.now_ns();
            tracing::info!(%sensor, paused_s = (resumed_at - paused_at) as f64 / 1e9, "acquisition resumes");
            let pause = DeviceStatus {
                t_ns: paused_at,
                sensor,
                event: StatusEvent::AcquisitionPaused,
                reason: "spool full".into(),
            };
            let resume = DeviceStatus {
                t_ns: resumed_at,
                sensor,
                event: StatusEvent::AcquisitionResumed,
                reason: "spool has room again".into(),
            };
            for status in [pause, resume] {
                if let Err(e) = context.submit(status) {
                    tracing::warn!(%sensor, error = %e, "pause report not queued");
                }
            }
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

/// The protocol frame of a timestamped revolution. Its base time is the earliest of `t0` and
/// the sample times (reported angles may step back slightly around the start flag).
pub fn revolution_frame(sensor: SensorId, rev: &Revolution) -> LidarRevolution {
    let t0 = rev.samples.iter().map(|s| s.t_ns).fold(rev.t0_ns, u64::min);
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
