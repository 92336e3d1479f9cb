//! File I/O shared by every command: atomic writes (temp file + rename, so a
//! crash never leaves a partial output) and JSON reads that name the file.

use crate::error::{Error, Result};
use serde::{Serialize, de::DeserializeOwned};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Temporary sibling of `path` (same directory, so the rename is atomic). It
/// keeps the extension, for writers that pick the format from it.
pub fn temp_sibling(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        let _ = std::fs::create_dir_all(dir);
    }
    path.with_file_name(format!(".tmp{}-{name}", std::process::id()))
}

/// Moves a finished temporary file over its destination.
pub fn commit(tmp: &Path, path: &Path) -> Result<()> {
    std::fs::rename(tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(tmp);
        Error::io(path, e)
    })
}

/// Writes `bytes` to `path` atomically: to a temporary file in the same
/// directory, flushed, then renamed over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// Like [`write_atomic`], with a writer callback.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let tmp = temp_sibling(path);
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        write(&mut f)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, e));
    }
    Ok(())
}

/// Serialises `value` as pretty JSON to `path`, atomically.
pub fn write_json_atomic<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes =
        serde_json::to_vec_pretty(value).map_err(|e| Error::format(path, "(serialise)", e))?;
    write_atomic(path, &bytes)
}

/// Like [`write_json_atomic`] but compact (one line): for large documents
/// whose arrays would otherwise take one line per number.
pub fn write_json_compact_atomic<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes = serde_json::to_vec(value).map_err(|e| Error::format(path, "(serialise)", e))?;
    write_atomic(path, &bytes)
}

/// Checks a versioned document's header: the `format` tag and the
/// `version` must be the expected ones (errors name the file and the key).
pub fn check_header(
    path: &Path,
    (format, version): (&str, u32),
    (want_format, want_version): (&str, u32),
) -> Result<()> {
    if format != want_format {
        return Err(Error::format(
            path,
            "format",
            format!("expected {want_format}, found {format}"),
        ));
    }
    if version != want_version {
        return Err(Error::format(
            path,
            "version",
            format!("expected {want_version}, found {version} (unsupported)"),
        ));
    }
    Ok(())
}

/// Reads JSON from `path`; a parse error names the file, the failing key
/// path where serde reports it, and the line.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_json(path, &text)
}

/// [`read_json`] on text already read from `path`.
fn parse_json<T: DeserializeOwned>(path: &Path, text: &str) -> Result<T> {
    serde_json::from_str(text).map_err(|e| {
        let key = if e.is_eof() {
            "(truncated file)".to_string()
        } else {
            format!("line {}", e.line())
        };
        Error::format(path, key, e)
    })
}

/// The header every document svkernel writes carries: its `format` tag
/// and `version` (the rest of the document is skipped).
#[derive(Clone, Debug, Default, PartialEq, serde::Deserialize)]
pub struct Header {
    pub format: Option<String>,
    pub version: Option<u32>,
}

/// Reads just the header of the JSON document at `path` ([`Header`]; both
/// fields `None` for JSON that is not an object).
pub fn read_header(path: &Path) -> Result<Header> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    header_of(path, &text)
}

fn header_of(path: &Path, text: &str) -> Result<Header> {
    if !text.trim_start().starts_with('{') {
        // (Truncated or empty files are worded by the full parse.)
        return parse_json::<serde::de::IgnoredAny>(path, text).map(|_| Header::default());
    }
    parse_json(path, text)
}

