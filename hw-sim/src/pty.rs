//! Runs an emulated [`Device`] on a Linux pty behind a symlink, so that real clients open it like
//! `/dev/ttyUSB0` (research notes `lidar-protocols.md` §3.2).
//!
//! The pty rules this follows:
//! - the slave is put in raw mode (`cfmakeraw`) right after `openpty` and then closed: the runner
//!   keeps only the master, so `POLLHUP` on the master tells whether a client holds the slave;
//! - output is dropped while no client is connected (`POLLHUP`), and HUP → connected is a new
//!   connection ([`Device::on_connect`]); a client closing calls [`Device::on_disconnect`];
//! - output is paced at `wire_bytes_per_sec × time_scale` bytes per real second; when the
//!   backlog exceeds a bound, whole units are dropped (a UART overrun) and counted;
//! - the device's clock is the real time since spawn × `time_scale`;
//! - the symlink is created atomically (temporary link, then rename), so a client never sees a
//!   half-made or stale link.

use std::collections::VecDeque;
use std::io;
use std::os::fd::{AsFd, AsRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nix::errno::Errno;
use nix::fcntl::{FcntlArg, OFlag, fcntl};
use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
use nix::pty::openpty;
use nix::sys::termios::{SetArg, cfmakeraw, tcgetattr, tcsetattr};
use tracing::{debug, info, warn};

use crate::device::{Device, WireUnit};
use crate::faults::{FaultConfig, FaultInjector, SentLog, SentSample};

/// How the runner drives its device.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PtyOptions {
    /// Simulated seconds per real second (1.0 = real time). Also scales the wire rate.
    pub time_scale: f64,
    /// Faults injected into the device's output.
    pub faults: FaultConfig,
    /// Seed of the fault injector.
    pub seed: u64,
    /// The real instant of simulated time 0; `None` = when the device starts. Give a shared
    /// world clock's epoch when other emulators (e.g. the turntable under the Sweep) must see
    /// the same simulated time.
    pub epoch: Option<Instant>,
}

impl Default for PtyOptions {
    fn default() -> Self {
        Self {
            time_scale: 1.0,
            faults: FaultConfig::default(),
            seed: 0,
            epoch: None,
        }
    }
}

/// Why a pty runner could not start or carry out a request.
#[derive(Debug, thiserror::Error)]
pub enum PtyError {
    /// `time_scale` was zero, negative or not finite.
    #[error("time scale must be a positive number, got {0}")]
    BadTimeScale(f64),
    /// The kernel refused to allocate or configure a pty.
    #[error("cannot set up a pty: {0}")]
    Pty(#[from] nix::Error),
    /// The link path is taken by something that is not a symlink.
    #[error("{0} exists and is not a symlink; refusing to replace it")]
    NotASymlink(PathBuf),
    /// Creating the symlink failed.
    #[error("cannot create the link {path}: {source}")]
    Link {
        /// The requested link path.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The runner thread could not be started.
    #[error("cannot start the pty thread: {0}")]
    Thread(io::Error),
    /// The runner thread is gone (shut down, or its device panicked).
    #[error("the pty runner has stopped")]
    Stopped,
}

/// Byte counters of a runner.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PtyStats {
    /// Bytes written to the pty (after fault injection).
    pub bytes_written: u64,
    /// Bytes dropped because the backlog exceeded its bound (UART overrun).
    pub bytes_dropped_overrun: u64,
    /// Wire units (nodes, capsules, blocks) dropped whole by those overruns.
    pub units_dropped_overrun: u64,
    /// Bytes dropped because no client held the port.
    pub bytes_dropped_no_client: u64,
    /// Bytes received from clients.
    pub bytes_read: u64,
    /// Client connections seen (HUP → connected transitions).
    pub connects: u64,
}

#[derive(Debug, Default)]
struct SharedStats {
    bytes_written: AtomicU64,
    bytes_dropped_overrun: AtomicU64,
    units_dropped_overrun: AtomicU64,
    bytes_dropped_no_client: AtomicU64,
    bytes_read: AtomicU64,
    connects: AtomicU64,
}

impl SharedStats {
    fn snapshot(&self) -> PtyStats {
        PtyStats {
            bytes_written: self.bytes_written.load(Ordering::Relaxed),
            bytes_dropped_overrun: self.bytes_dropped_overrun.load(Ordering::Relaxed),
            units_dropped_overrun: self.units_dropped_overrun.load(Ordering::Relaxed),
            bytes_dropped_no_client: self.bytes_dropped_no_client.load(Ordering::Relaxed),
            bytes_read: self.bytes_read.load(Ordering::Relaxed),
            connects: self.connects.load(Ordering::Relaxed),
        }
    }
}

fn add(counter: &AtomicU64, n: usize) {
    counter.fetch_add(n as u64, Ordering::Relaxed);
}

/// Requests from the handle to the runner thread.
enum Command {
    Unplug(Sender<()>),
    Replug(Sender<Result<PathBuf, PtyError>>),
    Shutdown,
}

/// A pty master with the name of its slave.
struct Pty {
    master: OwnedFd,
    slave_path: PathBuf,
}

impl Pty {
    /// Allocates a pty, puts the slave in raw mode, remembers its path and closes it.
    fn open() -> Result<Self, PtyError> {
        let pair = openpty(None, None)?;
        let mut termios = tcgetattr(&pair.slave)?;
        cfmakeraw(&mut termios);
        tcsetattr(&pair.slave, SetArg::TCSANOW, &termios)?;
        let slave_path = nix::unistd::ttyname(&pair.slave)?;
        // Closing the slave is what makes POLLHUP on the master mean "no client".
        drop(pair.slave);
        let flags = OFlag::from_bits_truncate(fcntl(&pair.master, FcntlArg::F_GETFL)?);
        fcntl(&pair.master, FcntlArg::F_SETFL(flags | OFlag::O_NONBLOCK))?;
        Ok(Self {
            master: pair.master,
            slave_path,
        })
    }

