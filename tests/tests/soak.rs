//! The soak and fault run: K synthetic edges (the uplink benchmark's clients,
//! `scan3d_hw_sim::fleet`, each with its own certificate, spool and session) stream both lidars
//! at full sensor rate for N minutes to one server, a real `scan3d serve` process on loopback,
//! through a seeded impairing UDP relay (loss, delay ± jitter, reordering). Midway the server is
//! killed with SIGKILL and restarted on the same port and data directory. At the end every frame
//! every edge produced must be in the recordings (read back from disk), and the server's RSS,
//! open file descriptors and CPU, sampled over time from `/proc/<pid>/status`, `/proc/<pid>/fd`
//! and `/proc/<pid>/stat` (utime + stime), are printed as a table, with the CPU of this test
//! process (the simulated edges and the relay) beside the server's. The server's `status` says
//! what its live pipeline did with each session, just before the kill and once the restarted
//! server processed all it recorded: every session's pose stage must have matched RPLidar
//! revolutions.
//!
//! ```text
//! SOAK_MINUTES=10 SOAK_EDGES=16 \
//!     cargo test -p scan3d-tests --release --test soak -- --ignored --nocapture
//! ```
//!
//! Knobs (environment, defaults in brackets): `SOAK_MINUTES` [10], `SOAK_EDGES` [16],
//! `SOAK_LOSS` [0.05], `SOAK_DELAY_MS` [200], `SOAK_JITTER_MS` [50] (one-way, each direction:
//! a round trip costs twice), `SOAK_REORDER` [1], `SOAK_SEED` [1], `SOAK_KILL_AT` [0.5, the
//! fraction of the run at which the server is killed], `SOAK_SAMPLE_S` [10, the sampling period],
//! `SOAK_DRAIN_S` [300, how long the edges may take to deliver their backlog after producing],
//! `SOAK_PIPELINE_S` [600, how long the restarted server's pipeline may take after that to process
//! all it recorded: it rebuilds every session from its recording],
//! `SOAK_PIPELINE` [1; 0: `[pipeline] enabled = false`, the server only records, to compare],
//! `SOAK_CC` [unset: the edge's own QUIC settings (BBR); `cubic`: quinn's default Cubic, to
//! compare],
//! `SOAK_KEEP` [unset: the work directory with recordings, spools and server logs is kept only
//! when the run fails].
//!
//! The server process is this test binary re-run as `scan3d serve --config …` (the library's
//! CLI entry, exactly what the `scan3d` binary's `main` calls, with the same logging), so the
//! SIGKILL is real; `SOAK_SERVER_BIN=/path/to/scan3d` runs that binary instead.

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use scan3d_edge::uplink::spool::{Spool, SpoolConfig};
use scan3d_hw_sim::fleet::{self, EdgeHandle, EdgeIdentity, LidarStream, Producers, SimEdge};
use scan3d_hw_sim::world::World;
use scan3d_server::recording::{read_session, session_dir};
use scan3d_tests::relay::{Impairment, UdpRelay};

/// Environment variable that turns this test binary into the server child.
const CHILD_CONFIG_VAR: &str = "SCAN3D_SOAK_SERVER_CONFIG";

/// The server's body when this binary is re-run as the child (see [`ServerProcess::spawn`]).
#[test]
#[ignore = "runs only as the server child of the soak run"]
fn soak_server_child() {
    let Ok(config) = std::env::var(CHILD_CONFIG_VAR) else {
        return;
    };
    use clap::Parser;
    scan3d_service::daemon::init_logging("info");
    let cli = scan3d_server::cli::Cli::parse_from(["scan3d", "serve", "--config", &config]);
    scan3d_server::cli::execute(cli, &mut std::io::sink()).expect("server ran");
}

/// The run's parameters, from the environment.
#[derive(Debug, Clone)]
struct Plan {
    minutes: f64,
    edges: usize,
    impairment: Impairment,
    kill_at: f64,
    sample_every: Duration,
    drain_limit: Duration,
    /// How long the server's pipeline may take to process everything recorded, after the drain.
    pipeline_limit: Duration,
    /// Whether the server runs its live pipeline (`SOAK_PIPELINE`, on by default); off, it only
    /// records and the pipeline's checks are skipped.
    pipeline: bool,
    /// `SOAK_CC=cubic`: the edges' QUIC connections use quinn's default Cubic instead of the
    /// edge's BBR, to compare; unset, the edges run with the edge's own transport settings.
    cubic: bool,
}

/// Reads `name` as a `T`, or `default` when unset.
fn env_or<T: std::str::FromStr>(name: &str, default: T) -> anyhow::Result<T>
where
    T::Err: std::fmt::Display,
{
    match std::env::var(name) {
        Ok(text) => text
            .trim()
            .parse()
            .map_err(|e| anyhow::anyhow!("{name}={text:?}: {e}")),
        Err(_) => Ok(default),
    }
}

