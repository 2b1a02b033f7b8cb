//! One run of a sweep in a process of its own: `rover-twin run` with the run's seed and overrides,
//! under a wall-clock limit. Whatever the run does (hangs, panics, exits, is killed, refuses its
//! input) it is one row with its outcome and reason, and the campaign goes on.
//!
//! The child gets its own process group, so a terminal's Ctrl-C reaches the sweep alone, which
//! passes one SIGINT on (the run finalizes its logs and its row is dropped as not a result). At
//! the time limit the child gets SIGTERM (the run aborts and finalizes its logs) and, if it is
//! still there after a grace period (a thread stuck where no signal is looked at), SIGKILL.

use super::results::{METRICS, Row, one_line, triage};
use super::{KeepLogs, RunPlan, Sweep, run_dir};
use crate::score::Score;
use anyhow::{Context, Result};
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// How long a run may take after SIGTERM before it is killed.
const GRACE: Duration = Duration::from_secs(15);
/// How often the child is looked at.
const POLL: Duration = Duration::from_millis(50);

/// What one child run needs.
pub(crate) struct ChildRun<'a> {
    /// The `rover-twin` executable.
    pub exe: &'a Path,
    /// The campaign.
    pub sweep: &'a Sweep,
    /// The campaign's output folder.
    pub out: &'a Path,
    /// Which logs to keep.
    pub keep: KeepLogs,
    /// Wall-clock limit of the run (`None`: from the scenario's time limit).
    pub timeout: Option<Duration>,
    /// Threads each run may use for its parallel image work (`RAYON_NUM_THREADS`), when set.
    pub threads: Option<usize>,
    /// The sweep's stop flag.
    pub interrupt: &'a AtomicBool,
}

/// The default wall-clock limit of a run whose scenario allows `time_limit_s` simulated
/// seconds: a run going slower than a fifth of real time, plus a minute to start, counts as hung.
pub fn default_timeout(time_limit_s: f64) -> Duration {
    Duration::from_secs_f64(5.0 * time_limit_s.max(0.0) + 60.0)
}

/// The command line of a run (`reproduce`): what a user types to get the same run alone.
pub(crate) fn reproduce(sweep: &Sweep, plan: &RunPlan) -> String {
    let mut r = format!("rover-twin run {} --seed {}", sweep.scenario_path.display(), plan.seed);
    if let Some(f) = sweep.file.sweep.fidelity {
        r += &format!(" --fidelity {}", f.name());
    }
    for (k, v) in &plan.overrides {
        r += &format!(" --set '{k}={v}'");
    }
    r
}

/// How the child ended.
enum Ended {
    Exited(ExitStatus),
    TimedOut,
}

/// The last line of the run's stderr that says `error`, else its last line.
fn stderr_reason(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    let line = lines.iter().rev().find(|l| l.starts_with("error")).or(lines.last());
    line.map(|l| one_line(l)).unwrap_or_default()
}

fn status_text(st: &ExitStatus) -> String {
    match (st.code(), st.signal()) {
        (Some(c), _) => format!("exit status {c}"),
        (None, Some(s)) => {
            let name = Signal::try_from(s).map(|s| s.as_str().to_string()).unwrap_or_else(|_| s.to_string());
            format!("killed by signal {name}")
        }
        _ => st.to_string(),
    }
}

