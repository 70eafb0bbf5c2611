//! The whole `scan3d-edge` daemon's CPU cost at full sensor rate, with the real release
//! binaries: `scan3d pair` and `scan3d serve` on loopback, `scan3d-sim rig` (static head: the
//! RPLidar and the Sweep on ptys, the IMU at 200 Hz and the motor HAT behind the I2C socket),
//! and `scan3d-edge` on the rig's `edge.toml` (the operator flow of `tests/rig_e2e.rs`, through
//! [`scan3d_tests::operator`]).
//!
//! `cargo bench -p scan3d-tests --bench edge_daemon [-- --window 60 --warmup 10 --strace 20]`
//!
//! After the warm-up it samples `/proc/PID/stat` and `/proc/PID/task/*/{stat,schedstat}` over
//! the window and prints the process's CPU as a share of one core (user and kernel), and the
//! same per thread, by the thread's name (`rplidar`, `sweep`, `imu`, `stepper`, `uplink`, …),
//! with the sensors' data rates from `scan3d status --json` so the numbers are at full rate.
//! Then, if strace is installed, a second pass attaches `strace -f -ff` to the same daemon and
//! counts system calls per second per thread and per call; strace slows every call down, so
//! its pass reports no CPU figures.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use scan3d_tests::operator::{self, OperatorRig, wait_until};

/// Benchmark the edge daemon's CPU and system calls at full sensor rate on the rig.
#[derive(Debug, Parser)]
struct Args {
    /// Seconds of the CPU window.
    #[arg(long, default_value_t = 60)]
    window: u64,
    /// Seconds of streaming before the window starts.
    #[arg(long, default_value_t = 10)]
    warmup: u64,
    /// Seconds of the strace pass (0: none).
    #[arg(long, default_value_t = 20)]
    strace: u64,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// One thread's counters at one moment.
#[derive(Debug, Clone)]
struct ThreadSample {
    name: String,
    /// Clock ticks in user mode.
    utime: u64,
    /// Clock ticks in the kernel.
    stime: u64,
    /// Nanoseconds on a CPU (schedstat), finer than the ticks.
    runtime_ns: u64,
}

/// `comm`, utime and stime of a `stat` line (comm may hold spaces, so split at the last ')').
fn parse_stat(text: &str) -> Option<(String, u64, u64)> {
    let open = text.find('(')?;
    let close = text.rfind(')')?;
    let name = text[open + 1..close].to_owned();
    let fields: Vec<&str> = text[close + 1..].split_whitespace().collect();
    // Fields after comm start at field 3 (state); utime is field 14, stime field 15.
    let utime = fields.get(11)?.parse().ok()?;
    let stime = fields.get(12)?.parse().ok()?;
    Some((name, utime, stime))
}

/// Every live thread of `pid` by its id.
fn threads(pid: u32) -> BTreeMap<u32, ThreadSample> {
    let mut out = BTreeMap::new();
    let Ok(entries) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return out;
    };
    for entry in entries.flatten() {
        let Some(tid) = entry.file_name().to_str().and_then(|t| t.parse().ok()) else {
            continue;
        };
        let dir = entry.path();
        let Some((name, utime, stime)) = std::fs::read_to_string(dir.join("stat"))
            .ok()
            .and_then(|t| parse_stat(&t))
        else {
            continue;
        };
        let runtime_ns = std::fs::read_to_string(dir.join("schedstat"))
            .ok()
            .and_then(|t| t.split_whitespace().next()?.parse().ok())
            .unwrap_or(0);
        out.insert(
            tid,
            ThreadSample {
                name,
                utime,
                stime,
                runtime_ns,
            },
        );
    }
    out
}

/// The whole process's utime and stime (ticks; threads that ended included).
fn process_ticks(pid: u32) -> (u64, u64) {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|t| parse_stat(&t))
        .map(|(_, u, s)| (u, s))
        .expect("the edge daemon's /proc/PID/stat")
}

fn clock_ticks_per_s() -> f64 {
    Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|out| String::from_utf8(out.stdout).ok()?.trim().parse().ok())
        .unwrap_or(100.0)
}

