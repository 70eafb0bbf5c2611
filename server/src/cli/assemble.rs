//! `scan3d assemble SESSION_DIR… --out cloud.ply|cloud.pcd|cloud.scans`: the static scans of
//! recorded sessions, turned into one world-frame cloud by eq. (1) and spliced across positions
//! (and sessions: an edge that rebooted between positions records a new session).
//!
//! With `--moving` the sessions are trolley passes instead, every Sweep sample placed with the
//! pose at its own time ([`super::assemble_moving`]).
//!
//! Every output keeps each point's sensor origin (one per half revolution), so `.scans` feeds
//! the octree's ray casting directly and PLY/PCD open in any viewer.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;

use crate::pipeline::offline;
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::assembly::{AssembledScan, cut_range};
use scan3d_map::cloud::io;

/// Options of `scan3d assemble`.
#[derive(Debug, clap::Args)]
pub struct AssembleArgs {
    /// Session directories: `data_dir/sessions/<edge>/<session-id>`.
    #[arg(required = true, num_args = 1..)]
    pub session_dirs: Vec<PathBuf>,
    /// Output file(s); the format follows the extension (`.ply`, `.pcd`, `.scans`).
    #[arg(long, required = true)]
    pub out: Vec<PathBuf>,
    /// Only these positions (by name; repeatable). Default: every scan of the sessions.
    #[arg(long = "position", value_name = "NAME")]
    pub positions: Vec<String>,
    /// Drop points farther than this from their sensor origin, metres.
    #[arg(long, value_name = "M")]
    pub max_range: Option<f64>,
    /// Go on with the readable rest of a damaged recording (with a warning) instead of failing.
    #[arg(long)]
    pub lenient: bool,
    /// Trolley passes: place every Sweep sample with the pose of `base` at its own time (the
    /// pose stage's trajectory from the RPLidar and IMU, in the room frame the pass anchors).
    #[arg(long, conflicts_with = "positions")]
    pub moving: bool,
    /// With `--moving`: only the samples within the pass of this name.
    #[arg(long, value_name = "NAME", requires = "moving")]
    pub pass: Option<String>,
    /// With `--moving`: the octree's voxel edge, metres (default the pipeline's, 0.05); ray
    /// bundles keep their origins within a quarter of it.
    #[arg(long, alias = "res", value_name = "M", requires = "moving")]
    pub resolution: Option<f64>,
    /// With `--moving`: also write the octree (`.bt` or `.ot`), the bundles inserted from their
    /// origins as the map stage inserts a static scan's.
    #[arg(long, value_name = "FILE", requires = "moving")]
    pub bt: Option<PathBuf>,
}

/// The scans of a session directory, assembled; fails if part of the recording is damaged.
/// (For the simulator until it calls [`crate::pipeline::offline::assemble_session`] itself.)
pub fn assemble_session(session_dir: &std::path::Path) -> anyhow::Result<Vec<AssembledScan>> {
    assemble_session_checked(session_dir, false)
}

/// The scans of a session directory, assembled by the pipeline's assembly stage, streaming;
/// with `lenient`, from what is readable of a damaged recording.
fn assemble_session_checked(
    session_dir: &std::path::Path,
    lenient: bool,
) -> anyhow::Result<Vec<AssembledScan>> {
    offline::assemble_session(session_dir, lenient)
        .context("cannot assemble the session (--lenient assembles what is readable)")
}

/// Runs `scan3d assemble`.
pub fn run(args: &AssembleArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    for path in &args.out {
        io::CloudFormat::from_path(path).ok_or_else(|| {
            anyhow::anyhow!(
                "{}: unknown cloud format (use .ply, .pcd or .scans)",
                path.display()
            )
        })?;
    }
    if args.moving {
        return crate::cli::assemble_moving::run(args, out);
    }
    let mut scans: Vec<AssembledScan> = Vec::new();
    for dir in &args.session_dirs {
        scans.extend(
            assemble_session_checked(dir, args.lenient)?
                .into_iter()
                .filter(|s| args.positions.is_empty() || args.positions.contains(&s.position.name)),
        );
    }
    if scans.is_empty() {
        anyhow::bail!(
            "no static scan{} in {}",
            if args.positions.is_empty() {
                String::new()
            } else {
                format!(" at {}", args.positions.join(", "))
            },
            args.session_dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    for scan in &scans {
        writeln!(
            out,
            "scan {} at {} ({:.2}, {:.2}, heading {:.1}°): {} points, {} origins, {} warnings, {}",
            scan.scan_id,
            scan.position.name,
            scan.position.x_m,
            scan.position.y_m,
            scan.position.heading_deg,
            scan.points(),
            scan.scans.len(),
            scan.warnings.len(),
            match scan.outcome {
                Some(outcome) => format!("{outcome:?}").to_lowercase(),
                None => "end not recorded".into(),
            }
        )?;
    }
    let mut cloud: Vec<RayBundle> = scans.into_iter().flat_map(|s| s.scans).collect();
    if let Some(max_range) = args.max_range {
        let cut = cut_range(&mut cloud, max_range);
        writeln!(out, "dropped {cut} points beyond {max_range} m")?;
    }
    for path in &args.out {
        io::save(path, &cloud)?;
        writeln!(out, "wrote {}", path.display())?;
    }
    Ok(())
}
