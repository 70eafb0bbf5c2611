#!/usr/bin/env bash
# Interop check: Slamtec's official SDK (PyPI pyrplidarsdk 0.1.2, which embeds SDK 2.x) reads
# the scan3d-sim RPLidar emulator through a pty, exactly as it would read /dev/ttyUSB0.
#
# Needs: python3 with venv, network access to PyPI (once), cargo (unless $SCAN3D_SIM points at a
# built scan3d-sim binary). Exits with the smoke script's status (0 = pass).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/scan3d-interop.XXXXXX")"
sim_pid=""

cleanup() {
    if [[ -n "$sim_pid" ]] && kill -0 "$sim_pid" 2>/dev/null; then
        kill -TERM "$sim_pid" 2>/dev/null || true
        wait "$sim_pid" 2>/dev/null || true
    fi
    rm -rf "$tmp"
}
trap cleanup EXIT

echo "== venv + pyrplidarsdk==0.1.2 in $tmp/venv"
python3 -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install --quiet --disable-pip-version-check pyrplidarsdk==0.1.2

if [[ -n "${SCAN3D_SIM:-}" ]]; then
    sim="$SCAN3D_SIM"
else
    echo "== cargo build --release --bin scan3d-sim"
    (cd "$root" && cargo build --release --bin scan3d-sim)
    sim="${CARGO_TARGET_DIR:-$root/target}/release/scan3d-sim"
fi
[[ -x "$sim" ]] || { echo "scan3d-sim not found at $sim" >&2; exit 1; }

link="$tmp/ttyRPLIDAR"
echo "== starting $sim device rplidar --link $link --model a1 --seed 1"
"$sim" device rplidar --link "$link" --model a1 --seed 1 >"$tmp/sim.out" 2>"$tmp/sim.log" &
sim_pid=$!

# Wait for the emulator to print the link path (it does so once the link exists).
for _ in $(seq 100); do
    if [[ "$(head -n1 "$tmp/sim.out" 2>/dev/null)" == "$link" ]]; then
        break
    fi
    if ! kill -0 "$sim_pid" 2>/dev/null; then
        echo "scan3d-sim exited early:" >&2
        cat "$tmp/sim.log" >&2
        exit 1
    fi
    sleep 0.1
done
if [[ "$(head -n1 "$tmp/sim.out" 2>/dev/null)" != "$link" ]]; then
    echo "scan3d-sim did not report $link within 10 s" >&2
    cat "$tmp/sim.log" >&2
    exit 1
fi

echo "== pyrplidarsdk smoke test"
status=0
timeout 60 "$tmp/venv/bin/python" "$here/pyrplidarsdk_smoke.py" "$link" --baud 115200 || status=$?
if [[ $status -ne 0 ]]; then
    echo "== emulator log" >&2
    tail -n 40 "$tmp/sim.log" >&2
fi

kill -TERM "$sim_pid" 2>/dev/null || true
sim_status=0
wait "$sim_pid" || sim_status=$?
sim_pid=""
if [[ $sim_status -ne 0 ]]; then
    echo "scan3d-sim exited with status $sim_status" >&2
fi
if [[ -e "$link" || -L "$link" ]]; then
    echo "scan3d-sim left $link behind" >&2
fi
exit "$status"
