//! Synthetic edges for load and soak runs: many real edge uplink clients, each with its own
//! pairing bundle (its own certificate, hence its own edge name on the server), its own spool
//! and session, fed with realistic lidar revolutions at the sensors' real rates.
//!
//! Used by the uplink benchmark (`hw-sim/benches/uplink.rs`) and the soak and fault run
//! (`tests/tests/soak.rs`).
//!
//! Frames are synthetic [`LidarRevolution`]s measured in the default conference room by the
//! emulators' own scanners (true ranges plus the sensors' noise models): RPLidar express
//! revolutions of 727 samples (4000 samples/s at 5.5 rev/s, range in mm, quality 47 or 0 for no
//! return, as the driver reports express capsules) and Sweep revolutions of 110 samples (range
//! in cm, signal strength falling with range), with per-sample times spread over the revolution.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use nix::time::{ClockId, clock_gettime};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use scan3d_edge::clock::{MonotonicClock, SharedClock};
use scan3d_edge::uplink::client::{SubmitError, Uplink, UplinkConfig, UplinkHandle, UplinkStats};
use scan3d_edge::uplink::tls;
use scan3d_protocol::{
    Frame, LidarRevolution, MountInfo, SensorId, StaticScan, StaticScanEnd, StaticScanOutcome,
    StaticScanStart, StaticScanYaws, YawRun, encode,
};
use scan3d_server::ingest::pki::{self, PairRequest};
use tokio::runtime::Runtime;
use tokio::sync::watch;

use crate::installation;
use crate::mounts;
use crate::rplidar::RplidarEmulator;
use crate::sweep::SweepEmulator;
use crate::world::{Scanner, World};

