//! `scan3d assemble --moving SESSION_DIR… --out X.ply [--resolution R] [--pass NAME] [--bt FILE]`:
//! trolley passes assembled offline (issue 21, §III-B of the paper), every Sweep sample placed
//! with the pose of `base` at its own sample time.
//!
//! Each session runs twice, streaming: first through the session pipeline with only the pose
//! stage (the live daemon's [`PoseStage`], so the trajectory is the one it gave, anchored in the
//! room frame by the pass's start), then its Sweep revolutions and its recorded Sweep mount
//! (`Body::Mounts`, the edge's `[sweep.mount]`) go to [`MovingAssembler`] along that trajectory
//! (x, y, yaw interpolated between RPLidar poses; roll and pitch 0). The cloud keeps each point's
//! sensor origin (bundles drift at most a quarter voxel, see [`scan3d_map::cloud::moving`]); the
//! octree inserts the same bundles as the static path's map stage does.

use std::io::Write;
use std::path::Path;

use anyhow::Context;

use crate::cli::assemble::AssembleArgs;
use crate::cli::map::write_tree;
use crate::pipeline::offline::run_session;
use crate::pipeline::{PipelineSettings, PoseStage, Products};
use crate::recording::visit_session;
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::moving::{
    MovingAssembler, MovingSettings, MovingTotals, PlanarTrajectory, RigidTransform,
    TrajectoryPoint,
};
use scan3d_map::octree::{Resolution, VoxelMap};
use scan3d_protocol::{Body, LidarRevolution, SensorId, SensorMount};
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

/// The samples of `rev` measured within `[from_ns, to_ns]`; `None` when none is.
fn within(rev: &LidarRevolution, from_ns: u64, to_ns: u64) -> Option<LidarRevolution> {
    let mut kept = LidarRevolution::new(rev.sensor, rev.t0_ns, rev.t1_ns);
    for (sample, t_ns) in rev.samples.iter().zip(rev.sample_times_ns()) {
        if (from_ns..=to_ns).contains(&t_ns) {
            kept.samples.push(*sample);
        }
    }
    (!kept.samples.is_empty()).then_some(kept)
}

/// A session's Sweep revolutions placed along `trajectory` (only samples within `span`, edge
/// ns, when given); every bundle handed out goes to `octree` with `max_range` (negative: none).
/// Fails when the session recorded Sweep revolutions but no Sweep mount before them.
fn assemble_session(
    session_dir: &Path,
    trajectory: &PlanarTrajectory,
    span: Option<(u64, u64)>,
    settings: &MovingSettings,
    mut octree: Option<&mut VoxelMap>,
    max_range: f64,
) -> anyhow::Result<(Vec<RayBundle>, MovingTotals)> {
    let mut assembler: Option<MovingAssembler> = None;
    let mut unmounted = 0u64;
    let mut failure: Option<anyhow::Error> = None;
    // Losses were checked (or allowed with --lenient) by the trajectory's run.
    let _report = visit_session(session_dir, |recorded| {
        match &recorded.frame.body {
            Body::Mounts(mounts) => {
                if let Some(mount) = mounts.sensors.iter().find(|m| m.sensor == SensorId::SWEEP)
                    && assembler.is_none()
                {
                    match sweep_assembler(mount, settings) {
                        Ok(new) => assembler = Some(new),
                        Err(e) => failure = failure.take().or(Some(e)),
                    }
                }
            }
            Body::Revolution(rev) if rev.sensor == SensorId::SWEEP => {
                let rev = match span {
                    Some((from, to)) => match within(rev, from, to) {
                        Some(kept) => std::borrow::Cow::Owned(kept),
                        None => return Ok(()),
                    },
                    None => std::borrow::Cow::Borrowed(rev),
                };
                match &mut assembler {
                    Some(assembler) => {
                        assembler.add_revolution(&rev, trajectory);
                        let new = assembler.take_new();
                        if let Some(octree) = octree.as_deref_mut() {
                            for bundle in &new {
                                octree.insert_bundle(bundle, max_range);
                            }
                        }
                    }
                    None => unmounted += 1,
                }
            }
            _ => {}
        }
        Ok(())
    })
    .with_context(|| format!("cannot read the session {}", session_dir.display()))?;
    if let Some(e) = failure {
        return Err(e);
    }
    match assembler {
        Some(assembler) => {
            if unmounted > 0 {
                tracing::warn!(
                    revolutions = unmounted,
                    "Sweep revolutions recorded before the Sweep's mount were skipped"
                );
            }
            let totals = assembler.totals();
            Ok((assembler.finish(), totals))
        }
        None => anyhow::bail!(
            "{}: no Sweep mount recorded (the edge's [sweep.mount]), so its samples cannot be placed",
            session_dir.display()
        ),
    }
}

