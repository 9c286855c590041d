//! A run's place in the matrix: its value index on each axis (the last axis varies fastest),
//! and its axis values as text for messages.

use super::axis::Axis;

/// The value index on each axis of run `index` (the last axis varies fastest).
pub fn point_of(axes: &[Axis], mut index: usize) -> Vec<usize> {
    let mut p = vec![0; axes.len()];
    for (slot, a) in p.iter_mut().zip(axes).rev() {
        let n = a.values.len().max(1);
        *slot = index % n;
        index /= n;
    }
    p
}

/// Run `index`'s axis values as `field = value, …`, for messages.
pub fn describe(axes: &[Axis], index: usize) -> String {
    let p = point_of(axes, index);
    let mut parts = Vec::new();
    for (a, &v) in axes.iter().zip(&p) {
        for (f, x) in a.fields.iter().zip(&a.values[v]) {
            parts.push(format!("{f} = {x}"));
        }
    }
    if parts.is_empty() {
        "the base run".into()
    } else {
        parts.join(", ")
    }
}
