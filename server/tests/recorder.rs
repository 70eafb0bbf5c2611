//! The session recorder against real files: round trip, duplicates across restarts, crash
//! tolerance (files cut short inside their last chunk), acknowledgement prefix, and validity for
//! the mcap crate's own strict readers.

use std::fs;
use std::path::{Path, PathBuf};

use scan3d_protocol::{
    Ack, Command, DeviceStatus, Frame, Heartbeat, Hello, ImuSample, LidarRevolution, SensorId,
    SensorInfo, StatusEvent, StepperState, TimePong, encode,
};
use scan3d_server::recording::{
    Appended, CHUNKS_PER_FILE, RecorderError, SessionRecorder, list_sessions, read_session,
    visit_session,
};

const EDGE: &str = "trolley-pi";
const SESSION: u64 = 1;
/// 2026-01-01T00:00:00Z in ns since the UNIX epoch: a plausible server receive time.
const T0: u64 = 1_767_225_600_000_000_000;

/// A revolution of `n` samples with pseudo-random (badly compressible) values.
fn revolution(sensor: SensorId, t0_ns: u64, n: u32, seed: u64) -> LidarRevolution {
    let mut rev = LidarRevolution::new(sensor, t0_ns, t0_ns + 100_000_000);
    let mut x = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    for i in 0..n {
        x = x
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let range = (x >> 40) as f32 / 1000.0;
        rev.push(
            i as f32 * 360.0 / n as f32,
            range,
            (x >> 56) as u8,
            t0_ns + u64::from(i) * 40_000,
        )
        .expect("sample within the revolution");
    }
    rev
}

/// Frames of every edge body type, seqs 0.., with the topic each must be recorded on.
fn mixed_frames() -> Vec<(Frame, &'static str)> {
    let hello = Hello::new(
        EDGE,
        "0.1.0",
        vec![SensorInfo {
            sensor: SensorId::RPLIDAR,
            model: "A2".into(),
            firmware: "1.29".into(),
            serial: "X".into(),
        }],
    );
    let bodies: Vec<(scan3d_protocol::Body, &'static str)> = vec![
        (hello.into(), "/scan3d/hello"),
        (
            revolution(SensorId::RPLIDAR, 1_000, 360, 1).into(),
            "/scan3d/lidar/rplidar",
        ),
        (
            revolution(SensorId::SWEEP, 2_000, 500, 2).into(),
            "/scan3d/lidar/sweep",
        ),
        (
            ImuSample {
                t_ns: 3_000,
                accel_mps2: [0.1, 0.2, 9.81],
                gyro_radps: [0.0, 0.01, 0.0],
                mag_ut: [20.0, -3.0, 40.0],
                orientation: Some([1.0, 0.0, 0.0, 0.0]),
            }
            .into(),
            "/scan3d/imu",
        ),
        (
            StepperState {
                t_ns: 4_000,
                commanded_angle_deg: 1.8,
                step_index: 1,
                holding: true,
            }
            .into(),
            "/scan3d/stepper",
        ),
        (
            TimePong {
                t0_ns: 10,
                t1_ns: 5_000,
                t2_ns: 5_100,
            }
            .into(),
            "/scan3d/timepong",
        ),
        (
            DeviceStatus {
                t_ns: 6_000,
                sensor: SensorId::SWEEP,
                event: StatusEvent::SensorLost,
                reason: "no answer".into(),
            }
            .into(),
            "/scan3d/status",
        ),
        (Heartbeat { sent_ns: 7_000 }.into(), "/scan3d/heartbeat"),
        (Ack::UpTo { seq: 0 }.into(), "/scan3d/ack"),
    ];
    bodies
        .into_iter()
        .enumerate()
        .map(|(seq, (body, topic))| (Frame::new(SESSION, seq as u64, body), topic))
        .collect()
}

fn append(rec: &mut SessionRecorder, frame: &Frame, t: u64) -> Appended {
    let raw = encode(frame).expect("encode");
    rec.append(&raw, frame, t).expect("append")
}

fn session_path(data_dir: &Path) -> PathBuf {
    data_dir
        .join("sessions")
        .join(EDGE)
        .join("0000000000000001")
}

fn seqs(dir: &Path) -> Vec<u64> {
    read_session(dir)
        .expect("read")
        .iter()
        .map(|r| r.frame.seq)
        .collect()
}

