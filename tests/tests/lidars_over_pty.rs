//! The edge's lidar acquisition (drivers, serial shell, revolution timing) against the hw-sim
//! emulators over real Linux ptys, on a scaled clock.
//!
//! Every test compares what the edge decoded with the emulator's log of what it put on the
//! wire, so "the driver rejected garbage" and "the driver lost good data" are told apart.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use scan3d_edge::acquisition::{Acquisition, AcquisitionEvent};
use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig, ScanMode};
use scan3d_edge::drivers::sweep::{Sweep, SweepConfig};
use scan3d_edge::lidar::{DeviceInfo, LidarDriver, LidarEvent};
use scan3d_edge::serial::SerialOptions;
use scan3d_edge::timing::{Revolution, TimedSample, TimingConfig};
use scan3d_hw_sim::device::Device;
use scan3d_hw_sim::faults::{FaultConfig, SentSample};
use scan3d_hw_sim::installation;
use scan3d_hw_sim::mounts;
use scan3d_hw_sim::pty::{PtyDevice, PtyHandle, PtyOptions};
use scan3d_hw_sim::rplidar::{RplidarEmulator, RplidarEmulatorConfig, RplidarModel};
use scan3d_hw_sim::sweep::{SweepEmulator, SweepEmulatorConfig};
use scan3d_hw_sim::world::World;

/// Simulated seconds per real second, for devices and edge alike, where the test checks
/// timing (revolution periods): real time, so that a busy machine delays the emulator and the
/// edge by a small share of a revolution (at ×10, 10 ms of scheduling delay was half of one).
const TIME_SCALE: f64 = 1.0;

/// The time scale of the replug test, whose handshake waits (reset, spin-up) are device time.
const REPLUG_TIME_SCALE: f64 = 10.0;

/// Real seconds a test waits for the revolutions it needs: generous, for a busy machine.
const COLLECT_DEADLINE: Duration = Duration::from_secs(60);

