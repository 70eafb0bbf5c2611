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
    /// Print the daemon's answer as JSON (`{"edges": [{"name", "connected", "sensors": [...],
    /// "static_scans": [...], "sessions": [...]}]}`).
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

/// Lays out rows of cells in columns as wide as their widest cell: the first `left` columns
/// left-aligned, the others right-aligned, two spaces between.
fn columns(rows: &[Vec<String>], left: usize) -> String {
    use std::fmt::Write as _;
    let width = |i: usize| {
        rows.iter()
            .filter_map(|row| row.get(i))
            .map(|cell| cell.chars().count())
            .max()
            .unwrap_or(0)
    };
    let widths: Vec<usize> = (0..rows.iter().map(Vec::len).max().unwrap_or(0))
        .map(width)
        .collect();
    let mut s = String::new();
    for row in rows {
        let mut line = String::new();
        for (i, cell) in row.iter().enumerate() {
            if i > 0 {
                line.push_str("  ");
            }
            let _ = if i < left {
                write!(line, "{cell:<w$}", w = widths[i])
            } else {
                write!(line, "{cell:>w$}", w = widths[i])
            };
        }
        let _ = writeln!(s, "{}", line.trim_end());
    }
    s
}

/// The report for a human: one line per session (clock sync as its error bound and skew:
/// the raw offset between two unrelated monotonic clocks means nothing to read), then each
/// edge's sensors, the head's live pose per session and the static scans.
pub fn table(report: &Value) -> String {
    use std::fmt::Write as _;
    let edges = report["edges"].as_array().cloned().unwrap_or_default();
    if edges.is_empty() {
        return "(no edge connected, no session seen)\n".to_owned();
    }
    let num = |v: &Value| v.as_u64().map_or("-".to_owned(), |n| n.to_string());
    let fixed = |v: &Value, scale: f64, digits: usize| {
        v.as_f64()
            .map_or("-".to_owned(), |n| format!("{:.digits$}", n / scale))
    };
    let mut rows = vec![
        [
            "edge",
            "state",
            "session",
            "frames",
            "samples",
            "revs",
            "occupied",
            "free",
            "lag ms",
            "lag fr",
            "sync ±ms",
            "skew ppm",
            "IoU w",
        ]
        .map(str::to_owned)
        .to_vec(),
    ];
    for edge in &edges {
        let name = edge["name"].as_str().unwrap_or("?").to_owned();
        let state = if edge["connected"] == Value::Bool(false) {
            "gone"
        } else {
            "connected"
        };
        let sessions = edge["sessions"].as_array().cloned().unwrap_or_default();
        if sessions.is_empty() {
            rows.push(vec![
                name.clone(),
                state.to_owned(),
                "(no session yet)".to_owned(),
            ]);
        }
        for session in &sessions {
            let sync = &session["timesync"];
            // A retired worker's numbers are its last; its snapshots come from disk.
            let state = if session["retired"] == Value::Bool(true) {
                "retired"
            } else {
                state
            };
            rows.push(vec![
                name.clone(),
                state.to_owned(),
                session["id"].as_str().unwrap_or("?").to_owned(),
                num(&session["frames"]),
                num(&session["samples"]),
                num(&session["revolutions"]),
                num(&session["occupied_voxels"]),
                num(&session["free_voxels"]),
                num(&session["lag_ms"]),
                num(&session["lag_frames"]),
                fixed(&sync["error_bound_ns"], 1e6, 3),
                fixed(&sync["skew_ppm"], 1.0, 2),
                fixed(&session["metrics"]["iou"]["weighted"], 1.0, 4),
            ]);
        }
    }
    let mut s = columns(&rows, 3);
    for edge in &edges {
        let name = edge["name"].as_str().unwrap_or("?");
        let sensors = edge["sensors"].as_array().cloned().unwrap_or_default();
        if !sensors.is_empty() {
            let _ = writeln!(s, "\n{name}: sensors");
            let mut rows = vec![
                [
                    "sensor",
                    "model",
                    "state",
                    "frames/s",
                    "samples/s",
                    "last data",
                ]
                .map(str::to_owned)
                .to_vec(),
            ];
            let mut reasons = vec![String::new()];
            for sensor in &sensors {
                let state = sensor["state"].as_str().unwrap_or("?").to_owned();
                // The reason goes last: it can be a long error chain, and trailing it keeps the
                // numeric columns aligned and readable.
                let reason = sensor["reason"].as_str().unwrap_or("").to_owned();
                rows.push(vec![
                    sensor["kind"].as_str().unwrap_or("?").to_owned(),
                    sensor["model"].as_str().unwrap_or("").to_owned(),
                    state,
                    fixed(&sensor["frames_per_s"], 1.0, 1),
                    fixed(&sensor["samples_per_s"], 1.0, 0),
                    sensor["last_data_age_s"]
                        .as_f64()
                        .map_or("never".to_owned(), |a| format!("{a:.1} s ago")),
                ]);
                reasons.push(reason);
            }
            // The header's reason is empty; each sensor's trails its row.
            for (line, reason) in columns(&rows, 3).lines().zip(reasons) {
                let _ = writeln!(s, "  {}", format!("{line}  {reason}").trim_end());
            }
        }
        let sessions = edge["sessions"].as_array().cloned().unwrap_or_default();
        let posed: Vec<&Value> = sessions.iter().filter(|s| s["pose"].is_object()).collect();
        if !posed.is_empty() {
            let _ = writeln!(s, "\n{name}: pose of the head (live, from the RPLidar)");
            for session in posed {
                let pose = &session["pose"];
                let c = |i: usize| pose["covariance"][i].as_f64().unwrap_or(f64::NAN);
                let frame = if pose["anchored"] == Value::Bool(true) {
                    "room frame"
                } else {
                    "session frame: no pass started"
                };
                let _ = writeln!(
                    s,
                    "  {}: x {:.3} m, y {:.3} m, yaw {:.1}° (σ {:.0} mm, {:.2}°), path {:.1} m ({frame})",
                    session["id"].as_str().unwrap_or("?"),
                    pose["x"].as_f64().unwrap_or(f64::NAN),
                    pose["y"].as_f64().unwrap_or(f64::NAN),
                    pose["yaw_deg"].as_f64().unwrap_or(f64::NAN),
                    (c(0) + c(4)).sqrt() * 1e3,
                    c(8).sqrt().to_degrees(),
                    pose["path_m"].as_f64().unwrap_or(f64::NAN),
                );
                let latency = &session["revolution_to_pose"];
                if latency.is_object() {
                    let server = &session["accept_to_pose"];
                    let server = if server.is_object() {
                        format!(
                            "; on the server {} (p50), {} (p99)",
                            fixed(&server["p50_ms"], 1.0, 0) + " ms",
                            fixed(&server["p99_ms"], 1.0, 0) + " ms",
                        )
                    } else {
                        String::new()
                    };
                    let _ = writeln!(
                        s,
                        "    pose {} after its revolution's end (p50), {} (p99), over {} poses{server}",
                        fixed(&latency["p50_ms"], 1.0, 0) + " ms",
                        fixed(&latency["p99_ms"], 1.0, 0) + " ms",
                        num(&latency["count"]),
                    );
                }
            }
        }
        let passes: Vec<(&str, &Value)> = sessions
            .iter()
            .flat_map(|session| {
                let id = session["id"].as_str().unwrap_or("?");
                session["passes"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(move |pass| (id, pass))
            })
            .collect();
        if !passes.is_empty() {
            let _ = writeln!(
                s,
                "\n{name}: trolley passes (placed live along the trajectory)"
            );
            for (id, pass) in passes {
                let state = if pass["stopped"] == Value::Bool(true) {
                    "stopped"
                } else {
                    "running"
                };
                let _ = writeln!(
                    s,
                    "  {:?} ({id}): {state}, {} Sweep revolutions, {} points, {} held, {} dropped",
                    pass["name"].as_str().unwrap_or("?"),
                    num(&pass["revolutions"]),
                    num(&pass["points"]),
                    num(&pass["held"]),
                    num(&pass["dropped"]),
                );
            }
        }
        let scans = edge["static_scans"].as_array().cloned().unwrap_or_default();
        if !scans.is_empty() {
            let _ = writeln!(s, "\n{name}: static scans");
            for scan in &scans {
                let _ = writeln!(
                    s,
                    "  scan {} at {:?} ({}): {}, {} revolutions, yaw {:.1}° of {:.1}°, {} late steps",
                    num(&scan["scan_id"]),
                    scan["position"].as_str().unwrap_or(""),
                    scan["session"].as_str().unwrap_or("?"),
                    scan["outcome"].as_str().unwrap_or("running"),
                    num(&scan["revolutions"]),
                    scan["yaw_deg"].as_f64().unwrap_or(0.0),
                    scan["total_deg"].as_f64().unwrap_or(0.0),
                    num(&scan["late_steps"]),
                );
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_fits_its_columns_and_shows_sync_as_bound_and_skew() {
        let report = serde_json::json!({"edges": [
            {"name": "pi", "connected": true, "sessions": [
                {"id": "00000000000000ab", "frames": 12, "samples": 3400, "revolutions": 7,
                 "occupied_voxels": 90, "free_voxels": 1200, "lag_ms": 35, "lag_frames": 2,
                 "timesync": {"offset_ns": -1_796_277_375_188_796_000i64, "skew_ppm": 1.234,
                              "error_bound_ns": 250_000},
                 "metrics": null,
                 "pose": {"x": 1.5082, "y": 2.1798, "yaw_deg": -89.75,
                          "covariance": [9e-6, 0.0, 0.0, 0.0, 7e-6, 0.0, 0.0, 0.0, 4e-6],
                          "path_m": 16.39, "revolutions": 475, "anchored": true}}],
             "sensors": [{"kind": "sweep", "model": "Sweep", "state": "lost",
                          "reason": "unplugged", "frames_per_s": 2.0, "samples_per_s": 1000.0,
                          "last_data_age_s": 4.25}],
             "static_scans": [{"session": "00000000000000ab", "scan_id": 0, "position": "door",
                               "total_deg": 360.0, "revolutions": 12, "yaw_deg": 43.2,
                               "late_steps": 1, "failed_steps": 0, "warnings": 1,
                               "tagged": 100, "outcome": null}]},
            {"name": "a-much-longer-edge-name", "connected": false, "sessions": [
                {"id": "00000000000000cd", "frames": 1, "samples": 0, "revolutions": 0,
                 "occupied_voxels": 0, "free_voxels": 0, "lag_ms": 0, "lag_frames": 0,
                 "timesync": null, "metrics": null}]}]});
        let table = table(&report);
        let lines: Vec<&str> = table.lines().collect();
        let cells: Vec<&str> = lines[1].split_whitespace().collect();
        assert_eq!(
            cells,
            [
                "pi",
                "connected",
                "00000000000000ab",
                "12",
                "3400",
                "7",
                "90",
                "1200",
                "35",
                "2",
                "0.250",
                "1.23",
                "-"
            ]
        );
        assert!(!table.contains("1796277"), "no raw offset: {table}");
        // Columns line up whatever the names: every session starts at the same column.
        let at = |line: &str| line.find("000000000000").unwrap();
        assert_eq!(at(lines[1]), at(lines[2]), "{table}");
        assert!(
            lines[2].starts_with("a-much-longer-edge-name  gone "),
            "{table}"
        );
        let sweep = table
            .lines()
            .find(|line| line.trim_start().starts_with("sweep"))
            .expect("a sweep row");
        assert!(
            sweep.contains(" lost ") && sweep.ends_with("s ago  unplugged"),
            "the reason trails the row: {table}"
        );
        assert!(
            table.contains("4.2 s ago") || table.contains("4.3 s ago"),
            "{table}"
        );
        assert!(
            table.contains(
                "scan 0 at \"door\" (00000000000000ab): running, 12 revolutions, yaw 43.2° of 360.0°, 1 late steps"
            ),
            "{table}"
        );
        assert!(
            table.contains(
                "00000000000000ab: x 1.508 m, y 2.180 m, yaw -89.8° (σ 4 mm, 0.11°), path 16.4 m (room frame)"
            ),
            "{table}"
        );
        let empty = super::table(&serde_json::json!({"edges": []}));
        assert!(empty.contains("no edge connected"), "{empty}");
    }

    #[test]
    fn the_table_shows_retired_sessions_passes_and_the_pose_latency() {
        let report = serde_json::json!({"edges": [
            {"name": "pi", "connected": true, "sensors": [], "static_scans": [], "sessions": [
                {"id": "00000000000000ab", "retired": true, "frames": 3, "samples": 0,
                 "revolutions": 0, "occupied_voxels": 0, "free_voxels": 0, "lag_ms": 0,
                 "lag_frames": 0, "timesync": null, "metrics": null},
                {"id": "00000000000000cd", "retired": false, "frames": 9, "samples": 10,
                 "revolutions": 2, "occupied_voxels": 1, "free_voxels": 2, "lag_ms": 0,
                 "lag_frames": 0, "timesync": null, "metrics": null,
                 "pose": {"x": 0.0, "y": 0.0, "yaw_deg": 0.0, "covariance": [0, 0, 0, 0, 0, 0, 0, 0, 0],
                          "path_m": 0.0, "revolutions": 2, "anchored": true},
                 "revolution_to_pose": {"count": 475, "p50_ms": 99.07, "p99_ms": 161.9,
                                        "max_ms": 219.5},
                 "accept_to_pose": {"count": 475, "p50_ms": 4.2, "p99_ms": 11.6, "max_ms": 30.0},
                 "passes": [{"name": "loop", "stopped": false, "revolutions": 400,
                             "samples": 43015, "unplaced_samples": 0, "points": 43015,
                             "held": 1, "dropped": 0}]}]}]});
        let table = table(&report);
        let lines: Vec<&str> = table.lines().collect();
        assert!(
            lines[1].starts_with("pi    retired    00000000000000ab"),
            "{table}"
        );
        assert!(
            lines[2].starts_with("pi    connected  00000000000000cd"),
            "{table}"
        );
        assert!(
            table.contains(
                "pose 99 ms after its revolution's end (p50), 162 ms (p99), over 475 poses; \
                 on the server 4 ms (p50), 12 ms (p99)"
            ),
            "{table}"
        );
        assert!(
            table.contains(
                "\"loop\" (00000000000000cd): running, 400 Sweep revolutions, 43015 points, 1 held, 0 dropped"
            ),
            "{table}"
        );
    }
}
