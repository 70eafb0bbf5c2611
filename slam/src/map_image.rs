//! Occupancy rasters written the way ROS tools read them: `map_server`'s PGM (binary P5) + YAML
//! pair, as `map_saver` writes it, and a PNG to look at (optionally with a trajectory drawn on
//! it, axes and a scale bar in metres). Independent of how the grid was built: it takes one
//! value per cell.

use std::io::{self, Write};

use crate::pose::Pose2;

/// `map_server`'s trinary pixel for an occupied cell (black).
pub const OCCUPIED_PIXEL: u8 = 0;
/// `map_server`'s trinary pixel for a free cell (white).
pub const FREE_PIXEL: u8 = 254;
/// `map_server`'s trinary pixel for an unknown cell (grey).
pub const UNKNOWN_PIXEL: u8 = 205;

/// The thresholds written into the YAML. A reader computes p = (255 − pixel) / 255 and calls
/// p > 0.65 occupied, p < 0.196 free: 0 → 1.0, 254 → 0.004, 205 → 0.19608 (just above 0.196,
/// hence that odd value), so the three pixels read back as written whatever thresholds the
/// cells were classified with.
const YAML_OCCUPIED_THRESH: &str = "0.65";
const YAML_FREE_THRESH: &str = "0.196";

/// Why a raster cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RasterError {
    #[error("a raster needs at least one cell each way, got {width} x {height}")]
    Empty { width: usize, height: usize },
    #[error("{width} x {height} cells is too large for an image")]
    TooLarge { width: usize, height: usize },
    #[error("{width} x {height} cells need {expected} values, got {got}")]
    CellCount {
        width: usize,
        height: usize,
        expected: usize,
        got: usize,
    },
    #[error("the resolution must be a positive number of metres per cell, got {0}")]
    Resolution(f64),
    #[error("the origin must be finite, got ({0}, {1})")]
    Origin(f64, f64),
    #[error("cell (column {column}, row {row}) has occupancy probability {value}, outside [0, 1]")]
    Probability {
        column: usize,
        row: usize,
        value: f32,
    },
}

/// A 2D occupancy raster: `width × height` square cells of `resolution` metres, cell (column
/// c, row r) covering x ∈ [origin_x + c·res, origin_x + (c+1)·res) and likewise in y — row 0
/// is the lowest y, as in a ROS `OccupancyGrid`. Each cell is unknown (`None`) or a probability
/// of occupancy.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyRaster {
    width: usize,
    height: usize,
    resolution: f64,
    origin: (f64, f64),
    cells: Vec<Option<f32>>,
}

impl OccupancyRaster {
    /// A raster from its cells, row-major from the lowest row (`cells[row * width + column]`);
    /// `origin` is the (x, y) of the lower-left corner of cell (0, 0), in metres.
    pub fn new(
        width: usize,
        height: usize,
        resolution: f64,
        origin: (f64, f64),
        cells: Vec<Option<f32>>,
    ) -> Result<Self, RasterError> {
        if width == 0 || height == 0 {
            return Err(RasterError::Empty { width, height });
        }
        // PNG sizes are u32, and the RGB buffer takes three bytes a cell.
        let expected = width
            .checked_mul(height)
            .filter(|n| n.checked_mul(3).is_some() && u32::try_from(width.max(height)).is_ok())
            .ok_or(RasterError::TooLarge { width, height })?;
        if cells.len() != expected {
            return Err(RasterError::CellCount {
                width,
                height,
                expected,
                got: cells.len(),
            });
        }
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(RasterError::Resolution(resolution));
        }
        if !(origin.0.is_finite() && origin.1.is_finite()) {
            return Err(RasterError::Origin(origin.0, origin.1));
        }
        if let Some(i) = cells
            .iter()
            .position(|c| c.is_some_and(|p| !(0.0..=1.0).contains(&p)))
        {
            return Err(RasterError::Probability {
                column: i % width,
                row: i / width,
                value: cells[i].unwrap_or_default(),
            });
        }
        Ok(Self {
            width,
            height,
            resolution,
            origin,
            cells,
        })
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Metres per cell.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// (x, y) of the lower-left corner of cell (0, 0), metres.
    pub fn origin(&self) -> (f64, f64) {
        self.origin
    }

    /// The cell at (column, row), row 0 lowest; `None` outside the raster or when unknown.
    pub fn cell(&self, column: usize, row: usize) -> Option<f32> {
        if column < self.width && row < self.height {
            self.cells[row * self.width + column]
        } else {
            None
        }
    }

