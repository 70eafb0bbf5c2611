#!/usr/bin/env bash
# Interop check of the server's recordings: runs the demo (emulated lidars -> edge daemon -> QUIC
# -> server), then
#   1. reads the recorded MCAP session with the official Python `mcap` package and compares
#      its per-topic message counts with what the server reported recording;
#   2. replays the recording with `scan3d replay` and checks that the scans it writes are
#      byte-identical to the ones the demo wrote from the live frames.
#
# Needs python3 with venv, PyPI access (once), and cargo unless $SCAN3D_BIN_DIR holds built
# scan3d-sim and scan3d binaries.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/scan3d-demo-check.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT

if [[ -n "${SCAN3D_BIN_DIR:-}" ]]; then
    bin="$SCAN3D_BIN_DIR"
else
    (cd "$root" && cargo build --release --bin scan3d-sim --bin scan3d)
    bin="${CARGO_TARGET_DIR:-$root/target}/release"
fi

echo "== demo into $tmp/out"
"$bin/scan3d-sim" demo --out "$tmp/out" --seconds 10
sessions=("$tmp"/out/session/sessions/sim-edge/*)
[[ ${#sessions[@]} -eq 1 ]] || { echo "expected one recorded session, found ${#sessions[@]}" >&2; exit 1; }
session="${sessions[0]}"

echo "== python mcap reads $session"
python3 -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install --quiet --disable-pip-version-check mcap
"$tmp/venv/bin/python" "$here/mcap_check.py" "$session" --expect "$tmp/out/recorded-topics.json" --server-made /scan3d/timesync --complete

echo "== scan3d replay reproduces the live scans"
"$bin/scan3d" replay "$session" --out "$tmp/replay"
for ply in "$tmp"/out/scans/*.ply; do
    cmp "$ply" "$tmp/replay/scans/$(basename "$ply")"
    echo "identical: $(basename "$ply")"
done
echo "== scan3d assemble reproduces the demo's static map2 (position 'west', 10 m) from the recordings"
statics=("$tmp"/out/static-sessions/sessions/sim-edge/*)
[[ ${#statics[@]} -eq 3 ]] || { echo "expected three static-scan sessions, found ${#statics[@]}" >&2; exit 1; }
"$bin/scan3d" assemble "${statics[@]}" --position west --max-range 10 --out "$tmp/map2.scans"
cmp "$tmp/map2.scans" "$tmp/out/clouds/map2.scans"
echo "identical: map2.scans"

echo "== OctoMap's tools"
bash "$here/octomap_tools.sh" "$tmp/out"
echo "demo session check passed"