impl Plan {
    fn from_env() -> anyhow::Result<Self> {
        let soak = Impairment::soak(env_or("SOAK_SEED", 1)?);
        let plan = Plan {
            minutes: env_or("SOAK_MINUTES", 10.0)?,
            edges: env_or("SOAK_EDGES", 16)?,
            impairment: Impairment {
                loss: env_or("SOAK_LOSS", soak.loss)?,
                delay: Duration::from_millis(env_or("SOAK_DELAY_MS", 200)?),
                jitter: Duration::from_millis(env_or("SOAK_JITTER_MS", 50)?),
                reorder: env_or::<u8>("SOAK_REORDER", 1)? != 0,
                seed: soak.seed,
            },
            kill_at: env_or("SOAK_KILL_AT", 0.5)?,
            sample_every: Duration::from_secs(env_or("SOAK_SAMPLE_S", 10)?),
            drain_limit: Duration::from_secs(env_or("SOAK_DRAIN_S", 300)?),
            pipeline_limit: Duration::from_secs(env_or("SOAK_PIPELINE_S", 600)?),
            pipeline: env_or::<u8>("SOAK_PIPELINE", 1)? != 0,
            cubic: match std::env::var("SOAK_CC").as_deref() {
                Err(_) | Ok("") | Ok("default") | Ok("bbr") => false,
                Ok("cubic") => true,
                Ok(other) => bail!("SOAK_CC={other:?}: expected `cubic` or `default`"),
            },
        };
        if !(plan.minutes > 0.0 && plan.minutes <= 24.0 * 60.0) {
            bail!("SOAK_MINUTES={} is outside (0, 1440]", plan.minutes);
        }
        if !(1..=256).contains(&plan.edges) {
            bail!("SOAK_EDGES={} is outside 1..=256", plan.edges);
        }
        if !(0.0..1.0).contains(&plan.kill_at) {
            bail!("SOAK_KILL_AT={} is outside [0, 1)", plan.kill_at);
        }
        if plan.sample_every.is_zero() {
            bail!("SOAK_SAMPLE_S must be at least 1");
        }
        plan.impairment.validate()?;
        Ok(plan)
    }

    fn duration(&self) -> Duration {
        Duration::from_secs_f64(self.minutes * 60.0)
    }
}

/// The server as a child process, restartable on the same configuration.
struct ServerProcess {
    config: PathBuf,
    logs: PathBuf,
    child: Child,
    starts: usize,
}

impl ServerProcess {
    /// Starts `scan3d serve --config config`, its log in `logs/server-N.log`.
    fn spawn(config: &Path, logs: &Path) -> anyhow::Result<Self> {
        let child = Self::start_child(config, logs, 0)?;
        Ok(Self {
            config: config.to_path_buf(),
            logs: logs.to_path_buf(),
            child,
            starts: 1,
        })
    }

    fn start_child(config: &Path, logs: &Path, n: usize) -> anyhow::Result<Child> {
        let log = std::fs::File::create(logs.join(format!("server-{n}.log")))?;
        let mut command = match std::env::var_os("SOAK_SERVER_BIN") {
            Some(bin) => {
                let mut command = Command::new(bin);
                command.arg("serve").arg("--config").arg(config);
                command
            }
            None => {
                let mut command = Command::new(std::env::current_exe()?);
                command
                    .args([
                        "soak_server_child",
                        "--exact",
                        "--ignored",
                        "--nocapture",
                        "--test-threads=1",
                    ])
                    .env(CHILD_CONFIG_VAR, config);
                command
            }
        };
        command
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .context("cannot start the server process")
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGKILL: no commit, no close, no goodbye.
    fn kill(&mut self) -> anyhow::Result<()> {
        self.child.kill()?;
        self.child.wait()?;
        Ok(())
    }

    /// Starts the server again on the same configuration.
    fn restart(&mut self) -> anyhow::Result<()> {
        self.child = Self::start_child(&self.config, &self.logs, self.starts)?;
        self.starts += 1;
        Ok(())
    }

    /// SIGTERM and wait: the server commits, closes its recordings and exits 0.
    fn terminate(mut self) -> anyhow::Result<()> {
        let pid = nix::unistd::Pid::from_raw(i32::try_from(self.pid())?);
        nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM)?;
        let status = self.child.wait()?;
        if !status.success() {
            bail!("the server did not exit cleanly after SIGTERM: {status}");
        }
        Ok(())
    }
}

/// One reading of the server process.
#[derive(Debug, Clone, Copy)]
struct Sample {
    at: Duration,
    pid: u32,
    /// `VmRSS`, KiB; `None` if the process was not there (between kill and restart).
    rss_kib: Option<u64>,
    fds: Option<usize>,
    /// Frames waiting in all edges' spools.
    pending: usize,
    /// Frames acknowledged so far, all edges.
    acked: u64,
    /// Edges with at least one connection since the last server start.
    connected: usize,
    /// The server's CPU time so far (utime + stime), clock ticks; `None` if it was not there.
    server_cpu_ticks: Option<u64>,
    /// This process's (the simulated edges', the relay's) CPU time so far, clock ticks.
    own_cpu_ticks: Option<u64>,
}

/// Clock ticks per second of `/proc/<pid>/stat`'s times: `sysconf(_SC_CLK_TCK)`, which is
/// Linux's `USER_HZ`, 100 on every architecture (`proc(5)`; checked against the process CPU
/// clock by `proc_cpu_ticks_agree_with_the_process_cpu_clock`).
const CLOCK_TICKS_PER_S: f64 = 100.0;

