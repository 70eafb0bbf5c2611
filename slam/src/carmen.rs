//! CARMEN laser logs (`.clf` / `.log`), the format of the classic 2D SLAM benchmark data
//! (Intel, ACES, MIT CSAIL, FR079): front laser scans from `FLASER` and `ROBOTLASER1` lines,
//! wheel odometry from `ODOM` lines. A streaming reader over [`BufRead`]: one line in memory at
//! a time, every count checked before anything is allocated for it.

use std::f64::consts::{FRAC_PI_2, PI};
use std::io::BufRead;

use crate::pose::Pose2;
use crate::text::{LineError, LineReader, NextLine, Timestamp, parse_finite};

/// The most readings (or remission values) a laser line may announce. Real lasers give at most
/// a few thousand per scan; a larger count means a corrupt line and is refused before any
/// buffer is sized from it.
pub const MAX_READINGS: usize = 10_000;

/// How many malformed lines a lenient read remembers in [`SkipCounts::first_malformed`].
pub const MALFORMED_KEPT: usize = 5;

/// How to read a log.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReadOptions {
    /// Skip malformed lines (counting them) instead of stopping at the first one.
    pub lenient: bool,
}

/// One front-laser scan: a `FLASER` or `ROBOTLASER1` line.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserScan {
    /// 1-based line number in the log.
    pub line: usize,
    /// The line's ipc timestamp, the clock the benchmark relations use.
    pub timestamp: Timestamp,
    /// Ranges (m) as logged, beam `i` at `angle_min + i * angle_increment`. Readings at the
    /// max-range sentinel (e.g. 81.83 m in Intel) are kept: deciding that they mean "no
    /// return" is the caller's (see [`CarmenLog::largest_reading`]).
    pub ranges: Vec<f32>,
    /// Angle of the first beam in the laser frame (rad, counter-clockwise, x forward).
    pub angle_min: f64,
    /// Angle between consecutive beams (rad).
    pub angle_increment: f64,
    /// The laser's maximum range (m) when the line states it (`ROBOTLASER1`); `FLASER` does not.
    pub max_range: Option<f64>,
    /// The robot's odometry pose at the scan, as the line gives it (`FLASER`'s `odom_x odom_y
    /// odom_theta`, `ROBOTLASER1`'s robot pose).
    pub odometry: Pose2,
    /// The laser in the robot frame. `ROBOTLASER1`: robot pose⁻¹ ⊕ laser pose; `FLASER` has no
    /// offset of its own: CARMEN keeps it in the `robot_frontlaser_*offset` parameters, which
    /// [`read_log`] applies when the log has them (otherwise the identity, until
    /// [`CarmenLog::set_front_laser_offset`]).
    pub laser_offset: Pose2,
    /// Whether the line itself states where the laser sits on the robot (`ROBOTLASER1`), so a
    /// configured offset does not replace it.
    pub offset_in_line: bool,
    /// The line's first pose triple (CARMEN's "laser pose": raw odometry in the benchmark logs,
    /// the corrected pose in "corrected" logs) — the script's `--pose estimate`.
    pub laser_pose: Pose2,
}

/// One `ODOM` line.
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryReading {
    /// 1-based line number in the log.
    pub line: usize,
    /// The line's ipc timestamp.
    pub timestamp: Timestamp,
    /// The odometry pose (m, m, rad).
    pub pose: Pose2,
    /// Translational velocity (m/s).
    pub tv: f64,
    /// Rotational velocity (rad/s).
    pub rv: f64,
    /// Acceleration as logged (m/s²).
    pub accel: f64,
}

/// Lines that produced neither a scan nor an odometry reading.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SkipCounts {
    /// Blank lines and `#` comments.
    pub comments: usize,
    /// `RLASER` lines: the rear laser, not used for mapping.
    pub rear_laser: usize,
    /// Lines of other message types (`PARAM`, `RAWLASER1`, `SYNC`, `TRUEPOS`, …).
    pub other_messages: usize,
    /// Malformed lines skipped by a lenient read.
    pub malformed: usize,
    /// The first [`MALFORMED_KEPT`] of those, with their line numbers and what was wrong.
    pub first_malformed: Vec<LineError>,
}

