//! What the command-line tests share.

use std::process::Command;

/// The binary, with the built-in models (the variables that override them
/// removed) and a cache of this test run's own.
pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_svkernel"));
    for v in ["SVKERNEL_BASIS", "SVKERNEL_BASIS_DIFFUSE", "SVKERNEL_MODEL"] {
        c.env_remove(v);
    }
    c.env(
        "SVKERNEL_CACHE",
        std::env::temp_dir().join(format!("svk-cache-{}", std::process::id())),
    );
    c
}