    /// One trinary pixel per cell ([`OCCUPIED_PIXEL`], [`FREE_PIXEL`], [`UNKNOWN_PIXEL`]) in
    /// image order: the top row (highest y) first, as PGM and PNG store them.
    pub fn trinary_pixels(&self, thresholds: &Thresholds) -> Vec<u8> {
        let mut pixels = Vec::with_capacity(self.cells.len());
        for row in self.cells.chunks_exact(self.width).rev() {
            pixels.extend(row.iter().map(|c| match *c {
                Some(p) if f64::from(p) >= thresholds.occupied => OCCUPIED_PIXEL,
                Some(p) if f64::from(p) <= thresholds.free => FREE_PIXEL,
                _ => UNKNOWN_PIXEL,
            }));
        }
        pixels
    }
}

/// How cell probabilities become trinary pixels: ≥ `occupied` is occupied, ≤ `free` is free,
/// anything between (and unknown) is unknown. The defaults are `map_server`'s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    pub occupied: f64,
    pub free: f64,
}

impl Default for Thresholds {
    fn default() -> Self {
        Self {
            occupied: 0.65,
            free: 0.196,
        }
    }
}

/// Writes the raster as `map_server`'s binary PGM (P5, 8-bit, trinary pixels, top row first).
pub fn write_pgm(
    raster: &OccupancyRaster,
    thresholds: &Thresholds,
    mut out: impl Write,
) -> io::Result<()> {
    write!(
        out,
        "P5\n# CREATOR: scan3d-slam {:.3} m/pix\n{} {}\n255\n",
        raster.resolution, raster.width, raster.height
    )?;
    out.write_all(&raster.trinary_pixels(thresholds))
}

/// Writes the `map_server` YAML that goes with the image file `image` (a path relative to the
/// YAML's folder, as `map_saver` writes it).
pub fn write_yaml(raster: &OccupancyRaster, image: &str, mut out: impl Write) -> io::Result<()> {
    writeln!(out, "image: {}", yaml_string(image))?;
    writeln!(out, "mode: trinary")?;
    writeln!(out, "resolution: {}", yaml_float(raster.resolution))?;
    writeln!(
        out,
        "origin: [{}, {}, 0.0]",
        yaml_float(raster.origin.0),
        yaml_float(raster.origin.1)
    )?;
    writeln!(out, "negate: 0")?;
    writeln!(out, "occupied_thresh: {YAML_OCCUPIED_THRESH}")?;
    writeln!(out, "free_thresh: {YAML_FREE_THRESH}")
}

/// The shortest text that reads back as `v`, always with a decimal point so YAML sees a float.
fn yaml_float(v: f64) -> String {
    let s = format!("{v}");
    if s.contains('.') { s } else { s + ".0" }
}

/// A plain scalar when the name is plain, else a double-quoted YAML string.
fn yaml_string(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-' | '/'))
        && !s.starts_with('-');
    if plain {
        return s.to_owned();
    }
    let mut quoted = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => quoted.push_str("\\\""),
            '\\' => quoted.push_str("\\\\"),
            c if c.is_control() => quoted.push_str(&format!("\\u{:04x}", c as u32)),
            c => quoted.push(c),
        }
    }
    quoted + "\""
}

/// Writes the trinary pixels as an 8-bit greyscale PNG, same orientation as the PGM.
pub fn write_png(
    raster: &OccupancyRaster,
    thresholds: &Thresholds,
    out: impl Write,
) -> io::Result<()> {
    encode_png(
        raster.width,
        raster.height,
        png::ColorType::Grayscale,
        &raster.trinary_pixels(thresholds),
        out,
    )
}

/// The colour of a trajectory drawn by [`write_png_with_trajectory`].
pub const TRAJECTORY_RGB: [u8; 3] = [220, 30, 30];

/// The colour of the frame, ticks, labels and scale bar around the map.
pub const INK_RGB: [u8; 3] = [0, 0, 0];

/// The colour of the margin around the map.
pub const PAPER_RGB: [u8; 3] = [255, 255, 255];

