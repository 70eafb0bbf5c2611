//! `scan3d slam INPUT --out TRAJ.txt` (2D scan matching of a CARMEN log or a recorded
//! session) and `scan3d slam-eval TRAJ RELATIONS` (the Kümmerle relations metric).

use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use scan3d_slam::carmen::{ReadOptions, read_log};
use scan3d_slam::grid::{Grid, GridPyramid, MAX_CELLS};
use scan3d_slam::map_image::{Thresholds, write_pgm, write_png_with_trajectory, write_yaml};
use scan3d_slam::mapper::{Mapper, MapperConfig};
use scan3d_slam::matcher::Loss;
use scan3d_slam::odometry::{Calibration, MAX_LATENCY, OdometrySource};
use scan3d_slam::odometry_bias::{Slips, WheelError, distort_odometry};
use scan3d_slam::offline::{RangeLimits, map_log, map_log_calibrated, raster};
use scan3d_slam::pose::Pose2;
use scan3d_slam::relations::{
    EvalOptions, Formula, RelationError, Trajectory, evaluate, read_relations, read_trajectory,
    write_trajectory,
};

use super::parse_finite_numbers;
use crate::pose::scan_matching::map_session;

/// The largest `--laser-offset` accepted (m): a laser further than this from the robot's
/// origin is a typo, not a mount.
const MAX_LASER_OFFSET: f64 = 2.0;

/// Options of `scan3d slam`.
#[derive(Debug, clap::Args)]
pub struct SlamArgs {
    /// A CARMEN log (`.clf`/`.log`, or gzipped `.gz`: `FLASER`, `ROBOTLASER1`, `ODOM`) or a
    /// recorded session directory (its RPLidar revolutions).
    pub input: PathBuf,
    /// The trajectory to write: one `timestamp x y theta` line per laser scan, the timestamp as
    /// the log wrote it.
    #[arg(long, value_name = "TRAJ.txt")]
    pub out: PathBuf,
    /// Use the log's wheel odometry as the motion prior (the default when the log has it).
    #[arg(long, conflicts_with = "no_odometry")]
    pub odometry: bool,
    /// Ignore odometry: a constant-velocity prior and a search window, as on a trolley.
    #[arg(long)]
    pub no_odometry: bool,
    /// Odometry from the log's `ODOM` lines read this many seconds before each laser stamp.
    /// Without it (or `--laser-odometry`), a log with `ODOM` lines is matched once with the
    /// laser lines' own odometry, the `ODOM` lines' latency is estimated from that pass, and
    /// the log is matched again with them when they agree better with the scans.
    #[arg(long, value_name = "S", allow_negative_numbers = true, conflicts_with_all = ["no_odometry", "laser_odometry"])]
    pub odometry_latency: Option<f64>,
    /// Odometry from each laser line's own pose, in one pass (no calibration).
    #[arg(long, conflicts_with = "no_odometry")]
    pub laser_odometry: bool,
    /// Match scans against the map only (the one mode until loop closure lands).
    #[arg(long)]
    pub no_loop_closure: bool,
    /// Treat readings beyond this range (m) as no return. Without it, only readings at the
    /// log's no-return value (its largest reading: 81.83 / 50.00 / 81.91 m in the classic
    /// logs) count as no return.
    #[arg(long, value_name = "M")]
    pub max_range: Option<f64>,
    /// Drop readings closer than this (m).
    #[arg(long, value_name = "M", default_value_t = 0.1)]
    pub min_range: f64,
    /// Where a log's front laser sits ahead of the robot's origin (m, negative: behind), for
    /// `FLASER` lines, which carry no offset (FR079: 0.04 m; its sources disagree on the sign).
    /// Overrides the log's `PARAM robot_frontlaser_offset`; `ROBOTLASER1` lines keep their own.
    #[arg(long, value_name = "M", allow_negative_numbers = true)]
    pub laser_offset: Option<f64>,
    /// Distort a log's odometry before matching, to test the matcher against worse wheels:
    /// every step's turn grows by PER_RAD of itself plus PER_M radians per metre driven, its
    /// distance by SCALE of itself (e.g. `0,0.02,0.05`: 1.1° per metre, 5 % long).
    #[arg(long, value_name = "PER_RAD,PER_M,SCALE", value_parser = parse_wheel_error,
          allow_negative_numbers = true, allow_hyphen_values = true)]
    pub odometry_error: Option<WheelError>,
    /// Put slips into a log's odometry: every EVERY seconds one step jumps M metres forward
    /// and RAD radians, the signs alternating (e.g. `60,0.3,0.15`).
    #[arg(long, value_name = "EVERY,M,RAD", value_parser = parse_slips)]
    pub odometry_slips: Option<Slips>,
    /// Match only the first laser line and every N-th after it: the log as if written N times
    /// less often (e.g. 2 on FR079: 0.19 m between scans instead of 0.09), to test the
    /// matcher against sparser logs. Score the trajectory with the relations whose two scans
    /// were kept (`slam-eval`'s default) or `--interpolate --max-dt`.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..=1000))]
    pub every: Option<u16>,
    /// Every mapper parameter (see `deploy/slam.toml` for the keys and defaults).
    #[arg(long, value_name = "slam.toml")]
    pub config: Option<PathBuf>,
    /// Also write the final grid as ROS map_server `OUT.pgm` + `OUT.yaml`, and `OUT.png` with
    /// the trajectory drawn on it, axes and a scale bar in metres.
    #[arg(long, value_name = "OUT")]
    pub map: Option<PathBuf>,
    /// Skip malformed log lines (and count them) instead of stopping at the first one; for a
    /// session, match the readable rest of a damaged recording (with a warning).
    #[arg(long)]
    pub lenient: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// With a session: also run it through the live pipeline's pose and yaw-fusion stages and
    /// write the fusion's files into DIR: `trajectory_fused.tum` (room frame, the clock of
    /// `trajectory.tum`), `passes/NAME/trajectory_fused.tum`, `yaw_sources.csv`.
    #[arg(long, value_name = "DIR")]
    pub fused: Option<PathBuf>,
    /// With `--fused`: the true trajectory of `base` (TUM, on the same clock) to score each yaw
    /// source against: prints each source's yaw RMSE and writes `DIR/fig5.svg` and `fig5.png`.
    #[arg(long, value_name = "TRUTH.tum", requires = "fused")]
    pub truth: Option<PathBuf>,
}

