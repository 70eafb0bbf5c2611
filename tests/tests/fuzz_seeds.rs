//! Writes the seed corpus of every fuzz target into `<out>/<target>/` (default `fuzz/corpus`),
//! with the library's own encoders and writers: frames of every body type, recorded
//! driver ↔ emulator sessions in the drivers' session layout, small maps, clouds in every
//! format and encoding, a recorded mini session, the shipped configs and control requests.
//!
//! `FUZZ_CORPUS_DIR=DIR cargo test --workspace --test fuzz_seeds -- --ignored` writes them into
//! DIR (default `fuzz/corpus`); `fuzz/ci.sh` runs it so, sharing the workspace's test build. The
//! test that is not ignored writes them into a temporary directory and checks that every fuzz
//! target gets seeds, so a change that breaks an encoder fails `cargo test`, not the fuzz run.

// The fuzz targets read this layout; the generator only writes it.
#[allow(dead_code)]
#[path = "../../fuzz/src/stream.rs"]
mod stream;

use std::error::Error;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig, ScanMode};
use scan3d_edge::drivers::sweep::{Sweep, SweepConfig};
use scan3d_edge::lidar::{LidarDriver, LidarEvent};
use scan3d_hw_sim::device::Device;
use scan3d_hw_sim::mounts;
use scan3d_hw_sim::pair::Pair;
use scan3d_hw_sim::rplidar::{RplidarEmulator, RplidarEmulatorConfig, RplidarModel};
use scan3d_hw_sim::sweep::{SweepEmulator, SweepEmulatorConfig};
use scan3d_hw_sim::world::World;
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::io::Encoding;
use scan3d_map::cloud::pcd::write_pcd_bundles;
use scan3d_map::cloud::ply::write_ply_bundles;
use scan3d_map::cloud::scans_file::write_scans;
use scan3d_map::octree::{Resolution, SensorModel, VoxelMap};
use scan3d_protocol::{
    Ack, Body, ClockModel, Command, CommandOutcome, CommandReply, DeviceStatus, Frame, Heartbeat,
    Hello, ImuSample, LidarRevolution, MountInfo, PassEvent, PassMarker, SensorId, SensorInfo,
    SensorMount, SensorMounts, StaticScan, StaticScanEnd, StaticScanOutcome, StaticScanProblem,
    StaticScanStart, StaticScanWarning, StaticScanYaws, StatusEvent, StepperState, TimePing,
    TimePong, YawRun, encode,
};
use scan3d_server::ingest::control::ControlRequest;
use scan3d_server::recording::{ServerRecord, SessionRecorder};

type Result<T> = std::result::Result<T, Box<dyn Error>>;

const MS: u64 = 1_000_000;
/// The repository root (for the shipped example configs).
const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

struct Corpus {
    root: PathBuf,
}

impl Corpus {
    fn put(&self, target: &str, name: &str, bytes: &[u8]) -> Result<()> {
        let dir = self.root.join(target);
        fs::create_dir_all(&dir)?;
        fs::write(dir.join(name), bytes)?;
        Ok(())
    }
}

