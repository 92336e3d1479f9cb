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
    serde_json::from_str(&text).map_err(|e| {
        let key = if e.is_eof() {
            "(truncated file)".to_string()
        } else {
            format!("line {}", e.line())
        };
        Error::format(path, key, e)
    })
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

/// `#[serde(with = "crate::io::nan_as_null")]` on an `f64` field that can
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
