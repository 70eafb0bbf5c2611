//! `scan3d snapshot --edge NAME [--session ID] [--position NAME] --out DIR`: the running daemon
//! writes a session's live products into DIR: the octree (`.bt` and `.ot`), the cloud (PLY)
//! and, with a reference configured, the metric table. Default: the edge's latest session. A
//! session without 3D data yet (lidar only) gives a valid empty map and cloud.

use std::io::Write;
use std::path::PathBuf;

use super::DataDirArgs;
use crate::ingest::control::{request_snapshot, socket_path};

/// Options of `scan3d snapshot`.
#[derive(Debug, clap::Args)]
pub struct SnapshotArgs {
    /// The edge's name (as in its certificate).
    #[arg(long)]
    pub edge: String,
    /// The session (16 hex digits, its directory's name); default: the edge's latest.
    #[arg(long, value_name = "ID")]
    pub session: Option<String>,
    /// Only this static-scan position's products.
    #[arg(long, value_name = "NAME")]
    pub position: Option<String>,
    /// The directory to write into (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Which server.
    #[command(flatten)]
    pub data: DataDirArgs,
}

/// Runs `scan3d snapshot`.
pub fn run(args: &SnapshotArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let reply = request_snapshot(
        &socket_path(&args.data.resolve()?),
        &args.edge,
        args.session.as_deref(),
        args.position.as_deref(),
        &args.out,
    )?;
    writeln!(out, "{}", reply.detail)?;
    if let Some(files) = reply.data.as_ref().and_then(|d| d["files"].as_array()) {
        for file in files.iter().filter_map(|f| f.as_str()) {
            writeln!(out, "wrote {file}")?;
        }
    }
    Ok(())
}
