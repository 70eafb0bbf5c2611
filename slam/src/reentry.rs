//! Re-entry: a scan that comes back to a place mapped long ago is fitted to what was mapped
//! there then, and the pose moves onto it when the scan contradicts the old map where it stands.
//!
//! Matched against the whole map, a robot that returns after a loop meets two maps of the same
//! place: the old pass's walls, where they were, and the walls it has just integrated with the
//! drift gathered around the loop. The recent ones are nearer the prediction, and the drifted
//! pass carries on beside the old one (docs/slam.md: ACES's default draw at full range was such a
//! return, 0.7–0.95 m off on every relation across it). Here the scan is also matched against a
//! map of the old pass alone, built from the integrated scans ([`Keyframes`]) taken more than
//! [`ReentryConfig::min_age`] ago near where the robot is, over a window of
//! [`ReentryConfig::window`] and [`ReentryConfig::angle`]. The pose moves when the old map says
//! the scan is misplaced: at the pose the scan's endpoints fall where the old pass saw free
//! space ([`contradicted`]), and at the pose found they do not, and fit better.
//!
//! Only the pose from then on moves: the poses before keep their drift. Spreading the
//! correction back along the loop is loop closure's work, on the same keyframes.

use crate::grid::{Grid, GridPyramid};
use crate::mapper::MapperConfig;
use crate::matcher::{SearchWindow, match_scan, score, search};
use crate::pose::Pose2;

/// When and how far a scan returning to an old place is moved onto the old map.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReentryConfig {
    /// Check integrated scans against the old map (`false`: the whole map alone, as Hector).
    pub enabled: bool,
    /// Integrated scans older than this (s) make the old map.
    pub min_age: f64,
    /// ...and taken within this distance (m) of the sensor's pose.
    pub radius: f64,
    /// At most this many of them, the nearest.
    pub max_scans: usize,
    /// Half-width of the translation window searched (m): the drift a return can undo.
    pub window: f64,
    /// Half-width of the heading window (rad).
    pub angle: f64,
    /// The robot travels at least this far (m) between two checks.
    pub spacing: f64,
    /// The scan's mean occupancy on the old map at the pose found must reach this...
    pub min_score: f64,
    /// ...and exceed the one where the scan stands by this much.
    pub score_gain: f64,
    /// Where the scan stands, at least this fraction of its endpoints falls on the old map's
    /// free space...
    pub min_contradicted: f64,
    /// ...and at the pose found at most this fraction of that many.
    pub contradicted_ratio: f64,
    /// A cell is free below this occupancy probability (0.35: passed through by two beams or
    /// more at the default update model).
    pub free_below: f32,
    /// An endpoint in a free cell contradicts the map only when no occupied cell lies within
    /// this many cells of it (a wall endpoint a few centimetres in front of its wall does not).
    pub clearance: i32,
}

impl Default for ReentryConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            min_age: 60.0,
            radius: 3.0,
            max_scans: 30,
            window: 1.5,
            angle: 0.07,
            spacing: 1.0,
            min_score: 0.5,
            score_gain: 0.1,
            min_contradicted: 0.15,
            contradicted_ratio: 0.4,
            free_below: 0.35,
            clearance: 2,
        }
    }
}

/// What a re-entry check found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reentry {
    /// The sensor pose on the old map.
    pub sensor: Pose2,
    /// The integrated scans the old map was built from.
    pub scans: usize,
    /// The scan's mean occupancy on the old map where it stood and where it was found.
    pub score: (f64, f64),
    /// The fraction of its endpoints on the old map's free space, there and where found.
    pub contradicted: (f64, f64),
}

/// One integrated scan: when, from where, and its endpoints in the sensor frame.
#[derive(Debug, Clone)]
struct Keyframe {
    time: f64,
    sensor: Pose2,
    hits: Vec<(f64, f64)>,
}

/// At most this many integrated scans are kept: 20 km of travel at one every 0.4 m, about
/// 290 MB at 360 endpoints a scan (the Freiburg hospital log has 6,917 scans in all).
/// Past it the scans kept stay and new ones are not kept: the check then sees no old map there.
pub const MAX_KEYFRAMES: usize = 50_000;

/// The integrated scans, for the re-entry check (and, next, for loop closure).
#[derive(Debug, Clone, Default)]
pub struct Keyframes {
    frames: Vec<Keyframe>,
    /// Where the last check was made (the sensor's position).
    last_check: Option<(f64, f64)>,
}

