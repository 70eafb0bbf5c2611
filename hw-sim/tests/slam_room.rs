//! The slam mapper in the simulated conference room, scored against the simulator's ground truth
//! (issue 12, part 5).
//!
//! A trolley pushed once around the table (straights at 0.4 m/s, corners at 0.5 rad/s, starting
//! and ending at rest) carries an RPLidar 0.4 m above the floor, so each revolution is a
//! horizontal slice of [`World::conference_room`]: walls, the glass wall (random returns), the
//! doorway and its open leaf, table legs, chairs and boxes. Every beam is measured at its own time
//! from the pose the trolley has then, at the emulator's sample period and rotation rate, turning
//! clockwise like the real lidar. A revolution becomes one [`Scan`] stamped at its last beam
//! (`Scan::time` is the revolution's end, every `hit_times` ≤ 0, as the server stamps them; the
//! other stamp is tested too). The mapper returns each revolution's pose for the middle of its
//! beams ([`ScanResult::time`](scan3d_slam::mapper::ScanResult::time)), and the truth is taken
//! at that time.
//!
//! The mapper starts at the identity, so the truth is expressed relative to the true pose at the
//! first result's time; the error of a scan is the distance and the heading difference between
//! its pose and the truth.
//! Besides the mapper's own de-skew, a run can give it no beam times (no de-skew) or endpoints
//! already moved with the true motion (a perfect de-skew), which separates the de-skew's share of
//! the error from the matcher's.

use std::f64::consts::{FRAC_PI_2, TAU};
use std::sync::Arc;

use nalgebra::{Isometry3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use scan3d_hw_sim::mounts::RPLIDAR_POSITION_M;
use scan3d_hw_sim::noise::RangeNoise;
use scan3d_hw_sim::rplidar::{MAX_RANGE_M, MIN_RANGE_M, RplidarEmulatorConfig};
use scan3d_hw_sim::world::{Scanner, World};
use scan3d_slam::mapper::{Mapper, MapperConfig, MotionConfig, Scan};
use scan3d_slam::pose::{Pose2, wrap_angle};

/// Where the lidar sits on the trolley: 10 cm ahead of the point the trolley turns about.
const SENSOR_OFFSET: Pose2 = Pose2 {
    x: 0.10,
    y: 0.0,
    theta: 0.0,
};

/// Where the trolley starts: south of the table, facing east (+x), clear of every piece of
/// furniture by at least 0.3 m along the whole loop. Not on the 5 cm lattice the room is drawn on,
/// so the map's cells do not line up with the walls by construction (see [`FINE_RESOLUTION`]).
const START: Pose2 = Pose2 {
    x: 1.513,
    y: 1.037,
    theta: 0.0,
};

/// The trolley's speed (m/s) and turn rate (rad/s), linear between keyframes.
struct Drive {
    /// `(t s, v m/s, ω rad/s)`, times increasing.
    keyframes: Vec<(f64, f64, f64)>,
}

impl Drive {
    /// Once around the table counter-clockwise: 1 s at rest, speed up to 0.4 m/s, four straights
    /// (4.0, 2.8, 4.0, 2.8 m) joined by left turns of 90° taken at 0.3 m/s and `turn_rate`
    /// (reached and left over 0.5 s), then slow to a stop and rest 1 s.
    fn around_the_table(turn_rate: f64) -> Self {
        const CRUISE: f64 = 0.4;
        const CORNER: f64 = 0.3;
        const RAMP: f64 = 0.5;
        let mut keyframes = vec![(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, CRUISE, 0.0)];
        let mut t = 2.0;
        for (n, straight) in [4.0, 2.8, 4.0, 2.8].into_iter().enumerate() {
            // The first straight includes the 0.2 m covered while speeding up.
            t += if n == 0 { straight - 0.2 } else { straight } / CRUISE;
            keyframes.push((t, CRUISE, 0.0));
            // The two ramps turn turn_rate · RAMP together; the hold turns the rest of 90°.
            let hold = FRAC_PI_2 / turn_rate - RAMP;
            assert!(
                hold >= 0.0,
                "turn rate {turn_rate} too high for a {RAMP} s ramp"
            );
            t += RAMP;
            keyframes.push((t, CORNER, turn_rate));
            t += hold;
            keyframes.push((t, CORNER, turn_rate));
            t += RAMP;
            keyframes.push((t, CRUISE, 0.0));
        }
        keyframes.push((t + 1.0, 0.0, 0.0));
        keyframes.push((t + 2.0, 0.0, 0.0));
        Self { keyframes }
    }

    /// Standing still for `seconds`.
    fn standing(seconds: f64) -> Self {
        Self {
            keyframes: vec![(0.0, 0.0, 0.0), (seconds, 0.0, 0.0)],
        }
    }

    /// 1 s at rest, 1.2 m east at up to 0.3 m/s (speeding up and slowing down over 1 s),
    /// then standing for `seconds` from [`MOVING_UNTIL`] on: the map was not made where the head
    /// stands.
    fn moving_then_standing(seconds: f64) -> Self {
        Self {
            keyframes: vec![
                (0.0, 0.0, 0.0),
                (1.0, 0.0, 0.0),
                (2.0, 0.3, 0.0),
                (5.0, 0.3, 0.0),
                (MOVING_UNTIL, 0.0, 0.0),
                (MOVING_UNTIL + seconds, 0.0, 0.0),
            ],
        }
    }

    fn duration(&self) -> f64 {
        self.keyframes.last().map_or(0.0, |k| k.0)
    }

    /// Speed and turn rate at `t`.
    fn at(&self, t: f64) -> (f64, f64) {
        for pair in self.keyframes.windows(2) {
            let ((t0, v0, w0), (t1, v1, w1)) = (pair[0], pair[1]);
            if t <= t1 {
                let f = if t1 > t0 {
                    ((t - t0) / (t1 - t0)).clamp(0.0, 1.0)
                } else {
                    1.0
                };
                return (v0 + f * (v1 - v0), w0 + f * (w1 - w0));
            }
        }
        (0.0, 0.0)
    }

    /// The true trolley poses at `k · period` for every k up to the drive's end (midpoint
    /// integration of the unicycle; this table *is* the ground truth, so its integration error is
    /// no error).
    fn poses(&self, start: Pose2, period: f64) -> Vec<Pose2> {
        let steps = (self.duration() / period).floor() as usize;
        let mut poses = Vec::with_capacity(steps + 1);
        let (mut x, mut y, mut theta) = (start.x, start.y, start.theta);
        poses.push(start);
        for k in 0..steps {
            let (v, w) = self.at((k as f64 + 0.5) * period);
            let mid = theta + 0.5 * w * period;
            x += v * period * mid.cos();
            y += v * period * mid.sin();
            theta += w * period;
            poses.push(Pose2::new(x, y, theta));
        }
        poses
    }
}

/// When [`Drive::moving_then_standing`] stops (s).
const MOVING_UNTIL: f64 = 6.0;

/// Which beam's time a revolution is stamped with.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Stamp {
    /// `Scan::time` is the revolution's last beam; `hit_times` ≤ 0.
    RevolutionEnd,
    /// `Scan::time` is the revolution's first beam; `hit_times` ≥ 0.
    RevolutionStart,
}

