//! The paper's Figures 10–19 (and the experimental runs) rebuilt from the built-in scenarios.

use crate::paper::Results;
use crate::plot::{BarChart, Figure, Panel, Series};
use crate::sim::bench::{BAR, LPM, RPM};
use crate::sim::power::Power;
use crate::sim::scenario::{BLOCKED_APERTURES, SETS, TEST3_APERTURES};
use crate::sim::trace::Trace;

/// Which trace column a series shows, with its display scale.
#[derive(Clone, Copy)]
enum Col {
    P2,
    Lp,
    Inj,
    Motor,
    Speed,
    Torque,
}

impl Col {
    fn get(self, t: &Trace, k: usize) -> f64 {
        match self {
            Col::P2 => t.p2_pa[k] / BAR,
            Col::Lp => t.lp_pa[k] / BAR,
            Col::Inj => t.q_inj_m3_s[k] * LPM,
            Col::Motor => t.q_motor_m3_s[k] * LPM,
            Col::Speed => t.omega_rad_s[k] * RPM,
            Col::Torque => t.torque_nm[k],
        }
    }

    fn label(self) -> &'static str {
        match self {
            Col::P2 => "P2 (bar)",
            Col::Lp => "LP (bar)",
            Col::Inj => "flow injected into HP (L/min)",
            Col::Motor => "motor flow (L/min)",
            Col::Speed => "motor speed (rpm)",
            Col::Torque => "restraining torque (N·m)",
        }
    }
}

/// A series of `col` from scenario `name` over `[from, to]` (negative `from`: the last |from| s).
fn series(r: &Results, name: &str, label: &str, col: Col, from: f64, to: f64) -> Option<Series> {
    let t = r.trace(name)?;
    let end = *t.t_s.last()?;
    let (a, b) = if from < 0.0 {
        (end + from, end)
    } else {
        (from, to.min(end))
    };
    let w = t.window(a, b);
    Some(Series {
        label: label.into(),
        x: t.t_s[w.clone()].to_vec(),
        y: w.map(|k| col.get(t, k)).collect(),
    })
}

fn panel(title: String, col: Col, series: Vec<Series>) -> Panel {
    Panel {
        title,
        x_label: "time (s)".into(),
        y_label: col.label().into(),
        series,
    }
}

fn set_label(tag: &str) -> String {
    SETS.iter()
        .find(|s| s.0 == tag)
        .map(|s| s.1.join("+"))
        .unwrap_or_else(|| "HC3.1+HC3.3".into())
}

/// Panels of one config with every cylinder set overlaid.
fn per_config(
    r: &Results,
    group: &str,
    configs: &[usize],
    col: Col,
    from: f64,
    to: f64,
) -> Vec<Panel> {
    configs
        .iter()
        .map(|c| {
            let s = SETS
                .iter()
                .filter_map(|(tag, _)| {
                    series(
                        r,
                        &format!("{group}-cfg{c}-{tag}"),
                        &set_label(tag),
                        col,
                        from,
                        to,
                    )
                })
                .collect();
            panel(format!("Config {c}"), col, s)
        })
        .collect()
}

