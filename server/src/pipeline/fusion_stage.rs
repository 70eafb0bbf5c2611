//! The live yaw fusion stage: follows the pose stage in the pose lane (RPLidar, IMU, pass
//! markers in sample-time order) and replaces the yaw of each matcher pose the pose stage hands
//! on ([`StageContext::poses`]) with its covariance intersection with the IMU's Madgwick yaw
//! ([`crate::pose::fusion`]), and sets the pose's roll and pitch from the IMU's quaternion.
//!
//! The stage sees every frame of its lane, so each IMU sample reaches it before the
//! revolutions that end after it: a pose (at its revolution's middle) normally finds Madgwick
//! samples on both sides at once. When it does not (the IMU stopped) it is held until the
//! lane's time has passed it by the fuser's gap and then handed on as the matcher's alone:
//! poses leave in their time order, sometimes one frame late.
//!
//! A snapshot writes `trajectory_fused.tum` (the room frame, the clock of `trajectory.tum`,
//! roll and pitch in the quaternion), each pass's `passes/NAME/trajectory_fused.tum` and
//! `yaw_sources.csv` (each pose's yaw from the matcher, Madgwick, the gyro alone and the
//! fusion, in degrees, with variances and ω), from a copy taken while the pipeline is held
//! ([`Stage::snapshot_job`]). [`fuse_session`] runs a recorded session through
//! the same stage offline.

use std::collections::VecDeque;
use std::io::Write;
use std::path::Path;

use serde::Serialize;

use scan3d_protocol::{Body, Frame};
use scan3d_slam::fusion::FuserConfig;
use scan3d_slam::pose::{Pose2, wrap_angle};

use super::passes::PassSpans;
use super::pose_stage::{path_safe, tum_time, write_tum};
use super::snapshot::SnapshotWriter;
use super::{
    BasePose, PipelineError, PipelineSettings, Products, SnapshotJob, Stage, StageContext,
};
use crate::pose::fusion::{
    FusedPoseYaw, FusionCounts, MatcherPoseYaw, PoseFusion, UnfusedReason, YawSources,
};
use crate::pose::timesync::SessionClock;

/// One pose as the stage handed it on, with every source's yaw.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Record {
    pose: BasePose,
    sources: YawSources,
    unfused: Option<UnfusedReason>,
}

/// The fusion's part of `scan3d status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FusionStatus {
    /// Poses fused and poses left to the matcher, by reason.
    pub counts: FusionCounts,
    /// Madgwick's frame against the matcher's, degrees (once estimated).
    pub alignment_deg: Option<f64>,
    /// The newest pose's source: `fused` or why not.
    pub last: Option<&'static str>,
}

/// The yaw fusion stage (see the module's doc).
pub struct FusionStage {
    fusion: PoseFusion,
    /// Matcher poses handed on by the pose stage and not settled yet, time order.
    waiting: VecDeque<BasePose>,
    products: FusedProducts,
}

/// What the stage's products are made of: copied whole for a snapshot, so the files are made
/// after the pipeline is released ([`Stage::snapshot_job`]).
#[derive(Debug, Clone)]
struct FusedProducts {
    records: Vec<Record>,
    /// The newest session → room transform the poses carried.
    anchor: Option<Pose2>,
    /// The passes (the pose stage before it logs the markers ignored).
    passes: PassSpans,
    clock: SessionClock,
}

impl std::fmt::Debug for FusionStage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FusionStage")
            .field("records", &self.products.records.len())
            .field("counts", &self.fusion.counts())
            .finish_non_exhaustive()
    }
}

impl FusionStage {
    /// A stage fusing with `config` (refused when its values are: see `YawFuser::new`).
    pub fn new(config: FuserConfig) -> Result<Self, scan3d_slam::fusion::FusionError> {
        Ok(Self {
            fusion: PoseFusion::new(config)?,
            waiting: VecDeque::new(),
            products: FusedProducts {
                records: Vec::new(),
                anchor: None,
                passes: PassSpans::new(),
                clock: SessionClock::new(),
            },
        })
    }

    /// The time-sync models the snapshot maps edge times with.
    pub fn set_clock(&mut self, clock: SessionClock) {
        self.products.clock = clock;
    }

    /// Counts and alignment for `scan3d status`.
    pub fn status(&self) -> FusionStatus {
        FusionStatus {
            counts: self.fusion.counts(),
            alignment_deg: self
                .fusion
                .fuser()
                .alignment()
                .map(|a| a.offset.to_degrees()),
            last: self
                .products
                .records
                .last()
                .map(|r| r.unfused.map_or("fused", |reason| reason.as_str())),
        }
    }

    /// The fusion's counts so far.
    pub fn counts(&self) -> FusionCounts {
        self.fusion.counts()
    }

