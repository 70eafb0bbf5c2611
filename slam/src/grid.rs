//! Occupancy grids that grow as the robot explores, read by the matcher as a continuous function.
//!
//! A [`Grid`] keeps log-odds per cell in square tiles of 64 × 64 cells, allocated when an update
//! first lands in them and found through a small directory over the tiles' bounding box: no size
//! to configure, memory in proportion to the area seen rather than to its bounding box (an
//! L-shaped building 400 m × 180 m across, or two rooms a kilometre apart), and a lookup is a
//! directory read, two shifts and an index. Cell `(i, j)` covers `[i·r, (i+1)·r) × [j·r,
//! (j+1)·r)` in the map frame; its value is taken to sit at the cell centre, and
//! [`Grid::interpolate`] reads the occupancy probability between centres bilinearly, with its
//! gradient (Hector SLAM's M(P) and ∇M(P)).
//!
//! Updates follow Hector's rule: per scan, each cell a beam passes through gets one free update
//! and each endpoint cell one occupied update, even if several beams touch it; an endpoint
//! overrides a free update of the same scan. [`GridPyramid`] holds several grids, each half the
//! resolution of the previous, all updated from the same scans (not downsampled).

use crate::pose::Pose2;

/// How each observation changes a cell, in log-odds, and the bounds that keep cells revisable.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct UpdateModel {
    /// Probability that an endpoint cell is occupied (Hector's `update_factor_occupied`).
    pub hit_probability: f32,
    /// Probability of occupancy after a beam passed through (Hector's `update_factor_free`).
    pub miss_probability: f32,
    /// Log-odds clamp, both ways, so a cell can change its mind when the world changes.
    pub clamp_log_odds: f32,
    /// Consecutive endpoints closer than this (m), and in line with the endpoint before or
    /// after them, are joined: the cells between them are hit too. A wall seen at a grazing
    /// angle is sampled more sparsely than the cells, and a map that holds only its endpoints
    /// is densest where it was seen from, which pulls a scan along a corridor back towards
    /// where the wall was first seen (0: off).
    pub join_endpoints_within: f32,
    /// ...for a scan whose pose came without odometry (a constant-velocity prediction, a
    /// gyro's turn): nothing else holds such a pose along a corridor, and walls seen at
    /// grazing angles are joined across wider gaps. With odometry the wider joins cost more
    /// than they give (they close doorways seen obliquely; docs/slam.md).
    pub join_endpoints_within_without_odometry: f32,
}

impl Default for UpdateModel {
    fn default() -> Self {
        Self {
            hit_probability: 0.9,
            miss_probability: 0.4,
            clamp_log_odds: 8.0,
            join_endpoints_within: 0.2,
            join_endpoints_within_without_odometry: 0.8,
        }
    }
}

fn log_odds(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// The index of the cell `resolution` metres wide that contains the point (m): cell `(i, j)`
/// covers `[i·r, (i+1)·r) × [j·r, (j+1)·r)`.
pub(crate) fn cell_containing(resolution: f64, x: f64, y: f64) -> (i32, i32) {
    (
        (x / resolution).floor() as i32,
        (y / resolution).floor() as i32,
    )
}

/// One growing occupancy grid at one resolution.
#[derive(Debug, Clone)]
pub struct Grid {
    resolution: f64,
    /// Tile coordinates of directory column 0 / row 0.
    tile_origin: (i32, i32),
    tiles_wide: usize,
    tiles_high: usize,
    /// Per tile of the bounding box, row-major, where its cells start in the pools below
    /// (in tiles), or [`NO_TILE`] while nothing landed in it.
    directory: Vec<u32>,
    /// Log-odds per cell, tile after tile, [`TILE_CELLS`] per tile, row-major within a tile.
    log_odds: Vec<f32>,
    /// Occupancy probability per cell, kept beside the log-odds so lookups need no `exp`.
    probability: Vec<f32>,
    /// Per cell, the scan that last updated it: `2·scan` for a free update, `2·scan + 1` for a
    /// hit (so a hit may override the same scan's free update, never the reverse).
    mark: Vec<u32>,
    scans: u32,
    hit: f32,
    miss: f32,
    clamp: f32,
    /// [`UpdateModel::join_endpoints_within`]: how far apart [`Grid::integrate`] joins.
    join_within: f64,
    /// The most cells the grid may hold: [`MAX_CELLS`] (smaller in tests).
    cell_limit: usize,
}

/// A tile is `2^TILE_BITS` cells wide.
const TILE_BITS: u32 = 6;
/// Cells along a tile's edge.
const TILE: i32 = 1 << TILE_BITS;
/// Cells in a tile.
const TILE_CELLS: usize = 1 << (2 * TILE_BITS);
/// A directory entry whose tile was never allocated.
const NO_TILE: u32 = u32::MAX;
/// The occupancy probability of a cell nothing was seen in.
const UNKNOWN: f32 = 0.5;

/// Three consecutive endpoints are in line when the second segment turns from the first by
/// less than this (rad): a surface's samples, not a foreground edge against a background.
const JOIN_ANGLE: f64 = 0.2;

/// Tiles added on every side when the directory grows, so a robot driving along its edge does
/// not copy it on every scan.
const GROWTH_MARGIN: i32 = 4;

/// A grid never holds more than this many cells (600 MB at 12 bytes per cell; at 5 cm, 12.5 ha
/// of cells seen, as much as a 353 m square).
/// A trajectory that diverges would otherwise grow the map until memory runs out; a scan that
/// could take the grid past it is not integrated, and counted
/// ([`crate::mapper::Mapper::refused_integrations`]).
pub const MAX_CELLS: usize = 50_000_000;

/// The tiles' bounding box never spans more than this many tiles (a 16 MB directory: 6.5 km
/// square at 5 cm), however few of them hold cells.
const MAX_DIRECTORY_TILES: usize = 1 << 22;

/// The value at, and the gradient of, the interpolated occupancy at a point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Occupancy probability in [0, 1] (0.5 where nothing was seen).
    pub value: f64,
    /// ∂value/∂x, ∂value/∂y in the map frame, per metre.
    pub gradient: (f64, f64),
}

