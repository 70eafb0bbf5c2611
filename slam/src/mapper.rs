//! Incremental 2D SLAM without loop closure: each scan is matched against the map built so far,
//! then (when the robot has moved enough) integrated into it.
//!
//! [`Mapper::add_scan`] is the whole front end: predict the pose (wheel odometry when there is
//! some, a constant-velocity model otherwise), de-skew the scan when its beams carry their own
//! times, match it coarse to fine with the prediction as a Gaussian prior, and update the map
//! by Hector's distance/angle rule. The grid pyramid and the per-scan poses and covariances are
//! what a pose-graph layer (submaps, loop closure) will build on.

use crate::grid::{GridPyramid, UpdateModel};
use crate::matcher::{Match, MatchConfig, Matrix3, Prior, SearchWindow, match_scan, search};
use crate::pose::{Pose2, wrap_angle};
use crate::surface::{RefineConfig, Surfaces, Sweep, refine};

/// How the pose is predicted before matching, and how much the prediction is trusted.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionConfig {
    /// Use wheel odometry when a scan has it (`false`: constant velocity, as without odometry).
    pub use_odometry: bool,
    /// Odometry translation error, standard deviation per metre travelled.
    pub odometry_translation_per_m: f64,
    /// Odometry rotation error, standard deviation (rad) per radian turned.
    pub odometry_rotation_per_rad: f64,
    /// Odometry rotation error, standard deviation (rad) per metre travelled.
    pub odometry_rotation_per_m: f64,
    /// Smallest translation standard deviation of a prediction (m).
    pub min_translation_sigma: f64,
    /// Smallest rotation standard deviation of a prediction (rad).
    pub min_rotation_sigma: f64,
    /// Translation standard deviation (m) of a constant-velocity prediction, per second since
    /// the previous scan.
    pub velocity_translation_per_s: f64,
    /// Rotation standard deviation (rad) of a constant-velocity prediction, per second.
    pub velocity_rotation_per_s: f64,
    /// Without odometry, the window searched around the constant-velocity prediction (on the
    /// coarsest grid) before matching: a hand-pushed trolley turns when it likes.
    pub velocity_search: SearchWindow,
    /// ...searched when the match from the prediction scores below this (≥ 1: always); the
    /// better of the two matches is kept.
    pub velocity_search_below: f64,
}

impl Default for MotionConfig {
    fn default() -> Self {
        Self {
            use_odometry: true,
            odometry_translation_per_m: 0.2,
            odometry_rotation_per_rad: 0.2,
            odometry_rotation_per_m: 0.05,
            min_translation_sigma: 0.01,
            min_rotation_sigma: 0.005,
            velocity_translation_per_s: 0.5,
            velocity_rotation_per_s: 1.0,
            velocity_search: SearchWindow::default(),
            velocity_search_below: 1.1,
        }
    }
}

/// Every parameter of the mapper. `slam.toml` is this, key for key.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MapperConfig {
    /// Cell size of the finest grid (m).
    pub resolution: f64,
    /// Number of grids; each next one has cells twice as wide.
    pub levels: usize,
    /// Hit/miss log-odds updates of the grids.
    pub update: UpdateModel,
    /// The Gauss–Newton matcher.
    pub matcher: MatchConfig,
    /// The motion prior.
    pub motion: MotionConfig,
    /// The sub-cell refinement of each grid match.
    pub refine: RefineConfig,
    /// Integrate a scan into the map only after the robot moved this far (m) since the last
    /// integrated scan (Hector's `map_update_distance_thresh`)...
    pub map_update_distance: f64,
    /// ...or turned this much (rad).
    pub map_update_angle: f64,
    /// A match whose mean endpoint occupancy is below this is not trusted: the scan takes the
    /// predicted pose and is not integrated.
    pub min_score: f64,
}

impl Default for MapperConfig {
    fn default() -> Self {
        Self {
            resolution: 0.05,
            levels: 2,
            update: UpdateModel::default(),
            matcher: MatchConfig::default(),
            motion: MotionConfig::default(),
            refine: RefineConfig::default(),
            map_update_distance: 0.4,
            map_update_angle: 0.9,
            min_score: 0.0,
        }
    }
}

/// One laser scan, as the mapper takes it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scan {
    /// When the scan was taken (s, any origin, increasing).
    pub time: f64,
    /// Beam endpoints with a return, in the sensor frame (m).
    pub hits: Vec<(f64, f64)>,
    /// Per endpoint in `hits`, its time relative to `time` (s), when the lidar gives one: the
    /// scan is then de-skewed, and its pose is for the middle of these times (see
    /// [`Mapper::add_scan`]). Empty for an instantaneous scan.
    pub hit_times: Vec<f64>,
    /// The robot's wheel-odometry pose at `time`, if there is odometry. Its change from one
    /// scan to the next is taken as the motion between their poses (for scans with per-beam
    /// times, between the middles of their beams: stamp every scan at the same point of it).
    pub odometry: Option<Pose2>,
    /// The sensor's pose on the robot.
    pub sensor_offset: Pose2,
}

