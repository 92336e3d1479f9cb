//! Provenance recorded in every output: what made it.

use serde::{Deserialize, Serialize};

/// Who, what and when of an output file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// Crate version.
    pub version: String,
    /// `git rev-parse HEAD` at build time if available, at run time otherwise.
    pub git_commit: Option<String>,
    /// The command line, as given.
    pub command_line: Vec<String>,
    /// Rayon worker threads.
    pub threads: usize,
    /// Seconds since the Unix epoch at creation.
    pub created_unix_s: u64,
}

impl Provenance {
    /// Provenance of the running process.
    pub fn current() -> Self {
        Provenance {
            version: env!("CARGO_PKG_VERSION").to_string(),
            git_commit: git_commit(),
            command_line: std::env::args().collect(),
            threads: rayon::current_num_threads(),
            created_unix_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0),
        }
    }
}

fn git_commit() -> Option<String> {
    let out = std::process::Command::new("git")
        .args(["rev-parse", "HEAD"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stderr(std::process::Stdio::null())
        .output()
        .ok()?;
    let s = String::from_utf8(out.stdout).ok()?.trim().to_string();
    (out.status.success() && !s.is_empty()).then_some(s)
}
