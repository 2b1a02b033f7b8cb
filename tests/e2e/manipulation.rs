//! End-to-end: the arm acquires and stows the canister (`scenarios/acquire_stow.toml`: the rover
//! parked, the canister at arm's reach, only the wrist camera rendering), in both fidelities; and the
//! same grasp with the visual servoing switched off.

use std::path::Path;
use std::process::{Command, Output};

mod common;
use common::*;

fn run(out: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rover-twin"))
        .arg("run")
        .arg(root().join("scenarios/acquire_stow.toml"))
        .arg("--out")
        .arg(out)
        .args(["--quiet", "--set", "logging.rrd=false", "--set", "logging.mcap=false"])
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn the_arm_acquires_and_stows_the_canister_under_visual_servoing_in_both_fidelities() {
    for fidelity in ["kinematic", "dynamic"] {
        let dir = tempfile::tempdir().unwrap();
        let o = run(dir.path(), &["--fidelity", fidelity]);
        assert_eq!(o.status.code(), Some(0), "{fidelity}: {}", show(&o));
        let m = &score(dir.path())["metrics"];
        assert_eq!(m["canister_stowed"], true, "{fidelity}: {m}");
        // The handle within a centimetre of the tool centre point when the fingers closed.
        let err = m["grasp_position_error_m"].as_f64().unwrap();
        assert!(err < 0.01, "{fidelity}: grasped {err} m off the handle");
        assert_eq!(m["self_collisions"], 0, "{fidelity}: {m}");
    }
}

#[test]
fn the_servoed_grasp_lands_nearer_the_handle_than_an_open_loop_one_from_the_same_first_view() {
    // The same seeds (the same calibration errors and placements) with and without servoing, one
    // grasp each. Open loop, the arm goes where the first view of the handle put it through the
    // believed kinematics; servoed, the wrist camera closes the loop. (With the twin's calibration
    // errors and a first view from the near look pose the open-loop grasp is 1-1.5 cm off: within
    // the gripper's capture, so it holds too; the servoed one is nearer every time.)
    for seed in ["1", "2", "3"] {
        let grasp = |servo_steps: &str| {
            let dir = tempfile::tempdir().unwrap();
            let steps = format!("modules.manipulator_control.params.max_servo_steps={servo_steps}");
            let o = run(
                dir.path(),
                &[
                    "--fidelity",
                    "kinematic",
                    "--seed",
                    seed,
                    "--set",
                    &steps,
                    "--set",
                    "modules.manipulation.params.max_attempts=1",
                ],
            );
            let s = score(dir.path());
            let err = s["metrics"]["grasp_position_error_m"].as_f64();
            (err.unwrap_or_else(|| panic!("seed {seed}, {servo_steps} servo steps: no grasp\n{}", show(&o))))
                .max(0.0)
        };
        let (servoed, open) = (grasp("10"), grasp("0"));
        assert!(servoed < 0.01, "seed {seed}: the servoed grasp {servoed} m off the handle");
        assert!(servoed < open, "seed {seed}: servoed {servoed} m, open loop {open} m off the handle");
    }
}

#[test]
fn a_canister_nearer_than_the_look_poses_see_is_found_after_backing_up() {
    // 0.7 m ahead, the canister lies under the wrist camera's nearest view (0.9-1.35 m ahead): no
    // look pose sees anything of it. Backing up once (search_back_m) brings it into view; without
    // the back-up the acquisition fails.
    let near = ["--fidelity", "kinematic", "--set", "canister.x=0.7"];
    let dir = tempfile::tempdir().unwrap();
    let o = run(dir.path(), &near);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let m = &score(dir.path())["metrics"];
    assert_eq!(m["canister_stowed"], true, "{m}");
    assert!(m["distance_m"].as_f64().unwrap() > 0.3, "the rover did not back up: {m}");

    let dir = tempfile::tempdir().unwrap();
    let never = [&near[..], &["--set", "modules.manipulation.params.search_back_m=0"]].concat();
    let o = run(dir.path(), &never);
    assert_eq!(o.status.code(), Some(1), "{}", show(&o));
    let s = score(dir.path());
    assert_eq!(s["phases"][0]["status"], "failed", "{s}");
}
