//! Incremental 2D SLAM without loop closure: each scan is matched against the map built so far,
//! then (when the robot has moved enough) integrated into it.
//!
//! [`Mapper::add_scan`] is the whole front end: predict the pose (wheel odometry when there is
//! some, a constant-velocity model otherwise), de-skew the scan when its beams carry their own
//! times, match it coarse to fine with the prediction as a Gaussian prior, and update the map
//! by Hector's distance/angle rule. With [`SubmapConfig`] the scan is matched against a local
//! submap of the recent scans instead of the whole map: the unit a pose-graph layer (loop
//! closure) will join, with the per-scan poses and covariances.
//!
//! Each pose comes with its covariance ([`ScanResult::covariance`]): the uncertainty of the
//! reported pose itself, relative to the map, from what the scan says (its fit, scaled by its
//! measured residuals, plus a floor for the errors its endpoints share) combined with what the
//! prediction said (the previous pose's covariance carried forward plus the motion model's), as
//! the match weighed them. It does not include the map's drift from the world: without loop
//! closure that grows with the distance travelled and is nobody's measurement.

use std::collections::VecDeque;

use crate::grid::{GridPyramid, UpdateModel};
use crate::matcher::{Fit, Match, MatchConfig, Matrix3, Prior, SearchWindow, match_scan, search};
use crate::odometry_agreement::{OdometryAgreement, StepSigmas};
use crate::odometry_bias::OdometryBias;
use crate::pose::{Pose2, Velocity2, wrap_angle};
use crate::reentry::{Keyframes, ReentryConfig};
use crate::surface::{RefineConfig, Refinement, Surfaces, Sweep, refine};

/// What a scan's fit does not see in a pose's uncertainty. The fit counts every endpoint as an
/// independent measurement, so its covariance shrinks as one over their number; but neighbouring
/// endpoints are matched against the same cells and share those cells' errors, and some errors
/// are shared by all of them (the map's cell means, the grid's quantisation, the de-skew's
/// velocity). So the fit's covariance is inflated by a factor and a floor is added to it.
/// Calibrated in the simulated room with the RPLidar's noise (`hw-sim/tests/slam_room.rs`, a map
/// built from the true poses): the normalised estimation error squared averages 2.7 over the 3
/// degrees of freedom (per run 1.49–4.32; `docs/slam.md`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CovarianceConfig {
    /// The scan fit's covariance is multiplied by this (≥ 1): its endpoints are not independent
    /// measurements, neighbours are matched against the same map cells and share those cells'
    /// errors (a map made from one revolution has cells as noisy as the scan).
    pub fit_factor: f64,
    /// Standard deviation added along x and along y (m).
    pub translation_floor: f64,
    /// Standard deviation added to the heading (rad).
    pub rotation_floor: f64,
}

impl Default for CovarianceConfig {
    fn default() -> Self {
        Self {
            fit_factor: 4.0,
            translation_floor: 0.004,
            rotation_floor: 0.002,
        }
    }
}

impl CovarianceConfig {
    /// The floor as a covariance over (x, y, ψ).
    fn matrix(&self) -> Matrix3 {
        let (t, r) = (
            self.translation_floor * self.translation_floor,
            self.rotation_floor * self.rotation_floor,
        );
        [[t, 0.0, 0.0], [0.0, t, 0.0], [0.0, 0.0, r]]
    }
}

/// When the head stands still, its reported pose is the mean of its matches since it stopped,
/// not each revolution's own match: one revolution pins the pose to its match noise (about
/// 5 mm and 0.25° RMS for the RPLidar in the simulated room), and ten minutes of revolutions
/// would show excursions of three to four of those. The mean of N matches against the same map
/// keeps only the error they share (the map's): what the covariance floor stands for. A head
/// that has stood since the session's first pose is held at that pose itself: it defines the
/// map frame and the map is its scan, so it agrees with the map exactly, where other scans'
/// matches carry the map's error as a bias.
///
/// A hold is opened when the last `revolutions` matches all lie within `start_gate` of their
/// mean (Mahalanobis distance squared over x, y, θ with each match's covariance and the mean's,
/// χ² with 3 degrees of freedom) and, when a gyro's turn is given, it says no turn (within 3σ).
/// It collects the matches that follow within `gate` of the held pose (a match outside closes
/// it), still reporting each as matched, until [`SCATTER_AFTER`] are held: then the head stands,
/// and its reported pose is the held one. From then on the gate is taken with the matches'
/// observed scatter instead of their calibrated covariance, far tighter for a precise lidar, so
/// a head that starts moving is let go within millimetres; a match outside it is left out of
/// the mean, and standing ends at the second such match in a row beyond the calibrated gate too,
/// or the third within it (fewer are taken for outliers), or at once when the gyro says the head
/// turned. When the match right after letting go is back within the scatter, the hold is taken
/// up again. A pause shorter than [`SCATTER_AFTER`]
/// revolutions (2 s at 10 Hz) is never held, so a trolley that stops briefly is tracked as
/// before. While standing the prediction is the held pose with no motion, so neither the de-skew
/// nor the prior carries one revolution's noise into the next; the map is not updated (the head
/// has not moved). Scans predicted from wheel odometry are never held: the odometry says when
/// the robot stands (holding them cost ACES's relations 3.8 → 8.7 cm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StandstillConfig {
    /// Hold a standing head's pose (`false`: every revolution reports its own match).
    pub enabled: bool,
    /// Poses in a row (the matches, and the pose the map was integrated at when it is one of
    /// them), all consistent with one pose, before standing starts (≥ 2).
    pub revolutions: usize,
    /// The χ² gate (3 degrees of freedom) each of those poses must pass against their mean,
    /// with its covariance and the mean's: tighter than `gate`, so slow motion is not taken
    /// for standing (6.25 is the 90 % quantile).
    pub start_gate: f64,
    /// The χ² gate (3 degrees of freedom) a match must pass to count as not moved: 16.27 is
    /// the 99.9 % quantile, so a calibrated covariance leaves a standing head once in a
    /// thousand revolutions by chance, and then only for one.
    pub gate: f64,
}

impl Default for StandstillConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            revolutions: 2,
            start_gate: 6.25,
            gate: 16.27,
        }
    }
}

/// Matches held before a standing head's gate is taken with their observed scatter
/// ([`StandstillConfig`]): enough for a sample covariance of 3 degrees of freedom.
const SCATTER_AFTER: usize = 20;

/// Added to the observed scatter of a standing head's matches: 1 mm along x and y, 0.03° in
/// heading (standard deviations), so that a lidar without noise is not let go for a rounding.
const SCATTER_FLOOR: Matrix3 = [[1e-6, 0.0, 0.0], [0.0, 1e-6, 0.0], [0.0, 0.0, 2.7e-7]];

/// At most this many recent poses are kept for [`MotionConfig::velocity_window`].
const MAX_RECENT_POSES: usize = 256;

/// The weight of each trusted match in the running mean of scores ([`MotionConfig::poor_match_ratio`]).
const RECENT_SCORE_WEIGHT: f64 = 0.1;

/// At most this many scans in a row are set aside as logged out of order
/// ([`MotionConfig::out_of_order_poses`]): a robot that really moved is then followed, and one
/// whose scans keep fitting an earlier pose better is taken back there.
const MAX_OUT_OF_ORDER_IN_A_ROW: usize = 2;

/// A predicted step shorter than this (m) has no direction to go back against
/// ([`MotionConfig::out_of_order_back`]).
const MIN_PREDICTED_STEP: f64 = 0.02;

/// The lever (m) that turns a heading difference into a distance when a match is compared with
/// the recent poses ([`MotionConfig::out_of_order_turn_back`]).
const REVISIT_LEVER: f64 = 0.5;

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
    /// Without odometry, the constant-velocity prediction takes its velocity over at least
    /// this long (s) of the recent poses, not over the last interval alone (0: the last
    /// interval). Laser lines logged in bursts (Intel's: 30 % within 10 ms of the previous)
    /// make one interval's motion over its time a poor velocity, and a long gap after a burst
    /// multiplies it. (The odometry gate's constant-velocity candidate keeps the last
    /// interval: with it, FR079 keeps its map; with the window, 0.04 → 0.28 m.)
    pub velocity_window: f64,
    /// Without odometry, what the constant-velocity prediction scales the recent motion by:
    /// the time since the last scan, the scans since, or (`auto`) whichever of the two has
    /// predicted the recent matches better. Some logs keep a scan per distance travelled and
    /// stamp it when it was written (Intel, the Freiburg hospital): a scan's motion there does
    /// not grow with its interval, which may be 1 ms or 2 s.
    pub velocity_clock: VelocityClock,
    /// Without odometry, the window searched around the constant-velocity prediction (on the
    /// coarsest grid) before matching: a hand-pushed trolley turns when it likes.
    pub velocity_search: SearchWindow,
    /// ...searched when the match from the prediction scores below this (≥ 1: always); the
    /// better of the two matches is kept. Only with neither odometry nor a measured turn: with
    /// either, [`poor_match_ratio`](Self::poor_match_ratio) decides per scan.
    pub velocity_search_below: f64,
    /// With odometry, a match scoring below this fraction of the recent matches' mean score is
    /// poor: the constant-velocity prediction and the window search around the odometry's are
    /// tried too, and the best fit kept (per scan: a bad stretch of odometry cannot drag the
    /// matcher off the map). With a measured turn (a gyro) and no odometry, a poor match is
    /// searched around the prediction and a good one is not (the search is most of a live
    /// pose's cost).
    pub poor_match_ratio: f64,
    /// ...and the search's match replaces a poor one only when its score is higher by at least
    /// this much (and not poor itself): scores are noisy, a marginal gain is no evidence that
    /// the odometry was wrong.
    pub poor_match_gain: f64,
    /// With neither odometry nor a measured turn, a poor match (below
    /// [`poor_match_ratio`](Self::poor_match_ratio) of the recent mean, after the window search)
    /// is also tried at each of this many last poses. If one of them fits it better, and not
    /// poorly, the scan was logged out of order (taken there, earlier): it takes that pose, and
    /// is neither integrated nor carried into the velocity (Intel holds about 215 such lines;
    /// docs/slam.md). 0: off. At most two scans in a row are set aside this way; a third that
    /// fits an earlier pose better takes it as the pose in order, its velocity from standing.
    pub out_of_order_poses: usize,
    /// ...and so is a match, however good, that went back from the last pose against the
    /// prediction by more than this (m, along the predicted motion) to nearer one of those
    /// poses than the last: it takes its pose but is not carried on (Intel's late lines
    /// otherwise turn the next prediction around). 0: off.
    pub out_of_order_back: f64,
    /// ...or that turned against the predicted turn by more than this (rad). 0: off.
    pub out_of_order_turn_back: f64,
    /// With odometry, a match still poor after the window search is searched again over a
    /// window this many times longer (its translation; ≤ 1: not): wheels that slip 0.3 m put
    /// the robot beyond the first window, and every scan after it fits poorly there.
    pub wider_search: f64,
    /// With odometry, its motion over the last this many seconds is compared with the
    /// matches' ([`crate::odometry_agreement`]): where the two disagree, the odometry's
    /// prediction is widened for the next scan (per scan: a stretch of wrong odometry cannot pull
    /// the matches off the map, right odometry keeps its weight). 0: off.
    pub odometry_check_window: f64,
    /// ...where their mean squared error per degree of freedom, in the odometry model's
    /// standard deviations (translation and heading apart), exceeds this: that standard
    /// deviation by the square root of the ratio of the two (0: never)...
    pub odometry_check_threshold: f64,
    /// ...up to this factor on its standard deviations.
    pub odometry_max_widening: f64,
    /// With odometry, its systematic error (rotation per radian turned and per metre driven,
    /// translation scale) is learned from the matches over about this many steps and each
    /// odometry step is corrected by it before predicting ([`crate::odometry_bias`]): wheels
    /// that drift 1° per metre otherwise leak part of it into every match. 0: off.
    pub odometry_bias_window: f64,
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
            velocity_window: 1.0,
            velocity_clock: VelocityClock::Auto,
            velocity_search: SearchWindow::default(),
            velocity_search_below: 1.1,
            poor_match_ratio: 0.85,
            poor_match_gain: 0.0,
            out_of_order_poses: 24,
            out_of_order_back: 0.05,
            out_of_order_turn_back: 0.15,
            odometry_bias_window: 0.0,
            wider_search: 3.0,
            odometry_check_window: 2.0,
            odometry_check_threshold: 5.0,
            odometry_max_widening: 4.0,
        }
    }
}