/// The most `motion.wider_search` may widen the window search (its cost grows with the square).
const MAX_WIDER_SEARCH: f64 = 10.0;

/// The longest memory `motion.odometry_bias_window` may have (steps): a day of scans.
const MAX_BIAS_WINDOW: f64 = 1e6;

/// The largest distortion `--odometry-error` puts in, per term (wheels worse than that are not
/// a test of the matcher but a broken robot).
const MAX_WHEEL_ERROR: f64 = 0.5;

/// `PER_RAD,PER_M,SCALE` for `--odometry-error`.
fn parse_wheel_error(text: &str) -> Result<WheelError, String> {
    let [per_rad, per_m, scale] = parse_finite_numbers(text, "PER_RAD,PER_M,SCALE")?;
    if [per_rad, per_m, scale]
        .iter()
        .any(|v| v.abs() > MAX_WHEEL_ERROR)
    {
        return Err(format!(
            "each term must be within ±{MAX_WHEEL_ERROR}, got {text:?}"
        ));
    }
    Ok(WheelError {
        per_rad,
        per_m,
        scale,
    })
}

/// `EVERY,M,RAD` for `--odometry-slips`.
fn parse_slips(text: &str) -> Result<Slips, String> {
    let [every, translation, rotation] = parse_finite_numbers(text, "EVERY,M,RAD")?;
    if every < 1.0 || translation.abs() > 10.0 || rotation.abs() > std::f64::consts::PI {
        return Err(format!(
            "slips need EVERY ≥ 1 s, |M| ≤ 10 m and |RAD| ≤ π, got {text:?}"
        ));
    }
    Ok(Slips {
        every,
        translation,
        rotation,
    })
}

/// Reads `slam.toml`: every key optional, unknown keys refused with their line.
pub fn load_config(path: &Path) -> anyhow::Result<MapperConfig> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let config: MapperConfig = toml::from_str(&text)
        .map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_end()))?;
    validate(&config).with_context(|| format!("{}", path.display()))?;
    Ok(config)
}

