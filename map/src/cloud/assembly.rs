//! 3D assembly of static scans at known positions: the paper's eq. (1) with the mount geometry.
//!
//! The Sweep spins in a vertical plane on a turntable. θ is its beam azimuth in that plane,
//! with θ = 0 pointing up (z = L·cos θ), so θ ≈ π points down into the base, where the beam is
//! blocked. φ is the turntable's yaw. For a sample (L, θ) taken at yaw φ at the position
//! (x_p, y_p), eq. (1) gives
//!
//! ```text
//! x = x_p − L·sin θ·sin φ
//! y = y_p + L·sin θ·cos φ
//! z =       L·cos θ
//! ```
//!
//! Samples with θ ∈ (0, π) use the yaw in effect during the first half of the revolution;
//! the stepper turns by δφ while the beam crosses the blocked sector, so samples with
//! θ ∈ (π, 2π) use φ + δφ. Which yaw applies is decided when the sample is tagged on the edge;
//! θ is [`scan3d_protocol::theta_deg`], the definition the edge's blocked sector uses too.
//!
//! The samples reach the server once, in the Sweep's `Body::Revolution` frames; the edge's
//! `StaticScan::Yaws` messages name a revolution by its `t0_ns` and give φ for runs of its
//! sample indices. [`StaticScanAssembler`] joins the two by `t0_ns`, whichever comes first.
//!
//! Beyond the paper, [`MountGeometry`] places the Sweep's optical centre relative to the
//! turntable axis (its offset beside the axis and its height) and the azimuth at which the
//! device reports 0; [`Position`] adds a heading φ0 so several positions can be spliced in
//! one world frame.

use std::collections::VecDeque;

use scan3d_protocol::{
    Body, LidarRevolution, RevolutionSample, SensorId, StaticScan, StaticScanOutcome,
    StaticScanWarning, StaticScanYaws, YawRun,
};
use serde::{Deserialize, Serialize};

pub use super::RayBundle;

/// How the Sweep sits on the turntable.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MountGeometry {
    /// Distance of the Sweep's optical centre from the turntable axis, along the scan plane's
    /// normal (+ = towards yaw direction φ), metres.
    pub axis_offset_m: f64,
    /// Height of the optical centre above the floor, metres.
    pub height_m: f64,
    /// The device azimuth that points straight up (θ = 0 of eq. (1)), degrees.
    pub azimuth_zero_deg: f64,
}

impl Default for MountGeometry {
    fn default() -> Self {
        Self {
            axis_offset_m: 0.0,
            height_m: 0.0,
            azimuth_zero_deg: 0.0,
        }
    }
}

/// A scan position on the floor, in the global frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Position {
    /// The operator's name for it (e.g. `"door"`).
    pub name: String,
    /// x_p, metres.
    pub x_m: f64,
    /// y_p, metres.
    pub y_m: f64,
    /// φ0: the turntable yaw 0 expressed in the global frame, degrees.
    pub heading_deg: f64,
}

/// One Sweep sample of a static scan, with the turntable yaw it was taken at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticSample {
    /// Range L, metres (`0.0` = no return: skipped).
    pub range_m: f64,
    /// Device azimuth, degrees (counter-clockwise, as the Sweep reports it).
    pub azimuth_deg: f64,
    /// Turntable yaw φ in effect for this sample, degrees (relative to the position's heading).
    pub yaw_deg: f64,
}

/// The sensor origin (optical centre) at yaw `yaw_deg` for `position`.
pub fn sensor_origin(position: &Position, mount: &MountGeometry, yaw_deg: f64) -> [f64; 3] {
    let phi = (position.heading_deg + yaw_deg).to_radians();
    [
        position.x_m + mount.axis_offset_m * phi.cos(),
        position.y_m + mount.axis_offset_m * phi.sin(),
        mount.height_m,
    ]
}

/// Eq. (1): the world point of one sample, or `None` for a sample without return.
pub fn static_point(
    position: &Position,
    mount: &MountGeometry,
    sample: &StaticSample,
) -> Option<[f64; 3]> {
    if !(sample.range_m.is_finite() && sample.range_m > 0.0) {
        return None;
    }
    let theta = scan3d_protocol::theta_deg(sample.azimuth_deg, mount.azimuth_zero_deg).to_radians();
    let phi = (position.heading_deg + sample.yaw_deg).to_radians();
    let [ox, oy, oz] = sensor_origin(position, mount, sample.yaw_deg);
    let l = sample.range_m;
    Some([
        ox - l * theta.sin() * phi.sin(),
        oy + l * theta.sin() * phi.cos(),
        oz + l * theta.cos(),
    ])
}

