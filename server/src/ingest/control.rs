//! Operator control of connected edges: [`EdgeControl`] routes a [`Command`] to an edge's live
//! connection, and a local Unix socket lets `scan3d scan` (another process on the laptop) use it.
//!
//! The socket protocol is one JSON line each way, so it can be driven by hand with `socat`:
//!
//! ```text
//! → {"edge":"pi","command":{"StartStaticScan":{"position":"door","x_m":1.0,"y_m":2.0,"heading_deg":null}}}
//! ← {"ok":true,"detail":"sent to pi"}
//! ```
//!
//! The same socket answers requests for the live products ([`ProductRequest`], answered by the
//! pipeline's live driver through [`LiveProducts`]): `scan3d status` and `scan3d snapshot`.
//!
//! ```text
//! → {"request":"status"}
//! ← {"ok":true,"detail":"1 edge(s)","data":{"edges":[...]}}
//! → {"request":"snapshot","edge":"pi","out":"/tmp/snap"}
//! ← {"ok":true,"detail":"wrote ...","data":{...}}
//! ```
//!
//! The socket lives at `data_dir/control.sock` (see [`socket_path`]), so only users who can
//! write the recordings can command the edges.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use scan3d_protocol::{Command, InvalidCommand};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::mpsc;

/// The control socket of a server whose recordings live in `data_dir`.
pub fn socket_path(data_dir: &Path) -> PathBuf {
    data_dir.join("control.sock")
}

/// Why a command could not be routed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ControlError {
    /// No live connection of that edge.
    #[error("edge {edge:?} is not connected (connected: {connected})")]
    NotConnected {
        /// The edge asked for.
        edge: String,
        /// The edges that are, comma-separated (or "none").
        connected: String,
    },
    /// The command is not one an edge can be sent ([`Command::validate`]).
    #[error("invalid command: {0}")]
    Invalid(#[from] InvalidCommand),
}

/// Routes commands to the edges connected to an ingest server; cheap to clone.
#[derive(Debug, Clone, Default)]
pub struct EdgeControl {
    edges: Arc<Mutex<HashMap<String, mpsc::UnboundedSender<Command>>>>,
}

impl EdgeControl {
    /// Registers an edge's connection; its task receives the commands. A newer connection of
    /// the same edge replaces the older one.
    pub(crate) fn register(&self, edge: &str) -> mpsc::UnboundedReceiver<Command> {
        let (tx, rx) = mpsc::unbounded_channel();
        self.lock().insert(edge.to_owned(), tx);
        rx
    }

    /// Forgets an edge whose connection ended (unless a newer one already replaced it).
    pub(crate) fn unregister(&self, edge: &str) {
        let mut edges = self.lock();
        if edges
            .get(edge)
            .is_some_and(mpsc::UnboundedSender::is_closed)
        {
            edges.remove(edge);
        }
    }

    /// The connected edges, sorted.
    pub fn connected(&self) -> Vec<String> {
        let mut names: Vec<String> = self
            .lock()
            .iter()
            .filter(|(_, tx)| !tx.is_closed())
            .map(|(name, _)| name.clone())
            .collect();
        names.sort();
        names
    }

