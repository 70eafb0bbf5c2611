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
//! The socket lives at `data_dir/control.sock` (see [`socket_path`]), so only users who can
//! write the recordings can command the edges.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use scan3d_protocol::Command;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::mpsc;

/// The control socket of a server whose recordings live in `data_dir`.
pub fn socket_path(data_dir: &Path) -> PathBuf {
    data_dir.join("control.sock")
}

/// Why a command could not be routed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ControlError {
    /// No live connection of that edge.
    #[error("edge {edge:?} is not connected (connected: {connected})")]
    NotConnected {
        /// The edge asked for.
        edge: String,
        /// The edges that are, comma-separated (or "none").
        connected: String,
    },
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

    /// Queues `command` on `edge`'s connection (sent with the next outgoing frames).
    pub fn send(&self, edge: &str, command: Command) -> Result<(), ControlError> {
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

/// The answer to a [`ControlRequest`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ControlReply {
    /// Whether the command was queued on the edge's connection.
    pub ok: bool,
    /// What happened, for a human.
    pub detail: String,
}

/// The reply to one request line.
pub fn handle_request(control: &EdgeControl, line: &str) -> ControlReply {
    let request: ControlRequest = match serde_json::from_str(line) {
        Ok(request) => request,
        Err(e) => {
            return ControlReply {
                ok: false,
                detail: format!("malformed request: {e}"),
            };
        }
    };
    match control.send(&request.edge, request.command) {
        Ok(()) => ControlReply {
            ok: true,
            detail: format!("sent to {}", request.edge),
        },
        Err(e) => ControlReply {
            ok: false,
            detail: e.to_string(),
        },
    }
}

/// Serves the control socket at `path` until the task is dropped. A stale socket file left by
/// a crashed server is replaced.
pub async fn serve_socket(path: PathBuf, control: EdgeControl) -> std::io::Result<()> {
    if path.exists() && UnixStream::connect(&path).await.is_err() {
        std::fs::remove_file(&path)?;
    }
    let listener = UnixListener::bind(&path)?;
    tracing::info!(socket = %path.display(), "control socket ready");
    loop {
        let (stream, _) = listener.accept().await?;
        let control = control.clone();
        tokio::spawn(async move {
            if let Err(e) = answer(stream, &control).await {
                tracing::warn!(error = %e, "control connection failed");
            }
        });
    }
}

async fn answer(stream: UnixStream, control: &EdgeControl) -> std::io::Result<()> {
    let (read, mut write) = stream.into_split();
    let mut lines = BufReader::new(read).lines();
    while let Some(line) = lines.next_line().await? {
        let reply = handle_request(control, &line);
        tracing::info!(ok = reply.ok, detail = %reply.detail, "control request");
        let mut text = serde_json::to_string(&reply).map_err(std::io::Error::other)?;
        text.push('\n');
        write.write_all(text.as_bytes()).await?;
    }
    Ok(())
}

/// Sends one request to the server's control socket and waits for the reply (blocking; for
/// the CLI).
pub fn request(path: &Path, request: &ControlRequest) -> anyhow::Result<ControlReply> {
    use std::io::{BufRead, Write};
    let mut stream = std::os::unix::net::UnixStream::connect(path).map_err(|e| {
        anyhow::anyhow!(
            "cannot reach the server's control socket {} ({e}); is `scan3d serve` running with this data_dir?",
            path.display()
        )
    })?;
    stream.set_read_timeout(Some(std::time::Duration::from_secs(10)))?;
    let mut line = serde_json::to_string(request)?;
    line.push('\n');
    stream.write_all(line.as_bytes())?;
    let mut answer = String::new();
    std::io::BufReader::new(&stream).read_line(&mut answer)?;
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
}
