//! The pushed trolley of `scan3d-sim rig --trolley`: a path through the room and its exact
//! kinematics, a pure function of time.
//!
//! A path ([`TrolleyPath`]) starts at a point of the room, heading towards its first waypoint,
//! and runs through waypoints: straight legs from one to the next, each corner rounded by a
//! smooth turn. The trolley rests for `rest_s` from the rig's start, speeds up, follows the
//! path at each leg's speed and stops at the last waypoint, where it stays
//! ([`TrolleyPath::end_of_path_s`]).
//!
//! Smoothness, so the IMU sees plausible signals:
//! - a turn of angle θ with tightest radius R is 2|θ|R long; its curvature rises and falls as
//!   κ(u) = κ_peak·sin²(πu/L) with κ_peak = 1/R, so curvature, yaw rate and centripetal
//!   acceleration are continuous and the yaw acceleration is bounded; the turn is symmetric,
//!   so the straight legs lie on the lines between the waypoints (the path cuts each corner);
//! - a speed change from v₀ to v₁ follows v₀ + (v₁ − v₀)(1 − cos(πτ/T))/2 with
//!   T = π|v₁ − v₀|/(2·max_accel_m_s2): the tangential acceleration is continuous and at most
//!   `max_accel_m_s2`. The trolley speeds up from rest at the start, changes speed at the end
//!   of the turn that begins a leg, and slows down to rest exactly at the last waypoint.
//!
//! Time `t` is in seconds since the rig's start (the emulators' time base, [`BaseTrajectory`]
//! takes nanoseconds). The frame of the trolley is `base`: origin at its reference point on
//! the floor (the point that follows the path), x forwards, z up.
//!
//! The path file (TOML, `scan3d-sim rig --trolley PATH.toml`, docs/simulator.md):
//!
//! ```toml
//! rest_s = 20.0           # at rest from the rig's start (default 20)
//! speed_m_s = 0.3         # speed of every leg unless the waypoint says (default 0.3)
//! turn_radius_m = 0.6     # tightest radius of every turn unless the waypoint says (default 0.6)
//! max_accel_m_s2 = 0.2    # of the speed changes (default 0.2)
//! start = [1.6, 0.85]     # x, y in the room, m; the heading is towards the first waypoint
//!
//! [[waypoint]]
//! x = 6.3
//! y = 0.85
//! speed_m_s = 0.25        # on the leg that ends here (optional)
//! turn_radius_m = 0.6     # of the turn at this waypoint (optional)
//! ```

use std::f64::consts::PI;
use std::path::Path;
use std::sync::Arc;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use scan3d_service::config::{ConfigError, parse_toml, read_text};
use serde::Deserialize;
use toml::Spanned;

use crate::world::{PoseSource, Shape, World};

/// Seconds the default path rests before it moves.
pub const DEFAULT_REST_S: f64 = 20.0;
/// Default speed of a leg, m/s.
pub const DEFAULT_SPEED_M_S: f64 = 0.3;
/// Default tightest radius of a turn, m.
pub const DEFAULT_TURN_RADIUS_M: f64 = 0.6;
/// Default bound of the tangential acceleration, m/s².
pub const DEFAULT_MAX_ACCEL_M_S2: f64 = 0.2;
/// Bound of the centripetal acceleration v²/R at a turn's tightest point, m/s².
pub const MAX_LATERAL_ACCEL_M_S2: f64 = 1.0;
/// Sharpest turn at a waypoint, degrees (the turn's tangent length grows without bound at 180°).
pub const MAX_TURN_DEG: f64 = 135.0;
/// Most waypoints a path file may hold.
pub const MAX_WAYPOINTS: usize = 1000;
/// How far the trolley's reference point must stay from walls and furniture, m (half its
/// footprint's diagonal, 0.6 × 0.4 m, rounded up).
pub const TROLLEY_CLEARANCE_M: f64 = 0.4;
/// The trolley's height, m: furniture below it is in its way.
pub const TROLLEY_HEIGHT_M: f64 = 1.2;

/// Arc-length spacing of the precomputed positions, m.
const GRID_M: f64 = 0.01;

/// The planar state of the trolley's `base` at one instant, in the room frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrolleyState {
    /// Distance travelled along the path, m.
    pub s_m: f64,
    /// Position of the reference point, m.
    pub position_m: [f64; 2],
    /// Heading of base x, radians counter-clockwise from room x (not wrapped: it accumulates
    /// the turns).
    pub heading_rad: f64,
    /// Speed along the path, m/s (never negative).
    pub speed_m_s: f64,
    /// Tangential acceleration (d speed / dt), m/s².
    pub tangential_accel_m_s2: f64,
    /// Curvature of the path here, 1/m (positive: turning left).
    pub curvature_per_m: f64,
    /// Yaw rate, rad/s (positive counter-clockwise seen from above).
    pub yaw_rate_rad_s: f64,
    /// Yaw acceleration, rad/s².
    pub yaw_accel_rad_s2: f64,
    /// Velocity, m/s.
    pub velocity_m_s: [f64; 2],
    /// Acceleration (tangential plus centripetal), m/s².
    pub accel_m_s2: [f64; 2],
}

impl TrolleyState {
    /// The pose of `base` in `room` (on the floor, level).
    pub fn pose(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(self.position_m[0], self.position_m[1], 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.heading_rad),
        )
    }

    /// The same state as a [`BaseMotion`] (3D vectors in the room frame).
    pub fn motion(&self) -> BaseMotion {
        BaseMotion {
            pose: self.pose(),
            angular_velocity_rad_s: Vector3::new(0.0, 0.0, self.yaw_rate_rad_s),
            angular_accel_rad_s2: Vector3::new(0.0, 0.0, self.yaw_accel_rad_s2),
            accel_m_s2: Vector3::new(self.accel_m_s2[0], self.accel_m_s2[1], 0.0),
        }
    }
}

/// How a rigid `base` moves at one instant, in the room frame: what an IMU on it measures and
/// where a sensor on it points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaseMotion {
    /// `base` → `room`.
    pub pose: Isometry3<f64>,
    /// Angular velocity, rad/s, room frame.
    pub angular_velocity_rad_s: Vector3<f64>,
    /// Angular acceleration, rad/s², room frame.
    pub angular_accel_rad_s2: Vector3<f64>,
    /// Acceleration of `base`'s origin, m/s², room frame (without gravity).
    pub accel_m_s2: Vector3<f64>,
}

/// A `base` moving through the room on the emulators' time base (ns since the rig's start).
pub trait BaseTrajectory: std::fmt::Debug + Send + Sync {
    /// The motion at simulated time `t_ns`.
    fn motion_at(&self, t_ns: u64) -> BaseMotion;
}

/// A `base` that stands still.
impl BaseTrajectory for Isometry3<f64> {
    fn motion_at(&self, _t_ns: u64) -> BaseMotion {
        BaseMotion {
            pose: *self,
            angular_velocity_rad_s: Vector3::zeros(),
            angular_accel_rad_s2: Vector3::zeros(),
            accel_m_s2: Vector3::zeros(),
        }
    }
}

/// A sensor mounted on a moving `base`: a [`PoseSource`] for the lidar emulators.
#[derive(Debug, Clone)]
pub struct OnBase {
    /// How the base moves.
    pub base: Arc<dyn BaseTrajectory>,
    /// The sensor's mount, sensor → base.
    pub mount: Isometry3<f64>,
}