    /// Queues `command` on `edge`'s connection (sent with the next outgoing frames). The
    /// command is validated first ([`Command::validate`]): this is the only way commands reach
    /// a connection, so a connection never holds one it cannot encode.
    pub fn send(&self, edge: &str, command: Command) -> Result<(), ControlError> {
        command.validate()?;
        let sent = self
            .lock()
            .get(edge)
            .is_some_and(|tx| tx.send(command).is_ok());
        if sent {
            Ok(())
        } else {
            let connected = self.connected();
            Err(ControlError::NotConnected {
                edge: edge.to_owned(),
                connected: if connected.is_empty() {
                    "none".into()
                } else {
                    connected.join(", ")
                },
            })
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, mpsc::UnboundedSender<Command>>> {
        self.edges.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// One request on the control socket.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ControlRequest {
    /// The edge's name (its certificate's).
    pub edge: String,
    /// What to tell it.
    pub command: Command,
}

/// A request for the live products (the pipeline's), told apart from a [`ControlRequest`] by
/// its `"request"` key.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "request", rename_all = "snake_case", deny_unknown_fields)]
pub enum ProductRequest {
    /// Every edge and session: frames, samples, voxels, lag, time sync, metrics.
    Status,
    /// Write a session's octree (`.bt`, `.ot`), cloud (PLY) and metric table into `out`.
    Snapshot {
        /// The edge's name.
        edge: String,
        /// The session id (16 hex digits); default: the edge's latest session.
        #[serde(default)]
        session: Option<String>,
        /// Only this static-scan position's products.
        #[serde(default)]
        position: Option<String>,
        /// The directory to write into (absolute: the daemon's working directory is not the
        /// client's).
        out: PathBuf,
    },
}

/// What answers [`ProductRequest`]s: the pipeline's live driver. Answers may take a while (a
/// snapshot waits for its session to catch up and writes files): they run on a blocking
/// thread, never on the socket's task.
pub trait LiveProducts: Send + Sync {
    /// The reply to one request.
    fn answer(&self, request: &ProductRequest) -> ControlReply;
}

/// The answer to a [`ControlRequest`] or a [`ProductRequest`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ControlReply {
    /// Whether the command was queued on the edge's connection (the request answered).
    pub ok: bool,
    /// What happened, for a human.
    pub detail: String,
    /// What a [`ProductRequest`] asked for (the status, the files a snapshot wrote).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data: Option<serde_json::Value>,
}

impl ControlReply {
    fn failed(detail: String) -> Self {
        ControlReply {
            ok: false,
            detail,
            data: None,
        }
    }
}

/// A parsed request line.
enum Request {
    Command(ControlRequest),
    Products(ProductRequest),
}

fn parse_request(line: &str) -> Result<Request, String> {
    let value: serde_json::Value =
        serde_json::from_str(line).map_err(|e| format!("malformed request: {e}"))?;
    if value.get("request").is_some() {
        serde_json::from_value(value)
            .map(Request::Products)
            .map_err(|e| format!("malformed request: {e}"))
    } else {
        serde_json::from_value(value)
            .map(Request::Command)
            .map_err(|e| format!("malformed request: {e}"))
    }
}

fn send_command(control: &EdgeControl, request: ControlRequest) -> ControlReply {
    match control.send(&request.edge, request.command) {
        Ok(()) => ControlReply {
            ok: true,
            detail: format!("sent to {}", request.edge),
            data: None,
        },
        Err(e) => ControlReply::failed(e.to_string()),
    }
}

/// The reply to one request line, without live products (a [`ProductRequest`] is refused).
pub fn handle_request(control: &EdgeControl, line: &str) -> ControlReply {
    match parse_request(line) {
        Ok(Request::Command(request)) => send_command(control, request),
        Ok(Request::Products(_)) => ControlReply::failed(NO_PIPELINE.into()),
        Err(detail) => ControlReply::failed(detail),
    }
}

const NO_PIPELINE: &str = "the server runs without the live pipeline ([pipeline] enabled = false)";

/// The reply to one request line; product requests go to `live` on a blocking thread.
async fn handle_line(
    control: &EdgeControl,
    live: Option<&Arc<dyn LiveProducts>>,
    line: &str,
) -> ControlReply {
    match parse_request(line) {
        Ok(Request::Command(request)) => send_command(control, request),
        Ok(Request::Products(request)) => match live {
            None => ControlReply::failed(NO_PIPELINE.into()),
            Some(live) => {
                let live = live.clone();
                tokio::task::spawn_blocking(move || live.answer(&request))
                    .await
                    .unwrap_or_else(|e| ControlReply::failed(format!("request failed: {e}")))
            }
        },
        Err(detail) => ControlReply::failed(detail),
    }
}

/// Longest control socket path: `sun_path` holds 108 bytes on Linux, one of them the
/// terminating NUL.
pub const MAX_SOCKET_PATH_LEN: usize = 107;

/// Permissions of the control socket: owner only. Connecting needs write permission, so this
/// and the peer check ([`ControlSocket`]) both say "the server's own user (or root)".
pub const SOCKET_MODE: u32 = 0o600;

/// Bounds on what the control socket accepts, so a local client cannot make it hold memory,
/// tasks or file descriptors for ever.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControlLimits {
    /// Longest request line, newline excluded; a longer one is answered with an error and the
    /// connection closed.
    pub max_line_len: usize,
    /// Connections served at once; a further one is answered with an error and closed.
    pub max_connections: usize,
    /// A connection that sends no complete request (or does not take its reply) for this long
    /// is closed.
    pub idle_timeout: Duration,
    /// First pause after a failed `accept` (e.g. EMFILE); doubled on each further failure.
    pub accept_backoff_min: Duration,
    /// Longest pause after a failed `accept`.
    pub accept_backoff_max: Duration,
}

impl Default for ControlLimits {
    /// 64 KiB lines (a request is a few hundred bytes), 16 connections, 30 s idle, accept
    /// retries after 10 ms up to 1 s.
    fn default() -> Self {
        ControlLimits {
            max_line_len: 64 * 1024,
            max_connections: 16,
            idle_timeout: Duration::from_secs(30),
            accept_backoff_min: Duration::from_millis(10),
            accept_backoff_max: Duration::from_secs(1),
        }
    }
}

/// Why the control socket could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum SocketError {
    /// The path does not fit in `sun_path`.
    #[error(
        "control socket path {} is {len} bytes, longer than the {max} bytes a Unix socket path may have; choose a shorter data_dir",
        path.display()
    )]
    PathTooLong {
        /// The socket path.
        path: PathBuf,
        /// Its length in bytes.
        len: usize,
        /// [`MAX_SOCKET_PATH_LEN`].
        max: usize,
    },
    /// Another server already listens on the path.
    #[error("control socket {}: another server is already listening on it", path.display())]
    InUse {
        /// The socket path.
        path: PathBuf,
    },
    /// Removing a stale socket, binding or setting the mode failed.
    #[error("control socket {}: {source}", path.display())]
    Io {
        /// The socket path.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

/// The bound control socket; [`ControlSocket::serve`] answers its connections.
///
/// Who may connect: the socket file is [`SOCKET_MODE`] (set explicitly, whatever the umask),
/// and every connection's peer credentials (`SO_PEERCRED`) must be the server's own effective
/// uid or root; anyone else is answered with an error and disconnected.
#[derive(Debug)]
pub struct ControlSocket {
    listener: UnixListener,
    path: PathBuf,
    limits: ControlLimits,
    live: Option<Arc<dyn LiveProducts>>,
}

impl std::fmt::Debug for dyn LiveProducts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LiveProducts")
    }
}