/// One static scan of a session, assembled in the world frame.
#[derive(Debug, Clone, PartialEq)]
pub struct AssembledScan {
    /// The scan's number within its edge session.
    pub scan_id: u32,
    /// Where it was taken.
    pub position: Position,
    /// How the Sweep sat on the turntable.
    pub mount: MountGeometry,
    /// Points grouped by sensor origin: one group per half revolution (each half has one yaw,
    /// hence one optical centre; one run of a `StaticScan::Yaws` message), in recorded order.
    pub scans: Vec<RayBundle>,
    /// How it ended, if the end was recorded.
    pub outcome: Option<StaticScanOutcome>,
    /// Warnings the edge sent (late or failed steps, missed sectors).
    pub warnings: Vec<StaticScanWarning>,
    /// Samples without a return (range 0), skipped.
    pub no_return: u64,
}

impl AssembledScan {
    /// Number of points.
    pub fn points(&self) -> usize {
        self.scans.iter().map(|s| s.points.len()).sum()
    }
}

/// Sweep revolutions kept for yaw messages that come after them (the edge sends a
/// revolution's yaws once its samples are decided, normally just before the revolution frame).
const RECENT_REVOLUTIONS: usize = 64;
/// Yaw messages kept while their revolution frame has not come yet.
const WAITING_YAWS: usize = 64;

/// Turns a session's frames into world-frame points with eq. (1): feed every recorded body in
/// order (Sweep revolutions and `StaticScan` messages; others are ignored), then take
/// [`StaticScanAssembler::finish`]. A revolution's yaws and its samples are joined by the
/// revolution's `t0_ns` in either order, from a bounded buffer of recent Sweep revolutions and
/// of yaw messages waiting for theirs. Samples that cannot be placed — their scan's start was
/// not recorded, their revolution is missing (a later one came first) or was evicted, an index
/// past its revolution's end — are counted in [`StaticScanAssembler::orphan_samples`], never
/// guessed.
#[derive(Debug, Default)]
pub struct StaticScanAssembler {
    scans: Vec<AssembledScan>,
    orphans: u64,
    /// How many origin groups of each scan [`StaticScanAssembler::take_new`] has handed out.
    taken: Vec<usize>,
    /// The last Sweep revolutions since a scan started, `(t0_ns, samples)`, oldest first.
    revolutions: VecDeque<(u64, Vec<RevolutionSample>)>,
    /// Yaw messages whose revolution has not come yet, oldest first.
    waiting: VecDeque<StaticScanYaws>,
}

/// Points seen from one sensor origin (a half revolution of a static scan), handed out by
/// [`StaticScanAssembler::take_new`] as soon as they are complete, for incremental maps.
#[derive(Debug, Clone, PartialEq)]
pub struct NewRays {
    /// Index of the scan in [`StaticScanAssembler::scans`].
    pub scan_index: usize,
    /// The operator's name of the scan's position.
    pub position: String,
    /// The points and their origin, world frame.
    pub rays: RayBundle,
}

impl StaticScanAssembler {
    /// An empty assembler.
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes one frame body: Sweep revolutions and `StaticScan` messages; anything else is
    /// ignored.
    pub fn on_body(&mut self, body: &Body) {
        match body {
            Body::Revolution(rev) if rev.sensor == SensorId::SWEEP => self.on_revolution(rev),
            Body::StaticScan(message) => self.on_static_scan(message),
            _ => {}
        }
    }