#[test]
fn round_trip_keeps_exact_bytes_topics_and_times() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let frames = mixed_frames();
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    assert_eq!(rec.path(), session_path(tmp.path()).join("0000.mcap"));
    let mut raws = Vec::new();
    for (i, (frame, _)) in frames.iter().enumerate() {
        let raw = encode(frame).expect("encode");
        assert_eq!(
            rec.append(&raw, frame, T0 + i as u64).expect("append"),
            Appended::Buffered
        );
        raws.push(raw);
    }
    // The protocol's documented example frame, byte for byte, on the heartbeat channel.
    let hb = Frame::new(SESSION, 2, Heartbeat { sent_ns: 3 });
    let hb_raw = vec![
        0x53, 0x33, 0x44, 0x50, 0x01, 0x00, 0x04, 0x00, 0x00, 0x00, 0x01, 0x02, 0x07, 0x03,
    ];
    // seq 2 is already recorded (the sweep revolution): a duplicate, whatever its body.
    assert_eq!(
        rec.append(&hb_raw, &hb, T0).expect("append"),
        Appended::Duplicate
    );
    let command = Frame::new(SESSION, 0, Command::StopStaticScan);
    let command_raw = encode(&command).expect("encode");
    assert_eq!(
        rec.append_command(&command_raw, &command, T0 + 100)
            .expect("command"),
        Appended::Buffered
    );
    assert_eq!(rec.pending(), frames.len());
    assert_eq!(rec.commit().expect("commit"), Some(frames.len() as u64 - 1));
    assert_eq!(rec.pending(), 0);
    assert_eq!(rec.close().expect("close"), Some(frames.len() as u64 - 1));

    let read = read_session(&session_path(tmp.path())).expect("read");
    assert_eq!(read.len(), frames.len() + 1);
    for (i, (frame, topic)) in frames.iter().enumerate() {
        assert_eq!(read[i].raw, raws[i], "raw bytes of frame {i}");
        assert_eq!(&read[i].frame, frame);
        assert_eq!(read[i].topic, *topic);
        assert_eq!(read[i].log_time_ns, T0 + i as u64);
    }
    let last = &read[frames.len()];
    assert_eq!(last.topic, "/scan3d/command");
    assert_eq!(last.frame, command);
    assert_eq!(last.log_time_ns, T0 + 100);
}

#[test]
fn closed_files_satisfy_the_official_reader() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let frames = mixed_frames();
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    for (i, (frame, _)) in frames.iter().enumerate() {
        append(&mut rec, frame, T0 + i as u64 * 1000);
        if i % 3 == 2 {
            rec.commit().expect("commit");
        }
    }
    // Two more revolutions so one topic has several messages.
    for seq in 9..11u64 {
        let f = Frame::new(SESSION, seq, revolution(SensorId::RPLIDAR, seq, 100, seq));
        append(&mut rec, &f, T0 + seq * 1000);
    }
    rec.close().expect("close");

    let bytes = fs::read(session_path(tmp.path()).join("0000.mcap")).expect("read file");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary parses")
        .expect("file has a summary");
    let stats = summary.stats.as_ref().expect("statistics");
    assert_eq!(stats.message_count, 11);
    assert_eq!(stats.channel_count, 9);
    assert_eq!(stats.message_start_time, T0);
    assert_eq!(stats.message_end_time, T0 + 10_000);
    assert!(stats.chunk_count >= 4, "every commit ends a chunk");
    let per_topic: std::collections::BTreeMap<String, u64> = stats
        .channel_message_counts
        .iter()
        .map(|(id, n)| (summary.channels[id].topic.clone(), *n))
        .collect();
    let expected: std::collections::BTreeMap<String, u64> = [
        ("/scan3d/hello", 1),
        ("/scan3d/lidar/rplidar", 3),
        ("/scan3d/lidar/sweep", 1),
        ("/scan3d/imu", 1),
        ("/scan3d/stepper", 1),
        ("/scan3d/timepong", 1),
        ("/scan3d/status", 1),
        ("/scan3d/heartbeat", 1),
        ("/scan3d/ack", 1),
    ]
    .into_iter()
    .map(|(t, n)| (t.to_string(), n))
    .collect();
    assert_eq!(per_topic, expected);
    for channel in summary.channels.values() {
        assert_eq!(channel.message_encoding, "scan3d-frame");
        assert!(channel.schema.is_none());
    }

    // The strict streaming reader (end magic, CRCs) reads every message without error.
    let messages: Vec<mcap::Message> = mcap::MessageStream::new(&bytes)
        .expect("stream")
        .collect::<Result<_, _>>()
        .expect("every message reads");
    assert_eq!(messages.len(), 11);
    let rev = &messages[1];
    assert_eq!(rev.channel.topic, "/scan3d/lidar/rplidar");
    assert_eq!(rev.channel.metadata["body"], "Revolution");
    assert_eq!(rev.channel.metadata["sensor"], "rplidar");
    assert_eq!(rev.sequence, 1);
    assert_eq!(rev.log_time, T0 + 1000);
    // publish_time: the revolution's end on the edge clock (t0 1000 + 100 ms).
    assert_eq!(rev.publish_time, 100_001_000);
    let hello = &messages[0];
    assert_eq!(
        hello.publish_time, hello.log_time,
        "no edge time in a hello"
    );
    assert_eq!(
        hello.data.as_ref(),
        encode(&frames[0].0).expect("encode").as_slice()
    );
}

