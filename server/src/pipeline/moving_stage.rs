//! Assembly along movement, live (issue 21, the paper's "map1"): every sample of the vertical
//! Sweep placed with the pose of `base` at its own sample time, per trolley pass.
//!
//! The stage takes the Sweep's revolutions, the pass markers (`Body::Pass`) and the poses of
//! `base` the pose lane hands on ([`super::BasePose`], [`super::StreamId::Poses`]), in sample-time
//! order. It keeps a bounded window of recent poses and holds each Sweep revolution that falls
//! in a pass until the poses cover its last sample (as
//! [`scan3d_map::cloud::moving::poses_cover`]): a revolution is sent at
//! its end, and the pose for its last samples comes from an RPLidar revolution that ends later,
//! so it is held for about one RPLidar revolution, never extrapolated past the tolerance
//! ([`MovingSettings::extrapolation_tolerance_ns`], used only at the session's end). It is then
//! placed by [`MovingAssembler`]: x, y and yaw interpolated between the poses in the room frame
//! (with the anchor of the newest pose used: a pass start re-anchors the trajectory), roll and
//! pitch from [`super::BasePose::roll_pitch`] when a fusion stage gave them (else level), the
//! Sweep's mount from the session's `Body::Mounts`. Samples outside every pass are not placed:
//! static scans stay the assembly stage's. A pass covers the sample times [start, stop), by the
//! rules the pose and fusion stages follow too ([`super::passes`]).
//!
//! **Where it runs.** In the assembly lane, after the [`super::AssemblyStage`]: that lane then
//! takes the Sweep, the static-scan messages, the pass markers and the poses, and the placed
//! bundles go on in [`StageContext::rays`] (tagged [`RaySource::Pass`]) through the same
//! [`super::FilterStage`] and [`super::MapStage`] as the static scans' — one filter
//! configuration, one session octree, and the map stage keeps a cloud and an octree per pass
//! beside those per position (`passes/NAME/cloud.ply`, `passes/NAME/map.bt` in a snapshot). A
//! lane of its own would have needed its own filter and map stages, or rays crossing lanes.
//! The Poses stream is declared in the lane only when the session will make poses (a pose
//! stage and an RPLidar in the `Hello`), so static-scan sessions never wait for it.
//!
//! **Memory.** The pose window is trimmed to what the held revolutions and the next one need,
//! and capped at [`MovingOptions::max_poses`]; at most [`MovingOptions::max_held`] revolutions
//! are held (the oldest is dropped beyond: counted per pass, logged once). The products (cloud
//! and octrees) grow with the passes, as a position's do.

use std::collections::VecDeque;

use serde::Serialize;

use scan3d_map::cloud::moving::{
    MovingAssembler, MovingSettings, PlanarTrajectory, RigidTransform, TrajectoryPoint,
};
use scan3d_map::octree::Resolution;
use scan3d_protocol::{Body, Frame, LidarRevolution, PassEvent, SensorId};

use super::passes::{PassChange, PassSpans};
use super::{BasePose, NewBundle, RaySource, Stage, StageContext};

/// Which Sweep samples the stage places.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MovingScope {
    /// Those within a pass (from its start to its stop), each pass its own products (live).
    Passes,
    /// Every sample of the session, as one product named `""`, with the anchor of the newest
    /// pose (`scan3d assemble --moving` without `--pass`): a revolution is held until the
    /// trajectory is anchored in the room, or the session ends.
    Whole,
}

/// How the [`MovingStage`] places and what it keeps.
#[derive(Debug, Clone, PartialEq)]
pub struct MovingOptions {
    /// Which samples are placed.
    pub scope: MovingScope,
    /// Sweep revolutions held at most while waiting for the poses; beyond, the oldest is
    /// dropped (counted, logged once).
    pub max_held: usize,
    /// Poses kept at most in the window.
    pub max_poses: usize,
    /// Keep every pose used, in the room frame (the offline command returns it).
    pub keep_trajectory: bool,
}

/// Default [`MovingOptions::max_held`]: 64 Sweep revolutions, 6 to 13 s at its 5 to 10 Hz —
/// far more than the one RPLidar revolution a revolution waits for its poses.
pub const DEFAULT_MAX_HELD: usize = 64;

