//! The thin I/O shell that runs a sans-I/O [`LidarDriver`] on a serial port.
//!
//! It owns the port and the loop: write what the driver wants written, read with a timeout no
//! longer than the driver's next deadline, feed bytes with their arrival time, fire timers.
//! Reads are paced ([`SerialOptions::read_coalesce`]), but a read the driver asks for
//! ([`LidarDriver::poll_read_deadline`]: the bytes completing a revolution are due) happens
//! then, not at the next paced read ([`next_read_at`]).
//! When the device vanishes (USB unplug, pty removed) it reports [`SerialEvent::Lost`], retries
//! opening with exponential backoff, and on success restarts the driver's handshake.

use std::io::{ErrorKind, Read, Write};
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
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
    /// Reads are paced: after a read that returned only a little data, the next one waits
    /// until this long (edge-clock time) has passed since it, so bytes arrive in batches as a
    /// USB adapter's latency timer (16 ms on an FTDI) delivers them anyway. At 10 ms a lidar
    /// streaming at full rate costs about 100 reads a second instead of one per few bytes;
    /// [`crate::timing`]'s lower-envelope fit takes the measurement times back from the
    /// least-delayed sample of each batch, and a sample reaches the static-scan controller at
    /// most this much later. A driver's read deadline ([`LidarDriver::poll_read_deadline`])
    /// brings a read forward. Shared: the owner may change it while the port runs.
    pub read_coalesce: ReadPace,
    /// Reopen the port after it disappears (daemon). When `false`, the first failure to open or
    /// a lost device ends [`run`] with an error (one-shot tools such as `probe`).
    pub reconnect: bool,
    /// First reconnect delay; doubled after each failure up to `max_backoff`.
    pub initial_backoff: Duration,
    /// Longest reconnect delay.
    pub max_backoff: Duration,
}

impl SerialOptions {
    /// Defaults for a device at `path` and `baud`: reads paced at 10 ms, reconnect with
    /// 100 ms … 2 s backoff.
    pub fn new(path: impl Into<PathBuf>, baud: u32) -> Self {
        Self {
            path: path.into(),
            baud,
            max_read_wait: Duration::from_millis(50),
            read_coalesce: ReadPace::new(Duration::from_millis(10)),
            reconnect: true,
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(2),
        }
    }
}

/// How long reads let bytes gather ([`SerialOptions::read_coalesce`]); clones share the value,
/// so a worker can read faster while something waits on the samples and slower otherwise.
#[derive(Debug, Clone, Default)]
pub struct ReadPace(Arc<AtomicU64>);

impl ReadPace {
    /// A pace of `pace` (edge-clock time).
    pub fn new(pace: Duration) -> Self {
        let shared = Self::default();
        shared.set(pace);
        shared
    }

    /// Changes the pace, from the next read on.
    pub fn set(&self, pace: Duration) {
        let ns = u64::try_from(pace.as_nanos()).unwrap_or(u64::MAX);
        self.0.store(ns, Ordering::Relaxed);
    }