impl PoseSource for OnBase {
    fn pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        self.base.motion_at(t_ns).pose * self.mount
    }
}

/// One piece of the path's geometry, by arc length.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Piece {
    /// A straight at constant heading.
    Straight,
    /// A turn of `angle_rad` (signed) with curvature `peak`·sin²(πu/L), peak = 2·angle/L.
    Turn { angle_rad: f64 },
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Segment {
    s0: f64,
    length: f64,
    heading0: f64,
    piece: Piece,
}

impl Segment {
    /// Heading, curvature and d curvature / ds at `u` metres into the segment.
    fn at(&self, u: f64) -> (f64, f64, f64) {
        match self.piece {
            Piece::Straight => (self.heading0, 0.0, 0.0),
            Piece::Turn { angle_rad } => {
                let l = self.length;
                let peak = 2.0 * angle_rad / l;
                let w = 2.0 * PI * u / l;
                let heading = self.heading0 + peak * (u / 2.0 - l / (4.0 * PI) * w.sin());
                let curvature = peak * (PI * u / l).sin().powi(2);
                let dcurvature = peak * (PI / l) * w.sin();
                (heading, curvature, dcurvature)
            }
        }
    }
}

/// One speed phase of the motion, by time since the motion began.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Phase {
    t0: f64,
    s0: f64,
    v0: f64,
    v1: f64,
    duration: f64,
}

impl Phase {
    /// Distance since the phase began, speed and tangential acceleration at `tau`.
    fn at(&self, tau: f64) -> (f64, f64, f64) {
        if self.v0 == self.v1 {
            return (self.v0 * tau, self.v0, 0.0);
        }
        let dv = self.v1 - self.v0;
        let w = PI / self.duration;
        let s = self.v0 * tau + dv / 2.0 * (tau - (w * tau).sin() / w);
        let v = self.v0 + dv * (1.0 - (w * tau).cos()) / 2.0;
        let a = dv * w / 2.0 * (w * tau).sin();
        (s, v, a)
    }
}

/// A speed change starting at arc length `s`: from `v0` to `v1`.
#[derive(Debug, Clone, Copy)]
struct SpeedChange {
    s: f64,
    v0: f64,
    v1: f64,
    /// The waypoint line it belongs to, for errors.
    line: usize,
}

/// A validated trolley path with its kinematics (see the [module docs](self)).
#[derive(Debug, Clone)]
pub struct TrolleyPath {
    start: [f64; 2],
    waypoints: Vec<[f64; 2]>,
    rest_s: f64,
    segments: Vec<Segment>,
    phases: Vec<Phase>,
    length_m: f64,
    motion_s: f64,
    /// Positions every [`GRID_M`] of arc length.
    grid: Vec<[f64; 2]>,
}

/// A waypoint as the path file writes it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct WaypointSpec {
    x: Spanned<f64>,
    y: Spanned<f64>,
    speed_m_s: Option<Spanned<f64>>,
    turn_radius_m: Option<Spanned<f64>>,
}

/// The path file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct PathSpec {
    rest_s: Option<Spanned<f64>>,
    speed_m_s: Option<Spanned<f64>>,
    turn_radius_m: Option<Spanned<f64>>,
    max_accel_m_s2: Option<Spanned<f64>>,
    start: Spanned<[f64; 2]>,
    #[serde(default)]
    waypoint: Vec<Spanned<WaypointSpec>>,
}

/// A waypoint after parsing: where, how fast the leg to it is, the radius of its turn, and the
/// line it was written on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Waypoint {
    /// Position in the room, m.
    pub xy: [f64; 2],
    /// Speed of the leg that ends here, m/s.
    pub speed_m_s: f64,
    /// Tightest radius of the turn here, m.
    pub turn_radius_m: f64,
    /// Line in the path file (0 when built in code).
    pub line: usize,
}

/// The whole path before its kinematics are built.
#[derive(Debug, Clone, PartialEq)]
pub struct PathSettings {
    /// Seconds at rest from the rig's start.
    pub rest_s: f64,
    /// Bound of the tangential acceleration, m/s².
    pub max_accel_m_s2: f64,
    /// Where the trolley starts, m.
    pub start: [f64; 2],
    /// The waypoints, at least one.
    pub waypoints: Vec<Waypoint>,
}

/// An error at a line of the path file (0: no line).
type LineError = (usize, String);

fn line_of(text: &str, span: std::ops::Range<usize>) -> usize {
    text.get(..span.start)
        .map_or(0, |head| head.bytes().filter(|&b| b == b'\n').count())
        + 1
}

impl TrolleyPath {
    /// The default path through the demo room ([`World::conference_room`]): three sides of a
    /// loop around the table, clear of the chairs, the boxes, the door and the glass (at least
    /// [`TROLLEY_CLEARANCE_M`]), 15.9 m at 0.2–0.3 m/s with three left turns: about 65 s of
    /// motion after [`DEFAULT_REST_S`] at rest.
    pub fn demo_room() -> Self {
        let wp = |x: f64, y: f64, speed_m_s: f64| Waypoint {
            xy: [x, y],
            speed_m_s,
            turn_radius_m: DEFAULT_TURN_RADIUS_M,
            line: 0,
        };
        Self::new(&PathSettings {
            rest_s: DEFAULT_REST_S,
            max_accel_m_s2: DEFAULT_MAX_ACCEL_M_S2,
            start: [1.6, 0.85],
            waypoints: vec![
                wp(6.3, 0.85, 0.25),
                wp(6.3, 5.2, 0.3),
                wp(1.5, 5.2, 0.25),
                wp(1.5, 2.2, 0.2),
            ],
        })
        .expect("the default path is valid")
    }

