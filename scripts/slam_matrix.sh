#!/usr/bin/env bash
# The SLAM matrix of issue 22: `scan3d slam` over every benchmark log, with and without
# odometry, full range and clipped to 6 m (`--max-range 6`), at map_update_distance 0.3 / 0.4 /
# 0.5 (the top-level key of `scan3d slam --config`), each scored with `scan3d slam-eval`
# (Kümmerle relations, mean absolute translational error, no loop closure).
#
# Usage: scripts/slam_matrix.sh [SCAN3D_BINARY] [OUT_DIR] [LOG...]
#   SCAN3D_BINARY  default target/release/scan3d (build: cargo build --release -p scan3d-server)
#   OUT_DIR        default /tmp/slam_matrix (trajectories, per-run TSV rows, the summary)
#   LOG            intel aces fr079 fr-clinic (default: all; each read from testdata/slam/)
# Prints one row per run (log, odometry, range, map_update_distance, error, wall seconds) and a
# summary: per log and mode the default's (0.4) error, the median and the worst of the three.
# Environment: SLAM_MATRIX_DATA overrides the data folder (e.g. full logs outside the
# repository; each LOG then needs LOG.clf[.gz] and LOG.relations there); SLAM_MATRIX_MODES
# restricts the modes (default "odometry no-odometry"); SLAM_MATRIX_RANGES the ranges (default
# "full 6"); SLAM_MATRIX_DISTANCES the map_update_distances (default "0.3 0.4 0.5");
# SLAM_MATRIX_CONFIG names a slam.toml whose keys every run takes too (it must not
# set map_update_distance); SLAM_MATRIX_ARGS adds arguments to every `scan3d slam` run (e.g.
# "--odometry-error 0,0.02,0" to test the matcher against wheels that drift 1.1° per metre, or
# "--every 2" against a log written half as often).
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
bin="${1:-$here/target/release/scan3d}"
out="${2:-/tmp/slam_matrix}"
shift $(( $# > 2 ? 2 : $# )) || true
logs=("$@")
[ ${#logs[@]} -eq 0 ] && logs=(intel aces fr079 fr-clinic)
data="${SLAM_MATRIX_DATA:-$here/testdata/slam}"
mkdir -p "$out"
rows="$out/rows.tsv"
: > "$rows"
for log in "${logs[@]}"; do
  clf="$data/$log.clf.gz"; [ -f "$clf" ] || clf="$data/$log.clf"
  rel="$data/$log.relations"
  for odo in ${SLAM_MATRIX_MODES:-odometry no-odometry}; do
    for range in ${SLAM_MATRIX_RANGES:-full 6}; do
      for d in ${SLAM_MATRIX_DISTANCES:-0.3 0.4 0.5}; do
        cfg="$out/mud_$d.toml"; { echo "map_update_distance = $d"; [ -z "${SLAM_MATRIX_CONFIG:-}" ] || cat "$SLAM_MATRIX_CONFIG"; } > "$cfg"
        traj="$out/${log}_${odo}_${range}_$d.txt"
        args=(slam "$clf" --out "$traj" --config "$cfg" --quiet "--$odo")
        [ "$range" = 6 ] && args+=(--max-range 6)
        # shellcheck disable=SC2206 # the extra arguments are split on purpose
        [ -z "${SLAM_MATRIX_ARGS:-}" ] || args+=(${SLAM_MATRIX_ARGS})
        start=$(date +%s.%N)
        "$bin" "${args[@]}" > /dev/null
        wall=$(echo "$(date +%s.%N) - $start" | bc)
        err=$("$bin" slam-eval --json "$traj" "$rel" | python3 -c 'import json,sys; print("%.4f" % json.load(sys.stdin)["abs_trans_m"]["mean"])')
        printf '%s\t%s\t%s\t%s\t%s\t%.1f\n' "$log" "$odo" "$range" "$d" "$err" "$wall" | tee -a "$rows"
      done
    done
  done
done
echo
echo "log	mode	range	default(0.4)	median	worst"
python3 - "$rows" <<'PY'
import sys, collections
runs = collections.defaultdict(dict)
for line in open(sys.argv[1]):
    log, odo, rng, d, err, _ = line.split("\t")
    runs[(log, odo, rng)][d] = float(err)
for (log, odo, rng), by_d in runs.items():
    errs = sorted(by_d.values())
    print(f"{log}\t{odo}\t{rng}\t{by_d.get('0.4', float('nan')):.4f}\t{errs[len(errs)//2]:.4f}\t{errs[-1]:.4f}")
PY
