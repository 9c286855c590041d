//! Heat maps of a sweep: a metric over two axes, each cell the mean over the runs that share
//! its two values (the other axes averaged out, as the title says), PNG and SVG
//! (`plot::write_both`).

use super::expand::point_of;
use super::run::Status;
use super::store::Identity;
use super::table::{Cells, Table};
use crate::plot::{DrawError, Render};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// The metrics drawn: column and label with unit.
pub const METRICS: [(&str, &str); 4] = [
    ("efficiency_pct", "efficiency, generator / supplied (%)"),
    ("generator_power_w", "generator power (W)"),
    ("p2_mean_bar", "mean P2 (bar)"),
    ("time_at_relief_s", "time at the relief (s)"),
];

/// One heat map.
#[derive(Debug, Clone)]
pub struct HeatMap {
    /// File stem (`heatmap-efficiency_pct`).
    pub name: String,
    /// Title on top.
    pub title: String,
    /// How each cell was made (the axes averaged over, runs per cell).
    pub subtitle: String,
    /// The metric with its unit.
    pub metric: String,
    /// x axis (columns).
    pub x_label: String,
    /// y axis (rows).
    pub y_label: String,
    /// Column labels.
    pub x_ticks: Vec<String>,
    /// Row labels.
    pub y_ticks: Vec<String>,
    /// `cells[y][x]`: the mean, `None` where no run of the cell finished with the metric.
    pub cells: Vec<Vec<Option<f64>>>,
    /// Runs averaged in each cell, `counts[y][x]`: a cell over fewer than [`HeatMap::per_cell`]
    /// (failed runs, or runs without the metric) says so in its text.
    pub counts: Vec<Vec<usize>>,
    /// The runs each cell has in the matrix.
    pub per_cell: usize,
}

/// The heat maps of [`METRICS`] over axes `x` and `y` (indices into `identity.axes`) from a
/// table of the sweep's rows; failed runs are left out of the means.
pub fn heatmaps(identity: &Identity, table: &Table, (x, y): (usize, usize)) -> Vec<HeatMap> {
    let (ax, ay) = (&identity.axes[x], &identity.axes[y]);
    let (nx, ny) = (ax.values.len(), ay.values.len());
    let runs: Vec<usize> = match table.column("run").map(|c| &c.cells) {
        Some(Cells::U64(v)) => v.iter().map(|r| r.unwrap_or(0) as usize).collect(),
        _ => Vec::new(),
    };
    let ok: Vec<bool> = match table.column("status").map(|c| &c.cells) {
        Some(Cells::Str(v)) => v
            .iter()
            .map(|s| s.as_deref() != Some(Status::Failed.as_str()))
            .collect(),
        _ => vec![false; runs.len()],
    };
    let others: Vec<String> = identity
        .axes
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != x && *i != y)
        .map(|(_, a)| a.name())
        .collect();
    let per_cell = identity.keys.len() / (nx * ny).max(1);
    let failed = ok.iter().filter(|o| !**o).count();
    let subtitle = format!(
        "{}{}",
        if others.is_empty() {
            "one run a cell".to_string()
        } else {
            format!(
                "each cell the mean over {} ({per_cell} runs a cell)",
                others.join(", ")
            )
        },
        match failed {
            0 => String::new(),
            n => format!("; {n} failed runs left out"),
        }
    );
    METRICS
        .iter()
        .filter_map(|(col, label)| {
            let cells = table.column(col)?;
            let mut sum = vec![vec![(0.0, 0usize); nx]; ny];
            for (row, &run) in runs.iter().enumerate() {
                let (Some(v), true) = (cells.cells.number(row), ok[row] && run > 0) else {
                    continue;
                };
                let p = point_of(&identity.axes, run - 1);
                let s = &mut sum[p[y]][p[x]];
                s.0 += v;
                s.1 += 1;
            }
            Some(HeatMap {
                name: format!("heatmap-{col}"),
                title: format!("{}: {label}", identity.name),
                subtitle: subtitle.clone(),
                metric: label.to_string(),
                x_label: ax.name(),
                y_label: ay.name(),
                x_ticks: (0..nx).map(|i| ax.label(i)).collect(),
                y_ticks: (0..ny).map(|i| ay.label(i)).collect(),
                counts: sum
                    .iter()
                    .map(|r| r.iter().map(|c| c.1).collect())
                    .collect(),
                per_cell,
                cells: sum
                    .into_iter()
                    .map(|r| {
                        r.into_iter()
                            .map(|(s, n)| (n > 0).then(|| s / n as f64))
                            .collect()
                    })
                    .collect(),
            })
        })
        .collect()
}

