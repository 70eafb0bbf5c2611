//! The paper's Fig. 5 (yaw-fusion accuracy) from a fused run ([`crate::pipeline::FusedRun`])
//! and the true yaw: each source's yaw error against time (gyro integration alone, Madgwick,
//! the matcher alone, the CI fusion), drawn as `fig11`/`fig12` are (`scan3d_map::eval::plot`),
//! and the errors' RMSE per source.

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;

use scan3d_map::eval::plot::{Fig5Series, fig5_png, fig5_svg};
use scan3d_slam::pose::wrap_angle;

use crate::pipeline::FusedRun;

/// A truth sample farther than this from a pose (s) is not interpolated to it.
const TRUTH_MAX_GAP_S: f64 = 0.5;

/// The true yaw at `t_ns` from `truth` ((ns, rad), time increasing), linear between the two
/// samples around it on the unwrapped angle; `None` outside or across a gap.
pub fn truth_at(truth: &[(u64, f64)], t_ns: u64) -> Option<f64> {
    let i = truth.partition_point(|s| s.0 <= t_ns);
    let before = truth.get(i.checked_sub(1)?)?;
    if before.0 == t_ns {
        return Some(before.1);
    }
    let after = truth.get(i)?;
    let span = (after.0 - before.0) as f64 * 1e-9;
    if span > TRUTH_MAX_GAP_S {
        return None;
    }
    let u = (t_ns - before.0) as f64 / (after.0 - before.0) as f64;
    Some(wrap_angle(before.1 + u * wrap_angle(after.1 - before.1)))
}

/// Each source's yaw error (degrees) per pose against `truth`, as Fig. 5's curves: time in
/// seconds from the first pose, in the order gyro, Madgwick, matcher, fusion.
pub fn yaw_errors(run: &FusedRun, truth: &[(u64, f64)]) -> Vec<Fig5Series> {
    let names = [
        "gyro integration alone",
        "Madgwick",
        "matcher alone",
        "CI fusion",
    ];
    let mut series: Vec<Fig5Series> = names
        .iter()
        .map(|label| Fig5Series {
            label: (*label).to_owned(),
            points: Vec::new(),
        })
        .collect();
    let Some(t0) = run.sources.first().map(|s| s.t_s) else {
        return series;
    };
    for s in &run.sources {
        let t_ns = crate::pipeline::pose_stage::edge_ns(s.t_s);
        let Some(truth) = truth_at(truth, t_ns) else {
            continue;
        };
        let t = s.t_s - t0;
        let y = &s.yaws;
        for (k, yaw) in [y.gyro, y.madgwick, Some(y.matcher), Some(y.fused)]
            .into_iter()
            .enumerate()
        {
            if let Some(yaw) = yaw {
                series[k]
                    .points
                    .push((t, wrap_angle(yaw - truth).to_degrees()));
            }
        }
    }
    series
}

/// RMSE (degrees) of one source's errors, with how many poses it covers.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SourceRmse {
    /// The source.
    pub label: String,
    /// Root mean square of its errors, degrees (NaN without poses).
    pub rmse_deg: f64,
    /// Poses compared.
    pub poses: usize,
}

/// The RMSE of each curve of [`yaw_errors`], optionally over the poses from `from_s` (s from
/// the first pose) on only.
pub fn rmse(series: &[Fig5Series], from_s: f64) -> Vec<SourceRmse> {
    series
        .iter()
        .map(|s| {
            let errors: Vec<f64> = s
                .points
                .iter()
                .filter(|p| p.0 >= from_s)
                .map(|p| p.1)
                .collect();
            let rmse_deg = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
            SourceRmse {
                label: s.label.clone(),
                rmse_deg,
                poses: errors.len(),
            }
        })
        .collect()
}

