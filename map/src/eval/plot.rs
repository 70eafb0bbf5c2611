//! The paper's Fig. 11 (metric scores per map) and Fig. 12 (resolution against build time,
//! evaluation time, tree size and occupied volume), drawn with plotters as SVG text or PNG.
//!
//! Text uses the bundled DejaVu Sans (`map/assets/`, Bitstream Vera license) through
//! plotters' `ab_glyph` backend, so no system font library is needed.

use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// The bundled font (DejaVu Sans; license in `map/assets/DejaVuSans-LICENSE.txt`).
const FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
/// The family name the charts ask for.
const FAMILY: &str = "sans-serif";

/// Why a figure could not be drawn.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlotError {
    /// The bundled font could not be registered.
    #[error("cannot load the bundled font")]
    Font,
    /// The plotting backend failed (e.g. the PNG could not be written).
    #[error("drawing failed: {0}")]
    Draw(String),
    /// Nothing to draw.
    #[error("no data to plot")]
    NoData,
}

fn font() -> Result<(), PlotError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED
        .get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok { Ok(()) } else { Err(PlotError::Font) }
}

fn draw_err<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> PlotError {
    PlotError::Draw(e.to_string())
}

/// One group of Fig. 11: a map's scores against the reference.
#[derive(Debug, Clone, PartialEq)]
pub struct Fig11Group {
    /// Map name under the group.
    pub label: String,
    /// Weighted IoU (eq. M7).
    pub iou: f64,
    /// Mean log-odds error (eq. M8 / |C|).
    pub log_odds_mean: Option<f64>,
    /// Correlation, the paper's form (eq. M9).
    pub correlation: Option<f64>,
    /// Mean probability over C (the red bar).
    pub mean_probability: Option<f64>,
    /// Mean |p_ref - p_target| over C (the whisker on the red bar).
    pub deviation: Option<f64>,
}

/// Size of both figures in pixels.
const SIZE: (u32, u32) = (1000, 560);

const BAR_COLORS: [RGBColor; 4] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
];
const BAR_NAMES: [&str; 3] = [
    "IoU (weighted, eq. M7)",
    "correlation (eq. M9)",
    "mean probability ± mean |p_ref − p_tar|",
];
/// The colour of the similarity bars, in [`BAR_NAMES`] order.
const SIMILARITY_COLORS: [RGBColor; 3] = [BAR_COLORS[0], BAR_COLORS[2], BAR_COLORS[3]];

fn fig11<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    groups: &[Fig11Group],
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    font()?;
    if groups.is_empty() {
        return Err(PlotError::NoData);
    }
    root.fill(&WHITE).map_err(draw_err)?;
    let root = root
        .titled("Fig. 11: metric scores against the reference", (FAMILY, 24))
        .map_err(draw_err)?;
    // The similarities share a 0–1 axis; the log-odds error (nats, 0 is ideal, unbounded) has
    // its own panel and axis.
    let (left, right) = root.split_horizontally((SIZE.0 as f64 * 0.70) as u32);
    similarities(&left, groups)?;
    log_odds_panel(&right, groups)?;
    root.present().map_err(draw_err)
}

