#!/usr/bin/env bash
# Interop check with OctoMap's own tools (Debian octomap-tools 1.9.7):
#   1. `scan3d map` builds trees from OctoMap's example data; `convert_octree` reads our .bt and
#      .ot, and `compare_octrees` of our .ot against OctoMap's golden .ot prints `KLD: 0`;
#   2. the demo's maps (if a demo output directory is given) open in `convert_octree` too.
#
# Usage: octomap_tools.sh [DEMO_OUT_DIR]. Needs ../shared beside the repo, and installs
# octomap-tools with apt-get when `compare_octrees` is missing.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
data="$root/../shared/data/octomap"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/scan3d-octomap.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT

if ! command -v compare_octrees >/dev/null 2>&1; then
    echo "== installing octomap-tools"
    apt-get update -qq && apt-get install -y -qq octomap-tools >/dev/null
fi
if [[ -n "${SCAN3D_BIN_DIR:-}" ]]; then
    bin="$SCAN3D_BIN_DIR"
else
    (cd "$root" && cargo build --release --bin scan3d)
    bin="$root/target/release"
fi

check_tree() { # name graph resolution
    local name="$1" graph="$2" res="$3"
    "$bin/scan3d" map "$graph" --res "$res" --out "$tmp/$name.ot" --quiet >/dev/null
    "$bin/scan3d" map "$graph" --res "$res" --out "$tmp/$name.bt" --quiet >/dev/null
    convert_octree "$tmp/$name.bt" "$tmp/$name.from_bt.ot" >/dev/null 2>&1 \
        || { echo "convert_octree cannot read our $name.bt" >&2; exit 1; }
    convert_octree "$tmp/$name.ot" "$tmp/$name.from_ot.bt" >/dev/null 2>&1 \
        || { echo "convert_octree cannot read our $name.ot" >&2; exit 1; }
    local kld
    kld="$(compare_octrees "$tmp/$name.ot" "$data/reference/${name}_${res}.ot" 2>/dev/null | grep '^KLD:')"
    [[ "$kld" == "KLD: 0" ]] || { echo "$name at $res: compare_octrees says '$kld'" >&2; exit 1; }
    echo "ok: $name at $res m: convert_octree reads .bt and .ot; compare_octrees $kld"
}

check_tree spherical_scan "$data/spherical_scan.graph" 0.1
check_tree scan_dat "$data/derived/scan_dat.graph" 0.2
check_tree geb079_sim "$data/derived/geb079_sim.graph" 0.1

if [[ $# -ge 1 && -d "$1/maps" ]]; then
    for map in "$1"/maps/*.bt; do
        convert_octree "$map" "$tmp/demo.ot" >/dev/null 2>&1 \
            || { echo "convert_octree cannot read the demo's $map" >&2; exit 1; }
        echo "ok: convert_octree reads the demo's $(basename "$map")"
    done
fi
echo "octomap-tools interop passed"
