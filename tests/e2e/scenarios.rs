//! End-to-end: `rover-twin run`, `check` and `sweep` as a user runs them, with their files read back
//! (score.json, MCAP with the mcap crate, the Rerun recording with rerun's own decoder).

#![allow(clippy::disallowed_methods)] // the tests time out their child processes on the wall clock

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::*;

/// Entity paths of a Rerun recording's data store.
fn rrd_entities(path: &Path) -> BTreeSet<String> {
    use rerun::external::re_log_encoding::DecoderApp;
    use rerun::log::{Chunk, LogMsg};
    let reader = std::io::BufReader::new(std::fs::File::open(path).unwrap());
    let mut out = BTreeSet::new();
    for msg in DecoderApp::decode_lazy(reader) {
        if let LogMsg::ArrowMsg(store, arrow) = msg.unwrap()
            && store.is_recording()
        {
            out.insert(Chunk::from_arrow_msg(&arrow).unwrap().entity_path().to_string());
        }
    }
    out
}

#[test]
fn a_short_run_succeeds_scores_and_writes_valid_logs() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&data("short.toml"), dir.path(), &[]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let s = score(dir.path());
    assert_eq!(s["success"], true);
    assert_eq!(s["scenario"], "short");
    for k in ["seed", "sim_time_s", "wall_time_s", "phases", "metrics"] {
        assert!(s.get(k).is_some(), "score.json lacks {k}");
    }
    let m = &s["metrics"];
    for k in [
        "distance_m",
        "final_position_error_m",
        "position_error_rms_m",
        "canister_stowed",
        "collisions",
        "max_tilt_deg",
        "module_cpu_s",
    ] {
        assert!(m.get(k).is_some(), "metrics lack {k}");
    }
    assert!(m["distance_m"].as_f64().unwrap() > 2.5, "{m}");
    assert!(m["module_cpu_s"]["locomotion"].as_f64().unwrap() > 0.0);
    let phases = s["phases"].as_array().unwrap();
    assert_eq!(phases.len(), 2);
    assert!(phases.iter().all(|p| p["success"] == true && p["end_s"].as_f64() >= p["start_s"].as_f64()));

    // MCAP: Foxglove schemas, counts that match the configured rates.
    let topics = read_mcap(&dir.path().join("run.mcap"));
    let sim = s["sim_time_s"].as_f64().unwrap();
    let tf = &topics["/tf"];
    let links = tf.iter().filter(|m| m["child_frame_id"] == "base_link").count();
    // Truth at 10 Hz (defaults) over the run.
    assert!((links as f64 - sim * 10.0).abs() <= 2.0, "{links} base_link transforms over {sim} s");
    // The last `turn_to` faced a point 4 m south of the goal: the rover heads -90 deg.
    let q = &tf.iter().rfind(|m| m["child_frame_id"] == "base_link").unwrap()["rotation"];
    let [w, x, y, z] = ["w", "x", "y", "z"].map(|k| q[k].as_f64().unwrap());
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z)).to_degrees();
    // (Faced from where the estimate put the rover when the command came: the skid turn of
    // 180 deg moves the rover and the estimate's heading drifts, 9 deg off in the last run.)
    assert!((yaw + 90.0).abs() < 15.0, "heading {yaw} deg after facing the point south");
    assert!(topics["/estimate/localization/pose"].len() as f64 >= sim * 10.0 - 2.0);
    assert_eq!(topics["/world/terrain"].len(), 1);
    assert!(topics["/events"].iter().any(|e| e["message"].as_str().unwrap().contains("module_lifecycle")));
    assert!(topics["/messages"].iter().any(|m| m["kind"] == "ack"));
    assert_eq!(topics["/score"].len(), 1);
    // Foxglove's 3D scene: the robot's links as entities locked to the frames /tf moves, the
    // terrain mesh, the true track.
    let entities = |topic: &str| -> Vec<serde_json::Value> {
        topics[topic].iter().flat_map(|u| u["entities"].as_array().unwrap().clone()).collect()
    };
    let robot = entities("/scene/robot");
    let frames: BTreeSet<&str> = tf.iter().map(|t| t["child_frame_id"].as_str().unwrap()).collect();
    assert!(robot.len() > 20, "{} robot entities", robot.len());
    for e in &robot {
        assert_eq!(e["frame_locked"], true, "{e}");
        assert!(frames.contains(e["frame_id"].as_str().unwrap()), "{} has no transform", e["frame_id"]);
    }
    let terrain = entities("/scene/world").into_iter().find(|e| e["id"] == "terrain").expect("terrain");
    let mesh = &terrain["triangles"][0];
    let (points, indices) = (mesh["points"].as_array().unwrap().len(), mesh["indices"].as_array().unwrap());
    assert!(points > 100 && indices.len() % 3 == 0, "{points} points, {} indices", indices.len());
    assert!(indices.iter().all(|i| (i.as_u64().unwrap() as usize) < points), "indices within the points");
    // The true track's newest message (what a viewer shows after a seek to the end) is all of it.
    let last = &topics["/scene/tracks/truth"].last().unwrap()["entities"][0];
    let points = last["lines"][0]["points"].as_array().unwrap().len();
    assert!(points as f64 >= sim - 2.0, "{points} points of the true track over {sim} s");
    // Rerun: the entity tree.
    let ents = rrd_entities(&dir.path().join("run.rrd"));
    for e in [
        "/world/terrain",
        "/world/truth/base_link",
        "/world/truth/arm_link_1",
        "/world/estimate/localization_pose",
        "/logs/events",
        "/score",
    ] {
        assert!(ents.contains(e), "{e} missing from the recording: {ents:?}");
    }
    assert!(ents.iter().any(|e| e.starts_with("/plots/errors/")), "{ents:?}");
}

