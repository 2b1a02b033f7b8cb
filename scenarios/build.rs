//! Records the git commit the binary is built from (`ROVER_TWIN_GIT_COMMIT`, "unknown" outside a
//! git checkout), for the provenance a sweep writes into its summary and `sweep merge` checks.
//! Reruns only when HEAD or a branch moves, not on every source edit.

use std::path::Path;
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let o = Command::new("git").args(args).output().ok()?;
    o.status.success().then(|| String::from_utf8_lossy(&o.stdout).trim().to_string())
}

fn main() {
    let commit = git(&["rev-parse", "HEAD"]).unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=ROVER_TWIN_GIT_COMMIT={commit}");
    // Without a rerun-if-changed line cargo would rerun this script on any change in the package.
    println!("cargo:rerun-if-changed=build.rs");
    // HEAD lives in the checkout's git dir; branches in the common one (they differ in a worktree).
    let dirs = [
        git(&["rev-parse", "--absolute-git-dir"]),
        git(&["rev-parse", "--path-format=absolute", "--git-common-dir"]),
    ];
    for dir in dirs.into_iter().flatten() {
        for p in ["HEAD", "refs/heads", "packed-refs"] {
            let path = Path::new(&dir).join(p);
            // A path that does not exist would make cargo rerun the script every build.
            if path.exists() {
                println!("cargo:rerun-if-changed={}", path.display());
            }
        }
    }
}
