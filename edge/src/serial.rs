//! The thin I/O shell that runs a sans-I/O [`LidarDriver`] on a serial port.
//!
//! It owns the port and the loop: write what the driver wants written, read with a timeout no
//! longer than the driver's next deadline, feed bytes with their arrival time, fire timers.
//! When the device vanishes (USB unplug, pty removed) it reports [`SerialEvent::Lost`], retries
//! opening with exponential backoff, and on success restarts the driver's handshake.

use std::io::{ErrorKind, Read, Write};
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serialport::{ClearBuffer, SerialPort, TTYPort};

use crate::clock::Clock;
use crate::lidar::{LidarDriver, LidarEvent, Transmit};

/// How to open and keep a serial link.
#[derive(Debug, Clone)]
pub struct SerialOptions {
    /// Device path, e.g. `/dev/rplidar` (udev link) or a pty link from the simulator.
    pub path: PathBuf,
    /// Line rate (8N1).
    pub baud: u32,
    /// Longest single blocking read, real time. Bounds how late shutdown is noticed.
    pub max_read_wait: Duration,
    /// After a read that returned only a little data, wait this long (edge-clock time) before
    /// reading again, so bytes arrive in batches as a USB adapter's latency timer delivers them.
    /// This roughly halves the edge's system calls at full sensor rate; the added delay is the
    /// same for every read, so [`crate::timing`]'s lower-envelope fit absorbs it.
    pub read_coalesce: Duration,
    /// Reopen the port after it disappears (daemon). When `false`, the first failure to open or
    /// a lost device ends [`run`] with an error (one-shot tools such as `probe`).
    pub reconnect: bool,
    /// First reconnect delay; doubled after each failure up to `max_backoff`.
    pub initial_backoff: Duration,
    /// Longest reconnect delay.
    pub max_backoff: Duration,
}

impl SerialOptions {
    /// Defaults for a device at `path` and `baud`: reconnect with 100 ms … 2 s backoff.
    pub fn new(path: impl Into<PathBuf>, baud: u32) -> Self {
        Self {
            path: path.into(),
            baud,
            max_read_wait: Duration::from_millis(50),
            read_coalesce: Duration::from_millis(2),
            reconnect: true,
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(2),
        }
    }
}

/// What the shell reports to its caller.
#[derive(Debug, Clone, PartialEq)]
pub enum SerialEvent {
    /// The port was opened (first time or after a loss); the driver handshake restarts.
    Opened,
    /// The device went away or the port failed; reconnecting if enabled.
    Lost(String),
    /// An event from the driver.
    Driver(LidarEvent),
}

/// Why [`run`] stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum SerialError {
    /// The port could not be opened.
    #[error("cannot open {path}: {reason}")]
    Open {
        /// The device path.
        path: PathBuf,
        /// Human-readable cause, with a hint where one helps.
        reason: String,
    },
    /// The device disappeared and reconnecting was disabled.
    #[error("lost {path}: {reason}")]
    Lost {
        /// The device path.
        path: PathBuf,
        /// What failed.
        reason: String,
    },
}

/// Runs `driver` on the port until `on_event` returns [`ControlFlow::Break`] or `shutdown` is
/// set. On a clean stop the driver's `stop()` bytes are written before returning.
pub fn run<D: LidarDriver + ?Sized>(
    driver: &mut D,
    options: &SerialOptions,
    clock: &dyn Clock,
    shutdown: &AtomicBool,
    mut on_event: impl FnMut(SerialEvent) -> ControlFlow<()>,
) -> Result<(), SerialError> {
    let mut backoff = options.initial_backoff;
    loop {
        if shutdown.load(Ordering::Relaxed) {
            return Ok(());
        }
        let mut port = match open(&options.path, options.baud, options.max_read_wait) {
            Ok(port) => port,
            Err(reason) if options.reconnect => {
                tracing::debug!(path = %options.path.display(), %reason, "open failed; retrying");
                sleep_unless_shutdown(backoff, shutdown);
                backoff = (backoff * 2).min(options.max_backoff);
                continue;
            }
            Err(reason) => {
                return Err(SerialError::Open {
                    path: options.path.clone(),
                    reason,
                });
            }
        };
        backoff = options.initial_backoff;
        tracing::info!(path = %options.path.display(), baud = options.baud, "serial port open");
        if on_event(SerialEvent::Opened).is_break() {
            return Ok(());
        }
        driver.start(clock.now_ns());
        match session(driver, &mut port, options, clock, shutdown, &mut on_event) {
            Ok(()) => {
                driver.stop(clock.now_ns());
                // Best effort: the device may already be gone.
                let _ = flush_transmits(driver, &mut port, &mut DtrWarning::default());
                return Ok(());
            }
            Err(reason) => {
                tracing::warn!(path = %options.path.display(), %reason, "serial device lost");
                if on_event(SerialEvent::Lost(reason.clone())).is_break() {
                    return Ok(());
                }
                if !options.reconnect {
                    return Err(SerialError::Lost {
                        path: options.path.clone(),
                        reason,
                    });
                }
                sleep_unless_shutdown(backoff, shutdown);
            }
        }
    }
}

