//! A simulated I2C bus: register-level device emulators behind [`embedded_hal::i2c::I2c`].
//!
//! On the Pi the IMU (MPU-9250 at 0x68, AK8963 at 0x0C) and the motor HAT (PCA9685 at 0x60)
//! share one bus. Here every emulator implements the small [`I2cDevice`] trait and an
//! [`I2cBus`] dispatches each transaction by address, so drivers run unchanged against any mix
//! of emulated chips. The emulators stay pure: they see bytes and a time pushed in by the bus
//! (from a [`Clock`], e.g. [`SimClock`]), never a clock of their own.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use embedded_hal::delay::DelayNs;
use embedded_hal::i2c::{
    ErrorKind, ErrorType, I2c, NoAcknowledgeSource, Operation, SevenBitAddress,
};
use scan3d_edge::clock::{Clock, SharedClock};

/// A device did not acknowledge a data byte (it answered its address but refused the transfer).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("data not acknowledged")]
pub struct Nack;

/// An emulated I2C target (slave) device.
///
/// A transaction reaches a device as a sequence of transfers: each run of adjacent write
/// operations arrives as one [`I2cDevice::write`] (the bytes are sent without a repeated
/// start in between, as embedded-hal specifies), each read operation as one
/// [`I2cDevice::read`]. The end of a write transfer is the I2C STOP or repeated START.
pub trait I2cDevice: Send {
    /// The device's primary 7-bit address.
    fn address(&self) -> u8;

    /// Whether the device acknowledges `address` (its own, or a broadcast such as the general
    /// call 0x00 or a PCA9685 ALLCALL address).
    fn responds_to(&self, address: u8) -> bool {
        address == self.address()
    }

    /// A write transfer to `address`; `bytes` is everything the host sent after the address
    /// (usually a register pointer followed by data). An empty slice is an address probe.
    fn write(&mut self, address: u8, bytes: &[u8]) -> Result<(), Nack>;

    /// A read transfer from `address` filling `buf` (from the device's register pointer).
    fn read(&mut self, address: u8, buf: &mut [u8]) -> Result<(), Nack>;

    /// Simulated time in nanoseconds, pushed in before each transaction (never decreases).
    /// Devices without timing ignore it.
    fn set_time_ns(&mut self, _now_ns: u64) {}
}

/// An emulator shared between the bus and the code that inspects it.
pub type SharedDevice = Arc<Mutex<dyn I2cDevice>>;

/// Why a simulated transaction failed, as the host controller would see it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum BusError {
    /// No device acknowledged this 7-bit address.
    #[error("no device acknowledged address {0:#04x}")]
    AddressNack(u8),
    /// The device at this address refused a data byte.
    #[error("device at {0:#04x} did not acknowledge data")]
    DataNack(u8),
}

impl embedded_hal::i2c::Error for BusError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::AddressNack(_) => ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address),
            Self::DataNack(_) => ErrorKind::NoAcknowledge(NoAcknowledgeSource::Data),
        }
    }
}

/// Runs one embedded-hal transaction against the devices that answered `address`.
///
/// Every responder receives the writes (broadcast addresses reach several chips); reads are
/// answered by the first responder.
pub fn run_transaction<D: I2cDevice + ?Sized>(
    responders: &mut [&mut D],
    address: u8,
    operations: &mut [Operation<'_>],
) -> Result<(), BusError> {
    if responders.is_empty() {
        return Err(BusError::AddressNack(address));
    }
    if operations.is_empty() {
        // An address-only probe: acknowledged, nothing transferred.
        return Ok(());
    }
    let mut pending_write: Vec<u8> = Vec::new();
    let mut in_write = false;
    for operation in operations.iter_mut() {
        match operation {
            Operation::Write(bytes) => {
                pending_write.extend_from_slice(bytes);
                in_write = true;
            }
            Operation::Read(buf) => {
                if in_write {
                    flush_write(responders, address, &pending_write)?;
                    pending_write.clear();
                    in_write = false;
                }
                if let Some(first) = responders.first_mut() {
                    first
                        .read(address, buf)
                        .map_err(|Nack| BusError::DataNack(address))?;
                }
            }
        }
    }
    if in_write {
        flush_write(responders, address, &pending_write)?;
    }
    Ok(())
}

fn flush_write<D: I2cDevice + ?Sized>(
    responders: &mut [&mut D],
    address: u8,
    bytes: &[u8],
) -> Result<(), BusError> {
    for device in responders.iter_mut() {
        device
            .write(address, bytes)
            .map_err(|Nack| BusError::DataNack(address))?;
    }
    Ok(())
}

/// Traffic counters of a simulated bus (for "I2C transactions per second").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BusStats {
    /// Transactions attempted (one START … STOP each).
    pub transactions: u64,
    /// Data bytes written by the host.
    pub bytes_written: u64,
    /// Data bytes read by the host.
    pub bytes_read: u64,
    /// Transactions that ended in a NACK.
    pub nacks: u64,
}

