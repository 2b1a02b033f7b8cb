//! Monte Carlo sweeps: dispersions drawn from a master seed, each run in a process of its own
//! under a wall-clock limit, shards, merging, resuming, re-running chosen runs, `runs.csv` (with
//! each failure's triage), `summary.json`, `junit.xml`, an HTML report, and comparing campaigns.
//!
//! Run `i` of a campaign gets its seed and dispersed values from `(master_seed, i)` alone, so it is
//! reproducible on its own (`rover-twin run SCENARIO --seed S --set k=v ...`, the `reproduce` column)
//! and a campaign's results do not depend on `--jobs`, on how it is sharded, or on being resumed.

mod bench;
mod child;
pub mod compare;
mod junit;
pub mod provenance;
mod report;
pub mod results;

pub use bench::bench;
pub use child::default_timeout;
pub use provenance::Provenance;
pub use results::{
    Campaign, METRICS, Metric, MetricSummary, Row, Summary, merge, metric_values, percentile, read, wilson,
};

use crate::scenario::{self, FidelityName};
use anyhow::{Context, Result, bail};
use framework::config::ConfigError;
use framework::seed::splitmix64 as mix;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_pcg::Pcg64Mcg;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// A sweep file.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SweepFile {
    /// Campaign settings.
    pub sweep: SweepSettings,
    /// Dispersed scenario parameters.
    #[serde(default, rename = "dispersion")]
    pub dispersions: Vec<Dispersion>,
}

/// Which run logs to keep.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum KeepLogs {
    /// Keep the Rerun/MCAP logs of failed runs only.
    #[default]
    Failed,
    /// Keep every run's logs.
    All,
    /// Keep none.
    None,
}

/// Campaign settings.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SweepSettings {
    /// The scenario, relative to the sweep file.
    pub scenario: String,
    /// Number of runs.
    #[serde(default = "default_runs")]
    pub runs: u64,
    /// Master seed of the campaign.
    #[serde(default)]
    pub master_seed: u64,
    /// Which logs to keep.
    #[serde(default)]
    pub keep_logs: KeepLogs,
    /// Fidelity for every run (default: the scenario's).
    #[serde(default)]
    pub fidelity: Option<FidelityName>,
    /// Fixed overrides applied to every run (`key = value`).
    #[serde(default)]
    pub set: BTreeMap<String, toml::Value>,
    /// Wall-clock limit of each run, s (default: five times the scenario's `run.time_limit_s`
    /// plus a minute); a run past it is stopped and counts as failed with outcome `timeout`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run_timeout_s: Option<f64>,
}

fn default_runs() -> u64 {
    10
}

/// A normal distribution.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct NormalSpec {
    /// Mean.
    pub mean: f64,
    /// Standard deviation.
    pub sigma: f64,
}

/// One dispersed parameter: exactly one distribution.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Dispersion {
    /// Scenario key (`world.seed`, `canister.x`, `twin.imu.gyro_noise_density`, ...).
    pub key: String,
    /// Uniform real in [lo, hi).
    #[serde(default)]
    pub uniform: Option<[f64; 2]>,
    /// Uniform integer in [lo, hi].
    #[serde(default)]
    pub uniform_int: Option<[i64; 2]>,
    /// Normal.
    #[serde(default)]
    pub normal: Option<NormalSpec>,
    /// One of these values, equally likely.
    #[serde(default)]
    pub choice: Option<Vec<toml::Value>>,
    /// Each of these values in turn, drawn by the run index, not at random: the grid dispersions
    /// of a sweep together enumerate every combination (the first varies fastest), a table of
    /// cases such as fault kind x mission phase.
    #[serde(default)]
    pub grid: Option<Vec<toml::Value>>,
}