impl ControlSocket {
    /// Binds the socket at `path`, replacing a stale socket file left by a crashed server
    /// (but never one a live server answers on).
    pub async fn bind(path: PathBuf, limits: ControlLimits) -> Result<Self, SocketError> {
        use std::os::unix::fs::PermissionsExt;
        let len = path.as_os_str().len();
        if len > MAX_SOCKET_PATH_LEN {
            return Err(SocketError::PathTooLong {
                path,
                len,
                max: MAX_SOCKET_PATH_LEN,
            });
        }
        let io_err = |path: &Path| {
            let path = path.to_path_buf();
            move |source| SocketError::Io { path, source }
        };
        if std::fs::symlink_metadata(&path).is_ok() {
            if UnixStream::connect(&path).await.is_ok() {
                return Err(SocketError::InUse { path });
            }
            std::fs::remove_file(&path).map_err(io_err(&path))?;
        }
        let listener = UnixListener::bind(&path).map_err(io_err(&path))?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(SOCKET_MODE))
            .map_err(io_err(&path))?;
        tracing::info!(socket = %path.display(), "control socket ready");
        Ok(ControlSocket {
            listener,
            path,
            limits,
            live: None,
        })
    }

    /// Also answers [`ProductRequest`]s, with `live`.
    pub fn with_live(mut self, live: Arc<dyn LiveProducts>) -> Self {
        self.live = Some(live);
        self
    }

    /// The socket's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Answers connections for as long as the task runs. A failed `accept` (EMFILE, ENOMEM,
    /// ...) is logged and retried after a growing pause, so the socket neither dies nor spins.
    pub async fn serve(self, control: EdgeControl) -> std::convert::Infallible {
        let listener = &self.listener;
        let accept = move || -> AcceptFuture<'_> {
            Box::pin(async move { listener.accept().await.map(|(stream, _)| stream) })
        };
        accept_loop(accept, &self.path, self.limits, control, self.live.clone()).await
    }
}

type AcceptFuture<'a> =
    std::pin::Pin<Box<dyn std::future::Future<Output = std::io::Result<UnixStream>> + Send + 'a>>;

/// Why a peer may not use the control socket, if it may not: only the server's own effective
/// uid and root are allowed.
fn peer_refusal(peer_uid: Option<u32>, own_uid: u32) -> Option<String> {
    match peer_uid {
        Some(uid) if uid == own_uid || uid == 0 => None,
        Some(uid) => Some(format!(
            "permission denied: uid {uid} is not the server's (uid {own_uid}) or root"
        )),
        None => Some("permission denied: no peer credentials".to_owned()),
    }
}