/// Who de-skews a revolution.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Deskew {
    /// The mapper, from the beams' `hit_times`.
    Mapper,
    /// Nobody: empty `hit_times`, every beam taken as if at `Scan::time`.
    None,
    /// The ground truth: each endpoint moved with the true motion into the sensor frame at
    /// `Scan::time` (empty `hit_times`), the best any de-skew can do.
    Truth,
}

/// Where the trolley goes.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Path {
    /// [`Drive::around_the_table`] at the run's turn rate.
    AroundTheTable,
    /// [`Drive::standing`] for this many seconds.
    Standing(f64),
    /// [`Drive::moving_then_standing`] for this many seconds of standing.
    MovingThenStanding(f64),
}

/// One simulated run: what the lidar and the trolley are like, and how the mapper is fed.
#[derive(Debug, Clone, Copy)]
struct Run {
    noise: RangeNoise,
    path: Path,
    turn_rate: f64,
    /// The lidar's revolutions per second.
    rotation_hz: f64,
    stamp: Stamp,
    deskew: Deskew,
    /// Wheel odometry with drift and noise (`None`: no odometry, constant-velocity prior).
    odometry: Option<OdometryError>,
    config: MapperConfig,
    /// Where the trolley starts.
    start: Pose2,
    seed: u64,
}

impl Run {
    /// The trolley as it is: no odometry, pushed at ≤ 0.5 rad/s, revolutions stamped at their end,
    /// default mapper configuration but for `use_odometry`.
    fn trolley(noise: RangeNoise) -> Self {
        Self {
            noise,
            path: Path::AroundTheTable,
            turn_rate: 0.5,
            rotation_hz: RplidarEmulatorConfig::default().rotation_hz,
            stamp: Stamp::RevolutionEnd,
            deskew: Deskew::Mapper,
            odometry: None,
            // A trolley at walking pace in an 8 × 6 m room integrates every 10 cm / 0.1 rad:
            // with the benchmark logs' 0.4 m / 0.9 rad (the defaults) the noise-free heading
            // error reaches 0.89° instead of 0.56°, the map being too sparse between updates.
            config: MapperConfig {
                motion: MotionConfig {
                    use_odometry: false,
                    ..MotionConfig::default()
                },
                map_update_distance: 0.1,
                map_update_angle: 0.1,
                ..MapperConfig::default()
            },
            start: START,
            seed: 12,
        }
    }
}

/// Wheel odometry's error: a systematic scale error (wheel radius, track width) and Gaussian noise
/// per scan interval.
#[derive(Debug, Clone, Copy)]
struct OdometryError {
    translation_scale: f64,
    rotation_scale: f64,
    /// Standard deviation per metre travelled (m).
    translation_sigma_per_m: f64,
    /// Standard deviation per radian turned (rad).
    rotation_sigma_per_rad: f64,
}