impl Grid {
    /// An empty grid of square cells `resolution` metres wide.
    pub fn new(resolution: f64, model: &UpdateModel) -> Self {
        assert!(
            resolution.is_finite() && resolution > 0.0,
            "grid resolution must be positive"
        );
        Self {
            resolution,
            tile_origin: (0, 0),
            tiles_wide: 0,
            tiles_high: 0,
            directory: Vec::new(),
            log_odds: Vec::new(),
            probability: Vec::new(),
            mark: Vec::new(),
            scans: 0,
            hit: log_odds(model.hit_probability),
            miss: log_odds(model.miss_probability),
            clamp: model.clamp_log_odds,
            join_within: f64::from(model.join_endpoints_within.max(0.0)),
            cell_limit: MAX_CELLS,
        }
    }

    /// Cell edge length (m).
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// The lowest and highest world cell indices of the cells ever updated (the smallest box
    /// holding all of them), or `None` while the grid is empty.
    pub fn known_bounds(&self) -> Option<((i32, i32), (i32, i32))> {
        let mut bounds: Option<((i32, i32), (i32, i32))> = None;
        for (slot, &tile) in self.directory.iter().enumerate() {
            if tile == NO_TILE {
                continue;
            }
            let corner = (
                (self.tile_origin.0 + (slot % self.tiles_wide) as i32) * TILE,
                (self.tile_origin.1 + (slot / self.tiles_wide) as i32) * TILE,
            );
            let first = tile as usize * TILE_CELLS;
            for (n, _) in self.mark[first..first + TILE_CELLS]
                .iter()
                .enumerate()
                .filter(|(_, mark)| **mark != 0)
            {
                let n = n as i32;
                let cell = (corner.0 + (n & (TILE - 1)), corner.1 + (n >> TILE_BITS));
                bounds = Some(match bounds {
                    None => (cell, cell),
                    Some((lo, hi)) => (
                        (lo.0.min(cell.0), lo.1.min(cell.1)),
                        (hi.0.max(cell.0), hi.1.max(cell.1)),
                    ),
                });
            }
        }
        bounds
    }

    /// Cells held in memory: those of the tiles anything landed in.
    pub fn allocated_cells(&self) -> usize {
        self.log_odds.len()
    }

    /// Bytes the cells and the directory take (12 a cell, 4 a tile of the bounding box).
    pub fn allocated_bytes(&self) -> usize {
        self.log_odds.len() * (size_of::<f32>() * 2 + size_of::<u32>())
            + self.directory.len() * size_of::<u32>()
    }

    /// Number of scans integrated so far.
    pub fn scans(&self) -> u32 {
        self.scans
    }

    /// Log-odds of the world cell `(i, j)`; 0 (probability ½) where nothing was seen.
    pub fn log_odds(&self, cell: (i32, i32)) -> f32 {
        self.index(cell).map_or(0.0, |k| self.log_odds[k])
    }