#[test]
fn duplicates_are_ignored_within_a_run_and_across_a_restart() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = session_path(tmp.path());
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq * 10 });

    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    for seq in 0..5 {
        assert_eq!(append(&mut rec, &hb(seq), T0 + seq), Appended::Buffered);
    }
    assert_eq!(
        append(&mut rec, &hb(3), T0),
        Appended::Duplicate,
        "buffered"
    );
    assert_eq!(rec.commit().expect("commit"), Some(4));
    assert_eq!(append(&mut rec, &hb(4), T0), Appended::Duplicate, "durable");
    rec.close().expect("close");

    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(
        rec.path(),
        dir.join("0001.mcap"),
        "a restart starts a new file"
    );
    assert_eq!(rec.durable_prefix(), Some(4));
    for seq in 0..5 {
        assert_eq!(append(&mut rec, &hb(seq), T0), Appended::Duplicate, "{seq}");
    }
    assert_eq!(rec.commit().expect("nothing to commit"), Some(4));
    for seq in 5..8 {
        assert_eq!(append(&mut rec, &hb(seq), T0 + seq), Appended::Buffered);
    }
    assert_eq!(rec.commit().expect("commit"), Some(7));
    rec.close().expect("close");

    assert_eq!(seqs(&dir), (0..8).collect::<Vec<_>>());
    let sessions = list_sessions(tmp.path()).expect("list");
    assert_eq!(sessions.len(), 1);
    assert_eq!(sessions[0].edge, EDGE);
    assert_eq!(sessions[0].session_id, SESSION);
    assert_eq!(sessions[0].files, 2);
    assert_eq!(sessions[0].incomplete_files, 0);
    assert_eq!(sessions[0].frames, 8);
    assert_eq!(sessions[0].frames_per_topic["/scan3d/heartbeat"], 8);
    assert_eq!(sessions[0].first_log_time_ns, Some(T0));
    assert_eq!(sessions[0].last_log_time_ns, Some(T0 + 7));
}

#[test]
fn commit_acknowledges_only_the_contiguous_prefix() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq });
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    assert_eq!(rec.commit().expect("empty commit"), None);
    append(&mut rec, &hb(1), T0);
    assert_eq!(rec.commit().expect("commit"), None, "0 is missing");
    append(&mut rec, &hb(0), T0);
    append(&mut rec, &hb(3), T0);
    append(&mut rec, &hb(5), T0);
    assert_eq!(
        rec.commit().expect("commit"),
        Some(1),
        "stops before the gap at 2"
    );
    append(&mut rec, &hb(2), T0);
    assert_eq!(rec.commit().expect("commit"), Some(3), "gap at 4 remains");
    append(&mut rec, &hb(4), T0);
    // Buffered but not committed: not acknowledged yet.
    assert_eq!(rec.durable_prefix(), Some(3));
    assert_eq!(rec.commit().expect("commit"), Some(5));
    rec.close().expect("close");

    // Out-of-order durable seqs survive a restart too.
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_prefix(), Some(5));
    append(&mut rec, &hb(7), T0);
    rec.close().expect("close");
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_prefix(), Some(5));
    assert_eq!(append(&mut rec, &hb(7), T0), Appended::Duplicate);
    append(&mut rec, &hb(6), T0);
    assert_eq!(rec.commit().expect("commit"), Some(7));
    rec.close().expect("close");
}

#[test]
fn durable_ranges_list_every_durable_seq_including_those_past_a_gap() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq });
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    assert!(rec.durable_ranges().is_empty());
    for seq in [1, 2, 4, 5, 6, 9] {
        append(&mut rec, &hb(seq), T0);
    }
    assert!(rec.durable_ranges().is_empty(), "nothing committed yet");
    rec.commit().expect("commit");
    assert_eq!(rec.durable_ranges(), vec![1..=2, 4..=6, 9..=9]);
    append(&mut rec, &hb(0), T0);
    append(&mut rec, &hb(3), T0);
    rec.commit().expect("commit");
    assert_eq!(rec.durable_ranges(), vec![0..=6, 9..=9]);
    rec.close().expect("close");
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_ranges(), vec![0..=6, 9..=9], "after a restart");
}

#[test]
fn an_undecodable_frame_is_recorded_raw_acknowledged_and_its_seq_is_a_duplicate_afterwards() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq });
    let garbage = b"S3DP\x01\x00\x00\x00\x03\x00\xff\xff\xff".to_vec();
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    append(&mut rec, &hb(0), T0);
    assert_eq!(
        rec.append_undecodable(1, &garbage, "malformed payload", T0 + 1)
            .expect("undecodable"),
        Appended::Buffered
    );
    append(&mut rec, &hb(2), T0 + 2);
    assert_eq!(
        rec.append_undecodable(1, &garbage, "again", T0 + 3)
            .expect("resend"),
        Appended::Duplicate
    );
    assert_eq!(append(&mut rec, &hb(1), T0), Appended::Duplicate);
    assert_eq!(rec.commit().expect("commit"), Some(2), "acks move past it");
    rec.close().expect("close");

    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_ranges(), vec![0..=2]);
    assert_eq!(
        rec.append_undecodable(1, &garbage, "after restart", T0 + 4)
            .expect("resend"),
        Appended::Duplicate
    );
    assert_eq!(append(&mut rec, &hb(1), T0), Appended::Duplicate);
    rec.close().expect("close");

    let dir = session_path(tmp.path());
    let mut visited = Vec::new();
    let report = visit_session(&dir, |r| {
        visited.push(r.frame.seq);
        Ok(())
    })
    .expect("visit does not fail on undecodable records");
    assert_eq!(report.undecodable_frames, 1);
    assert!(report.losses.is_empty() && report.missing_seqs.is_empty());
    assert_eq!(visited, vec![0, 2]);
    let sessions = list_sessions(tmp.path()).expect("list");
    assert_eq!(sessions[0].frames, 2);
    assert_eq!(sessions[0].undecodable_frames, 1);
    assert_eq!(sessions[0].skipped_messages, 0);
}