/// The odometry model's standard deviations for a step: translation per metre driven,
/// rotation per radian turned and per metre driven, none below the configured smallest.
impl StepSigmas for MotionConfig {
    fn step_sigmas(&self, step: &Pose2) -> (f64, f64) {
        let distance = step.x.hypot(step.y);
        let rotation = self.odometry_rotation_per_rad * step.theta.abs()
            + self.odometry_rotation_per_m * distance;
        (
            (self.odometry_translation_per_m * distance).max(self.min_translation_sigma),
            rotation.max(self.min_rotation_sigma),
        )
    }
}

/// What a constant-velocity prediction scales the recent motion by ([`MotionConfig::velocity_clock`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VelocityClock {
    /// The time since the last scan: the robot moves at the recent velocity (a lidar turning
    /// at its own rate, scans stamped when they were taken).
    Time,
    /// The count of scans: each scan moves as the recent ones did on average (a log that keeps
    /// a scan per distance travelled).
    Scans,
    /// Whichever of the two has predicted the recent matches better, per scan.
    Auto,
}

/// How well each clock of [`VelocityClock`] has predicted the recent matches (running means of
/// the distance between each one's prediction and the match), and which one `auto` follows.
#[derive(Debug, Clone, Copy, Default)]
struct ClockErrors {
    time: f64,
    scans: f64,
    by_scans: bool,
}

/// The weight of each match in [`ClockErrors`]' running means (about the last 50 scans).
const CLOCK_ERROR_WEIGHT: f64 = 0.02;

/// `auto` changes clocks when the other one's error is below this fraction of the followed
/// one's: on a log stamped as scans were taken the two differ by noise (FR079's), and the
/// prediction should not flip between them.
const CLOCK_SWITCH_RATIO: f64 = 0.8;

/// The lever (m) that turns a heading error into a distance in [`ClockErrors`].
const CLOCK_ERROR_LEVER: f64 = 1.0;

impl ClockErrors {
    /// Adds how far each clock's prediction was from the motion the match found.
    fn observe(&mut self, by_time: &Pose2, by_scans: &Pose2, found: &Pose2) {
        let distance = |predicted: &Pose2| {
            (predicted.x - found.x).hypot(predicted.y - found.y)
                + CLOCK_ERROR_LEVER * wrap_angle(predicted.theta - found.theta).abs()
        };
        self.time += CLOCK_ERROR_WEIGHT * (distance(by_time) - self.time);
        self.scans += CLOCK_ERROR_WEIGHT * (distance(by_scans) - self.scans);
        let (followed, other) = if self.by_scans {
            (self.scans, self.time)
        } else {
            (self.time, self.scans)
        };
        if other < CLOCK_SWITCH_RATIO * followed {
            self.by_scans = !self.by_scans;
        }
    }

    /// The clock to predict with: the configured one, or for `auto` the one followed now.
    fn clock(&self, configured: VelocityClock) -> VelocityClock {
        match configured {
            VelocityClock::Auto if self.by_scans => VelocityClock::Scans,
            VelocityClock::Auto => VelocityClock::Time,
            fixed => fixed,
        }
    }
}

/// The recent motion a constant-velocity prediction extrapolates: in the frame of the last
/// pose, over `time` seconds and `scans` scans.
#[derive(Debug, Clone, Copy)]
struct RecentMotion {
    moved: Pose2,
    time: f64,
    scans: usize,
}

impl RecentMotion {
    /// The predicted motion over the next `dt` seconds (one scan), by `clock`, and the time
    /// its spread grows with.
    fn predict(&self, dt: f64, clock: VelocityClock) -> (Pose2, f64) {
        let (ratio, elapsed) = match clock {
            VelocityClock::Scans if self.scans > 0 => {
                let scans = self.scans as f64;
                (1.0 / scans, self.time / scans)
            }
            _ if self.time > 0.0 => ((dt / self.time).clamp(0.0, 5.0), dt),
            _ => (0.0, dt),
        };
        let m = &self.moved;
        (
            Pose2::new(m.x * ratio, m.y * ratio, m.theta * ratio),
            elapsed.abs(),
        )
    }
}

/// Local submaps, as Cartographer's local SLAM keeps them: each scan is matched against a map of
/// the recent scans only, not against everything mapped so far. Walls mapped on an earlier pass
/// through the same place carry that pass's drift, and can pull a scan toward the old pass;
/// joining the passes is loop closure's work, on finished submaps. Off by default: without loop
/// closure the benchmark logs that revisit their rooms lose the anchor a whole map gives them
/// (`docs/slam.md`, "Local submaps").
///
/// Two submaps are active at a time: every integrated scan goes into both; when the newer one
/// holds `scans` scans a new one is started and the older, now holding twice that, is finished
/// (dropped: the whole map, [`Mapper::map`], keeps everything for output). A scan is matched
/// against the older active submap, which holds between `scans` and twice `scans` scans, so
/// the map it meets never starts from empty.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SubmapConfig {
    /// Integrated scans per submap before the next one starts (0: no submaps, every scan is
    /// matched against the whole map).
    pub scans: usize,
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
    /// Endpoints farther than this from the lidar (m) are neither matched nor integrated: with
    /// 1° between beams a wall 30 m away is sampled every half metre, too sparsely for a 5 cm
    /// grid to hold. In the Freiburg hospital's halls it cut the drift over minutes by a third
    /// (Hector SLAM and Cartographer cut at 30 m too).
    pub max_range: f64,
    /// A match whose mean endpoint occupancy is below this is not trusted: the scan takes the
    /// predicted pose and is not integrated.
    pub min_score: f64,
    /// What the reported covariance adds for the errors a scan's endpoints share.
    pub covariance: CovarianceConfig,
    /// Holding a standing head's pose.
    pub standstill: StandstillConfig,
    /// Matching against local submaps instead of the whole map.
    pub submap: SubmapConfig,
    /// Fitting a scan that returns to a place mapped long ago to the old map there.
    pub reentry: ReentryConfig,
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
            max_range: 30.0,
            min_score: 0.0,
            covariance: CovarianceConfig::default(),
            standstill: StandstillConfig::default(),
            submap: SubmapConfig::default(),
            reentry: ReentryConfig::default(),
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
    /// A measured heading change since the previous scan (a gyro's), which then replaces the
    /// motion model's rotation in the prior.
    pub rotation: Option<RotationPrior>,
}

impl Scan {
    /// The time the scan's pose will be for ([`ScanResult::time`]): the middle of its beams'
    /// times when it has one per endpoint, else its stamp.
    pub fn reference_time(&self) -> f64 {
        if self.is_timed() {
            self.time + middle_of(&self.hit_times)
        } else {
            self.time
        }
    }

    fn is_timed(&self) -> bool {
        !self.hit_times.is_empty() && self.hit_times.len() == self.hits.len()
    }
}

/// A heading change measured between two scans by another sensor (a gyro's yaw increment), for
/// the mapper's motion prior: the prediction turns by it, with its variance, instead of by the
/// odometry's or the constant-velocity model's rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationPrior {
    /// The heading change (rad, counter-clockwise) from the previous scan's reference time
    /// ([`ScanResult::time`]) to this scan's ([`Scan::reference_time`]).
    pub increment: f64,
    /// Its variance (rad²).
    pub variance: f64,
}

/// What the mapper did with one scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanResult {
    /// The time the pose is for (s): the scan's `time`, or for a scan with per-beam times the
    /// middle of its beams.
    pub time: f64,
    /// The robot pose at `time`, in the map frame: the scan's match ([`ScanResult::matched`]),
    /// or while the head stands still the mean of its matches since it stopped
    /// ([`StandstillConfig`]).
    pub pose: Pose2,
    /// The pose this scan's match found (for a match not trusted, the prediction): what `pose`
    /// is unless the head stands still.
    pub matched: Pose2,
    /// Whether `pose` is a standing head's held pose.
    pub standing: bool,
    /// The pose the motion model predicted.
    pub predicted: Pose2,
    /// The robot's velocity at `time`, in the map frame: for a revolution the one its
    /// refinement found with the pose, else the mean since the previous scan (0 for the first).
    pub velocity: Velocity2,
    /// Covariance of `pose` over (x, y, θ) in the map frame (m², m·rad, rad²): the match's
    /// ([`ScanResult::match_covariance`]), or for a held pose the mean's: the floor, which the
    /// matches share, plus the rest of their mean covariance over their number. Relative to the
    /// map, drift not included.
    pub covariance: Matrix3,
    /// Covariance of `matched` (m², m·rad, rad²): what the scan says and what the prediction
    /// said, combined as the match weighed them (see the module doc). 0 for the first scan,
    /// which defines the map frame; for a match not trusted, the prediction's.
    pub match_covariance: Matrix3,
    /// Covariance of the robot pose from the scan alone (its fit and the floor, no prior), for
    /// fusing with a source the prior did not already use; `None` when not matched.
    pub scan_covariance: Option<Matrix3>,
    /// Mean endpoint occupancy of the match on the finest grid (0 when not matched).
    pub score: f64,
    /// Whether the scan was integrated into the map.
    pub integrated: bool,
    /// Whether the scan was set aside as logged out of order: `pose` is the earlier pose it
    /// fits, and neither the map nor the next prediction used it
    /// ([`MotionConfig::out_of_order_poses`]).
    pub out_of_order: bool,
    /// Whether the scan returned to a place mapped long ago and its pose was moved onto that
    /// old map (`matched` is where the current map put it; [`crate::reentry`]).
    pub reentered: bool,
}

/// The incremental mapper: a grid pyramid and the last pose.
#[derive(Debug, Clone)]
pub struct Mapper {
    config: MapperConfig,
    /// Every integrated scan: the map for output, and the one matched against without submaps
    /// (its refinement endpoints are kept only then).
    whole: Submap,
    /// With submaps ([`SubmapConfig`]), the active ones, oldest first; scans are matched
    /// against the first.
    active: VecDeque<Submap>,
    last: Option<Last>,
    last_integrated: Option<Pose2>,
    refused: usize,
    standstill: Standstill,
    /// A running mean of the trusted matches' scores, against which a poor match is judged.
    recent_score: Option<f64>,
    /// The recent poses with their times, oldest first: back to the first one at least
    /// [`MotionConfig::velocity_window`] before the last, and at least the last
    /// [`MotionConfig::out_of_order_poses`].
    recent_poses: VecDeque<(f64, Pose2)>,
    /// Where the scans set aside as out of order since the last one that was not were taken,
    /// oldest first: a log's late lines come in bursts, each taken beside the one before.
    set_aside: Vec<Pose2>,
    /// The integrated scans, for the re-entry check.
    keyframes: Keyframes,
    /// How well each velocity clock has predicted the recent matches.
    clock_errors: ClockErrors,
    /// The odometry's systematic error as the matches show it
    /// ([`MotionConfig::odometry_bias_window`]; `None`: off).
    odometry_bias: Option<OdometryBias>,
    /// How well the odometry has agreed with the matches lately
    /// ([`MotionConfig::odometry_check_window`]).
    odometry_agreement: OdometryAgreement,
}

/// When a revolution's endpoints were seen: per endpoint, its time from the reference time
/// (the middle of the beams); the sensor pose at the previous reference; the time since.
#[derive(Debug, Clone, Copy)]
struct Timing<'a> {
    offsets: &'a [f64],
    from: Pose2,
    interval: f64,
}

/// One local submap: its grids, the refinement's endpoints, and how many scans it holds.
#[derive(Debug, Clone)]
struct Submap {
    map: GridPyramid,
    surfaces: Surfaces,
    scans: usize,
}