/// The 0–1 panel: IoU, correlation, mean probability with its deviation whisker.
fn similarities<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    groups: &[Fig11Group],
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    let bars = |g: &Fig11Group| [Some(g.iou), g.correlation, g.mean_probability];
    // Room above 1 for the value labels and the legend.
    let top = 1.45;
    let n = groups.len() as f64;
    let mut chart = ChartBuilder::on(area)
        .caption("similarity (1 = identical)", (FAMILY, 17))
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0..n, 0.0..top)
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_x_axis()
        .y_desc("score (0–1)")
        .y_labels(8)
        .y_label_formatter(&|v| {
            if *v <= 1.0 + 1e-9 {
                format!("{v:.1}")
            } else {
                String::new()
            }
        })
        .label_style((FAMILY, 15))
        .draw()
        .map_err(draw_err)?;
    let width = 0.24;
    let x_of = |i: usize, k: usize| i as f64 + 0.14 + k as f64 * width;
    for (k, (color, name)) in SIMILARITY_COLORS.iter().zip(BAR_NAMES).enumerate() {
        let rects = groups.iter().enumerate().filter_map(move |(i, g)| {
            let v = bars(g)[k].filter(|v| v.is_finite())?;
            let x0 = x_of(i, k);
            Some(Rectangle::new(
                [(x0, 0.0), (x0 + width * 0.9, v)],
                color.filled(),
            ))
        });
        chart
            .draw_series(rects)
            .map_err(draw_err)?
            .label(name)
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], color.filled()));
    }
    // The deviation whiskers on the mean-probability bars: a stem and two caps.
    for (i, g) in groups.iter().enumerate() {
        let (Some(p), Some(d)) = (g.mean_probability, g.deviation) else {
            continue;
        };
        if !(p.is_finite() && d.is_finite()) {
            continue;
        }
        let x = x_of(i, 2) + 0.45 * width;
        let (y0, y1) = ((p - d).max(0.0), p + d);
        let lines = [
            vec![(x, y0), (x, y1)],
            vec![(x - 0.03, y1), (x + 0.03, y1)],
            vec![(x - 0.03, y0), (x + 0.03, y0)],
        ];
        chart
            .draw_series(
                lines
                    .into_iter()
                    .map(|l| PathElement::new(l, BLACK.stroke_width(2))),
            )
            .map_err(draw_err)?;
    }
    // Values on top of the bars, group names below.
    let style = TextStyle::from((FAMILY, 12).into_font()).pos(Pos::new(HPos::Center, VPos::Bottom));
    for (i, g) in groups.iter().enumerate() {
        for (k, v) in bars(g).iter().enumerate() {
            if let Some(v) = v.filter(|v| v.is_finite()) {
                let x = x_of(i, k) + 0.45 * width;
                // The red bar's number goes above its whisker.
                let above = if k == 2 {
                    v + g.deviation.unwrap_or(0.0)
                } else {
                    v
                };
                chart
                    .draw_series(std::iter::once(Text::new(
                        format!("{v:.3}"),
                        (x, above + top * 0.005),
                        style.clone(),
                    )))
                    .map_err(draw_err)?;
            }
        }
        let label =
            TextStyle::from((FAMILY, 17).into_font()).pos(Pos::new(HPos::Center, VPos::Top));
        chart
            .draw_series(std::iter::once(Text::new(
                g.label.clone(),
                (i as f64 + 0.5, -top * 0.01),
                label,
            )))
            .map_err(draw_err)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FAMILY, 14))
        .draw()
        .map_err(draw_err)
}

/// The log-odds error panel: eq. M8's mean per common voxel, in nats, on its own axis.
fn log_odds_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    groups: &[Fig11Group],
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    let highest = groups
        .iter()
        .filter_map(|g| g.log_odds_mean)
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max);
    let top = if highest > 0.0 { highest * 1.25 } else { 0.1 };
    let n = groups.len() as f64;
    let color = BAR_COLORS[1];
    let mut chart = ChartBuilder::on(area)
        .caption("log-odds error (eq. M8; 0 = identical)", (FAMILY, 17))
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(65)
        .build_cartesian_2d(0.0..n, 0.0..top)
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_x_axis()
        .y_desc("nats per common voxel")
        .label_style((FAMILY, 13))
        .draw()
        .map_err(draw_err)?;
    let width = 0.5;
    chart
        .draw_series(groups.iter().enumerate().filter_map(|(i, g)| {
            let v = g.log_odds_mean.filter(|v| v.is_finite())?;
            let x0 = i as f64 + 0.25;
            Some(Rectangle::new([(x0, 0.0), (x0 + width, v)], color.filled()))
        }))
        .map_err(draw_err)?;
    let style = TextStyle::from((FAMILY, 12).into_font()).pos(Pos::new(HPos::Center, VPos::Bottom));
    let label = TextStyle::from((FAMILY, 13).into_font()).pos(Pos::new(HPos::Center, VPos::Top));
    for (i, g) in groups.iter().enumerate() {
        let x = i as f64 + 0.5;
        let text = g
            .log_odds_mean
            .filter(|v| v.is_finite())
            .map_or_else(|| "-".to_string(), |v| format!("{v:.4}"));
        let v = g.log_odds_mean.filter(|v| v.is_finite()).unwrap_or(0.0);
        chart
            .draw_series([
                Text::new(text, (x, v + top * 0.01), style.clone()),
                Text::new(g.label.clone(), (x, -top * 0.01), label.clone()),
            ])
            .map_err(draw_err)?;
    }
    Ok(())
}

