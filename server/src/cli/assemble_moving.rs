//! `scan3d assemble --moving SESSION_DIR… --out X.ply [--resolution R] [--pass NAME] [--bt FILE]`:
//! trolley passes assembled offline (issue 21, §III-B of the paper), every Sweep sample placed
//! with the pose of `base` at its own sample time.
//!
//! Each session runs once, streaming, through the live daemon's session pipeline: the pose
//! stage ([`PoseStage`]: the trajectory of `base` from the RPLidar and the IMU, anchored in the
//! room by the pass's start) hands its poses to the moving stage ([`crate::pipeline::MovingStage`]), which places
//! each Sweep sample with the pose at its own time and the recorded Sweep mount (`Body::Mounts`,
//! the edge's `[sweep.mount]`); the filter and map stages keep the pass's cloud and octree. So
//! the files are the bytes a live snapshot writes as `passes/NAME/cloud.ply` and
//! `passes/NAME/map.bt` (a test holds them to it). Without `--pass`, every Sweep sample of the
//! session is placed, in the room frame of the newest pass start. Over several sessions the
//! clouds are concatenated and one octree grows across them.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::cli::assemble::AssembleArgs;
use crate::cli::map::write_tree;
use crate::pipeline::offline::{feed_session, run_session};
use crate::pipeline::{
    MovingOptions, MovingScope, PassStatus, PipelineSettings, PoseStage, Products, SessionPipeline,
};
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::moving::{PlanarTrajectory, TrajectoryPoint};
use scan3d_map::octree::{Octree, Resolution, VoxelMap};
use scan3d_slam::pose::Pose2;

/// What the first run keeps: the pose stage's trajectory only.
const TRAJECTORY_ONLY: Products = Products {
    revolution_points: false,
    position_maps: false,
    cloud: false,
    static_scans: false,
    octrees: false,
    trajectory: true,
};

/// One pass as the pose stage saw it: name and span of edge time, ns (`None`: never stopped).
pub type PassSpan = (String, u64, Option<u64>);

/// A session's trajectory of `base` as the pose stage gives it.
#[derive(Debug, Clone)]
pub struct SessionTrajectory {
    /// The poses, edge ns.
    pub trajectory: PlanarTrajectory,
    /// Whether a pass start put it in the room frame (else it is in the session's own).
    pub anchored: bool,
    /// The session's passes.
    pub passes: Vec<PassSpan>,
}

/// The pose stage's room-frame poses as a trajectory (2D: roll and pitch 0); a pose not after
/// the previous one is skipped.
pub fn trajectory_of(stage: &PoseStage) -> PlanarTrajectory {
    let mut trajectory = PlanarTrajectory::new();
    for (t_ns, pose) in stage.room_poses() {
        let Pose2 { x, y, theta } = pose;
        if let Err(e) = trajectory.push(TrajectoryPoint {
            t_ns,
            x_m: x,
            y_m: y,
            yaw_rad: theta,
            roll_rad: 0.0,
            pitch_rad: 0.0,
        }) {
            tracing::warn!("a pose of the trajectory is skipped: {e}");
        }
    }
    trajectory
}

/// Runs `session_dir` through the pose stage (as `scan3d slam SESSION_DIR` and the daemon do);
/// fails when it has no RPLidar revolution to give a trajectory.
pub fn session_trajectory(session_dir: &Path, lenient: bool) -> anyhow::Result<SessionTrajectory> {
    let (pipeline, _report) = run_session(
        session_dir,
        &PipelineSettings::default(),
        TRAJECTORY_ONLY,
        lenient,
    )
    .with_context(|| {
        format!(
            "cannot track the session {} (--lenient uses what is readable)",
            session_dir.display()
        )
    })?;
    let stage = pipeline
        .pose()
        .expect("the pipeline keeps the trajectory it was asked for");
    let trajectory = trajectory_of(stage);
    if trajectory.points().is_empty() {
        anyhow::bail!(
            "{}: no RPLidar revolution, so no trajectory to place the Sweep's samples with",
            session_dir.display()
        );
    }
    Ok(SessionTrajectory {
        trajectory,
        anchored: stage.anchored(),
        passes: stage.pass_spans(),
    })
}

/// What [`assemble_moving_sessions`] made.
#[derive(Debug)]
pub struct MovingProducts {
    /// The pass's cloud (every session's, in order): room frame, one bundle per origin,
    /// through the revolution filters, cut at the max range.
    pub cloud: Vec<RayBundle>,
    /// The pass's octree, grown across the sessions (`None` when not asked for).
    pub octree: Option<Octree>,
    /// The poses of `base` used to place the samples, room frame, each session's in time order
    /// (`t_ns` on the edge's clock; roll and pitch 0 unless a fusion stage gave them).
    pub trajectory: Vec<TrajectoryPoint>,
    /// What happened in each session.
    pub sessions: Vec<MovingSessionSummary>,
}

/// One session of [`assemble_moving_sessions`].
#[derive(Debug, Clone)]
pub struct MovingSessionSummary {
    /// The session directory.
    pub dir: PathBuf,
    /// Poses the pose stage made.
    pub poses: usize,
    /// Whether a pass start put the trajectory in the room frame.
    pub anchored: bool,
    /// The passes of the session, in start order.
    pub passes: Vec<String>,
    /// The pass asked for (or the whole session, named `""`): revolutions and samples placed,
    /// points kept; `None` when the session has no such pass.
    pub placed: Option<PassStatus>,
}

/// The moving stage's product name for `pass` (`""`: the whole session).
fn product_name(pass: Option<&str>) -> &str {
    pass.unwrap_or("")
}