/// Every figure that has data in `r`.
pub fn all(r: &Results) -> Vec<Figure> {
    let mut figs = Vec::new();
    let mut f10 = per_config(r, "test1", &[1, 3], Col::Inj, -20.0, 0.0);
    f10.extend(per_config(r, "test1", &[1, 3], Col::Motor, -20.0, 0.0));
    figs.push(Figure {
        name: "fig10-test1-flows".into(),
        title: "Test I (valve 100 %): flow injected into HP (top) and motor flow (bottom), Config 1 | Config 3".into(),
        panels: f10,
        cols: 2,
    });
    figs.push(Figure {
        name: "fig11-test1-motor-speed".into(),
        title: "Test I: motor speed, Config 1 | 2 | 3".into(),
        panels: per_config(r, "test1", &[1, 2, 3], Col::Speed, -20.0, 0.0),
        cols: 3,
    });
    figs.push(Figure {
        name: "fig12-test1-p2".into(),
        title: "Test I: HP accumulator pressure, Config 1 | 2 | 3".into(),
        panels: per_config(r, "test1", &[1, 2, 3], Col::P2, -20.0, 0.0),
        cols: 3,
    });
    let f13 = SETS
        .iter()
        .map(|(tag, _)| {
            let s = (1..=4)
                .filter_map(|c| {
                    series(
                        r,
                        &format!("test2-cfg{c}-{tag}"),
                        &format!("Config {c}"),
                        Col::P2,
                        0.0,
                        f64::INFINITY,
                    )
                })
                .collect();
            panel(set_label(tag), Col::P2, s)
        })
        .collect();
    figs.push(Figure {
        name: "fig13-test2-p2-by-config".into(),
        title: "Test II (valve closed): P2 by geometrical configuration, per cylinder set".into(),
        panels: f13,
        cols: 2,
    });
    figs.push(Figure {
        name: "fig14-test2-p2-by-cylinders".into(),
        title: "Test II (valve closed): P2 by cylinders on duty, per configuration".into(),
        panels: per_config(r, "test2", &[1, 2, 3, 4], Col::P2, 0.0, f64::INFINITY),
        cols: 2,
    });
    figs.push(Figure {
        name: "fig15-torque".into(),
        title: "Restraining torque (valve closed near 100 bar), Config 1 | 2 | 3".into(),
        panels: per_config(r, "torque", &[1, 2, 3], Col::Torque, -20.0, 0.0),
        cols: 3,
    });
    figs.push(Figure {
        name: "fig16-torque-p2".into(),
        title: "P2 during the torque runs, Config 1 | 2 | 3".into(),
        panels: per_config(r, "torque", &[1, 2, 3], Col::P2, 0.0, f64::INFINITY),
        cols: 3,
    });
    let ap = |col: Col, from: f64, to: f64| -> Vec<Series> {
        TEST3_APERTURES
            .iter()
            .filter_map(|a| series(r, &format!("test3-ap{a}"), &format!("{a} %"), col, from, to))
            .collect()
    };
    figs.push(Figure {
        name: "fig17-test3-p2".into(),
        title: "Test III: HC3.1 + HC3.4, Config 1, valve opens at 100 bar".into(),
        panels: vec![
            panel("P2 by aperture".into(), Col::P2, ap(Col::P2, 0.0, 400.0)),
            panel("LP by aperture".into(), Col::Lp, ap(Col::Lp, 0.0, 400.0)),
        ],
        cols: 2,
    });
    figs.push(Figure {
        name: "fig18-test3-output".into(),
        title: "Test III, 200–400 s: P2, motor flow, motor speed".into(),
        panels: vec![
            panel("P2".into(), Col::P2, ap(Col::P2, 200.0, 400.0)),
            panel(
                "motor flow".into(),
                Col::Motor,
                ap(Col::Motor, 200.0, 400.0),
            ),
            panel(
                "motor speed".into(),
                Col::Speed,
                ap(Col::Speed, 200.0, 400.0),
            ),
        ],
        cols: 3,
    });
    let bl = |col: Col| -> Vec<Series> {
        BLOCKED_APERTURES
            .iter()
            .filter_map(|a| {
                series(
                    r,
                    &format!("blocked-ap{a}"),
                    &format!("{a} %"),
                    col,
                    0.0,
                    f64::INFINITY,
                )
            })
            .collect()
    };
    figs.push(Figure {
        name: "fig19-blocked-input".into(),
        title: "Blocked input from 102 bar: autonomy of the HP accumulator by aperture".into(),
        panels: vec![
            panel("P2".into(), Col::P2, bl(Col::P2)),
            panel("motor flow".into(), Col::Motor, bl(Col::Motor)),
            panel("motor speed".into(), Col::Speed, bl(Col::Speed)),
        ],
        cols: 3,
    });
    let exp = |names: &[&str], col: Col| -> Vec<Series> {
        names
            .iter()
            .filter_map(|n| series(r, n, n, col, 0.0, f64::INFINITY))
            .collect()
    };
    let charges = [
        "exp-charge-64.5",
        "exp-charge-67.2",
        "exp-charge-72",
        "exp-9pct-101.5",
    ];
    let discharges = ["exp-discharge-102", "exp-discharge-84", "exp-discharge-71"];
    figs.push(Figure {
        name: "fig22-29-experimental-runs".into(),
        title: "Experimental runs of Section 4.2 (simulated): charging, 9 % aperture, discharges"
            .into(),
        panels: vec![
            panel(
                "charging / 9 % runs: P2".into(),
                Col::P2,
                exp(&charges, Col::P2),
            ),
            panel("discharges: P2".into(), Col::P2, exp(&discharges, Col::P2)),
            panel(
                "discharges: motor speed".into(),
                Col::Speed,
                exp(&discharges, Col::Speed),
            ),
        ],
        cols: 3,
    });
    figs.retain(|f| f.panels.iter().any(|p| !p.series.is_empty()));
    figs
}

