//! The mapper over a whole recorded log: laser readings to [`Scan`]s (range limits, the
//! no-return sentinel, odometry), one pose per scan out, and the finished grid as a raster.

use crate::carmen::{CarmenLog, LaserScan};
use crate::grid::Grid;
use crate::map_image::{OccupancyRaster, RasterError};
use crate::mapper::{Mapper, MapperConfig, Scan, ScanResult};
use crate::odometry::{Calibration, OdometrySource, calibrate};
use crate::pose::Pose2;
use crate::relations::Trajectory;

/// Which readings of a laser line become beam endpoints.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeLimits {
    /// Readings below this are dropped (m): the laser's own housing, dust.
    pub min_range: f64,
    /// Readings above this are treated as no return (m). `None`: only the no-return value
    /// below is.
    pub max_range: Option<f64>,
    /// The value a laser writes for "no return" (81.83 m in Intel, 50.00 m in ACES); readings
    /// within 5 mm of it carry no endpoint.
    pub no_return: Option<f64>,
}

impl RangeLimits {
    /// The limits for a log: `max_range` if given, and the log's largest reading as its
    /// no-return value (in the benchmark logs it is the sentinel; elsewhere it drops at most
    /// the farthest reading).
    pub fn for_log(log: &CarmenLog, min_range: f64, max_range: Option<f64>) -> Self {
        Self {
            min_range,
            max_range,
            no_return: log.largest_reading().map(f64::from),
        }
    }

    fn keeps(&self, range: f64) -> bool {
        range.is_finite()
            && range >= self.min_range
            && self.max_range.is_none_or(|max| range <= max)
            && self
                .no_return
                .is_none_or(|value| (range - value).abs() > 0.005)
    }
}

/// The beam endpoints of one laser line in the laser frame.
pub fn endpoints(laser: &LaserScan, limits: &RangeLimits) -> Vec<(f64, f64)> {
    let line_max = laser.max_range;
    laser
        .ranges
        .iter()
        .enumerate()
        .filter_map(|(i, &r)| {
            let r = f64::from(r);
            if !limits.keeps(r) || line_max.is_some_and(|max| r >= max) {
                return None;
            }
            let a = laser.angle_min + i as f64 * laser.angle_increment;
            Some((r * a.cos(), r * a.sin()))
        })
        .collect()
}

/// What running the mapper over a recording (a log, a session) produced.
#[derive(Debug, Clone)]
pub struct MapperRun {
    /// One pose per scan, with its timestamp (a log's laser lines keep their text).
    pub trajectory: Trajectory,
    /// Per scan, what the mapper did.
    pub results: Vec<ScanResult>,
    /// The mapper at the end (its map).
    pub mapper: Mapper,
}

/// Maps a CARMEN log with `odometry`, one pose per scan (used when
/// `config.motion.use_odometry`). `progress` is called after each scan with the number done.
pub fn map_log(
    log: &CarmenLog,
    config: &MapperConfig,
    limits: &RangeLimits,
    odometry: &[Pose2],
    mut progress: impl FnMut(usize),
) -> MapperRun {
    assert_eq!(
        odometry.len(),
        log.scans.len(),
        "one odometry pose per scan"
    );
    let mut mapper = Mapper::new(*config);
    let mut results = Vec::with_capacity(log.scans.len());
    for (done, (laser, odometry)) in log.scans.iter().zip(odometry).enumerate() {
        let scan = Scan {
            time: laser.timestamp.seconds,
            hits: endpoints(laser, limits),
            hit_times: Vec::new(),
            odometry: Some(*odometry),
            sensor_offset: laser.laser_offset,
            rotation: None,
        };
        results.push(mapper.add_scan(&scan));
        progress(done + 1);
    }
    let poses: Vec<Pose2> = results.iter().map(|r| r.pose).collect();
    MapperRun {
        trajectory: Trajectory::from_scans(&log.scans, &poses),
        results,
        mapper,
    }
}

/// A log mapped with the odometry that agrees best with its scans.
#[derive(Debug, Clone)]
pub struct CalibratedRun {
    /// The run that was kept.
    pub run: MapperRun,
    /// The odometry it used.
    pub odometry: OdometrySource,
    /// How each source agreed with the first pass; `None` when odometry is off or the log has
    /// no `ODOM` lines (the laser lines' odometry is then the only one).
    pub calibration: Option<Calibration>,
}