/// Copies `file` to a fresh session directory cut at `len` bytes.
fn truncated_copy(file: &Path, len: u64) -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = session_path(tmp.path());
    fs::create_dir_all(&dir).expect("mkdir");
    let bytes = fs::read(file).expect("read");
    let cut = usize::try_from(len).expect("length fits");
    fs::write(dir.join("0000.mcap"), &bytes[..cut]).expect("write");
    (tmp, dir)
}

/// After `truncated_copy`: read_session gives exactly `expected` seqs and `open` continues in
/// 0001.mcap with the durable prefix `expected.last()`.
fn assert_recovers(tmp: &tempfile::TempDir, dir: &Path, expected: &[u64], what: &str) {
    assert_eq!(seqs(dir), expected, "{what}: frames read");
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.path(), dir.join("0001.mcap"), "{what}");
    assert_eq!(rec.durable_prefix(), expected.last().copied(), "{what}");
    rec.close().expect("close");
    let sessions = list_sessions(tmp.path()).expect("list");
    assert_eq!(sessions[0].files, 2, "{what}");
    assert_eq!(sessions[0].incomplete_files, 1, "{what}");
    assert_eq!(sessions[0].frames, expected.len() as u64, "{what}");
}

/// One past the last seq `committed_then_more` appends: 26 revolutions of 2000 samples, about
/// 680 KB uncompressed, enough for zstd to push output into the file, less than one 1 MiB chunk.
const UNCOMMITTED_END: u64 = 30;

/// Writes seqs 0..4 and commits, then appends 4..UNCOMMITTED_END (badly compressible
/// revolutions) without committing. Returns the recorder and the file length after the commit.
fn committed_then_more(data_dir: &Path) -> (SessionRecorder, u64) {
    let mut rec = SessionRecorder::open(data_dir, EDGE, SESSION).expect("open");
    for seq in 0..4u64 {
        let f = Frame::new(SESSION, seq, revolution(SensorId::SWEEP, seq, 300, seq));
        append(&mut rec, &f, T0 + seq);
    }
    assert_eq!(rec.commit().expect("commit"), Some(3));
    let committed_len = fs::metadata(rec.path()).expect("stat").len();
    for seq in 4..UNCOMMITTED_END {
        let f = Frame::new(SESSION, seq, revolution(SensorId::RPLIDAR, seq, 2000, seq));
        append(&mut rec, &f, T0 + seq);
    }
    (rec, committed_len)
}

#[test]
fn crash_without_destructor_keeps_exactly_the_committed_frames() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (rec, committed_len) = committed_then_more(tmp.path());
    let file = rec.path().to_path_buf();
    // A crash: no destructor runs, nothing more is flushed.
    std::mem::forget(rec);
    let len = fs::metadata(&file).expect("stat").len();
    assert!(
        len > committed_len + 1000,
        "the unfinished chunk reached the file ({committed_len} -> {len})"
    );
    let committed: Vec<u64> = (0..4).collect();
    let span = len - committed_len;
    for cut in [
        committed_len,
        committed_len + 1,
        committed_len + 9,
        committed_len + 40,
        committed_len + span / 2,
        len - 1,
        len,
    ] {
        let (copy, dir) = truncated_copy(&file, cut);
        assert_recovers(&copy, &dir, &committed, &format!("cut at {cut} of {len}"));
    }
}