    fn on_static_scan(&mut self, message: &StaticScan) {
        match message {
            StaticScan::Started(start) => self.scans.push(AssembledScan {
                scan_id: start.scan_id,
                position: Position {
                    name: start.position.clone(),
                    x_m: start.x_m,
                    y_m: start.y_m,
                    heading_deg: start.heading_deg,
                },
                mount: MountGeometry {
                    axis_offset_m: start.mount.axis_offset_m,
                    height_m: start.mount.height_m,
                    azimuth_zero_deg: start.mount.azimuth_zero_deg,
                },
                scans: Vec::new(),
                outcome: None,
                warnings: Vec::new(),
                no_return: 0,
            }),
            StaticScan::Yaws(yaws) => self.on_yaws(yaws),
            StaticScan::Warning(warning) => {
                if let Some(scan) = self.current(warning.scan_id) {
                    scan.warnings.push(warning.clone());
                }
            }
            StaticScan::Finished(end) => {
                if let Some(scan) = self.current(end.scan_id) {
                    scan.outcome = Some(end.outcome);
                }
            }
        }
    }

    fn on_yaws(&mut self, yaws: &StaticScanYaws) {
        if self.current(yaws.scan_id).is_none() {
            self.orphans = self.orphans.saturating_add(yaws.tagged_samples());
            return;
        }
        let t0 = yaws.revolution_t0_ns;
        if let Some(index) = self.revolutions.iter().position(|(t, _)| *t == t0) {
            let samples = std::mem::take(&mut self.revolutions[index].1);
            self.join(yaws.scan_id, &samples, &yaws.runs);
            self.revolutions[index].1 = samples;
        } else if self
            .revolutions
            .back()
            .is_some_and(|(newest, _)| *newest > t0)
        {
            // Revolution frames come in time order: one older than the newest seen that is
            // not here was dropped on the edge or evicted here.
            self.orphans = self.orphans.saturating_add(yaws.tagged_samples());
        } else {
            if self.waiting.len() == WAITING_YAWS
                && let Some(oldest) = self.waiting.pop_front()
            {
                self.orphans = self.orphans.saturating_add(oldest.tagged_samples());
            }
            self.waiting.push_back(yaws.clone());
        }
    }

    fn on_revolution(&mut self, rev: &LidarRevolution) {
        if self.scans.is_empty() {
            // No static scan yet: nothing can refer to this revolution.
            return;
        }
        let t0 = rev.t0_ns;
        let mut index = 0;
        while index < self.waiting.len() {
            let waiting_t0 = self.waiting[index].revolution_t0_ns;
            if waiting_t0 > t0 {
                index += 1;
                continue;
            }
            let Some(yaws) = self.waiting.remove(index) else {
                break;
            };
            if waiting_t0 == t0 {
                self.join(yaws.scan_id, &rev.samples, &yaws.runs);
            } else {
                // A later revolution came first: this one will not come.
                self.orphans = self.orphans.saturating_add(yaws.tagged_samples());
            }
        }
        if self.revolutions.len() == RECENT_REVOLUTIONS {
            self.revolutions.pop_front();
        }
        self.revolutions.push_back((t0, rev.samples.clone()));
    }

    /// Places the runs of one revolution's samples in the scan `scan_id`.
    fn join(&mut self, scan_id: u32, samples: &[RevolutionSample], runs: &[YawRun]) {
        let Some(scan) = self.current(scan_id) else {
            let tagged = runs.iter().map(|r| u64::from(r.count)).sum::<u64>();
            self.orphans = self.orphans.saturating_add(tagged);
            return;
        };
        let past_end = scan.add(samples, runs);
        self.orphans = self.orphans.saturating_add(past_end);
    }

    /// Samples that could not be placed: their scan's start was never seen, their revolution
    /// frame is missing or was evicted, or their index is past its revolution's end — plus
    /// those still waiting for a revolution frame (at the end of a session, the ones whose
    /// revolution was never sent).
    pub fn orphan_samples(&self) -> u64 {
        self.waiting
            .iter()
            .fold(self.orphans, |n, y| n.saturating_add(y.tagged_samples()))
    }

    /// The assembled scans, in start order.
    pub fn finish(self) -> Vec<AssembledScan> {
        self.scans
    }

    /// The scans assembled so far, in start order.
    pub fn scans(&self) -> &[AssembledScan] {
        &self.scans
    }

    /// The origin groups completed since the last call, in recorded order. Every group is
    /// complete once the body that produced it was taken (one yaw per half revolution), so a
    /// live map can insert them at once; they stay in [`StaticScanAssembler::scans`] too.
    pub fn take_new(&mut self) -> Vec<NewRays> {
        self.taken.resize(self.scans.len(), 0);
        let mut new = Vec::new();
        for (scan_index, (scan, taken)) in self.scans.iter().zip(&mut self.taken).enumerate() {
            new.extend(scan.scans[*taken..].iter().map(|rays| NewRays {
                scan_index,
                position: scan.position.name.clone(),
                rays: rays.clone(),
            }));
            *taken = scan.scans.len();
        }
        new
    }

