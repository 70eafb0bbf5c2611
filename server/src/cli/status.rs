//! `scan3d status [--json]`: what the running daemon's live pipeline has built, per connected
//! edge and session: frames, samples, revolutions, occupied/free voxels, pipeline lag, time
//! sync, the latest metrics. Asks the daemon through its control socket (found like
//! `scan3d scan` finds it: `--data-dir`, or the `data_dir` of `--config`).

use std::io::Write;

use serde_json::Value;

use super::DataDirArgs;
use crate::ingest::control::{ProductRequest, request_products, socket_path};

/// Options of `scan3d status`.
#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// Print the daemon's answer as JSON (`{"edges": [{"name", "sessions": [...]}]}`).
    #[arg(long)]
    pub json: bool,
    /// Which server.
    #[command(flatten)]
    pub data: DataDirArgs,
}

/// The daemon's status report as JSON (the `data` of its reply).
pub fn query(data: &DataDirArgs) -> anyhow::Result<Value> {
    let reply = request_products(&socket_path(&data.resolve()?), &ProductRequest::Status)?;
    if !reply.ok {
        anyhow::bail!("{}", reply.detail);
    }
    reply
        .data
        .ok_or_else(|| anyhow::anyhow!("the server's status reply carries no report"))
}

/// Runs `scan3d status`.
pub fn run(args: &StatusArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let report = query(&args.data)?;
    if args.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&report)?)?;
    } else {
        write!(out, "{}", table(&report))?;
    }
    Ok(())
}

/// The report as a table, one line per session.
pub fn table(report: &Value) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:<16} {:<16} {:>7} {:>9} {:>6} {:>9} {:>9} {:>7} {:>6} {:>10} {:>8} {:>8} {:>8}",
        "edge",
        "session",
        "frames",
        "samples",
        "revs",
        "occupied",
        "free",
        "lag ms",
        "lag fr",
        "offset ms",
        "skew ppm",
        "± ms",
        "IoU w"
    );
    let edges = report["edges"].as_array().cloned().unwrap_or_default();
    if edges.is_empty() {
        let _ = writeln!(s, "(no edge connected, no session seen)");
    }
    let num = |v: &Value| v.as_u64().map_or("-".to_owned(), |n| n.to_string());
    let ms = |v: &Value, digits: usize| {
        v.as_f64()
            .map_or("-".to_owned(), |n| format!("{:.digits$}", n / 1e6))
    };
    for edge in &edges {
        let mut name = edge["name"].as_str().unwrap_or("?").to_owned();
        if edge["connected"] == Value::Bool(false) {
            name.push_str(" (gone)");
        }
        let sessions = edge["sessions"].as_array().cloned().unwrap_or_default();
        if sessions.is_empty() {
            let _ = writeln!(s, "{name:<16} (no session yet)");
        }
        for session in &sessions {
            let sync = &session["timesync"];
            let _ = writeln!(
                s,
                "{:<16} {:<16} {:>7} {:>9} {:>6} {:>9} {:>9} {:>7} {:>6} {:>10} {:>8} {:>8} {:>8}",
                name,
                session["id"].as_str().unwrap_or("?"),
                num(&session["frames"]),
                num(&session["samples"]),
                num(&session["revolutions"]),
                num(&session["occupied_voxels"]),
                num(&session["free_voxels"]),
                num(&session["lag_ms"]),
                num(&session["lag_frames"]),
                ms(&sync["offset_ns"], 3),
                sync["skew_ppm"]
                    .as_f64()
                    .map_or("-".to_owned(), |p| format!("{p:.2}")),
                ms(&sync["error_bound_ns"], 3),
                session["metrics"]["iou"]["weighted"]
                    .as_f64()
                    .map_or("-".to_owned(), |w| format!("{w:.4}")),
            );
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_has_a_line_per_session_with_its_lag_and_time_sync() {
        let report = serde_json::json!({"edges": [{"name": "pi", "connected": true, "sessions": [
            {"id": "00000000000000ab", "frames": 12, "samples": 3400, "revolutions": 7,
             "occupied_voxels": 90, "free_voxels": 1200, "lag_ms": 35, "lag_frames": 2,
             "timesync": {"offset_ns": -1_500_000, "skew_ppm": null, "error_bound_ns": 250_000},
             "metrics": null}]}]});
        let table = table(&report);
        let line = table.lines().nth(1).unwrap();
        let cells: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(
            cells,
            [
                "pi",
                "00000000000000ab",
                "12",
                "3400",
                "7",
                "90",
                "1200",
                "35",
                "2",
                "-1.500",
                "-",
                "0.250",
                "-"
            ]
        );
        let empty = super::table(&serde_json::json!({"edges": []}));
        assert!(empty.contains("no edge connected"), "{empty}");
    }
}