#[test]
fn dropped_recorder_cut_inside_its_last_chunk_keeps_exactly_the_committed_frames() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (rec, committed_len) = committed_then_more(tmp.path());
    let file = rec.path().to_path_buf();
    // Dropped without close: the MCAP writer finishes the last chunk and the summary (unsynced).
    drop(rec);
    let bytes = fs::read(&file).expect("read");
    // By the MCAP spec, a record is opcode (u8) + length (u64 LE) + body; chunks are opcode 0x06.
    let at = usize::try_from(committed_len).expect("fits");
    assert_eq!(bytes[at], 0x06, "a chunk follows the committed data");
    let body_len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().expect("8 bytes"));
    let chunk_end = committed_len + 9 + body_len;
    assert!(chunk_end < bytes.len() as u64);

    let committed: Vec<u64> = (0..4).collect();
    for cut in [
        committed_len + 1,
        committed_len + 9,
        committed_len + 9 + body_len / 3,
        chunk_end - 1,
    ] {
        let (copy, dir) = truncated_copy(&file, cut);
        assert_recovers(&copy, &dir, &committed, &format!("cut at {cut}"));
    }
    // Control: cut right after the chunk, it is complete and all its frames are read back.
    let (_copy, dir) = truncated_copy(&file, chunk_end);
    assert_eq!(seqs(&dir), (0..UNCOMMITTED_END).collect::<Vec<_>>());
    // And the whole file (summary included) reads back complete.
    assert_eq!(
        seqs(file.parent().expect("dir")),
        (0..UNCOMMITTED_END).collect::<Vec<_>>()
    );
}

#[test]
fn empty_leftover_file_is_skipped() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = session_path(tmp.path());
    fs::create_dir_all(&dir).expect("mkdir");
    // A crash right after the file was created.
    fs::write(dir.join("0000.mcap"), b"").expect("write");
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    assert_eq!(rec.path(), dir.join("0001.mcap"));
    assert_eq!(rec.durable_prefix(), None);
    rec.close().expect("close");
    assert!(read_session(&dir).expect("read").is_empty());
}

#[test]
fn refuses_foreign_sessions_misdirected_bodies_and_unsafe_edge_names() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    let other = Frame::new(2, 0, Heartbeat { sent_ns: 0 });
    let raw = encode(&other).expect("encode");
    assert!(matches!(
        rec.append(&raw, &other, T0),
        Err(RecorderError::WrongSession {
            expected: 1,
            got: 2
        })
    ));
    let command = Frame::new(SESSION, 0, Command::StopStaticScan);
    let raw = encode(&command).expect("encode");
    assert!(matches!(
        rec.append(&raw, &command, T0),
        Err(RecorderError::Misdirected { seq: 0, .. })
    ));
    let hb = Frame::new(SESSION, 0, Heartbeat { sent_ns: 0 });
    let raw = encode(&hb).expect("encode");
    assert!(matches!(
        rec.append_command(&raw, &hb, T0),
        Err(RecorderError::Misdirected { seq: 0, .. })
    ));
    // Refusals do not break the recorder.
    assert_eq!(
        rec.append(&raw, &hb, T0).expect("append"),
        Appended::Buffered
    );
    assert_eq!(rec.commit().expect("commit"), Some(0));
    rec.close().expect("close");

    for bad in ["", "..", "../etc", "a/b"] {
        assert!(matches!(
            SessionRecorder::open(tmp.path(), bad, SESSION),
            Err(RecorderError::InvalidEdgeName(_))
        ));
    }
}

/// Frames per chunk in `chunked_session`: it commits after every `PER_CHUNK` frames.
const PER_CHUNK: u64 = 5;

/// Records `chunks * PER_CHUNK` revolutions, one chunk per commit, and closes the file. The
/// sweep channel is first used in chunk `sweep_from` (its channel record lives there); from
/// then on rplidar and sweep alternate. Returns the file and its chunk index (offset, length),
/// in file order.
fn chunked_session(data_dir: &Path, chunks: u64, sweep_from: u64) -> (PathBuf, Vec<(u64, u64)>) {
    let mut rec = SessionRecorder::open(data_dir, EDGE, SESSION).expect("open");
    for seq in 0..chunks * PER_CHUNK {
        let sensor = if seq >= sweep_from * PER_CHUNK && seq % 2 == 1 {
            SensorId::SWEEP
        } else {
            SensorId::RPLIDAR
        };
        let f = Frame::new(SESSION, seq, revolution(sensor, seq * 1000, 200, seq));
        append(&mut rec, &f, T0 + seq);
        if seq % PER_CHUNK == PER_CHUNK - 1 {
            rec.commit().expect("commit");
        }
    }
    let path = rec.path().to_path_buf();
    rec.close().expect("close");
    let bytes = fs::read(&path).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("closed file has a summary");
    let mut chunks: Vec<(u64, u64)> = summary
        .chunk_indexes
        .iter()
        .map(|c| (c.chunk_start_offset, c.chunk_length))
        .collect();
    chunks.sort();
    (path, chunks)
}

/// The chunk (its position in `chunks`) that holds byte `offset`.
fn chunk_holding(chunks: &[(u64, u64)], offset: u64) -> usize {
    chunks
        .iter()
        .position(|&(start, len)| (start..start + len).contains(&offset))
        .expect("offset inside a chunk")
}

fn flip_bit(path: &Path, offset: u64, bit: u8) {
    let mut bytes = fs::read(path).expect("read");
    bytes[usize::try_from(offset).expect("offset fits")] ^= 1 << bit;
    fs::write(path, bytes).expect("write");
}