fn validate(config: &MapperConfig) -> anyhow::Result<()> {
    if !(config.resolution.is_finite() && config.resolution >= 0.005 && config.resolution <= 1.0) {
        bail!(
            "resolution must be between 0.005 and 1 m, not {}",
            config.resolution
        );
    }
    if !(1..=6).contains(&config.levels) {
        bail!("levels must be 1 to 6, not {}", config.levels);
    }
    let u = &config.update;
    if !(0.5 < u.hit_probability && u.hit_probability < 1.0) {
        bail!(
            "update.hit_probability must be in (0.5, 1), not {}",
            u.hit_probability
        );
    }
    if !(0.0 < u.miss_probability && u.miss_probability < 0.5) {
        bail!(
            "update.miss_probability must be in (0, 0.5), not {}",
            u.miss_probability
        );
    }
    if !(u.clamp_log_odds.is_finite() && u.clamp_log_odds > 0.0) {
        bail!("update.clamp_log_odds must be positive");
    }
    for (key, value) in [
        ("join_endpoints_within", u.join_endpoints_within),
        (
            "join_endpoints_within_without_odometry",
            u.join_endpoints_within_without_odometry,
        ),
    ] {
        if !(0.0..=1.0).contains(&value) {
            bail!("update.{key} must be 0 to 1 m, not {value}");
        }
    }
    let m = &config.matcher;
    if m.coarse_iterations > 100 || m.fine_iterations > 100 || m.fine_iterations == 0 {
        bail!("matcher iterations must be 1 to 100 (fine) and 0 to 100 (coarse)");
    }
    if !(m.residual_sigma.is_finite() && m.residual_sigma > 0.0) {
        bail!("matcher.residual_sigma must be positive");
    }
    let r = &config.refine;
    if r.iterations > 100 || r.min_points == 0 {
        bail!("refine.iterations must be at most 100 and refine.min_points at least 1");
    }
    let robust = match r.loss {
        Loss::Squared => 1.0,
        Loss::Huber { delta } => delta,
        Loss::Cauchy { c } => c,
    };
    if !(robust.is_finite() && robust > 0.0) {
        bail!("refine.loss: its delta or c must be positive");
    }
    for (name, v) in [
        (
            "refine.velocity_translation_sigma",
            r.velocity_translation_sigma,
        ),
        ("refine.velocity_rotation_sigma", r.velocity_rotation_sigma),
    ] {
        if !(v.is_finite() && v > 0.0) {
            bail!("{name} must be positive, not {v}");
        }
    }
    let s = &config.motion.velocity_search;
    if s.angle > 0.0 && (s.angle_step <= 0.0 || s.angle / s.angle_step > 1000.0) {
        bail!("motion.velocity_search: angle / angle_step must be at most 1000");
    }
    if !(0.0..=std::f64::consts::PI).contains(&s.max_angle)
        || !(0.0..=MAX_SEARCH_TRANSLATION).contains(&s.max_translation)
    {
        bail!(
            "motion.velocity_search: max_angle must be within [0, π] and max_translation within \
             [0, {MAX_SEARCH_TRANSLATION}] m"
        );
    }
    if config.max_range.is_nan() || config.max_range <= 0.0 {
        bail!("max_range must be positive, not {}", config.max_range);
    }
    if !(0.0..=10.0).contains(&config.motion.velocity_window) {
        bail!(
            "motion.velocity_window must be 0 to 10 s, not {}",
            config.motion.velocity_window
        );
    }
    if !(0.0..=MAX_WIDER_SEARCH).contains(&config.motion.wider_search) {
        bail!(
            "motion.wider_search must be 0 to {MAX_WIDER_SEARCH}, not {}",
            config.motion.wider_search
        );
    }
    if !(0.0..=MAX_BIAS_WINDOW).contains(&config.motion.odometry_bias_window) {
        bail!(
            "motion.odometry_bias_window must be 0 to {MAX_BIAS_WINDOW} steps, not {}",
            config.motion.odometry_bias_window
        );
    }
    if config.motion.out_of_order_poses > MAX_OUT_OF_ORDER_POSES {
        bail!(
            "motion.out_of_order_poses must be 0 to {MAX_OUT_OF_ORDER_POSES}, not {}",
            config.motion.out_of_order_poses
        );
    }
    for (key, value, limit, unit) in [
        (
            "odometry_check_window",
            config.motion.odometry_check_window,
            60.0,
            "s",
        ),
        (
            "out_of_order_back",
            config.motion.out_of_order_back,
            1.0,
            "m",
        ),
        (
            "out_of_order_turn_back",
            config.motion.out_of_order_turn_back,
            std::f64::consts::PI,
            "rad",
        ),
    ] {
        if !(0.0..=limit).contains(&value) {
            bail!("motion.{key} must be 0 to {limit:.2} {unit}, not {value}");
        }
    }
    if !(0.0..=1e6).contains(&config.motion.odometry_check_threshold) {
        bail!(
            "motion.odometry_check_threshold must be 0 to 1e6, not {}",
            config.motion.odometry_check_threshold
        );
    }
    if !(1.0..=100.0).contains(&config.motion.odometry_max_widening) {
        bail!(
            "motion.odometry_max_widening must be 1 to 100, not {}",
            config.motion.odometry_max_widening
        );
    }
    if !(0.0..=1.0).contains(&config.motion.poor_match_ratio) {
        bail!(
            "motion.poor_match_ratio must be within [0, 1], not {}",
            config.motion.poor_match_ratio
        );
    }
    for (name, v) in [
        ("map_update_distance", config.map_update_distance),
        ("map_update_angle", config.map_update_angle),
        (
            "motion.min_translation_sigma",
            config.motion.min_translation_sigma,
        ),
        (
            "motion.min_rotation_sigma",
            config.motion.min_rotation_sigma,
        ),
        ("refine.sigma_floor", r.sigma_floor),
        ("refine.max_translation", r.max_translation),
        ("refine.max_rotation", r.max_rotation),
        ("matcher.reference_endpoints", m.reference_endpoints),
        ("motion.poor_match_gain", config.motion.poor_match_gain),
        ("motion.velocity_search.prior_weight", s.prior_weight),
        ("motion.velocity_search.sigmas", s.sigmas),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            bail!("{name} must be a non-negative number, not {v}");
        }
    }
    let e = &config.reentry;
    for (key, value, limit, unit) in [
        ("min_age", e.min_age, 1e6, " s"),
        ("radius", e.radius, 50.0, " m"),
        ("window", e.window, MAX_SEARCH_TRANSLATION, " m"),
        ("angle", e.angle, 0.35, " rad"),
        ("spacing", e.spacing, 1e3, " m"),
        ("min_score", e.min_score, 1.0, ""),
        ("score_gain", e.score_gain, 1.0, ""),
        ("min_contradicted", e.min_contradicted, 1.0, ""),
        ("contradicted_ratio", e.contradicted_ratio, 1.0, ""),
        ("free_below", f64::from(e.free_below), 0.5, ""),
    ] {
        if !(0.0..=limit).contains(&value) {
            bail!("reentry.{key} must be 0 to {limit}{unit}, not {value}");
        }
    }
    if !(1..=MAX_REENTRY_SCANS).contains(&e.max_scans) || !(0..=10).contains(&e.clearance) {
        bail!(
            "reentry.max_scans must be 1 to {MAX_REENTRY_SCANS} and reentry.clearance 0 to 10 cells"
        );
    }
    Ok(())
}