/// Fig. 11 as an SVG document.
pub fn fig11_svg(groups: &[Fig11Group]) -> Result<String, PlotError> {
    let mut svg = String::new();
    fig11(
        SVGBackend::with_string(&mut svg, SIZE).into_drawing_area(),
        groups,
    )?;
    Ok(svg)
}

/// Fig. 11 as a PNG file at `path`.
pub fn fig11_png(groups: &[Fig11Group], path: &Path) -> Result<(), PlotError> {
    fig11(BitMapBackend::new(path, SIZE).into_drawing_area(), groups)
}

/// One resolution of Fig. 12.
#[derive(Debug, Clone, PartialEq)]
pub struct Fig12Row {
    /// Voxel edge in metres.
    pub resolution: f64,
    /// Octree build time (insertion + tree), seconds.
    pub build_s: f64,
    /// Evaluation time (all metrics, the map against itself), seconds.
    pub eval_s: f64,
    /// OctoMap node count.
    pub nodes: u64,
    /// Occupied volume, m³.
    pub occupied_m3: f64,
}

/// One Fig. 12 panel: title, y axis, points, colour.
type Panel<'a> = (&'a str, &'a str, Vec<(f64, f64)>, RGBColor);

fn panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    title: &str,
    y_desc: &str,
    xs: Range<f64>,
    points: Vec<(f64, f64)>,
    color: RGBColor,
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    let top = points.iter().map(|p| p.1).fold(0.0f64, f64::max) * 1.15;
    let top = if top > 0.0 && top.is_finite() {
        top
    } else {
        1.0
    };
    let mut chart = ChartBuilder::on(area)
        .caption(title, (FAMILY, 18))
        .margin(12)
        .x_label_area_size(38)
        .y_label_area_size(70)
        .build_cartesian_2d(xs, 0.0..top)
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc("resolution [m]")
        .y_desc(y_desc)
        .label_style((FAMILY, 13))
        .y_label_formatter(&|v| {
            if v.abs() >= 1e4 {
                format!("{v:.1e}")
            } else {
                let t = format!("{v:.4}");
                t.trim_end_matches('0').trim_end_matches('.').to_string()
            }
        })
        .draw()
        .map_err(draw_err)?;
    chart
        .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))
        .map_err(draw_err)?;
    chart
        .draw_series(
            points
                .into_iter()
                .map(|p| Circle::new(p, 4, color.filled())),
        )
        .map_err(draw_err)?;
    Ok(())
}

