//! What an edge's sensors are doing, for `scan3d status`: per sensor its state, data rate and
//! the age of its last data, and the progress of each static scan by position. Pure: frames
//! and the time they were recorded go in, a [`SensorStatus`] list comes out.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use scan3d_protocol::{Body, SensorId, StatusEvent};
use serde::Serialize;

use crate::ingest::scan_progress::ScanProgress;

/// Data rates are measured over this window.
pub const RATE_WINDOW: Duration = Duration::from_secs(5);
/// A sensor without data for this long is `idle` (not `streaming`).
pub const STREAMING_WITHIN: Duration = Duration::from_secs(3);
/// Static scans kept per edge (the newest).
pub const SCANS_KEPT: usize = 64;
/// Frames remembered per sensor for the rate (an IMU at 200 Hz fills 1000 in the window).
const RATE_FRAMES: usize = 4096;

/// One sensor in `scan3d status --json` (`edges[].sensors[]`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SensorStatus {
    /// `rplidar`, `sweep`, `imu`, `stepper` (or `sensor#N` for an id this server does not
    /// know).
    pub kind: String,
    /// The model the edge reported (empty if none yet).
    pub model: String,
    /// `streaming` (data within [`STREAMING_WITHIN`]), `idle`, `lost` or `paused` (the edge
    /// said so), or `gone` (the edge is not connected).
    pub state: String,
    /// The edge's reason for `lost` or `paused`.
    pub reason: Option<String>,
    /// Frames per second over the last [`RATE_WINDOW`] (revolutions for a lidar, readings for
    /// the IMU, state changes for the stepper).
    pub frames_per_s: f64,
    /// Samples per second over the last [`RATE_WINDOW`] (lidar samples; the IMU's readings).
    pub samples_per_s: f64,
    /// Seconds since its last data was recorded (`None`: none yet).
    pub last_data_age_s: Option<f64>,
}

#[derive(Debug, Default)]
struct Track {
    model: String,
    /// The last lost/paused event and its reason, cleared by back/resumed.
    trouble: Option<(&'static str, String)>,
    recent: VecDeque<(Instant, u32)>,
    last: Option<Instant>,
}

/// One edge's sensors and static scans as its frames tell them.
#[derive(Debug, Default)]
pub struct EdgeActivity {
    sensors: BTreeMap<SensorId, Track>,
    scans: VecDeque<(u64, ScanProgress)>,
}

impl EdgeActivity {
    /// Takes one recorded frame body of session `session_id`, recorded at `now`.
    pub fn on_body(&mut self, session_id: u64, body: &Body, now: Instant) {
        match body {
            Body::Hello(hello) => {
                for info in &hello.sensors {
                    self.sensors.entry(info.sensor).or_default().model = info.model.clone();
                }
            }
            Body::Revolution(rev) => self.data(rev.sensor, rev.samples.len(), now),
            Body::Imu(_) => self.data(SensorId::IMU, 1, now),
            Body::Stepper(_) => self.data(SensorId::STEPPER, 0, now),
            Body::Status(status) => {
                let track = self.sensors.entry(status.sensor).or_default();
                track.trouble = match status.event {
                    StatusEvent::SensorLost => Some(("lost", status.reason.clone())),
                    StatusEvent::AcquisitionPaused => Some(("paused", status.reason.clone())),
                    StatusEvent::SensorBack | StatusEvent::AcquisitionResumed => None,
                };
            }
            Body::StaticScan(message) => {
                let scan_id = ScanProgress::scan_of(message);
                let index = self
                    .scans
                    .iter()
                    .position(|(s, p)| *s == session_id && p.scan_id == scan_id);
                let index = match index {
                    Some(index) => index,
                    None => {
                        if self.scans.len() >= SCANS_KEPT {
                            self.scans.pop_front();
                        }
                        self.scans
                            .push_back((session_id, ScanProgress::new(scan_id)));
                        self.scans.len() - 1
                    }
                };
                self.scans[index].1.on_message(message);
            }
            _ => {}
        }
    }

    fn data(&mut self, sensor: SensorId, samples: usize, now: Instant) {
        let track = self.sensors.entry(sensor).or_default();
        track.last = Some(now);
        track.trouble = None;
        if track.recent.len() >= RATE_FRAMES {
            track.recent.pop_front();
        }
        track
            .recent
            .push_back((now, u32::try_from(samples).unwrap_or(u32::MAX)));
    }