impl Keyframes {
    /// Keeps a scan integrated at `time` from `sensor` (endpoints in the sensor frame).
    pub fn add(&mut self, time: f64, sensor: Pose2, hits: &[(f64, f64)]) {
        if self.frames.len() < MAX_KEYFRAMES {
            self.frames.push(Keyframe {
                time,
                sensor,
                hits: hits.to_vec(),
            });
        }
    }

    /// Number of scans kept.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether none is kept.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Checks a scan about to be integrated from `sensor` at `time` against the old map around
    /// it; returns where the old map puts it when it has to move. The old map is built and
    /// matched as `mapper` builds and matches its own, under `mapper.reentry`.
    pub fn check(
        &mut self,
        mapper: &MapperConfig,
        hits: &[(f64, f64)],
        sensor: Pose2,
        time: f64,
    ) -> Option<Reentry> {
        let config = &mapper.reentry;
        if !config.enabled || hits.is_empty() {
            return None;
        }
        if let Some((x, y)) = self.last_check
            && (x - sensor.x).hypot(y - sensor.y) < config.spacing
        {
            return None;
        }
        let mut near: Vec<(f64, usize)> = self
            .frames
            .iter()
            .enumerate()
            .filter(|(_, k)| time - k.time > config.min_age)
            .map(|(i, k)| ((k.sensor.x - sensor.x).hypot(k.sensor.y - sensor.y), i))
            .filter(|&(d, _)| d < config.radius)
            .collect();
        // Fewer than three scans hardly make a map of the place.
        if near.len() < 3 {
            return None;
        }
        self.last_check = Some((sensor.x, sensor.y));
        near.sort_by(|a, b| a.0.total_cmp(&b.0));
        near.truncate(config.max_scans.max(3));
        let mut old = GridPyramid::new(mapper.resolution, mapper.levels, &mapper.update);
        for &(_, i) in &near {
            let frame = &self.frames[i];
            old.integrate(&frame.sensor, &frame.hits, &[]);
        }
        let coarsest = old.levels().last().expect("a pyramid has a level");
        let window = SearchWindow {
            angle: config.angle,
            angle_step: 0.01,
            translation: config.window,
            prior_weight: 0.0,
            sigmas: 0.0,
            max_angle: config.angle,
            max_translation: config.window,
        };
        let start = search(coarsest, hits, sensor, &window, None);
        let found = match_scan(&old, hits, start, None, &mapper.matcher);
        // Gauss–Newton without a prior may slide beyond the window (along a corridor): that is
        // no place the search vouched for.
        let moved = sensor.between(&found.pose);
        let step = old.finest().resolution();
        if moved.x.hypot(moved.y) > config.window + 2.0 * step
            || moved.theta.abs() > config.angle + 2.0 * window.angle_step
            || moved.x.hypot(moved.y) < step
        {
            return None;
        }
        let contradicted_standing = contradicted(old.finest(), hits, &sensor, config);
        let contradicted_found = contradicted(old.finest(), hits, &found.pose, config);
        let standing = score(old.finest(), hits, &sensor);
        let misplaced = contradicted_standing >= config.min_contradicted
            && contradicted_found <= config.contradicted_ratio * contradicted_standing;
        let fits = found.score >= config.min_score && found.score > standing + config.score_gain;
        (misplaced && fits).then_some(Reentry {
            sensor: found.pose,
            scans: near.len(),
            score: (standing, found.score),
            contradicted: (contradicted_standing, contradicted_found),
        })
    }
}

