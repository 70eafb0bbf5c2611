//! Exact wire bytes, written by hand from the header layout in the crate docs and postcard's
//! format (LEB128 varints, zig-zag for signed, little-endian floats, varint enum tags).

use scan3d_protocol::{
    Ack, Body, ClockModel, Command, CommandOutcome, CommandReply, DecodeError, DeviceStatus,
    Direction, EncodeError, Frame, FrameHeader, FrameReader, HEADER_LEN, Heartbeat, Hello,
    ImuSample, InvalidMounts, LidarRevolution, MAX_FRAME_LEN, PROTOCOL_VERSION, PassEvent,
    PassMarker, RevolutionSample, SensorId, SensorInfo, SensorMount, SensorMounts, StaticScan,
    StaticScanProblem, StaticScanWarning, StaticScanYaws, StatusEvent, StepperState, TimePing,
    TimePong, YawRun, decode, decode_header, encode,
};

/// `S3DP`, version 1 LE.
const MAGIC_V2: [u8; 6] = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00];

/// Header for a payload of `len` bytes (len < 256), built by hand.
fn header(len: u8) -> Vec<u8> {
    let mut h = MAGIC_V2.to_vec();
    h.extend_from_slice(&[len, 0x00, 0x00, 0x00]);
    h
}

/// Asserts that `frame` encodes to exactly `header(payload.len()) ++ payload` and decodes back.
fn assert_wire(frame: Frame, payload: &[u8]) {
    let mut expected = header(u8::try_from(payload.len()).expect("test payload < 256 bytes"));
    expected.extend_from_slice(payload);
    let bytes = encode(&frame).expect("encodes");
    assert_eq!(bytes, expected, "encoding of {frame:?}");
    assert_eq!(decode(&expected), Ok((frame, expected.len())));
}

#[test]
fn heartbeat_frame_exact_bytes() {
    let frame = Frame::new(1, 2, Heartbeat { sent_ns: 3 });
    let bytes = encode(&frame).unwrap();
    assert_eq!(
        bytes,
        [
            0x53, 0x33, 0x44, 0x50, // magic "S3DP"
            0x02, 0x00, // version 2 LE
            0x04, 0x00, 0x00, 0x00, // payload length 4 LE
            0x01, // session id 1
            0x02, // seq 2
            0x07, // body tag 7 = Heartbeat
            0x03, // sent_ns 3
        ]
    );
    assert_eq!(bytes.len(), HEADER_LEN + 4);
    assert_eq!(decode(&bytes), Ok((frame, 14)));
}

#[test]
fn header_to_bytes_and_decode_header() {
    let h = FrameHeader {
        version: 2,
        payload_len: 0x0102_0304,
    };
    let bytes = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0x04, 0x03, 0x02, 0x01];
    assert_eq!(h.to_bytes(), bytes);
    // 0x01020304 is > MAX_FRAME_LEN, so decode_header rejects the length it parsed.
    assert_eq!(
        decode_header(&bytes),
        Err(DecodeError::TooLarge {
            len: 0x0102_0304 + 10,
            max: 4 * 1024 * 1024
        })
    );
    let small = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0x10, 0x00, 0x00, 0x00];
    assert_eq!(
        decode_header(&small),
        Ok(FrameHeader {
            version: 2,
            payload_len: 16
        })
    );
}

#[test]
fn varint_session_and_seq() {
    // 300 = 0b10_0101100 -> AC 02; u64::MAX -> nine FF then 01.
    assert_wire(
        Frame::new(300, u64::MAX, TimePing { t0_ns: 0 }),
        &[
            0xAC, 0x02, // session 300
            0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01, // seq u64::MAX
            0x04, // tag 4 = TimePing
            0x00, // t0 0
        ],
    );
}