impl Dispersion {
    /// The values at the edges of what it draws, each with the field that gives it: both ends of
    /// a range (4 sigma either side of a normal's mean), every choice and grid value.
    fn extremes(&self) -> Vec<(&'static str, toml::Value)> {
        let f = toml::Value::Float;
        if let Some([lo, hi]) = self.uniform {
            vec![("uniform", f(lo)), ("uniform", f(hi))]
        } else if let Some([lo, hi]) = self.uniform_int {
            vec![("uniform_int", toml::Value::Integer(lo)), ("uniform_int", toml::Value::Integer(hi))]
        } else if let Some(n) = &self.normal {
            vec![("normal", f(n.mean - 4.0 * n.sigma)), ("normal", f(n.mean + 4.0 * n.sigma))]
        } else if let Some(c) = &self.choice {
            c.iter().map(|v| ("choice", v.clone())).collect()
        } else if let Some(g) = &self.grid {
            g.iter().map(|v| ("grid", v.clone())).collect()
        } else {
            Vec::new()
        }
    }

    fn draw(&self, rng: &mut Pcg64Mcg) -> toml::Value {
        if let Some([lo, hi]) = self.uniform {
            toml::Value::Float(rng.random_range(lo..hi))
        } else if let Some([lo, hi]) = self.uniform_int {
            toml::Value::Integer(rng.random_range(lo..=hi))
        } else if let Some(n) = &self.normal {
            toml::Value::Float(Normal::new(n.mean, n.sigma).expect("validated").sample(rng))
        } else if let Some(c) = &self.choice {
            c[rng.random_range(0..c.len())].clone()
        } else if let Some(g) = &self.grid {
            // Placed by the run index in `Sweep::plan`; not random.
            g[0].clone()
        } else {
            unreachable!("validated: one distribution")
        }
    }
}

/// A loaded sweep.
#[derive(Clone, Debug)]
pub struct Sweep {
    /// The file's content.
    pub file: SweepFile,
    /// The sweep file.
    pub path: PathBuf,
    /// The scenario file.
    pub scenario_path: PathBuf,
}

/// Scenario keys (and their sub-keys) that change nothing at kinematic fidelity: contact friction,
/// the solver's settings, the wheel drives, the suspension and the servo gains are parts of the
/// dynamics (the step, gravity, servo tolerances and the gripper's rules apply in both).
const DYNAMIC_ONLY: &[&str] = &[
    "world.friction",
    "twin.physics.solver_iterations",
    "twin.physics.pgs_iterations",
    "twin.physics.friction_model",
    "twin.physics.friction_in_bias_pass",
    "twin.physics.terrain_cell_m",
    "twin.wheels",
    "twin.suspension",
    "twin.servos.full_effort_error",
    "twin.servos.damping_time_s",
];

impl Sweep {
    /// The dispersed keys that have no effect at the fidelity the runs use, each with why: a
    /// campaign that disperses them learns nothing about them, and should say so.
    pub fn ineffective_dispersions(&self) -> Vec<String> {
        let fidelity = self
            .file
            .sweep
            .fidelity
            .or_else(|| scenario::load(&self.scenario_path, &[]).ok().map(|l| l.scenario.run.fidelity));
        if fidelity != Some(FidelityName::Kinematic) {
            return Vec::new();
        }
        self.file
            .dispersions
            .iter()
            .filter(|d| DYNAMIC_ONLY.iter().any(|k| d.key == *k || d.key.starts_with(&format!("{k}."))))
            .map(|d| {
                format!(
                    "dispersion of '{}' has no effect at kinematic fidelity (it is part of the dynamics)",
                    d.key
                )
            })
            .collect()
    }
}