/// Writes the map as an RGB PNG to look at: the cells (grey as in [`write_png`], one pixel
/// each) inside a frame with axes in metres (ticks every 1, 2 or 5 × 10^k m, numbered), a
/// scale bar below them, and the positions of `trajectory` (metres, the raster's frame) joined
/// by a line in [`TRAJECTORY_RGB`]. The parts of the trajectory outside the raster are clipped
/// away, so far-off poses cost nothing.
pub fn write_png_with_trajectory(
    raster: &OccupancyRaster,
    thresholds: &Thresholds,
    trajectory: &[Pose2],
    out: impl Write,
) -> io::Result<()> {
    let layout = Layout::of(raster)
        .ok_or_else(|| io::Error::other("the map with its axes is too large for a PNG"))?;
    let mut canvas = Canvas::new(layout.width, layout.height);
    let grey = raster.trinary_pixels(thresholds);
    for (row, cells) in grey.chunks_exact(raster.width).enumerate() {
        for (col, &g) in cells.iter().enumerate() {
            canvas.set(layout.left + col, layout.top + row, [g, g, g]);
        }
    }
    let (w, h) = (raster.width as f64, raster.height as f64);
    // Image coordinates: u along columns, v down from the top edge, in cells.
    let to_image = |p: &Pose2| {
        (
            (p.x - raster.origin.0) / raster.resolution,
            h - (p.y - raster.origin.1) / raster.resolution,
        )
    };
    for pair in trajectory.windows(2) {
        let (a, b) = (to_image(&pair[0]), to_image(&pair[1]));
        let Some((a, b)) = clip_segment(a, b, w, h) else {
            continue;
        };
        // One sample per half cell along the clipped segment: at most 2 (w + h) + 1 samples.
        let steps = (2.0 * (b.0 - a.0).abs().max((b.1 - a.1).abs())).ceil() as usize;
        for k in 0..=steps {
            let s = if steps == 0 {
                0.0
            } else {
                k as f64 / steps as f64
            };
            let (u, v) = (a.0 + s * (b.0 - a.0), a.1 + s * (b.1 - a.1));
            let (col, row) = (u.floor(), v.floor());
            if col >= 0.0 && row >= 0.0 && col < w && row < h {
                canvas.set(
                    layout.left + col as usize,
                    layout.top + row as usize,
                    TRAJECTORY_RGB,
                );
            }
        }
    }
    layout.draw(&mut canvas);
    encode_png(
        layout.width,
        layout.height,
        png::ColorType::Rgb,
        &canvas.rgb,
        out,
    )
}

/// An RGB image being drawn, paper-coloured at first; writes outside it are ignored.
struct Canvas {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn new(width: usize, height: usize) -> Self {
        Canvas {
            width,
            height,
            rgb: PAPER_RGB.repeat(width * height),
        }
    }

    fn set(&mut self, col: usize, row: usize, rgb: [u8; 3]) {
        if col < self.width && row < self.height {
            let i = 3 * (row * self.width + col);
            self.rgb[i..i + 3].copy_from_slice(&rgb);
        }
    }

    fn fill(&mut self, col: usize, row: usize, width: usize, height: usize, rgb: [u8; 3]) {
        for r in row..row.saturating_add(height).min(self.height) {
            for c in col..col.saturating_add(width).min(self.width) {
                self.set(c, r, rgb);
            }
        }
    }

    /// `text` in [`glyph`]s `scale` pixels a dot, its top-left corner at (col, row).
    fn text(&mut self, col: usize, row: usize, text: &str, scale: usize) {
        for (i, c) in text.chars().enumerate() {
            let left = col + i * GLYPH_ADVANCE * scale;
            for (dy, bits) in glyph(c).iter().enumerate() {
                for dx in 0..GLYPH_WIDTH {
                    if bits & (1 << (GLYPH_WIDTH - 1 - dx)) != 0 {
                        self.fill(left + dx * scale, row + dy * scale, scale, scale, INK_RGB);
                    }
                }
            }
        }
    }
}

/// Dots across a glyph of the built-in font.
const GLYPH_WIDTH: usize = 5;
/// Dots down a glyph.
const GLYPH_HEIGHT: usize = 7;
/// Dots from one glyph's left edge to the next one's.
const GLYPH_ADVANCE: usize = 6;