    /// The client's baud rate as set on the slave (`TCGETS2` on the master), if readable.
    fn client_baud(&self) -> Option<u32> {
        nix::ioctl_read_bad!(tcgets2, nix::libc::TCGETS2, nix::libc::termios2);
        // SAFETY: an all-zero termios2 is a valid value of this plain C struct.
        let mut t: nix::libc::termios2 = unsafe { std::mem::zeroed() };
        // SAFETY: TCGETS2 writes one termios2 through the pointer, which points to a live value
        // of that type; the fd is our open master.
        unsafe { tcgets2(self.master.as_raw_fd(), &mut t) }.ok()?;
        Some(t.c_ospeed)
    }
}

/// Points `link` at `target`, atomically replacing an older symlink there.
fn create_link(link: &Path, target: &Path) -> Result<(), PtyError> {
    let link_err = |source| PtyError::Link {
        path: link.to_path_buf(),
        source,
    };
    if let Ok(meta) = std::fs::symlink_metadata(link)
        && !meta.file_type().is_symlink()
    {
        return Err(PtyError::NotASymlink(link.to_path_buf()));
    }
    let name = link
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = link.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    match std::fs::remove_file(&tmp) {
        Ok(()) => {}
        Err(e) if e.kind() == io::ErrorKind::NotFound => {}
        Err(e) => return Err(link_err(e)),
    }
    std::os::unix::fs::symlink(target, &tmp).map_err(link_err)?;
    std::fs::rename(&tmp, link).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        link_err(e)
    })
}

/// Removes `link` if it still points at `target` (someone else may have replaced it).
fn remove_link(link: &Path, target: &Path) {
    if std::fs::read_link(link).is_ok_and(|t| t == target)
        && let Err(e) = std::fs::remove_file(link)
    {
        warn!(link = %link.display(), "cannot remove the link: {e}");
    }
}

/// A unit waiting to be written: its (corrupted) bytes and the samples to log once it is out.
struct Pending {
    bytes: Vec<u8>,
    written: usize,
    samples: Vec<SentSample>,
}