impl Submap {
    fn new(config: &MapperConfig) -> Self {
        Self {
            map: GridPyramid::new(config.resolution, config.levels, &config.update),
            surfaces: Surfaces::new(config.resolution, &config.refine),
            scans: 0,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Last {
    time: f64,
    pose: Pose2,
    odometry: Option<Pose2>,
    /// Motion over the previous interval, in the frame of its start, and that interval (s).
    motion: Pose2,
    interval: f64,
    velocity: Velocity2,
    covariance: Matrix3,
}

impl Mapper {
    /// A mapper with an empty map.
    pub fn new(config: MapperConfig) -> Self {
        Self {
            whole: Submap::new(&config),
            active: if config.submap.scans > 0 {
                VecDeque::from([Submap::new(&config)])
            } else {
                VecDeque::new()
            },
            config,
            last: None,
            last_integrated: None,
            refused: 0,
            standstill: Standstill::default(),
            recent_score: None,
            recent_poses: VecDeque::new(),
            set_aside: Vec::new(),
            keyframes: Keyframes::default(),
            clock_errors: ClockErrors::default(),
            odometry_bias: (config.motion.odometry_bias_window > 0.0)
                .then(|| OdometryBias::new(config.motion.odometry_bias_window)),
            odometry_agreement: OdometryAgreement::default(),
        }
    }

    /// The grids built so far.
    pub fn map(&self) -> &GridPyramid {
        &self.whole.map
    }

    /// The grids scans are matched against now: the oldest active submap's, or the whole map's
    /// without submaps.
    pub fn matching_map(&self) -> &GridPyramid {
        &self.matching().map
    }

    /// What scans are matched against now (see [`Mapper::matching_map`]).
    fn matching(&self) -> &Submap {
        self.active.front().unwrap_or(&self.whole)
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
        // The pose is for the reference time of the scan as given, far endpoints or not (the
        // caller's gyro increment ends there).
        let reference = scan.reference_time();
        match self.within_range(scan) {
            Some(near) => self.add_scan_at(&near, reference),
            None => self.add_scan_at(scan, reference),
        }
    }

    /// The scan without its endpoints beyond [`MapperConfig::max_range`], or `None` when it
    /// has none.
    fn within_range(&self, scan: &Scan) -> Option<Scan> {
        let max = self.config.max_range;
        let near = |&(x, y): &(f64, f64)| x.hypot(y) <= max;
        if scan.hits.iter().all(near) {
            return None;
        }
        let timed = scan.is_timed();
        let mut hits = Vec::with_capacity(scan.hits.len());
        let mut hit_times = Vec::new();
        for (i, hit) in scan.hits.iter().enumerate() {
            if near(hit) {
                hits.push(*hit);
                if timed {
                    hit_times.push(scan.hit_times[i]);
                }
            }
        }
        Some(Scan {
            time: scan.time,
            hits,
            hit_times,
            odometry: scan.odometry,
            sensor_offset: scan.sensor_offset,
            rotation: scan.rotation,
        })
    }

    fn add_scan_at(&mut self, scan: &Scan, reference: f64) -> ScanResult {
        let timed = scan.is_timed();
        let middle = reference - scan.time;
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
            if self.integrate(scan, reference, &pose, &scan.hits) {
                self.standstill.integrated(&pose, &[[0.0; 3]; 3]);
            }
            self.last = Some(Last {
                time: reference,
                pose,
                odometry: scan.odometry,
                motion: Pose2::default(),
                interval: 0.0,
                velocity: Velocity2::default(),
                covariance: [[0.0; 3]; 3],
            });
            self.remember(reference, pose);
            return ScanResult {
                time: reference,
                pose,
                matched: pose,
                standing: false,
                predicted: pose,
                velocity: Velocity2::default(),
                covariance: [[0.0; 3]; 3],
                match_covariance: [[0.0; 3]; 3],
                scan_covariance: None,
                score: 0.0,
                integrated: true,
                out_of_order: false,
                reentered: false,
            };
        };
        let dt = reference - last.time;
        let (motion, information, from_odometry) =
            self.predict(&last, scan, dt, self.config.motion.use_odometry);
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
        // The prediction's covariance over the sensor pose: the last pose's carried along the
        // predicted motion, and the motion model's (the prior's information, inverted).
        let prior_covariance = add(
            &carry(&last.covariance, &last.pose, &start),
            &inverse_of_diagonal(&information),
        );
        let mut matched: Match = match_scan(
            self.matching_map(),
            &hits,
            start,
            Some(&prior),
            &self.config.matcher,
        );
        let mut prior = prior;
        // With odometry or a measured turn (a gyro), a match well below the recent ones is
        // poor: the odometry may have slipped, the trolley may have been shoved, and the window
        // search may replace the match (the gate is per scan). With neither, the search runs
        // whenever the match is below `velocity_search_below`.
        let normal = self.recent_score.map_or(f64::NEG_INFINITY, |recent| {
            self.config.motion.poor_match_ratio * recent
        });
        let gated = from_odometry || scan.rotation.is_some();
        let poor = gated && matched.score < normal;
        // A replacement must gain this much on the current match and not be poor itself.
        let needed = |current: f64| (current + self.config.motion.poor_match_gain).max(normal);
        // Whether the constant-velocity candidate or the window search replaced the match.
        let mut replaced = false;
        if poor && from_odometry {
            // Try the constant-velocity prediction too (what the scans alone say the robot
            // was doing), with its own, looser prior.
            let (guess, guess_information, _) = self.predict(&last, scan, dt, false);
            let guess_start = last.pose.compose(&guess).compose(&scan.sensor_offset);
            let guess_prior = Prior {
                pose: guess_start,
                information: guess_information,
            };
            let second = match_scan(
                self.matching_map(),
                &hits,
                guess_start,
                Some(&guess_prior),
                &self.config.matcher,
            );
            if second.score > matched.score && second.score >= needed(matched.score) {
                matched = second;
                prior = guess_prior;
                replaced = true;
            }
        }
        let (search_wanted, needed) = if from_odometry {
            (poor, needed(matched.score))
        } else if gated {
            (poor, matched.score)
        } else {
            let below = matched.score < self.config.motion.velocity_search_below;
            (below, matched.score)
        };
        // With odometry, a match still poor after the window is searched again over a window
        // `wider_search` times as long: a slip or a shove beyond the first one's reach.
        let reaches = [1.0, self.config.motion.wider_search];
        for (attempt, reach) in reaches.into_iter().enumerate() {
            let again = attempt > 0;
            if !search_wanted
                || (again && (!from_odometry || reach <= 1.0 || matched.score >= normal))
            {
                break;
            }
            // A poor fit from the prediction: the trolley may have turned, the odometry may
            // have slipped. Search a window on the coarsest grid around the prediction and
            // keep whichever match fits better (with odometry: only one that is not poor).
            let coarsest = self
                .matching_map()
                .levels()
                .last()
                .expect("at least one level");
            let mut window = self.config.motion.velocity_search.around(
                1.0 / information[0][0].sqrt(),
                1.0 / information[2][2].sqrt(),
            );
            window.translation *= reach;
            let window = &window;
            let loose = no_tighter_than(&information, coarsest.resolution(), window.angle_step);
            let found = search(coarsest, &hits, start, window, Some(&loose));
            // The prediction was wrong here: the prior is centred where the search found the
            // scan for the matches that follow (the odometry's as loose as the search). A gyro's
            // prediction keeps its own prior: re-centring its tight heading on the search's
            // coarse step would pull the heading by up to a step.
            let wide = Prior {
                pose: found,
                information: if from_odometry { loose } else { information },
            };
            let second = match_scan(
                self.matching_map(),
                &hits,
                found,
                Some(&wide),
                &self.config.matcher,
            );
            // Without odometry the two are weighed as the search weighs its candidates: a
            // match away from the prediction must fit better by more than the distance costs
            // (along a corridor the map cannot tell them apart, and the prediction stands).
            let prediction = Prior {
                pose: start,
                information: loose,
            };
            let weighed = |m: &Match| {
                if from_odometry {
                    m.score
                } else {
                    m.score - window.prior_weight * prediction.squared_distance(&m.pose)
                }
            };
            if weighed(&second) > weighed(&matched) && second.score >= needed {
                matched = second;
                replaced = true;
                if from_odometry || scan.rotation.is_none() {
                    prior = wide;
                }
            }
        }
        // The robot's pose by the match.
        let mut pose = matched.pose.compose(&scan.sensor_offset.inverse());
        // A poor match may be a scan logged out of order: taken earlier, where the robot was. So
        // may a good one that went back against the prediction to where the robot was a few
        // scans ago: it fits there, but the next scan is to be predicted from the last pose in
        // order, not from it.
        let unaided = !gated && !from_odometry;
        let may_set_aside = unaided && self.set_aside.len() < MAX_OUT_OF_ORDER_IN_A_ROW;
        let poor_here = matched.score < normal;
        let went_back =
            may_set_aside && !poor_here && self.went_back(&last.pose, &predicted, &pose);
        let late = if may_set_aside && (poor_here || went_back) {
            let earlier = self.earlier_match(&hits, &scan.sensor_offset, &information);
            if went_back {
                Some(
                    earlier
                        .filter(|e| e.score >= matched.score)
                        .unwrap_or(matched),
                )
            } else {
                earlier.filter(|e| e.score >= normal && e.score > matched.score)
            }
        } else {
            None
        };
        // Late lines set aside as many times in a row as allowed, and this one fits poorly
        // where predicted too but well at an earlier pose: the track in order is what went
        // wrong. The robot is back there, standing: it carries on from that pose, the velocity
        // started again (a jump is not a motion to extrapolate).
        let stuck = unaided && !may_set_aside && poor_here;
        let back_there = stuck
            .then(|| self.earlier_match(&hits, &scan.sensor_offset, &information))
            .flatten()
            .filter(|e| e.score >= normal && e.score > matched.score);
        let relocalised = back_there.is_some();
        if let Some(earlier) = back_there {
            prior = Prior {
                pose: earlier.pose,
                information,
            };
            pose = earlier.pose.compose(&scan.sensor_offset.inverse());
            matched = earlier;
        }
        if let Some(earlier) = late {
            let taken_at = earlier.pose.compose(&scan.sensor_offset.inverse());
            self.set_aside.push(taken_at);
            let floor = self.config.covariance.matrix();
            let fit = self.scaled(earlier.fit);
            let covariance = scan_alone(&fit, &floor, &earlier.pose, &taken_at);
            return ScanResult {
                time: reference,
                pose: taken_at,
                matched: taken_at,
                standing: false,
                predicted,
                velocity: last.velocity,
                covariance,
                match_covariance: covariance,
                scan_covariance: Some(covariance),
                score: earlier.score,
                integrated: false,
                out_of_order: true,
                reentered: false,
            };
        }
        let mut hits = hits;
        if timed && dt > 0.0 {
            // De-skew again with the motion the match found, and match again.
            let found = last.pose.between(&pose);
            hits = deskew(&scan.hits, &relative, &scan.sensor_offset, &found, dt);
            matched = match_scan(
                self.matching_map(),
                &hits,
                matched.pose,
                Some(&prior),
                &self.config.matcher,
            );
            pose = matched.pose.compose(&scan.sensor_offset.inverse());
        }
        let trusted = matched.score >= self.config.min_score;
        // The sensor pose reported, what the scan says about it, and its velocity if found.
        let (sensor, fit, sensor_velocity) = if !trusted {
            pose = predicted;
            (start, None, None)
        } else if self.config.refine.enabled {
            let timing = (timed && dt > 0.0).then(|| Timing {
                offsets: &relative,
                from: last.pose.compose(&scan.sensor_offset),
                interval: dt,
            });
            let (refined, placed) = self.refine_match(scan, &hits, &matched.pose, timing, &prior);
            pose = refined.pose.compose(&scan.sensor_offset.inverse());
            if let Some(placed) = placed {
                hits = placed;
            }
            match refined.fit {
                Some(fit) => (refined.pose, Some(fit), refined.velocity),
                None => (matched.pose, Some(matched.fit), None),
            }
        } else {
            (matched.pose, Some(matched.fit), None)
        };
        let floor = self.config.covariance.matrix();
        let fit = fit.map(|fit| self.scaled(fit));
        let sensor_covariance = fit.map_or(prior_covariance, |fit| {
            weighed(&fit, &floor, &information, &prior_covariance)
        });
        let covariance = carry(&sensor_covariance, &sensor, &pose);
        let scan_covariance = fit.map(|fit| scan_alone(&fit, &floor, &sensor, &pose));
        let mut velocity = match sensor_velocity {
            Some(v) => robot_velocity(&v, &sensor, &pose),
            None if dt > 0.0 => Velocity2 {
                x: (pose.x - last.pose.x) / dt,
                y: (pose.y - last.pose.y) / dt,
                theta: wrap_angle(pose.theta - last.pose.theta) / dt,
            },
            None => last.velocity,
        };
        let (matched_pose, match_covariance) = (pose, covariance);
        let turned = scan
            .rotation
            .is_some_and(|r| r.increment.abs() > 3.0 * r.variance.max(0.0).sqrt());
        // With wheel odometry the prediction knows when the robot stands: no hold.
        let held = if trusted && !turned && !from_odometry && self.config.standstill.enabled {
            let floor = carry(&floor, &sensor, &pose);
            self.standstill
                .observe(&self.config.standstill, &pose, &covariance, &floor)
        } else {
            self.standstill.leave();
            None
        };
        let (mut pose, covariance, found) = match held {
            Some((held, held_covariance)) => {
                velocity = Velocity2::default();
                (held, held_covariance, Pose2::default())
            }
            None if relocalised => {
                velocity = Velocity2::default();
                (pose, covariance, Pose2::default())
            }
            None => (pose, covariance, last.pose.between(&pose)),
        };
        if trusted {
            self.recent_score = Some(match self.recent_score {
                Some(recent) => recent + RECENT_SCORE_WEIGHT * (matched.score - recent),
                None => matched.score,
            });
        }
        if trusted && !relocalised && self.without_odometry(scan) {
            let recent = self.recent_motion(&last);
            self.clock_errors.observe(
                &recent.predict(dt, VelocityClock::Time).0,
                &recent.predict(dt, VelocityClock::Scans).0,
                &last.pose.between(&matched_pose),
            );
        }
        if from_odometry {
            let window = self.config.motion.odometry_check_window;
            match scan.odometry {
                Some(odometry) if trusted && !relocalised && window > 0.0 => {
                    // A match the gate's candidates replaced (a slip, a shove) has dealt with
                    // the odometry's error at this scan: it is not held against the next ones.
                    if replaced {
                        self.odometry_agreement.restart();
                    }
                    self.odometry_agreement.observe(
                        reference,
                        matched_pose,
                        odometry,
                        window,
                        &self.config.motion,
                    );
                }
                _ => self.odometry_agreement.pause(),
            }
        }
        if from_odometry && trusted && !relocalised && matched.score >= normal {
            let m = &self.config.motion;
            if let (Some(step), Some(bias)) =
                (self.odometry_step(&last, scan), self.odometry_bias.as_mut())
            {
                let (_, sigma) = m.step_sigmas(&step);
                bias.observe(&step, &last.pose.between(&matched_pose), sigma);
            }
        }
        // Back at a place mapped long ago: the old map there may say the scan is misplaced.
        let reentry = if trusted && held.is_none() && self.due(&pose) {
            let sensor = pose.compose(&scan.sensor_offset);
            self.keyframes.check(&self.config, &hits, sensor, reference)
        } else {
            None
        };
        let reentered = reentry.is_some();
        if let Some(reentry) = reentry {
            let moved = reentry.sensor.compose(&scan.sensor_offset.inverse());
            // The recent poses move with it, so the velocity over them is the robot's, not the
            // correction; the odometry's agreement with the matches starts again after the jump.
            let correction = moved.compose(&pose.inverse());
            for (_, recent) in &mut self.recent_poses {
                *recent = correction.compose(recent);
            }
            self.odometry_agreement.restart();
            pose = moved;
        }
        let integrated = trusted
            && held.is_none()
            && self.due(&pose)
            && self.integrate(scan, reference, &pose, &hits);
        self.last = Some(Last {
            time: reference,
            pose,
            odometry: scan.odometry,
            motion: found,
            interval: dt,
            velocity,
            covariance,
        });
        if relocalised {
            self.recent_poses.clear();
        }
        self.remember(reference, pose);
        ScanResult {
            time: reference,
            pose,
            matched: matched_pose,
            standing: held.is_some(),
            predicted,
            velocity,
            covariance,
            match_covariance,
            scan_covariance,
            score: if trusted { matched.score } else { 0.0 },
            integrated,
            out_of_order: false,
            reentered,
        }
    }

    /// `fit` with its scale multiplied by the configured `fit_factor` (endpoints are not
    /// independent measurements; docs/slam.md).
    fn scaled(&self, fit: Fit) -> Fit {
        Fit {
            scale: fit.scale * self.config.covariance.fit_factor.max(1.0),
            ..fit
        }
    }

    /// Whether a match placing the robot `here` went back from the `last` pose against the
    /// prediction (`predicted`): behind it along the predicted motion by more than
    /// [`MotionConfig::out_of_order_back`], or turned against the predicted turn by more than
    /// [`MotionConfig::out_of_order_turn_back`], and to nearer one of the earlier poses
    /// than the last one.
    fn went_back(&self, last: &Pose2, predicted: &Pose2, here: &Pose2) -> bool {
        let motion = &self.config.motion;
        let (ahead, step) = (last.between(predicted), last.between(here));
        let length = ahead.x.hypot(ahead.y);
        let drove_back = motion.out_of_order_back > 0.0
            && length > MIN_PREDICTED_STEP
            && (step.x * ahead.x + step.y * ahead.y) / length < -motion.out_of_order_back;
        let turned_back = motion.out_of_order_turn_back > 0.0
            && step.theta * ahead.theta < 0.0
            && (step.theta - ahead.theta).abs() > motion.out_of_order_turn_back;
        if !(drove_back || turned_back) {
            return false;
        }
        let distance = |p: &Pose2| {
            (p.x - here.x).hypot(p.y - here.y)
                + REVISIT_LEVER * wrap_angle(p.theta - here.theta).abs()
        };
        let mut recent = self
            .recent_poses
            .iter()
            .rev()
            .take(motion.out_of_order_poses)
            .map(|(_, pose)| distance(pose));
        recent
            .next()
            .is_some_and(|to_last| recent.any(|to_earlier| to_earlier < to_last))
    }

    /// The best match of `hits` started where the scans just set aside were taken, then at each
    /// of the earlier poses (not the last), each with the prediction's `information` around it;
    /// poses within 5 cm and 0.03 rad of one already tried are skipped. `None` when there is
    /// none to try.
    fn earlier_match(
        &self,
        hits: &[(f64, f64)],
        sensor_offset: &Pose2,
        information: &Matrix3,
    ) -> Option<Match> {
        let mut tried: Vec<Pose2> = Vec::new();
        let mut best: Option<Match> = None;
        // A late line in a burst was taken beside the one set aside before it.
        let earlier_poses = self.recent_poses.iter().rev().map(|(_, pose)| pose);
        let candidates = self.set_aside.iter().rev().chain(
            earlier_poses
                .take(self.config.motion.out_of_order_poses)
                .skip(1),
        );
        for earlier in candidates {
            let near = |t: &Pose2| {
                (t.x - earlier.x).hypot(t.y - earlier.y) < 0.05
                    && wrap_angle(t.theta - earlier.theta).abs() < 0.03
            };
            if tried.iter().any(near) {
                continue;
            }
            tried.push(*earlier);
            let start = earlier.compose(sensor_offset);
            let prior = Prior {
                pose: start,
                information: *information,
            };
            let candidate = match_scan(
                self.matching_map(),
                hits,
                start,
                Some(&prior),
                &self.config.matcher,
            );
            if best.as_ref().is_none_or(|b| candidate.score > b.score) {
                best = Some(candidate);
            }
        }
        best
    }

    /// Integrates a scan taken at a known robot `pose` (mapping with known poses, or a map
    /// prepared before localising in it), its endpoints within `max_range` (`hit_times` are not used: a
    /// revolution is integrated as if instantaneous at `pose`). Does not move the mapper's own
    /// pose. Returns whether it was integrated (see [`Mapper::refused_integrations`]).
    pub fn integrate_at(&mut self, scan: &Scan, pose: &Pose2) -> bool {
        match self.within_range(scan) {
            Some(near) => self.integrate_joining(&near, pose, &near.hits, None),
            None => self.integrate_joining(scan, pose, &scan.hits, None),
        }
    }

    /// Sets the robot's pose at `time` (a reference time, as [`ScanResult::time`]) to a known
    /// one with its `covariance`, standing still: the next scan is predicted from it. Used to
    /// localise in a prepared map, or to place a session's start.
    pub fn start_at(&mut self, time: f64, pose: Pose2, covariance: Matrix3) {
        self.standstill.leave();
        self.last = Some(Last {
            time,
            pose,
            odometry: None,
            motion: Pose2::default(),
            interval: 0.0,
            velocity: Velocity2::default(),
            covariance,
        });
        self.recent_poses.clear();
        self.set_aside.clear();
        self.remember(time, pose);
    }

    /// The sub-cell refinement of a trusted grid match (`matched`, a sensor pose): of the
    /// de-skewed `hits` for an instantaneous scan, or for a revolution of its endpoints as
    /// measured, each seen along a velocity found with the pose. Returns the refinement and,
    /// for a revolution whose refinement was taken, its endpoints placed with its velocity.
    fn refine_match(
        &self,
        scan: &Scan,
        hits: &[(f64, f64)],
        matched: &Pose2,
        timing: Option<Timing>,
        prior: &Prior,
    ) -> (Refinement, Option<Vec<(f64, f64)>>) {
        let config = &self.config.refine;
        let Some(timing) = timing else {
            let refined = refine(
                &self.matching().surfaces,
                hits,
                *matched,
                None,
                Some(prior),
                config,
            );
            return (refined, None);
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
            &self.matching().surfaces,
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
        (refined, placed)
    }

    /// The predicted motion since the last scan (in its frame) and the prior's information
    /// matrix over the sensor pose.
    fn predict(
        &self,
        last: &Last,
        scan: &Scan,
        dt: f64,
        use_odometry: bool,
    ) -> (Pose2, Matrix3, bool) {
        let m = &self.config.motion;
        let odometry = self
            .odometry_step(last, scan)
            .filter(|_| use_odometry)
            .map(|step| {
                self.odometry_bias
                    .as_ref()
                    .map_or(step, |bias| bias.correct(&step))
            });
        let (motion, sigma_t, sigma_r) = match odometry {
            Some(delta) => {
                // Widened where the odometry has lately disagreed with the scans.
                let widening = self
                    .odometry_agreement
                    .widening(m.odometry_check_threshold, m.odometry_max_widening);
                let (translation, rotation) = m.step_sigmas(&delta);
                (
                    delta,
                    widening.translation * translation,
                    widening.rotation * rotation,
                )
            }
            None => {
                // With odometry at hand (the gate's constant-velocity candidate), the last
                // interval's motion: what the scans alone said the robot was just doing.
                let (motion, elapsed) = if self.without_odometry(scan) {
                    let clock = self.clock_errors.clock(m.velocity_clock);
                    self.recent_motion(last).predict(dt, clock)
                } else {
                    let last_interval = RecentMotion {
                        moved: last.motion,
                        time: last.interval,
                        scans: 1,
                    };
                    last_interval.predict(dt, VelocityClock::Time)
                };
                (
                    motion,
                    m.velocity_translation_per_s * elapsed,
                    m.velocity_rotation_per_s * elapsed,
                )
            }
        };
        let sigma_t = sigma_t.max(m.min_translation_sigma);
        let mut sigma_r = sigma_r.max(m.min_rotation_sigma);
        let mut motion = motion;
        if let Some(rotation) = scan.rotation {
            // A measured turn replaces the model's, with its own variance (kept above a
            // microradian so that the information stays finite).
            motion.theta = wrap_angle(rotation.increment);
            sigma_r = rotation.variance.max(0.0).sqrt().max(1e-6);
        }
        let information = [
            [1.0 / (sigma_t * sigma_t), 0.0, 0.0],
            [0.0, 1.0 / (sigma_t * sigma_t), 0.0],
            [0.0, 0.0, 1.0 / (sigma_r * sigma_r)],
        ];
        (motion, information, odometry.is_some())
    }

    /// The odometry's step from the last scan to `scan`, as the wheels reported it (`None`
    /// without odometry on both, or with odometry off).
    fn odometry_step(&self, last: &Last, scan: &Scan) -> Option<Pose2> {
        match (
            self.config.motion.use_odometry,
            last.odometry,
            scan.odometry,
        ) {
            (true, Some(before), Some(now)) => Some(before.between(&now)),
            _ => None,
        }
    }

    /// Whether `scan` is predicted without odometry: by a constant velocity over the recent
    /// poses ([`MotionConfig::velocity_window`]; the odometry gate's constant-velocity
    /// candidate takes the last interval's).
    fn without_odometry(&self, scan: &Scan) -> bool {
        !(self.config.motion.use_odometry && scan.odometry.is_some())
    }

    /// The motion the constant-velocity prediction extrapolates: over the recent poses back to
    /// [`MotionConfig::velocity_window`] before the last, or the last interval's.
    fn recent_motion(&self, last: &Last) -> RecentMotion {
        let window = self.config.motion.velocity_window;
        let newest = self.recent_poses.len().saturating_sub(1);
        let from = self
            .recent_poses
            .iter()
            .rposition(|(time, _)| last.time - time >= window)
            .unwrap_or(0);
        match self.recent_poses.get(from) {
            Some(&(time, pose)) if window > 0.0 && from < newest => {
                let moved = pose.between(&last.pose);
                let (sin, cos) = moved.theta.sin_cos();
                RecentMotion {
                    moved: Pose2::new(
                        cos * moved.x + sin * moved.y,
                        -sin * moved.x + cos * moved.y,
                        moved.theta,
                    ),
                    time: last.time - time,
                    scans: newest - from,
                }
            }
            _ => RecentMotion {
                moved: last.motion,
                time: last.interval,
                scans: 1,
            },
        }
    }

    /// Keeps `pose` at `time` among the recent poses, and drops those no longer needed.
    fn remember(&mut self, time: f64, pose: Pose2) {
        self.set_aside.clear();
        self.recent_poses.push_back((time, pose));
        let window = self.config.motion.velocity_window;
        let kept = self.config.motion.out_of_order_poses.max(1);
        while self.recent_poses.len() > kept
            && (time - self.recent_poses[1].0 >= window
                || self.recent_poses.len() > MAX_RECENT_POSES)
        {
            self.recent_poses.pop_front();
        }
    }

    fn due(&self, pose: &Pose2) -> bool {
        self.last_integrated.is_none_or(|at| {
            (pose.x - at.x).hypot(pose.y - at.y) >= self.config.map_update_distance
                || wrap_angle(pose.theta - at.theta).abs() >= self.config.map_update_angle
        })
    }

    /// Integrates `hits` of `scan` (taken at `time`) at the robot's `pose`, and keeps the scan
    /// for the re-entry check when it went in.
    fn integrate(&mut self, scan: &Scan, time: f64, pose: &Pose2, hits: &[(f64, f64)]) -> bool {
        let integrated = self.integrate_joining(scan, pose, hits, self.join_within(scan));
        if integrated && self.config.reentry.enabled {
            self.keyframes
                .add(time, pose.compose(&scan.sensor_offset), hits);
        }
        integrated
    }

    /// How far apart `scan`'s endpoints are joined when it is integrated: wider when its pose
    /// came without odometry ([`UpdateModel::join_endpoints_within_without_odometry`]).
    fn join_within(&self, scan: &Scan) -> Option<f64> {
        self.without_odometry(scan).then(|| {
            f64::from(
                self.config
                    .update
                    .join_endpoints_within_without_odometry
                    .max(0.0),
            )
        })
    }

    /// [`Mapper::integrate`], joining endpoints up to `join_within` apart (`None`: the model's
    /// [`UpdateModel::join_endpoints_within`]).
    fn integrate_joining(
        &mut self,
        scan: &Scan,
        pose: &Pose2,
        hits: &[(f64, f64)],
        join_within: Option<f64>,
    ) -> bool {
        let sensor = pose.compose(&scan.sensor_offset);
        if !self
            .whole
            .map
            .integrate_joining(&sensor, hits, &[], join_within)
        {
            self.refused += 1;
            return false;
        }
        let refine = self.config.refine.enabled;
        if self.active.is_empty() && refine {
            self.whole.surfaces.integrate(&sensor, hits);
        }
        for submap in &mut self.active {
            // A submap covers less than the whole map, which just took the scan: it grows.
            submap
                .map
                .integrate_joining(&sensor, hits, &[], join_within);
            if refine {
                submap.surfaces.integrate(&sensor, hits);
            }
            submap.scans += 1;
        }
        if self
            .active
            .back()
            .is_some_and(|newest| newest.scans >= self.config.submap.scans)
        {
            self.active.push_back(Submap::new(&self.config));
            if self.active.len() > 2 {
                self.active.pop_front();
            }
        }
        self.last_integrated = Some(*pose);
        true
    }
}

/// A standing head's matches ([`StandstillConfig`]): the recent ones while it may be moving,
/// then the sum of those since it stopped, about the first (headings unwrapped from its).
#[derive(Debug, Clone, Default)]
struct Standstill {
    /// The last poses (pose, covariance, whether the map was integrated at it) while not
    /// standing, oldest first.
    recent: Vec<(Pose2, Matrix3, bool)>,
    /// While standing: the matches held.
    hold: Option<Hold>,
    /// The hold just let go, for one revolution: when the next match is back within its
    /// scatter, the strikes were outliers and it is taken up again.
    left: Option<Hold>,
}

#[derive(Debug, Clone)]
struct Hold {
    first: Pose2,
    /// Sums of x, y and θ − first.θ (wrapped) over the matches held.
    sum: [f64; 3],
    /// Sum of their covariances.
    covariance_sum: Matrix3,
    /// Sum of the outer products of their offsets from `first` (x, y, wrapped θ): their
    /// scatter, with `sum`.
    offsets_squared: Matrix3,
    count: usize,
    /// Matches in a row outside the gate.
    strikes: usize,
    /// The session's first pose (it defines the map frame; the map is its scan, placed
    /// there), with its covariance, when the head has stood there since: that pose agrees with
    /// the map exactly, where other scans' matches carry the map's error as a bias. Held
    /// instead of the mean.
    anchor: Option<(Pose2, Matrix3)>,
}

impl Hold {
    fn start(members: &[(Pose2, Matrix3, bool)]) -> Self {
        let mut hold = Hold {
            first: members[0].0,
            sum: [0.0; 3],
            covariance_sum: [[0.0; 3]; 3],
            offsets_squared: [[0.0; 3]; 3],
            count: 0,
            strikes: 0,
            anchor: None,
        };
        for (pose, covariance, integrated) in members {
            hold.add(pose, covariance);
            if *integrated {
                hold.anchor = Some((*pose, *covariance));
            }
        }
        hold
    }

    fn add(&mut self, pose: &Pose2, covariance: &Matrix3) {
        let d = self.offset(pose);
        self.sum[0] += pose.x;
        self.sum[1] += pose.y;
        self.sum[2] += d[2];
        self.covariance_sum = add(&self.covariance_sum, covariance);
        for (i, row) in self.offsets_squared.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += d[i] * d[j];
            }
        }
        self.count += 1;
    }

    fn offset(&self, pose: &Pose2) -> [f64; 3] {
        [
            pose.x - self.first.x,
            pose.y - self.first.y,
            wrap_angle(pose.theta - self.first.theta),
        ]
    }

    /// The mean of the matches held.
    fn mean(&self) -> Pose2 {
        let n = self.count as f64;
        Pose2::new(
            self.sum[0] / n,
            self.sum[1] / n,
            self.first.theta + self.sum[2] / n,
        )
    }

    /// Whether `pose` (covariance `covariance`) is within `gate` of the held pose with both
    /// covariances (calibrated).
    fn within_calibrated(
        &self,
        pose: &Pose2,
        covariance: &Matrix3,
        floor: &Matrix3,
        gate: f64,
    ) -> bool {
        let (held, held_covariance) = self.held(floor);
        mahalanobis(pose, &held, &add(covariance, &held_covariance)) <= gate
    }

    /// Whether `pose` is within `gate` of the held matches' mean with their observed scatter
    /// (plus [`SCATTER_FLOOR`]); `false` while fewer than [`SCATTER_AFTER`] are held. For a
    /// precise lidar far tighter than the calibrated covariance, so a head that starts moving
    /// is let go within millimetres.
    fn within_scatter(&self, pose: &Pose2, gate: f64) -> bool {
        if self.count < SCATTER_AFTER {
            return false;
        }
        let n = self.count as f64;
        let mean = [
            self.sum[0] / n - self.first.x,
            self.sum[1] / n - self.first.y,
            self.sum[2] / n,
        ];
        let scatter = [0, 1, 2].map(|i| {
            [0, 1, 2].map(|j| {
                let c = (self.offsets_squared[i][j] - n * mean[i] * mean[j]) / (n - 1.0);
                c * (1.0 + 1.0 / n) + SCATTER_FLOOR[i][j]
            })
        });
        mahalanobis(pose, &self.mean(), &scatter) <= gate
    }

    /// The held pose and its covariance: the anchor's, or the mean of the matches with the
    /// `floor` they share plus the rest of their mean covariance over their number
    /// (`C̄ / N + F (1 − 1/N)`).
    fn held(&self, floor: &Matrix3) -> (Pose2, Matrix3) {
        if let Some(anchor) = self.anchor {
            return anchor;
        }
        let n = self.count as f64;
        let mean = self.mean();
        let covariance = [0, 1, 2].map(|i| {
            [0, 1, 2].map(|j| self.covariance_sum[i][j] / (n * n) + floor[i][j] * (1.0 - 1.0 / n))
        });
        (mean, covariance)
    }
}

impl Standstill {
    /// Takes a trusted match; returns the held pose and its covariance while standing.
    fn observe(
        &mut self,
        config: &StandstillConfig,
        pose: &Pose2,
        covariance: &Matrix3,
        floor: &Matrix3,
    ) -> Option<(Pose2, Matrix3)> {
        if let Some(hold) = &mut self.hold {
            let calibrated = hold.within_calibrated(pose, covariance, floor, config.gate);
            if hold.count < SCATTER_AFTER {
                if calibrated {
                    hold.add(pose, covariance);
                    return (hold.count >= SCATTER_AFTER).then(|| hold.held(floor));
                }
                self.leave();
            } else if hold.within_scatter(pose, config.gate) {
                hold.strikes = 0;
                hold.add(pose, covariance);
                return Some(hold.held(floor));
            } else {
                // Outside the scatter: an outlier, or the head moves. Let go at the second in a
                // row beyond the calibrated gate too, or at the third within it.
                hold.strikes += 1;
                if hold.strikes < if calibrated { 3 } else { 2 } {
                    return Some(hold.held(floor));
                }
                let mut left = self.hold.take().expect("holding");
                left.strikes = 0;
                self.leave();
                self.left = Some(left);
                return None;
            }
        } else if let Some(left) = self.left.take()
            && left.within_scatter(pose, config.gate)
        {
            // The match after letting go is back where the head stood: those were outliers.
            let hold = self.hold.insert(left);
            hold.add(pose, covariance);
            return Some(hold.held(floor));
        }
        self.recent.push((*pose, *covariance, false));
        let wanted = config.revolutions.max(2);
        if self.recent.len() > wanted {
            self.recent.remove(0);
        }
        if self.recent.len() < wanted {
            return None;
        }
        let members = Hold::start(&self.recent);
        let (mean, mean_covariance) = Hold {
            anchor: None,
            ..members.clone()
        }
        .held(floor);
        let still = self
            .recent
            .iter()
            .all(|(p, c, _)| mahalanobis(p, &mean, &add(c, &mean_covariance)) <= config.start_gate);
        if !still {
            return None;
        }
        self.recent.clear();
        self.hold = Some(members);
        None
    }