/// Writes `fig5.svg` and `fig5.png` into `dir` (created if missing): the yaw error against
/// time for gyro integration alone, Madgwick, the matcher alone and the CI fusion. `truth_yaw`
/// is the true yaw of `base` (rad) at times in ns on the clock of the run's `t_s` (UNIX ns of
/// the server's clock when the session had time-sync models, as a TUM truth file's t × 1e9).
/// Returns the files written.
pub fn write_fig5(
    run: &FusedRun,
    truth_yaw: &[(u64, f64)],
    dir: &Path,
) -> anyhow::Result<Vec<PathBuf>> {
    let series: Vec<Fig5Series> = yaw_errors(run, truth_yaw)
        .into_iter()
        .filter(|s| !s.points.is_empty())
        .collect();
    anyhow::ensure!(
        !series.is_empty(),
        "no pose of the run lies within the truth's time span: nothing to plot"
    );
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let svg_path = dir.join("fig5.svg");
    let svg = fig5_svg(&series)?;
    std::fs::write(&svg_path, svg)
        .with_context(|| format!("cannot write {}", svg_path.display()))?;
    let png_path = dir.join("fig5.png");
    fig5_png(&series, &png_path).with_context(|| format!("cannot write {}", png_path.display()))?;
    Ok(vec![svg_path, png_path])
}

/// Reads a TUM trajectory's (t, yaw) as [`write_fig5`] takes the truth: t × 1e9 as ns, the yaw
/// of the quaternion. Comment lines (`#`) are skipped; a malformed line is an error with its
/// number.
pub fn read_tum_yaw(text: &str) -> anyhow::Result<Vec<(u64, f64)>> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .with_context(|| format!("line {}: not numbers", n + 1))?;
        anyhow::ensure!(v.len() == 8, "line {}: {} fields, want 8", n + 1, v.len());
        anyhow::ensure!(v[0].is_finite() && v[0] >= 0.0, "line {}: bad time", n + 1);
        let [qx, qy, qz, qw] = [v[4], v[5], v[6], v[7]];
        let yaw = (2.0 * (qw * qz + qx * qy)).atan2(1.0 - 2.0 * (qy * qy + qz * qz));
        out.push(((v[0] * 1e9).round() as u64, yaw));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::fusion_stage::PoseYaws;

    #[test]
    fn the_truth_is_interpolated_across_the_seam_and_not_across_a_gap() {
        let truth = [
            (0, 179f64.to_radians()),
            (100_000_000, (-179f64).to_radians()),
        ];
        let mid = truth_at(&truth, 50_000_000).expect("inside");
        assert!((mid.abs() - std::f64::consts::PI).abs() < 1e-9, "{mid}");
        let gap = [(0, 0.0), (2_000_000_000, 1.0)];
        assert_eq!(truth_at(&gap, 1_000_000_000), None);
        assert_eq!(truth_at(&gap, 3_000_000_000), None);
    }

    #[test]
    fn fig5_is_written_with_the_errors_against_the_truth() {
        let pose = |t_s: f64, yaw: f64| PoseYaws {
            t_s,
            yaws: crate::pose::fusion::YawSources {
                t_ns: 0,
                matcher: yaw + 0.01,
                matcher_variance: 1e-4,
                madgwick: Some(yaw - 0.02),
                madgwick_variance: Some(4e-4),
                gyro: Some(yaw + 0.03 * t_s),
                gyro_variance: Some(1e-3),
                fused: yaw,
                fused_variance: 1e-4,
                omega: Some(0.4),
            },
            fused_from_both: true,
        };
        let run = FusedRun {
            sources: (0..10).map(|k| pose(f64::from(k) * 0.2, 0.5)).collect(),
            trajectory: Vec::new(),
            counts: Default::default(),
            on_server_clock: false,
        };
        let truth: Vec<(u64, f64)> = (0..30).map(|k| (k * 100_000_000, 0.5)).collect();
        let series = yaw_errors(&run, &truth);
        let rms = rmse(&series, 0.0);
        assert!(
            (rms[2].rmse_deg - 0.01f64.to_degrees()).abs() < 1e-9,
            "{rms:?}"
        );
        assert!(rms[3].rmse_deg < 1e-9 && rms[1].rmse_deg > 1.0, "{rms:?}");
        let dir = tempfile::tempdir().expect("temp dir");
        let files = write_fig5(&run, &truth, dir.path()).expect("written");
        assert_eq!(files.len(), 2);
        let svg = std::fs::read_to_string(&files[0]).expect("svg");
        assert!(svg.contains("CI fusion") && svg.contains("yaw error"));
        assert!(std::fs::metadata(&files[1]).expect("png").len() > 1000);
    }
}
