//! A sweep's rows as a table of typed columns — the run, its axis values, its status and
//! figures, units in the column names — written as CSV and Parquet, and read back.

use super::axis::value_text;
use super::expand::point_of;
use super::key::RunKey;
use super::run::{Figures, Row};
use super::store::Identity;
use arrow_array::{
    Array, ArrayRef, Float64Array, Int64Array, RecordBatch, StringArray, UInt64Array,
};
use arrow_schema::{DataType, Field, Schema};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

/// A column's cells (`None`: empty in the CSV, null in Parquet).
#[derive(Debug, Clone, PartialEq)]
pub enum Cells {
    /// Counts.
    U64(Vec<Option<u64>>),
    /// Integers (an axis of integer values).
    I64(Vec<Option<i64>>),
    /// Numbers.
    F64(Vec<Option<f64>>),
    /// Text.
    Str(Vec<Option<String>>),
}

impl Cells {
    fn len(&self) -> usize {
        match self {
            Cells::U64(v) => v.len(),
            Cells::I64(v) => v.len(),
            Cells::F64(v) => v.len(),
            Cells::Str(v) => v.len(),
        }
    }

    /// Cell `i` as the CSV holds it (numbers in their shortest exact form).
    pub fn text(&self, i: usize) -> String {
        match self {
            Cells::U64(v) => v[i].map(|x| x.to_string()),
            Cells::I64(v) => v[i].map(|x| x.to_string()),
            Cells::F64(v) => v[i].map(|x| x.to_string()),
            Cells::Str(v) => v[i].clone(),
        }
        .unwrap_or_default()
    }

    /// Cell `i` as a number, if it is one.
    pub fn number(&self, i: usize) -> Option<f64> {
        match self {
            Cells::U64(v) => v[i].map(|x| x as f64),
            Cells::I64(v) => v[i].map(|x| x as f64),
            Cells::F64(v) => v[i],
            Cells::Str(_) => None,
        }
    }
}

/// A named column.
#[derive(Debug, Clone, PartialEq)]
pub struct Column {
    /// Its name, with its unit (`p2_mean_bar`), or an axis's field.
    pub name: String,
    /// Its cells.
    pub cells: Cells,
}

/// Columns of equal length.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Table {
    /// The columns, in order.
    pub columns: Vec<Column>,
}

/// Why a table could not be written or read, named with its file.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// Parquet or Arrow refused (their error as the source).
    #[error("{path}")]
    Parquet {
        /// The file.
        path: String,
        /// The library's error.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A column of a type the table does not hold.
    #[error("{path}: column {column} is {kind}, not a sweep table's")]
    Type {
        /// The file.
        path: String,
        /// The column.
        column: String,
        /// Its type.
        kind: String,
    },
}