fn fig12<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    rows: &[Fig12Row],
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    font()?;
    if rows.is_empty() {
        return Err(PlotError::NoData);
    }
    root.fill(&WHITE).map_err(draw_err)?;
    let root = root
        .titled("Fig. 12: resolution against size and time", (FAMILY, 24))
        .map_err(draw_err)?;
    let lo = rows.iter().map(|r| r.resolution).fold(f64::MAX, f64::min);
    let hi = rows.iter().map(|r| r.resolution).fold(f64::MIN, f64::max);
    let pad = ((hi - lo) * 0.05).max(lo * 0.05).max(1e-3);
    let xs = (lo - pad).max(0.0)..hi + pad;
    let areas = root.split_evenly((2, 2));
    let series = |f: &dyn Fn(&Fig12Row) -> f64| -> Vec<(f64, f64)> {
        rows.iter().map(|r| (r.resolution, f(r))).collect()
    };
    let specs: [Panel; 4] = [
        (
            "octree build time",
            "seconds",
            series(&|r| r.build_s),
            BAR_COLORS[0],
        ),
        (
            "evaluation time (all metrics)",
            "milliseconds",
            series(&|r| r.eval_s * 1e3),
            BAR_COLORS[3],
        ),
        (
            "octree nodes",
            "nodes",
            series(&|r| r.nodes as f64),
            BAR_COLORS[2],
        ),
        (
            "occupied volume",
            "m³",
            series(&|r| r.occupied_m3),
            BAR_COLORS[1],
        ),
    ];
    for (area, (title, y, points, color)) in areas.iter().zip(specs) {
        panel(area, title, y, xs.clone(), points, color)?;
    }
    root.present().map_err(draw_err)
}

/// Fig. 12 as an SVG document.
pub fn fig12_svg(rows: &[Fig12Row]) -> Result<String, PlotError> {
    let mut svg = String::new();
    fig12(
        SVGBackend::with_string(&mut svg, SIZE).into_drawing_area(),
        rows,
    )?;
    Ok(svg)
}

/// Fig. 12 as a PNG file at `path`.
pub fn fig12_png(rows: &[Fig12Row], path: &Path) -> Result<(), PlotError> {
    fig12(BitMapBackend::new(path, SIZE).into_drawing_area(), rows)
}

/// One curve of Fig. 5: a yaw source's error against time.
#[derive(Debug, Clone, PartialEq)]
pub struct Fig5Series {
    /// The legend's label.
    pub label: String,
    /// (time s from the run's start, yaw error degrees), time increasing.
    pub points: Vec<(f64, f64)>,
}

fn fig5<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    series: &[Fig5Series],
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    font()?;
    let all = || series.iter().flat_map(|s| s.points.iter());
    if all().next().is_none() {
        return Err(PlotError::NoData);
    }
    let (t0, t1) = all().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (lo, hi) = all().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
    let pad = ((hi - lo) * 0.08).max(0.05);
    let xs = t0..if t1 > t0 { t1 } else { t0 + 1.0 };
    root.fill(&WHITE).map_err(draw_err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption("Fig. 5: yaw error against time", (FAMILY, 24))
        .margin(16)
        .x_label_area_size(42)
        .y_label_area_size(70)
        .build_cartesian_2d(xs, (lo - pad)..(hi + pad))
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc("time [s]")
        .y_desc("yaw error [°]")
        .label_style((FAMILY, 14))
        .draw()
        .map_err(draw_err)?;
    for (k, s) in series.iter().enumerate() {
        let color = BAR_COLORS[k % BAR_COLORS.len()];
        chart
            .draw_series(LineSeries::new(s.points.clone(), color.stroke_width(2)))
            .map_err(draw_err)?
            .label(s.label.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(3))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FAMILY, 14))
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(draw_err)?;
    root.present().map_err(draw_err)
}

/// The paper's Fig. 5 (yaw-fusion accuracy: each source's yaw error against time) as an SVG
/// document.
pub fn fig5_svg(series: &[Fig5Series]) -> Result<String, PlotError> {
    let mut svg = String::new();
    fig5(
        SVGBackend::with_string(&mut svg, SIZE).into_drawing_area(),
        series,
    )?;
    Ok(svg)
}

/// Fig. 5 as a PNG file at `path`.
pub fn fig5_png(series: &[Fig5Series], path: &Path) -> Result<(), PlotError> {
    fig5(BitMapBackend::new(path, SIZE).into_drawing_area(), series)
}