#[test]
fn the_same_seed_gives_the_same_score_and_trajectory() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    for d in [&a, &b] {
        let o = run(&data("short.toml"), d.path(), &["--seed", "42"]);
        assert!(o.status.code().is_some_and(|c| c < 2), "{}", show(&o));
    }
    let strip = |mut v: serde_json::Value| {
        let o = v.as_object_mut().unwrap();
        o.remove("wall_time_s");
        o.remove("speed");
        o.remove("logs");
        o["metrics"].as_object_mut().unwrap().remove("module_cpu_s");
        v
    };
    assert_eq!(strip(score(a.path())), strip(score(b.path())));
    let tf = |d: &Path| read_mcap(&d.join("run.mcap")).remove("/tf").unwrap();
    assert_eq!(tf(a.path()), tf(b.path()), "ground-truth trajectories differ");
    // Another seed changes the noise, hence the estimate.
    let c = tempfile::tempdir().unwrap();
    run(&data("short.toml"), c.path(), &["--seed", "43"]);
    assert_ne!(
        score(a.path())["metrics"]["final_position_error_m"],
        score(c.path())["metrics"]["final_position_error_m"]
    );
}

#[test]
fn exit_codes_tell_success_mission_failure_and_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    // An unreachable goal: the plan runs, the criterion fails.
    let o =
        run(&data("short.toml"), dir.path(), &["--fidelity", "kinematic", "--set", "criteria.goal.x=9.0"]);
    assert_eq!(o.status.code(), Some(1), "{}", show(&o));
    let s = score(dir.path());
    assert_eq!(s["outcome"], "mission_failure");
    assert!(s["criteria"].as_array().unwrap().iter().any(|c| c["passed"] == false));
    // A misspelt override names itself.
    let o = run(&data("short.toml"), dir.path(), &["--set", "run.time_limt_s=3"]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--set run.time_limt_s=3") && err.contains("unknown field"), "{err}");
    // A phase for a module the system does not have: not run, naming it, and not a success.
    let text = std::fs::read_to_string(data("short.toml"))
        .unwrap()
        .replace("../../../scenarios", &root().join("scenarios").display().to_string())
        + "\n[[phase]]\nname = \"acquire\"\nsteps = [{ to = \"manipulation\", command = \"acquire_canister\" }]\n";
    let p = dir.path().join("missing_module.toml");
    std::fs::write(&p, text).unwrap();
    let o = run(&p, dir.path(), &["--fidelity", "kinematic"]);
    assert_eq!(o.status.code(), Some(1), "{}", show(&o));
    let s = score(dir.path());
    let acquire = s["phases"].as_array().unwrap().iter().find(|p| p["name"] == "acquire").unwrap().clone();
    assert_eq!((acquire["status"].as_str(), acquire["success"].as_bool()), (Some("not_run"), Some(false)));
    assert!(acquire["reason"].as_str().unwrap().contains("manipulation"), "{acquire}");
}

