//! PNG plots for reports (paper figures, HIL reports, latency, identification).
//!
//! One small API over `plotters`: a figure is a grid of panels, a panel has labelled axes
//! (linear or log10) and series (lines or points). The DejaVu Sans font is embedded in
//! the binary (assets/DejaVuSans.ttf), so no system font packages are needed.
//! Offline only: never called from the real-time path.

use std::path::Path;
use std::sync::Once;

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

static FONT: Once = Once::new();

fn ensure_font() {
    FONT.call_once(|| {
        // Registering fails only if the embedded bytes are not a font: a build error.
        let _ = register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../assets/DejaVuSans.ttf"),
        );
    });
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Style {
    Line,
    Dashed,
    Points,
}

/// One data series.
#[derive(Debug, Clone)]
pub struct Series {
    pub label: String,
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    pub style: Style,
    /// Index into the palette (series with the same index share a colour).
    pub color: usize,
}

impl Series {
    pub fn line(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>, color: usize) -> Series {
        Series {
            label: label.into(),
            x,
            y,
            style: Style::Line,
            color,
        }
    }
    pub fn dashed(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>, color: usize) -> Series {
        Series {
            label: label.into(),
            x,
            y,
            style: Style::Dashed,
            color,
        }
    }
    pub fn points(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>, color: usize) -> Series {
        Series {
            label: label.into(),
            x,
            y,
            style: Style::Points,
            color,
        }
    }
}

/// Axis scale.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Scale {
    #[default]
    Linear,
    Log10,
}

/// One panel: title, axis labels (with units), scales, optional fixed ranges, series.
#[derive(Debug, Clone, Default)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub x_scale: Scale,
    pub y_scale: Scale,
    pub x_range: Option<(f64, f64)>,
    pub y_range: Option<(f64, f64)>,
    pub series: Vec<Series>,
}

impl Panel {
    pub fn new(
        title: impl Into<String>,
        x_label: impl Into<String>,
        y_label: impl Into<String>,
    ) -> Panel {
        Panel {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            ..Panel::default()
        }
    }
    pub fn log_x(mut self) -> Panel {
        self.x_scale = Scale::Log10;
        self
    }
    pub fn log_y(mut self) -> Panel {
        self.y_scale = Scale::Log10;
        self
    }
    pub fn x_range(mut self, lo: f64, hi: f64) -> Panel {
        self.x_range = Some((lo, hi));
        self
    }
    pub fn y_range(mut self, lo: f64, hi: f64) -> Panel {
        self.y_range = Some((lo, hi));
        self
    }
    pub fn with(mut self, series: Series) -> Panel {
        self.series.push(series);
        self
    }
}

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

fn transform(v: f64, scale: Scale) -> Option<f64> {
    match scale {
        Scale::Linear => v.is_finite().then_some(v),
        Scale::Log10 => (v.is_finite() && v > 0.0).then(|| v.log10()),
    }
}

fn range_of(panel: &Panel, axis_x: bool) -> (f64, f64) {
    let (scale, fixed) = if axis_x {
        (panel.x_scale, panel.x_range)
    } else {
        (panel.y_scale, panel.y_range)
    };
    if let Some((lo, hi)) = fixed {
        if let (Some(a), Some(b)) = (transform(lo, scale), transform(hi, scale)) {
            return (a, b);
        }
    }
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for s in &panel.series {
        let (vals, other) = if axis_x { (&s.x, &s.y) } else { (&s.y, &s.x) };
        for (v, o) in vals.iter().zip(other) {
            let (xo, yo) = if axis_x { (*v, *o) } else { (*o, *v) };
            // Only points visible on the other axis's fixed range count.
            let visible = if axis_x {
                panel
                    .y_range
                    .is_none_or(|(a, b)| yo >= a.min(b) && yo <= a.max(b))
            } else {
                panel
                    .x_range
                    .is_none_or(|(a, b)| xo >= a.min(b) && xo <= a.max(b))
            };
            if let (true, Some(t)) = (visible, transform(*v, scale)) {
                lo = lo.min(t);
                hi = hi.max(t);
            }
        }
    }
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo <= f64::EPSILON * hi.abs().max(1.0) {
        let pad = if lo == 0.0 { 1.0 } else { 0.05 * lo.abs() };
        return (lo - pad, hi + pad);
    }
    if axis_x {
        (lo, hi)
    } else {
        let pad = 0.05 * (hi - lo);
        (lo - pad, hi + pad)
    }
}