/// A whole log: its scans and odometry in file order, and what was skipped.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CarmenLog {
    /// The laser lines, in file order.
    pub scans: Vec<LaserScan>,
    /// The `ODOM` lines, in file order.
    pub odometry: Vec<OdometryReading>,
    /// Lines that gave neither.
    pub skipped: SkipCounts,
    /// The front laser's pose on the robot from the log's `PARAM robot_frontlaser_offset`,
    /// `robot_frontlaser_side_offset` and `robot_frontlaser_angular_offset` lines (CARMEN's
    /// names; missing ones are 0), `None` when it has none of them.
    pub front_laser_param: Option<Pose2>,
}

/// Reads a CARMEN log. Strict by default: the first malformed line is the error, naming its
/// line number and what is wrong. With `options.lenient` malformed lines are skipped and
/// counted in [`CarmenLog::skipped`]; a read failure ends the read either way.
pub fn read_log(reader: impl BufRead, options: &ReadOptions) -> Result<CarmenLog, LineError> {
    let mut lines = LineReader::new(reader);
    let mut log = CarmenLog::default();
    loop {
        let parsed = match lines.next_line()? {
            NextLine::End => break,
            NextLine::Line(line, text) => {
                parse_line(line, &text).map_err(|what| LineError { line, what })
            }
            NextLine::TooLong(e) => Err(e),
        };
        match parsed {
            Ok(Message::Scan(scan)) => log.scans.push(scan),
            Ok(Message::Odometry(odom)) => log.odometry.push(odom),
            Ok(Message::Comment) => log.skipped.comments += 1,
            Ok(Message::RearLaser) => log.skipped.rear_laser += 1,
            Ok(Message::Other) => log.skipped.other_messages += 1,
            Ok(Message::FrontLaserParam(axis, value)) => {
                let pose = log.front_laser_param.get_or_insert_with(Pose2::default);
                match axis {
                    OffsetAxis::Forward => pose.x = value,
                    OffsetAxis::Side => pose.y = value,
                    OffsetAxis::Angle => pose.theta = value,
                }
            }
            Err(e) if options.lenient => {
                log.skipped.malformed += 1;
                if log.skipped.first_malformed.len() < MALFORMED_KEPT {
                    log.skipped.first_malformed.push(e);
                }
            }
            Err(e) => return Err(e),
        }
    }
    if let Some(offset) = log.front_laser_param {
        log.set_front_laser_offset(offset);
    }
    Ok(log)
}

impl CarmenLog {
    /// Puts the front laser at `offset` in the robot frame on every scan whose line does not
    /// state its own (`FLASER`): the mapper then matches the laser where it is and reports the
    /// robot's pose, the one the benchmark relations refer to.
    pub fn set_front_laser_offset(&mut self, offset: Pose2) {
        for scan in self.scans.iter_mut().filter(|s| !s.offset_in_line) {
            scan.laser_offset = offset;
        }
    }

    /// Keeps the first laser line and every `every`-th after it (1 or 0: all), the `ODOM`
    /// lines untouched: the same run with scans `every` times sparser, to test the matcher
    /// against logs written less often than the ones its defaults were chosen on.
    pub fn keep_every(&mut self, every: usize) {
        if every > 1 {
            let scans = std::mem::take(&mut self.scans);
            self.scans = scans.into_iter().step_by(every).collect();
        }
    }

    /// One odometry pose per scan: the laser line's own odometry triple. This is what the
    /// reference script's `--carmen-to-traj` writes (its default `--pose odom`), so the raw
    /// odometry baselines of the benchmark notes are reproduced from it.
    pub fn odometry_poses(&self) -> Vec<Pose2> {
        self.scans.iter().map(|s| s.odometry).collect()
    }

