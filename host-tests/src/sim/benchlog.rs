//! Bench logs: the CSV a bench engineer records and `pto fit` reads.
//!
//! Columns (header required, any order, extra columns ignored; units are part of the names):
//! `time_s, shaft_angle_deg, p2_bar, lp_bar, motor_rpm, aperture_pct, on_duty, config`.
//! `on_duty` is four characters `0`/`1` for HC3.1..HC3.4 (e.g. `1001`), `config` is 1..=4;
//! both must stay the same through a log. Errors name the file, the line and the column.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// One log.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchLog {
    /// Where it was read from (or will be written to).
    pub path: PathBuf,
    /// Time, s (strictly increasing).
    pub t: Vec<f64>,
    /// Shaft angle, deg.
    pub theta_deg: Vec<f64>,
    /// HP pressure, bar.
    pub p2_bar: Vec<f64>,
    /// LP pressure, bar.
    pub lp_bar: Vec<f64>,
    /// Motor speed, rpm.
    pub rpm: Vec<f64>,
    /// Commanded valve aperture, %.
    pub aperture_pct: Vec<f64>,
    /// Cylinders on duty, HC3.1..HC3.4.
    pub on_duty: [bool; 4],
    /// Geometry, 1..=4.
    pub config: usize,
}

/// A malformed log.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{file}{}: column `{column}`: {message}", line_part(*.line))]
pub struct LogError {
    /// File.
    pub file: String,
    /// 1-based line (1 = header); 0 for the file as a whole.
    pub line: usize,
    /// Column name.
    pub column: String,
    /// What is wrong.
    pub message: String,
}

/// `:line` for an error at a line, nothing for one about the whole file.
fn line_part(line: usize) -> String {
    if line == 0 {
        String::new()
    } else {
        format!(":{line}")
    }
}

/// (column, lowest allowed value, highest allowed value), in the column's unit.
const COLUMNS: [(&str, f64, f64); 6] = [
    ("time_s", f64::NEG_INFINITY, f64::INFINITY),
    ("shaft_angle_deg", -30.0, 30.0),
    ("p2_bar", -1.0, 400.0),
    ("lp_bar", -1.0, 100.0),
    ("motor_rpm", -100.0, 10_000.0),
    ("aperture_pct", 0.0, 100.0),
];

impl BenchLog {
    /// Reads and checks a log.
    pub fn read(path: &Path) -> Result<BenchLog, LogError> {
        let file = path.display().to_string();
        let err = |line: usize, column: &str, message: String| LogError {
            file: file.clone(),
            line,
            column: column.into(),
            message,
        };
        let mut rdr = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .from_path(path)
            .map_err(|e| err(0, "-", format!("cannot open: {e}")))?;
        let headers = rdr
            .headers()
            .map_err(|e| err(1, "-", e.to_string()))?
            .clone();
        let find = |name: &str| -> Result<usize, LogError> {
            if let Some(i) = headers.iter().position(|h| h == name) {
                return Ok(i);
            }
            // Same quantity with another unit: say so rather than "missing".
            let stem = name.rsplit_once('_').map_or(name, |(s, _)| s);
            let other = headers
                .iter()
                .find(|h| h.rsplit_once('_').is_some_and(|(s, _)| s == stem));
            Err(err(
                1,
                name,
                match other {
                    Some(h) => format!("found `{h}`: this column must be in the unit of `{name}`"),
                    None => format!(
                        "missing (have: {}; need: time_s, shaft_angle_deg, p2_bar, lp_bar, \
                         motor_rpm, aperture_pct, on_duty, config)",
                        headers.iter().collect::<Vec<_>>().join(", ")
                    ),
                },
            ))
        };
        let idx: Vec<usize> = COLUMNS
            .iter()
            .map(|(n, _, _)| find(n))
            .collect::<Result<_, _>>()?;
        let (i_duty, i_cfg) = (find("on_duty")?, find("config")?);
        let mut cols: [Vec<f64>; 6] = Default::default();
        let mut duty: Option<[bool; 4]> = None;
        let mut config: Option<usize> = None;
        for (k, rec) in rdr.records().enumerate() {
            let line = k + 2;
            let rec = rec.map_err(|e| err(line, "-", e.to_string()))?;
            for (c, ((name, lo, hi), &i)) in COLUMNS.iter().zip(&idx).enumerate() {
                let raw = rec.get(i).unwrap_or("");
                let v: f64 = raw
                    .parse()
                    .ok()
                    .filter(|v: &f64| v.is_finite())
                    .ok_or_else(|| err(line, name, format!("not a number: {raw:?}")))?;
                if v < *lo || v > *hi {
                    return Err(err(line, name, format!("{v} outside [{lo}, {hi}]")));
                }
                if c == 0
                    && let Some(&last) = cols[0].last()
                    && v <= last
                {
                    return Err(err(
                        line,
                        name,
                        format!("{v} s is not after {last} s (time must increase)"),
                    ));
                }
                cols[c].push(v);
            }
            let d = rec.get(i_duty).unwrap_or("");
            let mask: [bool; 4] = match d.as_bytes() {
                [a, b, c, e] if [a, b, c, e].iter().all(|x| **x == b'0' || **x == b'1') => {
                    [*a == b'1', *b == b'1', *c == b'1', *e == b'1']
                }
                _ => {
                    return Err(err(
                        line,
                        "on_duty",
                        format!("{d:?}: want four 0/1 characters for HC3.1..HC3.4, e.g. 1001"),
                    ));
                }
            };
            if duty.is_some_and(|m| m != mask) {
                return Err(err(
                    line,
                    "on_duty",
                    "changes within the log (split it where the duty changes)".into(),
                ));
            }
            duty = Some(mask);
            let c = rec.get(i_cfg).unwrap_or("");
            let cfg = c
                .parse::<usize>()
                .ok()
                .filter(|v| (1..=4).contains(v))
                .ok_or_else(|| err(line, "config", format!("{c:?}: want 1, 2, 3 or 4")))?;
            if config.is_some_and(|x| x != cfg) {
                return Err(err(
                    line,
                    "config",
                    "changes within the log (split it where the geometry changes)".into(),
                ));
            }
            config = Some(cfg);
        }
        if cols[0].len() < 10 {
            return Err(err(0, "time_s", "needs at least 10 samples".into()));
        }
        let on_duty = duty.unwrap_or_default();
        if !on_duty.iter().any(|b| *b) {
            return Err(err(2, "on_duty", "no cylinder on duty".into()));
        }
        let [t, theta_deg, p2, lp, rpm, aperture] = cols;
        Ok(BenchLog {
            path: path.to_path_buf(),
            t,
            theta_deg,
            p2_bar: p2,
            lp_bar: lp,
            rpm,
            aperture_pct: aperture,
            on_duty,
            config: config.unwrap_or(1),
        })
    }