#[test]
fn a_flipped_bit_in_one_chunk_loses_exactly_that_chunk_and_the_rest_is_read() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (path, chunks) = chunked_session(tmp.path(), 12, 3);
    let len = fs::metadata(&path).expect("stat").len();
    // The chunk at a quarter of the file, which also declares the sweep channel.
    let damaged = chunk_holding(&chunks, len / 4);
    assert_eq!(
        damaged, 3,
        "the quarter mark falls in chunk 3 (test layout)"
    );
    let (start, chunk_len) = chunks[damaged];
    flip_bit(&path, start + chunk_len / 2, 3);

    let dir = session_path(tmp.path());
    let (frames, report) = scan3d_server::recording::read_session_report(&dir).expect("read");
    let lost = damaged as u64 * PER_CHUNK..=damaged as u64 * PER_CHUNK + PER_CHUNK - 1;
    let expected: Vec<u64> = (0..12 * PER_CHUNK).filter(|s| !lost.contains(s)).collect();
    assert_eq!(
        frames.iter().map(|f| f.frame.seq).collect::<Vec<_>>(),
        expected,
        "every frame of the other chunks"
    );
    for f in &frames {
        let want = if f.frame.seq % 2 == 1 && f.frame.seq >= 3 * PER_CHUNK {
            "/scan3d/lidar/sweep"
        } else {
            "/scan3d/lidar/rplidar"
        };
        assert_eq!(
            f.topic, want,
            "seq {}: topic known without its channel record",
            f.frame.seq
        );
        assert_eq!(f.raw, encode(&f.frame).expect("encode"));
    }
    assert_eq!(report.losses.len(), 1, "{:?}", report.losses);
    let loss = &report.losses[0];
    assert_eq!(loss.file, path);
    assert_eq!((loss.start, loss.end), (start, start + chunk_len));
    assert_eq!(loss.chunks, 1);
    assert_eq!(loss.messages, Some(PER_CHUNK));
    assert!(
        loss.reason.contains("CRC") || loss.reason.contains("lz4"),
        "{}",
        loss.reason
    );
    assert_eq!(report.missing_seqs, vec![lost.clone()]);
    assert_eq!(report.incomplete_files, 0, "damage is not a crash");

    // The strict reader refuses, naming the file and the loss.
    let err = read_session(&dir).expect_err("damaged");
    let text = err.to_string();
    assert!(matches!(err, RecorderError::Damaged { .. }));
    assert!(
        text.contains("0000.mcap") && text.contains("5 messages lost"),
        "{text}"
    );
    assert!(text.contains("edge seqs missing: 15..=19"), "{text}");
    let sessions = list_sessions(tmp.path()).expect("list");
    assert_eq!(sessions[0].frames, 11 * PER_CHUNK);
    assert_eq!(sessions[0].losses, report.losses);

    // The session index, written at close, still counts the damaged frames as recorded (they
    // were acknowledged; the edge no longer has them). Without it, a reopen reads the files:
    // what the damage took is not recorded any more, and a resend records it again.
    fs::remove_file(dir.join("recorded.idx")).expect("rm index");
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_ranges(), vec![0..=14, 20..=59]);
    let again = Frame::new(SESSION, 15, Heartbeat { sent_ns: 15 });
    assert_eq!(append(&mut rec, &again, T0), Appended::Buffered);
    rec.close().expect("close");
}

#[test]
fn a_corrupt_chunk_length_is_skipped_up_to_the_next_chunk_that_validates() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (path, chunks) = chunked_session(tmp.path(), 8, 0);
    let (start, _) = chunks[2];
    // Bit 44 of the record length (its 6th byte): far past the end of the file.
    flip_bit(&path, start + 1 + 5, 4);
    let dir = session_path(tmp.path());
    let (frames, report) = scan3d_server::recording::read_session_report(&dir).expect("read");
    let expected: Vec<u64> = (0..8 * PER_CHUNK)
        .filter(|s| !(2 * PER_CHUNK..3 * PER_CHUNK).contains(s))
        .collect();
    assert_eq!(
        frames.iter().map(|f| f.frame.seq).collect::<Vec<_>>(),
        expected
    );
    assert_eq!(report.losses.len(), 1, "{:?}", report.losses);
    let loss = &report.losses[0];
    assert_eq!(
        (loss.start, loss.end),
        (start, chunks[3].0),
        "up to the next chunk"
    );
    assert_eq!(loss.chunks, 1);
    assert_eq!(
        loss.messages, None,
        "the stretch's message index is not trusted"
    );
    assert_eq!(report.missing_seqs, vec![10..=14]);
}

#[test]
fn a_torn_tail_is_a_crash_not_a_loss() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (path, chunks) = chunked_session(tmp.path(), 4, 0);
    let (start, len) = chunks[3];
    let (copy, dir) = truncated_copy(&path, start + len / 2);
    let (frames, report) = scan3d_server::recording::read_session_report(&dir).expect("read");
    assert_eq!(frames.len() as u64, 3 * PER_CHUNK);
    assert!(report.losses.is_empty(), "{:?}", report.losses);
    assert_eq!(report.incomplete_files, 1);
    assert_eq!(
        seqs(&dir).len() as u64,
        3 * PER_CHUNK,
        "strict read succeeds"
    );
    drop(copy);
}

