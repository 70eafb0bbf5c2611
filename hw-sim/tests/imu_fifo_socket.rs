//! The edge's IMU thread in its default FIFO mode, over the I2C socket, against the emulated
//! MPU-9250 + AK8963 in real time: the samples and rates of the per-sample path (200 a second,
//! a field every other one), each stamped with its measurement time; and a socket that goes
//! away is one loss naming the socket, not the bus error's generic words.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, channel};
use std::time::{Duration, Instant};

use scan3d_edge::clock::{ClockDelay, MonotonicClock, SharedClock};
use scan3d_edge::config::ImuSection;
use scan3d_edge::i2c_socket::SocketI2c;
use scan3d_edge::imu_worker::{ImuEvent, ImuWorker};
use scan3d_hw_sim::i2c::I2cBus;
use scan3d_hw_sim::i2c_socket::I2cSocketServer;
use scan3d_hw_sim::imu::{
    AkEmulatorConfig, ImuEmulator, ImuEmulatorConfig, ImuTruth, MpuEmulatorConfig,
    STANDARD_GRAVITY, TrueImu,
};
use scan3d_protocol::ImuSample;

const DEADLINE: Duration = Duration::from_secs(60);

/// Gyro z in °/s is 0.5 × (the time in ms, modulo 400): a reading says when it was measured,
/// to about 0.03 ms.
struct TimeInGyroZ;

impl ImuTruth for TimeInGyroZ {
    fn sample(&self, t_ns: u64) -> TrueImu {
        let ms = ((t_ns / 1000) % 400_000) as f64 / 1000.0;
        TrueImu {
            accel_m_s2: [0.0, 0.0, STANDARD_GRAVITY],
            gyro_rad_s: [0.0, 0.0, (0.5 * ms).to_radians()],
            mag_ut: [20.0, 0.0, -40.0],
        }
    }
}

fn next_event(events: &Receiver<ImuEvent>, started: Instant) -> ImuEvent {
    let left = DEADLINE.saturating_sub(started.elapsed());
    events
        .recv_timeout(left)
        .unwrap_or_else(|e| panic!("no IMU event within {DEADLINE:?}: {e}"))
}

#[test]
fn fifo_samples_come_at_the_full_rate_with_their_measurement_times_and_a_lost_socket_is_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("i2c.sock");
    let clock: SharedClock = Arc::new(MonotonicClock::new());
    let bus = I2cBus::with_clock(clock.clone());
    let quiet = ImuEmulatorConfig {
        mpu: MpuEmulatorConfig {
            accel_sigma_m_s2: [0.0; 3],
            gyro_sigma_rad_s: [0.0; 3],
            ..MpuEmulatorConfig::default()
        },
        ak: AkEmulatorConfig {
            mag_sigma_ut: [0.0; 3],
            ..AkEmulatorConfig::default()
        },
    };
    bus.attach(Arc::new(std::sync::Mutex::new(ImuEmulator::new(
        quiet,
        Arc::new(TimeInGyroZ),
    ))));
    let server = I2cSocketServer::start(&path, bus).unwrap();

    // The default read mode is the FIFO; no bias estimate (the gyro is a ramp here).
    let section: ImuSection = toml::from_str("gyro_bias_samples = 0").unwrap();
    let (tx, events) = channel();
    let worker = ImuWorker::spawn(
        SocketI2c::new(&path),
        ClockDelay(clock.clone()),
        section,
        clock.clone(),
        move |event| {
            let _ = tx.send(event);
        },
    )
    .unwrap();
    let started = Instant::now();
    match next_event(&events, started) {
        ImuEvent::Ready(ids) => assert_eq!(ids.who_am_i, 0x71),
        other => panic!("expected Ready, got {other:?}"),
    }

    // Three seconds of samples.
    let mut samples: Vec<ImuSample> = Vec::new();
    while samples
        .last()
        .is_none_or(|last| last.t_ns - samples[0].t_ns < 3_000_000_000)
    {
        match next_event(&events, started) {
            ImuEvent::Sample(sample) => samples.push(sample),
            other => panic!("expected samples, got {other:?}"),
        }
    }
    let seconds = (samples.last().unwrap().t_ns - samples[0].t_ns) as f64 / 1e9;
    let rate = (samples.len() - 1) as f64 / seconds;
    let fields = samples.iter().filter(|s| !s.mag_ut[0].is_nan()).count() as f64 / seconds;
    assert!(samples.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
    // Stamp error after the first second (the envelope spans half a second by then).
    let worst_ms = samples
        .iter()
        .filter(|s| s.t_ns - samples[0].t_ns > 1_000_000_000)
        .map(|s| {
            let measured_ms = f64::from(s.gyro_radps[2]).to_degrees() / 0.5;
            let stamped_ms = (s.t_ns % 400_000_000) as f64 / 1e6;
            let error = stamped_ms - measured_ms;
            if error.abs() > 200.0 {
                (error - 400.0 * error.signum()).abs()
            } else {
                error.abs()
            }
        })
        .fold(0.0f64, f64::max);
    println!(
        "FIFO over the socket: {rate:.1} samples/s, {fields:.1} fields/s, worst stamp error \
         {worst_ms:.3} ms"
    );
    assert!((rate - 200.0).abs() < 2.0, "{rate} samples/s");
    assert!((fields - 100.0).abs() < 2.0, "{fields} fields/s");
    assert!(worst_ms < 4.0, "worst stamp error {worst_ms} ms");

    // The socket goes away: one loss, naming the socket, in the bus error's own words.
    server.shutdown();
    let reason = loop {
        match next_event(&events, started) {
            ImuEvent::Lost(reason) => break reason,
            ImuEvent::Sample(_) => {}
            other => panic!("expected the loss, got {other:?}"),
        }
    };
    assert!(
        reason.contains("I2C socket") && reason.contains(&path.display().to_string()),
        "{reason}"
    );
    assert!(!reason.contains("A different error"), "{reason}");
    let report = worker.stop();
    assert_eq!(report.fifo_overflows, 0);
    assert!(report.failed_reads >= 10);
}
