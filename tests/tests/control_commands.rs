//! Operator commands through the real control socket to a real, connected edge connection:
//! a command the edge could not act on (a 5 MiB or a 4 KiB position name) is refused on the
//! socket with a clear error and never reaches the connection, which stays up and keeps
//! working. Scans through the real edge daemon on the emulated turntable head: the edge's
//! answer (waiting for the Sweep, accepted, refused with the reason), the scan followed to its
//! end, a second scan and a stop with nothing running refused, an edge that is not connected.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::uplink::tls::client_config;
use scan3d_hw_sim::installation::{self, EdgeThread, ServerThread};
use scan3d_hw_sim::noise::RangeNoise;
use scan3d_hw_sim::turntable_head::{TurntableHead, TurntableHeadOptions};
use scan3d_hw_sim::world::World;
use scan3d_map::cloud::assembly::Position;
use scan3d_protocol::{Ack, Body, Command, CommandOutcome, Frame, FrameReader, Heartbeat, encode};
use scan3d_server::ingest::control::{
    CommandRequest, CommandState, CommandStatus, ControlRequest, request, request_command,
    socket_path,
};

const SESSION: u64 = 11;

/// Reads frames from the server until `wanted` matches one (or 5 s pass).
async fn receive(
    recv: &mut quinn::RecvStream,
    reader: &mut FrameReader,
    wanted: impl Fn(&Frame) -> bool,
) -> Option<Frame> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        while let Ok(Some(frame)) = reader.next_frame() {
            if wanted(&frame) {
                return Some(frame);
            }
        }
        let chunk = tokio::time::timeout_at(deadline, recv.read_chunk(4096, true)).await;
        let Ok(Ok(Some(chunk))) = chunk else {
            return None;
        };
        reader.push(&chunk.bytes);
    }
}

fn acked(seq: u64) -> impl Fn(&Frame) -> bool {
    move |frame| matches!(frame.body, Body::Ack(Ack::UpTo { seq: s }) if s >= seq)
}

/// `scan3d scan`'s request, from a blocking thread as the CLI makes it.
async fn operator(socket: &Path, command: Command) -> scan3d_server::ingest::control::ControlReply {
    let socket = socket.to_path_buf();
    tokio::task::spawn_blocking(move || {
        request(
            &socket,
            &ControlRequest {
                edge: installation::EDGE_NAME.into(),
                command,
            },
        )
    })
    .await
    .expect("join")
    .expect("the control socket answers")
}

/// A paired edge bundle, a running server with its control socket, and a runtime to drive
/// the edge's side from.
struct Site {
    dir: tempfile::TempDir,
    bundle: std::path::PathBuf,
    data: std::path::PathBuf,
    server: ServerThread,
    socket: std::path::PathBuf,
    runtime: tokio::runtime::Runtime,
}

impl Site {
    fn start() -> Self {
        let dir = tempfile::tempdir().expect("temp dir");
        let pki = dir.path().join("pki");
        let bundle = installation::pair_certificates(&pki).expect("pairing");
        let data = dir.path().join("data");
        let server =
            ServerThread::start(installation::ingest_config(&pki, &data, 0)).expect("server");
        let socket = socket_path(&data);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .expect("runtime");
        Site {
            dir,
            bundle,
            data,
            server,
            socket,
            runtime,
        }
    }
}