/// `(kind, samples/s, frames/s)` of every sensor of the edge, from `scan3d status --json`.
fn sensor_rates(rig: &OperatorRig) -> Vec<(String, f64, f64)> {
    let out = rig.scan3d(&["status", "--json"]);
    let Ok(status) = serde_json::from_slice::<serde_json::Value>(&out.stdout) else {
        return Vec::new();
    };
    status["edges"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|edge| edge["sensors"].as_array().cloned().unwrap_or_default())
        .filter(|sensor| sensor["state"] == "streaming")
        .map(|sensor| {
            (
                sensor["kind"].as_str().unwrap_or("?").to_owned(),
                sensor["samples_per_s"].as_f64().unwrap_or(0.0),
                sensor["frames_per_s"].as_f64().unwrap_or(0.0),
            )
        })
        .collect()
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|text| text.split_whitespace().next().map(str::to_owned))
        .unwrap_or_else(|| "?".into())
}

/// CPU of one thread name over the window: (share of one core from schedstat, user s, kernel s).
#[derive(Debug, Default, Clone, Copy)]
struct Cpu {
    threads: usize,
    runtime_s: f64,
    user_s: f64,
    kernel_s: f64,
}

fn main() {
    let args = Args::parse();
    operator::build_binaries(&["scan3d-server", "scan3d-edge", "scan3d-hw-sim"]);
    let dir = tempfile::tempdir().expect("temp dir");
    let rig = OperatorRig::start(dir.path(), "edge-bench-01");
    let pid = rig.edge.pid();
    wait_until(
        "the edge's sensors to stream",
        Duration::from_secs(90),
        || {
            let streaming = sensor_rates(&rig);
            ["rplidar", "sweep", "imu"]
                .iter()
                .all(|kind| streaming.iter().any(|(k, _, _)| k == kind))
        },
    );
    println!(
        "edge daemon bench: scan3d-edge (pid {pid}) on scan3d-sim rig (static head, IMU at 200 Hz), \
         scan3d serve on loopback; warm-up {} s, window {} s, load average {}",
        args.warmup,
        args.window,
        load_average()
    );
    std::thread::sleep(Duration::from_secs(args.warmup));

    let ticks = clock_ticks_per_s();
    let before = threads(pid);
    let (user0, kernel0) = process_ticks(pid);
    let started = Instant::now();
    std::thread::sleep(Duration::from_secs(args.window));
    let after = threads(pid);
    let (user1, kernel1) = process_ticks(pid);
    let wall = started.elapsed().as_secs_f64();
    let rates = sensor_rates(&rig);

    let user = (user1 - user0) as f64 / ticks;
    let kernel = (kernel1 - kernel0) as f64 / ticks;
    println!();
    println!("data streamed (scan3d status --json at the end of the window):");
    println!("| sensor | samples/s | frames/s |");
    println!("| --- | ---: | ---: |");
    for (kind, samples, frames) in &rates {
        println!("| {kind} | {samples:.0} | {frames:.1} |");
    }
    println!();
    println!(
        "whole process over {wall:.1} s: {:.2} % of one core ({:.2} s user, {:.2} s kernel)",
        100.0 * (user + kernel) / wall,
        user,
        kernel
    );
    let mut by_name: BTreeMap<String, Cpu> = BTreeMap::new();
    for (tid, end) in &after {
        let start = before.get(tid);
        let delta = |f: fn(&ThreadSample) -> u64| f(end) - start.map_or(0, f);
        let cpu = by_name.entry(end.name.clone()).or_default();
        cpu.threads += 1;
        cpu.runtime_s += delta(|t| t.runtime_ns) as f64 * 1e-9;
        cpu.user_s += delta(|t| t.utime) as f64 / ticks;
        cpu.kernel_s += delta(|t| t.stime) as f64 / ticks;
    }
    let mut rows: Vec<(String, Cpu)> = by_name.into_iter().collect();
    rows.sort_by(|a, b| b.1.runtime_s.total_cmp(&a.1.runtime_s));
    println!();
    println!("per thread (CPU time on a core from schedstat; user/kernel from stat ticks):");
    println!("| thread | n | % of one core | user s | kernel s |");
    println!("| --- | ---: | ---: | ---: | ---: |");
    for (name, cpu) in &rows {
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.2} |",
            cpu.threads,
            100.0 * cpu.runtime_s / wall,
            cpu.user_s,
            cpu.kernel_s
        );
    }

    if args.strace > 0 {
        strace_pass(pid, args.strace, &rig.path("strace"));
    }
    if std::env::var_os("EDGE_BENCH_KEEP_LOG").is_some() {
        println!("\nedge log:\n{}", rig.edge_log());
    }
}

