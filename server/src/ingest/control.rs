//! Operator control of connected edges: [`EdgeControl`] routes a [`Command`] to an edge's live
//! connection, and a local Unix socket lets `scan3d scan` (another process on the laptop) use it.
//!
//! The socket protocol is JSON lines, so it can be driven by hand with `socat`. A command
//! followed until the edge answers ([`CommandRequest`], what `scan3d scan` sends) gets one
//! [`CommandStatus`] line per change, the last with `"done":true`:
//!
//! ```text
//! → {"request":"command","edge":"pi","command":{"StartStaticScan":{"position":"door","x_m":1.0,"y_m":2.0,"heading_deg":null}},"follow":false}
//! ← {"ok":true,"detail":"edge pi started static scan 0","data":{"state":"accepted","done":true,"scan_id":0,...}}
//! ```
//!
//! The edge's answer is its [`CommandReply`] frame (recorded in the session), matched by the
//! command frame's sequence number; with `"follow":true` the static scan's frames are folded
//! into [`ScanProgress`] until it ends. A bare command (no `"request"` key) is only queued:
//!
//! ```text
//! → {"edge":"pi","command":"StopStaticScan"}
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

use scan3d_protocol::{
    Body, Command, CommandOutcome, CommandReply, InvalidCommand, PassEvent, PassMarker, SensorId,
    StaticScan,
};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::{broadcast, mpsc, oneshot};

use super::scan_progress::ScanProgress;

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
    /// A trolley pass for an edge whose latest `Hello` lists no RPLidar ([`pass_refusal`]).
    #[error("edge {edge:?} has no RPLidar (its Hello lists: {sensors}): a trolley pass needs one")]
    NoRplidar {
        /// The edge.
        edge: String,
        /// The sensors its `Hello` lists, comma-separated (or "none").
        sensors: String,
    },
}

/// Why the server refuses `command` for `edge` without asking it: a [`Command::StartPass`] when
/// the edge's latest `Hello` (its `sensors`, `None` when none was seen) lists no RPLidar.
/// Pure, so the rule is tested without a connection.
pub fn pass_refusal(
    edge: &str,
    command: &Command,
    sensors: Option<&[SensorId]>,
) -> Option<ControlError> {
    let sensors = sensors?;
    if !matches!(command, Command::StartPass { .. }) || sensors.contains(&SensorId::RPLIDAR) {
        return None;
    }
    Some(ControlError::NoRplidar {
        edge: edge.to_owned(),
        sensors: if sensors.is_empty() {
            "none".to_owned()
        } else {
            sensors
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        },
    })
}

/// A command on its way to an edge's connection task; `sent` learns the session and sequence
/// number the command's frame got (which the edge's [`CommandReply`] names).
#[derive(Debug)]
pub struct QueuedCommand {
    /// The command.
    pub command: Command,
    /// Told where the command went, if someone follows it.
    pub sent: Option<oneshot::Sender<SentCommand>>,
}

/// Where a command went: the edge session it was recorded in and its frame's sequence number.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SentCommand {
    /// The edge session.
    pub session_id: u64,
    /// The server frame's sequence number in that session.
    pub seq: u64,
}

/// What a follower of a command sees of an edge: its connection coming and going, and the
/// recorded frames that answer commands ([`Body::CommandReply`]) or tell a static scan's
/// progress ([`Body::StaticScan`]).
#[derive(Debug, Clone, PartialEq)]
pub enum EdgeEvent {
    /// The edge connected.
    Connected,
    /// The edge's connection ended (no newer one replaced it).
    Disconnected {
        /// Why.
        reason: String,
    },
    /// A frame recorded for the first time.
    Frame {
        /// Its session.
        session_id: u64,
        /// A `CommandReply`, a `StaticScan` or a `Pass`.
        body: Body,
    },
}

/// Events buffered per edge for followers that fall behind.
const EVENT_CAPACITY: usize = 4096;

#[derive(Debug, Default)]
struct Links {
    commands: HashMap<String, mpsc::UnboundedSender<QueuedCommand>>,
    /// Kept across reconnections, so a follower sees the edge come back.
    events: HashMap<String, broadcast::Sender<EdgeEvent>>,
    /// The sensors of each edge's latest `Hello`.
    sensors: HashMap<String, Vec<SensorId>>,
}

impl Links {
    fn events(&mut self, edge: &str) -> &broadcast::Sender<EdgeEvent> {
        self.events
            .entry(edge.to_owned())
            .or_insert_with(|| broadcast::channel(EVENT_CAPACITY).0)
    }
}

/// A command queued by [`EdgeControl::submit`]: where it went, and the edge's events from
/// before it was queued on.
#[derive(Debug)]
pub struct CommandTicket {
    /// Fires once the connection task recorded the command and queued its frame.
    pub sent: oneshot::Receiver<SentCommand>,
    /// The edge's events.
    pub events: broadcast::Receiver<EdgeEvent>,
}

/// Routes commands to the edges connected to an ingest server; cheap to clone.
#[derive(Debug, Clone, Default)]
pub struct EdgeControl {
    links: Arc<Mutex<Links>>,
}