/// A 5 × 7 dot glyph (one row a byte, the leftmost dot the highest of five bits) for the
/// characters the axes need: digits, `-`, `.`, `m`, `x`, `y`, parentheses and space; any
/// other character is blank.
fn glyph(c: char) -> [u8; GLYPH_HEIGHT] {
    match c {
        '0' => [0x0e, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0e],
        '1' => [0x04, 0x0c, 0x04, 0x04, 0x04, 0x04, 0x0e],
        '2' => [0x0e, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1f],
        '3' => [0x1f, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0e],
        '4' => [0x02, 0x06, 0x0a, 0x12, 0x1f, 0x02, 0x02],
        '5' => [0x1f, 0x10, 0x1e, 0x01, 0x01, 0x11, 0x0e],
        '6' => [0x06, 0x08, 0x10, 0x1e, 0x11, 0x11, 0x0e],
        '7' => [0x1f, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0e, 0x11, 0x11, 0x0e, 0x11, 0x11, 0x0e],
        '9' => [0x0e, 0x11, 0x11, 0x0f, 0x01, 0x02, 0x0c],
        '-' => [0x00, 0x00, 0x00, 0x1f, 0x00, 0x00, 0x00],
        '.' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x0c, 0x0c],
        'm' => [0x00, 0x00, 0x1a, 0x15, 0x15, 0x15, 0x15],
        'x' => [0x00, 0x00, 0x11, 0x0a, 0x04, 0x0a, 0x11],
        'y' => [0x00, 0x00, 0x11, 0x11, 0x0f, 0x01, 0x0e],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        _ => [0; GLYPH_HEIGHT],
    }
}

/// Width in pixels of `text` at `scale` (no trailing gap).
fn text_width(text: &str, scale: usize) -> usize {
    let n = text.chars().count();
    if n == 0 {
        0
    } else {
        ((n - 1) * GLYPH_ADVANCE + GLYPH_WIDTH) * scale
    }
}

/// The smallest of 1, 2, 5 × 10^k that is at least `at_least` (a positive finite number).
fn nice_at_least(at_least: f64) -> f64 {
    let decade = 10f64.powf(at_least.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * decade)
        .find(|v| *v >= at_least * (1.0 - 1e-12))
        .unwrap_or(10.0 * decade)
}

/// The largest of 1, 2, 5 × 10^k that is at most `at_most` (a positive finite number).
fn nice_at_most(at_most: f64) -> f64 {
    let decade = 10f64.powf(at_most.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * decade)
        .find(|v| *v <= at_most * (1.0 + 1e-12))
        .unwrap_or(decade)
}

/// `value` (a multiple of `step`, metres) as the axes print it: as many decimals as `step`
/// needs, no `-0`.
fn format_metres(value: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let text = format!("{value:.decimals$}");
    if text
        .trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        text.trim_start_matches('-').to_owned()
    } else {
        text
    }
}

/// Where everything goes in the annotated PNG: the map's cells at (`left`, `top`), one pixel
/// a cell; a one-pixel frame just outside them; ticks and numbers on the left (y) and bottom
/// (x) edges; the scale bar under the x numbers, starting at the map's left edge.
#[derive(Debug, Clone, PartialEq)]
struct Layout {
    /// The whole image, pixels.
    width: usize,
    height: usize,
    /// The column and row of the map's top-left cell.
    left: usize,
    top: usize,
    /// The map's size in cells (= pixels).
    map_width: usize,
    map_height: usize,
    /// Pixels a dot of the font (1, or 2 for maps at least 400 cells wide or high).
    scale: usize,
    /// x ticks: (column, label); y ticks: (row, label).
    x_ticks: Vec<(usize, String)>,
    y_ticks: Vec<(usize, String)>,
    /// The scale bar: its length in metres, in pixels, and the row of its top edge.
    bar_metres: f64,
    bar_pixels: usize,
    bar_row: usize,
}

/// Pixels at least between two ticks.
const TICK_SPACING: f64 = 80.0;

