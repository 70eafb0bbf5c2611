//! The ingest endpoint: edges connect over QUIC with mutual TLS; each connection gets a task
//! that records every frame durably and acknowledges it.
//!
//! One bidirectional stream per connection carries length-prefixed frames both ways
//! (`scan3d_protocol` framing): edge → server data, server → edge acks and commands. Time-sync
//! pings and pongs go as QUIC datagrams instead (one frame each, unsequenced, never
//! acknowledged or resent), so a backlog on the stream cannot delay them. The task
//! - learns the edge's name from its client certificate (a connection without a valid one
//!   never gets here: the TLS handshake refuses it);
//! - appends each frame to its session's [`SessionRecorder`], ignoring duplicates (resends);
//! - every `commit_interval` finishes the MCAP chunk, fsyncs, and acknowledges what became
//!   durable in each session, as ranges ([`AckPlan`]): a frame is acknowledged only once it is
//!   on disk, and a gap in the sequence numbers does not stop the acknowledgement of later ones;
//! - every `time_sync_interval` pings the edge in a datagram stamped with the server's
//!   monotonic clock ([`ServerClock`]); each pong that answers a ping of this connection feeds
//!   the edge's [`TimeSync`] estimator (kept across reconnects, reset when the edge's session
//!   or its `Hello::clock_id` changes), and each new [`ClockModel`] is recorded in the pong's
//!   session (`/scan3d/timesync`) and reported ([`IngestEvent::TimeSync`]);
//! - rejects frames it cannot use (bad magic, unknown protocol version, over the size limit)
//!   with a logged reason and closes the connection cleanly. A frame whose header is fine but
//!   whose payload does not decode, or that carries a server → edge body, is recorded raw
//!   ([`SessionRecorder::append_undecodable`]), acknowledged and reported, when its session and
//!   seq can be read ([`decode_ids`]); otherwise it is counted and logged.
//!
//! # What a peer can cost ([`IngestLimits`])
//!
//! - Unauthenticated peers: at most `max_handshakes` handshakes in progress, each for at most
//!   `handshake_timeout`; above `retry_above_handshakes` in progress, a peer must first prove
//!   its address with a QUIC Retry (stateless for the server). Only connections that completed
//!   the handshake with a valid certificate take one of the `max_connections` slots, so a
//!   flood of Initials that never complete cannot keep a paired edge out.
//! - An authenticated edge that opens no stream within `first_stream_timeout` is dropped.
//! - Per edge connection, at most `max_sessions_per_edge` recordings are open (the least
//!   recently used one is committed, acknowledged and closed to open another; one unused for
//!   `session_idle_timeout` is closed), and at most `max_buffered_bytes_per_edge` of frames wait
//!   for a commit (more commits early). Memory and file descriptors per edge are bounded
//!   whatever session ids it sends.
//!
//! # A second connection under a connected name
//!
//! See [`claim_slot`]: replace the old connection when it has been silent for
//! `replace_after_silence`, refuse the new one while the old is demonstrably alive.
//!
//! Shutdown follows mini-redis: a `watch` channel tells every task to stop; each commits what
//! it has, closes its recordings (writing the MCAP summary) and closes its connection.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use scan3d_protocol::{
    Body, Command, DecodeError, Direction, Frame, HEADER_LEN, decode, decode_header, decode_ids,
    encode,
};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tokio::task::JoinSet;

use super::acks::AckPlan;
use super::control::{EdgeControl, QueuedCommand, SentCommand};
use super::tls;
use crate::pose::timesync::{
    ClockModel, EdgeClock, MonotonicServerClock, Pinger, ServerClock, TimeSyncConfig,
};
use crate::recording::{Appended, ServerRecord, SessionRecorder, body_name};

/// QUIC application close codes the server uses.
pub mod close_code {
    /// Normal close (server shutting down, edge going away).
    pub const DONE: u32 = 0;
    /// The peer sent bytes that are not scan3d frames, or of another protocol version, or
    /// opened no stream in time.
    pub const PROTOCOL_ERROR: u32 = 1;
    /// The server could not record (disk full, permissions): the edge keeps its spool.
    pub const STORAGE_ERROR: u32 = 2;
    /// Too many edges connected.
    pub const BUSY: u32 = 3;
    /// Another connection under the same edge name is alive (two devices share one
    /// certificate, or the edge came back before its old connection went quiet): retry later.
    pub const DUPLICATE_EDGE: u32 = 4;
}

/// Acks sent per session per commit at most (see [`AckPlan::next_acks`]); the rest follow on
/// the next commits.
const MAX_ACKS_PER_COMMIT: usize = 64;

/// What unauthenticated peers and each edge connection may cost; see the module docs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IngestLimits {
    /// TLS handshakes in progress at once; further Initials are refused (`CONNECTION_REFUSED`).
    pub max_handshakes: usize,
    /// With more handshakes than this in progress, a peer whose address is not validated gets
    /// a QUIC Retry first (0: always).
    pub retry_above_handshakes: usize,
    /// A handshake not finished by then is dropped.
    pub handshake_timeout: Duration,
    /// An authenticated connection that opened no stream by then is closed.
    pub first_stream_timeout: Duration,
    /// Session recordings open at once per edge connection.
    pub max_sessions_per_edge: usize,
    /// A session recording without frames for this long is committed and closed.
    pub session_idle_timeout: Duration,
    /// Frame bytes appended but not yet committed, across one edge's recordings; over it the
    /// edge's recordings are committed at once.
    pub max_buffered_bytes_per_edge: usize,
    /// A new connection under an edge name already connected replaces the old connection if
    /// the old one received nothing for this long; otherwise the new one is refused.
    pub replace_after_silence: Duration,
}