#[test]
fn hello_exact_bytes() {
    let hello = Hello::new(
        "pi",
        "0.1",
        vec![SensorInfo {
            sensor: SensorId::RPLIDAR,
            model: "A1".into(),
            firmware: "1.29".into(),
            serial: String::new(),
        }],
    )
    .with_clock_id(*b"boot-id-0123456\x7f");
    assert_eq!(hello.protocol_version, PROTOCOL_VERSION);
    assert_wire(
        Frame::new(9, 0, hello),
        &[
            0x09, 0x00, 0x00, // session 9, seq 0, tag 0 = Hello
            0x02, b'p', b'i', // device name
            0x03, b'0', b'.', b'1', // software version
            0x02, // protocol version 2 (varint u16)
            0x01, // one sensor
            0x00, // sensor 0 = rplidar
            0x02, b'A', b'1', // model
            0x04, b'1', b'.', b'2', b'9', // firmware
            0x00, // empty serial
            b'b', b'o', b'o', b't', b'-', b'i', b'd', b'-', // clock id: 16 raw bytes,
            b'0', b'1', b'2', b'3', b'4', b'5', b'6', 0x7f, // no length prefix
        ],
    );
}

#[test]
fn clock_model_exact_bytes() {
    let model = ClockModel {
        offset_ns: -2,
        skew_ppm: 1.0,
        error_bound_ns: 300,
        skew_bound_ppm: 0.0,
        ref_edge_ns: 5,
        fit_from_edge_ns: 4,
        fit_to_edge_ns: 6,
        valid_from_edge_ns: 6,
        min_delay_ns: 1,
        exchanges: 3,
    };
    assert_eq!(Body::from(model).direction(), Direction::ServerToEdge);
    assert_wire(
        Frame::new(1, 2, model),
        &[
            0x01, 0x02, 0x0b, // session 1, seq 2, tag 11 = ClockModel
            0x03, // offset -2 (zig-zag varint)
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xf0, 0x3f, // skew 1.0 ppm (f64 LE)
            0xac, 0x02, // error bound 300 ns
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, // skew bound 0.0
            0x05, // reference edge time
            0x04, 0x06, // fitted exchanges from, to
            0x06, // valid from edge time
            0x01, // min delay
            0x03, // exchanges
        ],
    );
}

#[test]
fn revolution_exact_bytes() {
    let mut rev = LidarRevolution::new(SensorId::SWEEP, 1000, 1100);
    rev.push(90.0, 1.5, 47, 1050).unwrap();
    assert_eq!(
        rev.samples,
        [RevolutionSample {
            angle_deg: 90.0,
            range_m: 1.5,
            quality: 47,
            offset_ns: 50
        }]
    );
    assert_wire(
        Frame::new(1, 1, rev),
        &[
            0x01, 0x01, 0x01, // session, seq, tag 1 = Revolution
            0x01, // sensor 1 = sweep
            0xE8, 0x07, // t0 1000
            0xCC, 0x08, // t1 1100
            0x01, // one sample
            0x00, 0x00, 0xB4, 0x42, // 90.0f32
            0x00, 0x00, 0xC0, 0x3F, // 1.5f32
            0x2F, // quality 47
            0x32, // offset 50
        ],
    );
}

#[test]
fn imu_exact_bytes_with_and_without_orientation() {
    let imu = ImuSample {
        t_ns: 7,
        accel_mps2: [1.0, -1.0, 0.0],
        gyro_radps: [0.5, 0.0, 0.0],
        mag_ut: [0.0, 0.0, 2.0],
        orientation: None,
    };
    let mut payload = vec![
        0x01, 0x02, 0x02, // session, seq, tag 2 = Imu
        0x07, // t_ns
        0x00, 0x00, 0x80, 0x3F, 0x00, 0x00, 0x80, 0xBF, 0x00, 0x00, 0x00, 0x00, // accel
        0x00, 0x00, 0x00, 0x3F, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, // gyro
        0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x40, // mag
    ];
    let mut none = payload.clone();
    none.push(0x00); // None
    assert_wire(Frame::new(1, 2, imu), &none);

    payload.push(0x01); // Some
    payload.extend_from_slice(&[0x00, 0x00, 0x80, 0x3F]); // w = 1
    payload.extend_from_slice(&[0x00; 12]); // x, y, z = 0
    let with_q = ImuSample {
        orientation: Some([1.0, 0.0, 0.0, 0.0]),
        ..imu
    };
    assert_wire(Frame::new(1, 2, with_q), &payload);
}

#[test]
fn stepper_exact_bytes() {
    assert_wire(
        Frame::new(
            1,
            3,
            StepperState {
                t_ns: 5,
                commanded_angle_deg: 0.5,
                step_index: -3,
                holding: true,
            },
        ),
        &[
            0x01, 0x03, 0x03, // session, seq, tag 3 = Stepper
            0x05, // t_ns
            0x00, 0x00, 0x00, 0x3F, // 0.5f32
            0x05, // -3 zig-zag = 5
            0x01, // holding
        ],
    );
}

