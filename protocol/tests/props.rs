//! Property tests: arbitrary frames round-trip through `encode` / `decode` and through a
//! `FrameReader` fed at random chunk boundaries; arbitrary bytes never panic the decoder and never
//! produce a frame without a valid header.

use proptest::prelude::*;
use scan3d_protocol::{
    Ack, Body, ClockModel, Command, CommandOutcome, CommandReply, DecodeError, DeviceStatus, Frame,
    FrameReader, HEADER_LEN, Heartbeat, Hello, ImuSample, LidarRevolution, MountInfo, PassEvent,
    PassMarker, RevolutionSample, SensorId, SensorInfo, SensorMount, SensorMounts, StaticScan,
    StaticScanEnd, StaticScanOutcome, StaticScanProblem, StaticScanStart, StaticScanWarning,
    StaticScanYaws, StatusEvent, StepperState, TimePing, TimePong, YawRun, decode, encode,
};

/// `S3DP` + version 1 LE: the only start a decodable frame can have.
const VALID_START: [u8; 6] = [0x53, 0x33, 0x44, 0x50, 0x02, 0x00];

/// Any `f32` except NaN (NaN != NaN would make equality checks meaningless).
fn f32s() -> impl Strategy<Value = f32> {
    use proptest::num::f32::*;
    POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO | INFINITE
}

/// Any `f64` except NaN.
fn f64s() -> impl Strategy<Value = f64> {
    use proptest::num::f64::*;
    POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO | INFINITE
}

fn text() -> impl Strategy<Value = String> {
    ".{0,12}"
}

fn sensor() -> impl Strategy<Value = SensorId> {
    any::<u8>().prop_map(SensorId)
}

fn hello() -> impl Strategy<Value = Hello> {
    let info = (sensor(), text(), text(), text()).prop_map(|(sensor, model, firmware, serial)| {
        SensorInfo {
            sensor,
            model,
            firmware,
            serial,
        }
    });
    (
        text(),
        text(),
        any::<u16>(),
        prop::collection::vec(info, 0..5),
        any::<[u8; 16]>(),
    )
        .prop_map(
            |(device_name, software_version, protocol_version, sensors, clock_id)| Hello {
                device_name,
                software_version,
                protocol_version,
                sensors,
                clock_id,
            },
        )
}

fn revolution() -> impl Strategy<Value = LidarRevolution> {
    let sample = (f32s(), f32s(), any::<u8>(), any::<u32>()).prop_map(
        |(angle_deg, range_m, quality, offset_ns)| RevolutionSample {
            angle_deg,
            range_m,
            quality,
            offset_ns,
        },
    );
    (
        sensor(),
        any::<u64>(),
        any::<u64>(),
        prop::collection::vec(sample, 0..40),
    )
        .prop_map(|(sensor, t0_ns, t1_ns, samples)| LidarRevolution {
            sensor,
            t0_ns,
            t1_ns,
            samples,
        })
}

fn triple() -> impl Strategy<Value = [f32; 3]> {
    [f32s(), f32s(), f32s()]
}

fn imu() -> impl Strategy<Value = ImuSample> {
    (
        any::<u64>(),
        triple(),
        triple(),
        triple(),
        prop::option::of([f32s(), f32s(), f32s(), f32s()]),
    )
        .prop_map(
            |(t_ns, accel_mps2, gyro_radps, mag_ut, orientation)| ImuSample {
                t_ns,
                accel_mps2,
                gyro_radps,
                mag_ut,
                orientation,
            },
        )
}

fn stepper() -> impl Strategy<Value = StepperState> {
    (any::<u64>(), f32s(), any::<i64>(), any::<bool>()).prop_map(
        |(t_ns, commanded_angle_deg, step_index, holding)| StepperState {
            t_ns,
            commanded_angle_deg,
            step_index,
            holding,
        },
    )
}

fn ack() -> impl Strategy<Value = Ack> {
    prop_oneof![
        any::<u64>().prop_map(|seq| Ack::UpTo { seq }),
        (any::<u64>(), any::<u64>()).prop_map(|(first, last)| Ack::Range { first, last }),
    ]
}

