#!/usr/bin/env bash
# Fuzz smoke run (fuzz/README.md): writes the seed corpora, builds every target with the nightly
# toolchain, and runs each for a fixed number of executions from its seeds and its committed
# reproducers (fuzz/regressions/<target>/). Fails on the first crash, timeout or OOM.
#
#   fuzz/ci.sh                 # FUZZ_RUNS=20000 executions per target
#   FUZZ_RUNS=1000 fuzz/ci.sh  # quicker
#   fuzz/ci.sh frame ply       # only these targets
set -euo pipefail
cd "$(dirname "$0")"
fuzz_dir=$PWD
runs=${FUZZ_RUNS:-20000}
# Sanitizer off (the code under test has no `unsafe` on these paths; libFuzzer still catches
# panics, aborts, timeouts and the allocation budget's aborts), debug assertions and overflow
# checks on: the build flags of every cargo-fuzz command below must be the same, or it rebuilds.
flags=(--sanitizer none --debug-assertions)
# The smoke run checks for crashes, not speed: the fuzz profile at opt-level 1 with line tables
# only builds in 259–268 s cold instead of 292 s (2 cores, 7 December 2026), and the 20 000 runs per
# target take the same 0–4 s. `long.sh` keeps Cargo.toml's opt-level 3.
export CARGO_PROFILE_RELEASE_OPT_LEVEL=1 CARGO_PROFILE_RELEASE_DEBUG=line-tables-only

if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
  echo "== installing cargo-fuzz"
  cargo install cargo-fuzz --locked
fi

# A workspace test (tests/tests/fuzz_seeds.rs), run with `--workspace` so that it shares the
# workspace's test build (features and profile): after `cargo test --workspace` it builds nothing.
echo "== seeds (tests/tests/fuzz_seeds.rs, stable, the workspace's test build)"
FUZZ_CORPUS_DIR="$fuzz_dir/corpus" \
  cargo test --quiet --manifest-path "$fuzz_dir/../Cargo.toml" --workspace --test fuzz_seeds -- \
  --ignored --exact write_fuzz_seeds --nocapture

if [ $# -gt 0 ]; then
  targets=("$@")
else
  mapfile -t targets < <(cargo +nightly fuzz list)
fi

echo "== build (nightly, fuzz/target)"
cargo +nightly fuzz build "${flags[@]}"

for target in "${targets[@]}"; do
  echo "== $target: $runs runs"
  mkdir -p "corpus/$target" "regressions/$target" "artifacts/$target"
  start=$SECONDS
  # The first corpus directory receives new inputs; regressions/ is only read.
  cargo +nightly fuzz run "${flags[@]}" "$target" "corpus/$target" "regressions/$target" -- \
    -runs="$runs" -timeout=30 -rss_limit_mb=2048 -print_final_stats=1 2>"artifacts/$target/ci.log" ||
    { tail -n 60 "artifacts/$target/ci.log"; echo "fuzz target $target failed (log: fuzz/artifacts/$target/ci.log)"; exit 1; }
  grep -E '^(stat::number_of_executed_units|stat::peak_rss_mb)' "artifacts/$target/ci.log" | tr '\n' ' '
  echo "($((SECONDS - start)) s)"
done
echo "== fuzz smoke run: ${#targets[@]} targets, $runs runs each, no crash"