/// One connected stretch: returns `Ok` on a requested stop, `Err(reason)` when the port fails.
fn session<D: LidarDriver + ?Sized>(
    driver: &mut D,
    port: &mut TTYPort,
    options: &SerialOptions,
    clock: &dyn Clock,
    shutdown: &AtomicBool,
    on_event: &mut impl FnMut(SerialEvent) -> ControlFlow<()>,
) -> Result<(), String> {
    let mut buf = vec![0u8; 4096];
    let mut dtr_warning = DtrWarning::default();
    loop {
        flush_transmits(driver, port, &mut dtr_warning)?;
        while let Some(event) = driver.poll_event() {
            if on_event(SerialEvent::Driver(event)).is_break() {
                return Ok(());
            }
        }
        if shutdown.load(Ordering::Relaxed) {
            return Ok(());
        }
        let now = clock.now_ns();
        let deadline = driver.poll_timeout();
        if deadline.is_some_and(|deadline| deadline <= now) {
            driver.handle_timeout(now);
            continue;
        }
        let wait = deadline
            .map(|deadline| clock.real_duration(deadline.saturating_sub(now)))
            .unwrap_or(options.max_read_wait)
            .clamp(Duration::from_millis(1), options.max_read_wait);
        port.set_timeout(wait).map_err(|e| e.to_string())?;
        match port.read(&mut buf) {
            // A pty whose master closed, or a USB adapter that vanished, reads as EOF.
            Ok(0) => return Err("end of file (device disconnected)".into()),
            Ok(n) => {
                driver.handle_input(clock.now_ns(), &buf[..n]);
                if n < buf.len() / 4 && !options.read_coalesce.is_zero() {
                    let coalesce_ns =
                        u64::try_from(options.read_coalesce.as_nanos()).unwrap_or(u64::MAX);
                    std::thread::sleep(clock.real_duration(coalesce_ns));
                }
            }
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {}
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e.to_string()),
        }
    }
}

/// Logs the first DTR failure per connection only: a pty cannot carry modem lines.
#[derive(Default)]
struct DtrWarning(bool);

fn flush_transmits<D: LidarDriver + ?Sized>(
    driver: &mut D,
    port: &mut TTYPort,
    dtr_warning: &mut DtrWarning,
) -> Result<(), String> {
    while let Some(transmit) = driver.poll_transmit() {
        match transmit {
            Transmit::Write(bytes) => {
                port.write_all(&bytes).map_err(|e| e.to_string())?;
                port.flush().map_err(|e| e.to_string())?;
            }
            Transmit::FlushInput => port.clear(ClearBuffer::Input).map_err(|e| e.to_string())?,
            Transmit::SetDtr(level) => {
                if let Err(e) = port.write_data_terminal_ready(level)
                    && !dtr_warning.0
                {
                    tracing::info!(error = %e, "cannot set DTR (no modem lines, e.g. a pty); motor left as is");
                    dtr_warning.0 = true;
                }
            }
        }
    }
    Ok(())
}

/// Opens `path` raw 8N1 at `baud`, with a readable reason on failure.
pub fn open(path: &Path, baud: u32, timeout: Duration) -> Result<TTYPort, String> {
    serialport::new(path.to_string_lossy(), baud)
        .timeout(timeout)
        .open_native()
        .map_err(|e| {
            let hint = match e.kind() {
                serialport::ErrorKind::Io(ErrorKind::PermissionDenied) => {
                    " (add the user to the dialout group, or check the udev rules)"
                }
                serialport::ErrorKind::NoDevice
                | serialport::ErrorKind::Io(ErrorKind::NotFound) => {
                    " (is the device plugged in? check the path)"
                }
                _ => "",
            };
            format!("{e}{hint}")
        })
}

fn sleep_unless_shutdown(total: Duration, shutdown: &AtomicBool) {
    let end = Instant::now() + total;
    while !shutdown.load(Ordering::Relaxed) {
        let left = end.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return;
        }
        std::thread::sleep(left.min(Duration::from_millis(20)));
    }
}
