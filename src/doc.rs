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
    /// Checks shapes and values; errors name `origin` and the key. (By
    /// default: nothing beyond what serde checks.)
    fn validate(&self, _origin: &Path) -> Result<()> {
        Ok(())
    }
}

/// What a document of each `format` tag holds, in words.
fn describe(format: &str) -> Option<&'static str> {
    Some(match format {
        "svkernel.profile" => "a simulated profile, from `svkernel simulate profile`",
        "svkernel.kernels" => "a kernel tally, from `svkernel simulate kernels`",
        "svkernel.basis" => "the basis BSSRDF model, from `svkernel fit profiles`",
        "svkernel.metamodel" => "the kernel meta-model, from `svkernel fit kernels`",
        "svkernel.reference" => "a reference tally, from `svkernel render --method reference`",
        "svkernel.render" => "the summary of a render",
        "svkernel.compare" => "the summary of a comparison",
        "svkernel.experiments" => "the results of `svkernel experiments`",
        "svkernel.checkpoint" => "a simulation checkpoint",
        _ => return None,
    })
}

/// "a `F` document (what it holds)" for the `format` tag F.
fn document(format: &str) -> String {
    match describe(format) {
        Some(what) => format!("a `{format}` document ({what})"),
        None => format!("a `{format}` document"),
    }
}

/// The `format` tag of a JSON document, if it has one (`None` also for
/// JSON that is not an object); errors name `origin`.
pub fn format_of(text: &str, origin: &Path) -> Result<Option<String>> {
    Ok(header_of(text, origin)?.0)
}

/// The `format` tag and the `version` (if a whole number) of a JSON
/// document, read in one parse that skips the rest.
fn header_of(text: &str, origin: &Path) -> Result<(Option<String>, Option<u64>)> {
    if !text.trim_start().starts_with('{') {
        // Truncated or empty text is worded by the full parse.
        serde_json::from_str::<serde::de::IgnoredAny>(text).map_err(|e| json_error(origin, e))?;
        return Ok((None, None));
    }
    let head: Header = serde_json::from_str(text).map_err(|e| json_error(origin, e))?;
    let format = match head.format {
        Some(serde_json::Value::String(f)) => Some(f),
        _ => None,
    };
    Ok((format, head.version.as_ref().and_then(|v| v.as_u64())))
}

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
    let expected = document(T::FORMAT);
    let (format, version) = header_of(text, origin)?;
    match format.as_deref() {
        Some(f) if f == T::FORMAT => {}
        Some(f) => {
            let found = if describe(f).is_some() {
                document(f)
            } else {
                format!("a `{f}` document, not one svkernel writes")
            };
            return Err(Error::format(
                origin,
                "format",
                format!("this is {found}; expected {expected}"),
            ));
        }
        None => {
            return Err(Error::format(
                origin,
                "format",
                format!("not an svkernel document (no format tag); expected {expected}"),
            ));
        }
    }
    match version {
        Some(v) if v == u64::from(T::VERSION) => {}
        found => {
            let found = found.map_or("none".to_string(), |v| v.to_string());
            return Err(Error::format(
                origin,
                "version",
                format!(
                    "expected {}, found {found} (unsupported by this build)",
                    T::VERSION
                ),
            ));
        }
    }
    let doc: T = serde_json::from_str(text).map_err(|e| json_error(origin, e))?;
    doc.validate(origin)?;
    Ok(doc)
}

/// `#[serde(with = "crate::doc::nan_as_null")]` on an `f64` field that can
/// be undefined (a relative error against a black image): JSON has no NaN,
/// serde_json writes NaN and ±∞ as `null`, and this reads `null` back as
/// NaN instead of refusing the document.
pub mod nan_as_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_f64(*v)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> std::result::Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metamodel::meta::MetaModelFile;

    fn err(text: &str) -> String {
        from_json::<MetaModelFile>(text, Path::new("m.json"))
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn a_document_of_another_kind_is_named_by_its_tag() {
        let e = err(r#"{"format": "svkernel.kernels", "version": 2, "paths": 1}"#);
        assert!(
            e.contains("m.json")
                && e.contains("`svkernel.kernels`")
                && e.contains("kernel tally")
                && e.contains("expected a `svkernel.metamodel`"),
            "{e}"
        );
        let e = err(r#"{"format": "other.thing"}"#);
        assert!(
            e.contains("`other.thing`") && e.contains("not one svkernel writes"),
            "{e}"
        );
        for untagged in [r#"{"all": 1}"#, "[1, 2]", "3"] {
            let e = err(untagged);
            assert!(e.contains("not an svkernel document"), "{e}");
        }
        let e = err(r#"{"format": "svkernel.metamodel", "version": 7}"#);
        assert!(e.contains("version") && e.contains("found 7"), "{e}");
        let e = err(r#"{"format": "svkernel.metamodel"}"#);
        assert!(e.contains("version") && e.contains("found none"), "{e}");
        let e = err(r#"{"format": "svkernel.meta"#);
        assert!(e.contains("truncated"), "{e}");
        assert!(!e.contains("missing field"), "{e}");
    }

    #[test]
    fn an_undefined_number_reads_back_as_nan() {
        #[derive(serde::Serialize, serde::Deserialize)]
        struct X {
            #[serde(with = "nan_as_null")]
            v: f64,
        }
        let text = serde_json::to_string(&X { v: f64::NAN }).unwrap();
        assert_eq!(text, r#"{"v":null}"#);
        let back: X = serde_json::from_str(&text).unwrap();
        assert!(back.v.is_nan());
        let back: X = serde_json::from_str(r#"{"v":0.25}"#).unwrap();
        assert_eq!(back.v, 0.25);
    }
}
