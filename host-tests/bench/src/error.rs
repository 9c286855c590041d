//! Why a bench file could not be loaded: every field outside its range, named with its file,
//! its path, the allowed range and the unit.

use std::fmt;

/// One field outside its allowed range (or otherwise inconsistent).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldError {
    /// Dotted path of the field, e.g. `cylinder[2].bore_mm`.
    pub field: String,
    /// What is wrong, e.g. `0 outside [1, 500] (mm)`.
    pub message: String,
}

/// Why a bench file could not be loaded.
#[derive(Debug, Clone, PartialEq)]
pub enum BenchError {
    /// The file could not be read.
    Io {
        /// The file.
        file: String,
        /// The OS error.
        message: String,
    },
    /// Not valid TOML, an unknown key, a missing key or a wrong type.
    Parse {
        /// The file.
        file: String,
        /// The parser's message (it names the line and key).
        message: String,
    },
    /// Fields outside their ranges; all of them are listed.
    Invalid {
        /// The file.
        file: String,
        /// Every offending field.
        errors: Vec<FieldError>,
    },
}

impl fmt::Display for BenchError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BenchError::Io { file, message } => write!(f, "{file}: cannot read: {message}"),
            BenchError::Parse { file, message } => write!(f, "{file}: {}", message.trim_end()),
            BenchError::Invalid { file, errors } => {
                for (i, e) in errors.iter().enumerate() {
                    if i > 0 {
                        writeln!(f)?;
                    }
                    write!(f, "{file}:{}: {}", e.field, e.message)?;
                }
                Ok(())
            }
        }
    }
}

impl std::error::Error for BenchError {}

/// Why [`BenchFile::set_field`](super::BenchFile::set_field) could not set a field: every
/// message starts with the dotted path. Messages are whole (the TOML parser's included):
/// `--set` errors ([`OverrideError`]) embed them.
#[derive(Debug, thiserror::Error)]
pub enum SetFieldError {
    /// The bench file could not be turned into a TOML tree.
    #[error(transparent)]
    Serialize(#[from] toml::ser::Error),
    /// `name[i]` with `i` not a number or no closing `]`.
    #[error("{path}: bad index in `{part}`")]
    BadIndex {
        /// The dotted path.
        path: String,
        /// The segment with the bad index.
        part: String,
    },
    /// The path goes on below a value.
    #[error("{path}: `{key}` is inside a value, not a table")]
    NotATable {
        /// The dotted path.
        path: String,
        /// The key below the value.
        key: String,
    },
    /// No such field; the fields at that level are listed.
    #[error("{path}: unknown field `{key}` (fields here: {})", .known.join(", "))]
    UnknownField {
        /// The dotted path.
        path: String,
        /// The unknown key.
        key: String,
        /// The keys there.
        known: Vec<String>,
    },
    /// An index on a field that is not a list.
    #[error("{path}: `{key}` is not a list")]
    NotAList {
        /// The dotted path.
        path: String,
        /// The field.
        key: String,
    },
    /// An index past the list's end.
    #[error("{path}: index {index} outside `{key}`'s 0..{len}")]
    IndexOutside {
        /// The dotted path.
        path: String,
        /// The list.
        key: String,
        /// The index asked for.
        index: usize,
        /// The list's length.
        len: usize,
    },
    /// The value is not TOML (nor a string once quoted).
    #[error("{path}: `{value}` is not a value: {error}")]
    NotAValue {
        /// The dotted path.
        path: String,
        /// The value as given.
        value: String,
        /// The TOML parser's error.
        error: Box<toml::de::Error>,
    },
    /// The value's type is not the field's.
    #[error("{path}: `{value}` is a {given}, the field holds a {held}")]
    WrongType {
        /// The dotted path.
        path: String,
        /// The value as given.
        value: String,
        /// Its TOML type.
        given: &'static str,
        /// The field's TOML type.
        held: &'static str,
    },
    /// The edited tree is no longer a bench file.
    #[error("{path}: {error}")]
    Rebuild {
        /// The dotted path.
        path: String,
        /// The TOML deserialiser's error.
        error: Box<toml::de::Error>,
    },
}

/// Why a `--set NAME=VALUE` override could not be applied
/// ([`apply_override`](super::apply_override)).
#[derive(Debug, thiserror::Error)]
pub enum OverrideError {
    /// No `=`.
    #[error("--set {kv}: want name=value")]
    Syntax {
        /// The argument as given.
        kv: String,
    },
    /// A dotted path (or a non-numeric value) that [`SetFieldError`] refused.
    #[error("--set {0}")]
    Field(SetFieldError),
    /// A plain name that is neither a short name nor a top-level bench field; the short names
    /// are listed.
    #[error("--set {error}{}", or_shortcuts(.shortcuts))]
    FieldOrShortcut {
        /// Why it is not a top-level field.
        error: SetFieldError,
        /// The short names `--set` also takes.
        shortcuts: Vec<String>,
    },
}

/// ` (or a parameter: a, b)` after an unknown name, nothing without short names.
fn or_shortcuts(names: &[String]) -> String {
    if names.is_empty() {
        String::new()
    } else {
        format!(" (or a parameter: {})", names.join(", "))
    }
}