#[test]
fn time_pong_and_acks_exact_bytes() {
    assert_wire(
        Frame::new(
            1,
            4,
            TimePong {
                t0_ns: 1,
                t1_ns: 2,
                t2_ns: 128,
            },
        ),
        &[0x01, 0x04, 0x05, 0x01, 0x02, 0x80, 0x01],
    );
    assert_wire(
        Frame::new(1, 0, Ack::UpTo { seq: 127 }),
        &[0x01, 0x00, 0x06, 0x00, 0x7F],
    );
    assert_wire(
        Frame::new(1, 0, Ack::Range { first: 5, last: 6 }),
        &[0x01, 0x00, 0x06, 0x01, 0x05, 0x06],
    );
}

#[test]
fn status_exact_bytes() {
    let events = [
        (StatusEvent::SensorLost, 0x00),
        (StatusEvent::SensorBack, 0x01),
        (StatusEvent::AcquisitionPaused, 0x02),
        (StatusEvent::AcquisitionResumed, 0x03),
    ];
    for (event, tag) in events {
        let status = DeviceStatus {
            t_ns: 0,
            sensor: SensorId::IMU,
            event,
            reason: "x".into(),
        };
        assert_wire(
            Frame::new(1, 0, status),
            &[0x01, 0x00, 0x08, 0x00, 0x02, tag, 0x01, b'x'],
        );
    }
}

#[test]
fn command_exact_bytes() {
    assert_wire(
        Frame::new(
            1,
            0,
            Command::StartStaticScan {
                position: "p1".into(),
                x_m: 1.0,
                y_m: -2.0,
                heading_deg: None,
            },
        ),
        &[
            0x01, 0x00, 0x09, 0x00, // session, seq, tag 9 = Command, 0 = StartStaticScan
            0x02, b'p', b'1', // position
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xF0, 0x3F, // 1.0f64
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xC0, // -2.0f64
            0x00, // no heading
        ],
    );
    assert_wire(
        Frame::new(1, 0, Command::StopStaticScan),
        &[0x01, 0x00, 0x09, 0x01],
    );
    assert_wire(
        Frame::new(
            1,
            0,
            Command::SetMotorSpeed {
                sensor: SensorId::SWEEP,
                hz: 5.0,
            },
        ),
        &[0x01, 0x00, 0x09, 0x02, 0x01, 0x00, 0x00, 0xA0, 0x40],
    );
}

#[test]
fn command_reply_exact_bytes() {
    let reply = CommandReply {
        command_seq: 3,
        t_ns: 7,
        outcome: CommandOutcome::Accepted { scan_id: Some(0) },
    };
    assert_eq!(
        Body::from(reply.clone()).direction(),
        Direction::EdgeToServer
    );
    assert_wire(
        Frame::new(1, 4, reply),
        &[
            0x01, 0x04, 0x0C, // session, seq, tag 12 = CommandReply
            0x03, 0x07, // command_seq, t_ns
            0x00, 0x01, 0x00, // Accepted, Some(scan 0)
        ],
    );
    assert_wire(
        Frame::new(
            1,
            5,
            CommandReply {
                command_seq: 3,
                t_ns: 8,
                outcome: CommandOutcome::Refused {
                    reason: "no".into(),
                },
            },
        ),
        &[0x01, 0x05, 0x0C, 0x03, 0x08, 0x02, 0x02, b'n', b'o'],
    );
    assert_wire(
        Frame::new(
            1,
            6,
            CommandReply {
                command_seq: 3,
                t_ns: 9,
                outcome: CommandOutcome::Waiting { reason: "w".into() },
            },
        ),
        &[0x01, 0x06, 0x0C, 0x03, 0x09, 0x01, 0x01, b'w'],
    );
}

