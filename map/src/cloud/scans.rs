//! Lidar revolutions as the server received them: every revolution's samples as points in the
//! sensor's own scan plane, collected per sensor and exported as PLY.
//!
//! The server pipeline's revolution stage wraps it: the demo writes `scans/*.ply` with it from
//! live frames, and `scan3d replay` from a recording, so the two can be compared byte for byte.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use scan3d_protocol::{Body, Frame, LidarRevolution, SensorId};

use super::CloudPoint;
use super::ply::write_ply;

/// The point in the sensor's scan plane (x forward at angle 0, y 90° counter-clockwise) of a
/// sample reported at `angle_deg` by `sensor`: RPLidars report clockwise angles, the Sweep
/// counter-clockwise ones.
pub fn scan_plane_point(sensor: SensorId, angle_deg: f32, range_m: f32) -> [f32; 3] {
    let ccw = if sensor == SensorId::RPLIDAR {
        -angle_deg
    } else {
        angle_deg
    }
    .to_radians();
    [range_m * ccw.cos(), range_m * ccw.sin(), 0.0]
}

/// Per-sensor totals of what was collected.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SensorTotals {
    /// Revolutions received.
    pub revolutions: u64,
    /// Samples received (returns and no-returns).
    pub samples: u64,
    /// Samples with a return (range > 0), i.e. points.
    pub points: u64,
}

/// Collects lidar revolutions into per-sensor point sets.
#[derive(Debug, Default)]
pub struct RevolutionCollector {
    points: BTreeMap<SensorId, Vec<CloudPoint>>,
    totals: BTreeMap<SensorId, SensorTotals>,
}

impl RevolutionCollector {
    /// An empty collector.
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes a frame; anything but a lidar revolution is ignored.
    pub fn on_frame(&mut self, frame: &Frame) {
        if let Body::Revolution(rev) = &frame.body {
            self.add(rev);
        }
    }

    /// Adds one revolution.
    pub fn add(&mut self, rev: &LidarRevolution) {
        let totals = self.totals.entry(rev.sensor).or_default();
        totals.revolutions += 1;
        totals.samples += rev.samples.len() as u64;
        let points = self.points.entry(rev.sensor).or_default();
        for s in rev.samples.iter().filter(|s| s.range_m > 0.0) {
            totals.points += 1;
            points.push(CloudPoint {
                position: scan_plane_point(rev.sensor, s.angle_deg, s.range_m),
                intensity: s.quality.into(),
            });
        }
    }

    /// Totals per sensor.
    pub fn totals(&self) -> &BTreeMap<SensorId, SensorTotals> {
        &self.totals
    }

    /// Writes `dir/<sensor name>.ply` for every sensor seen; returns the files.
    pub fn write_ply_files(&self, dir: &Path) -> std::io::Result<Vec<PathBuf>> {
        std::fs::create_dir_all(dir)?;
        let mut written = Vec::new();
        for (sensor, points) in &self.points {
            let path = dir.join(format!("{sensor}.ply"));
            write_ply(BufWriter::new(File::create(&path)?), points)?;
            written.push(path);
        }
        Ok(written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rplidar_angles_are_clockwise_and_sweep_angles_counter_clockwise() {
        let [x, y, _] = scan_plane_point(SensorId::RPLIDAR, 90.0, 2.0);
        assert!(x.abs() < 1e-6 && (y + 2.0).abs() < 1e-6);
        let [x, y, _] = scan_plane_point(SensorId::SWEEP, 90.0, 2.0);
        assert!(x.abs() < 1e-6 && (y - 2.0).abs() < 1e-6);
    }

    #[test]
    fn collects_points_with_returns_only() {
        let mut rev = LidarRevolution::new(SensorId::SWEEP, 0, 200_000_000);
        rev.push(0.0, 1.0, 100, 0).unwrap();
        rev.push(90.0, 0.0, 0, 1_000).unwrap();
        rev.push(180.0, 2.0, 90, 2_000).unwrap();
        let mut collector = RevolutionCollector::new();
        collector.on_frame(&Frame::new(1, 0, rev));
        let totals = collector.totals()[&SensorId::SWEEP];
        assert_eq!(
            (totals.revolutions, totals.samples, totals.points),
            (1, 3, 2)
        );
        let dir = std::env::temp_dir().join(format!("scan3d-scans-{}", std::process::id()));
        let files = collector.write_ply_files(&dir).unwrap();
        assert_eq!(files, vec![dir.join("sweep.ply")]);
        let bytes = std::fs::read(&files[0]).unwrap();
        assert!(bytes.windows(16).any(|w| w == b"element vertex 2"));
        let _ = std::fs::remove_dir_all(dir);
    }
}
