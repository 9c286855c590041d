//! Figures: a grid of panels of line series, or a bar chart, written as PNG and SVG.

use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// Line and bar colours in MATLAB's default order (`lines`), which the bench engineers know; on
/// white each is legible (plotters' `Palette99` put a pale yellow third).
const SERIES_COLORS: [RGBColor; 7] = [
    RGBColor(0, 114, 189),
    RGBColor(217, 83, 25),
    RGBColor(237, 177, 32),
    RGBColor(126, 47, 142),
    RGBColor(119, 172, 48),
    RGBColor(77, 190, 238),
    RGBColor(162, 20, 47),
];

/// The colour of the `i`-th series or bar (the palette repeats after seven).
fn series_color(i: usize) -> RGBAColor {
    SERIES_COLORS[i % SERIES_COLORS.len()].to_rgba()
}

/// Why a figure could not be written, named with its file.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// Plotting failed (the backend's error as the source).
    #[error("{path}")]
    Draw {
        /// The file.
        path: PathBuf,
        /// The plotting library's error.
        source: DrawError,
    },
    /// The rendered file could not be renamed into place.
    #[error("{path}")]
    Rename {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

/// A plotting backend's error.
pub type DrawError = Box<dyn std::error::Error + Send + Sync>;

/// One line.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// x values.
    pub x: Vec<f64>,
    /// y values.
    pub y: Vec<f64>,
}

/// One panel.
#[derive(Debug, Clone)]
pub struct Panel {
    /// Caption.
    pub title: String,
    /// x-axis label with unit.
    pub x_label: String,
    /// y-axis label with unit.
    pub y_label: String,
    /// Lines.
    pub series: Vec<Series>,
}

/// A figure: panels laid out in `cols` columns.
#[derive(Debug, Clone)]
pub struct Figure {
    /// File stem (`fig17-test3-p2`).
    pub name: String,
    /// Title on top.
    pub title: String,
    /// Panels.
    pub panels: Vec<Panel>,
    /// Columns.
    pub cols: usize,
}

static FONT: Once = Once::new();

