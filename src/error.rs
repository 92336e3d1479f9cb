//! Typed errors of the library. The CLI wraps them with `anyhow`.

use std::path::PathBuf;

/// Every error the library reports. Each variant names what was wrong and
/// where (parameter, file, key), so the CLI can print it as is (after
/// naming a parameter by its flag).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// A parameter outside its domain (e.g. an albedo of 1.2); `name` is the
    /// library's name of the parameter (`albedo`, `eta`, `max_events`,
    /// `meta_model`, …), not how a user set it: the layer above names that
    /// (the CLI maps it to its flag, `--albedo`; the scene loader to the
    /// scene file and key, `medium.eta`).
    #[error("invalid {name} = {value}: must be {allowed}")]
    Param {
        name: &'static str,
        value: String,
        allowed: &'static str,
    },
    /// A file that could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file whose content is malformed; `key` names the offending entry.
    #[error("{path}: {key}: {msg}")]
    Format {
        path: PathBuf,
        key: String,
        msg: String,
    },
    /// A fit that failed (did not converge, or had too little data).
    #[error(transparent)]
    Fit(#[from] crate::fit::lm::FitError),
    /// Tallies that cannot be merged (different configuration, overlapping shards).
    #[error("cannot merge {path}: {msg}")]
    Merge { path: PathBuf, msg: String },
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub(crate) fn param(name: &'static str, value: impl ToString, allowed: &'static str) -> Self {
        Error::Param {
            name,
            value: value.to_string(),
            allowed,
        }
    }
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    pub(crate) fn format(
        path: impl Into<PathBuf>,
        key: impl Into<String>,
        msg: impl ToString,
    ) -> Self {
        Error::Format {
            path: path.into(),
            key: key.into(),
            msg: msg.to_string(),
        }
    }
}
