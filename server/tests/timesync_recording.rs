//! Clock models in a session recording: server-made records (no wire frame, no sequence
//! number of either side), read back by `SessionClock` so a replay maps edge times exactly as
//! live.

use scan3d_protocol::{Body, ClockModel, Command, Frame, Heartbeat, encode};
use scan3d_server::pose::timesync::{Exchange, SessionClock, TimeSync};
use scan3d_server::recording::{
    Appended, RecorderError, ServerRecord, SessionReader, SessionRecord, SessionRecorder,
    read_session_report,
};

const EDGE: &str = "trolley-pi";
const SESSION: u64 = 0xc10c;
const LOG_NS: u64 = 1_767_225_600_000_000_000;

/// Models from a real fit: the edge 3 s ahead of the server, 40 ppm fast, 1 ms paths.
fn models() -> Vec<ClockModel> {
    let mut sync = TimeSync::default();
    (0..12u64)
        .filter_map(|k| {
            let t0 = LOG_NS + k * 1_000_000_000;
            let theta = 3_000_000_000 + (k * 40_000) as i64;
            let t1 = (t0 as i64 + 1_000_000 + theta) as u64;
            let t2 = t1 + 20_000;
            let t3 = (t2 as i64 - theta) as u64 + 1_000_000 + k * 7_000;
            sync.add(Exchange {
                t0_ns: t0,
                t1_ns: t1,
                t2_ns: t2,
                t3_ns: t3,
            })
        })
        .collect()
}

#[test]
fn recorded_clock_models_map_edge_times_exactly_as_the_live_ones_and_leave_no_edge_gap() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let models = models();
    let mut live = SessionClock::new();
    let mut rec = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("open");
    for (edge_seq, model) in models.iter().enumerate() {
        let heartbeat = Frame::new(SESSION, edge_seq as u64, Heartbeat { sent_ns: 1 });
        let raw = encode(&heartbeat).unwrap();
        assert_eq!(
            rec.append(&raw, &heartbeat, LOG_NS).unwrap(),
            Appended::Buffered
        );
        rec.append_record(&ServerRecord::ClockModel(*model), LOG_NS)
            .unwrap();
        live.push(*model);
    }
    // The models take no server seq: commands are numbered from 0.
    assert_eq!(rec.next_command_seq(), 0);
    // A clock model is never a wire frame the server records.
    let as_frame = Frame::new(SESSION, 0, models[0]);
    assert!(matches!(
        rec.append_command(&encode(&as_frame).unwrap(), &as_frame, LOG_NS),
        Err(RecorderError::Misdirected { .. })
    ));
    assert!(matches!(
        rec.append(&encode(&as_frame).unwrap(), &as_frame, LOG_NS),
        Err(RecorderError::Misdirected { .. })
    ));
    let command = Frame::new(SESSION, 0, Command::StopStaticScan);
    rec.append_command(&encode(&command).unwrap(), &command, LOG_NS)
        .unwrap();
    // Every edge frame is durable; the models are no edge seqs.
    assert_eq!(rec.commit().unwrap(), Some(models.len() as u64 - 1));
    rec.close().unwrap();

    let dir = scan3d_server::recording::session_dir(tmp.path(), EDGE, SESSION);
    let (frames, report) = read_session_report(&dir).expect("read");
    assert!(report.missing_seqs.is_empty(), "{report:?}");
    assert_eq!(frames.len(), models.len() + 1, "heartbeats and the command");
    assert!(
        !frames
            .iter()
            .any(|f| f.topic == "/scan3d/timesync" || matches!(f.frame.body, Body::ClockModel(_)))
    );
    let mut on_topic = Vec::new();
    let _report = SessionReader::new(&dir)
        .visit(|record| {
            if let SessionRecord::Server(server) = record {
                assert_eq!(server.topic, "/scan3d/timesync");
                assert_eq!(server.log_time_ns, LOG_NS);
                on_topic.push(server.record);
            }
            Ok(())
        })
        .expect("records");
    assert_eq!(
        on_topic,
        models
            .iter()
            .map(|m| ServerRecord::ClockModel(*m))
            .collect::<Vec<_>>()
    );
    let reopened = SessionRecorder::open(tmp.path(), EDGE, SESSION).expect("reopen");
    assert_eq!(reopened.next_command_seq(), 1);
    drop(reopened);

    let replayed = SessionClock::from_session(&dir).expect("models");
    assert_eq!(replayed, live);
    let first = models[0].valid_from_edge_ns;
    let last = models.last().unwrap().valid_from_edge_ns + 5_000_000_000;
    for k in 0..=10_000u64 {
        let edge_ns = first - 1_000_000_000 + (last - first + 1_000_000_000) / 10_000 * k;
        assert_eq!(replayed.to_server_ns(edge_ns), live.to_server_ns(edge_ns));
        // And it is the truth to within the exchanges' small asymmetry (≤ 0.04 ms here):
        // edge = server + 3 s + 40 ppm · (server − LOG_NS).
        let mapped = live.to_server_ns(edge_ns).unwrap();
        let since =
            (i128::from(edge_ns) - i128::from(LOG_NS) - 3_000_000_000) as f64 / (1.0 + 40e-6);
        let truth = (i128::from(LOG_NS) + since.round() as i128) as u64;
        assert!(
            mapped.abs_diff(truth) < 100_000,
            "edge {edge_ns}: mapped {mapped}, truth {truth}"
        );
    }
}