/// A run's revolutions as the mapper gets them, and the true trolley poses every `period`
/// seconds from time 0.
struct Simulated {
    revolutions: Vec<Scan>,
    truth: Vec<Pose2>,
    period: f64,
}

impl Simulated {
    /// The true pose at `time` (the nearest sample: a sample period is 0.5 ms).
    fn truth_at(&self, time: f64) -> Pose2 {
        let k = (time / self.period).round().max(0.0) as usize;
        self.truth[k.min(self.truth.len() - 1)]
    }
}

/// One revolution of the rotor: its first and last sample index, and the beams that returned
/// (sample index, endpoint in the sensor frame).
struct Turn {
    first: usize,
    last: usize,
    beams: Vec<(usize, (f64, f64))>,
}

/// The isometry of a pose in the horizontal plane at `height`.
fn isometry(pose: &Pose2, height: f64) -> Isometry3<f64> {
    Isometry3::new(
        Vector3::new(pose.x, pose.y, height),
        Vector3::z() * pose.theta,
    )
}

/// Simulates the lidar along the trolley's `truth` (poses every `period` seconds, one beam each):
/// the rotor turns clockwise at `hz`, a beam at device angle φ looks along azimuth −φ in the sensor
/// frame, and a revolution ends where the rotor angle wraps. The last, incomplete revolution is
/// dropped.
fn revolutions(
    truth: &[Pose2],
    period: f64,
    hz: f64,
    scanner: &Scanner,
    run: &Run,
    rng: &mut ChaCha8Rng,
) -> Vec<Scan> {
    let height = RPLIDAR_POSITION_M[2];
    let mut turns: Vec<Turn> = Vec::new();
    for (k, pose) in truth.iter().enumerate() {
        let phase = k as f64 * period * hz;
        let azimuth = -phase.fract() * TAU;
        if turns.len() <= phase.floor() as usize {
            turns.push(Turn {
                first: k,
                last: k,
                beams: Vec::new(),
            });
        }
        let turn = turns.last_mut().expect("pushed");
        turn.last = k;
        let sensor = isometry(&pose.compose(&SENSOR_OFFSET), height);
        if let Some(range) = scanner.measure_from(&sensor, azimuth, rng) {
            turn.beams
                .push((k, (range * azimuth.cos(), range * azimuth.sin())));
        }
    }
    // The last revolution is complete only if the rotor wrapped right after it.
    let complete = ((truth.len() as f64) * period * hz).floor() as usize;
    turns.truncate(complete);

    let mut odometry_rng = ChaCha8Rng::seed_from_u64(run.seed ^ 0x0d0);
    let mut odometry = Pose2::default();
    let mut previous_truth: Option<Pose2> = None;
    let mut out = Vec::with_capacity(turns.len());
    for turn in turns {
        let stamp = match run.stamp {
            Stamp::RevolutionEnd => turn.last,
            Stamp::RevolutionStart => turn.first,
        };
        let hits = turn.beams;
        let time = stamp as f64 * period;
        let here = truth[stamp];
        let odometry = run.odometry.map(|error| {
            if let Some(before) = previous_truth {
                let step = noisy_step(&before.between(&here), &error, &mut odometry_rng);
                odometry = odometry.compose(&step);
            }
            odometry
        });
        previous_truth = Some(here);
        let hit_times = match run.deskew {
            Deskew::Mapper => hits
                .iter()
                .map(|&(k, _)| k as f64 * period - time)
                .collect(),
            Deskew::None | Deskew::Truth => Vec::new(),
        };
        let hits = match run.deskew {
            Deskew::Mapper | Deskew::None => hits.into_iter().map(|(_, p)| p).collect(),
            Deskew::Truth => {
                let to_stamp = here.compose(&SENSOR_OFFSET).inverse();
                hits.into_iter()
                    .map(|(k, (x, y))| {
                        let (wx, wy) = truth[k].compose(&SENSOR_OFFSET).transform_point(x, y);
                        to_stamp.transform_point(wx, wy)
                    })
                    .collect()
            }
        };
        out.push(Scan {
            time,
            hits,
            hit_times,
            odometry,
            sensor_offset: SENSOR_OFFSET,
            rotation: None,
        });
    }
    out
}

/// A true motion as wheel odometry would have measured it.
fn noisy_step(step: &Pose2, error: &OdometryError, rng: &mut ChaCha8Rng) -> Pose2 {
    let distance = step.x.hypot(step.y);
    let mut draw = |sigma: f64| {
        if sigma > 0.0 {
            Normal::new(0.0, sigma)
                .expect("a positive sigma")
                .sample(rng)
        } else {
            0.0
        }
    };
    let tx = draw(error.translation_sigma_per_m * distance);
    let ty = draw(error.translation_sigma_per_m * distance);
    let tr = draw(error.rotation_sigma_per_rad * step.theta.abs());
    Pose2::new(
        step.x * error.translation_scale + tx,
        step.y * error.translation_scale + ty,
        step.theta * error.rotation_scale + tr,
    )
}

