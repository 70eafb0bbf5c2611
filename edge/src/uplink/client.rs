//! The QUIC client that carries the edge's frames to the server and never loses one.
//!
//! Producers (acquisition threads) call [`UplinkHandle::submit`]: the frame gets the next
//! sequence number of this boot's session and goes into the [`Spool`]. The [`Uplink`] task
//! connects with the edge bundle, sends everything unsent in order, and removes frames from
//! the spool only when the server acknowledges them (after they are on its disk). After a
//! reconnect everything unacknowledged is sent again; the server ignores what it already has.
//!
//! Frames go out in batches, to keep the edge's wake-ups and packets few at full sensor rate:
//! each time the task wakes it writes every unsent frame (up to [`MAX_BATCH_BYTES`]) in one
//! stream write. A frame submitted with [`UplinkHandle::submit`] wakes it at once (revolutions,
//! status, replies); one submitted with [`UplinkHandle::submit_deferred`] (the IMU's 200
//! readings a second) rides with the next write, which comes at the latest
//! [`UplinkConfig::batch_delay`] after the previous one: while frames flow, a timer set at each
//! write covers the deferred frames, and only the first deferred frame after a quiet spell wakes
//! the task. A deferred frame is in the spool from the moment it is submitted, so batching
//! changes when it is sent, never whether.
//!
//! Time-sync pings arrive as QUIC datagrams and are answered with a pong datagram at once
//! ([`super::timesync::answer_ping`]): pongs never enter the spool, so a backlog cannot delay
//! them and a reconnect never resends a stale one.
//!
//! A failed TLS authentication is told apart by who refused ([`classify`]): this edge's TLS
//! stack rejecting the server's certificate (unknown CA, a name that is not `server_name`,
//! expired…; a locally raised crypto error) is [`ConnectFailure::ServerCertificateRejected`];
//! the server closing the connection with a TLS alert (it does not accept this edge's
//! certificate) is [`ConnectFailure::RefusedByServer`]. Either is logged as an error naming the
//! side that refused, on every attempt, counted in [`UplinkStats::auth_failures`], and retried
//! with a long backoff (the operator may be fixing the pairing), never silently.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use scan3d_protocol::{Ack, Body, Command, Frame, FrameReader, encode};
use tokio::sync::{Notify, mpsc, watch};

use super::spool::{Spool, SpoolConfig, SpoolError};
use crate::clock::SharedClock;

/// How to reach the server.
#[derive(Debug, Clone)]
pub struct UplinkConfig {
    /// `host:port` of `scan3d serve`.
    pub server: String,
    /// The name the server certificate must carry.
    pub server_name: String,
    /// TLS client configuration from the edge bundle ([`super::tls::client_config`]).
    pub client_config: quinn::ClientConfig,
    /// Where and how much to spool.
    pub spool: SpoolConfig,
    /// First reconnect delay (doubles up to `max_backoff`).
    pub min_backoff: Duration,
    /// Longest reconnect delay after ordinary failures.
    pub max_backoff: Duration,
    /// Reconnect delay after the server refused the certificate.
    pub auth_backoff: Duration,
    /// On shutdown, how long to keep sending before leaving the rest in the on-disk spool.
    pub drain_timeout: Duration,
    /// Longest time a frame from [`UplinkHandle::submit_deferred`] waits for company before
    /// it is sent.
    pub batch_delay: Duration,
}

/// Most bytes of frames written to the stream in one write.
pub const MAX_BATCH_BYTES: usize = 256 * 1024;

impl UplinkConfig {
    /// Defaults: 200 ms … 5 s backoff, 30 s after an authentication failure, 3 s drain,
    /// deferred frames sent within 100 ms.
    pub fn new(
        server: String,
        server_name: String,
        client_config: quinn::ClientConfig,
        spool: SpoolConfig,
    ) -> Self {
        Self {
            server,
            server_name,
            client_config,
            spool,
            min_backoff: Duration::from_millis(200),
            max_backoff: Duration::from_secs(5),
            auth_backoff: Duration::from_secs(30),
            drain_timeout: Duration::from_secs(3),
            batch_delay: Duration::from_millis(100),
        }
    }
}