/// An assembler for the Sweep at `mount`.
fn sweep_assembler(
    mount: &SensorMount,
    settings: &MovingSettings,
) -> anyhow::Result<MovingAssembler> {
    MovingAssembler::new(RigidTransform::from_sensor_mount(mount), settings.clone())
        .context("the recorded Sweep mount cannot be used")
}

/// Runs `scan3d assemble --moving`.
pub fn run(args: &AssembleArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let (session_dirs, outs, pass, bt, max_range) = (
        &args.session_dirs,
        &args.out,
        args.pass.as_deref(),
        args.bt.as_deref(),
        args.max_range,
    );
    let defaults = PipelineSettings::default();
    let res = Resolution::new(args.resolution.unwrap_or(defaults.resolution_m))?;
    if let Some(path) = bt
        && crate::cli::map::TreeFormat::of(path).is_none()
    {
        anyhow::bail!("{}: a map must end in .bt or .ot", path.display());
    }
    let mut settings = MovingSettings::for_resolution(res.meters());
    settings.max_range_m = max_range;
    let mut octree = bt.map(|_| VoxelMap::new(res, defaults.sensor));
    let mut cloud: Vec<RayBundle> = Vec::new();
    let mut found_pass = pass.is_none();
    let mut seen_passes: Vec<String> = Vec::new();
    for dir in session_dirs {
        let tracked = session_trajectory(dir, args.lenient)?;
        let span = match pass {
            Some(name) => {
                seen_passes.extend(tracked.passes.iter().map(|p| p.0.clone()));
                // The pass's last start of that name in this session, if any.
                match tracked.passes.iter().rev().find(|p| p.0 == name) {
                    Some((_, start, stop)) => {
                        found_pass = true;
                        Some((*start, stop.unwrap_or(u64::MAX)))
                    }
                    None => continue,
                }
            }
            None => None,
        };
        let (bundles, totals) = assemble_session(
            dir,
            &tracked.trajectory,
            span,
            &settings,
            octree.as_mut(),
            max_range.unwrap_or(-1.0),
        )?;
        writeln!(
            out,
            "{}: {} poses in the {} frame; {} Sweep revolutions, {} samples placed ({} without \
             a return, {} before and {} after the trajectory), {} points kept",
            dir.display(),
            tracked.trajectory.points().len(),
            if tracked.anchored {
                "room"
            } else {
                "session's own (no pass started)"
            },
            totals.revolutions,
            totals.placed,
            totals.no_return,
            totals.before_span,
            totals.after_span,
            bundles.iter().map(|b| b.points.len()).sum::<usize>(),
        )?;
        cloud.extend(bundles);
    }
    if !found_pass {
        seen_passes.dedup();
        anyhow::bail!(
            "no pass named {:?} in {} (passes: {})",
            pass.unwrap_or_default(),
            session_dirs
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
    for path in outs {
        scan3d_map::cloud::io::save(path, &cloud)?;
        writeln!(out, "wrote {}", path.display())?;
    }
    if let (Some(path), Some(map)) = (bt, octree) {
        let tree = map.to_octree();
        write_tree(path, &tree)?;
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