    /// The poses handed on so far (session frame, the fused yaw), with every source's yaw.
    pub fn poses(&self) -> impl Iterator<Item = (&BasePose, &YawSources)> {
        self.products.records.iter().map(|r| (&r.pose, &r.sources))
    }

    /// Hands on the settled poses: each waiting matcher pose rewritten with its outcome.
    fn hand_on(&mut self, ctx: &mut StageContext, settled: Vec<FusedPoseYaw>) {
        for outcome in settled {
            // Poses settle in the order they came; an older waiting one has been given up.
            while let Some(pose) = self.waiting.pop_front() {
                if pose.t_ns < outcome.t_ns {
                    tracing::debug!(t_ns = pose.t_ns, "a pose the fusion never settled");
                    continue;
                }
                if pose.t_ns > outcome.t_ns {
                    self.waiting.push_front(pose);
                    break;
                }
                let pose = rewrite(pose, &outcome);
                self.products.records.push(Record {
                    pose,
                    sources: outcome.sources,
                    unfused: outcome.unfused,
                });
                ctx.poses.push(pose);
                break;
            }
        }
    }

    /// Writes `yaw_sources.csv`: per pose, t (as in the TUM files), then the matcher's,
    /// Madgwick's, the gyro-alone and the fused yaw (degrees, the reported frame) each with its
    /// standard deviation (degrees), ω and the fused pose's source.
    pub fn write_yaw_sources(&self, out: &mut dyn Write) -> std::io::Result<()> {
        self.products.write_yaw_sources(out)
    }

    /// The run so far in the reported frame: every source's yaw per pose and the fused
    /// trajectory, times as in the TUM files.
    pub fn run(&self) -> FusedRun {
        let offset = self.products.anchor.map_or(0.0, |a| a.theta);
        let room = |yaw: f64| wrap_angle(yaw + offset);
        let sources = self
            .products
            .records
            .iter()
            .map(|r| {
                let s = &r.sources;
                PoseYaws {
                    t_s: tum_time(&self.products.clock, s.t_ns as f64 * 1e-9),
                    yaws: YawSources {
                        matcher: room(s.matcher),
                        madgwick: s.madgwick.map(room),
                        gyro: s.gyro.map(room),
                        fused: room(s.fused),
                        ..*s
                    },
                    fused_from_both: r.unfused.is_none(),
                }
            })
            .collect();
        let trajectory = self
            .products
            .records
            .iter()
            .map(|r| {
                let pose = self.products.reported(&r.pose.pose);
                let [roll, pitch] = r.pose.roll_pitch.unwrap_or([0.0, 0.0]);
                FusedRoomPose {
                    t_ns: r.pose.t_ns,
                    t_s: tum_time(&self.products.clock, r.pose.t_ns as f64 * 1e-9),
                    x: pose.x,
                    y: pose.y,
                    yaw: pose.theta,
                    roll,
                    pitch,
                }
            })
            .collect();
        FusedRun {
            sources,
            trajectory,
            counts: self.fusion.counts(),
            on_server_clock: !self.products.clock.models().is_empty(),
        }
    }
}

/// `pose` with the fused yaw: θ and the yaw variance replaced, the yaw's cross covariances
/// scaled by σ_fused/σ_matcher (their correlations kept, so the matrix stays positive
/// semi-definite), roll and pitch set.
fn rewrite(mut pose: BasePose, outcome: &FusedPoseYaw) -> BasePose {
    pose.pose.theta = outcome.yaw;
    if outcome.matcher_variance > 0.0 && outcome.variance >= 0.0 {
        let scale = (outcome.variance / outcome.matcher_variance).sqrt();
        for k in [2, 5, 6, 7] {
            pose.covariance[k] *= scale;
        }
        pose.covariance[8] = outcome.variance;
    }
    if outcome.roll_pitch.is_some() {
        pose.roll_pitch = outcome.roll_pitch;
    }
    pose
}