impl Default for IngestLimits {
    fn default() -> Self {
        Self {
            max_handshakes: 64,
            retry_above_handshakes: 8,
            handshake_timeout: Duration::from_secs(5),
            first_stream_timeout: Duration::from_secs(10),
            max_sessions_per_edge: 8,
            session_idle_timeout: Duration::from_secs(60),
            max_buffered_bytes_per_edge: 16 << 20,
            // Two keep-alive intervals and a margin: a live peer answers keep-alives.
            replace_after_silence: tls::KEEP_ALIVE_INTERVAL * 2 + Duration::from_secs(1),
        }
    }
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
    /// Authenticated edges served at once; more are refused with [`close_code::BUSY`].
    pub max_connections: usize,
    /// Bounds on handshakes, sessions and buffers.
    pub limits: IngestLimits,
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
    /// A new clock model for an edge session (also recorded in the session).
    TimeSync {
        /// The edge.
        edge: String,
        /// Its session.
        session_id: u64,
        /// How the session's edge clock maps to the server's monotonic clock.
        model: ClockModel,
    },
    /// A connection ended.
    Disconnected {
        /// The edge.
        edge: String,
        /// Why.
        reason: String,
    },
}

/// A consumer of what ingest reports that must never make ingest wait (the live pipeline,
/// `pipeline::live`, which queues frames with `try_send`). Called on the connection's task, in
/// recording order: a frame is reported once, when the recorder accepted it (not a duplicate).
pub trait IngestSink: Send + Sync {
    /// Takes one event; must return at once.
    fn on_event(&self, event: IngestEvent);
}

/// Counters over the server's lifetime.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IngestStats {
    /// Connections that completed the TLS handshake with a valid client certificate.
    pub connections: u64,
    /// Connection attempts refused (handshake failed or timed out, too many handshakes or
    /// edges, duplicate edge name).
    pub refused: u64,
    /// Handshakes dropped after [`IngestLimits::handshake_timeout`].
    pub handshake_timeouts: u64,
    /// QUIC Retry packets sent to validate a peer's address under load.
    pub address_validations: u64,
    /// Authenticated connections closed because they opened no stream in time.
    pub no_stream: u64,
    /// Connections that replaced a silent connection under the same edge name.
    pub replaced: u64,
    /// Connections refused because the same edge name was connected and alive.
    pub duplicate_names: u64,
    /// Frames recorded.
    pub frames: u64,
    /// Bytes of frames recorded.
    pub bytes: u64,
    /// Resent frames ignored because they were already recorded.
    pub duplicates: u64,
    /// Connections closed for protocol errors (bad magic, version, size).
    pub rejected: u64,
    /// Frames whose payload did not decode, recorded raw and acknowledged.
    pub undecodable: u64,
    /// Frames carrying a server → edge body, recorded raw and acknowledged.
    pub misdirected: u64,
    /// Undecodable frames whose session and seq could not even be read: dropped, never
    /// acknowledged.
    pub unidentified: u64,
    /// Recordings closed to make room for another session of the same edge.
    pub sessions_evicted: u64,
    /// Recordings closed after [`IngestLimits::session_idle_timeout`] without frames.
    pub sessions_idle_closed: u64,
    /// Commits made early because an edge buffered [`IngestLimits::max_buffered_bytes_per_edge`].
    pub early_commits: u64,
    /// The most session recordings open at once, all edges together.
    pub peak_recorders_open: u64,
}