    /// The `ODOM` lines as a track to read at any time; `None` when the log has none (MIT
    /// CSAIL).
    pub fn odometry_track(&self) -> Option<OdometryTrack> {
        if self.odometry.is_empty() {
            return None;
        }
        let mut readings: Vec<(f64, Pose2)> = self
            .odometry
            .iter()
            .map(|o| (o.timestamp.seconds, o.pose))
            .collect();
        readings.sort_by(|a, b| a.0.total_cmp(&b.0));
        Some(OdometryTrack { readings })
    }

    /// The largest range reading in the log. In the benchmark `FLASER` logs it is the
    /// "no return" sentinel (81.83 m Intel, 50.00 m ACES, 81.91 m CSAIL), which occurs often;
    /// a caller without `--max-range` can treat readings equal to it as no return.
    pub fn largest_reading(&self) -> Option<f32> {
        self.scans
            .iter()
            .flat_map(|s| s.ranges.iter().copied())
            .reduce(f32::max)
    }
}

/// A log's `ODOM` readings in time order.
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryTrack {
    readings: Vec<(f64, Pose2)>,
}

impl OdometryTrack {
    /// The odometry pose at `t` (s): SE(2) interpolation between the two readings around it,
    /// the end reading outside their span.
    pub fn at(&self, t: f64) -> Pose2 {
        let readings = &self.readings;
        let i = readings.partition_point(|r| r.0 < t);
        if i == 0 {
            return readings[0].1;
        }
        if i == readings.len() {
            return readings[i - 1].1;
        }
        let (t0, a) = readings[i - 1];
        let (t1, b) = readings[i];
        if t1 <= t0 {
            return b;
        }
        a.interpolate(&b, (t - t0) / (t1 - t0))
    }
}

enum Message {
    Scan(LaserScan),
    Odometry(OdometryReading),
    Comment,
    RearLaser,
    FrontLaserParam(OffsetAxis, f64),
    Other,
}

/// Which part of the front laser's pose a CARMEN parameter gives.
enum OffsetAxis {
    Forward,
    Side,
    Angle,
}

fn parse_line(line: usize, text: &str) -> Result<Message, String> {
    let fields: Vec<&str> = text.split_ascii_whitespace().collect();
    let Some((&tag, rest)) = fields.split_first() else {
        return Ok(Message::Comment);
    };
    if tag.starts_with('#') {
        return Ok(Message::Comment);
    }
    match tag {
        "FLASER" => parse_flaser(line, rest).map(Message::Scan),
        "ROBOTLASER1" => parse_robotlaser1(line, rest).map(Message::Scan),
        "ODOM" => parse_odom(line, rest).map(Message::Odometry),
        "RLASER" => Ok(Message::RearLaser),
        "PARAM" => parse_param(rest),
        _ => Ok(Message::Other),
    }
}

/// `PARAM name value [hostname [logger_timestamp]]`: the front laser's offset parameters are
/// kept (a non-numeric value is an error), every other parameter is skipped.
fn parse_param(rest: &[&str]) -> Result<Message, String> {
    let axis = match rest.first() {
        Some(&"robot_frontlaser_offset") => OffsetAxis::Forward,
        Some(&"robot_frontlaser_side_offset") => OffsetAxis::Side,
        Some(&"robot_frontlaser_angular_offset") => OffsetAxis::Angle,
        _ => return Ok(Message::Other),
    };
    let value = rest
        .get(1)
        .ok_or_else(|| format!("PARAM {} has no value", rest[0]))?;
    Ok(Message::FrontLaserParam(
        axis,
        parse_finite(value, &format!("PARAM {}", rest[0]))?,
    ))
}

/// A reading count from the log, refused above [`MAX_READINGS`] before anything is sized by it.
fn parse_count(field: Option<&&str>, tag: &str, what: &str) -> Result<usize, String> {
    let field = field.ok_or_else(|| format!("{tag} ends before its {what}"))?;
    let n: usize = field
        .parse()
        .map_err(|_| format!("{tag}: {what} is not a count: {field:?}"))?;
    if n > MAX_READINGS {
        return Err(format!(
            "{tag} says {n} {what}, more than the {MAX_READINGS} accepted"
        ));
    }
    Ok(n)
}

