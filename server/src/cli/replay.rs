//! `scan3d replay SESSION_DIR`: feeds a recorded session back through the server pipeline as
//! if it arrived live, in recorded order (optionally at the recorded pace), streaming.

use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;

use crate::pipeline::offline::feed_session;
use crate::pipeline::{PipelineSettings, Products, SessionPipeline};
use scan3d_map::cloud::filter::Filter;

/// Options of `scan3d replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// A session directory: `data_dir/sessions/<edge>/<session-id>`.
    pub session_dir: PathBuf,
    /// Write the pipeline's outputs here: `scans/<lidar>.ply` (every revolution in its sensor's
    /// plane) and the session's snapshot (`map.bt`, `map.ot`, `cloud.ply`, with `--reference`
    /// `metrics.json` and `metrics.txt`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replay at the recorded pace instead of as fast as possible.
    #[arg(long)]
    pub realtime: bool,
    /// Go on with the readable rest of a damaged recording (with a warning) instead of failing.
    #[arg(long)]
    pub lenient: bool,
    /// Voxel edge length of the octree, metres.
    #[arg(long, alias = "res", value_name = "M", default_value_t = 0.05)]
    pub resolution: f64,
    /// Rays longer than this are cut (free up to the cut, no hit), metres.
    #[arg(long, value_name = "M")]
    pub max_range: Option<f64>,
    /// Per-revolution filters, in order: `voxel:LEAF`, `box:x0,y0,z0,x1,y1,z1`, `box-out:…`.
    #[arg(long = "filter", value_name = "FILTER", allow_hyphen_values = true)]
    pub filters: Vec<Filter>,
    /// Filters of the snapshot's cloud, in order: `sor:K,ALPHA`, `gauss:SIGMA,RADIUS`, ….
    #[arg(
        long = "snapshot-filter",
        value_name = "FILTER",
        allow_hyphen_values = true
    )]
    pub snapshot_filters: Vec<Filter>,
    /// A reference map (`.bt`/`.ot`, same resolution) to compute the metrics against.
    #[arg(long, alias = "ref", value_name = "REF")]
    pub reference: Option<PathBuf>,
}

/// Runs `scan3d replay`.
pub fn run(args: &ReplayArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let settings = PipelineSettings {
        resolution_m: args.resolution,
        max_range_m: args.max_range,
        revolution_filters: args.filters.clone(),
        snapshot_filters: args.snapshot_filters.clone(),
        reference: args.reference.clone(),
        ..PipelineSettings::default()
    };
    let products = Products {
        revolution_points: true,
        ..Products::default()
    };
    let mut pipeline = SessionPipeline::with_products(&settings, products)?;
    let started = Instant::now();
    let mut first_log_time = None;
    let mut frames = 0u64;
    // Losses are checked by feed_session (an error unless --lenient).
    let _report = feed_session(&mut pipeline, &args.session_dir, args.lenient, |recorded| {
        frames += 1;
        if args.realtime {
            let first = *first_log_time.get_or_insert(recorded.log_time_ns);
            let due = Duration::from_nanos(recorded.log_time_ns.saturating_sub(first));
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
    })
    .context("cannot replay the session (--lenient replays what is readable)")?;
    writeln!(
        out,
        "replayed {frames} frames from {}",
        args.session_dir.display()
    )?;
    let status = pipeline.status();
    if status.missing_frames + status.undecodable_frames + status.stale_frames > 0 {
        writeln!(
            out,
            "skipped: {} frames missing from the session, {} undecodable, {} out of order",
            status.missing_frames, status.undecodable_frames, status.stale_frames
        )?;
    }
    let collector = pipeline
        .revolution_points()
        .context("the replay pipeline collects revolutions")?;
    for (sensor, totals) in collector.totals() {
        writeln!(
            out,
            "{sensor}: {} revolutions, {} samples, {} points",
            totals.revolutions, totals.samples, totals.points
        )?;
    }
    if let Some(dir) = &args.out {
        for path in collector.write_ply_files(&dir.join("scans"))? {
            writeln!(out, "wrote {}", path.display())?;
        }
        // The trajectory is stamped on the server's clock through the recorded models.
        pipeline.set_clock(crate::pose::timesync::SessionClock::from_session(
            &args.session_dir,
        )?);
        let snapshot = pipeline.write_snapshot(dir, None)?;
        writeln!(
            out,
            "snapshot: {} static scans, {} points, {} nodes ({} occupied, {} free voxels)",
            pipeline.assembly().static_scans(),
            snapshot.points,
            snapshot.nodes,
            snapshot.occupied_voxels,
            snapshot.free_voxels
        )?;
        for path in &snapshot.files {
            writeln!(out, "wrote {}", path.display())?;
        }
    }
    Ok(())
}