/// Runs the built `scan3d` binary; (exit success, stdout, stderr).
fn scan3d(args: &[&std::ffi::OsStr]) -> (bool, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_scan3d"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("run scan3d");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn offline_commands_fail_on_a_damaged_recording_unless_lenient() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (path, chunks) = chunked_session(tmp.path(), 12, 3);
    let (start, len) = chunks[3];
    flip_bit(&path, start + len / 2, 0);
    let data_dir = tmp.path().as_os_str();
    let dir = session_path(tmp.path());
    let dir = dir.as_os_str();
    let os = std::ffi::OsStr::new;

    let (ok, stdout, stderr) = scan3d(&[os("sessions"), os("--data-dir"), data_dir]);
    assert!(!ok, "sessions must fail: {stdout}");
    let last = stderr.lines().last().unwrap_or_default();
    assert!(last.starts_with("scan3d: "), "{stderr}");
    assert!(
        last.contains(path.to_str().expect("utf-8")) && last.contains("5 messages lost"),
        "one line naming the file and the loss: {stderr}"
    );
    assert!(
        stdout.contains("1 damaged"),
        "the table still shows it: {stdout}"
    );
    let (ok, stdout, _) = scan3d(&[os("sessions"), os("--data-dir"), data_dir, os("--lenient")]);
    assert!(ok);
    assert!(stdout.contains(" 55 "), "55 frames read: {stdout}");

    let (ok, _, stderr) = scan3d(&[os("replay"), dir]);
    assert!(!ok);
    assert!(stderr.contains("5 messages lost"), "{stderr}");
    let (ok, stdout, _) = scan3d(&[os("replay"), dir, os("--lenient")]);
    assert!(ok);
    assert!(stdout.contains("replayed 55 frames"), "{stdout}");

    // assemble: the damage stops it first; leniently it gets as far as finding no static scan.
    let out = tmp.path().join("cloud.ply");
    let (ok, _, stderr) = scan3d(&[os("assemble"), dir, os("--out"), out.as_os_str()]);
    assert!(!ok);
    assert!(stderr.contains("5 messages lost"), "{stderr}");
    let (ok, _, stderr) = scan3d(&[
        os("assemble"),
        dir,
        os("--out"),
        out.as_os_str(),
        os("--lenient"),
    ]);
    assert!(!ok);
    let last = stderr.lines().last().unwrap_or_default();
    assert!(
        last.contains("no static scan"),
        "went on past the damage: {stderr}"
    );
}

#[test]
fn reopening_trusts_the_index_of_closed_files_instead_of_reading_them() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (path, chunks) = chunked_session(tmp.path(), 4, 0);
    // Garble a chunk without changing the file's length: a reopen that read the file would
    // lose its seqs; one that trusts the index does not.
    let (start, len) = chunks[1];
    flip_bit(&path, start + len / 2, 1);
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_ranges(), vec![0..=19], "from the index");
    assert_eq!(rec.path(), session_path(tmp.path()).join("0001.mcap"));
    rec.close().expect("close");
    let index = fs::read_to_string(session_path(tmp.path()).join("recorded.idx")).expect("index");
    assert!(
        index.contains("\nfile 0 ") && index.contains("\nfile 1 "),
        "{index}"
    );
    assert!(index.contains("\nedge 0-19\n"), "{index}");
}

#[test]
fn an_index_that_no_longer_matches_the_files_is_ignored() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (path, chunks) = chunked_session(tmp.path(), 4, 0);
    let dir = session_path(tmp.path());
    // A torn or corrupt index: every file is read instead.
    let index_path = dir.join("recorded.idx");
    let good = fs::read(&index_path).expect("index");
    let mut bad = good.clone();
    let at = bad.len() - 12;
    bad[at] ^= 1;
    fs::write(&index_path, &bad).expect("write");
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_ranges(), vec![0..=19]);
    drop(rec);

    // A file shorter than the index says (cut after chunk 1): the index is not trusted.
    fs::remove_file(dir.join("0001.mcap")).expect("rm");
    fs::write(&index_path, &good).expect("restore index");
    let bytes = fs::read(&path).expect("read");
    let (start, _) = chunks[2];
    fs::write(&path, &bytes[..usize::try_from(start).expect("fits")]).expect("cut");
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(
        rec.durable_ranges(),
        vec![0..=9],
        "what the file still holds"
    );
    rec.close().expect("close");
}

#[test]
fn a_crashed_run_is_read_once_then_indexed() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq });
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    for seq in 0..3 {
        append(&mut rec, &hb(seq), T0);
    }
    rec.commit().expect("commit");
    std::mem::forget(rec); // A crash: no close, no index.
    let dir = session_path(tmp.path());
    assert!(!dir.join("recorded.idx").exists());
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(
        rec.durable_ranges(),
        vec![0..=2],
        "read from the crashed file"
    );
    let index = fs::read_to_string(dir.join("recorded.idx")).expect("indexed at open");
    assert!(
        index.contains("\nfile 0 ") && index.contains("\nedge 0-2\n"),
        "{index}"
    );
    drop(rec);
}