    /// Occupancy probability of the world cell `(i, j)`; ½ where nothing was seen.
    pub fn probability(&self, cell: (i32, i32)) -> f32 {
        self.index(cell).map_or(UNKNOWN, |k| self.probability[k])
    }

    /// Whether the cell was ever updated.
    pub fn is_known(&self, cell: (i32, i32)) -> bool {
        self.index(cell).is_some_and(|k| self.mark[k] != 0)
    }

    /// The world cell that contains the point (m).
    pub fn cell_of(&self, x: f64, y: f64) -> (i32, i32) {
        cell_containing(self.resolution, x, y)
    }

    /// The directory slot of the tile holding cell `(i, j)`, if the directory covers it.
    fn slot(&self, (i, j): (i32, i32)) -> Option<usize> {
        let col = (i >> TILE_BITS).checked_sub(self.tile_origin.0)?;
        let row = (j >> TILE_BITS).checked_sub(self.tile_origin.1)?;
        if col < 0 || row < 0 || col as usize >= self.tiles_wide || row as usize >= self.tiles_high
        {
            return None;
        }
        Some(row as usize * self.tiles_wide + col as usize)
    }

    /// Where cell `(i, j)` is in the pools, if its tile was allocated.
    fn index(&self, cell: (i32, i32)) -> Option<usize> {
        let tile = self.directory[self.slot(cell)?];
        (tile != NO_TILE).then(|| tile as usize * TILE_CELLS + within_tile(cell))
    }

    /// Where cell `(i, j)` is in the pools, allocating its tile (unknown cells) if needed. The
    /// directory must cover the cell ([`Grid::cover`]).
    fn index_allocating(&mut self, cell: (i32, i32)) -> usize {
        let slot = self.slot(cell).expect("covered");
        if self.directory[slot] == NO_TILE {
            self.directory[slot] = (self.log_odds.len() / TILE_CELLS) as u32;
            self.log_odds.resize(self.log_odds.len() + TILE_CELLS, 0.0);
            self.probability
                .resize(self.probability.len() + TILE_CELLS, UNKNOWN);
            self.mark.resize(self.mark.len() + TILE_CELLS, 0);
        }
        self.directory[slot] as usize * TILE_CELLS + within_tile(cell)
    }

    /// The occupancy probability and its gradient at the point (m), bilinear between the four
    /// cell centres around it.
    pub fn interpolate(&self, x: f64, y: f64) -> Sample {
        // Map coordinates in cells, with cell centres on the integers.
        let u = x / self.resolution - 0.5;
        let v = y / self.resolution - 0.5;
        let (u0, v0) = (u.floor(), v.floor());
        let (fu, fv) = (u - u0, v - v0);
        let (i, j) = (u0 as i32, v0 as i32);
        let inside_one_tile = (i & (TILE - 1)) != TILE - 1 && (j & (TILE - 1)) != TILE - 1;
        let (p00, p10, p01, p11) = if inside_one_tile {
            // Fast path: all four in one tile, all unknown if nothing landed in it.
            self.index((i, j))
                .map_or((UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN), |k| {
                    let w = TILE as usize;
                    (
                        self.probability[k],
                        self.probability[k + 1],
                        self.probability[k + w],
                        self.probability[k + w + 1],
                    )
                })
        } else {
            (
                self.probability((i, j)),
                self.probability((i + 1, j)),
                self.probability((i, j + 1)),
                self.probability((i + 1, j + 1)),
            )
        };
        let (p00, p10, p01, p11) = (
            f64::from(p00),
            f64::from(p10),
            f64::from(p01),
            f64::from(p11),
        );
        let bottom = p00 + fu * (p10 - p00);
        let top = p01 + fu * (p11 - p01);
        let value = bottom + fv * (top - bottom);
        let du = (1.0 - fv) * (p10 - p00) + fv * (p11 - p01);
        let dv = top - bottom;
        Sample {
            value,
            gradient: (du / self.resolution, dv / self.resolution),
        }
    }

