//! `scan3d sessions`: lists the recorded sessions under a data directory, as a table or as JSON
//! lines (one object per session).

use std::io::Write;

use anyhow::Context;

use super::DataDirArgs;
use crate::recording::{SessionReport, SessionSummary, list_sessions};

/// Options of `scan3d sessions`.
#[derive(Debug, clap::Args)]
pub struct SessionsArgs {
    /// Where the sessions are.
    #[command(flatten)]
    pub data: DataDirArgs,
    /// Print one JSON object per session instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Exit 0 even when a recording is damaged (the damage is still listed and warned about).
    #[arg(long)]
    pub lenient: bool,
}

/// Lidar revolutions per sensor, from the `/scan3d/lidar/<sensor>` topic counts.
fn revolutions(summary: &SessionSummary) -> Vec<(&str, u64)> {
    summary
        .frames_per_topic
        .iter()
        .filter_map(|(topic, &n)| Some((topic.strip_prefix("/scan3d/lidar/")?, n)))
        .collect()
}

/// Seconds of data: from the first to the last sample time (the edge's clock), whatever the
/// files and however late the frames arrived.
fn duration_s(summary: &SessionSummary) -> f64 {
    match (summary.first_sample_ns, summary.last_sample_ns) {
        (Some(first), Some(last)) => last.saturating_sub(first) as f64 / 1e9,
        _ => 0.0,
    }
}

/// Files a crash cut short (not those a live server is still writing).
fn cut_short(summary: &SessionSummary) -> usize {
    summary
        .incomplete_files
        .saturating_sub(summary.files_being_written)
}

fn json_line(summary: &SessionSummary) -> serde_json::Value {
    serde_json::json!({
        "edge": summary.edge,
        "session": format!("{:016x}", summary.session_id),
        "dir": summary.dir,
        "files": summary.files,
        "incomplete_files": summary.incomplete_files,
        "cut_short_files": cut_short(summary),
        "open": summary.files_being_written > 0,
        "frames": summary.frames,
        "frames_per_topic": summary.frames_per_topic,
        "revolutions": revolutions(summary).into_iter().collect::<std::collections::BTreeMap<_, _>>(),
        "skipped_messages": summary.skipped_messages,
        "undecodable_frames": summary.undecodable_frames,
        "losses": summary.losses,
        "missing_seqs": summary.missing_seqs,
        "first_log_time_ns": summary.first_log_time_ns,
        "last_log_time_ns": summary.last_log_time_ns,
        "first_sample_ns": summary.first_sample_ns,
        "last_sample_ns": summary.last_sample_ns,
        "duration_s": duration_s(summary),
        "bytes": summary.bytes,
    })
}

/// Runs `scan3d sessions`.
pub fn run(args: &SessionsArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let data_dir = args.data.resolve()?;
    let sessions = list_sessions(&data_dir)
        .with_context(|| format!("cannot list sessions under {}", data_dir.display()))?;
    print(args, &data_dir, &sessions, out)?;
    let damaged: Vec<String> = sessions.iter().filter_map(loss_line).collect();
    if damaged.is_empty() {
        return Ok(());
    }
    let line = damaged.join("; ");
    if args.lenient {
        tracing::warn!("recordings damaged: {line}");
        return Ok(());
    }
    anyhow::bail!("recordings damaged (--lenient to list anyway): {line}")
}

/// What a session lost, in one line (see [`SessionReport::loss_line`]).
fn loss_line(summary: &SessionSummary) -> Option<String> {
    SessionReport {
        losses: summary.losses.clone(),
        missing_seqs: summary.missing_seqs.clone(),
        ..SessionReport::default()
    }
    .loss_line()
}