/// Trajectory error over all scans of a run.
#[derive(Debug, Clone, Copy)]
struct Errors {
    scans: usize,
    max_translation: f64,
    rms_translation: f64,
    max_rotation: f64,
    rms_rotation: f64,
}

impl std::fmt::Display for Errors {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} scans: translation max {:.1} mm, RMS {:.1} mm; rotation max {:.3}°, RMS {:.3}°",
            self.scans,
            self.max_translation * 1e3,
            self.rms_translation * 1e3,
            self.max_rotation.to_degrees(),
            self.rms_rotation.to_degrees()
        )
    }
}

/// The revolutions `run` produces, with their ground truth.
fn simulate(run: &Run) -> Simulated {
    let lidar = RplidarEmulatorConfig::default();
    let period = f64::from(lidar.standard_sample_us) * 1e-6;
    let drive = match run.path {
        Path::AroundTheTable => Drive::around_the_table(run.turn_rate),
        Path::Standing(seconds) => Drive::standing(seconds),
        Path::MovingThenStanding(seconds) => Drive::moving_then_standing(seconds),
    };
    let truth = drive.poses(run.start, period);
    let scanner = Scanner {
        world: Arc::new(World::conference_room()),
        pose: isometry(&run.start, RPLIDAR_POSITION_M[2]),
        noise: run.noise,
        min_range_m: MIN_RANGE_M,
        max_range_m: MAX_RANGE_M,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(run.seed);
    let revolutions = revolutions(&truth, period, run.rotation_hz, &scanner, run, &mut rng);
    assert!(revolutions.len() > 200, "{} revolutions", revolutions.len());
    Simulated {
        revolutions,
        truth,
        period,
    }
}

/// Simulates `run`, feeds every revolution to a fresh mapper and scores its poses.
fn score(run: &Run) -> Errors {
    let simulated = simulate(run);
    let revolutions = &simulated.revolutions;

    let mut mapper = Mapper::new(run.config);
    let mut origin = None;
    let (mut sum_t, mut sum_r) = (0.0, 0.0);
    let (mut max_t, mut max_r) = (0.0f64, 0.0f64);
    for revolution in revolutions {
        let result = mapper.add_scan(revolution);
        let found = result.pose;
        let truth = simulated.truth_at(result.time);
        let want = origin.get_or_insert(truth).between(&truth);
        let t = (found.x - want.x).hypot(found.y - want.y);
        let r = wrap_angle(found.theta - want.theta).abs();
        sum_t += t * t;
        sum_r += r * r;
        max_t = max_t.max(t);
        max_r = max_r.max(r);
    }
    assert_eq!(mapper.refused_integrations(), 0);
    let n = revolutions.len() as f64;
    Errors {
        scans: revolutions.len(),
        max_translation: max_t,
        rms_translation: (sum_t / n).sqrt(),
        max_rotation: max_r,
        rms_rotation: (sum_r / n).sqrt(),
    }
}

/// The finest cell size the noise-free tests map with (m). The default 5 cm grid stores a wall
/// at the centre of the cell its endpoints fall in, up to half a cell (2.5 cm) from the true face;
/// this room's walls all lie on one 5 cm lattice, so that quantisation does not average out over
/// walls and shifts the whole trajectory (17 mm RMS from this start, 35 mm when the walls fall on
/// cell boundaries). A 1 cm bound needs finer cells.
const FINE_RESOLUTION: f64 = 0.025;

/// The trolley without odometry, noise-free beams, on the fine grid.
fn noise_free() -> Run {
    let mut run = Run::trolley(RangeNoise::NONE);
    run.config.resolution = FINE_RESOLUTION;
    run
}

#[test]
fn noise_free_beams_give_every_pose_within_1_cm_and_0_2_degrees() {
    let errors = score(&noise_free());
    println!("noise-free, de-skewed, {FINE_RESOLUTION} m cells: {errors}");
    assert!(errors.max_translation <= 0.01, "{errors}");
    assert!(errors.rms_rotation <= 0.2f64.to_radians(), "{errors}");
    assert!(errors.max_rotation <= 0.2f64.to_radians(), "{errors}");
}

#[test]
fn the_sub_cell_refinement_halves_the_error_under_rplidar_noise() {
    // The grid stores a noisy wall at the centre of whichever cell most of its endpoints fell in;
    // the refinement matches against the mean of those endpoints.
    let refined = score(&Run::trolley(RangeNoise::RPLIDAR));
    let mut run = Run::trolley(RangeNoise::RPLIDAR);
    run.config.refine.enabled = false;
    let grid_only = score(&run);
    println!("RPLidar noise, refined: {refined}\nRPLidar noise, grid match only: {grid_only}");
    assert!(
        refined.rms_translation <= 0.6 * grid_only.rms_translation,
        "{refined} vs {grid_only}"
    );
    assert!(
        refined.max_translation <= 0.8 * grid_only.max_translation,
        "{refined} vs {grid_only}"
    );
}

#[test]
fn rplidar_range_noise_keeps_the_trajectory_within_3_cm_with_the_default_configuration() {
    let errors = score(&Run::trolley(RangeNoise::RPLIDAR));
    println!("RPLidar noise, de-skewed, default configuration: {errors}");
    assert!(errors.max_translation <= 0.03, "{errors}");
    assert!(errors.rms_translation <= 0.015, "{errors}");
    assert!(errors.max_rotation <= 0.6f64.to_radians(), "{errors}");
}

#[test]
fn without_de_skew_the_same_run_is_several_times_worse() {
    let with = score(&noise_free());
    let without = score(&Run {
        deskew: Deskew::None,
        ..noise_free()
    });
    println!("noise-free, de-skewed: {with}\nnoise-free, not de-skewed: {without}");
    assert!(
        without.max_translation >= 3.0 * with.max_translation,
        "{with} vs {without}"
    );
    assert!(
        without.rms_translation >= 3.0 * with.rms_translation,
        "{with} vs {without}"
    );
    assert!(
        without.rms_rotation >= 3.0 * with.rms_rotation,
        "{with} vs {without}"
    );
}

#[test]
fn where_a_revolution_is_stamped_does_not_change_its_pose() {
    // The mapper matches a revolution at the middle of its beams whatever its stamp: stamped at
    // its first beam instead of its last, every pose is the same.
    let end = score(&noise_free());
    let start = score(&Run {
        stamp: Stamp::RevolutionStart,
        ..noise_free()
    });
    println!("stamped at the end: {end}\nstamped at the start: {start}");
    assert!(
        (start.max_translation - end.max_translation).abs() < 1e-6
            && (start.rms_translation - end.rms_translation).abs() < 1e-6,
        "{end} vs {start}"
    );
    assert!(
        (start.max_rotation - end.max_rotation).abs() < 1e-6
            && (start.rms_rotation - end.rms_rotation).abs() < 1e-6,
        "{end} vs {start}"
    );
}

#[test]
fn drifting_wheel_odometry_as_the_prior_keeps_noise_free_beams_within_1_cm() {
    let mut run = noise_free();
    run.config.motion.use_odometry = true;
    run.odometry = Some(OdometryError {
        translation_scale: 1.02,
        rotation_scale: 0.98,
        translation_sigma_per_m: 0.02,
        rotation_sigma_per_rad: 0.02,
    });
    let errors = score(&run);
    println!("noise-free, de-skewed, odometry prior: {errors}");
    assert!(errors.max_translation <= 0.01, "{errors}");
    assert!(errors.rms_rotation <= 0.2f64.to_radians(), "{errors}");
}

#[test]
fn with_a_perfect_de_skew_noise_free_beams_give_every_pose_within_1_cm_and_0_2_degrees() {
    // The matcher meets the bounds at every scan when it is given each beam where it was
    // seen from; what the mapper's own de-skew adds is measured by the next test.
    let perfect = score(&Run {
        deskew: Deskew::Truth,
        ..noise_free()
    });
    println!("de-skewed with the true motion: {perfect}");
    assert!(perfect.max_translation <= 0.005, "{perfect}");
    assert!(perfect.max_rotation <= 0.2f64.to_radians(), "{perfect}");
}

#[test]
fn the_mappers_de_skew_places_the_trolley_within_a_few_millimetres_of_a_perfect_de_skew() {
    let mapper = score(&noise_free());
    let perfect = score(&Run {
        deskew: Deskew::Truth,
        ..noise_free()
    });
    println!("de-skewed by the mapper: {mapper}\nde-skewed with the true motion: {perfect}");
    assert!(
        mapper.max_translation <= perfect.max_translation + 0.005,
        "{mapper} vs {perfect}"
    );
    assert!(
        mapper.rms_translation <= perfect.rms_translation + 0.0025,
        "{mapper} vs {perfect}"
    );
    // What is left of the heading error is the de-skew's: one velocity over a revolution while
    // the turn rate ramps up or down at a corner.
    assert!(
        mapper.rms_rotation <= perfect.rms_rotation + 0.15f64.to_radians(),
        "{mapper} vs {perfect}"
    );
}

/// How a run's reported covariances compare with its errors: the normalised estimation error
/// squared eᵀ C⁻¹ e of each revolution's pose against the truth (3 degrees of freedom: its mean
/// is 3 when the covariance is right), averaged over the run, and per component eᵢ² / Cᵢᵢ.
#[derive(Debug, Clone, Copy)]
struct Nees {
    scans: usize,
    mean: f64,
    x: f64,
    y: f64,
    theta: f64,
    rms_translation: f64,
    rms_rotation: f64,
    /// What the covariances say those RMS should be: √(mean of Cxx + Cyy) and √(mean Cθθ).
    sigma_translation: f64,
    sigma_rotation: f64,
}

impl std::fmt::Display for Nees {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} scans: NEES {:.2} (x {:.2}, y {:.2}, θ {:.2}); error RMS {:.1} mm, {:.3}°, \
             reported {:.1} mm, {:.3}°",
            self.scans,
            self.mean,
            self.x,
            self.y,
            self.theta,
            self.rms_translation * 1e3,
            self.rms_rotation.to_degrees(),
            self.sigma_translation * 1e3,
            self.sigma_rotation.to_degrees()
        )
    }
}

