//! Speed of `scan3d_map::eval` (issue 6): all metrics on geb079_sim at 0.05 m, its `.ot`
//! (2.76 M leaves) against its `.bt` (1.67 M leaves), both made with the octree module; target
//! ≤ 50 ms after loading, loading ≥ 100 M nodes/s. Printed beside OctoMap's
//! `benches/octomap_bench.cpp`'s `cmp` on the same pair (compiled with g++ -O2 -DNDEBUG against
//! Debian's liboctomap-dev; skipped with a message when that is not possible).
//!
//! `cargo bench -p scan3d-map --bench eval`. Times are the best of `EVAL_BENCH_REPS`
//! (default 7) runs, as the machine is shared. The two map files are built once and cached in
//! the target directory.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use common::{octomap_bench, octomap_data};

use scan3d_map::eval::{LeafMap, evaluate};
use scan3d_map::octree::{Octree, Resolution, SensorModel, VoxelMap, read_graph};

fn best<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::MAX;
    let mut out = None;
    for _ in 0..reps {
        let t = Instant::now();
        let v = f();
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(v);
    }
    (best, out.expect("reps > 0"))
}

/// geb079_sim at 0.05 m as (.ot, .bt) files, built with the octree module on first use.
fn maps(dir: &Path) -> (PathBuf, PathBuf) {
    let ot = dir.join("geb079_sim_0.05.ot");
    let bt = dir.join("geb079_sim_0.05.bt");
    if ot.exists() && bt.exists() {
        return (ot, bt);
    }
    let graph = octomap_data("derived/geb079_sim.graph");
    let bytes = std::fs::read(&graph).expect("read geb079_sim.graph");
    let bundles = read_graph(&bytes).expect("geb079_sim.graph parses");
    let t = Instant::now();
    let mut map = VoxelMap::new(
        Resolution::new(0.05).expect("valid"),
        SensorModel::default(),
    );
    for s in &bundles {
        map.insert_bundle(s, -1.0);
    }
    let tree = map.to_octree();
    println!(
        "built geb079_sim at 0.05 m in {:.2} s (cached in {})",
        t.elapsed().as_secs_f64(),
        dir.display()
    );
    std::fs::write(&ot, tree.to_ot_bytes()).expect("write .ot");
    std::fs::write(&bt, tree.to_bt_bytes()).expect("write .bt");
    (ot, bt)
}

/// Best "read" and "compare" seconds of `octomap_bench cmp a b` over `reps` runs.
fn octomap_cmp(exe: &Path, a: &Path, b: &Path, reps: usize) -> Option<(f64, f64)> {
    let secs_after = |line: &str, key: &str| -> Option<f64> {
        let rest = &line[line.find(key)? + key.len()..];
        rest.split_whitespace().next()?.parse().ok()
    };
    let (mut read, mut cmp) = (f64::MAX, f64::MAX);
    for _ in 0..reps {
        let out = Command::new(exe).arg("cmp").arg(a).arg(b).output().ok()?;
        let text = String::from_utf8_lossy(&out.stdout);
        let line = text.lines().find(|l| l.starts_with("cmp "))?;
        read = read.min(secs_after(line, "read ")?);
        cmp = cmp.min(secs_after(line, "compare ")?);
    }
    Some((read, cmp))
}

fn main() {
    let reps: usize = std::env::var("EVAL_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(7)
        .max(1);
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    let (ot_path, bt_path) = maps(&dir);
    let ot_bytes = std::fs::read(&ot_path).expect("read .ot");
    let bt_bytes = std::fs::read(&bt_path).expect("read .bt");
    let (t_ot, ot) = best(reps, || {
        Octree::read(&ot_bytes, SensorModel::default()).expect("our .ot reads")
    });
    let (t_bt, bt) = best(reps, || {
        Octree::read(&bt_bytes, SensorModel::default()).expect("our .bt reads")
    });
    println!(
        "Octree::read .ot: {} nodes / {} leaves in {t_ot:.4} s = {:.1} M nodes/s; \
         .bt: {} nodes / {} leaves in {t_bt:.4} s = {:.1} M nodes/s (octree module, for comparison)",
        ot.num_nodes(),
        ot.num_leaves(),
        ot.num_nodes() as f64 / t_ot / 1e6,
        bt.num_nodes(),
        bt.num_leaves(),
        bt.num_nodes() as f64 / t_bt / 1e6,
    );
    let (t_lot, lot) = best(reps, || {
        LeafMap::read(&ot_bytes, SensorModel::default()).expect("our .ot reads")
    });
    let (t_lbt, lbt) = best(reps, || {
        LeafMap::read(&bt_bytes, SensorModel::default()).expect("our .bt reads")
    });
    println!(
        "load for eval (LeafMap::read): .ot {t_lot:.4} s = {:.1} M nodes/s, .bt {t_lbt:.4} s = {:.1} M nodes/s (target >= 100)",
        lot.num_nodes() as f64 / t_lot / 1e6,
        lbt.num_nodes() as f64 / t_lbt / 1e6,
    );
    let (t_eval, m) = best(reps, || evaluate(&lot, &lbt, None).expect("evaluates"));
    println!(
        "eval .ot vs .bt (all metrics): {:.1} ms (target <= 50 ms; paper: 75 ms for 9 979 nodes); \
         |U| {} voxels, |C| {}, {} distinct value pairs",
        t_eval * 1e3,
        m.voxels,
        m.log_odds.common_voxels,
        distinct_pairs(&lot, &lbt),
    );
    println!(
        "  KLD sum {:.6e}, IoU occ {:?} free {:?} weighted {:.6}, confusion {:?}",
        m.log_odds.sum, m.iou.occupied, m.iou.free, m.iou.weighted, m.confusion
    );
    if std::env::var_os("EVAL_BENCH_NO_OCTOMAP").is_some() {
        println!("octomap_bench cmp: skipped (EVAL_BENCH_NO_OCTOMAP set)");
        return;
    }
    if let Some(exe) = octomap_bench("octomap_bench_eval") {
        match octomap_cmp(&exe, &ot_path, &bt_path, reps.min(3)) {
            Some((read, cmp)) => println!(
                "octomap_bench cmp on the same pair: read {:.4} s ({:.1} M nodes/s), confusion only {:.1} ms; \
                 ours: read {:.4} s, all metrics {:.1} ms",
                read,
                (ot.num_nodes() + bt.num_nodes()) as f64 / read / 1e6,
                cmp * 1e3,
                t_lot + t_lbt,
                t_eval * 1e3
            ),
            None => println!("octomap_bench cmp: run failed"),
        }
    }
}

fn distinct_pairs(a: &LeafMap, b: &LeafMap) -> usize {
    scan3d_map::eval::compare(
        a,
        b,
        None,
        [
            scan3d_map::eval::Role::Reference,
            scan3d_map::eval::Role::Target,
        ],
    )
    .map_or(0, |c| c.pairs.len())
}
