//! Edge → server uplink on loopback, with everything real: QUIC, mutual TLS 1.3 (rustls/ring)
//! with certificates from the pairing code, the edge's spool, and the server's MCAP recording
//! fsynced to disk every commit.
//!
//! `cargo bench -p scan3d-hw-sim --bench uplink`
//!
//! Prints the numbers issue 3 asks for:
//! 1. uplink throughput: one edge submits realistic revolution frames as fast as its spool
//!    accepts until all of them are acknowledged (= durable on the server): frames/s and MB/s;
//! 2. latency at full sensor rate (RPLidar 5.5 rev/s + Sweep 5 rev/s): submit → recorded and
//!    submit → acknowledged, p50/p99/max;
//! 3. server CPU per edge at full sensor rate for K edges at once, and how many edges one server
//!    core keeps up with.
//!
//! The server (`IngestServer`, via the rig's [`ServerThread`], as `scan3d serve` runs it) lives
//! in a child process — this same binary started with `--serve` — so its CPU time
//! (`CLOCK_PROCESS_CPUTIME_ID`: every thread, including tokio's short-lived blocking threads) is
//! the server's and nothing else's. The simulated edges are the real edge `Uplink` client, one
//! per edge with its own session id and spool, on a tokio runtime in this process; they share one
//! pairing bundle (the server then files all of them under the same edge name, keyed by
//! session). Both processes share the 2 cores of the machine.
//!
//! Frames are synthetic [`LidarRevolution`]s measured in the default conference room by the
//! emulators' own scanners (true ranges plus the sensors' noise models): RPLidar express
//! revolutions of 727 samples (4000 samples/s at 5.5 rev/s, range in mm, quality 47 or 0 for no
//! return, as the driver reports express capsules) and Sweep revolutions of 110 samples (range
//! in cm, signal strength falling with range), with per-sample times spread over the revolution.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use nix::time::{ClockId, clock_gettime};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use scan3d_edge::clock::{MonotonicClock, SharedClock};
use scan3d_edge::uplink::client::{SubmitError, Uplink, UplinkConfig, UplinkHandle, UplinkStats};
use scan3d_edge::uplink::spool::SpoolConfig;
use scan3d_edge::uplink::tls;
use scan3d_hw_sim::mounts;
use scan3d_hw_sim::rig::{self, ServerThread};
use scan3d_hw_sim::rplidar::RplidarEmulator;
use scan3d_hw_sim::sweep::SweepEmulator;
use scan3d_hw_sim::world::{Scanner, World};
use scan3d_protocol::{Frame, LidarRevolution, SensorId, encode};
use scan3d_server::ingest::server::{IngestEvent, IngestStats};
use tokio::runtime::Runtime;
use tokio::sync::{mpsc, watch};

/// The server's commit (chunk + fsync + ack) interval: the default of `deploy/server.toml`.
const COMMIT_INTERVAL: Duration = Duration::from_millis(100);
/// The server's time-sync ping interval: the default of `deploy/server.toml`.
const TIME_SYNC_INTERVAL: Duration = Duration::from_secs(1);
/// Frames per throughput run.
const THROUGHPUT_FRAMES: usize = 20_000;
/// Unacknowledged frames allowed in the "in memory" throughput run (≈ 5.5 MB, below the
/// spool's 8 MiB memory limit, so nothing spills to the edge's disk).
const IN_MEMORY_WINDOW: usize = 1024;
/// How long each full-rate run submits.
const RATE_RUN: Duration = Duration::from_secs(10);
/// Simulated edges per full-rate run; the first run is also the latency run.
const FLEET_SIZES: [usize; 5] = [1, 4, 16, 32, 64];
/// How often the acknowledgement watcher looks at every edge's spool.
const ACK_POLL: Duration = Duration::from_millis(1);
/// How often the driver of a run polls for a condition.
const POLL: Duration = Duration::from_micros(200);
/// Longest wait for connections or for the last acknowledgements.
const WAIT_LIMIT: Duration = Duration::from_secs(30);
/// Command-line flag that turns this binary into the server child.
const SERVE_FLAG: &str = "--serve";

/// Runs the three sections, or serves as the server child when started with `--serve`.
fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if let [_, flag, pki_dir, data_dir] = args.as_slice()
        && flag == SERVE_FLAG
    {
        return serve(Path::new(pki_dir), Path::new(data_dir));
    }
    let bench = Bench::new()?;
    bench.print_environment()?;
    let in_memory = bench.throughput_run("in memory (<= 1024 unacked)", Some(IN_MEMORY_WINDOW))?;
    let backlog = bench.throughput_run("backlog (all queued at once)", None)?;
    print_throughput(&[in_memory, backlog]);
    let mut fleets = Vec::new();
    for edges in FLEET_SIZES {
        fleets.push(bench.rate_run(edges)?);
    }
    print_latency(&fleets[0]);
    print_fleets(&fleets);
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Clocks

