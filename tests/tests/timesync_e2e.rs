//! Time sync over real QUIC on loopback: the server pings in datagrams, the edge's uplink
//! answers in datagrams, the server's clock model arrives as an event and is recorded in the
//! session, the recorded models map edge times exactly as the live ones, and no pong ever
//! passes through the edge's spool or the session's stream frames.

use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::clock::{Clock, MonotonicClock};
use scan3d_edge::uplink::client::{Uplink, UplinkConfig};
use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::installation::{self, EDGE_NAME, ServerThread};
use scan3d_protocol::{Body, DeviceStatus, Hello, SensorId, StatusEvent};
use scan3d_server::ingest::server::IngestEvent;
use scan3d_server::pose::timesync::{MonotonicServerClock, ServerClock, SessionClock};
use scan3d_server::recording::{SessionReader, SessionRecord, read_session, session_dir};

const SESSION: u64 = 0x71_3e_5a_c0;

#[test]
fn the_clock_model_arrives_is_recorded_and_replays_identically_and_pongs_never_touch_the_spool() {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = dir.path().join("pki");
    let data = dir.path().join("data");
    let bundle = installation::pair_certificates(&pki).expect("pairing");
    let mut config = installation::ingest_config(&pki, &data, 0);
    config.time_sync_interval = Duration::from_millis(50);
    let mut server = ServerThread::start(config).expect("server");
    let edge_clock = Arc::new(MonotonicClock::new());
    let server_clock = MonotonicServerClock::new();

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let section = installation::uplink_section(server.addr(), &bundle);
    let uplink_config = UplinkConfig::new(
        section.server.clone(),
        section.tls_name().to_owned(),
        client_config(&bundle).expect("bundle"),
        section
            .spool_config(dir.path().join("spool"))
            .expect("spool"),
    );
    let (uplink, handle, _commands) = runtime
        .block_on(async { Uplink::new(uplink_config, edge_clock.clone(), SESSION) })
        .expect("uplink");
    handle
        .submit(Hello::new(EDGE_NAME, "0", Vec::new()).with_clock_id(edge_clock.clock_id()))
        .expect("hello");
    let submitted = 1 + 20;
    for _ in 1..submitted {
        handle
            .submit(DeviceStatus {
                t_ns: edge_clock.now_ns(),
                sensor: SensorId::IMU,
                event: StatusEvent::SensorBack,
                reason: String::new(),
            })
            .expect("spooled");
    }
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = runtime.spawn(uplink.run(stopped));

    // Live: the models as the server reports them.
    let mut live = SessionClock::new();
    let mut models = 0;
    let end = Instant::now() + Duration::from_secs(30);
    while models < 20 || handle.pending() > 0 {
        assert!(
            Instant::now() < end,
            "only {models} clock models, {} frames unacknowledged",
            handle.pending()
        );
        match server.events.try_recv() {
            Ok(IngestEvent::TimeSync {
                session_id, model, ..
            }) => {
                assert_eq!(session_id, SESSION);
                live.push(model);
                models += 1;
            }
            Ok(_) => {}
            Err(_) => std::thread::sleep(Duration::from_millis(10)),
        }
    }
    // Loopback: the edge's CLOCK_MONOTONIC mapped to the server's clock is within a few ms of
    // the server's clock (both follow the same kernel clock; only the anchors differ).
    let model = *live.models().last().expect("a model");
    let now_edge = edge_clock.now_ns();
    let now_server = server_clock.now_ns();
    let mapped = model.to_server_ns(now_edge);
    assert!(
        mapped.abs_diff(now_server) < 5_000_000,
        "{model:?} maps now to {mapped}, the server clock reads {now_server}"
    );
    assert!(model.error_bound_ns < 5_000_000, "{model:?}");
    assert!(model.exchanges >= 1);

    stop.send(true).expect("stop");
    let stats = runtime.block_on(task).expect("uplink task");
    server.stop();

    // Pongs never went through the spool: only what the test submitted was ever queued, and
    // the session holds no pong among its stream frames.
    assert_eq!(stats.submitted, submitted);
    assert_eq!(handle.pending(), 0);
    let frames = read_session(&session_dir(&data, EDGE_NAME, SESSION)).expect("recording");
    assert!(
        !frames
            .iter()
            .any(|f| matches!(f.frame.body, Body::TimePong(_) | Body::TimePing(_))),
        "a time-sync frame was recorded from the stream"
    );
    let hello = frames
        .iter()
        .find_map(|f| match &f.frame.body {
            Body::Hello(hello) => Some(hello.clone()),
            _ => None,
        })
        .expect("the hello is recorded");
    assert_eq!(
        hello.clock_id,
        MonotonicClock::new().clock_id(),
        "the boot id"
    );
    let mut recorded = 0;
    let _report = SessionReader::new(&session_dir(&data, EDGE_NAME, SESSION))
        .visit(|record| {
            if let SessionRecord::Server(server) = record {
                recorded += usize::from(server.topic == "/scan3d/timesync");
            }
            Ok(())
        })
        .expect("records");
    assert!(
        recorded >= models,
        "{recorded} models recorded, {models} reported"
    );

    // Replay: the recorded models map every edge time as the live ones did.
    let replayed = SessionClock::from_session(&session_dir(&data, EDGE_NAME, SESSION))
        .expect("the models read back");
    assert_eq!(&replayed.models()[..live.models().len()], live.models());
    // (Past the last live model the replay knows the later ones the server made at shutdown.)
    let first = live.models()[0].valid_from_edge_ns - 1_000_000;
    let last = model.valid_from_edge_ns;
    for k in 0..=1_000u64 {
        let edge_ns = first + (last - first) / 1_000 * k;
        assert_eq!(
            replayed.to_server_ns(edge_ns),
            live.to_server_ns(edge_ns),
            "edge time {edge_ns}"
        );
    }
}
