//! Edge → server uplink on loopback, with everything real: QUIC, mutual TLS 1.3 (rustls/ring)
//! with certificates from the pairing code, the edge's spool, and the server's MCAP recording
//! fsynced to disk every commit.
//!
//! `cargo bench -p scan3d-hw-sim --bench uplink` (`UPLINK_BENCH_EDGES=1,16` picks the fleet
//! sizes; default 1, 4, 8, 16, 24, 32, 48, 64; `UPLINK_BENCH_PIPELINE=1` runs the server with
//! its live mapping pipeline on, `[pipeline]` defaults, and every edge making static scans
//! back to back on its Sweep: 18 steps of 10°, its revolutions tagged with their yaws, so the
//! server assembles and inserts 3D points as for a real turntable)
//!
//! Prints:
//! 1. uplink throughput: one edge submits realistic revolution frames as fast as its spool
//!    accepts until all of them are acknowledged (= durable on the server): frames/s and MB/s;
//! 2. latency at full sensor rate (RPLidar 5.5 rev/s + Sweep 5 rev/s): submit → recorded and
//!    submit → acknowledged, p50/p99/max;
//! 3. K edges at once at full sensor rate: per K, frames sent, recorded and acknowledged, ack
//!    latency p50/p99/max, server CPU and the server's resident memory (RSS at the end of the
//!    row, and its peak so far); then the largest K measured at which every frame was
//!    recorded and acknowledged with ack p99 ≤ 3 × the commit interval. Only measured fleet
//!    sizes are reported: nothing is extrapolated.
//!
//! The server (`IngestServer`, via the rig's [`ServerThread`], as `scan3d serve` runs it) lives
//! in a child process — this same binary started with `--serve` — so its CPU time
//! (`CLOCK_PROCESS_CPUTIME_ID`: every thread, including tokio's short-lived blocking threads) is
//! the server's and nothing else's. The simulated edges are the synthetic edges of
//! [`scan3d_hw_sim::fleet`]: the real edge `Uplink` client, each with its own pairing bundle
//! (issued here by the code behind `scan3d pair`, so each is a distinct edge name on the server),
//! its own session and spool, on a tokio runtime in this process. Both processes share the
//! machine's cores with whatever else runs: the load average is printed next to the numbers.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use nix::time::ClockId;
use scan3d_edge::uplink::client::SubmitError;
use scan3d_hw_sim::fleet::{
    self, EdgeHandle, EdgeIdentity, LidarStream, Produced, Producers, SimEdge, StaticScanPlan,
    Submission, clock_ns, mono_ns,
};
use scan3d_hw_sim::installation::{self, ServerThread};
use scan3d_hw_sim::world::World;
use scan3d_server::ingest::server::{IngestEvent, IngestStats};
use scan3d_server::pipeline::PipelineSettings;
use scan3d_server::pipeline::live::LiveSettings;
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
/// Simulated edges per full-rate run when `UPLINK_BENCH_EDGES` does not say; the first run is
/// also the latency run.
const FLEET_SIZES: [usize; 8] = [1, 4, 8, 16, 24, 32, 48, 64];
/// Environment variable with comma-separated fleet sizes to run instead of [`FLEET_SIZES`].
const FLEET_SIZES_VAR: &str = "UPLINK_BENCH_EDGES";
/// Largest fleet the server child admits (`max_connections`) and pairing prepares.
const MAX_FLEET: usize = 256;
/// How often the acknowledgement watcher looks at every edge's spool.
const ACK_POLL: Duration = Duration::from_millis(1);
/// How often the driver of a run polls for a condition.
const POLL: Duration = Duration::from_micros(200);
/// Longest wait for connections or for the last acknowledgements.
const WAIT_LIMIT: Duration = Duration::from_secs(30);
/// Command-line flag that turns this binary into the server child.
const SERVE_FLAG: &str = "--serve";
/// Environment variable that turns the server's live pipeline and the edges' static scans on.
const PIPELINE_VAR: &str = "UPLINK_BENCH_PIPELINE";
/// Turntable steps per synthetic static scan in pipeline mode (180° in 10° steps).
const STATIC_SCAN_STEPS: u32 = 18;

/// Whether this run has the pipeline on ([`PIPELINE_VAR`]; the server child inherits it).
fn pipeline_on() -> bool {
    std::env::var(PIPELINE_VAR).is_ok_and(|v| v == "1")
}