impl EdgeControl {
    /// Registers an edge's connection; its task receives the commands. A newer connection of
    /// the same edge replaces the older one.
    pub(crate) fn register(&self, edge: &str) -> mpsc::UnboundedReceiver<QueuedCommand> {
        let (tx, rx) = mpsc::unbounded_channel();
        let mut links = self.lock();
        links.commands.insert(edge.to_owned(), tx);
        let _ = links.events(edge).send(EdgeEvent::Connected);
        rx
    }

    /// Forgets an edge whose connection ended (unless a newer one already replaced it), and
    /// tells its followers why.
    pub(crate) fn unregister(&self, edge: &str, reason: &str) {
        let mut links = self.lock();
        if links
            .commands
            .get(edge)
            .is_some_and(mpsc::UnboundedSender::is_closed)
        {
            links.commands.remove(edge);
            let _ = links.events(edge).send(EdgeEvent::Disconnected {
                reason: reason.to_owned(),
            });
        }
    }

    /// Hands a recorded frame of `edge` to the followers of its commands, if it is one they
    /// follow (a command reply, a static-scan message, a pass marker); a `Hello` updates the
    /// edge's known sensors ([`pass_refusal`]).
    pub(crate) fn publish(&self, edge: &str, frame: &scan3d_protocol::Frame) {
        if let Body::Hello(hello) = &frame.body {
            let sensors = hello.sensors.iter().map(|info| info.sensor).collect();
            self.lock().sensors.insert(edge.to_owned(), sensors);
            return;
        }
        if matches!(
            frame.body,
            Body::CommandReply(_) | Body::StaticScan(_) | Body::Pass(_)
        ) && let Some(events) = self.lock().events.get(edge)
        {
            let _ = events.send(EdgeEvent::Frame {
                session_id: frame.session_id,
                body: frame.body.clone(),
            });
        }
    }

    /// The connected edges, sorted.
    pub fn connected(&self) -> Vec<String> {
        let mut names: Vec<String> = self
            .lock()
            .commands
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
        self.queue(edge, command, None).map(drop)
    }

    /// [`EdgeControl::send`], and follow the command: the ticket tells where it went and
    /// carries the edge's events from now on (the edge's reply among them).
    pub fn submit(&self, edge: &str, command: Command) -> Result<CommandTicket, ControlError> {
        let (tx, rx) = oneshot::channel();
        let events = self.queue(edge, command, Some(tx))?;
        Ok(CommandTicket { sent: rx, events })
    }

    fn queue(
        &self,
        edge: &str,
        command: Command,
        sent: Option<oneshot::Sender<SentCommand>>,
    ) -> Result<broadcast::Receiver<EdgeEvent>, ControlError> {
        command.validate()?;
        let mut links = self.lock();
        // A disconnected edge is told as such (below), whatever its last Hello said.
        let connected = links.commands.get(edge).is_some_and(|tx| !tx.is_closed());
        if connected
            && let Some(refusal) =
                pass_refusal(edge, &command, links.sensors.get(edge).map(Vec::as_slice))
        {
            return Err(refusal);
        }
        let events = links.events(edge).subscribe();
        let queued = links
            .commands
            .get(edge)
            .is_some_and(|tx| tx.send(QueuedCommand { command, sent }).is_ok());
        drop(links);
        if queued {
            Ok(events)
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

    fn lock(&self) -> std::sync::MutexGuard<'_, Links> {
        self.links.lock().unwrap_or_else(|e| e.into_inner())
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

/// A command that the control socket follows until the edge answers (and, with `follow`,
/// until the static scan it started ends), told apart by `"request":"command"`:
///
/// ```text
/// → {"request":"command","edge":"pi","command":{"StartStaticScan":{...}},"follow":true}
/// ← {"ok":true,"detail":"edge pi waits: waiting for the Sweep to stream","data":{"state":"waiting","done":false,...}}
/// ← {"ok":true,"detail":"static scan 0 at \"door\": 3 revolutions, ...","data":{"state":"running","done":false,"progress":{...}}}
/// ← {"ok":true,"detail":"static scan 0 at \"door\" completed: ...","data":{"state":"completed","done":true,...}}
/// ```
///
/// Every line's `data` is a [`CommandStatus`]; the last has `"done":true`, and its `ok` says
/// whether the command did what was asked. Without an update the socket repeats the current
/// status every few seconds, so a client can bound its wait per line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CommandRequest {
    /// The edge's name (its certificate's).
    pub edge: String,
    /// What to tell it.
    pub command: Command,
    /// Follow a static scan the command starts until it ends (and the edge while it waits
    /// for the Sweep), instead of answering with the edge's first reply.
    #[serde(default)]
    pub follow: bool,
    /// How long to wait for the edge's reply, seconds (default [`REPLY_TIMEOUT`]).
    #[serde(default)]
    pub reply_timeout_s: Option<f64>,
}

/// How long the control socket waits for an edge to answer a command.
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(15);
/// How long a followed edge may stay disconnected before its command is given up as lost.
pub const LOST_GRACE: Duration = Duration::from_secs(30);
/// How often a followed command's status is repeated when nothing changes.
pub const KEEPALIVE: Duration = Duration::from_secs(5);

/// Where a followed command stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommandState {
    /// Queued or sent; no reply yet.
    Sent,
    /// The edge is not connected (final).
    NotConnected,
    /// The edge did not answer in time (final).
    Timeout,
    /// The edge refused, with the reason (final).
    Refused,
    /// The edge accepted and waits (for the Sweep to stream).
    Waiting,
    /// The edge accepted (final unless followed).
    Accepted,
    /// The static scan runs.
    Running,
    /// The static scan turned the whole planned angle (final).
    Completed,
    /// The static scan was stopped (final).
    Stopped,
    /// The static scan was aborted after failed steps (final).
    Aborted,
    /// The edge's connection was lost and did not come back in time (final).
    Lost,
}

/// One status line of a followed command (the `data` of each reply line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandStatus {
    /// Where it stands.
    pub state: CommandState,
    /// Whether this is the last line.
    pub done: bool,
    /// Whether the command did (or, not done yet, is doing) what was asked.
    pub ok: bool,
    /// The edge.
    pub edge: String,
    /// The edge session the command went to (16 hex digits), once sent.
    pub session: Option<String>,
    /// The command frame's sequence number, once sent.
    pub command_seq: Option<u64>,
    /// The static scan concerned, once the edge named it.
    pub scan_id: Option<u32>,
    /// The edge's reason (refused, waiting), or why the command was given up.
    pub reason: Option<String>,
    /// The static scan's progress, while followed.
    pub progress: Option<ScanProgress>,
    /// The trolley pass a `StartPass` / `StopPass` opened or closed (the edge's marker, stamped
    /// on its clock).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pass: Option<PassMarker>,
    /// Seconds since the request.
    pub elapsed_s: f64,
    /// One line for a human.
    pub detail: String,
}