/// Reads a POSIX clock in nanoseconds (0 if the kernel refuses, which Linux never does for
/// the monotonic and CPU-time clocks).
pub fn clock_ns(clock: ClockId) -> u64 {
    clock_gettime(clock)
        .map(|t| u64::try_from(Duration::from(t).as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// `CLOCK_MONOTONIC` in nanoseconds: one clock for every process on the machine, so a server
/// child can stamp "recorded" on the same time line as the edges' "submitted".
pub fn mono_ns() -> u64 {
    clock_ns(ClockId::CLOCK_MONOTONIC)
}

// ---------------------------------------------------------------------------------------------
// Identities

/// One synthetic edge's identity: its name (certificate CN) and its pairing bundle.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EdgeIdentity {
    /// The edge name the server files its recordings under.
    pub name: String,
    /// The bundle directory `scan3d pair` made for it (`pki_dir/edges/NAME`).
    pub bundle: PathBuf,
}

/// The name of the `index`th synthetic edge (`sim-edge-000`, `sim-edge-001`, …).
pub fn edge_name(index: usize) -> String {
    format!("{}-{index:03}", installation::EDGE_NAME)
}

/// Issues `count` edge bundles in `pki_dir` with the pairing code `scan3d pair` runs (the first
/// also creates the CA and a `localhost` server certificate), one identity per synthetic edge,
/// so that the server sees `count` distinct edges instead of one edge connecting `count` times.
/// Existing bundles of the same names are replaced.
pub fn pair_edges(pki_dir: &Path, count: usize) -> anyhow::Result<Vec<EdgeIdentity>> {
    (0..count)
        .map(|index| {
            let name = edge_name(index);
            let outcome = pki::pair(&PairRequest {
                dir: pki_dir.to_path_buf(),
                edge: name.clone(),
                server_names: Vec::new(),
                force: true,
            })?;
            Ok(EdgeIdentity {
                name,
                bundle: outcome.edge_dir,
            })
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Synthetic revolutions

/// How a lidar model reports a beam.
#[derive(Debug, Clone, Copy)]
enum Model {
    /// RPLidar A1 express scan: clockwise angles, mm ranges, fixed quality 47.
    RplidarExpress,
    /// Scanse Sweep: counter-clockwise angles, cm ranges, signal strength 0–255.
    Sweep,
}

impl Model {
    /// The scanner's azimuth (counter-clockwise, radians) of a reported angle.
    fn azimuth_rad(self, angle_deg: f64) -> f64 {
        match self {
            Model::RplidarExpress => -angle_deg.to_radians(),
            Model::Sweep => angle_deg.to_radians(),
        }
    }

    /// The reported range and quality of a measured range (`None`: no return).
    fn report(self, range_m: Option<f64>, rng: &mut impl Rng) -> (f32, u8) {
        let Some(range) = range_m else {
            return (0.0, 0);
        };
        match self {
            Model::RplidarExpress => (((range * 1000.0).round() / 1000.0) as f32, 47),
            Model::Sweep => {
                let strength = 250.0 - 12.0 * range + rng.random_range(-15.0..15.0);
                (
                    ((range * 100.0).round() / 100.0) as f32,
                    strength.clamp(1.0, 255.0) as u8,
                )
            }
        }
    }
}

/// One lidar's frame stream: its rate and a pool of distinct revolutions to restamp.
#[derive(Clone)]
pub struct LidarStream {
    /// The sensor's name, for reports.
    pub name: &'static str,
    /// Revolutions per second.
    pub hz: f64,
    /// Samples per revolution.
    pub samples: usize,
    templates: Arc<[LidarRevolution]>,
}

impl LidarStream {
    /// Distinct revolutions in each pool (different start angles and noise).
    const POOL: usize = 16;

    /// Both lidars of an edge, measured in `world`: RPLidar first, then Sweep.
    pub fn both(world: &Arc<World>) -> anyhow::Result<[Self; 2]> {
        Ok([Self::rplidar(world)?, Self::sweep(world)?])
    }

    /// RPLidar A1 express: 4000 samples/s at 5.5 rev/s.
    pub fn rplidar(world: &Arc<World>) -> anyhow::Result<Self> {
        let scanner = RplidarEmulator::default_scanner(world.clone(), mounts::rplidar());
        Self::synthesize(
            "RPLidar",
            SensorId::RPLIDAR,
            Model::RplidarExpress,
            5.5,
            727,
            &scanner,
        )
    }

    /// Scanse Sweep at 5 rev/s.
    pub fn sweep(world: &Arc<World>) -> anyhow::Result<Self> {
        let scanner = SweepEmulator::default_scanner(world.clone(), mounts::sweep());
        Self::synthesize("Sweep", SensorId::SWEEP, Model::Sweep, 5.0, 110, &scanner)
    }

    /// A pool of revolutions of `samples` beams each, measured by `scanner` as `model` reports.
    fn synthesize(
        name: &'static str,
        sensor: SensorId,
        model: Model,
        hz: f64,
        samples: usize,
        scanner: &Scanner,
    ) -> anyhow::Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(u64::from(sensor.0));
        let jitter = Normal::new(0.0, 0.05)?;
        let period_ns = 1e9 / hz;
        let step_deg = 360.0 / samples as f64;
        let mut templates = Vec::with_capacity(Self::POOL);
        for _ in 0..Self::POOL {
            let mut revolution = LidarRevolution::new(sensor, 0, period_ns as u64);
            let start_deg = rng.random_range(0.0..step_deg);
            for i in 0..samples {
                let angle =
                    (start_deg + i as f64 * step_deg + jitter.sample(&mut rng)).rem_euclid(360.0);
                let measured = scanner.measure(model.azimuth_rad(angle), &mut rng);
                let (range_m, quality) = model.report(measured, &mut rng);
                let t_ns = (i as f64 * period_ns / samples as f64) as u64;
                revolution.push(angle as f32, range_m, quality, t_ns)?;
            }
            templates.push(revolution);
        }
        Ok(Self {
            name,
            hz,
            samples,
            templates: templates.into(),
        })
    }

    /// Time between revolutions.
    pub fn period(&self) -> Duration {
        Duration::from_secs_f64(1.0 / self.hz)
    }

    /// The `index`th revolution of the stream, ending at `end_ns` on the edge clock.
    pub fn revolution(&self, index: usize, end_ns: u64) -> LidarRevolution {
        let mut revolution = self.templates[index % self.templates.len()].clone();
        let span = revolution.t1_ns - revolution.t0_ns;
        revolution.t1_ns = end_ns.max(span);
        revolution.t0_ns = revolution.t1_ns - span;
        revolution
    }

    /// Average encoded frame size in bytes (header included).
    pub fn frame_bytes(&self) -> anyhow::Result<f64> {
        let mut total = 0;
        for (seq, revolution) in self.templates.iter().enumerate() {
            total += encode(&Frame::new(u64::MAX, seq as u64, revolution.clone()))?.len();
        }
        Ok(total as f64 / self.templates.len() as f64)
    }
}

// ---------------------------------------------------------------------------------------------
// Simulated edges

/// A frame an edge submitted: its sequence number and when (`CLOCK_MONOTONIC` ns).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Submission {
    /// The frame's sequence number in the edge's session.
    pub seq: u64,
    /// When it was submitted, [`mono_ns`].
    pub at_ns: u64,
}

/// The producers' view of one simulated edge; cheap to clone.
#[derive(Clone)]
pub struct EdgeHandle {
    /// The edge's name (its certificate CN).
    pub name: Arc<str>,
    /// This run's session id.
    pub session_id: u64,
    /// The uplink's producer side.
    pub uplink: UplinkHandle,
    clock: SharedClock,
}

impl EdgeHandle {
    /// Submits the `index`th revolution of `stream`, stamped now.
    pub fn submit(&self, stream: &LidarStream, index: usize) -> Result<Submission, SubmitError> {
        self.submit_body(stream.revolution(index, self.clock.now_ns()).into())
    }

    /// Submits one frame body, noting when.
    pub fn submit_body(&self, body: scan3d_protocol::Body) -> Result<Submission, SubmitError> {
        let at_ns = mono_ns();
        let seq = self.uplink.submit(body)?;
        Ok(Submission { seq, at_ns })
    }

    /// Every frame with a sequence number below this is acknowledged.
    ///
    /// The spool drops a frame exactly when the server's acknowledgement for it arrives; while
    /// the server acknowledges in order (on loopback it does), `submitted − pending` is the
    /// acknowledged prefix. Reading `submitted` before `pending` (and the uplink counting a
    /// submission only after spooling it) can only make the result too small, never too large.
    /// `pending() == 0` is the exact "everything acknowledged".
    pub fn acked_prefix(&self) -> u64 {
        let submitted = self.uplink.stats().submitted;
        submitted.saturating_sub(self.uplink.pending() as u64)
    }
}

/// The uplink settings a real edge paired as `identity` would use to reach `server`: its TLS
/// bundle, an 8 MiB memory + 256 MiB disk spool in `spool_dir` (as [`installation::uplink_section`]),
/// the edge's default backoffs and QUIC transport.
pub fn uplink_config(
    server: SocketAddr,
    identity: &EdgeIdentity,
    spool_dir: PathBuf,
) -> anyhow::Result<UplinkConfig> {
    let section = installation::uplink_section(server, &identity.bundle);
    let spool = section.spool_config(spool_dir)?;
    Ok(UplinkConfig::new(
        section.server.clone(),
        section.tls_name().to_owned(),
        tls::client_config(&section.pki_dir)?,
        spool,
    ))
}

/// One simulated edge: the real uplink client with its own identity, spool and session.
pub struct SimEdge {
    /// What producers use.
    pub handle: EdgeHandle,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<UplinkStats>,
}

impl SimEdge {
    /// Starts an uplink to `server` as `identity`, spooling in `spool_dir`, on `runtime`, with
    /// the edge's own settings ([`uplink_config`]).
    pub fn start(
        runtime: &Runtime,
        server: SocketAddr,
        identity: &EdgeIdentity,
        spool_dir: PathBuf,
        session_id: u64,
    ) -> anyhow::Result<Self> {
        let config = uplink_config(server, identity, spool_dir)?;
        Self::start_with(runtime, config, identity, session_id)
    }

    /// Starts an uplink with `config` (from [`uplink_config`], possibly changed) as `identity`.
    pub fn start_with(
        runtime: &Runtime,
        config: UplinkConfig,
        identity: &EdgeIdentity,
        session_id: u64,
    ) -> anyhow::Result<Self> {
        let clock: SharedClock = Arc::new(MonotonicClock::new());
        // Synthetic edges act on no server command: the receiver is dropped.
        let (uplink, handle, _commands) = Uplink::new(config, clock.clone(), session_id)?;
        let (stop, stopped) = watch::channel(false);
        let task = runtime.spawn(uplink.run(stopped));
        Ok(Self {
            handle: EdgeHandle {
                name: identity.name.as_str().into(),
                session_id,
                uplink: handle,
                clock,
            },
            stop,
            task,
        })
    }

    /// Stops the uplink (after at most its drain timeout) and returns its counters.
    pub fn stop(self, runtime: &Runtime) -> anyhow::Result<UplinkStats> {
        let _ = self.stop.send(true);
        Ok(runtime.block_on(self.task)?)
    }
}

/// What one producer submitted.
#[derive(Debug, Default)]
pub struct Produced {
    /// Every frame the spool took, in order.
    pub submissions: Vec<Submission>,
    /// Frames the spool refused (the server did not keep up; a real edge pauses acquisition).
    pub refused: u64,
}

/// Static scans a synthetic edge runs back to back on its Sweep stream, so the server's
/// pipeline assembles and inserts 3D points as it does for a real turntable: each scan turns
/// 180° in `revolutions` steps, one per Sweep revolution, and every revolution's samples outside
/// the blocked sector (θ in 150°–210°) are tagged with their yaw, half a revolution before the
/// step and half after, as the edge's controller does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StaticScanPlan {
    /// Sweep revolutions (turntable steps) per static scan.
    pub revolutions: u32,
}

impl StaticScanPlan {
    /// The yaw runs of revolution `r` of a scan for a Sweep revolution of `samples` samples at
    /// even azimuths, and how many samples they tag.
    fn runs(&self, r: u32, samples: u32) -> (Vec<YawRun>, u64) {
        let step = 180.0 / f64::from(self.revolutions);
        let azimuth = |i: u32| 360.0 * f64::from(i) / f64::from(samples);
        let mut runs: Vec<YawRun> = Vec::new();
        let mut tagged = 0;
        for i in 0..samples {
            let a = azimuth(i);
            if (150.0..=210.0).contains(&a) {
                continue;
            }
            let yaw = (step * f64::from(if a < 180.0 { r } else { r + 1 })) as f32;
            tagged += 1;
            match runs.last_mut() {
                Some(run) if run.yaw_deg == yaw && run.first_index + run.count == i => {
                    run.count += 1
                }
                _ => runs.push(YawRun {
                    first_index: i,
                    count: 1,
                    yaw_deg: yaw,
                }),
            }
        }
        (runs, tagged)
    }
}

/// Submits one revolution of `stream` per period from `first` until `deadline`, as the edge's
/// acquisition does when a revolution completes; with `static_scans`, a Sweep stream also
/// submits the static-scan messages around its revolutions (see [`StaticScanPlan`]).
pub async fn produce(
    edge: EdgeHandle,
    stream: LidarStream,
    first: tokio::time::Instant,
    deadline: tokio::time::Instant,
    static_scans: Option<StaticScanPlan>,
) -> Produced {
    let mut tick = tokio::time::interval_at(first, stream.period());
    let mut produced = Produced::default();
    let plan = static_scans.filter(|_| {
        stream
            .templates
            .first()
            .is_some_and(|t| t.sensor == SensorId::SWEEP)
    });
    let mut scan_id = 0u32;
    let mut tagged = 0u64;
    let submit = |produced: &mut Produced, body: scan3d_protocol::Body| match edge.submit_body(body)
    {
        Ok(submission) => produced.submissions.push(submission),
        Err(_) => produced.refused += 1,
    };
    for index in 0.. {
        if tick.tick().await >= deadline {
            break;
        }
        let revolution = stream.revolution(index, edge.clock.now_ns());
        let Some(plan) = plan else {
            submit(&mut produced, revolution.into());
            continue;
        };
        let r = (index % plan.revolutions as usize) as u32;
        if r == 0 {
            submit(
                &mut produced,
                StaticScan::Started(StaticScanStart {
                    scan_id,
                    t_ns: revolution.t0_ns,
                    position: format!("fleet-{scan_id}"),
                    x_m: 4.0,
                    y_m: 3.0,
                    heading_deg: 0.0,
                    step_deg: 180.0 / f64::from(plan.revolutions),
                    total_deg: 180.0,
                    blocked_sector_deg: 60.0,
                    mount: MountInfo {
                        axis_offset_m: 0.05,
                        height_m: 1.0,
                        azimuth_zero_deg: 0.0,
                    },
                })
                .into(),
            );
            tagged = 0;
        }
        let samples = u32::try_from(revolution.samples.len()).unwrap_or(u32::MAX);
        let (runs, n) = plan.runs(r, samples);
        tagged += n;
        let yaws = StaticScanYaws {
            scan_id,
            revolution_t0_ns: revolution.t0_ns,
            runs,
        };
        let t1 = revolution.t1_ns;
        submit(&mut produced, revolution.into());
        submit(&mut produced, StaticScan::Yaws(yaws).into());
        if r + 1 == plan.revolutions {
            submit(
                &mut produced,
                StaticScan::Finished(StaticScanEnd {
                    scan_id,
                    t_ns: t1,
                    outcome: StaticScanOutcome::Completed,
                    yaw_deg: 180.0,
                    revolutions: plan.revolutions,
                    tagged,
                    blocked: 0,
                    untrusted: 0,
                    late_steps: 0,
                    failed_steps: 0,
                })
                .into(),
            );
            scan_id += 1;
        }
    }
    produced
}

/// Producers running on a runtime, one per lidar stream per edge; see [`Producers::start`].
pub struct Producers {
    tasks: Vec<tokio::task::JoinHandle<Produced>>,
    edges: usize,
    streams: usize,
}

impl Producers {
    /// Starts one producer per lidar stream per edge on `runtime`, every lidar at its own
    /// random phase (real edges are not in step; seeded by the edge's index), from `begin`
    /// until `deadline`.
    pub fn start(
        runtime: &Runtime,
        edges: &[EdgeHandle],
        streams: &[LidarStream],
        begin: tokio::time::Instant,
        deadline: tokio::time::Instant,
    ) -> Self {
        Self::start_with(runtime, edges, streams, begin, deadline, None)
    }

    /// [`Producers::start`], every edge also running `static_scans` on its Sweep stream.
    pub fn start_with(
        runtime: &Runtime,
        edges: &[EdgeHandle],
        streams: &[LidarStream],
        begin: tokio::time::Instant,
        deadline: tokio::time::Instant,
        static_scans: Option<StaticScanPlan>,
    ) -> Self {
        let tasks = edges
            .iter()
            .enumerate()
            .flat_map(|(i, edge)| {
                let mut rng = ChaCha8Rng::seed_from_u64(i as u64);
                streams.iter().map(move |stream| {
                    let phase = stream.period().mul_f64(rng.random_range(0.0..1.0));
                    (edge.clone(), stream.clone(), phase)
                })
            })
            .map(|(edge, stream, phase)| {
                runtime.spawn(produce(edge, stream, begin + phase, deadline, static_scans))
            })
            .collect();
        Self {
            tasks,
            edges: edges.len(),
            streams: streams.len(),
        }
    }

    /// Waits for every producer (until their deadline) and returns what each edge produced,
    /// in edge order, submissions sorted by sequence number.
    pub fn join(self, runtime: &Runtime) -> anyhow::Result<Vec<Produced>> {
        let mut per_edge: Vec<Produced> = (0..self.edges).map(|_| Produced::default()).collect();
        for (i, task) in self.tasks.into_iter().enumerate() {
            let produced = runtime.block_on(task)?;
            let edge = &mut per_edge[i / self.streams.max(1)];
            edge.submissions.extend(produced.submissions);
            edge.refused += produced.refused;
        }
        for edge in &mut per_edge {
            edge.submissions.sort_by_key(|s| s.seq);
        }
        Ok(per_edge)
    }
}

/// Per edge, the times at which its acknowledged prefix grew: `(prefix, CLOCK_MONOTONIC ns)`,
/// polled every `every` until `stop` (so acknowledgement times are late by up to a poll).
pub async fn watch_acks(
    edges: Vec<EdgeHandle>,
    every: Duration,
    mut stop: watch::Receiver<bool>,
) -> Vec<Vec<(u64, u64)>> {
    let mut timelines: Vec<Vec<(u64, u64)>> = vec![Vec::new(); edges.len()];
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.changed() => return timelines,
        }
        let now = mono_ns();
        for (edge, timeline) in edges.iter().zip(&mut timelines) {
            let prefix = edge.acked_prefix();
            if timeline.last().is_none_or(|&(last, _)| prefix > last) {
                timeline.push((prefix, now));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_synthetic_edge_gets_its_own_certificate_and_name() {
        let dir = std::env::temp_dir().join(format!("scan3d-fleet-pair-{}", std::process::id()));
        let identities = pair_edges(&dir, 3).unwrap();
        let names: Vec<&str> = identities.iter().map(|i| i.name.as_str()).collect();
        assert_eq!(names, ["sim-edge-000", "sim-edge-001", "sim-edge-002"]);
        let certs: Vec<Vec<u8>> = identities
            .iter()
            .map(|i| std::fs::read(i.bundle.join("edge.pem")).unwrap())
            .collect();
        assert_ne!(certs[0], certs[1]);
        assert_ne!(certs[1], certs[2]);
        // One CA for all of them, so one server trusts every edge.
        let cas: Vec<Vec<u8>> = identities
            .iter()
            .map(|i| std::fs::read(i.bundle.join("ca.pem")).unwrap())
            .collect();
        assert!(cas.windows(2).all(|w| w[0] == w[1]));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