/// One frame of every body type (every variant of the enums inside too).
fn frames() -> Vec<(&'static str, Frame)> {
    let session = 0x5eed_0001;
    let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 1_000, 182_000_000);
    for i in 0..8u64 {
        let _ = rev.push(
            i as f32 * 45.0,
            1.5 + i as f32 * 0.1,
            47,
            1_000 + i * 20_000_000,
        );
    }
    let mount = MountInfo {
        axis_offset_m: 0.05,
        height_m: 1.0,
        azimuth_zero_deg: 0.0,
    };
    let bodies: Vec<(&str, Body)> = vec![
        (
            "hello",
            Hello::new(
                "edge-pi-01",
                "0.1.0",
                vec![SensorInfo {
                    sensor: SensorId::RPLIDAR,
                    model: "A1".into(),
                    firmware: "1.29".into(),
                    serial: "00112233".into(),
                }],
            )
            .into(),
        ),
        ("revolution", rev.into()),
        (
            "imu",
            ImuSample {
                t_ns: 5,
                accel_mps2: [0.0, 0.0, 9.81],
                gyro_radps: [0.01, 0.0, -0.01],
                mag_ut: [20.0, 0.0, 40.0],
                orientation: Some([1.0, 0.0, 0.0, 0.0]),
            }
            .into(),
        ),
        (
            "stepper",
            StepperState {
                t_ns: 6,
                commanded_angle_deg: 1.8,
                step_index: -1,
                holding: true,
            }
            .into(),
        ),
        ("time_ping", TimePing { t0_ns: 7 }.into()),
        (
            "time_pong",
            TimePong {
                t0_ns: 7,
                t1_ns: 8,
                t2_ns: 9,
            }
            .into(),
        ),
        (
            "clock_model",
            ClockModel {
                offset_ns: -3_000_000_000,
                skew_ppm: 41.5,
                error_bound_ns: 1_200_000,
                skew_bound_ppm: 3.0,
                ref_edge_ns: 90_000_000_000,
                fit_from_edge_ns: 60_000_000_000,
                fit_to_edge_ns: 94_000_000_000,
                valid_from_edge_ns: 95_000_000_000,
                min_delay_ns: 2_100_000,
                exchanges: 14,
            }
            .into(),
        ),
        ("ack_up_to", Ack::UpTo { seq: 41 }.into()),
        ("ack_range", Ack::Range { first: 3, last: 9 }.into()),
        ("heartbeat", Heartbeat { sent_ns: 3 }.into()),
        (
            "status",
            DeviceStatus {
                t_ns: 10,
                sensor: SensorId::SWEEP,
                event: StatusEvent::SensorLost,
                reason: "read: EIO".into(),
            }
            .into(),
        ),
        (
            "status_paused",
            DeviceStatus {
                t_ns: 11,
                sensor: SensorId::IMU,
                event: StatusEvent::AcquisitionPaused,
                reason: "spool full".into(),
            }
            .into(),
        ),
        (
            "command_start",
            Command::StartStaticScan {
                position: "p1".into(),
                x_m: 1.0,
                y_m: 2.0,
                heading_deg: Some(90.0),
            }
            .into(),
        ),
        ("command_stop", Command::StopStaticScan.into()),
        (
            "command_reply",
            CommandReply {
                command_seq: 1,
                t_ns: 5,
                outcome: CommandOutcome::Refused {
                    reason: "no [stepper] in edge.toml".into(),
                },
            }
            .into(),
        ),
        (
            "command_speed",
            Command::SetMotorSpeed {
                sensor: SensorId::SWEEP,
                hz: 2.0,
            }
            .into(),
        ),
        (
            "command_start_pass",
            Command::StartPass {
                name: Some("loop".into()),
                x_m: 1.6,
                y_m: 0.85,
                heading_deg: -90.0,
            }
            .into(),
        ),
        ("command_stop_pass", Command::StopPass.into()),
        (
            "mounts",
            SensorMounts {
                sensors: vec![
                    SensorMount {
                        sensor: SensorId::RPLIDAR,
                        x_m: 0.1,
                        y_m: 0.0,
                        z_m: 0.4,
                        roll_deg: 180.0,
                        pitch_deg: 0.0,
                        yaw_deg: 0.0,
                    },
                    SensorMount {
                        sensor: SensorId::SWEEP,
                        x_m: -0.2,
                        y_m: 0.0,
                        z_m: 1.0,
                        roll_deg: 90.0,
                        pitch_deg: 0.0,
                        yaw_deg: 90.0,
                    },
                ],
            }
            .into(),
        ),
        (
            "pass_started",
            PassMarker {
                t_ns: 16,
                event: PassEvent::Started {
                    name: "loop".into(),
                    x_m: 1.6,
                    y_m: 0.85,
                    heading_deg: -90.0,
                },
            }
            .into(),
        ),
        (
            "pass_stopped",
            PassMarker {
                t_ns: 17,
                event: PassEvent::Stopped {
                    name: "loop".into(),
                },
            }
            .into(),
        ),
        (
            "static_started",
            StaticScan::Started(StaticScanStart {
                scan_id: 1,
                t_ns: 12,
                position: "p1".into(),
                x_m: 1.0,
                y_m: 2.0,
                heading_deg: 0.0,
                step_deg: 1.8,
                total_deg: 180.0,
                blocked_sector_deg: 60.0,
                mount,
            })
            .into(),
        ),
        (
            "static_yaws",
            StaticScan::Yaws(StaticScanYaws {
                scan_id: 1,
                revolution_t0_ns: 13,
                runs: vec![
                    YawRun {
                        first_index: 0,
                        count: 150,
                        yaw_deg: 0.0,
                    },
                    YawRun {
                        first_index: 211,
                        count: u32::MAX,
                        yaw_deg: f32::NAN,
                    },
                ],
            })
            .into(),
        ),
        (
            "static_warning",
            StaticScan::Warning(StaticScanWarning {
                scan_id: 1,
                t_ns: 14,
                revolution: 3,
                problem: StaticScanProblem::SectorMissed,
                detail: "late".into(),
            })
            .into(),
        ),
        (
            "static_finished",
            StaticScan::Finished(StaticScanEnd {
                scan_id: 1,
                t_ns: 15,
                outcome: StaticScanOutcome::Completed,
                yaw_deg: 180.0,
                revolutions: 100,
                tagged: 5000,
                blocked: 1000,
                untrusted: 2,
                late_steps: 0,
                failed_steps: 0,
            })
            .into(),
        ),
    ];
    bodies
        .into_iter()
        .enumerate()
        .map(|(seq, (name, body))| {
            (
                name,
                Frame {
                    session_id: session,
                    seq: seq as u64,
                    body,
                },
            )
        })
        .collect()
}