/// Loads and checks a sweep file and its scenario (with every dispersion key applied once, so a
/// misspelt key fails here with its location, not in run 37).
pub fn load(path: &Path) -> Result<Sweep, ConfigError> {
    let (doc, files) = scenario::load_merged(path)?;
    let file: SweepFile = scenario::deserialize_located(&doc, &files, &[])?;
    let err = |parts: &[&str], msg: String| {
        Err(scenario::locate(&parts.iter().map(|s| s.to_string()).collect::<Vec<_>>(), &files, &[], msg))
    };
    if !(1..=MAX_RUNS).contains(&file.sweep.runs) {
        return err(&["sweep", "runs"], format!("must be 1..={MAX_RUNS}, got {}", file.sweep.runs));
    }
    if let Some(t) = file.sweep.run_timeout_s
        && !(t > 0.0 && t <= MAX_RUN_TIMEOUT_S)
    {
        return err(
            &["sweep", "run_timeout_s"],
            format!("must be in (0, {MAX_RUN_TIMEOUT_S:e}] s, got {}", framework::config::num(t)),
        );
    }
    for (i, d) in file.dispersions.iter().enumerate() {
        let idx = i.to_string();
        let n = [
            d.uniform.is_some(),
            d.uniform_int.is_some(),
            d.normal.is_some(),
            d.choice.is_some(),
            d.grid.is_some(),
        ]
        .iter()
        .filter(|b| **b)
        .count();
        if n != 1 {
            return err(
                &["dispersion", &idx],
                format!(
                    "'{}' needs exactly one of uniform, uniform_int, normal, choice, grid (has {n})",
                    d.key
                ),
            );
        }
        if d.grid.as_ref().is_some_and(|c| c.is_empty()) {
            return err(&["dispersion", &idx, "grid"], "needs at least one value".into());
        }
        if let Some([lo, hi]) = d.uniform
            && !(lo.is_finite() && hi.is_finite() && lo < hi && (hi - lo).is_finite())
        {
            return err(&["dispersion", &idx, "uniform"], format!("needs lo < hi, got [{lo}, {hi}]"));
        }
        if let Some([lo, hi]) = d.uniform_int
            && lo > hi
        {
            return err(&["dispersion", &idx, "uniform_int"], format!("needs lo <= hi, got [{lo}, {hi}]"));
        }
        if let Some(nm) = &d.normal
            && !(nm.sigma.is_finite() && nm.sigma >= 0.0 && nm.mean.is_finite())
        {
            return err(
                &["dispersion", &idx, "normal"],
                format!("needs a finite mean and sigma >= 0, got {nm:?}"),
            );
        }
        if d.choice.as_ref().is_some_and(|c| c.is_empty()) {
            return err(&["dispersion", &idx, "choice"], "needs at least one value".into());
        }
    }
    let base = path.parent().unwrap_or(Path::new("."));
    let scenario_path = base.join(&file.sweep.scenario);
    if !scenario_path.exists() {
        return err(
            &["sweep", "scenario"],
            format!("scenario file {} does not exist", scenario_path.display()),
        );
    }
    let sweep = Sweep { file, path: path.to_path_buf(), scenario_path };
    // Every dispersion applied once (run 0's values) must give a valid scenario.
    let plan = sweep.plan(0);
    if let Err(e) = scenario::load(&sweep.scenario_path, &plan.overrides) {
        let key = e.key.clone().unwrap_or_default();
        let pos = sweep
            .file
            .dispersions
            .iter()
            .position(|d| key == d.key || key.starts_with(&format!("{}.", d.key)));
        let at = match pos {
            Some(i) => scenario::locate(
                &["dispersion".into(), i.to_string(), "key".into()],
                &files,
                &[],
                format!("applied to {}: {}", sweep.scenario_path.display(), e.message),
            ),
            None => e,
        };
        return Err(at);
    }
    Ok(sweep)
}