#[test]
fn the_flat_mission_finds_acquires_and_stows_the_canister_from_its_cameras() {
    // Point, locate (TrackingTarget on the operator's box), approach in legs
    // (CoordinatorVisualTracking), acquire (the wrist camera's markers, the grasp under visual
    // servoing: CoordinatorManipulation and ManipulatorControl), stow, return; the plan names no
    // canister coordinates.
    let dir = tempfile::tempdir().unwrap();
    let o = run(
        &root().join("scenarios/canister_acquisition_flat.toml"),
        dir.path(),
        &["--fidelity", "kinematic"],
    );
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let s = score(dir.path());
    let phase =
        |name: &str| s["phases"].as_array().unwrap().iter().find(|p| p["name"] == name).unwrap().clone();
    for name in ["point", "locate", "approach", "acquire", "stow", "return"] {
        assert_eq!(phase(name)["status"], "succeeded", "phase {name}: {}", show(&o));
    }
    assert_eq!(s["metrics"]["canister_stowed"], true);
    assert_eq!(s["metrics"]["self_collisions"], 0);
    // The approach ended within its 1.5 m of the canister (the true track), the rover then back
    // at its start (the return phase drove it there).
    let end = phase("approach")["end_s"].as_f64().unwrap();
    let track = std::fs::read_to_string(dir.path().join("track.csv")).unwrap();
    let at_end = track
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse::<f64>().unwrap()).collect::<Vec<f64>>())
        .min_by(|a, b| (a[0] - end).abs().total_cmp(&(b[0] - end).abs()))
        .unwrap();
    let d = (at_end[1] - 3.0).hypot(at_end[2]);
    assert!(d < 1.5, "the approach ended {d:.2} m from the canister");
    assert_eq!(phase("return")["status"], "succeeded");
    // The fused location the approach ended on agrees with the truth within its uncertainty
    // (later the arm moves the canister, and the tracker may follow it).
    let topics = read_mcap(&dir.path().join("run.mcap"));
    let targets = &topics["/slots/tracking/target"];
    let located = targets
        .iter()
        .rev()
        .filter(|t| t["stamp"].as_f64().unwrap() <= end * 1e9)
        .find(|t| t["value"]["position"].is_array())
        .expect("a location");
    let p: Vec<f64> =
        located["value"]["position"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let c = &located["value"]["covariance"];
    let sigma = (c[0].as_f64().unwrap() + c[4].as_f64().unwrap()).sqrt();
    let err = (p[0] - 3.0).hypot(p[1]);
    assert!(
        err < 3.0 * sigma + 0.1 && err < 0.3,
        "located {err:.2} m from the canister (sigma {sigma:.2} m)"
    );
    // The canister's pose from the wrist camera's markers when it first saw it (from the look
    // pose, before the arm took it) agrees with the truth (3, 0, yaw 180) within its uncertainty
    // (the pose estimate's included) and a few centimetres.
    let objects = &topics["/slots/tracking/wrist/objects"];
    let acquire_start = phase("acquire")["start_s"].as_f64().unwrap();
    let first =
        objects.iter().filter(|r| r["stamp"].as_f64().unwrap() >= acquire_start * 1e9).find_map(|r| {
            r["value"]["objects"]
                .as_array()
                .unwrap()
                .iter()
                .find(|o| o["object"] == "canister" && o["seen_frames"].as_u64().unwrap() >= 3)
                .cloned()
        });
    let o = first.expect("the canister seen by the wrist camera");
    let t: Vec<f64> =
        o["map_from_object"]["translation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let c = &o["map_covariance"];
    let sigma = (c[0].as_f64().unwrap() + c[7].as_f64().unwrap()).sqrt();
    let err = (t[0] - 3.0).hypot(t[1]);
    assert!(
        err < 3.0 * sigma + 0.03 && err < 0.15,
        "markers place the canister {err:.3} m off (sigma {sigma:.3})"
    );
    let q: Vec<f64> =
        o["map_from_object"]["rotation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let yaw = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]))
        .euler_angles()
        .2
        .to_degrees();
    assert!((yaw.abs() - 180.0).abs() < 5.0, "canister yaw {yaw:.1} deg for 180");
    // Facing it: the markers' canister is ahead of base_link.
    let b: Vec<f64> = o["base_from_object"]["translation"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let bearing = b[1].atan2(b[0]).to_degrees();
    assert!(bearing.abs() < 15.0, "the canister {bearing:.1} degrees off the rover's heading");
    // The scripted operator marked the canister in the first head-camera image (operator input).
    let sel = &topics["/slots/operator/target_selection"];
    assert_eq!(sel.len(), 1);
    let v = &sel[0]["value"];
    assert_eq!(
        (v["source"].as_str(), v["target"].as_str(), v["camera"].as_str()),
        (Some("operator"), Some("canister"), Some("head_stereo"))
    );
    let b: Vec<f64> = v["bbox"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    // 7 m straight ahead on flat ground: a small box near the image's vertical centre line.
    assert!(b[0] < b[2] && b[1] < b[3] && b[2] - b[0] < 40.0, "{b:?}");
    assert!(((b[0] + b[2]) / 2.0 - 320.0).abs() < 40.0, "{b:?}");
}

/// Runs visual_approach: it succeeds, the rover within 2 m of the canister and facing it.
fn visual_approach_reaches_the_canister() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&root().join("scenarios/visual_approach.toml"), dir.path(), &[]);
    let s = score(dir.path());
    assert_eq!(o.status.code(), Some(0), "{}\n{s:#}", show(&o));
    let m = &s["metrics"];
    assert!(m["canister_distance_m"].as_f64().unwrap() <= 2.0, "{m}");
    assert!(m["canister_bearing_deg"].as_f64().unwrap().abs() <= 15.0, "{m}");
}

#[test]
fn point_locate_approach_track_reaches_a_canister_17_m_away_on_rough_ground() {
    // visual_approach: full dynamics on the Mars-like yard, the rover steering with its own pose
    // estimate, the canister known only from the operator's box and the cameras. (Its locations
    // fused at their own depth rather than the estimate's, a rock 2.5 m in front of the canister
    // on its line of sight takes the estimate over and the approach ends 4.2 m from it.)
    visual_approach_reaches_the_canister();
}

#[test]
fn bad_scenario_files_give_exact_locations() {
    let dir = tempfile::tempdir().unwrap();
    let base = std::fs::read_to_string(data("short.toml"))
        .unwrap()
        .replace("../../../scenarios", &root().join("scenarios").display().to_string());
    let cases: &[(&str, &str, &str)] = &[
        // (replace, with, expected "file:line" + text)
        ("timeout_s = 10.0 }", "timeout_s = 10.0, speeed = 1 }", ":20:"),
        ("time_limit_s = 60.0", "time_limit_s = -1.0", ":16:"),
        ("file = \"flat_yard.toml\"", "file = 7", ":7:"),
    ];
    for (i, (from, to, at)) in cases.iter().enumerate() {
        let p = dir.path().join(format!("bad{i}.toml"));
        assert!(base.contains(from), "{from}");
        std::fs::write(&p, base.replacen(from, to, 1)).unwrap();
        for cmd in [vec!["check"], vec!["run", "--quiet", "--out", "/nonexistent/never"]] {
            let o = rover_twin().args(&cmd).arg(&p).output().unwrap();
            assert_eq!(o.status.code(), Some(2), "{}", show(&o));
            let err = String::from_utf8_lossy(&o.stderr);
            assert!(err.contains(&format!("bad{i}.toml{at}")), "case {i} ({cmd:?}): {err}");
        }
    }
    let o = rover_twin()
        .arg("check")
        .arg(root().join("scenarios/traverse.toml"))
        .arg(root().join("worlds/mars_yard.toml"))
        .arg(root().join("scenarios/canister_sweep.toml"))
        .arg(root().join("scenarios/config/modules/arm.toml"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    // A sweep dispersing a key the scenario does not have: located at the dispersion's key.
    let sweep = dir.path().join("bad_sweep.toml");
    let sw = std::fs::read_to_string(data("sweep.toml"))
        .unwrap()
        .replace(
            "scenario = \"short.toml\"",
            &format!("scenario = {:?}", data("short.toml").display().to_string()),
        )
        .replace("key = \"rover.y\"", "key = \"rover.why\"");
    std::fs::write(&sweep, sw).unwrap();
    let o = rover_twin().arg("check").arg(&sweep).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad_sweep.toml:10:") && err.contains("why"), "{err}");
    // A module configuration with a pose outside the joint limits.
    let arm = dir.path().join("arm.toml");
    std::fs::write(&arm, "[framework]\nperiod_s = 0.1\n[params.poses]\nbad = [9.0, 0, 0, 0, 0, 0]\n")
        .unwrap();
    let o = rover_twin().arg("check").arg(&arm).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("arm.toml"), "{}", show(&o));
}

fn interrupt(pid: u32) {
    // The shell's own `kill`: no procps needed.
    let st = Command::new("sh").args(["-c", &format!("kill -INT {pid}")]).status().unwrap();
    assert!(st.success());
}

#[test]
fn sigint_during_a_run_leaves_complete_valid_logs() {
    let dir = tempfile::tempdir().unwrap();
    let mut child = rover_twin()
        .arg("run")
        .arg(root().join("scenarios/traverse.toml"))
        // Without the localization pair's rendering: the run must get a few simulated tens of
        // seconds far in the wall time below also when the tests beside it load the machine.
        .args(["--quiet", "--set", "modules.cameras.params.loc_stereo_hz=0", "--out"])
        .arg(dir.path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !dir.path().join("run.mcap").exists() {
        assert!(t0.elapsed() < Duration::from_secs(120), "the run wrote nothing");
        std::thread::sleep(Duration::from_millis(50));
    }
    // Let it run a few simulated tens of seconds.
    std::thread::sleep(Duration::from_secs(3));
    interrupt(child.id());
    assert_eq!(child.wait().unwrap().code(), Some(2));
    let s = score(dir.path());
    assert_eq!(s["outcome"], "aborted");
    assert!(s["abort_reason"].as_str().unwrap().contains("interrupted"));
    assert_eq!(s["success"], false);
    let topics = read_mcap(&dir.path().join("run.mcap"));
    assert!(topics["/tf"].len() > 100);
    assert_eq!(topics["/score"].len(), 1);
    assert!(rrd_entities(&dir.path().join("run.rrd")).contains("/world/truth/base_link"));
}

#[test]
fn camera_frames_reach_the_logs_as_images_and_point_clouds() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&data("cameras.toml"), dir.path(), &[]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let sim = score(dir.path())["sim_time_s"].as_f64().unwrap();
    let topics = read_mcap(&dir.path().join("run.mcap"));
    let left = &topics["/sensors/head_stereo/left"];
    // images_hz = 1 over the run.
    assert!((left.len() as f64 - sim).abs() <= 2.0, "{} images over {sim} s", left.len());
    let img = &left[left.len() / 2];
    assert_eq!(
        (img["encoding"].as_str(), img["width"].as_u64(), img["height"].as_u64()),
        (Some("mono8"), Some(320), Some(240))
    );
    use base64::Engine;
    let px = base64::engine::general_purpose::STANDARD.decode(img["data"].as_str().unwrap()).unwrap();
    assert_eq!(px.len(), 320 * 240);
    assert!(px.iter().any(|&p| p > 50), "the rendered image is black");
    let depth = &topics["/sensors/tof_left/depth"];
    assert_eq!(depth[0]["encoding"], "32FC1");
    let clouds = &topics["/sensors/tof_left/points"];
    let n = |m: &serde_json::Value| {
        base64::engine::general_purpose::STANDARD.decode(m["data"].as_str().unwrap()).unwrap().len() / 12
    };
    assert!(
        clouds.iter().any(|c| n(c) > 1000),
        "no ToF points: the mast looks at the ground after 'mast_up'"
    );
    let ents = rrd_entities(&dir.path().join("run.rrd"));
    for e in [
        "/sensors/head_stereo/left",
        "/sensors/head_stereo/right",
        "/sensors/tof_left/depth",
        "/world/truth/tof_left_optical/points",
    ] {
        assert!(ents.contains(e), "{e} missing: {ents:?}");
    }
    // No image travels as JSON.
    assert!(!topics.keys().any(|t| t.starts_with("/slots/cameras/")), "{:?}", topics.keys());
}

#[test]
fn markers_give_a_marker_tables_pose_in_map_and_reach_the_logs() {
    let dir = tempfile::tempdir().unwrap();
    // Quads searched at a third of the resolution: the table's 37-47 px markers then count as
    // small, and once the table is seen its box is also searched at full resolution.
    let o = run(&data("markers.toml"), dir.path(), &["--set", "modules.tracking_marker.params.decimate=3"]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let topics = read_mcap(&dir.path().join("run.mcap"));
    // Once the pan-tilt unit has stopped: the table's four markers, its pose from all of them
    // where the world file puts it (the start is known exactly here, so the error is the vision's
    // and the believed calibration's).
    let objects = &topics["/slots/tracking/objects"];
    let last = &objects.last().unwrap()["value"]["objects"];
    let table = last.as_array().unwrap().iter().find(|o| o["object"] == "marker_table").expect("the table");
    assert_eq!(table["markers"], serde_json::json!([10, 11, 12, 13]));
    let t: Vec<f64> = table["map_from_object"]["translation"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert!((t[0] - 4.0).hypot(t[1] + 1.5) < 0.03 && t[2].abs() < 0.03, "table at {t:?}");
    let q: Vec<f64> = table["map_from_object"]["rotation"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let estimated =
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]));
    let truth = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 160f64.to_radians());
    let err = estimated.angle_to(&truth).to_degrees();
    assert!(err < 1.0, "table rotation off by {err} deg");
    assert!(table["seen_frames"].as_u64().unwrap() >= 3);
    // Once seen, the table's box is also searched at full resolution: the window covers its
    // markers.
    let detections = &topics["/slots/tracking/markers"];
    let last = &detections.last().unwrap()["value"];
    let regions = last["regions"].as_array().unwrap();
    assert_eq!(regions.len(), 1, "one region, the table's: {regions:?}");
    let r: Vec<f64> = regions[0].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    for m in last["markers"].as_array().unwrap() {
        for c in m["corners"].as_array().unwrap() {
            let (u, v) = (c[0].as_f64().unwrap(), c[1].as_f64().unwrap());
            assert!(u > r[0] && u < r[2] && v > r[1] && v < r[3], "corner ({u}, {v}) outside {r:?}");
        }
    }
    // Drawn: outlines over the image (four markers, and the region once the table is tracked),
    // the pose in 3D.
    let notes = &topics["/sensors/head_stereo/left/markers"];
    let last = notes.last().unwrap();
    assert_eq!(last["points"].as_array().unwrap().len(), 5, "four markers and a region: {last}");
    assert!(topics.contains_key("/tracking/objects/head_stereo/marker_table"));
    let ents = rrd_entities(&dir.path().join("run.rrd"));
    for e in [
        "/sensors/head_stereo/left/markers",
        "/sensors/head_stereo/left/markers/regions",
        "/world/estimate/objects/head_stereo/marker_table",
    ] {
        assert!(ents.contains(e), "{e} missing");
    }
}

#[test]
fn a_hung_module_ends_the_run_naming_it_with_finalized_logs() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&data("hang.toml"), dir.path(), &[]);
    assert_eq!(o.status.code(), Some(2), "{}", show(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("module 'localization_fusion' hung"), "{}", show(&o));
    let s = score(dir.path());
    assert_eq!(s["outcome"], "aborted");
    assert!(s["abort_reason"].as_str().unwrap().contains("localization_fusion"));
    let topics = read_mcap(&dir.path().join("run.mcap"));
    assert!(topics["/tf"].len() > 20);
    assert!(rrd_entities(&dir.path().join("run.rrd")).contains("/world/truth/base_link"));
}

#[test]
fn a_wheel_that_stalls_a_move_of_the_acquisition_is_recovered_from_and_the_move_driven_again() {
    // acquire_stall: a wheel jams as the rover drives the last 0.4 m to the grasp distance.
    // Locomotion faults naming the wheel and the motion; CoordinatorManipulation clears the fault
    // and drives what is left (the stalled move once failed the acquisition).
    let dir = tempfile::tempdir().unwrap();
    let o = run(&data("acquire_stall.toml"), dir.path(), &["--set", "logging.rrd=false"]);
    let s = score(dir.path());
    assert_eq!(o.status.code(), Some(0), "{}\n{s:#}", show(&o));
    assert_eq!(s["metrics"]["canister_stowed"], true, "{s:#}");
    let topics = read_mcap(&dir.path().join("run.mcap"));
    let notes: Vec<String> =
        topics["/events"].iter().map(|e| e["message"].as_str().unwrap().to_string()).collect();
    let at = |text: &str| notes.iter().position(|n| n.contains(text));
    let stalled = at("stalled while driving forward").expect("the jammed wheel stalls the drive");
    let recovered = at("the move stalled").expect("the coordinator recovers");
    assert!(stalled < recovered, "{notes:#?}");
}

#[test]
fn every_hostile_file_is_refused_with_its_file_line_and_key_never_a_panic() {
    // tests/e2e/data/hostile: each file once crashed, hung or exhausted memory in `check` or
    // `run`, or was accepted and then failed every run. Now each is exit 2 and a located message.
    let expected: &[(&str, &str)] = &[
        ("world_reversed_range.toml", "terrain.slopes.0.x_range_m"),
        ("world_nan_range.toml", "must be a finite"),
        ("world_infinite_crater.toml", "terrain.craters.0.radius_m"),
        ("world_rock_larger_than_terrain.toml", "rocks.max_diameter_m"),
        ("world_ten_billion_craters.toml", "grid-cell updates"),
        ("world_dust_rocks.toml", "rocks.min_diameter_m"),
        ("world_not_toml.toml", "world_not_toml.toml:3:"),
        ("scenario_twin_typo.toml", "twin.physics.dt_ss"),
        ("scenario_module_typo.toml", "modules.locomotion.params.speeed"),
        ("scenario_huge_timeout.toml", "phase.0.steps.0.timeout_s"),
        ("scenario_nan_start.toml", "rover.x"),
        ("scenario_off_terrain.toml", "off the terrain"),
        ("scenario_imu_too_fast.toml", "twin.imu.rate_hz"),
        ("scenario_collision_cell.toml", "twin.physics.terrain_cell_m"),
        ("scenario_module_period.toml", "modules.locomotion.framework.period_s"),
        ("scenario_trigger_state.toml", "event.0.module_state.state"),
        ("scenario_trigger_module.toml", "event.0.module_state.module"),
        ("sweep_range_end.toml", "dispersion.0.grid"),
        ("sweep_twin_typo.toml", "dispersion.0.uniform"),
    ];
    let dir = data("hostile");
    let mut files: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    let mut listed: Vec<String> = expected.iter().map(|e| e.0.to_string()).collect();
    listed.sort();
    assert_eq!(files, listed, "every hostile file has its expected message here");
    for (file, want) in expected {
        let o = rover_twin().arg("check").arg(dir.join(file)).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{file}: {}", show(&o));
        assert!(!err.contains("panicked"), "{file} panicked: {err}");
        // Located: the file the user wrote, a line number, and the key.
        let located = err.lines().any(|l| {
            l.split_once(".toml:").is_some_and(|(_, rest)| rest.starts_with(|c: char| c.is_ascii_digit()))
        });
        assert!(located && err.contains(want), "{file}: wanted a located message with '{want}', got: {err}");
    }
}

#[test]
fn events_fire_on_phase_ends_module_states_and_distances_and_infractions_say_when_and_where() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&data("conditions.toml"), dir.path(), &[]);
    assert!(o.status.code().is_some_and(|c| c < 2), "{}", show(&o));
    let s = score(dir.path());
    let phase_end = |name: &str| {
        s["phases"].as_array().unwrap().iter().find(|p| p["name"] == name).unwrap()["end_s"].as_f64().unwrap()
    };
    let isolated = |module: &str| {
        s["infractions"]
            .as_array()
            .unwrap()
            .iter()
            .find(|i| {
                i["kind"] == "isolated" && i["detail"].as_str().unwrap().contains(&format!("'{module}'"))
            })
            .unwrap_or_else(|| panic!("no isolation of {module} in {}", s["infractions"]))
            .clone()
    };
    let t = |i: &serde_json::Value| i["t_s"].as_f64().unwrap();
    // Half a second after the mast was up (the debug command reaches the arm within a few ticks).
    let arm = isolated("arm");
    let delay = t(&arm) - phase_end("mast_up");
    assert!((0.5..0.7).contains(&delay), "the arm crashed {delay} s after mast_up ended");
    // A fifth of a second after the arm entered Safe.
    let delay = t(&isolated("ptu")) - t(&arm);
    assert!((0.2..0.4).contains(&delay), "the pan-tilt crashed {delay} s after the arm");
    // Where the rover came within 2.5 m of the canister at (3, 0).
    let g = isolated("gripper");
    let [x, y] = [g["position_m"][0].as_f64().unwrap(), g["position_m"][1].as_f64().unwrap()];
    let d = (3.0 - x).hypot(y);
    assert!((2.2..=2.5).contains(&d), "the gripper crashed {d} m from the canister");
    assert_eq!(s["metrics"]["route_completion"], 1.0);
    // States entered on the way up do not trigger events.
    assert_eq!(s["unsent_events"], serde_json::json!(["locomotion.get_state"]));
}