#[test]
fn mounts_exact_bytes_and_direction() {
    let mounts = SensorMounts {
        sensors: vec![SensorMount {
            sensor: SensorId::IMU,
            x_m: 1.0,
            y_m: 0.0,
            z_m: -2.0,
            roll_deg: 0.0,
            pitch_deg: 0.0,
            yaw_deg: 1.0,
        }],
    };
    assert_eq!(Body::from(mounts.clone()).name(), "Mounts");
    assert_eq!(
        Body::from(mounts.clone()).direction(),
        Direction::EdgeToServer
    );
    let mut payload = vec![
        0x01, 0x02, 0x0D, // session, seq, tag 13 = Mounts
        0x01, // one mount
        0x02, // sensor imu
    ];
    for v in [1.0f64, 0.0, -2.0, 0.0, 0.0, 1.0] {
        payload.extend_from_slice(&v.to_le_bytes());
    }
    assert_wire(Frame::new(1, 2, mounts), &payload);
    assert_wire(
        Frame::new(1, 2, SensorMounts { sensors: vec![] }),
        &[0x01, 0x02, 0x0D, 0x00],
    );
}

#[test]
fn pass_markers_exact_bytes_and_direction() {
    let started = PassMarker {
        t_ns: 5,
        event: PassEvent::Started {
            name: "p".into(),
            x_m: 1.0,
            y_m: -2.0,
            heading_deg: 0.0,
        },
    };
    assert_eq!(Body::from(started.clone()).name(), "Pass");
    assert_eq!(
        Body::from(started.clone()).direction(),
        Direction::EdgeToServer
    );
    let mut payload = vec![
        0x01, 0x03, 0x0E, // session, seq, tag 14 = Pass
        0x05, // t_ns
        0x00, 0x01, b'p', // Started, name "p"
    ];
    for v in [1.0f64, -2.0, 0.0] {
        payload.extend_from_slice(&v.to_le_bytes());
    }
    assert_wire(Frame::new(1, 3, started), &payload);
    assert_wire(
        Frame::new(
            1,
            4,
            PassMarker {
                t_ns: 6,
                event: PassEvent::Stopped { name: "p".into() },
            },
        ),
        &[0x01, 0x04, 0x0E, 0x06, 0x01, 0x01, b'p'],
    );
}

#[test]
fn pass_commands_exact_bytes_and_validation() {
    let start = Command::StartPass {
        name: None,
        x_m: 0.0,
        y_m: 0.0,
        heading_deg: 0.0,
    };
    assert_eq!(start.validate(), Ok(()));
    let mut payload = vec![0x01, 0x00, 0x09, 0x03, 0x00]; // Command, StartPass, no name
    payload.extend_from_slice(&[0; 24]);
    assert_wire(Frame::new(1, 0, start), &payload);
    assert_wire(
        Frame::new(1, 0, Command::StopPass),
        &[0x01, 0x00, 0x09, 0x04],
    );
    let named = |name: &str, heading_deg: f64| Command::StartPass {
        name: Some(name.into()),
        x_m: 1.0,
        y_m: 2.0,
        heading_deg,
    };
    assert_eq!(named("hall", 90.0).validate(), Ok(()));
    assert!(named("", 0.0).validate().is_err());
    assert!(named("a\nb", 0.0).validate().is_err());
    assert!(named(&"x".repeat(5 << 20), 0.0).validate().is_err());
    assert_eq!(
        named("a", f64::NAN).validate().unwrap_err().to_string(),
        "heading_deg = NaN is not a finite number"
    );
}

#[test]
fn hostile_counts_in_the_new_bodies_are_malformed_not_allocated() {
    let cases: &[(&str, &[u8])] = &[
        (
            "mounts count u32::MAX with no entries",
            &[0x01, 0x02, 0x0D, 0xFF, 0xFF, 0xFF, 0xFF, 0x0F],
        ),
        (
            "mounts count 2 with one byte",
            &[0x01, 0x02, 0x0D, 0x02, 0x00],
        ),
        (
            "mounts count past u64",
            &[
                0x01, 0x02, 0x0D, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01,
            ],
        ),
        (
            "pass name of u32::MAX bytes",
            &[
                0x01, 0x03, 0x0E, 0x05, 0x01, 0xFF, 0xFF, 0xFF, 0xFF, 0x0F, b'p',
            ],
        ),
        (
            "unknown pass event 2",
            &[0x01, 0x03, 0x0E, 0x05, 0x02, 0x00],
        ),
        ("unknown body tag 15", &[0x01, 0x03, 0x0F, 0x00]),
        ("unknown command 5", &[0x01, 0x03, 0x09, 0x05]),
    ];
    for (what, payload) in cases {
        let mut bytes = header(payload.len() as u8);
        bytes.extend_from_slice(payload);
        match decode(&bytes) {
            Err(e @ DecodeError::Malformed(_)) => assert!(!e.is_fatal(), "{what}"),
            other => panic!("{what}: expected Malformed, got {other:?}"),
        }
    }
}