/// The accept loop of [`ControlSocket::serve`], with `accept` standing for the listener.
async fn accept_loop<'a>(
    mut accept: impl FnMut() -> AcceptFuture<'a>,
    path: &Path,
    limits: ControlLimits,
    control: EdgeControl,
    live: Option<Arc<dyn LiveProducts>>,
) -> std::convert::Infallible {
    let slots = Arc::new(tokio::sync::Semaphore::new(limits.max_connections));
    let own_uid = nix::unistd::geteuid().as_raw();
    let mut backoff = limits.accept_backoff_min;
    loop {
        let stream = match accept().await {
            Ok(stream) => {
                backoff = limits.accept_backoff_min;
                stream
            }
            Err(e) => {
                tracing::warn!(
                    socket = %path.display(),
                    error = %e,
                    retry_in_ms = backoff.as_millis(),
                    "control socket cannot accept; retrying"
                );
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(limits.accept_backoff_max);
                continue;
            }
        };
        let peer_uid = stream.peer_cred().ok().map(|cred| cred.uid());
        let refusal = peer_refusal(peer_uid, own_uid);
        let permit = match (refusal, slots.clone().try_acquire_owned()) {
            (None, Ok(permit)) => permit,
            (refusal, _) => {
                let detail = refusal.unwrap_or_else(|| {
                    format!(
                        "too many control connections (at most {} at once)",
                        limits.max_connections
                    )
                });
                tracing::warn!(%detail, "control connection refused");
                // Best effort and never blocking: a refusal costs one write at most.
                let _ = stream.try_write(reply_line(&ControlReply::failed(detail)).as_bytes());
                continue;
            }
        };
        let control = control.clone();
        let live = live.clone();
        tokio::spawn(async move {
            let _permit = permit;
            if let Err(e) = answer(stream, &control, live.as_ref(), &limits).await {
                tracing::warn!(error = %e, "control connection failed");
            }
        });
    }
}

/// Binds the control socket at `path` with the default [`ControlLimits`] and serves it for as
/// long as the task runs; returns only if the socket cannot be opened. Callers that must fail
/// at start on a bad path use [`ControlSocket::bind`] and [`ControlSocket::serve`] instead.
pub async fn serve_socket(path: PathBuf, control: EdgeControl) -> std::io::Result<()> {
    let socket = ControlSocket::bind(path, ControlLimits::default())
        .await
        .map_err(std::io::Error::other)?;
    match socket.serve(control).await {}
}

fn reply_line(reply: &ControlReply) -> String {
    // A struct of a bool and a string always serialises.
    let mut text = serde_json::to_string(reply).unwrap_or_default();
    text.push('\n');
    text
}

async fn answer(
    stream: UnixStream,
    control: &EdgeControl,
    live: Option<&Arc<dyn LiveProducts>>,
    limits: &ControlLimits,
) -> std::io::Result<()> {
    use tokio::io::AsyncReadExt;
    let timed_out = || {
        std::io::Error::new(
            std::io::ErrorKind::TimedOut,
            "idle control connection closed",
        )
    };
    let (read, mut write) = stream.into_split();
    let mut reader = BufReader::new(read);
    let mut line = Vec::new();
    loop {
        line.clear();
        let limit = u64::try_from(limits.max_line_len)
            .unwrap_or(u64::MAX)
            .saturating_add(1);
        let mut limited = (&mut reader).take(limit);
        let read = limited.read_until(b'\n', &mut line);
        let n = tokio::time::timeout(limits.idle_timeout, read)
            .await
            .map_err(|_| timed_out())??;
        if n == 0 {
            return Ok(());
        }
        let complete = line.last() == Some(&b'\n');
        if complete {
            line.pop();
        }
        let (reply, close) = if line.len() > limits.max_line_len {
            let detail = format!(
                "request line longer than {} bytes; closing the connection",
                limits.max_line_len
            );
            (ControlReply::failed(detail), true)
        } else {
            let reply = match std::str::from_utf8(&line) {
                Ok(text) => handle_line(control, live, text).await,
                Err(e) => ControlReply::failed(format!("malformed request: not UTF-8 ({e})")),
            };
            // A last line without newline is answered, then the peer's end of stream closes.
            (reply, false)
        };
        tracing::info!(ok = reply.ok, detail = %reply.detail, "control request");
        let text = reply_line(&reply);
        let write_reply = write.write_all(text.as_bytes());
        tokio::time::timeout(limits.idle_timeout, write_reply)
            .await
            .map_err(|_| timed_out())??;
        if close {
            return Ok(());
        }
    }
}