/// CPU time `pid` has used (utime + stime, all its threads, not its children), clock ticks.
fn cpu_ticks(pid: &str) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // `pid (comm) state ppid …`: comm may hold spaces and parentheses, so split after the last
    // `)`; utime and stime are fields 14 and 15, the 12th and 13th after it.
    let after_comm = &stat[stat.rfind(')')? + 1..];
    let mut fields = after_comm.split_whitespace().skip(11);
    let utime: u64 = fields.next()?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    Some(utime + stime)
}

/// The CPU a process used between two readings of its ticks, as % of one core over `wall`.
fn cpu_percent(from_ticks: u64, to_ticks: u64, wall: Duration) -> f64 {
    to_ticks.saturating_sub(from_ticks) as f64 / CLOCK_TICKS_PER_S / wall.as_secs_f64() * 100.0
}

/// `VmRSS` of `pid` in KiB.
fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// Open file descriptors of `pid`.
fn fd_count(pid: u32) -> Option<usize> {
    Some(std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count())
}

/// Samples the server (whichever process currently has `pid`) every `every` until `stop`.
fn sample_server(
    pid: Arc<AtomicU32>,
    edges: Vec<EdgeHandle>,
    baseline: Arc<Mutex<Vec<u64>>>,
    every: Duration,
    stop: Arc<AtomicBool>,
    start: Instant,
) -> Vec<Sample> {
    let mut samples = Vec::new();
    let mut next = start;
    while !stop.load(Ordering::Relaxed) {
        if Instant::now() < next {
            std::thread::sleep(Duration::from_millis(100));
            continue;
        }
        next += every;
        let pid = pid.load(Ordering::SeqCst);
        let baseline = baseline.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let sample = Sample {
            at: start.elapsed(),
            pid,
            rss_kib: rss_kib(pid),
            fds: fd_count(pid),
            pending: edges.iter().map(|e| e.uplink.pending()).sum(),
            acked: edges.iter().map(EdgeHandle::acked_prefix).sum(),
            connected: edges
                .iter()
                .zip(&baseline)
                .filter(|(e, b)| e.uplink.stats().connections > **b)
                .count(),
            server_cpu_ticks: cpu_ticks(&pid.to_string()),
            own_cpu_ticks: cpu_ticks("self"),
        };
        // As it happens too, so a run that hangs at its end is not blind.
        eprintln!("soak sample: {sample:?}");
        samples.push(sample);
    }
    samples
}