/// Default [`MovingOptions::max_poses`]: 1024 poses, 100 s of RPLidar revolutions at 10 Hz.
pub const DEFAULT_MAX_POSES: usize = 1024;

impl Default for MovingOptions {
    /// The live daemon's: passes only, the caps above, no trajectory kept (the pose stage
    /// writes it).
    fn default() -> Self {
        MovingOptions {
            scope: MovingScope::Passes,
            max_held: DEFAULT_MAX_HELD,
            max_poses: DEFAULT_MAX_POSES,
            keep_trajectory: false,
        }
    }
}

/// One pass as the moving stage saw it (a session's `status --json`, `passes[]`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct PassStatus {
    /// The pass's name (`scan3d trolley start … --name`).
    pub name: String,
    /// Whether it was stopped (its latest start, when started more than once).
    pub stopped: bool,
    /// Sweep revolutions (or their parts within the pass) placed.
    pub revolutions: u64,
    /// Samples placed.
    pub samples: u64,
    /// Samples with a return left unplaced: before the first pose, or after the last one by
    /// more than the extrapolation tolerance at the session's end.
    pub unplaced_samples: u64,
    /// Points the map stage took (after the revolution filters).
    pub points: u64,
    /// Revolutions waiting for the poses now.
    pub held: u64,
    /// Revolutions dropped because too many were held (the poses stopped coming).
    pub dropped: u64,
}

/// A Sweep revolution waiting for the poses: its parts per pass.
#[derive(Debug)]
struct Held {
    /// Its last sample's time, ns.
    last_ns: u64,
    /// Its first sample's time, ns.
    first_ns: u64,
    /// (pass name, the revolution's samples within the pass).
    pieces: Vec<(String, LidarRevolution)>,
}

/// The live assembly along movement; see the [module docs](self).
#[derive(Debug)]
pub struct MovingStage {
    settings: MovingSettings,
    options: MovingOptions,
    /// Made from the session's Sweep mount.
    assembler: Option<MovingAssembler>,
    poses: VecDeque<BasePose>,
    held: VecDeque<Held>,
    /// The passes (the pose stage logs the markers ignored).
    spans: PassSpans,
    /// Per pass name, what was placed (`stopped` filled in from `spans` when asked).
    passes: Vec<PassStatus>,
    /// The last sample time of the newest revolution placed, ns.
    placed_to_ns: Option<u64>,
    /// Sweep revolutions in a pass that came before the Sweep's mount (or with a bad one).
    unmounted: u64,
    /// Poses forgotten because the window was full.
    forgotten_poses: u64,
    trajectory: Vec<TrajectoryPoint>,
    logged_unmounted: bool,
    logged_drop: bool,
    logged_poses: bool,
}

impl MovingStage {
    /// A stage for octrees of `res` (bundles drift at most a quarter voxel, samples are
    /// extrapolated at most 50 ms at the session's end; the filters and the range cut are the
    /// pipeline's filter and map stages').
    pub fn new(res: Resolution, options: MovingOptions) -> Self {
        let mut settings = MovingSettings::for_resolution(res.meters());
        settings.keep_cloud = false;
        MovingStage {
            settings,
            options,
            assembler: None,
            poses: VecDeque::new(),
            held: VecDeque::new(),
            spans: PassSpans::new(),
            passes: Vec::new(),
            placed_to_ns: None,
            unmounted: 0,
            forgotten_poses: 0,
            trajectory: Vec::new(),
            logged_unmounted: false,
            logged_drop: false,
            logged_poses: false,
        }
    }

    /// Sets the options (before the first frame).
    pub fn set_options(&mut self, options: MovingOptions) {
        self.options = options;
    }

    /// The options in use.
    pub fn options(&self) -> &MovingOptions {
        &self.options
    }

    /// The passes seen, in first-start order (the map stage's points not filled in:
    /// [`super::SessionPipeline::passes`] does).
    pub fn passes(&self) -> Vec<PassStatus> {
        self.passes
            .iter()
            .map(|status| PassStatus {
                stopped: self.spans.stopped(&status.name).unwrap_or(false),
                ..status.clone()
            })
            .collect()
    }

    /// The passes as (name, start, stop) in edge ns, in start order.
    pub fn pass_spans(&self) -> Vec<(String, u64, Option<u64>)> {
        self.spans.as_tuples()
    }