/// Sends one request to the server's control socket and waits for the reply (blocking; for
/// the CLI).
pub fn request(path: &Path, request: &ControlRequest) -> anyhow::Result<ControlReply> {
    request_with(path, request, std::time::Duration::from_secs(10))
}

/// Sends one [`ProductRequest`] and waits for the reply (blocking): up to a minute, as a
/// snapshot waits for its session to catch up and writes files.
pub fn request_products(path: &Path, request: &ProductRequest) -> anyhow::Result<ControlReply> {
    request_with(path, request, std::time::Duration::from_secs(60))
}

/// Asks the daemon listening on `socket` for a snapshot (what `scan3d snapshot` does, for the
/// simulator and tests); a refusal is an error with the daemon's reason. `out` is made absolute against this process's working
/// directory first.
pub fn request_snapshot(
    socket: &Path,
    edge: &str,
    session: Option<&str>,
    position: Option<&str>,
    out: &Path,
) -> anyhow::Result<ControlReply> {
    let out = std::path::absolute(out)
        .map_err(|e| anyhow::anyhow!("snapshot directory {}: {e}", out.display()))?;
    let reply = request_products(
        socket,
        &ProductRequest::Snapshot {
            edge: edge.to_owned(),
            session: session.map(str::to_owned),
            position: position.map(str::to_owned),
            out,
        },
    )?;
    if !reply.ok {
        anyhow::bail!("{}", reply.detail);
    }
    Ok(reply)
}