fn frame_seeds(c: &Corpus) -> Result<()> {
    let mut stream = Vec::new();
    for (name, frame) in frames() {
        let bytes = encode(&frame)?;
        c.put("frame", name, &bytes)?;
        stream.extend_from_slice(&bytes);
    }
    c.put("frame", "stream", &stream)?;
    // A skippable malformed frame (valid header, payload of one bad variant tag) mid-stream.
    let good = encode(&Frame::new(1, 0, Heartbeat { sent_ns: 1 }))?;
    let mut bad = good.clone();
    if let Some(tag) = bad.get_mut(12) {
        *tag = 0x7f;
    }
    c.put(
        "frame",
        "malformed_mid_stream",
        &[good.clone(), bad, good].concat(),
    )?;
    Ok(())
}

/// Records a driver ↔ emulator session for `millis` of simulated time in 2 ms reads, as the
/// drivers' session layout with `settings` as its first byte. Fails unless the session got as
/// far as streaming samples (a seed that stops in the handshake would waste the fuzzer's time).
fn session<D: LidarDriver, E: Device>(
    driver: D,
    device: E,
    millis: u64,
    settings: u8,
) -> Result<Vec<u8>> {
    let mut pair = Pair::new(driver, device, 2 * MS).record();
    let mut samples = 0u64;
    pair.run_until(millis * MS, |_, e| {
        samples += u64::from(matches!(e, LidarEvent::Sample(_)));
    });
    if samples == 0 {
        return Err(
            format!("the recorded session never streamed (settings {settings:#04x})").into(),
        );
    }
    Ok(stream::write(
        settings,
        &pair.recording.take().unwrap_or_default(),
    ))
}