/// Viridis, sampled at five points (perceptually uniform, readable in grey).
const VIRIDIS: [(u8, u8, u8); 5] = [
    (68, 1, 84),
    (59, 82, 139),
    (33, 145, 140),
    (94, 201, 98),
    (253, 231, 37),
];

/// The colour of `u` in [0, 1].
fn colour(u: f64) -> RGBColor {
    let u = if u.is_finite() {
        u.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let s = u * (VIRIDIS.len() - 1) as f64;
    let i = (s.floor() as usize).min(VIRIDIS.len() - 2);
    let f = s - i as f64;
    let mix = |a: u8, b: u8| (f64::from(a) + (f64::from(b) - f64::from(a)) * f).round() as u8;
    let (a, b) = (VIRIDIS[i], VIRIDIS[i + 1]);
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// A number for a cell: 4 significant digits.
fn cell_text(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    if !(1e-3..1e6).contains(&v.abs()) {
        return format!("{v:.3e}");
    }
    let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
    format!("{v:.digits$}")
}

impl HeatMap {
    /// The smallest and largest cell (0..1 if none).
    fn range(&self) -> (f64, f64) {
        let (lo, hi) = self
            .cells
            .iter()
            .flatten()
            .flatten()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(*v), hi.max(*v))
            });
        if !lo.is_finite() {
            (0.0, 1.0)
        } else if hi <= lo {
            (lo - 0.5, lo + 0.5)
        } else {
            (lo, hi)
        }
    }
}

impl Render for HeatMap {
    fn name(&self) -> &str {
        &self.name
    }