fn request_with(
    path: &Path,
    request: &impl Serialize,
    timeout: std::time::Duration,
) -> anyhow::Result<ControlReply> {
    use std::io::{BufRead, Write};
    let mut stream = std::os::unix::net::UnixStream::connect(path).map_err(|e| {
        anyhow::anyhow!(
            "cannot reach the server's control socket {} ({e}); is `scan3d serve` running with this data_dir?",
            path.display()
        )
    })?;
    stream.set_read_timeout(Some(timeout))?;
    let mut line = serde_json::to_string(request)?;
    line.push('\n');
    // A server that refuses a request before reading all of it (too long) answers and closes:
    // the write then fails, but its answer is there to read and says why.
    let written = stream.write_all(line.as_bytes());
    let mut answer = String::new();
    let read = std::io::BufReader::new(&stream).read_line(&mut answer);
    match (read, written) {
        (Ok(n), _) if n > 0 => {}
        (_, Err(e)) => anyhow::bail!("control socket {}: {e}", path.display()),
        (Err(e), Ok(())) => anyhow::bail!("control socket {}: {e}", path.display()),
        (Ok(_), Ok(())) => {
            anyhow::bail!(
                "control socket {}: closed without an answer",
                path.display()
            )
        }
    }
    serde_json::from_str(&answer)
        .map_err(|e| anyhow::anyhow!("unreadable answer from the server ({e}): {answer:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_to_the_registered_edge_only() {
        let control = EdgeControl::default();
        let mut rx = control.register("pi");
        let reply = handle_request(
            &control,
            r#"{"edge":"pi","command":{"StartStaticScan":{"position":"door","x_m":1.0,"y_m":2.0,"heading_deg":90.0}}}"#,
        );
        assert!(reply.ok, "{reply:?}");
        assert_eq!(
            rx.try_recv().ok(),
            Some(Command::StartStaticScan {
                position: "door".into(),
                x_m: 1.0,
                y_m: 2.0,
                heading_deg: Some(90.0),
            })
        );
        let reply = handle_request(&control, r#"{"edge":"other","command":"StopStaticScan"}"#);
        assert!(!reply.ok);
        assert_eq!(
            reply.detail,
            "edge \"other\" is not connected (connected: pi)"
        );
        let reply = handle_request(&control, "{not json");
        assert!(!reply.ok);
        assert!(reply.detail.starts_with("malformed request"), "{reply:?}");
        drop(rx);
        control.unregister("pi");
        assert!(control.connected().is_empty());
    }

    #[test]
    fn product_requests_are_told_from_commands_by_their_request_key() {
        let control = EdgeControl::default();
        let _rx = control.register("pi");
        // Without a live pipeline, a product request is refused with the reason.
        let reply = handle_request(&control, r#"{"request":"status"}"#);
        assert_eq!(reply, ControlReply::failed(NO_PIPELINE.into()));
        // A product request with an unknown key or kind is malformed, not taken for a command.
        for line in [
            r#"{"request":"reboot"}"#,
            r#"{"request":"snapshot","edge":"pi"}"#,
        ] {
            let reply = handle_request(&control, line);
            assert!(
                reply.detail.starts_with("malformed request"),
                "{line}: {reply:?}"
            );
        }
        assert_eq!(
            parse_request(r#"{"request":"snapshot","edge":"pi","out":"/tmp/s"}"#)
                .map(|r| match r {
                    Request::Products(p) => Some(p),
                    Request::Command(_) => None,
                })
                .ok()
                .flatten(),
            Some(ProductRequest::Snapshot {
                edge: "pi".into(),
                session: None,
                position: None,
                out: PathBuf::from("/tmp/s"),
            })
        );
        // Commands are answered as before, without a `data` key on the wire.
        let reply = handle_request(&control, r#"{"edge":"pi","command":"StopStaticScan"}"#);
        assert_eq!(
            reply_line(&reply),
            "{\"ok\":true,\"detail\":\"sent to pi\"}\n"
        );
    }

    #[tokio::test]
    async fn socket_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = socket_path(dir.path());
        let control = EdgeControl::default();
        let mut rx = control.register("pi");
        let server = tokio::spawn(serve_socket(path.clone(), control));
        while !path.exists() {
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        }
        let reply = tokio::task::spawn_blocking(move || {
            request(
                &path,
                &ControlRequest {
                    edge: "pi".into(),
                    command: Command::StopStaticScan,
                },
            )
        })
        .await
        .unwrap()
        .unwrap();
        assert!(reply.ok);
        assert_eq!(rx.recv().await, Some(Command::StopStaticScan));
        server.abort();
    }

    fn test_limits() -> ControlLimits {
        ControlLimits {
            max_line_len: 1024,
            max_connections: 2,
            idle_timeout: Duration::from_secs(5),
            accept_backoff_min: Duration::from_millis(1),
            accept_backoff_max: Duration::from_millis(4),
        }
    }

    /// A control socket serving `control` in `dir` with `limits`.
    async fn start(
        dir: &Path,
        control: &EdgeControl,
        limits: ControlLimits,
    ) -> (PathBuf, tokio::task::JoinHandle<std::convert::Infallible>) {
        let socket = ControlSocket::bind(socket_path(dir), limits).await.unwrap();
        let path = socket.path().to_path_buf();
        (path, tokio::spawn(socket.serve(control.clone())))
    }

    /// Sends `bytes`, ends its side, and reads everything the server writes until it closes
    /// (or 5 s pass). A server that closes with part of the request unread resets the
    /// connection after its reply: the reply is kept.
    async fn exchange(path: &Path, bytes: &[u8]) -> String {
        use tokio::io::AsyncReadExt;
        let mut stream = UnixStream::connect(path).await.unwrap();
        stream.write_all(bytes).await.unwrap();
        stream.shutdown().await.unwrap();
        let mut reply = Vec::new();
        let read_all = async {
            let mut chunk = [0u8; 4096];
            loop {
                match stream.read(&mut chunk).await {
                    Ok(0) => break,
                    Ok(n) => reply.extend_from_slice(&chunk[..n]),
                    Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => break,
                    Err(e) => panic!("{e}"),
                }
            }
        };
        tokio::time::timeout(Duration::from_secs(5), read_all)
            .await
            .expect("the server neither answered nor closed");
        String::from_utf8(reply).unwrap()
    }

    fn stop_line() -> String {
        "{\"edge\":\"pi\",\"command\":\"StopStaticScan\"}\n".to_owned()
    }

    #[test]
    fn an_oversized_command_is_refused_and_never_reaches_the_edge() {
        let control = EdgeControl::default();
        let mut rx = control.register("pi");
        let request = ControlRequest {
            edge: "pi".into(),
            command: Command::StartStaticScan {
                position: "x".repeat(5 * 1024 * 1024),
                x_m: 1.0,
                y_m: 2.0,
                heading_deg: None,
            },
        };
        let reply = handle_request(&control, &serde_json::to_string(&request).unwrap());
        assert!(!reply.ok, "{reply:?}");
        assert_eq!(
            reply.detail,
            "invalid command: position name of 5242880 bytes: must be 1 to 256 bytes"
        );
        // Nothing was queued on the edge's connection, which stays registered and usable.
        assert!(rx.try_recv().is_err());
        assert_eq!(control.connected(), ["pi"]);
        assert!(handle_request(&control, stop_line().trim()).ok);
        assert_eq!(rx.try_recv().ok(), Some(Command::StopStaticScan));
        // The same check guards every route, not only the socket.
        let nan = Command::StartStaticScan {
            position: "p".into(),
            x_m: f64::NAN,
            y_m: 0.0,
            heading_deg: None,
        };
        assert!(matches!(
            control.send("pi", nan),
            Err(ControlError::Invalid(_))
        ));
        assert!(rx.try_recv().is_err());
    }

    #[tokio::test]
    async fn the_socket_is_owner_only_whatever_the_umask() {
        let dir = tempfile::tempdir().unwrap();
        let (path, server) = start(dir.path(), &EdgeControl::default(), test_limits()).await;
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, SOCKET_MODE);
        server.abort();
    }

    #[test]
    fn only_the_servers_own_uid_and_root_may_connect() {
        assert_eq!(peer_refusal(Some(1000), 1000), None);
        assert_eq!(peer_refusal(Some(0), 1000), None);
        assert_eq!(
            peer_refusal(Some(1001), 1000).as_deref(),
            Some("permission denied: uid 1001 is not the server's (uid 1000) or root")
        );
        assert!(peer_refusal(None, 1000).is_some());
    }

    #[tokio::test]
    async fn a_path_longer_than_sun_path_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let deep = dir.path().join("d".repeat(120));
        let err = ControlSocket::bind(socket_path(&deep), test_limits())
            .await
            .unwrap_err();
        let text = err.to_string();
        assert!(
            matches!(err, SocketError::PathTooLong { max: 107, .. }),
            "{text}"
        );
        assert!(
            text.contains(&socket_path(&deep).display().to_string()),
            "{text}"
        );
        assert!(text.contains("107 bytes"), "{text}");
    }

    #[tokio::test]
    async fn a_live_socket_is_not_stolen_by_a_second_server() {
        let dir = tempfile::tempdir().unwrap();
        let (_path, server) = start(dir.path(), &EdgeControl::default(), test_limits()).await;
        let err = ControlSocket::bind(socket_path(dir.path()), test_limits())
            .await
            .unwrap_err();
        assert!(matches!(err, SocketError::InUse { .. }), "{err}");
        server.abort();
    }

    #[tokio::test]
    async fn accept_errors_are_retried_and_the_socket_keeps_serving() {
        let dir = tempfile::tempdir().unwrap();
        let socket = ControlSocket::bind(socket_path(dir.path()), test_limits())
            .await
            .unwrap();
        let path = socket.path().to_path_buf();
        let control = EdgeControl::default();
        let mut rx = control.register("pi");
        let failures = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = failures.clone();
        let server = tokio::spawn(async move {
            let listener = &socket.listener;
            let accept = move || -> AcceptFuture<'_> {
                let counted = counted.clone();
                Box::pin(async move {
                    // Three EMFILEs, as when the process is out of file descriptors.
                    if counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst) < 3 {
                        return Err(std::io::Error::from_raw_os_error(24));
                    }
                    listener.accept().await.map(|(stream, _)| stream)
                })
            };
            accept_loop(accept, &socket.path, socket.limits, control, None).await
        });
        let reply = exchange_one(&path, &stop_line()).await;
        assert!(reply.starts_with("{\"ok\":true"), "{reply}");
        assert_eq!(rx.recv().await, Some(Command::StopStaticScan));
        assert!(failures.load(std::sync::atomic::Ordering::SeqCst) >= 4);
        assert!(!server.is_finished());
        server.abort();
    }

    #[tokio::test(start_paused = true)]
    async fn a_persistent_accept_error_backs_off_instead_of_spinning() {
        let calls = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = calls.clone();
        let accept = move || -> AcceptFuture<'static> {
            counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            Box::pin(async { Err(std::io::Error::from_raw_os_error(24)) })
        };
        let limits = ControlLimits {
            accept_backoff_min: Duration::from_millis(10),
            accept_backoff_max: Duration::from_millis(1000),
            ..test_limits()
        };
        let looping = accept_loop(
            accept,
            Path::new("test.sock"),
            limits,
            EdgeControl::default(),
            None,
        );
        // Ten seconds of (virtual) time: 10+20+...+640 ms, then one try a second.
        let _ = tokio::time::timeout(Duration::from_secs(10), looping).await;
        let calls = calls.load(std::sync::atomic::Ordering::SeqCst);
        assert!((8..=18).contains(&calls), "{calls} accept calls in 10 s");
    }

    /// Sends one line and reads one reply line, leaving the connection open.
    async fn exchange_one(path: &Path, line: &str) -> String {
        let stream = UnixStream::connect(path).await.unwrap();
        let (read, mut write) = stream.into_split();
        write.write_all(line.as_bytes()).await.unwrap();
        let mut reply = String::new();
        tokio::time::timeout(
            Duration::from_secs(5),
            BufReader::new(read).read_line(&mut reply),
        )
        .await
        .unwrap()
        .unwrap();
        reply
    }

    #[tokio::test]
    async fn an_overlong_request_line_is_answered_with_an_error_and_closed() {
        let dir = tempfile::tempdir().unwrap();
        let control = EdgeControl::default();
        let mut rx = control.register("pi");
        let (path, server) = start(dir.path(), &control, test_limits()).await;
        // 4 KiB without a newline, then a valid request that must not be served.
        let mut bytes = vec![b'a'; 4096];
        bytes.extend_from_slice(stop_line().as_bytes());
        let reply = exchange(&path, &bytes).await;
        assert_eq!(
            reply,
            "{\"ok\":false,\"detail\":\"request line longer than 1024 bytes; closing the connection\"}\n"
        );
        assert!(rx.try_recv().is_err());
        // A line of exactly the limit is read (and refused as JSON, not as too long).
        let mut exact = vec![b' '; 1024];
        exact.push(b'\n');
        let reply = exchange(&path, &exact).await;
        assert!(reply.contains("malformed request"), "{reply}");
        server.abort();
    }

    #[tokio::test]
    async fn connections_beyond_the_limit_are_refused_until_one_closes() {
        let dir = tempfile::tempdir().unwrap();
        let control = EdgeControl::default();
        let _rx = control.register("pi");
        let (path, server) = start(dir.path(), &control, test_limits()).await;
        // Two idle connections take both slots (each answered once, so they are being served).
        let first = UnixStream::connect(&path).await.unwrap();
        let second = UnixStream::connect(&path).await.unwrap();
        for stream in [&first, &second] {
            stream.writable().await.unwrap();
        }
        let mut held = Vec::new();
        for stream in [first, second] {
            let (read, mut write) = stream.into_split();
            write.write_all(stop_line().as_bytes()).await.unwrap();
            let mut reader = BufReader::new(read);
            let mut reply = String::new();
            reader.read_line(&mut reply).await.unwrap();
            assert!(reply.starts_with("{\"ok\":true"), "{reply}");
            held.push((reader, write));
        }
        let reply = exchange(&path, stop_line().as_bytes()).await;
        assert_eq!(
            reply,
            "{\"ok\":false,\"detail\":\"too many control connections (at most 2 at once)\"}\n"
        );
        // Closing one frees its slot.
        drop(held.pop());
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        loop {
            let reply = exchange(&path, stop_line().as_bytes()).await;
            if reply.starts_with("{\"ok\":true") {
                break;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "slot never freed: {reply}"
            );
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        server.abort();
    }

    #[tokio::test]
    async fn an_idle_connection_is_closed_after_the_timeout() {
        use tokio::io::AsyncReadExt;
        let dir = tempfile::tempdir().unwrap();
        let limits = ControlLimits {
            idle_timeout: Duration::from_millis(50),
            ..test_limits()
        };
        let (path, server) = start(dir.path(), &EdgeControl::default(), limits).await;
        let mut stream = UnixStream::connect(&path).await.unwrap();
        // Half a request, then silence.
        stream.write_all(b"{\"edge\":").await.unwrap();
        let started = std::time::Instant::now();
        let mut rest = Vec::new();
        let read = tokio::time::timeout(Duration::from_secs(5), stream.read_to_end(&mut rest))
            .await
            .expect("the idle connection was not closed");
        assert_eq!(read.unwrap(), 0);
        assert!(started.elapsed() >= Duration::from_millis(40));
        server.abort();
    }
}