struct BusInner {
    devices: Vec<SharedDevice>,
    clock: Option<SharedClock>,
    stats: BusStats,
}

/// A simulated I2C bus with several device emulators, implementing [`I2c`].
///
/// Cloning gives another handle to the same bus (like `embedded-hal-bus` sharing one physical
/// bus between drivers); each transaction is atomic.
#[derive(Clone)]
pub struct I2cBus {
    inner: Arc<Mutex<BusInner>>,
}

impl Default for I2cBus {
    fn default() -> Self {
        Self::new()
    }
}

impl std::fmt::Debug for I2cBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let inner = lock(&self.inner);
        f.debug_struct("I2cBus")
            .field("devices", &inner.devices.len())
            .field("stats", &inner.stats)
            .finish()
    }
}

impl I2cBus {
    /// An empty bus without a clock: devices keep whatever time they were given.
    pub fn new() -> Self {
        Self {
            inner: Arc::new(Mutex::new(BusInner {
                devices: Vec::new(),
                clock: None,
                stats: BusStats::default(),
            })),
        }
    }

    /// An empty bus that pushes `clock`'s time into every device before each transaction.
    pub fn with_clock(clock: SharedClock) -> Self {
        let bus = Self::new();
        lock(&bus.inner).clock = Some(clock);
        bus
    }

    /// Connects a device. Attaching the same device twice has no effect.
    pub fn attach(&self, device: SharedDevice) {
        let mut inner = lock(&self.inner);
        let new = Arc::as_ptr(&device);
        if !inner
            .devices
            .iter()
            .any(|d| std::ptr::addr_eq(Arc::as_ptr(d), new))
        {
            inner.devices.push(device);
        }
    }

    /// Traffic so far.
    pub fn stats(&self) -> BusStats {
        lock(&self.inner).stats
    }
}

impl ErrorType for I2cBus {
    type Error = BusError;
}