    /// Every sensor seen, by id, at `now`; `connected`: whether the edge is.
    pub fn sensors(&self, now: Instant, connected: bool) -> Vec<SensorStatus> {
        self.sensors
            .iter()
            .map(|(sensor, track)| {
                let in_window = track
                    .recent
                    .iter()
                    .filter(|(t, _)| now.saturating_duration_since(*t) <= RATE_WINDOW);
                let (frames, samples) =
                    in_window.fold((0u64, 0u64), |(f, s), (_, n)| (f + 1, s + u64::from(*n)));
                let window = RATE_WINDOW.as_secs_f64();
                let age = track.last.map(|t| now.saturating_duration_since(t));
                let (state, reason) = match (&track.trouble, age) {
                    _ if !connected => ("gone", None),
                    (Some((state, reason)), _) => (*state, Some(reason.clone())),
                    (None, Some(age)) if age <= STREAMING_WITHIN => ("streaming", None),
                    _ => ("idle", None),
                };
                SensorStatus {
                    kind: sensor.to_string(),
                    model: track.model.clone(),
                    state: state.to_owned(),
                    reason,
                    frames_per_s: frames as f64 / window,
                    samples_per_s: if *sensor == SensorId::IMU {
                        frames as f64 / window
                    } else {
                        samples as f64 / window
                    },
                    last_data_age_s: age.map(|a| a.as_secs_f64()),
                }
            })
            .collect()
    }

    /// The static scans seen (the newest [`SCANS_KEPT`]), oldest first, with their session.
    pub fn scans(&self) -> Vec<(u64, ScanProgress)> {
        self.scans.iter().cloned().collect()
    }
}

#[cfg(test)]
mod tests {
    use scan3d_protocol::{
        DeviceStatus, Hello, ImuSample, LidarRevolution, SensorInfo, StaticScan, StaticScanYaws,
        YawRun,
    };

    use super::*;

    fn revolution(sensor: SensorId, samples: usize) -> Body {
        let mut rev = LidarRevolution::new(sensor, 0, 1);
        for i in 0..samples {
            rev.push(i as f32, 1.0, 10, 0).unwrap();
        }
        rev.into()
    }

    #[test]
    fn sensors_report_state_rate_and_age_and_scans_their_progress() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut activity = EdgeActivity::default();
        activity.on_body(
            1,
            &Hello::new(
                "pi",
                "0",
                vec![SensorInfo {
                    sensor: SensorId::SWEEP,
                    model: "Sweep".into(),
                    firmware: String::new(),
                    serial: String::new(),
                }],
            )
            .into(),
            at(0),
        );
        // Ten Sweep revolutions of 500 samples, one every 500 ms.
        for i in 0..10 {
            activity.on_body(1, &revolution(SensorId::SWEEP, 500), at(500 * i));
        }
        let imu = ImuSample {
            t_ns: 0,
            accel_mps2: [0.0; 3],
            gyro_radps: [0.0; 3],
            mag_ut: [0.0; 3],
            orientation: None,
        };
        activity.on_body(1, &imu.into(), at(100));
        let sensors = activity.sensors(at(4500), true);
        let sweep = &sensors[0];
        assert_eq!(
            (sweep.kind.as_str(), sweep.model.as_str()),
            ("sweep", "Sweep")
        );
        assert_eq!(sweep.state, "streaming");
        assert_eq!(sweep.frames_per_s, 2.0);
        assert_eq!(sweep.samples_per_s, 1000.0);
        assert_eq!(sweep.last_data_age_s, Some(0.0));
        let imu = &sensors[1];
        assert_eq!((imu.kind.as_str(), imu.state.as_str()), ("imu", "idle"));
        assert_eq!(imu.last_data_age_s, Some(4.4));
        // Lost, then gone with the edge.
        activity.on_body(
            1,
            &DeviceStatus {
                t_ns: 0,
                sensor: SensorId::SWEEP,
                event: StatusEvent::SensorLost,
                reason: "unplugged".into(),
            }
            .into(),
            at(4600),
        );
        let sweep = &activity.sensors(at(4700), true)[0];
        assert_eq!(
            (sweep.state.as_str(), sweep.reason.as_deref()),
            ("lost", Some("unplugged"))
        );
        assert_eq!(activity.sensors(at(4700), false)[0].state, "gone");
        // Static scans by session and id.
        let yaws = |scan_id| {
            Body::from(StaticScan::Yaws(StaticScanYaws {
                scan_id,
                revolution_t0_ns: 0,
                runs: vec![YawRun {
                    first_index: 0,
                    count: 3,
                    yaw_deg: 9.0,
                }],
            }))
        };
        activity.on_body(1, &yaws(0), at(5000));
        activity.on_body(1, &yaws(0), at(5500));
        activity.on_body(2, &yaws(0), at(5500));
        let scans = activity.scans();
        assert_eq!(scans.len(), 2);
        assert_eq!((scans[0].0, scans[0].1.revolutions), (1, 2));
        assert_eq!((scans[1].0, scans[1].1.revolutions), (2, 1));
    }
}
