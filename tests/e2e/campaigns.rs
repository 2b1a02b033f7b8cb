//! End-to-end: Monte Carlo campaigns as CI runs them. `rover-twin sweep` with its runs in
//! processes of their own (a hung run is one failed row and the campaign completes), shards and
//! `merge`, `--resume` after SIGINT, `--indices` and `--rerun-failed`, `--min-success-rate`,
//! `junit.xml`, provenance, and `sweep compare`.

#![allow(clippy::disallowed_methods)] // the tests time out their child processes on the wall clock

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::*;

fn sweep(file: &Path, out: &Path, extra: &[&str]) -> Output {
    rover_twin().arg("sweep").arg(file).arg("--quiet").arg("--out").arg(out).args(extra).output().unwrap()
}

/// The rows of `runs.csv` without the wall-clock column (last).
fn csv_rows(dir: &Path) -> Vec<Vec<String>> {
    let mut r = csv::Reader::from_path(dir.join("runs.csv")).unwrap();
    r.records()
        .map(|rec| {
            let v: Vec<String> = rec.unwrap().iter().map(String::from).collect();
            v[..v.len() - 1].to_vec()
        })
        .collect()
}

/// The rows of `runs.csv` by column name.
fn table(dir: &Path) -> Vec<BTreeMap<String, String>> {
    let mut r = csv::Reader::from_path(dir.join("runs.csv")).unwrap();
    let head: Vec<String> = r.headers().unwrap().iter().map(String::from).collect();
    r.records().map(|rec| head.iter().cloned().zip(rec.unwrap().iter().map(String::from)).collect()).collect()
}

fn csv_rows_or_empty(dir: &Path) -> Vec<csv::StringRecord> {
    csv::Reader::from_path(dir.join("runs.csv"))
        .map(|mut r| r.records().filter_map(Result::ok).collect())
        .unwrap_or_default()
}

fn interrupt(pid: u32) {
    // The shell's own `kill`: no procps needed.
    let st = Command::new("sh").args(["-c", &format!("kill -INT {pid}")]).status().unwrap();
    assert!(st.success());
}

#[test]
fn sweeps_do_not_depend_on_jobs_or_sharding() {
    let (one, two, s1, s2, merged) = (
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
    );
    let sweep = |out: &Path, extra: &[&str]| {
        let o = rover_twin()
            .arg("sweep")
            .arg(data("sweep.toml"))
            .arg("--quiet")
            .arg("--out")
            .arg(out)
            .args(extra)
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(0), "{}", show(&o));
        String::from_utf8_lossy(&o.stdout).to_string()
    };
    let text = sweep(one.path(), &["--jobs", "1"]);
    assert!(text.contains("runs per minute"), "{text}");
    sweep(two.path(), &["--jobs", "2"]);
    sweep(s1.path(), &["--shard", "1/2"]);
    sweep(s2.path(), &["--shard", "2/2"]);
    let rows = csv_rows(one.path());
    assert_eq!(rows.len(), 6);
    assert_eq!(rows, csv_rows(two.path()));
    assert_eq!(csv_rows(s1.path()).len() + csv_rows(s2.path()).len(), 6);
    let o = rover_twin()
        .args(["sweep", "merge"])
        .arg(s1.path())
        .arg(s2.path())
        .arg("--out")
        .arg(merged.path())
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    assert_eq!(rows, csv_rows(merged.path()));
    let summary = |d: &Path| {
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(d.join("summary.json")).unwrap())
            .unwrap()
    };
    assert_eq!(summary(one.path()), summary(merged.path()));
    assert_eq!(summary(one.path())["runs"], 6);
    // The merged report draws the same plots, the rover tracks included (their files are copied
    // from the shards).
    let report = |d: &Path| std::fs::read_to_string(d.join("report.html")).unwrap();
    assert!(report(one.path()).contains("rover tracks"));
    assert!(report(merged.path()).contains("rover tracks"), "the merged report lacks the tracks");
    assert_eq!(report(one.path()).matches("<svg").count(), report(merged.path()).matches("<svg").count());
    // Each run reproduces on its own with the command in its row.
    let header: Vec<String> = csv::Reader::from_path(one.path().join("runs.csv"))
        .unwrap()
        .headers()
        .unwrap()
        .iter()
        .map(String::from)
        .collect();
    let rep = header.iter().position(|h| h == "reproduce").unwrap();
    let d = tempfile::tempdir().unwrap();
    let args: Vec<String> = rows[3][rep].split(" --").skip(1).map(|a| a.replace('\'', "")).collect();
    let mut cmd = rover_twin();
    cmd.arg("run")
        .arg(rows[3][rep].split_whitespace().nth(2).unwrap())
        .arg("--quiet")
        .arg("--out")
        .arg(d.path());
    for a in args {
        let (k, v) = a.split_once(' ').unwrap();
        cmd.arg(format!("--{k}")).arg(v);
    }
    let o = cmd.current_dir(root()).output().unwrap();
    assert!(o.status.code().is_some_and(|c| c < 2), "{}", show(&o));
    let dist = header.iter().position(|h| h == "distance_m").unwrap();
    let s = score(d.path());
    assert_eq!(format!("{:.6}", s["metrics"]["distance_m"].as_f64().unwrap()), rows[3][dist]);
}