    /// The map was just integrated at `pose` (the head not standing): it may start a hold.
    fn integrated(&mut self, pose: &Pose2, covariance: &Matrix3) {
        match self.recent.last_mut() {
            Some(last) if last.0 == *pose => last.2 = true,
            _ => self.recent.push((*pose, *covariance, true)),
        }
    }

    /// The head moves (or nothing is known): forget the matches.
    fn leave(&mut self) {
        self.hold = None;
        self.left = None;
        self.recent.clear();
    }
}

/// The robot pose's covariance from the scan alone: `fit`'s plus the `floor`, at the `sensor`
/// pose, carried to the robot's `pose`.
fn scan_alone(fit: &Fit, floor: &Matrix3, sensor: &Pose2, pose: &Pose2) -> Matrix3 {
    carry(&add(&fit.covariance(), floor), sensor, pose)
}

/// `(a − b)ᵀ C⁻¹ (a − b)` over x, y and the wrapped heading difference; infinite when `C` is
/// singular.
fn mahalanobis(a: &Pose2, b: &Pose2, covariance: &Matrix3) -> f64 {
    let e = nalgebra::Vector3::new(a.x - b.x, a.y - b.y, wrap_angle(a.theta - b.theta));
    let c = nalgebra::Matrix3::from_fn(|i, j| covariance[i][j]);
    c.try_inverse().map_or(f64::INFINITY, |inverse| {
        (e.transpose() * inverse * e)[(0, 0)]
    })
}

/// `information` (diagonal) loosened so that no standard deviation is below `translation` (m)
/// or `rotation` (rad): a prior centred on a search's result is no surer than its steps.
fn no_tighter_than(information: &Matrix3, translation: f64, rotation: f64) -> Matrix3 {
    let mut loose = *information;
    let limits = [translation, translation, rotation];
    for (k, limit) in limits.iter().enumerate() {
        loose[k][k] = loose[k][k].min(1.0 / (limit * limit));
    }
    loose
}

/// `a + b`.
fn add(a: &Matrix3, b: &Matrix3) -> Matrix3 {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| a[i][j] + b[i][j]))
}

