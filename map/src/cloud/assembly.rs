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
//! here every sample carries its own φ.
//!
//! Beyond the paper, [`MountGeometry`] places the Sweep's optical centre relative to the
//! turntable axis (its offset beside the axis and its height) and the azimuth at which the
//! device reports 0; [`Position`] adds a heading φ0 so several positions can be spliced in
//! one world frame.

use scan3d_protocol::{Body, StaticScan, StaticScanOutcome, StaticScanSamples, StaticScanWarning};
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
    let theta = (sample.azimuth_deg - mount.azimuth_zero_deg).to_radians();
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
    /// hence one optical centre), in recorded order.
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

/// Turns a session's `StaticScan` frames into world-frame points with eq. (1): feed every
/// recorded frame in order, then take [`StaticScanAssembler::finish`]. Samples of a scan whose
/// start was not recorded are counted in [`StaticScanAssembler::orphan_samples`], never guessed.
#[derive(Debug, Default)]
pub struct StaticScanAssembler {
    scans: Vec<AssembledScan>,
    orphans: u64,
    /// How many origin groups of each scan [`StaticScanAssembler::take_new`] has handed out.
    taken: Vec<usize>,
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

    /// Takes one frame body; anything but `StaticScan` is ignored.
    pub fn on_body(&mut self, body: &Body) {
        let Body::StaticScan(message) = body else {
            return;
        };
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
            StaticScan::Samples(batch) => match self.current(batch.scan_id) {
                Some(scan) => scan.add(batch),
                None => self.orphans += batch.samples.len() as u64,
            },
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

    /// Samples whose scan start was never seen.
    pub fn orphan_samples(&self) -> u64 {
        self.orphans
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
    fn add(&mut self, batch: &StaticScanSamples) {
        let mut current_yaw: Option<f32> = None;
        for sample in &batch.samples {
            let static_sample = StaticSample {
                range_m: f64::from(sample.range_m),
                azimuth_deg: f64::from(sample.azimuth_deg),
                yaw_deg: f64::from(sample.yaw_deg),
            };
            let Some(point) = static_point(&self.position, &self.mount, &static_sample) else {
                self.no_return += 1;
                continue;
            };
            if current_yaw != Some(sample.yaw_deg) {
                current_yaw = Some(sample.yaw_deg);
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

    #[test]
    fn the_assembler_groups_points_by_half_revolution_origin() {
        use scan3d_protocol::{MountInfo, StaticScanEnd, StaticScanStart, TaggedSweepSample};
        let mut assembler = StaticScanAssembler::new();
        // Samples before any start are orphans, not guessed.
        let batch = |scan_id, samples: Vec<TaggedSweepSample>| {
            Body::StaticScan(StaticScan::Samples(StaticScanSamples {
                scan_id,
                revolution: 0,
                t_ns: 0,
                samples,
            }))
        };
        let tagged = |azimuth_deg, range_m, yaw_deg| TaggedSweepSample {
            azimuth_deg,
            range_m,
            quality: 9,
            yaw_deg,
        };
        assembler.on_body(&batch(0, vec![tagged(90.0, 1.0, 0.0)]));
        assert_eq!(assembler.orphan_samples(), 1);
        assembler.on_body(&Body::StaticScan(StaticScan::Started(StaticScanStart {
            scan_id: 0,
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
        })));
        assembler.on_body(&batch(
            0,
            vec![
                tagged(90.0, 2.0, 0.0),
                tagged(100.0, 0.0, 0.0), // no return
                tagged(270.0, 2.0, 1.8),
            ],
        ));
        let new = assembler.take_new();
        assert_eq!(
            new.len(),
            2,
            "both half revolutions are complete once their batch is in"
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
        assembler.on_body(&Body::StaticScan(StaticScan::Finished(StaticScanEnd {
            scan_id: 0,
            t_ns: 1,
            outcome: StaticScanOutcome::Completed,
            yaw_deg: 180.0,
            revolutions: 100,
            tagged: 3,
            blocked: 0,
            untrusted: 0,
            late_steps: 0,
            failed_steps: 0,
        })));
        let scans = assembler.finish();
        assert_eq!(scans.len(), 1);
        let scan = &scans[0];
        assert_eq!(scan.outcome, Some(StaticScanOutcome::Completed));
        assert_eq!((scan.points(), scan.no_return), (2, 1));
        assert_eq!(scan.scans.len(), 2, "one origin per half revolution");
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
        let q = scan.scans[1].points[0].map(f64::from);
        assert!(close_f32(
            q,
            [o2[0] + 2.0 * phi.sin(), o2[1] - 2.0 * phi.cos(), 0.5]
        ));
    }

    fn close_f32(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5)
    }
}