fn status() -> impl Strategy<Value = DeviceStatus> {
    let event = prop_oneof![
        Just(StatusEvent::SensorLost),
        Just(StatusEvent::SensorBack),
        Just(StatusEvent::AcquisitionPaused),
        Just(StatusEvent::AcquisitionResumed),
    ];
    (any::<u64>(), sensor(), event, text()).prop_map(|(t_ns, sensor, event, reason)| DeviceStatus {
        t_ns,
        sensor,
        event,
        reason,
    })
}

fn command() -> impl Strategy<Value = Command> {
    prop_oneof![
        (text(), f64s(), f64s(), prop::option::of(f64s())).prop_map(
            |(position, x_m, y_m, heading_deg)| Command::StartStaticScan {
                position,
                x_m,
                y_m,
                heading_deg,
            }
        ),
        Just(Command::StopStaticScan),
        (sensor(), f32s()).prop_map(|(sensor, hz)| Command::SetMotorSpeed { sensor, hz }),
        (prop::option::of(text()), f64s(), f64s(), f64s()).prop_map(
            |(name, x_m, y_m, heading_deg)| Command::StartPass {
                name,
                x_m,
                y_m,
                heading_deg,
            }
        ),
        Just(Command::StopPass),
    ]
}

fn static_scan() -> impl Strategy<Value = StaticScan> {
    let mount = (f64s(), f64s(), f64s()).prop_map(|(axis_offset_m, height_m, azimuth_zero_deg)| {
        MountInfo {
            axis_offset_m,
            height_m,
            azimuth_zero_deg,
        }
    });
    let start = (
        (any::<u32>(), any::<u64>(), text(), f64s(), f64s()),
        (f64s(), f64s(), f64s(), f64s(), mount),
    )
        .prop_map(
            |(
                (scan_id, t_ns, position, x_m, y_m),
                (heading_deg, step_deg, total_deg, blocked_sector_deg, mount),
            )| StaticScanStart {
                scan_id,
                t_ns,
                position,
                x_m,
                y_m,
                heading_deg,
                step_deg,
                total_deg,
                blocked_sector_deg,
                mount,
            },
        );
    let run =
        (any::<u32>(), any::<u32>(), f32s()).prop_map(|(first_index, count, yaw_deg)| YawRun {
            first_index,
            count,
            yaw_deg,
        });
    let yaws = (
        any::<u32>(),
        any::<u64>(),
        prop::collection::vec(run, 0..40),
    )
        .prop_map(|(scan_id, revolution_t0_ns, runs)| StaticScanYaws {
            scan_id,
            revolution_t0_ns,
            runs,
        });
    let problem = prop_oneof![
        Just(StaticScanProblem::LateStep),
        Just(StaticScanProblem::StepFailed),
        Just(StaticScanProblem::SectorMissed),
        Just(StaticScanProblem::PredictedLate),
    ];
    let warning = (any::<u32>(), any::<u64>(), any::<u32>(), problem, text()).prop_map(
        |(scan_id, t_ns, revolution, problem, detail)| StaticScanWarning {
            scan_id,
            t_ns,
            revolution,
            problem,
            detail,
        },
    );
    let outcome = prop_oneof![
        Just(StaticScanOutcome::Completed),
        Just(StaticScanOutcome::Aborted),
        Just(StaticScanOutcome::Stopped),
    ];
    let end = (
        (any::<u32>(), any::<u64>(), outcome, f64s(), any::<u32>()),
        (
            any::<u64>(),
            any::<u64>(),
            any::<u64>(),
            any::<u64>(),
            any::<u64>(),
        ),
    )
        .prop_map(
            |(
                (scan_id, t_ns, outcome, yaw_deg, revolutions),
                (tagged, blocked, untrusted, late_steps, failed_steps),
            )| StaticScanEnd {
                scan_id,
                t_ns,
                outcome,
                yaw_deg,
                revolutions,
                tagged,
                blocked,
                untrusted,
                late_steps,
                failed_steps,
            },
        );
    prop_oneof![
        start.prop_map(StaticScan::Started),
        yaws.prop_map(StaticScan::Yaws),
        warning.prop_map(StaticScan::Warning),
        end.prop_map(StaticScan::Finished),
    ]
}