/// Reads a POSIX clock in nanoseconds (0 if the kernel refuses, which Linux never does for
/// these clocks).
fn clock_ns(clock: ClockId) -> u64 {
    clock_gettime(clock)
        .map(|t| u64::try_from(Duration::from(t).as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// `CLOCK_MONOTONIC`: one clock for both processes, so the server child can stamp "recorded"
/// on the same time line as the edges' "submitted".
fn mono_ns() -> u64 {
    clock_ns(ClockId::CLOCK_MONOTONIC)
}

/// CPU time of this whole process (all threads, also those that already exited).
fn process_cpu_ns() -> u64 {
    clock_ns(ClockId::CLOCK_PROCESS_CPUTIME_ID)
}

/// Polls `done` every [`POLL`] until it holds; fails after `limit`.
fn wait_until(limit: Duration, what: &str, mut done: impl FnMut() -> bool) -> anyhow::Result<()> {
    let start = Instant::now();
    while !done() {
        if start.elapsed() > limit {
            bail!("timed out after {limit:?} waiting for {what}");
        }
        std::thread::sleep(POLL);
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The server child

/// The server child: serves until its stdin says `stop` (or closes), answering `cpu` with its
/// CPU time; then prints its counters and, for every frame recorded, when it was recorded.
///
/// The recorded time is stamped by a collector thread as the server's `IngestEvent::Frame`
/// arrives (the server emits it right after appending the frame to its recording).
fn serve(pki_dir: &Path, data_dir: &Path) -> anyhow::Result<()> {
    let mut config = rig::ingest_config(pki_dir, data_dir, 0);
    config.commit_interval = COMMIT_INTERVAL;
    config.time_sync_interval = TIME_SYNC_INTERVAL;
    config.max_connections = FLEET_SIZES.iter().copied().max().unwrap_or(1);
    let mut server = ServerThread::start(config)?;
    let events = std::mem::replace(&mut server.events, mpsc::unbounded_channel().1);
    let collector = std::thread::spawn(move || collect_recorded(events));
    let mut out = BufWriter::new(std::io::stdout().lock());
    writeln!(out, "addr {}", server.addr())?;
    out.flush()?;
    for line in std::io::stdin().lock().lines() {
        if line? != "cpu" {
            break;
        }
        writeln!(out, "cpu {}", process_cpu_ns())?;
        out.flush()?;
    }
    let s = server.stop();
    let recorded = collector
        .join()
        .map_err(|_| anyhow!("the event collector panicked"))?;
    writeln!(
        out,
        "stats {} {} {} {} {} {}",
        s.connections, s.refused, s.frames, s.bytes, s.duplicates, s.rejected
    )?;
    for ((session_id, seq), at_ns) in recorded {
        writeln!(out, "frame {session_id} {seq} {at_ns}")?;
    }
    out.flush()?;
    Ok(())
}

/// When each `(session, seq)` was first recorded (`CLOCK_MONOTONIC` ns).
type Recorded = HashMap<(u64, u64), u64>;

/// Stamps every recorded frame until the server drops its event sender.
fn collect_recorded(mut events: mpsc::UnboundedReceiver<IngestEvent>) -> Recorded {
    let mut recorded = Recorded::new();
    while let Some(event) = events.blocking_recv() {
        if let IngestEvent::Frame { frame, .. } = event {
            recorded.insert((frame.session_id, frame.seq), mono_ns());
        }
    }
    recorded
}

/// The parent's side of the server child (line protocol on its stdin/stdout). If the parent
/// gives up early, dropping this closes the child's stdin and the child shuts down by itself.
struct ServerProcess {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    addr: SocketAddr,
}

/// What the server child reports when it stops.
struct ServerReport {
    stats: IngestStats,
    recorded: Recorded,
}

impl ServerProcess {
    /// Starts the child recording under `data_dir` and waits until it listens.
    fn start(pki_dir: &Path, data_dir: &Path) -> anyhow::Result<Self> {
        let mut child = Command::new(std::env::current_exe()?)
            .arg(SERVE_FLAG)
            .arg(pki_dir)
            .arg(data_dir)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .context("cannot start the server child")?;
        let stdin = child.stdin.take().context("no stdin pipe to the server")?;
        let mut stdout = BufReader::new(child.stdout.take().context("no stdout pipe")?);
        let addr = read_reply(&mut stdout, "addr")?.parse()?;
        Ok(Self {
            child,
            stdin,
            stdout,
            addr,
        })
    }

    /// The server's CPU time so far (ns, all its threads).
    fn cpu_ns(&mut self) -> anyhow::Result<u64> {
        writeln!(self.stdin, "cpu")?;
        self.stdin.flush()?;
        Ok(read_reply(&mut self.stdout, "cpu")?.parse()?)
    }

    /// Shuts the server down cleanly (final commit, recordings closed) and collects its report.
    fn stop(mut self) -> anyhow::Result<ServerReport> {
        writeln!(self.stdin, "stop")?;
        self.stdin.flush()?;
        let counters: Vec<u64> = read_reply(&mut self.stdout, "stats")?
            .split(' ')
            .map(str::parse)
            .collect::<Result<_, _>>()?;
        let &[connections, refused, frames, bytes, duplicates, rejected] = counters.as_slice()
        else {
            bail!(
                "the server reported {} counters, expected 6",
                counters.len()
            );
        };
        let mut recorded = Recorded::new();
        for line in self.stdout.lines() {
            let line = line?;
            let numbers: Vec<u64> = line
                .strip_prefix("frame ")
                .with_context(|| format!("unexpected line from the server: {line}"))?
                .split(' ')
                .map(str::parse)
                .collect::<Result<_, _>>()?;
            let &[session_id, seq, at_ns] = numbers.as_slice() else {
                bail!("malformed frame line from the server: {line}");
            };
            recorded.insert((session_id, seq), at_ns);
        }
        let status = self.child.wait()?;
        if !status.success() {
            bail!("the server child failed: {status}");
        }
        Ok(ServerReport {
            stats: IngestStats {
                connections,
                refused,
                frames,
                bytes,
                duplicates,
                rejected,
                ..IngestStats::default()
            },
            recorded,
        })
    }
}

/// Reads one `KEY value` line from the server child and returns the value.
fn read_reply(stdout: &mut impl BufRead, key: &str) -> anyhow::Result<String> {
    let mut line = String::new();
    if stdout.read_line(&mut line)? == 0 {
        bail!("the server child exited before answering `{key}`");
    }
    line.trim_end()
        .strip_prefix(key)
        .and_then(|rest| rest.strip_prefix(' '))
        .map(str::to_owned)
        .with_context(|| format!("expected `{key} …` from the server, got {line:?}"))
}

// ---------------------------------------------------------------------------------------------
// Synthetic revolutions

/// How a lidar model reports a beam.
#[derive(Debug, Clone, Copy)]
enum Model {
    /// RPLidar A1 express scan: clockwise angles, mm ranges, fixed quality 47.
    RplidarExpress,
    /// Scanse Sweep: counter-clockwise angles, cm ranges, signal strength 0–255.
    Sweep,
}

impl Model {
    /// The scanner's azimuth (counter-clockwise, radians) of a reported angle.
    fn azimuth_rad(self, angle_deg: f64) -> f64 {
        match self {
            Model::RplidarExpress => -angle_deg.to_radians(),
            Model::Sweep => angle_deg.to_radians(),
        }
    }

    /// The reported range and quality of a measured range (`None`: no return).
    fn report(self, range_m: Option<f64>, rng: &mut impl Rng) -> (f32, u8) {
        let Some(range) = range_m else {
            return (0.0, 0);
        };
        match self {
            Model::RplidarExpress => (((range * 1000.0).round() / 1000.0) as f32, 47),
            Model::Sweep => {
                let strength = 250.0 - 12.0 * range + rng.random_range(-15.0..15.0);
                (
                    ((range * 100.0).round() / 100.0) as f32,
                    strength.clamp(1.0, 255.0) as u8,
                )
            }
        }
    }
}

/// One lidar's frame stream: its rate and a pool of distinct revolutions to restamp.
#[derive(Clone)]
struct LidarStream {
    name: &'static str,
    hz: f64,
    samples: usize,
    templates: Arc<[LidarRevolution]>,
}

impl LidarStream {
    /// Distinct revolutions in each pool (different start angles and noise).
    const POOL: usize = 16;

    /// RPLidar A1 express: 4000 samples/s at 5.5 rev/s.
    fn rplidar(world: &Arc<World>) -> anyhow::Result<Self> {
        let scanner = RplidarEmulator::default_scanner(world.clone(), mounts::rplidar());
        Self::synthesize(
            "RPLidar",
            SensorId::RPLIDAR,
            Model::RplidarExpress,
            5.5,
            727,
            &scanner,
        )
    }

    /// Scanse Sweep at 5 rev/s.
    fn sweep(world: &Arc<World>) -> anyhow::Result<Self> {
        let scanner = SweepEmulator::default_scanner(world.clone(), mounts::sweep());
        Self::synthesize("Sweep", SensorId::SWEEP, Model::Sweep, 5.0, 110, &scanner)
    }

    /// A pool of revolutions of `samples` beams each, measured by `scanner` as `model` reports.
    fn synthesize(
        name: &'static str,
        sensor: SensorId,
        model: Model,
        hz: f64,
        samples: usize,
        scanner: &Scanner,
    ) -> anyhow::Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(u64::from(sensor.0));
        let jitter = Normal::new(0.0, 0.05)?;
        let period_ns = 1e9 / hz;
        let step_deg = 360.0 / samples as f64;
        let mut templates = Vec::with_capacity(Self::POOL);
        for _ in 0..Self::POOL {
            let mut revolution = LidarRevolution::new(sensor, 0, period_ns as u64);
            let start_deg = rng.random_range(0.0..step_deg);
            for i in 0..samples {
                let angle =
                    (start_deg + i as f64 * step_deg + jitter.sample(&mut rng)).rem_euclid(360.0);
                let measured = scanner.measure(model.azimuth_rad(angle), &mut rng);
                let (range_m, quality) = model.report(measured, &mut rng);
                let t_ns = (i as f64 * period_ns / samples as f64) as u64;
                revolution.push(angle as f32, range_m, quality, t_ns)?;
            }
            templates.push(revolution);
        }
        Ok(Self {
            name,
            hz,
            samples,
            templates: templates.into(),
        })
    }

    /// Time between revolutions.
    fn period(&self) -> Duration {
        Duration::from_secs_f64(1.0 / self.hz)
    }

    /// The `index`th revolution of the stream, ending at `end_ns` on the edge clock.
    fn revolution(&self, index: usize, end_ns: u64) -> LidarRevolution {
        let mut revolution = self.templates[index % self.templates.len()].clone();
        let span = revolution.t1_ns - revolution.t0_ns;
        revolution.t1_ns = end_ns.max(span);
        revolution.t0_ns = revolution.t1_ns - span;
        revolution
    }

    /// Average encoded frame size in bytes (header included).
    fn frame_bytes(&self) -> anyhow::Result<f64> {
        let mut total = 0;
        for (seq, revolution) in self.templates.iter().enumerate() {
            total += encode(&Frame::new(u64::MAX, seq as u64, revolution.clone()))?.len();
        }
        Ok(total as f64 / self.templates.len() as f64)
    }
}

// ---------------------------------------------------------------------------------------------
// Simulated edges

/// A frame an edge submitted: its sequence number and when (`CLOCK_MONOTONIC` ns).
#[derive(Debug, Clone, Copy)]
struct Submission {
    seq: u64,
    at_ns: u64,
}

/// The producers' view of one simulated edge; cheap to clone.
#[derive(Clone)]
struct EdgeHandle {
    session_id: u64,
    uplink: UplinkHandle,
    clock: SharedClock,
}

impl EdgeHandle {
    /// Submits the `index`th revolution of `stream`, stamped now.
    fn submit(&self, stream: &LidarStream, index: usize) -> Result<Submission, SubmitError> {
        let revolution = stream.revolution(index, self.clock.now_ns());
        let at_ns = mono_ns();
        let seq = self.uplink.submit(revolution)?;
        Ok(Submission { seq, at_ns })
    }

    /// Every frame with a sequence number below this is acknowledged.
    ///
    /// The spool drops a frame exactly when the server's acknowledgement for it arrives, and
    /// the server acknowledges contiguous prefixes (`Ack::UpTo`), so `submitted − pending` is
    /// the acknowledged prefix. Reading `submitted` before `pending` (and the uplink counting a
    /// submission only after spooling it) can only make the result too small, never too large.
    fn acked_prefix(&self) -> u64 {
        let submitted = self.uplink.stats().submitted;
        submitted.saturating_sub(self.uplink.pending() as u64)
    }
}

/// One simulated edge: the real uplink client with its own spool and session.
struct SimEdge {
    handle: EdgeHandle,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<UplinkStats>,
}

impl SimEdge {
    /// Starts an uplink to `server` with the pairing bundle in `bundle`.
    fn start(
        runtime: &Runtime,
        server: SocketAddr,
        bundle: &Path,
        spool_dir: PathBuf,
        session_id: u64,
    ) -> anyhow::Result<Self> {
        let section = rig::uplink_section(server, bundle);
        let mut spool = SpoolConfig::new(spool_dir);
        spool.memory_limit_bytes = usize::try_from(section.spool_memory_mb << 20)?;
        spool.disk_limit_bytes = section.spool_disk_mb << 20;
        let config = UplinkConfig::new(
            section.server.clone(),
            section.tls_name().to_owned(),
            tls::client_config(&section.pki_dir)?,
            spool,
        );
        let clock: SharedClock = Arc::new(MonotonicClock::new());
        // This benchmark's edges act on no server command: the receiver is dropped.
        let (uplink, handle, _commands) = Uplink::new(config, clock.clone(), session_id)?;
        let (stop, stopped) = watch::channel(false);
        let task = runtime.spawn(uplink.run(stopped));
        Ok(Self {
            handle: EdgeHandle {
                session_id,
                uplink: handle,
                clock,
            },
            stop,
            task,
        })
    }
}

/// A server child and `K` edges connected to it, for one run.
struct Fleet {
    server: ServerProcess,
    edges: Vec<SimEdge>,
}

/// CPU time of the server child and of this process (the edges) at one instant.
#[derive(Debug, Clone, Copy)]
struct CpuMark {
    at: Instant,
    server_ns: u64,
    edges_ns: u64,
}

/// CPU shares of one core over a window.
#[derive(Debug, Clone, Copy)]
struct CpuShare {
    server: f64,
    edges: f64,
}

impl Fleet {
    /// Starts a server recording under `dir/data` and `edges` uplinks, and waits until all are
    /// connected.
    fn start(bench: &Bench, dir: &Path, edges: usize) -> anyhow::Result<Self> {
        let server = ServerProcess::start(&bench.pki_dir, &dir.join("data"))?;
        let edges = (0..edges)
            .map(|i| {
                let spool = dir.join(format!("edge-{i}"));
                SimEdge::start(
                    &bench.runtime,
                    server.addr,
                    &bench.bundle,
                    spool,
                    i as u64 + 1,
                )
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        wait_until(WAIT_LIMIT, "every edge to connect", || {
            edges
                .iter()
                .all(|e| e.handle.uplink.stats().connections > 0)
        })?;
        Ok(Self { server, edges })
    }

    /// The producers' handles of every edge, in edge order.
    fn handles(&self) -> Vec<EdgeHandle> {
        self.edges.iter().map(|e| e.handle.clone()).collect()
    }

    /// CPU times of the server and of this process, now.
    fn cpu_mark(&mut self) -> anyhow::Result<CpuMark> {
        Ok(CpuMark {
            at: Instant::now(),
            server_ns: self.server.cpu_ns()?,
            edges_ns: process_cpu_ns(),
        })
    }

    /// CPU shares of one core since `start`, and the wall time.
    fn cpu_since(&mut self, start: CpuMark) -> anyhow::Result<(CpuShare, Duration)> {
        let end = self.cpu_mark()?;
        let wall = end.at - start.at;
        let share = |ns: u64| ns as f64 / wall.as_nanos() as f64;
        let cpu = CpuShare {
            server: share(end.server_ns.saturating_sub(start.server_ns)),
            edges: share(end.edges_ns.saturating_sub(start.edges_ns)),
        };
        Ok((cpu, wall))
    }

    /// Stops the edges (after their last acknowledgement), then the server.
    fn stop(self, runtime: &Runtime) -> anyhow::Result<ServerReport> {
        for edge in self.edges {
            let _ = edge.stop.send(true);
            runtime.block_on(edge.task)?;
        }
        self.server.stop()
    }
}

/// Per frame of `submissions` (of edge `session_id`): the latency to when it was recorded, in
/// ms, or `None` if it never was.
fn recorded_latencies(
    report: &ServerReport,
    session_id: u64,
    submissions: &[Submission],
) -> Vec<Option<f64>> {
    submissions
        .iter()
        .map(|s| {
            report
                .recorded
                .get(&(session_id, s.seq))
                .map(|&at| ms_between(s.at_ns, at))
        })
        .collect()
}

/// Milliseconds from `from_ns` to `to_ns` (0 if the clock readings cross).
fn ms_between(from_ns: u64, to_ns: u64) -> f64 {
    to_ns.saturating_sub(from_ns) as f64 / 1e6
}

// ---------------------------------------------------------------------------------------------
// Runs

/// Everything shared by the runs: the work directory, the PKI, the edges' runtime, the streams.
struct Bench {
    work: WorkDir,
    pki_dir: PathBuf,
    bundle: PathBuf,
    runtime: Runtime,
    streams: [LidarStream; 2],
    runs: std::cell::Cell<usize>,
}

/// A temporary directory on disk, removed when dropped.
struct WorkDir(PathBuf);

impl Drop for WorkDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Result of one throughput run.
struct ThroughputRun {
    mode: &'static str,
    frames: usize,
    wall: Duration,
    bytes: u64,
    cpu: CpuShare,
    spool_full: u64,
    missing: usize,
}

/// Result of one full-rate run.
struct RateRun {
    edges: usize,
    wall: Duration,
    frames: usize,
    refused: u64,
    cpu: CpuShare,
    recorded_ms: Vec<f64>,
    acked_ms: Vec<f64>,
    not_recorded: usize,
    not_acked: usize,
    stats: IngestStats,
}

impl RateRun {
    /// Every frame taken by the spool, recorded and acknowledged.
    fn kept_up(&self) -> bool {
        self.refused == 0 && self.not_recorded == 0 && self.not_acked == 0
    }

    /// Adds one edge's frames: when the server recorded each, and when the edge's
    /// acknowledgement `timeline` (from [`watch_acks`]) first went past it.
    fn add_edge(
        &mut self,
        report: &ServerReport,
        session_id: u64,
        produced: &Produced,
        timeline: &[(u64, u64)],
    ) {
        self.frames += produced.submissions.len();
        self.refused += produced.refused;
        for latency in recorded_latencies(report, session_id, &produced.submissions) {
            match latency {
                Some(ms) => self.recorded_ms.push(ms),
                None => self.not_recorded += 1,
            }
        }
        for s in &produced.submissions {
            let first_past = timeline.partition_point(|&(prefix, _)| prefix <= s.seq);
            match timeline.get(first_past) {
                Some(&(_, at_ns)) => self.acked_ms.push(ms_between(s.at_ns, at_ns)),
                None => self.not_acked += 1,
            }
        }
    }
}

impl Bench {
    /// Pairs certificates in a fresh work directory and synthesizes the frame pools.
    fn new() -> anyhow::Result<Self> {
        let work = WorkDir(
            std::env::temp_dir().join(format!("scan3d-bench-uplink-{}", std::process::id())),
        );
        let pki_dir = work.0.join("pki");
        let bundle = rig::pair_certificates(&pki_dir)?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("sim-edges")
            .enable_all()
            .build()?;
        let world = Arc::new(World::conference_room());
        Ok(Self {
            streams: [LidarStream::rplidar(&world)?, LidarStream::sweep(&world)?],
            work,
            pki_dir,
            bundle,
            runtime,
            runs: std::cell::Cell::new(0),
        })
    }

    /// A fresh directory for the next run.
    fn run_dir(&self) -> PathBuf {
        let n = self.runs.get();
        self.runs.set(n + 1);
        self.work.0.join(format!("run-{n}"))
    }

    /// Prints what the numbers were measured on.
    fn print_environment(&self) -> anyhow::Result<()> {
        let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
        println!("scan3d uplink benchmark");
        println!(
            "  machine  {cores} cores, shared by the server child and the simulated edges (numbers include that contention)"
        );
        println!(
            "  network  loopback 127.0.0.1, real QUIC + mutual TLS 1.3 (rustls/ring), certificates from `scan3d pair` code"
        );
        println!(
            "  server   IngestServer in its own process, 2 tokio workers; MCAP chunks fsynced to {} ({}),",
            self.work.0.display(),
            filesystem(&self.work.0)
        );
        println!(
            "           commit_interval {} ms and time sync every {} s as in deploy/server.toml",
            COMMIT_INTERVAL.as_millis(),
            TIME_SYNC_INTERVAL.as_secs()
        );
        println!(
            "  edges    the real edge Uplink client, own spool (8 MiB memory, 256 MiB disk) and session each"
        );
        for stream in &self.streams {
            println!(
                "  frames   {:<8} revolution: {} samples, {:.0} B encoded on average, {} rev/s",
                stream.name,
                stream.samples,
                stream.frame_bytes()?,
                stream.hz
            );
        }
        println!();
        Ok(())
    }

    /// One edge submits [`THROUGHPUT_FRAMES`] frames (RPLidar and Sweep alternating) as fast as
    /// its spool takes them — with at most `window` unacknowledged if given — until all are
    /// acknowledged.
    fn throughput_run(
        &self,
        mode: &'static str,
        window: Option<usize>,
    ) -> anyhow::Result<ThroughputRun> {
        let mut fleet = Fleet::start(self, &self.run_dir(), 1)?;
        let edge = fleet.edges[0].handle.clone();
        let start = fleet.cpu_mark()?;
        let mut submissions = Vec::with_capacity(THROUGHPUT_FRAMES);
        let mut spool_full = 0;
        for i in 0..THROUGHPUT_FRAMES {
            let stream = &self.streams[i % 2];
            if let Some(window) = window {
                wait_until(WAIT_LIMIT, "acknowledgements", || {
                    edge.uplink.pending() < window
                })?;
            }
            let submission = loop {
                match edge.submit(stream, i / 2) {
                    Ok(submission) => break submission,
                    Err(SubmitError::Full) => {
                        spool_full += 1;
                        wait_until(WAIT_LIMIT, "room in the spool", || edge.uplink.has_room())?;
                    }
                    Err(e) => return Err(e.into()),
                }
            };
            submissions.push(submission);
        }
        let last = submissions.last().map_or(0, |s| s.seq);
        wait_until(WAIT_LIMIT, "the last acknowledgement", || {
            edge.acked_prefix() > last
        })?;
        let (cpu, wall) = fleet.cpu_since(start)?;
        let report = fleet.stop(&self.runtime)?;
        let missing = recorded_latencies(&report, edge.session_id, &submissions)
            .iter()
            .filter(|l| l.is_none())
            .count();
        Ok(ThroughputRun {
            mode,
            frames: THROUGHPUT_FRAMES,
            wall,
            bytes: report.stats.bytes,
            cpu,
            spool_full,
            missing,
        })
    }

    /// `edges` edges stream both lidars at their real rates for [`RATE_RUN`].
    fn rate_run(&self, edges: usize) -> anyhow::Result<RateRun> {
        let mut fleet = Fleet::start(self, &self.run_dir(), edges)?;
        let handles = fleet.handles();
        let (stop_watch, watch_stopped) = watch::channel(false);
        let watcher = self
            .runtime
            .spawn(watch_acks(handles.clone(), watch_stopped));
        let start = fleet.cpu_mark()?;
        let begin = tokio::time::Instant::from_std(start.at);
        let deadline = begin + RATE_RUN;
        let producers: Vec<_> = handles
            .iter()
            .enumerate()
            .flat_map(|(i, edge)| {
                // Real edges are not in step: each lidar starts at a random phase.
                let mut rng = ChaCha8Rng::seed_from_u64(i as u64);
                self.streams.iter().map(move |stream| {
                    let phase = stream.period().mul_f64(rng.random_range(0.0..1.0));
                    (edge.clone(), stream.clone(), phase)
                })
            })
            .map(|(edge, stream, phase)| {
                self.runtime
                    .spawn(produce(edge, stream, begin + phase, deadline))
            })
            .collect();
        let mut per_edge: Vec<Produced> = (0..edges).map(|_| Produced::default()).collect();
        for (i, producer) in producers.into_iter().enumerate() {
            let produced = self.runtime.block_on(producer)?;
            let edge = &mut per_edge[i / self.streams.len()];
            edge.submissions.extend(produced.submissions);
            edge.refused += produced.refused;
        }
        let (cpu, wall) = fleet.cpu_since(start)?;
        // Wait for the last acknowledgements; a server that fell behind shows up as unacked.
        let all_acked = wait_until(WAIT_LIMIT, "the last acknowledgements", || {
            handles.iter().zip(&per_edge).all(|(edge, produced)| {
                let last = produced.submissions.iter().map(|s| s.seq).max();
                last.is_none_or(|last| edge.acked_prefix() > last)
            })
        });
        if let Err(e) = all_acked {
            eprintln!("{edges} edges: {e}");
        }
        let _ = stop_watch.send(true);
        let timelines = self.runtime.block_on(watcher)?;
        let report = fleet.stop(&self.runtime)?;
        let mut run = RateRun {
            edges,
            wall,
            frames: 0,
            refused: 0,
            cpu,
            recorded_ms: Vec::new(),
            acked_ms: Vec::new(),
            not_recorded: 0,
            not_acked: 0,
            stats: report.stats,
        };
        for ((edge, produced), timeline) in handles.iter().zip(&per_edge).zip(&timelines) {
            run.add_edge(&report, edge.session_id, produced, timeline);
        }
        run.recorded_ms.sort_by(f64::total_cmp);
        run.acked_ms.sort_by(f64::total_cmp);
        Ok(run)
    }
}

/// What one producer submitted.
#[derive(Default)]
struct Produced {
    submissions: Vec<Submission>,
    /// Frames the spool refused (the server did not keep up).
    refused: u64,
}

/// Submits one revolution of `stream` per period from `first` until `deadline`, as the edge's
/// acquisition does when a revolution completes.
async fn produce(
    edge: EdgeHandle,
    stream: LidarStream,
    first: tokio::time::Instant,
    deadline: tokio::time::Instant,
) -> Produced {
    let mut tick = tokio::time::interval_at(first, stream.period());
    let mut produced = Produced::default();
    for index in 0.. {
        if tick.tick().await >= deadline {
            break;
        }
        match edge.submit(&stream, index) {
            Ok(submission) => produced.submissions.push(submission),
            Err(_) => produced.refused += 1,
        }
    }
    produced
}

/// Per edge, the times at which its acknowledged prefix grew: `(prefix, CLOCK_MONOTONIC ns)`,
/// polled every [`ACK_POLL`] until `stop` (so acknowledgement times are late by up to a poll).
async fn watch_acks(
    edges: Vec<EdgeHandle>,
    mut stop: watch::Receiver<bool>,
) -> Vec<Vec<(u64, u64)>> {
    let mut timelines: Vec<Vec<(u64, u64)>> = vec![Vec::new(); edges.len()];
    let mut tick = tokio::time::interval(ACK_POLL);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.changed() => return timelines,
        }
        let now = mono_ns();
        for (edge, timeline) in edges.iter().zip(&mut timelines) {
            let prefix = edge.acked_prefix();
            if timeline.last().is_none_or(|&(last, _)| prefix > last) {
                timeline.push((prefix, now));
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Report

/// The file system type of `path`, to tell whether fsync is real.
fn filesystem(path: &Path) -> &'static str {
    use nix::sys::statfs::{
        BTRFS_SUPER_MAGIC, EXT4_SUPER_MAGIC, OVERLAYFS_SUPER_MAGIC, TMPFS_MAGIC, XFS_SUPER_MAGIC,
        statfs,
    };
    let Ok(stat) = statfs(path) else {
        return "file system unknown";
    };
    match stat.filesystem_type() {
        EXT4_SUPER_MAGIC => "ext2/3/4 on a block device",
        XFS_SUPER_MAGIC => "xfs",
        BTRFS_SUPER_MAGIC => "btrfs",
        OVERLAYFS_SUPER_MAGIC => "overlayfs",
        TMPFS_MAGIC => "tmpfs: fsync costs nothing here!",
        _ => "other file system",
    }
}

/// The `q` quantile (nearest rank) of sorted values, in ms.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (q * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// A share of one core as a percentage.
fn percent(share: f64) -> String {
    format!("{:.1} %", share * 100.0)
}

/// Section 1: the throughput table.
fn print_throughput(runs: &[ThroughputRun]) {
    println!(
        "1. Uplink throughput: 1 edge, {THROUGHPUT_FRAMES} frames (RPLidar/Sweep alternating), submitted as fast as the spool"
    );
    println!("   takes them, timed from the first submit until the last is acknowledged (durable)");
    println!(
        "   {:<30} {:>8} {:>9} {:>7} {:>11} {:>10} {:>11} {:>9}",
        "mode", "seconds", "frames/s", "MB/s", "server CPU", "edge CPU", "spool full", "missing"
    );
    for run in runs {
        let secs = run.wall.as_secs_f64();
        println!(
            "   {:<30} {:>8.2} {:>9.0} {:>7.1} {:>11} {:>10} {:>11} {:>9}",
            run.mode,
            secs,
            run.frames as f64 / secs,
            run.bytes as f64 / secs / 1e6,
            percent(run.cpu.server),
            percent(run.cpu.edges),
            run.spool_full,
            run.missing
        );
    }
    println!(
        "   (MB/s: frame bytes the server recorded, 1 MB = 10^6 B; CPU in % of one core; \"backlog\" spills to the edge's disk spool)"
    );
    println!();
}

/// Section 2: latency of one edge at full sensor rate.
fn print_latency(run: &RateRun) {
    println!(
        "2. Latency at full sensor rate: 1 edge, RPLidar 5.5 rev/s + Sweep 5 rev/s for {} s, {} frames",
        RATE_RUN.as_secs(),
        run.frames
    );
    println!(
        "   {:<34} {:>8} {:>8} {:>8}",
        "", "p50 ms", "p99 ms", "max ms"
    );
    for (name, sorted) in [
        ("submit -> recorded by the server", &run.recorded_ms),
        ("submit -> acknowledged (durable)", &run.acked_ms),
    ] {
        println!(
            "   {:<34} {:>8.1} {:>8.1} {:>8.1}",
            name,
            quantile(sorted, 0.5),
            quantile(sorted, 0.99),
            quantile(sorted, 1.0)
        );
    }
    println!(
        "   recorded: stamped in the server process as its recorder takes the frame; acknowledged: the edge's spool"
    );
    println!(
        "   drops the frame (acked prefix = submitted - pending, polled every {} ms); commit_interval {} ms bounds the wait",
        ACK_POLL.as_millis(),
        COMMIT_INTERVAL.as_millis()
    );
    println!(
        "   (the Sweep's 200 ms period is a multiple of the commit interval, so its frames keep one phase to the"
    );
    println!("   commit tick: p50 depends on that phase, p99 and max on the interval)");
    println!();
}

/// Section 3: server CPU per edge and edges per core, with the keep-up verdicts.
fn print_fleets(runs: &[RateRun]) {
    println!(
        "3. Server CPU at full sensor rate: K edges at once, each RPLidar 5.5 rev/s + Sweep 5 rev/s, {} s per row",
        RATE_RUN.as_secs()
    );
    println!(
        "   {:>5} {:>7} {:>9} {:>11} {:>9} {:>10} {:>10} {:>8} {:>8} {:>8} {:>8}",
        "K",
        "frames",
        "frames/s",
        "server CPU",
        "per edge",
        "edges/core",
        "edges CPU",
        "rec p99",
        "ack p50",
        "ack p99",
        "ack max"
    );
    for run in runs {
        let edges_per_core = run.edges as f64 / run.cpu.server;
        println!(
            "   {:>5} {:>7} {:>9.0} {:>11} {:>9} {:>10.0} {:>10} {:>8.1} {:>8.1} {:>8.1} {:>8.1}",
            run.edges,
            run.frames,
            run.frames as f64 / run.wall.as_secs_f64(),
            percent(run.cpu.server),
            format!("{:.2} %", run.cpu.server * 100.0 / run.edges as f64),
            edges_per_core,
            percent(run.cpu.edges),
            quantile(&run.recorded_ms, 0.99),
            quantile(&run.acked_ms, 0.5),
            quantile(&run.acked_ms, 0.99),
            quantile(&run.acked_ms, 1.0),
        );
    }
    println!(
        "   (CPU in % of one core over the submitting window; edges/core = K / server CPU share, extrapolated;"
    );
    println!("    latencies in ms; edges CPU = this process: K uplink clients and the producers)");
    for run in runs {
        let verdict = if run.kept_up() {
            "kept up: every frame recorded and acknowledged".to_owned()
        } else {
            format!(
                "FELL BEHIND: {} refused by a full spool, {} not recorded, {} not acknowledged",
                run.refused, run.not_recorded, run.not_acked
            )
        };
        println!(
            "   K={:<3} {verdict} (server: {} frames, {} duplicates, {} rejected)",
            run.edges, run.stats.frames, run.stats.duplicates, run.stats.rejected
        );
    }
    if let Some(largest) = runs.last() {
        let bound = 3 * COMMIT_INTERVAL;
        let max_ms = quantile(&largest.acked_ms, 1.0);
        let bounded = largest.kept_up() && max_ms <= bound.as_secs_f64() * 1e3;
        println!(
            "   => one server core keeps up with about {:.0} edges at full sensor rate (extrapolated from K={});",
            largest.edges as f64 / largest.cpu.server,
            largest.edges
        );
        println!(
            "      latency at K={} {} (ack max {:.1} ms vs {} ms = 3 x commit_interval)",
            largest.edges,
            if bounded {
                "stayed bounded"
            } else {
                "was NOT bounded"
            },
            max_ms,
            bound.as_millis()
        );
    }
}