    /// Sweep revolutions to be placed that came before the Sweep's mount: not placed.
    pub fn unmounted(&self) -> u64 {
        self.unmounted
    }

    /// Whether a Sweep mount was seen (the samples can be placed).
    pub fn mounted(&self) -> bool {
        self.assembler.is_some()
    }

    /// Pass stops without an open start of their name: ignored.
    pub fn stray_stops(&self) -> u64 {
        self.spans.stray_stops()
    }

    /// Poses forgotten because the window was full.
    pub fn forgotten_poses(&self) -> u64 {
        self.forgotten_poses
    }

    /// Every pose used to place samples, room frame, in time order (with
    /// [`MovingOptions::keep_trajectory`]).
    pub fn trajectory(&self) -> &[TrajectoryPoint] {
        &self.trajectory
    }

    fn status_mut(&mut self, name: &str) -> &mut PassStatus {
        let index = match self.passes.iter().position(|p| p.name == name) {
            Some(i) => i,
            None => {
                self.passes.push(PassStatus {
                    name: name.to_string(),
                    ..PassStatus::default()
                });
                self.passes.len() - 1
            }
        };
        &mut self.passes[index]
    }

    /// A pass marker ([`PassSpans`]' rules): a pass is listed from its start.
    fn on_pass(&mut self, t_ns: u64, event: &PassEvent) {
        if let PassChange::Started { .. } = self.spans.apply(t_ns, event) {
            self.status_mut(event.name());
        }
    }

    /// The parts of `rev` to place: within each pass it overlaps, or all of it.
    fn pieces(&self, rev: &LidarRevolution) -> Vec<(String, LidarRevolution)> {
        match self.options.scope {
            MovingScope::Whole => vec![(String::new(), rev.clone())],
            MovingScope::Passes => self
                .spans
                .spans()
                .iter()
                .filter_map(|span| {
                    within(rev, span.start_ns, span.end_ns())
                        .map(|piece| (span.name.clone(), piece))
                })
                .collect(),
        }
    }

    fn on_sweep(&mut self, ctx: &mut StageContext, rev: &LidarRevolution) {
        let pieces = self.pieces(rev);
        if pieces.is_empty() {
            return;
        }
        if self.assembler.is_none() {
            self.unmounted += 1;
            if !self.logged_unmounted {
                self.logged_unmounted = true;
                tracing::warn!(
                    "Sweep revolutions of a pass came before the Sweep's mount (the edge's \
                     [sweep.mount]): not placed"
                );
            }
            return;
        }
        let times = || rev.sample_times_ns();
        let first_ns = times().min().unwrap_or(rev.t0_ns);
        let last_ns = times().max().unwrap_or(rev.t0_ns);
        for (name, _) in &pieces {
            self.status_mut(name).held += 1;
        }
        self.held.push_back(Held {
            last_ns,
            first_ns,
            pieces,
        });
        self.place_covered(ctx);
        while self.held.len() > self.options.max_held {
            let dropped = self.held.pop_front().expect("more than the cap");
            for (name, _) in &dropped.pieces {
                let status = self.status_mut(name);
                status.held -= 1;
                status.dropped += 1;
            }
            if !self.logged_drop {
                self.logged_drop = true;
                tracing::warn!(
                    max_held = self.options.max_held,
                    "Sweep revolutions waited too long for the poses of base (is the RPLidar \
                     or the pose stage stopped?): the oldest are dropped, counted per pass"
                );
            }
        }
    }

    fn on_new_pose(&mut self, ctx: &mut StageContext, pose: &BasePose) {
        if self.poses.back().is_some_and(|last| pose.t_ns <= last.t_ns) {
            return;
        }
        self.poses.push_back(*pose);
        if self.poses.len() > self.options.max_poses {
            self.poses.pop_front();
            self.forgotten_poses += 1;
            if !self.logged_poses {
                self.logged_poses = true;
                tracing::warn!(
                    max_poses = self.options.max_poses,
                    "the window of poses of base is full: the oldest are forgotten"
                );
            }
        }
        self.place_covered(ctx);
    }

