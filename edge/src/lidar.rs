//! The contract every lidar driver fulfils, in the style of `quinn-proto`: a deterministic state
//! machine with no I/O and no clock of its own. The caller feeds it bytes and the time, and pulls
//! out bytes to write, serial-line actions, timer deadlines and events.
//!
//! ```text
//!            handle_input(now, bytes) ─┐        ┌─ poll_transmit() -> Transmit (write / flush / DTR)
//!  serial ──>  handle_timeout(now)   ──┼─ driver ┼─ poll_event()    -> LidarEvent (info, health, samples…)
//!                          start/stop ─┘        └─ poll_timeout()  -> next deadline (edge clock, ns)
//! ```
//!
//! All times are nanoseconds on the edge's [`crate::clock::Clock`].

use serde::Serialize;

/// One measurement exactly as the device reported it (no timestamp yet: see [`ArrivedSample`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RawSample {
    /// Beam angle in degrees in `[0, 360)`, in the device's own convention
    /// (RPLidar: clockwise seen from above; Sweep: counter-clockwise).
    pub angle_deg: f32,
    /// Range in metres; `0.0` means "no return".
    pub range_m: f32,
    /// RPLidar: the 6-bit quality (0–63; express samples report 47 or 0).
    /// Sweep: signal strength (0–255).
    pub quality: u8,
    /// The device flagged this sample as the first of a new 360° revolution.
    pub new_revolution: bool,
}

/// A decoded sample with the edge-clock time at which the read that completed it returned.
///
/// Arrival times are later than measurement times by the serial latency and jitter;
/// [`crate::timing`] turns them into per-sample measurement times.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ArrivedSample {
    /// The sample as decoded.
    pub sample: RawSample,
    /// Edge clock (ns) when the bytes that completed this sample were read.
    pub arrival_ns: u64,
}

/// Something the driver needs done on the serial line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Transmit {
    /// Write these bytes to the device.
    Write(Vec<u8>),
    /// Discard whatever the OS has buffered from the device (`tcflush(TCIFLUSH)`).
    FlushInput,
    /// Set the DTR line (RPLidar A1 motor control: `false` = spin, `true` = stop).
    /// A pty cannot carry DTR; the I/O shell logs the failure and carries on.
    SetDtr(bool),
}

/// Which device family a driver speaks to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum LidarKind {
    /// Slamtec RPLidar A1 or A2.
    Rplidar,
    /// Scanse Sweep.
    Sweep,
}

/// Identity of the connected device.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct DeviceInfo {
    /// `"A1"`, `"A2"` (RPLidar, from the model byte's major nibble) or `"Sweep"`.
    pub model: String,
    /// Firmware version as text, e.g. `"1.29"` (Sweep: from the IV receipt, e.g. `"1.1"`).
    pub firmware: String,
    /// Hardware revision as the device reports it.
    pub hardware: u32,
    /// Serial number as text: RPLidar as Slamtec's SDK prints it (16 bytes in hex, byte 0 first);
    /// Sweep as reported in the IV receipt.
    pub serial: String,
}

/// RPLidar health status (GET_HEALTH).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum HealthStatus {
    /// Status 0.
    Good,
    /// Status 1.
    Warning,
    /// Status 2 (protection stop).
    Error,
}

/// What a driver reports to its caller.
#[derive(Debug, Clone, PartialEq)]
pub enum LidarEvent {
    /// The device answered its identity query.
    Info(DeviceInfo),
    /// RPLidar GET_HEALTH answer.
    Health {
        /// Overall status.
        status: HealthStatus,
        /// Device error code (little-endian on the wire).
        error_code: u16,
    },
    /// The device is streaming samples; `sample_period_ns` is the nominal time between two
    /// samples in this mode (from GET_SAMPLERATE / the Sweep's sample-rate code).
    Scanning {
        /// Nominal sample period in nanoseconds.
        sample_period_ns: u64,
    },
    /// One decoded, validated sample.
    Sample(ArrivedSample),
    /// The sample just emitted was the last of its revolution: the driver has seen, in bytes
    /// it cannot decode yet, that the next sample starts a new one (an RPLidar express capsule
    /// whose start angle wrapped past 360°). Decided from the bytes alone, so a replay of the
    /// same bytes closes the same revolutions; the revolution can be closed now instead of
    /// when the next one's first sample is decoded, a capsule (8 ms) later.
    RevolutionComplete,
    /// A recoverable problem (retrying, resyncing, device busy…), for the log.
    Warning(String),
    /// The driver gave up: no answer, wrong device, or a device error. It stays idle until
    /// [`LidarDriver::start`] is called again.
    Failed(DriverError),
}

/// Why a driver gave up.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DriverError {
    /// The device did not answer `command` within the deadline, after retries.
    #[error(
        "no answer to {command} after {attempts} attempts (is this the right port and baud rate?)"
    )]
    NoAnswer {
        /// The command name, e.g. `"GET_INFO"` or `"ID"`.
        command: &'static str,
        /// How many times it was sent.
        attempts: u32,
    },
    /// The device answered, but not like the expected device.
    #[error("wrong device: {0}")]
    WrongDevice(String),
    /// The device reported an error it cannot recover from by itself.
    #[error("device error: {0}")]
    Device(String),
}

/// Counters a driver keeps about the byte stream, for summaries and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct DriverStats {
    /// Bytes received.
    pub bytes_in: u64,
    /// Bytes skipped while hunting for valid framing.
    pub bytes_discarded: u64,
    /// Frames (nodes, capsules, blocks, receipts) that failed a checksum or consistency check.
    pub frames_rejected: u64,
    /// Samples emitted as [`LidarEvent::Sample`].
    pub samples_emitted: u64,
    /// Times the parser lost framing and had to resynchronise.
    pub resyncs: u64,
}

/// A sans-I/O lidar protocol driver.
///
/// Drive it with [`crate::serial`] on real hardware, or directly in tests with byte slices.
pub trait LidarDriver {
    /// The device family this driver speaks to.
    fn kind(&self) -> LidarKind;
    /// (Re)start the connection handshake and then scanning, forgetting any parser state.
    /// Called after opening (or re-opening) the port.
    fn start(&mut self, now_ns: u64);
    /// Ask the device to stop streaming (STOP / DX) and go idle.
    fn stop(&mut self, now_ns: u64);
    /// Feed bytes read from the device at `now_ns`.
    fn handle_input(&mut self, now_ns: u64, bytes: &[u8]);
    /// Let timers fire; call when [`LidarDriver::poll_timeout`]'s deadline has passed.
    fn handle_timeout(&mut self, now_ns: u64);
    /// The next deadline at which [`LidarDriver::handle_timeout`] must be called, if any.
    fn poll_timeout(&self) -> Option<u64>;
    /// When (edge clock, ns) the bytes that complete the current revolution are expected, if
    /// the driver can tell: the I/O shell reads then even if its pace
    /// ([`crate::serial::SerialOptions::read_coalesce`]) would let the bytes gather longer, so
    /// a revolution leaves the edge as soon as it is complete without reading fast all the
    /// time. Only the time of reads depends on it, never what is decoded. `None` by default
    /// (the Sweep's reads keep their pace).
    fn poll_read_deadline(&self) -> Option<u64> {
        None
    }
    /// The next serial-line action, if any.
    fn poll_transmit(&mut self) -> Option<Transmit>;
    /// The next event, if any.
    fn poll_event(&mut self) -> Option<LidarEvent>;
    /// Byte-stream counters since construction.
    fn stats(&self) -> DriverStats;
}
