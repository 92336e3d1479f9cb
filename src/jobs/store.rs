//! The document store: every file read and write of the jobs. Writes are
//! atomic (temporary file + rename, so a crash never leaves a partial
//! output); reads name the file in every error; versioned documents are
//! checked by [`crate::doc`].

use crate::doc::Document;
use crate::error::{Error, Result};
use crate::forward::kernel::KernelDoc;
use crate::forward::profile::ProfileDoc;
use crate::forward::runner::CheckpointStore;
use crate::metamodel::basis::BasisModel;
use crate::metamodel::meta::MetaModelFile;
use serde::{Serialize, de::DeserializeOwned};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Writes `bytes` to `path` atomically: to a temporary file in the same
/// folder (created if missing; a failure to create it is reported), flushed,
/// then renamed over `path` ([`tempfile`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// The folder a file of `path` goes into, created (errors name it).
fn folder_of(path: &Path) -> Result<&Path> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    Ok(dir)
}

/// The temporary files that outputs are written to before they are renamed
/// into place: `.tmp-*`, created with mode 0666 less the umask, as a plain
/// file would be (not the 0600 of a private temporary file).
fn temp_builder() -> tempfile::Builder<'static, 'static> {
    let mut b = tempfile::Builder::new();
    b.prefix(".tmp-");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        b.permissions(std::fs::Permissions::from_mode(0o666));
    }
    b
}

/// Like [`write_atomic`], with a writer callback.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> Result<()> {
    let dir = folder_of(path)?;
    let mut tmp = temp_builder()
        .tempfile_in(dir)
        .map_err(|e| Error::io(dir, e))?;
    write(tmp.as_file_mut())
        .and_then(|()| tmp.as_file().sync_all())
        .map_err(|e| Error::io(path, e))?;
    tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
    Ok(())
}

/// Runs `write` on a temporary path beside `path` that keeps its extension
/// (for writers that pick the format from it, such as the plot backends),
/// then renames it into place; on failure nothing is left behind.
pub fn write_atomic_path<E: std::fmt::Display>(
    path: &Path,
    write: impl FnOnce(&Path) -> std::result::Result<(), E>,
) -> Result<()> {
    let dir = folder_of(path)?;
    let ext = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    let tmp = temp_builder()
        .suffix(&ext)
        .tempfile_in(dir)
        .map_err(|e| Error::io(dir, e))?
        .into_temp_path();
    write(&tmp).map_err(|e| Error::format(path, "(write)", e))?;
    tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
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

/// Reads and parses JSON from `path` (any type; for versioned documents use
/// [`load`]); errors name the file and the line.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| crate::doc::json_error(path, e))
}

/// The `format` tag of the JSON document at `path` ([`crate::doc::format_of`]).
pub fn read_format(path: &Path) -> Result<Option<String>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    crate::doc::format_of(&text, path)
}

/// Loads a versioned document ([`crate::doc::from_json`]): a file of
/// another kind is named by its `format` tag; errors name the file.
pub fn load<T: Document>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    crate::doc::from_json(&text, path)
}

macro_rules! loadable {
    ($($t:ty),*) => {$(
        impl $t {
            /// Loads and validates the document at `path` ([`load`]).
            pub fn load(path: &Path) -> Result<Self> {
                load(path)
            }
        }
    )*};
}
loadable!(
    ProfileDoc,
    KernelDoc,
    BasisModel,
    MetaModelFile,
    crate::jobs::render::ReferenceDoc,
    crate::jobs::render::RenderDoc,
    crate::jobs::compare::CompareDoc,
    crate::jobs::experiments::ExperimentsDoc
);

/// A content hash (SHA-256, first 64 bits, hex) of byte strings, each
/// terminated so that `["ab", "c"]` and `["a", "bc"]` differ. It names cache
/// entries and identifies reference simulations.
pub fn content_hash<'a>(parts: impl IntoIterator<Item = &'a [u8]>) -> String {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    h.finalize()[..8]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// A checkpoint kept in a file, replaced atomically
/// ([`crate::forward::runner::CheckpointStore`]).
#[derive(Debug, Clone)]
pub struct FileCheckpoint(pub PathBuf);

impl FileCheckpoint {
    pub fn arc(path: impl Into<PathBuf>) -> Arc<dyn CheckpointStore> {
        Arc::new(FileCheckpoint(path.into()))
    }
}

impl CheckpointStore for FileCheckpoint {
    fn origin(&self) -> &Path {
        &self.0
    }
    fn load(&self) -> Result<Option<Vec<u8>>> {
        match std::fs::read(&self.0) {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(Error::io(&self.0, e)),
        }
    }
    fn save(&self, bytes: &[u8]) -> Result<()> {
        write_atomic(&self.0, bytes)
    }
    fn clear(&self) -> Result<()> {
        match std::fs::remove_file(&self.0) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(&self.0, e)),
            _ => Ok(()),
        }
    }
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
        // Created as a plain file would be: mode 0666 less the umask (which
        // never removes the owner's read bit), not 0600.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let probe = dir.join("probe");
            std::fs::write(&probe, "").unwrap();
            let mode = |f: &Path| std::fs::metadata(f).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode(&p), mode(&probe));
            std::fs::remove_file(&probe).unwrap();
        }
        // A truncated file names itself.
        std::fs::write(&p, "{\"a\": ").unwrap();
        let e = read_json::<serde_json::Value>(&p).unwrap_err().to_string();
        assert!(e.contains("x.json") && e.contains("truncated"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
