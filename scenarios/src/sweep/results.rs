//! A campaign's results: the rows of `runs.csv` (with the triage of each failure), `summary.json`
//! (success rate, metric percentiles, failures grouped by cause, provenance), reading them back,
//! and `sweep merge`.

use super::provenance::Provenance;
use super::{SweepFile, run_dir};
use crate::score::{PhaseStatus, Score};
use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

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
    /// Outcome: `success`, `mission_failure`, `aborted` (the run stopped itself: a hung module,
    /// an internal error), `timeout` (no result within the per-run wall-clock limit), `crashed`
    /// (the run's process died) or `error` (the run's input was refused).
    pub outcome: String,
    /// The first phase that failed (empty if none did).
    pub failed_phase: String,
    /// The criteria not met, `;`-separated (empty if all held or none were checked).
    pub failed_criteria: String,
    /// Why the run failed, in one line (empty on success).
    pub reason: String,
    /// Metrics, by name (numbers as text, empty when absent).
    pub metrics: Vec<String>,
    /// The command that reproduces the run.
    pub reproduce: String,
    /// Wall time, s (wall-clock: varies between runs).
    pub wall_time_s: f64,
}

impl Row {
    /// What a failed run's failure is, for grouping: the outcome, the phase that failed and the
    /// criteria not met (the reason's free text, with its numbers, is left out so that equal
    /// failures group). `None` for a success.
    pub fn cause(&self) -> Option<String> {
        if self.success {
            return None;
        }
        let mut c = self.outcome.clone();
        if !self.failed_phase.is_empty() {
            c += &format!(" in phase {}", self.failed_phase);
        }
        if !self.failed_criteria.is_empty() {
            c += &format!(" (criteria: {})", self.failed_criteria.replace(';', ", "));
        }
        Some(c)
    }
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
    ("route_completion", |s| format!("{:.6}", s.metrics.route_completion)),
    ("infractions", |s| s.infractions.len().to_string()),
    ("final_state", |s| s.metrics.final_state.clone()),
];

fn optional(v: Option<f64>) -> String {
    v.map(|v| format!("{v:.6}")).unwrap_or_default()
}

/// The triage of a scored run: the first failed phase, the criteria not met, and why it failed.
pub fn triage(score: &Score) -> (String, String, String) {
    let phase = score.phases.iter().find(|p| p.status == PhaseStatus::Failed);
    let failed: Vec<&crate::score::CriterionResult> = score.criteria.iter().filter(|c| !c.passed).collect();
    let criteria = failed.iter().map(|c| c.name.as_str()).collect::<Vec<_>>().join(";");
    let reason = if score.success {
        String::new()
    } else if let Some(r) = &score.abort_reason {
        r.clone()
    } else if let Some(p) = phase {
        format!("phase {} failed: {}", p.name, p.reason.as_deref().unwrap_or("no reason given"))
    } else if !failed.is_empty() {
        let each: Vec<String> =
            failed.iter().map(|c| format!("{} = {} (wanted {})", c.name, c.value, c.limit)).collect();
        format!("criteria not met: {}", each.join(", "))
    } else {
        score.outcome.clone()
    };
    (phase.map(|p| p.name.clone()).unwrap_or_default(), criteria, one_line(&reason))
}

/// Text on one line (newlines and tabs become spaces, runs of spaces one), for a CSV cell.
pub fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

const TRIAGE: [&str; 3] = ["failed_phase", "failed_criteria", "reason"];

pub(crate) fn header(sweep: &SweepFile) -> Vec<String> {
    let mut h = vec!["index".to_string(), "seed".into()];
    h.extend(sweep.dispersions.iter().map(|d| d.key.clone()));
    h.extend(["success".to_string(), "outcome".into()]);
    h.extend(TRIAGE.map(String::from));
    h.extend(METRICS.iter().map(|(name, _)| name.to_string()));
    h.extend(["reproduce".to_string(), "wall_time_s".into()]);
    h
}

pub(crate) fn row_record(r: &Row) -> Vec<String> {
    let mut v = vec![r.index.to_string(), r.seed.to_string()];
    v.extend(r.values.iter().cloned());
    v.extend([r.success.to_string(), r.outcome.clone()]);
    v.extend([r.failed_phase.clone(), r.failed_criteria.clone(), r.reason.clone()]);
    v.extend(r.metrics.iter().cloned());
    v.extend([r.reproduce.clone(), format!("{:.3}", r.wall_time_s)]);
    v
}

