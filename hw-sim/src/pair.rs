//! An edge driver wired straight to an emulator in memory, on simulated time: no pty, no
//! threads, fully deterministic (the idea of `quinn-proto`'s test `Pair`).
//!
//! Useful for fast protocol tests and for benchmarks that replay a realistic byte stream.

use scan3d_edge::lidar::{LidarDriver, LidarEvent, Transmit};

use crate::device::{Device, WireUnit};

/// One read as the driver saw it: the simulated time and the bytes.
pub type Chunk = (u64, Vec<u8>);

/// A driver and a device exchanging bytes every `step_ns` of simulated time.
pub struct Pair<D, E> {
    /// The edge side.
    pub driver: D,
    /// The emulated device.
    pub device: E,
    /// Current simulated time, ns.
    pub now_ns: u64,
    /// How often bytes move between the two, ns (a serial read's worth of time).
    pub step_ns: u64,
    /// Every chunk delivered to the driver, when recording is on.
    pub recording: Option<Vec<Chunk>>,
    units: Vec<WireUnit>,
}

impl<D: LidarDriver, E: Device> Pair<D, E> {
    /// Connects the two at time 0 and starts the driver's handshake.
    pub fn new(mut driver: D, mut device: E, step_ns: u64) -> Self {
        device.on_connect(0);
        driver.start(0);
        Self {
            driver,
            device,
            now_ns: 0,
            step_ns: step_ns.max(1),
            recording: None,
            units: Vec::new(),
        }
    }

    /// Keep a copy of every chunk the driver receives (for replaying it later).
    pub fn record(mut self) -> Self {
        self.recording = Some(Vec::new());
        self
    }

    /// Runs until `until_ns`, handing every driver event to `on_event` with its time.
    pub fn run_until(&mut self, until_ns: u64, mut on_event: impl FnMut(u64, LidarEvent)) {
        while self.now_ns < until_ns {
            self.now_ns = (self.now_ns + self.step_ns).min(until_ns);
            let now = self.now_ns;
            self.units.clear();
            self.device.poll_output(now, &mut self.units);
            let bytes: Vec<u8> = self
                .units
                .iter()
                .flat_map(|u| u.bytes.iter().copied())
                .collect();
            if !bytes.is_empty() {
                self.driver.handle_input(now, &bytes);
                if let Some(recording) = &mut self.recording {
                    recording.push((now, bytes));
                }
            }
            if self
                .driver
                .poll_timeout()
                .is_some_and(|deadline| deadline <= now)
            {
                self.driver.handle_timeout(now);
            }
            while let Some(transmit) = self.driver.poll_transmit() {
                if let Transmit::Write(bytes) = transmit {
                    self.device.on_host_bytes(now, &bytes);
                }
            }
            while let Some(event) = self.driver.poll_event() {
                on_event(now, event);
            }
        }
    }
}

/// Feeds recorded chunks to a driver from its start, as the serial shell would, handing every
/// event to `on_event`. Transmits are discarded: the recording already holds the answers.
pub fn replay<D: LidarDriver + ?Sized>(
    driver: &mut D,
    chunks: &[Chunk],
    mut on_event: impl FnMut(LidarEvent),
) {
    driver.start(0);
    for (now, bytes) in chunks {
        if driver
            .poll_timeout()
            .is_some_and(|deadline| deadline <= *now)
        {
            driver.handle_timeout(*now);
        }
        driver.handle_input(*now, bytes);
        while driver.poll_transmit().is_some() {}
        while let Some(event) = driver.poll_event() {
            on_event(event);
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig, ScanMode};
    use scan3d_edge::drivers::sweep::{Sweep, SweepConfig};

    use super::*;
    use crate::mounts;
    use crate::rplidar::{RplidarEmulator, RplidarEmulatorConfig};
    use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
    use crate::world::World;

    const MS: u64 = 1_000_000;

    fn count(events: &[LidarEvent]) -> (usize, bool) {
        let samples = events
            .iter()
            .filter(|e| matches!(e, LidarEvent::Sample(_)))
            .count();
        let info = events.iter().any(|e| matches!(e, LidarEvent::Info(_)));
        (samples, info)
    }

    #[test]
    fn rplidar_driver_and_emulator_agree_sample_for_sample_in_memory() {
        let world = Arc::new(World::conference_room());
        for mode in [ScanMode::Standard, ScanMode::Express] {
            let device = RplidarEmulator::new(
                RplidarEmulatorConfig {
                    spinup_s: 0.2,
                    ..Default::default()
                },
                RplidarEmulator::default_scanner(world.clone(), mounts::rplidar()),
                3,
            );
            let driver = Rplidar::new(RplidarConfig {
                scan_mode: mode,
                ..Default::default()
            });
            let mut pair = Pair::new(driver, device, MS);
            let mut events = Vec::new();
            pair.run_until(3_000 * MS, |_, e| events.push(e));
            let (samples, info) = count(&events);
            assert!(info, "{mode:?}: no device info");
            // About 2.5 s of streaming after handshake and spin-up.
            let expected = if mode == ScanMode::Express {
                4000.0
            } else {
                2000.0
            } * 2.5;
            assert!(
                (samples as f64 / expected - 1.0).abs() < 0.15,
                "{mode:?}: {samples} samples, expected about {expected}"
            );
            assert_eq!(pair.driver.stats().frames_rejected, 0);
        }
    }

    #[test]
    fn sweep_driver_and_emulator_agree_in_memory() {
        let world = Arc::new(World::conference_room());
        let device = SweepEmulator::new(
            SweepEmulatorConfig {
                settle_ms: 1000,
                ..Default::default()
            },
            SweepEmulator::default_scanner(world, mounts::sweep()),
            4,
        );
        let driver = Sweep::new(SweepConfig::default()).expect("valid config");
        let mut pair = Pair::new(driver, device, MS);
        let mut events = Vec::new();
        pair.run_until(4_000 * MS, |_, e| events.push(e));
        let (samples, info) = count(&events);
        assert!(info);
        // Streams from about 1 s (settle) at 550 samples/s.
        assert!((1400..=1700).contains(&samples), "{samples} samples");
    }

    #[test]
    fn a_replayed_recording_decodes_the_same_samples() {
        let world = Arc::new(World::conference_room());
        let device = RplidarEmulator::new(
            RplidarEmulatorConfig {
                spinup_s: 0.2,
                ..Default::default()
            },
            RplidarEmulator::default_scanner(world, mounts::rplidar()),
            5,
        );
        let mut pair = Pair::new(Rplidar::new(RplidarConfig::default()), device, MS).record();
        let mut live = 0;
        pair.run_until(1_000 * MS, |_, e| {
            live += u64::from(matches!(e, LidarEvent::Sample(_)))
        });
        let chunks = pair.recording.take().unwrap_or_default();
        let mut replayed = 0;
        replay(&mut Rplidar::new(RplidarConfig::default()), &chunks, |e| {
            replayed += u64::from(matches!(e, LidarEvent::Sample(_)));
        });
        assert!(live > 1000);
        assert_eq!(replayed, live);
    }
}