/// The fraction of `points` (sensor frame) placed at `pose` that fall on cells of `grid` seen
/// free (below [`ReentryConfig::free_below`]) with no occupied cell within
/// [`ReentryConfig::clearance`] cells: endpoints where the map says there is nothing to hit.
pub fn contradicted(
    grid: &Grid,
    points: &[(f64, f64)],
    pose: &Pose2,
    config: &ReentryConfig,
) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let r = config.clearance.max(0);
    let count = points
        .iter()
        .filter(|&&(x, y)| {
            let (mx, my) = pose.transform_point(x, y);
            let (i, j) = grid.cell_of(mx, my);
            grid.is_known((i, j))
                && grid.probability((i, j)) < config.free_below
                && !(-r..=r).any(|di| (-r..=r).any(|dj| grid.probability((i + di, j + dj)) > 0.5))
        })
        .count();
    count as f64 / points.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{Segment, cast, rectangle};

    /// A room with an inner wall and a pillar: no two places in it look alike. The walls run
    /// along cell centres of the 5 cm grid: the grid match has no half-cell bias to test.
    fn walls() -> Vec<Segment> {
        let mut walls = rectangle((0.025, 0.025), (9.025, 6.025)).to_vec();
        walls.push(((3.025, 0.025), (3.025, 2.525)));
        walls.extend(rectangle((6.025, 3.525), (6.825, 4.125)));
        walls
    }

    /// Keyframes of a pass along the room at time 0–10 s, each scan from where it was taken.
    fn first_pass() -> Keyframes {
        let mut keyframes = Keyframes::default();
        for k in 0..11 {
            let sensor = Pose2::new(4.0 + 0.25 * f64::from(k), 2.0, 0.1);
            keyframes.add(f64::from(k), sensor, &cast(&walls(), &sensor, 360));
        }
        keyframes
    }

    fn check(
        keyframes: &mut Keyframes,
        hits: &[(f64, f64)],
        sensor: Pose2,
        time: f64,
    ) -> Option<Reentry> {
        keyframes.check(&MapperConfig::default(), hits, sensor, time)
    }

    #[test]
    fn a_scan_back_after_a_drift_is_moved_onto_the_old_map() {
        let truth = Pose2::new(5.1, 1.6, 0.3);
        let hits = cast(&walls(), &truth, 360);
        // The robot believes it is 0.7 m and 2° away from where it is.
        let drifted = Pose2::new(5.6, 2.1, 0.335);
        let found = check(&mut first_pass(), &hits, drifted, 100.0).expect("a re-entry");
        let off = (found.sensor.x - truth.x).hypot(found.sensor.y - truth.y);
        assert!(off < 0.03, "{found:?}");
        assert!(
            (found.sensor.theta - truth.theta).abs() < 0.005,
            "{found:?}"
        );
        assert!(
            found.contradicted.0 >= 0.15 && found.contradicted.1 < 0.05,
            "{found:?}"
        );
        assert_eq!(found.scans, 11);
    }

    #[test]
    fn a_scan_where_the_old_map_puts_it_stays() {
        let truth = Pose2::new(5.1, 1.6, 0.3);
        let hits = cast(&walls(), &truth, 360);
        assert_eq!(check(&mut first_pass(), &hits, truth, 100.0), None);
    }

    #[test]
    fn only_old_scans_near_the_robot_are_checked_against_and_not_every_scan() {
        let truth = Pose2::new(5.1, 1.6, 0.3);
        let hits = cast(&walls(), &truth, 360);
        let drifted = Pose2::new(5.6, 2.1, 0.335);
        // A minute has not passed since the first pass: it is the current map, not an old one.
        assert_eq!(check(&mut first_pass(), &hits, drifted, 30.0), None);
        // Far from where the old scans were taken.
        let far = Pose2::new(drifted.x, drifted.y + 40.0, drifted.theta);
        assert_eq!(check(&mut first_pass(), &hits, far, 100.0), None);
        // A second check within a metre of the last one is not made.
        let mut keyframes = first_pass();
        assert!(check(&mut keyframes, &hits, drifted, 100.0).is_some());
        let nearby = Pose2::new(drifted.x + 0.5, drifted.y, drifted.theta);
        assert_eq!(check(&mut keyframes, &hits, nearby, 101.0), None);
        // Switched off.
        let off = MapperConfig {
            reentry: ReentryConfig {
                enabled: false,
                ..ReentryConfig::default()
            },
            ..MapperConfig::default()
        };
        let found = first_pass().check(&off, &hits, drifted, 100.0);
        assert_eq!(found, None);
    }

    #[test]
    fn endpoints_in_seen_free_space_contradict_the_map_and_those_at_its_walls_do_not() {
        let mut map = GridPyramid::new(0.05, 1, &crate::grid::UpdateModel::default());
        let from = Pose2::new(4.5, 3.0, 0.0);
        for _ in 0..3 {
            map.integrate(&from, &cast(&walls(), &from, 720), &[]);
        }
        let config = ReentryConfig::default();
        let hits = cast(&walls(), &from, 360);
        assert_eq!(contradicted(map.finest(), &hits, &from, &config), 0.0);
        // Two centimetres in front of their walls: within the clearance.
        let near = Pose2::new(from.x + 0.02, from.y - 0.02, 0.0);
        assert_eq!(contradicted(map.finest(), &hits, &near, &config), 0.0);
        // Half a metre off along x, the endpoints of the walls across x fall in the room
        // (those along x stay on their walls): more than a re-entry needs.
        let off = Pose2::new(from.x - 0.5, from.y, 0.0);
        let fraction = contradicted(map.finest(), &hits, &off, &config);
        assert!(fraction > config.min_contradicted, "{fraction}");
        assert_eq!(contradicted(map.finest(), &[], &off, &config), 0.0);
    }
}