/// Counters of the uplink.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct UplinkStats {
    /// Frames accepted by [`UplinkHandle::submit`].
    pub submitted: u64,
    /// Frames refused because the spool was full (the caller paused acquisition).
    pub refused_full: u64,
    /// Frames refused because the spool could not write to disk (the caller paused).
    pub refused_unwritable: u64,
    /// Storage episodes: runs of failed spool writes, from the first failure to the first
    /// success ([`Spool::storage_episodes`]).
    pub storage_episodes: u64,
    /// Frames lost on the edge, which the server will never receive: torn or corrupt spool
    /// records dropped at start-up ([`Recovery::damaged_records`](super::spool::Recovery)) plus
    /// spilled frames that could not be read back ([`Spool::lost_frames`]).
    pub frames_lost_on_edge: u64,
    /// Connections established.
    pub connections: u64,
    /// Connections that failed TLS authentication, on either side (this edge rejecting the
    /// server's certificate, or the server refusing this edge's).
    pub auth_failures: u64,
    /// Of those, the ones where this edge rejected the server's certificate.
    pub server_certificate_rejections: u64,
    /// Frames written to a connection (resends included).
    pub frames_sent: u64,
    /// Acknowledgements received.
    pub acks: u64,
    /// The last connection problem, for status displays.
    pub last_error: Option<String>,
}

/// Why a frame was not taken.
#[derive(Debug, thiserror::Error)]
pub enum SubmitError {
    /// The spool is full: pause acquisition until [`UplinkHandle::has_room`].
    #[error("spool full: the server has not acknowledged enough frames")]
    Full,
    /// The spool cannot write to disk (full or failing): pause acquisition until
    /// [`UplinkHandle::has_room`], which retries the writes with a backoff.
    #[error("spool cannot write to disk: {reason}")]
    Unwritable {
        /// The write error.
        reason: String,
    },
    /// The frame cannot be encoded (over the size limit).
    #[error("cannot encode the frame: {0}")]
    Encode(#[from] scan3d_protocol::EncodeError),
    /// The spool's disk failed.
    #[error("spool: {0}")]
    Spool(SpoolError),
}

struct Inner {
    spool: Mutex<Spool>,
    next_seq: Mutex<u64>,
    /// A frame that must go now.
    wake: Notify,
    /// A deferred frame was submitted while no timer covered deferred frames.
    deferred: Notify,
    /// Deferred frames are covered: the task's flush timer is set (or [`Inner::deferred`] was
    /// notified). Cleared by the task when its timer found nothing to send.
    deferred_covered: AtomicBool,
    session_id: u64,
    clock: SharedClock,
    stats: Mutex<UplinkStats>,
    commands: mpsc::UnboundedSender<ReceivedCommand>,
}

impl Inner {
    fn spool(&self) -> MutexGuard<'_, Spool> {
        self.spool.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Puts the unsent frames, in order, into `batch` (cleared first) until it holds
    /// [`MAX_BATCH_BYTES`] or more; returns how many.
    fn next_batch(&self, batch: &mut Vec<u8>) -> u64 {
        batch.clear();
        let mut spool = self.spool();
        let mut frames = 0;
        while batch.len() < MAX_BATCH_BYTES {
            let Some(frame) = spool.next_unsent() else {
                break;
            };
            batch.extend_from_slice(&frame.bytes);
            frames += 1;
        }
        frames
    }