fn driver_seeds(c: &Corpus) -> Result<()> {
    let world = Arc::new(World::conference_room());
    // Settings bits as the rplidar target reads them: bit 0 standard scan.
    for (name, model, mode, settings) in [
        ("a1_express", RplidarModel::A1, ScanMode::Express, 0u8),
        ("a1_standard", RplidarModel::A1, ScanMode::Standard, 1),
        ("a2_express", RplidarModel::A2, ScanMode::Express, 0),
    ] {
        let device = RplidarEmulator::new(
            RplidarEmulatorConfig {
                model,
                spinup_s: 0.05,
                ..Default::default()
            },
            RplidarEmulator::default_scanner(world.clone(), mounts::rplidar()),
            1,
        );
        let driver = Rplidar::new(RplidarConfig {
            scan_mode: mode,
            ..Default::default()
        });
        c.put("rplidar", name, &session(driver, device, 600, settings)?)?;
    }
    // Settings bits as the sweep target reads them: bits 0–3 motor Hz, 4–5 sample-rate code.
    for (name, motor_hz, code, settings) in [
        ("keep_settings", None, None, 0u8),
        ("motor_2hz_code_2", Some(2u8), Some(2u8), 2 | (2 << 4)),
    ] {
        let device = SweepEmulator::new(
            SweepEmulatorConfig {
                settle_ms: 300,
                ..Default::default()
            },
            SweepEmulator::default_scanner(world.clone(), mounts::sweep()),
            2,
        );
        let driver = Sweep::new(SweepConfig {
            motor_hz,
            sample_rate_code: code,
            ..Default::default()
        })?;
        c.put("sweep", name, &session(driver, device, 1_400, settings)?)?;
    }
    Ok(())
}

/// A few scans of a box room seen from two origins (small enough for seeds).
fn room_scans() -> Vec<RayBundle> {
    let mut scans = Vec::new();
    for (k, origin) in [[0.0, 0.0, 0.5], [0.6, -0.4, 0.5]].into_iter().enumerate() {
        let mut points = Vec::new();
        for i in 0..24 {
            let a = i as f32 * std::f32::consts::TAU / 24.0 + k as f32 * 0.1;
            let (s, c) = a.sin_cos();
            // Walls of a 3 × 2 m room, floor and ceiling points.
            let t = (1.5 / c.abs().max(1e-3)).min(1.0 / s.abs().max(1e-3));
            points.push([c * t, s * t, 0.5 + (i % 3) as f32 * 0.4]);
            points.push([c * 0.7, s * 0.7, 0.0]);
        }
        scans.push(RayBundle { origin, points });
    }
    scans
}

fn map_seeds(c: &Corpus) -> Result<()> {
    for (name, res) in [("res_0.25", 0.25), ("res_0.5", 0.5)] {
        let mut map = VoxelMap::new(Resolution::new(res)?, SensorModel::default());
        for scan in room_scans() {
            map.insert_bundle(&scan, -1.0);
        }
        let tree = map.to_octree();
        c.put("bt", name, &tree.to_bt_bytes())?;
        c.put("ot", name, &tree.to_ot_bytes())?;
    }
    let empty = VoxelMap::new(Resolution::new(0.1)?, SensorModel::default()).to_octree();
    c.put("bt", "empty", &empty.to_bt_bytes())?;
    c.put("ot", "empty", &empty.to_ot_bytes())?;
    c.put("graph", "two_nodes", &graph(&room_scans()))?;
    Ok(())
}

/// A binary ScanGraph (OctoMap's `ScanGraph::writeBinary`): node count; per node its point
/// cloud (count, then `Vector3`s as i32 3 + 3 × f64), pose (`Vector3`, then a `Quaternion` as
/// i32 4 + 4 × f64) and id; edge count; per edge two ids, a pose and a weight.
fn graph(scans: &[RayBundle]) -> Vec<u8> {
    fn vec3(out: &mut Vec<u8>, v: [f64; 3]) {
        out.extend_from_slice(&3i32.to_le_bytes());
        v.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
    }
    fn quat(out: &mut Vec<u8>, q: [f64; 4]) {
        out.extend_from_slice(&4i32.to_le_bytes());
        q.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
    }
    let mut g = (scans.len() as u32).to_le_bytes().to_vec();
    for (id, scan) in scans.iter().enumerate() {
        g.extend_from_slice(&(scan.points.len().min(6) as u32).to_le_bytes());
        for p in scan.points.iter().take(6) {
            // Points relative to the node pose (a pure translation here).
            vec3(&mut g, [0, 1, 2].map(|i| f64::from(p[i]) - scan.origin[i]));
        }
        vec3(&mut g, scan.origin);
        quat(&mut g, [1.0, 0.0, 0.0, 0.0]);
        g.extend_from_slice(&(id as u32).to_le_bytes());
    }
    g.extend_from_slice(&1u32.to_le_bytes());
    g.extend_from_slice(&0u32.to_le_bytes());
    g.extend_from_slice(&1u32.to_le_bytes());
    vec3(&mut g, [0.6, -0.4, 0.0]);
    quat(&mut g, [1.0, 0.0, 0.0, 0.0]);
    g.extend_from_slice(&1.0f64.to_le_bytes());
    g
}