/// The inverse of a symmetric positive definite 3×3 matrix.
fn inverse(m: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let m = nalgebra::Matrix3::from_fn(|i, j| m[i][j]);
    let inv = m.try_inverse().expect("a positive definite covariance");
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| inv[(i, j)]))
}

/// Which of a scan's estimates a NEES is of.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Estimate {
    /// Each revolution's own match and its covariance (`ScanResult::matched`,
    /// `ScanResult::match_covariance`): what the calibration is of.
    Match,
    /// The reported pose and covariance (`ScanResult::pose`, `ScanResult::covariance`): the
    /// match, or a standing head's held mean.
    Reported,
}

/// Localises `run`'s revolutions in a map built from the true poses, so that the error of each
/// pose is its match's alone (no drift), and scores the reported covariances against it.
///
/// The map: the same path with another draw of the noise, each revolution de-skewed with the
/// true motion and integrated at its true pose whenever the trolley has moved 10 cm or turned
/// 0.1 rad since the last one (the trolley's rule, so the map is as dense as a live one). Then a
/// mapper that does not integrate starts at the true pose of `run`'s first revolution and matches
/// every following one as it would live (de-skewed by itself, constant-velocity prior); its
/// frame is the room's.
fn nees(run: &Run, which: Estimate) -> Nees {
    let config = MapperConfig {
        map_update_distance: f64::INFINITY,
        map_update_angle: f64::INFINITY,
        ..run.config
    };
    let mut mapper = Mapper::new(config);
    let drawn = simulate(&Run {
        deskew: Deskew::Truth,
        seed: run.seed ^ 0x5eed_0fa9,
        ..*run
    });
    let mut integrated: Option<Pose2> = None;
    for revolution in &drawn.revolutions {
        let truth = drawn.truth_at(revolution.time);
        let due = integrated.is_none_or(|at| {
            (truth.x - at.x).hypot(truth.y - at.y) >= run.config.map_update_distance
                || wrap_angle(truth.theta - at.theta).abs() >= run.config.map_update_angle
        });
        if due {
            assert!(mapper.integrate_at(revolution, &truth));
            integrated = Some(truth);
        }
    }

    let simulated = simulate(run);
    let (first, rest) = simulated.revolutions.split_first().expect("revolutions");
    let time = first.reference_time();
    mapper.start_at(time, simulated.truth_at(time), [[0.0; 3]; 3]);
    let (mut sum, mut sx, mut sy, mut st) = (0.0, 0.0, 0.0, 0.0);
    let (mut sum_t, mut sum_r) = (0.0, 0.0);
    let (mut var_t, mut var_r) = (0.0, 0.0);
    for revolution in rest {
        let result = mapper.add_scan(revolution);
        let truth = simulated.truth_at(result.time);
        let (pose, c) = match which {
            Estimate::Match => (result.matched, &result.match_covariance),
            Estimate::Reported => (result.pose, &result.covariance),
        };
        let e = [
            pose.x - truth.x,
            pose.y - truth.y,
            wrap_angle(pose.theta - truth.theta),
        ];
        let information = inverse(c);
        sum += (0..3)
            .map(|i| (0..3).map(|j| e[i] * information[i][j] * e[j]).sum::<f64>())
            .sum::<f64>();
        sx += e[0] * e[0] / c[0][0];
        sy += e[1] * e[1] / c[1][1];
        st += e[2] * e[2] / c[2][2];
        sum_t += e[0] * e[0] + e[1] * e[1];
        sum_r += e[2] * e[2];
        var_t += c[0][0] + c[1][1];
        var_r += c[2][2];
    }
    let n = rest.len() as f64;
    Nees {
        scans: rest.len(),
        mean: sum / n,
        x: sx / n,
        y: sy / n,
        theta: st / n,
        rms_translation: (sum_t / n).sqrt(),
        rms_rotation: (sum_r / n).sqrt(),
        sigma_translation: (var_t / n).sqrt(),
        sigma_rotation: (var_r / n).sqrt(),
    }
}