    /// Parses and validates a path file's text; `origin` names it in errors, which start with
    /// the line of the offending key.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        let error = |(line, message): LineError| ConfigError::Parse {
            path: origin.to_path_buf(),
            message: if line > 0 {
                format!("line {line}: {message}")
            } else {
                message
            },
        };
        let spec: PathSpec = parse_toml(text, origin)?;
        let settings = Self::settings(text, spec).map_err(error)?;
        Self::build(&settings).map_err(error)
    }

    /// Reads and parses a path file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::from_toml_str(&read_text(path)?, path)
    }

    /// A path from settings built in code; the error names the waypoint (by index) or setting.
    pub fn new(settings: &PathSettings) -> Result<Self, String> {
        Self::build(settings).map_err(|(_, message)| message)
    }

    fn settings(text: &str, spec: PathSpec) -> Result<PathSettings, LineError> {
        let value = |v: &Option<Spanned<f64>>,
                     default: f64,
                     key: &str,
                     range: std::ops::RangeInclusive<f64>,
                     unit: &str|
         -> Result<f64, LineError> {
            match v {
                None => Ok(default),
                Some(v) => {
                    let x = *v.get_ref();
                    if x.is_finite() && range.contains(&x) {
                        Ok(x)
                    } else {
                        Err((
                            line_of(text, v.span()),
                            format!(
                                "`{key}` = {x}: expected {} to {} {unit}",
                                range.start(),
                                range.end()
                            ),
                        ))
                    }
                }
            }
        };
        let rest_s = value(&spec.rest_s, DEFAULT_REST_S, "rest_s", 0.0..=3600.0, "s")?;
        let speed = value(
            &spec.speed_m_s,
            DEFAULT_SPEED_M_S,
            "speed_m_s",
            0.05..=2.0,
            "m/s",
        )?;
        let radius = value(
            &spec.turn_radius_m,
            DEFAULT_TURN_RADIUS_M,
            "turn_radius_m",
            0.1..=100.0,
            "m",
        )?;
        let max_accel_m_s2 = value(
            &spec.max_accel_m_s2,
            DEFAULT_MAX_ACCEL_M_S2,
            "max_accel_m_s2",
            0.01..=2.0,
            "m/s²",
        )?;
        let start_line = line_of(text, spec.start.span());
        let start = *spec.start.get_ref();
        if !start.iter().all(|v| v.is_finite() && v.abs() <= 1000.0) {
            return Err((
                start_line,
                format!("`start` = {start:?}: expected [x, y] in metres, at most 1000 m"),
            ));
        }
        if spec.waypoint.is_empty() {
            return Err((
                start_line,
                "no [[waypoint]]: a path needs at least one after `start`".to_owned(),
            ));
        }
        if spec.waypoint.len() > MAX_WAYPOINTS {
            let line = line_of(text, spec.waypoint[MAX_WAYPOINTS].span());
            return Err((
                line,
                format!("{} waypoints: at most {MAX_WAYPOINTS}", spec.waypoint.len()),
            ));
        }
        let mut waypoints = Vec::with_capacity(spec.waypoint.len());
        for entry in &spec.waypoint {
            let line = line_of(text, entry.span());
            let w = entry.get_ref();
            for (key, v) in [("x", &w.x), ("y", &w.y)] {
                let x = *v.get_ref();
                if !(x.is_finite() && x.abs() <= 1000.0) {
                    return Err((
                        line_of(text, v.span()),
                        format!("waypoint `{key}` = {x}: expected metres, at most 1000"),
                    ));
                }
            }
            waypoints.push(Waypoint {
                xy: [*w.x.get_ref(), *w.y.get_ref()],
                speed_m_s: value(&w.speed_m_s, speed, "speed_m_s", 0.05..=2.0, "m/s")?,
                turn_radius_m: value(&w.turn_radius_m, radius, "turn_radius_m", 0.1..=100.0, "m")?,
                line,
            });
        }
        Ok(PathSettings {
            rest_s,
            max_accel_m_s2,
            start,
            waypoints,
        })
    }

    fn build(settings: &PathSettings) -> Result<Self, LineError> {
        let where_ = |i: usize, w: &Waypoint| {
            if w.line > 0 {
                format!("the waypoint at line {}", w.line)
            } else {
                format!("waypoint #{}", i + 1)
            }
        };
        let err = |w: &Waypoint, message: String| (w.line, message);
        let n = settings.waypoints.len();
        if n == 0 {
            return Err((0, "a path needs at least one waypoint".to_owned()));
        }
        // Corner points: start, the waypoints.
        let mut points = vec![settings.start];
        points.extend(settings.waypoints.iter().map(|w| w.xy));
        let mut directions = Vec::with_capacity(n);
        let mut lengths = Vec::with_capacity(n);
        for (i, w) in settings.waypoints.iter().enumerate() {
            let (a, b) = (points[i], points[i + 1]);
            let d = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            if d < 0.01 {
                return Err(err(
                    w,
                    format!(
                        "{} is {d:.3} m from the point before it: at least 0.01 m",
                        where_(i, w)
                    ),
                ));
            }
            directions.push((b[1] - a[1]).atan2(b[0] - a[0]));
            lengths.push(d);
        }
        // The turn at each waypoint but the last: its angle, length and tangent length.
        let mut turns = Vec::with_capacity(n);
        for (i, w) in settings.waypoints.iter().enumerate() {
            if i + 1 == n {
                turns.push((0.0, 0.0, 0.0));
                continue;
            }
            let angle = wrap_pi(directions[i + 1] - directions[i]);
            if angle.abs() > MAX_TURN_DEG.to_radians() {
                return Err(err(
                    w,
                    format!(
                        "{} turns the trolley by {:.1}°: at most {MAX_TURN_DEG}° (add a \
                         waypoint to split the turn)",
                        where_(i, w),
                        angle.to_degrees()
                    ),
                ));
            }
            let lateral =
                w.speed_m_s.max(settings.waypoints[i + 1].speed_m_s).powi(2) / w.turn_radius_m;
            if lateral > MAX_LATERAL_ACCEL_M_S2 {
                return Err(err(
                    w,
                    format!(
                        "the turn at {} pushes the trolley sideways at {lateral:.2} m/s² \
                         (speed²/turn_radius_m): at most {MAX_LATERAL_ACCEL_M_S2}; slow down \
                         or widen the turn",
                        where_(i, w)
                    ),
                ));
            }
            if angle.abs() < 1e-9 {
                turns.push((0.0, 0.0, 0.0));
                continue;
            }
            let length = 2.0 * angle.abs() * w.turn_radius_m;
            let turn = Segment {
                s0: 0.0,
                length,
                heading0: 0.0,
                piece: Piece::Turn { angle_rad: angle },
            };
            let [x, y] = integrate(&[turn], 0.0, length, 400);
            let tangent = x - y / angle.tan();
            turns.push((angle, length, tangent));
        }
        // Segments, checking each straight is long enough for the turns at its ends.
        let mut segments = Vec::new();
        let mut s = 0.0;
        let mut heading = directions[0];
        let mut turn_end_s = vec![0.0; n];
        for (i, w) in settings.waypoints.iter().enumerate() {
            let before = if i == 0 { 0.0 } else { turns[i - 1].2 };
            let straight = lengths[i] - before - turns[i].2;
            if straight < -1e-9 {
                return Err(err(
                    w,
                    format!(
                        "{} is {:.2} m from the point before it; the turns at both ends need \
                         {:.2} m (bring the waypoints further apart or lower turn_radius_m)",
                        where_(i, w),
                        lengths[i],
                        before + turns[i].2
                    ),
                ));
            }
            let straight = straight.max(0.0);
            if straight > 0.0 {
                segments.push(Segment {
                    s0: s,
                    length: straight,
                    heading0: heading,
                    piece: Piece::Straight,
                });
                s += straight;
            }
            let (angle, length, _) = turns[i];
            if length > 0.0 {
                segments.push(Segment {
                    s0: s,
                    length,
                    heading0: heading,
                    piece: Piece::Turn { angle_rad: angle },
                });
                s += length;
                heading += angle;
            }
            turn_end_s[i] = s;
        }
        let length_m = s;
        // Speed changes: from rest at the start, at the end of each turn, to rest at the end.
        let ramp = |v0: f64, v1: f64| {
            let duration = PI * (v1 - v0).abs() / (2.0 * settings.max_accel_m_s2);
            (duration, (v0 + v1) / 2.0 * duration)
        };
        let first = &settings.waypoints[0];
        let mut changes = vec![SpeedChange {
            s: 0.0,
            v0: 0.0,
            v1: first.speed_m_s,
            line: first.line,
        }];
        for (pair, &s) in settings.waypoints.windows(2).zip(&turn_end_s) {
            let (a, b) = (&pair[0], &pair[1]);
            if a.speed_m_s != b.speed_m_s {
                changes.push(SpeedChange {
                    s,
                    v0: a.speed_m_s,
                    v1: b.speed_m_s,
                    line: b.line,
                });
            }
        }
        let last = &settings.waypoints[n - 1];
        let (_, stop_distance) = ramp(last.speed_m_s, 0.0);
        changes.push(SpeedChange {
            s: length_m - stop_distance,
            v0: last.speed_m_s,
            v1: 0.0,
            line: last.line,
        });
        for pair in changes.windows(2) {
            let (_, d) = ramp(pair[0].v0, pair[0].v1);
            if pair[0].s + d > pair[1].s + 1e-9 {
                let line = pair[1].line.max(pair[0].line);
                return Err((
                    line,
                    format!(
                        "the speed changes from {} to {} m/s and from {} to {} m/s overlap \
                         ({:.2} m needed, {:.2} m available; max_accel_m_s2 = {}): lengthen \
                         the leg or raise max_accel_m_s2",
                        pair[0].v0,
                        pair[0].v1,
                        pair[1].v0,
                        pair[1].v1,
                        d,
                        (pair[1].s - pair[0].s).max(0.0),
                        settings.max_accel_m_s2
                    ),
                ));
            }
        }
        // Phases in time: each change, then cruising to the next one.
        let mut phases = Vec::new();
        let mut t = 0.0;
        for (k, change) in changes.iter().enumerate() {
            let (duration, d) = ramp(change.v0, change.v1);
            phases.push(Phase {
                t0: t,
                s0: change.s,
                v0: change.v0,
                v1: change.v1,
                duration,
            });
            t += duration;
            if let Some(next) = changes.get(k + 1) {
                let cruise = (next.s - change.s - d).max(0.0);
                if cruise > 0.0 {
                    let duration = cruise / change.v1;
                    phases.push(Phase {
                        t0: t,
                        s0: change.s + d,
                        v0: change.v1,
                        v1: change.v1,
                        duration,
                    });
                    t += duration;
                }
            }
        }
        let motion_s = t;
        // Positions every GRID_M.
        let steps = (length_m / GRID_M).ceil() as usize;
        let mut grid = Vec::with_capacity(steps + 1);
        let mut p = settings.start;
        grid.push(p);
        for k in 0..steps {
            let a = k as f64 * GRID_M;
            let b = ((k + 1) as f64 * GRID_M).min(length_m);
            let d = integrate(&segments, a, b, 2);
            p = [p[0] + d[0], p[1] + d[1]];
            grid.push(p);
        }
        Ok(Self {
            start: settings.start,
            waypoints: settings.waypoints.iter().map(|w| w.xy).collect(),
            rest_s: settings.rest_s,
            segments,
            phases,
            length_m,
            motion_s,
            grid,
        })
    }

    /// Where the trolley starts: x, y (m) and heading (degrees, towards the first waypoint).
    pub fn start_pose(&self) -> [f64; 3] {
        let h = self.segments.first().map_or(0.0, |s| s.heading0);
        [self.start[0], self.start[1], h.to_degrees()]
    }

    /// The waypoints, in order (the path passes the corner points they define).
    pub fn waypoints(&self) -> &[[f64; 2]] {
        &self.waypoints
    }

    /// Seconds at rest from the rig's start before the trolley moves.
    pub fn rest_s(&self) -> f64 {
        self.rest_s
    }

    /// The same path resting `rest_s` seconds from the rig's start instead (the motion, and so
    /// everything after the rest, moves by the difference): room for an operator's calibration
    /// turn before the push. A negative or non-finite `rest_s` is taken as 0.
    pub fn with_rest_s(&self, rest_s: f64) -> Self {
        Self {
            rest_s: if rest_s.is_finite() {
                rest_s.max(0.0)
            } else {
                0.0
            },
            ..self.clone()
        }
    }

    /// Seconds of motion.
    pub fn motion_s(&self) -> f64 {
        self.motion_s
    }

    /// The time (s since the rig's start) the trolley comes to rest at the end of its path.
    pub fn end_of_path_s(&self) -> f64 {
        self.rest_s + self.motion_s
    }

    /// Length of the path, m.
    pub fn length_m(&self) -> f64 {
        self.length_m
    }

    /// The state at `t_s` seconds since the rig's start (at rest before the motion and after
    /// the end of the path).
    pub fn state_at(&self, t_s: f64) -> TrolleyState {
        let tau = t_s - self.rest_s;
        let (s, v, a) = if tau.is_nan() || tau <= 0.0 {
            (0.0, 0.0, 0.0)
        } else if tau >= self.motion_s {
            (self.length_m, 0.0, 0.0)
        } else {
            let i = self
                .phases
                .partition_point(|p| p.t0 <= tau)
                .saturating_sub(1);
            let phase = &self.phases[i];
            let (ds, v, a) = phase.at(tau - phase.t0);
            ((phase.s0 + ds).clamp(0.0, self.length_m), v.max(0.0), a)
        };
        let (heading, curvature, dcurvature) = self.geometry_at(s);
        let position = self.position_at(s);
        let (c, sn) = (heading.cos(), heading.sin());
        let lateral = curvature * v * v;
        TrolleyState {
            s_m: s,
            position_m: position,
            heading_rad: heading,
            speed_m_s: v,
            tangential_accel_m_s2: a,
            curvature_per_m: curvature,
            yaw_rate_rad_s: curvature * v,
            yaw_accel_rad_s2: dcurvature * v * v + curvature * a,
            velocity_m_s: [v * c, v * sn],
            accel_m_s2: [a * c - lateral * sn, a * sn + lateral * c],
        }
    }

    /// The pose of `base` in `room` at `t_s` seconds since the rig's start.
    pub fn pose_at_s(&self, t_s: f64) -> Isometry3<f64> {
        self.state_at(t_s).pose()
    }

    /// Heading, curvature and d curvature / ds at arc length `s`.
    fn geometry_at(&self, s: f64) -> (f64, f64, f64) {
        geometry(&self.segments, s)
    }

    /// Position at arc length `s`: the grid point below it plus Simpson's rule to `s`.
    fn position_at(&self, s: f64) -> [f64; 2] {
        let s = s.clamp(0.0, self.length_m);
        let k = ((s / GRID_M).floor() as usize).min(self.grid.len() - 1);
        let base = self.grid[k];
        let from = k as f64 * GRID_M;
        if s <= from {
            return base;
        }
        let d = integrate(&self.segments, from, s, 2);
        [base[0] + d[0], base[1] + d[1]]
    }

    /// The smallest distance from the path (sampled every 5 cm) to the room's walls and to the
    /// furniture below [`TROLLEY_HEIGHT_M`], and what and where it is; a path that leaves the
    /// room's interior gives a negative distance.
    pub fn clearance(&self, world: &World) -> Clearance {
        let room = world.room();
        let mut worst = Clearance {
            distance_m: f64::INFINITY,
            what: String::new(),
            at: self.start,
        };
        let steps = (self.length_m / 0.05).ceil().max(1.0) as usize;
        for k in 0..=steps {
            let p = self.position_at(self.length_m * k as f64 / steps as f64);
            let walls = [
                p[0] - room.min.x,
                room.max.x - p[0],
                p[1] - room.min.y,
                room.max.y - p[1],
            ];
            let wall = walls.into_iter().fold(f64::INFINITY, f64::min);
            if wall < worst.distance_m {
                worst = Clearance {
                    distance_m: wall,
                    what: "the room's walls".to_owned(),
                    at: p,
                };
            }
            for primitive in world.primitives() {
                let bounds = primitive.shape.bounds();
                if bounds.max.z <= 0.01 || bounds.min.z >= TROLLEY_HEIGHT_M {
                    continue;
                }
                let d = match &primitive.shape {
                    Shape::Box(b) => {
                        let dx = (b.min.x - p[0]).max(p[0] - b.max.x).max(0.0);
                        let dy = (b.min.y - p[1]).max(p[1] - b.max.y).max(0.0);
                        (dx * dx + dy * dy).sqrt()
                    }
                    Shape::Rect(r) => {
                        let a = [r.corner.x, r.corner.y];
                        let b = [a[0] + r.edge_u.x, a[1] + r.edge_u.y];
                        let c = [a[0] + r.edge_v.x, a[1] + r.edge_v.y];
                        segment_distance(p, a, b).min(segment_distance(p, a, c))
                    }
                };
                if d < worst.distance_m {
                    worst = Clearance {
                        distance_m: d,
                        what: format!("\"{}\"", primitive.name),
                        at: p,
                    };
                }
            }
        }
        worst
    }
}

