//! What the end-to-end tests share: the `rover-twin` binary, the repository's folders, and reading
//! a run's output back. Each test file is its own crate and uses what it needs of these.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `rover-twin` binary under test.
pub fn rover_twin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rover-twin"))
}

/// The repository's root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// A file of `tests/e2e/data`.
pub fn data(name: &str) -> PathBuf {
    root().join("tests/e2e/data").join(name)
}

/// A command's output, for assertion messages.
pub fn show(o: &Output) -> String {
    format!(
        "stdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A JSON file.
pub fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// A run's `score.json`.
pub fn score(out: &Path) -> serde_json::Value {
    json(&out.join("score.json"))
}