/// A unique link path for one test.
fn link(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("scan3d-e2e-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir.join(name)
}

fn scaled_clock(time_scale: f64) -> SharedClock {
    Arc::new(ScaledClock::new(time_scale))
}

/// An emulator on a pty and the edge acquisition reading it.
struct Rig {
    pty: PtyHandle,
    acquisition: Acquisition,
    events: Receiver<AcquisitionEvent>,
    info: Option<DeviceInfo>,
    revolutions: Vec<Revolution>,
}

impl Rig {
    fn start(
        name: &str,
        device: Box<dyn Device>,
        driver: Box<dyn LidarDriver + Send>,
        baud: u32,
        faults: FaultConfig,
        time_scale: f64,
    ) -> Self {
        let path = link(name);
        let options = PtyOptions {
            time_scale,
            faults,
            seed: 7,
            epoch: None,
        };
        let pty = PtyDevice::spawn(path.clone(), device, options).expect("pty device");
        let (acquisition, events) = Acquisition::spawn(
            driver,
            SerialOptions::new(path, baud),
            scaled_clock(time_scale),
            TimingConfig::default(),
            false,
        );
        Self {
            pty,
            acquisition,
            events,
            info: None,
            revolutions: Vec::new(),
        }
    }

    /// Collects events until `revolutions` full revolutions arrived or `timeout` (real) passed.
    fn collect(&mut self, revolutions: usize, timeout: Duration) {
        let end = Instant::now() + timeout;
        while self.revolutions.len() < revolutions {
            let left = end.saturating_duration_since(Instant::now());
            assert!(
                !left.is_zero(),
                "only {} of {revolutions} revolutions within {timeout:?}",
                self.revolutions.len()
            );
            match self
                .events
                .recv_timeout(left.min(Duration::from_millis(100)))
            {
                Ok(AcquisitionEvent::Driver(LidarEvent::Info(info))) => self.info = Some(info),
                Ok(AcquisitionEvent::Revolution(rev)) => self.revolutions.push(rev),
                Ok(AcquisitionEvent::Driver(LidarEvent::Failed(e))) => panic!("driver failed: {e}"),
                Ok(_) | Err(_) => {}
            }
        }
    }

    /// Stops the edge, then the device; returns everything the device sent.
    fn stop(self) -> (Vec<Revolution>, Option<DeviceInfo>, Vec<SentSample>) {
        self.acquisition.stop().expect("acquisition stops cleanly");
        let sent = self.pty.sent_log().snapshot();
        self.pty.shutdown();
        (self.revolutions, self.info, sent)
    }
}

fn rplidar_rig(
    name: &str,
    model: RplidarModel,
    baud: u32,
    mode: ScanMode,
    faults: FaultConfig,
    time_scale: f64,
) -> Rig {
    let world = Arc::new(World::conference_room());
    let config = RplidarEmulatorConfig {
        model,
        baud,
        spinup_s: 0.5,
        ..Default::default()
    };
    let device = RplidarEmulator::new(
        config,
        RplidarEmulator::default_scanner(world, mounts::rplidar()),
        11,
    );
    // Answers may come late on a busy machine: wait for them generously (device time), so
    // that load slows the test down instead of failing the handshake.
    let driver = Rplidar::new(RplidarConfig {
        scan_mode: mode,
        baud,
        answer_timeout_ms: 10_000,
        info_timeout_ms: 5_000,
        spinup_timeout_ms: 30_000,
        ..Default::default()
    });
    Rig::start(
        name,
        Box::new(device),
        Box::new(driver),
        baud,
        faults,
        time_scale,
    )
}

fn sweep_rig(
    name: &str,
    config: SweepEmulatorConfig,
    driver: SweepConfig,
    faults: FaultConfig,
) -> Rig {
    let world = Arc::new(World::conference_room());
    let device = SweepEmulator::new(
        config,
        SweepEmulator::default_scanner(world, mounts::sweep()),
        12,
    );
    // As for the RPLidar: generous waits for answers and data (device time).
    let driver = Sweep::new(SweepConfig {
        answer_timeout_ms: 10_000,
        silence_timeout_ms: 20_000,
        settle_timeout_ms: 60_000,
        ..driver
    })
    .expect("valid sweep config");
    Rig::start(
        name,
        Box::new(device),
        Box::new(driver),
        115_200,
        faults,
        TIME_SCALE,
    )
}

/// How strictly a decoded sample must equal the one the emulator sent.
#[derive(Clone, Copy, PartialEq)]
enum Integrity {
    /// Every field is protected by a checksum (express capsules, Sweep blocks): a decoded
    /// sample must equal a sent one.
    Checksummed,
    /// RPLidar standard nodes carry no checksum: a bit flip inside the quality, distance or
    /// low angle bits leaves a well-framed node with a wrong value that no receiver can detect.
    /// Such a sample is tolerated, but only where the injector touched that very node, and only
    /// within the driver's angle-consistency window (10° steps), which catches larger flips.
    UnprotectedFields,
}

/// Matches decoded samples, in order, against the emulator's log. Panics if a decoded sample
/// does not appear in the log (after the previous match). Returns, over the stretch of the log
/// the edge was reading, (untouched samples sent, untouched samples decoded).
///
/// Angles may differ by up to 0.05° (an eighth of the express sample spacing): when one capsule
/// is lost, the driver still decodes the capsule before it by interpolating across the gap.
fn match_against_log(
    revolutions: &[Revolution],
    sent: &[SentSample],
    integrity: Integrity,
) -> (usize, usize) {
    let decoded: Vec<&TimedSample> = revolutions.iter().flat_map(|r| &r.samples).collect();
    assert!(!decoded.is_empty(), "nothing decoded");
    let same = |d: &TimedSample, s: &SentSample| {
        let angle_error = (d.angle_deg - s.sample.angle_deg).abs();
        let exact = angle_error < 0.05
            && (d.range_m - s.sample.range_m).abs() < 0.0005
            && d.quality == s.sample.quality;
        let undetectable_flip =
            s.touched && integrity == Integrity::UnprotectedFields && angle_error < 10.0;
        exact || undetectable_flip
    };
    let (matched, unexplained) = installation::match_in_order(&decoded, sent, |d, s| same(d, s));
    if let Some(&i) = unexplained.first() {
        panic!(
            "{} decoded samples were never sent, the first #{i}: {:?}",
            unexplained.len(),
            decoded[i]
        );
    }
    let (first, last) = (matched[0], *matched.last().unwrap_or(&0));
    let untouched_sent = sent[first..=last].iter().filter(|s| !s.touched).count();
    let untouched_decoded = matched.iter().filter(|&&k| !sent[k].touched).count();
    (untouched_sent, untouched_decoded)
}

fn assert_period_near(revolutions: &[Revolution], hz: f64) {
    let mut periods: Vec<f64> = revolutions
        .iter()
        .map(|r| (r.t1_ns - r.t0_ns) as f64 / 1e9)
        .collect();
    periods.sort_by(f64::total_cmp);
    let median = periods[periods.len() / 2];
    assert!(
        (median * hz - 1.0).abs() < 0.05,
        "median revolution period {median:.4} s, expected {:.4} s",
        1.0 / hz
    );
}

fn check_rplidar(name: &str, model: RplidarModel, baud: u32, mode: ScanMode) {
    let mut rig = rplidar_rig(name, model, baud, mode, FaultConfig::default(), TIME_SCALE);
    rig.collect(12, COLLECT_DEADLINE);
    let (revolutions, info, sent) = rig.stop();
    let info = info.expect("device info");
    assert_eq!(
        info.model,
        if model == RplidarModel::A1 {
            "A1"
        } else {
            "A2"
        }
    );
    assert_eq!(info.firmware, "1.29");
    assert_eq!(info.hardware, 7);
    let (sent_ok, decoded_ok) = match_against_log(&revolutions, &sent, Integrity::Checksummed);
    assert_eq!(
        decoded_ok, sent_ok,
        "a clean line must lose nothing between the first and last decoded sample"
    );
    assert_period_near(
        &revolutions[1..],
        RplidarEmulatorConfig::default().rotation_hz,
    );
    let per_rev = revolutions.iter().map(|r| r.samples.len()).sum::<usize>() / revolutions.len();
    let expected = match mode {
        // 4000 samples/s at 5.5 Hz.
        ScanMode::Express => 727.0,
        // The wire limits standard scans: 5 bytes per node.
        ScanMode::Standard => (baud as f64 / 50.0).min(2000.0) / 5.5,
    };
    assert!(
        (per_rev as f64 / expected - 1.0).abs() < 0.1,
        "{per_rev} samples per revolution, expected about {expected:.0}"
    );
}

#[test]
fn rplidar_a1_express_at_115200() {
    check_rplidar("a1-express", RplidarModel::A1, 115_200, ScanMode::Express);
}

#[test]
fn rplidar_a1_standard_at_115200() {
    check_rplidar("a1-standard", RplidarModel::A1, 115_200, ScanMode::Standard);
}

#[test]
fn rplidar_a2_express_at_256000() {
    check_rplidar("a2-express", RplidarModel::A2, 256_000, ScanMode::Express);
}

#[test]
fn rplidar_a2_standard_at_256000() {
    check_rplidar("a2-standard", RplidarModel::A2, 256_000, ScanMode::Standard);
}

#[test]
fn sweep_waits_for_the_motor_to_settle_after_a_speed_change_then_streams() {
    let device = SweepEmulatorConfig {
        motor_hz: 5,
        settle_ms: 3000,
        ..Default::default()
    };
    let driver = SweepConfig {
        motor_hz: Some(7),
        ..Default::default()
    };
    let started = Instant::now();
    let mut rig = sweep_rig("sweep-settle", device, driver, FaultConfig::default());
    rig.collect(10, COLLECT_DEADLINE);
    // MS07 restarts the 3 s settle: no revolution can arrive before it is over.
    assert!(started.elapsed().as_secs_f64() * TIME_SCALE >= 3.0);
    let (revolutions, info, sent) = rig.stop();
    assert_eq!(info.expect("device info").model, "Sweep");
    let (sent_ok, decoded_ok) = match_against_log(&revolutions, &sent, Integrity::Checksummed);
    assert_eq!(decoded_ok, sent_ok);
    assert_period_near(&revolutions[1..], 7.0);
}

fn check_corruption(mut rig: Rig, revolutions: usize, integrity: Integrity) {
    rig.collect(revolutions, COLLECT_DEADLINE);
    let (revolutions, _, sent) = rig.stop();
    let touched = sent.iter().filter(|s| s.touched).count();
    assert!(
        touched > 0,
        "the fault injector touched nothing: the test proves nothing"
    );
    let (sent_ok, decoded_ok) = match_against_log(&revolutions, &sent, integrity);
    let ratio = decoded_ok as f64 / sent_ok as f64;
    assert!(
        ratio >= 0.95,
        "decoded {decoded_ok} of {sent_ok} untouched samples ({ratio:.3})"
    );
}

#[test]
fn rplidar_express_survives_corruption() {
    let faults = FaultConfig::corrupt(1e-3);
    check_corruption(
        rplidar_rig(
            "a1-corrupt-x",
            RplidarModel::A1,
            115_200,
            ScanMode::Express,
            faults,
            TIME_SCALE,
        ),
        25,
        Integrity::Checksummed,
    );
}

#[test]
fn rplidar_standard_survives_corruption() {
    let faults = FaultConfig::corrupt(1e-3);
    check_corruption(
        rplidar_rig(
            "a1-corrupt-s",
            RplidarModel::A1,
            115_200,
            ScanMode::Standard,
            faults,
            TIME_SCALE,
        ),
        25,
        Integrity::UnprotectedFields,
    );
}

#[test]
fn sweep_survives_corruption() {
    let device = SweepEmulatorConfig {
        settle_ms: 500,
        ..Default::default()
    };
    let rig = sweep_rig(
        "sweep-corrupt",
        device,
        SweepConfig::default(),
        FaultConfig::corrupt(1e-3),
    );
    check_corruption(rig, 25, Integrity::Checksummed);
}

#[test]
fn samples_flow_again_within_three_seconds_of_a_replug() {
    let mut rig = rplidar_rig(
        "a1-replug",
        RplidarModel::A1,
        115_200,
        ScanMode::Express,
        FaultConfig::default(),
        REPLUG_TIME_SCALE,
    );
    rig.collect(3, COLLECT_DEADLINE);
    rig.pty.unplug().expect("unplug");
    // The edge notices the unplug, then keeps retrying (backoff 100 ms doubling to 2 s); leave
    // it unplugged for a second of retries.
    let deadline = Instant::now() + COLLECT_DEADLINE;
    loop {
        assert!(
            Instant::now() < deadline,
            "the edge did not notice the unplug"
        );
        if let Ok(AcquisitionEvent::Lost(_)) = rig.events.recv_timeout(Duration::from_millis(50)) {
            break;
        }
    }
    std::thread::sleep(Duration::from_secs(1));
    let before = rig.revolutions.len();
    rig.pty.replug().expect("replug");
    let replugged = Instant::now();
    // The port is open again within the backoff's bound (2 s) and a second of slack: the edge's
    // retry cadence, which load does not stretch by seconds. (Revolutions counted while the
    // events are read are kept.)
    let deadline = replugged + COLLECT_DEADLINE;
    loop {
        assert!(Instant::now() < deadline, "the port was never reopened");
        match rig.events.recv_timeout(Duration::from_millis(50)) {
            Ok(AcquisitionEvent::Opened) => break,
            Ok(AcquisitionEvent::Revolution(rev)) => rig.revolutions.push(rev),
            _ => {}
        }
    }
    let reopened = replugged.elapsed();
    assert!(
        reopened <= Duration::from_secs(3),
        "the port reopened {reopened:?} after the replug"
    );
    // Then samples flow again: the handshake and a revolution, however busy the machine.
    rig.collect(before + 1, COLLECT_DEADLINE);
    rig.stop();
}
