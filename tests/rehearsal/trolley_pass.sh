#!/bin/bash
# The trolley rehearsal of README.md, measured: `scan3d serve` + `scan3d-sim rig --trolley` (the
# default path: 20 s at rest, about 65 s around the table, then at rest) + the real
# `scan3d-edge`; a pass opened at the path's start pose while the trolley rests; a snapshot once
# the truth says `# end of path`; `scan3d traj-eval` of the pass against the truth. About two
# minutes. Needs the release binaries: `cargo build --release`, then
#   tests/rehearsal/trolley_pass.sh [RUN_DIR]
set -u
B=${SCAN3D_BIN_DIR:-$(cd "$(dirname "$0")/../.." && pwd)/target/release}
R=${1:-/tmp/scan3d-trolley-pass}
rm -rf "$R"; mkdir -p "$R"
cd "$R"
$B/scan3d pair --dir "$R/pki" --edge edge-sim-01 > pair.log 2>&1
cat > server.toml <<TOML
listen = "127.0.0.1:4473"
pki_dir = "$R/pki"
data_dir = "$R/data"
TOML
$B/scan3d serve --config server.toml > serve.log 2>&1 &
echo $! > serve.pid
$B/scan3d-sim rig --dir "$R/head" --trolley --truth "$R/truth.tum" > rig.log 2>&1 &
echo $! > rig.pid
for i in $(seq 1 50); do [ -f "$R/head/edge.toml" ] && break; sleep 0.2; done
{ printf 'device_name = "edge-sim-01"\nstate_dir = "%s/edge-state"\n' "$R"; cat "$R/head/edge.toml"
  printf '[uplink]\nserver = "127.0.0.1:4473"\nserver_name = "localhost"\npki_dir = "%s/pki/edges/edge-sim-01"\n' "$R"
} > edge.toml
$B/scan3d-edge --config edge.toml > edge.log 2>&1 &
echo $! > edge.pid
# The trolley rests 20 s from the rig's start: open the pass at its start pose a few seconds in.
sleep 8
$B/scan3d trolley start --config server.toml --edge edge-sim-01 --at 1.6,0.85,0 --name loop > start.log 2>&1
echo "start rc=$?" >> start.log
for i in $(seq 1 200); do grep -q "end of path" "$R/truth.tum" 2>/dev/null && break; sleep 1; done
sleep 3
$B/scan3d trolley stop --config server.toml --edge edge-sim-01 > stop.log 2>&1
$B/scan3d status --config server.toml --json > status.json 2>&1
sleep 2
$B/scan3d snapshot --config server.toml --edge edge-sim-01 --out "$R/snap" > snap.log 2>&1
$B/scan3d traj-eval "$R/snap/passes/loop/trajectory.tum" "$R/truth.tum" > eval.txt 2>&1
$B/scan3d traj-eval "$R/snap/trajectory.tum" "$R/truth.tum" > eval-all.txt 2>&1
$B/scan3d traj-eval "$R/snap/passes/loop/trajectory_fused.tum" "$R/truth.tum" > eval-fused.txt 2>&1
kill $(cat edge.pid) $(cat rig.pid) $(cat serve.pid) 2>/dev/null
wait 2>/dev/null
cat start.log stop.log eval.txt eval-all.txt eval-fused.txt
ls -l "$R/snap/passes/loop"