/// The runs the calibration is checked on: the trolley around the table, and a head standing at
/// three places (by the start, east of the table, west by the glass wall), each with a few
/// draws of the RPLidar's noise.
fn calibration_runs() -> Vec<(String, Run)> {
    let mut runs = Vec::new();
    for seed in [1, 2, 3] {
        let mut run = Run::trolley(RangeNoise::RPLIDAR);
        run.seed = seed;
        runs.push((format!("around the table, seed {seed}"), run));
    }
    let places = [
        START,
        Pose2 {
            x: 6.31,
            y: 4.27,
            theta: 2.2,
        },
        Pose2 {
            x: 1.27,
            y: 4.9,
            theta: -1.0,
        },
    ];
    for (k, place) in places.into_iter().enumerate() {
        for seed in [1, 2] {
            let mut run = Run::trolley(RangeNoise::RPLIDAR);
            run.path = Path::Standing(25.0);
            run.rotation_hz = 10.0;
            run.start = place;
            run.seed = seed + 10 * k as u64;
            runs.push((format!("standing at place {k}, seed {}", run.seed), run));
        }
    }
    runs
}

#[test]
fn the_reported_covariance_matches_the_error_of_a_match_against_a_true_map() {
    // Issue 20: averaged over a run, the normalised estimation error squared lies in
    // [1.5, 4.5] for the 3 degrees of freedom (3 when the covariance is exactly right).
    let mut means = Vec::new();
    for (name, run) in calibration_runs() {
        let matched = nees(&run, Estimate::Match);
        let reported = nees(&run, Estimate::Reported);
        println!("{name}: {matched}\n    reported (held when standing): {reported}");
        means.push((matched.mean, name));
    }
    means.sort_by(|a, b| a.0.total_cmp(&b.0));
    let median = means[means.len() / 2].0;
    let (lowest, highest) = (&means[0], &means[means.len() - 1]);
    println!(
        "NEES over {} runs: median {median:.2}, lowest {:.2} ({}), highest {:.2} ({})",
        means.len(),
        lowest.0,
        lowest.1,
        highest.0,
        highest.1
    );
    // All runs together (the figure the issue bounds), and each run alone with a margin: the
    // runs differ in how their map is wrong (a standing head's map is one revolution).
    let pooled = means.iter().map(|m| m.0).sum::<f64>() / means.len() as f64;
    println!("NEES over all runs: {pooled:.2}");
    assert!((1.5..=4.5).contains(&pooled), "pooled NEES {pooled:.2}");
    assert!((1.5..=4.5).contains(&median), "median NEES {median:.2}");
    for (mean, name) in &means {
        assert!((1.0..=6.0).contains(mean), "{name}: NEES {mean:.2}");
    }
}

