#!/usr/bin/env bash
# The long fuzz run (fuzz/README.md): each target for FUZZ_SECONDS of wall time (default 600),
# one after another, at nice 10, in libFuzzer's fork mode with one job at a time (`-fork=1`), so
# that a crash, timeout or OOM is counted and saved (fuzz/artifacts/<target>/) and the run goes
# on. Each target's log is fuzz/long/<target>.log; the summary table (executions, crashes,
# timeouts, OOMs from the last status line) is printed at the end and written to
# fuzz/long/summary.md.
#
#   fuzz/long.sh                     # every target, 600 s each
#   FUZZ_SECONDS=3600 fuzz/long.sh bt ot
#   fuzz/long.sh --summary           # only print the table of the logs already there
set -euo pipefail
cd "$(dirname "$0")"
secs=${FUZZ_SECONDS:-600}
flags=(--sanitizer none --debug-assertions)
mkdir -p long

summary() {
  echo "| target | executions | crashes | timeouts | OOMs | seconds |"
  echo "| --- | ---: | ---: | ---: | ---: | ---: |"
  for log in long/*.log; do
    local t line
    t=$(basename "$log" .log)
    # Fork mode: `#N: cov: … exec/s … oom/timeout/crash: a/b/c time: Ts job: …`.
    line=$(grep -E '^#[0-9]+: cov:' "$log" | tail -n 1 || true)
    if [ -z "$line" ]; then
      echo "| $t | (no status line) | | | | |"
      continue
    fi
    echo "$line" | sed -E 's/^#([0-9]+): .*oom\/timeout\/crash: ([0-9]+)\/([0-9]+)\/([0-9]+) time: ([0-9]+)s.*/| '"$t"' | \1 | \4 | \3 | \2 | \5 |/'
  done
}

if [ "${1:-}" = "--summary" ]; then
  summary
  exit 0
fi

if [ $# -gt 0 ]; then
  targets=("$@")
else
  mapfile -t targets < <(cargo +nightly fuzz list)
fi
cargo +nightly fuzz build "${flags[@]}"
for target in "${targets[@]}"; do
  mkdir -p "corpus/$target" "artifacts/$target"
  echo "== $target: $secs s"
  nice -n 10 cargo +nightly fuzz run "${flags[@]}" "$target" "corpus/$target" -- \
    -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 \
    -max_total_time="$secs" -timeout=30 -rss_limit_mb=2048 \
    >"long/$target.log" 2>&1 || true
done
summary | tee long/summary.md