    /// The latest scan with this id (ids restart with each edge session).
    fn current(&mut self, scan_id: u32) -> Option<&mut AssembledScan> {
        self.scans.iter_mut().rev().find(|s| s.scan_id == scan_id)
    }
}

impl AssembledScan {
    /// Adds the tagged samples of one revolution: an origin group per run (the edge makes one
    /// run per half revolution), opened at its first point. Returns how many tagged indices
    /// lie past the revolution's end (not placed).
    fn add(&mut self, samples: &[RevolutionSample], runs: &[YawRun]) -> u64 {
        let mut past_end = 0u64;
        for run in runs {
            let mut group_open = false;
            let first = usize::try_from(run.first_index).unwrap_or(usize::MAX);
            let count = usize::try_from(run.count).unwrap_or(usize::MAX);
            let end = first.saturating_add(count);
            let placed = samples.get(first.min(samples.len())..end.min(samples.len()));
            let placed = placed.unwrap_or_default();
            past_end = past_end.saturating_add((count - placed.len()) as u64);
            for sample in placed {
                let static_sample = StaticSample {
                    range_m: f64::from(sample.range_m),
                    azimuth_deg: f64::from(sample.angle_deg),
                    yaw_deg: f64::from(run.yaw_deg),
                };
                let Some(point) = static_point(&self.position, &self.mount, &static_sample) else {
                    self.no_return += 1;
                    continue;
                };
                if !group_open {
                    group_open = true;
                    self.scans.push(RayBundle {
                        origin: sensor_origin(&self.position, &self.mount, static_sample.yaw_deg),
                        points: Vec::new(),
                    });
                }
                if let Some(scan) = self.scans.last_mut() {
                    scan.points.push(point.map(|c| c as f32));
                }
            }
        }
        past_end
    }
}