/// How far a standing head's live poses move over `seconds` of revolutions at 10 Hz (the mapper
/// as live: from the identity, `config`, RPLidar noise drawn with `seed`): the largest and RMS
/// distance and heading difference of the reported poses from the first one counted, and the
/// same for each revolution's own match, counted from 3 s after the head stopped (the mapper
/// holds a head that has stood 2 s). `after_moving`: the head first moves 1.2 m and then stands
/// (the map was made elsewhere, so the held pose is the mean of the matches); else it stands
/// from the start (where the map was made).
fn standing_drift(seconds: f64, seed: u64, config: &MapperConfig, after_moving: bool) -> Drift {
    let mut run = Run::trolley(RangeNoise::RPLIDAR);
    run.path = if after_moving {
        Path::MovingThenStanding(seconds)
    } else {
        Path::Standing(seconds)
    };
    run.rotation_hz = 10.0;
    run.seed = seed;
    run.config = *config;
    // The mapper holds a head that has stood 2 s (`SCATTER_AFTER` revolutions at 10 Hz).
    let from = 3.0 + if after_moving { MOVING_UNTIL } else { 0.0 };
    let simulated = simulate(&run);
    let mut mapper = Mapper::new(run.config);
    let mut reported = Excursion::default();
    let mut matched = Excursion::default();
    let (mut scans, mut standing) = (0, 0);
    let mut origin: Option<(Pose2, Pose2)> = None;
    for revolution in &simulated.revolutions {
        let result = mapper.add_scan(revolution);
        if result.time < from {
            continue;
        }
        let (first_reported, first_matched) = *origin.get_or_insert((result.pose, result.matched));
        reported.add(&first_reported.between(&result.pose));
        matched.add(&first_matched.between(&result.matched));
        scans += 1;
        standing += usize::from(result.standing);
    }
    let drift = Drift {
        reported,
        matched,
        scans,
        standing,
    };
    let case = if after_moving {
        "after moving"
    } else {
        "from the start"
    };
    println!("standing {seconds} s {case}, seed {seed}: {drift}");
    drift
}

/// The largest and RMS distance and heading difference of poses from the origin.
#[derive(Debug, Clone, Copy, Default)]
struct Excursion {
    max_translation: f64,
    max_rotation: f64,
    sum_t: f64,
    sum_r: f64,
    count: usize,
}