fn body() -> impl Strategy<Value = Body> {
    prop_oneof![
        hello().prop_map(Body::Hello),
        revolution().prop_map(Body::Revolution),
        imu().prop_map(Body::Imu),
        stepper().prop_map(Body::Stepper),
        any::<u64>().prop_map(|t0_ns| Body::TimePing(TimePing { t0_ns })),
        (any::<u64>(), any::<u64>(), any::<u64>()).prop_map(|(t0_ns, t1_ns, t2_ns)| {
            Body::TimePong(TimePong {
                t0_ns,
                t1_ns,
                t2_ns,
            })
        }),
        ack().prop_map(Body::Ack),
        any::<u64>().prop_map(|sent_ns| Body::Heartbeat(Heartbeat { sent_ns })),
        status().prop_map(Body::Status),
        command().prop_map(Body::Command),
        static_scan().prop_map(Body::StaticScan),
        clock_model().prop_map(Body::ClockModel),
        command_reply().prop_map(Body::CommandReply),
        mounts().prop_map(Body::Mounts),
        pass().prop_map(Body::Pass),
    ]
}

fn mounts() -> impl Strategy<Value = SensorMounts> {
    let mount = (sensor(), (f64s(), f64s(), f64s()), (f64s(), f64s(), f64s())).prop_map(
        |(sensor, (x_m, y_m, z_m), (roll_deg, pitch_deg, yaw_deg))| SensorMount {
            sensor,
            x_m,
            y_m,
            z_m,
            roll_deg,
            pitch_deg,
            yaw_deg,
        },
    );
    prop::collection::vec(mount, 0..5).prop_map(|sensors| SensorMounts { sensors })
}

fn pass() -> impl Strategy<Value = PassMarker> {
    let event = prop_oneof![
        (text(), f64s(), f64s(), f64s()).prop_map(|(name, x_m, y_m, heading_deg)| {
            PassEvent::Started {
                name,
                x_m,
                y_m,
                heading_deg,
            }
        }),
        text().prop_map(|name| PassEvent::Stopped { name }),
    ];
    (any::<u64>(), event).prop_map(|(t_ns, event)| PassMarker { t_ns, event })
}

fn command_reply() -> impl Strategy<Value = CommandReply> {
    let outcome = prop_oneof![
        proptest::option::of(any::<u32>()).prop_map(|scan_id| CommandOutcome::Accepted { scan_id }),
        text().prop_map(|reason| CommandOutcome::Waiting { reason }),
        text().prop_map(|reason| CommandOutcome::Refused { reason }),
    ];
    (any::<u64>(), any::<u64>(), outcome).prop_map(|(command_seq, t_ns, outcome)| CommandReply {
        command_seq,
        t_ns,
        outcome,
    })
}

fn clock_model() -> impl Strategy<Value = ClockModel> {
    (
        (any::<i64>(), f64s(), any::<u64>(), f64s()),
        (any::<u64>(), any::<u64>(), any::<u64>(), any::<u32>()),
        (any::<u64>(), any::<u64>()),
    )
        .prop_map(
            |(
                (offset_ns, skew_ppm, error_bound_ns, skew_bound_ppm),
                (ref_edge_ns, valid_from_edge_ns, min_delay_ns, exchanges),
                (fit_from_edge_ns, fit_to_edge_ns),
            )| ClockModel {
                offset_ns,
                skew_ppm,
                error_bound_ns,
                skew_bound_ppm,
                ref_edge_ns,
                fit_from_edge_ns,
                fit_to_edge_ns,
                valid_from_edge_ns,
                min_delay_ns,
                exchanges,
            },
        )
}

fn frame() -> impl Strategy<Value = Frame> {
    (any::<u64>(), any::<u64>(), body()).prop_map(|(session_id, seq, body)| Frame {
        session_id,
        seq,
        body,
    })
}