/// What the mapper did with one scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanResult {
    /// The time the pose is for (s): the scan's `time`, or for a scan with per-beam times the
    /// middle of its beams.
    pub time: f64,
    /// The robot pose at `time`, in the map frame.
    pub pose: Pose2,
    /// The pose the motion model predicted.
    pub predicted: Pose2,
    /// Covariance of the matched sensor pose from the scan alone (`None` for the first scan
    /// and for scans whose match was not trusted).
    pub covariance: Option<Matrix3>,
    /// Mean endpoint occupancy of the match on the finest grid (0 when not matched).
    pub score: f64,
    /// Whether the scan was integrated into the map.
    pub integrated: bool,
}

/// The incremental mapper: a grid pyramid and the last pose.
#[derive(Debug, Clone)]
pub struct Mapper {
    config: MapperConfig,
    map: GridPyramid,
    surfaces: Surfaces,
    last: Option<Last>,
    last_integrated: Option<Pose2>,
    refused: usize,
}

/// When a revolution's endpoints were seen: per endpoint, its time from the reference time
/// (the middle of the beams); the sensor pose at the previous reference; the time since.
#[derive(Debug, Clone, Copy)]
struct Timing<'a> {
    offsets: &'a [f64],
    from: Pose2,
    interval: f64,
}

#[derive(Debug, Clone, Copy)]
struct Last {
    time: f64,
    pose: Pose2,
    odometry: Option<Pose2>,
    /// Motion over the previous interval, in the frame of its start, and that interval (s).
    motion: Pose2,
    interval: f64,
}

impl Mapper {
    /// A mapper with an empty map.
    pub fn new(config: MapperConfig) -> Self {
        Self {
            map: GridPyramid::new(config.resolution, config.levels, &config.update),
            surfaces: Surfaces::new(config.resolution, &config.refine),
            config,
            last: None,
            last_integrated: None,
            refused: 0,
        }
    }

    /// The grids built so far.
    pub fn map(&self) -> &GridPyramid {
        &self.map
    }

    /// The configuration.
    pub fn config(&self) -> &MapperConfig {
        &self.config
    }

    /// Scans that could not be integrated because the grid would have grown past its limit.
    pub fn refused_integrations(&self) -> usize {
        self.refused
    }

    /// Matches a scan against the map, integrates it when due, and returns its pose.
    ///
    /// A scan with per-beam times is matched, and its pose returned, at the middle of its
    /// beams' times ([`ScanResult::time`]), not at its stamp. A wrong velocity bends a
    /// revolution symmetrically about its middle, so the pose there is the one the scan fixes
    /// whatever the velocity; and the velocity between two such poses does not carry one
    /// scan's error into the next. Matched at the stamp instead, a heading error returned with
    /// the opposite sign one revolution later (the de-skew uses the motion from the last pose,
    /// error included), and the pose at the stamp is an extrapolation half a revolution long.
    pub fn add_scan(&mut self, scan: &Scan) -> ScanResult {
        let timed = !scan.hit_times.is_empty() && scan.hit_times.len() == scan.hits.len();
        // The reference time within the scan, relative to its stamp.
        let middle = if timed {
            middle_of(&scan.hit_times)
        } else {
            0.0
        };
        let reference = scan.time + middle;
        let relative: Vec<f64> = if timed {
            scan.hit_times.iter().map(|t| t - middle).collect()
        } else {
            Vec::new()
        };
        let Some(last) = self.last else {
            let pose = scan
                .odometry
                .filter(|_| self.config.motion.use_odometry)
                .unwrap_or_default();
            self.integrate(scan, &pose, &scan.hits);
            self.last = Some(Last {
                time: reference,
                pose,
                odometry: scan.odometry,
                motion: Pose2::default(),
                interval: 0.0,
            });
            return ScanResult {
                time: reference,
                pose,
                predicted: pose,
                covariance: None,
                score: 0.0,
                integrated: true,
            };
        };
        let dt = reference - last.time;
        let (motion, information, from_odometry) = self.predict(&last, scan, dt);
        let predicted = last.pose.compose(&motion);

        let hits = if timed {
            deskew(&scan.hits, &relative, &scan.sensor_offset, &motion, dt)
        } else {
            scan.hits.clone()
        };
        let start = predicted.compose(&scan.sensor_offset);
        let prior = Prior {
            pose: start,
            information,
        };
        let mut matched: Match =
            match_scan(&self.map, &hits, start, Some(&prior), &self.config.matcher);
        if !from_odometry && matched.score < self.config.motion.velocity_search_below {
            // A poor fit from the prediction: the trolley may have turned. Search a window on
            // the coarsest grid and keep whichever match fits better.
            let coarsest = self.map.levels().last().expect("at least one level");
            let found = search(coarsest, &hits, start, &self.config.motion.velocity_search);
            let wide = Prior {
                pose: found,
                information,
            };
            let second = match_scan(&self.map, &hits, found, Some(&wide), &self.config.matcher);
            if second.score > matched.score {
                matched = second;
            }
        }
        let mut pose = matched.pose.compose(&scan.sensor_offset.inverse());
        let mut hits = hits;
        if timed && dt > 0.0 {
            // De-skew again with the motion the match found, and match again.
            let found = last.pose.between(&pose);
            hits = deskew(&scan.hits, &relative, &scan.sensor_offset, &found, dt);
            matched = match_scan(
                &self.map,
                &hits,
                matched.pose,
                Some(&prior),
                &self.config.matcher,
            );
            pose = matched.pose.compose(&scan.sensor_offset.inverse());
        }
        let trusted = matched.score >= self.config.min_score;
        if !trusted {
            pose = predicted;
        } else if self.config.refine.enabled {
            let timing = (timed && dt > 0.0).then(|| Timing {
                offsets: &relative,
                from: last.pose.compose(&scan.sensor_offset),
                interval: dt,
            });
            let (refined, placed) = self.refine_match(scan, &hits, &matched.pose, timing, &prior);
            pose = refined.compose(&scan.sensor_offset.inverse());
            if let Some(placed) = placed {
                hits = placed;
            }
        }
        let integrated = trusted && self.due(&pose) && self.integrate(scan, &pose, &hits);
        let found = last.pose.between(&pose);
        self.last = Some(Last {
            time: reference,
            pose,
            odometry: scan.odometry,
            motion: found,
            interval: dt,
        });
        ScanResult {
            time: reference,
            pose,
            predicted,
            covariance: trusted.then_some(matched.covariance),
            score: if trusted { matched.score } else { 0.0 },
            integrated,
        }
    }

