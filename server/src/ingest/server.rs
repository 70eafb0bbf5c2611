//! The ingest endpoint: edges connect over QUIC with mutual TLS; each connection gets a task
//! that records every frame durably and acknowledges it.
//!
//! One bidirectional stream per connection carries length-prefixed frames both ways
//! (`scan3d_protocol` framing): edge → server data, server → edge acks, time-sync pings and
//! commands. The task
//! - learns the edge's name from its client certificate (a connection without a valid one
//!   never gets here: the TLS handshake refuses it);
//! - appends each frame to its session's [`SessionRecorder`], ignoring duplicates (resends);
//! - every `commit_interval` finishes the MCAP chunk, fsyncs, and acknowledges the durable
//!   prefix of each session: a frame is acknowledged only once it is on disk;
//! - every `time_sync_interval` pings the edge and keeps NTP-style offset estimates;
//! - rejects frames it cannot use (bad magic, unknown protocol version, over the size limit)
//!   with a logged reason and closes the connection cleanly; malformed payloads are skipped.
//!
//! Shutdown follows mini-redis: a `watch` channel tells every task to stop; each commits what
//! it has, closes its recordings (writing the MCAP summary) and closes its connection.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use scan3d_protocol::{
    Ack, Body, Command, DecodeError, Direction, Frame, HEADER_LEN, TimePing, decode, decode_header,
    encode,
};
use tokio::sync::{Semaphore, mpsc, watch};
use tokio::task::JoinSet;

use super::control::EdgeControl;
use super::recorder::{Appended, SessionRecorder};
use super::timesync::{Estimate, Exchange, TimeSync};
use super::tls;

/// QUIC application close codes the server uses.
pub mod close_code {
    /// Normal close (server shutting down, edge going away).
    pub const DONE: u32 = 0;
    /// The peer sent bytes that are not scan3d frames, or of another protocol version.
    pub const PROTOCOL_ERROR: u32 = 1;
    /// The server could not record (disk full, permissions): the edge keeps its spool.
    pub const STORAGE_ERROR: u32 = 2;
    /// Too many edges connected.
    pub const BUSY: u32 = 3;
}

/// Everything the ingest server needs to run.
#[derive(Debug, Clone)]
pub struct IngestConfig {
    /// UDP address to listen on.
    pub listen: SocketAddr,
    /// The directory given to `scan3d pair` (CA, server certificate).
    pub pki_dir: PathBuf,
    /// Recordings go to `data_dir/sessions/…`.
    pub data_dir: PathBuf,
    /// How often chunks are finished, fsynced and acknowledged.
    pub commit_interval: Duration,
    /// How often each edge is pinged for time sync.
    pub time_sync_interval: Duration,
    /// Edges served at once; more are refused with [`close_code::BUSY`].
    pub max_connections: usize,
}

/// What the server reports while it runs (for the demo, tests and a live view).
#[derive(Debug, Clone, PartialEq)]
pub enum IngestEvent {
    /// An edge authenticated and connected.
    Connected {
        /// The name in its certificate.
        edge: String,
        /// Where it connects from.
        remote: SocketAddr,
    },
    /// A frame was recorded for the first time (resent duplicates are not reported again).
    Frame {
        /// The edge it came from.
        edge: String,
        /// The decoded frame.
        frame: Frame,
    },
    /// A new time-sync estimate for an edge session.
    TimeSync {
        /// The edge.
        edge: String,
        /// Its session.
        session_id: u64,
        /// Offset and round trip.
        estimate: Estimate,
    },
    /// A connection ended.
    Disconnected {
        /// The edge.
        edge: String,
        /// Why.
        reason: String,
    },
}

/// Counters over the server's lifetime.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IngestStats {
    /// Connections that completed the TLS handshake with a valid client certificate.
    pub connections: u64,
    /// Connection attempts refused (handshake failed, too many edges).
    pub refused: u64,
    /// Frames recorded.
    pub frames: u64,
    /// Bytes of frames recorded.
    pub bytes: u64,
    /// Resent frames ignored because they were already recorded.
    pub duplicates: u64,
    /// Frames skipped as malformed, or connections closed for protocol errors.
    pub rejected: u64,
}