/// Checks that every value the sweep's dispersions can draw gives a valid run (`rover-twin
/// check`): each end of a range (4 sigma either side of a normal's mean), each choice and grid
/// value, with the fixed overrides and run 0's other values. Keys the twin, the modules or the
/// world read are checked by building what a run builds. (A sweep itself checks run 0 alone when
/// it starts: a value a run refuses is that run's error row, and the campaign goes on.)
pub fn check_ranges(sweep: &Sweep) -> Result<(), ConfigError> {
    let (_, files) = scenario::load_merged(&sweep.path)?;
    let plan = sweep.plan(0);
    for (i, d) in sweep.file.dispersions.iter().enumerate() {
        for (field, v) in d.extremes() {
            let text = value_text(&v);
            let overrides: Vec<(String, String)> = plan
                .overrides
                .iter()
                .map(|(k, x)| if *k == d.key { (k.clone(), text.clone()) } else { (k.clone(), x.clone()) })
                .collect();
            let built = match scenario::load(&sweep.scenario_path, &overrides) {
                Err(e) => Err(e.to_string()),
                Ok(l) if BUILT.iter().any(|k| d.key.starts_with(k)) => {
                    crate::runner::check(&l).map_err(|e| format!("{e:#}"))
                }
                Ok(_) => Ok(()),
            };
            if let Err(why) = built {
                let parts = ["dispersion".to_string(), i.to_string(), field.to_string()];
                return Err(scenario::locate(&parts, &files, &[], format!("its value {text} gives: {why}")));
            }
        }
    }
    Ok(())
}

/// Most runs a campaign may have.
pub const MAX_RUNS: u64 = 1_000_000;
/// Longest wall-clock limit of a run, s.
pub const MAX_RUN_TIMEOUT_S: f64 = 1e7;

/// Scenario keys whose values only building the run's world, twin and modules checks.
const BUILT: &[&str] = &["twin.", "modules.", "sensors.", "world.", "rover.", "canister."];

/// What run `index` of a campaign is: its seed and overrides.
#[derive(Clone, Debug, PartialEq)]
pub struct RunPlan {
    /// Index in the campaign.
    pub index: u64,
    /// Run seed.
    pub seed: u64,
    /// Overrides (fixed ones first, then the dispersions), as `--set` would give them.
    pub overrides: Vec<(String, String)>,
    /// The dispersed values alone, by key.
    pub dispersed: Vec<(String, String)>,
}

/// A TOML value as `--set` text (floats keep every digit so that a run reproduces exactly).
fn value_text(v: &toml::Value) -> String {
    match v {
        toml::Value::Float(f) => format!("{f:?}"),
        toml::Value::String(s) => toml::Value::String(s.clone()).to_string(),
        other => other.to_string(),
    }
}

impl Sweep {
    /// The plan of run `index`.
    pub fn plan(&self, index: u64) -> RunPlan {
        let m = self.file.sweep.master_seed;
        let seed = mix(mix(m) ^ index);
        let mut rng = Pcg64Mcg::seed_from_u64(mix(seed ^ 0xD15_9E25));
        let mut overrides: Vec<(String, String)> =
            self.file.sweep.set.iter().map(|(k, v)| (k.clone(), value_text(v))).collect();
        let mut dispersed = Vec::new();
        let mut stride = 1u64;
        for d in &self.file.dispersions {
            let value = match &d.grid {
                Some(g) => {
                    let n = g.len() as u64;
                    let v = g[((index / stride) % n) as usize].clone();
                    stride = stride.saturating_mul(n);
                    v
                }
                None => d.draw(&mut rng),
            };
            let v = value_text(&value);
            overrides.push((d.key.clone(), v.clone()));
            dispersed.push((d.key.clone(), v));
        }
        RunPlan { index, seed, overrides, dispersed }
    }

    /// Indices of shard `k` of `n` (1-based `k`): every n-th run, so shards are balanced.
    pub fn shard(&self, k: u64, n: u64) -> Vec<u64> {
        (0..self.file.sweep.runs).filter(|i| i % n == k - 1).collect()
    }
}

