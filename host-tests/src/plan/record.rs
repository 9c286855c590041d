//! A campaign's segment as planned and the record of its log (the `.segment.toml` sidecar
//! `pto link campaign run` writes beside each log and `pto fit` reads), with the campaign
//! file's errors: what the fit needs of a campaign, without the planning.

use crate::sim::scenario::{Scenario, ScenarioError};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The link's highest telemetry rate, Hz (`pto link monitor --rate`).
pub const MAX_RATE_HZ: f64 = 128.0;
/// Bench time a segment costs besides its own length, min: the host's reset, the valve and
/// duty set, the pressures settling.
pub const SETUP_MIN: f64 = 1.0;

/// One segment of a campaign: a run the bench does and the rate it is logged at.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Segment {
    /// Log rate, Hz (1 to [`MAX_RATE_HZ`]).
    pub rate_hz: f64,
    /// What the operator sets on the rack drive (people read it; the run says it exactly).
    pub operator: String,
    /// The run: geometry, cylinders, motion, valve, start pressures, length.
    pub run: Scenario,
}

impl Segment {
    /// Bench time, min: the run and its set-up.
    pub fn minutes(&self) -> f64 {
        self.run.duration_s / 60.0 + SETUP_MIN
    }

    /// What the operator must change on the bench for it: the lever's motion, the cylinders
    /// or the geometry (the controller sets the valve, the duty's solenoids and the reset).
    pub(crate) fn setup(&self) -> (String, String, Vec<String>) {
        (
            format!("{:?}", self.run.motion),
            self.run.config.clone(),
            self.run.cylinders.clone(),
        )
    }
}

/// Why a campaign file was refused: the file, the field, the value and what is allowed.
#[derive(Debug, thiserror::Error)]
pub enum CampaignError {
    /// Unreadable, or not a campaign.
    #[error("{file}: {message}")]
    File {
        /// The file.
        file: String,
        /// What is wrong.
        message: String,
    },
    /// A field out of range.
    #[error("{file}: {field} = {value}: {allowed}")]
    Field {
        /// The file.
        file: String,
        /// The field's path (`segment[2].rate_hz`).
        field: String,
        /// Its value.
        value: String,
        /// What is allowed, with the unit.
        allowed: String,
    },
    /// A segment's run does not prepare on the bench.
    #[error("{file}: segment[{index}].run: {source}")]
    Run {
        /// The file.
        file: String,
        /// The segment.
        index: usize,
        /// Why.
        source: ScenarioError,
    },
}

/// How a segment's log came out.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Logged as planned (or synthesised): the fit takes it.
    Complete,
    /// Stopped before its end (Ctrl-C, the link lost): rerun.
    Unfinished,
    /// Logged, but not as planned (the motion off, frames lost, a trip, a restart): rerun.
    Mismatch,
}

impl Status {
    /// As the runner reports it: `complete`, or a shouted `MISMATCH` / `UNFINISHED`.
    pub fn label(self) -> &'static str {
        match self {
            Status::Complete => "complete",
            Status::Mismatch => "MISMATCH",
            Status::Unfinished => "UNFINISHED",
        }
    }
}

/// The sidecar of a segment's log (`<stem>.segment.toml` (`run1.csv` → `run1.segment.toml`)): which campaign and segment it is and
/// how it came out. `pto fit` takes a log with a complete sidecar at every sample (the rate was
/// chosen for it) and refuses one marked unfinished or mismatched.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Record {
    /// The campaign file.
    pub campaign: String,
    /// The segment's place in it (from 0).
    pub index: usize,
    /// How it came out.
    pub status: Status,
    /// Why, when not complete.
    #[serde(default)]
    pub note: String,
    /// The segment as planned.
    pub segment: Segment,
}

impl Record {
    /// The sidecar's path for the log at `log`.
    pub fn path_for(log: &Path) -> std::path::PathBuf {
        log.with_extension("segment.toml")
    }

    /// Writes the sidecar of the log at `log` (whole: a temporary file renamed over it).
    pub fn write_for(&self, log: &Path) -> std::io::Result<()> {
        let path = Self::path_for(log);
        let text = toml::to_string(self).map_err(std::io::Error::other)?;
        let tmp = path.with_extension("toml.tmp");
        std::fs::write(&tmp, text)?;
        std::fs::rename(&tmp, &path)
    }

    /// The sidecar of the log at `log`, if it has one.
    pub fn read_for(log: &Path) -> Result<Option<Record>, CampaignError> {
        let path = Self::path_for(log);
        let file = path.display().to_string();
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => {
                return Err(CampaignError::File {
                    file,
                    message: format!("cannot read: {e}"),
                });
            }
        };
        toml::from_str(&text)
            .map(Some)
            .map_err(|e| CampaignError::File {
                file,
                message: e.to_string().trim_end().to_string(),
            })
    }
}