/// The inverse of a diagonal information matrix (the motion prior's).
fn inverse_of_diagonal(information: &Matrix3) -> Matrix3 {
    let mut out = [[0.0; 3]; 3];
    for (k, row) in out.iter_mut().enumerate() {
        row[k] = 1.0 / information[k][k];
    }
    out
}

/// The covariance of a pose `from` carried rigidly to `to`: `to` is `from` composed with a
/// fixed transform, so an error in `from`'s heading swings `to` about `from`
/// (`F C Fᵀ`, F = ∂to/∂from in map coordinates). Carries a robot pose's covariance to its
/// sensor's, and back.
fn carry(covariance: &Matrix3, from: &Pose2, to: &Pose2) -> Matrix3 {
    let (dx, dy) = (to.x - from.x, to.y - from.y);
    let f = nalgebra::Matrix3::new(1.0, 0.0, -dy, 0.0, 1.0, dx, 0.0, 0.0, 1.0);
    let c = nalgebra::Matrix3::from_fn(|i, j| covariance[i][j]);
    let out = f * c * f.transpose();
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| out[(i, j)]))
}

/// The covariance of the pose a match reports, which minimised the scan's cost plus the prior's:
/// to first order that pose is `(A + B)⁻¹ (A x_s + B x_p)`, A the scan's information as the match
/// weighed it, x_s what the scan alone would say (covariance `scale · A⁻¹ + floor`), B the
/// prior's information and x_p its mean (covariance `prior_covariance`, which may exceed B⁻¹:
/// the prior weighs only the motion model, the previous pose's error comes on top). So
/// `C = M (scale · A + A · floor · A + B · P · B) M`, M = (A + B)⁻¹; with an exact scale, no
/// floor and P = B⁻¹ it is the Gauss–Newton (A + B)⁻¹.
fn weighed(
    fit: &Fit,
    floor: &Matrix3,
    information: &Matrix3,
    prior_covariance: &Matrix3,
) -> Matrix3 {
    let m3 = |m: &Matrix3| nalgebra::Matrix3::from_fn(|i, j| m[i][j]);
    let (a, f, b, p) = (
        m3(&fit.information),
        m3(floor),
        m3(information),
        m3(prior_covariance),
    );
    let Some(m) = (a + b).try_inverse() else {
        return *prior_covariance;
    };
    let middle = a * fit.scale + a * f * a + b * p * b;
    let c = m * middle * m;
    // Symmetric by construction; rounding is not.
    let c = (c + c.transpose()) * 0.5;
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| c[(i, j)]))
}