impl Layout {
    /// The layout for `raster`; `None` when the image would be too large for a PNG.
    fn of(raster: &OccupancyRaster) -> Option<Layout> {
        let (w, h, res) = (raster.width, raster.height, raster.resolution);
        let (ox, oy) = raster.origin;
        let scale = if w.max(h) >= 400 { 2 } else { 1 };
        let glyph_height = GLYPH_HEIGHT * scale;
        let tick = 4 * scale;
        let gap = 2 * scale;
        let step = nice_at_least(TICK_SPACING * res);
        // The ticks: multiples of `step` within the map, in metres, and their offset in cells.
        let ticks = |from: f64, cells: usize| -> Vec<(f64, f64)> {
            let to = from + cells as f64 * res;
            let first = (from / step - 1e-9).ceil() as i64;
            let last = (to / step + 1e-9).floor() as i64;
            // At most cells / 80 + 2 ticks: `step` is at least 80 cells.
            (first..=last)
                .map(|k| (k as f64 * step, (k as f64 * step - from) / res))
                .collect()
        };
        let x_values = ticks(ox, w);
        let y_values = ticks(oy, h);
        let label = |v: f64| format_metres(v, step);
        let y_label_width = y_values
            .iter()
            .map(|&(v, _)| text_width(&label(v), scale))
            .max()
            .unwrap_or(0);
        let x_label_half = x_values
            .iter()
            .map(|&(v, _)| text_width(&label(v), scale).div_ceil(2))
            .max()
            .unwrap_or(0);
        let y_title = "y (m)";
        let left = (gap + y_label_width + gap + tick + 1).max(text_width(y_title, scale) + gap);
        let top = gap + glyph_height + 2 * gap;
        let bar_metres = nice_at_most(w as f64 * res / 4.0);
        let bar_pixels = (bar_metres / res).round() as usize;
        let bar_row = top + h + 1 + tick + gap + glyph_height + 3 * gap;
        let bottom_rows = 1 + tick + gap + glyph_height + 3 * gap + glyph_height + gap;
        let right = (x_label_half + gap).max(1 + gap);
        let width = left.checked_add(w)?.checked_add(right)?;
        let height = top.checked_add(h)?.checked_add(bottom_rows)?;
        let pixels = width.checked_mul(height)?;
        pixels.checked_mul(3)?;
        u32::try_from(width.max(height)).ok()?;
        Some(Layout {
            width,
            height,
            left,
            top,
            map_width: w,
            map_height: h,
            scale,
            x_ticks: x_values
                .iter()
                .map(|&(v, cells)| (left + cells.round() as usize, label(v)))
                .collect(),
            y_ticks: y_values
                .iter()
                .map(|&(v, cells)| (top + h - (cells.round() as usize).min(h), label(v)))
                .collect(),
            bar_metres,
            bar_pixels,
            bar_row,
        })
    }

    /// Draws the frame, the ticks and their numbers, the axis titles and the scale bar.
    fn draw(&self, canvas: &mut Canvas) {
        let (s, left, top) = (self.scale, self.left, self.top);
        let (w, h) = (self.map_width, self.map_height);
        let (tick, gap, glyph_height) = (4 * s, 2 * s, GLYPH_HEIGHT * s);
        // The frame, one pixel outside the cells.
        canvas.fill(left - 1, top - 1, w + 2, 1, INK_RGB);
        canvas.fill(left - 1, top + h, w + 2, 1, INK_RGB);
        canvas.fill(left - 1, top - 1, 1, h + 2, INK_RGB);
        canvas.fill(left + w, top - 1, 1, h + 2, INK_RGB);
        for (col, text) in &self.x_ticks {
            canvas.fill(*col, top + h + 1, 1, tick, INK_RGB);
            let half = text_width(text, s) / 2;
            canvas.text(col.saturating_sub(half), top + h + 1 + tick + gap, text, s);
        }
        for (row, text) in &self.y_ticks {
            canvas.fill(left - 1 - tick, *row, tick, 1, INK_RGB);
            let col = (left - 1 - tick - gap).saturating_sub(text_width(text, s));
            canvas.text(col, row.saturating_sub(glyph_height / 2), text, s);
        }
        canvas.text(gap, gap, "y (m)", s);
        let x_title = "x (m)";
        canvas.text(
            (left + w).saturating_sub(text_width(x_title, s)),
            self.bar_row,
            x_title,
            s,
        );
        // The scale bar, as thick as a third of a glyph, its number after it.
        let thickness = (glyph_height / 3).max(2);
        canvas.fill(
            left,
            self.bar_row + thickness,
            self.bar_pixels,
            thickness,
            INK_RGB,
        );
        let bar_text = format!("{} m", format_metres(self.bar_metres, self.bar_metres));
        canvas.text(left + self.bar_pixels + 2 * gap, self.bar_row, &bar_text, s);
    }
}