/// Options of a sweep.
#[derive(Clone, Debug)]
pub struct SweepOptions {
    /// Runs (default: the file's).
    pub runs: Option<u64>,
    /// Parallel jobs (default: all cores).
    pub jobs: Option<usize>,
    /// Shard `(k, n)`, 1-based.
    pub shard: Option<(u64, u64)>,
    /// Only these run indices (of the shard, if one is given).
    pub indices: Option<Vec<u64>>,
    /// Keep the rows already in `out` (a campaign interrupted there) and run only the others.
    pub resume: bool,
    /// Wall-clock limit of each run, s (default: the file's, else from the scenario's time limit).
    pub run_timeout_s: Option<f64>,
    /// Output folder.
    pub out: PathBuf,
    /// Keep logs (default: the file's).
    pub keep_logs: Option<KeepLogs>,
    /// No progress bar.
    pub quiet: bool,
    /// Stop flag (SIGINT/SIGTERM).
    pub interrupt: Arc<AtomicBool>,
}

impl SweepOptions {
    /// Parallel jobs: the option, or all cores.
    fn jobs(&self) -> usize {
        self.jobs.unwrap_or_else(cores).max(1)
    }
}

fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

/// The folder of run `index` of a sweep writing to `out` (score, track, logs).
pub(crate) fn run_dir(out: &Path, index: u64) -> PathBuf {
    out.join("runs").join(format!("{index:05}"))
}

/// What a sweep did.
#[derive(Clone, Debug)]
pub struct SweepResult {
    /// Rows written, by index (those of a resumed campaign included).
    pub rows: Vec<Row>,
    /// Runs done by this invocation (not kept from an earlier one).
    pub ran: usize,
    /// The summary written.
    pub summary: Summary,
    /// The sweep was interrupted before every run finished.
    pub interrupted: bool,
    /// Wall time, s.
    pub wall_s: f64,
    /// Jobs used.
    pub jobs: usize,
}

/// The campaign a sweep writes to `o.out` and the run indices it holds.
fn campaign(sweep: &Sweep, o: &SweepOptions) -> Result<(Campaign, Vec<u64>)> {
    let runs = sweep.file.sweep.runs;
    let mut indices = match o.shard {
        Some((k, n)) => sweep.shard(k, n),
        None => (0..runs).collect(),
    };
    if let Some(pick) = &o.indices {
        if let Some(i) = pick.iter().find(|&&i| i >= runs) {
            bail!("run index {i} is out of range: the campaign has {runs} runs (0 to {})", runs - 1);
        }
        indices.retain(|i| pick.contains(i));
    }
    let c = Campaign {
        sweep_file: sweep.path.display().to_string(),
        sweep: sweep.file.clone(),
        shard: o.shard.map(|(k, n)| [k, n]),
        indices: o.indices.clone(),
        runs,
        provenance: Some(Provenance::of(sweep)?),
    };
    Ok((c, indices))
}

/// The rows of an earlier invocation of the same campaign in `o.out`, to keep (`--resume`).
fn resumed(c: &Campaign, indices: &[u64], o: &SweepOptions) -> Result<BTreeMap<u64, Row>> {
    let (old, rows) =
        read(&o.out).with_context(|| format!("--resume: nothing to resume in {}", o.out.display()))?;
    if old.sweep != c.sweep || old.runs != c.runs || old.shard != c.shard || old.indices != c.indices {
        bail!(
            "--resume: {} holds another campaign (its sweep file, run count, shard or indices differ)",
            o.out.display()
        );
    }
    let diff = Provenance::differences(old.provenance.as_ref(), c.provenance.as_ref());
    if !diff.is_empty() {
        bail!(
            "--resume: {} was made from other inputs or another build: {}",
            o.out.display(),
            diff.join("; ")
        );
    }
    Ok(rows.into_iter().filter(|r| indices.contains(&r.index)).map(|r| (r.index, r)).collect())
}

/// The indices of the failed runs in sweep folder `dir`, which must hold a campaign of `sweep`,
/// and that campaign's run count (`--rerun-failed`; it may have been run with `--runs`).
pub fn failed_indices(dir: &Path, sweep: &Sweep) -> Result<(Vec<u64>, u64)> {
    let (c, rows) = read(dir)?;
    let mut theirs = c.sweep.clone();
    theirs.sweep.runs = sweep.file.sweep.runs;
    if theirs != sweep.file {
        bail!("--rerun-failed: {} holds a campaign of another sweep file (or an edited one)", dir.display());
    }
    Ok((rows.iter().filter(|r| !r.success).map(|r| r.index).collect(), c.runs))
}