    /// The CSV text.
    pub fn to_csv(&self) -> String {
        let mut s = String::from(
            "time_s,shaft_angle_deg,p2_bar,lp_bar,motor_rpm,aperture_pct,on_duty,config\n",
        );
        let duty: String = self
            .on_duty
            .iter()
            .map(|b| if *b { '1' } else { '0' })
            .collect();
        for i in 0..self.t.len() {
            let _ = writeln!(
                s,
                "{:.4},{:.4},{:.3},{:.3},{:.1},{:.2},{duty},{}",
                self.t[i],
                self.theta_deg[i],
                self.p2_bar[i],
                self.lp_bar[i],
                self.rpm[i],
                self.aperture_pct[i],
                self.config
            );
        }
        s
    }

    /// Writes the log (to a temporary name, then renamed: never half-written).
    pub fn write(&self) -> Result<(), crate::output::OutputError> {
        crate::output::write_atomic(&self.path, self.to_csv().as_bytes())
    }

    /// The valve schedule as (time from the log's start, aperture %) steps.
    pub fn valve_steps(&self) -> (Vec<f64>, Vec<f64>) {
        let t0 = self.t[0];
        let (mut ts, mut ap) = (vec![0.0], vec![self.aperture_pct[0]]);
        for i in 1..self.t.len() {
            if (self.aperture_pct[i] - *ap.last().unwrap_or(&0.0)).abs() > 1e-9 {
                ts.push(self.t[i] - t0);
                ap.push(self.aperture_pct[i]);
            }
        }
        (ts, ap)
    }

    /// Name for reports: the file stem.
    pub fn name(&self) -> String {
        self.path
            .file_stem()
            .map_or_else(|| "log".into(), |s| s.to_string_lossy().into_owned())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("pto-log-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn body(n: usize) -> String {
        let mut s = String::new();
        for i in 0..n {
            let _ = writeln!(s, "{},0.5,100,8,200,12,1001,1", i as f64 * 0.1);
        }
        s
    }

    #[test]
    fn errors_name_file_line_and_column() {
        let h = "time_s,shaft_angle_deg,p2_bar,lp_bar,motor_rpm,aperture_pct,on_duty,config\n";
        let ok = write("ok.csv", &format!("{h}{}", body(20)));
        let log = BenchLog::read(&ok).unwrap();
        assert_eq!(log.on_duty, [true, false, false, true]);
        assert_eq!(log.t.len(), 20);
        let e = BenchLog::read(&write(
            "missing.csv",
            &format!("time_s,p2_bar\n{}", "0,1\n"),
        ))
        .unwrap_err();
        assert_eq!((e.line, e.column.as_str()), (1, "shaft_angle_deg"));
        let e = BenchLog::read(&write(
            "unit.csv",
            "time_s,shaft_angle_deg,p2_psi,lp_bar,motor_rpm,aperture_pct,on_duty,config\n",
        ))
        .unwrap_err();
        assert!(e.message.contains("found `p2_psi`"), "{e}");
        let mut b = body(20);
        b.push_str("1.0,0.5,100,8,200,12,1001,1\n");
        let e = BenchLog::read(&write("time.csv", &format!("{h}{b}"))).unwrap_err();
        assert_eq!((e.line, e.column.as_str()), (22, "time_s"));
        assert!(
            e.to_string().contains("time.csv:22: column `time_s`"),
            "{e}"
        );
        let e = BenchLog::read(&write(
            "range.csv",
            &format!("{h}{}0.0,0.5,500,8,200,12,1001,1\n", ""),
        ))
        .unwrap_err();
        assert_eq!((e.line, e.column.as_str()), (2, "p2_bar"));
        let e = BenchLog::read(&write(
            "duty.csv",
            &format!("{h}{}5,0.5,100,8,200,12,1000,1\n", body(3)),
        ))
        .unwrap_err();
        assert_eq!((e.line, e.column.as_str()), (5, "on_duty"));
    }
}