/// The standard figure of a single run: P2/LP, flows, motor speed, torque, the valve aperture
/// and the chamber pressures of the cylinders on duty (`on_duty`, with their names).
pub fn single(name: &str, t: &Trace, on_duty: &[(usize, String)]) -> Figure {
    let s = |label: &str, col: Col| Series {
        label: label.into(),
        x: t.t_s.clone(),
        y: (0..t.len()).map(|k| col.get(t, k)).collect(),
    };
    Figure {
        name: name.into(),
        title: format!("{name}: pressures, flows, motor speed and restraining torque"),
        panels: vec![
            Panel {
                title: "pressures".into(),
                x_label: "time (s)".into(),
                y_label: "pressure (bar)".into(),
                series: vec![s("P2", Col::P2), s("LP", Col::Lp)],
            },
            Panel {
                title: "flows".into(),
                x_label: "time (s)".into(),
                y_label: "flow (L/min)".into(),
                series: vec![s("injected into HP", Col::Inj), s("motor", Col::Motor)],
            },
            panel(
                "motor speed".into(),
                Col::Speed,
                vec![s("motor", Col::Speed)],
            ),
            panel(
                "restraining torque".into(),
                Col::Torque,
                vec![s("shaft", Col::Torque)],
            ),
            Panel {
                title: "control valve".into(),
                x_label: "time (s)".into(),
                y_label: "aperture (%)".into(),
                series: vec![Series {
                    label: "aperture".into(),
                    x: t.t_s.clone(),
                    y: t.aperture_pct.clone(),
                }],
            },
            Panel {
                title: "chamber pressures (cylinders on duty)".into(),
                x_label: "time (s)".into(),
                y_label: "pressure (bar)".into(),
                series: on_duty
                    .iter()
                    .flat_map(|(i, n)| {
                        [(&t.p_cap_pa[*i], "cap"), (&t.p_rod_pa[*i], "rod")].map(|(p, side)| {
                            Series {
                                label: format!("{n} {side}"),
                                x: t.t_s.clone(),
                                y: p.iter().map(|v| v / BAR).collect(),
                            }
                        })
                    })
                    .collect(),
            },
        ],
        cols: 2,
    }
}

/// Running mean of `y` over `t` (trapezoidal), from the first sample.
fn running_mean(t: &[f64], y: &[f64]) -> Vec<f64> {
    let mut out = Vec::with_capacity(y.len());
    let mut area = 0.0;
    for k in 0..y.len() {
        if k > 0 {
            area += 0.5 * (y[k] + y[k - 1]) * (t[k] - t[k - 1]);
        }
        let span = t[k] - t[0];
        out.push(if span > 0.0 { area / span } else { y[k] });
    }
    out
}

/// `<name>-power`: the input, valve-hydraulic and generator power of a run, instantaneous and
/// as running means.
pub fn power_traces(name: &str, t: &Trace) -> Figure {
    let cols: [(&str, &Vec<f64>); 3] = [
        ("shaft input", &t.input_power_w),
        ("hydraulic at the valve (P2·Q)", &t.valve_power_w),
        ("generator", &t.generator_power_w),
    ];
    let panel = |title: &str, mean: bool| Panel {
        title: title.into(),
        x_label: "time (s)".into(),
        y_label: "power (W)".into(),
        series: cols
            .iter()
            .map(|(label, y)| Series {
                label: (*label).into(),
                x: t.t_s.clone(),
                y: if mean {
                    running_mean(&t.t_s, y)
                } else {
                    (*y).clone()
                },
            })
            .collect(),
    };
    Figure {
        name: format!("{name}-power"),
        title: format!("{name}: power along the path from the shaft to the generator"),
        panels: vec![
            panel("instantaneous", false),
            panel("mean since the start", true),
        ],
        cols: 2,
    }
}

/// `<name>-losses`: where the mean input power of a run goes, W and % of the input.
pub fn loss_breakdown(name: &str, p: &Power) -> BarChart {
    let mut bars = vec![("shaft input".to_string(), p.input_w)];
    bars.extend(p.losses.by_cause().iter().map(|(l, w)| (l.to_string(), *w)));
    bars.push(("into storage".into(), p.stored_w.total_w()));
    bars.push(("generator".into(), p.generator_w));
    let value_text = bars
        .iter()
        .map(|(_, w)| {
            if p.input_w > 0.0 {
                format!("{w:.1} W ({:.1} %)", 100.0 * w / p.input_w)
            } else {
                format!("{w:.1} W")
            }
        })
        .collect();
    let eff = crate::sim::power::percent_text(p.efficiency);
    BarChart {
        name: format!("{name}-losses"),
        title: format!(
            "{name}: mean power over {:.0} s; efficiency (generator / supplied) {eff}",
            p.duration_s
        ),
        x_label: "mean power (W)".into(),
        bars,
        value_text,
    }
}
