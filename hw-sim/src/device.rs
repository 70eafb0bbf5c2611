//! The contract between an emulated device and the pty runner: a deterministic state machine
//! driven by simulated time (nanoseconds since the device was powered on).

use scan3d_edge::lidar::RawSample;

/// A piece of device output that is produced (and possibly corrupted) as a whole: a receipt,
/// a descriptor, an RPLidar node or capsule, a Sweep data block.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct WireUnit {
    /// The bytes as the device sends them.
    pub bytes: Vec<u8>,
    /// The samples these bytes encode, exactly as a correct decoder must report them
    /// (empty for non-sample output).
    pub samples: Vec<RawSample>,
}

/// An emulated serial device.
pub trait Device: Send {
    /// The line rate in bytes per simulated second (8N1: baud / 10).
    fn wire_bytes_per_sec(&self) -> f64;
    /// Bytes the host wrote, at simulated time `now_ns`.
    fn on_host_bytes(&mut self, now_ns: u64, bytes: &[u8]);
    /// A host opened the port (for the first time or again).
    fn on_connect(&mut self, now_ns: u64);
    /// The host closed the port.
    fn on_disconnect(&mut self, now_ns: u64);
    /// Append to `out` everything the device has produced up to `now_ns`, in order.
    fn poll_output(&mut self, now_ns: u64, out: &mut Vec<WireUnit>);
}
