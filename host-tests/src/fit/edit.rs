//! The fitted bench file as an edit of the input: only the fields the fit changed are
//! rewritten, in place, so the engineer's comments, order and layout stay.

use super::*;
use toml_edit::{DocumentMut, Item, Table};

/// Why the fitted bench text could not be made.
#[derive(Debug, thiserror::Error)]
pub enum EditError {
    /// The input bench text is not TOML (it was parsed once already, so this is unexpected).
    #[error("the input bench file: {0}")]
    Parse(#[from] toml_edit::TomlError),
    /// A bench could not be serialised.
    #[error("serialising the bench: {0}")]
    Serialise(#[from] toml::ser::Error),
}

/// `input` (the text of the bench file the fit started from) with every field where `fitted`
/// differs from `start` set to its fitted value; comments and layout kept. A field the input
/// left to its default is added to its table.
pub fn fitted_bench_text(
    input: &str,
    start: &BenchFile,
    fitted: &BenchFile,
) -> Result<String, EditError> {
    let mut doc: DocumentMut = input.parse()?;
    let s: DocumentMut = toml::to_string(start)?.parse()?;
    let f: DocumentMut = toml::to_string(fitted)?.parse()?;
    merge(doc.as_table_mut(), s.as_table(), f.as_table());
    Ok(doc.to_string())
}

fn same(a: &Item, b: &Item) -> bool {
    match (a.as_value(), b.as_value()) {
        (Some(x), Some(y)) => x.to_string().trim() == y.to_string().trim(),
        _ => a.to_string() == b.to_string(),
    }
}

fn merge(out: &mut Table, start: &Table, fitted: &Table) {
    for (key, fv) in fitted.iter() {
        let sv = start.get(key);
        if let (Some(ft), Some(st)) = (fv.as_table(), sv.and_then(Item::as_table)) {
            match out.get_mut(key).and_then(Item::as_table_mut) {
                Some(ot) => merge(ot, st, ft),
                None => {
                    if ft
                        .iter()
                        .any(|(k, v)| st.get(k).is_none_or(|s| !same(s, v)))
                    {
                        out.insert(key, fv.clone());
                    }
                }
            }
            continue;
        }
        if sv.is_some_and(|s| same(s, fv)) {
            continue;
        }
        match out.get_mut(key) {
            // Keep the input's decoration (its trailing comment, its spacing).
            Some(Item::Value(ov)) if fv.is_value() => {
                let decor = ov.decor().clone();
                if let Some(nv) = fv.as_value() {
                    *ov = nv.clone();
                    *ov.decor_mut() = decor;
                }
            }
            _ => {
                out.insert(key, fv.clone());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::bench::REFERENCE_BENCH_TOML;

    /// The reference bench with two fitted fields: only those two lines change, every comment
    /// stays, and the text reads back as the fitted bench.
    #[test]
    fn only_the_fitted_fields_change_and_the_comments_stay() {
        let start = Bench::reference().file;
        let mut fitted = start.clone();
        fitted.oil.trapped_air_fraction = 0.0412;
        fitted.hp_accumulator.precharge_bar = 44.87;
        let text = fitted_bench_text(REFERENCE_BENCH_TOML, &start, &fitted).unwrap();
        let back: BenchFile = toml::from_str(&text).unwrap();
        assert_eq!(back, fitted);
        let (a, b): (Vec<&str>, Vec<&str>) = (
            REFERENCE_BENCH_TOML.lines().collect(),
            text.lines().collect(),
        );
        assert_eq!(a.len(), b.len(), "same number of lines");
        let changed: Vec<(&str, &str)> = a
            .iter()
            .zip(&b)
            .filter(|(x, y)| x != y)
            .map(|(x, y)| (*x, *y))
            .collect();
        println!("{changed:#?}");
        assert_eq!(changed.len(), 2);
        assert!(
            changed
                .iter()
                .all(|(x, _)| !x.trim_start().starts_with('#'))
        );
        assert!(b.iter().filter(|l| l.trim_start().starts_with('#')).count() > 20);
    }
}