#[test]
fn an_oversized_command_is_refused_and_the_edge_stays_connected() {
    let Site {
        dir: _dir,
        bundle,
        data: _,
        server,
        socket,
        runtime,
    } = Site::start();
    runtime.block_on(async {
        let (_endpoint, connection, mut send, mut recv) =
            connect_edge(server.addr(), &bundle).await;
        let mut reader = FrameReader::new();
        let heartbeat = |seq| encode(&Frame::new(SESSION, seq, Heartbeat { sent_ns: 1 })).unwrap();
        send.write_all(&heartbeat(0)).await.expect("write");
        assert!(receive(&mut recv, &mut reader, acked(0)).await.is_some());
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        while !socket.exists() {
            assert!(tokio::time::Instant::now() < deadline, "no control socket");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }

        let start = |position: String| Command::StartStaticScan {
            position,
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: None,
        };
        // 5 MiB: refused by the socket's line limit before it is even parsed.
        let reply = operator(&socket, start("x".repeat(5 * 1024 * 1024))).await;
        assert!(!reply.ok, "{reply:?}");
        assert_eq!(
            reply.detail,
            "request line longer than 65536 bytes; closing the connection"
        );
        // Within the line limit but over the name limit: refused by the command check.
        let reply = operator(&socket, start("x".repeat(4096))).await;
        assert!(!reply.ok, "{reply:?}");
        assert_eq!(
            reply.detail,
            "invalid command: position name of 4096 bytes: must be 1 to 256 bytes"
        );

        // The connection is untouched: frames are still acknowledged, and a valid command
        // arrives on it.
        send.write_all(&heartbeat(1)).await.expect("write");
        assert!(
            receive(&mut recv, &mut reader, acked(1)).await.is_some(),
            "the edge connection did not survive the refused command"
        );
        let reply = operator(&socket, Command::StopStaticScan).await;
        assert!(reply.ok, "{reply:?}");
        let command = receive(&mut recv, &mut reader, |f| {
            matches!(f.body, Body::Command(_))
        })
        .await;
        assert_eq!(
            command.map(|f| f.body),
            Some(Body::Command(Command::StopStaticScan))
        );
        assert!(
            connection.close_reason().is_none(),
            "{:?}",
            connection.close_reason()
        );
        connection.close(0u32.into(), b"done");
    });
    let stats = server.stop();
    assert_eq!(stats.frames, 2, "{stats:?}");
}

/// Connects to `server` as the paired edge and opens the frame stream.
async fn connect_edge(
    server: SocketAddr,
    bundle: &Path,
) -> (
    quinn::Endpoint,
    quinn::Connection,
    quinn::SendStream,
    quinn::RecvStream,
) {
    let mut endpoint =
        quinn::Endpoint::client(SocketAddr::from(([127, 0, 0, 1], 0))).expect("endpoint");
    endpoint.set_default_client_config(client_config(bundle).expect("bundle"));
    let connection = endpoint
        .connect(server, "localhost")
        .expect("connect")
        .await
        .expect("handshake");
    let (send, recv) = connection.open_bi().await.expect("stream");
    (endpoint, connection, send, recv)
}