#[test]
fn mounts_validate_counts_duplicates_and_finiteness() {
    let mount = |sensor, x_m| SensorMount {
        sensor,
        x_m,
        y_m: 0.0,
        z_m: 0.0,
        roll_deg: 0.0,
        pitch_deg: 0.0,
        yaw_deg: 0.0,
    };
    let ok = SensorMounts {
        sensors: vec![mount(SensorId::RPLIDAR, 0.1), mount(SensorId::IMU, 0.0)],
    };
    assert_eq!(ok.validate(), Ok(()));
    assert_eq!(ok.get(SensorId::RPLIDAR).map(|m| m.x_m), Some(0.1));
    assert_eq!(ok.get(SensorId::SWEEP), None);
    let twice = SensorMounts {
        sensors: vec![mount(SensorId::IMU, 0.0), mount(SensorId::IMU, 1.0)],
    };
    assert_eq!(
        twice.validate(),
        Err(InvalidMounts::Duplicate {
            sensor: SensorId::IMU
        })
    );
    let nan = SensorMounts {
        sensors: vec![mount(SensorId::SWEEP, f64::INFINITY)],
    };
    assert_eq!(
        nan.validate().unwrap_err().to_string(),
        "the sweep mount's x_m = inf is not a finite number"
    );
    let many = SensorMounts {
        sensors: (0..=256u32)
            .map(|i| mount(SensorId(i as u8), 0.0))
            .collect(),
    };
    assert!(matches!(
        many.validate(),
        Err(InvalidMounts::TooMany { count: 257, .. })
    ));
}

#[test]
fn static_scan_yaws_exact_bytes() {
    // Two runs of one 2 Hz revolution: the first half at 0°, the second at 1.8° after the
    // blocked sector; the samples themselves are in the Sweep revolution with t0 = 300.
    assert_wire(
        Frame::new(
            1,
            0,
            StaticScan::Yaws(StaticScanYaws {
                scan_id: 2,
                revolution_t0_ns: 300,
                runs: vec![
                    YawRun {
                        first_index: 0,
                        count: 209,
                        yaw_deg: 0.0,
                    },
                    YawRun {
                        first_index: 292,
                        count: 208,
                        yaw_deg: 1.8,
                    },
                ],
            }),
        ),
        &[
            0x01, 0x00, 0x0A, 0x01, // session, seq, tag 10 = StaticScan, 1 = Yaws
            0x02, // scan_id
            0xAC, 0x02, // revolution_t0_ns 300 (varint)
            0x02, // two runs
            0x00, 0xD1, 0x01, // first_index 0, count 209
            0x00, 0x00, 0x00, 0x00, // 0.0f32
            0xA4, 0x02, 0xD0, 0x01, // first_index 292, count 208
            0x66, 0x66, 0xE6, 0x3F, // 1.8f32
        ],
    );
    assert_wire(
        Frame::new(
            1,
            0,
            StaticScan::Warning(StaticScanWarning {
                scan_id: 0,
                t_ns: 5,
                revolution: 6,
                problem: StaticScanProblem::LateStep,
                detail: String::new(),
            }),
        ),
        &[0x01, 0x00, 0x0A, 0x02, 0x00, 0x05, 0x06, 0x00, 0x00],
    );
}

#[test]
fn revolution_of_2000_samples_is_compact() {
    let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 1, 100);
    for i in 0..2000u32 {
        // 50 ms + i * 25 µs: every offset is in [2^21, 2^28), a 4-byte varint.
        let t = 1 + 50_000_000 + u64::from(i) * 25_000;
        rev.push(i as f32 * 0.18, 2.0, 47, t).unwrap();
    }
    let bytes = encode(&Frame::new(1, 1, rev.clone())).unwrap();
    // header 10 + session/seq/tag/sensor/t0/t1 6 + length varint 2000 (2) + 2000 × (4 + 4 + 1 + 4)
    assert_eq!(bytes.len(), 10 + 6 + 2 + 2000 * 13);
    let (Frame { body, .. }, _) = decode(&bytes).unwrap();
    assert_eq!(body, Body::Revolution(rev));
}

