//! Versioned documents: every file svkernel writes (profiles, kernel
//! tallies, basis models, meta-models, reference tallies) is a JSON object
//! with a `format` tag and a `version`. Parsing is pure: [`from_json`] takes
//! the text and the name to give in errors (a file path, or the name of a
//! built-in copy); the job layer ([`crate::jobs::store`]) reads the files.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize, de::DeserializeOwned};
use std::path::Path;

/// A document type: its tag, version and the checks serde cannot make.
pub trait Document: Serialize + DeserializeOwned {
    /// The `format` tag, e.g. `svkernel.metamodel`.
    const FORMAT: &'static str;
    /// The version this build reads and writes.
    const VERSION: u32;
    /// What the document is, in words ("kernel meta-model").
    const WHAT: &'static str;
    /// Checks shapes and values; errors name `origin` and the key.
    fn validate(&self, origin: &Path) -> Result<()>;
}

/// The documents this crate knows, for naming a file of the wrong kind.
const KNOWN: &[(&str, &str)] = &[
    ("svkernel.profile", "radial profile"),
    ("svkernel.kernels", "kernel tally"),
    ("svkernel.basis", "basis BSSRDF model"),
    ("svkernel.metamodel", "kernel meta-model"),
    ("svkernel.reference", "reference tally"),
    ("svkernel.checkpoint", "checkpoint"),
];

#[derive(Deserialize)]
struct Header {
    format: Option<serde_json::Value>,
    version: Option<serde_json::Value>,
}

/// Maps a serde error to one that names `origin` and the line.
pub fn json_error(origin: &Path, e: serde_json::Error) -> Error {
    let key = if e.is_eof() {
        "(truncated file)".to_string()
    } else {
        format!("line {}", e.line())
    };
    Error::format(origin, key, e)
}

/// Parses a document of type `T`: first its header (a file of another kind
/// is named by its `format` tag), then the whole, then [`Document::validate`].
pub fn from_json<T: Document>(text: &str, origin: &Path) -> Result<T> {
    let head: Header = serde_json::from_str(text).map_err(|e| json_error(origin, e))?;
    let want = || format!("expected a {} (`{}`)", T::WHAT, T::FORMAT);
    match head.format {
        Some(serde_json::Value::String(f)) if f == T::FORMAT => {}
        Some(serde_json::Value::String(f)) => {
            let what = KNOWN
                .iter()
                .find(|(tag, _)| *tag == f)
                .map(|(_, w)| format!("a {w} (`{f}`)"))
                .unwrap_or_else(|| format!("a `{f}` document"));
            return Err(Error::format(
                origin,
                "format",
                format!("this is {what}; {}", want()),
            ));
        }
        _ => {
            return Err(Error::format(
                origin,
                "format",
                format!("no `format` tag: not an svkernel document; {}", want()),
            ));
        }
    }
    match head.version.as_ref().and_then(|v| v.as_u64()) {
        Some(v) if v == u64::from(T::VERSION) => {}
        Some(v) => {
            return Err(Error::format(
                origin,
                "version",
                format!(
                    "version {v} is not supported: this build reads version {} of `{}`",
                    T::VERSION,
                    T::FORMAT
                ),
            ));
        }
        None => {
            return Err(Error::format(
                origin,
                "version",
                "missing or not a whole number",
            ));
        }
    }
    let doc: T = serde_json::from_str(text).map_err(|e| json_error(origin, e))?;
    doc.validate(origin)?;
    Ok(doc)
}

/// Serialises a document as pretty JSON (`compact = false`) or on one line.
pub fn to_json<T: Serialize>(doc: &T, compact: bool, origin: &Path) -> Result<Vec<u8>> {
    if compact {
        serde_json::to_vec(doc)
    } else {
        serde_json::to_vec_pretty(doc)
    }
    .map_err(|e| Error::format(origin, "(serialise)", e))
}