/// Maps a CARMEN log with the laser lines' odometry, and when the log also has `ODOM` lines
/// and odometry is on, calibrates their latency against that pass and maps the log again with
/// them if they agree better (see [`crate::odometry`]). `progress` counts scans over both
/// passes.
pub fn map_log_calibrated(
    log: &CarmenLog,
    config: &MapperConfig,
    limits: &RangeLimits,
    mut progress: impl FnMut(usize),
) -> CalibratedRun {
    let first = map_log(log, config, limits, &log.odometry_poses(), &mut progress);
    if !config.motion.use_odometry || log.odometry.is_empty() {
        return CalibratedRun {
            run: first,
            odometry: OdometrySource::LaserLines,
            calibration: None,
        };
    }
    let matched: Vec<Pose2> = first.results.iter().map(|r| r.pose).collect();
    let calibration = calibrate(log, &matched);
    let source = calibration.best();
    let run = match source {
        OdometrySource::LaserLines => first,
        OdometrySource::Track { .. } => {
            let poses = source.poses(log).expect("the log has ODOM lines");
            let done = log.scans.len();
            map_log(log, config, limits, &poses, |n| progress(done + n))
        }
    };
    CalibratedRun {
        run,
        odometry: source,
        calibration: Some(calibration),
    }
}

/// The grid's known area (the smallest box holding every cell seen) as a raster for the image
/// writers: unknown cells stay unknown.
pub fn raster(grid: &Grid) -> Result<OccupancyRaster, RasterError> {
    let ((i0, j0), (i1, j1)) = grid.known_bounds().unwrap_or(((0, 0), (-1, -1)));
    let (width, height) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
    let mut cells = Vec::with_capacity(width * height);
    for row in 0..height as i32 {
        for column in 0..width as i32 {
            let cell = (i0 + column, j0 + row);
            cells.push(grid.is_known(cell).then(|| grid.probability(cell)));
        }
    }
    let r = grid.resolution();
    OccupancyRaster::new(
        width,
        height,
        r,
        (f64::from(i0) * r, f64::from(j0) * r),
        cells,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::carmen::{ReadOptions, read_log};

    #[test]
    fn the_no_return_value_and_readings_out_of_range_carry_no_endpoint() {
        let line = "FLASER 5 1.00 81.83 0.05 7.00 2.00 0 0 0 0 0 0 1.000000 host 1.0\n";
        let log = read_log(line.as_bytes(), &ReadOptions::default()).expect("log");
        let limits = RangeLimits::for_log(&log, 0.1, Some(6.0));
        let points = endpoints(&log.scans[0], &limits);
        // 1.00 (beam 0, at −90°) and 2.00 (beam 4) stay; 81.83 is no return, 0.05 too close,
        // 7.00 beyond 6 m.
        assert_eq!(points.len(), 2);
        assert!((points[0].0).abs() < 1e-9 && (points[0].1 + 1.0).abs() < 1e-9);
        let unclipped = RangeLimits::for_log(&log, 0.1, None);
        assert_eq!(endpoints(&log.scans[0], &unclipped).len(), 3);
    }

    #[test]
    fn a_raster_of_the_grid_keeps_unknown_cells_unknown_and_its_origin() {
        let mut grid = Grid::new(0.5, &crate::grid::UpdateModel::default());
        grid.integrate((-0.75, 0.25), &[(2.25, 0.25)], &[]);
        grid.integrate((-0.75, 0.25), &[(-0.75, 1.25)], &[]);
        let raster = raster(&grid).expect("raster");
        // Cells (−2, 0) to (4, 2): the beams' cells, and nothing around them.
        assert_eq!(raster.origin(), (-1.0, 0.0));
        assert_eq!((raster.width(), raster.height()), (7, 3));
        assert!(raster.cell(6, 0).expect("seen") > 0.5);
        assert!(raster.cell(0, 2).expect("seen") > 0.5);
        assert!(raster.cell(3, 0).expect("seen") < 0.5);
        assert_eq!(raster.cell(6, 2), None);
        let empty = Grid::new(0.5, &crate::grid::UpdateModel::default());
        assert!(super::raster(&empty).is_err());
    }
}