/// The timing of a [`CommandFollower`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FollowTiming {
    /// Wait for the edge's reply at most this long.
    pub reply_timeout: Duration,
    /// A disconnected edge is lost after this long.
    pub lost_grace: Duration,
}

impl Default for FollowTiming {
    fn default() -> Self {
        FollowTiming {
            reply_timeout: REPLY_TIMEOUT,
            lost_grace: LOST_GRACE,
        }
    }
}

/// Messages kept while the reply is awaited (a scan's first frames may come first).
const EARLY_EVENTS: usize = 1024;

/// The state machine of one followed command, without a network: fed where the command went
/// ([`CommandFollower::on_sent`]), the edge's events and the time, it says what to tell the
/// client. `Instant`s are passed in.
#[derive(Debug)]
pub struct CommandFollower {
    edge: String,
    starts_scan: bool,
    /// A `StartPass` or `StopPass`: the edge's pass marker is kept for the status.
    pass_command: bool,
    /// The server refused the command itself (its reason is the whole line).
    by_server: bool,
    pass: Option<PassMarker>,
    follow: bool,
    timing: FollowTiming,
    started: std::time::Instant,
    sent: Option<SentCommand>,
    state: CommandState,
    scan_id: Option<u32>,
    reason: Option<String>,
    progress: Option<ScanProgress>,
    lost: Option<(std::time::Instant, String)>,
    early: Vec<EdgeEvent>,
}

impl CommandFollower {
    /// A follower of `command` to `edge`, asked at `now`.
    pub fn new(
        edge: &str,
        command: &Command,
        follow: bool,
        timing: FollowTiming,
        now: std::time::Instant,
    ) -> Self {
        CommandFollower {
            edge: edge.to_owned(),
            starts_scan: matches!(command, Command::StartStaticScan { .. }),
            pass_command: matches!(command, Command::StartPass { .. } | Command::StopPass),
            by_server: false,
            pass: None,
            follow,
            timing,
            started: now,
            sent: None,
            state: CommandState::Sent,
            scan_id: None,
            reason: None,
            progress: None,
            lost: None,
            early: Vec::new(),
        }
    }

    /// The command could not be queued (the edge is not connected, the command invalid).
    pub fn failed(&mut self, error: &ControlError, now: std::time::Instant) -> CommandStatus {
        self.state = match error {
            ControlError::NotConnected { .. } => CommandState::NotConnected,
            ControlError::Invalid(_) | ControlError::NoRplidar { .. } => CommandState::Refused,
        };
        self.by_server = true;
        self.reason = Some(error.to_string());
        self.status(now)
    }

    /// The connection task sent the command; events that came first are replayed.
    pub fn on_sent(&mut self, sent: SentCommand, now: std::time::Instant) -> Option<CommandStatus> {
        self.sent = Some(sent);
        let mut update = None;
        for event in std::mem::take(&mut self.early) {
            if let Some(status) = self.on_event(&event, now) {
                update = Some(status);
                if self.is_done() {
                    break;
                }
            }
        }
        update
    }

    /// One event of the edge; the status to tell, if it changed.
    pub fn on_event(
        &mut self,
        event: &EdgeEvent,
        now: std::time::Instant,
    ) -> Option<CommandStatus> {
        if self.is_done() {
            return None;
        }
        match event {
            EdgeEvent::Connected => {
                self.lost = None;
                None
            }
            EdgeEvent::Disconnected { reason } => {
                self.lost = Some((now, reason.clone()));
                None
            }
            EdgeEvent::Frame { session_id, body } => {
                let Some(sent) = self.sent else {
                    if self.early.len() < EARLY_EVENTS {
                        self.early.push(event.clone());
                    }
                    return None;
                };
                if *session_id != sent.session_id {
                    return None;
                }
                match body {
                    Body::CommandReply(reply) if reply.command_seq == sent.seq => {
                        self.on_reply(reply, now)
                    }
                    Body::StaticScan(message) => self.on_scan(message, event, now),
                    // The edge sends the marker just before its reply.
                    Body::Pass(marker) if self.pass_command => {
                        self.pass = Some(marker.clone());
                        None
                    }
                    _ => None,
                }
            }
        }
    }