#[test]
fn encode_rejects_frames_over_the_maximum() {
    let big = Hello::new("x".repeat(MAX_FRAME_LEN), "0", Vec::new());
    match encode(&Frame::new(1, 0, big)) {
        Err(EncodeError::TooLarge { len, max }) => {
            assert_eq!(max, 4 * 1024 * 1024);
            assert!(len > max);
        }
        other => panic!("expected TooLarge, got {other:?}"),
    }
}

#[test]
fn encode_accepts_a_frame_of_exactly_the_maximum() {
    // payload = session 00, seq 00, tag 00, name (4-byte varint length + n), version "" 00,
    // protocol 02, sensors 00, clock id 16 bytes => 26 + n bytes; header 10 + 26 + n =
    // MAX_FRAME_LEN.
    let n = MAX_FRAME_LEN - 36;
    let hello = Hello::new("y".repeat(n), "", Vec::new());
    let bytes = encode(&Frame::new(0, 0, hello)).unwrap();
    assert_eq!(bytes.len(), MAX_FRAME_LEN);
    assert_eq!(&bytes[6..10], &((MAX_FRAME_LEN - 10) as u32).to_le_bytes());
}

#[test]
fn decode_bad_magic() {
    let mut bytes = encode(&Frame::new(1, 2, Heartbeat { sent_ns: 3 })).unwrap();
    bytes[3] = b'Q';
    assert_eq!(decode(&bytes), Err(DecodeError::BadMagic));
    // Reported as soon as the first wrong byte is seen.
    assert_eq!(decode(b"X"), Err(DecodeError::BadMagic));
    assert_eq!(decode(b"S3X"), Err(DecodeError::BadMagic));
    assert!(DecodeError::BadMagic.is_fatal());
}

#[test]
fn decode_wrong_version() {
    let bytes = [0x53, 0x33, 0x44, 0x50, 0x03, 0x00, 0x04, 0x00, 0x00, 0x00];
    let err = decode(&bytes).unwrap_err();
    assert_eq!(
        err,
        DecodeError::UnsupportedVersion {
            got: 3,
            supported: 2
        }
    );
    assert!(err.is_fatal());
    // Reported before the length bytes arrive.
    assert_eq!(
        decode(&[0x53, 0x33, 0x44, 0x50, 0x00, 0x01]),
        Err(DecodeError::UnsupportedVersion {
            got: 256,
            supported: 2
        })
    );
}

#[test]
fn decode_too_large_before_payload_arrives() {
    // payload 0x3FFFF7 + header 10 = 0x400001 = MAX_FRAME_LEN + 1
    let over = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0xF7, 0xFF, 0x3F, 0x00];
    let err = decode(&over).unwrap_err();
    assert_eq!(
        err,
        DecodeError::TooLarge {
            len: 4_194_305,
            max: 4_194_304
        }
    );
    assert!(err.is_fatal());
    let max = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0xFF, 0xFF, 0xFF, 0xFF];
    assert_eq!(
        decode(&max),
        Err(DecodeError::TooLarge {
            len: 0xFFFF_FFFF + 10,
            max: 4_194_304
        })
    );
    // Exactly the maximum is accepted and waits for its payload.
    let at_max = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0xF6, 0xFF, 0x3F, 0x00];
    assert_eq!(
        decode(&at_max),
        Err(DecodeError::Incomplete { needed: 4_194_294 })
    );
}

#[test]
fn decode_truncated_header_and_payload() {
    let bytes = [
        0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0x04, 0x00, 0x00, 0x00, 0x01, 0x02, 0x07, 0x03,
    ];
    assert_eq!(decode(&[]), Err(DecodeError::Incomplete { needed: 10 }));
    assert_eq!(
        decode(&bytes[..3]),
        Err(DecodeError::Incomplete { needed: 7 })
    );
    assert_eq!(
        decode(&bytes[..10]),
        Err(DecodeError::Incomplete { needed: 4 })
    );
    assert_eq!(
        decode(&bytes[..13]),
        Err(DecodeError::Incomplete { needed: 1 })
    );
    assert!(!DecodeError::Incomplete { needed: 1 }.is_fatal());
}