/// A bound, not yet running, ingest server.
pub struct IngestServer {
    endpoint: quinn::Endpoint,
    config: IngestConfig,
    control: EdgeControl,
}

impl IngestServer {
    /// Loads the server certificate and binds the UDP socket.
    pub fn bind(config: IngestConfig) -> anyhow::Result<Self> {
        let server_config = tls::server_config(&config.pki_dir)?;
        let endpoint = quinn::Endpoint::server(server_config, config.listen)
            .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", config.listen))?;
        Ok(Self {
            endpoint,
            config,
            control: EdgeControl::default(),
        })
    }

    /// A handle that sends commands to the connected edges (e.g. to start a static scan).
    pub fn control(&self) -> EdgeControl {
        self.control.clone()
    }

    /// The bound address (useful with port 0).
    pub fn local_addr(&self) -> anyhow::Result<SocketAddr> {
        Ok(self.endpoint.local_addr()?)
    }

    /// Serves until `shutdown` resolves, then closes every connection cleanly.
    pub async fn run(
        self,
        events: Option<mpsc::UnboundedSender<IngestEvent>>,
        shutdown: impl Future<Output = ()>,
    ) -> IngestStats {
        let shared = Arc::new(Shared {
            config: self.config,
            events,
            stats: Mutex::new(IngestStats::default()),
            edges: Mutex::new(HashMap::new()),
            control: self.control,
            next_connection_id: std::sync::atomic::AtomicU64::new(0),
        });
        let (stop_tx, stop_rx) = watch::channel(false);
        let slots = Arc::new(Semaphore::new(shared.config.max_connections.max(1)));
        let mut tasks = JoinSet::new();
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                () = &mut shutdown => break,
                incoming = self.endpoint.accept() => {
                    let Some(incoming) = incoming else { break };
                    let Ok(permit) = slots.clone().try_acquire_owned() else {
                        tracing::warn!(remote = %incoming.remote_address(), "too many edges; refusing");
                        shared.count(|s| s.refused += 1);
                        incoming.refuse();
                        continue;
                    };
                    let shared = shared.clone();
                    let stop = stop_rx.clone();
                    tasks.spawn(async move {
                        handle_incoming(incoming, shared, stop).await;
                        drop(permit);
                    });
                }
                Some(_) = tasks.join_next(), if !tasks.is_empty() => {}
            }
        }
        tracing::info!("shutting down: committing and closing every session");
        let _ = stop_tx.send(true);
        while tasks.join_next().await.is_some() {}
        self.endpoint
            .close(close_code::DONE.into(), b"server shutting down");
        self.endpoint.wait_idle().await;
        *lock(&shared.stats)
    }
}

struct Shared {
    config: IngestConfig,
    events: Option<mpsc::UnboundedSender<IngestEvent>>,
    stats: Mutex<IngestStats>,
    /// The live connection of each edge. An edge that reconnects before the server noticed
    /// its old connection die (a short outage) replaces it: the old task closes its
    /// recordings first, so one session is never written by two tasks at once.
    edges: Mutex<HashMap<String, EdgeSlot>>,
    /// Commands for the edges, routed to their live connection's task.
    control: EdgeControl,
    next_connection_id: std::sync::atomic::AtomicU64,
}

/// An edge's current connection and a way to wait until its task has closed its recordings.
struct EdgeSlot {
    id: u64,
    connection: quinn::Connection,
    finished: watch::Receiver<bool>,
}

impl Shared {
    fn count(&self, update: impl FnOnce(&mut IngestStats)) {
        update(&mut lock(&self.stats));
    }

    fn emit(&self, event: IngestEvent) {
        if let Some(events) = &self.events {
            let _ = events.send(event);
        }
    }
}

