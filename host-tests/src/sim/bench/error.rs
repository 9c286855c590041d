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
