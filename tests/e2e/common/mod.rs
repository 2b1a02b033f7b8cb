//! What the end-to-end tests share: the `rover-twin` binary, the repository's folders, and reading
//! a run's output back. Each test file is its own crate and uses what it needs of these.

#![allow(dead_code)]

use std::collections::BTreeMap;
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

/// `rover-twin run SCENARIO --out OUT --quiet EXTRA...`.
pub fn run(scenario: &Path, out: &Path, extra: &[&str]) -> Output {
    rover_twin().arg("run").arg(scenario).arg("--out").arg(out).arg("--quiet").args(extra).output().unwrap()
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

/// Messages per topic of an MCAP file, checking CRCs, the summary and monotonic log times.
pub fn read_mcap(path: &Path) -> BTreeMap<String, Vec<serde_json::Value>> {
    let bytes = std::fs::read(path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary section");
    let stats = summary.stats.as_ref().expect("statistics");
    assert!(!summary.chunk_indexes.is_empty(), "chunk indexes");
    let mut out: BTreeMap<String, Vec<serde_json::Value>> = BTreeMap::new();
    let mut last = 0u64;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        assert!(m.log_time >= last, "log times go backwards on {}", m.channel.topic);
        last = m.log_time;
        let schema = m.channel.schema.as_ref().expect("every channel has a schema");
        assert_eq!(schema.encoding, "jsonschema");
        serde_json::from_slice::<serde_json::Value>(&schema.data).expect("schema is JSON");
        out.entry(m.channel.topic.clone()).or_default().push(serde_json::from_slice(&m.data).unwrap());
    }
    assert_eq!(stats.message_count, out.values().map(|v| v.len() as u64).sum::<u64>());
    out
}