async fn handle_incoming(
    incoming: quinn::Incoming,
    shared: Arc<Shared>,
    stop: watch::Receiver<bool>,
) {
    let remote = incoming.remote_address();
    let connection = match incoming.await {
        Ok(connection) => connection,
        Err(e) => {
            tracing::warn!(%remote, error = %e, "refused a connection (TLS handshake failed)");
            shared.count(|s| s.refused += 1);
            return;
        }
    };
    let edge = match tls::edge_identity(&connection) {
        Ok(edge) => edge,
        Err(e) => {
            tracing::warn!(%remote, error = %e, "refused a connection without a usable client certificate");
            shared.count(|s| s.refused += 1);
            connection.close(close_code::PROTOCOL_ERROR.into(), b"no client identity");
            return;
        }
    };
    tracing::info!(%edge, %remote, "edge connected");
    shared.count(|s| s.connections += 1);
    shared.emit(IngestEvent::Connected {
        edge: edge.clone(),
        remote,
    });
    let id = shared
        .next_connection_id
        .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let (finished_tx, finished) = watch::channel(false);
    let slot = EdgeSlot {
        id,
        connection: connection.clone(),
        finished,
    };
    let previous = lock(&shared.edges).insert(edge.clone(), slot);
    if let Some(mut previous) = previous {
        tracing::info!(%edge, "replacing the edge's previous connection");
        previous.connection.close(
            close_code::DONE.into(),
            b"replaced by a newer connection of this edge",
        );
        let _ = previous.finished.wait_for(|done| *done).await;
    }
    let commands = shared.control.register(&edge);
    let mut session = EdgeConnection::new(edge.clone(), shared.clone());
    let reason = session.serve(&connection, stop, commands).await;
    session.close_all();
    let _ = finished_tx.send(true);
    {
        let mut edges = lock(&shared.edges);
        if edges.get(&edge).is_some_and(|slot| slot.id == id) {
            edges.remove(&edge);
        }
    }
    shared.control.unregister(&edge);
    tracing::info!(%edge, %reason, "edge disconnected");
    shared.emit(IngestEvent::Disconnected { edge, reason });
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

/// What one edge connection keeps.
struct EdgeConnection {
    edge: String,
    shared: Arc<Shared>,
    recorders: HashMap<u64, SessionRecorder>,
    acked: HashMap<u64, u64>,
    sent_seq: HashMap<u64, u64>,
    time_sync: HashMap<u64, TimeSync>,
    /// The most recent session seen on this connection: the one pinged for time sync.
    current_session: Option<u64>,
    buffer: Vec<u8>,
}

/// Why a connection loop ended, as text for the log.
type EndReason = String;

impl EdgeConnection {
    fn new(edge: String, shared: Arc<Shared>) -> Self {
        Self {
            edge,
            shared,
            recorders: HashMap::new(),
            acked: HashMap::new(),
            sent_seq: HashMap::new(),
            time_sync: HashMap::new(),
            current_session: None,
            buffer: Vec::new(),
        }
    }

    async fn serve(
        &mut self,
        connection: &quinn::Connection,
        mut stop: watch::Receiver<bool>,
        mut commands: mpsc::UnboundedReceiver<Command>,
    ) -> EndReason {
        let (mut send, mut recv) = tokio::select! {
            streams = connection.accept_bi() => match streams {
                Ok(streams) => streams,
                Err(e) => return format!("no stream opened: {e}"),
            },
            _ = stop.changed() => return "server shutting down".into(),
        };
        let mut commit_tick = tokio::time::interval(self.shared.config.commit_interval);
        let mut ping_tick = tokio::time::interval(self.shared.config.time_sync_interval);
        ping_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            let mut outgoing = Vec::new();
            let ended = tokio::select! {
                chunk = recv.read_chunk(64 * 1024, true) => match chunk {
                    Ok(Some(chunk)) => {
                        self.buffer.extend_from_slice(&chunk.bytes);
                        match self.process_buffer() {
                            Ok(()) => None,
                            Err(reason) => {
                                connection.close(close_code::PROTOCOL_ERROR.into(), reason.as_bytes());
                                Some(reason)
                            }
                        }
                    }
                    Ok(None) => Some("the edge finished its stream".to_owned()),
                    Err(e) => Some(match connection.close_reason() {
                        Some(quinn::ConnectionError::ApplicationClosed(close)) => format!(
                            "the edge closed the connection: {}",
                            String::from_utf8_lossy(&close.reason)
                        ),
                        _ => format!("connection lost: {e}"),
                    }),
                },
                _ = commit_tick.tick() => match self.commit(&mut outgoing) {
                    Ok(()) => None,
                    Err(reason) => {
                        connection.close(close_code::STORAGE_ERROR.into(), reason.as_bytes());
                        Some(reason)
                    }
                },
                _ = ping_tick.tick() => {
                    self.ping(&mut outgoing);
                    None
                }
                // Commands wait until the edge has said which session it runs.
                Some(command) = commands.recv(), if self.current_session.is_some() => {
                    match self.command(command, &mut outgoing) {
                        Ok(()) => None,
                        Err(reason) => {
                            connection.close(close_code::STORAGE_ERROR.into(), reason.as_bytes());
                            Some(reason)
                        }
                    }
                }
                _ = stop.changed() => {
                    let _ = self.commit(&mut outgoing);
                    if let Err(e) = write_frames(&mut send, &outgoing).await {
                        tracing::debug!(edge = %self.edge, error = %e, "final acks not sent");
                    }
                    connection.close(close_code::DONE.into(), b"server shutting down");
                    return "server shutting down".into();
                }
            };
            if let Some(reason) = ended {
                // Whatever was received is made durable even though the edge cannot be told.
                let _ = self.commit(&mut Vec::new());
                return reason;
            }
            if let Err(e) = write_frames(&mut send, &outgoing).await {
                let _ = self.commit(&mut Vec::new());
                return format!("cannot write to the edge: {e}");
            }
        }
    }

    /// Decodes every complete frame in the buffer. `Err` = a protocol error that ends the
    /// connection (the reason is logged and sent in the close frame).
    fn process_buffer(&mut self) -> Result<(), String> {
        let mut consumed = 0;
        let result = loop {
            let rest = &self.buffer[consumed..];
            match decode(rest) {
                Ok((frame, len)) => {
                    let raw = rest[..len].to_vec();
                    consumed += len;
                    if let Err(reason) = self.on_frame(frame, &raw) {
                        break Err(reason);
                    }
                }
                Err(DecodeError::Incomplete { .. }) => break Ok(()),
                Err(DecodeError::Malformed(detail)) => {
                    // The header was fine, so its length tells where the next frame starts.
                    let skip = decode_header(rest)
                        .map(|h| HEADER_LEN + h.payload_len as usize)
                        .unwrap_or(rest.len());
                    tracing::warn!(edge = %self.edge, %detail, bytes = skip, "skipping a malformed frame");
                    self.shared.count(|s| s.rejected += 1);
                    consumed += skip;
                }
                Err(fatal) => {
                    self.shared.count(|s| s.rejected += 1);
                    let reason = format!("rejected the stream: {fatal}");
                    tracing::warn!(edge = %self.edge, "{reason}; closing the connection");
                    break Err(reason);
                }
            }
        };
        self.buffer.drain(..consumed.min(self.buffer.len()));
        result
    }

    fn on_frame(&mut self, frame: Frame, raw: &[u8]) -> Result<(), String> {
        if frame.body.direction() == Direction::ServerToEdge {
            tracing::warn!(edge = %self.edge, seq = frame.seq, "ignoring a server-to-edge frame sent by the edge");
            self.shared.count(|s| s.rejected += 1);
            return Ok(());
        }
        let session_id = frame.session_id;
        let now = unix_now_ns();
        if !self.recorders.contains_key(&session_id) {
            let recorder = block(|| {
                SessionRecorder::open(&self.shared.config.data_dir, &self.edge, session_id)
            })
            .map_err(|e| format!("cannot open the recording of session {session_id:016x}: {e}"))?;
            self.recorders.insert(session_id, recorder);
        }
        if let Body::TimePong(pong) = &frame.body {
            let exchange = Exchange {
                t0_ns: pong.t0_ns,
                t1_ns: pong.t1_ns,
                t2_ns: pong.t2_ns,
                t3_ns: now,
            };
            let sync = self.time_sync.entry(session_id).or_default();
            if sync.add(exchange)
                && let Some(estimate) = sync.estimate()
            {
                tracing::debug!(edge = %self.edge, offset_ms = estimate.offset_ns / 1e6, rtt_ms = estimate.delay_ns / 1e6, "time sync");
                self.shared.emit(IngestEvent::TimeSync {
                    edge: self.edge.clone(),
                    session_id,
                    estimate,
                });
            }
        }
        self.current_session = Some(session_id);
        let recorder = self
            .recorders
            .get_mut(&session_id)
            .ok_or("recorder vanished")?;
        match recorder.append(raw, &frame, now) {
            Ok(Appended::Buffered) => {
                let bytes = raw.len() as u64;
                self.shared.count(|s| {
                    s.frames += 1;
                    s.bytes += bytes;
                });
                self.shared.emit(IngestEvent::Frame {
                    edge: self.edge.clone(),
                    frame,
                });
            }
            // A resend of something already recorded: the next commit acknowledges it again
            // (every connection starts with nothing acknowledged).
            Ok(Appended::Duplicate) => self.shared.count(|s| s.duplicates += 1),
            Err(e) => return Err(format!("cannot record session {session_id:016x}: {e}")),
        }
        Ok(())
    }

    /// Makes every session durable and queues acks for what became durable.
    fn commit(&mut self, outgoing: &mut Vec<Frame>) -> Result<(), String> {
        for (&session_id, recorder) in &mut self.recorders {
            let durable = block(|| recorder.commit())
                .map_err(|e| format!("cannot commit session {session_id:016x}: {e}"))?;
            let Some(up_to) = durable else { continue };
            if self
                .acked
                .get(&session_id)
                .is_some_and(|&acked| acked >= up_to)
            {
                continue;
            }
            self.acked.insert(session_id, up_to);
            let seq = next_seq(&mut self.sent_seq, session_id);
            outgoing.push(Frame::new(session_id, seq, Ack::UpTo { seq: up_to }));
        }
        Ok(())
    }

    /// Records a command in the edge's current session and queues it for sending.
    fn command(&mut self, command: Command, outgoing: &mut Vec<Frame>) -> Result<(), String> {
        let Some(session_id) = self.current_session else {
            return Ok(());
        };
        let seq = next_seq(&mut self.sent_seq, session_id);
        let frame = Frame::new(session_id, seq, command);
        let raw = encode(&frame).map_err(|e| format!("cannot encode a command: {e}"))?;
        if let Some(recorder) = self.recorders.get_mut(&session_id) {
            recorder
                .append_command(&raw, &frame, unix_now_ns())
                .map_err(|e| format!("cannot record a command: {e}"))?;
        }
        tracing::info!(edge = %self.edge, command = ?frame.body, "command sent");
        outgoing.push(frame);
        Ok(())
    }

    fn ping(&mut self, outgoing: &mut Vec<Frame>) {
        if let Some(session_id) = self.current_session {
            let seq = next_seq(&mut self.sent_seq, session_id);
            outgoing.push(Frame::new(
                session_id,
                seq,
                TimePing {
                    t0_ns: unix_now_ns(),
                },
            ));
        }
    }

    fn close_all(&mut self) {
        for (session_id, recorder) in self.recorders.drain() {
            if let Err(e) = block(|| recorder.close()) {
                tracing::warn!(edge = %self.edge, session = format!("{session_id:016x}"), error = %e, "closing the recording failed");
            }
        }
    }
}

fn next_seq(counters: &mut HashMap<u64, u64>, session_id: u64) -> u64 {
    let counter = counters.entry(session_id).or_insert(0);
    let seq = *counter;
    *counter += 1;
    seq
}

async fn write_frames(send: &mut quinn::SendStream, frames: &[Frame]) -> anyhow::Result<()> {
    for frame in frames {
        send.write_all(&encode(frame)?).await?;
    }
    Ok(())
}

/// Runs blocking file work (fsync) without stalling the other connections' tasks.
fn block<T>(work: impl FnOnce() -> T) -> T {
    match tokio::runtime::Handle::try_current() {
        Ok(handle) if handle.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(work)
        }
        _ => work(),
    }
}

/// Server wall clock, ns since the UNIX epoch (the clock of MCAP log times and time sync).
pub fn unix_now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}
