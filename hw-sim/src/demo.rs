//! `scan3d-sim demo`: both emulated lidars on real ptys, read by the edge's own acquisition
//! code (drivers, serial shell, revolution timing) on a scaled clock; the 2D scans are written
//! as PLY and a summary is printed.

use std::fmt::Write as _;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use anyhow::Context;
use scan3d_edge::acquisition::{Acquisition, AcquisitionEvent, AcquisitionSummary};
use scan3d_edge::clock::{ScaledClock, SharedClock};
use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig};
use scan3d_edge::drivers::sweep::{Sweep, SweepConfig};
use scan3d_edge::lidar::{DeviceInfo, LidarDriver, LidarEvent};
use scan3d_edge::serial::SerialOptions;
use scan3d_edge::timing::{Revolution, TimingConfig};
use scan3d_server::cloud::CloudPoint;
use scan3d_server::cloud::ply::write_ply;

use crate::device::Device;
use crate::faults::FaultConfig;
use crate::mounts;
use crate::pty::{PtyDevice, PtyHandle, PtyOptions};
use crate::rplidar::{RplidarEmulator, RplidarEmulatorConfig};
use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
use crate::world::World;

/// Options of `scan3d-sim demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Output directory (scans/*.ply are written below it).
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Seconds of sensor data to collect per lidar, counted from when it starts streaming.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Simulated seconds per real second (devices and edge clock alike).
    #[arg(long, default_value_t = 10.0)]
    pub time_scale: f64,
    /// Per-byte corruption rate injected on both serial lines (stray bytes and bit flips).
    #[arg(long, default_value_t = 0.0)]
    pub corrupt: f64,
    /// Seed for the world's noise and the fault injection.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// One simulated lidar and the edge acquisition reading it.
struct Lane {
    name: &'static str,
    pty: PtyHandle,
    acquisition: Acquisition,
    events: Receiver<AcquisitionEvent>,
    info: Option<DeviceInfo>,
    revolutions: Vec<Revolution>,
}

/// What the demo measured for one lidar.
#[derive(Debug, Clone)]
pub struct LaneReport {
    /// `rplidar` or `sweep`.
    pub name: &'static str,
    /// The device's identity as the edge read it.
    pub info: Option<DeviceInfo>,
    /// Full revolutions decoded.
    pub revolutions: usize,
    /// Samples inside those revolutions.
    pub samples: usize,
    /// Samples the emulator put on the wire.
    pub samples_sent: usize,
    /// Frames the driver rejected (checksum / consistency).
    pub frames_rejected: u64,
    /// Bytes skipped while resynchronising.
    pub bytes_discarded: u64,
    /// Samples decoded but outside full revolutions (first partial turn, turn at stop).
    pub samples_outside_revolutions: u64,
    /// Seconds of sensor time covered by the revolutions.
    pub sensor_seconds: f64,
    /// CPU time of the edge thread reading this lidar.
    pub cpu_time: Duration,
    /// Where the scan was written.
    pub ply: PathBuf,
}

impl Lane {
    fn start(
        name: &'static str,
        link: PathBuf,
        device: Box<dyn Device>,
        driver: Box<dyn LidarDriver + Send>,
        baud: u32,
        clock: &SharedClock,
        options: PtyOptions,
    ) -> anyhow::Result<Self> {
        let pty = PtyDevice::spawn(link.clone(), device, options)
            .with_context(|| format!("cannot start the emulated {name}"))?;
        let (acquisition, events) = Acquisition::spawn(
            driver,
            SerialOptions::new(link, baud),
            clock.clone(),
            TimingConfig::default(),
        );
        Ok(Self {
            name,
            pty,
            acquisition,
            events,
            info: None,
            revolutions: Vec::new(),
        })
    }

    fn drain(&mut self) {
        while let Ok(event) = self.events.try_recv() {
            match event {
                AcquisitionEvent::Driver(LidarEvent::Info(info)) => self.info = Some(info),
                AcquisitionEvent::Revolution(rev) => self.revolutions.push(rev),
                AcquisitionEvent::Lost(reason) => {
                    tracing::warn!(lidar = self.name, %reason, "lost the device");
                }
                AcquisitionEvent::Driver(LidarEvent::Warning(text)) => {
                    tracing::info!(lidar = self.name, "{text}")
                }
                AcquisitionEvent::Driver(LidarEvent::Failed(error)) => {
                    tracing::warn!(lidar = self.name, %error, "driver gave up; restarting")
                }
                AcquisitionEvent::Opened | AcquisitionEvent::Driver(_) => {}
            }
        }
    }