impl ChildRun<'_> {
    /// Runs `plan`; `None` when the sweep was interrupted before the run ended (not a result:
    /// its folder is removed).
    pub fn run(&self, plan: &RunPlan) -> Result<Option<Row>> {
        let dir = run_dir(self.out, plan.index);
        let reproduce = reproduce(self.sweep, plan);
        let row = |outcome: &str, reason: String| Row {
            index: plan.index,
            seed: plan.seed,
            values: plan.dispersed.iter().map(|(_, v)| v.clone()).collect(),
            success: false,
            outcome: outcome.into(),
            failed_phase: String::new(),
            failed_criteria: String::new(),
            reason: one_line(&reason),
            metrics: vec![String::new(); METRICS.len()],
            reproduce: reproduce.clone(),
            wall_time_s: 0.0,
        };
        // The parent reads the run's scenario first: a dispersion that draws a value the scenario
        // refuses is this run's error, located in the files, without starting a process.
        let loaded = match crate::scenario::load(&self.sweep.scenario_path, &plan.overrides) {
            Ok(l) => l,
            Err(e) => return Ok(Some(row("error", e.to_string()))),
        };
        let timeout = self.timeout.unwrap_or_else(|| default_timeout(loaded.scenario.run.time_limit_s));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let stderr_path = dir.join("stderr.txt");
        let stderr = std::fs::File::create(&stderr_path)
            .with_context(|| format!("creating {}", stderr_path.display()))?;
        let mut cmd = Command::new(self.exe);
        cmd.arg("run").arg(&self.sweep.scenario_path).args(["--seed", &plan.seed.to_string(), "--quiet"]);
        cmd.arg("--out").arg(&dir);
        if let Some(f) = self.sweep.file.sweep.fidelity {
            cmd.args(["--fidelity", f.name()]);
        }
        if self.keep == KeepLogs::None {
            cmd.arg("--no-logs");
        }
        for (k, v) in &plan.overrides {
            cmd.arg("--set").arg(format!("{k}={v}"));
        }
        if let Some(n) = self.threads
            && std::env::var_os("RAYON_NUM_THREADS").is_none()
        {
            cmd.env("RAYON_NUM_THREADS", n.to_string());
        }
        cmd.stdin(Stdio::null()).stdout(Stdio::null()).stderr(stderr).process_group(0);
        // A run outlives no sweep: if the sweep dies (SIGKILL, a second Ctrl-C, a CI job's end),
        // the run gets SIGTERM and ends as an interrupted run does, its logs finalized.
        #[cfg(target_os = "linux")]
        #[allow(unsafe_code)]
        {
            let sweep_pid = nix::unistd::getpid();
            // SAFETY: the closure runs in the forked child before exec and only calls prctl(2)
            // and getppid(2), which are async-signal-safe; it touches no memory shared with the
            // parent.
            unsafe {
                cmd.pre_exec(move || {
                    nix::sys::prctl::set_pdeathsig(Signal::SIGTERM).map_err(std::io::Error::from)?;
                    // The sweep died between the fork and the line above: no run without it.
                    if nix::unistd::getppid() != sweep_pid {
                        return Err(std::io::Error::other("the sweep is gone"));
                    }
                    Ok(())
                });
            }
        }
        let _ = std::fs::remove_file(dir.join("score.json"));
        #[allow(clippy::disallowed_methods)] // the sweep driver times its child processes
        let t0 = std::time::Instant::now();
        let mut child = cmd.spawn().with_context(|| format!("starting {}", self.exe.display()))?;
        let pid = Pid::from_raw(child.id() as i32);
        let mut signalled: Option<Duration> = None;
        let mut interrupted = false;
        let mut timed_out = false;
        let ended = loop {
            if let Some(st) = child.try_wait()? {
                break (st, timed_out);
            }
            let now = t0.elapsed();
            if signalled.is_none() && self.interrupt.load(Ordering::SeqCst) {
                interrupted = true;
                let _ = kill(pid, Signal::SIGINT);
                signalled = Some(now);
            } else if signalled.is_none() && now > timeout {
                timed_out = true;
                let _ = kill(pid, Signal::SIGTERM);
                signalled = Some(now);
            } else if signalled.is_some_and(|s| now > s + GRACE) {
                let _ = child.kill();
            }
            std::thread::sleep(POLL);
        };
        let wall = t0.elapsed().as_secs_f64();
        if interrupted {
            let _ = std::fs::remove_dir_all(&dir);
            return Ok(None);
        }
        let text = std::fs::read_to_string(dir.join("score.json")).ok();
        let full: Option<Score> = text.as_deref().and_then(|t| serde_json::from_str(t).ok());
        let partial: Option<serde_json::Value> = text.as_deref().and_then(|t| serde_json::from_str(t).ok());
        // A run that finished on its own just as the limit came is not a timeout.
        let (status, timed_out) = ended;
        let ended = if timed_out && full.as_ref().is_none_or(|s| s.outcome == "aborted") {
            Ended::TimedOut
        } else {
            Ended::Exited(status)
        };
        let mut r = match (&ended, &full) {
            (Ended::TimedOut, _) => {
                let at = partial
                    .as_ref()
                    .and_then(|v| v["sim_time_s"].as_f64())
                    .map(|t| format!(" (stopped at {t:.1} s simulated)"))
                    .unwrap_or_default();
                let limit = timeout.as_secs_f64();
                let r = row("timeout", format!("no result within the wall-clock limit of {limit:.0} s{at}"));
                // What the run measured before it was stopped still counts as its metrics.
                let metrics = full.as_ref().map(|s| METRICS.iter().map(|(_, value)| value(s)).collect());
                Row { metrics: metrics.unwrap_or(r.metrics.clone()), ..r }
            }
            (Ended::Exited(_), Some(score)) => {
                let (failed_phase, failed_criteria, reason) = triage(score);
                Row {
                    success: score.success,
                    outcome: score.outcome.clone(),
                    failed_phase,
                    failed_criteria,
                    reason,
                    metrics: METRICS.iter().map(|(_, value)| value(score)).collect(),
                    ..row("", String::new())
                }
            }
            (Ended::Exited(st), None) => match &partial {
                // A run that stopped itself (a hung module under lockstep) scores what it knows.
                Some(v) if v["outcome"].is_string() => row(
                    v["outcome"].as_str().unwrap_or("aborted"),
                    v["abort_reason"].as_str().map(String::from).unwrap_or_else(|| status_text(st)),
                ),
                _ if st.code() == Some(2) => row("error", stderr_reason(&stderr_path)),
                _ => {
                    let last = stderr_reason(&stderr_path);
                    let sep = if last.is_empty() { "" } else { ": " };
                    row("crashed", format!("{}{sep}{last}", status_text(st)))
                }
            },
        };
        r.wall_time_s = full.as_ref().map(|s| s.wall_time_s).unwrap_or(wall);
        // The run's folder says what the row says.
        match full {
            Some(mut score) if matches!(ended, Ended::TimedOut) => {
                score.outcome = r.outcome.clone();
                score.abort_reason = Some(r.reason.clone());
                crate::runner::write_score(&dir, &score)?;
            }
            None if !r.success => {
                let score = serde_json::json!({
                    "scenario": loaded.scenario.name,
                    "scenario_file": self.sweep.scenario_path.display().to_string(),
                    "seed": plan.seed, "success": false, "outcome": r.outcome, "abort_reason": r.reason,
                    "sim_time_s": partial.as_ref().and_then(|v| v["sim_time_s"].as_f64()),
                });
                std::fs::write(dir.join("score.json"), serde_json::to_string_pretty(&score)? + "\n")?;
            }
            _ => {}
        }
        self.tidy(&dir, r.success)?;
        Ok(Some(r))
    }

    /// Removes what the campaign does not keep of a finished run.
    fn tidy(&self, dir: &Path, success: bool) -> Result<()> {
        let mut remove: Vec<PathBuf> = Vec::new();
        if self.keep == KeepLogs::Failed && success {
            remove.extend(["run.rrd", "run.mcap", "blueprint.rbl"].map(|f| dir.join(f)));
        }
        let stderr = dir.join("stderr.txt");
        if success || std::fs::metadata(&stderr).is_ok_and(|m| m.len() == 0) {
            remove.push(stderr);
        }
        for f in remove {
            let _ = std::fs::remove_file(f);
        }
        Ok(())
    }
}
