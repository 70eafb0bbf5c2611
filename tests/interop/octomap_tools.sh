#!/usr/bin/env bash
# Interop check with OctoMap's own tools (Debian octomap-tools 1.9.7):
#   1. `scan3d map` builds trees from OctoMap's example data; `convert_octree` reads our .bt and
#      .ot, and `compare_octrees` of our .ot against OctoMap's golden .ot prints `KLD: 0`;
#   2. the demo's maps (if a demo output directory is given) open in `convert_octree` too.
#
# Usage: octomap_tools.sh [DEMO_OUT_DIR]. Reads OctoMap's data vendored in testdata/octomap/.
# Installs octomap-tools with apt-get when a tool is missing (as root); if that is not possible
# it skips with a notice, or fails when SCAN3D_REQUIRE_OCTOMAP=1 (CI sets it).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/scan3d-octomap.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT

# Path of testdata/octomap/REL; a file stored gzip'd (REL.gz, see its README) is unpacked into $tmp.
data() {
    local plain="$root/testdata/octomap/$1"
    if [[ -f "$plain" ]]; then
        echo "$plain"
    else
        local out="$tmp/data/$1"
        mkdir -p "$(dirname "$out")"
        if [[ ! -f "$out" ]]; then
            gzip -dc "$plain.gz" >"$out.part" || { echo "cannot unpack $plain.gz" >&2; exit 1; }
            mv "$out.part" "$out"
        fi
        echo "$out"
    fi
}

# OctoMap's tools, or skip (fail when SCAN3D_REQUIRE_OCTOMAP=1) when they cannot be had.
need_octomap_tools() {
    local tool
    for tool in compare_octrees convert_octree; do
        command -v "$tool" >/dev/null 2>&1 && continue
        if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null 2>&1; then
            echo "== installing octomap-tools"
            apt-get update -qq && apt-get install -y -qq octomap-tools >/dev/null || true
            command -v "$tool" >/dev/null 2>&1 && continue
        fi
        if [[ "${SCAN3D_REQUIRE_OCTOMAP:-}" == 1 ]]; then
            echo "SCAN3D_REQUIRE_OCTOMAP=1 but OctoMap's $tool is not installed (apt-get install octomap-tools)" >&2
            exit 1
        fi
        echo "skipped: OctoMap's $tool is not installed (apt-get install octomap-tools);" \
            "SCAN3D_REQUIRE_OCTOMAP=1 makes this a failure"
        exit 0
    done
}
need_octomap_tools
if [[ -n "${SCAN3D_BIN_DIR:-}" ]]; then
    bin="$SCAN3D_BIN_DIR"
else
    (cd "$root" && cargo build --release --bin scan3d)
    bin="${CARGO_TARGET_DIR:-$root/target}/release"
fi

check_tree() { # name graph resolution
    local name="$1" graph="$2" res="$3"
    "$bin/scan3d" map "$graph" --resolution "$res" --out "$tmp/$name.ot" --quiet >/dev/null
    "$bin/scan3d" map "$graph" --resolution "$res" --out "$tmp/$name.bt" --quiet >/dev/null
    convert_octree "$tmp/$name.bt" "$tmp/$name.from_bt.ot" >/dev/null 2>&1 \
        || { echo "convert_octree cannot read our $name.bt" >&2; exit 1; }
    convert_octree "$tmp/$name.ot" "$tmp/$name.from_ot.bt" >/dev/null 2>&1 \
        || { echo "convert_octree cannot read our $name.ot" >&2; exit 1; }
    local kld
    kld="$(compare_octrees "$tmp/$name.ot" "$(data "reference/${name}_${res}.ot")" 2>/dev/null | grep '^KLD:')"
    [[ "$kld" == "KLD: 0" ]] || { echo "$name at $res: compare_octrees says '$kld'" >&2; exit 1; }
    echo "ok: $name at $res m: convert_octree reads .bt and .ot; compare_octrees $kld"
}

check_tree spherical_scan "$(data spherical_scan.graph)" 0.1
check_tree scan_dat "$(data derived/scan_dat.graph)" 0.2
check_tree geb079_sim "$(data derived/geb079_sim.graph)" 0.1

if [[ $# -ge 1 && -d "$1/maps" ]]; then
    for map in "$1"/maps/*.bt; do
        convert_octree "$map" "$tmp/demo.ot" >/dev/null 2>&1 \
            || { echo "convert_octree cannot read the demo's $map" >&2; exit 1; }
        echo "ok: convert_octree reads the demo's $(basename "$map")"
    done
fi
echo "octomap-tools interop passed"