    /// Seconds of sensor time covered by the revolutions received so far.
    fn sensor_seconds(&self) -> f64 {
        self.revolutions
            .iter()
            .map(|r| r.t1_ns.saturating_sub(r.t0_ns))
            .sum::<u64>() as f64
            / 1e9
    }

    fn has_enough(&self, seconds: f64) -> bool {
        self.sensor_seconds() >= seconds
    }

    fn finish(
        self,
        scans: &Path,
        to_plane: fn(f32, f32) -> [f32; 3],
    ) -> anyhow::Result<LaneReport> {
        let sensor_seconds = self.sensor_seconds();
        let summary: AcquisitionSummary = self
            .acquisition
            .stop()
            .with_context(|| format!("{} acquisition", self.name))?;
        let samples_sent = self.pty.sent_log().len();
        self.pty.shutdown();
        let points: Vec<CloudPoint> = self
            .revolutions
            .iter()
            .flat_map(|rev| &rev.samples)
            .filter(|s| s.range_m > 0.0)
            .map(|s| CloudPoint {
                position: to_plane(s.angle_deg, s.range_m),
                intensity: s.quality.into(),
            })
            .collect();
        let ply = scans.join(format!("{}.ply", self.name));
        let file =
            File::create(&ply).with_context(|| format!("cannot create {}", ply.display()))?;
        write_ply(BufWriter::new(file), &points)
            .with_context(|| format!("cannot write {}", ply.display()))?;
        Ok(LaneReport {
            name: self.name,
            info: self.info,
            revolutions: self.revolutions.len(),
            samples: self.revolutions.iter().map(|r| r.samples.len()).sum(),
            samples_sent,
            frames_rejected: summary.driver.frames_rejected,
            bytes_discarded: summary.driver.bytes_discarded,
            samples_outside_revolutions: summary.samples_outside_revolutions,
            sensor_seconds,
            cpu_time: summary.cpu_time,
            ply,
        })
    }
}

/// Pty options of one emulated lidar: the demo's time scale and faults, its own fault seed.
fn pty_options(args: &DemoArgs, seed_offset: u64) -> PtyOptions {
    PtyOptions {
        time_scale: args.time_scale,
        faults: FaultConfig::corrupt(args.corrupt),
        seed: args.seed.wrapping_add(seed_offset),
    }
}

/// RPLidar angles are clockwise seen from above: the sensor-plane point is at −θ.
fn rplidar_plane_point(angle_deg: f32, range_m: f32) -> [f32; 3] {
    let a = -angle_deg.to_radians();
    [range_m * a.cos(), range_m * a.sin(), 0.0]
}

/// Sweep azimuths are counter-clockwise in the sensor plane.
fn sweep_plane_point(angle_deg: f32, range_m: f32) -> [f32; 3] {
    let a = angle_deg.to_radians();
    [range_m * a.cos(), range_m * a.sin(), 0.0]
}