/// Runs a sweep (or one shard of it, or chosen runs of it).
pub fn run(sweep: &Sweep, o: &SweepOptions) -> Result<SweepResult> {
    #[allow(clippy::disallowed_methods)] // the sweep driver times itself (not a module)
    let t0 = std::time::Instant::now();
    let mut sweep = sweep.clone();
    sweep.file.sweep.runs = o.runs.unwrap_or(sweep.file.sweep.runs);
    if !(1..=MAX_RUNS).contains(&sweep.file.sweep.runs) {
        bail!("--runs {}: give 1 to {MAX_RUNS}", sweep.file.sweep.runs);
    }
    // What every run builds, built once before any run starts (with the fixed overrides; a value
    // a dispersion draws is its run's own affair): a misspelt [twin] or [modules.*] key of the
    // scenario or of `set` (free tables its types cannot check) fails the campaign here, not as N
    // error rows.
    let fixed: Vec<(String, String)> =
        sweep.plan(0).overrides.into_iter().take(sweep.file.sweep.set.len()).collect();
    let first = scenario::load(&sweep.scenario_path, &fixed)?;
    crate::runner::check(&first).context("the scenario with the sweep's fixed overrides cannot start")?;
    let (campaign, indices) = campaign(&sweep, o)?;
    let done = if o.resume { resumed(&campaign, &indices, o)? } else { BTreeMap::new() };
    std::fs::create_dir_all(&o.out).with_context(|| format!("creating {}", o.out.display()))?;
    std::fs::write(o.out.join("campaign.json"), serde_json::to_string_pretty(&campaign)?)?;
    let jobs = o.jobs();
    let keep = o.keep_logs.unwrap_or(sweep.file.sweep.keep_logs);
    // Rows are appended (and flushed) as runs finish, so an interrupted sweep keeps them all.
    let csv_path = o.out.join("runs.csv");
    let mut w =
        csv::Writer::from_path(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?;
    w.write_record(results::header(&sweep.file))?;
    for r in done.values() {
        w.write_record(results::row_record(r))?;
    }
    w.flush()?;
    let writer = parking_lot::Mutex::new(w);
    let todo: Vec<u64> = indices.iter().copied().filter(|i| !done.contains_key(i)).collect();
    let bar = if o.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let b = indicatif::ProgressBar::new(indices.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} runs  ETA {eta}  {msg}",
            )
            .expect("valid template"),
        );
        b.set_position(done.len() as u64);
        b
    };
    let failures = std::sync::atomic::AtomicU64::new(done.values().filter(|r| !r.success).count() as u64);
    let exe = std::env::current_exe().context("finding the rover-twin executable")?;
    let child = child::ChildRun {
        exe: &exe,
        sweep: &sweep,
        out: &o.out,
        keep,
        timeout: o.run_timeout_s.or(sweep.file.sweep.run_timeout_s).map(std::time::Duration::from_secs_f64),
        // Runs side by side share the cores: each gets its share for its parallel image work.
        threads: (jobs > 1).then(|| (cores() / jobs).max(1)),
        interrupt: &o.interrupt,
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(jobs).build()?;
    let results: Vec<Result<Option<Row>>> = pool.install(|| {
        todo.par_iter()
            .map(|&i| {
                if o.interrupt.load(Ordering::SeqCst) {
                    return Ok(None);
                }
                let plan = sweep.plan(i);
                let row = child.run(&plan).with_context(|| format!("run {i} (seed {})", plan.seed))?;
                if let Some(r) = &row {
                    let mut w = writer.lock();
                    w.write_record(results::row_record(r))?;
                    w.flush()?;
                    if !r.success {
                        failures.fetch_add(1, Ordering::Relaxed);
                    }
                    bar.inc(1);
                    bar.set_message(format!("{} failed", failures.load(Ordering::Relaxed)));
                }
                Ok(row)
            })
            .collect()
    });
    bar.finish_and_clear();
    drop(writer);
    let mut rows: Vec<Row> = done.into_values().collect();
    let mut ran = 0;
    for r in results {
        if let Some(row) = r? {
            rows.push(row);
            ran += 1;
        }
    }
    rows.sort_by_key(|r| r.index);
    let interrupted = rows.len() < indices.len();
    let partial = rows.len() as u64 != sweep.file.sweep.runs;
    // Final file: sorted by index (same content whatever the completion order).
    let summary = results::write_results(&o.out, &sweep.file, &rows, partial, Some(&campaign))?;
    Ok(SweepResult { rows, ran, summary, interrupted, wall_s: t0.elapsed().as_secs_f64(), jobs })
}