    fn stats(&self) -> MutexGuard<'_, UplinkStats> {
        self.stats.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The counters, with the spool's own filled in.
    fn snapshot(&self) -> UplinkStats {
        let spool = self.spool();
        let (storage_episodes, frames_lost_on_edge) = (
            spool.storage_episodes(),
            spool.recovery().damaged_records + spool.lost_frames(),
        );
        drop(spool);
        UplinkStats {
            storage_episodes,
            frames_lost_on_edge,
            ..self.stats().clone()
        }
    }
}

/// The producers' side of the uplink; cheap to clone.
#[derive(Clone)]
pub struct UplinkHandle {
    inner: Arc<Inner>,
}

impl UplinkHandle {
    /// Queues a frame for the server and wakes the uplink to send it now; returns its
    /// sequence number.
    pub fn submit(&self, body: impl Into<Body>) -> Result<u64, SubmitError> {
        let seq = self.push(body.into())?;
        self.inner.wake.notify_one();
        Ok(seq)
    }

    /// Queues a frame that may wait up to [`UplinkConfig::batch_delay`] to go out with others
    /// (small frequent frames: IMU readings); returns its sequence number. Durability and
    /// order are those of [`UplinkHandle::submit`]: it is in the spool when this returns.
    pub fn submit_deferred(&self, body: impl Into<Body>) -> Result<u64, SubmitError> {
        let seq = self.push(body.into())?;
        if !self.inner.deferred_covered.swap(true, Ordering::AcqRel) {
            self.inner.deferred.notify_one();
        }
        Ok(seq)
    }

    /// Encodes `body` with the next sequence number into the spool.
    fn push(&self, body: Body) -> Result<u64, SubmitError> {
        let mut next_seq = self
            .inner
            .next_seq
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        let seq = *next_seq;
        let bytes = encode(&Frame::new(self.inner.session_id, seq, body))?;
        match self.inner.spool().push(self.inner.session_id, seq, bytes) {
            Ok(()) => {}
            Err(SpoolError::Full) => {
                self.inner.stats().refused_full += 1;
                return Err(SubmitError::Full);
            }
            Err(SpoolError::Unwritable { reason }) => {
                self.inner.stats().refused_unwritable += 1;
                return Err(SubmitError::Unwritable { reason });
            }
            Err(e) => return Err(SubmitError::Spool(e)),
        }
        *next_seq += 1;
        drop(next_seq);
        self.inner.stats().submitted += 1;
        Ok(seq)
    }

    /// After a [`SubmitError::Full`] or [`SubmitError::Unwritable`]: whether acquisition may
    /// resume (enough acknowledged, and the disk writable again). While the spool's disk fails,
    /// each call retries the pending writes once their backoff has elapsed
    /// ([`Spool::retry_storage`]), so the caller only has to poll.
    pub fn has_room(&self) -> bool {
        let mut spool = self.inner.spool();
        if spool.storage_failing() {
            spool.retry_storage(self.inner.clock.now_ns());
        }
        spool.has_room()
    }

    /// Frames waiting for an acknowledgement.
    pub fn pending(&self) -> usize {
        self.inner.spool().len()
    }

    /// This boot's session id.
    pub fn session_id(&self) -> u64 {
        self.inner.session_id
    }