fn parse_ranges(fields: &[&str], tag: &str) -> Result<Vec<f32>, String> {
    fields
        .iter()
        .enumerate()
        .map(|(i, f)| match f.parse::<f32>() {
            Ok(r) if r.is_finite() && r >= 0.0 => Ok(r),
            Ok(_) => Err(format!(
                "{tag}: reading {} is not a finite range ≥ 0: {f:?}",
                i + 1
            )),
            Err(_) => Err(format!("{tag}: reading {} is not a number: {f:?}", i + 1)),
        })
        .collect()
}

fn parse_pose(fields: &[&str], tag: &str, what: &str) -> Result<Pose2, String> {
    let v = |i: usize, axis: &str| parse_finite(fields[i], &format!("{tag}: {what} {axis}"));
    Ok(Pose2::new(v(0, "x")?, v(1, "y")?, v(2, "theta")?))
}

/// `FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_timestamp [ipc_hostname
/// [logger_timestamp]]`, beam geometry as CARMEN's reader guesses it from n.
fn parse_flaser(line: usize, rest: &[&str]) -> Result<LaserScan, String> {
    const TAG: &str = "FLASER";
    let n = parse_count(rest.first(), TAG, "readings")?;
    let after = rest.len() - 1;
    // readings, two pose triples, the ipc timestamp; hostname and logger time may follow.
    if after < n + 7 || after > n + 9 {
        return Err(format!(
            "{TAG} says {n} readings but has {after} fields after the count (expected {} to {}: \
             readings, two poses, ipc timestamp, hostname, logger timestamp)",
            n + 7,
            n + 9
        ));
    }
    let f = &rest[1..];
    let ranges = parse_ranges(&f[..n], TAG)?;
    let laser_pose = parse_pose(&f[n..n + 3], TAG, "laser pose")?;
    let odometry = parse_pose(&f[n + 3..n + 6], TAG, "odometry pose")?;
    let timestamp = Timestamp::parse(f[n + 6], &format!("{TAG}: the ipc timestamp"))?;
    if let Some(logger) = f.get(n + 8) {
        parse_finite(logger, &format!("{TAG}: the logger timestamp"))?;
    }
    let (angle_min, angle_increment) = flaser_beam_geometry(n);
    Ok(LaserScan {
        line,
        timestamp,
        ranges,
        angle_min,
        angle_increment,
        max_range: None,
        odometry,
        laser_offset: Pose2::default(),
        offset_in_line: false,
        laser_pose,
    })
}

/// First beam angle and increment (rad) of an `FLASER` line with `n` readings, as CARMEN's
/// `carmen_laser_guess_angle_increment` (readlog.c): start −90°, 1° for 180/181 readings,
/// 0.5° for 360/361, 0.25° for 400/401, otherwise 180° spread over the n − 1 gaps.
pub fn flaser_beam_geometry(n: usize) -> (f64, f64) {
    let increment = match n {
        180 | 181 => PI / 180.0,
        360 | 361 => PI / 360.0,
        400 | 401 => PI / 720.0,
        0 | 1 => 0.0,
        _ => PI / (n - 1) as f64,
    };
    (-FRAC_PI_2, increment)
}