    fn size(&self) -> (u32, u32) {
        let nx = self.x_ticks.len() as u32;
        let ny = self.y_ticks.len() as u32;
        // Wide enough for the subtitle (≈ 7.5 px a character at its 15 px).
        let text = (self.subtitle.chars().count() as u32 * 15 / 2 + 80).min(2400);
        (
            (300 + 90 * nx).clamp(700, 1800).max(text),
            (200 + 48 * ny).clamp(480, 1200),
        )
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
        let root = root.titled(&self.title, ("sans-serif", 22))?;
        let (w, _) = root.dim_in_pixel();
        let (map, bar) = root.split_horizontally(w.saturating_sub(130));
        let (lo, hi) = self.range();
        let (nx, ny) = (self.x_ticks.len() as i32, self.y_ticks.len() as i32);
        let mut chart = ChartBuilder::on(&map)
            .caption(&self.subtitle, ("sans-serif", 15))
            .margin(10)
            .x_label_area_size(50)
            .y_label_area_size(110)
            // `0..n` segmented has a segment for every value of 0..=n: n − 1 is the last.
            .build_cartesian_2d(
                (0..(nx - 1).max(0)).into_segmented(),
                (0..(ny - 1).max(0)).into_segmented(),
            )?;
        let tick = |ticks: &[String], v: &SegmentValue<i32>| match v {
            SegmentValue::CenterOf(i) => ticks.get(*i as usize).cloned().unwrap_or_default(),
            _ => String::new(),
        };
        chart
            .configure_mesh()
            .disable_mesh()
            .x_labels(nx as usize + 1)
            .y_labels(ny as usize + 1)
            .x_label_formatter(&|v| tick(&self.x_ticks, v))
            .y_label_formatter(&|v| tick(&self.y_ticks, v))
            .x_desc(&self.x_label)
            .y_desc(&self.y_label)
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 15))
            .draw()?;
        let label_cells = nx <= 24 && ny <= 30;
        for (j, row) in self.cells.iter().enumerate() {
            for (i, v) in row.iter().enumerate() {
                let (i, j) = (i as i32, j as i32);
                let fill = v.map_or(RGBColor(210, 210, 210), |v| colour((v - lo) / (hi - lo)));
                chart.draw_series(std::iter::once(Rectangle::new(
                    [
                        (SegmentValue::Exact(i), SegmentValue::Exact(j)),
                        (SegmentValue::Exact(i + 1), SegmentValue::Exact(j + 1)),
                    ],
                    fill.filled(),
                )))?;
                if label_cells {
                    let dark = v.is_some_and(|v| (v - lo) / (hi - lo) < 0.6);
                    let style = TextStyle::from(("sans-serif", 13).into_font())
                        .color(if dark { &WHITE } else { &BLACK })
                        .pos(Pos::new(HPos::Center, VPos::Center));
                    let n = self.counts[j as usize][i as usize];
                    let text = match v {
                        None => "–".to_string(),
                        Some(v) if n < self.per_cell => {
                            format!("{} ({n}/{})", cell_text(*v), self.per_cell)
                        }
                        Some(v) => cell_text(*v),
                    };
                    chart.draw_series(std::iter::once(Text::new(
                        text,
                        (SegmentValue::CenterOf(i), SegmentValue::CenterOf(j)),
                        style,
                    )))?;
                }
            }
        }
        // The colour bar.
        let mut scale = ChartBuilder::on(&bar)
            .margin_top(40)
            .margin_bottom(60)
            .margin_right(10)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..1.0, lo..hi)?;
        scale
            .configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .y_desc(&self.metric)
            .label_style(("sans-serif", 12))
            .axis_desc_style(("sans-serif", 12))
            .draw()?;
        let steps = 64;
        scale.draw_series((0..steps).map(|k| {
            let a = lo + (hi - lo) * f64::from(k) / f64::from(steps);
            let b = lo + (hi - lo) * f64::from(k + 1) / f64::from(steps);
            Rectangle::new(
                [(0.0, a), (1.0, b)],
                colour((f64::from(k) + 0.5) / f64::from(steps)).filled(),
            )
        }))?;
        Ok(root.present()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sweep::run::{Figures, Row};
    use crate::sweep::{Axis, RunKey};

    fn figures(p2_mean_bar: f64) -> Figures {
        Figures {
            simulated_s: 1.0,
            steps: 1,
            p2_min_bar: 0.0,
            p2_mean_bar,
            p2_max_bar: 0.0,
            time_at_relief_s: 0.0,
            lp_min_bar: 0.0,
            lp_max_bar: 0.0,
            motor_speed_mean_rpm: 0.0,
            motor_speed_max_rpm: 0.0,
            motor_speed_std_rpm: 0.0,
            input_power_w: 1.0,
            pumped_power_w: 1.0,
            motor_shaft_power_w: 1.0,
            generator_power_w: 1.0,
            efficiency_pct: None,
            efficiency_with_storage_pct: None,
            losses_w: 0.0,
            relief_loss_w: 0.0,
            stored_w: 0.0,
            balance_worst_rel: 0.0,
        }
    }

    /// A cell is the mean over the other axes of the runs that share its two values; a failed
    /// run is left out, a cell with none is empty, a metric no run has (efficiency here) too.
    #[test]
    fn a_cell_is_the_mean_over_the_other_axes_without_failed_runs() {
        let axis = |f: &str, v: &[i64]| Axis {
            fields: vec![f.into()],
            values: v.iter().map(|x| vec![toml::Value::Integer(*x)]).collect(),
        };
        // x (2 values) × other (3 values) × y (2 values): run i has key i, P2 = i.
        let axes = vec![
            axis("x", &[1, 2]),
            axis("o", &[1, 2, 3]),
            axis("y", &[5, 6]),
        ];
        let keys: Vec<RunKey> = (0..12).map(RunKey).collect();
        let mut rows = std::collections::HashMap::new();
        for i in 0..12u64 {
            let failed = i == 1 || i == 3 || i == 5;
            rows.insert(
                RunKey(i),
                Row {
                    key: RunKey(i),
                    status: if failed { Status::Failed } else { Status::Ok },
                    figures: (!failed).then(|| figures(i as f64)),
                    error: failed.then(|| "x".into()),
                    wall_s: 0.0,
                },
            );
        }
        let identity = Identity {
            format: 1,
            name: "t".into(),
            matrix: "t.toml".into(),
            sweep_id: String::new(),
            scenario: "s".into(),
            bench: "b".into(),
            axes,
            keys,
            shard: None,
            heatmap: Some((0, 2)),
        };
        let t = Table::of_rows(&identity, &rows, &identity.indices());
        let maps = heatmaps(&identity, &t, (0, 2));
        let p2 = maps
            .iter()
            .find(|m| m.name == "heatmap-p2_mean_bar")
            .unwrap();
        // x = 1, y = 5: runs 0, 2, 4 → mean 2; x = 1, y = 6: runs 1, 3, 5 all failed → empty;
        // x = 2, y = 5: runs 6, 8, 10 → 8; x = 2, y = 6: runs 7, 9, 11 → 9.
        assert_eq!(
            p2.cells,
            vec![vec![Some(2.0), Some(8.0)], vec![None, Some(9.0)]]
        );
        assert_eq!(p2.x_ticks, ["1", "2"]);
        assert_eq!(p2.y_ticks, ["5", "6"]);
        assert!(
            p2.subtitle
                .contains("mean over o (3 runs a cell); 3 failed runs left out")
        );
        let eff = maps
            .iter()
            .find(|m| m.name == "heatmap-efficiency_pct")
            .unwrap();
        assert!(eff.cells.iter().flatten().all(Option::is_none));
    }
}