    /// Hands out every frame not yet sent, as the connection task would (tests).
    #[cfg(test)]
    pub(crate) fn drain_unsent(&self) -> Vec<super::spool::SpooledFrame> {
        let mut spool = self.inner.spool();
        std::iter::from_fn(|| spool.next_unsent()).collect()
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> UplinkStats {
        self.inner.snapshot()
    }
}

/// The connection task; see the module docs.
pub struct Uplink {
    inner: Arc<Inner>,
    config: UplinkConfig,
}

/// How one connection attempt ended.
enum SessionEnd {
    Shutdown,
    Failed(ConnectFailure),
}

impl SessionEnd {
    fn lost(reason: String) -> Self {
        SessionEnd::Failed(ConnectFailure::Other(reason))
    }
}

/// Why a connection failed, by who refused it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConnectFailure {
    /// This edge's TLS stack rejected the server's certificate: signed by another CA than the
    /// bundle's `ca.pem`, not valid for `server_name`, expired, revoked…
    ServerCertificateRejected {
        /// rustls' reason, e.g. `invalid peer certificate: UnknownIssuer`.
        reason: String,
    },
    /// The server closed the connection with a TLS alert: it does not accept this edge's
    /// certificate (another pairing, revoked, expired).
    RefusedByServer {
        /// The alert's name, e.g. `UnknownCA`, `BadCertificate`, `CertificateRequired`.
        alert: String,
        /// The server's close reason, if it gave one.
        reason: String,
    },
    /// Anything else: network, timeouts, the server closing for another reason.
    Other(String),
}

impl std::fmt::Display for ConnectFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConnectFailure::ServerCertificateRejected { reason } => {
                write!(f, "this edge rejected the server's certificate: {reason}")
            }
            ConnectFailure::RefusedByServer { alert, reason } if reason.is_empty() => {
                write!(
                    f,
                    "the server refused this edge's certificate (TLS alert {alert})"
                )
            }
            ConnectFailure::RefusedByServer { alert, reason } => write!(
                f,
                "the server refused this edge's certificate (TLS alert {alert}: {reason})"
            ),
            ConnectFailure::Other(reason) => f.write_str(reason),
        }
    }
}

/// Classifies a quinn connection error by who refused: a crypto error (QUIC codes
/// 0x100–0x1ff, a TLS alert) raised by this side's TLS stack is a rejected server
/// certificate; one received in the server's CONNECTION_CLOSE is the server refusing this
/// edge (TLS 1.3 reports it only after the client thinks the handshake is done).
pub fn classify(error: &quinn::ConnectionError) -> ConnectFailure {
    let alert = |code: quinn::TransportErrorCode| {
        let code = u64::from(code);
        (0x100..=0x1ff)
            .contains(&code)
            .then(|| rustls::AlertDescription::from((code - 0x100) as u8))
    };
    match error {
        quinn::ConnectionError::TransportError(e) if alert(e.code).is_some() => {
            ConnectFailure::ServerCertificateRejected {
                reason: e.reason.clone(),
            }
        }
        quinn::ConnectionError::ConnectionClosed(close) => match alert(close.error_code) {
            Some(alert) => ConnectFailure::RefusedByServer {
                alert: format!("{alert:?}"),
                reason: String::from_utf8_lossy(&close.reason).into_owned(),
            },
            None => ConnectFailure::Other(error.to_string()),
        },
        other => ConnectFailure::Other(other.to_string()),
    }
}

/// A command from the server with the `seq` of the frame that carried it, which the edge's
/// [`scan3d_protocol::CommandReply`] names.
#[derive(Debug, Clone, PartialEq)]
pub struct ReceivedCommand {
    /// The server frame's sequence number.
    pub seq: u64,
    /// The command.
    pub command: Command,
}

impl Uplink {
    /// Opens the spool (recovering frames a previous run left on disk) and picks this boot's
    /// session id. Commands from the server arrive on the returned receiver.
    pub fn new(
        config: UplinkConfig,
        clock: SharedClock,
        session_id: u64,
    ) -> Result<(Self, UplinkHandle, mpsc::UnboundedReceiver<ReceivedCommand>), SpoolError> {
        let spool = Spool::open(config.spool.clone())?;
        let recovery = spool.recovery();
        if recovery.damaged_records > 0 {
            // Each damaged run was logged with its segment and offset; the frames around it
            // are resent and released by the server's range acknowledgements.
            tracing::error!(
                damaged_records = recovery.damaged_records,
                damaged_bytes = recovery.damaged_bytes,
                recovered = recovery.frames,
                "frames lost on the edge: the spool held torn or corrupt records"
            );
        }
        let (commands, commands_rx) = mpsc::unbounded_channel();
        let inner = Arc::new(Inner {
            spool: Mutex::new(spool),
            next_seq: Mutex::new(0),
            wake: Notify::new(),
            deferred: Notify::new(),
            deferred_covered: AtomicBool::new(false),
            session_id,
            clock,
            stats: Mutex::new(UplinkStats::default()),
            commands,
        });
        let handle = UplinkHandle {
            inner: inner.clone(),
        };
        Ok((Self { inner, config }, handle, commands_rx))
    }

