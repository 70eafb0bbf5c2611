//! The offline drivers: a recorded session streamed through a [`SessionPipeline`] frame by frame
//! ([`visit_session_items`]; never the whole session in memory), for `scan3d replay`,
//! `scan3d assemble`, `scan3d map SESSION_DIR` and the simulator.
//!
//! The recording's order is the edges' sequence order: an edge sends its frames in order on one
//! stream, resends keep their number and the recorder drops duplicates. Frames lost from a
//! damaged recording are a gap the pipeline counts; undecodable frames are counted as such.

use std::path::Path;

use scan3d_map::cloud::assembly::AssembledScan;

use super::{PipelineError, PipelineSettings, Products, SessionPipeline};
use crate::recording::{
    RecordedFrame, RecorderError, SessionItem, SessionReport, check_losses, visit_session_items,
};

/// Why a recorded session could not be run through the pipeline.
#[derive(Debug, thiserror::Error)]
pub enum SessionRunError {
    /// The pipeline could not be built (settings, reference map).
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// The recording could not be read (or is damaged and `lenient` was not given).
    #[error(transparent)]
    Recorder(#[from] RecorderError),
}

/// Feeds every frame of the session in `session_dir` to `pipeline`, calling `before` with each
/// recorded frame first (e.g. to keep the recorded pace), then flushes it. A damaged recording
/// fails with [`RecorderError::Damaged`] after the readable frames were fed, unless `lenient`
/// (then a warning says what was lost).
pub fn feed_session(
    pipeline: &mut SessionPipeline,
    session_dir: &Path,
    lenient: bool,
    mut before: impl FnMut(&RecordedFrame),
) -> Result<SessionReport, RecorderError> {
    let report = visit_session_items(session_dir, |item| {
        match item {
            SessionItem::Frame(recorded) => {
                before(&recorded);
                pipeline.on_frame(&recorded.frame);
            }
            SessionItem::Undecodable(frame) => {
                tracing::warn!(
                    dir = %session_dir.display(),
                    seq = frame.seq,
                    reason = %frame.reason,
                    "skipping a frame the server could not decode"
                );
                pipeline.on_undecodable(frame.seq);
            }
        }
        Ok(())
    })?;
    pipeline.flush();
    check_losses(&report, session_dir, lenient)?;
    Ok(report)
}

/// Runs a recorded session through a pipeline with `settings` keeping `products`; returns the
/// pipeline and the reader's report (losses already checked, see [`feed_session`]).
pub fn run_session(
    session_dir: &Path,
    settings: &PipelineSettings,
    products: Products,
    lenient: bool,
) -> Result<(SessionPipeline, SessionReport), SessionRunError> {
    let mut pipeline = SessionPipeline::with_products(settings, products)?;
    let report = feed_session(&mut pipeline, session_dir, lenient, |_| {})?;
    Ok((pipeline, report))
}

/// The static scans of a session directory, assembled by the pipeline's assembly stage; with
/// `lenient`, from what is readable of a damaged recording.
pub fn assemble_session(
    session_dir: &Path,
    lenient: bool,
) -> Result<Vec<AssembledScan>, RecorderError> {
    let products = Products {
        revolution_points: false,
        position_maps: false,
        cloud: false,
        static_scans: true,
        octrees: false,
        trajectory: false,
    };
    let mut pipeline = SessionPipeline::with_products(&PipelineSettings::default(), products)
        .expect("the default settings are valid and name no reference");
    // Losses are checked by feed_session (an error unless lenient).
    let _report = feed_session(&mut pipeline, session_dir, lenient, |_| {})?;
    let orphans = pipeline.assembly().orphan_samples();
    if orphans > 0 {
        tracing::warn!(
            samples = orphans,
            "static-scan samples without a recorded start were skipped"
        );
    }
    Ok(pipeline.into_static_scans())
}

/// What `scan3d map SESSION_DIR` keeps: the session's octree only.
pub const MAP_ONLY: Products = Products {
    revolution_points: false,
    position_maps: false,
    cloud: false,
    static_scans: false,
    octrees: true,
    trajectory: false,
};
