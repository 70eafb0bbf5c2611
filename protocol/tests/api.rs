//! The small helpers around the wire types: sensor names, revolution building, ack coverage,
//! version compatibility and message directions.

use scan3d_protocol::{
    Ack, Body, Command, Direction, Frame, Heartbeat, Hello, IncompatibleVersion, LidarRevolution,
    PROTOCOL_VERSION, SampleTimeError, SensorId, TimePing, TimePong, check_compatible,
};

#[test]
fn sensor_ids_have_documented_values_and_names() {
    assert_eq!(SensorId::RPLIDAR, SensorId(0));
    assert_eq!(SensorId::SWEEP, SensorId(1));
    assert_eq!(SensorId::IMU, SensorId(2));
    assert_eq!(SensorId::STEPPER, SensorId(3));
    let names: Vec<String> = (0..5).map(|i| SensorId(i).to_string()).collect();
    assert_eq!(names, ["rplidar", "sweep", "imu", "stepper", "sensor#4"]);
    assert_eq!(SensorId(200).name(), None);
}

#[test]
fn revolution_push_stores_offsets_and_rejects_out_of_range_times() {
    let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 1_000, 5_000);
    rev.push(0.0, 1.0, 10, 1_000).unwrap();
    rev.push(180.0, 2.0, 20, 1_000 + u64::from(u32::MAX))
        .unwrap();
    assert_eq!(rev.samples[0].offset_ns, 0);
    assert_eq!(rev.samples[1].offset_ns, u32::MAX);
    assert_eq!(
        rev.sample_times_ns().collect::<Vec<_>>(),
        [1_000, 4_294_968_295]
    );
    assert_eq!(
        rev.push(1.0, 1.0, 1, 999),
        Err(SampleTimeError {
            t0_ns: 1_000,
            t_ns: 999
        })
    );
    assert_eq!(
        rev.push(1.0, 1.0, 1, 4_294_968_296),
        Err(SampleTimeError {
            t0_ns: 1_000,
            t_ns: 4_294_968_296
        })
    );
    assert_eq!(rev.samples.len(), 2);
}

#[test]
fn sample_times_saturate_instead_of_overflowing() {
    let mut rev = LidarRevolution::new(SensorId::SWEEP, u64::MAX - 1, u64::MAX);
    rev.push(0.0, 0.0, 0, u64::MAX).unwrap();
    rev.samples[0].offset_ns = 10; // as a hostile peer could send it
    assert_eq!(rev.sample_times_ns().collect::<Vec<_>>(), [u64::MAX]);
}

#[test]
fn ack_coverage() {
    let up_to = Ack::UpTo { seq: 10 };
    assert!(up_to.covers(0) && up_to.covers(10));
    assert!(!up_to.covers(11));
    let range = Ack::Range {
        first: 20,
        last: 22,
    };
    assert!(!range.covers(19));
    assert!(range.covers(20) && range.covers(21) && range.covers(22));
    assert!(!range.covers(23));
}

#[test]
fn version_compatibility() {
    assert_eq!(PROTOCOL_VERSION, 2);
    assert_eq!(check_compatible(2), Ok(()));
    for older_or_newer in [1, 3] {
        assert_eq!(
            check_compatible(older_or_newer),
            Err(IncompatibleVersion {
                peer: older_or_newer,
                supported: 2
            })
        );
    }
    let mut hello = Hello::new("pi", "0.1.0", Vec::new());
    assert_eq!(hello.check_compatible(), Ok(()));
    hello.protocol_version = 0;
    let err = hello.check_compatible().unwrap_err();
    assert_eq!(
        err.to_string(),
        "peer speaks protocol version 0, this build speaks version 2"
    );
}

#[test]
fn body_directions_and_conversions() {
    let hello = Frame::new(1, 0, Hello::new("pi", "0", Vec::new()));
    assert_eq!(hello.body.direction(), Direction::EdgeToServer);
    assert_eq!(
        Body::from(TimePing { t0_ns: 1 }).direction(),
        Direction::ServerToEdge
    );
    assert_eq!(
        Body::from(TimePong {
            t0_ns: 1,
            t1_ns: 2,
            t2_ns: 3
        })
        .direction(),
        Direction::EdgeToServer
    );
    assert_eq!(
        Body::from(Command::StopStaticScan).direction(),
        Direction::ServerToEdge
    );
    assert_eq!(
        Body::from(Ack::UpTo { seq: 0 }).direction(),
        Direction::Both
    );
    assert_eq!(
        Frame::new(7, 8, Heartbeat { sent_ns: 9 }),
        Frame {
            session_id: 7,
            seq: 8,
            body: Body::Heartbeat(Heartbeat { sent_ns: 9 })
        }
    );
}

#[test]
fn a_clock_model_maps_edge_time_with_its_offset_and_skew_and_widens_its_bound() {
    let model = scan3d_protocol::ClockModel {
        // The edge is 5 s ahead at edge time 100 s and gains 20 µs per second.
        offset_ns: 5_000_000_000,
        skew_ppm: 20.0,
        error_bound_ns: 400_000,
        skew_bound_ppm: 2.0,
        ref_edge_ns: 100_000_000_000,
        fit_from_edge_ns: 95_000_000_000,
        fit_to_edge_ns: 100_000_000_000,
        valid_from_edge_ns: 100_000_000_000,
        min_delay_ns: 2_000_000,
        exchanges: 10,
    };
    assert_eq!(model.to_server_ns(100_000_000_000), 95_000_000_000);
    // 10 s later the edge is 200 µs further ahead.
    assert_eq!(model.to_server_ns(110_000_000_000), 104_999_800_000);
    // 10 s earlier it was 200 µs less ahead.
    assert_eq!(model.to_server_ns(90_000_000_000), 85_000_200_000);
    assert_eq!(model.error_bound_at(100_000_000_000), 400_000);
    // Within the exchanges fitted the bound holds as is; outside it widens with the skew's.
    assert_eq!(model.error_bound_at(96_000_000_000), 400_000);
    assert_eq!(model.error_bound_at(110_000_000_000), 420_000);
    assert_eq!(model.error_bound_at(85_000_000_000), 420_000);
    // Times the offset would push below zero saturate instead of wrapping.
    assert_eq!(model.to_server_ns(1_000), 0);
}
