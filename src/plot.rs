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

fn tick_label(v: f64, scale: Scale) -> String {
    match scale {
        Scale::Linear => {
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
            if (v - v.round()).abs() < 1e-9 {
                format!("1e{}", v.round() as i64)
            } else {
                format!("{p:.2e}")
            }
        }
    }
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
    let (y0, y1) = range_of(panel, false);
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
        .x_label_formatter(&|v| tick_label(*v, xs))
        .y_label_formatter(&|v| tick_label(*v, ys))
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
                        PathElement::new(vec![(x, y), (x + 18, y)], legend_color.stroke_width(1))
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
            .position(SeriesLabelPosition::UpperRight)
            .draw()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
