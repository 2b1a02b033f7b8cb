//! End-to-end localization runs through `rover-twin run`: the fused pose against the wheels, vision
//! alone and the truth, as the score reports them (`metrics.localization`).

#![allow(clippy::disallowed_methods)]

use std::path::Path;
use std::process::{Command, Output};

mod common;
use common::*;

fn run(scenario: &Path, out: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rover-twin"))
        .arg("run")
        .arg(scenario)
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .args(["--set", "logging.rrd=false"])
        .output()
        .unwrap()
}

/// A source's drift as a percentage of the distance driven.
fn drift(s: &serde_json::Value, source: &str) -> f64 {
    s["metrics"]["localization"]["sources"][source]["drift_percent"].as_f64().unwrap()
}

#[test]
fn on_a_slipping_slope_the_fused_estimate_follows_vision_not_the_wheels() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&root().join("scenarios/localization_slope.toml"), dir.path());
    assert!(o.status.success(), "{}", show(&o));
    let s = score(dir.path());
    let (fused, visual, wheels) = (drift(&s, "fused"), drift(&s, "visual"), drift(&s, "wheels"));
    println!("slope: fused {fused:.2} %, visual {visual:.2} %, wheels {wheels:.2} %");
    // The wheels slip by several per cent; the fusion stays well below them.
    assert!(wheels > 5.0, "the wheels slip: {wheels} %");
    assert!(fused < wheels / 2.5, "fused {fused} % vs wheels {wheels} %");
}

#[test]
fn a_ten_second_visual_dropout_is_bridged_and_vision_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&root().join("tests/e2e/data/slope_dropout.toml"), dir.path());
    assert!(o.status.success(), "{}", show(&o));
    let s = score(dir.path());
    let l = &s["metrics"]["localization"];
    let fused = drift(&s, "fused");
    println!(
        "dropout: fused {fused:.2} %, visual {:.2} %, wheels {:.2} %, {} frames, {} lost",
        drift(&s, "visual"),
        drift(&s, "wheels"),
        l["visual_frames"],
        l["visual_lost"]
    );
    // No images for 10 s at 10 Hz: about 100 frames fewer than the climb alone gives, and a new
    // keyframe (at least one loss or restart) when they come back; the run reaches its goal.
    let frames = l["visual_frames"].as_u64().unwrap();
    let sim = s["sim_time_s"].as_f64().unwrap();
    assert!((frames as f64) < (sim - 10.0) * 10.0, "{frames} frames in {sim} s");
    assert!(s["phases"][0]["success"] == true);
}
