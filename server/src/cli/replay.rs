//! `scan3d replay SESSION_DIR`: feeds a recorded session back through the server pipeline as
//! if it arrived live, in recorded order (optionally at the recorded pace).

use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;

use crate::ingest::recorder::read_session_checked;
use scan3d_map::cloud::scans::ScanCollector;

/// Options of `scan3d replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// A session directory: `data_dir/sessions/<edge>/<session-id>`.
    pub session_dir: PathBuf,
    /// Write the pipeline's outputs here (today: `scans/<lidar>.ply`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replay at the recorded pace instead of as fast as possible.
    #[arg(long)]
    pub realtime: bool,
    /// Go on with the readable rest of a damaged recording (with a warning) instead of failing.
    #[arg(long)]
    pub lenient: bool,
}

/// Runs `scan3d replay`.
pub fn run(args: &ReplayArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let frames = read_session_checked(&args.session_dir, args.lenient)
        .context("cannot replay the session (--lenient replays what is readable)")?;
    let mut collector = ScanCollector::new();
    let started = Instant::now();
    let first_log_time = frames.first().map_or(0, |f| f.log_time_ns);
    for recorded in &frames {
        if args.realtime {
            let due = Duration::from_nanos(recorded.log_time_ns.saturating_sub(first_log_time));
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        collector.on_frame(&recorded.frame);
    }
    writeln!(
        out,
        "replayed {} frames from {}",
        frames.len(),
        args.session_dir.display()
    )?;
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
    }
    Ok(())
}
