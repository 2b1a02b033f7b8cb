//! End-to-end tests of the workbench. The tests live in `tests/tests/` and drive the `rover-twin`
//! binary the way a user does; this library only carries helpers they share.

use std::path::PathBuf;
use std::process::Command;

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// A `rover-twin` command built from this workspace (through cargo, same profile as the tests).
pub fn rover_twin() -> Command {
    let mut c = Command::new(env!("CARGO"));
    c.current_dir(workspace_root()).args(["run", "--quiet", "-p", "scenarios", "--bin", "rover-twin", "--"]);
    c
}