/// What a document of each `format` tag holds, in words.
fn describe(format: &str) -> Option<&'static str> {
    Some(match format {
        crate::forward::profile::PROFILE_FORMAT => {
            "a simulated profile, from `svkernel simulate profile`"
        }
        crate::forward::kernel::KERNEL_FORMAT => "a kernel tally, from `svkernel simulate kernels`",
        crate::metamodel::basis::BASIS_FORMAT => {
            "the basis BSSRDF model, from `svkernel fit profiles`"
        }
        crate::metamodel::meta::META_FORMAT => "the kernel meta-model, from `svkernel fit kernels`",
        crate::render::reference::REFERENCE_FORMAT => {
            "a reference tally, from `svkernel render --method reference`"
        }
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

/// Reads a versioned svkernel document: first just its header, so that a
/// file of another kind is refused by its `format` tag ("is a
/// `svkernel.kernels` document; expected a `svkernel.metamodel` document")
/// rather than by the first field it lacks, then the whole document.
/// Errors name the file and the key.
pub fn read_document<T: DeserializeOwned>(
    path: &Path,
    expected_format: &str,
    expected_version: u32,
) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let header = header_of(path, &text)?;
    let expected = document(expected_format);
    match header.format.as_deref() {
        None => {
            return Err(Error::format(
                path,
                "format",
                format!("not an svkernel document (no format tag); expected {expected}"),
            ));
        }
        Some(f) if f != expected_format => {
            let found = if describe(f).is_some() {
                document(f)
            } else {
                format!("a `{f}` document, not one svkernel writes")
            };
            return Err(Error::format(
                path,
                "format",
                format!("this is {found}; expected {expected}"),
            ));
        }
        Some(_) => {}
    }
    match header.version {
        Some(v) if v == expected_version => {}
        found => {
            let found = found.map_or("none".to_string(), |v| v.to_string());
            return Err(Error::format(
                path,
                "version",
                format!("expected {expected_version}, found {found} (unsupported)"),
            ));
        }
    }
    parse_json(path, &text)
}

/// Writes an f64 array as `.npy` (readable by `numpy.load`), atomically.
pub fn write_npy_atomic<D: ndarray::Dimension>(
    path: &Path,
    array: &ndarray::Array<f64, D>,
) -> Result<()> {
    use ndarray_npy::WriteNpyExt;
    write_atomic_with(path, |f| {
        array
            .write_npy(std::io::BufWriter::new(f))
            .map_err(|e| std::io::Error::other(e.to_string()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_and_read_back() {
        let dir = std::env::temp_dir().join(format!("svk-io-{}", std::process::id()));
        let p = dir.join("sub/x.json");
        write_json_atomic(&p, &serde_json::json!({"a": 1})).unwrap();
        let v: serde_json::Value = read_json(&p).unwrap();
        assert_eq!(v["a"], 1);
        // No temporary file left behind.
        let n = std::fs::read_dir(p.parent().unwrap()).unwrap().count();
        assert_eq!(n, 1);
        // A truncated file names itself.
        std::fs::write(&p, "{\"a\": ").unwrap();
        let e = read_json::<serde_json::Value>(&p).unwrap_err().to_string();
        assert!(e.contains("x.json") && e.contains("truncated"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn documents_are_told_apart_by_their_format_tag() {
        let dir = std::env::temp_dir().join(format!("svk-io-doc-{}", std::process::id()));
        let p = dir.join("doc.json");
        let read = |text: &str| {
            write_atomic(&p, text.as_bytes()).unwrap();
            read_document::<serde_json::Value>(&p, crate::metamodel::meta::META_FORMAT, 1)
                .map_err(|e| e.to_string())
        };
        let ok = r#"{"format": "svkernel.metamodel", "version": 1, "all": 3}"#;
        assert_eq!(read(ok).unwrap()["all"], 3);
        for (text, want) in [
            // Another svkernel document: both formats named, in words.
            (
                r#"{"paths": 1, "format": "svkernel.kernels", "version": 2}"#,
                &[
                    "doc.json",
                    "`svkernel.kernels`",
                    "kernel tally",
                    "`svkernel.metamodel`",
                ][..],
            ),
            (
                r#"{"format": "geojson", "version": 1}"#,
                &[
                    "`geojson`",
                    "not one svkernel writes",
                    "`svkernel.metamodel`",
                ],
            ),
            // Not an svkernel document at all.
            (
                r#"{"type": "FeatureCollection"}"#,
                &["doc.json", "not an svkernel document"],
            ),
            ("[1, 2, 3]", &["doc.json", "not an svkernel document"]),
            // The right kind, another version.
            (
                r#"{"format": "svkernel.metamodel", "version": 7}"#,
                &["version", "expected 1, found 7"],
            ),
            (
                r#"{"format": "svkernel.metamodel"}"#,
                &["version", "expected 1, found none"],
            ),
            // Damaged: still named as before.
            (r#"{"format": "svkernel.meta"#, &["doc.json", "truncated"]),
        ] {
            let e = read(text).unwrap_err();
            for w in want {
                assert!(e.contains(w), "{text}: '{w}' not in: {e}");
            }
            assert!(!e.contains("Some(") && !e.contains("None"), "{e}");
        }
        write_atomic(&p, b"[1]").unwrap();
        assert_eq!(
            read_header(&p).unwrap(),
            Header {
                format: None,
                version: None
            }
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