    /// The pace, nanoseconds of edge-clock time.
    pub fn ns(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
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
    /// Every event of the bytes read so far was delivered; the shell waits for more input
    /// (a caller that batches events sends its batch now).
    Drained,
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
    let mut open_errors = RepeatLimit::default();
    loop {
        if shutdown.load(Ordering::Relaxed) {
            return Ok(());
        }
        let mut port = match open(&options.path, options.baud, options.max_read_wait) {
            Ok(port) => port,
            Err(reason) if options.reconnect => {
                if open_errors.should_log(&reason, Instant::now()) {
                    tracing::error!(path = %options.path.display(), "cannot open {}: {reason} (retrying)", options.path.display());
                } else {
                    tracing::debug!(path = %options.path.display(), %reason, "open failed; retrying");
                }
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
        open_errors = RepeatLimit::default();
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
    // Edge-clock time before which the next read waits (pacing; see `read_coalesce`).
    let mut next_read_ns: Option<u64> = None;
    loop {
        flush_transmits(driver, port, &mut dtr_warning)?;
        let mut delivered = false;
        while let Some(event) = driver.poll_event() {
            delivered = true;
            if on_event(SerialEvent::Driver(event)).is_break() {
                return Ok(());
            }
        }
        if delivered && on_event(SerialEvent::Drained).is_break() {
            return Ok(());
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
        if let Some(at) = next_read_at(next_read_ns, driver.poll_read_deadline()) {
            if at > now {
                // Pacing: let the bytes gather, but never past the driver's next deadline
                // (already in the future here) or the longest wait (shutdown).
                let until = deadline.map_or(at, |deadline| deadline.min(at));
                std::thread::sleep(clock.real_duration(until - now).min(options.max_read_wait));
                continue;
            }
            next_read_ns = None;
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
                let read_ns = clock.now_ns();
                driver.handle_input(read_ns, &buf[..n]);
                let coalesce_ns = options.read_coalesce.ns();
                if n < buf.len() / 4 && coalesce_ns > 0 {
                    next_read_ns = Some(read_ns.saturating_add(coalesce_ns));
                }
            }
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {}
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e.to_string()),
        }
    }
}

/// When the next read is due (edge clock, ns): the paced time `paced` (`None`: now), brought
/// forward to the driver's `read_deadline` when that is earlier. A read deadline never delays
/// a read, and without a pace pending it changes nothing: the read happens at once.
pub fn next_read_at(paced: Option<u64>, read_deadline: Option<u64>) -> Option<u64> {
    match (paced, read_deadline) {
        (Some(paced), Some(deadline)) => Some(paced.min(deadline)),
        (paced, _) => paced,
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

/// How often an unchanged open error is logged again while the device stays unavailable.
pub const OPEN_ERROR_REPEAT: Duration = Duration::from_secs(60);

/// Decides when a repeated error is worth a log line: the first, one whose text changed, and
/// then at most once per [`OPEN_ERROR_REPEAT`].
#[derive(Debug, Default)]
pub struct RepeatLimit {
    last: Option<(String, Instant)>,
}

impl RepeatLimit {
    /// Whether `message`, seen `now`, should be logged (and if so, remembers it).
    pub fn should_log(&mut self, message: &str, now: Instant) -> bool {
        let due = match &self.last {
            None => true,
            Some((last, at)) => last != message || now.duration_since(*at) >= OPEN_ERROR_REPEAT,
        };
        if due {
            self.last = Some((message.to_owned(), now));
        }
        due
    }
}

/// What the path of a serial device is, as far as opening it is concerned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PathKind {
    /// Nothing there (or a dangling udev link).
    Missing,
    /// A character device (a tty, or the pty the simulator links).
    CharDevice,
    /// Something else: a regular file, a directory, a socket (its description).
    Other(&'static str),
    /// It could not be examined (e.g. a directory without search permission).
    Unknown,
}

impl PathKind {
    /// Examines `path` (following links, as opening does).
    pub fn of(path: &Path) -> Self {
        use std::os::unix::fs::FileTypeExt;
        match std::fs::metadata(path) {
            Ok(meta) => {
                let t = meta.file_type();
                if t.is_char_device() {
                    Self::CharDevice
                } else if t.is_file() {
                    Self::Other("a regular file")
                } else if t.is_dir() {
                    Self::Other("a directory")
                } else if t.is_block_device() {
                    Self::Other("a block device")
                } else if t.is_socket() {
                    Self::Other("a socket")
                } else if t.is_fifo() {
                    Self::Other("a named pipe")
                } else {
                    Self::Other("not a character device")
                }
            }
            Err(e) if e.kind() == ErrorKind::NotFound => Self::Missing,
            Err(_) => Self::Unknown,
        }
    }
}

/// Why a serial port could not be opened, for the hint that goes with it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpenFailure {
    /// Not allowed: the user is not in the dialout group, or the udev rules give other modes.
    PermissionDenied,
    /// Another process has the port (EBUSY from TIOCEXCL, or serialport's flock).
    Busy,
    /// The device or its link is not there.
    Missing,
    /// The path is not a serial device (a regular file, a directory, or a character device that
    /// is no terminal: ENOTTY).
    NotSerial(&'static str),
    /// Anything else: the error's own text stands.
    Other,
}

impl OpenFailure {
    /// Classifies an open error from serialport (its kind and text) and what the path is.
    pub fn classify(kind: serialport::ErrorKind, description: &str, path: PathKind) -> Self {
        match path {
            PathKind::Missing => return Self::Missing,
            PathKind::Other(what) => return Self::NotSerial(what),
            PathKind::CharDevice | PathKind::Unknown => {}
        }
        let text = description.to_ascii_lowercase();
        match kind {
            serialport::ErrorKind::Io(ErrorKind::PermissionDenied) => Self::PermissionDenied,
            serialport::ErrorKind::Io(ErrorKind::NotFound) => Self::Missing,
            // serialport reports EBUSY and a held flock as NoDevice.
            serialport::ErrorKind::NoDevice if text.contains("lock") || text.contains("busy") => {
                Self::Busy
            }
            serialport::ErrorKind::NoDevice => Self::Missing,
            _ if text.contains("typewriter") || text.contains("inappropriate ioctl") => {
                Self::NotSerial("not a terminal")
            }
            _ if text.contains("busy") => Self::Busy,
            _ => Self::Other,
        }
    }

    /// The one-line reason for `path`, with the hint that helps.
    pub fn message(self, path: &Path, error: &str) -> String {
        let path = path.display();
        match self {
            Self::PermissionDenied => format!(
                "permission denied on {path}: add the user to the dialout group \
                 (`sudo usermod -aG dialout $USER`, then log in again) or check the udev rules \
                 (deploy/udev)"
            ),
            Self::Busy => {
                format!("{path} is in use by another process (find it with `fuser -v {path}`)")
            }
            Self::Missing => format!(
                "{path} does not exist: is the device plugged in? is its udev link there \
                 (`ls -l {path}`, deploy/udev)?"
            ),
            Self::NotSerial(what) => format!("{path} is not a serial device ({what})"),
            Self::Other => error.to_owned(),
        }
    }
}

/// Opens `path` raw 8N1 at `baud`, with a readable reason on failure ([`OpenFailure`]).
pub fn open(path: &Path, baud: u32, timeout: Duration) -> Result<TTYPort, String> {
    // A regular file "opens" and then fails its first ioctl; refuse it by what it is.
    let kind = PathKind::of(path);
    if let PathKind::Other(what) = kind {
        return Err(OpenFailure::NotSerial(what).message(path, ""));
    }
    serialport::new(path.to_string_lossy(), baud)
        .timeout(timeout)
        .open_native()
        .map_err(|e| {
            let kind = PathKind::of(path);
            OpenFailure::classify(e.kind(), &e.description, kind).message(path, &e.to_string())
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

#[cfg(test)]
mod tests {
    use super::*;

    fn classify(kind: serialport::ErrorKind, text: &str, path: PathKind) -> OpenFailure {
        OpenFailure::classify(kind, text, path)
    }

    #[test]
    fn open_errors_get_the_hint_that_fits_their_cause() {
        use serialport::ErrorKind as K;
        let dev = PathKind::CharDevice;
        assert_eq!(
            classify(K::Io(ErrorKind::PermissionDenied), "Permission denied", dev),
            OpenFailure::PermissionDenied
        );
        // EBUSY (TIOCEXCL held) and serialport's own flock both come as NoDevice.
        assert_eq!(
            classify(K::NoDevice, "Device or resource busy", dev),
            OpenFailure::Busy
        );
        assert_eq!(
            classify(
                K::NoDevice,
                "Unable to acquire exclusive lock on serial port",
                dev
            ),
            OpenFailure::Busy
        );
        assert_eq!(
            classify(K::NoDevice, "No such device", dev),
            OpenFailure::Missing
        );
        assert_eq!(
            classify(
                K::Io(ErrorKind::NotFound),
                "No such file or directory",
                PathKind::Missing
            ),
            OpenFailure::Missing
        );
        // ENOTTY, whatever libc calls it.
        assert_eq!(
            classify(K::Unknown, "Not a typewriter", dev),
            OpenFailure::NotSerial("not a terminal")
        );
        assert_eq!(
            classify(K::Unknown, "Inappropriate ioctl for device", dev),
            OpenFailure::NotSerial("not a terminal")
        );
        assert_eq!(
            classify(
                K::Unknown,
                "Not a typewriter",
                PathKind::Other("a regular file")
            ),
            OpenFailure::NotSerial("a regular file")
        );
        assert_eq!(classify(K::Unknown, "I/O error", dev), OpenFailure::Other);

        let path = Path::new("/dev/ttyUSB9");
        let busy = OpenFailure::Busy.message(path, "");
        assert!(busy.contains("in use by another process"), "{busy}");
        let denied = OpenFailure::PermissionDenied.message(path, "");
        assert!(
            denied.contains("dialout") && denied.contains("udev"),
            "{denied}"
        );
        let missing = OpenFailure::Missing.message(path, "");
        assert!(
            missing.contains("plugged in") && missing.contains("udev link"),
            "{missing}"
        );
    }

    #[test]
    fn opening_a_regular_file_or_a_missing_path_says_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("ttyFAKE");
        std::fs::write(&file, b"").unwrap();
        let e = open(&file, 115_200, Duration::from_millis(10)).unwrap_err();
        assert_eq!(
            e,
            format!("{} is not a serial device (a regular file)", file.display())
        );
        assert!(!e.contains("typewriter"));
        let missing = dir.path().join("ttyGONE");
        let e = open(&missing, 115_200, Duration::from_millis(10)).unwrap_err();
        assert!(
            e.contains("does not exist") && e.contains("plugged in"),
            "{e}"
        );
        assert_eq!(PathKind::of(dir.path()), PathKind::Other("a directory"));
    }

    #[test]
    fn a_read_deadline_brings_a_paced_read_forward_but_never_delays_one() {
        // Paced at 20 ms after a read at 100 ms: the revolution's bytes are due at 107 ms.
        assert_eq!(next_read_at(Some(120), Some(107)), Some(107));
        // Due later than the paced read (or already past): the earlier one wins.
        assert_eq!(next_read_at(Some(120), Some(150)), Some(120));
        assert_eq!(next_read_at(Some(120), Some(90)), Some(90));
        // No deadline (the Sweep, standard nodes): the pace alone.
        assert_eq!(next_read_at(Some(120), None), Some(120));
        // Nothing paced (a full buffer was just read): read at once either way.
        assert_eq!(next_read_at(None, Some(150)), None);
        assert_eq!(next_read_at(None, None), None);
    }

    #[test]
    fn an_unchanged_error_is_repeated_at_most_once_a_minute() {
        let mut limit = RepeatLimit::default();
        let t0 = Instant::now();
        assert!(limit.should_log("missing", t0));
        assert!(!limit.should_log("missing", t0 + Duration::from_secs(1)));
        assert!(!limit.should_log("missing", t0 + Duration::from_secs(59)));
        assert!(limit.should_log("missing", t0 + Duration::from_secs(60)));
        assert!(!limit.should_log("missing", t0 + Duration::from_secs(61)));
        // A different cause is news.
        assert!(limit.should_log("busy", t0 + Duration::from_secs(62)));
    }
}