#[test]
fn a_command_sent_after_a_reconnect_is_recorded_not_taken_for_a_resend() {
    let Site {
        dir: _dir,
        bundle,
        data,
        server,
        socket,
        runtime,
    } = Site::start();
    let positions = ["first", "second"];
    runtime.block_on(async {
        // The same exchange on two connections of one session: a heartbeat, its ack, a command.
        for (seq, position) in positions.into_iter().enumerate() {
            let seq = seq as u64;
            let (_endpoint, connection, mut send, mut recv) =
                connect_edge(server.addr(), &bundle).await;
            let mut reader = FrameReader::new();
            let heartbeat = encode(&Frame::new(SESSION, seq, Heartbeat { sent_ns: 1 })).unwrap();
            send.write_all(&heartbeat).await.expect("write");
            assert!(receive(&mut recv, &mut reader, acked(seq)).await.is_some());
            let reply = operator(
                &socket,
                Command::StartStaticScan {
                    position: position.into(),
                    x_m: 0.0,
                    y_m: 0.0,
                    heading_deg: None,
                },
            )
            .await;
            assert!(reply.ok, "{reply:?}");
            let sent = receive(&mut recv, &mut reader, |f| {
                matches!(f.body, Body::Command(_))
            });
            assert!(sent.await.is_some(), "the command did not reach the edge");
            connection.close(0u32.into(), b"reconnecting");
            // The server replaces a closed connection at once; give it the close.
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    });
    server.stop();
    let recorded = scan3d_server::recording::read_session(&scan3d_server::recording::session_dir(
        &data,
        installation::EDGE_NAME,
        SESSION,
    ))
    .expect("the session reads");
    let commands: Vec<String> = recorded
        .iter()
        .filter_map(|r| match &r.frame.body {
            Body::Command(Command::StartStaticScan { position, .. }) => Some(position.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(
        commands, positions,
        "every command sent must be in the recording"
    );
}

/// The real edge daemon on the emulated turntable head (Sweep on a pty, stepper and IMU on
/// the emulated I2C bus), streaming to `server`.
struct Head {
    head: TurntableHead,
    edge: EdgeThread,
    session_id: u64,
}

impl Head {
    /// `settle_ms`: the Sweep's motor settle time (simulated ms at 10× speed), so a scan asked
    /// for early finds the Sweep not streaming yet. `stepper`: whether edge.toml has one.
    fn start(site: &Site, settle_ms: u64, stepper: bool) -> Self {
        let world = Arc::new(World::from_toml_str(scan3d_tests::BOX_ROOM).expect("room"));
        let start = Position {
            name: "a".into(),
            x_m: 2.0,
            y_m: 1.5,
            heading_deg: 0.0,
        };
        let time_scale = 10.0;
        let head = TurntableHead::start(
            &site.dir.path().join("links"),
            world,
            start,
            &TurntableHeadOptions {
                time_scale,
                motor_hz: 2,
                seed: 3,
                sweep_settle_ms: settle_ms,
                noise: RangeNoise::SWEEP,
            },
        )
        .expect("head");
        let mut config = head.edge_config(
            &site.dir.path().join("edge-state"),
            Some(installation::uplink_section(
                site.server.addr(),
                &site.bundle,
            )),
        );
        if !stepper {
            config.stepper = None;
        }
        let clock: SharedClock = Arc::new(ScaledClock::new(time_scale));
        let session_id = rand::random::<u64>();
        let edge = EdgeThread::start_with_i2c(config, clock, session_id, Some(head.bus()))
            .expect("edge daemon");
        Head {
            head,
            edge,
            session_id,
        }
    }

    fn stop(self) {
        self.edge.stop().expect("the edge daemon stops");
        self.head.shutdown();
    }
}

/// What `scan3d scan` asks (the CLI calls the same library function), retried while the edge
/// is not connected yet (up to 60 s); every status line is kept.
fn scan(
    socket: &Path,
    command: Command,
    follow: bool,
    on_update: &mut dyn FnMut(&CommandStatus),
) -> CommandStatus {
    let request = CommandRequest {
        edge: installation::EDGE_NAME.into(),
        command,
        follow,
        reply_timeout_s: Some(60.0),
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let last = request_command(socket, &request, on_update).expect("the socket answers");
        if last.state != CommandState::NotConnected || Instant::now() > deadline {
            return last;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn start_at(name: &str) -> Command {
    Command::StartStaticScan {
        position: name.into(),
        x_m: 2.0,
        y_m: 1.5,
        heading_deg: Some(0.0),
    }
}

#[test]
fn scans_through_the_real_edge_daemon_are_answered_followed_and_refused_with_reasons() {
    let site = Site::start();
    let deadline = Instant::now() + Duration::from_secs(20);
    while !site.socket.exists() {
        assert!(Instant::now() < deadline, "no control socket");
        std::thread::sleep(Duration::from_millis(5));
    }
    // Not connected: one readable line.
    let nobody = request_command(
        &site.socket,
        &CommandRequest {
            edge: "nobody".into(),
            command: start_at("x"),
            follow: true,
            reply_timeout_s: None,
        },
        &mut |_| {},
    )
    .expect("the socket answers");
    assert_eq!(
        (nobody.state, nobody.ok, nobody.done),
        (CommandState::NotConnected, false, true)
    );
    assert_eq!(
        nobody.detail,
        "edge \"nobody\" is not connected (connected: none)"
    );

    // The Sweep takes 60 simulated seconds (6 s here) to settle: a scan asked for at once
    // waits for it, and is not refused for that.
    let head = Head::start(&site, 60_000, true);
    let ignore = &mut |_: &CommandStatus| {};
    let first = scan(&site.socket, start_at("a"), false, ignore);
    assert_eq!(
        (first.state, first.ok, first.done),
        (CommandState::Waiting, true, true),
        "{first:?}"
    );
    assert_eq!(
        first.detail,
        "edge sim-edge accepted and waits: waiting for the Sweep to stream"
    );
    // A second scan while one waits is refused; a stop cancels the waiting one.
    let second = scan(&site.socket, start_at("b"), false, ignore);
    assert_eq!(
        (second.state, second.ok),
        (CommandState::Refused, false),
        "{second:?}"
    );
    assert!(
        second.detail.contains("is waiting for the Sweep"),
        "{}",
        second.detail
    );
    let stop = scan(&site.socket, Command::StopStaticScan, false, ignore);
    assert_eq!(
        (stop.state, stop.ok),
        (CommandState::Accepted, true),
        "{stop:?}"
    );
    // Nothing runs now: --stop says so, non-zero.
    let stop = scan(&site.socket, Command::StopStaticScan, false, ignore);
    assert_eq!(
        (stop.state, stop.ok),
        (CommandState::Refused, false),
        "{stop:?}"
    );
    assert_eq!(
        stop.detail,
        "edge sim-edge refused: no static scan is running"
    );

    // Followed to its end: waiting (perhaps), running with progress, completed. A second scan
    // asked for while it runs is refused.
    let (running_tx, running_rx) = std::sync::mpsc::channel::<()>();
    let socket = site.socket.clone();
    let follower = std::thread::spawn(move || {
        let mut seen = Vec::new();
        let last = scan(&socket, start_at("c"), true, &mut |status| {
            if status.state == CommandState::Running {
                let _ = running_tx.send(());
            }
            seen.push(status.clone());
        });
        (last, seen)
    });
    running_rx
        .recv_timeout(Duration::from_secs(120))
        .expect("the scan never ran");
    let during = scan(&site.socket, start_at("d"), false, ignore);
    assert_eq!(
        (during.state, during.ok),
        (CommandState::Refused, false),
        "{during:?}"
    );
    assert!(during.detail.contains("is running"), "{}", during.detail);
    let (last, seen) = follower.join().expect("follower");
    assert_eq!(
        (last.state, last.ok, last.done),
        (CommandState::Completed, true, true),
        "{last:?}"
    );
    let progress = last.progress.expect("progress");
    assert!(progress.revolutions > 10, "{progress:?}");
    assert!(
        (progress.yaw_deg - progress.total_deg).abs() < 5.0,
        "yaw {} of {}",
        progress.yaw_deg,
        progress.total_deg
    );
    let running: Vec<u32> = seen
        .iter()
        .filter(|s| s.state == CommandState::Running)
        .filter_map(|s| s.progress.as_ref().map(|p| p.revolutions))
        .collect();
    assert!(running.len() >= 2, "progress lines: {running:?}");
    assert!(running.windows(2).all(|w| w[0] <= w[1]), "{running:?}");

    let session_id = head.session_id;
    head.stop();
    site.server.stop();
    // Every reply is in the recording, answering its command by seq.
    let recorded = scan3d_server::recording::read_session(&scan3d_server::recording::session_dir(
        &site.data,
        installation::EDGE_NAME,
        session_id,
    ))
    .expect("the session reads");
    let commands: Vec<u64> = recorded
        .iter()
        .filter(|r| matches!(r.frame.body, Body::Command(_)))
        .map(|r| r.frame.seq)
        .collect();
    let replies: Vec<(u64, CommandOutcome)> = recorded
        .iter()
        .filter_map(|r| match &r.frame.body {
            Body::CommandReply(reply) => Some((reply.command_seq, reply.outcome.clone())),
            _ => None,
        })
        .collect();
    assert_eq!(commands.len(), 6, "{commands:?}");
    for seq in &commands {
        assert!(
            replies.iter().any(|(s, _)| s == seq),
            "command {seq} has no reply: {replies:?}"
        );
    }
    assert!(
        recorded.iter().any(|r| r.topic == "/scan3d/command_reply"),
        "replies are recorded on their topic"
    );
}

#[test]
fn a_scan_on_an_edge_without_a_stepper_is_refused_with_the_reason() {
    let site = Site::start();
    let head = Head::start(&site, 3000, false);
    let last = scan(&site.socket, start_at("a"), true, &mut |_| {});
    assert_eq!(
        (last.state, last.ok, last.done),
        (CommandState::Refused, false, true),
        "{last:?}"
    );
    assert_eq!(
        last.detail,
        "edge sim-edge refused: static scans are off: no [stepper] in edge.toml"
    );
    head.stop();
    site.server.stop();
}