    /// Places the held revolutions the poses cover, oldest first, and trims the window.
    fn place_covered(&mut self, ctx: &mut StageContext) {
        while let Some(front) = self.held.front() {
            let Some(end) = self.poses.iter().position(|p| p.t_ns >= front.last_ns) else {
                break;
            };
            let anchor = match self.options.scope {
                MovingScope::Passes => self.poses[end].room_from_session,
                // The whole session in the room frame of the newest pass start.
                MovingScope::Whole => match self.poses.back().and_then(|p| p.room_from_session) {
                    Some(anchor) => Some(anchor),
                    None => break,
                },
            };
            let held = self.held.pop_front().expect("the front");
            self.place(ctx, held, end, anchor);
        }
        self.trim();
    }

    /// Forgets the poses no revolution to come needs: keeps one at or before the oldest held
    /// revolution's first sample and the newest placed one's last sample.
    fn trim(&mut self) {
        let keep_from = match (self.held.front(), self.placed_to_ns) {
            (Some(held), Some(placed)) => held.first_ns.min(placed),
            (Some(held), None) => held.first_ns,
            (None, Some(placed)) => placed,
            (None, None) => return,
        };
        while self.poses.len() > 1 && self.poses[1].t_ns <= keep_from {
            self.poses.pop_front();
        }
    }

    /// Places `held` along the window's poses up to index `end` (inclusive), taken to the room
    /// frame by `anchor` (the session's own frame with `None`).
    fn place(
        &mut self,
        ctx: &mut StageContext,
        held: Held,
        end: usize,
        anchor: Option<scan3d_slam::pose::Pose2>,
    ) {
        let used: Vec<&BasePose> = self.poses.iter().take(end + 1).collect();
        let mut trajectory = PlanarTrajectory::new();
        for pose in &used {
            let room = match anchor {
                Some(anchor) => anchor.compose(&pose.pose),
                None => pose.pose,
            };
            let [roll_rad, pitch_rad] = pose.roll_pitch.unwrap_or([0.0, 0.0]);
            let point = TrajectoryPoint {
                t_ns: pose.t_ns,
                x_m: room.x,
                y_m: room.y,
                yaw_rad: room.theta,
                roll_rad,
                pitch_rad,
            };
            if trajectory.push(point).is_err() {
                continue;
            }
            if self.options.keep_trajectory
                && self
                    .trajectory
                    .last()
                    .is_none_or(|last| last.t_ns < point.t_ns)
            {
                self.trajectory.push(point);
            }
        }
        self.placed_to_ns = Some(
            self.placed_to_ns
                .map_or(held.last_ns, |t| t.max(held.last_ns)),
        );
        let Some(assembler) = self.assembler.as_mut() else {
            // Never: a revolution is held only once a mount made the assembler.
            for (name, _) in &held.pieces {
                let status = self.status_mut(name);
                status.held -= 1;
                status.dropped += 1;
            }
            return;
        };
        let mut placed = Vec::with_capacity(held.pieces.len());
        for (name, piece) in held.pieces {
            let counts = assembler.add_revolution(&piece, &trajectory);
            let bundles = assembler.take_new();
            ctx.rays.extend(bundles.into_iter().map(|rays| NewBundle {
                source: RaySource::Pass(name.clone()),
                rays,
            }));
            placed.push((name, counts));
        }
        for (name, counts) in placed {
            let status = self.status_mut(&name);
            status.held -= 1;
            status.revolutions += 1;
            status.samples += counts.placed;
            status.unplaced_samples += counts.before_span + counts.after_span;
        }
    }
}

/// The samples of `rev` measured in `[from_ns, to_ns)` (a pass from its start to its stop);
/// `None` when none is.
pub fn within(rev: &LidarRevolution, from_ns: u64, to_ns: u64) -> Option<LidarRevolution> {
    let mut kept = LidarRevolution::new(rev.sensor, rev.t0_ns, rev.t1_ns);
    for (sample, t_ns) in rev.samples.iter().zip(rev.sample_times_ns()) {
        if (from_ns..to_ns).contains(&t_ns) {
            kept.samples.push(*sample);
        }
    }
    (!kept.samples.is_empty()).then_some(kept)
}

