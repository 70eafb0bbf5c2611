//! The whole `scan3d map` process against OctoMap's own whole-process tool, `graph2tree`
//! (octomap-tools), on the same `.graph` in the same run: read the file, insert every scan,
//! write the `.bt`. `cargo bench -p scan3d-server --bench map_process`.
//!
//! Process start-up, parsing and writing count here, unlike `scan3d-map`'s octree bench
//! (insertion only). `graph2tree` also writes two `.ot` files and prints statistics, which
//! `scan3d map` does not; its insertion dominates its time. Both `.bt` files are compared
//! byte for byte. Times are the best of `MAP_BENCH_REPS` (default 5) runs, wall and child
//! CPU; `MAP_BENCH_RES=0.2,0.1` picks the resolutions (default 0.05,0.1,0.2). Without
//! `graph2tree` on PATH only ours is timed (a failure with `SCAN3D_REQUIRE_OCTOMAP=1`).

#[path = "../../map/tests/common/mod.rs"]
mod testdata;

use std::path::Path;
use std::process::Command;
use std::time::Instant;

/// CPU seconds used by waited-for children so far (user + system).
fn children_cpu() -> f64 {
    // SAFETY: getrusage writes one `rusage` into the zeroed struct it is given.
    let usage = unsafe {
        let mut u: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_CHILDREN, &mut u);
        u
    };
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    secs(usage.ru_utime) + secs(usage.ru_stime)
}

/// Best wall and best child-CPU seconds of `reps` runs of `exe args`; panics with the tool's
/// stderr if a run fails.
fn best_run(reps: usize, exe: &Path, args: &[&str]) -> (f64, f64) {
    let (mut wall, mut cpu) = (f64::MAX, f64::MAX);
    for _ in 0..reps {
        let (t, c) = (Instant::now(), children_cpu());
        let out = Command::new(exe)
            .args(args)
            .output()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", exe.display()));
        let (dt, dc) = (t.elapsed().as_secs_f64(), children_cpu() - c);
        assert!(
            out.status.success(),
            "{} {args:?} failed: {}",
            exe.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        wall = wall.min(dt);
        cpu = cpu.min(dc);
    }
    (wall, cpu)
}

fn main() {
    let reps: usize = std::env::var("MAP_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5)
        .max(1);
    let resolutions: Vec<f64> = std::env::var("MAP_BENCH_RES")
        .ok()
        .map(|v| v.split(',').filter_map(|r| r.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![0.05, 0.1, 0.2]);
    let graph = testdata::octomap_data("derived/geb079_sim.graph");
    let graph_s = graph.to_string_lossy().into_owned();
    let ours = Path::new(env!("CARGO_BIN_EXE_scan3d"));
    let octomap = testdata::octomap_tool("graph2tree");
    let dir = tempfile::tempdir().expect("temp dir");
    println!(
        "input geb079_sim.graph ({} bytes); whole processes, best of {reps}",
        std::fs::metadata(&graph).map_or(0, |m| m.len())
    );
    for res in resolutions {
        let r = format!("{res}");
        let our_bt = dir.path().join(format!("ours_{r}.bt"));
        let our_bt_s = our_bt.to_string_lossy().into_owned();
        let (t, c) = best_run(
            reps,
            ours,
            &[
                "map",
                &graph_s,
                "--resolution",
                &r,
                "--out",
                &our_bt_s,
                "--quiet",
            ],
        );
        println!("ours    res {r}: scan3d map {t:.4} s (cpu {c:.4} s)");
        let Some(g2t) = &octomap else {
            continue;
        };
        let their_bt = dir.path().join(format!("octomap_{r}.bt"));
        let their_bt_s = their_bt.to_string_lossy().into_owned();
        let (to, co) = best_run(reps, g2t, &["-i", &graph_s, "-o", &their_bt_s, "-res", &r]);
        let same = std::fs::read(&our_bt).ok() == std::fs::read(&their_bt).ok();
        println!(
            "octomap res {r}: graph2tree {to:.4} s (cpu {co:.4} s); ratio octomap/ours: {:.1}x (cpu {:.1}x); .bt files {}",
            to / t,
            co / c,
            if same { "identical" } else { "DIFFER" }
        );
    }
}