/// Tick label for value `v` (in transformed units) on an axis spanning `lo..hi`.
///
/// Linear: values within a billionth of the span of zero print as `0` (no `-5.6e-17`).
/// Log: plain decimals (`0.316`, `15.8`) when the whole axis lies within 1e-3..1e5,
/// else scientific (`3.16e-5`), so one axis never mixes both.
fn tick_label(v: f64, scale: Scale, lo: f64, hi: f64) -> String {
    match scale {
        Scale::Linear => {
            let v = if v.abs() <= 1e-9 * (hi - lo).abs() {
                0.0
            } else {
                v
            };
            let a = v.abs();
            if a != 0.0 && !(1e-3..1e5).contains(&a) {
                format!("{v:.1e}")
            } else {
                let s = format!("{v:.4}");
                let s = s.trim_end_matches('0').trim_end_matches('.');
                if s == "-0" {
                    "0".into()
                } else {
                    s.to_string()
                }
            }
        }
        Scale::Log10 => {
            let p = 10f64.powf(v);
            let plain = lo.min(hi) >= -3.0 - 1e-9 && lo.max(hi) < 5.0;
            if plain {
                // Three significant digits.
                let decimals = (2 - v.floor() as i64).max(0) as usize;
                let s = format!("{p:.decimals$}");
                if s.contains('.') {
                    s.trim_end_matches('0').trim_end_matches('.').to_string()
                } else {
                    s
                }
            } else if (v - v.round()).abs() < 1e-9 {
                format!("1e{}", v.round() as i64)
            } else {
                format!("{p:.2e}")
            }
        }
    }
}

/// Where the legend hides the least data: the corner whose legend-sized box holds the
/// fewest points of the drawn series (lines sampled along their segments), and that
/// number. Ties keep the upper right.
fn legend_corner(
    panel: &Panel,
    x_range: (f64, f64),
    y_range: (f64, f64),
    box_fraction: (f64, f64),
) -> (SeriesLabelPosition, usize) {
    let (bw, bh) = box_fraction;
    let nx = |x: f64| (x - x_range.0) / (x_range.1 - x_range.0);
    let ny = |y: f64| (y - y_range.0) / (y_range.1 - y_range.0);
    // (x interval, y interval) in unit coordinates, y up: upper right, upper left,
    // lower right, lower left.
    let corners = [
        ((1.0 - bw, 1.0), (1.0 - bh, 1.0)),
        ((0.0, bw), (1.0 - bh, 1.0)),
        ((1.0 - bw, 1.0), (0.0, bh)),
        ((0.0, bw), (0.0, bh)),
    ];
    let mut counts = [0usize; 4];
    let mut count = |u: f64, w: f64| {
        for (k, ((x0, x1), (y0, y1))) in corners.iter().enumerate() {
            if u >= *x0 && u <= *x1 && w >= *y0 && w <= *y1 {
                counts[k] += 1;
            }
        }
    };
    for s in &panel.series {
        let pts: Vec<(f64, f64)> =
            s.x.iter()
                .zip(&s.y)
                .filter_map(|(x, y)| {
                    Some((
                        nx(transform(*x, panel.x_scale)?),
                        ny(transform(*y, panel.y_scale)?),
                    ))
                })
                .collect();
        if s.style == Style::Points {
            pts.iter().for_each(|&(u, w)| count(u, w));
            continue;
        }
        for pair in pts.windows(2) {
            let ((u0, w0), (u1, w1)) = (pair[0], pair[1]);
            let pieces = ((u1 - u0).abs().max((w1 - w0).abs()) / 0.01)
                .ceil()
                .clamp(1.0, 200.0);
            for i in 0..pieces as usize {
                let t = i as f64 / pieces;
                count(u0 + t * (u1 - u0), w0 + t * (w1 - w0));
            }
        }
        if let Some(&(u, w)) = pts.last() {
            count(u, w);
        }
    }
    let best = (0..4).min_by_key(|&k| (counts[k], k)).unwrap_or(0);
    let position = match best {
        1 => SeriesLabelPosition::UpperLeft,
        2 => SeriesLabelPosition::LowerRight,
        3 => SeriesLabelPosition::LowerLeft,
        _ => SeriesLabelPosition::UpperRight,
    };
    (position, counts[best])
}