/// Drops points farther than `max_range_m` from their scan's sensor origin (a range limit
/// applied after assembly, e.g. the paper's 6 m / 10 m maps); returns how many were dropped.
pub fn cut_range(scans: &mut [RayBundle], max_range_m: f64) -> usize {
    let mut cut = 0;
    for scan in scans {
        let o = scan.origin;
        let before = scan.points.len();
        scan.points.retain(|p| {
            let d2: f64 = (0..3).map(|i| (f64::from(p[i]) - o[i]).powi(2)).sum();
            d2 <= max_range_m * max_range_m
        });
        cut += before - scan.points.len();
    }
    cut
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at_origin() -> Position {
        Position {
            name: "p".into(),
            x_m: 0.0,
            y_m: 0.0,
            heading_deg: 0.0,
        }
    }

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
    }

    fn point(position: &Position, range: f64, azimuth: f64, yaw: f64) -> [f64; 3] {
        let sample = StaticSample {
            range_m: range,
            azimuth_deg: azimuth,
            yaw_deg: yaw,
        };
        static_point(position, &MountGeometry::default(), &sample).expect("a return")
    }

    #[test]
    fn equation_one_by_hand() {
        let p = Position {
            name: "a".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 0.0,
        };
        // θ = 0: straight up.
        assert!(close(point(&p, 2.0, 0.0, 30.0), [1.0, 2.0, 2.0]));
        // θ = 90°, φ = 0: along +y.
        assert!(close(point(&p, 2.0, 90.0, 0.0), [1.0, 4.0, 0.0]));
        // θ = 90°, φ = 90°: along −x.
        assert!(close(point(&p, 2.0, 90.0, 90.0), [-1.0, 2.0, 0.0]));
        // θ = 270° (second half): the opposite side of the same plane.
        assert!(close(point(&p, 2.0, 270.0, 0.0), [1.0, 0.0, 0.0]));
    }

    #[test]
    fn the_second_half_revolution_uses_phi_plus_delta_phi() {
        // The beam at θ = 90° before the step and θ = 270° after a 1.8° step sees two points
        // whose planes differ by exactly δφ.
        let p = at_origin();
        let first = point(&p, 1.0, 90.0, 0.0);
        let second = point(&p, 1.0, 270.0, 1.8);
        let angle_first = first[1].atan2(first[0]).to_degrees();
        let angle_second = (-second[1]).atan2(-second[0]).to_degrees();
        assert!(
            (angle_second - angle_first - 1.8).abs() < 1e-9,
            "{angle_first} {angle_second}"
        );
    }

    #[test]
    fn mount_geometry_and_heading_move_the_origin() {
        let mount = MountGeometry {
            axis_offset_m: 0.1,
            height_m: 1.0,
            azimuth_zero_deg: 180.0,
        };
        let p = Position {
            name: "b".into(),
            x_m: 3.0,
            y_m: 0.0,
            heading_deg: 90.0,
        };
        assert!(close(sensor_origin(&p, &mount, 0.0), [3.0, 0.1, 1.0]));
        // Device azimuth 180° is "up" on this mount.
        let s = StaticSample {
            range_m: 1.5,
            azimuth_deg: 180.0,
            yaw_deg: 0.0,
        };
        assert!(close(
            static_point(&p, &mount, &s).unwrap(),
            [3.0, 0.1, 2.5]
        ));
        let none = StaticSample { range_m: 0.0, ..s };
        assert_eq!(static_point(&p, &mount, &none), None);
    }

    use scan3d_protocol::{MountInfo, StaticScanEnd, StaticScanStart};

    fn started(scan_id: u32) -> Body {
        Body::StaticScan(StaticScan::Started(StaticScanStart {
            scan_id,
            t_ns: 0,
            position: "door".into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 90.0,
            step_deg: 1.8,
            total_deg: 180.0,
            blocked_sector_deg: 60.0,
            mount: MountInfo {
                axis_offset_m: 0.1,
                height_m: 0.5,
                azimuth_zero_deg: 0.0,
            },
        }))
    }

    /// A Sweep revolution starting at `t0_ns` with samples (azimuth, range).
    fn revolution(sensor: SensorId, t0_ns: u64, samples: &[(f32, f32)]) -> Body {
        let mut rev = LidarRevolution::new(sensor, t0_ns, t0_ns + 500_000_000);
        for (k, &(azimuth, range)) in samples.iter().enumerate() {
            rev.push(azimuth, range, 9, t0_ns + k as u64).unwrap();
        }
        Body::Revolution(rev)
    }

    fn yaws(scan_id: u32, revolution_t0_ns: u64, runs: &[(u32, u32, f32)]) -> Body {
        Body::StaticScan(StaticScan::Yaws(StaticScanYaws {
            scan_id,
            revolution_t0_ns,
            runs: runs
                .iter()
                .map(|&(first_index, count, yaw_deg)| YawRun {
                    first_index,
                    count,
                    yaw_deg,
                })
                .collect(),
        }))
    }

    /// Four samples: up-ish first half, a blocked one, a no-return, the second half.
    const SAMPLES: [(f32, f32); 5] = [
        (90.0, 2.0),
        (100.0, 0.0), // no return
        (180.0, 0.3), // blocked: in no run
        (270.0, 2.0),
        (280.0, 2.0),
    ];

    #[test]
    fn yaws_are_joined_with_their_sweep_revolution_by_t0_and_grouped_by_half_revolution_origin() {
        let mut assembler = StaticScanAssembler::new();
        // Yaws before any start are orphans, not guessed.
        assembler.on_body(&yaws(0, 7, &[(0, 1, 0.0)]));
        assert_eq!(assembler.orphan_samples(), 1);
        assembler.on_body(&started(0));
        // The yaws usually come just before their revolution; they wait for it.
        assembler.on_body(&yaws(0, 1_000, &[(0, 2, 0.0), (3, 2, 1.8)]));
        assert!(assembler.take_new().is_empty());
        assert_eq!(assembler.orphan_samples(), 1 + 4, "waiting, not placed yet");
        // An RPLidar revolution with the same t0 is another sensor's.
        assembler.on_body(&revolution(SensorId::RPLIDAR, 1_000, &SAMPLES));
        assert!(assembler.take_new().is_empty());
        assembler.on_body(&revolution(SensorId::SWEEP, 1_000, &SAMPLES));
        assert_eq!(assembler.orphan_samples(), 1);
        let new = assembler.take_new();
        assert_eq!(
            new.len(),
            2,
            "both half revolutions are complete once joined"
        );
        assert!(
            new.iter()
                .all(|n| n.scan_index == 0 && n.position == "door")
        );
        assert_eq!(new[1].rays, assembler.scans()[0].scans[1]);
        assert!(
            assembler.take_new().is_empty(),
            "each group is handed out once"
        );
        // The other order: the revolution first, then its yaws (from the recent buffer).
        assembler.on_body(&revolution(SensorId::SWEEP, 2_000, &SAMPLES));
        assembler.on_body(&yaws(0, 2_000, &[(0, 1, 3.6)]));
        assert_eq!(assembler.take_new().len(), 1);
        assembler.on_body(&Body::StaticScan(StaticScan::Finished(StaticScanEnd {
            scan_id: 0,
            t_ns: 1,
            outcome: StaticScanOutcome::Completed,
            yaw_deg: 180.0,
            revolutions: 100,
            tagged: 5,
            blocked: 2,
            untrusted: 0,
            late_steps: 0,
            failed_steps: 0,
        })));
        assert_eq!(assembler.orphan_samples(), 1);
        let scans = assembler.finish();
        assert_eq!(scans.len(), 1);
        let scan = &scans[0];
        assert_eq!(scan.outcome, Some(StaticScanOutcome::Completed));
        assert_eq!((scan.points(), scan.no_return), (4, 1));
        assert_eq!(scan.scans.len(), 3, "one origin per half revolution");
        // φ = 90°: the optical centre is 0.1 m along (cos φ, sin φ) = +y from (1, 2), 0.5 m up.
        let o = scan.scans[0].origin;
        assert!(close(o, [1.0, 2.1, 0.5]), "{o:?}");
        // θ = 90°, φ = 90°: the beam points along −x.
        let p = scan.scans[0].points[0].map(f64::from);
        assert!(close_f32(p, [-1.0, 2.1, 0.5]), "{p:?}");
        // Second half at φ + δφ = 91.8°: θ = 270° points along +x rotated by 1.8°.
        let phi = 91.8f64.to_radians();
        let o2 = scan.scans[1].origin;
        assert!(close(
            o2,
            [1.0 + 0.1 * phi.cos(), 2.0 + 0.1 * phi.sin(), 0.5]
        ));
        assert_eq!(scan.scans[1].points.len(), 2);
        let q = scan.scans[1].points[0].map(f64::from);
        assert!(close_f32(
            q,
            [o2[0] + 2.0 * phi.sin(), o2[1] - 2.0 * phi.cos(), 0.5]
        ));
    }

    #[test]
    fn yaws_of_a_missing_or_evicted_revolution_and_indices_past_its_end_are_orphans() {
        let mut assembler = StaticScanAssembler::new();
        assembler.on_body(&started(0));
        // Waiting for revolution 1 000, but 2 000 comes: 1 000 was dropped on the edge.
        assembler.on_body(&yaws(0, 1_000, &[(0, 3, 0.0)]));
        assembler.on_body(&revolution(SensorId::SWEEP, 2_000, &SAMPLES));
        assert_eq!(assembler.orphan_samples(), 3);
        // Yaws for a revolution older than the newest seen, not in the buffer: orphans at once.
        assembler.on_body(&yaws(0, 1_500, &[(0, 2, 0.0)]));
        assert_eq!(assembler.orphan_samples(), 5);
        // Indices past the revolution's five samples.
        assembler.on_body(&yaws(0, 2_000, &[(3, 4, 1.8)]));
        assert_eq!(assembler.orphan_samples(), 7);
        assert_eq!(assembler.scans()[0].points(), 2);
        // A revolution pushed out of the bounded buffer cannot be joined any more.
        for k in 0..RECENT_REVOLUTIONS as u64 {
            assembler.on_body(&revolution(SensorId::SWEEP, 3_000 + k, &SAMPLES));
        }
        assembler.on_body(&yaws(0, 2_000, &[(0, 1, 1.8)]));
        assert_eq!(assembler.orphan_samples(), 8);
        // Yaws of a scan never started.
        assembler.on_body(&yaws(9, 3_000, &[(0, 1, 1.8)]));
        assert_eq!(assembler.orphan_samples(), 9);
        assert_eq!(assembler.scans()[0].points(), 2, "nothing was guessed");
    }

    fn close_f32(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5)
    }
}
