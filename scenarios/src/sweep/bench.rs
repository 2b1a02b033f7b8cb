//! `sweep --bench`: how a campaign's throughput scales with its jobs.

use super::{KeepLogs, Row, Sweep, SweepOptions, run, say};
use anyhow::{Context, Result, bail};
use std::path::Path;

/// `sweep --bench`: the campaign's throughput with one job, with all jobs in one sweep, and as
/// independent single-job processes (one shard each) started side by side — the reference a
/// parallel sweep is measured against on a machine whose cores do not scale perfectly. No logs.
pub fn bench(sw: &Sweep, o: &SweepOptions, path: &Path) -> Result<()> {
    let jobs = o.jobs();
    let runs = o.runs.unwrap_or((2 * jobs as u64).max(4));
    let base = o.out.join("bench");
    let opts = |j: usize, dir: &str| SweepOptions {
        runs: Some(runs),
        jobs: Some(j),
        shard: None,
        indices: None,
        resume: false,
        run_timeout_s: o.run_timeout_s,
        out: base.join(dir),
        keep_logs: Some(KeepLogs::None),
        quiet: true,
        interrupt: o.interrupt.clone(),
    };
    say(&format!("bench: {runs} runs of {} each way, {jobs} jobs, logs off", sw.scenario_path.display()));
    let one = run(sw, &opts(1, "1job"))?;
    say(&format!(
        "  1 job, one sweep:             {:7.1} s  {:6.2} runs/min",
        one.wall_s,
        runs as f64 / one.wall_s * 60.0
    ));
    let all = run(sw, &opts(jobs, "alljobs"))?;
    say(&format!(
        "  {jobs} jobs, one sweep:            {:7.1} s  {:6.2} runs/min",
        all.wall_s,
        runs as f64 / all.wall_s * 60.0
    ));
    let exe = std::env::current_exe().context("finding the rover-twin executable")?;
    #[allow(clippy::disallowed_methods)] // wall-clock timing of child processes
    let t0 = std::time::Instant::now();
    let children: Vec<_> = (1..=jobs)
        .map(|k| {
            std::process::Command::new(&exe)
                .arg("sweep")
                .arg(path)
                .args(["--runs", &runs.to_string(), "--jobs", "1", "--keep-logs", "none", "--quiet"])
                .args(["--shard", &format!("{k}/{jobs}")])
                .arg("--out")
                .arg(base.join(format!("proc{k}")))
                .stdout(std::process::Stdio::null())
                .spawn()
        })
        .collect::<Result<_, _>>()
        .context("starting the independent processes")?;
    for mut c in children {
        let st = c.wait()?;
        if !st.success() {
            bail!("an independent sweep process failed ({st})");
        }
    }
    let procs = t0.elapsed().as_secs_f64();
    say(&format!(
        "  {jobs} independent processes:     {:7.1} s  {:6.2} runs/min",
        procs,
        runs as f64 / procs * 60.0
    ));
    let (s_in, s_proc) = (one.wall_s / all.wall_s, one.wall_s / procs);
    say(&format!(
        "speed-up from 1 to {jobs} jobs: {s_in:.2}x in one sweep vs {s_proc:.2}x for independent processes: {:.0}% of the attainable",
        100.0 * s_in / s_proc
    ));
    // Equal results whatever the job count (wall-clock columns aside).
    let strip = |rows: &[Row]| rows.iter().map(|r| Row { wall_time_s: 0.0, ..r.clone() }).collect::<Vec<_>>();
    if strip(&one.rows) != strip(&all.rows) {
        bail!("results differ between 1 and {jobs} jobs: the runs are not deterministic");
    }
    Ok(())
}