    fn on_reply(&mut self, reply: &CommandReply, now: std::time::Instant) -> Option<CommandStatus> {
        match &reply.outcome {
            CommandOutcome::Refused { reason } => {
                self.state = CommandState::Refused;
                self.reason = Some(reason.clone());
            }
            CommandOutcome::Waiting { reason } => {
                self.state = CommandState::Waiting;
                self.reason = Some(reason.clone());
            }
            CommandOutcome::Accepted { scan_id } => {
                self.scan_id = *scan_id;
                self.reason = None;
                match scan_id {
                    Some(id) if self.follow && self.starts_scan => {
                        self.state = CommandState::Running;
                        self.progress = Some(ScanProgress::new(*id));
                        for event in std::mem::take(&mut self.early) {
                            if let EdgeEvent::Frame {
                                body: Body::StaticScan(message),
                                ..
                            } = &event
                            {
                                self.fold(message);
                            }
                        }
                    }
                    _ => self.state = CommandState::Accepted,
                }
            }
        }
        Some(self.status(now))
    }

    fn on_scan(
        &mut self,
        message: &StaticScan,
        event: &EdgeEvent,
        now: std::time::Instant,
    ) -> Option<CommandStatus> {
        match self.state {
            CommandState::Running => self.fold(message).then(|| self.status(now)),
            CommandState::Sent | CommandState::Waiting => {
                // The scan's first frames may overtake the reply.
                if self.early.len() < EARLY_EVENTS {
                    self.early.push(event.clone());
                }
                None
            }
            _ => None,
        }
    }

    /// Folds a message of the followed scan; true if it was one.
    fn fold(&mut self, message: &StaticScan) -> bool {
        let Some(progress) = &mut self.progress else {
            return false;
        };
        if !progress.on_message(message) {
            return false;
        }
        if let Some(outcome) = progress.outcome.as_deref() {
            self.state = match outcome {
                "completed" => CommandState::Completed,
                "aborted" => CommandState::Aborted,
                _ => CommandState::Stopped,
            };
        }
        true
    }

    /// The time passed: the final status if the reply is overdue or the edge lost.
    pub fn on_tick(&mut self, now: std::time::Instant) -> Option<CommandStatus> {
        if self.is_done() {
            return None;
        }
        if self.state == CommandState::Sent
            && now.duration_since(self.started) >= self.timing.reply_timeout
        {
            self.state = CommandState::Timeout;
            self.reason = Some(match &self.lost {
                Some((_, why)) => format!("the edge disconnected before it answered ({why})"),
                None => format!(
                    "no answer within {} s (is the edge's scan3d-edge as new as this server?)",
                    self.timing.reply_timeout.as_secs_f64()
                ),
            });
            return Some(self.status(now));
        }
        if let Some((since, why)) = &self.lost
            && now.duration_since(*since) >= self.timing.lost_grace
        {
            self.reason = Some(format!(
                "the edge's connection ended ({why}) and did not come back within {} s",
                self.timing.lost_grace.as_secs_f64()
            ));
            self.state = CommandState::Lost;
            return Some(self.status(now));
        }
        None
    }

    /// Whether the last status was told.
    pub fn is_done(&self) -> bool {
        match self.state {
            CommandState::Sent | CommandState::Running => false,
            CommandState::Waiting => !self.follow,
            _ => true,
        }
    }

    /// The current status.
    pub fn status(&self, now: std::time::Instant) -> CommandStatus {
        let done = self.is_done();
        let ok = matches!(
            self.state,
            CommandState::Sent
                | CommandState::Waiting
                | CommandState::Accepted
                | CommandState::Running
                | CommandState::Completed
        );
        let edge = &self.edge;
        let reason = self.reason.as_deref().unwrap_or("");
        let progress = self.progress.as_ref();
        let summary = || progress.map_or_else(String::new, ScanProgress::summary);
        let detail = match self.state {
            CommandState::Sent => format!("sent to {edge}; waiting for its answer"),
            CommandState::NotConnected | CommandState::Refused if self.by_server => {
                reason.to_owned()
            }
            CommandState::NotConnected => reason.to_owned(),
            CommandState::Timeout => format!("edge {edge} did not answer: {reason}"),
            CommandState::Refused => format!("edge {edge} refused: {reason}"),
            CommandState::Waiting => format!("edge {edge} accepted and waits: {reason}"),
            CommandState::Accepted if self.pass_command => match &self.pass {
                Some(PassMarker {
                    event:
                        PassEvent::Started {
                            name,
                            x_m,
                            y_m,
                            heading_deg,
                        },
                    t_ns,
                }) => format!(
                    "edge {edge} started pass {name:?} at x {x_m} m, y {y_m} m, heading {heading_deg}° (edge time {t_ns} ns)"
                ),
                Some(PassMarker {
                    event: PassEvent::Stopped { name },
                    t_ns,
                }) => format!("edge {edge} stopped pass {name:?} (edge time {t_ns} ns)"),
                None => format!("edge {edge} accepted"),
            },
            CommandState::Accepted => match (self.starts_scan, self.scan_id) {
                (true, Some(id)) => format!("edge {edge} started static scan {id}"),
                (false, Some(id)) => format!("edge {edge} stops static scan {id}"),
                _ => format!("edge {edge} accepted"),
            },
            CommandState::Running => summary(),
            CommandState::Completed => format!("{} — completed", summary()),
            CommandState::Stopped => format!("{} — stopped before the end", summary()),
            CommandState::Aborted => format!("{} — aborted (failed steps)", summary()),
            CommandState::Lost => format!("edge {edge} lost: {reason}"),
        };
        CommandStatus {
            state: self.state,
            done,
            ok,
            edge: edge.clone(),
            session: self.sent.map(|s| format!("{:016x}", s.session_id)),
            command_seq: self.sent.map(|s| s.seq),
            scan_id: self.scan_id,
            reason: self.reason.clone(),
            progress: self.progress.clone(),
            pass: self.pass.clone(),
            elapsed_s: now.duration_since(self.started).as_secs_f64(),
            detail,
        }
    }
}