/// How close a path comes to the room's walls or furniture ([`TrolleyPath::clearance`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Clearance {
    /// The smallest distance, m (negative: outside the room).
    pub distance_m: f64,
    /// What it is closest to.
    pub what: String,
    /// Where on the path, m.
    pub at: [f64; 2],
}

impl BaseTrajectory for TrolleyPath {
    fn motion_at(&self, t_ns: u64) -> BaseMotion {
        self.state_at(t_ns as f64 * 1e-9).motion()
    }
}

/// Floor bumps under the trolley: its roll and pitch as band-limited functions of the distance
/// travelled, so they change only while it moves (a floor is not level, and a trolley's wheels
/// rock it over joints and tiles).
///
/// Each angle is a sum of [`FloorBumps::COMPONENTS`] sines of the distance with wavelengths
/// drawn uniformly from `wavelength_m` and random phases (from `seed`), scaled so the angle's
/// RMS over a long run is `rms_deg`. At 0.3 m/s wavelengths of 0.15–1 m give 0.3–2 Hz.
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct FloorBumps {
    /// RMS of roll and of pitch, degrees.
    pub rms_deg: f64,
    /// Shortest and longest wavelength along the path, m.
    pub wavelength_m: [f64; 2],
    /// Seed of the wavelengths and phases.
    pub seed: u64,
}