    /// Makes the directory cover the cells `[lo, hi]` (inclusive), growing it with a margin, and
    /// checks that the grid may allocate every tile of that box it has not yet. Returns false
    /// (and changes nothing) if that could exceed [`MAX_CELLS`] or the directory
    /// [`MAX_DIRECTORY_TILES`]: a scan whose box has more tiles than it touches may be refused
    /// a few hundred tiles early, never let past the limit.
    fn cover(&mut self, lo: (i32, i32), hi: (i32, i32)) -> bool {
        let (lo, hi) = (
            (lo.0 >> TILE_BITS, lo.1 >> TILE_BITS),
            (hi.0 >> TILE_BITS, hi.1 >> TILE_BITS),
        );
        let (x1, y1) = (
            self.tile_origin.0 + self.tiles_wide as i32 - 1,
            self.tile_origin.1 + self.tiles_high as i32 - 1,
        );
        let covered = self.tiles_wide > 0
            && lo.0 >= self.tile_origin.0
            && lo.1 >= self.tile_origin.1
            && hi.0 <= x1
            && hi.1 <= y1;
        let (nx0, ny0, nx1, ny1) = if covered {
            (self.tile_origin.0, self.tile_origin.1, x1, y1)
        } else if self.tiles_wide == 0 {
            (
                lo.0 - GROWTH_MARGIN,
                lo.1 - GROWTH_MARGIN,
                hi.0 + GROWTH_MARGIN,
                hi.1 + GROWTH_MARGIN,
            )
        } else {
            (
                if lo.0 < self.tile_origin.0 {
                    lo.0 - GROWTH_MARGIN
                } else {
                    self.tile_origin.0
                },
                if lo.1 < self.tile_origin.1 {
                    lo.1 - GROWTH_MARGIN
                } else {
                    self.tile_origin.1
                },
                if hi.0 > x1 { hi.0 + GROWTH_MARGIN } else { x1 },
                if hi.1 > y1 { hi.1 + GROWTH_MARGIN } else { y1 },
            )
        };
        let width = (i64::from(nx1) - i64::from(nx0) + 1) as usize;
        let height = (i64::from(ny1) - i64::from(ny0) + 1) as usize;
        if width.saturating_mul(height) > MAX_DIRECTORY_TILES {
            return false;
        }
        // The box's tiles not allocated yet: more than the scan can touch, never fewer. Counted
        // only when the whole box could take the grid past its limit (rarely: per scan, the
        // box's tiles are a few hundred).
        let box_tiles = ((hi.0 - lo.0 + 1) as usize) * ((hi.1 - lo.1 + 1) as usize);
        if self.log_odds.len() + box_tiles * TILE_CELLS > self.cell_limit {
            let held = |ti: i32, tj: i32| {
                self.slot((ti * TILE, tj * TILE))
                    .is_some_and(|k| self.directory[k] != NO_TILE)
            };
            let mut missing = 0;
            for tj in lo.1..=hi.1 {
                for ti in lo.0..=hi.0 {
                    missing += usize::from(!held(ti, tj));
                }
            }
            if self.log_odds.len() + missing * TILE_CELLS > self.cell_limit {
                return false;
            }
        }
        if covered {
            return true;
        }
        let mut directory = vec![NO_TILE; width * height];
        let (dx, dy) = (
            (self.tile_origin.0 - nx0) as usize,
            (self.tile_origin.1 - ny0) as usize,
        );
        for row in 0..self.tiles_high {
            let from = row * self.tiles_wide..(row + 1) * self.tiles_wide;
            let to = (row + dy) * width + dx;
            directory[to..to + self.tiles_wide].copy_from_slice(&self.directory[from]);
        }
        self.tile_origin = (nx0, ny0);
        self.tiles_wide = width;
        self.tiles_high = height;
        self.directory = directory;
        true
    }

    fn apply(&mut self, k: usize, delta: f32) {
        let l = (self.log_odds[k] + delta).clamp(-self.clamp, self.clamp);
        self.log_odds[k] = l;
        self.probability[k] = 1.0 / (1.0 + (-l).exp());
    }

    /// Integrates one scan taken from `origin` (m, map frame): every cell from the origin to
    /// each of `hits` gets a free update and the cell of each hit an occupied update; every cell
    /// to each of `misses` (beams that returned nothing within range, cut at the range) only a
    /// free update. Returns false if the grid would have had to grow past [`MAX_CELLS`] (the
    /// scan is then not integrated).
    pub fn integrate(
        &mut self,
        origin: (f64, f64),
        hits: &[(f64, f64)],
        misses: &[(f64, f64)],
    ) -> bool {
        self.integrate_joining(origin, hits, misses, self.join_within)
    }

