//! `scan3d snapshot --edge NAME [--session ID] [--position NAME] --out DIR`: the running daemon
//! writes a session's live products into DIR: the octree (`.bt` and `.ot`), the cloud (PLY)
//! and, with a reference configured, the metric table. Default: the edge's latest session. A
//! session without 3D data yet (lidar only) gives a valid empty map and cloud. `--json` prints
//! the daemon's answer (the files written, with its `detail`) as one JSON object.

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
    /// Print the daemon's answer as JSON (`{"detail", "files": [...], ...}`).
    #[arg(long)]
    pub json: bool,
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
    if args.json {
        let mut value = reply.data.clone().unwrap_or(serde_json::Value::Null);
        if let serde_json::Value::Object(object) = &mut value {
            object.insert("detail".into(), reply.detail.clone().into());
        } else {
            value = serde_json::json!({ "detail": reply.detail, "data": value });
        }
        writeln!(out, "{}", serde_json::to_string_pretty(&value)?)?;
        return Ok(());
    }
    writeln!(out, "{}", reply.detail)?;
    if let Some(files) = reply.data.as_ref().and_then(|d| d["files"].as_array()) {
        for file in files.iter().filter_map(|f| f.as_str()) {
            writeln!(out, "wrote {file}")?;
        }
    }
    Ok(())
}
