//! Monte Carlo sweeps: dispersions drawn from a master seed, runs in parallel, shards, merging,
//! `runs.csv`, `summary.json` and an HTML report.
//!
//! Run `i` of a campaign gets its seed and dispersed values from `(master_seed, i)` alone, so it is
//! reproducible on its own (`rover-twin run SCENARIO --seed S --set k=v ...`, the `reproduce` column)
//! and a campaign's results do not depend on `--jobs` or on how it is sharded.

use crate::runner::{self, RunOptions};
use crate::scenario::{self, FidelityName};
use crate::score::Score;
use anyhow::{Context, Result, anyhow, bail};
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
    if file.sweep.runs == 0 {
        return err(&["sweep", "runs"], "must be at least 1".into());
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
            && !(lo.is_finite() && hi.is_finite() && lo < hi)
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

/// One row of `runs.csv`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// Run index.
    pub index: u64,
    /// Run seed.
    pub seed: u64,
    /// Dispersed values, in dispersion order.
    pub values: Vec<String>,
    /// Mission success.
    pub success: bool,
    /// Outcome.
    pub outcome: String,
    /// Metrics, by name (numbers as text, empty when absent).
    pub metrics: Vec<String>,
    /// The command that reproduces the run.
    pub reproduce: String,
    /// Wall time, s (wall-clock: varies between runs).
    pub wall_time_s: f64,
}

/// A metric column: its name and how a run's score fills it.
pub type Metric = (&'static str, fn(&Score) -> String);

/// Metric columns of `runs.csv`, in order, each with the formatting of its value (empty when the
/// run has none).
pub const METRICS: &[Metric] = &[
    ("sim_time_s", |s| format!("{:.3}", s.sim_time_s)),
    ("distance_m", |s| format!("{:.6}", s.metrics.distance_m)),
    ("final_position_error_m", |s| optional(s.metrics.final_position_error_m)),
    ("position_error_rms_m", |s| optional(s.metrics.position_error_rms_m)),
    ("canister_stowed", |s| s.metrics.canister_stowed.to_string()),
    ("canister_distance_m", |s| optional(s.metrics.canister_distance_m)),
    ("canister_bearing_deg", |s| optional(s.metrics.canister_bearing_deg)),
    ("collisions", |s| s.metrics.collisions.to_string()),
    ("self_collisions", |s| s.metrics.self_collisions.to_string()),
    ("grasp_position_error_m", |s| optional(s.metrics.grasp_position_error_m)),
    ("max_tilt_deg", |s| format!("{:.6}", s.metrics.max_tilt_deg)),
    ("final_state", |s| s.metrics.final_state.clone()),
];

fn optional(v: Option<f64>) -> String {
    v.map(|v| format!("{v:.6}")).unwrap_or_default()
}

fn header(sweep: &SweepFile) -> Vec<String> {
    let mut h = vec!["index".to_string(), "seed".into()];
    h.extend(sweep.dispersions.iter().map(|d| d.key.clone()));
    h.extend(["success".to_string(), "outcome".into()]);
    h.extend(METRICS.iter().map(|(name, _)| name.to_string()));
    h.extend(["reproduce".to_string(), "wall_time_s".into()]);
    h
}

fn row_record(r: &Row) -> Vec<String> {
    let mut v = vec![r.index.to_string(), r.seed.to_string()];
    v.extend(r.values.iter().cloned());
    v.extend([r.success.to_string(), r.outcome.clone()]);
    v.extend(r.metrics.iter().cloned());
    v.extend([r.reproduce.clone(), format!("{:.3}", r.wall_time_s)]);
    v
}

fn parse_row(rec: &csv::StringRecord, n_disp: usize) -> Result<Row> {
    let get = |i: usize| rec.get(i).map(str::to_string).ok_or_else(|| anyhow!("short row"));
    let mut i = 0;
    let index = get(i)?.parse()?;
    i += 1;
    let seed = get(i)?.parse()?;
    i += 1;
    let values = (0..n_disp).map(|k| get(i + k)).collect::<Result<Vec<_>>>()?;
    i += n_disp;
    let success = get(i)?.parse()?;
    let outcome = get(i + 1)?;
    i += 2;
    let metrics = (0..METRICS.len()).map(|k| get(i + k)).collect::<Result<Vec<_>>>()?;
    i += METRICS.len();
    Ok(Row {
        index,
        seed,
        values,
        success,
        outcome,
        metrics,
        reproduce: get(i)?,
        wall_time_s: get(i + 1)?.parse()?,
    })
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
        self.jobs.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)).max(1)
    }
}