/// Most integrated scans a re-entry check builds its old map from (each is integrated anew).
const MAX_REENTRY_SCANS: usize = 500;

/// Most earlier poses a poor match may be tried at (each costs a match, on a poor scan).
const MAX_OUT_OF_ORDER_POSES: usize = 256;

/// Largest translation half-width of a grown search window (m): the search steps in coarse
/// cells, at most 20 each way.
const MAX_SEARCH_TRANSLATION: f64 = 2.0;

/// Opens a log, through gzip when its name ends in `.gz`.
fn open_log(path: &Path) -> anyhow::Result<Box<dyn BufRead>> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    Ok(if path.extension().is_some_and(|e| e == "gz") {
        Box::new(BufReader::new(flate2::read::GzDecoder::new(file)))
    } else {
        Box::new(BufReader::new(file))
    })
}

fn progress_bar(total: u64, quiet: bool) -> Option<ProgressBar> {
    (!quiet && total > 2000).then(|| {
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template("matching [{bar:40}] {human_pos}/{human_len} scans {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    })
}

/// Runs `scan3d slam`.
pub fn run(args: &SlamArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let mut config = match &args.config {
        Some(path) => load_config(path)?,
        None => MapperConfig::default(),
    };
    if let Some(max) = args.max_range
        && !(max.is_finite() && max > args.min_range)
    {
        bail!(
            "--max-range must be a number above --min-range ({}), not {max}",
            args.min_range
        );
    }
    if args.no_odometry {
        config.motion.use_odometry = false;
    } else if args.odometry {
        config.motion.use_odometry = true;
    }
    if args.fused.is_some() && !args.input.is_dir() {
        bail!("--fused needs a recorded session directory, not a log");
    }
    let started = Instant::now();
    let (run, source) = if args.input.is_dir() {
        if args.every.is_some() || args.odometry_error.is_some() || args.odometry_slips.is_some() {
            bail!(
                "--every, --odometry-error and --odometry-slips change a CARMEN log's laser \
                 lines or wheel odometry; {} is a session, which has neither",
                args.input.display()
            );
        }
        let limits = RangeLimits {
            min_range: args.min_range,
            max_range: args.max_range,
            no_return: None,
        };
        // A session does not say how many revolutions it holds before it is read: a counter.
        let bar = (!args.quiet).then(|| {
            let bar = ProgressBar::new_spinner();
            bar.set_style(
                ProgressStyle::with_template(
                    "matching {spinner} {human_pos} revolutions {elapsed}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_spinner()),
            );
            bar
        });
        let (run, recording) =
            map_session(&args.input, &config, &limits, None, args.lenient, |done| {
                if let Some(bar) = &bar
                    && done % 64 == 0
                {
                    bar.set_position(done as u64);
                }
            })
            .with_context(|| {
                format!(
                    "cannot match the session {} (--lenient matches what is readable)",
                    args.input.display()
                )
            })?;
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
        if recording.undecodable_frames > 0 {
            writeln!(
                out,
                "skipped {} frames the server recorded but could not decode",
                recording.undecodable_frames
            )?;
        }
        (run, "session revolutions")
    } else {
        let mut log = read_log(
            open_log(&args.input)?,
            &ReadOptions {
                lenient: args.lenient,
            },
        )
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.input.display()))?;
        if log.skipped.malformed > 0 {
            writeln!(
                out,
                "skipped {} malformed line(s) (first: {})",
                log.skipped.malformed,
                log.skipped
                    .first_malformed
                    .iter()
                    .map(|e| e.to_string())
                    .collect::<Vec<_>>()
                    .join("; ")
            )?;
        }
        if log.scans.is_empty() {
            bail!(
                "{}: no laser scans (FLASER or ROBOTLASER1 lines)",
                args.input.display()
            );
        }
        if let Some(forward) = args.laser_offset {
            if !(forward.is_finite() && forward.abs() <= MAX_LASER_OFFSET) {
                bail!("--laser-offset must be within ±{MAX_LASER_OFFSET} m, not {forward}");
            }
            log.set_front_laser_offset(Pose2::new(forward, 0.0, 0.0));
        }
        if let Some(every) = args.every.filter(|&n| n > 1) {
            log.keep_every(usize::from(every));
            writeln!(
                out,
                "kept 1 laser line in {every}: {} scans",
                log.scans.len()
            )?;
        }
        if args.odometry_error.is_some() || args.odometry_slips.is_some() {
            let error = args.odometry_error.unwrap_or_default();
            distort_odometry(&mut log, &error, args.odometry_slips.as_ref());
            writeln!(
                out,
                "odometry distorted: {:+} rad per rad turned, {:+} rad per m driven, {:+} of \
                 every distance{}",
                error.per_rad,
                error.per_m,
                error.scale,
                args.odometry_slips.map_or(String::new(), |s| format!(
                    "; a slip of {} m and {} rad every {} s",
                    s.translation, s.rotation, s.every
                ))
            )?;
        }
        let limits = RangeLimits::for_log(&log, args.min_range, args.max_range);
        let fixed = match (args.odometry_latency, args.laser_odometry) {
            (Some(latency), _) => {
                if !(latency.is_finite() && latency.abs() <= MAX_LATENCY) {
                    bail!("--odometry-latency must be within ±{MAX_LATENCY} s, not {latency}");
                }
                Some(OdometrySource::Track { latency })
            }
            (None, true) => Some(OdometrySource::LaserLines),
            (None, false) => None,
        };
        let calibrating = fixed.is_none() && config.motion.use_odometry && !log.odometry.is_empty();
        let passes = if calibrating { 2 } else { 1 };
        let bar = progress_bar((passes * log.scans.len()) as u64, args.quiet);
        // Each scan's matching time (over both passes when calibrating), for the p50 / p99 line.
        let mut per_scan = Vec::with_capacity(passes * log.scans.len());
        let mut scan_started = Instant::now();
        let progress = |done: usize| {
            let now = Instant::now();
            per_scan.push((now - scan_started).as_secs_f64());
            scan_started = now;
            if let Some(bar) = &bar
                && done.is_multiple_of(256)
            {
                bar.set_position(done as u64);
            }
        };
        let (run, odometry) = match fixed {
            Some(source) => {
                let poses = source.poses(&log).with_context(|| {
                    format!(
                        "{}: --odometry-latency needs ODOM lines, and the log has none",
                        args.input.display()
                    )
                })?;
                (
                    map_log(&log, &config, &limits, &poses, progress),
                    describe(&source, None),
                )
            }
            None => {
                let calibrated = map_log_calibrated(&log, &config, &limits, progress);
                let said = describe(&calibrated.odometry, calibrated.calibration.as_ref());
                (calibrated.run, said)
            }
        };
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
        if config.motion.use_odometry {
            writeln!(out, "odometry: {odometry}")?;
        }
        per_scan.sort_by(f64::total_cmp);
        writeln!(
            out,
            "time per scan: p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms over {} matches",
            1e3 * nearest_rank(&per_scan, 0.50),
            1e3 * nearest_rank(&per_scan, 0.99),
            1e3 * per_scan.last().copied().unwrap_or(0.0),
            per_scan.len()
        )?;
        (run, "laser lines")
    };
    let elapsed = started.elapsed().as_secs_f64();
    let (trajectory, mapper) = (&run.trajectory, &run.mapper);
    let (scans, duration) = (run.results.len(), span(trajectory));
    let file =
        File::create(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut writer = BufWriter::new(file);
    write_trajectory(trajectory, &mut writer)
        .and_then(|()| writer.flush())
        .with_context(|| format!("writing {}", args.out.display()))?;
    writeln!(
        out,
        "{scans} {source} matched in {elapsed:.2} s ({:.0}× real time over {duration:.1} s of data); odometry {}; trajectory {}",
        if elapsed > 0.0 {
            duration / elapsed
        } else {
            0.0
        },
        if config.motion.use_odometry {
            "on"
        } else {
            "off"
        },
        args.out.display()
    )?;
    writeln!(out, "{}", describe_map(mapper.map()))?;
    let out_of_order = run.results.iter().filter(|r| r.out_of_order).count();
    if out_of_order > 0 {
        writeln!(
            out,
            "{out_of_order} scan(s) set aside as logged out of order: each fits an earlier pose \
             better than the predicted one, or went back to one against the prediction; it \
             keeps that pose, is not mapped, and the next scan is predicted from the last pose \
             in order"
        )?;
    }
    let reentries: Vec<f64> = run
        .results
        .iter()
        .filter(|r| r.reentered)
        .map(|r| r.time)
        .collect();
    if !reentries.is_empty() {
        let mut times: Vec<String> = reentries
            .iter()
            .take(10)
            .map(|t| format!("{:.1}", t - run.results[0].time))
            .collect();
        if reentries.len() > times.len() {
            times.push("…".into());
        }
        writeln!(
            out,
            "{} re-entr{} onto the old map (back at a place mapped over {:.0} s before, the scan \
             contradicted it where it stood) at {} s into the log",
            reentries.len(),
            if reentries.len() == 1 { "y" } else { "ies" },
            config.reentry.min_age,
            times.join(", ")
        )?;
    }
    let refused = mapper.refused_integrations();
    if refused > 0 {
        tracing::warn!(
            scans = refused,
            cells = MAX_CELLS,
            area_seen_m2 = %format_args!(
                "{:.0}",
                MAX_CELLS as f64 * config.resolution * config.resolution
            ),
            "the map reached its size limit: those scans were not mapped, and where the map \
             has nothing the trajectory follows the prior alone"
        );
    }
    if let Some(stem) = &args.map {
        write_map(mapper, trajectory, stem)?;
        writeln!(out, "map {0}.pgm, {0}.yaml, {0}.png", stem.display())?;
    }
    if let Some(dir) = &args.fused {
        write_fused(&args.input, dir, args.truth.as_deref(), out)?;
    }
    Ok(())
}

/// The `q` quantile (0..1) of sorted `values` by the nearest-rank rule; 0 when there are none.
fn nearest_rank(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let rank = (q * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// `--fused DIR [--truth TRUTH.tum]`: the session through the pose and fusion stages; with a
/// truth, each source's yaw RMSE and Fig. 5.
fn write_fused(
    session: &Path,
    dir: &Path,
    truth: Option<&Path>,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    let (run, files) = crate::pipeline::fusion_stage::fuse_session_into(session, dir)?;
    let c = run.counts;
    writeln!(
        out,
        "yaw fusion: {} poses fused, {} the matcher's alone (aligning {}, no orientation {}, no \
         IMU nearby {}, frame-defining {}, field unknown {}); {} IMU stop(s); {}",
        c.fused,
        c.matcher_only,
        c.aligning,
        c.no_orientation,
        c.no_imu_nearby,
        c.exact_matcher,
        c.variance_unknown,
        c.imu_stops,
        files
            .iter()
            .map(|f| f.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    )?;
    let Some(truth) = truth else {
        return Ok(());
    };
    let text =
        std::fs::read_to_string(truth).with_context(|| format!("reading {}", truth.display()))?;
    let truth_yaw =
        crate::yaw_plot::read_tum_yaw(&text).with_context(|| format!("{}", truth.display()))?;
    let series = crate::yaw_plot::yaw_errors(&run, &truth_yaw);
    let rmse = crate::yaw_plot::rmse(&series, 0.0);
    for r in &rmse {
        writeln!(
            out,
            "yaw RMSE {:<24} {:.3}° over {} poses",
            r.label, r.rmse_deg, r.poses
        )?;
    }
    // Over the poses where every source has a yaw (Madgwick from its alignment on).
    let both: Vec<f64> = series
        .iter()
        .find(|s| s.label == "Madgwick")
        .map(|s| s.points.iter().map(|p| p.0).collect())
        .unwrap_or_default();
    if let Some(&from) = both.first() {
        let r = crate::yaw_plot::rmse(&series, from);
        let fused = r[3].rmse_deg;
        writeln!(
            out,
            "from {from:.1} s (all sources): gyro {:.3}°, Madgwick {:.3}°, matcher {:.3}°, fused \
             {fused:.3}°; fused/matcher {:.3}, fused/Madgwick {:.3}",
            r[0].rmse_deg,
            r[1].rmse_deg,
            r[2].rmse_deg,
            fused / r[2].rmse_deg,
            fused / r[1].rmse_deg
        )?;
    }
    let figures = crate::yaw_plot::write_fig5(&run, &truth_yaw, dir)?;
    writeln!(
        out,
        "{}",
        figures
            .iter()
            .map(|f| f.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    )?;
    Ok(())
}

/// One line on the odometry a log was matched with, and why.
fn describe(source: &OdometrySource, calibration: Option<&Calibration>) -> String {
    let chosen = match source {
        OdometrySource::LaserLines => "the laser lines' own poses".to_owned(),
        OdometrySource::Track { latency } => {
            format!("the ODOM lines, read {latency:.3} s before each laser stamp")
        }
    };
    match calibration {
        None => chosen,
        Some(c) => {
            let track = c.track.map_or(String::new(), |(latency, disagreement)| {
                format!(
                    ", the ODOM lines at {latency:.3} s {:.3}°",
                    disagreement.to_degrees()
                )
            });
            format!(
                "{chosen} (mean heading disagreement per scan with a first pass: the laser lines {:.3}°{track})",
                c.laser_lines.to_degrees()
            )
        }
    }
}

fn span(trajectory: &Trajectory) -> f64 {
    match (trajectory.poses.first(), trajectory.poses.last()) {
        (Some(a), Some(b)) => b.timestamp.seconds - a.timestamp.seconds,
        _ => 0.0,
    }
}

/// One line on the map's size: the cells its grids hold (tiles where scans landed), their
/// memory, and the extent of the cells seen on the finest grid (what `--map` writes).
fn describe_map(map: &GridPyramid) -> String {
    let held: usize = map.levels().iter().map(Grid::allocated_cells).sum();
    let bytes: usize = map.levels().iter().map(Grid::allocated_bytes).sum();
    let finest = map.finest();
    let r = finest.resolution();
    let extent = finest.known_bounds().map_or_else(
        || "nothing seen".to_owned(),
        |((i0, j0), (i1, j1))| {
            let (w, h) = (i1 - i0 + 1, j1 - j0 + 1);
            format!(
                "the cells seen span {:.1} × {:.1} m ({w} × {h} cells of {r} m)",
                f64::from(w) * r,
                f64::from(h) * r
            )
        },
    );
    format!(
        "map: {:.2} M cells held over {} grid(s) ({:.0} MB); {extent}",
        held as f64 / 1e6,
        map.levels().len(),
        bytes as f64 / 1e6
    )
}

/// Writes `STEM.pgm` + `STEM.yaml` (map_server) and `STEM.png` (with the trajectory).
fn write_map(mapper: &Mapper, trajectory: &Trajectory, stem: &Path) -> anyhow::Result<()> {
    let raster = raster(mapper.map().finest()).context("the map is empty")?;
    let with = |ext: &str| {
        let mut name = stem.as_os_str().to_owned();
        name.push(ext);
        PathBuf::from(name)
    };
    let thresholds = Thresholds::default();
    let write = |path: PathBuf,
                 f: &dyn Fn(&mut BufWriter<File>) -> std::io::Result<()>|
     -> anyhow::Result<()> {
        let file = File::create(&path).with_context(|| format!("creating {}", path.display()))?;
        let mut w = BufWriter::new(file);
        f(&mut w)
            .and_then(|()| w.flush())
            .with_context(|| format!("writing {}", path.display()))
    };
    let pgm = with(".pgm");
    let image_name = pgm
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    write(pgm, &|w| write_pgm(&raster, &thresholds, w))?;
    write(with(".yaml"), &|w| write_yaml(&raster, &image_name, w))?;
    let poses: Vec<Pose2> = trajectory.poses.iter().map(|p| p.pose).collect();
    write(with(".png"), &|w| {
        write_png_with_trajectory(&raster, &thresholds, &poses, w)
    })?;
    Ok(())
}

/// Options of `scan3d slam-eval`.
#[derive(Debug, clap::Args)]
pub struct SlamEvalArgs {
    /// The trajectory: `timestamp x y theta` per line.
    pub trajectory: PathBuf,
    /// The reference relations: `t1 t2 x y z roll pitch yaw` per line.
    pub relations: PathBuf,
    /// One JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
    /// A relation counts when both ends have a pose within this many seconds.
    #[arg(long, value_name = "S", default_value_t = 0.001)]
    pub max_dt: f64,
    /// `kummerle` (the published tables) or `cartographer` (its compute_relations_metrics).
    #[arg(long, default_value = "kummerle")]
    pub formula: Formula,
    /// Interpolate the pose at each relation end instead of taking the nearest one.
    #[arg(long)]
    pub interpolate: bool,
    /// Also list the N relations with the largest translational error (their two timestamps,
    /// span and errors), to see where a trajectory goes wrong. In the JSON as `worst`.
    #[arg(long, value_name = "N")]
    pub worst: Option<usize>,
}

/// Runs `scan3d slam-eval`.
pub fn run_eval(args: &SlamEvalArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    if !(args.max_dt.is_finite() && args.max_dt >= 0.0) {
        bail!(
            "--max-dt must be a non-negative number of seconds, not {}",
            args.max_dt
        );
    }
    let open = |path: &Path| -> anyhow::Result<BufReader<File>> {
        Ok(BufReader::new(
            File::open(path).with_context(|| format!("opening {}", path.display()))?,
        ))
    };
    let trajectory = read_trajectory(open(&args.trajectory)?)
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.trajectory.display()))?;
    let relations = read_relations(open(&args.relations)?)
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.relations.display()))?;
    if trajectory.poses.is_empty() {
        bail!("{}: no poses", args.trajectory.display());
    }
    let report = evaluate(
        &trajectory,
        &relations,
        &EvalOptions {
            max_dt: args.max_dt,
            formula: args.formula,
            interpolate: args.interpolate,
        },
    );
    // The largest translational errors first, only when asked for.
    let worst = args.worst.map(|n| {
        let mut worst: Vec<&RelationError> = report.per_relation.iter().collect();
        worst.sort_by(|a, b| b.trans_m.total_cmp(&a.trans_m));
        worst.truncate(n);
        worst
    });
    if args.json {
        let mut value = serde_json::to_value(&report)?;
        if let (Some(worst), Some(object)) = (&worst, value.as_object_mut()) {
            object.insert("worst".into(), serde_json::to_value(worst)?);
        }
        writeln!(out, "{value}")?;
        return Ok(());
    }
    write!(out, "{report}")?;
    if let Some(worst) = &worst {
        writeln!(out, "worst relations (translational error):")?;
        writeln!(
            out,
            "  {:>18} {:>18} {:>9} {:>9} {:>9}",
            "t1", "t2", "span s", "trans m", "rot deg"
        )?;
        for e in worst {
            writeln!(
                out,
                "  {:>18} {:>18} {:>9.1} {:>9.4} {:>9.3}",
                e.t1.text,
                e.t2.text,
                (e.t2.seconds - e.t1.seconds).abs(),
                e.trans_m,
                e.rot_deg
            )?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odometry_distortions_are_read_and_bounded() {
        let error = parse_wheel_error("0.05, -0.02,0.1").expect("three terms");
        assert_eq!(
            (error.per_rad, error.per_m, error.scale),
            (0.05, -0.02, 0.1)
        );
        for bad in ["0,0.02", "0,0.6,0", "0,nan,0", "a,b,c"] {
            assert!(parse_wheel_error(bad).is_err(), "{bad}");
        }
        let slips = parse_slips("60,0.3,-0.15").expect("a slip");
        assert_eq!(
            (slips.every, slips.translation, slips.rotation),
            (60.0, 0.3, -0.15)
        );
        for bad in ["0.5,0.3,0.1", "60,11,0", "60,0,4", "60,0.3"] {
            assert!(parse_slips(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_nearest_rank_quantile_is_a_value_of_the_list() {
        let values: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(nearest_rank(&values, 0.5), 50.0);
        assert_eq!(nearest_rank(&values, 0.99), 99.0);
        assert_eq!(nearest_rank(&values, 1.0), 100.0);
        assert_eq!(nearest_rank(&values, 0.0), 1.0);
        assert_eq!(nearest_rank(&[], 0.5), 0.0);
    }

    #[test]
    fn the_documented_slam_toml_is_exactly_the_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/slam.toml");
        assert_eq!(
            load_config(&path).expect("deploy/slam.toml"),
            MapperConfig::default()
        );
    }

    #[test]
    fn an_unknown_or_out_of_range_key_is_refused_with_its_place() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("slam.toml");
        std::fs::write(&path, "resolution = 0.05\n[matcher]\nfine_iteratons = 3\n").unwrap();
        let error = format!("{:#}", load_config(&path).unwrap_err());
        assert!(
            error.contains("fine_iteratons") && error.contains("line 3"),
            "{error}"
        );
        std::fs::write(&path, "levels = 40\n").unwrap();
        let error = format!("{:#}", load_config(&path).unwrap_err());
        assert!(error.contains("levels must be 1 to 6"), "{error}");
        for (text, said) in [
            ("[refine]\nsigma_floor = -0.01\n", "refine.sigma_floor"),
            (
                "[refine]\nvelocity_rotation_sigma = 0\n",
                "refine.velocity_rotation_sigma",
            ),
            ("[refine]\nmin_points = 0\n", "refine.min_points"),
            (
                "[update]\njoin_endpoints_within = 2.0\n",
                "update.join_endpoints_within",
            ),
            (
                "[update]\njoin_endpoints_within_without_odometry = -0.1\n",
                "update.join_endpoints_within_without_odometry",
            ),
            ("[refine.loss]\nkind = \"cauchy\"\nc = 0.0\n", "refine.loss"),
            ("[reentry]\nwindow = 5.0\n", "reentry.window"),
            ("[reentry]\nmax_scans = 0\n", "reentry.max_scans"),
            (
                "[motion]\npoor_match_ratio = 1.5\n",
                "motion.poor_match_ratio",
            ),
            (
                "[motion]\nvelocity_window = -1.0\n",
                "motion.velocity_window",
            ),
            ("[motion]\nwider_search = 50.0\n", "motion.wider_search"),
            (
                "[motion]\nodometry_bias_window = -5.0\n",
                "motion.odometry_bias_window",
            ),
            (
                "[motion]\nodometry_check_window = 600.0\n",
                "motion.odometry_check_window",
            ),
            (
                "[motion]\nodometry_check_threshold = -1.0\n",
                "motion.odometry_check_threshold",
            ),
            (
                "[motion]\nodometry_max_widening = 0.5\n",
                "motion.odometry_max_widening",
            ),
            (
                "[motion]\nout_of_order_poses = 100000\n",
                "motion.out_of_order_poses",
            ),
            (
                "[motion]\nout_of_order_back = -0.05\n",
                "motion.out_of_order_back",
            ),
            (
                "[motion]\nout_of_order_turn_back = 4.0\n",
                "motion.out_of_order_turn_back",
            ),
            (
                "[motion.velocity_search]\nmax_translation = 5.0\n",
                "max_translation",
            ),
            (
                "[matcher]\nreference_endpoints = -1.0\n",
                "matcher.reference_endpoints",
            ),
            ("max_range = 0.0\n", "max_range must be positive"),
        ] {
            std::fs::write(&path, text).unwrap();
            let error = format!("{:#}", load_config(&path).unwrap_err());
            assert!(error.contains(said), "{text}: {error}");
        }
    }
}

/// Options of `scan3d traj-eval`.
#[derive(Debug, clap::Args)]
pub struct TrajEvalArgs {
    /// The estimate: TUM lines `t x y z qx qy qz qw` (e.g. a snapshot's `trajectory.tum` or a
    /// pass's `passes/NAME/trajectory.tum`).
    pub estimate: PathBuf,
    /// The reference in the same frame and clock (e.g. `scan3d-sim rig --truth`).
    pub reference: PathBuf,
    /// Compare only the estimated poses from this time on (s, the files' clock).
    #[arg(long, value_name = "T")]
    pub from: Option<f64>,
    /// Compare only the estimated poses up to this time (s).
    #[arg(long, value_name = "T")]
    pub to: Option<f64>,
    /// One JSON object instead of the text.
    #[arg(long)]
    pub json: bool,
}

/// Runs `scan3d traj-eval`.
pub fn run_traj_eval(args: &TrajEvalArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    use scan3d_slam::tum::{read_tum, trajectory_error};
    let read = |path: &Path| -> anyhow::Result<Vec<scan3d_slam::tum::TumPose>> {
        let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
        read_tum(BufReader::new(file)).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
    };
    let estimate = read(&args.estimate)?;
    let reference = read(&args.reference)?;
    let Some(error) = trajectory_error(&estimate, &reference, args.from, args.to) else {
        bail!(
            "no pose of {} lies within the time span of {} (are both on the same clock?)",
            args.estimate.display(),
            args.reference.display()
        );
    };
    if args.json {
        writeln!(out, "{}", serde_json::to_string(&error)?)?;
    } else {
        writeln!(
            out,
            "{} poses compared ({} outside the reference): position RMSE {:.4} m (max {:.4} m), \
             heading RMSE {:.3}° (max {:.3}°)",
            error.compared,
            error.outside,
            error.position_rmse_m,
            error.position_max_m,
            error.heading_rmse_deg,
            error.heading_max_deg
        )?;
    }
    Ok(())
}