    /// Connects, sends and reconnects until `shutdown` turns true; then sends for at most
    /// `drain_timeout` more and leaves the rest in the on-disk spool for the next start.
    pub async fn run(self, mut shutdown: watch::Receiver<bool>) -> UplinkStats {
        let endpoint = match quinn::Endpoint::client(SocketAddr::from(([0, 0, 0, 0], 0))) {
            Ok(mut endpoint) => {
                endpoint.set_default_client_config(self.config.client_config.clone());
                Some(endpoint)
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot open a UDP socket; frames stay spooled");
                None
            }
        };
        let mut backoff = self.config.min_backoff;
        while let Some(endpoint) = &endpoint {
            if *shutdown.borrow() {
                break;
            }
            let started = Instant::now();
            let end = match self.resolve().await {
                Ok(addr) => self.session(endpoint, addr, &mut shutdown).await,
                Err(reason) => SessionEnd::lost(reason),
            };
            let wait = match end {
                SessionEnd::Shutdown => break,
                SessionEnd::Failed(failure @ ConnectFailure::ServerCertificateRejected { .. }) => {
                    tracing::error!(server = %self.config.server, server_name = %self.config.server_name, %failure,
                        "this edge refused the server: check that pki_dir's ca.pem is the CA of this server's pairing and that server_name is one of the names given to `scan3d pair --server-name`");
                    let mut stats = self.inner.stats();
                    stats.auth_failures += 1;
                    stats.server_certificate_rejections += 1;
                    stats.last_error = Some(failure.to_string());
                    self.config.auth_backoff
                }
                SessionEnd::Failed(failure @ ConnectFailure::RefusedByServer { .. }) => {
                    tracing::error!(server = %self.config.server, %failure,
                        "the server refused this edge: check that pki_dir holds the bundle `scan3d pair` made for this edge on this server");
                    let mut stats = self.inner.stats();
                    stats.auth_failures += 1;
                    stats.last_error = Some(failure.to_string());
                    self.config.auth_backoff
                }
                SessionEnd::Failed(ConnectFailure::Other(reason)) => {
                    tracing::warn!(server = %self.config.server, %reason, "uplink down; retrying");
                    self.inner.stats().last_error = Some(reason);
                    if started.elapsed() > Duration::from_secs(10) {
                        backoff = self.config.min_backoff;
                    }
                    let wait = backoff;
                    backoff = (backoff * 2).min(self.config.max_backoff);
                    wait
                }
            };
            tokio::select! {
                () = tokio::time::sleep(wait) => {}
                _ = shutdown.changed() => {}
            }
        }
        if let Some(endpoint) = endpoint {
            endpoint.close(0u32.into(), b"edge shutting down");
            endpoint.wait_idle().await;
        }
        let mut spool = self.inner.spool();
        if let Err(e) = spool.shutdown_flush() {
            tracing::error!(error = %e, "could not write the spool to disk");
        }
        let left = spool.len();
        drop(spool);
        if left > 0 {
            tracing::info!(
                frames = left,
                "unacknowledged frames kept on disk for the next start"
            );
        }
        self.inner.snapshot()
    }

    async fn resolve(&self) -> Result<SocketAddr, String> {
        let mut addrs = tokio::net::lookup_host(&self.config.server)
            .await
            .map_err(|e| format!("cannot resolve {}: {e}", self.config.server))?;
        addrs
            .next()
            .ok_or_else(|| format!("{} resolves to no address", self.config.server))
    }