    /// The sub-cell refinement of a trusted grid match (`matched`, a sensor pose): of the
    /// de-skewed `hits` for an instantaneous scan, or for a revolution of its endpoints as
    /// measured, each seen along a velocity found with the pose. Returns the refined sensor pose
    /// and, for a revolution whose refinement was taken, its endpoints placed with that velocity.
    fn refine_match(
        &self,
        scan: &Scan,
        hits: &[(f64, f64)],
        matched: &Pose2,
        timing: Option<Timing>,
        prior: &Prior,
    ) -> (Pose2, Option<Vec<(f64, f64)>>) {
        let config = &self.config.refine;
        let Some(timing) = timing else {
            let refined = refine(&self.surfaces, hits, *matched, None, Some(prior), config);
            return (refined.pose, None);
        };
        // The sensor's velocity from the last pose to this grid match, in the map frame.
        let (from, dt) = (timing.from, timing.interval);
        let (sigma_t, sigma_r) = (
            config.velocity_translation_sigma,
            config.velocity_rotation_sigma,
        );
        let sweep = Sweep {
            offsets: timing.offsets,
            velocity: [
                (matched.x - from.x) / dt,
                (matched.y - from.y) / dt,
                wrap_angle(matched.theta - from.theta) / dt,
            ],
            information: [
                1.0 / (sigma_t * sigma_t),
                1.0 / (sigma_t * sigma_t),
                1.0 / (sigma_r * sigma_r),
            ],
        };
        let refined = refine(
            &self.surfaces,
            &scan.hits,
            *matched,
            Some(&sweep),
            Some(prior),
            config,
        );
        let placed = match (refined.taken, refined.velocity) {
            (true, Some(velocity)) => Some(sweep.place(&scan.hits, &refined.pose, &velocity)),
            _ => None,
        };
        (refined.pose, placed)
    }

    /// The predicted motion since the last scan (in its frame) and the prior's information
    /// matrix over the sensor pose.
    fn predict(&self, last: &Last, scan: &Scan, dt: f64) -> (Pose2, Matrix3, bool) {
        let m = &self.config.motion;
        let odometry = match (m.use_odometry, last.odometry, scan.odometry) {
            (true, Some(before), Some(now)) => Some(before.between(&now)),
            _ => None,
        };
        let (motion, sigma_t, sigma_r) = match odometry {
            Some(delta) => {
                let distance = delta.x.hypot(delta.y);
                (
                    delta,
                    m.odometry_translation_per_m * distance,
                    m.odometry_rotation_per_rad * delta.theta.abs()
                        + m.odometry_rotation_per_m * distance,
                )
            }
            None => {
                let ratio = if last.interval > 0.0 {
                    (dt / last.interval).clamp(0.0, 5.0)
                } else {
                    0.0
                };
                let motion = Pose2::new(
                    last.motion.x * ratio,
                    last.motion.y * ratio,
                    last.motion.theta * ratio,
                );
                (
                    motion,
                    m.velocity_translation_per_s * dt.abs(),
                    m.velocity_rotation_per_s * dt.abs(),
                )
            }
        };
        let sigma_t = sigma_t.max(m.min_translation_sigma);
        let sigma_r = sigma_r.max(m.min_rotation_sigma);
        let information = [
            [1.0 / (sigma_t * sigma_t), 0.0, 0.0],
            [0.0, 1.0 / (sigma_t * sigma_t), 0.0],
            [0.0, 0.0, 1.0 / (sigma_r * sigma_r)],
        ];
        (motion, information, odometry.is_some())
    }