/// Runs the demo and prints its summary on stdout.
pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.seconds > 0.0, "--seconds must be positive");
    anyhow::ensure!(
        args.time_scale > 0.0 && args.time_scale.is_finite(),
        "--time-scale must be positive"
    );
    anyhow::ensure!(
        (0.0..=0.1).contains(&args.corrupt),
        "--corrupt must be within 0..=0.1"
    );
    let scans = args.out.join("scans");
    std::fs::create_dir_all(&scans)
        .with_context(|| format!("cannot create {}", scans.display()))?;
    let links = std::env::temp_dir().join(format!("scan3d-demo-{}", std::process::id()));
    std::fs::create_dir_all(&links)
        .with_context(|| format!("cannot create {}", links.display()))?;

    let world = Arc::new(World::conference_room());
    let clock: SharedClock = Arc::new(ScaledClock::new(args.time_scale));
    let started = Instant::now();
    println!(
        "scan3d demo: conference room 8 x 6 x 3 m, RPLidar A1 (express) + Scanse Sweep on ptys, time x{}",
        args.time_scale
    );

    let rplidar_cfg = RplidarEmulatorConfig::default();
    let mut lanes = vec![
        Lane::start(
            "rplidar",
            links.join("rplidar"),
            Box::new(RplidarEmulator::new(
                rplidar_cfg.clone(),
                RplidarEmulator::default_scanner(world.clone(), mounts::rplidar()),
                args.seed,
            )),
            Box::new(Rplidar::new(RplidarConfig {
                baud: rplidar_cfg.baud,
                ..RplidarConfig::default()
            })),
            rplidar_cfg.baud,
            &clock,
            pty_options(args, 100),
        )?,
        Lane::start(
            "sweep",
            links.join("sweep"),
            Box::new(SweepEmulator::new(
                SweepEmulatorConfig::default(),
                SweepEmulator::default_scanner(world.clone(), mounts::sweep()),
                args.seed.wrapping_add(1),
            )),
            Box::new(Sweep::new(SweepConfig::default())?),
            115_200,
            &clock,
            pty_options(args, 101),
        )?,
    ];

    // Generous deadline: handshakes, the Sweep's motor settling (6 s) and the data itself.
    let deadline_ns = clock.now_ns() + ((args.seconds + 30.0) * 1e9) as u64;
    loop {
        for lane in &mut lanes {
            lane.drain();
        }
        if lanes.iter().all(|lane| lane.has_enough(args.seconds)) {
            break;
        }
        if clock.now_ns() > deadline_ns {
            let waiting: Vec<_> = lanes
                .iter()
                .filter(|l| !l.has_enough(args.seconds))
                .map(|l| l.name)
                .collect();
            anyhow::bail!("timed out waiting for data from {}", waiting.join(" and "));
        }
        std::thread::sleep(Duration::from_millis(10));
    }

    let mut reports = Vec::new();
    let mut lanes = lanes.into_iter();
    if let Some(lane) = lanes.next() {
        reports.push(lane.finish(&scans, rplidar_plane_point)?);
    }
    if let Some(lane) = lanes.next() {
        reports.push(lane.finish(&scans, sweep_plane_point)?);
    }
    let _ = std::fs::remove_dir(&links);
    print!("{}", summary(&reports, started.elapsed()));
    Ok(())
}

/// The human-readable summary printed at the end of the demo.
fn summary(reports: &[LaneReport], wall: Duration) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:<8} {:<22} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9}",
        "lidar", "device", "revs", "samples", "sent", "rejected", "discard B", "edge CPU"
    );
    // Sum of each lidar's CPU share: the cost of both streaming at full rate at once.
    let mut core_share = 0.0;
    for r in reports {
        let device = r
            .info
            .as_ref()
            .map(|i| format!("{} fw {} hw {}", i.model, i.firmware, i.hardware))
            .unwrap_or_else(|| "?".into());
        let cpu_share = if r.sensor_seconds > 0.0 {
            format!(
                "{:.2}%",
                r.cpu_time.as_secs_f64() * 100.0 / r.sensor_seconds
            )
        } else {
            "-".into()
        };
        let _ = writeln!(
            s,
            "{:<8} {:<22} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9}",
            r.name,
            device,
            r.revolutions,
            r.samples,
            r.samples_sent,
            r.frames_rejected,
            r.bytes_discarded,
            cpu_share
        );
        if r.sensor_seconds > 0.0 {
            core_share += r.cpu_time.as_secs_f64() / r.sensor_seconds;
        }
    }
    for r in reports {
        let _ = writeln!(
            s,
            "{}: {:.1} s of scans, {} samples outside full revolutions (first partial turn, turn at stop); wrote {}",
            r.name,
            r.sensor_seconds,
            r.samples_outside_revolutions,
            r.ply.display()
        );
    }
    let _ = writeln!(
        s,
        "edge CPU for both lidars at full rate: {:.2} % of one core ({:.1} ms per second of sensor time); wall time {:.1} s",
        core_share * 100.0,
        core_share * 1e3,
        wall.as_secs_f64()
    );
    s
}
