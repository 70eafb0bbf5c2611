//! `scan3d-edge probe` end to end: the CLI (run in-process) against emulated devices on ptys.

use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;
use scan3d_edge::cli::{Cli, execute};
use scan3d_hw_sim::device::Device;
use scan3d_hw_sim::mounts;
use scan3d_hw_sim::pty::{PtyDevice, PtyHandle, PtyOptions};
use scan3d_hw_sim::rplidar::{RplidarEmulator, RplidarEmulatorConfig, RplidarModel};
use scan3d_hw_sim::sweep::{SweepEmulator, SweepEmulatorConfig};
use scan3d_hw_sim::world::World;
use serde_json::Value;

const TIME_SCALE: &str = "10";

fn link(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("scan3d-probe-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir.join(name)
}

fn spawn(name: &str, device: Box<dyn Device>) -> PtyHandle {
    let options = PtyOptions {
        time_scale: 10.0,
        ..Default::default()
    };
    PtyDevice::spawn(link(name), device, options).expect("pty device")
}

fn rplidar(name: &str, model: RplidarModel, baud: u32) -> PtyHandle {
    let world = Arc::new(World::conference_room());
    let config = RplidarEmulatorConfig {
        model,
        baud,
        ..Default::default()
    };
    let scanner = RplidarEmulator::default_scanner(world, mounts::rplidar());
    spawn(name, Box::new(RplidarEmulator::new(config, scanner, 1)))
}

/// Runs `scan3d-edge ARGS…` in-process; returns stdout lines as JSON, or the error line.
fn probe(args: &[&str]) -> Result<Vec<Value>, String> {
    let cli = Cli::try_parse_from(std::iter::once("scan3d-edge").chain(args.iter().copied()))
        .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    execute(cli, &mut out).map_err(|e| format!("{e:#}"))?;
    String::from_utf8(out)
        .expect("utf-8 output")
        .lines()
        .map(|line| serde_json::from_str(line).map_err(|e| format!("not JSON: {line}: {e}")))
        .collect()
}

fn check_revolutions(lines: &[Value], count: usize, max_range: f64) {
    let revolutions: Vec<&Value> = lines.iter().filter(|l| l["type"] == "revolution").collect();
    assert_eq!(revolutions.len(), count);
    for rev in revolutions {
        let angles = rev["angles_deg"].as_array().expect("angles");
        let ranges = rev["ranges_m"].as_array().expect("ranges");
        let qualities = rev["qualities"].as_array().expect("qualities");
        assert!(angles.len() > 100, "only {} samples", angles.len());
        assert_eq!(angles.len(), ranges.len());
        assert_eq!(angles.len(), qualities.len());
        assert!(
            angles
                .iter()
                .all(|a| (0.0..360.0).contains(&a.as_f64().unwrap_or(-1.0)))
        );
        assert!(
            ranges
                .iter()
                .all(|r| (0.0..max_range).contains(&r.as_f64().unwrap_or(-1.0)))
        );
        let (t0, t1) = (
            rev["t0_ns"].as_u64().expect("t0"),
            rev["t1_ns"].as_u64().expect("t1"),
        );
        assert!(t1 > t0);
    }
}

#[test]
fn probe_rplidar_a2_prints_info_health_and_revolutions() {
    let device = rplidar("a2", RplidarModel::A2, 256_000);
    let path = device.link().display().to_string();
    let lines = probe(&[
        "probe",
        "rplidar",
        &path,
        "--baud",
        "256000",
        "--revolutions",
        "2",
        "--time-scale",
        TIME_SCALE,
    ])
    .expect("probe succeeds");
    // The emulator's serial is the 16 ASCII bytes "scan3d-rplidar-1", printed byte 0 first.
    let serial: String = b"scan3d-rplidar-1"
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect();
    assert_eq!(
        lines[0],
        serde_json::json!({"type": "info", "model": "A2", "firmware": "1.29", "hardware": 7, "serial": serial})
    );
    assert_eq!(
        lines[1],
        serde_json::json!({"type": "health", "status": "good", "error_code": 0})
    );
    check_revolutions(&lines, 2, 12.0);
    device.shutdown();
}

#[test]
fn probe_sweep_prints_info_and_revolutions() {
    let world = Arc::new(World::conference_room());
    let config = SweepEmulatorConfig {
        settle_ms: 1000,
        ..Default::default()
    };
    let scanner = SweepEmulator::default_scanner(world, mounts::sweep());
    let device = spawn("sweep", Box::new(SweepEmulator::new(config, scanner, 2)));
    let path = device.link().display().to_string();
    let lines = probe(&[
        "probe",
        "sweep",
        &path,
        "--revolutions",
        "3",
        "--time-scale",
        TIME_SCALE,
    ])
    .expect("probe succeeds");
    assert_eq!(lines[0]["type"], "info");
    assert_eq!(lines[0]["model"], "Sweep");
    assert!(
        lines.iter().all(|l| l["type"] != "health"),
        "the Sweep has no health query"
    );
    check_revolutions(&lines, 3, 40.0);
    device.shutdown();
}

#[test]
fn probing_a_missing_device_fails_with_one_clear_line() {
    let missing = link("nothing-here");
    let err = probe(&["probe", "rplidar", &missing.display().to_string()]).unwrap_err();
    assert!(err.starts_with("cannot open"), "{err}");
    assert!(err.contains("nothing-here"), "{err}");
    assert!(!err.contains('\n'), "{err}");
}

#[test]
fn probing_the_wrong_device_fails_with_one_clear_line() {
    // A Sweep answers nothing an RPLidar driver understands.
    let world = Arc::new(World::conference_room());
    let scanner = SweepEmulator::default_scanner(world, mounts::sweep());
    let device = spawn(
        "wrong",
        Box::new(SweepEmulator::new(
            SweepEmulatorConfig::default(),
            scanner,
            3,
        )),
    );
    let path = device.link().display().to_string();
    let err = probe(&["probe", "rplidar", &path, "--time-scale", TIME_SCALE]).unwrap_err();
    assert!(err.contains("no answer to GET_INFO"), "{err}");
    assert!(!err.contains('\n'), "{err}");
    device.shutdown();
}