/// The figures' columns: name (with unit) and value.
type FigureColumn = (&'static str, fn(&Figures) -> Option<f64>);

const FIGURES: [FigureColumn; 20] = [
    ("input_power_w", |f| Some(f.input_power_w)),
    ("pumped_power_w", |f| Some(f.pumped_power_w)),
    ("motor_shaft_power_w", |f| Some(f.motor_shaft_power_w)),
    ("generator_power_w", |f| Some(f.generator_power_w)),
    ("efficiency_pct", |f| f.efficiency_pct),
    ("efficiency_with_storage_pct", |f| {
        f.efficiency_with_storage_pct
    }),
    ("losses_w", |f| Some(f.losses_w)),
    ("relief_loss_w", |f| Some(f.relief_loss_w)),
    ("stored_w", |f| Some(f.stored_w)),
    ("p2_min_bar", |f| Some(f.p2_min_bar)),
    ("p2_mean_bar", |f| Some(f.p2_mean_bar)),
    ("p2_max_bar", |f| Some(f.p2_max_bar)),
    ("time_at_relief_s", |f| Some(f.time_at_relief_s)),
    ("lp_min_bar", |f| Some(f.lp_min_bar)),
    ("lp_max_bar", |f| Some(f.lp_max_bar)),
    ("motor_speed_mean_rpm", |f| Some(f.motor_speed_mean_rpm)),
    ("motor_speed_max_rpm", |f| Some(f.motor_speed_max_rpm)),
    ("motor_speed_std_rpm", |f| Some(f.motor_speed_std_rpm)),
    ("balance_worst_rel", |f| Some(f.balance_worst_rel)),
    ("simulated_s", |f| Some(f.simulated_s)),
];

impl Table {
    /// The table of `identity`'s runs `indices` (from 0, in order) from their rows; a run
    /// without a row is left out.
    pub fn of_rows(identity: &Identity, rows: &HashMap<RunKey, Row>, indices: &[usize]) -> Table {
        let done: Vec<(usize, &Row)> = indices
            .iter()
            .filter_map(|&i| rows.get(&identity.keys[i]).map(|r| (i, r)))
            .collect();
        let mut columns = vec![
            Column {
                name: "run".into(),
                cells: Cells::U64(done.iter().map(|(i, _)| Some(*i as u64 + 1)).collect()),
            },
            Column {
                name: "key".into(),
                cells: Cells::Str(done.iter().map(|(_, r)| Some(r.key.to_string())).collect()),
            },
            Column {
                name: "scenario".into(),
                cells: Cells::Str(vec![Some(identity.scenario.clone()); done.len()]),
            },
        ];
        let points: Vec<Vec<usize>> = done
            .iter()
            .map(|(i, _)| point_of(&identity.axes, *i))
            .collect();
        for (a, axis) in identity.axes.iter().enumerate() {
            for (f, field) in axis.fields.iter().enumerate() {
                let values: Vec<&toml::Value> =
                    points.iter().map(|p| &axis.values[p[a]][f]).collect();
                let all = &axis.values;
                let cells = if all.iter().all(|v| v[f].is_integer()) {
                    Cells::I64(values.iter().map(|v| v.as_integer()).collect())
                } else if all.iter().all(|v| v[f].is_integer() || v[f].is_float()) {
                    Cells::F64(
                        values
                            .iter()
                            .map(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64)))
                            .collect(),
                    )
                } else {
                    Cells::Str(values.iter().map(|v| Some(value_text(v))).collect())
                };
                columns.push(Column {
                    name: field.clone(),
                    cells,
                });
            }
        }
        columns.push(Column {
            name: "status".into(),
            cells: Cells::Str(
                done.iter()
                    .map(|(_, r)| Some(r.status.as_str().into()))
                    .collect(),
            ),
        });
        for (name, get) in FIGURES {
            columns.push(Column {
                name: name.into(),
                cells: Cells::F64(
                    done.iter()
                        .map(|(_, r)| r.figures.as_ref().and_then(get))
                        .collect(),
                ),
            });
        }
        columns.push(Column {
            name: "steps".into(),
            cells: Cells::U64(
                done.iter()
                    .map(|(_, r)| r.figures.as_ref().map(|f| f.steps))
                    .collect(),
            ),
        });
        columns.push(Column {
            name: "wall_s".into(),
            cells: Cells::F64(done.iter().map(|(_, r)| Some(r.wall_s)).collect()),
        });
        columns.push(Column {
            name: "error".into(),
            cells: Cells::Str(done.iter().map(|(_, r)| r.error.clone()).collect()),
        });
        Table { columns }
    }

    /// Rows.
    pub fn len(&self) -> usize {
        self.columns.first().map_or(0, |c| c.cells.len())
    }

    /// No rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The column named `name`.
    pub fn column(&self, name: &str) -> Option<&Column> {
        self.columns.iter().find(|c| c.name == name)
    }

    /// The table as CSV text: a header, then a line per row.
    pub fn csv(&self) -> Result<String, csv::Error> {
        let mut w = csv::Writer::from_writer(Vec::new());
        w.write_record(self.columns.iter().map(|c| &c.name))?;
        for i in 0..self.len() {
            w.write_record(self.columns.iter().map(|c| c.cells.text(i)))?;
        }
        let bytes = w
            .into_inner()
            .map_err(|e| csv::Error::from(e.into_error()))?;
        Ok(String::from_utf8_lossy(&bytes).into_owned())
    }

    /// The table as a Parquet file's bytes (uncompressed; typed columns, nulls for empty
    /// cells). `path` names the file in errors.
    pub fn parquet(&self, path: &str) -> Result<Vec<u8>, TableError> {
        let err = |source: Box<dyn std::error::Error + Send + Sync>| TableError::Parquet {
            path: path.into(),
            source,
        };
        let fields: Vec<Field> = self
            .columns
            .iter()
            .map(|c| {
                let t = match c.cells {
                    Cells::U64(_) => DataType::UInt64,
                    Cells::I64(_) => DataType::Int64,
                    Cells::F64(_) => DataType::Float64,
                    Cells::Str(_) => DataType::Utf8,
                };
                Field::new(&c.name, t, true)
            })
            .collect();
        let arrays: Vec<ArrayRef> = self
            .columns
            .iter()
            .map(|c| -> ArrayRef {
                match &c.cells {
                    Cells::U64(v) => Arc::new(UInt64Array::from(v.clone())),
                    Cells::I64(v) => Arc::new(Int64Array::from(v.clone())),
                    Cells::F64(v) => Arc::new(Float64Array::from(v.clone())),
                    Cells::Str(v) => Arc::new(StringArray::from(v.clone())),
                }
            })
            .collect();
        let schema = Arc::new(Schema::new(fields));
        let batch = RecordBatch::try_new(schema.clone(), arrays).map_err(|e| err(Box::new(e)))?;
        let mut buf = Vec::new();
        let mut w = parquet::arrow::ArrowWriter::try_new(&mut buf, schema, None)
            .map_err(|e| err(Box::new(e)))?;
        w.write(&batch).map_err(|e| err(Box::new(e)))?;
        w.close().map_err(|e| err(Box::new(e)))?;
        Ok(buf)
    }

    /// Reads a table [`Table::parquet`] wrote.
    pub fn read_parquet(path: &Path) -> Result<Table, TableError> {
        let name = path.display().to_string();
        let err = |source: Box<dyn std::error::Error + Send + Sync>| TableError::Parquet {
            path: name.clone(),
            source,
        };
        let file = std::fs::File::open(path).map_err(|e| err(Box::new(e)))?;
        let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file)
            .map_err(|e| err(Box::new(e)))?
            .build()
            .map_err(|e| err(Box::new(e)))?;
        let mut table = Table::default();
        for batch in reader {
            let batch = batch.map_err(|e| err(Box::new(e)))?;
            let schema = batch.schema();
            for (i, f) in schema.fields().iter().enumerate() {
                let a = batch.column(i);
                let cells = cells_of(a.as_ref()).ok_or_else(|| TableError::Type {
                    path: name.clone(),
                    column: f.name().clone(),
                    kind: f.data_type().to_string(),
                })?;
                match table.columns.get_mut(i) {
                    Some(c) => c.cells.extend(cells),
                    None => table.columns.push(Column {
                        name: f.name().clone(),
                        cells,
                    }),
                }
            }
        }
        Ok(table)
    }
}

impl Cells {
    fn extend(&mut self, more: Cells) {
        match (self, more) {
            (Cells::U64(a), Cells::U64(b)) => a.extend(b),
            (Cells::I64(a), Cells::I64(b)) => a.extend(b),
            (Cells::F64(a), Cells::F64(b)) => a.extend(b),
            (Cells::Str(a), Cells::Str(b)) => a.extend(b),
            // A column's type is the same in every batch of one file.
            _ => {}
        }
    }
}

fn cells_of(a: &dyn Array) -> Option<Cells> {
    let any = a.as_any();
    if let Some(x) = any.downcast_ref::<UInt64Array>() {
        return Some(Cells::U64(x.iter().collect()));
    }
    if let Some(x) = any.downcast_ref::<Int64Array>() {
        return Some(Cells::I64(x.iter().collect()));
    }
    if let Some(x) = any.downcast_ref::<Float64Array>() {
        return Some(Cells::F64(x.iter().collect()));
    }
    if let Some(x) = any.downcast_ref::<StringArray>() {
        return Some(Cells::Str(
            x.iter().map(|s| s.map(str::to_string)).collect(),
        ));
    }
    None
}