    /// [`Grid::integrate`], joining consecutive endpoints up to `join_within` (m) apart instead
    /// of the model's [`UpdateModel::join_endpoints_within`].
    pub fn integrate_joining(
        &mut self,
        origin: (f64, f64),
        hits: &[(f64, f64)],
        misses: &[(f64, f64)],
        join_within: f64,
    ) -> bool {
        let start = self.cell_of(origin.0, origin.1);
        let (mut lo, mut hi) = (start, start);
        for &(x, y) in hits.iter().chain(misses) {
            let c = self.cell_of(x, y);
            lo = (lo.0.min(c.0), lo.1.min(c.1));
            hi = (hi.0.max(c.0), hi.1.max(c.1));
        }
        if !self.cover(lo, hi) {
            return false;
        }
        self.scans += 1;
        let free_mark = 2 * self.scans;
        for (n, &(x, y)) in hits.iter().chain(misses).enumerate() {
            let end = self.cell_of(x, y);
            let is_hit = n < hits.len();
            self.trace(start, end, free_mark);
            if is_hit {
                self.hit_once(end, free_mark);
            }
        }
        if join_within > 0.0 {
            // Hits are in beam order: neighbours in the slice are neighbouring beams.
            let within = join_within;
            let near = |a: (f64, f64), b: (f64, f64)| (b.0 - a.0).hypot(b.1 - a.1) <= within;
            let in_line = |a: (f64, f64), b: (f64, f64), c: (f64, f64)| {
                let (u, v) = ((b.0 - a.0, b.1 - a.1), (c.0 - b.0, c.1 - b.1));
                let cross = u.0 * v.1 - u.1 * v.0;
                let dot = u.0 * v.0 + u.1 * v.1;
                dot > 0.0 && cross.abs() <= JOIN_ANGLE.tan() * dot
            };
            for n in 0..hits.len().saturating_sub(1) {
                let (a, b) = (hits[n], hits[n + 1]);
                if !near(a, b) {
                    continue;
                }
                let before = n > 0 && near(hits[n - 1], a) && in_line(hits[n - 1], a, b);
                let after =
                    n + 2 < hits.len() && near(b, hits[n + 2]) && in_line(a, b, hits[n + 2]);
                if before || after {
                    let (from, to) = (self.cell_of(a.0, a.1), self.cell_of(b.0, b.1));
                    bresenham(from, to, |cell| self.hit_once(cell, free_mark));
                }
            }
        }
        true
    }

    /// An occupied update of `cell`, once per scan (`free_mark` is the scan's, see `mark`); it
    /// undoes the scan's free update of the cell if there was one: the endpoint wins.
    fn hit_once(&mut self, cell: (i32, i32), free_mark: u32) {
        let hit_mark = free_mark + 1;
        let k = self.index_allocating(cell);
        if self.mark[k] != hit_mark {
            if self.mark[k] == free_mark {
                self.apply(k, -self.miss);
            }
            self.mark[k] = hit_mark;
            self.apply(k, self.hit);
        }
    }

    /// Free updates along the cells from `start` to `end`, both excluded from nothing but the
    /// end cell (Bresenham, integer arithmetic).
    fn trace(&mut self, start: (i32, i32), end: (i32, i32), free_mark: u32) {
        // A beam crosses a tile in up to 128 cells: look each tile up once.
        let mut tile = None;
        let mut first_cell = 0;
        bresenham(start, end, |cell| {
            if cell == end {
                return;
            }
            let here = (cell.0 >> TILE_BITS, cell.1 >> TILE_BITS);
            if tile != Some(here) {
                tile = Some(here);
                first_cell = self.index_allocating((here.0 * TILE, here.1 * TILE));
            }
            let k = first_cell + within_tile(cell);
            if self.mark[k] < free_mark {
                self.mark[k] = free_mark;
                self.apply(k, self.miss);
            }
        });
    }
}

/// Where cell `(i, j)` is within its tile (row-major).
fn within_tile((i, j): (i32, i32)) -> usize {
    (((j & (TILE - 1)) << TILE_BITS) | (i & (TILE - 1))) as usize
}

/// Visits the cells of the line from `start` to `end`, both included (Bresenham, integer
/// arithmetic).
fn bresenham(start: (i32, i32), end: (i32, i32), mut visit: impl FnMut((i32, i32))) {
    let (dx, dy) = ((end.0 - start.0).abs(), -(end.1 - start.1).abs());
    let (sx, sy) = (
        if start.0 < end.0 { 1 } else { -1 },
        if start.1 < end.1 { 1 } else { -1 },
    );
    let mut err = dx + dy;
    let (mut i, mut j) = start;
    loop {
        visit((i, j));
        if (i, j) == end {
            return;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            i += sx;
        }
        if e2 <= dx {
            err += dx;
            j += sy;
        }
    }
}

/// Grids at several resolutions, level 0 the finest and each next level half as fine.
#[derive(Debug, Clone)]
pub struct GridPyramid {
    levels: Vec<Grid>,
}

impl GridPyramid {
    /// `levels` grids, the finest with cells `resolution` metres wide.
    pub fn new(resolution: f64, levels: usize, model: &UpdateModel) -> Self {
        assert!(levels >= 1, "a pyramid needs at least one level");
        Self {
            levels: (0..levels)
                .map(|level| Grid::new(resolution * f64::from(1u32 << level), model))
                .collect(),
        }
    }

