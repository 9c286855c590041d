//! An axis of the matrix: the fields it sets together and its values, a value as text, and
//! the two axes the heat maps are drawn over.

use serde::{Deserialize, Serialize};

/// One axis: a field, or fields set together, and its values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Axis {
    /// The dotted paths it sets (`bench.hp_accumulator.volume_l`).
    pub fields: Vec<String>,
    /// Its values: one per field each (in JSON as TOML text: `"5.0"`, `"\"HC3.1\""`).
    #[serde(with = "toml_text")]
    pub values: Vec<Vec<toml::Value>>,
}

/// TOML values as their TOML text in JSON (`sweep.json`): a TOML value read back from JSON
/// would not keep its type (an integer-valued float becomes an integer), nor survive
/// `serde_json`'s `arbitrary_precision`, which a dependency turns on.
mod toml_text {
    use serde::{Deserialize, Deserializer, Serializer, de::Error};

    pub fn serialize<S: Serializer>(v: &[Vec<toml::Value>], s: S) -> Result<S::Ok, S::Error> {
        let text: Vec<Vec<String>> = v
            .iter()
            .map(|r| r.iter().map(toml::Value::to_string).collect())
            .collect();
        serde::Serialize::serialize(&text, s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Vec<toml::Value>>, D::Error> {
        let text = Vec::<Vec<String>>::deserialize(d)?;
        text.into_iter()
            .map(|r| {
                r.into_iter()
                    .map(|t| {
                        let mut table: toml::Table =
                            toml::from_str(&format!("v = {t}")).map_err(D::Error::custom)?;
                        table
                            .remove("v")
                            .ok_or_else(|| D::Error::custom("no value"))
                    })
                    .collect()
            })
            .collect()
    }
}

impl Axis {
    /// `bench.hp_accumulator.volume_l`, or linked fields joined by ` / `.
    pub fn name(&self) -> String {
        self.fields.join(" / ")
    }

    /// Value `i` as text (`4`, `HC3.1+HC3.4`, `30 / 8`).
    pub fn label(&self, i: usize) -> String {
        self.values[i]
            .iter()
            .map(value_text)
            .collect::<Vec<_>>()
            .join(" / ")
    }
}

/// A value as a table cell: a number or string as is, a list of strings joined by `+`
/// (`HC3.1+HC3.4`), anything else as inline TOML.
pub fn value_text(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => s.clone(),
        toml::Value::Integer(i) => i.to_string(),
        toml::Value::Float(x) => x.to_string(),
        toml::Value::Array(a) if a.iter().all(|x| x.is_str()) => a
            .iter()
            .filter_map(|x| x.as_str())
            .collect::<Vec<_>>()
            .join("+"),
        other => other.to_string(),
    }
}

/// The heat maps' axes when the matrix names none: the first two axes of more than one value.
pub fn default_heatmap(axes: &[Axis]) -> Option<(usize, usize)> {
    let mut many = (0..axes.len()).filter(|&i| axes[i].values.len() > 1);
    Some((many.next()?, many.next()?))
}

/// The axes of a `heatmap = [X, Y]` list: each a field of an axis, two different axes.
pub fn heatmap_axes(axes: &[Axis], names: &[String]) -> Result<(usize, usize), String> {
    let find = |n: &str| {
        axes.iter()
            .position(|a| a.fields.iter().any(|f| f == n) || a.name() == n)
            .ok_or_else(|| {
                let have: Vec<String> = axes.iter().map(Axis::name).collect();
                format!(
                    "heatmap: `{n}` is not an axis (axes: {})",
                    if have.is_empty() {
                        "none".into()
                    } else {
                        have.join(", ")
                    }
                )
            })
    };
    match names {
        [x, y] => {
            let (x, y) = (find(x)?, find(y)?);
            if x == y {
                return Err(format!(
                    "heatmap: `{}` twice: want two different axes",
                    axes[x].name()
                ));
            }
            Ok((x, y))
        }
        _ => Err(format!(
            "heatmap: want two axes, X and Y, got {}",
            names.len()
        )),
    }
}