fn register_font() {
    FONT.call_once(|| {
        // The dejavu crate ships the font, so no system font is needed. Registration only fails
        // on corrupt font bytes, which the crate's own tests exclude.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// Keeps at most ~`max` points, preserving each bucket's min and max (peaks stay visible).
fn decimate(x: &[f64], y: &[f64], max: usize) -> Vec<(f64, f64)> {
    let n = x.len().min(y.len());
    if n <= max {
        return x.iter().zip(y).map(|(a, b)| (*a, *b)).collect();
    }
    let bucket = n.div_ceil(max / 2);
    let mut out = Vec::with_capacity(max + 2);
    for start in (0..n).step_by(bucket) {
        let end = (start + bucket).min(n);
        let (mut imin, mut imax) = (start, start);
        for i in start..end {
            if y[i] < y[imin] {
                imin = i;
            }
            if y[i] > y[imax] {
                imax = i;
            }
        }
        let (a, b) = if imin < imax {
            (imin, imax)
        } else {
            (imax, imin)
        };
        out.push((x[a], y[a]));
        if b != a {
            out.push((x[b], y[b]));
        }
    }
    out
}

fn bounds(p: &Panel) -> ((f64, f64), (f64, f64)) {
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for s in &p.series {
        for (x, y) in s.x.iter().zip(&s.y) {
            if x.is_finite() && y.is_finite() {
                x0 = x0.min(*x);
                x1 = x1.max(*x);
                y0 = y0.min(*y);
                y1 = y1.max(*y);
            }
        }
    }
    if !x0.is_finite() {
        return ((0.0, 1.0), (0.0, 1.0));
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    let pad = ((y1 - y0) * 0.05).max(1e-9 + y1.abs() * 1e-3);
    ((x0, x1), (y0 - pad, y1 + pad))
}

/// Draws one panel with lines `width` px wide: 1 on the bitmap backend, whose wider lines are
/// rasterised with spikes and gaps at steep turns (stray strokes across neighbouring panels).
fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    p: &Panel,
    width: u32,
) -> Result<(), DrawError>
where
    DB::ErrorType: 'static,
{
    let ((x0, x1), (y0, y1)) = bounds(p);
    let legend = p.series.len() > 1 || p.series.first().is_some_and(|s| !s.label.is_empty());
    // Headroom for the legend, so it sits above the data instead of on it: one line of it is
    // ≈ 6 % of the panel's height.
    let y1 = if legend {
        y1 + (y1 - y0) * (0.08 + 0.07 * p.series.len() as f64)
    } else {
        y1
    };
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, ("sans-serif", 18))
        .margin(8)
        .margin_right(34)
        .x_label_area_size(38)
        .y_label_area_size(62)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    chart
        .configure_mesh()
        .x_desc(&p.x_label)
        .y_desc(&p.y_label)
        .label_style(("sans-serif", 13))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (i, s) in p.series.iter().enumerate() {
        let color = series_color(i);
        let pts = decimate(&s.x, &s.y, 4000);
        chart
            .draw_series(LineSeries::new(pts, color.stroke_width(width)))?
            .label(&s.label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    if legend {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.3))
            .label_font(("sans-serif", 12))
            .position(SeriesLabelPosition::UpperRight)
            .draw()?;
    }
    Ok(())
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    fig: &Figure,
    width: u32,
) -> Result<(), DrawError>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let root = root.titled(&fig.title, ("sans-serif", 22))?;
    let cols = fig.cols.max(1);
    let rows = fig.panels.len().div_ceil(cols).max(1);
    let areas = root.split_evenly((rows, cols));
    for (area, p) in areas.iter().zip(&fig.panels) {
        draw_panel(area, p, width)?;
    }
    Ok(root.present()?)
}

/// Line width of the data in the PNG (see [`draw_panel`]) and in the SVG.
const PNG_LINE_PX: u32 = 1;
const SVG_LINE_PX: u32 = 2;

impl Figure {
    /// Size in pixels: 560 × 380 per panel and 60 for the title.
    fn size(&self) -> (u32, u32) {
        let cols = self.cols.max(1);
        let rows = self.panels.len().div_ceil(cols).max(1);
        (560 * cols as u32, 60 + 380 * rows as u32)
    }

    /// Writes `<dir>/<name>.png` and `.svg`; returns the PNG path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf, PlotError> {
        write_both(self, dir)
    }
}

/// What [`write_both`] renders: a size and a drawing on any backend.
pub trait Render {
    /// File stem.
    fn name(&self) -> &str;
    /// Size in pixels.
    fn size(&self) -> (u32, u32);
    /// Draws it on `root`, data lines `width` px wide.
    fn render<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, Shift>,
        width: u32,
    ) -> Result<(), DrawError>
    where
        DB::ErrorType: 'static;
}

impl Render for Figure {
    fn name(&self) -> &str {
        &self.name
    }
    fn size(&self) -> (u32, u32) {
        Figure::size(self)
    }
    fn render<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, Shift>,
        width: u32,
    ) -> Result<(), DrawError>
    where
        DB::ErrorType: 'static,
    {
        draw(root, self, width)
    }
}