/// Liang–Barsky: the part of segment a–b inside [0, w] × [0, h], if any (None for non-finite ends).
fn clip_segment(a: (f64, f64), b: (f64, f64), w: f64, h: f64) -> Option<((f64, f64), (f64, f64))> {
    if ![a.0, a.1, b.0, b.1].iter().all(|v| v.is_finite()) {
        return None;
    }
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0_f64, 1.0_f64);
    for (p, q) in [(-dx, a.0), (dx, w - a.0), (-dy, a.1), (dy, h - a.1)] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    (t0 <= t1).then_some({
        (
            (a.0 + t0 * dx, a.1 + t0 * dy),
            (a.0 + t1 * dx, a.1 + t1 * dy),
        )
    })
}

fn encode_png(
    width: usize,
    height: usize,
    color: png::ColorType,
    data: &[u8],
    out: impl Write,
) -> io::Result<()> {
    let to_io = |e: png::EncodingError| match e {
        png::EncodingError::IoError(e) => e,
        e => io::Error::other(e),
    };
    // Both fit in u32: checked in OccupancyRaster::new and Layout::of.
    let mut encoder = png::Encoder::new(out, width as u32, height as u32);
    encoder.set_color(color);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(to_io)?;
    writer.write_image_data(data).map_err(to_io)?;
    writer.finish().map_err(to_io)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 3 × 2 cells of 5 cm, lower-left corner at (−1.5, 2.0). Bottom row: free, occupied,
    /// unknown; top row: 0.5 (undecided), 0.1 (free), 0.9 (occupied).
    fn tiny() -> OccupancyRaster {
        let cells = vec![Some(0.0), Some(1.0), None, Some(0.5), Some(0.1), Some(0.9)];
        OccupancyRaster::new(3, 2, 0.05, (-1.5, 2.0), cells).unwrap()
    }

    #[test]
    fn the_pgm_is_binary_p5_with_the_top_row_first_and_map_servers_pixel_values() {
        let mut out = Vec::new();
        write_pgm(&tiny(), &Thresholds::default(), &mut out).unwrap();
        let mut expected = b"P5\n# CREATOR: scan3d-slam 0.050 m/pix\n3 2\n255\n".to_vec();
        expected.extend_from_slice(&[205, 254, 0, 254, 0, 205]);
        assert_eq!(out, expected);
    }

    #[test]
    fn the_yaml_has_map_servers_keys_and_the_lower_left_origin() {
        let mut out = Vec::new();
        write_yaml(&tiny(), "intel.pgm", &mut out).unwrap();
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "image: intel.pgm\nmode: trinary\nresolution: 0.05\norigin: [-1.5, 2.0, 0.0]\n\
             negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
        );
        let mut out = Vec::new();
        write_yaml(&tiny(), "my map: \"v2\".pgm", &mut out).unwrap();
        assert!(
            String::from_utf8(out)
                .unwrap()
                .starts_with("image: \"my map: \\\"v2\\\".pgm\"\n")
        );
    }

    #[test]
    fn the_written_pixels_read_back_as_written_under_the_yaml_thresholds() {
        // map_server: p = (255 − pixel) / 255; occupied if p > 0.65, free if p < 0.196.
        let read = |pixel: u8| {
            let p = (255.0 - f64::from(pixel)) / 255.0;
            if p > 0.65 {
                100
            } else if p < 0.196 {
                0
            } else {
                -1
            }
        };
        assert_eq!(
            [read(OCCUPIED_PIXEL), read(FREE_PIXEL), read(UNKNOWN_PIXEL)],
            [100, 0, -1]
        );
    }

    fn decode(bytes: &[u8]) -> (png::OutputInfo, Vec<u8>) {
        let mut reader = png::Decoder::new(bytes).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        (info, buf)
    }

    #[test]
    fn the_png_decodes_to_the_pgm_pixels() {
        let mut out = Vec::new();
        write_png(&tiny(), &Thresholds::default(), &mut out).unwrap();
        let (info, pixels) = decode(&out);
        assert_eq!((info.width, info.height), (3, 2));
        assert_eq!(info.color_type, png::ColorType::Grayscale);
        assert_eq!(pixels, vec![205, 254, 0, 254, 0, 205]);
    }

    #[test]
    fn a_trajectory_is_drawn_over_the_map_and_clipped_to_it() {
        // Along the bottom row's centre line (y = 2.025), from far outside on the left.
        let path = [
            Pose2::new(-1e12, 2.025, 0.0),
            Pose2::new(-1.425, 2.025, 0.0),
        ];
        let mut out = Vec::new();
        write_png_with_trajectory(&tiny(), &Thresholds::default(), &path, &mut out).unwrap();
        let (info, rgb) = decode(&out);
        assert_eq!(info.color_type, png::ColorType::Rgb);
        let layout = Layout::of(&tiny()).unwrap();
        assert_eq!(
            (info.width as usize, info.height as usize),
            (layout.width, layout.height)
        );
        // (col, row) of the map's cells, inside the frame.
        let px = |col: usize, row: usize| {
            let i = 3 * ((layout.top + row) * layout.width + layout.left + col);
            &rgb[i..i + 3]
        };
        // Image row 1 is the bottom row: columns 0 and 1 crossed, column 2 not reached.
        assert_eq!(px(0, 1), TRAJECTORY_RGB);
        assert_eq!(px(1, 1), TRAJECTORY_RGB);
        assert_eq!(px(2, 1), [205, 205, 205]);
        assert_eq!(px(0, 0), [205, 205, 205]);
        assert_eq!(px(2, 0), [0, 0, 0]);
    }

    /// An all-unknown raster of `width` × `height` cells of `resolution` m at `origin`, as
    /// the annotated PNG draws it: (pixels, width, height).
    fn annotated(
        width: usize,
        height: usize,
        resolution: f64,
        origin: (f64, f64),
    ) -> (Vec<u8>, usize, usize) {
        let raster = OccupancyRaster::new(
            width,
            height,
            resolution,
            origin,
            vec![None; width * height],
        )
        .unwrap();
        let mut out = Vec::new();
        write_png_with_trajectory(&raster, &Thresholds::default(), &[], &mut out).unwrap();
        let (info, rgb) = decode(&out);
        (rgb, info.width as usize, info.height as usize)
    }

    /// The longest run of ink in each row below `from_row`: (row, first column, length).
    fn longest_ink_runs(
        rgb: &[u8],
        width: usize,
        height: usize,
        from_row: usize,
    ) -> Vec<(usize, usize, usize)> {
        let ink = |col: usize, row: usize| rgb[3 * (row * width + col)..][..3] == INK_RGB;
        (from_row..height)
            .filter_map(|row| {
                let mut best: Option<(usize, usize)> = None;
                let mut col = 0;
                while col < width {
                    if ink(col, row) {
                        let start = col;
                        while col < width && ink(col, row) {
                            col += 1;
                        }
                        if best.is_none_or(|(_, n)| col - start > n) {
                            best = Some((start, col - start));
                        }
                    }
                    col += 1;
                }
                best.map(|(start, n)| (row, start, n))
            })
            .collect()
    }

    #[test]
    fn the_scale_bar_is_as_long_as_its_metres_at_the_resolution_under_the_map() {
        // 20 m × 10 m; the bar is the largest 1/2/5 × 10^k m within a quarter of the width.
        for (cells, resolution, bar_m) in [(400, 0.05, 5.0), (200, 0.1, 5.0), (300, 0.05, 2.0)] {
            let (rgb, width, height) = annotated(cells, cells / 2, resolution, (0.0, 0.0));
            // The frame: its top edge is the first row of ink as wide as the map and the frame.
            let runs = longest_ink_runs(&rgb, width, height, 0);
            let &(frame_top, frame_col, _) = runs
                .iter()
                .find(|&&(_, _, n)| n == cells + 2)
                .expect("the frame's top edge");
            let (left, frame_row) = (frame_col + 1, frame_top + cells / 2 + 1);
            let at = |col: usize, row: usize| &rgb[3 * (row * width + col)..][..3];
            assert_eq!(at(left, frame_top + 1), [UNKNOWN_PIXEL; 3]);
            assert!((frame_col..left + cells + 1).all(|c| at(c, frame_row) == INK_RGB));
            assert_eq!(at(left + cells / 2, frame_row - 1), [UNKNOWN_PIXEL; 3]);
            // Below the frame: the bar, from the map's left edge, bar_m / resolution long.
            let bar: Vec<_> = runs
                .iter()
                .filter(|&&(row, _, n)| row > frame_row && n > 10)
                .collect();
            let expected = (bar_m / resolution).round() as usize;
            assert!(!bar.is_empty(), "no scale bar below row {frame_row}");
            for &&(_, start, n) in &bar {
                assert_eq!(
                    (start, n),
                    (left, expected),
                    "{cells} cells of {resolution} m"
                );
            }
            // Ticks every nice step under the frame: at 0 m, and one step further.
            let layout = Layout::of(
                &OccupancyRaster::new(
                    cells,
                    cells / 2,
                    resolution,
                    (0.0, 0.0),
                    vec![None; cells * cells / 2],
                )
                .unwrap(),
            )
            .unwrap();
            assert_eq!(layout.x_ticks[0], (left, "0".to_owned()));
            let step = (layout.x_ticks[1].0 - left) as f64 * resolution;
            assert!(
                [2.0, 5.0, 10.0].iter().any(|s| (s - step).abs() < 1e-9),
                "{step}"
            );
            for &(col, _) in &layout.x_ticks {
                assert_eq!(
                    rgb[3 * ((frame_row + 1) * width + col)..][..3],
                    INK_RGB,
                    "tick at column {col}"
                );
            }
        }
    }

    #[test]
    fn the_axes_are_numbered_in_metres_of_the_raster_frame() {
        // 47 m × 36 m from (−20, −15), as a benchmark log's map: ticks every 5 m.
        let raster =
            OccupancyRaster::new(940, 720, 0.05, (-20.0, -15.0), vec![None; 940 * 720]).unwrap();
        let layout = Layout::of(&raster).unwrap();
        let labels: Vec<&str> = layout.x_ticks.iter().map(|(_, t)| t.as_str()).collect();
        assert_eq!(
            labels,
            ["-20", "-15", "-10", "-5", "0", "5", "10", "15", "20", "25"]
        );
        assert_eq!(layout.x_ticks[4].0, layout.left + 400);
        let labels: Vec<&str> = layout.y_ticks.iter().map(|(_, t)| t.as_str()).collect();
        assert_eq!(labels, ["-15", "-10", "-5", "0", "5", "10", "15", "20"]);
        // y = 0 m is 300 cells above the bottom edge, image rows counting down.
        assert_eq!(layout.y_ticks[3].0, layout.top + 720 - 300);
        assert_eq!((layout.bar_metres, layout.bar_pixels), (10.0, 200));
        // The numbers are drawn: the glyphs of "0" under its tick, centred.
        let mut expected = Canvas::new(layout.width, layout.height);
        let (col, text) = &layout.x_ticks[4];
        let s = layout.scale;
        let text_row = layout.top + 720 + 1 + 4 * s + 2 * s;
        expected.text(col - text_width(text, s) / 2, text_row, text, s);
        let mut drawn = Canvas::new(layout.width, layout.height);
        layout.draw(&mut drawn);
        let region = |c: &Canvas| -> Vec<u8> {
            (text_row..text_row + GLYPH_HEIGHT * s)
                .flat_map(|r| {
                    let i = 3 * (r * c.width + col - 10);
                    c.rgb[i..i + 3 * 20].to_vec()
                })
                .collect()
        };
        assert_eq!(region(&drawn), region(&expected));
        assert!(region(&drawn).chunks(3).any(|p| p == INK_RGB));
        assert_eq!(format_metres(-0.0, 5.0), "0");
        assert_eq!(format_metres(2.5, 0.5), "2.5");
        assert_eq!(format_metres(-0.2, 0.2), "-0.2");
    }

    #[test]
    fn rasters_with_bad_sizes_resolutions_or_probabilities_are_refused() {
        let cells = || vec![Some(0.5); 6];
        assert_eq!(
            OccupancyRaster::new(3, 2, 0.05, (0.0, 0.0), vec![None; 5])
                .unwrap_err()
                .to_string(),
            "3 x 2 cells need 6 values, got 5"
        );
        assert!(matches!(
            OccupancyRaster::new(3, 2, 0.0, (0.0, 0.0), cells()),
            Err(RasterError::Resolution(_))
        ));
        assert!(matches!(
            OccupancyRaster::new(0, 2, 0.05, (0.0, 0.0), vec![]),
            Err(RasterError::Empty { .. })
        ));
        assert!(matches!(
            OccupancyRaster::new(usize::MAX, 2, 0.05, (0.0, 0.0), vec![]),
            Err(RasterError::TooLarge { .. })
        ));
        let mut bad = cells();
        bad[4] = Some(f32::NAN);
        assert_eq!(
            OccupancyRaster::new(3, 2, 0.05, (0.0, 0.0), bad)
                .unwrap_err()
                .to_string(),
            "cell (column 1, row 1) has occupancy probability NaN, outside [0, 1]"
        );
    }
}
