#!/usr/bin/env python3
"""Smoke test: Slamtec's official SDK (via the PyPI wrapper pyrplidarsdk 0.1.2) against the
scan3d-sim RPLidar emulator.

Usage: pyrplidarsdk_smoke.py PORT [--baud 115200] [--serial HEX] [--scans N]

Checks that what the SDK decodes matches what `scan3d-sim device rplidar --model a1` was started
with: model 0x18 (A1M8), firmware 1.29, hardware 7, the serial number, health good / error 0,
and a few scans (the SDK's express path) of plausible size with angles in [0, 2π) rad and ranges
that fit in the simulated room. Exits 0 on success, 1 with a message on stderr otherwise.
"""

import argparse
import math
import sys
import time

# What the emulator reports by default (hw-sim/src/rplidar.rs, RplidarEmulatorConfig::default).
EXPECTED_MODEL = 0x18
EXPECTED_FIRMWARE = (1 << 8) | 29  # 1.29, as the SDK packs it: major << 8 | minor
EXPECTED_HARDWARE = 7
EXPECTED_SERIAL = b"scan3d-rplidar-1".hex().upper()
# The default room: 8 x 6 m, the sensor at (4, 3); through the glass wall and the door the
# farthest surfaces are the corridor and hall walls, well under 8.5 m away.
MIN_RANGE_M = 0.15
MAX_RANGE_M = 8.5
# 4000 samples/s at ~5.5 rev/s: ~727 per revolution (fewer when beams see no return).
MIN_POINTS = 300
MAX_POINTS = 1000


class SmokeFailure(Exception):
    pass


def check(cond, message):
    if not cond:
        raise SmokeFailure(message)


def run(port, baud, serial_hex, scans):
    from pyrplidarsdk import RplidarDriver

    lidar = RplidarDriver(port=port, baudrate=baud)
    check(lidar.connect(), f"connect({port}, {baud}) failed")
    try:
        info = lidar.get_device_info()
        check(info is not None, "get_device_info() returned None")
        print(f"info: {info!r}")
        check(info.model == EXPECTED_MODEL, f"model {info.model:#x}, expected {EXPECTED_MODEL:#x}")
        check(
            info.firmware_version == EXPECTED_FIRMWARE,
            f"firmware {info.firmware_version:#x}, expected {EXPECTED_FIRMWARE:#x} (1.29)",
        )
        check(
            info.hardware_version == EXPECTED_HARDWARE,
            f"hardware {info.hardware_version}, expected {EXPECTED_HARDWARE}",
        )
        check(
            str(info.serial_number).upper() == serial_hex,
            f"serial {info.serial_number}, expected {serial_hex}",
        )

        health = lidar.get_health()
        check(health is not None, "get_health() returned None")
        print(f"health: {health!r}")
        check(health.status == 0, f"health status {health.status}, expected 0 (good)")
        check(health.error_code == 0, f"health error code {health.error_code}, expected 0")

        check(lidar.start_scan(), "start_scan() failed")
        got = 0
        deadline = time.monotonic() + 20.0
        while got < scans:
            check(time.monotonic() < deadline, f"only {got} of {scans} scans within 20 s")
            data = lidar.get_scan_data()
            if data is None:
                continue
            angles, ranges, qualities = data
            n = len(angles)
            check(
                n == len(ranges) == len(qualities),
                f"scan lists of different lengths: {n}, {len(ranges)}, {len(qualities)}",
            )
            check(
                MIN_POINTS <= n <= MAX_POINTS,
                f"scan {got}: {n} points, expected {MIN_POINTS}..{MAX_POINTS}",
            )
            bad_angles = [a for a in angles if not 0.0 <= a < 2.0 * math.pi]
            check(not bad_angles, f"scan {got}: angles outside [0, 2pi): {bad_angles[:5]}")
            bad_ranges = [r for r in ranges if not MIN_RANGE_M <= r <= MAX_RANGE_M]
            check(
                not bad_ranges,
                f"scan {got}: ranges outside [{MIN_RANGE_M}, {MAX_RANGE_M}] m: {bad_ranges[:5]}",
            )
            print(
                f"scan {got}: {n} points, angles {min(angles):.3f}..{max(angles):.3f} rad, "
                f"ranges {min(ranges):.3f}..{max(ranges):.3f} m"
            )
            got += 1
        lidar.stop_scan()
    finally:
        lidar.disconnect()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port")
    parser.add_argument("--baud", type=int, default=115200)
    parser.add_argument("--serial", default=EXPECTED_SERIAL, help="expected serial, hex")
    parser.add_argument("--scans", type=int, default=5)
    args = parser.parse_args()
    try:
        run(args.port, args.baud, args.serial.upper(), args.scans)
    except SmokeFailure as e:
        print(f"pyrplidarsdk smoke test FAILED: {e}", file=sys.stderr)
        return 1
    except ImportError as e:
        print(f"pyrplidarsdk smoke test FAILED: cannot import pyrplidarsdk: {e}", file=sys.stderr)
        return 1
    print("pyrplidarsdk smoke test passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