impl Stage for FusionStage {
    fn name(&self) -> &'static str {
        "fusion"
    }

    fn on_frame(&mut self, ctx: &mut StageContext, frame: &Frame) {
        let mut settled = match &frame.body {
            Body::Mounts(mounts) => {
                self.fusion.on_mounts(mounts);
                Vec::new()
            }
            Body::Imu(sample) => self.fusion.on_imu(sample),
            Body::Pass(marker) => {
                self.products.passes.apply(marker.t_ns, &marker.event);
                Vec::new()
            }
            _ => Vec::new(),
        };
        for pose in std::mem::take(&mut ctx.poses) {
            if pose.room_from_session.is_some() {
                self.products.anchor = pose.room_from_session;
            }
            self.waiting.push_back(pose);
            settled.extend(self.fusion.on_pose(MatcherPoseYaw {
                t_ns: pose.t_ns,
                yaw: pose.pose.theta,
                variance: pose.covariance[8],
            }));
        }
        if !ctx.late {
            // The lane is in sample-time order: every IMU sample up to this frame's time has
            // come through.
            settled.extend(self.fusion.advance_to(ctx.key_ns));
        }
        self.hand_on(ctx, settled);
    }

    fn flush(&mut self, ctx: &mut StageContext) {
        let settled = self.fusion.advance_to(u64::MAX);
        self.hand_on(ctx, settled);
    }

    fn snapshot(&mut self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        self.products.write(out)
    }

    /// The records, anchor, passes and clock copied; the files made and written after.
    fn snapshot_job(&self, position: Option<&str>) -> Option<SnapshotJob> {
        if position.is_some() || self.products.records.is_empty() {
            return None;
        }
        let products = self.products.clone();
        Some(Box::new(move |out: &mut SnapshotWriter| {
            products.write(out)
        }))
    }
}

impl FusedProducts {
    /// A session-frame pose in the reported frame (the room's once a pass anchored it).
    fn reported(&self, pose: &Pose2) -> Pose2 {
        self.anchor.map_or(*pose, |a| a.compose(pose))
    }

    /// Writes the fused trajectory's poses whose edge ns `keep` takes as TUM lines.
    fn write_fused_tum(
        &self,
        out: &mut dyn Write,
        keep: impl Fn(u64) -> bool,
    ) -> std::io::Result<()> {
        let poses = self.records.iter().filter(|r| keep(r.pose.t_ns)).map(|r| {
            (
                r.pose.t_ns as f64 * 1e-9,
                self.reported(&r.pose.pose),
                r.pose.roll_pitch,
            )
        });
        write_tum(out, &self.clock, poses)
    }

    /// Writes `yaw_sources.csv`: per pose, t (as in the TUM files), then the matcher's,
    /// Madgwick's, the gyro-alone and the fused yaw (degrees, the reported frame) each with its
    /// standard deviation (degrees), ω and the fused pose's source.
    fn write_yaw_sources(&self, out: &mut dyn Write) -> std::io::Result<()> {
        writeln!(
            out,
            "t,matcher_deg,matcher_sigma_deg,madgwick_deg,madgwick_sigma_deg,gyro_deg,\
             gyro_sigma_deg,fused_deg,fused_sigma_deg,omega,source"
        )?;
        let offset = self.anchor.map_or(0.0, |a| a.theta);
        let deg = |yaw: f64| wrap_angle(yaw + offset).to_degrees();
        let sigma = |v: f64| v.max(0.0).sqrt().to_degrees();
        let opt = |v: Option<f64>, f: &dyn Fn(f64) -> f64| {
            v.map_or(String::new(), |v| format!("{:.4}", f(v)))
        };
        for r in &self.records {
            let s = &r.sources;
            writeln!(
                out,
                "{:.6},{:.4},{:.4},{},{},{},{},{:.4},{:.4},{},{}",
                tum_time(&self.clock, s.t_ns as f64 * 1e-9),
                deg(s.matcher),
                sigma(s.matcher_variance),
                opt(s.madgwick, &deg),
                opt(s.madgwick_variance, &sigma),
                opt(s.gyro, &deg),
                opt(s.gyro_variance, &sigma),
                deg(s.fused),
                sigma(s.fused_variance),
                s.omega.map_or(String::new(), |w| format!("{w:.4}")),
                r.unfused.map_or("fused", |reason| reason.as_str()),
            )?;
        }
        Ok(())
    }
    /// Writes the stage's part of a session snapshot (nothing for a position's, or before the
    /// first pose).
    fn write(&self, out: &mut SnapshotWriter) -> Result<(), PipelineError> {
        if out.snapshot.position.is_some() || self.records.is_empty() {
            return Ok(());
        }
        out.render("trajectory_fused.tum", |tum| {
            self.write_fused_tum(tum, |_| true)
        })?;
        for name in self.passes.names() {
            let subdir = Path::new("passes").join(path_safe(&name));
            out.render_in(&subdir, "trajectory_fused.tum", |tum| {
                self.write_fused_tum(tum, |t_ns| self.passes.covers(&name, t_ns))
            })?;
        }
        out.render("yaw_sources.csv", |csv| self.write_yaw_sources(csv))
    }
}

/// Every source's yaw at one pose, in the reported (room) frame, rad and rad².
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PoseYaws {
    /// Its time as in the TUM files: UNIX s of the server's clock (edge s without a model).
    pub t_s: f64,
    /// The sources' yaws (and the pose's edge time), turned into the room frame.
    #[serde(flatten)]
    pub yaws: YawSources,
    /// Whether both sources went in.
    pub fused_from_both: bool,
}