/// The reply line carrying `status`.
fn status_reply(status: &CommandStatus) -> ControlReply {
    ControlReply {
        ok: status.ok,
        detail: status.detail.clone(),
        data: serde_json::to_value(status).ok(),
    }
}

/// Follows `request` on the socket: writes each status line until the last.
async fn stream_command<W: tokio::io::AsyncWrite + Unpin>(
    control: &EdgeControl,
    request: CommandRequest,
    write: &mut W,
    write_timeout: Duration,
) -> std::io::Result<()> {
    use std::time::Instant;
    let timing = FollowTiming {
        reply_timeout: request
            .reply_timeout_s
            .filter(|s| s.is_finite() && *s > 0.0)
            .map_or(REPLY_TIMEOUT, |s| Duration::from_secs_f64(s.min(3600.0))),
        ..FollowTiming::default()
    };
    let mut follower = CommandFollower::new(
        &request.edge,
        &request.command,
        request.follow,
        timing,
        Instant::now(),
    );
    let mut emit = async |status: CommandStatus| -> std::io::Result<()> {
        tracing::info!(edge = %status.edge, state = ?status.state, detail = %status.detail, "command status");
        let line = reply_line(&status_reply(&status));
        tokio::time::timeout(write_timeout, write.write_all(line.as_bytes()))
            .await
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "client not reading"))?
    };
    let CommandTicket {
        mut sent,
        mut events,
    } = match control.submit(&request.edge, request.command.clone()) {
        Ok(ticket) => ticket,
        Err(e) => return emit(follower.failed(&e, Instant::now())).await,
    };
    let mut sent_pending = true;
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let mut last_emit = Instant::now();
    loop {
        let update = tokio::select! {
            result = &mut sent, if sent_pending => {
                sent_pending = false;
                // A dropped sender: the connection ended with the command queued; the reply
                // timeout says so.
                result.ok().and_then(|s| follower.on_sent(s, Instant::now()))
            }
            event = events.recv() => match event {
                Ok(event) => follower.on_event(&event, Instant::now()),
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    tracing::warn!(edge = %request.edge, missed = n, "a command's follower fell behind the edge's events");
                    None
                }
                Err(broadcast::error::RecvError::Closed) => follower.on_tick(Instant::now()),
            },
            _ = tick.tick() => {
                let now = Instant::now();
                follower.on_tick(now).or_else(|| {
                    (now.duration_since(last_emit) >= KEEPALIVE).then(|| follower.status(now))
                })
            }
        };
        if let Some(status) = update {
            let done = status.done;
            emit(status).await?;
            last_emit = Instant::now();
            if done {
                return Ok(());
            }
        }
    }
}

/// A parsed request line.
enum Request {
    Command(ControlRequest),
    Products(ProductRequest),
    Follow(CommandRequest),
}

fn parse_request(line: &str) -> Result<Request, String> {
    let value: serde_json::Value =
        serde_json::from_str(line).map_err(|e| format!("malformed request: {e}"))?;
    if let Some(serde_json::Value::Object(mut object)) =
        (value.get("request") == Some(&serde_json::Value::from("command"))).then_some(value.clone())
    {
        object.remove("request");
        serde_json::from_value(serde_json::Value::Object(object))
            .map(Request::Follow)
            .map_err(|e| format!("malformed request: {e}"))
    } else if value.get("request").is_some() {
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
        Ok(Request::Follow(_)) => {
            ControlReply::failed("a followed command needs the socket (ControlSocket)".into())
        }
        Err(detail) => ControlReply::failed(detail),
    }
}

const NO_PIPELINE: &str = "the server runs without the live pipeline ([pipeline] enabled = false)";