    async fn session(
        &self,
        endpoint: &quinn::Endpoint,
        addr: SocketAddr,
        shutdown: &mut watch::Receiver<bool>,
    ) -> SessionEnd {
        let connecting = match endpoint.connect(addr, &self.config.server_name) {
            Ok(connecting) => connecting,
            Err(e) => return SessionEnd::lost(format!("cannot connect to {addr}: {e}")),
        };
        let connection = tokio::select! {
            result = connecting => match result {
                Ok(connection) => connection,
                Err(e) => return SessionEnd::Failed(match classify(&e) {
                    ConnectFailure::Other(_) => ConnectFailure::Other(format!("cannot connect to {addr}: {e}")),
                    failure => failure,
                }),
            },
            _ = shutdown.changed() => return SessionEnd::Shutdown,
        };
        let (mut send, recv) = match connection.open_bi().await {
            Ok(streams) => streams,
            Err(e) => {
                return SessionEnd::Failed(match classify(&e) {
                    ConnectFailure::Other(_) => {
                        ConnectFailure::Other(format!("cannot open a stream: {e}"))
                    }
                    failure => failure,
                });
            }
        };
        tracing::info!(server = %addr, session = format!("{:016x}", self.inner.session_id), "uplink connected");
        self.inner.stats().connections += 1;
        self.inner.spool().rewind();
        let reader = tokio::spawn(read_from_server(recv, self.inner.clone()));
        let pongs = tokio::spawn(answer_pings(connection.clone(), self.inner.clone()));
        let mut drain_until: Option<tokio::time::Instant> = None;
        let mut batch: Vec<u8> = Vec::new();
        // When the deferred frames submitted since the last write go out at the latest.
        let mut flush_at: Option<tokio::time::Instant> = None;
        // No timer yet: the first deferred frame wakes the task.
        self.inner.deferred_covered.store(false, Ordering::Release);
        let end = loop {
            // Send everything not yet sent on this connection, in order, in one write.
            let frames = self.inner.next_batch(&mut batch);
            if frames > 0 {
                // A write blocked by flow or congestion control must not hold shutdown past the
                // drain deadline. The write is never cancelled half way (the stream would carry
                // a torn frame) except by closing the connection: the frames stay spooled.
                let mut write = std::pin::pin!(send.write_all(&batch));
                let outcome = loop {
                    tokio::select! {
                        written = &mut write => break WriteOutcome::Written(written),
                        _ = connection.closed() => break WriteOutcome::ConnectionClosed,
                        _ = shutdown.changed(), if drain_until.is_none() => {
                            drain_until = Some(tokio::time::Instant::now() + self.config.drain_timeout);
                        }
                        () = sleep_until_deadline(drain_until) => break WriteOutcome::DrainTimedOut,
                    }
                };
                match outcome {
                    WriteOutcome::Written(Ok(())) => {
                        self.inner.stats().frames_sent += frames;
                        // Deferred frames from now on ride with the next write, at the latest
                        // at this timer.
                        flush_at = Some(tokio::time::Instant::now() + self.config.batch_delay);
                        self.inner.deferred_covered.store(true, Ordering::Release);
                    }
                    WriteOutcome::Written(Err(e)) => {
                        break lost_or_refused(&connection, format!("write failed: {e}"));
                    }
                    WriteOutcome::ConnectionClosed => {
                        break lost_or_refused(&connection, "connection closed".into());
                    }
                    WriteOutcome::DrainTimedOut => {
                        tracing::info!(
                            "drain timeout with a write still blocked; the spooled frames are sent after the next start"
                        );
                        connection.close(0u32.into(), b"edge shutting down");
                        break SessionEnd::Shutdown;
                    }
                }
                continue;
            }
            if let Some(deadline) = drain_until
                && (self.inner.spool().is_empty() || tokio::time::Instant::now() >= deadline)
            {
                connection.close(0u32.into(), b"edge shutting down");
                break SessionEnd::Shutdown;
            }
            let wait_drain = async {
                match drain_until {
                    Some(deadline) => {
                        tokio::time::sleep_until(
                            deadline.min(tokio::time::Instant::now() + Duration::from_millis(50)),
                        )
                        .await
                    }
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                () = self.inner.wake.notified() => {}
                () = self.inner.deferred.notified() => {
                    // The first deferred frame after a quiet spell: it waits for company.
                    flush_at.get_or_insert(tokio::time::Instant::now() + self.config.batch_delay);
                }
                () = sleep_until_deadline(flush_at) => {
                    // The top of the loop sends what came. Were nothing to come, the timer
                    // stops and the next deferred frame wakes the task: the flag is cleared
                    // before that read, so a frame submitted after it notifies.
                    flush_at = None;
                    self.inner.deferred_covered.store(false, Ordering::Release);
                }
                () = wait_drain => {}
                _ = shutdown.changed(), if drain_until.is_none() => {
                    drain_until = Some(tokio::time::Instant::now() + self.config.drain_timeout);
                }
                _ = connection.closed() => break lost_or_refused(&connection, "connection closed".into()),
            }
        };
        reader.abort();
        pongs.abort();
        end
    }
}

/// How a frame's write on the connection ended.
enum WriteOutcome {
    /// The stream took it (or failed).
    Written(Result<(), quinn::WriteError>),
    /// The connection closed while the write was blocked.
    ConnectionClosed,
    /// Shutting down, and the drain deadline passed while the write was blocked.
    DrainTimedOut,
}

/// Waits until `deadline`, or for ever without one.
async fn sleep_until_deadline(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline).await,
        None => std::future::pending().await,
    }
}