/// Reads one record by column name (`runs.csv` written before the triage columns existed reads
/// with them empty).
fn parse_row(head: &BTreeMap<String, usize>, rec: &csv::StringRecord, n_disp: usize) -> Result<Row> {
    let col = |name: &str| head.get(name).copied();
    let get = |name: &str| -> Result<String> {
        let i = col(name).ok_or_else(|| anyhow!("no column '{name}'"))?;
        rec.get(i).map(str::to_string).ok_or_else(|| anyhow!("short row (no '{name}')"))
    };
    let optional = |name: &str| col(name).and_then(|i| rec.get(i)).unwrap_or_default().to_string();
    let first = col("seed").ok_or_else(|| anyhow!("no column 'seed'"))? + 1;
    let values = (first..first + n_disp)
        .map(|i| rec.get(i).map(str::to_string).ok_or_else(|| anyhow!("short row")))
        .collect::<Result<Vec<_>>>()?;
    Ok(Row {
        index: get("index")?.parse().context("index")?,
        seed: get("seed")?.parse().context("seed")?,
        values,
        success: get("success")?.parse().context("success")?,
        outcome: get("outcome")?,
        failed_phase: optional("failed_phase"),
        failed_criteria: optional("failed_criteria"),
        reason: optional("reason"),
        metrics: METRICS.iter().map(|(name, _)| optional(name)).collect(),
        reproduce: get("reproduce")?,
        wall_time_s: get("wall_time_s")?.parse().context("wall_time_s")?,
    })
}

/// Campaign identity, written beside the results so that `merge`, `--resume`, `--rerun-failed`
/// and `compare` know what a folder holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Campaign {
    /// The sweep file.
    pub sweep_file: String,
    /// Its content (as loaded).
    pub sweep: SweepFile,
    /// Shard `[k, n]`.
    pub shard: Option<[u64; 2]>,
    /// The run indices asked for, when not every run of the campaign (or shard) was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub indices: Option<Vec<u64>>,
    /// Runs of the whole campaign.
    pub runs: u64,
    /// What made the results: inputs and binary (absent in folders written before it existed).
    #[serde(default)]
    pub provenance: Option<Provenance>,
}

/// Reads a sweep folder: its campaign and the rows of its `runs.csv`, by index. A last line cut
/// short (a sweep killed while writing it) is dropped; any other bad line is an error naming it.
pub fn read(dir: &Path) -> Result<(Campaign, Vec<Row>)> {
    let cpath = dir.join("campaign.json");
    let c: Campaign = serde_json::from_str(
        &std::fs::read_to_string(&cpath)
            .with_context(|| format!("{}: not a sweep folder (no campaign.json)", dir.display()))?,
    )
    .with_context(|| cpath.display().to_string())?;
    let path = dir.join("runs.csv");
    let mut r = csv::ReaderBuilder::new()
        .flexible(true)
        .from_path(&path)
        .with_context(|| format!("reading {}", path.display()))?;
    let head: BTreeMap<String, usize> =
        r.headers()?.iter().enumerate().map(|(i, h)| (h.to_string(), i)).collect();
    let records: Vec<_> = r.records().collect();
    let mut rows: BTreeMap<u64, Row> = BTreeMap::new();
    for (line, rec) in records.iter().enumerate() {
        let last = line + 1 == records.len();
        let parsed = rec
            .as_ref()
            .map_err(|e| anyhow!("{e}"))
            .and_then(|rec| parse_row(&head, rec, c.sweep.dispersions.len()));
        match parsed {
            Ok(row) => {
                let index = row.index;
                if rows.insert(index, row).is_some() {
                    bail!("{}:{}: run {index} appears twice", path.display(), line + 2);
                }
            }
            Err(_) if last => {}
            Err(e) => return Err(e.context(format!("{}:{}", path.display(), line + 2))),
        }
    }
    Ok((c, rows.into_values().collect()))
}