/// Writes `<dir>/<name>.png` and `.svg`, rendered to temporary names and renamed, so a failed
/// run leaves no half-written figure; returns the PNG path.
pub fn write_both<R: Render>(fig: &R, dir: &Path) -> Result<PathBuf, PlotError> {
    register_font();
    let size = fig.size();
    let name = fig.name();
    let png = dir.join(format!("{name}.png"));
    let svg = dir.join(format!("{name}.svg"));
    let png_tmp = dir.join(format!(".{name}.tmp.png"));
    let svg_tmp = dir.join(format!(".{name}.tmp.svg"));
    fig.render(
        BitMapBackend::new(&png_tmp, size).into_drawing_area(),
        PNG_LINE_PX,
    )
    .map_err(|source| PlotError::Draw {
        path: png.clone(),
        source,
    })?;
    fig.render(
        SVGBackend::new(&svg_tmp, size).into_drawing_area(),
        SVG_LINE_PX,
    )
    .map_err(|source| PlotError::Draw {
        path: svg.clone(),
        source,
    })?;
    std::fs::rename(&png_tmp, &png).map_err(|source| PlotError::Rename {
        path: png.clone(),
        source,
    })?;
    std::fs::rename(&svg_tmp, &svg).map_err(|source| PlotError::Rename {
        path: svg.clone(),
        source,
    })?;
    Ok(png)
}

/// Horizontal bars with their values written beside them (a loss breakdown).
#[derive(Debug, Clone)]
pub struct BarChart {
    /// File stem.
    pub name: String,
    /// Title on top.
    pub title: String,
    /// Axis label with unit.
    pub x_label: String,
    /// (label, value), drawn top to bottom.
    pub bars: Vec<(String, f64)>,
    /// How a value is written beside its bar (`"{:.1} W"`-like, applied by the caller).
    pub value_text: Vec<String>,
}

impl BarChart {
    /// Writes `<dir>/<name>.png` and `.svg`; returns the PNG path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf, PlotError> {
        write_both(self, dir)
    }
}