    fn due(&self, pose: &Pose2) -> bool {
        self.last_integrated.is_none_or(|at| {
            (pose.x - at.x).hypot(pose.y - at.y) >= self.config.map_update_distance
                || wrap_angle(pose.theta - at.theta).abs() >= self.config.map_update_angle
        })
    }

    fn integrate(&mut self, scan: &Scan, pose: &Pose2, hits: &[(f64, f64)]) -> bool {
        let sensor = pose.compose(&scan.sensor_offset);
        if self.map.integrate(&sensor, hits, &[]) {
            if self.config.refine.enabled {
                self.surfaces.integrate(&sensor, hits);
            }
            self.last_integrated = Some(*pose);
            true
        } else {
            self.refused += 1;
            false
        }
    }
}

/// The middle of a scan's beam times: halfway between the first and the last.
fn middle_of(times: &[f64]) -> f64 {
    let (lo, hi) = times
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
            (lo.min(t), hi.max(t))
        });
    if lo.is_finite() && hi.is_finite() {
        0.5 * (lo + hi)
    } else {
        0.0
    }
}

/// Moves each endpoint to where it would have been seen from the sensor pose at the reference
/// time its `times` are relative to, given the robot's `motion` over the `interval` that ends
/// there (constant velocity): a beam taken `t` seconds after the reference was seen from the
/// robot pose `(t / interval) · motion` relative to it, x, y and θ scaled alike (a first-order
/// approximation of the arc, under a millimetre at trolley speeds).
fn deskew(
    hits: &[(f64, f64)],
    times: &[f64],
    sensor_offset: &Pose2,
    motion: &Pose2,
    interval: f64,
) -> Vec<(f64, f64)> {
    if interval <= 0.0 {
        return hits.to_vec();
    }
    let to_sensor = sensor_offset.inverse();
    hits.iter()
        .zip(times)
        .map(|(&(x, y), &t)| {
            let f = t / interval;
            let at = Pose2::new(motion.x * f, motion.y * f, motion.theta * f);
            // Sensor at time t, relative to the sensor at the scan time.
            let relative = to_sensor.compose(&at).compose(sensor_offset);
            relative.transform_point(x, y)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_timed_scans_pose_is_for_the_middle_of_its_beams_and_an_instant_scans_for_its_stamp() {
        let mut mapper = Mapper::new(MapperConfig::default());
        let hits = vec![(2.0, 0.0), (0.0, 2.0), (-2.0, 0.0)];
        let timed = Scan {
            time: 10.0,
            hits: hits.clone(),
            hit_times: vec![-0.18, -0.1, -0.02],
            ..Scan::default()
        };
        assert!((mapper.add_scan(&timed).time - 9.9).abs() < 1e-12);
        let instant = Scan {
            time: 10.5,
            hits,
            ..Scan::default()
        };
        assert_eq!(mapper.add_scan(&instant).time, 10.5);
    }

    #[test]
    fn a_beam_taken_after_the_scan_time_is_moved_by_the_motion_since() {
        // Moving +x at 1 m/s; a beam 0.5 s late saw a point 1 m ahead: from the scan-time pose
        // that point is 1.5 m ahead.
        let motion = Pose2::new(1.0, 0.0, 0.0);
        let out = deskew(
            &[(1.0, 0.0), (1.0, 0.0)],
            &[0.0, 0.5],
            &Pose2::default(),
            &motion,
            1.0,
        );
        assert!((out[0].0 - 1.0).abs() < 1e-12);
        assert!((out[1].0 - 1.5).abs() < 1e-12 && out[1].1.abs() < 1e-12);
        // Turning left at 1 rad/s: a beam 0.1 s late along the sensor's x is rotated by 0.1 rad.
        let turn = Pose2::new(0.0, 0.0, 1.0);
        let out = deskew(&[(2.0, 0.0)], &[0.1], &Pose2::default(), &turn, 1.0);
        assert!((out[0].1 - 2.0 * 0.1f64.sin()).abs() < 1e-12);
    }
}