#[test]
fn sigint_during_a_sweep_keeps_the_finished_rows() {
    let dir = tempfile::tempdir().unwrap();
    let mut child = rover_twin()
        .arg("sweep")
        .arg(data("sweep.toml"))
        .args(["--runs", "400", "--jobs", "1", "--quiet", "--out"])
        .arg(dir.path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while csv_rows_or_empty(dir.path()).len() < 2 {
        assert!(t0.elapsed() < Duration::from_secs(120), "no rows written");
        std::thread::sleep(Duration::from_millis(100));
    }
    interrupt(child.id());
    let st = child.wait().unwrap();
    assert_eq!(st.code(), Some(2));
    let rows = csv_rows(dir.path());
    assert!(rows.len() >= 2 && rows.len() < 400, "{} rows", rows.len());
    assert!(rows.iter().all(|r| r.len() == rows[0].len() && (r[5] == "true" || r[5] == "false")));
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["partial"], true);
    assert_eq!(s["runs"].as_u64().unwrap() as usize, rows.len());
}

/// Writes a sweep file over `scenario` into `dir`.
fn sweep_file(dir: &Path, scenario: &Path, body: &str) -> PathBuf {
    let path = dir.join("campaign.toml");
    let text = format!(
        "[sweep]\nscenario = \"{}\"\nmaster_seed = 3\nfidelity = \"kinematic\"\n{body}",
        scenario.display()
    );
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_hung_run_is_one_failed_row_and_the_campaign_completes_and_gates() {
    let tmp = tempfile::tempdir().unwrap();
    // hang.toml makes localization_fusion hang at its event's time. Run 0: the module's own hang
    // timeout (2 s) stops the run; run 2: that timeout is too long to matter and the sweep's
    // wall-clock limit stops it; runs 1 and 3: the event falls after the run's end.
    let file = sweep_file(
        tmp.path(),
        &data("hang.toml"),
        "runs = 4\nkeep_logs = \"failed\"\nrun_timeout_s = 25.0\n\
         [[dispersion]]\nkey = \"event.0.at_s\"\ngrid = [4.0, 1000.0]\n\
         [[dispersion]]\nkey = \"modules.localization_fusion.framework.hang_timeout_s\"\ngrid = [2.0, 50000.0]\n",
    );
    let out = tmp.path().join("out");
    let o = sweep(&file, &out, &["--jobs", "2"]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let rows = table(&out);
    let outcomes: Vec<&str> = rows.iter().map(|r| r["outcome"].as_str()).collect();
    assert_eq!(outcomes, ["aborted", "success", "timeout", "success"], "{rows:?}");
    assert!(rows[0]["reason"].contains("'localization_fusion' hung"), "{}", rows[0]["reason"]);
    assert!(rows[2]["reason"].contains("wall-clock limit of 25 s"), "{}", rows[2]["reason"]);
    // The runs' folders say what their rows say, and the stopped run's logs are finalized.
    assert_eq!(score(&out.join("runs/00002"))["outcome"], "timeout");
    let mcap = std::fs::read(out.join("runs/00002/run.mcap")).unwrap();
    assert!(mcap::Summary::read(&mcap).unwrap().is_some(), "the timed-out run's MCAP has no summary");
    assert_eq!(score(&out.join("runs/00000"))["outcome"], "aborted");
    let s = json(&out.join("summary.json"));
    assert_eq!((s["runs"].as_u64(), s["successes"].as_u64()), (Some(4), Some(2)));
    let causes = s["failures_by_cause"].as_object().unwrap();
    assert_eq!(causes.len(), 2, "{causes:?}");
    assert_eq!(causes["timeout"], serde_json::json!([2]));
    assert!(s["provenance"]["world_sha256"].as_str().is_some_and(|h| h.len() == 64), "{s}");
    let junit = std::fs::read_to_string(out.join("junit.xml")).unwrap();
    assert_eq!(junit.matches("<testcase ").count(), 4);
    assert_eq!(junit.matches("<error type=\"timeout\"").count(), 1, "{junit}");
    assert!(junit.contains("errors=\"2\""), "{junit}");
    let report = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(report.contains("Failures by cause"));
    // As a CI gate (resuming the finished campaign runs nothing again).
    let o = sweep(&file, &out, &["--resume", "--min-success-rate", "0.9"]);
    assert_eq!(o.status.code(), Some(1), "{}", show(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("2 of 4 runs succeeded: 50.0% (95% CI") && err.contains("below the minimum"),
        "{err}"
    );
    assert!(String::from_utf8_lossy(&o.stdout).starts_with("0 runs"), "{}", show(&o));
    let o = sweep(&file, &out, &["--resume", "--min-success-rate", "0.5"]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
}

#[test]
fn a_run_whose_drawn_value_is_refused_is_one_error_row() {
    let tmp = tempfile::tempdir().unwrap();
    let file = sweep_file(
        tmp.path(),
        &data("short.toml"),
        "runs = 2\nkeep_logs = \"none\"\n[[dispersion]]\nkey = \"run.observe_s\"\ngrid = [1.0, -1.0]\n",
    );
    let out = tmp.path().join("out");
    let o = sweep(&file, &out, &[]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let rows = table(&out);
    assert_eq!(rows[0]["outcome"], "success");
    assert_eq!(rows[1]["outcome"], "error");
    assert!(
        rows[1]["reason"].contains("run.observe_s") && rows[1]["reason"].contains(">= 0"),
        "{:?}",
        rows[1]
    );
    assert_eq!(json(&out.join("summary.json"))["runs"], 2);
}

#[test]
fn resume_after_sigint_rerun_and_indices_give_the_uninterrupted_campaigns_rows() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = |name: &str| tmp.path().join(name);
    let o = sweep(&data("sweep.toml"), &dir("full"), &["--jobs", "2"]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    let full = csv_rows(&dir("full"));
    assert_eq!(full.len(), 6);

    // Interrupted, then resumed.
    let mut child = rover_twin()
        .arg("sweep")
        .arg(data("sweep.toml"))
        .args(["--jobs", "1", "--quiet", "--out"])
        .arg(dir("resumed"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while csv_rows_or_empty(&dir("resumed")).len() < 2 {
        assert!(t0.elapsed() < Duration::from_secs(120), "no rows written");
        std::thread::sleep(Duration::from_millis(50));
    }
    interrupt(child.id());
    assert_eq!(child.wait().unwrap().code(), Some(2));
    let kept = csv_rows(&dir("resumed")).len();
    assert!((2..6).contains(&kept), "{kept} rows before the resume");
    let o = sweep(&data("sweep.toml"), &dir("resumed"), &["--resume", "--jobs", "2"]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    assert!(String::from_utf8_lossy(&o.stdout).starts_with(&format!("{} runs", 6 - kept)), "{}", show(&o));
    assert_eq!(csv_rows(&dir("resumed")), full);
    assert_eq!(json(&dir("resumed").join("summary.json")), json(&dir("full").join("summary.json")));

    // Compared with itself resumed: no change.
    let o = rover_twin().args(["sweep", "compare"]).arg(dir("full")).arg(dir("resumed")).output().unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("no change"), "{}", show(&o));
    let cmp = json(&dir("resumed").join("compare/compare.json"));
    assert_eq!((cmp["paired"].as_bool(), cmp["p_value"].as_f64()), (Some(true), Some(1.0)));
    assert!(cmp["changes"].as_array().unwrap().is_empty());

    // Chosen runs keep their seeds and values.
    let o = sweep(&data("sweep.toml"), &dir("picked"), &["--indices", "1,4"]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    assert_eq!(csv_rows(&dir("picked")), vec![full[1].clone(), full[4].clone()]);
    assert_eq!(json(&dir("picked").join("summary.json"))["partial"], true);

    // Failed runs again: a copy of the campaign with run 3 marked failed.
    std::fs::create_dir_all(dir("failed")).unwrap();
    std::fs::copy(dir("full").join("campaign.json"), dir("failed").join("campaign.json")).unwrap();
    let mut text = std::fs::read_to_string(dir("full").join("runs.csv")).unwrap();
    let line = text.lines().nth(4).unwrap().to_string();
    assert!(line.starts_with("3,"), "{line}");
    text = text.replace(&line, &line.replacen(",true,success,", ",false,mission_failure,", 1));
    std::fs::write(dir("failed").join("runs.csv"), text).unwrap();
    let o = sweep(&data("sweep.toml"), &dir("rerun"), &["--rerun-failed", dir("failed").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(0), "{}", show(&o));
    assert_eq!(csv_rows(&dir("rerun")), vec![full[3].clone()]);

    // Shards made from other inputs do not merge.
    for (name, keep) in [("x", 0..3u64), ("y", 3..6)] {
        std::fs::create_dir_all(dir(name)).unwrap();
        let mut c = json(&dir("full").join("campaign.json"));
        if name == "y" {
            c["provenance"]["world_sha256"] = "0".repeat(64).into();
        }
        std::fs::write(dir(name).join("campaign.json"), c.to_string()).unwrap();
        let text = std::fs::read_to_string(dir("full").join("runs.csv")).unwrap();
        let lines: Vec<&str> = text
            .lines()
            .enumerate()
            .filter(|(i, _)| *i == 0 || keep.contains(&(*i as u64 - 1)))
            .map(|(_, l)| l)
            .collect();
        std::fs::write(dir(name).join("runs.csv"), lines.join("\n") + "\n").unwrap();
    }
    let o = rover_twin()
        .args(["sweep", "merge"])
        .arg(dir("x"))
        .arg(dir("y"))
        .arg("--out")
        .arg(dir("merged"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", show(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("world file differs"), "{}", show(&o));
}