fn cloud_seeds(c: &Corpus) -> Result<()> {
    let scans: Vec<RayBundle> = room_scans()
        .into_iter()
        .map(|mut s| {
            s.points.truncate(12);
            s
        })
        .collect();
    let one = &scans[..1];
    for (name, set) in [("two_origins", &scans[..]), ("one_origin", one)] {
        for (enc, encoding) in [("binary", Encoding::Binary), ("ascii", Encoding::Ascii)] {
            let mut ply = Vec::new();
            write_ply_bundles(&mut ply, set, encoding)?;
            c.put("ply", &format!("{name}_{enc}"), &ply)?;
            let mut pcd = Vec::new();
            write_pcd_bundles(&mut pcd, set, encoding)?;
            c.put("pcd", &format!("{name}_{enc}"), &pcd)?;
        }
        let mut bytes = Vec::new();
        write_scans(&mut bytes, set)?;
        c.put("scans", name, &bytes)?;
    }
    let mut with_empty = Vec::new();
    write_scans(
        &mut with_empty,
        &[
            RayBundle {
                origin: [0.0; 3],
                points: Vec::new(),
            },
            scans[0].clone(),
        ],
    )?;
    c.put("scans", "with_empty_scan", &with_empty)?;
    Ok(())
}

/// A recorded mini session: the MCAP file `SessionRecorder` writes for a few frames, a
/// command and a server-made record (a clock model), committed in two chunks and closed.
fn session_seeds(c: &Corpus) -> Result<()> {
    // Its own directory: the two tests of this file may run at once in one process.
    let tmp = tempfile::tempdir()?;
    let session_id = 0x5eed_0001;
    let mut rec = SessionRecorder::open(tmp.path(), "edge-pi-01", session_id)?;
    let dir = rec.session_dir().to_path_buf();
    let mut committed = 0;
    for (_, frame) in frames() {
        let raw = encode(&frame)?;
        if matches!(frame.body, Body::Command(_)) {
            rec.append_command(&raw, &frame, 1_000 + frame.seq)?;
        } else if let Body::ClockModel(model) = frame.body {
            // A server-made record, on its own channel and schema as the server writes it.
            rec.append_record(&ServerRecord::ClockModel(model), 1_000 + frame.seq)?;
        } else if frame.body.direction() != scan3d_protocol::Direction::ServerToEdge {
            rec.append(&raw, &frame, 1_000 + frame.seq)?;
        }
        committed += 1;
        if committed == 6 {
            rec.commit()?;
        }
    }
    rec.close()?;
    for entry in fs::read_dir(&dir)? {
        let path = entry?.path();
        if path.extension().is_some_and(|e| e == "mcap") {
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
            c.put("mcap_session", &name.unwrap_or_default(), &fs::read(&path)?)?;
        }
    }
    Ok(())
}