/// The table (or JSON lines) of `scan3d sessions`.
fn print(
    args: &SessionsArgs,
    data_dir: &std::path::Path,
    sessions: &[SessionSummary],
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    if args.json {
        for summary in sessions {
            writeln!(out, "{}", json_line(summary))?;
        }
        return Ok(());
    }
    if sessions.is_empty() {
        writeln!(
            out,
            "no sessions under {}",
            data_dir.join("sessions").display()
        )?;
        return Ok(());
    }
    let rows: Vec<[String; 6]> = sessions
        .iter()
        .map(|s| {
            let revs = revolutions(s)
                .into_iter()
                .map(|(sensor, n)| format!("{sensor}={n}"))
                .collect::<Vec<_>>()
                .join(" ");
            let mut notes = Vec::new();
            if s.files_being_written > 0 {
                notes.push("open: being recorded".to_owned());
            }
            if cut_short(s) > 0 {
                notes.push(format!("{} cut short", cut_short(s)));
            }
            if !s.losses.is_empty() {
                notes.push(format!("{} damaged", s.losses.len()));
            }
            let files = if notes.is_empty() {
                s.files.to_string()
            } else {
                format!("{} ({})", s.files, notes.join(", "))
            };
            [
                s.edge.clone(),
                format!("{:016x}", s.session_id),
                files,
                s.frames.to_string(),
                if revs.is_empty() { "-".into() } else { revs },
                format!("{:.1} s", duration_s(s)),
            ]
        })
        .collect();
    let header = [
        "EDGE",
        "SESSION",
        "FILES",
        "FRAMES",
        "REVOLUTIONS",
        "DURATION",
    ];
    let mut widths = header.map(str::len);
    for row in &rows {
        for (width, cell) in widths.iter_mut().zip(row) {
            *width = (*width).max(cell.len());
        }
    }
    let mut print = |cells: [&str; 6]| -> std::io::Result<()> {
        let line: Vec<String> = cells
            .iter()
            .zip(widths)
            .enumerate()
            .map(|(i, (cell, w))| match i {
                // Numbers right-aligned.
                2 | 3 => format!("{cell:>w$}"),
                _ => format!("{cell:<w$}"),
            })
            .collect();
        writeln!(out, "{}", line.join("  ").trim_end())
    };
    print(header)?;
    for row in &rows {
        print(row.each_ref().map(String::as_str))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;
    use crate::recording::SessionRecorder;
    use scan3d_protocol::{Frame, Hello, LidarRevolution, SensorId, encode};

    fn record(data_dir: &std::path::Path) {
        record_open(data_dir).close().expect("close");
    }

    /// The session of [`record`], its recorder still open (as a live server has it).
    fn record_open(data_dir: &std::path::Path) -> SessionRecorder {
        let mut rec = SessionRecorder::open(data_dir, "trolley-pi", 0xabc).expect("open");
        let frames = [
            Frame::new(0xabc, 0, Hello::new("trolley-pi", "0.1.0", vec![])),
            // 58 s of data (edge clock), received within 2.5 s (a backlog sent late).
            Frame::new(
                0xabc,
                1,
                LidarRevolution::new(SensorId::RPLIDAR, 1_000_000_000, 1_100_000_000),
            ),
            Frame::new(
                0xabc,
                2,
                LidarRevolution::new(SensorId::SWEEP, 5_000_000_000, 5_500_000_000),
            ),
            Frame::new(
                0xabc,
                3,
                LidarRevolution::new(SensorId::RPLIDAR, 58_900_000_000, 59_000_000_000),
            ),
        ];
        // Receive times 1.0 s .. 3.5 s after the epoch.
        for (i, frame) in frames.iter().enumerate() {
            let raw = encode(frame).expect("encode");
            let t = 1_000_000_000 + i as u64 * 833_333_333;
            rec.append(&raw, frame, t).expect("append");
        }
        rec.commit().expect("commit");
        rec
    }

    fn table_of(data_dir: &std::path::Path) -> String {
        let mut out = Vec::new();
        let args = SessionsArgs {
            data: DataDirArgs {
                data_dir: Some(data_dir.to_path_buf()),
                config: PathBuf::from("/nonexistent/server.toml"),
            },
            json: false,
            lenient: false,
        };
        run(&args, &mut out).expect("run");
        String::from_utf8(out).expect("utf8")
    }

    #[test]
    fn a_recording_being_written_is_open_not_cut_short() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let rec = record_open(tmp.path());
        let text = table_of(tmp.path());
        assert!(text.contains("1 (open: being recorded)"), "{text}");
        assert!(!text.contains("cut short"), "{text}");
        // A crash leaves the file without its end and unlocked: cut short. (Its bytes as they
        // are now, in another data directory, are what a crash leaves.)
        let file = tmp
            .path()
            .join("sessions/trolley-pi/0000000000000abc/0000.mcap");
        let crashed = tempfile::tempdir().expect("tempdir");
        let dir = crashed.path().join("sessions/trolley-pi/0000000000000abc");
        std::fs::create_dir_all(&dir).expect("mkdir");
        std::fs::copy(&file, dir.join("0000.mcap")).expect("copy");
        drop(rec);
        let text = table_of(crashed.path());
        assert!(!text.contains("open"), "{text}");
        assert!(text.contains("1 (1 cut short)"), "{text}");
    }

    #[test]
    fn table_lists_sessions_with_revolutions_per_lidar() {
        let tmp = tempfile::tempdir().expect("tempdir");
        record(tmp.path());
        let mut out = Vec::new();
        let args = SessionsArgs {
            data: DataDirArgs {
                data_dir: Some(tmp.path().to_path_buf()),
                config: PathBuf::from("/nonexistent/server.toml"),
            },
            json: false,
            lenient: false,
        };
        run(&args, &mut out).expect("run");
        let text = String::from_utf8(out).expect("utf8");
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2, "{text}");
        assert_eq!(
            lines[0],
            "EDGE        SESSION           FILES  FRAMES  REVOLUTIONS        DURATION"
        );
        assert_eq!(
            lines[1],
            "trolley-pi  0000000000000abc      1       4  rplidar=2 sweep=1  58.0 s"
        );
    }

    #[test]
    fn json_lines_carry_counts() {
        let tmp = tempfile::tempdir().expect("tempdir");
        record(tmp.path());
        let mut out = Vec::new();
        let args = SessionsArgs {
            data: DataDirArgs {
                data_dir: Some(tmp.path().to_path_buf()),
                config: PathBuf::from("/nonexistent/server.toml"),
            },
            json: true,
            lenient: false,
        };
        run(&args, &mut out).expect("run");
        let text = String::from_utf8(out).expect("utf8");
        let value: serde_json::Value = serde_json::from_str(text.trim_end()).expect("json");
        assert_eq!(value["edge"], "trolley-pi");
        assert_eq!(value["session"], "0000000000000abc");
        assert_eq!(value["frames"], 4);
        assert_eq!(value["revolutions"]["rplidar"], 2);
        assert_eq!(value["revolutions"]["sweep"], 1);
        assert_eq!(value["frames_per_topic"]["/scan3d/hello"], 1);
        assert_eq!(value["first_log_time_ns"], 1_000_000_000u64);
        assert_eq!(value["last_log_time_ns"], 3_499_999_999u64);
    }

    #[test]
    fn empty_data_dir_says_so() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let mut out = Vec::new();
        let args = SessionsArgs {
            data: DataDirArgs {
                data_dir: Some(tmp.path().to_path_buf()),
                config: PathBuf::from("/nonexistent/server.toml"),
            },
            json: false,
            lenient: false,
        };
        run(&args, &mut out).expect("run");
        let text = String::from_utf8(out).expect("utf8");
        assert!(text.starts_with("no sessions under "), "{text}");
    }
}