impl I2c<SevenBitAddress> for I2cBus {
    fn transaction(
        &mut self,
        address: u8,
        operations: &mut [Operation<'_>],
    ) -> Result<(), Self::Error> {
        let mut inner = lock(&self.inner);
        let now = inner.clock.as_ref().map(|c| c.now_ns());
        let result = {
            let mut guards: Vec<MutexGuard<'_, dyn I2cDevice>> = Vec::new();
            for device in &inner.devices {
                let mut guard = lock(device);
                if let Some(now) = now {
                    guard.set_time_ns(now);
                }
                if guard.responds_to(address) {
                    guards.push(guard);
                }
            }
            let mut responders: Vec<&mut dyn I2cDevice> =
                guards.iter_mut().map(|g| &mut **g).collect();
            run_transaction(&mut responders, address, operations)
        };
        let (written, read) = operation_sizes(operations);
        let stats = &mut inner.stats;
        stats.transactions += 1;
        stats.bytes_written += written;
        stats.bytes_read += read;
        if result.is_err() {
            stats.nacks += 1;
        }
        result
    }
}

fn operation_sizes(operations: &[Operation<'_>]) -> (u64, u64) {
    operations
        .iter()
        .fold((0, 0), |(w, r), operation| match operation {
            Operation::Write(bytes) => (w + bytes.len() as u64, r),
            Operation::Read(buf) => (w, r + buf.len() as u64),
        })
}

/// Locks a mutex, ignoring poisoning (an emulator's state stays usable after a test panic).
pub(crate) fn lock<T: ?Sized>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A manually advanced simulated clock; its [`DelayNs`] advances it instead of sleeping.
///
/// Share it (it is a cheap handle) between an [`I2cBus`] and the code that paces a driver, so
/// a test runs at simulated time with no real waiting.
#[derive(Debug, Clone, Default)]
pub struct SimClock {
    now_ns: Arc<AtomicU64>,
}

impl SimClock {
    /// A clock at t = 0.
    pub fn new() -> Self {
        Self::default()
    }

    /// Moves time forward by `ns`.
    pub fn advance_ns(&self, ns: u64) {
        self.now_ns.fetch_add(ns, Ordering::SeqCst);
    }

    /// Sets the time; a time earlier than now is ignored (time never goes backwards).
    pub fn set_ns(&self, now_ns: u64) {
        self.now_ns.fetch_max(now_ns, Ordering::SeqCst);
    }

    /// This clock as a [`SharedClock`] for [`I2cBus::with_clock`].
    pub fn shared(&self) -> SharedClock {
        Arc::new(self.clone())
    }
}

impl Clock for SimClock {
    fn now_ns(&self) -> u64 {
        self.now_ns.load(Ordering::SeqCst)
    }
}

impl DelayNs for SimClock {
    fn delay_ns(&mut self, ns: u32) {
        self.advance_ns(u64::from(ns));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A one-register-pointer device storing 4 bytes, to test the bus plumbing.
    struct Regs {
        address: u8,
        regs: [u8; 4],
        ptr: usize,
        writes: Vec<Vec<u8>>,
        time: u64,
    }

    impl Regs {
        fn new(address: u8) -> Self {
            Self {
                address,
                regs: [0xA0, 0xA1, 0xA2, 0xA3],
                ptr: 0,
                writes: Vec::new(),
                time: 0,
            }
        }
    }

    impl I2cDevice for Regs {
        fn address(&self) -> u8 {
            self.address
        }
        fn responds_to(&self, address: u8) -> bool {
            address == self.address || address == 0x00
        }
        fn write(&mut self, _address: u8, bytes: &[u8]) -> Result<(), Nack> {
            self.writes.push(bytes.to_vec());
            if let Some((&p, data)) = bytes.split_first() {
                self.ptr = usize::from(p);
                for &b in data {
                    *self.regs.get_mut(self.ptr).ok_or(Nack)? = b;
                    self.ptr += 1;
                }
            }
            Ok(())
        }
        fn read(&mut self, _address: u8, buf: &mut [u8]) -> Result<(), Nack> {
            for b in buf {
                *b = *self.regs.get(self.ptr).ok_or(Nack)?;
                self.ptr += 1;
            }
            Ok(())
        }
        fn set_time_ns(&mut self, now_ns: u64) {
            self.time = now_ns;
        }
    }

    #[test]
    fn dispatches_by_address_merges_adjacent_writes_and_counts() {
        let clock = SimClock::new();
        let mut bus = I2cBus::with_clock(clock.shared());
        let a = Arc::new(Mutex::new(Regs::new(0x10)));
        let b = Arc::new(Mutex::new(Regs::new(0x11)));
        bus.attach(a.clone());
        bus.attach(b.clone());
        bus.attach(a.clone());
        clock.advance_ns(1234);

        let mut out = [0u8; 2];
        bus.write_read(0x11, &[0x02], &mut out).unwrap();
        assert_eq!(out, [0xA2, 0xA3]);
        bus.transaction(
            0x10,
            &mut [Operation::Write(&[0x01]), Operation::Write(&[0x55, 0x66])],
        )
        .unwrap();
        assert_eq!(lock(&a).writes, vec![vec![0x01, 0x55, 0x66]]);
        assert_eq!(lock(&a).regs, [0xA0, 0x55, 0x66, 0xA3]);
        assert!(lock(&b).writes == vec![vec![0x02]]);
        assert_eq!(lock(&a).time, 1234);

        assert_eq!(bus.write(0x42, &[0x00]), Err(BusError::AddressNack(0x42)));
        assert_eq!(
            bus.write(0x10, &[0x03, 1, 2]),
            Err(BusError::DataNack(0x10))
        );
        assert_eq!(
            bus.stats(),
            BusStats {
                transactions: 4,
                bytes_written: 8,
                bytes_read: 2,
                nacks: 2
            }
        );
    }

    #[test]
    fn broadcast_writes_reach_every_responder() {
        let mut bus = I2cBus::new();
        let a = Arc::new(Mutex::new(Regs::new(0x10)));
        let b = Arc::new(Mutex::new(Regs::new(0x11)));
        bus.attach(a.clone());
        bus.attach(b.clone());
        bus.write(0x00, &[0x00, 0x77]).unwrap();
        assert_eq!(lock(&a).regs[0], 0x77);
        assert_eq!(lock(&b).regs[0], 0x77);
    }

    #[test]
    fn sim_clock_delay_advances_time_and_never_goes_back() {
        let mut clock = SimClock::new();
        clock.delay_us(500);
        assert_eq!(clock.now_ns(), 500_000);
        clock.set_ns(100);
        assert_eq!(clock.now_ns(), 500_000);
        clock.set_ns(2_000_000);
        assert_eq!(clock.now_ns(), 2_000_000);
    }
}