fn text_seeds(c: &Corpus) -> Result<()> {
    let root = Path::new(ROOT);
    c.put(
        "edge_config",
        "deploy_edge",
        &fs::read(root.join("deploy/edge.toml"))?,
    )?;
    c.put("edge_config", "minimal", b"device_name = \"edge\"\n")?;
    c.put(
        "edge_config",
        "rplidar_only",
        b"device_name = \"e\"\n[rplidar]\npath = \"/dev/ttyUSB0\"\nanswer_timeout_ms = 10\nscan_mode = \"standard\"\n",
    )?;
    c.put(
        "server_config",
        "deploy_server",
        &fs::read(root.join("deploy/server.toml"))?,
    )?;
    c.put("server_config", "empty", b"")?;
    // The first lines of the vendored Intel log (ODOM and FLASER), a ROBOTLASER1 line and a
    // relations file.
    let intel = {
        use std::io::Read;
        let mut text = String::new();
        flate2::read::GzDecoder::new(fs::File::open(root.join("testdata/slam/intel.clf.gz"))?)
            .read_to_string(&mut text)?;
        text.lines().take(12).collect::<Vec<_>>().join("\n") + "\n"
    };
    c.put("carmen_log", "intel_head", intel.as_bytes())?;
    c.put(
        "carmen_log",
        "robotlaser1",
        b"# comment\nROBOTLASER1 0 -1.5708 3.1416 0.0175 81.9 0.01 0 3 1.0 2.0 81.9 0 0.1 0 0 0 0 0 0 0 0 0 0 1.000000 host 1.0\nODOM 0 0 0 0 0 0 1.5 host 1.5\n",
    )?;
    let relations = fs::read_to_string(root.join("testdata/slam/intel.relations"))?;
    let relations: String = relations
        .lines()
        .take(6)
        .map(|l| format!("{l}\n"))
        .collect();
    let trajectory =
        "976052905.167303 0 0 0\n976052911.885496 -0.05 -0.12 -1.68\n976052913.712702 0.3 0 0\n";
    c.put(
        "slam_text",
        "intel",
        format!("{trajectory}\0{relations}").as_bytes(),
    )?;
    for (i, (_, frame)) in frames()
        .into_iter()
        .filter(|(_, f)| matches!(f.body, Body::Command(_)))
        .enumerate()
    {
        let Body::Command(command) = frame.body else {
            continue;
        };
        let request = ControlRequest {
            edge: "edge-pi-01".into(),
            command,
        };
        c.put(
            "control_request",
            &format!("command_{i}"),
            serde_json::to_string(&request)?.as_bytes(),
        )?;
    }
    Ok(())
}

fn write_all(root: PathBuf) -> Result<()> {
    let c = Corpus { root };
    frame_seeds(&c)?;
    driver_seeds(&c)?;
    map_seeds(&c)?;
    cloud_seeds(&c)?;
    session_seeds(&c)?;
    text_seeds(&c)?;
    println!("seeds written to {}", c.root.display());
    Ok(())
}

/// The fuzz targets, as `fuzz/Cargo.toml` names its `[[bin]]`s.
fn fuzz_targets() -> Vec<String> {
    let manifest =
        fs::read_to_string(Path::new(ROOT).join("fuzz/Cargo.toml")).expect("fuzz/Cargo.toml");
    let manifest: toml::Table = toml::from_str(&manifest).expect("fuzz/Cargo.toml is TOML");
    manifest
        .get("bin")
        .and_then(toml::Value::as_array)
        .expect("fuzz/Cargo.toml has [[bin]]s")
        .iter()
        .filter_map(|bin| bin.get("name")?.as_str().map(String::from))
        .collect()
}

/// Writes the seed corpora into `$FUZZ_CORPUS_DIR` (default `fuzz/corpus`) for `fuzz/ci.sh`.
#[test]
#[ignore = "writes fuzz/corpus; fuzz/ci.sh runs it"]
fn write_fuzz_seeds() -> Result<()> {
    let root = std::env::var_os("FUZZ_CORPUS_DIR")
        .map_or_else(|| PathBuf::from(ROOT).join("fuzz/corpus"), PathBuf::from);
    write_all(root)
}

#[test]
fn every_fuzz_target_gets_seeds() -> Result<()> {
    let dir = tempfile::tempdir()?;
    write_all(dir.path().to_path_buf())?;
    let targets = fuzz_targets();
    assert!(targets.len() >= 15, "fuzz/Cargo.toml lists {targets:?}");
    for target in &targets {
        let seeds = fs::read_dir(dir.path().join(target))
            .map(|entries| entries.count())
            .unwrap_or(0);
        assert!(seeds > 0, "no seeds for the fuzz target {target}");
    }
    Ok(())
}