/// Assembles trolley passes offline through the live pipeline (pose stage, moving stage, filter
/// and map stages): each session in `sessions` in turn, the samples of the pass named `pass`
/// (the latest start of that name in each session; sessions without it are skipped) or, with
/// `None`, every Sweep sample of the session. With `octree`, the pass's octree is grown across
/// the sessions. Fails when a session cannot be read (unless `lenient`), has no RPLidar
/// revolution or no Sweep mount, or no session has the pass.
pub fn assemble_moving_sessions(
    sessions: &[PathBuf],
    settings: &PipelineSettings,
    pass: Option<&str>,
    lenient: bool,
    octree: bool,
) -> anyhow::Result<MovingProducts> {
    let name = product_name(pass);
    let products = Products {
        revolution_points: false,
        position_maps: false,
        cloud: true,
        static_scans: false,
        octrees: octree,
        trajectory: true,
    };
    let mut map: Option<VoxelMap> = None;
    let mut out = MovingProducts {
        cloud: Vec::new(),
        octree: None,
        trajectory: Vec::new(),
        sessions: Vec::new(),
    };
    let mut seen_passes: Vec<String> = Vec::new();
    for dir in sessions {
        let mut pipeline = SessionPipeline::with_products(settings, products)?;
        let moving = pipeline
            .moving_mut()
            .expect("the pipeline keeps the trajectory, so it places along it");
        moving.set_options(MovingOptions {
            scope: if pass.is_some() {
                MovingScope::Passes
            } else {
                MovingScope::Whole
            },
            // Offline the whole session may wait for its pass start (the demo's standing
            // revolutions before it): held as long as it takes.
            max_held: usize::MAX,
            keep_trajectory: true,
            ..MovingOptions::default()
        });
        if let Some(seed) = map.take() {
            pipeline.seed_pass_map(name, seed);
        }
        // Losses are checked by feed_session (an error unless lenient).
        let _report = feed_session(&mut pipeline, dir, lenient, |_| {}).with_context(|| {
            format!(
                "cannot read the session {} (--lenient uses what is readable)",
                dir.display()
            )
        })?;
        let pose = pipeline.pose().expect("the pose stage is kept");
        let poses = pose.poses().len();
        if poses == 0 {
            anyhow::bail!(
                "{}: no RPLidar revolution, so no trajectory to place the Sweep's samples with",
                dir.display()
            );
        }
        let moving = pipeline.moving().expect("the moving stage is kept");
        if !moving.mounted() {
            anyhow::bail!(
                "{}: no Sweep mount recorded (the edge's [sweep.mount]), so its samples cannot \
                 be placed",
                dir.display()
            );
        }
        let passes: Vec<String> = moving.pass_spans().into_iter().map(|p| p.0).collect();
        seen_passes.extend(passes.iter().cloned());
        let anchored = pose.anchored();
        let placed = pipeline.passes().into_iter().find(|p| p.name == name);
        out.trajectory.extend_from_slice(moving.trajectory());
        let mut maps = pipeline.take_maps();
        out.cloud.extend(maps.pass_cloud(name));
        map = maps.take_pass_map(name).or(map);
        out.sessions.push(MovingSessionSummary {
            dir: dir.clone(),
            poses,
            anchored,
            passes,
            placed,
        });
    }
    if pass.is_some() && out.sessions.iter().all(|s| s.placed.is_none()) {
        seen_passes.dedup();
        anyhow::bail!(
            "no pass named {:?} in {} (passes: {})",
            name,
            sessions
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            if seen_passes.is_empty() {
                "none".to_string()
            } else {
                seen_passes.join(", ")
            }
        );
    }
    out.octree = match map {
        Some(map) => Some(map.to_octree()),
        None if octree => Some(Octree::empty(
            Resolution::new(settings.resolution_m)?,
            settings.sensor,
        )),
        None => None,
    };
    Ok(out)
}

/// Runs `scan3d assemble --moving`.
pub fn run(args: &AssembleArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let defaults = PipelineSettings::default();
    let settings = PipelineSettings {
        resolution_m: args.resolution.unwrap_or(defaults.resolution_m),
        max_range_m: args.max_range,
        ..defaults
    };
    let res = Resolution::new(settings.resolution_m)?;
    let bt = args.bt.as_deref();
    if let Some(path) = bt
        && crate::cli::map::TreeFormat::of(path).is_none()
    {
        anyhow::bail!("{}: a map must end in .bt or .ot", path.display());
    }
    let made = assemble_moving_sessions(
        &args.session_dirs,
        &settings,
        args.pass.as_deref(),
        args.lenient,
        bt.is_some(),
    )?;
    for session in &made.sessions {
        let Some(placed) = &session.placed else {
            writeln!(
                out,
                "{}: no pass named {:?} (passes: {})",
                session.dir.display(),
                args.pass.as_deref().unwrap_or_default(),
                session.passes.join(", ")
            )?;
            continue;
        };
        writeln!(
            out,
            "{}: {} poses in the {} frame; {} Sweep revolutions placed, {} samples ({} outside \
             the trajectory), {} points kept",
            session.dir.display(),
            session.poses,
            if session.anchored {
                "room"
            } else {
                "session's own (no pass started)"
            },
            placed.revolutions,
            placed.samples,
            placed.unplaced_samples,
            placed.points,
        )?;
    }
    for path in &args.out {
        scan3d_map::cloud::io::save(path, &made.cloud)?;
        writeln!(out, "wrote {}", path.display())?;
    }
    if let (Some(path), Some(tree)) = (bt, &made.octree) {
        write_tree(path, tree)?;
        writeln!(
            out,
            "wrote {}: resolution {} m, {} leaves ({} occupied, {} free)",
            path.display(),
            res.meters(),
            tree.num_leaves(),
            tree.num_occupied(),
            tree.num_free()
        )?;
    }
    Ok(())
}