/// Parses a list of run indices: `3`, `0,4,9`, `10-19`, `0-4,8`.
pub fn parse_indices(s: &str) -> Result<Vec<u64>, String> {
    let mut v = Vec::new();
    for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let num = |t: &str| t.trim().parse::<u64>().map_err(|_| format!("'{t}' in '{s}' is not a run index"));
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b) = (num(a)?, num(b)?);
                if a > b {
                    return Err(format!("range '{part}' runs backwards"));
                }
                v.extend(a..=b);
            }
            None => v.push(num(part)?),
        }
    }
    if v.is_empty() {
        return Err(format!("no run index in '{s}'"));
    }
    v.sort_unstable();
    v.dedup();
    Ok(v)
}

/// Parses `K/N`.
pub fn parse_shard(s: &str) -> Result<(u64, u64), String> {
    let (k, n) = s.split_once('/').ok_or_else(|| format!("shard '{s}' is not K/N"))?;
    let (k, n): (u64, u64) = (
        k.parse().map_err(|_| format!("bad K in '{s}'"))?,
        n.parse().map_err(|_| format!("bad N in '{s}'"))?,
    );
    if n == 0 || k == 0 || k > n {
        return Err(format!("shard '{s}' needs 1 <= K <= N"));
    }
    Ok((k, n))
}