impl Stage for MovingStage {
    fn name(&self) -> &'static str {
        "moving"
    }

    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
        match &frame.body {
            Body::Revolution(rev) if rev.sensor == SensorId::SWEEP => self.on_sweep(ctx, rev),
            Body::Pass(marker) => self.on_pass(marker.t_ns, &marker.event),
            Body::Mounts(mounts) => {
                let Some(mount) = mounts.sensors.iter().find(|m| m.sensor == SensorId::SWEEP)
                else {
                    return;
                };
                match MovingAssembler::new(
                    RigidTransform::from_sensor_mount(mount),
                    self.settings.clone(),
                ) {
                    Ok(assembler) => self.assembler = Some(assembler),
                    Err(e) => tracing::warn!("the recorded Sweep mount cannot be used: {e}"),
                }
            }
            _ => {}
        }
    }

    fn on_pose(&mut self, ctx: &mut StageContext, pose: &BasePose) {
        self.on_new_pose(ctx, pose);
    }

    /// The session's end: the revolutions still held are placed with the poses there are
    /// (samples past the last pose by more than the tolerance are counted, not placed).
    fn flush(&mut self, ctx: &mut StageContext) {
        self.place_covered(ctx);
        let anchor = self.poses.back().and_then(|p| p.room_from_session);
        while let Some(held) = self.held.pop_front() {
            let end = self.poses.len().saturating_sub(1);
            self.place(ctx, held, end, anchor);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scan3d_map::cloud::moving::{BaseTrajectory, place_revolution};
    use scan3d_protocol::{PassMarker, SensorMount, SensorMounts};
    use scan3d_slam::pose::Pose2;

    const MOUNT: SensorMount = SensorMount {
        sensor: SensorId::SWEEP,
        x_m: 0.1,
        y_m: 0.0,
        z_m: 1.0,
        roll_deg: 0.0,
        pitch_deg: -90.0,
        yaw_deg: 0.0,
    };

    /// A Sweep revolution of `n` samples 10 ms apart from `t0_ms`, every range 1 m.
    fn revolution(t0_ms: u64, n: usize) -> LidarRevolution {
        let t0 = t0_ms * 1_000_000;
        let mut rev = LidarRevolution::new(SensorId::SWEEP, t0, t0 + 100_000_000);
        for i in 0..n {
            rev.push(i as f32 * 30.0, 1.0, 10, t0 + i as u64 * 10_000_000)
                .unwrap();
        }
        rev
    }

    /// `base` at `t_ms` moving along x at 1 m/s, in the session's frame, anchored so that the
    /// room is the session shifted by (2, 1).
    fn pose(t_ms: u64) -> BasePose {
        BasePose {
            t_ns: t_ms * 1_000_000,
            pose: Pose2 {
                x: t_ms as f64 * 1e-3,
                y: 0.0,
                theta: 0.1,
            },
            covariance: [0.0; 9],
            roll_pitch: None,
            room_from_session: Some(Pose2 {
                x: 2.0,
                y: 1.0,
                theta: 0.0,
            }),
        }
    }

    fn frame(body: impl Into<Body>) -> Frame {
        Frame::new(1, 0, body)
    }

    /// A stage for 5 cm voxels, the Sweep mounted, the pass "a" started at 0.
    fn started(options: MovingOptions) -> (MovingStage, StageContext) {
        let mut stage = MovingStage::new(Resolution::new(0.05).unwrap(), options);
        let mut ctx = StageContext::default();
        stage.on_frame(
            &mut ctx,
            &frame(SensorMounts {
                sensors: vec![MOUNT],
            }),
        );
        stage.on_frame(
            &mut ctx,
            &frame(PassMarker {
                t_ns: 0,
                event: PassEvent::Started {
                    name: "a".into(),
                    x_m: 2.0,
                    y_m: 1.0,
                    heading_deg: 0.0,
                },
            }),
        );
        (stage, ctx)
    }

    fn points(ctx: &StageContext) -> Vec<[f32; 3]> {
        ctx.rays
            .iter()
            .flat_map(|r| r.rays.points.clone())
            .collect()
    }

    #[test]
    fn a_revolution_is_held_until_the_poses_cover_it_then_placed_by_interpolation() {
        let (mut stage, mut ctx) = started(MovingOptions::default());
        stage.on_pose(&mut ctx, &pose(0));
        stage.on_pose(&mut ctx, &pose(50));
        // Samples from 20 to 110 ms: the poses end at 50 ms.
        stage.on_frame(&mut ctx, &frame(revolution(20, 10)));
        assert!(ctx.rays.is_empty(), "not placed (nor extrapolated) yet");
        assert_eq!(stage.passes()[0].held, 1);
        stage.on_pose(&mut ctx, &pose(150));
        let status = &stage.passes()[0];
        assert_eq!(
            (status.held, status.revolutions, status.samples),
            (0, 1, 10)
        );
        assert!(
            ctx.rays
                .iter()
                .all(|r| r.source == RaySource::Pass("a".into()))
        );
        // The same as placing along the three poses, in the room frame.
        let mut trajectory = PlanarTrajectory::new();
        for p in [0, 50, 150].map(pose) {
            let room = p.in_room();
            trajectory
                .push(TrajectoryPoint {
                    t_ns: p.t_ns,
                    x_m: room.x,
                    y_m: room.y,
                    yaw_rad: room.theta,
                    roll_rad: 0.0,
                    pitch_rad: 0.0,
                })
                .unwrap();
        }
        let mount = RigidTransform::from_sensor_mount(&MOUNT);
        let expected: Vec<[f32; 3]> = place_revolution(&revolution(20, 10), &trajectory, &mount, 0)
            .samples
            .iter()
            .map(|s| s.point.map(|c| c as f32))
            .collect();
        assert_eq!(points(&ctx), expected);
        // x of the first sample's origin: 2 + 0.02 m travelled + the mount's 0.1 m at 0.1 rad.
        let first = &ctx.rays[0].rays.origin;
        assert!(
            (first[0] - (2.02 + 0.1 * 0.1f64.cos())).abs() < 1e-9,
            "{first:?}"
        );
        assert!(trajectory.span_ns().is_some());
    }

    #[test]
    fn samples_outside_every_pass_are_not_placed() {
        let (mut stage, mut ctx) = started(MovingOptions::default());
        stage.on_frame(
            &mut ctx,
            &frame(PassMarker {
                t_ns: 60_000_000,
                event: PassEvent::Stopped { name: "a".into() },
            }),
        );
        stage.on_pose(&mut ctx, &pose(0));
        stage.on_frame(&mut ctx, &frame(revolution(20, 10)));
        stage.on_frame(&mut ctx, &frame(revolution(200, 10)));
        stage.on_pose(&mut ctx, &pose(400));
        // 20, 30, 40, 50 ms are in the pass; the second revolution is after it.
        assert_eq!(points(&ctx).len(), 4);
        assert_eq!(stage.passes()[0].revolutions, 1);
    }

    #[test]
    fn held_revolutions_are_capped_and_the_oldest_dropped() {
        let (mut stage, mut ctx) = started(MovingOptions {
            max_held: 2,
            ..MovingOptions::default()
        });
        for k in 0..5 {
            stage.on_frame(&mut ctx, &frame(revolution(100 * k, 10)));
        }
        let status = &stage.passes()[0];
        assert_eq!((status.held, status.dropped), (2, 3));
        stage.on_pose(&mut ctx, &pose(0));
        stage.on_pose(&mut ctx, &pose(1000));
        let status = &stage.passes()[0];
        assert_eq!((status.held, status.revolutions), (0, 2));
        // The two kept are the newest: their first sample at 300 ms.
        assert_eq!(points(&ctx).len(), 20);
    }

    #[test]
    fn the_pose_window_keeps_only_what_is_needed() {
        let (mut stage, mut ctx) = started(MovingOptions::default());
        for k in 0..100 {
            stage.on_pose(&mut ctx, &pose(100 * k));
            stage.on_frame(&mut ctx, &frame(revolution(100 * k, 5)));
        }
        assert!(stage.poses.len() <= 3, "{}", stage.poses.len());
        assert_eq!(stage.passes()[0].revolutions, 99);
    }

    #[test]
    fn within_keeps_the_samples_of_the_span_only() {
        let rev = revolution(0, 10);
        let kept = within(&rev, 20_000_000, 50_000_000).unwrap();
        assert_eq!(
            kept.samples.len(),
            3,
            "the stop's own time is after the pass"
        );
        assert!(within(&rev, 200_000_000, 300_000_000).is_none());
    }
}