/// `ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode n
/// r_1..r_n m rem_1..rem_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv
/// forward_safety_dist side_safety_dist turn_axis ipc_timestamp [ipc_hostname [logger_timestamp]]`.
fn parse_robotlaser1(line: usize, rest: &[&str]) -> Result<LaserScan, String> {
    const TAG: &str = "ROBOTLASER1";
    if rest.len() < 8 {
        return Err(format!(
            "{TAG} has {} fields, fewer than its 8-field header",
            rest.len()
        ));
    }
    let header = |i: usize, what: &str| parse_finite(rest[i], &format!("{TAG}: {what}"));
    let angle_min = header(1, "start_angle")?;
    header(2, "fov")?;
    let angle_increment = header(3, "angular_res")?;
    let max_range = header(4, "max_range")?;
    let n = parse_count(rest.get(7), TAG, "readings")?;
    let ranges_at = 8;
    let m = parse_count(rest.get(ranges_at + n), TAG, "remission values")?;
    let tail_at = ranges_at + n + 1 + m;
    // two pose triples, tv rv, two safety distances, turn axis, ipc timestamp; host/logger may follow.
    let after = rest.len().saturating_sub(tail_at);
    if rest.len() < tail_at || !(12..=14).contains(&after) {
        return Err(format!(
            "{TAG} says {n} readings and {m} remission values but has {after} fields after them \
             (expected 12 to 14: two poses, tv, rv, safety distances, turn axis, ipc timestamp, \
             hostname, logger timestamp)"
        ));
    }
    let ranges = parse_ranges(&rest[ranges_at..ranges_at + n], TAG)?;
    for (i, f) in rest[ranges_at + n + 1..tail_at].iter().enumerate() {
        parse_finite(f, &format!("{TAG}: remission {}", i + 1))?;
    }
    let t = &rest[tail_at..];
    let laser_pose = parse_pose(&t[0..3], TAG, "laser pose")?;
    let odometry = parse_pose(&t[3..6], TAG, "robot pose")?;
    for (i, what) in [
        "tv",
        "rv",
        "forward_safety_dist",
        "side_safety_dist",
        "turn_axis",
    ]
    .iter()
    .enumerate()
    {
        parse_finite(t[6 + i], &format!("{TAG}: {what}"))?;
    }
    let timestamp = Timestamp::parse(t[11], &format!("{TAG}: the ipc timestamp"))?;
    if let Some(logger) = t.get(13) {
        parse_finite(logger, &format!("{TAG}: the logger timestamp"))?;
    }
    Ok(LaserScan {
        line,
        timestamp,
        ranges,
        angle_min,
        angle_increment,
        max_range: Some(max_range),
        odometry,
        laser_offset: odometry.between(&laser_pose),
        offset_in_line: true,
        laser_pose,
    })
}