/// The runner: one device on one pty (re-created on replug), driven by one thread.
pub struct PtyDevice {
    link: PathBuf,
    device: Box<dyn Device>,
    pty: Option<Pty>,
    connected: bool,
    baud_checked: bool,
    injector: FaultInjector,
    log: SentLog,
    stats: Arc<SharedStats>,
    slave_path: Arc<Mutex<Option<PathBuf>>>,
    time_scale: f64,
    start: Instant,
    last_tick: Instant,
    budget: f64,
    backlog: VecDeque<Pending>,
    backlog_bytes: usize,
    units: Vec<WireUnit>,
}

impl PtyDevice {
    /// Allocates a pty, links `link` to it and starts a thread running `device` on it.
    /// Returns once the link exists, so a client can open it right away.
    pub fn spawn(
        link: PathBuf,
        device: Box<dyn Device>,
        options: PtyOptions,
    ) -> Result<PtyHandle, PtyError> {
        if !(options.time_scale.is_finite() && options.time_scale > 0.0) {
            return Err(PtyError::BadTimeScale(options.time_scale));
        }
        let pty = Pty::open()?;
        create_link(&link, &pty.slave_path)?;
        info!(link = %link.display(), slave = %pty.slave_path.display(), "device plugged in");
        let slave_path = Arc::new(Mutex::new(Some(pty.slave_path.clone())));
        let stats = Arc::new(SharedStats::default());
        let log = SentLog::new();
        let now = Instant::now();
        let runner = Self {
            link: link.clone(),
            device,
            pty: Some(pty),
            connected: false,
            baud_checked: false,
            injector: FaultInjector::new(options.faults, options.seed),
            log: log.clone(),
            stats: Arc::clone(&stats),
            slave_path: Arc::clone(&slave_path),
            time_scale: options.time_scale,
            start: options.epoch.unwrap_or(now),
            last_tick: now,
            budget: 0.0,
            backlog: VecDeque::new(),
            backlog_bytes: 0,
            units: Vec::new(),
        };
        let (tx, rx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("pty-device".into())
            .spawn(move || runner.run(rx));
        let thread = match thread {
            Ok(t) => t,
            Err(e) => {
                if let Some(p) = lock(&slave_path).as_ref() {
                    remove_link(&link, p);
                }
                return Err(PtyError::Thread(e));
            }
        };
        Ok(PtyHandle {
            link,
            commands: tx,
            thread: Some(thread),
            stats,
            log,
            slave_path,
        })
    }

    /// Wire bytes per real second.
    fn rate(&self) -> f64 {
        self.device.wire_bytes_per_sec() * self.time_scale
    }

    /// Backlog bound: a quarter second of wire time, at least 1 KiB.
    fn backlog_limit(&self) -> usize {
        (self.rate() * 0.25).max(1024.0) as usize
    }

    fn sim_now_ns(&self, now: Instant) -> u64 {
        (now.duration_since(self.start).as_secs_f64() * self.time_scale * 1e9) as u64
    }

    fn run(mut self, commands: Receiver<Command>) {
        loop {
            match commands.try_recv() {
                Ok(Command::Shutdown) | Err(mpsc::TryRecvError::Disconnected) => break,
                Ok(Command::Unplug(reply)) => {
                    self.unplug();
                    let _ = reply.send(());
                }
                Ok(Command::Replug(reply)) => {
                    let _ = reply.send(self.replug());
                }
                Err(mpsc::TryRecvError::Empty) => {}
            }
            self.step();
        }
        self.unplug();
    }

    /// One iteration: notice (dis)connections, read host bytes, run the device, write paced output.
    fn step(&mut self) {
        let Some(pty) = &self.pty else {
            // Unplugged: the device keeps running, its output goes nowhere.
            std::thread::sleep(Duration::from_millis(2));
            self.tick_device(self.sim_now_ns(Instant::now()));
            return;
        };
        let mut fds = [PollFd::new(pty.master.as_fd(), PollFlags::POLLIN)];
        let timeout = if self.backlog.is_empty() { 2u16 } else { 1u16 };
        let revents = match poll(&mut fds, PollTimeout::from(timeout)) {
            Ok(_) => fds[0].revents().unwrap_or(PollFlags::empty()),
            Err(Errno::EINTR) => PollFlags::empty(),
            Err(e) => {
                warn!("poll on the pty failed: {e}");
                PollFlags::POLLHUP
            }
        };
        let hup = revents.contains(PollFlags::POLLHUP);
        if hup {
            if self.connected {
                self.disconnect();
            }
            // POLLHUP makes poll return at once: sleep so that this loop does not spin.
            std::thread::sleep(Duration::from_millis(2));
        } else if !self.connected {
            self.connect();
        }
        if self.connected && revents.contains(PollFlags::POLLIN) {
            self.read_host();
        }
        self.tick_device(self.sim_now_ns(Instant::now()));
        if self.connected {
            self.write_paced();
        }
    }

    fn connect(&mut self) {
        self.connected = true;
        self.baud_checked = false;
        self.budget = 0.0;
        self.stats.connects.fetch_add(1, Ordering::Relaxed);
        let now = self.sim_now_ns(Instant::now());
        info!(link = %self.link.display(), "client connected");
        self.device.on_connect(now);
    }

    fn disconnect(&mut self) {
        self.connected = false;
        add(&self.stats.bytes_dropped_no_client, self.backlog_bytes);
        self.backlog.clear();
        self.backlog_bytes = 0;
        let now = self.sim_now_ns(Instant::now());
        info!(link = %self.link.display(), "client disconnected");
        self.device.on_disconnect(now);
    }

    fn read_host(&mut self) {
        let mut buf = [0u8; 1024];
        loop {
            let Some(pty) = &self.pty else { return };
            match nix::unistd::read(&pty.master, &mut buf) {
                Ok(0) | Err(Errno::EAGAIN) => return,
                Ok(n) => {
                    if !self.baud_checked {
                        self.baud_checked = true;
                        self.check_baud();
                    }
                    add(&self.stats.bytes_read, n);
                    let now = self.sim_now_ns(Instant::now());
                    // Bring the device up to date first, so its output stays in time order.
                    self.tick_device(now);
                    self.device
                        .on_host_bytes(now, buf.get(..n).unwrap_or_default());
                }
                Err(Errno::EINTR) => {}
                Err(e) => {
                    debug!("read from the pty: {e}");
                    self.disconnect();
                    return;
                }
            }
        }
    }

    /// Logs a mismatch between the client's baud rate and the device's.
    fn check_baud(&self) {
        let expected = (self.device.wire_bytes_per_sec() * 10.0).round() as u32;
        match self.pty.as_ref().and_then(Pty::client_baud) {
            Some(baud) if baud != expected => {
                warn!(
                    client_baud = baud,
                    device_baud = expected,
                    "client baud rate mismatch"
                );
            }
            Some(baud) => debug!(baud, "client baud rate"),
            None => debug!("cannot read the client's baud rate"),
        }
    }

    /// Runs the device up to now and queues (or drops) what it produced.
    fn tick_device(&mut self, now: u64) {
        let mut units = std::mem::take(&mut self.units);
        self.device.poll_output(now, &mut units);
        let limit = self.backlog_limit();
        for unit in units.drain(..) {
            if !self.connected {
                add(&self.stats.bytes_dropped_no_client, unit.bytes.len());
                continue;
            }
            let out = self.injector.inject(&unit);
            if self.backlog_bytes + out.bytes.len() > limit {
                add(&self.stats.bytes_dropped_overrun, out.bytes.len());
                add(&self.stats.units_dropped_overrun, 1);
                continue;
            }
            self.backlog_bytes += out.bytes.len();
            self.backlog.push_back(Pending {
                bytes: out.bytes,
                written: 0,
                samples: out.samples,
            });
        }
        self.units = units;
    }

    /// Writes as many backlog bytes as the wire rate allows since the last call.
    fn write_paced(&mut self) {
        let now = Instant::now();
        let dt = now.duration_since(self.last_tick).as_secs_f64();
        self.last_tick = now;
        let rate = self.rate();
        // Allow a burst of a few milliseconds of wire time, no more.
        self.budget = (self.budget + dt * rate).min((rate * 0.004).max(16.0));
        while self.budget >= 1.0 {
            let Some(pty) = &self.pty else { return };
            let Some(front) = self.backlog.front_mut() else {
                break;
            };
            let rest = front.bytes.get(front.written..).unwrap_or_default();
            let n = rest.len().min(self.budget as usize);
            if n > 0 {
                match nix::unistd::write(&pty.master, rest.get(..n).unwrap_or_default()) {
                    Ok(k) => {
                        front.written += k;
                        self.backlog_bytes = self.backlog_bytes.saturating_sub(k);
                        self.budget -= k as f64;
                        add(&self.stats.bytes_written, k);
                    }
                    Err(Errno::EAGAIN) | Err(Errno::EINTR) => break,
                    Err(e) => {
                        debug!("write to the pty: {e}");
                        self.disconnect();
                        return;
                    }
                }
            }
            if front.written >= front.bytes.len() {
                self.log.record(&front.samples);
                self.backlog.pop_front();
            }
        }
    }

    fn unplug(&mut self) {
        if self.connected {
            self.disconnect();
        }
        if let Some(pty) = self.pty.take() {
            remove_link(&self.link, &pty.slave_path);
            *lock(&self.slave_path) = None;
            info!(link = %self.link.display(), "device unplugged");
            // Dropping the master hangs up any client still holding the slave.
            drop(pty);
        }
    }

    fn replug(&mut self) -> Result<PathBuf, PtyError> {
        self.unplug();
        let pty = Pty::open()?;
        create_link(&self.link, &pty.slave_path)?;
        let path = pty.slave_path.clone();
        info!(link = %self.link.display(), slave = %path.display(), "device plugged in again");
        *lock(&self.slave_path) = Some(path.clone());
        self.pty = Some(pty);
        Ok(path)
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Controls a running [`PtyDevice`]. Dropping it stops the thread and removes the link.
pub struct PtyHandle {
    link: PathBuf,
    commands: Sender<Command>,
    thread: Option<JoinHandle<()>>,
    stats: Arc<SharedStats>,
    log: SentLog,
    slave_path: Arc<Mutex<Option<PathBuf>>>,
}

impl PtyHandle {
    /// The symlink clients open.
    pub fn link(&self) -> &Path {
        &self.link
    }

    /// The current pty slave (`/dev/pts/N`), or `None` while unplugged.
    pub fn slave_path(&self) -> Option<PathBuf> {
        lock(&self.slave_path).clone()
    }

    /// The log of every sample written to the pty.
    pub fn sent_log(&self) -> SentLog {
        self.log.clone()
    }

    /// Byte counters so far.
    pub fn stats(&self) -> PtyStats {
        self.stats.snapshot()
    }

    /// The device vanishes: the link is removed and the pty closed, so an open client gets a
    /// hang-up. The device keeps running (and keeps its state) until [`PtyHandle::replug`].
    pub fn unplug(&self) -> Result<(), PtyError> {
        let (tx, rx) = mpsc::channel();
        self.commands
            .send(Command::Unplug(tx))
            .map_err(|_| PtyError::Stopped)?;
        wait_reply(&rx)
    }

    /// The device comes back on a new pty behind the same link; returns the new slave path.
    pub fn replug(&self) -> Result<PathBuf, PtyError> {
        let (tx, rx) = mpsc::channel();
        self.commands
            .send(Command::Replug(tx))
            .map_err(|_| PtyError::Stopped)?;
        wait_reply(&rx)?
    }

    /// Stops the thread and removes the link.
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        let _ = self.commands.send(Command::Shutdown);
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            warn!(link = %self.link.display(), "the pty thread panicked");
            if let Some(p) = self.slave_path() {
                remove_link(&self.link, &p);
            }
        }
    }
}

fn wait_reply<T>(rx: &Receiver<T>) -> Result<T, PtyError> {
    match rx.recv_timeout(Duration::from_secs(5)) {
        Ok(v) => Ok(v),
        Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => Err(PtyError::Stopped),
    }
}

impl Drop for PtyHandle {
    fn drop(&mut self) {
        self.stop();
    }
}

impl std::fmt::Debug for PtyHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PtyHandle")
            .field("link", &self.link)
            .field("slave_path", &self.slave_path())
            .field("stats", &self.stats())
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Write};

    use scan3d_edge::lidar::RawSample;

    use super::*;

    /// Answers "ping" with "pong", "burst" with 36 units of 64 bytes and "flood" with 10 units of
    /// 1000 bytes (one sample per unit), and says "HELLO" once at power-on, before any client can
    /// be there.
    struct TestDevice {
        events: Arc<Mutex<Vec<&'static str>>>,
        out: Vec<WireUnit>,
        greeted: bool,
    }

    impl Device for TestDevice {
        fn wire_bytes_per_sec(&self) -> f64 {
            11_520.0
        }
        fn on_host_bytes(&mut self, _now_ns: u64, bytes: &[u8]) {
            if bytes == b"ping" {
                self.out.push(WireUnit {
                    bytes: b"pong".to_vec(),
                    samples: vec![],
                });
            } else if bytes == b"burst" {
                for i in 0..36u8 {
                    let sample = RawSample {
                        angle_deg: f32::from(i),
                        range_m: 1.0,
                        quality: 10,
                        new_revolution: false,
                    };
                    self.out.push(WireUnit {
                        bytes: vec![i; 64],
                        samples: vec![sample],
                    });
                }
            } else if bytes == b"flood" {
                // 10 000 bytes at once: more than the 2880-byte backlog bound (0.25 s of wire).
                for i in 0..10u8 {
                    let sample = RawSample {
                        angle_deg: f32::from(i),
                        range_m: 2.0,
                        quality: 10,
                        new_revolution: false,
                    };
                    self.out.push(WireUnit {
                        bytes: vec![i; 1000],
                        samples: vec![sample],
                    });
                }
            }
        }
        fn on_connect(&mut self, _now_ns: u64) {
            lock(&self.events).push("connect");
        }
        fn on_disconnect(&mut self, _now_ns: u64) {
            lock(&self.events).push("disconnect");
        }
        fn poll_output(&mut self, _now_ns: u64, out: &mut Vec<WireUnit>) {
            if !self.greeted {
                self.greeted = true;
                out.push(WireUnit {
                    bytes: b"HELLO".to_vec(),
                    samples: vec![],
                });
            }
            out.append(&mut self.out);
        }
    }

    fn spawn(name: &str) -> (PtyHandle, Arc<Mutex<Vec<&'static str>>>, PathBuf) {
        let dir = std::env::temp_dir().join(format!("scan3d-pty-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let link = dir.join("ttyTEST");
        let events = Arc::new(Mutex::new(Vec::new()));
        let dev = TestDevice {
            events: Arc::clone(&events),
            out: vec![],
            greeted: false,
        };
        let handle = PtyDevice::spawn(link.clone(), Box::new(dev), PtyOptions::default()).unwrap();
        // The power-on "HELLO" must have gone nowhere before a client opens the port.
        assert!(
            wait_for(|| handle.stats().bytes_dropped_no_client >= 5),
            "HELLO not dropped"
        );
        (handle, events, dir)
    }

    fn open(path: &Path) -> Box<dyn serialport::SerialPort> {
        serialport::new(path.to_string_lossy(), 115_200)
            .timeout(Duration::from_secs(2))
            .open()
            .unwrap()
    }

    fn read_n(port: &mut dyn serialport::SerialPort, n: usize) -> Vec<u8> {
        let mut got = vec![0u8; n];
        port.read_exact(&mut got).unwrap();
        got
    }

    /// Whether `cond` holds within a generous deadline (a busy machine only makes it slower).
    fn wait_for(mut cond: impl FnMut() -> bool) -> bool {
        let deadline = Instant::now() + Duration::from_secs(30);
        while Instant::now() < deadline {
            if cond() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        false
    }

    #[test]
    fn client_exchanges_bytes_and_misses_output_from_before_it_connected() {
        let (handle, events, dir) = spawn("exchange");
        assert_eq!(std::fs::read_link(handle.link()).ok(), handle.slave_path());

        let mut port = open(handle.link());
        port.write_all(b"ping").unwrap();
        assert_eq!(read_n(port.as_mut(), 4), b"pong");
        assert_eq!(handle.stats().connects, 1);
        assert_eq!(handle.stats().bytes_read, 4);
        drop(port);
        assert!(wait_for(
            || lock(&events).as_slice() == ["connect", "disconnect"]
        ));

        let link = handle.link().to_path_buf();
        handle.shutdown();
        assert!(
            std::fs::symlink_metadata(&link).is_err(),
            "link left behind"
        );
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn unplug_hangs_up_the_client_and_replug_brings_the_device_back() {
        let (handle, events, dir) = spawn("replug");
        let mut port = open(handle.link());
        port.write_all(b"ping").unwrap();
        assert_eq!(read_n(port.as_mut(), 4), b"pong");

        handle.unplug().unwrap();
        assert!(
            std::fs::symlink_metadata(handle.link()).is_err(),
            "link still there"
        );
        assert_eq!(handle.slave_path(), None);
        let mut buf = [0u8; 4];
        let err = port.read(&mut buf).unwrap_err();
        assert_ne!(
            err.kind(),
            io::ErrorKind::TimedOut,
            "read should fail, not time out"
        );
        drop(port);

        let slave = handle.replug().unwrap();
        assert_eq!(std::fs::read_link(handle.link()).unwrap(), slave);
        let mut port = open(handle.link());
        port.write_all(b"ping").unwrap();
        assert_eq!(read_n(port.as_mut(), 4), b"pong");
        assert_eq!(
            lock(&events).as_slice(),
            ["connect", "disconnect", "connect"]
        );
        drop(port);
        drop(handle);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn output_is_paced_at_the_wire_rate_and_logged_when_sent() {
        let (handle, _events, dir) = spawn("pacing");
        let mut port = open(handle.link());
        let t0 = Instant::now();
        port.write_all(b"burst").unwrap();
        let got = read_n(port.as_mut(), 36 * 64);
        let elapsed = t0.elapsed().as_secs_f64();
        // 2304 bytes at 11 520 B/s take 0.2 s; allow slack for the initial burst allowance.
        assert!(elapsed >= 0.18, "2304 bytes arrived in {elapsed} s");
        for (i, chunk) in got.chunks(64).enumerate() {
            assert!(
                chunk.iter().all(|&b| usize::from(b) == i),
                "unit {i} mangled"
            );
        }
        // The runner records a unit right after its last byte was written: give it a moment.
        assert!(wait_for(|| handle.sent_log().len() == 36));
        let log = handle.sent_log().snapshot();
        assert!(
            log.iter()
                .enumerate()
                .all(|(i, s)| s.sample.angle_deg == i as f32 && !s.touched)
        );
        assert_eq!(handle.stats().bytes_written, 36 * 64);
        drop(port);
        drop(handle);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn overrun_drops_whole_units_and_counts_them() {
        let (handle, _events, dir) = spawn("overrun");
        let mut port = open(handle.link());
        port.write_all(b"flood").unwrap();
        // Units 0 and 1 fit in the bound (2000 ≤ 2880 bytes); the other eight are dropped.
        let got = read_n(port.as_mut(), 2000);
        assert!(got[..1000].iter().all(|&b| b == 0) && got[1000..].iter().all(|&b| b == 1));
        assert!(wait_for(|| handle.sent_log().len() == 2));
        std::thread::sleep(Duration::from_millis(100));
        let stats = handle.stats();
        assert_eq!(
            (stats.bytes_written, stats.bytes_dropped_overrun),
            (2000, 8000)
        );
        assert_eq!(handle.sent_log().len(), 2);
        drop(port);
        drop(handle);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn refuses_bad_time_scale_and_non_symlink_paths() {
        let dir = std::env::temp_dir().join(format!("scan3d-pty-{}-refuse", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("regular");
        std::fs::write(&file, b"keep me").unwrap();
        let dev = || -> Box<dyn Device> {
            Box::new(TestDevice {
                events: Arc::default(),
                out: vec![],
                greeted: true,
            })
        };
        let bad = PtyOptions {
            time_scale: 0.0,
            ..PtyOptions::default()
        };
        assert!(matches!(
            PtyDevice::spawn(dir.join("x"), dev(), bad),
            Err(PtyError::BadTimeScale(_))
        ));
        assert!(matches!(
            PtyDevice::spawn(file.clone(), dev(), PtyOptions::default()),
            Err(PtyError::NotASymlink(_))
        ));
        assert_eq!(std::fs::read(&file).unwrap(), b"keep me");
        let _ = std::fs::remove_dir_all(dir);
    }
}