#[test]
fn a_short_fuzzing_run_finds_no_panic() {
    // The campaign is `rover-twin bench fuzz` (1 000 000 cases by default, minutes on a release
    // build); a few thousand here keep the harness itself tested.
    let dir = tempfile::tempdir().unwrap();
    let o = rover_twin()
        .args(["bench", "fuzz", "--cases", "3000", "--generate-every", "50", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    assert!(out.contains("3000 cases in") && out.contains("no panic"), "{out}");
    for target in ["scenario", "world", "module configuration", "twin configuration"] {
        assert!(out.contains(target), "no {target} cases: {out}");
    }
}

/// `run --live`: a Foxglove client (the SDK's WebSocket protocol, `foxglove.sdk.v1`) connecting
/// after the run started is told the topics, gets the latched robot model on subscribing, and the
/// simulated time; the run still writes its files and ends as it would.
#[test]
fn a_live_run_streams_the_scene_to_a_foxglove_client() {
    use std::io::BufRead;
    use tungstenite::Message;
    use tungstenite::client::IntoClientRequest;
    let dir = tempfile::tempdir().unwrap();
    let mut child = rover_twin()
        .arg("run")
        .arg(data("short.toml"))
        // Real time (22 s): the client must subscribe while the run goes, also when the tests
        // running beside this one leave it little of the machine (at 4x it once connected only as
        // the run ended).
        .args(["--quiet", "--live=127.0.0.1:0", "--pace", "1", "--out"])
        .arg(dir.path())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    let port: u16 = line
        .split("ws://127.0.0.1:")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no address in {line:?}"));
    let mut req = format!("ws://127.0.0.1:{port}").into_client_request().unwrap();
    req.headers_mut().insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut ws, _) = tungstenite::connect(req).unwrap();
    let (mut topics, mut subscribed, mut robot, mut time) = (BTreeMap::new(), false, None, 0u64);
    let (mut sub_id, mut subscribed_at) = (7u32, None::<Instant>);
    let t0 = Instant::now();
    let wanted = ["/tf", "/scene/world", "/estimate/localization/pose"];
    while robot.is_none() || time == 0 || !wanted.iter().all(|t| topics.contains_key(*t)) {
        assert!(t0.elapsed() < Duration::from_secs(60), "robot {robot:?}, time {time}, topics {topics:?}");
        let m = ws.read().unwrap_or_else(|e| panic!("{e}: robot {robot:?}, time {time}, topics {topics:?}"));
        match m {
            Message::Text(t) => {
                let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                if v["op"] == "advertise" {
                    for c in v["channels"].as_array().unwrap() {
                        topics.insert(c["topic"].as_str().unwrap().to_string(), c["id"].as_u64().unwrap());
                    }
                }
            }
            Message::Binary(b) if b[0] == 1 => {
                // Message data: opcode, subscription id (u32), log time (u64), the JSON message.
                let msg: serde_json::Value = serde_json::from_slice(&b[13..]).unwrap();
                let base = msg["entities"]
                    .as_array()
                    .and_then(|e| e.iter().find(|e| e["id"] == "robot/base_link/0"));
                robot = robot.or(base.cloned());
            }
            Message::Binary(b) if b[0] == 2 => time = u64::from_le_bytes(b[1..9].try_into().unwrap()),
            _ => {}
        }
        // The latched robot model is sent to a new subscriber; under load the SDK has been seen to
        // send it before the subscription took, so a subscriber without it after 3 s subscribes again.
        if let Some(since) = subscribed_at
            && robot.is_none()
            && since.elapsed() > Duration::from_secs(3)
        {
            let unsub = serde_json::json!({ "op": "unsubscribe", "subscriptionIds": [sub_id] });
            ws.send(Message::Text(unsub.to_string().into())).unwrap();
            sub_id += 1;
            subscribed = false;
        }
        if !subscribed && let Some(id) = topics.get("/scene/robot") {
            let sub = serde_json::json!({ "op": "subscribe", "subscriptions": [{ "id": sub_id, "channelId": id }] });
            ws.send(Message::Text(sub.to_string().into())).unwrap();
            subscribed = true;
            subscribed_at = Some(Instant::now());
        }
    }
    assert_eq!(robot.unwrap()["frame_id"], "base_link");
    drop(ws);
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(0));
    assert_eq!(score(dir.path())["success"], true);
    assert!(dir.path().join("run.mcap").exists());
}