/// `ODOM x y theta tv rv accel ipc_timestamp [ipc_hostname [logger_timestamp]]`.
fn parse_odom(line: usize, rest: &[&str]) -> Result<OdometryReading, String> {
    const TAG: &str = "ODOM";
    if rest.len() < 7 || rest.len() > 9 {
        return Err(format!(
            "{TAG} has {} fields (expected 7 to 9: x y theta tv rv accel ipc_timestamp \
             hostname logger_timestamp)",
            rest.len()
        ));
    }
    let pose = parse_pose(&rest[0..3], TAG, "pose")?;
    let v = |i: usize, what: &str| parse_finite(rest[i], &format!("{TAG}: {what}"));
    let (tv, rv, accel) = (v(3, "tv")?, v(4, "rv")?, v(5, "accel")?);
    let timestamp = Timestamp::parse(rest[6], &format!("{TAG}: the ipc timestamp"))?;
    if rest.len() == 9 {
        v(8, "the logger timestamp")?;
    }
    Ok(OdometryReading {
        line,
        timestamp,
        pose,
        tv,
        rv,
        accel,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flaser(n: usize, ranges: &str, tail: &str) -> String {
        format!("FLASER {n} {ranges} {tail}")
    }

    const TAIL: &str = "1.0 2.0 0.5 1.0 2.0 0.5 976052857.337530 nohost 0.000246";

    fn strict(text: &str) -> Result<CarmenLog, LineError> {
        read_log(text.as_bytes(), &ReadOptions::default())
    }

    #[test]
    fn an_flaser_line_gives_ranges_beam_geometry_odometry_and_the_timestamp_text() {
        let ranges: Vec<String> = (0..180).map(|i| format!("{}.25", i % 7)).collect();
        let text = format!("# a comment\n\n{}\n", flaser(180, &ranges.join(" "), TAIL));
        let log = strict(&text).unwrap();
        assert_eq!(log.skipped.comments, 2);
        let scan = &log.scans[0];
        assert_eq!(scan.line, 3);
        assert_eq!(scan.timestamp.text, "976052857.337530");
        assert_eq!(scan.timestamp.seconds, 976052857.33753);
        assert_eq!(scan.ranges.len(), 180);
        assert_eq!(scan.ranges[1], 1.25);
        assert_eq!(scan.angle_min, -FRAC_PI_2);
        assert!((scan.angle_increment.to_degrees() - 1.0).abs() < 1e-12);
        assert_eq!(scan.max_range, None);
        assert_eq!(scan.odometry, Pose2::new(1.0, 2.0, 0.5));
        assert_eq!(scan.laser_offset, Pose2::default());
    }

    #[test]
    fn beam_increments_follow_carmens_guess_from_the_reading_count() {
        for (n, deg) in [(180, 1.0), (181, 1.0), (360, 0.5), (361, 0.5), (401, 0.25)] {
            let (start, inc) = flaser_beam_geometry(n);
            assert_eq!(start, -FRAC_PI_2);
            assert!((inc.to_degrees() - deg).abs() < 1e-12, "{n} readings");
        }
        assert!((flaser_beam_geometry(91).1.to_degrees() - 2.0).abs() < 1e-12);
    }

    #[test]
    fn a_robotlaser1_line_gives_its_own_geometry_and_the_laser_offset_from_the_robot_pose() {
        // Robot at (1, 2) facing +y; laser 0.1 m ahead of it, same heading.
        let line = "ROBOTLASER1 0 -1.25 2.5 0.5 30.0 0.01 0 3 1.0 2.0 3.0 2 0.1 0.2 \
                    1.0 2.1 1.5707963267948966 1.0 2.0 1.5707963267948966 0.3 0.1 0.5 0.2 0 \
                    1.5 host 1.6";
        let log = strict(line).unwrap();
        let scan = &log.scans[0];
        assert_eq!(scan.ranges, vec![1.0, 2.0, 3.0]);
        assert_eq!((scan.angle_min, scan.angle_increment), (-1.25, 0.5));
        assert_eq!(scan.max_range, Some(30.0));
        assert_eq!(scan.odometry, Pose2::new(1.0, 2.0, FRAC_PI_2));
        assert!((scan.laser_offset.x - 0.1).abs() < 1e-12);
        assert!(scan.laser_offset.y.abs() < 1e-12 && scan.laser_offset.theta.abs() < 1e-12);
        assert_eq!(scan.timestamp.text, "1.5");
    }

    #[test]
    fn the_front_laser_offset_comes_from_carmen_params_or_the_caller_and_spares_robotlaser1() {
        let ranges = vec!["1.5"; 360].join(" ");
        let text = format!(
            "PARAM robot_frontlaser_offset -0.04 nohost 0.0\n\
             PARAM robot_frontlaser_angular_offset 0.01 nohost 0.0\n{}\n",
            flaser(360, &ranges, TAIL)
        );
        let mut log = strict(&text).unwrap();
        assert_eq!(log.front_laser_param, Some(Pose2::new(-0.04, 0.0, 0.01)));
        let scan = &log.scans[0];
        assert_eq!(scan.ranges.len(), 360);
        assert!((scan.angle_increment.to_degrees() - 0.5).abs() < 1e-12);
        assert_eq!(scan.laser_offset, Pose2::new(-0.04, 0.0, 0.01));
        assert!(!scan.offset_in_line);
        assert_eq!(log.skipped.other_messages, 0);

        let robotlaser = "ROBOTLASER1 0 -1.557706 3.141593 0.017453 81.9 0 0 2 1.0 2.0 0 \
                          1.22 0.0 0.0 1.0 0.0 0.0 0 0 0 0 0 1.5 nohost 0.0";
        let mut mixed = strict(&format!("{text}{robotlaser}\n")).unwrap();
        mixed.set_front_laser_offset(Pose2::new(0.04, 0.0, 0.0));
        assert_eq!(mixed.scans[0].laser_offset, Pose2::new(0.04, 0.0, 0.0));
        let own = mixed.scans[1].laser_offset;
        assert!((own.x - 0.22).abs() < 1e-12 && own.y.abs() < 1e-12 && own.theta.abs() < 1e-12);
        assert_eq!(mixed.scans[1].angle_min, -1.557706);

        log.set_front_laser_offset(Pose2::default());
        assert_eq!(log.scans[0].laser_offset, Pose2::default());
        let err = strict("PARAM robot_frontlaser_offset ahead nohost 0").unwrap_err();
        assert!(err.to_string().contains("robot_frontlaser_offset"), "{err}");
    }

    #[test]
    fn odom_lines_rear_lasers_and_other_messages_are_read_or_counted() {
        let text = "ODOM 0.000000 0.000000 -0.002458 0.1 0.2 0.0 976052857.337284 nohost 0.0\n\
                    RLASER 2 1.0 1.0 0 0 0 0 0 0 5.0 h 5.0\n\
                    PARAM robot_front_laser_max 50.0 nohost 0.0\n";
        let log = strict(text).unwrap();
        assert_eq!(log.odometry.len(), 1);
        assert_eq!(log.odometry[0].pose.theta, -0.002458);
        assert_eq!((log.odometry[0].tv, log.odometry[0].rv), (0.1, 0.2));
        assert_eq!(log.odometry[0].timestamp.text, "976052857.337284");
        assert!(log.scans.is_empty());
        assert_eq!((log.skipped.rear_laser, log.skipped.other_messages), (1, 1));
    }

    #[test]
    fn a_reading_count_that_disagrees_with_the_fields_is_one_error_with_the_line_number() {
        let text = format!("ODOM 0 0 0 0 0 0 1.0\n{}", flaser(180, "1 2 3 4 5", TAIL));
        let err = strict(&text).unwrap_err();
        assert_eq!(err.line, 2);
        assert_eq!(
            err.to_string(),
            "line 2: FLASER says 180 readings but has 14 fields after the count (expected 187 \
             to 189: readings, two poses, ipc timestamp, hostname, logger timestamp)"
        );
    }

    #[test]
    fn non_numeric_and_non_finite_fields_are_named() {
        let err = strict(&flaser(2, "1.0 x", TAIL)).unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 1: FLASER: reading 2 is not a number: \"x\""
        );
        let err = strict(&flaser(2, "1.0 NaN", TAIL)).unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 1: FLASER: reading 2 is not a finite range ≥ 0: \"NaN\""
        );
        let err = strict("ODOM 0 inf 0 0 0 0 1.0").unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 1: ODOM: pose y is not finite: \"inf\""
        );
        let err = strict(&flaser(2, "1 2", "0 0 0 0 0 0 when nohost 0")).unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 1: FLASER: the ipc timestamp is not a number: \"when\""
        );
    }

    #[test]
    fn a_huge_reading_count_is_refused_before_anything_is_allocated() {
        let err = strict("FLASER 4000000000 1 2 3").unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 1: FLASER says 4000000000 readings, more than the 10000 accepted"
        );
        let err = strict("ROBOTLASER1 0 0 0 0 0 0 0 2 1 1 99999999 1").unwrap_err();
        assert!(
            err.to_string()
                .contains("99999999 remission values, more than"),
            "{err}"
        );
    }

    #[test]
    fn a_lenient_read_skips_malformed_lines_and_reports_the_first_few() {
        let good = flaser(2, "1 2", TAIL);
        let mut text = String::new();
        for i in 0..8 {
            text += &good;
            text += "\n";
            text += &format!("FLASER 2 1 {i}\n"); // too short
        }
        let log = read_log(text.as_bytes(), &ReadOptions { lenient: true }).unwrap();
        assert_eq!(log.scans.len(), 8);
        assert_eq!(log.skipped.malformed, 8);
        let lines: Vec<usize> = log.skipped.first_malformed.iter().map(|e| e.line).collect();
        assert_eq!(lines, vec![2, 4, 6, 8, 10]);
        assert!(strict(&text).is_err());
    }

    #[test]
    fn an_over_long_line_is_malformed_and_a_read_failure_ends_even_a_lenient_read() {
        let mut text = format!("FLASER 1 {}\n", "9".repeat(crate::text::MAX_LINE_BYTES));
        text += &flaser(2, "1 2", TAIL);
        let log = read_log(text.as_bytes(), &ReadOptions { lenient: true }).unwrap();
        assert_eq!((log.scans.len(), log.skipped.malformed), (1, 1));
        assert_eq!(log.scans[0].line, 2);
        assert_eq!(
            strict(&text).unwrap_err().to_string(),
            "line 1: longer than 1048576 bytes"
        );

        /// Gives one good line, then fails.
        struct Failing(bool);
        impl std::io::Read for Failing {
            fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
                if std::mem::replace(&mut self.0, true) {
                    return Err(std::io::Error::other("disk on fire"));
                }
                let line = b"ODOM 0 0 0 0 0 0 1.0\n";
                buf[..line.len()].copy_from_slice(line);
                Ok(line.len())
            }
        }
        let reader = std::io::BufReader::new(Failing(false));
        let err = read_log(reader, &ReadOptions { lenient: true }).unwrap_err();
        assert_eq!(err.to_string(), "line 2: cannot read: disk on fire");
    }

    #[test]
    fn the_odom_lines_are_a_track_read_between_its_readings() {
        let text = format!(
            "ODOM 1 0 1.0 0 0 0 11.0\nODOM 0 0 0 0 0 0 10.0\n{}\n",
            flaser(2, "1 2", "9 9 0 9 9 0 10.25"),
        );
        let log = strict(&text).unwrap();
        assert_eq!(log.odometry_poses(), vec![Pose2::new(9.0, 9.0, 0.0)]);
        let track = log.odometry_track().expect("two ODOM lines");
        // A quarter of the way along the SE(2) path from (0, 0, 0) to (1, 0, 1), whatever the
        // order of the lines.
        let (a, b) = (Pose2::new(0.0, 0.0, 0.0), Pose2::new(1.0, 0.0, 1.0));
        let d = a.between(&b);
        let expected = a.compose(&Pose2::new(0.25 * d.x, 0.25 * d.y, 0.25 * d.theta));
        let p = track.at(10.25);
        assert!((p.x - expected.x).abs() < 1e-12 && (p.y - expected.y).abs() < 1e-12);
        assert!((p.theta - 0.25).abs() < 1e-12);
        // Outside their span, the end readings.
        assert_eq!(track.at(12.0), b);
        assert_eq!(track.at(9.0), a);
        let no_odom = strict(&flaser(2, "1 2", "9 8 0.1 7 6 0.2 1.0")).unwrap();
        assert!(no_odom.odometry_track().is_none());
    }

    #[test]
    fn keeping_every_third_scan_keeps_the_first_and_each_third_after_and_the_odom_lines() {
        let mut text = String::from("ODOM 0 0 0 0 0 0 0.5\n");
        for i in 0..8 {
            text += &flaser(2, "1 2", &format!("{i} 0 0 {i} 0 0 {i}.0"));
            text.push('\n');
        }
        let mut log = strict(&text).unwrap();
        log.keep_every(1);
        assert_eq!(log.scans.len(), 8);
        log.keep_every(3);
        let kept: Vec<f64> = log.scans.iter().map(|s| s.timestamp.seconds).collect();
        assert_eq!(kept, vec![0.0, 3.0, 6.0]);
        assert_eq!(log.odometry.len(), 1);
    }
}