/// Draws panels in a grid of `cols` columns into a PNG of `width` x `height` pixels.
pub fn draw_png(
    path: &Path,
    width: u32,
    height: u32,
    cols: usize,
    panels: &[Panel],
) -> anyhow::Result<()> {
    ensure_font();
    let cols = cols.max(1);
    let rows = panels.len().div_ceil(cols).max(1);
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let areas = root.split_evenly((rows, cols));
    for (panel, area) in panels.iter().zip(areas.iter()) {
        draw_panel(panel, area)
            .map_err(|e| anyhow::anyhow!("{}: panel `{}`: {e}", path.display(), panel.title))?;
    }
    root.present()
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(())
}

fn draw_panel(
    panel: &Panel,
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
) -> Result<(), Box<dyn std::error::Error>> {
    let (x0, x1) = range_of(panel, true);
    let (y0, mut y1) = range_of(panel, false);
    // Legend: the corner that hides the least data; if every corner holds data and the
    // y range is free, raise the top of the y axis so the legend sits above the data.
    // Box size: 13 px text, about 7 px per character, 18 px glyph, padding and margin;
    // plotting area: the panel less the label areas, margins and caption.
    let labels: Vec<&str> = panel
        .series
        .iter()
        .filter(|s| !s.label.is_empty())
        .map(|s| s.label.as_str())
        .collect();
    let mut legend_position = SeriesLabelPosition::UpperRight;
    if !labels.is_empty() {
        let chars = labels.iter().map(|l| l.chars().count()).max().unwrap_or(0);
        let (aw, ah) = area.dim_in_pixel();
        let (w, h) = ((aw as f64 - 90.0).max(1.0), (ah as f64 - 90.0).max(1.0));
        let box_px = (chars as f64 * 7.0 + 50.0, labels.len() as f64 * 17.0 + 25.0);
        let fraction = ((box_px.0 / w).min(1.0), (box_px.1 / h).min(0.5));
        let (position, hidden) = legend_corner(panel, (x0, x1), (y0, y1), fraction);
        legend_position = position;
        if hidden > 0 && panel.y_range.is_none() {
            y1 += (y1 - y0) * fraction.1 / (1.0 - fraction.1);
            legend_position = SeriesLabelPosition::UpperRight;
        }
    }
    let y1 = y1;
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    let (xs, ys) = (panel.x_scale, panel.y_scale);
    chart
        .configure_mesh()
        .x_desc(panel.x_label.as_str())
        .y_desc(panel.y_label.as_str())
        .x_label_formatter(&|v| tick_label(*v, xs, x0, x1))
        .y_label_formatter(&|v| tick_label(*v, ys, y0, y1))
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 14))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    let mut any_label = false;
    for s in &panel.series {
        let color = PALETTE[s.color % PALETTE.len()];
        let pts: Vec<(f64, f64)> =
            s.x.iter()
                .zip(&s.y)
                .filter_map(|(x, y)| Some((transform(*x, xs)?, transform(*y, ys)?)))
                .collect();
        let legend_color = color;
        match s.style {
            Style::Line => {
                let anno = chart.draw_series(LineSeries::new(pts, color.stroke_width(2)))?;
                if !s.label.is_empty() {
                    anno.label(s.label.as_str()).legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 18, y)], legend_color.stroke_width(2))
                    });
                    any_label = true;
                }
            }
            Style::Dashed => {
                let anno =
                    chart.draw_series(DashedLineSeries::new(pts, 8, 5, color.stroke_width(2)))?;
                if !s.label.is_empty() {
                    anno.label(s.label.as_str()).legend(move |(x, y)| {
                        EmptyElement::at((x, y))
                            + PathElement::new(vec![(0, 0), (7, 0)], legend_color.stroke_width(2))
                            + PathElement::new(vec![(11, 0), (18, 0)], legend_color.stroke_width(2))
                    });
                    any_label = true;
                }
            }
            Style::Points => {
                let anno = chart
                    .draw_series(pts.into_iter().map(|p| Circle::new(p, 3, color.filled())))?;
                if !s.label.is_empty() {
                    anno.label(s.label.as_str())
                        .legend(move |(x, y)| Circle::new((x + 9, y), 3, legend_color.filled()));
                    any_label = true;
                }
            }
        }
    }
    if any_label {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(180, 180, 180))
            .label_font(("sans-serif", 13))
            .position(legend_position)
            .draw()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tick_labels_are_plain_where_they_can_be() {
        // Round-off at zero on a symmetric axis prints as 0, not -5.6e-17.
        assert_eq!(tick_label(-5.6e-17, Scale::Linear, -0.08, 0.08), "0");
        assert_eq!(tick_label(0.02, Scale::Linear, -0.08, 0.08), "0.02");
        // A log axis within 1e-3..1e5 reads in plain decimals, three significant digits.
        let log = |v: f64| v.log10();
        assert_eq!(
            tick_label(log(10f64.powf(0.2)), Scale::Log10, 0.0, 1.3),
            "1.58"
        );
        assert_eq!(
            tick_label(log(0.316227766), Scale::Log10, -3.0, 0.0),
            "0.316"
        );
        assert_eq!(tick_label(log(1e4), Scale::Log10, -1.0, 4.5), "10000");
        assert_eq!(tick_label(log(0.001), Scale::Log10, -3.0, 0.0), "0.001");
        // Beyond it, scientific throughout.
        assert_eq!(tick_label(-5.0, Scale::Log10, -8.0, -2.0), "1e-5");
        assert_eq!(tick_label(log(0.01), Scale::Log10, -8.0, -2.0), "1e-2");
    }

    #[test]
    fn legend_goes_where_it_hides_no_data() {
        // A rising line fills the upper right and the lower left.
        let x: Vec<f64> = (0..=100).map(f64::from).collect();
        let rising = Panel::new("t", "x", "y").with(Series::line("a", x.clone(), x.clone(), 0));
        let (position, hidden) = legend_corner(&rising, (0.0, 100.0), (0.0, 100.0), (0.3, 0.2));
        assert!(matches!(position, SeriesLabelPosition::UpperLeft));
        assert_eq!(hidden, 0);
        // A line along the top leaves the lower right free.
        let top = Panel::new("t", "x", "y").with(Series::line("a", x, vec![95.0; 101], 0));
        let (position, hidden) = legend_corner(&top, (0.0, 100.0), (0.0, 100.0), (0.3, 0.2));
        assert!(matches!(position, SeriesLabelPosition::LowerRight));
        assert_eq!(hidden, 0);
        // A sparse line crossing a corner counts as hiding data there.
        let sparse = Panel::new("t", "x", "y").with(Series::line(
            "a",
            vec![0.0, 100.0],
            vec![100.0, 100.0],
            0,
        ));
        let (position, _) = legend_corner(&sparse, (0.0, 100.0), (0.0, 100.0), (0.3, 0.2));
        assert!(matches!(position, SeriesLabelPosition::LowerRight));
    }

    #[test]
    fn draws_linear_and_log_panels_to_png() {
        let dir = std::env::temp_dir().join(format!("fastemu-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.png");
        let x: Vec<f64> = (1..200).map(|i| i as f64).collect();
        let y: Vec<f64> = x.iter().map(|v| 1.0 / v).collect();
        let p1 =
            Panel::new("linear", "x (s)", "y (m)").with(Series::line("a", x.clone(), y.clone(), 0));
        let p2 = Panel::new("log", "f (Hz)", "c (N s/m)")
            .log_x()
            .log_y()
            .with(Series::points("b", x, y, 1));
        draw_png(&path, 800, 400, 2, &[p1, p2]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        assert!(
            bytes.len() > 5_000,
            "a plot with text and lines is not a few bytes"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