/// Feeds `bytes` to a fresh reader in chunks of the given sizes (cycled), collecting every
/// result the reader gives until it asks for more bytes.
fn feed(bytes: &[u8], chunks: &[usize]) -> Vec<Result<Frame, DecodeError>> {
    let mut reader = FrameReader::new();
    let mut out = Vec::new();
    let mut rest = bytes;
    let mut sizes = chunks.iter().cycle();
    while !rest.is_empty() {
        let n = (*sizes.next().unwrap_or(&1)).clamp(1, rest.len());
        let (chunk, tail) = rest.split_at(n);
        rest = tail;
        reader.push(chunk);
        loop {
            match reader.next_frame() {
                Ok(Some(frame)) => out.push(Ok(frame)),
                Ok(None) => break,
                Err(e) => {
                    let fatal = e.is_fatal();
                    out.push(Err(e));
                    if fatal {
                        return out;
                    }
                }
            }
        }
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn frames_round_trip(frame in frame()) {
        let bytes = encode(&frame).unwrap();
        prop_assert_eq!(&bytes[..6], &VALID_START[..]);
        let payload_len = u32::from_le_bytes([bytes[6], bytes[7], bytes[8], bytes[9]]);
        prop_assert_eq!(payload_len as usize, bytes.len() - HEADER_LEN);
        prop_assert_eq!(decode(&bytes), Ok((frame, bytes.len())));
    }

    #[test]
    fn every_strict_prefix_is_incomplete(frame in frame(), cut in any::<prop::sample::Index>()) {
        let bytes = encode(&frame).unwrap();
        let at = cut.index(bytes.len());
        match decode(&bytes[..at]) {
            Err(DecodeError::Incomplete { needed }) => {
                prop_assert!(needed >= 1 && needed <= bytes.len() - at);
            }
            other => prop_assert!(false, "prefix of {} bytes gave {:?}", at, other),
        }
    }

    #[test]
    fn reader_reassembles_frames_split_anywhere(
        frames in prop::collection::vec(frame(), 1..5),
        chunks in prop::collection::vec(1usize..40, 1..12),
    ) {
        let stream: Vec<u8> = frames.iter().flat_map(|f| encode(f).unwrap()).collect();
        let got = feed(&stream, &chunks);
        let expected: Vec<Result<Frame, DecodeError>> = frames.into_iter().map(Ok).collect();
        prop_assert_eq!(got, expected);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn random_bytes_never_panic_nor_decode_without_header(
        keep in 0usize..=VALID_START.len(),
        random in prop::collection::vec(any::<u8>(), 0..200),
        chunks in prop::collection::vec(1usize..32, 1..8),
    ) {
        // Random bytes behind 0 to 6 bytes of a valid start, so every header check is reached.
        let mut bytes = VALID_START[..keep].to_vec();
        bytes.extend_from_slice(&random);
        if let Ok((_, used)) = decode(&bytes) {
            prop_assert!(bytes.starts_with(&VALID_START));
            prop_assert!(used <= bytes.len());
        }
        for result in feed(&bytes, &chunks) {
            if result.is_ok() {
                prop_assert!(bytes.starts_with(&VALID_START));
            }
        }
    }

    #[test]
    fn valid_header_random_payload_never_panics(
        payload in prop::collection::vec(any::<u8>(), 0..200),
        chunks in prop::collection::vec(1usize..32, 1..8),
    ) {
        let mut bytes = VALID_START.to_vec();
        bytes.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        bytes.extend_from_slice(&payload);
        match decode(&bytes) {
            Ok((_, used)) => prop_assert_eq!(used, bytes.len()),
            Err(e) => prop_assert!(matches!(e, DecodeError::Malformed(_)), "{:?}", e),
        }
        let results = feed(&bytes, &chunks);
        prop_assert_eq!(results.len(), 1);
    }

    #[test]
    fn corrupted_frames_never_panic(
        frame in frame(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..4),
        chunks in prop::collection::vec(1usize..32, 1..8),
    ) {
        let mut bytes = encode(&frame).unwrap();
        for (at, mask) in &flips {
            let i = at.index(bytes.len());
            bytes[i] ^= mask;
        }
        if decode(&bytes).is_ok() {
            prop_assert!(bytes.starts_with(&VALID_START));
        }
        for result in feed(&bytes, &chunks) {
            if result.is_ok() {
                prop_assert!(bytes.starts_with(&VALID_START));
            }
        }
    }
}