/// Attaches strace to every thread of `pid` for `seconds`, then counts system calls per second
/// per thread and per call.
fn strace_pass(pid: u32, seconds: u64, out: &Path) {
    let strace = ["/usr/bin/strace", "/bin/strace"]
        .into_iter()
        .map(PathBuf::from)
        .find(|p| p.exists());
    let Some(strace) = strace else {
        println!("\nstrace is not installed: no system call counts");
        return;
    };
    let names: BTreeMap<u32, String> = threads(pid)
        .into_iter()
        .map(|(tid, t)| (tid, t.name))
        .collect();
    std::fs::create_dir_all(out).expect("strace directory");
    let prefix = out.join("trace");
    let mut child = Command::new(&strace)
        .args(["-f", "-ff", "-qq", "-s", "0", "-e", "signal=none", "-o"])
        .arg(&prefix)
        .args(["-p", &pid.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start strace");
    let started = Instant::now();
    std::thread::sleep(Duration::from_secs(seconds));
    let _ = nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(child.id() as i32),
        nix::sys::signal::Signal::SIGINT,
    );
    let _ = child.wait();
    let wall = started.elapsed().as_secs_f64();

    // trace.TID: one line per call, `name(args) = result`; a call interrupted by another
    // thread's output shows as `name(… <unfinished ...>` and `<... name resumed>`: count the
    // first only.
    let mut per_thread: BTreeMap<String, BTreeMap<String, u64>> = BTreeMap::new();
    let mut per_call: BTreeMap<String, u64> = BTreeMap::new();
    for entry in std::fs::read_dir(out).expect("strace output").flatten() {
        let file = entry.file_name().to_string_lossy().into_owned();
        let Some(tid) = file
            .strip_prefix("trace.")
            .and_then(|t| t.parse::<u32>().ok())
        else {
            continue;
        };
        let name = names
            .get(&tid)
            .cloned()
            .unwrap_or_else(|| format!("thread {tid}"));
        let text = std::fs::read_to_string(entry.path()).unwrap_or_default();
        let calls = per_thread.entry(name).or_default();
        for line in text.lines() {
            let Some(call) = line.split('(').next() else {
                continue;
            };
            if call.is_empty() || !call.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                continue;
            }
            *calls.entry(call.to_owned()).or_default() += 1;
            *per_call.entry(call.to_owned()).or_default() += 1;
        }
    }
    let total: u64 = per_call.values().sum();
    println!();
    println!(
        "system calls over {wall:.1} s with strace attached (strace slows every call: no CPU \
         figures from this pass): {:.0} /s",
        total as f64 / wall
    );
    println!("| thread | calls/s | top calls (/s) |");
    println!("| --- | ---: | --- |");
    let mut threads: Vec<(String, BTreeMap<String, u64>)> = per_thread.into_iter().collect();
    threads.sort_by_key(|(_, calls)| std::cmp::Reverse(calls.values().sum::<u64>()));
    for (name, calls) in &threads {
        let sum: u64 = calls.values().sum();
        let mut top: Vec<(&String, &u64)> = calls.iter().collect();
        top.sort_by_key(|(_, n)| std::cmp::Reverse(**n));
        let top: Vec<String> = top
            .iter()
            .take(5)
            .map(|(call, n)| format!("{call} {:.0}", **n as f64 / wall))
            .collect();
        println!("| {name} | {:.0} | {} |", sum as f64 / wall, top.join(", "));
    }
    println!();
    println!("| system call | calls/s |");
    println!("| --- | ---: |");
    let mut calls: Vec<(String, u64)> = per_call.into_iter().collect();
    calls.sort_by_key(|(_, n)| std::cmp::Reverse(*n));
    for (call, n) in calls.iter().take(15) {
        println!("| {call} | {:.0} |", *n as f64 / wall);
    }
}
