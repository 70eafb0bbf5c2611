//! Insertion and `.bt` read speed of `scan3d_map::octree` against OctoMap 1.9.7 on the same
//! input in the same run (research/octomap.md §8). `cargo bench -p scan3d-map --bench octree`.
//!
//! OctoMap's side is `benches/octomap_bench.cpp`, compiled here with g++ -O2 -DNDEBUG
//! against Debian's liboctomap-dev; without g++ or the headers it is skipped with a message.
//! Times are best of `OCTREE_BENCH_REPS` (default 5) runs, as the machine is shared.
//! `OCTREE_BENCH_NO_OCTOMAP=1` skips OctoMap; `OCTREE_BENCH_WRITE_DIR=d` writes our trees there;
//! `OCTREE_BENCH_RES=0.2,0.1` picks the resolutions (default 0.05,0.1,0.2).

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use common::{octomap_bench, octomap_data};

use scan3d_map::cloud::RayBundle;
use scan3d_map::octree::{Octree, Resolution, SensorModel, VoxelMap, ray_keys, read_graph};

/// Process CPU time in seconds (less sensitive than wall time to other processes on the
/// shared cores; octomap_bench prints the same clock).
fn cpu_now() -> f64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_PROCESS_CPUTIME_ID)
        .map_or(0.0, |t| t.tv_sec() as f64 + t.tv_nsec() as f64 * 1e-9)
}

/// Best wall and best process-CPU seconds of `reps` runs, and the last result.
fn best<T>(reps: usize, mut f: impl FnMut() -> T) -> ((f64, f64), T) {
    let (mut wall, mut cpu) = (f64::MAX, f64::MAX);
    let mut out = None;
    for _ in 0..reps {
        let (t, c) = (Instant::now(), cpu_now());
        let v = f();
        cpu = cpu.min(cpu_now() - c);
        wall = wall.min(t.elapsed().as_secs_f64());
        out = Some(v);
    }
    ((wall, cpu), out.expect("reps > 0"))
}

/// Runs octomap_bench `reps` times and returns the best of the first number after `key`
/// (wall seconds), the best of the number after `cpu_key` on the same line (CPU seconds),
/// and the last stdout.
fn run_octomap(
    exe: &Path,
    args: &[&str],
    key: &str,
    cpu_key: &str,
    reps: usize,
) -> Option<((f64, f64), String)> {
    let (mut wall, mut cpu) = (f64::MAX, f64::MAX);
    let mut last = String::new();
    let first_number = |s: &str| -> Option<f64> {
        s.split(|c: char| c.is_whitespace() || c == ',' || c == ')')
            .find_map(|w| w.parse().ok())
    };
    for _ in 0..reps {
        let out = Command::new(exe).args(args).output().ok()?;
        last = String::from_utf8_lossy(&out.stdout).into_owned();
        let line = last.lines().find(|l| l.contains(key))?;
        let after = &line[line.find(key)? + key.len()..];
        wall = wall.min(first_number(after)?);
        if let Some(i) = after.find(cpu_key) {
            cpu = cpu.min(first_number(&after[i + cpu_key.len()..])?);
        }
    }
    Some(((wall, cpu), last))
}

fn insert_all(bundles: &[RayBundle], res: f64) -> VoxelMap {
    let mut map = VoxelMap::new(Resolution::new(res).expect("valid"), SensorModel::default());
    for s in bundles {
        map.insert_bundle(s, -1.0);
    }
    map
}