/// This process's resident set size now and at its peak (kB, from /proc; 0 if unreadable).
fn rss_kb() -> (u64, u64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// The acknowledgement p99 a fleet must stay within to count as kept up.
const ACK_P99_BOUND: Duration = COMMIT_INTERVAL.saturating_mul(3);

/// Runs the three sections, or serves as the server child when started with `--serve`.
fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if let [_, flag, pki_dir, data_dir] = args.as_slice()
        && flag == SERVE_FLAG
    {
        return serve(Path::new(pki_dir), Path::new(data_dir));
    }
    let sizes = fleet_sizes()?;
    let bench = Bench::new(sizes.iter().copied().max().unwrap_or(1))?;
    bench.print_environment()?;
    let in_memory = bench.throughput_run("in memory (<= 1024 unacked)", Some(IN_MEMORY_WINDOW))?;
    let backlog = bench.throughput_run("backlog (all queued at once)", None)?;
    print_throughput(&[in_memory, backlog]);
    let mut fleets = Vec::new();
    for edges in sizes {
        match bench.rate_run(edges) {
            Ok(run) => fleets.push(run),
            // A fleet that cannot even connect is reported, and larger ones are not tried.
            Err(e) => {
                println!("   K={edges}: run failed: {e:#}");
                break;
            }
        }
    }
    if let Some(first) = fleets.first() {
        print_latency(first);
    }
    print_fleets(&fleets);
    Ok(())
}