impl Default for FloorBumps {
    /// 0.3° RMS over 0.15–1 m: an office floor with tile joints under small castors.
    fn default() -> Self {
        Self {
            rms_deg: 0.3,
            wavelength_m: [0.15, 1.0],
            seed: 0xB0B,
        }
    }
}

impl FloorBumps {
    /// Sines per angle.
    pub const COMPONENTS: usize = 4;

    /// (amplitude rad, wave number rad/m, phase rad) of each sine of roll (`[0]`) and pitch
    /// (`[1]`).
    fn components(&self) -> [[(f64, f64, f64); Self::COMPONENTS]; 2] {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(self.seed);
        // A sine of amplitude a has RMS a/√2: n of them with equal amplitude have RMS a·√(n/2).
        let amplitude = self.rms_deg.to_radians() * (2.0 / Self::COMPONENTS as f64).sqrt();
        let [lo, hi] = self.wavelength_m;
        let mut out = [[(0.0, 0.0, 0.0); Self::COMPONENTS]; 2];
        for angle in &mut out {
            for c in angle.iter_mut() {
                let wavelength = lo + (hi - lo) * rng.random::<f64>();
                *c = (
                    amplitude,
                    2.0 * PI / wavelength,
                    2.0 * PI * rng.random::<f64>(),
                );
            }
        }
        out
    }
}

/// A [`TrolleyPath`] over a bumpy floor: the path's planar motion with the roll and pitch of
/// [`FloorBumps`] about the reference point (on the floor, so the tilt does not move it). The
/// lidars, the IMU and `--truth` all see the tilted pose.
#[derive(Debug, Clone)]
pub struct BumpyTrolley {
    path: Arc<TrolleyPath>,
    sines: [[(f64, f64, f64); FloorBumps::COMPONENTS]; 2],
}

impl BumpyTrolley {
    /// `path` over a floor with `bumps`.
    pub fn new(path: Arc<TrolleyPath>, bumps: &FloorBumps) -> Self {
        Self {
            path,
            sines: bumps.components(),
        }
    }

    /// The path underneath.
    pub fn path(&self) -> &Arc<TrolleyPath> {
        &self.path
    }

    /// Roll and pitch (rad) and their first and second derivatives by distance, at `s` m.
    fn tilt_at(&self, s: f64) -> [[f64; 3]; 2] {
        self.sines.map(|angle| {
            angle.iter().fold([0.0; 3], |[f, df, ddf], &(a, k, phase)| {
                let (sin, cos) = (k * s + phase).sin_cos();
                [f + a * sin, df + a * k * cos, ddf - a * k * k * sin]
            })
        })
    }

    /// Roll and pitch (rad) at `t_s` seconds since the rig's start.
    pub fn roll_pitch_at(&self, t_s: f64) -> [f64; 2] {
        let [roll, pitch] = self.tilt_at(self.path.state_at(t_s).s_m);
        [roll[0], pitch[0]]
    }

    /// The pose and the angular velocity (room frame) at `t_s`.
    fn pose_and_rate(&self, t_s: f64) -> (TrolleyState, Isometry3<f64>, Vector3<f64>) {
        let st = self.path.state_at(t_s);
        let [roll, pitch] = self.tilt_at(st.s_m);
        let v = st.speed_m_s;
        let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), st.heading_rad);
        let yaw_pitch = yaw * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), pitch[0]);
        let rotation = yaw_pitch * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), roll[0]);
        // R = Rz(ψ)·Ry(θ)·Rx(φ): ω = ψ̇ z + Rz(ψ)·θ̇ y + Rz(ψ)Ry(θ)·φ̇ x, with θ̇ = θ'(s)·v.
        let rate = Vector3::new(0.0, 0.0, st.yaw_rate_rad_s)
            + yaw * Vector3::new(0.0, pitch[1] * v, 0.0)
            + yaw_pitch * Vector3::new(roll[1] * v, 0.0, 0.0);
        let pose = Isometry3::from_parts(
            Translation3::new(st.position_m[0], st.position_m[1], 0.0),
            rotation,
        );
        (st, pose, rate)
    }
}

impl BaseTrajectory for BumpyTrolley {
    fn motion_at(&self, t_ns: u64) -> BaseMotion {
        let t = t_ns as f64 * 1e-9;
        let (st, pose, rate) = self.pose_and_rate(t);
        // The angular acceleration by a central difference of the rate (smooth, and tiny
        // next to the lever arm's other terms).
        let h = 1e-4;
        let alpha = (self.pose_and_rate(t + h).2 - self.pose_and_rate(t - h).2) / (2.0 * h);
        BaseMotion {
            pose,
            angular_velocity_rad_s: rate,
            angular_accel_rad_s2: alpha,
            accel_m_s2: Vector3::new(st.accel_m_s2[0], st.accel_m_s2[1], 0.0),
        }
    }
}