/// The folder of run `index` of a sweep writing to `out` (score, track, logs).
pub(crate) fn run_dir(out: &Path, index: u64) -> PathBuf {
    out.join("runs").join(format!("{index:05}"))
}

/// What a sweep did.
#[derive(Clone, Debug)]
pub struct SweepResult {
    /// Rows written, by index.
    pub rows: Vec<Row>,
    /// The sweep was interrupted before every run finished.
    pub interrupted: bool,
    /// Wall time, s.
    pub wall_s: f64,
    /// Jobs used.
    pub jobs: usize,
}

fn run_one(
    sweep: &Sweep,
    plan: &RunPlan,
    out: &Path,
    keep: KeepLogs,
    interrupt: Arc<AtomicBool>,
) -> Result<Option<Row>> {
    let dir = run_dir(out, plan.index);
    let loaded = scenario::load(&sweep.scenario_path, &plan.overrides)?;
    let opts = RunOptions {
        seed: Some(plan.seed),
        out: dir.clone(),
        fidelity: sweep.file.sweep.fidelity,
        quiet: true,
        write_logs: keep != KeepLogs::None,
        interrupt: interrupt.clone(),
    };
    let score = runner::run(&loaded, &opts)?;
    if score.outcome == "aborted" && interrupt.load(Ordering::SeqCst) {
        // Not a result: an interrupted run leaves no row (and no half logs).
        let _ = std::fs::remove_dir_all(&dir);
        return Ok(None);
    }
    if keep == KeepLogs::Failed && score.success {
        for f in ["run.rrd", "run.mcap", "blueprint.rbl"] {
            let _ = std::fs::remove_file(dir.join(f));
        }
    }
    let metrics = METRICS.iter().map(|(_, value)| value(&score)).collect();
    let mut reproduce = format!("rover-twin run {} --seed {}", sweep.scenario_path.display(), plan.seed);
    if let Some(f) = sweep.file.sweep.fidelity {
        reproduce += &format!(" --fidelity {}", f.name());
    }
    for (k, v) in &plan.overrides {
        reproduce += &format!(" --set '{k}={v}'");
    }
    Ok(Some(Row {
        index: plan.index,
        seed: plan.seed,
        values: plan.dispersed.iter().map(|(_, v)| v.clone()).collect(),
        success: score.success,
        outcome: score.outcome.clone(),
        metrics,
        reproduce,
        wall_time_s: score.wall_time_s,
    }))
}

/// Campaign identity, written beside the results so that `merge` joins only shards of one campaign.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Campaign {
    /// The sweep file.
    pub sweep_file: String,
    /// Its content (as loaded).
    pub sweep: SweepFile,
    /// Shard `[k, n]`.
    pub shard: Option<[u64; 2]>,
    /// Runs of the whole campaign.
    pub runs: u64,
}