/// Answers the server's time-sync ping datagrams until the connection ends.
async fn answer_pings(connection: quinn::Connection, inner: Arc<Inner>) {
    while let Ok(datagram) = connection.read_datagram().await {
        let received_ns = inner.clock.now_ns();
        let pong = super::timesync::answer_ping(
            &datagram,
            received_ns,
            inner.session_id,
            inner.clock.as_ref(),
        );
        match pong.map(|pong| connection.send_datagram(pong.into())) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::debug!(error = %e, "time-sync pong not sent"),
            Err(e) => tracing::debug!(error = %e, "ignoring a datagram from the server"),
        }
    }
}

/// Reads acks and commands from the server until the stream ends.
async fn read_from_server(mut recv: quinn::RecvStream, inner: Arc<Inner>) {
    let mut reader = FrameReader::new();
    loop {
        let chunk = match recv.read_chunk(64 * 1024, true).await {
            Ok(Some(chunk)) => chunk,
            Ok(None) | Err(_) => return,
        };
        reader.push(&chunk.bytes);
        loop {
            let frame = match reader.next_frame() {
                Ok(Some(frame)) => frame,
                Ok(None) => break,
                Err(e) if e.is_fatal() => {
                    tracing::warn!(error = %e, "the server sent something that is not scan3d frames");
                    return;
                }
                Err(e) => {
                    tracing::warn!(error = %e, "skipping a malformed frame from the server");
                    continue;
                }
            };
            match frame.body {
                Body::Ack(Ack::UpTo { seq }) => {
                    inner.spool().ack(frame.session_id, seq);
                    inner.stats().acks += 1;
                }
                Body::Ack(Ack::Range { first, last }) => {
                    inner.spool().ack_range(frame.session_id, first, last);
                    inner.stats().acks += 1;
                }
                // Pings belong in datagrams: one on the stream went through a queue, so its
                // timestamps say nothing about the path.
                Body::TimePing(_) => {
                    tracing::debug!("ignoring a time-sync ping on the stream");
                }
                Body::Command(command) => {
                    tracing::info!(?command, seq = frame.seq, "command from the server");
                    let _ = inner.commands.send(ReceivedCommand {
                        seq: frame.seq,
                        command,
                    });
                }
                other => tracing::debug!(?other, "ignoring an unexpected frame from the server"),
            }
        }
    }
}

/// Classifies the end of a connection that was up.
fn lost_or_refused(connection: &quinn::Connection, fallback: String) -> SessionEnd {
    match connection.close_reason() {
        Some(e) => SessionEnd::Failed(classify(&e)),
        None => SessionEnd::lost(fallback),
    }
}