/// The reply to one request line; product requests go to `live` on a blocking thread.
async fn handle_parsed(
    control: &EdgeControl,
    live: Option<&Arc<dyn LiveProducts>>,
    parsed: Result<Request, String>,
) -> ControlReply {
    match parsed {
        Ok(Request::Follow(_)) => ControlReply::failed("followed commands are streamed".into()),
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
            let parsed = match std::str::from_utf8(&line) {
                Ok(text) => parse_request(text),
                Err(e) => Err(format!("malformed request: not UTF-8 ({e})")),
            };
            if let Ok(Request::Follow(request)) = parsed {
                stream_command(control, request, &mut write, limits.idle_timeout).await?;
                continue;
            }
            let reply = handle_parsed(control, live, parsed).await;
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

/// How long a client waits for each status line of a followed command: several times
/// [`KEEPALIVE`], so only a server that stopped answering runs into it.
pub const STATUS_LINE_TIMEOUT: Duration = Duration::from_secs(60);

/// Sends a [`CommandRequest`] and reads its status lines (blocking; for the CLI): each goes to
/// `on_update`, the last (`done`) is returned. A refusal is a returned status with `ok` false,
/// not an error; errors are a server that cannot be reached or stops answering.
pub fn request_command(
    path: &Path,
    request: &CommandRequest,
    on_update: &mut dyn FnMut(&CommandStatus),
) -> anyhow::Result<CommandStatus> {
    use std::io::{BufRead, Write};
    let mut stream = connect_control(path, STATUS_LINE_TIMEOUT)?;
    let mut value = serde_json::to_value(request)?;
    if let serde_json::Value::Object(object) = &mut value {
        object.insert("request".into(), "command".into());
    }
    let mut line = serde_json::to_string(&value)?;
    line.push('\n');
    stream
        .write_all(line.as_bytes())
        .map_err(|e| anyhow::anyhow!("control socket {}: {e}", path.display()))?;
    let mut reader = std::io::BufReader::new(&stream);
    loop {
        let mut answer = String::new();
        let n = reader.read_line(&mut answer).map_err(|e| {
            anyhow::anyhow!(
                "control socket {}: no status for {} s ({e})",
                path.display(),
                STATUS_LINE_TIMEOUT.as_secs()
            )
        })?;
        if n == 0 {
            anyhow::bail!(
                "control socket {}: closed before the command's last status",
                path.display()
            );
        }
        let reply: ControlReply = serde_json::from_str(&answer)
            .map_err(|e| anyhow::anyhow!("unreadable answer from the server ({e}): {answer:?}"))?;
        let Some(data) = reply.data else {
            // A refusal of the request itself (malformed, too many connections).
            anyhow::bail!("{}", reply.detail);
        };
        let status: CommandStatus = serde_json::from_value(data)
            .map_err(|e| anyhow::anyhow!("unreadable command status from the server ({e})"))?;
        on_update(&status);
        if status.done {
            return Ok(status);
        }
    }
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

/// Connects to the server's control socket at `path`, reads timing out after `timeout`; a
/// socket nobody listens on is one line asking whether `scan3d serve` runs.
fn connect_control(
    path: &Path,
    timeout: std::time::Duration,
) -> anyhow::Result<std::os::unix::net::UnixStream> {
    let stream = std::os::unix::net::UnixStream::connect(path).map_err(|e| {
        anyhow::anyhow!(
            "cannot reach the server's control socket {} ({e}); is `scan3d serve` running with this data_dir?",
            path.display()
        )
    })?;
    stream.set_read_timeout(Some(timeout))?;
    Ok(stream)
}

fn request_with(
    path: &Path,
    request: &impl Serialize,
    timeout: std::time::Duration,
) -> anyhow::Result<ControlReply> {
    use std::io::{BufRead, Write};
    let mut stream = connect_control(path, timeout)?;
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

    fn start_command() -> Command {
        Command::StartStaticScan {
            position: "door".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: None,
        }
    }

    fn reply_event(session_id: u64, command_seq: u64, outcome: CommandOutcome) -> EdgeEvent {
        EdgeEvent::Frame {
            session_id,
            body: CommandReply {
                command_seq,
                t_ns: 1,
                outcome,
            }
            .into(),
        }
    }

    fn scan_event(session_id: u64, message: StaticScan) -> EdgeEvent {
        EdgeEvent::Frame {
            session_id,
            body: message.into(),
        }
    }

    fn finished(scan_id: u32, outcome: scan3d_protocol::StaticScanOutcome) -> StaticScan {
        StaticScan::Finished(scan3d_protocol::StaticScanEnd {
            scan_id,
            t_ns: 9,
            outcome,
            yaw_deg: 180.0,
            revolutions: 100,
            tagged: 1000,
            blocked: 10,
            untrusted: 0,
            late_steps: 1,
            failed_steps: 0,
        })
    }

    #[test]
    fn a_pass_start_is_refused_by_the_server_when_the_hello_lists_no_rplidar() {
        let start = Command::StartPass {
            name: None,
            x_m: 0.0,
            y_m: 0.0,
            heading_deg: 0.0,
        };
        let refusal = pass_refusal("pi", &start, Some(&[SensorId::SWEEP, SensorId::IMU]));
        assert_eq!(
            refusal.map(|e| e.to_string()).as_deref(),
            Some(
                "edge \"pi\" has no RPLidar (its Hello lists: sweep, imu): a trolley pass needs one"
            )
        );
        assert!(
            pass_refusal("pi", &start, Some(&[]))
                .unwrap()
                .to_string()
                .contains("lists: none")
        );
        assert_eq!(pass_refusal("pi", &start, Some(&[SensorId::RPLIDAR])), None);
        // No Hello seen yet: the edge decides; other commands are never refused here.
        assert_eq!(pass_refusal("pi", &start, None), None);
        assert_eq!(pass_refusal("pi", &Command::StopPass, Some(&[])), None);

        // Through EdgeControl: the latest Hello of a connected edge counts.
        let control = EdgeControl::default();
        let _rx = control.register("pi");
        let hello = |sensors: &[SensorId]| {
            let infos = sensors
                .iter()
                .map(|&sensor| scan3d_protocol::SensorInfo {
                    sensor,
                    model: String::new(),
                    firmware: String::new(),
                    serial: String::new(),
                })
                .collect();
            scan3d_protocol::Frame::new(1, 0, scan3d_protocol::Hello::new("pi", "0", infos))
        };
        control.publish("pi", &hello(&[SensorId::SWEEP]));
        assert!(matches!(
            control.send("pi", start.clone()),
            Err(ControlError::NoRplidar { .. })
        ));
        control.publish("pi", &hello(&[SensorId::SWEEP, SensorId::RPLIDAR]));
        assert_eq!(control.send("pi", start.clone()), Ok(()));
        let now = std::time::Instant::now();
        let mut follower = CommandFollower::new("pi", &start, false, FollowTiming::default(), now);
        let status = follower.failed(
            &ControlError::NoRplidar {
                edge: "pi".into(),
                sensors: "sweep".into(),
            },
            now,
        );
        assert!(!status.ok && status.done);
        assert_eq!(
            status.detail,
            "edge \"pi\" has no RPLidar (its Hello lists: sweep): a trolley pass needs one"
        );
    }

    #[test]
    fn a_followed_pass_start_reports_the_edges_marker() {
        let start = Command::StartPass {
            name: None,
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 90.0,
        };
        let now = std::time::Instant::now();
        let mut follower = CommandFollower::new("pi", &start, false, FollowTiming::default(), now);
        let marker = PassMarker {
            t_ns: 77,
            event: PassEvent::Started {
                name: "pass-1".into(),
                x_m: 1.0,
                y_m: 2.0,
                heading_deg: 90.0,
            },
        };
        // The marker comes just before the reply, possibly before the send is known.
        let marker_event = EdgeEvent::Frame {
            session_id: 5,
            body: marker.clone().into(),
        };
        assert_eq!(follower.on_event(&marker_event, now), None);
        assert_eq!(
            follower.on_sent(
                SentCommand {
                    session_id: 5,
                    seq: 3
                },
                now
            ),
            None
        );
        let status = follower
            .on_event(
                &reply_event(5, 3, CommandOutcome::Accepted { scan_id: None }),
                now,
            )
            .unwrap();
        assert!(status.ok && status.done);
        assert_eq!(status.pass, Some(marker));
        assert_eq!(
            status.detail,
            "edge pi started pass \"pass-1\" at x 1 m, y 2 m, heading 90° (edge time 77 ns)"
        );
    }

    #[test]
    fn a_followed_scan_goes_waiting_running_completed_and_ignores_other_commands_replies() {
        let t0 = std::time::Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let mut follower =
            CommandFollower::new("pi", &start_command(), true, FollowTiming::default(), t0);
        // The reply overtakes the connection task's word on where the command went.
        let waiting = reply_event(
            7,
            3,
            CommandOutcome::Waiting {
                reason: "waiting for the Sweep to stream".into(),
            },
        );
        assert_eq!(follower.on_event(&waiting, at(0)), None);
        let status = follower
            .on_sent(
                SentCommand {
                    session_id: 7,
                    seq: 3,
                },
                at(0),
            )
            .unwrap();
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::Waiting, false, true)
        );
        assert_eq!(
            status.detail,
            "edge pi accepted and waits: waiting for the Sweep to stream"
        );
        // Waiting has no reply deadline.
        assert_eq!(follower.on_tick(at(100)), None);
        // Another command's reply, another session's: not ours.
        let other = reply_event(7, 4, CommandOutcome::Accepted { scan_id: Some(5) });
        assert_eq!(follower.on_event(&other, at(1)), None);
        let stale = reply_event(6, 3, CommandOutcome::Accepted { scan_id: Some(5) });
        assert_eq!(follower.on_event(&stale, at(1)), None);
        let accepted = reply_event(7, 3, CommandOutcome::Accepted { scan_id: Some(0) });
        let status = follower.on_event(&accepted, at(101)).unwrap();
        assert_eq!(
            (status.state, status.scan_id),
            (CommandState::Running, Some(0))
        );
        // A disconnection that heals within the grace changes nothing.
        let lost = EdgeEvent::Disconnected {
            reason: "timeout".into(),
        };
        assert_eq!(follower.on_event(&lost, at(102)), None);
        assert_eq!(follower.on_tick(at(110)), None);
        assert_eq!(follower.on_event(&EdgeEvent::Connected, at(111)), None);
        assert_eq!(follower.on_tick(at(200)), None);
        let end = scan_event(
            7,
            finished(0, scan3d_protocol::StaticScanOutcome::Completed),
        );
        let status = follower.on_event(&end, at(201)).unwrap();
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::Completed, true, true)
        );
        let progress = status.progress.unwrap();
        assert_eq!((progress.revolutions, progress.late_steps), (100, 1));
        assert!(status.detail.ends_with("completed"), "{}", status.detail);
    }

    #[test]
    fn refused_stopped_overdue_and_lost_commands_end_not_ok_with_the_reason() {
        let t0 = std::time::Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let sent = SentCommand {
            session_id: 1,
            seq: 0,
        };
        // Refused.
        let mut follower =
            CommandFollower::new("pi", &start_command(), false, FollowTiming::default(), t0);
        follower.on_sent(sent, t0);
        let refused = reply_event(
            1,
            0,
            CommandOutcome::Refused {
                reason: "static scans are off: no [stepper] in edge.toml".into(),
            },
        );
        let status = follower.on_event(&refused, at(1)).unwrap();
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::Refused, true, false)
        );
        assert_eq!(
            status.detail,
            "edge pi refused: static scans are off: no [stepper] in edge.toml"
        );
        // Stopped while followed.
        let mut follower =
            CommandFollower::new("pi", &start_command(), true, FollowTiming::default(), t0);
        follower.on_sent(sent, t0);
        follower.on_event(
            &reply_event(1, 0, CommandOutcome::Accepted { scan_id: Some(2) }),
            t0,
        );
        let end = scan_event(1, finished(2, scan3d_protocol::StaticScanOutcome::Stopped));
        let status = follower.on_event(&end, at(5)).unwrap();
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::Stopped, true, false)
        );
        // No answer: bounded.
        let mut follower = CommandFollower::new(
            "pi",
            &Command::StopStaticScan,
            false,
            FollowTiming::default(),
            t0,
        );
        follower.on_sent(sent, t0);
        assert_eq!(follower.on_tick(at(14)), None);
        let status = follower.on_tick(at(15)).unwrap();
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::Timeout, true, false)
        );
        assert!(
            status
                .detail
                .starts_with("edge pi did not answer: no answer within 15 s"),
            "{}",
            status.detail
        );
        // Lost while running.
        let mut follower =
            CommandFollower::new("pi", &start_command(), true, FollowTiming::default(), t0);
        follower.on_sent(sent, t0);
        follower.on_event(
            &reply_event(1, 0, CommandOutcome::Accepted { scan_id: Some(0) }),
            t0,
        );
        let gone = EdgeEvent::Disconnected {
            reason: "connection lost".into(),
        };
        follower.on_event(&gone, at(10));
        assert_eq!(follower.on_tick(at(39)), None);
        let status = follower.on_tick(at(40)).unwrap();
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::Lost, true, false)
        );
        assert!(
            status.detail.contains("connection lost"),
            "{}",
            status.detail
        );
        // Not connected.
        let mut follower =
            CommandFollower::new("pi", &start_command(), false, FollowTiming::default(), t0);
        let status = follower.failed(
            &EdgeControl::default()
                .submit("pi", start_command())
                .unwrap_err(),
            t0,
        );
        assert_eq!(
            (status.state, status.done, status.ok),
            (CommandState::NotConnected, true, false)
        );
        assert_eq!(
            status.detail,
            "edge \"pi\" is not connected (connected: none)"
        );
    }

    #[tokio::test]
    async fn the_socket_streams_a_commands_status_until_the_edges_answer() {
        let dir = tempfile::tempdir().unwrap();
        let control = EdgeControl::default();
        let mut rx = control.register("pi");
        let (path, server) = start(dir.path(), &control, test_limits()).await;
        // A stand-in for the connection task: says where the command went, and the edge
        // refuses it.
        let edge = control.clone();
        let connection = tokio::spawn(async move {
            let queued = rx.recv().await.unwrap();
            assert_eq!(queued.command, Command::StopStaticScan);
            queued
                .sent
                .unwrap()
                .send(SentCommand {
                    session_id: 9,
                    seq: 4,
                })
                .unwrap();
            let frame = scan3d_protocol::Frame::new(
                9,
                12,
                CommandReply {
                    command_seq: 4,
                    t_ns: 1,
                    outcome: CommandOutcome::Refused {
                        reason: "no static scan is running".into(),
                    },
                },
            );
            edge.publish("pi", &frame);
            rx
        });
        let request = CommandRequest {
            edge: "pi".into(),
            command: Command::StopStaticScan,
            follow: false,
            reply_timeout_s: None,
        };
        let mut updates = Vec::new();
        let last = tokio::task::spawn_blocking(move || {
            let last = request_command(&path, &request, &mut |s| updates.push(s.clone()));
            (last, updates)
        })
        .await
        .unwrap();
        let (last, updates) = last;
        let last = last.unwrap();
        assert_eq!(updates.last(), Some(&last));
        assert_eq!((last.state, last.ok), (CommandState::Refused, false));
        assert_eq!(last.session.as_deref(), Some("0000000000000009"));
        assert_eq!(last.command_seq, Some(4));
        assert_eq!(last.detail, "edge pi refused: no static scan is running");
        let _rx = connection.await.unwrap();
        server.abort();
    }

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
            rx.try_recv().ok().map(|q| q.command),
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
        control.unregister("pi", "test");
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
                    Request::Command(_) | Request::Follow(_) => None,
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
        assert_eq!(
            rx.recv().await.map(|q| q.command),
            Some(Command::StopStaticScan)
        );
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
        assert_eq!(
            rx.try_recv().ok().map(|q| q.command),
            Some(Command::StopStaticScan)
        );
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
        assert_eq!(
            rx.recv().await.map(|q| q.command),
            Some(Command::StopStaticScan)
        );
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
