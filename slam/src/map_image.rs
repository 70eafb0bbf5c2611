//! Occupancy rasters written the way ROS tools read them: `map_server`'s PGM (binary P5) + YAML
//! pair, as `map_saver` writes it, and a PNG to look at (optionally with a trajectory drawn on
//! it). Independent of how the grid was built: it takes one value per cell.

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
        raster,
        png::ColorType::Grayscale,
        &raster.trinary_pixels(thresholds),
        out,
    )
}

/// The colour of a trajectory drawn by [`write_png_with_trajectory`].
pub const TRAJECTORY_RGB: [u8; 3] = [220, 30, 30];

/// Writes the map as an RGB PNG (grey as in [`write_png`]) with the positions of `trajectory`
/// (metres, the raster's frame) joined by a line in [`TRAJECTORY_RGB`]; the parts outside the
/// raster are clipped away, so far-off poses cost nothing.
pub fn write_png_with_trajectory(
    raster: &OccupancyRaster,
    thresholds: &Thresholds,
    trajectory: &[Pose2],
    out: impl Write,
) -> io::Result<()> {
    let grey = raster.trinary_pixels(thresholds);
    let mut rgb: Vec<u8> = grey.iter().flat_map(|&g| [g, g, g]).collect();
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
                let i = 3 * (row as usize * raster.width + col as usize);
                rgb[i..i + 3].copy_from_slice(&TRAJECTORY_RGB);
            }
        }
    }
    encode_png(raster, png::ColorType::Rgb, &rgb, out)
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
    raster: &OccupancyRaster,
    color: png::ColorType,
    data: &[u8],
    out: impl Write,
) -> io::Result<()> {
    let to_io = |e: png::EncodingError| match e {
        png::EncodingError::IoError(e) => e,
        e => io::Error::other(e),
    };
    // Both fit in u32: checked in OccupancyRaster::new.
    let mut encoder = png::Encoder::new(out, raster.width as u32, raster.height as u32);
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
        let px = |col: usize, row: usize| &rgb[3 * (row * 3 + col)..3 * (row * 3 + col) + 3];
        // Image row 1 is the bottom row: columns 0 and 1 crossed, column 2 not reached.
        assert_eq!(px(0, 1), TRAJECTORY_RGB);
        assert_eq!(px(1, 1), TRAJECTORY_RGB);
        assert_eq!(px(2, 1), [205, 205, 205]);
        assert_eq!(px(0, 0), [205, 205, 205]);
        assert_eq!(px(2, 0), [0, 0, 0]);
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