pub(crate) fn write_csv(path: &Path, sweep: &SweepFile, rows: &[Row]) -> Result<()> {
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

/// Writes `runs.csv`, `summary.json`, `junit.xml` and `report.html` for `rows`; returns the
/// summary.
pub fn write_results(
    out: &Path,
    sweep: &SweepFile,
    rows: &[Row],
    partial: bool,
    campaign: Option<&Campaign>,
) -> Result<Summary> {
    write_csv(&out.join("runs.csv"), sweep, rows)?;
    let summary = summarize(rows, partial, campaign.and_then(|c| c.provenance.clone()));
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&summary)? + "\n")?;
    let name = campaign.map(|c| c.sweep_file.clone()).unwrap_or_else(|| sweep.sweep.scenario.clone());
    super::junit::write(&out.join("junit.xml"), &name, sweep, rows, &summary)?;
    super::report::write(out, sweep, rows, &summary, campaign)?;
    Ok(summary)
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
    /// Not every planned run finished (interrupted, a shard, or a subset of the indices).
    pub partial: bool,
    /// Per numeric metric.
    pub metrics: BTreeMap<String, MetricSummary>,
    /// Outcomes counted.
    pub outcomes: BTreeMap<String, usize>,
    /// The failed runs' indices grouped by cause (outcome, failed phase, criteria not met).
    #[serde(default)]
    pub failures_by_cause: BTreeMap<String, Vec<u64>>,
    /// What made the results.
    #[serde(default)]
    pub provenance: Option<Provenance>,
}

impl Summary {
    /// The success rate with its interval, as a person reads it.
    pub fn rate_text(&self) -> String {
        let [lo, hi] = self.success_rate_ci95;
        format!(
            "{} of {} runs succeeded: {:.1}% (95% CI {:.1}%-{:.1}%)",
            self.successes,
            self.runs,
            100.0 * self.success_rate,
            100.0 * lo,
            100.0 * hi
        )
    }
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

/// A metric cell as a number (`true`/`false` as 1/0), if it is one.
pub fn metric_value(text: &str) -> Option<f64> {
    match text {
        "true" => Some(1.0),
        "false" => Some(0.0),
        _ => text.parse::<f64>().ok(),
    }
}

/// Numeric values of metric column `k`.
pub fn metric_values(rows: &[Row], k: usize) -> Vec<f64> {
    rows.iter().filter_map(|r| metric_value(r.metrics.get(k)?)).collect()
}

fn summarize(rows: &[Row], partial: bool, provenance: Option<Provenance>) -> Summary {
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
    let mut failures_by_cause: BTreeMap<String, Vec<u64>> = BTreeMap::new();
    for r in rows {
        *outcomes.entry(r.outcome.clone()).or_insert(0) += 1;
        if let Some(c) = r.cause() {
            failures_by_cause.entry(c).or_default().push(r.index);
        }
    }
    Summary {
        runs: rows.len(),
        successes,
        success_rate: if rows.is_empty() { 0.0 } else { successes as f64 / rows.len() as f64 },
        success_rate_ci95: wilson(successes, rows.len()),
        partial,
        metrics,
        outcomes,
        failures_by_cause,
        provenance,
    }
}

/// Joins shard folders into `out`: the same `runs.csv`, `summary.json` and report an unsharded
/// sweep gives (wall-clock columns aside). Shards of another campaign, or made from other inputs
/// or another build (their provenance differs), are refused. Each run's score and track are
/// copied into `out/runs/<index>/` (the report draws the tracks from there); logs stay in their
/// shard.
pub fn merge(dirs: &[PathBuf], out: &Path) -> Result<(Vec<Row>, Summary)> {
    let mut campaign: Option<(Campaign, &Path)> = None;
    let mut rows: BTreeMap<u64, Row> = BTreeMap::new();
    let mut shard_of: BTreeMap<u64, &Path> = BTreeMap::new();
    for d in dirs {
        let (c, shard_rows) = read(d)?;
        if let Some((first, first_dir)) = &campaign {
            if first.sweep != c.sweep || first.runs != c.runs {
                bail!("{}: a shard of another campaign (sweep file or run count differ)", d.display());
            }
            let diff = Provenance::differences(first.provenance.as_ref(), c.provenance.as_ref());
            if !diff.is_empty() {
                bail!(
                    "{}: made from other inputs or another build than {}: {}",
                    d.display(),
                    first_dir.display(),
                    diff.join("; ")
                );
            }
        }
        for row in shard_rows {
            shard_of.insert(row.index, d);
            let index = row.index;
            if rows.insert(index, row).is_some() {
                bail!("{}: run {index} appears in two shards", d.join("runs.csv").display());
            }
        }
        if campaign.is_none() {
            campaign = Some((c, d));
        }
    }
    let (c, _) = campaign.ok_or_else(|| anyhow!("no shard folders given"))?;
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
    let merged = Campaign { shard: None, indices: None, ..c };
    std::fs::write(out.join("campaign.json"), serde_json::to_string_pretty(&merged)?)?;
    let summary = write_results(out, &merged.sweep, &rows, partial, Some(&merged))?;
    Ok((rows, summary))
}