/// A base that turns in place about its own vertical (z of `base` through its origin) while
/// the base underneath rests: the operator's slow turn for `scan3d-edge calibrate mag`. The
/// extra yaw rises smoothly from 0 to `angle_rad` over `duration_s` from `start_s`,
/// ψ(u) = angle·(u − sin(2πu)/2π) with u the fraction of the turn done: the yaw rate
/// angle/T·(1 − cos 2πu) starts and ends at zero, peaks at twice the mean halfway. A whole
/// number of turns leaves the base as it was. The base underneath must be at rest during the
/// turn (the cross terms of a turn on a moving base are not modelled).
#[derive(Debug, Clone)]
pub struct TurnInPlace {
    /// The base that turns (at rest while it does).
    pub base: Arc<dyn BaseTrajectory>,
    /// When the turn starts, s since the rig's start.
    pub start_s: f64,
    /// How long it lasts, s (positive).
    pub duration_s: f64,
    /// The angle turned, rad (positive: counter-clockwise seen from above).
    pub angle_rad: f64,
}

impl TurnInPlace {
    /// When the turn ends, s since the rig's start.
    pub fn end_s(&self) -> f64 {
        self.start_s + self.duration_s
    }

    /// The extra yaw, its rate and its acceleration at `t_s`.
    fn yaw_at(&self, t_s: f64) -> [f64; 3] {
        if self.duration_s.is_nan() || self.duration_s <= 0.0 || t_s <= self.start_s {
            return [0.0; 3];
        }
        if t_s >= self.end_s() {
            return [self.angle_rad, 0.0, 0.0];
        }
        let u = (t_s - self.start_s) / self.duration_s;
        let phase = 2.0 * PI * u;
        let mean_rate = self.angle_rad / self.duration_s;
        [
            self.angle_rad * (u - phase.sin() / (2.0 * PI)),
            mean_rate * (1.0 - phase.cos()),
            mean_rate * 2.0 * PI / self.duration_s * phase.sin(),
        ]
    }
}

impl BaseTrajectory for TurnInPlace {
    fn motion_at(&self, t_ns: u64) -> BaseMotion {
        let under = self.base.motion_at(t_ns);
        let [yaw, rate, accel] = self.yaw_at(t_ns as f64 * 1e-9);
        let axis = under.pose.rotation * Vector3::z();
        BaseMotion {
            pose: under.pose * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            angular_velocity_rad_s: under.angular_velocity_rad_s + axis * rate,
            angular_accel_rad_s2: under.angular_accel_rad_s2 + axis * accel,
            accel_m_s2: under.accel_m_s2,
        }
    }
}

/// Heading, curvature and d curvature / ds at arc length `s` along `segments`.
fn geometry(segments: &[Segment], s: f64) -> (f64, f64, f64) {
    let i = segments
        .partition_point(|seg| seg.s0 <= s)
        .saturating_sub(1);
    let seg = &segments[i];
    seg.at((s - seg.s0).clamp(0.0, seg.length))
}

/// ∫ (cos ψ, sin ψ) ds from `a` to `b` by Simpson's rule over `n` (even) intervals.
fn integrate(segments: &[Segment], a: f64, b: f64, n: usize) -> [f64; 2] {
    let n = n.max(2) + n % 2;
    let h = (b - a) / n as f64;
    let mut sum = [0.0; 2];
    for k in 0..=n {
        let weight = if k == 0 || k == n {
            1.0
        } else if k % 2 == 1 {
            4.0
        } else {
            2.0
        };
        let (psi, _, _) = geometry(segments, a + h * k as f64);
        sum[0] += weight * psi.cos();
        sum[1] += weight * psi.sin();
    }
    [sum[0] * h / 3.0, sum[1] * h / 3.0]
}

/// `angle` wrapped into (−π, π].
fn wrap_pi(angle: f64) -> f64 {
    let a = angle.rem_euclid(2.0 * PI);
    if a > PI { a - 2.0 * PI } else { a }
}