/// Runs a sweep (or one shard of it).
pub fn run(sweep: &Sweep, o: &SweepOptions) -> Result<SweepResult> {
    #[allow(clippy::disallowed_methods)] // the sweep driver times itself (not a module)
    let t0 = std::time::Instant::now();
    let runs = o.runs.unwrap_or(sweep.file.sweep.runs);
    let mut sweep = sweep.clone();
    sweep.file.sweep.runs = runs;
    let indices = match o.shard {
        Some((k, n)) => sweep.shard(k, n),
        None => (0..runs).collect(),
    };
    std::fs::create_dir_all(&o.out).with_context(|| format!("creating {}", o.out.display()))?;
    let campaign = Campaign {
        sweep_file: sweep.path.display().to_string(),
        sweep: sweep.file.clone(),
        shard: o.shard.map(|(k, n)| [k, n]),
        runs,
    };
    std::fs::write(o.out.join("campaign.json"), serde_json::to_string_pretty(&campaign)?)?;
    let jobs = o.jobs();
    let keep = o.keep_logs.unwrap_or(sweep.file.sweep.keep_logs);
    // Rows are appended (and flushed) as runs finish, so an interrupted sweep keeps them all.
    let csv_path = o.out.join("runs.csv");
    let mut w =
        csv::Writer::from_path(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?;
    w.write_record(header(&sweep.file))?;
    w.flush()?;
    let writer = parking_lot::Mutex::new(w);
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
        b
    };
    let failures = std::sync::atomic::AtomicU64::new(0);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(jobs).build()?;
    let results: Vec<Result<Option<Row>>> = pool.install(|| {
        indices
            .par_iter()
            .map(|&i| {
                if o.interrupt.load(Ordering::SeqCst) {
                    return Ok(None);
                }
                let plan = sweep.plan(i);
                let row = run_one(&sweep, &plan, &o.out, keep, o.interrupt.clone())
                    .with_context(|| format!("run {i} (seed {})", plan.seed))?;
                if let Some(r) = &row {
                    let mut w = writer.lock();
                    w.write_record(row_record(r))?;
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
    let mut rows = Vec::new();
    for r in results {
        if let Some(row) = r? {
            rows.push(row);
        }
    }
    rows.sort_by_key(|r| r.index);
    let interrupted = rows.len() < indices.len();
    // Final file: sorted by index (same content whatever the completion order).
    write_results(&o.out, &sweep.file, &rows, interrupted, Some(&campaign))?;
    Ok(SweepResult { rows, interrupted, wall_s: t0.elapsed().as_secs_f64(), jobs })
}

fn write_csv(path: &Path, sweep: &SweepFile, rows: &[Row]) -> Result<()> {
    let tmp = path.with_extension("csv.tmp");
    let mut w = csv::Writer::from_path(&tmp)?;
    w.write_record(header(sweep))?;
    for r in rows {
        w.write_record(row_record(r))?;
    }
    w.flush()?;
    drop(w);
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// Writes `runs.csv`, `summary.json` and `report.html` for `rows`.
pub fn write_results(
    out: &Path,
    sweep: &SweepFile,
    rows: &[Row],
    partial: bool,
    campaign: Option<&Campaign>,
) -> Result<()> {
    write_csv(&out.join("runs.csv"), sweep, rows)?;
    let summary = summarize(rows, partial);
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&summary)? + "\n")?;
    crate::report::write(out, sweep, rows, &summary, campaign)?;
    Ok(())
}

/// Percentiles and moments of one metric.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MetricSummary {
    /// Runs with a value.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Minimum.
    pub min: f64,
    /// 5th percentile.
    pub p5: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Maximum.
    pub max: f64,
}

/// `summary.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Runs summarized.
    pub runs: usize,
    /// Successful runs.
    pub successes: usize,
    /// Success rate.
    pub success_rate: f64,
    /// 95% Wilson score interval of the success rate.
    pub success_rate_ci95: [f64; 2],
    /// Not every planned run finished (interrupted, or a shard).
    pub partial: bool,
    /// Per numeric metric.
    pub metrics: BTreeMap<String, MetricSummary>,
    /// Outcomes counted.
    pub outcomes: BTreeMap<String, usize>,
}

/// Wilson score interval for `k` successes out of `n`, at z = 1.96.
pub fn wilson(k: usize, n: usize) -> [f64; 2] {
    if n == 0 {
        return [0.0, 1.0];
    }
    let (n, p, z) = (n as f64, k as f64 / n as f64, 1.959_963_984_540_054);
    let d = 1.0 + z * z / n;
    let c = (p + z * z / (2.0 * n)) / d;
    let h = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / d;
    // At 0 and n successes the interval touches 0 and 1 exactly (rounding would miss them).
    let lo = if k == 0 { 0.0 } else { (c - h).max(0.0) };
    let hi = if k as f64 == n { 1.0 } else { (c + h).min(1.0) };
    [lo, hi]
}

/// Linear-interpolated percentile of sorted values.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// Numeric values of metric column `k`.
pub fn metric_values(rows: &[Row], k: usize) -> Vec<f64> {
    rows.iter()
        .filter_map(|r| {
            let t = r.metrics.get(k)?;
            match t.as_str() {
                "true" => Some(1.0),
                "false" => Some(0.0),
                _ => t.parse::<f64>().ok(),
            }
        })
        .collect()
}

fn summarize(rows: &[Row], partial: bool) -> Summary {
    let successes = rows.iter().filter(|r| r.success).count();
    let mut metrics = BTreeMap::new();
    for (k, (name, _)) in METRICS.iter().enumerate() {
        let mut v = metric_values(rows, k);
        if v.is_empty() {
            continue;
        }
        v.sort_by(f64::total_cmp);
        metrics.insert(
            name.to_string(),
            MetricSummary {
                n: v.len(),
                mean: v.iter().sum::<f64>() / v.len() as f64,
                min: v[0],
                p5: percentile(&v, 0.05),
                p50: percentile(&v, 0.5),
                p95: percentile(&v, 0.95),
                max: v[v.len() - 1],
            },
        );
    }
    let mut outcomes = BTreeMap::new();
    for r in rows {
        *outcomes.entry(r.outcome.clone()).or_insert(0) += 1;
    }
    Summary {
        runs: rows.len(),
        successes,
        success_rate: if rows.is_empty() { 0.0 } else { successes as f64 / rows.len() as f64 },
        success_rate_ci95: wilson(successes, rows.len()),
        partial,
        metrics,
        outcomes,
    }
}

/// Joins shard folders into `out`: the same `runs.csv`, `summary.json` and report an unsharded
/// sweep gives (wall-clock columns aside). Each run's score and track are copied into
/// `out/runs/<index>/` (the report draws the tracks from there); logs stay in their shard.
pub fn merge(dirs: &[PathBuf], out: &Path) -> Result<Vec<Row>> {
    let mut campaign: Option<Campaign> = None;
    let mut rows: BTreeMap<u64, Row> = BTreeMap::new();
    let mut shard_of: BTreeMap<u64, &Path> = BTreeMap::new();
    for d in dirs {
        let c: Campaign = serde_json::from_str(
            &std::fs::read_to_string(d.join("campaign.json"))
                .with_context(|| format!("{}: not a sweep folder (no campaign.json)", d.display()))?,
        )
        .with_context(|| format!("{}/campaign.json", d.display()))?;
        if let Some(first) = &campaign
            && (first.sweep != c.sweep || first.runs != c.runs)
        {
            bail!("{}: a shard of another campaign (sweep file or run count differ)", d.display());
        }
        let n_disp = c.sweep.dispersions.len();
        let path = d.join("runs.csv");
        let mut r = csv::Reader::from_path(&path).with_context(|| format!("reading {}", path.display()))?;
        for (line, rec) in r.records().enumerate() {
            let rec = rec.with_context(|| format!("{}:{}", path.display(), line + 2))?;
            let row = parse_row(&rec, n_disp).with_context(|| format!("{}:{}", path.display(), line + 2))?;
            shard_of.insert(row.index, d);
            if rows.insert(row.index, row).is_some() {
                bail!(
                    "{}:{}: run {} appears in two shards",
                    path.display(),
                    line + 2,
                    rec.get(0).unwrap_or("?")
                );
            }
        }
        campaign.get_or_insert(c);
    }
    let c = campaign.ok_or_else(|| anyhow!("no shard folders given"))?;
    std::fs::create_dir_all(out)?;
    for (&index, shard) in &shard_of {
        let (from, to) = (run_dir(shard, index), run_dir(out, index));
        for f in ["score.json", "track.csv"] {
            if from.join(f).exists() {
                std::fs::create_dir_all(&to)?;
                std::fs::copy(from.join(f), to.join(f))
                    .with_context(|| format!("copying {}", from.join(f).display()))?;
            }
        }
    }
    let rows: Vec<Row> = rows.into_values().collect();
    let partial = rows.len() as u64 != c.runs;
    let merged = Campaign { shard: None, ..c };
    std::fs::write(out.join("campaign.json"), serde_json::to_string_pretty(&merged)?)?;
    write_results(out, &merged.sweep, &rows, partial, Some(&merged))?;
    Ok(rows)
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

/// `sweep --bench`: the campaign's throughput with one job, with all jobs in this process, and as
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
        out: base.join(dir),
        keep_logs: Some(KeepLogs::None),
        quiet: true,
        interrupt: o.interrupt.clone(),
    };
    say(&format!("bench: {runs} runs of {} each way, {jobs} jobs, logs off", sw.scenario_path.display()));
    let one = run(sw, &opts(1, "1job"))?;
    say(&format!(
        "  1 job, in process:            {:7.1} s  {:6.2} runs/min",
        one.wall_s,
        runs as f64 / one.wall_s * 60.0
    ));
    let all = run(sw, &opts(jobs, "alljobs"))?;
    say(&format!(
        "  {jobs} jobs, in process:           {:7.1} s  {:6.2} runs/min",
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
        "speed-up from 1 to {jobs} jobs: {s_in:.2}x in process vs {s_proc:.2}x for independent processes: {:.0}% of the attainable",
        100.0 * s_in / s_proc
    ));
    // Equal results whatever the job count (wall-clock columns aside).
    let strip = |rows: &[Row]| rows.iter().map(|r| Row { wall_time_s: 0.0, ..r.clone() }).collect::<Vec<_>>();
    if strip(&one.rows) != strip(&all.rows) {
        bail!("results differ between 1 and {jobs} jobs: the runs are not deterministic");
    }
    Ok(())
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