/// The robot's velocity from its sensor's (`sensor_velocity`: x, y, ψ rates in the map frame),
/// the sensor at `sensor` and the robot at `robot`: the sensor's lever arm turns with the robot,
/// so its speed has an extra `ω × arm` the robot's has not.
fn robot_velocity(sensor_velocity: &[f64; 3], sensor: &Pose2, robot: &Pose2) -> Velocity2 {
    let [vx, vy, w] = *sensor_velocity;
    let (ax, ay) = (sensor.x - robot.x, sensor.y - robot.y);
    Velocity2 {
        x: vx + w * ay,
        y: vy - w * ax,
        theta: w,
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
    use crate::testing::{Segment, cast, rectangle};

    /// A 6 m × 4 m room with a pillar.
    fn room() -> Vec<Segment> {
        let mut walls = rectangle((-3.0167, -2.0333), (2.9833, 1.9667)).to_vec();
        walls.extend(rectangle((1.0167, 0.5167), (1.4167, 0.9167)));
        walls
    }

    /// Instantaneous scans of the room from `poses`, 0.1 s apart.
    fn scans(poses: &[Pose2]) -> Vec<Scan> {
        poses
            .iter()
            .enumerate()
            .map(|(k, pose)| Scan {
                time: 0.1 * k as f64,
                hits: cast(&room(), pose, 720),
                ..Scan::default()
            })
            .collect()
    }

    fn close(a: &Matrix3, b: &Matrix3, tolerance: f64) -> bool {
        (0..3).all(|i| (0..3).all(|j| (a[i][j] - b[i][j]).abs() <= tolerance))
    }

    #[test]
    fn the_covariance_of_a_weighed_match_is_the_inverse_of_the_summed_information() {
        let fit = Fit {
            information: [[4e4, 1e3, 0.0], [1e3, 2e4, 5e2], [0.0, 5e2, 9e4]],
            scale: 1.0,
            endpoints: 300,
        };
        let b = [[1e4, 0.0, 0.0], [0.0, 1e4, 0.0], [0.0, 0.0, 4e4]];
        let p = inverse_of_diagonal(&b);
        let zero = [[0.0; 3]; 3];
        // The prior's covariance as its information says, an exact scale, no floor: (A + B)⁻¹.
        let want = crate::matcher::invert(&add(&fit.information, &b)).expect("invertible");
        assert!(close(&weighed(&fit, &zero, &b, &p), &want, 1e-12));
        // A prior that knows nothing: the scan's own, scaled, plus the floor.
        let nothing = [[1e-12, 0.0, 0.0], [0.0, 1e-12, 0.0], [0.0, 0.0, 1e-12]];
        let floor = [[1e-5, 0.0, 0.0], [0.0, 1e-5, 0.0], [0.0, 0.0, 4e-6]];
        let scaled = Fit { scale: 4.0, ..fit };
        let alone = weighed(&scaled, &floor, &nothing, &inverse_of_diagonal(&nothing));
        let want = add(&scaled.covariance(), &floor);
        assert!(close(&alone, &want, 1e-9), "{alone:?} vs {want:?}");
        // A prior less sure than its information (the previous pose's error on top) widens it.
        let wider = weighed(&fit, &zero, &b, &p.map(|row| row.map(|v| 4.0 * v)));
        assert!((0..3).all(|k| wider[k][k] > want_diagonal(&fit, &b)[k]));
    }

    fn want_diagonal(fit: &Fit, b: &Matrix3) -> [f64; 3] {
        let c = crate::matcher::invert(&add(&fit.information, b)).expect("invertible");
        [c[0][0], c[1][1], c[2][2]]
    }

    /// Driving along x at 0.2 m/s while the wheel odometry slips once between scans 5 and 6
    /// (0.4 m sideways and 0.3 rad, then correct again): the poses the mapper reports, with
    /// the per-scan odometry gate at `poor_match_ratio`, and the true ones.
    fn through_a_slip(poor_match_ratio: f64) -> (Vec<ScanResult>, Vec<Pose2>) {
        let truth: Vec<Pose2> = (0..12)
            .map(|k| Pose2::new(-1.0 + 0.02 * f64::from(k), 0.1, 0.05))
            .collect();
        let slip = Pose2::new(0.0, 0.4, 0.3);
        let mut scans = scans(&truth);
        for (k, scan) in scans.iter_mut().enumerate() {
            let odometry = if k >= 6 {
                truth[k].compose(&slip)
            } else {
                truth[k]
            };
            scan.odometry = Some(odometry);
        }
        let mut config = MapperConfig::default();
        config.motion.poor_match_ratio = poor_match_ratio;
        let mut mapper = Mapper::new(config);
        let results = scans.iter().map(|s| mapper.add_scan(s)).collect();
        (results, truth)
    }

    /// Driving along x with scans logged `gaps[0]`, then `gaps[1]` apart, 0.05 m per scan
    /// (`per_scan`: a log that keeps a scan per distance travelled, stamped when written) or
    /// at 0.25 m/s (a lidar stamping each scan when it was taken): the largest translation
    /// error of the constant-velocity predictions (no odometry) by `clock` with the velocity
    /// taken over `window` seconds, once the scans span more than a second.
    fn worst_prediction_error(
        gaps: [f64; 2],
        per_scan: bool,
        window: f64,
        clock: VelocityClock,
    ) -> f64 {
        let times: Vec<f64> = (0..16)
            .scan(0.0, |time, k| {
                let stamp = *time;
                *time += gaps[k % 2];
                Some(stamp)
            })
            .collect();
        let truth: Vec<Pose2> = times
            .iter()
            .enumerate()
            .map(|(k, time)| {
                let x = if per_scan {
                    0.05 * k as f64
                } else {
                    0.25 * time
                };
                Pose2::new(-1.0 + x, 0.1, 0.05)
            })
            .collect();
        let mut scans = scans(&truth);
        for (scan, time) in scans.iter_mut().zip(&times) {
            scan.time = *time;
        }
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        config.motion.velocity_window = window;
        config.motion.velocity_clock = clock;
        let mut mapper = Mapper::new(config);
        let results: Vec<ScanResult> = scans.iter().map(|s| mapper.add_scan(s)).collect();
        (0..truth.len())
            .filter(|&k| times[k] > 1.0)
            .map(|k| {
                // The map's frame is the first scan's.
                let (p, t) = (&results[k].predicted, truth[0].between(&truth[k]));
                (p.x - t.x).hypot(p.y - t.y)
            })
            .fold(0.0, f64::max)
    }

    /// [`worst_prediction_error`] over a 0.5 s window by the clocks time, scans and auto.
    fn errors_by_clock(gaps: [f64; 2], per_scan: bool) -> (f64, f64, f64) {
        let error = |clock| worst_prediction_error(gaps, per_scan, 0.5, clock);
        (
            error(VelocityClock::Time),
            error(VelocityClock::Scans),
            error(VelocityClock::Auto),
        )
    }

    /// Scans logged in bursts, 0.01 s then 0.19 s apart, 0.05 m each (Intel's way).
    const BURSTS: [f64; 2] = [0.01, 0.19];

    /// Scans taken 0.05 s then 0.35 s apart (a lidar turning unevenly), their motion growing
    /// with the time between them: 0.0125 m, then 0.0875 m.
    const UNEVEN: [f64; 2] = [0.05, 0.35];

    /// Asserts that scan `k`'s pose is within 3 cm and 0.01 rad of `truth`.
    fn assert_within_3_cm_and_10_mrad(k: usize, pose: &Pose2, truth: &Pose2) {
        let error = (pose.x - truth.x).hypot(pose.y - truth.y);
        let heading = wrap_angle(pose.theta - truth.theta).abs();
        assert!(
            error < 0.03 && heading < 0.01,
            "scan {k}: {pose:?} against {truth:?}"
        );
    }

    /// Turning on the spot at 0.8 rad/s without odometry, with scan `repeated` logged again
    /// after scan 14 (as Intel's out-of-order laser lines are), the motion configured by
    /// `configure`: the results, the scan logged late among them at index 15, and the true
    /// poses of the scans in log order.
    fn through_a_late_scan(
        repeated: usize,
        configure: impl FnOnce(&mut MotionConfig),
    ) -> (Vec<ScanResult>, Vec<Pose2>) {
        let turning: Vec<Pose2> = (0..20)
            .map(|k| Pose2::new(-1.0, 0.1, 0.08 * f64::from(k)))
            .collect();
        let in_order = scans(&turning);
        let mut late = in_order[repeated].clone();
        late.time = in_order[14].time + 0.05;
        let mut logged = in_order[..15].to_vec();
        logged.push(late);
        logged.extend_from_slice(&in_order[15..]);
        let mut truth = turning[..15].to_vec();
        truth.push(turning[repeated]);
        truth.extend_from_slice(&turning[15..]);
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        configure(&mut config.motion);
        let mut mapper = Mapper::new(config);
        let results = logged.iter().map(|s| mapper.add_scan(s)).collect();
        (results, truth)
    }

    /// Asserts that every result is within 3 cm and 10 mrad of the truth (in the first
    /// scan's frame) and that only the scan at index 15 was set aside as out of order.
    fn assert_only_the_late_scan_set_aside(results: &[ScanResult], truth: &[Pose2]) {
        let start = truth[0];
        for (k, (result, truth)) in results.iter().zip(truth).enumerate() {
            // The map's frame is the first scan's.
            assert_within_3_cm_and_10_mrad(k, &result.pose, &start.between(truth));
            assert_eq!(result.out_of_order, k == 15, "scan {k}");
        }
        assert!(!results[15].integrated);
    }

    #[test]
    fn a_scan_logged_out_of_order_takes_its_earlier_pose_and_does_not_turn_the_map() {
        let (results, truth) = through_a_late_scan(6, |_| {});
        assert_only_the_late_scan_set_aside(&results, &truth);
        // Without the check the late scan is 0.72 rad from the prediction, beyond the window:
        // it is matched somewhere else, and taken.
        let (unchecked, truth) = through_a_late_scan(6, |m| m.out_of_order_poses = 0);
        assert!(unchecked.iter().all(|r| !r.out_of_order));
        let heading =
            wrap_angle(unchecked[15].pose.theta - truth[0].between(&truth[15]).theta).abs();
        assert!(heading > 0.1, "{:?}", unchecked[15].pose);
    }

    #[test]
    fn a_late_scan_that_fits_well_where_the_robot_was_is_set_aside_too() {
        // Scan 12 logged after scan 14 is 0.24 rad from the prediction: inside the window, it
        // matches well where it was taken, turned back against the turn.
        let (results, truth) = through_a_late_scan(12, |_| {});
        assert_only_the_late_scan_set_aside(&results, &truth);
        let turned_back = results[14].pose.theta - results[15].pose.theta;
        assert!((turned_back - 0.16).abs() < 0.01, "{turned_back}");
        // Without the rule it is matched as well, and taken as the newest pose in order.
        let (taken, _) = through_a_late_scan(12, |m| m.out_of_order_turn_back = 0.0);
        assert!(taken.iter().all(|r| !r.out_of_order));
        // A step against the predicted turn counts only when it lands nearer an earlier pose
        // than the last: a turn that stopped and swung back while driving on is followed.
        let mut mapper = Mapper::new(MapperConfig::default());
        let last = Pose2::new(0.1, 0.0, 0.1);
        mapper.remember(0.0, Pose2::default());
        mapper.remember(0.1, last);
        let predicted = last.compose(&Pose2::new(0.1, 0.0, 0.1));
        let swung = last.compose(&Pose2::new(0.15, 0.0, -0.1));
        assert!(!mapper.went_back(&last, &predicted, &swung));
        let returned = Pose2::new(0.01, 0.0, 0.0);
        assert!(mapper.went_back(&last, &predicted, &returned));
    }

    #[test]
    fn a_late_line_in_a_burst_is_looked_for_beside_the_one_set_aside_before_it() {
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        let mut mapper = Mapper::new(config);
        let mapped: Vec<Pose2> = (0..3)
            .map(|k| Pose2::new(-1.0, 0.1, 0.3 * f64::from(k)))
            .collect();
        for (scan, pose) in scans(&mapped).iter().zip(&mapped) {
            assert!(mapper.integrate_at(scan, pose));
        }
        // The robot has turned on to 1.5-2.4 rad; a line taken at 0.40 rad is logged now.
        for k in 0..4 {
            let heading = 1.5 + 0.3 * f64::from(k);
            mapper.remember(0.1 * f64::from(k), Pose2::new(-1.0, 0.1, heading));
        }
        let taken = Pose2::new(-1.0, 0.1, 0.40);
        let hits = cast(&room(), &taken, 720);
        let information = [[400.0, 0.0, 0.0], [0.0, 400.0, 0.0], [0.0, 0.0, 400.0]];
        let heading_error = |m: &Match| wrap_angle(m.pose.theta - taken.theta).abs();
        // From the recent poses alone it is not found: none is near where it was taken.
        let alone = mapper
            .earlier_match(&hits, &Pose2::default(), &information)
            .expect("recent poses to try");
        assert!(heading_error(&alone) > 0.3, "{:?}", alone.pose);
        // The line before it in the burst was set aside at 0.35 rad: this one is found there.
        mapper.set_aside.push(Pose2::new(-1.0, 0.1, 0.35));
        let beside = mapper
            .earlier_match(&hits, &Pose2::default(), &information)
            .expect("poses to try");
        assert!(heading_error(&beside) < 0.005, "{:?}", beside.pose);
        let off = (beside.pose.x - taken.x).hypot(beside.pose.y - taken.y);
        assert!(off < 0.03, "{off} {:?}", beside.pose);
        assert!(
            beside.score > alone.score + 0.2,
            "{} {}",
            beside.score,
            alone.score
        );
    }

    #[test]
    fn after_as_many_late_lines_as_allowed_a_scan_that_fits_where_the_robot_was_takes_it_back() {
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        let mut mapper = Mapper::new(config);
        let standing = Pose2::new(-1.0, 0.1, 0.3);
        let mapped = [Pose2::new(-1.0, 0.1, 0.0), standing];
        for (scan, pose) in scans(&mapped).iter().zip(&mapped) {
            assert!(mapper.integrate_at(scan, pose));
        }
        // The robot stood at `standing`, but the track in order went on to a wrong pose, beyond
        // the window around it; the last two scans were set aside at `standing`.
        mapper.start_at(0.0, standing, [[0.0; 3]; 3]);
        let wrong = Pose2::new(-0.5, 0.1, 0.9);
        mapper.remember(0.1, wrong);
        if let Some(last) = mapper.last.as_mut() {
            last.pose = wrong;
            last.time = 0.1;
        }
        mapper.recent_score = Some(0.8);
        mapper.set_aside = vec![standing; MAX_OUT_OF_ORDER_IN_A_ROW];
        let scan = Scan {
            time: 0.2,
            hits: cast(&room(), &standing, 720),
            ..Scan::default()
        };
        let result = mapper.add_scan(&scan);
        assert!(!result.out_of_order);
        assert_within_3_cm_and_10_mrad(0, &result.pose, &standing);
        let v = result.velocity;
        assert!(v.x == 0.0 && v.y == 0.0 && v.theta == 0.0, "{v:?}");
        // The next scan is predicted from there, standing.
        let next = Scan { time: 0.3, ..scan };
        let result = mapper.add_scan(&next);
        assert_within_3_cm_and_10_mrad(1, &result.predicted, &standing);
        assert_within_3_cm_and_10_mrad(1, &result.pose, &standing);
    }

    #[test]
    fn a_velocity_over_a_window_predicts_through_bursts_of_scans() {
        let error = |window| worst_prediction_error(BURSTS, true, window, VelocityClock::Time);
        let last_interval = error(0.0);
        let windowed = error(0.5);
        // After a burst, one interval's velocity is 5 m/s: a 0.19 s gap is predicted 0.25 m
        // (the ratio's cap) where the robot drove 0.05 m. Over 0.5 s it is 0.5 m/s: 0.095 m
        // over a gap, 0.005 m over a burst.
        assert!(last_interval > 0.15, "{last_interval}");
        assert!(windowed < 0.07, "{windowed}");
    }

    #[test]
    fn counting_scans_predicts_a_log_that_keeps_a_scan_per_distance() {
        // Each scan 0.05 m on: the scans' clock is right whatever the stamps say, time's is
        // off by up to 0.045 m (above); `auto` finds the better one from the matches.
        let (time, scans, auto) = errors_by_clock(BURSTS, true);
        assert!(time > 0.03, "{time}");
        assert!(scans < 0.01, "{scans}");
        assert!(auto < 0.01, "{auto}");
    }

    #[test]
    fn timing_predicts_a_lidar_that_stamps_its_scans_when_taken() {
        // The robot at 0.25 m/s and the scans 0.05 s or 0.35 s apart: time's clock is right,
        // the scans' predicts each step as the recent average, 0.05 m, off by up to 0.0375 m.
        let (time, scans, auto) = errors_by_clock(UNEVEN, false);
        assert!(time < 0.01, "{time}");
        assert!(scans > 0.025, "{scans}");
        assert!(auto < 0.01, "{auto}");
    }

    #[test]
    fn a_scan_without_odometry_joins_its_wall_across_wider_gaps() {
        // A wall 1 m ahead sampled every 0.5 m, as a far wall at a grazing angle is.
        let wall: Vec<(f64, f64)> = (-4..=4).map(|k| (0.5 * f64::from(k), 1.0)).collect();
        let between = |odometry: Option<Pose2>| {
            let mut mapper = Mapper::new(MapperConfig::default());
            let scan = Scan {
                hits: wall.clone(),
                odometry,
                ..Scan::default()
            };
            mapper.add_scan(&scan);
            let grid = mapper.map().finest();
            grid.probability(grid.cell_of(0.25, 1.0))
        };
        // Between two endpoints: joined (hit) without odometry, never seen with it.
        assert!(between(None) > 0.6, "{}", between(None));
        assert!(between(Some(Pose2::default())) <= 0.5);
    }

    /// Circling in the room (0.06 m and 0.1 rad a scan) on wheels that over-report every turn
    /// by 10 % and turn 0.1 rad per metre besides: the mean heading error of the last 100
    /// predictions, with the odometry's error learned over `window` steps (0: off).
    fn prediction_error_on_drifting_wheels(window: f64) -> f64 {
        let truth: Vec<Pose2> = (0..300)
            .map(|k| {
                let a = 0.1 * f64::from(k);
                Pose2::new(-1.0 + 0.6 * a.sin(), -0.5 - 0.6 * a.cos(), a)
            })
            .collect();
        let wheels = crate::odometry_bias::WheelError {
            per_rad: 0.1,
            per_m: 0.1,
            scale: 0.0,
        };
        let mut scans = scans(&truth);
        let mut odometry = truth[0];
        for (k, scan) in scans.iter_mut().enumerate() {
            if k > 0 {
                odometry = odometry.compose(&wheels.apply(&truth[k - 1].between(&truth[k])));
            }
            scan.odometry = Some(odometry);
        }
        let mut config = MapperConfig::default();
        config.motion.odometry_bias_window = window;
        let mut mapper = Mapper::new(config);
        let results: Vec<ScanResult> = scans.iter().map(|s| mapper.add_scan(s)).collect();
        let last = &results[200..];
        last.iter()
            .zip(&truth[200..])
            .map(|(r, t)| wrap_angle(r.predicted.theta - t.theta).abs())
            .sum::<f64>()
            / last.len() as f64
    }

    #[test]
    fn a_learned_odometry_error_corrects_the_prediction() {
        let off = prediction_error_on_drifting_wheels(0.0);
        let on = prediction_error_on_drifting_wheels(100.0);
        // Each step's odometry turns 16 mrad too far; learned, the prediction is within a few.
        assert!(off > 0.012, "without the correction: {off}");
        assert!(on < 0.004, "with it: {on}");
    }

    /// A new mapper with `config` fed `scans`; the last scan's result.
    fn last_result(config: MapperConfig, scans: &[Scan]) -> ScanResult {
        let mut mapper = Mapper::new(config);
        scans
            .iter()
            .map(|s| mapper.add_scan(s))
            .last()
            .expect("scans")
    }

    /// Standing, then one quick step of 0.3 m along x, then standing again, while the wheels
    /// slip 0.35 m further on that step: the last pose's error, with `wider_search`.
    fn after_a_long_slip(wider_search: f64) -> f64 {
        let truth: Vec<Pose2> = (0..12)
            .map(|k| Pose2::new(if k < 6 { -1.0 } else { -0.7 }, 0.1, 0.05))
            .collect();
        let mut scans = scans(&truth);
        for (k, scan) in scans.iter_mut().enumerate() {
            let slip = if k < 6 { 0.0 } else { 0.35 };
            scan.odometry = Some(truth[k].compose(&Pose2::new(slip, 0.0, 0.0)));
        }
        let mut config = MapperConfig::default();
        config.motion.wider_search = wider_search;
        let last = last_result(config, &scans);
        let truth = truth.last().expect("poses");
        (last.pose.x - truth.x).hypot(last.pose.y - truth.y)
    }

    /// Without odometry: the robot stands for five scans 0.1 s apart, then the next scan comes
    /// a second later, turned 0.6 rad and 0.1 m along (a log written less often than the robot
    /// turns); the error of that scan's pose with the window searched over `sigmas` of the
    /// prediction's standard deviations (0: the fixed ±0.35 rad), translation (m) plus heading
    /// (rad).
    fn after_a_turn_beyond_the_fixed_window(sigmas: f64) -> f64 {
        let mut truth = vec![Pose2::new(-0.5, 0.1, 0.05); 5];
        truth.push(Pose2::new(-0.4, 0.1, 0.65));
        let mut scans = scans(&truth);
        scans[5].time = 1.4;
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        config.motion.velocity_search.sigmas = sigmas;
        let last = last_result(config, &scans);
        // Without odometry the first scan's pose is the map's origin.
        let truth = truth[0].between(&truth[5]);
        (last.pose.x - truth.x).hypot(last.pose.y - truth.y)
            + wrap_angle(last.pose.theta - truth.theta).abs()
    }

    #[test]
    fn without_odometry_the_window_grows_with_the_time_since_the_last_scan() {
        // A second without a scan: the prediction's heading sigma is 1 rad (1 rad/s), and the
        // default window reaches one sigma.
        let grown =
            after_a_turn_beyond_the_fixed_window(MotionConfig::default().velocity_search.sigmas);
        assert!(grown < 0.01, "the window grown: {grown}");
        let fixed = after_a_turn_beyond_the_fixed_window(0.0);
        assert!(fixed > 0.1, "the fixed window: {fixed}");
    }

    #[test]
    fn a_slip_beyond_the_window_is_found_by_the_wider_search() {
        // The first window reaches 0.2 m from the odometry's prediction, the wider one 0.6 m.
        let wider = after_a_long_slip(MotionConfig::default().wider_search);
        assert!(wider < 0.03, "with the wider search: {wider}");
        let narrow = after_a_long_slip(1.0);
        assert!(narrow > 0.1, "without it: {narrow}");
    }

    #[test]
    fn a_slip_of_the_odometry_does_not_drag_the_matcher_off_the_map() {
        let (results, truth) = through_a_slip(MotionConfig::default().poor_match_ratio);
        for (k, (result, truth)) in results.iter().zip(&truth).enumerate() {
            assert_within_3_cm_and_10_mrad(k, &result.pose, truth);
        }
        // Without the gate the slipped odometry holds the match away from the map.
        let (ungated, truth) = through_a_slip(0.0);
        let last = ungated.last().expect("results").pose;
        let truth = truth.last().expect("poses");
        assert!(
            (last.x - truth.x).hypot(last.y - truth.y) > 0.1
                || wrap_angle(last.theta - truth.theta).abs() > 0.05,
            "{last:?}"
        );
    }

    #[test]
    fn a_heading_error_swings_a_pose_carried_along_a_lever() {
        // 0.01 rad of heading error at the origin, carried 2 m along x: 2 cm across, along y.
        let c = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1e-4]];
        let carried = carry(&c, &Pose2::default(), &Pose2::new(2.0, 0.0, 0.3));
        assert!((carried[1][1] - 4e-4).abs() < 1e-15 && carried[0][0] == 0.0);
        assert!((carried[1][2] - 2e-4).abs() < 1e-15 && (carried[2][2] - 1e-4).abs() < 1e-15);
    }

    #[test]
    fn a_lidar_ahead_of_the_turning_axis_moves_sideways_when_the_robot_turns_in_place() {
        // Turning in place at 1 rad/s, the lidar 0.1 m ahead (facing +x) moves at 0.1 m/s along
        // +y; the robot does not move.
        let robot = Pose2::default();
        let sensor = robot.compose(&Pose2::new(0.1, 0.0, 0.0));
        let v = robot_velocity(&[0.0, 0.1, 1.0], &sensor, &robot);
        assert!(
            v.x.abs() < 1e-15 && v.y.abs() < 1e-15 && v.theta == 1.0,
            "{v:?}"
        );
    }

    #[test]
    fn the_mapper_reports_the_velocity_and_a_covariance_that_the_prior_and_the_scan_share() {
        // Driving along x at 0.2 m/s, a scan every 0.1 s.
        let poses: Vec<Pose2> = (0..8)
            .map(|k| Pose2::new(-0.5 + 0.02 * f64::from(k), 0.1, 0.05))
            .collect();
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        let mut mapper = Mapper::new(config);
        let results: Vec<ScanResult> = scans(&poses).iter().map(|s| mapper.add_scan(s)).collect();
        assert_eq!(
            results[0].covariance, [[0.0; 3]; 3],
            "the first pose is the frame"
        );
        let last = results.last().expect("results");
        // The map frame is the first pose's: the motion is along its x.
        assert!(
            (last.velocity.x - 0.2).abs() < 0.02
                && last.velocity.y.abs() < 0.02
                && last.velocity.theta.abs() < 0.05,
            "{:?}",
            last.velocity
        );
        let (c, scan) = (last.covariance, last.scan_covariance.expect("matched"));
        // The reported pose is surer than the scan alone says, and no surer than the floor.
        let floor = config.covariance;
        for k in 0..3 {
            assert!(c[k][k] > 0.0 && c[k][k] < scan[k][k], "{c:?} vs {scan:?}");
        }
        assert!(scan[0][0] >= floor.translation_floor.powi(2));
        assert!(scan[2][2] >= floor.rotation_floor.powi(2));
    }

    #[test]
    fn a_rotation_prior_turns_the_prediction_and_narrows_the_heading() {
        let poses = [
            Pose2::new(0.0, 0.0, 0.0),
            Pose2::new(0.0, 0.0, 0.0),
            Pose2::new(0.0, 0.0, 0.12),
        ];
        let scans = scans(&poses);
        let mut config = MapperConfig::default();
        config.motion.use_odometry = false;
        let run = |rotation: Option<RotationPrior>| {
            let mut mapper = Mapper::new(config);
            mapper.add_scan(&scans[0]);
            mapper.add_scan(&scans[1]);
            mapper.add_scan(&Scan {
                rotation,
                ..scans[2].clone()
            })
        };
        let without = run(None);
        let gyro = RotationPrior {
            increment: 0.12,
            variance: 1e-6,
        };
        let with = run(Some(gyro));
        // Standing still, the constant-velocity model predicts no turn; the gyro says 0.12 rad.
        assert!(without.predicted.theta.abs() < 0.002, "{without:?}");
        assert!((with.predicted.theta - 0.12).abs() < 0.002, "{with:?}");
        assert!((with.pose.theta - 0.12).abs() < 0.002, "{with:?}");
        assert!(
            with.covariance[2][2] < without.covariance[2][2],
            "{:?} vs {:?}",
            with.covariance,
            without.covariance
        );
    }

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

    #[test]
    fn endpoints_beyond_the_range_limit_are_neither_matched_nor_integrated() {
        // The room's walls, and one far wall 8 m ahead seen by a revolution's beams.
        let mut hits = cast(&room(), &Pose2::default(), 720);
        let far: Vec<(f64, f64)> = (0..40).map(|i| (8.0, -1.0 + 0.05 * f64::from(i))).collect();
        hits.extend(&far);
        let hit_times: Vec<f64> = (0..hits.len()).map(|i| 1e-4 * i as f64).collect();
        let scan = Scan {
            time: 10.0,
            hits,
            hit_times,
            ..Scan::default()
        };
        let occupied = |mapper: &Mapper, (x, y): (f64, f64)| {
            let grid = mapper.map().finest();
            grid.probability(grid.cell_of(x, y)) > 0.5
        };
        for (max_range, far_wall) in [(5.0, false), (30.0, true)] {
            let mut mapper = Mapper::new(MapperConfig {
                max_range,
                ..MapperConfig::default()
            });
            let first = mapper.add_scan(&scan);
            // The pose is for the scan's reference time as given, far endpoints or not.
            assert_eq!(first.time, scan.reference_time());
            assert!(occupied(&mapper, (-3.0167, 0.0)), "the near wall is mapped");
            assert_eq!(
                occupied(&mapper, far[20]),
                far_wall,
                "max_range {max_range}"
            );
            let mut moved = scan.clone();
            moved.time += 0.1;
            let second = mapper.add_scan(&moved);
            assert_eq!(second.time, moved.reference_time());
            assert!(
                second.pose.x.hypot(second.pose.y) < 0.02,
                "{:?}",
                second.pose
            );
        }
    }

    #[test]
    fn with_a_gyro_a_shoved_trolley_is_found_by_the_search_and_keeps_the_gyros_heading() {
        // Along x at 0.2 m/s, a scan every 0.1 s, heading 0.05 rad; after the 8th scan the
        // trolley is shoved 0.25 m sideways, which no constant velocity predicts. The gyro says
        // (exactly) that it did not turn. The match from the prediction is poor there, and only
        // the window search finds the scan (without it, scan 8 is 0.13 m off).
        let truth: Vec<Pose2> = (0..16)
            .map(|k| {
                let shove = if k >= 8 { 0.25 } else { 0.0 };
                Pose2::new(-0.6 + 0.02 * f64::from(k), -0.1 + shove, 0.05)
            })
            .collect();
        let mut scans = scans(&truth);
        for scan in scans.iter_mut().skip(1) {
            scan.rotation = Some(RotationPrior {
                increment: 0.0,
                variance: 1e-8,
            });
        }
        let mut mapper = Mapper::new(MapperConfig {
            motion: MotionConfig {
                use_odometry: false,
                ..MotionConfig::default()
            },
            ..MapperConfig::default()
        });
        // The first scan defines the map frame.
        let origin = truth[0];
        for (k, (scan, truth)) in scans.iter().zip(&truth).enumerate() {
            let pose = mapper.add_scan(scan).pose;
            let truth = origin.between(truth);
            let error = (pose.x - truth.x).hypot(pose.y - truth.y);
            let heading = wrap_angle(pose.theta - truth.theta).abs();
            assert!(
                error < 0.02 && heading < 0.002,
                "scan {k}: {pose:?} against {truth:?}"
            );
        }
    }

    /// The room mapped first by `drifted` scans of a pass that drifted (placed 0.12 m off along
    /// x and y), then by `honest` scans at their true poses; then one scan taken at
    /// (0.3, −0.3, 0.2) and predicted there. Returns the mapper and the match's pose.
    fn after_a_drifted_pass(
        submap: SubmapConfig,
        drifted: usize,
        honest: usize,
    ) -> (Mapper, Pose2) {
        let mut mapper = Mapper::new(MapperConfig {
            submap,
            motion: MotionConfig {
                use_odometry: false,
                ..MotionConfig::default()
            },
            ..MapperConfig::default()
        });
        let drift = Pose2::new(0.12, 0.12, 0.0);
        let poses: Vec<Pose2> = (0..6)
            .map(|k| Pose2::new(-1.5 + 0.5 * f64::from(k), -0.5, 0.2))
            .collect();
        for (scan, pose) in scans(&poses).iter().zip(&poses).cycle().take(drifted) {
            assert!(mapper.integrate_at(scan, &drift.compose(pose)));
        }
        for (scan, pose) in scans(&poses).iter().zip(&poses).take(honest) {
            assert!(mapper.integrate_at(scan, pose));
        }
        let truth = Pose2::new(0.3, -0.3, 0.2);
        mapper.start_at(
            0.0,
            truth,
            [[1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
        );
        let mut scan = scans(&[truth]).remove(0);
        scan.time = 0.1;
        (mapper.clone(), mapper.add_scan(&scan).pose)
    }

    /// The robot drives along the room at 0–2.5 s, then (its map since holding the same walls
    /// integrated 0.5 m and 2° off, seen more often: a drifted pass) is back at 100 s, its
    /// odometry and its pose carrying that drift. Returns each pose of the return's scans
    /// minus the truth's (translation, m) and whether the scan re-entered.
    fn back_after_a_drifted_loop(reentry: ReentryConfig) -> Vec<(f64, bool)> {
        let mut mapper = Mapper::new(MapperConfig {
            reentry,
            ..MapperConfig::default()
        });
        let first: Vec<Pose2> = (0..26)
            .map(|k| Pose2::new(-1.5 + 0.1 * f64::from(k), -0.5, 0.2))
            .collect();
        for (scan, pose) in scans(&first).iter().zip(&first) {
            let scan = Scan {
                odometry: Some(*pose),
                ..scan.clone()
            };
            mapper.add_scan(&scan);
        }
        let drift = Pose2::new(0.5, 0.3, 0.035);
        for _ in 0..3 {
            for (scan, pose) in scans(&first).iter().zip(&first).step_by(4) {
                assert!(mapper.integrate_at(scan, &drift.compose(pose)));
            }
        }
        let back: Vec<Pose2> = (0..20)
            .map(|k| Pose2::new(0.8 - 0.1 * f64::from(k), -0.3, 0.25))
            .collect();
        mapper.start_at(
            99.9,
            drift.compose(&back[0]),
            [[1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
        );
        scans(&back)
            .iter()
            .zip(&back)
            .map(|(scan, truth)| {
                let scan = Scan {
                    time: 100.0 + scan.time,
                    odometry: Some(drift.compose(truth)),
                    ..scan.clone()
                };
                let result = mapper.add_scan(&scan);
                let off = (result.pose.x - truth.x).hypot(result.pose.y - truth.y);
                (off, result.reentered)
            })
            .collect()
    }

    #[test]
    fn a_robot_back_after_a_drifted_loop_moves_onto_the_old_map() {
        let returned = back_after_a_drifted_loop(ReentryConfig::default());
        let reentries = returned.iter().filter(|(_, r)| *r).count();
        assert_eq!(reentries, 1, "{returned:?}");
        // Before it, the drifted map holds the robot where the drift put it; from it on, the
        // old map does.
        let at = returned.iter().position(|(_, r)| *r).unwrap();
        assert!(
            returned[..at].iter().all(|(off, _)| *off > 0.4),
            "{returned:?}"
        );
        assert!(
            returned[at..].iter().all(|(off, _)| *off < 0.03),
            "{returned:?}"
        );
        // Without the check it stays in the drifted map.
        let stayed = back_after_a_drifted_loop(ReentryConfig {
            enabled: false,
            ..ReentryConfig::default()
        });
        assert!(stayed.iter().all(|(off, r)| *off > 0.4 && !r), "{stayed:?}");
    }

    #[test]
    fn a_scan_is_matched_against_the_recent_submap_not_an_earlier_drifted_pass() {
        let truth = Pose2::new(0.3, -0.3, 0.2);
        let off = |pose: Pose2| (pose.x - truth.x).hypot(pose.y - truth.y);
        // Against the whole map, the drifted pass's walls, seen four times as often as the true
        // ones, take the scan to their place (0.17 m off).
        let (_, whole) = after_a_drifted_pass(SubmapConfig { scans: 0 }, 12, 3);
        assert!(off(whole) > 0.1, "{whole:?}");
        // With submaps of 3 scans, the drifted ones are in finished submaps, dropped from
        // matching (the whole map keeps them): the scan meets only the three true ones.
        let (mapper, local) = after_a_drifted_pass(SubmapConfig { scans: 3 }, 12, 3);
        assert!(off(local) < 0.01, "{local:?}");
        let drifted_wall = (2.9833 + 0.12, 0.0);
        let occupied = |grid: &crate::grid::Grid| {
            grid.probability(grid.cell_of(drifted_wall.0, drifted_wall.1)) > 0.5
        };
        assert!(occupied(mapper.map().finest()));
        assert!(!occupied(mapper.matching_map().finest()));
    }
}