    /// The grids, finest first.
    pub fn levels(&self) -> &[Grid] {
        &self.levels
    }

    /// The finest grid.
    pub fn finest(&self) -> &Grid {
        &self.levels[0]
    }

    /// Integrates a scan, given in the sensor frame, seen from `sensor_pose` into every level.
    /// `hits` are beam endpoints; `misses` are points where beams without a return were cut.
    /// Returns false if a level refused to grow (see [`Grid::integrate`]).
    pub fn integrate(
        &mut self,
        sensor_pose: &Pose2,
        hits: &[(f64, f64)],
        misses: &[(f64, f64)],
    ) -> bool {
        self.integrate_joining(sensor_pose, hits, misses, None)
    }

    /// [`GridPyramid::integrate`], joining consecutive endpoints up to `join_within` (m) apart
    /// on every level (`None`: each level's model, [`UpdateModel::join_endpoints_within`]).
    pub fn integrate_joining(
        &mut self,
        sensor_pose: &Pose2,
        hits: &[(f64, f64)],
        misses: &[(f64, f64)],
        join_within: Option<f64>,
    ) -> bool {
        let to_map = |points: &[(f64, f64)]| -> Vec<(f64, f64)> {
            points
                .iter()
                .map(|&(x, y)| sensor_pose.transform_point(x, y))
                .collect()
        };
        let (hits, misses) = (to_map(hits), to_map(misses));
        let origin = (sensor_pose.x, sensor_pose.y);
        let mut all = true;
        for grid in &mut self.levels {
            let within = join_within.unwrap_or(grid.join_within);
            all &= grid.integrate_joining(origin, &hits, &misses, within);
        }
        all
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> Grid {
        Grid::new(0.1, &UpdateModel::default())
    }

    #[test]
    fn endpoints_in_line_are_joined_and_a_lone_pair_is_not() {
        let model = UpdateModel {
            join_endpoints_within: 0.25,
            ..UpdateModel::default()
        };
        // A wall along y = 1.05 seen at a grazing angle: endpoints 0.2 m apart, cells 0.1 m.
        let wall = [(1.05, 1.05), (1.25, 1.05), (1.45, 1.05), (1.65, 1.05)];
        let between = [(11, 10), (13, 10), (15, 10)];
        let mut joined = Grid::new(0.1, &model);
        assert!(joined.integrate((0.05, 0.05), &wall, &[]));
        let mut plain = Grid::new(
            0.1,
            &UpdateModel {
                join_endpoints_within: 0.0,
                ..model
            },
        );
        assert!(plain.integrate((0.05, 0.05), &wall, &[]));
        for cell in between {
            assert!(
                (joined.probability(cell) - 0.9).abs() < 1e-6,
                "{cell:?} joined"
            );
            assert!(plain.probability(cell) <= 0.5, "{cell:?} without joining");
        }
        // Two endpoints as close, but with no third in line: a foreground edge and the
        // background behind it, not a surface.
        let mut edge = Grid::new(0.1, &model);
        assert!(edge.integrate((0.05, 0.05), &[(1.05, 1.05), (1.15, 1.25)], &[]));
        assert!(edge.probability((11, 11)) <= 0.5);
        assert!(edge.probability((10, 11)) <= 0.5);
        // Farther apart than the limit: not joined either.
        let mut far = Grid::new(0.1, &model);
        let sparse = [(1.05, 1.05), (1.35, 1.05), (1.65, 1.05)];
        assert!(far.integrate((0.05, 0.05), &sparse, &[]));
        assert!(far.probability((12, 10)) <= 0.5);
    }

    #[test]
    fn a_beam_frees_the_cells_it_crosses_and_marks_its_end_occupied() {
        let mut g = grid();
        assert!(g.integrate((0.05, 0.05), &[(1.05, 0.05)], &[]));
        for i in 0..10 {
            assert!(g.probability((i, 0)) < 0.5, "cell {i} should be free");
        }
        assert!((g.probability((10, 0)) - 0.9).abs() < 1e-6);
        assert_eq!(g.probability((11, 0)), 0.5);
        assert!(!g.is_known((11, 0)));
    }

    #[test]
    fn a_cell_gets_one_update_per_scan_and_an_endpoint_wins_over_a_free_pass() {
        let mut g = grid();
        // Two beams to the same cell, and a third passing through it further on.
        g.integrate(
            (0.05, 0.05),
            &[(0.55, 0.05), (0.56, 0.04), (1.05, 0.05)],
            &[],
        );
        assert!((g.probability((5, 0)) - 0.9).abs() < 1e-6);
        assert!((g.probability((2, 0)) - 0.4).abs() < 1e-6);
        g.integrate((0.05, 0.05), &[(0.55, 0.05)], &[]);
        let twice = 1.0 / (1.0 + (-(2.0 * log_odds(0.9))).exp());
        assert!((g.probability((5, 0)) - twice).abs() < 1e-6);
    }

    #[test]
    fn the_grid_grows_in_every_direction_and_keeps_what_it_had() {
        let mut g = grid();
        g.integrate((0.0, 0.0), &[(1.0, 1.0)], &[]);
        let before = g.probability(g.cell_of(1.0, 1.0));
        g.integrate((0.0, 0.0), &[(-30.0, -12.0)], &[(25.0, 40.0)]);
        assert_eq!(g.probability(g.cell_of(1.0, 1.0)), before);
        assert!(g.probability(g.cell_of(-30.0, -12.0)) > 0.5);
        assert!(g.probability(g.cell_of(24.9, 39.8)) < 0.5);
        // From the hit at (−30, −12) to the last cell freed towards (25, 40), the endpoint's
        // own cell not freed.
        assert_eq!(g.known_bounds(), Some(((-300, -120), (249, 399))));
    }

    #[test]
    fn interpolation_is_exact_at_cell_centres_and_its_gradient_matches_finite_differences() {
        let mut g = grid();
        // A wall along x = 1 seen from several places, plus some free space: a varied surface.
        for k in 0..20 {
            let y0 = -0.5 + 0.05 * f64::from(k);
            let hits: Vec<_> = (0..30).map(|n| (1.0, -1.0 + 0.07 * f64::from(n))).collect();
            g.integrate((0.1, y0), &hits, &[]);
        }
        let c = (7, 3);
        let centre = ((f64::from(c.0) + 0.5) * 0.1, (f64::from(c.1) + 0.5) * 0.1);
        let s = g.interpolate(centre.0, centre.1);
        assert!((s.value - f64::from(g.probability(c))).abs() < 1e-9);

        let h = 1e-6;
        let mut checked = 0;
        for n in 0..200 {
            let x = 0.3 + 0.0037 * f64::from(n);
            let y = -0.4 + 0.0041 * f64::from(n);
            // Skip points within h of a cell-centre line, where the gradient is not continuous.
            let (u, v) = (x / 0.1 - 0.5, y / 0.1 - 0.5);
            if (u - u.round()).abs() < 1e-3 || (v - v.round()).abs() < 1e-3 {
                continue;
            }
            let s = g.interpolate(x, y);
            let dx = (g.interpolate(x + h, y).value - g.interpolate(x - h, y).value) / (2.0 * h);
            let dy = (g.interpolate(x, y + h).value - g.interpolate(x, y - h).value) / (2.0 * h);
            assert!(
                (s.gradient.0 - dx).abs() < 1e-5,
                "∂x at ({x}, {y}): {} vs {dx}",
                s.gradient.0
            );
            assert!(
                (s.gradient.1 - dy).abs() < 1e-5,
                "∂y at ({x}, {y}): {} vs {dy}",
                s.gradient.1
            );
            checked += 1;
        }
        assert!(checked > 150);
        // The wall makes the gradient point towards it (+x) just before it.
        assert!(g.interpolate(0.97, 0.2).gradient.0 > 1.0);
    }

    #[test]
    fn a_pyramid_updates_every_level_from_the_same_scan() {
        let mut p = GridPyramid::new(0.05, 3, &UpdateModel::default());
        p.integrate(
            &Pose2::new(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            &[(2.0, 0.0)],
            &[],
        );
        for grid in p.levels() {
            // The beam went along +y in the map frame.
            assert!(
                grid.probability(grid.cell_of(0.0, 2.01)) > 0.5,
                "{}",
                grid.resolution()
            );
            assert!(grid.probability(grid.cell_of(0.0, 1.0)) < 0.5);
        }
        assert_eq!(p.levels()[2].resolution(), 0.2);
    }

    #[test]
    fn a_grid_refuses_to_grow_past_its_cell_limit_and_stays_usable() {
        // A bounding box too large for the directory, though one beam touches few tiles.
        let mut g = Grid::new(0.001, &UpdateModel::default());
        assert!(!g.integrate((0.0, 0.0), &[(100_000.0, 100_000.0)], &[]));
        assert_eq!(g.scans(), 0);
        assert!(g.integrate((0.0, 0.0), &[(0.01, 0.0)], &[]));
        // More cells than the grid may hold: five tiles' worth, at 1 m per cell.
        let mut g = Grid::new(1.0, &UpdateModel::default());
        g.cell_limit = 5 * TILE_CELLS;
        assert!(g.integrate((0.5, 0.5), &[(10.5, 0.5)], &[]));
        assert_eq!(g.allocated_cells(), TILE_CELLS);
        // A beam across three more tiles: its box holds four, which would make five.
        assert!(g.integrate((0.5, 0.5), &[(200.5, 0.5)], &[]));
        assert_eq!(g.allocated_cells(), 4 * TILE_CELLS);
        // A beam whose box holds more tiles than remain is refused, and nothing changes.
        assert!(!g.integrate((0.5, 0.5), &[(0.5, 200.5)], &[]));
        assert_eq!(g.allocated_cells(), 4 * TILE_CELLS);
        assert_eq!(g.scans(), 2);
        assert!(g.probability((200, 0)) > 0.5);
        assert!(!g.is_known((0, 200)));
    }

    #[test]
    fn memory_follows_the_area_seen_not_its_bounding_box() {
        // Two rooms 2.5 km apart at 5 cm: their bounding box is 1.7 billion cells.
        let mut g = Grid::new(0.05, &UpdateModel::default());
        let room: Vec<(f64, f64)> = (0..360)
            .map(|k| {
                let a = f64::from(k).to_radians();
                (3.0 * a.cos(), 3.0 * a.sin())
            })
            .collect();
        for (x0, y0) in [(0.0, 0.0), (2000.0, -1500.0)] {
            let hits: Vec<_> = room.iter().map(|&(x, y)| (x0 + x, y0 + y)).collect();
            assert!(g.integrate((x0, y0), &hits, &[]));
            assert!(g.probability(g.cell_of(x0 + 3.0, y0)) > 0.5);
            assert!(g.probability(g.cell_of(x0 + 1.5, y0)) < 0.5);
        }
        // Each room (6 m across) touches at most 3 × 3 tiles of 3.2 m.
        assert!(
            g.allocated_cells() <= 2 * 9 * TILE_CELLS,
            "{}",
            g.allocated_cells()
        );
        assert!(!g.is_known(g.cell_of(1000.0, -750.0)));
        assert_eq!(g.probability(g.cell_of(1000.0, -750.0)), 0.5);
    }

    #[test]
    fn interpolation_across_tile_edges_reads_each_cell_where_it_is() {
        let mut g = grid();
        // Beams from inside tile (0, 0) across the edges at cells 0 / −1 and 63 / 64, both ways.
        for k in 0..72 {
            let a = f64::from(k) * 5.0f64.to_radians();
            let end = (0.3 + 7.0 * a.cos(), 0.2 + 7.0 * a.sin());
            g.integrate((0.3, 0.2), &[end], &[]);
        }
        let cells_at = |x: f64, y: f64| {
            let (u, v) = (x / 0.1 - 0.5, y / 0.1 - 0.5);
            let (i, j) = (u.floor() as i32, v.floor() as i32);
            let (fu, fv) = (u - u.floor(), v - v.floor());
            let p = |c| f64::from(g.probability(c));
            let bottom = p((i, j)) + fu * (p((i + 1, j)) - p((i, j)));
            let top = p((i, j + 1)) + fu * (p((i + 1, j + 1)) - p((i, j + 1)));
            bottom + fv * (top - bottom)
        };
        let mut straddling = 0;
        for n in 0..400 {
            // Points around x = 0 and x = 6.4 m, y = 0 and y = 6.4 m.
            let x = [-0.13, 6.31][n % 2] + 0.0007 * n as f64;
            let y = [-0.11, 6.33][(n / 2) % 2] + 0.0005 * n as f64;
            let (i, j) = (
                (x / 0.1 - 0.5).floor() as i32,
                (y / 0.1 - 0.5).floor() as i32,
            );
            straddling +=
                usize::from(i.rem_euclid(TILE) == TILE - 1 || j.rem_euclid(TILE) == TILE - 1);
            assert!(
                (g.interpolate(x, y).value - cells_at(x, y)).abs() < 1e-9,
                "({x}, {y})"
            );
        }
        assert!(straddling > 100, "{straddling}");
        // Cells seen on both sides of each edge, so the reads compared were not all unknown.
        for cell in [
            (-1, 2),
            (0, 2),
            (63, 2),
            (64, 2),
            (3, -1),
            (3, 0),
            (3, 63),
            (3, 64),
        ] {
            assert!(g.is_known(cell), "{cell:?}");
        }
    }
}