impl Render for BarChart {
    fn name(&self) -> &str {
        &self.name
    }
    fn size(&self) -> (u32, u32) {
        (900, 120 + 42 * self.bars.len().max(1) as u32)
    }
    fn render<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, Shift>,
        _width: u32,
    ) -> Result<(), DrawError>
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE)?;
        let root = root.titled(&self.title, ("sans-serif", 20))?;
        let n = self.bars.len().max(1);
        let (lo, hi) = self
            .bars
            .iter()
            .fold((0.0f64, 0.0f64), |(a, b), (_, v)| (a.min(*v), b.max(*v)));
        // Room on the right for the value texts.
        let span = (hi - lo).max(1e-9);
        let (x0, x1) = (lo - 0.02 * span, hi + 0.28 * span);
        let labels: Vec<String> = self.bars.iter().map(|b| b.0.clone()).collect();
        let mut chart = ChartBuilder::on(&root)
            .margin(10)
            .margin_right(24)
            .x_label_area_size(40)
            .y_label_area_size(230)
            .build_cartesian_2d(x0..x1, -0.5..(n as f64 - 0.5))?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .x_desc(&self.x_label)
            .y_labels(n)
            .y_label_formatter(&|y: &f64| {
                let i = y.round();
                // Bars run top to bottom: row i from the top sits at n − 1 − i.
                let k = n as f64 - 1.0 - i;
                if (y - i).abs() < 1e-6 && k >= 0.0 && (k as usize) < labels.len() {
                    labels[k as usize].clone()
                } else {
                    String::new()
                }
            })
            .label_style(("sans-serif", 14))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        for (i, (_, v)) in self.bars.iter().enumerate() {
            let y = (n - 1 - i) as f64;
            let color = series_color(i);
            chart.draw_series(std::iter::once(Rectangle::new(
                [(0.0, y - 0.34), (*v, y + 0.34)],
                color.filled(),
            )))?;
            if let Some(text) = self.value_text.get(i) {
                chart.draw_series(std::iter::once(Text::new(
                    text.clone(),
                    (v.max(0.0) + 0.01 * span, y + 0.15),
                    ("sans-serif", 14),
                )))?;
            }
        }
        Ok(root.present()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The figure as RGB pixels (what the PNG holds), lines `width` px wide.
    fn pixels(fig: &Figure, width: u32) -> (Vec<u8>, (u32, u32)) {
        register_font();
        let size = fig.size();
        let mut buf = vec![0u8; (size.0 * size.1 * 3) as usize];
        draw(
            BitMapBackend::with_buffer(&mut buf, size).into_drawing_area(),
            fig,
            width,
        )
        .unwrap();
        (buf, size)
    }

    /// Pixels of the first series' colour outside the first panel's cell (the left column
    /// below the title): strokes that escaped their panel.
    fn stray_pixels(fig: &Figure, width: u32) -> usize {
        let (buf, (w, h)) = pixels(fig, width);
        let c = series_color(0);
        let cell_w = w / fig.cols.max(1) as u32;
        let (title_h, cell_h) = (60, 380);
        let mut n = 0;
        for y in 0..h {
            for x in 0..w {
                let inside = x < cell_w && y >= title_h && y < title_h + cell_h;
                let k = ((y * w + x) * 3) as usize;
                if !inside && buf[k] == c.0 && buf[k + 1] == c.1 && buf[k + 2] == c.2 {
                    n += 1;
                }
            }
        }
        n
    }

    /// The PNG artefact of issue 21: with lines 2 px wide, plotters' bitmap backend drew
    /// strokes across the neighbouring panels and the titles at the steep turns of a noisy
    /// trace. At the width used for the PNG, no pixel of a panel's data lies outside it.
    #[test]
    fn png_lines_stay_inside_their_panel() {
        let n = 3000;
        let x: Vec<f64> = (0..n).map(|k| k as f64 * 0.01).collect();
        // A noisy, steep trace: alternate ±1 with a slow drift (like a pressure with sensor
        // noise at 30 s on a 560 px panel).
        let y: Vec<f64> = (0..n)
            .map(|k| (k as f64 * 0.003).sin() * 50.0 + if k % 2 == 0 { 8.0 } else { -8.0 })
            .collect();
        let quiet = Panel {
            title: "neighbour".into(),
            x_label: "time (s)".into(),
            y_label: "y".into(),
            series: vec![],
        };
        let fig = Figure {
            name: "stray".into(),
            title: "stray strokes".into(),
            cols: 2,
            panels: vec![
                Panel {
                    title: "noisy".into(),
                    x_label: "time (s)".into(),
                    y_label: "P2 (bar)".into(),
                    series: vec![Series {
                        label: String::new(),
                        x,
                        y,
                    }],
                },
                quiet.clone(),
                quiet.clone(),
                quiet,
            ],
        };
        let stray = stray_pixels(&fig, PNG_LINE_PX);
        println!(
            "stray pixels: {stray} at {PNG_LINE_PX} px, {} at 2 px",
            stray_pixels(&fig, 2)
        );
        assert_eq!(stray, 0);
    }

    #[test]
    fn decimation_keeps_extremes() {
        let x: Vec<f64> = (0..100_000).map(|k| k as f64).collect();
        let mut y = vec![0.0; 100_000];
        y[54_321] = 7.0;
        y[12_345] = -3.0;
        let d = decimate(&x, &y, 1000);
        assert!(d.len() <= 1002);
        assert!(d.iter().any(|p| p.1 == 7.0) && d.iter().any(|p| p.1 == -3.0));
    }

    #[test]
    fn figure_writes_png_and_svg() {
        let dir = std::env::temp_dir().join(format!("pto-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let fig = Figure {
            name: "t".into(),
            title: "test".into(),
            cols: 2,
            panels: vec![
                Panel {
                    title: "a".into(),
                    x_label: "time (s)".into(),
                    y_label: "P2 (bar)".into(),
                    series: vec![Series {
                        label: "x".into(),
                        x: vec![0.0, 1.0, 2.0],
                        y: vec![1.0, 3.0, 2.0],
                    }],
                };
                3
            ],
        };
        let png = fig.write(&dir).unwrap();
        assert!(std::fs::metadata(&png).unwrap().len() > 1000);
        assert!(std::fs::metadata(dir.join("t.svg")).unwrap().len() > 1000);
    }
}