/// Waits until `done`, polling every 100 ms; fails after `limit`.
fn wait_for(limit: Duration, what: &str, mut done: impl FnMut() -> bool) -> anyhow::Result<()> {
    let start = Instant::now();
    while !done() {
        if start.elapsed() > limit {
            bail!("timed out after {limit:?} waiting for {what}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(())
}

/// A UDP port that was free a moment ago (the server binds it; the restart binds it again).
fn free_udp_port() -> anyhow::Result<u16> {
    Ok(std::net::UdpSocket::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// Where the edge `identity` spools.
fn spool_dir(work: &tempfile::TempDir, identity: &EdgeIdentity) -> PathBuf {
    work.path().join("spools").join(&identity.name)
}

/// The sequence numbers of the frames left in the spool at `dir` (after the edge stopped: its
/// shutdown wrote everything unacknowledged to disk). Acknowledgements are not persisted, so
/// this may include frames the server has too.
fn spooled_seqs(dir: &Path) -> anyhow::Result<HashSet<u64>> {
    let mut spool = Spool::open(SpoolConfig::new(dir))?;
    let mut seqs = HashSet::new();
    while let Some(frame) = spool.next_unsent() {
        seqs.insert(frame.seq);
    }
    Ok(seqs)
}

/// What reading one edge's recording back found.
#[derive(Debug, Default)]
struct Readback {
    /// Frames the edge produced that are neither in the recording nor in its spool.
    lost: Vec<u64>,
    /// Frames the edge produced that are not in the recording yet but still in its spool (not
    /// lost: a restarted edge sends them).
    undelivered: u64,
    /// Frames recorded more than once.
    duplicates: u64,
    /// Frames in the recording (all bodies, time-sync pongs included).
    records: u64,
}

/// Reads the session of `edge` and checks that each of `seqs` is in it, or else still in
/// `spooled`.
fn read_back(
    data_dir: &Path,
    edge: &EdgeHandle,
    seqs: &[u64],
    spooled: &HashSet<u64>,
) -> anyhow::Result<Readback> {
    let dir = session_dir(data_dir, &edge.name, edge.session_id);
    let frames = read_session(&dir).with_context(|| format!("reading back {}", dir.display()))?;
    let mut seen: HashMap<u64, u64> = HashMap::new();
    for frame in &frames {
        *seen.entry(frame.frame.seq).or_default() += 1;
    }
    let missing: Vec<u64> = seqs
        .iter()
        .copied()
        .filter(|s| !seen.contains_key(s))
        .collect();
    Ok(Readback {
        undelivered: missing.iter().filter(|s| spooled.contains(s)).count() as u64,
        lost: missing
            .into_iter()
            .filter(|s| !spooled.contains(s))
            .collect(),
        duplicates: seen.values().map(|&n| n.saturating_sub(1)).sum(),
        records: frames.len() as u64,
    })
}

fn mib(kib: Option<u64>) -> String {
    kib.map_or("-".into(), |k| format!("{:.1}", k as f64 / 1024.0))
}

/// The server's and this process's CPU over the sampling period ending at `s`, % of one core
/// (`None` for the server across its restart: a new process, a new count).
fn period_cpu(previous: Option<&Sample>, s: &Sample) -> (Option<f64>, Option<f64>) {
    let Some(p) = previous else {
        return (None, None);
    };
    let wall = s.at - p.at;
    let server = match (p.server_cpu_ticks, s.server_cpu_ticks) {
        (Some(from), Some(to)) if p.pid == s.pid => Some(cpu_percent(from, to, wall)),
        _ => None,
    };
    let own = match (p.own_cpu_ticks, s.own_cpu_ticks) {
        (Some(from), Some(to)) => Some(cpu_percent(from, to, wall)),
        _ => None,
    };
    (server, own)
}

fn print_samples(samples: &[Sample], edges: usize, kill_at: Duration, restart_at: Duration) {
    println!(
        "  server process over time (RSS from /proc/PID/status VmRSS, fds = entries of /proc/PID/fd,"
    );
    println!(
        "  CPU = utime + stime from /proc/PID/stat over the period, % of one core; edges = this test"
    );
    println!("  process: the simulated edges, the relay and the sampler):");
    println!(
        "  {:>7} {:>8} {:>8} {:>5} {:>9} {:>9} {:>9} {:>8} {:>8} {:>8}",
        "t s",
        "pid",
        "RSS MiB",
        "fds",
        "pending",
        "acked/s",
        "connected",
        "srv CPU%",
        "%/edge",
        "edges%"
    );
    let percent = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.1}"));
    let mut previous: Option<&Sample> = None;
    for s in samples {
        let rate = previous.map_or(f64::NAN, |p| {
            s.acked.saturating_sub(p.acked) as f64 / (s.at - p.at).as_secs_f64()
        });
        let (server, own) = period_cpu(previous, s);
        previous = Some(s);
        let note = if s.at >= kill_at && s.at < restart_at + Duration::from_secs(1) {
            "  (killed / restarting)"
        } else {
            ""
        };
        println!(
            "  {:>7.0} {:>8} {:>8} {:>5} {:>9} {:>9.1} {:>9} {:>8} {:>8} {:>8}{note}",
            s.at.as_secs_f64(),
            s.pid,
            mib(s.rss_kib),
            s.fds.map_or("-".into(), |f| f.to_string()),
            s.pending,
            rate,
            s.connected,
            percent(server),
            percent(server.map(|c| c / edges as f64)),
            percent(own),
        );
    }
    let max_rss = samples.iter().filter_map(|s| s.rss_kib).max();
    let max_fds = samples.iter().filter_map(|s| s.fds).max();
    println!(
        "  max RSS {} MiB, max fds {}",
        mib(max_rss),
        max_fds.map_or("-".into(), |f| f.to_string())
    );
}

/// The median of `values` (`None` if empty).
fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    (!values.is_empty()).then(|| values[values.len() / 2])
}

/// The median of the server process `pid`'s CPU over the sampling periods it lived through
/// that end by `until`, its first period left out (start-up), % of one core.
fn median_server_cpu(samples: &[Sample], pid: u32, until: Duration) -> Option<f64> {
    let periods = samples
        .windows(2)
        .filter(|w| w[0].pid == pid && w[1].pid == pid && w[1].at <= until)
        .skip(1)
        .filter_map(|w| period_cpu(Some(&w[0]), &w[1]).0);
    median(periods.collect())
}

/// The server's live status (`scan3d status --json`'s report) through its control socket.
fn server_status(data_dir: &Path) -> anyhow::Result<serde_json::Value> {
    use scan3d_server::ingest::control::{ProductRequest, request_products, socket_path};
    let reply = request_products(&socket_path(data_dir), &ProductRequest::Status)?;
    if !reply.ok {
        bail!("status refused: {}", reply.detail);
    }
    reply.data.context("the status reply carries no report")
}

/// Polls the server's status every second until its live pipeline has processed every frame it
/// recorded of `edges` sessions, each with poses matched (fails after `limit`). The restarted
/// server rebuilds each session from its recording, so this can be well after the last
/// acknowledgement.
fn wait_for_pipeline(
    data_dir: &Path,
    edges: usize,
    limit: Duration,
) -> anyhow::Result<serde_json::Value> {
    let start = Instant::now();
    loop {
        let status = server_status(data_dir)?;
        let lines = pipeline_lines(&status);
        let done = lines.len() == edges
            && lines
                .iter()
                .all(|l| l.lag_frames == 0 && l.pose_revolutions.is_some_and(|r| r > 0));
        if done || start.elapsed() > limit {
            return Ok(status);
        }
        std::thread::sleep(Duration::from_secs(1));
    }
}

/// What the server's live pipeline did with one session, from its status.
#[derive(Debug, Default)]
struct PipelineLine {
    edge: String,
    revolutions: u64,
    /// `pose.revolutions`: RPLidar revolutions the pose stage matched (`None`: no pose stage).
    pose_revolutions: Option<u64>,
    path_m: f64,
    worker_cpu_ms: u64,
    /// Frames recorded and not yet processed.
    lag_frames: u64,
    catch_ups: u64,
    max_lag_ms: u64,
    missing_frames: u64,
    stream_releases: u64,
    accept_to_pose_p50_ms: Option<f64>,
    accept_to_pose_p99_ms: Option<f64>,
}

/// Every session's line in a status report.
fn pipeline_lines(status: &serde_json::Value) -> Vec<PipelineLine> {
    let u = |v: &serde_json::Value, key: &str| v.get(key).and_then(|x| x.as_u64()).unwrap_or(0);
    let mut lines = Vec::new();
    for edge in status["edges"].as_array().into_iter().flatten() {
        for session in edge["sessions"].as_array().into_iter().flatten() {
            let pose = session.get("pose").filter(|p| !p.is_null());
            let accept = session.get("accept_to_pose").filter(|p| !p.is_null());
            lines.push(PipelineLine {
                edge: edge["name"].as_str().unwrap_or("?").to_owned(),
                revolutions: u(session, "revolutions"),
                pose_revolutions: pose.map(|p| u(p, "revolutions")),
                path_m: pose.and_then(|p| p["path_m"].as_f64()).unwrap_or(0.0),
                worker_cpu_ms: u(session, "worker_cpu_ms"),
                lag_frames: u(session, "lag_frames"),
                catch_ups: u(session, "catch_ups"),
                max_lag_ms: u(session, "max_lag_ms"),
                missing_frames: u(session, "missing_frames"),
                stream_releases: u(session, "stream_releases"),
                accept_to_pose_p50_ms: accept.and_then(|a| a["p50_ms"].as_f64()),
                accept_to_pose_p99_ms: accept.and_then(|a| a["p99_ms"].as_f64()),
            });
        }
    }
    lines
}

fn print_pipeline(title: &str, lines: &[PipelineLine]) {
    println!("  {title}");
    println!(
        "  {:<14} {:>6} {:>5} {:>9} {:>7} {:>8} {:>6} {:>8} {:>7} {:>8} {:>9} {:>9}",
        "edge",
        "revs",
        "lag",
        "pose revs",
        "path m",
        "wkr CPU s",
        "catch",
        "max lag",
        "missing",
        "releases",
        "a→pose 50",
        "a→pose 99"
    );
    let ms = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.1}"));
    for l in lines {
        println!(
            "  {:<14} {:>6} {:>5} {:>9} {:>7.3} {:>8.1} {:>6} {:>8} {:>7} {:>8} {:>9} {:>9}",
            l.edge,
            l.revolutions,
            l.lag_frames,
            l.pose_revolutions.map_or("-".into(), |r| r.to_string()),
            l.path_m,
            l.worker_cpu_ms as f64 / 1e3,
            l.catch_ups,
            l.max_lag_ms,
            l.missing_frames,
            l.stream_releases,
            ms(l.accept_to_pose_p50_ms),
            ms(l.accept_to_pose_p99_ms),
        );
    }
}

#[test]
#[ignore = "the soak run takes minutes: SOAK_MINUTES=10 SOAK_EDGES=16 cargo test -p scan3d-tests --release --test soak -- --ignored --nocapture"]
fn a_fleet_through_a_lossy_network_and_a_killed_server_loses_no_frame() -> anyhow::Result<()> {
    let plan = Plan::from_env()?;
    let work = tempfile::tempdir()?;
    let pki = work.path().join("pki");
    let data = work.path().join("data");
    let logs = work.path().join("logs");
    std::fs::create_dir_all(&logs)?;

    let paired = Instant::now();
    let identities = fleet::pair_edges(&pki, plan.edges)?;
    let pairing = paired.elapsed();

    let port = free_udp_port()?;
    let server_addr = SocketAddr::from(([127, 0, 0, 1], port));
    let config = work.path().join("server.toml");
    std::fs::write(
        &config,
        format!(
            "listen = \"{server_addr}\"\npki_dir = {:?}\ndata_dir = {:?}\nmax_connections = {}\n{}",
            pki.display().to_string(),
            data.display().to_string(),
            plan.edges + 4,
            if plan.pipeline {
                ""
            } else {
                "[pipeline]\nenabled = false\n"
            }
        ),
    )?;
    let load_before = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let mut server = ServerProcess::spawn(&config, &logs)?;
    let first_spawned = Instant::now();
    let server_pid = Arc::new(AtomicU32::new(server.pid()));
    let relay = UdpRelay::start_impaired(server_addr, plan.impairment)?;

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("soak-edges")
        .enable_all()
        .build()?;
    let edges: Vec<SimEdge> = identities
        .iter()
        .enumerate()
        .map(|(i, identity)| {
            let session_id = plan.impairment.seed.wrapping_mul(1_000_003) + i as u64 + 1;
            let mut config =
                fleet::uplink_config(relay.local_addr(), identity, spool_dir(&work, identity))?;
            if plan.cubic {
                // The link's shared settings, with quinn's default congestion control.
                config
                    .client_config
                    .transport_config(Arc::new(scan3d_service::link::transport_config()));
            }
            SimEdge::start_with(&runtime, config, identity, session_id)
        })
        .collect::<anyhow::Result<_>>()?;
    let handles: Vec<EdgeHandle> = edges.iter().map(|e| e.handle.clone()).collect();
    let connections = |handles: &[EdgeHandle]| -> Vec<u64> {
        handles
            .iter()
            .map(|e| e.uplink.stats().connections)
            .collect()
    };
    wait_for(Duration::from_secs(120), "every edge to connect", || {
        connections(&handles).iter().all(|&c| c > 0)
    })?;

    let world = Arc::new(World::conference_room());
    let streams = LidarStream::both(&world)?;
    let start = Instant::now();
    let own_cpu_at_start = cpu_ticks("self");
    let begin = tokio::time::Instant::from_std(start);
    let duration = plan.duration();
    let producers = Producers::start(&runtime, &handles, &streams, begin, begin + duration);

    let baseline = Arc::new(Mutex::new(vec![0u64; handles.len()]));
    let stop_sampling = Arc::new(AtomicBool::new(false));
    let sampler = {
        let (pid, edges, baseline, stop) = (
            server_pid.clone(),
            handles.clone(),
            baseline.clone(),
            stop_sampling.clone(),
        );
        let every = plan.sample_every;
        std::thread::spawn(move || sample_server(pid, edges, baseline, every, stop, start))
    };

    // The fault: SIGKILL mid-run, restart two seconds later on the same port and data.
    let kill_at = duration.mul_f64(plan.kill_at);
    std::thread::sleep(kill_at.saturating_sub(start.elapsed()));
    let killed_pid = server.pid();
    // The first server's live pipeline, streaming: did it keep up?
    let before_kill = plan.pipeline.then(|| server_status(&data));
    // Its CPU just before it dies (a reaped process has no /proc entry).
    let killed_cpu_ticks = cpu_ticks(&killed_pid.to_string());
    server.kill()?;
    let first_alive = first_spawned.elapsed();
    let kill_at = start.elapsed();
    std::thread::sleep(Duration::from_secs(2));
    *baseline.lock().unwrap_or_else(|e| e.into_inner()) = connections(&handles);
    server.restart()?;
    let restarted = Instant::now();
    server_pid.store(server.pid(), Ordering::SeqCst);
    let restart_at = start.elapsed();
    let reconnected = wait_for(Duration::from_secs(120), "every edge to reconnect", || {
        let base = baseline.lock().unwrap_or_else(|e| e.into_inner()).clone();
        connections(&handles).iter().zip(&base).all(|(c, b)| c > b)
    });
    let all_back_at = start.elapsed();

    let produced = producers.join(&runtime)?;
    let produced_at = start.elapsed();
    // Deliver the backlog: every produced frame acknowledged.
    let drained = wait_for(plan.drain_limit, "the last acknowledgements", || {
        handles.iter().zip(&produced).all(|(edge, p)| {
            p.submissions
                .last()
                .is_none_or(|last| edge.acked_prefix() > last.seq)
        })
    });
    let drained_at = start.elapsed();
    stop_sampling.store(true, Ordering::Relaxed);
    let samples = sampler
        .join()
        .map_err(|_| anyhow::anyhow!("sampler panicked"))?;

    // All at once: each may spend its drain timeout sending what is left.
    let uplinks = std::thread::scope(|scope| {
        let stopping: Vec<_> = edges
            .into_iter()
            .map(|edge| scope.spawn(|| edge.stop(&runtime)))
            .collect();
        stopping
            .into_iter()
            .map(|t| t.join().map_err(|_| anyhow::anyhow!("an edge panicked"))?)
            .collect::<anyhow::Result<Vec<_>>>()
    })?;
    let relay_stats = relay.stats();
    relay.shutdown();
    let own_cpu_at_end = cpu_ticks("self");
    let own_wall = start.elapsed();
    let server_pid_end = server.pid();
    // What the live pipeline did, and the server's CPU, before it is asked to stop.
    let status = plan
        .pipeline
        .then(|| wait_for_pipeline(&data, plan.edges, plan.pipeline_limit));
    let pipeline_done_at = start.elapsed();
    let final_cpu_ticks = cpu_ticks(&server_pid_end.to_string());
    let second_alive = restarted.elapsed();
    let terminated = server.terminate();

    let mut lost = 0usize;
    let mut undelivered = 0u64;
    let mut duplicates = 0u64;
    let mut records = 0u64;
    let mut lost_detail = Vec::new();
    for ((edge, p), identity) in handles.iter().zip(&produced).zip(&identities) {
        let seqs: Vec<u64> = p.submissions.iter().map(|s| s.seq).collect();
        let spooled = spooled_seqs(&spool_dir(&work, identity))?;
        let back = read_back(&data, edge, &seqs, &spooled)?;
        lost += back.lost.len();
        undelivered += back.undelivered;
        duplicates += back.duplicates;
        records += back.records;
        if !back.lost.is_empty() {
            let first: Vec<u64> = back.lost.iter().take(10).copied().collect();
            lost_detail.push(format!(
                "{}: {} lost, first seqs {first:?}",
                edge.name,
                back.lost.len()
            ));
        }
    }
    let sent: usize = produced.iter().map(|p| p.submissions.len()).sum();
    let refused: u64 = produced.iter().map(|p| p.refused).sum();
    let reconnects: u64 = uplinks.iter().map(|u| u.connections).sum();
    let resent: u64 = uplinks.iter().map(|u| u.frames_sent).sum();

    println!();
    println!(
        "soak: {} edges x {:.1} min at full sensor rate (RPLidar 5.5 rev/s + Sweep 5 rev/s each), one server SIGKILL + restart",
        plan.edges, plan.minutes
    );
    println!(
        "  relay    loss {:.1} %, delay {} ± {} ms each way, reordering {}, seed {}",
        plan.impairment.loss * 100.0,
        plan.impairment.delay.as_millis(),
        plan.impairment.jitter.as_millis(),
        if plan.impairment.reorder { "on" } else { "off" },
        plan.impairment.seed
    );
    println!(
        "           {} forwarded, {} lost on purpose, {} dropped (cut/down), {} delivered out of order",
        relay_stats.forwarded, relay_stats.lost, relay_stats.dropped, relay_stats.reordered
    );
    println!(
        "  pairing  {} bundles in {:.0} ms",
        plan.edges,
        pairing.as_secs_f64() * 1e3
    );
    println!(
        "  fault    pid {killed_pid} SIGKILLed at {:.1} s, restarted at {:.1} s (pid {server_pid_end}); every edge reconnected by {:.1} s{}",
        kill_at.as_secs_f64(),
        restart_at.as_secs_f64(),
        all_back_at.as_secs_f64(),
        match &reconnected {
            Ok(()) => String::new(),
            Err(e) => format!(" ({e})"),
        }
    );
    println!(
        "  frames   {sent} produced, {refused} refused by a full spool, {records} records read back ({duplicates} duplicates),"
    );
    println!(
        "           {undelivered} not recorded but still in the edges' spools (not lost, sent on the next start), {lost} LOST (neither)"
    );
    println!(
        "           producing ended at {:.1} s, last acknowledgement at {:.1} s{}; {reconnects} connections, {resent} frames written (resends included)",
        produced_at.as_secs_f64(),
        drained_at.as_secs_f64(),
        match &drained {
            Ok(()) => String::new(),
            Err(e) => format!(" ({e})"),
        }
    );
    for line in &lost_detail {
        println!("           {line}");
    }
    print_samples(&samples, plan.edges, kill_at, restart_at);
    let per_edge = |percent: f64| percent / plan.edges as f64;
    match (killed_cpu_ticks, final_cpu_ticks) {
        (Some(first), Some(second)) => {
            let alive = first_alive + second_alive;
            let total = cpu_percent(0, first + second, alive);
            println!(
                "  CPU      server {:.1} s in {:.1} s alive (pid {killed_pid} {:.1} s, pid {server_pid_end} {:.1} s): {total:.1} % of one core, {:.2} % per edge",
                (first + second) as f64 / CLOCK_TICKS_PER_S,
                alive.as_secs_f64(),
                first as f64 / CLOCK_TICKS_PER_S,
                second as f64 / CLOCK_TICKS_PER_S,
                per_edge(total)
            );
            // Everything the server did for the run (ingest, recording, the pipeline, the
            // restarted server's rebuild from the recordings) per second of one edge's data.
            let edge_seconds = plan.edges as f64 * produced_at.as_secs_f64();
            println!(
                "           per second of one edge's data ({:.0} edge-seconds produced): {:.2} % of one core",
                edge_seconds,
                (first + second) as f64 / CLOCK_TICKS_PER_S / edge_seconds * 100.0
            );
        }
        _ => println!("  CPU      server: a /proc/PID/stat reading failed"),
    }
    // The first server saw the run live from its start; the restarted one rebuilt every
    // session from its recording while the edges kept streaming.
    if let Some(live) = median_server_cpu(&samples, killed_pid, produced_at) {
        println!(
            "           first server, live (median of its {:.0} s periods, the first left out): {live:.1} % of one core, {:.2} % per edge",
            plan.sample_every.as_secs_f64(),
            per_edge(live)
        );
    }
    if let Some(rebuilding) = median_server_cpu(&samples, server_pid_end, produced_at) {
        println!(
            "           restarted server while producing (its rebuild included): {rebuilding:.1} % of one core, {:.2} % per edge",
            per_edge(rebuilding)
        );
    }
    if let (Some(from), Some(to)) = (own_cpu_at_start, own_cpu_at_end) {
        let own = cpu_percent(from, to, own_wall);
        println!(
            "           this process (the {} simulated edges, the relay, the sampler) {:.1} s in {:.1} s: {own:.1} % of one core",
            plan.edges,
            to.saturating_sub(from) as f64 / CLOCK_TICKS_PER_S,
            own_wall.as_secs_f64()
        );
    }
    match &before_kill {
        None => println!("  pipeline off (SOAK_PIPELINE=0): the server only recorded"),
        Some(Ok(report)) => print_pipeline(
            "pipeline of the first server just before the kill (live; a→pose = accept_to_pose p50/p99 ms, lag = frames not processed yet, max lag ms):",
            &pipeline_lines(report),
        ),
        Some(Err(e)) => println!("  pipeline status before the kill not read: {e:#}"),
    }
    let pipeline = match &status {
        None => Vec::new(),
        Some(Ok(report)) => {
            let lines = pipeline_lines(report);
            println!(
                "           status read at {:.1} s, once the pipeline had processed all it recorded (or after SOAK_PIPELINE_S)",
                pipeline_done_at.as_secs_f64()
            );
            print_pipeline(
                "pipeline (the restarted server's `status` once it processed all it recorded; it rebuilt each session from its recording):",
                &lines,
            );
            lines
        }
        Some(Err(e)) => {
            println!("  pipeline status not read: {e:#}");
            Vec::new()
        }
    };
    let unfinished: Vec<&str> = pipeline
        .iter()
        .filter(|l| l.lag_frames > 0 || l.pose_revolutions.is_none_or(|r| r == 0))
        .map(|l| l.edge.as_str())
        .collect();
    println!("  load     load averages before: {}", load_before.trim());
    println!(
        "           at the end: {}",
        std::fs::read_to_string("/proc/loadavg")
            .unwrap_or_default()
            .trim()
    );
    if let Err(e) = &terminated {
        println!("  server   {e}");
    }

    let expected_sessions = if plan.pipeline { plan.edges } else { 0 };
    let failed = lost > 0
        || undelivered > 0
        || status.as_ref().is_some_and(Result::is_err)
        || pipeline.len() != expected_sessions
        || !unfinished.is_empty()
        || reconnected.is_err()
        || drained.is_err()
        || terminated.is_err();
    if failed || std::env::var_os("SOAK_KEEP").is_some() {
        // Recordings, spools and server logs, for a post-mortem.
        println!("  kept     {}", work.keep().display());
    }
    assert_eq!(lost, 0, "frames lost: {lost_detail:?}");
    assert_eq!(
        undelivered, 0,
        "frames still in the edges' spools when the run ended"
    );
    reconnected?;
    drained?;
    terminated?;
    status.transpose()?;
    assert_eq!(
        pipeline.len(),
        expected_sessions,
        "one live session per edge in the server's status"
    );
    assert!(
        unfinished.is_empty(),
        "sessions with frames not processed or no RPLidar revolution matched: {unfinished:?}"
    );
    Ok(())
}

#[test]
fn proc_cpu_ticks_agree_with_the_process_cpu_clock() {
    use nix::time::ClockId;
    let cpu_ns = || scan3d_hw_sim::fleet::clock_ns(ClockId::CLOCK_PROCESS_CPUTIME_ID);
    let (ticks_before, ns_before) = (cpu_ticks("self").expect("own stat"), cpu_ns());
    // Burn about half a second of CPU.
    let mut x = 0u64;
    while cpu_ns() - ns_before < 500_000_000 {
        x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
    }
    let (ticks_after, ns_after) = (cpu_ticks("self").expect("own stat"), cpu_ns());
    let from_ticks = (ticks_after - ticks_before) as f64 / CLOCK_TICKS_PER_S;
    let from_clock = (ns_after - ns_before) as f64 / 1e9;
    // Ticks are sampled at USER_HZ: a few of them either way, never a factor off.
    assert!(
        (from_ticks - from_clock).abs() < 0.1,
        "/proc/self/stat says {from_ticks:.3} s, the process CPU clock {from_clock:.3} s"
    );
    assert_eq!(cpu_ticks("0"), None, "no process 0 in /proc");
}

#[test]
fn cpu_percent_is_of_one_core_over_the_wall_time() {
    // 250 ticks = 2.5 s of CPU in 10 s: a quarter of one core.
    assert_eq!(cpu_percent(100, 350, Duration::from_secs(10)), 25.0);
    // Two busy threads for 10 s: two cores.
    assert_eq!(cpu_percent(0, 2000, Duration::from_secs(10)), 200.0);
}

#[test]
fn the_live_cpu_is_the_median_of_one_servers_periods_after_its_first() {
    let sample = |at_s: u64, pid: u32, ticks: u64| Sample {
        at: Duration::from_secs(at_s),
        pid,
        rss_kib: Some(1),
        fds: Some(1),
        pending: 0,
        acked: 0,
        connected: 1,
        server_cpu_ticks: Some(ticks),
        own_cpu_ticks: Some(0),
    };
    // Server 7: 90 % start-up, then 10 %, 30 %, 20 % of one core; server 8 after it at 100 %.
    let samples = [
        sample(0, 7, 0),
        sample(10, 7, 900),
        sample(20, 7, 1000),
        sample(30, 7, 1300),
        sample(40, 7, 1500),
        sample(50, 8, 0),
        sample(60, 8, 1000),
        sample(70, 8, 2000),
    ];
    assert_eq!(
        median_server_cpu(&samples, 7, Duration::from_secs(100)),
        Some(20.0)
    );
    // Only the periods that end by `until`: 10 % alone after the first.
    assert_eq!(
        median_server_cpu(&samples, 7, Duration::from_secs(20)),
        Some(10.0)
    );
    // Across the restart there is no period; server 8's first is left out.
    assert_eq!(
        median_server_cpu(&samples, 8, Duration::from_secs(100)),
        Some(100.0)
    );
    assert_eq!(
        median_server_cpu(&samples, 9, Duration::from_secs(100)),
        None
    );
}