impl Excursion {
    fn add(&mut self, pose: &Pose2) {
        let (t, r) = (pose.x.hypot(pose.y), wrap_angle(pose.theta).abs());
        self.max_translation = self.max_translation.max(t);
        self.max_rotation = self.max_rotation.max(r);
        self.sum_t += t * t;
        self.sum_r += r * r;
        self.count += 1;
    }
}

impl std::fmt::Display for Excursion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.count.max(1) as f64;
        write!(
            f,
            "max {:.2} mm, {:.3}°; RMS {:.2} mm, {:.3}°",
            self.max_translation * 1e3,
            self.max_rotation.to_degrees(),
            (self.sum_t / n).sqrt() * 1e3,
            (self.sum_r / n).sqrt().to_degrees()
        )
    }
}

/// A standing run's reported poses and its revolutions' own matches.
#[derive(Debug, Clone, Copy)]
struct Drift {
    reported: Excursion,
    matched: Excursion,
    scans: usize,
    /// Revolutions whose pose was a held one.
    standing: usize,
}

impl std::fmt::Display for Drift {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} revolutions ({} held): reported {}; matches {}",
            self.scans, self.standing, self.reported, self.matched
        )
    }
}

/// The trolley's configuration (the live pose stage's but for the map update distances).
fn trolley_config() -> MapperConfig {
    Run::trolley(RangeNoise::RPLIDAR).config
}

/// Whether a standing run's reported poses stayed within the goal: < 1 cm and < 0.2°.
fn within_goal(drift: &Drift) -> bool {
    drift.reported.max_translation < 0.01 && drift.reported.max_rotation < 0.2f64.to_radians()
}

#[test]
fn a_standing_heads_pose_moves_less_than_1_cm_and_0_2_degrees_over_a_minute() {
    // Issue 20 asks for < 1 cm and < 0.2° over ten minutes (the ignored test below). Each
    // revolution alone is matched with about 5 mm and 0.25° RMS of noise, so over 600
    // revolutions its largest excursion is 16 mm and 1.0°; the mapper holds a standing head
    // (`StandstillConfig`): where it stood when the map was made, or after moving, at the mean
    // of its matches since it stopped. Three draws of the noise, each within the goal; with
    // the hold off the same draws exceed it (so the test can fail).
    let config = trolley_config();
    let mut unheld = config;
    unheld.standstill.enabled = false;
    for after_moving in [false, true] {
        for seed in [12, 13, 14] {
            let drift = standing_drift(60.0, seed, &config, after_moving);
            assert!(drift.scans >= 570, "{drift}");
            assert!(within_goal(&drift), "{drift}");
            assert!(drift.standing + 2 >= drift.scans, "{drift}");
        }
        let drift = standing_drift(60.0, 12, &unheld, after_moving);
        assert!(!within_goal(&drift), "{drift}");
    }
}

#[test]
#[ignore = "ten minutes of revolutions: \
            cargo test -p scan3d-hw-sim --release --test slam_room -- --ignored"]
fn a_standing_heads_pose_moves_less_than_1_cm_and_0_2_degrees_over_ten_minutes() {
    for after_moving in [false, true] {
        let drift = standing_drift(600.0, 12, &trolley_config(), after_moving);
        assert!(drift.scans >= 5960, "{drift}");
        assert!(within_goal(&drift), "{drift}");
    }
}

#[test]
#[ignore = "a parameter sweep for docs/slam.md: \
            cargo test -p scan3d-hw-sim --release --test slam_room -- --ignored sweep"]
fn sweep_of_the_standstill_gates() {
    // Median and worst over three noise draws, for the gates around the defaults: the standing
    // head's excursions (from the start and after moving) and the trolley's error round the
    // table (RPLidar noise).
    for gate in [11.34, 16.27, 25.0] {
        for start_gate in [4.11, 6.25, 7.81] {
            let mut config = trolley_config();
            config.standstill.gate = gate;
            config.standstill.start_gate = start_gate;
            let (mut translation, mut rotation, mut trolley) = (Vec::new(), Vec::new(), Vec::new());
            for seed in [12, 13, 14] {
                for after_moving in [false, true] {
                    let drift = standing_drift(60.0, seed, &config, after_moving);
                    translation.push(drift.reported.max_translation * 1e3);
                    rotation.push(drift.reported.max_rotation.to_degrees());
                }
                let mut run = Run::trolley(RangeNoise::RPLIDAR);
                run.config = config;
                run.seed = seed;
                trolley.push(score(&run).max_translation * 1e3);
            }
            let stats = |v: &mut Vec<f64>| {
                v.sort_by(f64::total_cmp);
                (v[v.len() / 2], v[v.len() - 1])
            };
            let (t, r, m) = (
                stats(&mut translation),
                stats(&mut rotation),
                stats(&mut trolley),
            );
            println!(
                "SWEEP gate {gate}, start gate {start_gate}: standing max excursion median / worst \
                 {:.2} / {:.2} mm, {:.3} / {:.3}°; trolley max error {:.1} / {:.1} mm",
                t.0, t.1, r.0, r.1, m.0, m.1
            );
        }
    }
}