/// Distance from `p` to the segment `a`–`b` in the plane.
fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let ap = [p[0] - a[0], p[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 0.0 {
        ((ap[0] * ab[0] + ap[1] * ab[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let q = [a[0] + t * ab[0], a[1] + t * ab[1]];
    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The example of the module docs and docs/simulator.md.
    const EXAMPLE: &str = "\
rest_s = 20.0           # at rest from the rig's start (default 20)
speed_m_s = 0.3         # speed of every leg unless the waypoint says (default 0.3)
turn_radius_m = 0.6     # tightest radius of every turn unless the waypoint says (default 0.6)
max_accel_m_s2 = 0.2    # of the speed changes (default 0.2)
start = [1.6, 0.85]     # x, y in the room, m; the heading is towards the first waypoint

[[waypoint]]
x = 6.3
y = 0.85
speed_m_s = 0.25        # on the leg that ends here (optional)
turn_radius_m = 0.6     # of the turn at this waypoint (optional)

[[waypoint]]
x = 6.3
y = 5.2

[[waypoint]]
x = 1.5
y = 5.2
speed_m_s = 0.25

[[waypoint]]
x = 1.5
y = 2.2
speed_m_s = 0.2
";

    fn parse(text: &str) -> Result<TrolleyPath, String> {
        TrolleyPath::from_toml_str(text, Path::new("path.toml")).map_err(|e| e.to_string())
    }

    /// Every state of the timeline, 1 ms apart, from 1 s before the motion to 1 s after it.
    fn timeline(path: &TrolleyPath) -> Vec<(f64, TrolleyState)> {
        let (t0, t1) = (path.rest_s() - 1.0, path.end_of_path_s() + 1.0);
        let n = ((t1 - t0) / 1e-3).round() as usize;
        (0..=n)
            .map(|k| {
                let t = t0 + k as f64 * 1e-3;
                (t, path.state_at(t))
            })
            .collect()
    }

    #[test]
    fn the_default_path_rests_20_s_then_moves_60_to_90_s_at_0_2_to_0_5_m_s_with_turns() {
        let path = TrolleyPath::demo_room();
        eprintln!(
            "default path: {:.2} m, {:.2} s of motion",
            path.length_m(),
            path.motion_s()
        );
        assert_eq!(path.rest_s(), 20.0);
        assert!(
            (60.0..=90.0).contains(&path.motion_s()),
            "{} s of motion",
            path.motion_s()
        );
        let states = timeline(&path);
        let mut slow_s = 0.0;
        let mut turns = 0;
        let mut turning = false;
        for (t, st) in &states {
            let moving = *t > path.rest_s() && *t < path.end_of_path_s();
            if !moving {
                assert_eq!(st.speed_m_s, 0.0, "t {t}");
                continue;
            }
            assert!(st.speed_m_s <= 0.5 + 1e-12, "t {t}: {} m/s", st.speed_m_s);
            if st.speed_m_s < 0.2 - 1e-9 {
                slow_s += 1e-3;
                // Only while speeding up or slowing down.
                assert!(st.tangential_accel_m_s2.abs() > 0.0, "t {t}: slow cruise");
            }
            let now_turning = st.yaw_rate_rad_s.abs() > 0.05;
            if now_turning && !turning {
                turns += 1;
            }
            turning = now_turning;
        }
        // Speeding up from rest and slowing down to rest take π·v/(2·0.2) s each.
        assert!(slow_s < 3.0, "{slow_s} s below 0.2 m/s");
        assert_eq!(turns, 3);
    }

    #[test]
    fn position_velocity_heading_and_yaw_rate_are_continuous_and_consistent() {
        let path = TrolleyPath::demo_room();
        let states = timeline(&path);
        let h = 1e-3;
        for w in states.windows(3) {
            let [(t, a), (_, b), (_, c)] = [w[0], w[1], w[2]];
            // Derivatives by central differences against the analytic values.
            for i in 0..2 {
                let v = (c.position_m[i] - a.position_m[i]) / (2.0 * h);
                assert!((v - b.velocity_m_s[i]).abs() < 1e-4, "t {t}: velocity");
                let acc = (c.velocity_m_s[i] - a.velocity_m_s[i]) / (2.0 * h);
                assert!((acc - b.accel_m_s2[i]).abs() < 2e-3, "t {t}: accel {acc}");
            }
            let yaw_rate = (c.heading_rad - a.heading_rad) / (2.0 * h);
            assert!(
                (yaw_rate - b.yaw_rate_rad_s).abs() < 1e-4,
                "t {t}: yaw rate"
            );
            let yaw_accel = (c.yaw_rate_rad_s - a.yaw_rate_rad_s) / (2.0 * h);
            assert!(
                (yaw_accel - b.yaw_accel_rad_s2).abs() < 2e-3,
                "t {t}: yaw accel {yaw_accel} vs {}",
                b.yaw_accel_rad_s2
            );
            // Bounded: no jumps between samples 1 ms apart.
            let speed = |s: TrolleyState| s.speed_m_s;
            assert!((speed(c) - speed(b)).abs() <= DEFAULT_MAX_ACCEL_M_S2 * h + 1e-12);
            let acc = b.accel_m_s2[0].hypot(b.accel_m_s2[1]);
            assert!(acc <= 0.3, "t {t}: |a| = {acc} m/s²");
            assert!(
                b.yaw_rate_rad_s.abs() <= 0.3 / 0.6 + 1e-9,
                "t {t}: yaw rate"
            );
        }
    }

    #[test]
    fn the_yaw_rate_integrates_to_the_heading_change_and_the_path_ends_at_its_last_waypoint() {
        let path = TrolleyPath::demo_room();
        let states = timeline(&path);
        let integral: f64 = states
            .windows(2)
            .map(|w| (w[0].1.yaw_rate_rad_s + w[1].1.yaw_rate_rad_s) / 2.0 * 1e-3)
            .sum();
        let first = states[0].1;
        let last = states[states.len() - 1].1;
        let change = last.heading_rad - first.heading_rad;
        assert!((change - 3.0 * PI / 2.0).abs() < 1e-9, "{change}");
        assert!((integral - change).abs() < 1e-6, "{integral} vs {change}");
        assert_eq!(first.position_m, [1.6, 0.85]);
        let end = [1.5, 2.2];
        assert!(
            (last.position_m[0] - end[0]).hypot(last.position_m[1] - end[1]) < 1e-6,
            "{:?}",
            last.position_m
        );
        assert_eq!(path.start_pose(), [1.6, 0.85, 0.0]);
        // The straights lie on the lines between the waypoints: mid-leg points.
        let mid = |x: f64, y: f64| {
            states
                .iter()
                .map(|(_, s)| (s.position_m[0] - x).hypot(s.position_m[1] - y))
                .fold(f64::INFINITY, f64::min)
        };
        for (x, y) in [(4.0, 0.85), (6.3, 3.0), (4.0, 5.2), (1.5, 3.5)] {
            assert!(
                mid(x, y) < 1e-3,
                "({x}, {y}) is {} m off the path",
                mid(x, y)
            );
        }
    }

    #[test]
    fn the_default_path_keeps_clear_of_walls_and_furniture() {
        let world = World::conference_room();
        let clearance = TrolleyPath::demo_room().clearance(&world);
        assert!(clearance.distance_m >= TROLLEY_CLEARANCE_M, "{clearance:?}");
        // A path across the table is caught, and so is one through a wall.
        let across = "start = [1.5, 3.0]\n[[waypoint]]\nx = 6.5\ny = 3.0\n";
        let clearance = parse(across).unwrap().clearance(&world);
        assert!(clearance.distance_m < 0.01, "{clearance:?}");
        assert!(clearance.what.contains("table"), "{clearance:?}");
        let out = "start = [1.5, 3.0]\n[[waypoint]]\nx = 9.0\ny = 3.0\n";
        let clearance = parse(out).unwrap().clearance(&world);
        assert!(clearance.distance_m < 0.0, "{clearance:?}");
    }

    #[test]
    fn the_documented_example_is_the_default_path() {
        let example = parse(EXAMPLE).unwrap();
        let default = TrolleyPath::demo_room();
        assert_eq!(example.motion_s(), default.motion_s());
        for t in [0.0, 25.0, 50.0, 80.0, 200.0] {
            assert_eq!(example.state_at(t), default.state_at(t), "t {t}");
        }
    }

    #[test]
    fn speed_changes_are_bounded_and_the_leg_speeds_are_kept() {
        let text = "rest_s = 1\nmax_accel_m_s2 = 0.5\nstart = [0, 0]\n\
                    [[waypoint]]\nx = 3\ny = 0\nspeed_m_s = 0.4\n\
                    [[waypoint]]\nx = 3\ny = 3\nspeed_m_s = 0.2\n";
        let path = parse(text).unwrap();
        let states = timeline(&path);
        let max_speed = states.iter().map(|(_, s)| s.speed_m_s).fold(0.0, f64::max);
        assert!((max_speed - 0.4).abs() < 1e-9, "{max_speed}");
        let max_accel = states
            .iter()
            .map(|(_, s)| s.tangential_accel_m_s2.abs())
            .fold(0.0, f64::max);
        assert!(max_accel <= 0.5 + 1e-9 && max_accel > 0.49, "{max_accel}");
        // Cruising on the second leg at its own speed.
        let on_leg_2 = states
            .iter()
            .filter(|(_, s)| {
                s.position_m[0] > 2.999 && s.position_m[1] > 1.5 && s.position_m[1] < 2.5
            })
            .map(|(_, s)| s.speed_m_s)
            .collect::<Vec<_>>();
        assert!(!on_leg_2.is_empty());
        assert!(
            on_leg_2.iter().all(|v| (v - 0.2).abs() < 1e-9),
            "{on_leg_2:?}"
        );
        assert_eq!(path.rest_s(), 1.0);
    }

    #[test]
    fn path_errors_name_the_line_of_the_key() {
        let cases: [(&str, &str); 8] = [
            (
                "start = [0, 0]\nspeed = 0.3\n[[waypoint]]\nx = 1\ny = 0\n",
                "line 2: unknown field `speed`",
            ),
            (
                "start = [0, 0]\n\nspeed_m_s = 3.0\n[[waypoint]]\nx = 1\ny = 0\n",
                "line 3: `speed_m_s` = 3: expected 0.05 to 2 m/s",
            ),
            (
                "start = [0, 0]\n[[waypoint]]\nx = 1\ny = 0\nturn_radius_m = 0.0\n",
                "line 5: `turn_radius_m` = 0",
            ),
            ("rest_s = 1\nstart = [0, 0]\n", "line 2: no [[waypoint]]"),
            (
                "start = [0, 0]\n[[waypoint]]\nx = 1\ny = 0\n[[waypoint]]\nx = 0.2\ny = 0.1\n",
                "line 2: the waypoint at line 2 turns the trolley",
            ),
            (
                "start = [0, 0]\n[[waypoint]]\nx = 3\ny = 0\n[[waypoint]]\nx = 3\ny = 0.5\n",
                "line 5: the waypoint at line 5 is 0.50 m from the point before it; the turns at both ends need",
            ),
            (
                "start = [0, 0]\nmax_accel_m_s2 = 0.01\n[[waypoint]]\nx = 0.5\ny = 0\n",
                "line 3: the speed changes from 0 to 0.3 m/s and from 0.3 to 0 m/s overlap",
            ),
            (
                "start = [0, 0]\n[[waypoint]]\nx = 3\ny = 0\nspeed_m_s = 1.0\nturn_radius_m = 0.5\n[[waypoint]]\nx = 3\ny = 3\n",
                "line 2: the turn at the waypoint at line 2 pushes the trolley sideways at 2.00 m/s²",
            ),
        ];
        for (text, want) in cases {
            let got = parse(text).unwrap_err();
            assert!(
                got.starts_with(&format!("path.toml: {want}")),
                "{got}\nwant: {want}"
            );
        }
        let missing = TrolleyPath::load(Path::new("/nonexistent/path.toml")).unwrap_err();
        assert!(
            missing
                .to_string()
                .starts_with("cannot read /nonexistent/path.toml")
        );
    }

    #[test]
    fn a_sensor_on_the_trolley_moves_with_it() {
        let path = Arc::new(TrolleyPath::demo_room());
        let mount = Isometry3::translation(0.2, 0.0, 0.4);
        let sensor = OnBase {
            base: path.clone(),
            mount,
        };
        for t in [0.0, 30.0, 45.0, 60.0, 100.0] {
            let st = path.state_at(t);
            let p = sensor.pose_at((t * 1e9) as u64).translation.vector;
            let (s, c) = st.heading_rad.sin_cos();
            let want = [st.position_m[0] + 0.2 * c, st.position_m[1] + 0.2 * s, 0.4];
            for i in 0..3 {
                assert!((p[i] - want[i]).abs() < 1e-9, "t {t}: {p:?} vs {want:?}");
            }
        }
    }

    #[test]
    fn floor_bumps_tilt_the_trolley_by_their_rms_only_while_it_moves_with_a_consistent_rate() {
        let path = Arc::new(TrolleyPath::demo_room());
        let bumps = FloorBumps::default();
        let bumpy = BumpyTrolley::new(path.clone(), &bumps);
        // Along the whole path: RMS roll and pitch near the configured 0.3°.
        let n = 20_000;
        let (mut roll2, mut pitch2) = (0.0, 0.0);
        for k in 0..n {
            let s = path.length_m() * f64::from(k) / f64::from(n);
            let [roll, pitch] = bumpy.tilt_at(s);
            roll2 += roll[0] * roll[0];
            pitch2 += pitch[0] * pitch[0];
        }
        let rms = |sum: f64| (sum / f64::from(n)).sqrt().to_degrees();
        eprintln!(
            "floor bumps over {:.1} m: roll {:.3}°, pitch {:.3}° RMS (configured {})",
            path.length_m(),
            rms(roll2),
            rms(pitch2),
            bumps.rms_deg
        );
        for r in [rms(roll2), rms(pitch2)] {
            assert!((r / bumps.rms_deg - 1.0).abs() < 0.35, "{r}");
        }
        // At rest the tilt does not change and nothing turns.
        let at_rest = bumpy.motion_at(5_000_000_000);
        assert!(at_rest.angular_velocity_rad_s.norm() < 1e-12);
        assert_eq!(bumpy.roll_pitch_at(1.0), bumpy.roll_pitch_at(10.0));
        // The reference point still follows the path; the angular velocity is the derivative
        // of the pose: R(t+h) ≈ exp(ω h) R(t).
        let mut tilted = 0usize;
        for k in 0..400 {
            let t = 25.0 + f64::from(k) * 0.2;
            let ns = |t: f64| (t * 1e9).round() as u64;
            let m = bumpy.motion_at(ns(t));
            let p = m.pose.translation.vector;
            let st = path.state_at(t);
            assert!((p.x - st.position_m[0]).abs() < 1e-9 && p.z == 0.0);
            let h = 1e-3;
            let next = bumpy.motion_at(ns(t + h)).pose.rotation;
            let prev = bumpy.motion_at(ns(t - h)).pose.rotation;
            let numeric = (next * prev.inverse()).scaled_axis() / (2.0 * h);
            assert!(
                (numeric - m.angular_velocity_rad_s).norm() < 2e-3,
                "t {t}: {numeric} vs {}",
                m.angular_velocity_rad_s
            );
            let up = m.pose.rotation * Vector3::z();
            tilted += usize::from(up.z < (0.1f64).to_radians().cos());
        }
        assert!(
            tilted > 40,
            "only {tilted} of 400 poses tilted by more than 0.1°"
        );
    }

    #[test]
    fn a_turn_in_place_turns_the_resting_base_once_about_its_vertical_and_stops() {
        let path = Arc::new(TrolleyPath::demo_room());
        let rest: Arc<dyn BaseTrajectory> =
            Arc::new(BumpyTrolley::new(path.clone(), &FloorBumps::default()));
        let turn = TurnInPlace {
            base: rest.clone(),
            start_s: 2.0,
            duration_s: 10.0,
            angle_rad: 2.0 * PI,
        };
        let ns = |t: f64| (t * 1e9) as u64;
        let heading = |t: f64| turn.motion_at(ns(t)).pose.rotation.euler_angles().2;
        let start = path.start_pose();
        // Before, after: the resting base; halfway: half a turn; the origin never moves.
        for t in [0.0, 1.9, 12.1, 15.0] {
            let (a, b) = (turn.motion_at(ns(t)).pose, rest.motion_at(ns(t)).pose);
            assert!((a.translation.vector - b.translation.vector).norm() < 1e-9);
            assert!(a.rotation.angle_to(&b.rotation) < 1e-9, "at {t} s");
        }
        let half = heading(7.0) - start[2].to_radians();
        assert!(
            half.sin().abs() < 1e-2 && half.cos() < 0.0,
            "halfway {half}"
        );
        // The rate integrates to the angle, starts and ends at zero, peaks at twice the mean.
        let rate = |t: f64| turn.motion_at(ns(t)).angular_velocity_rad_s.z;
        let (mut sum, dt) = (0.0, 0.001);
        let mut peak: f64 = 0.0;
        for k in 0..10_000 {
            let r = rate(2.0 + (f64::from(k) + 0.5) * dt);
            sum += r * dt;
            peak = peak.max(r);
        }
        assert!((sum - 2.0 * PI).abs() < 1e-3, "{sum}");
        assert!((peak - 2.0 * 2.0 * PI / 10.0).abs() < 1e-3, "{peak}");
        assert!(rate(2.0001).abs() < 1e-3 && rate(11.9999).abs() < 1e-3);
        // A longer rest moves the motion, not the path.
        let later = path.with_rest_s(path.rest_s() + 15.0);
        assert_eq!(later.end_of_path_s(), path.end_of_path_s() + 15.0);
        let (a, b) = (later.state_at(50.0), path.state_at(35.0));
        assert_eq!(a.position_m, b.position_m);
    }
}