/// Writes a line to stdout and flushes.
pub fn say(s: &str) {
    let mut o = std::io::stdout().lock();
    let _ = writeln!(o, "{s}");
    let _ = o.flush();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_interval_brackets_the_rate() {
        // Reference values: Wilson score interval, 95%, 8 of 10 -> [0.4902, 0.9433].
        let [lo, hi] = wilson(8, 10);
        assert!((lo - 0.4902).abs() < 1e-4 && (hi - 0.9433).abs() < 1e-4, "{lo} {hi}");
        assert_eq!(wilson(0, 0), [0.0, 1.0]);
        let [lo, hi] = wilson(10, 10);
        assert!(hi == 1.0 && lo > 0.65);
    }

    #[test]
    fn percentiles_interpolate() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert_eq!(percentile(&v, 0.5), 3.0);
        assert_eq!(percentile(&v, 0.0), 1.0);
        assert_eq!(percentile(&v, 1.0), 5.0);
        assert!((percentile(&v, 0.05) - 1.2).abs() < 1e-12);
    }

    #[test]
    fn index_lists_take_single_indices_and_ranges() {
        assert_eq!(parse_indices("7, 0-2,1").unwrap(), vec![0, 1, 2, 7]);
        assert!(parse_indices("3-1").unwrap_err().contains("backwards"));
        assert!(parse_indices("a").unwrap_err().contains("not a run index"));
        assert!(parse_indices(",").is_err());
    }

    #[test]
    fn shards_partition_the_runs() {
        let file: SweepFile = toml::from_str("[sweep]\nscenario = \"x.toml\"\nruns = 11\n").unwrap();
        let s = Sweep { file, path: "s.toml".into(), scenario_path: "x.toml".into() };
        let mut all: Vec<u64> = (1..=3).flat_map(|k| s.shard(k, 3)).collect();
        all.sort();
        assert_eq!(all, (0..11).collect::<Vec<_>>());
        assert_eq!(parse_shard("2/3"), Ok((2, 3)));
        assert!(parse_shard("0/3").is_err() && parse_shard("4/3").is_err() && parse_shard("x").is_err());
    }

    #[test]
    fn run_plans_depend_on_master_seed_and_index_only() {
        let text = "[sweep]\nscenario = \"x.toml\"\nruns = 5\nmaster_seed = 9\n[[dispersion]]\nkey = \"a\"\nuniform = [0.0, 1.0]\n[[dispersion]]\nkey = \"b\"\nchoice = [\"p\", \"q\"]\n";
        let file: SweepFile = toml::from_str(text).unwrap();
        let s = Sweep { file, path: "s.toml".into(), scenario_path: "x.toml".into() };
        assert_eq!(s.plan(3), s.plan(3));
        assert_ne!(s.plan(3).seed, s.plan(4).seed);
        let v: f64 = s.plan(2).overrides[0].1.parse().unwrap();
        assert!((0.0..1.0).contains(&v));
        assert!(["\"p\"", "\"q\""].contains(&s.plan(2).overrides[1].1.as_str()));
    }

    #[test]
    fn grid_dispersions_enumerate_every_combination_by_run_index() {
        let text = "[sweep]\nscenario = \"x.toml\"\nruns = 6\n[[dispersion]]\nkey = \"event.0\"\ngrid = [{ to = \"a\", args = { n = 1 } }, { to = \"b\" }]\n[[dispersion]]\nkey = \"event.0.phase\"\ngrid = [\"p\", \"q\", \"r\"]\n[[dispersion]]\nkey = \"c\"\nuniform = [0.0, 1.0]\n";
        let file: SweepFile = toml::from_str(text).unwrap();
        let s = Sweep { file, path: "s.toml".into(), scenario_path: "x.toml".into() };
        let cells: std::collections::BTreeSet<(String, String)> = (0..6)
            .map(|i| {
                let o = s.plan(i).overrides;
                // A table's text reads back as the same table.
                let v = scenario::parse_value(&o[0].1);
                assert!(v.as_table().is_some_and(|t| t.contains_key("to")), "{}", o[0].1);
                (o[0].1.clone(), o[1].1.clone())
            })
            .collect();
        assert_eq!(cells.len(), 6, "{cells:?}");
        // The first grid varies fastest.
        assert_eq!(s.plan(0).overrides[1].1, s.plan(1).overrides[1].1);
        assert_ne!(s.plan(0).overrides[0].1, s.plan(1).overrides[0].1);
    }

    #[test]
    fn dispersions_of_the_dynamics_are_reported_as_ineffective_at_kinematic_fidelity() {
        let text = "[sweep]\nscenario = \"x.toml\"\nfidelity = \"kinematic\"\n[[dispersion]]\nkey = \"world.friction\"\nuniform = [0.4, 0.8]\n[[dispersion]]\nkey = \"twin.wheels.friction\"\nuniform = [0.4, 0.8]\n[[dispersion]]\nkey = \"twin.calibration.wheel_radius_fraction\"\nuniform = [0.0, 0.02]\n[[dispersion]]\nkey = \"twin.gripper.cradle_capture_m\"\nuniform = [0.04, 0.08]\n[[dispersion]]\nkey = \"twin.servos.stall_time_s\"\nuniform = [1.0, 2.0]\n";
        let file: SweepFile = toml::from_str(text).unwrap();
        let mut s = Sweep { file, path: "s.toml".into(), scenario_path: "x.toml".into() };
        let notes = s.ineffective_dispersions();
        assert_eq!(notes.len(), 2, "{notes:?}");
        assert!(notes[0].contains("world.friction") && notes[1].contains("twin.wheels.friction"));
        s.file.sweep.fidelity = Some(FidelityName::Dynamic);
        assert!(s.ineffective_dispersions().is_empty());
    }
}
