//! What a recording's channels are: the topics, message encodings and edge timestamps of the
//! wire frames it holds (the table in the [module documentation](super)).

use scan3d_protocol::{Body, StaticScan};

/// The MCAP message encoding of wire frames: S3DP header + postcard
/// [`Frame`](scan3d_protocol::Frame).
pub const MESSAGE_ENCODING: &str = "scan3d-frame";

/// The MCAP profile written in the file header.
pub const PROFILE: &str = "scan3d";

/// Name of the metadata record at the start of every file.
pub const SESSION_METADATA: &str = "scan3d-session";

/// The body type's name, as in [`Body`] (used in channel metadata and errors).
pub fn body_name(body: &Body) -> &'static str {
    body.name()
}

/// The MCAP topic a frame with this body is recorded on (see the module table). `TimePing` only
/// travels server → edge and is never recorded; it maps to `/scan3d/timeping` for completeness.
pub fn topic(body: &Body) -> String {
    match body {
        Body::Hello(_) => "/scan3d/hello".into(),
        Body::Revolution(rev) => match rev.sensor.name() {
            Some(name) => format!("/scan3d/lidar/{name}"),
            None => format!("/scan3d/lidar/sensor{}", rev.sensor.0),
        },
        Body::Imu(_) => "/scan3d/imu".into(),
        Body::Stepper(_) => "/scan3d/stepper".into(),
        Body::TimePing(_) => "/scan3d/timeping".into(),
        Body::TimePong(_) => "/scan3d/timepong".into(),
        Body::Ack(_) => "/scan3d/ack".into(),
        Body::Heartbeat(_) => "/scan3d/heartbeat".into(),
        Body::Status(_) => "/scan3d/status".into(),
        Body::Command(_) => "/scan3d/command".into(),
        Body::StaticScan(_) => "/scan3d/static_scan".into(),
        Body::ClockModel(_) => "/scan3d/timesync".into(),
        Body::CommandReply(_) => "/scan3d/command_reply".into(),
        Body::Mounts(_) => "/scan3d/mounts".into(),
        Body::Pass(_) => "/scan3d/pass".into(),
    }
}

/// The edge's timestamp of a body (its monotonic clock), if it has one.
pub(crate) fn edge_time_ns(body: &Body) -> Option<u64> {
    match body {
        Body::Revolution(rev) => Some(rev.t1_ns),
        Body::Imu(imu) => Some(imu.t_ns),
        Body::Stepper(st) => Some(st.t_ns),
        Body::TimePong(pong) => Some(pong.t2_ns),
        Body::Status(status) => Some(status.t_ns),
        Body::Heartbeat(hb) => Some(hb.sent_ns),
        Body::StaticScan(scan) => Some(match scan {
            StaticScan::Started(start) => start.t_ns,
            StaticScan::Yaws(yaws) => yaws.revolution_t0_ns,
            StaticScan::Warning(warning) => warning.t_ns,
            StaticScan::Finished(end) => end.t_ns,
        }),
        Body::ClockModel(model) => Some(model.valid_from_edge_ns),
        Body::CommandReply(reply) => Some(reply.t_ns),
        Body::Pass(marker) => Some(marker.t_ns),
        Body::Hello(_) | Body::TimePing(_) | Body::Ack(_) | Body::Command(_) | Body::Mounts(_) => {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_protocol::{
        Ack, Command, DeviceStatus, Heartbeat, Hello, ImuSample, LidarRevolution, SensorId,
        StatusEvent, StepperState, TimePing, TimePong,
    };

    #[test]
    fn topics_follow_the_table() {
        let cases: Vec<(Body, &str)> = vec![
            (Hello::new("pi", "0.1.0", vec![]).into(), "/scan3d/hello"),
            (
                LidarRevolution::new(SensorId::RPLIDAR, 0, 1).into(),
                "/scan3d/lidar/rplidar",
            ),
            (
                LidarRevolution::new(SensorId::SWEEP, 0, 1).into(),
                "/scan3d/lidar/sweep",
            ),
            (
                LidarRevolution::new(SensorId(9), 0, 1).into(),
                "/scan3d/lidar/sensor9",
            ),
            (
                ImuSample {
                    t_ns: 1,
                    accel_mps2: [0.0; 3],
                    gyro_radps: [0.0; 3],
                    mag_ut: [0.0; 3],
                    orientation: None,
                }
                .into(),
                "/scan3d/imu",
            ),
            (
                StepperState {
                    t_ns: 1,
                    commanded_angle_deg: 0.0,
                    step_index: 0,
                    holding: true,
                }
                .into(),
                "/scan3d/stepper",
            ),
            (
                TimePong {
                    t0_ns: 1,
                    t1_ns: 2,
                    t2_ns: 3,
                }
                .into(),
                "/scan3d/timepong",
            ),
            (TimePing { t0_ns: 1 }.into(), "/scan3d/timeping"),
            (
                DeviceStatus {
                    t_ns: 1,
                    sensor: SensorId::IMU,
                    event: StatusEvent::SensorLost,
                    reason: String::new(),
                }
                .into(),
                "/scan3d/status",
            ),
            (Heartbeat { sent_ns: 1 }.into(), "/scan3d/heartbeat"),
            (Ack::UpTo { seq: 1 }.into(), "/scan3d/ack"),
            (Command::StopStaticScan.into(), "/scan3d/command"),
            (
                scan3d_protocol::SensorMounts { sensors: vec![] }.into(),
                "/scan3d/mounts",
            ),
            (
                scan3d_protocol::PassMarker {
                    t_ns: 1,
                    event: scan3d_protocol::PassEvent::Stopped { name: "a".into() },
                }
                .into(),
                "/scan3d/pass",
            ),
        ];
        for (body, expected) in cases {
            assert_eq!(topic(&body), expected, "{body:?}");
        }
    }

    #[test]
    fn publish_time_is_the_edge_timestamp() {
        let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 100, 200);
        rev.samples.clear();
        assert_eq!(edge_time_ns(&rev.into()), Some(200));
        let pong = TimePong {
            t0_ns: 1,
            t1_ns: 2,
            t2_ns: 3,
        };
        assert_eq!(edge_time_ns(&pong.into()), Some(3));
        assert_eq!(edge_time_ns(&Ack::UpTo { seq: 4 }.into()), None);
    }
}