/// The fleet sizes to run: [`FLEET_SIZES_VAR`] if set, else [`FLEET_SIZES`].
fn fleet_sizes() -> anyhow::Result<Vec<usize>> {
    let Ok(list) = std::env::var(FLEET_SIZES_VAR) else {
        return Ok(FLEET_SIZES.to_vec());
    };
    let sizes = list
        .split(',')
        .map(|k| {
            let k: usize = k
                .trim()
                .parse()
                .with_context(|| format!("{FLEET_SIZES_VAR}: {k:?} is not a count"))?;
            if !(1..=MAX_FLEET).contains(&k) {
                bail!("{FLEET_SIZES_VAR}: {k} edges is outside 1..={MAX_FLEET}");
            }
            Ok(k)
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    if sizes.is_empty() {
        bail!("{FLEET_SIZES_VAR} names no fleet size");
    }
    Ok(sizes)
}

// ---------------------------------------------------------------------------------------------
// Clocks and load

/// CPU time of this whole process (all threads, also those that already exited).
fn process_cpu_ns() -> u64 {
    clock_ns(ClockId::CLOCK_PROCESS_CPUTIME_ID)
}

/// The 1-minute load average (`/proc/loadavg`), to print next to numbers measured on a
/// shared machine; NaN if unreadable.
fn load_average() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(f64::NAN)
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
    let mut config = installation::ingest_config(pki_dir, data_dir, 0);
    config.commit_interval = COMMIT_INTERVAL;
    config.time_sync_interval = TIME_SYNC_INTERVAL;
    config.max_connections = MAX_FLEET;
    let mut server = if pipeline_on() {
        let live = LiveSettings::new(PipelineSettings::default(), data_dir.to_path_buf());
        ServerThread::start_live(config, live)?
    } else {
        ServerThread::start(config)?
    };
    let events = std::mem::replace(&mut server.events, mpsc::unbounded_channel().1);
    let collector = std::thread::spawn(move || collect_recorded(events));
    let mut out = BufWriter::new(std::io::stdout().lock());
    writeln!(out, "addr {}", server.addr())?;
    out.flush()?;
    for line in std::io::stdin().lock().lines() {
        if line? != "cpu" {
            break;
        }
        let (rss, peak) = rss_kb();
        writeln!(out, "cpu {} {rss} {peak}", process_cpu_ns())?;
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

    /// The server's CPU time so far (ns, all its threads) and its resident memory now and at
    /// its peak (kB).
    fn usage(&mut self) -> anyhow::Result<(u64, u64, u64)> {
        writeln!(self.stdin, "cpu")?;
        self.stdin.flush()?;
        let reply = read_reply(&mut self.stdout, "cpu")?;
        let fields: Vec<u64> = reply
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .with_context(|| format!("cpu reply {reply:?}"))?;
        match fields.as_slice() {
            [ns, rss, peak] => Ok((*ns, *rss, *peak)),
            _ => bail!("cpu reply {reply:?}: expected three numbers"),
        }
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
// Fleets

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
    /// The server's resident memory now and at its peak (kB).
    server_rss_kb: u64,
    server_peak_kb: u64,
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
        if edges > bench.identities.len() {
            bail!(
                "{edges} edges, but only {} identities were paired",
                bench.identities.len()
            );
        }
        let server = ServerProcess::start(&bench.pki_dir, &dir.join("data"))?;
        let edges = (0..edges)
            .map(|i| {
                let spool = dir.join(format!("edge-{i}"));
                SimEdge::start(
                    &bench.runtime,
                    server.addr,
                    &bench.identities[i],
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
        let (server_ns, server_rss_kb, server_peak_kb) = self.server.usage()?;
        Ok(CpuMark {
            at: Instant::now(),
            server_ns,
            server_rss_kb,
            server_peak_kb,
            edges_ns: process_cpu_ns(),
        })
    }

    /// CPU shares of one core since `start`, and the wall time.
    fn cpu_since(&mut self, start: CpuMark) -> anyhow::Result<(CpuShare, Duration)> {
        self.cpu_mark_since(start).map(|(cpu, wall, _)| (cpu, wall))
    }

    /// [`Fleet::cpu_since`] and the mark it ended with (the server's memory then).
    fn cpu_mark_since(&mut self, start: CpuMark) -> anyhow::Result<(CpuShare, Duration, CpuMark)> {
        let end = self.cpu_mark()?;
        let wall = end.at - start.at;
        let share = |ns: u64| ns as f64 / wall.as_nanos() as f64;
        let cpu = CpuShare {
            server: share(end.server_ns.saturating_sub(start.server_ns)),
            edges: share(end.edges_ns.saturating_sub(start.edges_ns)),
        };
        Ok((cpu, wall, end))
    }

    /// Stops the edges (after their last acknowledgement), then the server.
    fn stop(self, runtime: &Runtime) -> anyhow::Result<ServerReport> {
        for edge in self.edges {
            edge.stop(runtime)?;
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

/// Everything shared by the runs: the work directory, the PKI with one identity per edge, the
/// edges' runtime, the streams.
struct Bench {
    work: WorkDir,
    pki_dir: PathBuf,
    identities: Vec<EdgeIdentity>,
    /// How long issuing [`identities`](Self::identities) took.
    pairing: Duration,
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
    /// The 1-minute load average when the run ended.
    load: f64,
    /// The server's resident memory when the submitting window ended, and its peak by then
    /// (kB; each row has its own server process).
    server_rss_kb: u64,
    server_peak_kb: u64,
}

impl RateRun {
    /// Every frame taken by the spool, recorded and acknowledged.
    fn all_delivered(&self) -> bool {
        self.refused == 0 && self.not_recorded == 0 && self.not_acked == 0
    }

    /// [`all_delivered`](Self::all_delivered), with ack p99 within [`ACK_P99_BOUND`].
    fn kept_up(&self) -> bool {
        self.all_delivered() && quantile(&self.acked_ms, 0.99) <= ACK_P99_BOUND.as_secs_f64() * 1e3
    }

    /// Adds one edge's frames: when the server recorded each, and when the edge's
    /// acknowledgement `timeline` (from [`fleet::watch_acks`]) first went past it.
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
    /// Pairs one identity per edge of the largest fleet (`edges`) in a fresh work directory
    /// and synthesizes the frame pools.
    fn new(edges: usize) -> anyhow::Result<Self> {
        let work = WorkDir(
            std::env::temp_dir().join(format!("scan3d-bench-uplink-{}", std::process::id())),
        );
        let pki_dir = work.0.join("pki");
        let paired = Instant::now();
        let identities = fleet::pair_edges(&pki_dir, edges)?;
        let pairing = paired.elapsed();
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("sim-edges")
            .enable_all()
            .build()?;
        let world = std::sync::Arc::new(World::conference_room());
        Ok(Self {
            streams: LidarStream::both(&world)?,
            work,
            pki_dir,
            identities,
            pairing,
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
            "  edges    the real edge Uplink client, own certificate (edge name), spool (8 MiB memory, 256 MiB disk) and session each"
        );
        let each = self.pairing / u32::try_from(self.identities.len().max(1)).unwrap_or(u32::MAX);
        println!(
            "  pairing  {} edge bundles issued with the `scan3d pair` code in {:.0} ms ({:.1} ms each: CA and server certificate once, then an ECDSA P-256 key and certificate per edge)",
            self.identities.len(),
            self.pairing.as_secs_f64() * 1e3,
            each.as_secs_f64() * 1e3
        );
        println!(
            "  load     1-minute load average {:.2} at the start (the machine is shared with other work)",
            load_average()
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
        let watcher =
            self.runtime
                .spawn(fleet::watch_acks(handles.clone(), ACK_POLL, watch_stopped));
        let start = fleet.cpu_mark()?;
        let begin = tokio::time::Instant::from_std(start.at);
        let deadline = begin + RATE_RUN;
        let static_scans = pipeline_on().then_some(StaticScanPlan {
            revolutions: STATIC_SCAN_STEPS,
        });
        let per_edge = Producers::start_with(
            &self.runtime,
            &handles,
            &self.streams,
            begin,
            deadline,
            static_scans,
        )
        .join(&self.runtime)?;
        let (cpu, wall, end) = fleet.cpu_mark_since(start)?;
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
            load: load_average(),
            server_rss_kb: end.server_rss_kb,
            server_peak_kb: end.server_peak_kb,
        };
        for ((edge, produced), timeline) in handles.iter().zip(&per_edge).zip(&timelines) {
            run.add_edge(&report, edge.session_id, produced, timeline);
        }
        run.recorded_ms.sort_by(f64::total_cmp);
        run.acked_ms.sort_by(f64::total_cmp);
        Ok(run)
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

/// Section 3: per fleet size, what was sent, recorded and acknowledged, how fast, at what
/// server CPU; then the largest fleet measured that kept up.
fn print_fleets(runs: &[RateRun]) {
    println!(
        "3. K edges at once at full sensor rate, each RPLidar 5.5 rev/s + Sweep 5 rev/s, {} s per row",
        RATE_RUN.as_secs()
    );
    if pipeline_on() {
        println!(
            "   server live pipeline ON ([pipeline] defaults: 0.05 m octree per session and position), every edge"
        );
        println!(
            "   making static scans back to back on its Sweep ({STATIC_SCAN_STEPS} steps of {}°): assembly and insertion run",
            180 / STATIC_SCAN_STEPS
        );
    }
    println!(
        "   {:>4} {:>7} {:>8} {:>7} {:>7} {:>8} {:>10} {:>8} {:>9} {:>8} {:>8} {:>8} {:>8} {:>5} {:>8} {:>8}",
        "K",
        "sent",
        "recorded",
        "acked",
        "refused",
        "frames/s",
        "server CPU",
        "per edge",
        "edges CPU",
        "rec p99",
        "ack p50",
        "ack p99",
        "ack max",
        "load",
        "RSS MB",
        "peak MB"
    );
    for run in runs {
        println!(
            "   {:>4} {:>7} {:>8} {:>7} {:>7} {:>8.0} {:>10} {:>8} {:>9} {:>8.1} {:>8.1} {:>8.1} {:>8.1} {:>5.1} {:>8.1} {:>8.1}",
            run.edges,
            run.frames,
            run.frames - run.not_recorded,
            run.frames - run.not_acked,
            run.refused,
            run.frames as f64 / run.wall.as_secs_f64(),
            percent(run.cpu.server),
            format!("{:.2} %", run.cpu.server * 100.0 / run.edges as f64),
            percent(run.cpu.edges),
            quantile(&run.recorded_ms, 0.99),
            quantile(&run.acked_ms, 0.5),
            quantile(&run.acked_ms, 0.99),
            quantile(&run.acked_ms, 1.0),
            run.load,
            run.server_rss_kb as f64 / 1024.0,
            run.server_peak_kb as f64 / 1024.0,
        );
    }
    println!(
        "   (sent: frames the edges' spools took; refused: frames a full spool turned away; CPU in % of one core"
    );
    println!(
        "    over the submitting window, per edge = server CPU / K; latencies in ms; edges CPU = this process: K"
    );
    println!(
        "    uplink clients and the producers; load = 1-minute load average at the end of the row, shared machine)"
    );
    let bound_ms = ACK_P99_BOUND.as_secs_f64() * 1e3;
    for run in runs {
        let p99 = quantile(&run.acked_ms, 0.99);
        let verdict = if run.kept_up() {
            format!(
                "kept up: every frame recorded and acknowledged, ack p99 {p99:.1} ms <= {bound_ms:.0} ms"
            )
        } else if run.all_delivered() {
            format!(
                "every frame recorded and acknowledged, but ack p99 {p99:.1} ms > {bound_ms:.0} ms"
            )
        } else {
            format!(
                "FELL BEHIND: {} refused by a full spool, {} not recorded, {} not acknowledged",
                run.refused, run.not_recorded, run.not_acked
            )
        };
        println!(
            "   K={:<3} {verdict} (server: {} connections, {} refused, {} frames, {} duplicates, {} rejected)",
            run.edges,
            run.stats.connections,
            run.stats.refused,
            run.stats.frames,
            run.stats.duplicates,
            run.stats.rejected
        );
    }
    match runs.iter().filter(|r| r.kept_up()).map(|r| r.edges).max() {
        Some(largest) => {
            let all_below = runs
                .iter()
                .filter(|r| r.edges < largest)
                .all(RateRun::kept_up);
            let top = runs.iter().map(|r| r.edges).max() == Some(largest);
            println!(
                "   => largest K measured that kept up (all recorded and acknowledged, ack p99 <= 3 x commit_interval = {bound_ms:.0} ms): {largest}{}{}",
                if all_below {
                    ""
                } else {
                    " (a smaller K did not: the machine's load varies)"
                },
                if top {
                    "; it is the largest K run, larger fleets were not measured"
                } else {
                    ""
                }
            );
        }
        None => println!(
            "   => no K measured kept up (all recorded and acknowledged, ack p99 <= {bound_ms:.0} ms)"
        ),
    }
}