#[test]
fn decode_garbage_payloads() {
    let cases: &[(&str, &[u8])] = &[
        ("unknown body tag 10", &[0x01, 0x02, 0x0A, 0x00]),
        ("payload shorter than its frame", &[0x01, 0x02, 0x07]),
        ("empty payload", &[]),
        (
            "varint longer than a u64",
            &[
                0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01,
            ],
        ),
        ("trailing byte", &[0x01, 0x02, 0x07, 0x03, 0x00]),
        (
            "bool 2",
            &[0x01, 0x03, 0x03, 0x05, 0, 0, 0, 0x3F, 0x05, 0x02],
        ),
        (
            "invalid UTF-8 reason",
            &[0x01, 0x00, 0x08, 0x00, 0x02, 0x00, 0x01, 0xFF],
        ),
        (
            "unknown status event 4",
            &[0x01, 0x00, 0x08, 0x00, 0x02, 0x04, 0x00],
        ),
        (
            "option tag 2",
            &[
                0x01, 0x00, 0x09, 0x00, 0x00, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0x02,
            ],
        ),
        (
            "vector length beyond the payload",
            &[0x01, 0x01, 0x01, 0x00, 0x00, 0x00, 0xFF, 0xFF, 0x03],
        ),
    ];
    for (what, payload) in cases {
        let mut bytes = header(payload.len() as u8);
        bytes.extend_from_slice(payload);
        match decode(&bytes) {
            Err(e @ DecodeError::Malformed(_)) => assert!(!e.is_fatal(), "{what}"),
            other => panic!("{what}: expected Malformed, got {other:?}"),
        }
    }
}

#[test]
fn decode_reports_trailing_bytes_in_the_message() {
    let mut bytes = header(5);
    bytes.extend_from_slice(&[0x01, 0x02, 0x07, 0x03, 0x00]);
    assert_eq!(
        decode(&bytes),
        Err(DecodeError::Malformed(
            "1 trailing bytes after the frame".into()
        ))
    );
}

#[test]
fn decode_leaves_the_next_frame_alone() {
    let mut bytes = header(4);
    bytes.extend_from_slice(&[0x01, 0x02, 0x07, 0x03]);
    bytes.extend_from_slice(&MAGIC_V2);
    let (frame, used) = decode(&bytes).unwrap();
    assert_eq!(used, 14);
    assert_eq!(frame, Frame::new(1, 2, Heartbeat { sent_ns: 3 }));
}

#[test]
fn reader_skips_a_malformed_frame_and_continues() {
    let mut stream = header(3);
    stream.extend_from_slice(&[0x01, 0x02, 0x0A]); // unknown tag
    stream.extend_from_slice(&header(4));
    stream.extend_from_slice(&[0x01, 0x03, 0x07, 0x09]);
    let mut reader = FrameReader::new();
    reader.push(&stream);
    assert_eq!(reader.buffered(), 27);
    assert!(matches!(
        reader.next_frame(),
        Err(DecodeError::Malformed(_))
    ));
    assert_eq!(reader.buffered(), 14);
    assert_eq!(
        reader.next_frame(),
        Ok(Some(Frame::new(1, 3, Heartbeat { sent_ns: 9 })))
    );
    assert_eq!(reader.next_frame(), Ok(None));
    assert_eq!(reader.buffered(), 0);
}

#[test]
fn reader_fatal_error_sticks() {
    let mut reader = FrameReader::new();
    reader.push(&[0x53, 0x33, 0x44, 0x50, 0x07, 0x00]);
    let expected = Err(DecodeError::UnsupportedVersion {
        got: 7,
        supported: 2,
    });
    assert_eq!(reader.next_frame(), expected);
    reader.push(&[0x00; 8]);
    assert_eq!(reader.next_frame(), expected);
    assert_eq!(reader.buffered(), 14);
}

#[test]
fn reader_byte_by_byte() {
    let stream = [
        0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0x04, 0x00, 0x00, 0x00, 0x01, 0x02, 0x07, 0x03,
    ];
    let mut reader = FrameReader::new();
    for &b in &stream[..13] {
        reader.push(&[b]);
        assert_eq!(reader.next_frame(), Ok(None));
    }
    reader.push(&stream[13..]);
    assert_eq!(
        reader.next_frame(),
        Ok(Some(Frame::new(1, 2, Heartbeat { sent_ns: 3 })))
    );
}