/// A tiny tmpfs mounted over a fresh directory, unmounted on drop.
struct TinyDisk(tempfile::TempDir);

impl TinyDisk {
    fn mount(size: &str) -> TinyDisk {
        let dir = tempfile::tempdir().expect("tempdir");
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .status()
            .expect("run mount");
        assert!(
            status.success(),
            "this test needs to mount a tmpfs (run as root, or in a user namespace with `unshare -rm`)"
        );
        TinyDisk(dir)
    }

    /// Writes a filler file until the disk is full.
    fn fill(&self) -> PathBuf {
        let path = self.0.path().join("filler");
        let mut file = fs::File::create(&path).expect("filler");
        let block = vec![0u8; 4096];
        loop {
            match std::io::Write::write(&mut file, &block) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) => {
                    assert_eq!(e.raw_os_error(), Some(28), "ENOSPC expected: {e}");
                    break;
                }
            }
        }
        path
    }
}

impl Drop for TinyDisk {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg(self.0.path())
            .status();
    }
}

#[test]
fn a_full_disk_fails_open_and_commit_as_storage_errors_without_leaving_empty_files() {
    let disk = TinyDisk::mount("512k");
    let data_dir = disk.0.path().join("data");
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq });
    let mut rec = SessionRecorder::open(&data_dir, EDGE, SESSION).expect("open");
    append(&mut rec, &hb(0), T0);
    rec.commit().expect("commit");
    rec.close().expect("close");
    let dir = session_path(&data_dir);
    let listing = || {
        let mut names: Vec<String> = fs::read_dir(&dir)
            .expect("ls")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let before = listing();
    assert_eq!(before, vec!["0000.mcap", "recorded.idx"]);

    let filler = disk.fill();
    for attempt in 0..3 {
        let err = SessionRecorder::open(&data_dir, EDGE, SESSION).expect_err("disk full");
        assert!(err.is_storage(), "attempt {attempt}: {err}");
        assert_eq!(listing(), before, "attempt {attempt}: nothing left behind");
    }
    assert!(!RecorderError::InvalidEdgeName("x".into()).is_storage());

    // Room for a new file, not for what is appended to it.
    fs::remove_file(&filler).expect("rm filler");
    let mut rec = SessionRecorder::open(&data_dir, EDGE, SESSION).expect("open with room");
    let filler = disk.fill();
    for seq in 1..40 {
        let f = Frame::new(SESSION, seq, revolution(SensorId::RPLIDAR, seq, 2000, seq));
        let raw = encode(&f).expect("encode");
        if let Err(e) = rec.append(&raw, &f, T0) {
            assert!(e.is_storage(), "{e}");
            break;
        }
    }
    let err = rec.commit().expect_err("disk full");
    assert!(err.is_storage(), "{err}");
    assert_eq!(
        rec.durable_ranges(),
        vec![0..=0],
        "nothing new acknowledged"
    );
    drop(rec);
    fs::remove_file(&filler).expect("rm filler");
    let rec = SessionRecorder::open(&data_dir, EDGE, SESSION).expect("open after the disk emptied");
    assert_eq!(rec.durable_ranges(), vec![0..=0]);
    rec.close().expect("close");
}

#[test]
fn a_long_recording_continues_in_a_new_file_so_the_writer_index_stays_bounded() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let hb = |seq: u64| Frame::new(SESSION, seq, Heartbeat { sent_ns: seq });
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    let dir = session_path(tmp.path());
    let commits = CHUNKS_PER_FILE + 5;
    for seq in 0..commits {
        append(&mut rec, &hb(seq), T0 + seq);
        assert_eq!(rec.commit().expect("commit"), Some(seq));
        let expected = if seq + 1 < CHUNKS_PER_FILE {
            "0000.mcap"
        } else {
            "0001.mcap"
        };
        assert_eq!(rec.path(), dir.join(expected), "after commit {seq}");
    }
    // The first file is finished (a summary) and indexed as soon as the recorder leaves it.
    let bytes = fs::read(dir.join("0000.mcap")).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("parse")
        .expect("summary");
    assert_eq!(summary.chunk_indexes.len() as u64, CHUNKS_PER_FILE);
    let index = fs::read_to_string(dir.join("recorded.idx")).expect("index");
    assert!(index.contains("\nfile 0 "), "{index}");
    rec.close().expect("close");
    assert_eq!(seqs(&dir), (0..commits).collect::<Vec<_>>());
    let sessions = list_sessions(tmp.path()).expect("list");
    assert_eq!((sessions[0].files, sessions[0].incomplete_files), (2, 0));
    let rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(rec.durable_ranges(), vec![0..=commits - 1]);
    assert_eq!(rec.path(), dir.join("0002.mcap"));
    rec.close().expect("close");
}