/// One pose of the fused trajectory of `base` in the room frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FusedRoomPose {
    /// Edge ns.
    pub t_ns: u64,
    /// As in the TUM files.
    pub t_s: f64,
    /// m.
    pub x: f64,
    /// m.
    pub y: f64,
    /// rad, counter-clockwise (the fused yaw).
    pub yaw: f64,
    /// rad (0 without the IMU's attitude).
    pub roll: f64,
    /// rad.
    pub pitch: f64,
}

/// A session's yaw fusion, offline ([`fuse_session`]): per pose, every source's yaw, and the
/// fused trajectory.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FusedRun {
    /// Every source's yaw per pose.
    pub sources: Vec<PoseYaws>,
    /// The fused trajectory of `base`.
    pub trajectory: Vec<FusedRoomPose>,
    /// Poses fused and not.
    pub counts: FusionCounts,
    /// Whether `t_s` is the server's clock (a time-sync model in the session), else the edge's.
    pub on_server_clock: bool,
}

/// The products [`fuse_session`] keeps: the trajectory (pose and fusion stages) only.
pub const TRAJECTORY_ONLY: Products = Products {
    revolution_points: false,
    position_maps: false,
    cloud: false,
    static_scans: false,
    octrees: false,
    trajectory: true,
};

/// Runs the recorded session in `session_dir` through the pipeline's pose lane (the pose stage,
/// then the fusion stage) and returns the fused run in the room frame, times on the server's
/// clock through the recorded time-sync models (as `trajectory.tum`).
pub fn fuse_session(session_dir: &Path) -> anyhow::Result<FusedRun> {
    let pipeline = fused_pipeline(session_dir)?;
    let stage = pipeline
        .fusion()
        .ok_or_else(|| anyhow::anyhow!("the pipeline has no fusion stage"))?;
    Ok(stage.run())
}

/// [`fuse_session`], also writing the fusion stage's snapshot files into `out_dir` (created if
/// missing): `trajectory_fused.tum`, `passes/NAME/trajectory_fused.tum`, `yaw_sources.csv`.
/// Returns the run and the files written.
pub fn fuse_session_into(
    session_dir: &Path,
    out_dir: &Path,
) -> anyhow::Result<(FusedRun, Vec<std::path::PathBuf>)> {
    use anyhow::Context;
    let pipeline = fused_pipeline(session_dir)?;
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("cannot create {}", out_dir.display()))?;
    let mut writer = SnapshotWriter::new(out_dir, None);
    let stage = pipeline
        .fusion()
        .ok_or_else(|| anyhow::anyhow!("the pipeline has no fusion stage"))?;
    stage.products.write(&mut writer)?;
    Ok((stage.run(), writer.snapshot.files))
}

fn fused_pipeline(session_dir: &Path) -> anyhow::Result<super::SessionPipeline> {
    use anyhow::Context;
    let (mut pipeline, _report) = super::offline::run_session(
        session_dir,
        &PipelineSettings::default(),
        TRAJECTORY_ONLY,
        false,
    )
    .with_context(|| format!("cannot run {}", session_dir.display()))?;
    let clock = SessionClock::from_session(session_dir)
        .with_context(|| format!("cannot read the clock models of {}", session_dir.display()))?;
    pipeline.set_clock(clock);
    Ok(pipeline)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fused_yaw_replaces_the_yaw_and_scales_its_cross_covariances() {
        let pose = BasePose {
            t_ns: 5,
            pose: Pose2::new(1.0, 2.0, 0.3),
            covariance: [4.0, 0.5, 0.2, 0.5, 1.0, 0.1, 0.2, 0.1, 0.04],
            roll_pitch: None,
            room_from_session: None,
        };
        let sources = YawSources {
            t_ns: 5,
            matcher: 0.3,
            matcher_variance: 0.04,
            madgwick: Some(0.2),
            madgwick_variance: Some(0.04),
            gyro: None,
            gyro_variance: None,
            fused: 0.25,
            fused_variance: 0.01,
            omega: Some(0.499),
        };
        let outcome = FusedPoseYaw {
            t_ns: 5,
            yaw: 0.25,
            variance: 0.01,
            matcher_variance: 0.04,
            roll_pitch: Some([0.01, -0.02]),
            unfused: None,
            sources,
        };
        let out = rewrite(pose, &outcome);
        assert_eq!(out.pose.theta, 0.25);
        assert_eq!((out.pose.x, out.pose.y), (1.0, 2.0));
        // σ halves: the cross terms halve, x and y stay.
        assert_eq!(
            out.covariance,
            [4.0, 0.5, 0.1, 0.5, 1.0, 0.05, 0.1, 0.05, 0.01]
        );
        assert_eq!(out.roll_pitch, Some([0.01, -0.02]));
    }
}