fn main() {
    let reps: usize = std::env::var("OCTREE_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5)
        .max(1);
    let graph = octomap_data("derived/geb079_sim.graph");
    let bytes = std::fs::read(&graph).expect("read geb079_sim.graph");
    let bundles = read_graph(&bytes).expect("geb079_sim.graph parses");
    let npts: usize = bundles.iter().map(|s| s.points.len()).sum();
    println!(
        "input geb079_sim.graph: {} bundles, {npts} points; best of {reps}",
        bundles.len()
    );
    let octomap = if std::env::var_os("OCTREE_BENCH_NO_OCTOMAP").is_some() {
        println!("OctoMap: skipped (OCTREE_BENCH_NO_OCTOMAP set)");
        None
    } else {
        octomap_bench("octomap_bench")
    };
    let graph_s = graph.to_string_lossy().into_owned();

    let resolutions: Vec<f64> = std::env::var("OCTREE_BENCH_RES")
        .ok()
        .map(|v| v.split(',').filter_map(|r| r.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![0.05, 0.1, 0.2]);
    for &res in &resolutions {
        let r = Resolution::new(res).expect("valid");
        let ((t_dda, _), keys) = best(reps, || {
            let mut n = 0u64;
            for s in &bundles {
                let o = s.origin.map(|c| c as f32);
                for p in &s.points {
                    ray_keys(&r, o, *p, |_| n += 1);
                }
            }
            n
        });
        println!(
            "ours  res {res}: ray stepping alone: {keys} ray keys ({:.1} per ray) in {t_dda:.4} s = {:.2} ns/key",
            keys as f64 / npts as f64,
            t_dda * 1e9 / keys as f64
        );
        let ((t_ins, c_ins), map) = best(reps, || insert_all(&bundles, res));
        let ((t_tree, _), tree) = best(reps, || map.to_octree());
        if let Some(dir) = std::env::var_os("OCTREE_BENCH_WRITE_DIR") {
            // For checking with OctoMap's own tools (convert_octree, compare_octrees).
            let dir = PathBuf::from(dir);
            let ot = std::fs::write(dir.join(format!("ours_{res}.ot")), tree.to_ot_bytes());
            let bt = std::fs::write(dir.join(format!("ours_{res}.bt")), tree.to_bt_bytes());
            if ot.is_err() || bt.is_err() {
                println!("could not write to {}", dir.display());
            }
        }
        println!(
            "ours  res {res}: insert {t_ins:.4} s (cpu {c_ins:.4} s, {:.2} M pts/s), derive tree {t_tree:.4} s, total {:.4} s; \
             {} voxels, tree {} nodes / {} leaves; memory: map {} B, tree {} B",
            npts as f64 / t_ins / 1e6,
            t_ins + t_tree,
            map.num_voxels(),
            tree.num_nodes(),
            tree.num_leaves(),
            map.memory_bytes(),
            tree.memory_bytes(),
        );
        if let Some(exe) = &octomap {
            let r = format!("{res}");
            match run_octomap(
                exe,
                &["insert", &graph_s, "-res", &r],
                "mode insertPointCloud:",
                "(cpu ",
                reps,
            ) {
                Some(((t, c), out)) => {
                    let mem = out
                        .split("memoryUsage ")
                        .nth(1)
                        .and_then(|s| s.split_whitespace().next())
                        .map_or("?", |s| s.trim_end_matches(|c: char| !c.is_ascii_digit()));
                    println!(
                        "octomap res {res}: insert {t:.4} s (cpu {c:.4} s); memoryUsage {mem} B; \
                         ratio octomap/ours: {:.1}x insert (cpu {:.1}x), {:.1}x insert+tree",
                        t / t_ins,
                        c / c_ins,
                        t / (t_ins + t_tree)
                    );
                }
                None => println!("octomap res {res}: run failed"),
            }
        }
    }

    for name in ["geb079.bt", "reference/geb079_sim_0.08.bt"] {
        let path = octomap_data(name);
        let file = std::fs::read(&path).expect("read a vendored map");
        let ((t, _), tree) = best(reps.max(5), || {
            Octree::read_bt(&file, SensorModel::default()).expect("reads")
        });
        let ((ti, _), leaves) = best(reps.max(5), || {
            tree.leaves().filter(|l| l.log_odds >= 0.0).count()
        });
        println!(
            "ours  read {name}: {} nodes in {t:.4} s = {:.1} M nodes/s; iterate {} leaves ({leaves} occupied) {ti:.4} s",
            tree.num_nodes(),
            tree.num_nodes() as f64 / t / 1e6,
            tree.num_leaves()
        );
        if let Some(exe) = &octomap {
            let p = path.to_string_lossy().into_owned();
            if let Some(((to, _), _)) =
                run_octomap(exe, &["read", &p, "-repeat", "5"], "read min", "cpu min", 1)
            {
                println!(
                    "octomap read {name}: {to:.4} s = {:.1} M nodes/s; ratio {:.1}x",
                    tree.num_nodes() as f64 / to / 1e6,
                    to / t
                );
            }
        }
    }
}