/// A bound, not yet running, ingest server.
pub struct IngestServer {
    endpoint: quinn::Endpoint,
    config: IngestConfig,
    control: EdgeControl,
    clock: Arc<dyn ServerClock>,
    time_sync: TimeSyncConfig,
    sink: Option<Arc<dyn IngestSink>>,
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
            clock: Arc::new(MonotonicServerClock::new()),
            time_sync: TimeSyncConfig::default(),
            sink: None,
        })
    }

    /// Uses `clock` for time-sync t0/t3 instead of [`MonotonicServerClock`] (tests, simulation).
    pub fn with_clock(mut self, clock: Arc<dyn ServerClock>) -> Self {
        self.clock = clock;
        self
    }

    /// Uses these time-sync estimator settings (e.g. another window) instead of the defaults.
    pub fn with_time_sync(mut self, config: TimeSyncConfig) -> Self {
        self.time_sync = config;
        self
    }

    /// Also reports every event to `sink` (besides the `events` channel of [`run`](Self::run)).
    pub fn with_sink(mut self, sink: Arc<dyn IngestSink>) -> Self {
        self.sink = Some(sink);
        self
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
        let max_handshakes = self.config.limits.max_handshakes.max(1);
        let shared = Arc::new(Shared {
            config: self.config,
            events,
            sink: self.sink,
            stats: Mutex::new(IngestStats::default()),
            edges: Mutex::new(HashMap::new()),
            control: self.control,
            next_connection_id: AtomicU64::new(0),
            recorders_open: AtomicUsize::new(0),
            clock: self.clock,
            time_sync: self.time_sync,
            edge_clocks: Mutex::new(HashMap::new()),
        });
        let (stop_tx, stop_rx) = watch::channel(false);
        let handshakes = Arc::new(Semaphore::new(max_handshakes));
        let mut tasks = JoinSet::new();
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                () = &mut shutdown => break,
                incoming = self.endpoint.accept() => {
                    let Some(incoming) = incoming else { break };
                    let in_progress = max_handshakes - handshakes.available_permits();
                    let remote = incoming.remote_address();
                    match admission(
                        in_progress,
                        &shared.config.limits,
                        incoming.remote_address_validated(),
                        incoming.may_retry(),
                    ) {
                        Admission::Retry => {
                            tracing::debug!(%remote, in_progress, "validating the address (QUIC retry)");
                            shared.count(|s| s.address_validations += 1);
                            if let Err(e) = incoming.retry() {
                                e.into_incoming().refuse();
                            }
                        }
                        Admission::Refuse => {
                            tracing::warn!(%remote, in_progress, "too many handshakes in progress; refusing");
                            shared.count(|s| s.refused += 1);
                            incoming.refuse();
                        }
                        Admission::Handshake => {
                            let Ok(permit) = handshakes.clone().try_acquire_owned() else {
                                incoming.refuse();
                                continue;
                            };
                            let shared = shared.clone();
                            let stop = stop_rx.clone();
                            tasks.spawn(handle_incoming(incoming, permit, shared, stop));
                        }
                    }
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

/// What to do with a new QUIC Initial.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Admission {
    /// Start the TLS handshake (takes one of `max_handshakes`).
    Handshake,
    /// Ask the peer to prove its address first (stateless for the server).
    Retry,
    /// Refuse: too many handshakes in progress even for validated peers.
    Refuse,
}

/// The admission rule for a new Initial, given the handshakes in progress: under load, peers
/// must validate their address before the server keeps any state for them, and there is a cap
/// even for validated ones (the handshake timeout frees their places).
fn admission(
    in_progress: usize,
    limits: &IngestLimits,
    address_validated: bool,
    may_retry: bool,
) -> Admission {
    if !address_validated && may_retry && in_progress >= limits.retry_above_handshakes {
        Admission::Retry
    } else if in_progress >= limits.max_handshakes {
        Admission::Refuse
    } else {
        Admission::Handshake
    }
}

struct Shared {
    config: IngestConfig,
    events: Option<mpsc::UnboundedSender<IngestEvent>>,
    sink: Option<Arc<dyn IngestSink>>,
    stats: Mutex<IngestStats>,
    /// The live connection of each authenticated edge: one entry per slot of
    /// `max_connections` (see [`claim_slot`]).
    edges: Mutex<HashMap<String, EdgeSlot>>,
    /// Commands for the edges, routed to their live connection's task.
    control: EdgeControl,
    next_connection_id: AtomicU64,
    /// Session recordings open now, all edges together.
    recorders_open: AtomicUsize,
    /// t0 and t3 of time-sync exchanges.
    clock: Arc<dyn ServerClock>,
    time_sync: TimeSyncConfig,
    /// The clock estimator of each edge, by name: it outlives connections, so a reconnect
    /// keeps the fit (one entry per paired edge at most).
    edge_clocks: Mutex<HashMap<String, EdgeClock>>,
}

/// An edge's current connection and a way to wait until its task has closed its recordings.
struct EdgeSlot {
    id: u64,
    remote: SocketAddr,
    connection: quinn::Connection,
    liveness: Arc<Liveness>,
    finished: watch::Receiver<bool>,
}

/// When a connection last received a UDP datagram, sampled by its task (a live peer sends at
/// least keep-alive acknowledgements every [`tls::KEEP_ALIVE_INTERVAL`]).
struct Liveness {
    /// `(datagrams received, when that count was first seen)`.
    last: Mutex<(u64, Instant)>,
}

impl Liveness {
    fn new(connection: &quinn::Connection) -> Self {
        Self {
            last: Mutex::new((connection.stats().udp_rx.datagrams, Instant::now())),
        }
    }

    /// Notes whether the connection received anything since the last call.
    fn observe(&self, connection: &quinn::Connection) {
        let datagrams = connection.stats().udp_rx.datagrams;
        let mut last = lock(&self.last);
        if datagrams != last.0 {
            *last = (datagrams, Instant::now());
        }
    }

    /// How long the connection has received nothing (as of the last observation).
    fn silent_for(&self, connection: &quinn::Connection) -> Duration {
        self.observe(connection);
        lock(&self.last).1.elapsed()
    }
}

/// The outcome of [`claim_slot`].
enum Claim {
    /// The edge was not connected: it has a new slot.
    New,
    /// The edge's previous connection was silent: the new one took its slot.
    Replaces {
        previous: EdgeSlot,
        silent_for: Duration,
    },
    /// The edge's previous connection is alive: the new one is refused.
    Duplicate {
        other: SocketAddr,
        silent_for: Duration,
    },
    /// Every slot is taken by other edges.
    Busy,
}

/// Takes a connection slot for `edge`, the rule for a second connection under a name that is
/// already connected included.
///
/// **Replace when the old connection is silent, refuse while it is alive.** An edge that comes
/// back after an outage the server has not noticed yet (Wi-Fi dropped, NAT rebinding, edge
/// crashed and restarted) has an old connection that receives nothing any more: after
/// `replace_after_silence` without a datagram (longer than two keep-alive intervals, which a
/// live peer would answer) the new connection replaces it, so such an edge waits a few seconds
/// at most, never until the 10 s idle timeout or for ever. Two live devices with one
/// certificate both keep their connections busy: the second is refused with
/// [`close_code::DUPLICATE_EDGE`], so the first keeps recording instead of the two evicting
/// each other, and every refusal is logged at warn with both addresses and counted
/// ([`IngestStats::duplicate_names`]). A closed old connection is replaced at once.
fn claim_slot(shared: &Shared, edge: &str, slot: EdgeSlot) -> Claim {
    let mut edges = lock(&shared.edges);
    let connected = edges.len();
    match edges.get(edge) {
        Some(old) => {
            let silent_for = old.liveness.silent_for(&old.connection);
            let closed = old.connection.close_reason().is_some();
            if closed || silent_for >= shared.config.limits.replace_after_silence {
                let previous = edges
                    .insert(edge.to_owned(), slot)
                    .expect("the old slot is there");
                Claim::Replaces {
                    previous,
                    silent_for,
                }
            } else {
                Claim::Duplicate {
                    other: old.remote,
                    silent_for,
                }
            }
        }
        None if connected >= shared.config.max_connections.max(1) => Claim::Busy,
        None => {
            edges.insert(edge.to_owned(), slot);
            Claim::New
        }
    }
}

impl Shared {
    fn count(&self, update: impl FnOnce(&mut IngestStats)) {
        update(&mut lock(&self.stats));
    }

    fn emit(&self, event: IngestEvent) {
        match (&self.sink, &self.events) {
            (Some(sink), Some(events)) => {
                sink.on_event(event.clone());
                let _ = events.send(event);
            }
            (Some(sink), None) => sink.on_event(event),
            (None, Some(events)) => {
                let _ = events.send(event);
            }
            (None, None) => {}
        }
    }

    fn recorder_opened(&self) {
        let open = self.recorders_open.fetch_add(1, Ordering::Relaxed) + 1;
        self.count(|s| s.peak_recorders_open = s.peak_recorders_open.max(open as u64));
    }

    fn recorder_closed(&self) {
        self.recorders_open.fetch_sub(1, Ordering::Relaxed);
    }
}

async fn handle_incoming(
    incoming: quinn::Incoming,
    handshake: OwnedSemaphorePermit,
    shared: Arc<Shared>,
    stop: watch::Receiver<bool>,
) {
    let remote = incoming.remote_address();
    let limits = &shared.config.limits;
    let connecting = match incoming.accept() {
        Ok(connecting) => connecting,
        Err(e) => {
            tracing::warn!(%remote, error = %e, "refused a connection");
            shared.count(|s| s.refused += 1);
            return;
        }
    };
    // Dropping `connecting` on timeout abandons the handshake (quinn closes it).
    let connection = match tokio::time::timeout(limits.handshake_timeout, connecting).await {
        Ok(Ok(connection)) => connection,
        Ok(Err(e)) => {
            tracing::warn!(%remote, error = %e, "refused a connection (TLS handshake failed)");
            shared.count(|s| s.refused += 1);
            return;
        }
        Err(_) => {
            tracing::warn!(%remote, timeout = ?limits.handshake_timeout, "handshake not finished in time; dropped");
            shared.count(|s| {
                s.refused += 1;
                s.handshake_timeouts += 1;
            });
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
    drop(handshake);
    let id = shared.next_connection_id.fetch_add(1, Ordering::Relaxed);
    let (finished_tx, finished) = watch::channel(false);
    let liveness = Arc::new(Liveness::new(&connection));
    let slot = EdgeSlot {
        id,
        remote,
        connection: connection.clone(),
        liveness: liveness.clone(),
        finished,
    };
    match claim_slot(&shared, &edge, slot) {
        Claim::New => {}
        Claim::Replaces {
            mut previous,
            silent_for,
        } => {
            tracing::warn!(%edge, %remote, previous = %previous.remote, ?silent_for,
                "a new connection of this edge replaces its silent previous one");
            shared.count(|s| s.replaced += 1);
            previous.connection.close(
                close_code::DONE.into(),
                b"replaced by a newer connection of this edge",
            );
            let _ = previous.finished.wait_for(|done| *done).await;
        }
        Claim::Duplicate { other, silent_for } => {
            tracing::warn!(%edge, %remote, connected = %other, ?silent_for,
                "refused a second connection under a connected edge name (two devices with one certificate, or the old connection is not silent yet)");
            shared.count(|s| {
                s.refused += 1;
                s.duplicate_names += 1;
            });
            connection.close(
                close_code::DUPLICATE_EDGE.into(),
                b"this edge name is connected from another address",
            );
            return;
        }
        Claim::Busy => {
            tracing::warn!(%edge, %remote, max = shared.config.max_connections, "too many edges; refusing");
            shared.count(|s| s.refused += 1);
            connection.close(close_code::BUSY.into(), b"too many edges");
            return;
        }
    }
    tracing::info!(%edge, %remote, "edge connected");
    shared.count(|s| s.connections += 1);
    shared.emit(IngestEvent::Connected {
        edge: edge.clone(),
        remote,
    });
    let commands = shared.control.register(&edge);
    let mut session = EdgeConnection::new(edge.clone(), shared.clone(), liveness);
    let reason = session.serve(&connection, stop, commands).await;
    session.close_all();
    let _ = finished_tx.send(true);
    {
        let mut edges = lock(&shared.edges);
        if edges.get(&edge).is_some_and(|slot| slot.id == id) {
            edges.remove(&edge);
        }
    }
    shared.control.unregister(&edge, &reason);
    tracing::info!(%edge, %reason, "edge disconnected");
    shared.emit(IngestEvent::Disconnected { edge, reason });
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

/// One open session recording of an edge connection.
struct OpenSession {
    recorder: SessionRecorder,
    /// What this connection acknowledged of the session.
    acks: AckPlan,
    last_used: Instant,
    /// Frame bytes appended since the last commit.
    buffered: usize,
}

/// What one edge connection keeps.
struct EdgeConnection {
    edge: String,
    shared: Arc<Shared>,
    liveness: Arc<Liveness>,
    /// At most [`IngestLimits::max_sessions_per_edge`].
    sessions: HashMap<u64, OpenSession>,
    /// Next server → edge seq per session: kept for the open sessions and the current one.
    sent_seq: HashMap<u64, u64>,
    /// Pings sent on this connection and not yet answered.
    pinger: Pinger,
    /// The most recent session seen on this connection: commands go to it.
    current_session: Option<u64>,
    buffer: Vec<u8>,
    /// Sum of the sessions' `buffered`.
    buffered: usize,
    /// Frames to send to the edge after the current step.
    outgoing: Vec<Frame>,
}

/// Why a connection loop ended, as text for the log.
type EndReason = String;

impl EdgeConnection {
    fn new(edge: String, shared: Arc<Shared>, liveness: Arc<Liveness>) -> Self {
        Self {
            edge,
            shared,
            liveness,
            sessions: HashMap::new(),
            sent_seq: HashMap::new(),
            pinger: Pinger::default(),
            current_session: None,
            buffer: Vec::new(),
            buffered: 0,
            outgoing: Vec::new(),
        }
    }

    async fn serve(
        &mut self,
        connection: &quinn::Connection,
        mut stop: watch::Receiver<bool>,
        mut commands: mpsc::UnboundedReceiver<QueuedCommand>,
    ) -> EndReason {
        let first_stream_timeout = self.shared.config.limits.first_stream_timeout;
        let (mut send, mut recv) = tokio::select! {
            streams = tokio::time::timeout(first_stream_timeout, connection.accept_bi()) => match streams {
                Ok(Ok(streams)) => streams,
                Ok(Err(e)) => return format!("no stream opened: {e}"),
                Err(_) => {
                    self.shared.count(|s| s.no_stream += 1);
                    connection.close(close_code::PROTOCOL_ERROR.into(), b"no stream opened in time");
                    return format!("no stream opened within {first_stream_timeout:?}");
                }
            },
            _ = stop.changed() => return "server shutting down".into(),
        };
        let mut commit_tick = tokio::time::interval(self.shared.config.commit_interval);
        let mut ping_tick = tokio::time::interval(self.shared.config.time_sync_interval);
        ping_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            let ended = tokio::select! {
                chunk = recv.read_chunk(64 * 1024, true) => match chunk {
                    Ok(Some(chunk)) => {
                        self.buffer.extend_from_slice(&chunk.bytes);
                        match self.process_buffer() {
                            Ok(()) => None,
                            Err(Failure::Protocol(reason)) => {
                                connection.close(close_code::PROTOCOL_ERROR.into(), reason.as_bytes());
                                Some(reason)
                            }
                            Err(Failure::Storage(reason)) => {
                                connection.close(close_code::STORAGE_ERROR.into(), reason.as_bytes());
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
                _ = commit_tick.tick() => {
                    self.liveness.observe(connection);
                    match self.commit().and_then(|()| self.close_idle_sessions()) {
                        Ok(()) => None,
                        Err(reason) => {
                            connection.close(close_code::STORAGE_ERROR.into(), reason.as_bytes());
                            Some(reason)
                        }
                    }
                }
                _ = ping_tick.tick() => {
                    self.ping(connection);
                    None
                }
                datagram = connection.read_datagram() => match datagram {
                    Ok(datagram) => match self.on_datagram(&datagram) {
                        Ok(()) => None,
                        Err(reason) => {
                            connection.close(close_code::STORAGE_ERROR.into(), reason.as_bytes());
                            Some(reason)
                        }
                    },
                    Err(e) => Some(format!("connection lost: {e}")),
                },
                // Commands wait until the edge has said which session it runs.
                Some(queued) = commands.recv(), if self.current_session.is_some() => {
                    match self.command(queued.command) {
                        Ok(sent) => {
                            if let Some(tell) = queued.sent {
                                let _ = tell.send(sent);
                            }
                            None
                        }
                        Err(reason) => {
                            connection.close(close_code::STORAGE_ERROR.into(), reason.as_bytes());
                            Some(reason)
                        }
                    }
                }
                _ = stop.changed() => {
                    let _ = self.commit();
                    let outgoing = std::mem::take(&mut self.outgoing);
                    if let Err(e) = write_frames(&mut send, &outgoing).await {
                        tracing::debug!(edge = %self.edge, error = %e, "final acks not sent");
                    }
                    connection.close(close_code::DONE.into(), b"server shutting down");
                    return "server shutting down".into();
                }
            };
            if let Some(reason) = ended {
                // Whatever was received is made durable even though the edge cannot be told.
                let _ = self.commit();
                return reason;
            }
            let outgoing = std::mem::take(&mut self.outgoing);
            if let Err(e) = write_frames(&mut send, &outgoing).await {
                let _ = self.commit();
                return format!("cannot write to the edge: {e}");
            }
        }
    }

    /// Decodes every complete frame in the buffer. `Err` ends the connection (the reason is
    /// logged and sent in the close frame).
    fn process_buffer(&mut self) -> Result<(), Failure> {
        let mut consumed = 0;
        let result = loop {
            let rest = &self.buffer[consumed..];
            match decode(rest) {
                Ok((frame, len)) => {
                    let raw = rest[..len].to_vec();
                    consumed += len;
                    if let Err(reason) = self.on_frame(frame, &raw) {
                        break Err(Failure::Storage(reason));
                    }
                }
                Err(DecodeError::Incomplete { .. }) => break Ok(()),
                Err(DecodeError::Malformed(detail)) => {
                    // The header was fine (and the whole frame is there), so its length tells
                    // where the next frame starts.
                    let len = decode_header(rest)
                        .map(|h| HEADER_LEN + h.payload_len as usize)
                        .unwrap_or(rest.len())
                        .min(rest.len());
                    let raw = rest[..len].to_vec();
                    consumed += len;
                    let reason = format!("payload does not decode: {detail}");
                    if let Err(reason) = self.on_undecodable(&raw, &reason, false) {
                        break Err(Failure::Storage(reason));
                    }
                }
                Err(fatal) => {
                    self.shared.count(|s| s.rejected += 1);
                    let reason = format!("rejected the stream: {fatal}");
                    tracing::warn!(edge = %self.edge, "{reason}; closing the connection");
                    break Err(Failure::Protocol(reason));
                }
            }
        };
        self.buffer.drain(..consumed.min(self.buffer.len()));
        result
    }

    /// A frame that cannot be recorded as what it claims to be (`misdirected`: a server → edge
    /// body; otherwise: a payload that does not decode). Recorded raw and acknowledged when its
    /// session and seq can be read, so it leaves no gap; counted and logged either way.
    fn on_undecodable(
        &mut self,
        raw: &[u8],
        reason: &str,
        misdirected: bool,
    ) -> Result<(), String> {
        let Some((session_id, seq)) = raw.get(HEADER_LEN..).and_then(decode_ids) else {
            tracing::warn!(edge = %self.edge, bytes = raw.len(), %reason,
                "dropped a frame whose session and seq cannot be read (it cannot be acknowledged)");
            self.shared.count(|s| s.unidentified += 1);
            return Ok(());
        };
        tracing::warn!(edge = %self.edge, session = format!("{session_id:016x}"), seq, %reason,
            "recording a frame that cannot be used raw, and acknowledging it");
        self.shared.count(|s| {
            if misdirected {
                s.misdirected += 1;
            } else {
                s.undecodable += 1;
            }
        });
        let now = unix_now_ns();
        let open = self.session(session_id)?;
        let appended = open
            .recorder
            .append_undecodable(seq, raw, reason, now)
            .map_err(|e| format!("cannot record session {session_id:016x}: {e}"))?;
        match appended {
            Appended::Buffered => self.buffered_bytes(session_id, raw.len())?,
            Appended::Duplicate => self.shared.count(|s| s.duplicates += 1),
        }
        Ok(())
    }

    fn on_frame(&mut self, frame: Frame, raw: &[u8]) -> Result<(), String> {
        if frame.body.direction() == Direction::ServerToEdge {
            let reason = format!(
                "a {} body, which only the server sends",
                body_name(&frame.body)
            );
            return self.on_undecodable(raw, &reason, true);
        }
        let session_id = frame.session_id;
        let now = unix_now_ns();
        if let Body::Hello(hello) = &frame.body {
            self.clock_identity(session_id, hello.clock_id);
        }
        if let Some(previous) = self.current_session
            && previous != session_id
            && !self.sessions.contains_key(&previous)
        {
            // Its recording was closed while it was current; nothing will be sent to it now.
            self.sent_seq.remove(&previous);
        }
        self.current_session = Some(session_id);
        let open = self.session(session_id)?;
        match open.recorder.append(raw, &frame, now) {
            Ok(Appended::Buffered) => {
                let bytes = raw.len() as u64;
                self.shared.count(|s| {
                    s.frames += 1;
                    s.bytes += bytes;
                });
                self.shared.control.publish(&self.edge, &frame);
                self.shared.emit(IngestEvent::Frame {
                    edge: self.edge.clone(),
                    frame,
                });
                self.buffered_bytes(session_id, raw.len())?;
            }
            // A resend of something already recorded: the next commit acknowledges it again
            // if this connection has not yet (every connection starts with nothing acknowledged).
            Ok(Appended::Duplicate) => self.shared.count(|s| s.duplicates += 1),
            Err(e) => return Err(format!("cannot record session {session_id:016x}: {e}")),
        }
        Ok(())
    }

    /// The open recording of `session_id`, opening it (and closing the least recently used
    /// one if [`IngestLimits::max_sessions_per_edge`] are open) if needed.
    fn session(&mut self, session_id: u64) -> Result<&mut OpenSession, String> {
        if !self.sessions.contains_key(&session_id) {
            let max = self.shared.config.limits.max_sessions_per_edge.max(1);
            while self.sessions.len() >= max {
                let Some(lru) = self
                    .sessions
                    .iter()
                    .min_by_key(|(_, open)| open.last_used)
                    .map(|(&id, _)| id)
                else {
                    break;
                };
                tracing::debug!(edge = %self.edge, session = format!("{lru:016x}"), "closing the least recently used recording to open another");
                self.shared.count(|s| s.sessions_evicted += 1);
                self.close_session(lru)?;
            }
            let recorder = off_runtime(|| {
                SessionRecorder::open(&self.shared.config.data_dir, &self.edge, session_id)
            })
            .map_err(|e| format!("cannot open the recording of session {session_id:016x}: {e}"))?;
            self.shared.recorder_opened();
            self.sessions.insert(
                session_id,
                OpenSession {
                    recorder,
                    acks: AckPlan::new(),
                    last_used: Instant::now(),
                    buffered: 0,
                },
            );
        }
        let open = self
            .sessions
            .get_mut(&session_id)
            .ok_or("recorder vanished")?;
        open.last_used = Instant::now();
        Ok(open)
    }

    /// Accounts `bytes` appended to `session_id`; commits every session of the edge when the
    /// edge's buffered bytes exceed [`IngestLimits::max_buffered_bytes_per_edge`].
    fn buffered_bytes(&mut self, session_id: u64, bytes: usize) -> Result<(), String> {
        if let Some(open) = self.sessions.get_mut(&session_id) {
            open.buffered += bytes;
        }
        self.buffered += bytes;
        if self.buffered > self.shared.config.limits.max_buffered_bytes_per_edge {
            self.shared.count(|s| s.early_commits += 1);
            self.commit()?;
        }
        Ok(())
    }

    /// Makes every open session durable and queues acks for what became durable.
    fn commit(&mut self) -> Result<(), String> {
        for (&session_id, open) in &mut self.sessions {
            commit_session(session_id, open, &mut self.sent_seq, &mut self.outgoing)?;
        }
        self.buffered = 0;
        Ok(())
    }

    /// Commits, acknowledges and closes the recording of `session_id`.
    fn close_session(&mut self, session_id: u64) -> Result<(), String> {
        let Some(mut open) = self.sessions.remove(&session_id) else {
            return Ok(());
        };
        self.buffered -= open.buffered.min(self.buffered);
        let committed = commit_session(
            session_id,
            &mut open,
            &mut self.sent_seq,
            &mut self.outgoing,
        );
        let closed = off_runtime(|| open.recorder.close());
        self.shared.recorder_closed();
        // Commands only go to the current session, whose numbering must go on.
        if self.current_session != Some(session_id) {
            self.sent_seq.remove(&session_id);
        }
        committed?;
        closed.map_err(|e| format!("cannot close session {session_id:016x}: {e}"))?;
        Ok(())
    }

    /// Closes the recordings that received nothing for [`IngestLimits::session_idle_timeout`].
    fn close_idle_sessions(&mut self) -> Result<(), String> {
        let timeout = self.shared.config.limits.session_idle_timeout;
        let idle: Vec<u64> = self
            .sessions
            .iter()
            .filter(|(_, open)| open.last_used.elapsed() >= timeout)
            .map(|(&id, _)| id)
            .collect();
        for session_id in idle {
            tracing::debug!(edge = %self.edge, session = format!("{session_id:016x}"), "closing an idle recording");
            self.shared.count(|s| s.sessions_idle_closed += 1);
            self.close_session(session_id)?;
        }
        Ok(())
    }

    /// Records a command in the edge's current session and queues it for sending; says where
    /// it went.
    fn command(&mut self, command: Command) -> Result<SentCommand, String> {
        let Some(session_id) = self.current_session else {
            return Err("a command without a session".into());
        };
        let frame = self.server_frame(session_id, command)?;
        let raw = encode(&frame).map_err(|e| format!("cannot encode a command: {e}"))?;
        let open = self.session(session_id)?;
        open.recorder
            .append_command(&raw, &frame, unix_now_ns())
            .map_err(|e| format!("cannot record a command: {e}"))?;
        tracing::info!(edge = %self.edge, command = ?frame.body, seq = frame.seq, "command sent");
        let sent = SentCommand {
            session_id,
            seq: frame.seq,
        };
        self.outgoing.push(frame);
        Ok(sent)
    }

    /// A server-originated frame of `session_id` with the next server sequence number.
    fn server_frame(&mut self, session_id: u64, body: impl Into<Body>) -> Result<Frame, String> {
        // A new connection numbers its frames from 0, but the session may hold commands of
        // earlier connections (and, in recordings made before server-made records, clock
        // models): go on above them, or the recorder takes this one for a resend.
        let floor = self.session(session_id)?.recorder.next_command_seq();
        let counter = self.sent_seq.entry(session_id).or_insert(0);
        *counter = (*counter).max(floor);
        let seq = next_seq(&mut self.sent_seq, session_id);
        Ok(Frame::new(session_id, seq, body))
    }

    /// Sends a time-sync ping as a datagram (the edge ignores its session id and seq, 0 before
    /// the edge said which session it runs). A ping that cannot be sent costs one exchange.
    fn ping(&mut self, connection: &quinn::Connection) {
        let ping = self.pinger.ping(self.shared.clock.now_ns());
        let frame = Frame::new(self.current_session.unwrap_or(0), 0, ping);
        let sent = encode(&frame).map_err(|e| e.to_string()).and_then(|bytes| {
            connection
                .send_datagram(bytes.into())
                .map_err(|e| e.to_string())
        });
        if let Err(e) = sent {
            tracing::debug!(edge = %self.edge, error = %e, "time-sync ping not sent");
        }
    }

    /// A datagram from the edge: a time-sync pong (anything else is logged and dropped; datagrams
    /// are not recorded). `Err` only when the new clock model cannot be recorded.
    fn on_datagram(&mut self, datagram: &[u8]) -> Result<(), String> {
        let t3_ns = self.shared.clock.now_ns();
        let frame = match decode(datagram) {
            Ok((frame, len)) if len == datagram.len() => frame,
            Ok(_) => {
                tracing::debug!(edge = %self.edge, bytes = datagram.len(), "dropped a datagram with bytes after its frame");
                return Ok(());
            }
            Err(e) => {
                tracing::debug!(edge = %self.edge, error = %e, "dropped a datagram that is not a frame");
                return Ok(());
            }
        };
        let Body::TimePong(pong) = &frame.body else {
            tracing::debug!(edge = %self.edge, body = body_name(&frame.body), "dropped a datagram that is not a time-sync pong");
            return Ok(());
        };
        let Some(exchange) = self.pinger.pong(pong, t3_ns) else {
            tracing::debug!(edge = %self.edge, t0_ns = pong.t0_ns, "dropped a pong that answers no ping of this connection");
            return Ok(());
        };
        let session_id = frame.session_id;
        let model = lock(&self.shared.edge_clocks)
            .entry(self.edge.clone())
            .or_insert_with(|| EdgeClock::new(session_id, self.shared.time_sync))
            .on_exchange(session_id, exchange);
        let Some(model) = model else {
            tracing::debug!(edge = %self.edge, ?exchange, "ignored an exchange with inconsistent timestamps");
            return Ok(());
        };
        tracing::debug!(edge = %self.edge, offset_ns = model.offset_ns, skew_ppm = model.skew_ppm,
            error_bound_ns = model.error_bound_ns, rtt_ns = exchange.delay_ns(), "time sync");
        self.session(session_id)?
            .recorder
            .append_record(&ServerRecord::ClockModel(model), unix_now_ns())
            .map_err(|e| format!("cannot record a clock model: {e}"))?;
        self.shared.emit(IngestEvent::TimeSync {
            edge: self.edge.clone(),
            session_id,
            model,
        });
        Ok(())
    }

    /// A `Hello` of `session_id` named its clock: the edge's estimator starts over when that is
    /// not the clock it was fitting.
    fn clock_identity(&mut self, session_id: u64, clock_id: [u8; 16]) {
        let started_over = lock(&self.shared.edge_clocks)
            .entry(self.edge.clone())
            .or_insert_with(|| EdgeClock::new(session_id, self.shared.time_sync))
            .on_hello(session_id, clock_id);
        if started_over {
            tracing::debug!(edge = %self.edge, session = format!("{session_id:016x}"), "a new edge clock: time sync starts over");
        }
    }

    fn close_all(&mut self) {
        for (session_id, open) in self.sessions.drain() {
            if let Err(e) = off_runtime(|| open.recorder.close()) {
                tracing::warn!(edge = %self.edge, session = format!("{session_id:016x}"), error = %e, "closing the recording failed");
            }
            self.shared.recorder_closed();
        }
        self.buffered = 0;
    }
}

/// Why processing received bytes ended the connection.
enum Failure {
    /// The bytes are not scan3d frames of this version ([`close_code::PROTOCOL_ERROR`]).
    Protocol(String),
    /// Recording failed ([`close_code::STORAGE_ERROR`]: the edge keeps its spool).
    Storage(String),
}

/// Commits one session and queues the acks its durable set now calls for.
fn commit_session(
    session_id: u64,
    open: &mut OpenSession,
    sent_seq: &mut HashMap<u64, u64>,
    outgoing: &mut Vec<Frame>,
) -> Result<(), String> {
    off_runtime(|| open.recorder.commit())
        .map_err(|e| format!("cannot commit session {session_id:016x}: {e}"))?;
    open.buffered = 0;
    let durable = open.recorder.durable_ranges();
    for ack in open.acks.next_acks(&durable, MAX_ACKS_PER_COMMIT) {
        let seq = next_seq(sent_seq, session_id);
        outgoing.push(Frame::new(session_id, seq, ack));
    }
    Ok(())
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
fn off_runtime<T>(work: impl FnOnce() -> T) -> T {
    match tokio::runtime::Handle::try_current() {
        Ok(handle) if handle.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(work)
        }
        _ => work(),
    }
}

/// Server wall clock, ns since the UNIX epoch (the clock of MCAP log times; time sync uses
/// [`ServerClock`], which is monotonic).
pub fn unix_now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn under_load_unvalidated_peers_get_a_retry_and_validated_ones_a_bounded_handshake() {
        let limits = IngestLimits {
            max_handshakes: 4,
            retry_above_handshakes: 2,
            ..IngestLimits::default()
        };
        // Few handshakes in progress: anyone may start one.
        assert_eq!(admission(0, &limits, false, true), Admission::Handshake);
        assert_eq!(admission(1, &limits, false, true), Admission::Handshake);
        // Above the threshold: prove the address first (stateless), then a handshake.
        assert_eq!(admission(2, &limits, false, true), Admission::Retry);
        assert_eq!(admission(2, &limits, true, false), Admission::Handshake);
        assert_eq!(admission(3, &limits, true, false), Admission::Handshake);
        // Full: refused even when validated, and a peer that already retried is not asked again.
        assert_eq!(admission(4, &limits, true, false), Admission::Refuse);
        assert_eq!(admission(4, &limits, false, false), Admission::Refuse);
        assert_eq!(admission(9, &limits, false, true), Admission::Retry);
        // 0: always validate.
        let always = IngestLimits {
            retry_above_handshakes: 0,
            ..limits
        };
        assert_eq!(admission(0, &always, false, true), Admission::Retry);
    }
}
