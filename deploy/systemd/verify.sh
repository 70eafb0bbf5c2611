#!/usr/bin/env bash
# Checks the scan3d systemd units with `systemd-analyze verify` against the built binaries.
#
#   deploy/systemd/verify.sh PATH/TO/scan3d-edge PATH/TO/scan3d
#
# verify insists that ExecStart= binaries exist, so the units are copied to a temporary directory
# with /usr/local/bin/scan3d-edge and /usr/local/bin/scan3d replaced by the given binaries. Any
# diagnostic that names one of the units counts as a failure (verify exits 0 on mere warnings such
# as an unknown key). scan3d.sysusers is checked with `systemd-sysusers --dry-run` against an empty
# root. Exits 0 if all is clean (or, with a "skipped" note, if systemd-analyze is not installed),
# 1 on problems, 2 on bad usage.
set -euo pipefail

if [[ $# -ne 2 ]]; then
    echo "usage: $0 SCAN3D_EDGE_BINARY SCAN3D_BINARY" >&2
    exit 2
fi
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
for bin in "$1" "$2"; do
    [[ -f "$bin" && -x "$bin" ]] || { echo "not an executable file: $bin" >&2; exit 2; }
done
edge_bin="$(realpath -e "$1")"
server_bin="$(realpath -e "$2")"
if ! command -v systemd-analyze >/dev/null 2>&1; then
    echo "systemd-analyze not installed: unit check skipped" >&2
    exit 0
fi

tmp="$(mktemp -d "${TMPDIR:-/tmp}/scan3d-units.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT

units=(scan3d-edge.service scan3d-server.service)
for unit in "${units[@]}"; do
    sed -e "s|^ExecStart=/usr/local/bin/scan3d-edge |ExecStart=$edge_bin |" \
        -e "s|^ExecStart=/usr/local/bin/scan3d |ExecStart=$server_bin |" \
        "$here/$unit" >"$tmp/$unit"
    if grep -q '^ExecStart=/usr/local/bin/' "$tmp/$unit"; then
        echo "$unit: ExecStart not substituted (unexpected binary path)" >&2
        exit 1
    fi
done

status=0
echo "== systemd-analyze verify ${units[*]}"
set +e
output="$(cd "$tmp" && SYSTEMD_LOG_COLOR=0 systemd-analyze verify "${units[@]/#/$tmp/}" 2>&1)"
verify_status=$?
set -e
[[ -n "$output" ]] && printf '%s\n' "$output"
if [[ $verify_status -ne 0 ]]; then
    echo "systemd-analyze verify failed with status $verify_status" >&2
    status=1
fi
# Diagnostics about other units on this machine are not ours to fix; ours name our files.
ours="$(printf '%s\n' "$output" | grep -E "scan3d-(edge|server)\.service" || true)"
if [[ -n "$ours" ]]; then
    echo "systemd-analyze verify reported problems in the scan3d units:" >&2
    printf '%s\n' "$ours" >&2
    status=1
fi

if command -v systemd-sysusers >/dev/null 2>&1; then
    echo "== systemd-sysusers --dry-run scan3d.sysusers"
    mkdir -p "$tmp/root/etc"
    set +e
    sysusers_output="$(SYSTEMD_LOG_COLOR=0 systemd-sysusers --dry-run --root="$tmp/root" "$here/scan3d.sysusers" 2>&1)"
    sysusers_status=$?
    set -e
    printf '%s\n' "$sysusers_output"
    if [[ $sysusers_status -ne 0 ]] || grep -qiE "scan3d\.sysusers:[0-9]+" <<<"$sysusers_output"; then
        echo "scan3d.sysusers has problems" >&2
        status=1
    fi
fi

if [[ $status -eq 0 ]]; then
    echo "units OK"
fi
exit "$status"
