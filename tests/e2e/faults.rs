//! End-to-end: faults injected into the flat canister mission (`scenarios/faults/*.toml`, kinematic)
//! through the Debugger are detected and recovered by Autonomy, and the mission still succeeds; a
//! Mission-context run refuses the injection.

use std::path::Path;
use std::process::{Command, Output};

mod common;
use common::*;

fn run(scenario: &str, out: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rover-twin"))
        .arg("run")
        .arg(root().join("scenarios/faults").join(scenario))
        .arg("--out")
        .arg(out)
        .args(["--quiet", "--set", "logging.rrd=false", "--set", "logging.mcap=false"])
        .args(extra)
        .output()
        .unwrap()
}

fn responses(s: &serde_json::Value) -> Vec<String> {
    s["faults"]
        .as_array()
        .map(|f| f.iter().map(|f| format!("{} -> {}", f["fault"], f["response"])).collect())
        .unwrap_or_default()
}

#[test]
fn a_navigator_crash_during_the_approach_is_restarted_and_the_mission_succeeds() {
    let dir = tempfile::tempdir().unwrap();
    let o = run("module_crash.toml", dir.path(), &[]);
    let s = score(dir.path());
    assert_eq!(o.status.code(), Some(0), "{}\n{s}", show(&o));
    assert!(s["metrics"]["isolated_modules"]["navigator"].is_string(), "{s}");
    let r = responses(&s);
    assert!(
        r.iter().any(|r| r.contains("'navigator' is isolated") && r.contains("restart 'navigator'")),
        "{r:?}"
    );
    assert_eq!(s["metrics"]["canister_stowed"], true);
}

#[test]
fn an_arm_servo_trip_during_the_acquisition_is_recovered_and_the_mission_succeeds() {
    let dir = tempfile::tempdir().unwrap();
    let o = run("arm_joint_fault.toml", dir.path(), &[]);
    let s = score(dir.path());
    assert_eq!(o.status.code(), Some(0), "{}\n{s}", show(&o));
    assert!(responses(&s).iter().any(|r| r.contains("is in fault") && r.contains("retry")), "{s}");

    // The same scenario in a Mission context: the Debugger refuses to inject, nothing happens; the
    // mission succeeds but the scenario's criterion (the fault handled) is not met: exit 1.
    let dir = tempfile::tempdir().unwrap();
    let o = run("arm_joint_fault.toml", dir.path(), &["--set", "run.purpose=\"mission\""]);
    let s = score(dir.path());
    assert_eq!(o.status.code(), Some(1), "{}\n{s}", show(&o));
    assert!(responses(&s).is_empty(), "{s}");
    assert!(s["phases"].as_array().unwrap().iter().all(|p| p["success"] == true), "{s}");
    let unmet: Vec<&serde_json::Value> =
        s["criteria"].as_array().unwrap().iter().filter(|c| c["passed"] == false).collect();
    assert!(unmet.len() == 1 && unmet[0]["value"] == "no fault reported", "{unmet:?}");
}

#[test]
fn a_locomotion_crash_mid_drive_stops_the_rover_at_once_and_the_system_ends_safe() {
    let dir = tempfile::tempdir().unwrap();
    let o = rover_twin()
        .arg("run")
        .arg(root().join("scenarios/fault_locomotion_crash.toml"))
        .arg("--out")
        .arg(dir.path())
        .args(["--quiet", "--set", "logging.rrd=false", "--set", "logging.mcap=false"])
        .output()
        .unwrap();
    let s = score(dir.path());
    assert_eq!(o.status.code(), Some(0), "{}\n{s}", show(&o));
    assert!(s["metrics"]["isolated_modules"]["locomotion"].is_string(), "{s}");
    let travel = s["criteria"].as_array().unwrap().iter().find(|c| c["name"] == "travel after 10 s").unwrap();
    assert_eq!(travel["passed"], true, "{travel}");
    // Stopped by the safing hook at once, well inside what the deadman would allow (0.3 m/s x 0.25 s).
    let moved: f64 = travel["value"].as_str().unwrap().trim_end_matches(" m").parse().unwrap();
    assert!(moved < 0.075, "{moved} m after the crash");
    assert_eq!(s["phases"][0]["status"], "failed", "{s}");
}