/// A quinn client configuration that is never used to connect (tests of the spool side).
#[cfg(test)]
pub(crate) fn unused_client_config() -> quinn::ClientConfig {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .expect("TLS 1.3")
        .with_root_certificates(rustls::RootCertStore::empty())
        .with_no_client_auth();
    quinn::ClientConfig::new(Arc::new(
        quinn::crypto::rustls::QuicClientConfig::try_from(tls).expect("a QUIC TLS config"),
    ))
}

#[cfg(test)]
mod tests {
    use scan3d_protocol::{Heartbeat, decode};

    use super::*;
    use crate::clock::MonotonicClock;

    fn uplink(dir: &std::path::Path) -> (Uplink, UplinkHandle) {
        let config = UplinkConfig::new(
            "localhost:1".into(),
            "localhost".into(),
            unused_client_config(),
            SpoolConfig::new(dir),
        );
        let (uplink, handle, _commands) =
            Uplink::new(config, Arc::new(MonotonicClock::new()), 7).unwrap();
        (uplink, handle)
    }

    fn seqs_of(batch: &[u8]) -> Vec<u64> {
        let mut rest = batch;
        let mut seqs = Vec::new();
        while !rest.is_empty() {
            let (frame, used): (Frame, usize) = decode(rest).unwrap();
            seqs.push(frame.seq);
            rest = &rest[used..];
        }
        seqs
    }

    #[test]
    fn deferred_and_immediate_frames_go_out_in_one_write_in_submission_order() {
        let dir = tempfile::tempdir().unwrap();
        let (uplink, handle) = uplink(dir.path());
        let beat = |n| Body::from(Heartbeat { sent_ns: n });
        assert_eq!(handle.submit_deferred(beat(0)).unwrap(), 0);
        assert!(
            uplink.inner.deferred_covered.load(Ordering::Acquire),
            "the first deferred frame asks for a flush"
        );
        assert_eq!(handle.submit_deferred(beat(1)).unwrap(), 1);
        assert_eq!(handle.submit(beat(2)).unwrap(), 2);
        assert_eq!(handle.submit_deferred(beat(3)).unwrap(), 3);
        let mut batch = Vec::new();
        assert_eq!(uplink.inner.next_batch(&mut batch), 4);
        assert_eq!(seqs_of(&batch), [0, 1, 2, 3]);
        // Sent, not acknowledged: still spooled, and nothing more to send.
        assert_eq!(handle.pending(), 4);
        assert_eq!(uplink.inner.next_batch(&mut batch), 0);
        assert!(batch.is_empty());
    }

    #[test]
    fn a_batch_stops_once_it_holds_the_most_bytes_of_one_write() {
        let dir = tempfile::tempdir().unwrap();
        let (uplink, handle) = uplink(dir.path());
        // Status frames of about 40 kB each: a batch takes frames until it holds 256 KiB.
        let big = |n: u64| {
            Body::from(scan3d_protocol::DeviceStatus {
                t_ns: n,
                sensor: scan3d_protocol::SensorId::IMU,
                event: scan3d_protocol::StatusEvent::SensorLost,
                reason: "x".repeat(40_000),
            })
        };
        for n in 0..10 {
            handle.submit_deferred(big(n)).unwrap();
        }
        let mut batch = Vec::new();
        let first = uplink.inner.next_batch(&mut batch);
        assert!(batch.len() >= MAX_BATCH_BYTES, "{} bytes", batch.len());
        assert!(
            batch.len() < MAX_BATCH_BYTES + 41_000,
            "{} bytes",
            batch.len()
        );
        let first_seqs = seqs_of(&batch);
        assert_eq!(first_seqs.len() as u64, first);
        let second = uplink.inner.next_batch(&mut batch);
        assert_eq!(first + second, 10);
        let mut all = first_seqs;
        all.extend(seqs_of(&batch));
        assert_eq!(all, (0..10).collect::<Vec<u64>>());
    }
}
