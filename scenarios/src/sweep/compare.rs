//! `rover-twin sweep compare A B`: what changed from campaign A to campaign B (before and after a
//! change of the code or the scenario).
//!
//! When both ran the same plans (every shared index has the same seed and dispersed values), the
//! runs pair by index: the outcome changes are listed run by run, the success rates are compared
//! with McNemar's exact test on the runs whose outcome changed, and each metric's shift is taken
//! run by run. Otherwise the campaigns are two samples: Fisher's exact test, and shifts of the
//! medians. `compare.json` and `compare.html` (with plots) hold the result.

use super::report::esc;
use super::results::{METRICS, Row, metric_value, read, wilson};
use anyhow::{Result, bail};
use plotters::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// One campaign's side of a comparison.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Side {
    /// Its folder.
    pub dir: String,
    /// Runs.
    pub runs: usize,
    /// Successes.
    pub successes: usize,
    /// Success rate.
    pub success_rate: f64,
    /// 95% Wilson interval.
    pub success_rate_ci95: [f64; 2],
}

/// A run whose outcome changed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Change {
    /// Run index.
    pub index: u64,
    /// Outcome (and cause of failure) in A.
    pub a: String,
    /// Outcome (and cause of failure) in B.
    pub b: String,
}

/// The shift of one metric from A to B.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shift {
    /// Values compared: pairs (paired), else the smaller of the two sample sizes.
    pub n: usize,
    /// Median in A.
    pub median_a: f64,
    /// Median in B.
    pub median_b: f64,
    /// Paired: the median of the per-run differences B - A; unpaired: median_b - median_a.
    pub median_shift: f64,
    /// Paired: the largest per-run |B - A| (0 for unpaired).
    pub max_abs_shift: f64,
}

/// `compare.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Comparison {
    /// Campaign A.
    pub a: Side,
    /// Campaign B.
    pub b: Side,
    /// The runs pair by index (same plans).
    pub paired: bool,
    /// Indices run in both.
    pub common_runs: usize,
    /// Success rate of B minus A (paired: over the runs both made).
    pub success_rate_difference: f64,
    /// The test used: `mcnemar_exact` (paired) or `fisher_exact`.
    pub test: String,
    /// Its two-sided p-value (1 when nothing differs).
    pub p_value: f64,
    /// Paired: runs that failed in A and succeed in B.
    pub fixed: Vec<u64>,
    /// Paired: runs that succeeded in A and fail in B.
    pub broken: Vec<u64>,
    /// Paired: every run whose outcome or cause of failure changed.
    pub changes: Vec<Change>,
    /// Metric shifts, by metric.
    pub metrics: BTreeMap<String, Shift>,
}

impl Comparison {
    /// Nothing changed: same outcomes run by run and no metric moved.
    pub fn unchanged(&self) -> bool {
        self.paired
            && self.changes.is_empty()
            && self.a.runs == self.b.runs
            && self.common_runs == self.a.runs
            && self.metrics.values().all(|s| s.max_abs_shift == 0.0)
    }
}

/// ln(k!) for k = 0..=n.
fn ln_factorials(n: usize) -> Vec<f64> {
    let mut v = vec![0.0; n + 1];
    for k in 1..=n {
        v[k] = v[k - 1] + (k as f64).ln();
    }
    v
}

/// McNemar's exact test: two-sided p of `b` against `c` discordant pairs (binomial, p = 1/2).
pub fn mcnemar_exact(b: usize, c: usize) -> f64 {
    let n = b + c;
    if n == 0 {
        return 1.0;
    }
    let lf = ln_factorials(n);
    let tail: f64 =
        (0..=b.min(c)).map(|k| (lf[n] - lf[k] - lf[n - k] - n as f64 * std::f64::consts::LN_2).exp()).sum();
    (2.0 * tail).min(1.0)
}

/// Fisher's exact test on the table [[a, b], [c, d]] (successes and failures of two samples):
/// the two-sided p, summing the tables at most as likely as the one observed.
pub fn fisher_exact(a: usize, b: usize, c: usize, d: usize) -> f64 {
    let (r1, r2, c1, n) = (a + b, c + d, a + c, a + b + c + d);
    if n == 0 {
        return 1.0;
    }
    let lf = ln_factorials(n);
    let ln_p = |x: usize| {
        lf[r1] + lf[r2] + lf[c1] + lf[n - c1] - lf[n] - lf[x] - lf[r1 - x] - lf[c1 - x] - lf[r2 + x - c1]
    };
    let (lo, hi) = (c1.saturating_sub(r2), r1.min(c1));
    let observed = ln_p(a);
    let p: f64 = (lo..=hi).map(ln_p).filter(|&l| l <= observed + 1e-7).map(f64::exp).sum();
    p.min(1.0)
}

fn side(dir: &Path, rows: &[Row]) -> Side {
    let successes = rows.iter().filter(|r| r.success).count();
    Side {
        dir: dir.display().to_string(),
        runs: rows.len(),
        successes,
        success_rate: if rows.is_empty() { 0.0 } else { successes as f64 / rows.len() as f64 },
        success_rate_ci95: wilson(successes, rows.len()),
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    super::results::percentile(&v, 0.5)
}

fn label(r: &Row) -> String {
    r.cause().unwrap_or_else(|| "success".into())
}

/// Compares the rows of two campaigns.
pub fn compare_rows(dir_a: &Path, a: &[Row], dir_b: &Path, b: &[Row]) -> Comparison {
    let by_b: BTreeMap<u64, &Row> = b.iter().map(|r| (r.index, r)).collect();
    let pairs: Vec<(&Row, &Row)> = a.iter().filter_map(|r| by_b.get(&r.index).map(|s| (r, *s))).collect();
    let paired = !pairs.is_empty() && pairs.iter().all(|(x, y)| x.seed == y.seed && x.values == y.values);
    let (sa, sb) = (side(dir_a, a), side(dir_b, b));
    let mut cmp = Comparison {
        success_rate_difference: sb.success_rate - sa.success_rate,
        a: sa,
        b: sb,
        paired,
        common_runs: pairs.len(),
        test: String::new(),
        p_value: 1.0,
        fixed: Vec::new(),
        broken: Vec::new(),
        changes: Vec::new(),
        metrics: BTreeMap::new(),
    };
    if paired {
        for (x, y) in &pairs {
            match (x.success, y.success) {
                (false, true) => cmp.fixed.push(x.index),
                (true, false) => cmp.broken.push(x.index),
                _ => {}
            }
            if label(x) != label(y) {
                cmp.changes.push(Change { index: x.index, a: label(x), b: label(y) });
            }
        }
        cmp.test = "mcnemar_exact".into();
        cmp.p_value = mcnemar_exact(cmp.fixed.len(), cmp.broken.len());
        // Over the runs both made, as the test is: a campaign compared with its re-run failures
        // is not a drop of the whole rate.
        cmp.success_rate_difference = (cmp.fixed.len() as f64 - cmp.broken.len() as f64) / pairs.len() as f64;
    } else {
        cmp.test = "fisher_exact".into();
        cmp.p_value = fisher_exact(
            cmp.a.successes,
            cmp.a.runs - cmp.a.successes,
            cmp.b.successes,
            cmp.b.runs - cmp.b.successes,
        );
    }
    for (k, (name, _)) in METRICS.iter().enumerate() {
        let value = |r: &Row| r.metrics.get(k).and_then(|t| metric_value(t));
        let shift = if paired {
            let d: Vec<(f64, f64)> = pairs.iter().filter_map(|(x, y)| Some((value(x)?, value(y)?))).collect();
            if d.is_empty() {
                continue;
            }
            Shift {
                n: d.len(),
                median_a: median(d.iter().map(|p| p.0).collect()),
                median_b: median(d.iter().map(|p| p.1).collect()),
                median_shift: median(d.iter().map(|p| p.1 - p.0).collect()),
                max_abs_shift: d.iter().map(|p| (p.1 - p.0).abs()).fold(0.0, f64::max),
            }
        } else {
            let (va, vb): (Vec<f64>, Vec<f64>) =
                (a.iter().filter_map(value).collect(), b.iter().filter_map(value).collect());
            if va.is_empty() || vb.is_empty() {
                continue;
            }
            let n = va.len().min(vb.len());
            let (ma, mb) = (median(va), median(vb));
            Shift { n, median_a: ma, median_b: mb, median_shift: mb - ma, max_abs_shift: 0.0 }
        };
        cmp.metrics.insert(name.to_string(), shift);
    }
    cmp
}

/// Compares the campaigns in folders `a` and `b`, writes `compare.json` and `compare.html` into
/// `out`, and returns the comparison.
pub fn compare(a: &Path, b: &Path, out: &Path) -> Result<Comparison> {
    let ((ca, ra), (cb, rb)) = (read(a)?, read(b)?);
    if ra.is_empty() || rb.is_empty() {
        bail!("nothing to compare: {} has {} runs, {} has {}", a.display(), ra.len(), b.display(), rb.len());
    }
    let cmp = compare_rows(a, &ra, b, &rb);
    std::fs::create_dir_all(out)?;
    std::fs::write(out.join("compare.json"), serde_json::to_string_pretty(&cmp)? + "\n")?;
    let mut notes = Vec::new();
    if ca.sweep.sweep.scenario != cb.sweep.sweep.scenario {
        notes.push(format!(
            "the scenarios differ: {} vs {}",
            ca.sweep.sweep.scenario, cb.sweep.sweep.scenario
        ));
    }
    let diff = super::provenance::Provenance::differences(ca.provenance.as_ref(), cb.provenance.as_ref());
    if !diff.is_empty() {
        notes.push(format!("provenance: {}", diff.join("; ")));
    }
    write_html(&out.join("compare.html"), &cmp, &ra, &rb, &notes)?;
    Ok(cmp)
}

/// The comparison in a few lines of text.
pub fn text(cmp: &Comparison) -> String {
    let mut t = String::new();
    let rate = |s: &Side| {
        format!(
            "{}/{} = {:.1}% (95% CI {:.1}%-{:.1}%)",
            s.successes,
            s.runs,
            100.0 * s.success_rate,
            100.0 * s.success_rate_ci95[0],
            100.0 * s.success_rate_ci95[1]
        )
    };
    let _ = writeln!(t, "A {}: {}", cmp.a.dir, rate(&cmp.a));
    let _ = writeln!(t, "B {}: {}", cmp.b.dir, rate(&cmp.b));
    let _ = writeln!(
        t,
        "success rate {:+.1} points ({}, {} runs in both): p = {:.4}",
        100.0 * cmp.success_rate_difference,
        if cmp.paired { "paired by index, McNemar exact" } else { "not paired, Fisher exact" },
        cmp.common_runs,
        cmp.p_value
    );
    if cmp.paired {
        let _ = writeln!(t, "fixed (failed in A, succeed in B): {:?}", cmp.fixed);
        let _ = writeln!(t, "broken (succeeded in A, fail in B): {:?}", cmp.broken);
        for c in &cmp.changes {
            let _ = writeln!(t, "  run {}: {} -> {}", c.index, c.a, c.b);
        }
    }
    for (name, s) in &cmp.metrics {
        if s.median_shift != 0.0 || s.max_abs_shift != 0.0 {
            let _ = writeln!(
                t,
                "metric {name}: median {:.4} -> {:.4} (shift {:+.4}{}, n = {})",
                s.median_a,
                s.median_b,
                s.median_shift,
                if cmp.paired { format!(", largest per run {:.4}", s.max_abs_shift) } else { String::new() },
                s.n
            );
        }
    }
    if cmp.unchanged() {
        let _ = writeln!(t, "no change: every run has the same outcome and the same metrics");
    }
    t
}

fn plot(name: &str, cmp: &Comparison, a: &[Row], b: &[Row], k: usize) -> Result<Option<String>> {
    let value = |r: &Row| r.metrics.get(k).and_then(|t| metric_value(t));
    let mut buf = String::new();
    if cmp.paired {
        let by_b: BTreeMap<u64, &Row> = b.iter().map(|r| (r.index, r)).collect();
        let pts: Vec<(f64, f64, bool)> = a
            .iter()
            .filter_map(|x| {
                let y = by_b.get(&x.index)?;
                Some((value(x)?, value(y)?, x.success == y.success))
            })
            .collect();
        if pts.len() < 2 {
            return Ok(None);
        }
        let lo = pts.iter().map(|p| p.0.min(p.1)).fold(f64::INFINITY, f64::min);
        let hi = pts.iter().map(|p| p.0.max(p.1)).fold(f64::NEG_INFINITY, f64::max);
        let pad = if hi - lo < 1e-9 { 0.5 } else { 0.05 * (hi - lo) };
        let (lo, hi) = (lo - pad, hi + pad);
        {
            let root = SVGBackend::with_string(&mut buf, (420, 360)).into_drawing_area();
            root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
            let mut ch = ChartBuilder::on(&root)
                .caption(format!("{name}: B against A, run by run"), ("sans-serif", 15))
                .margin(10)
                .x_label_area_size(30)
                .y_label_area_size(50)
                .build_cartesian_2d(lo..hi, lo..hi)
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            ch.configure_mesh().x_desc("A").y_desc("B").draw().map_err(|e| anyhow::anyhow!("{e}"))?;
            ch.draw_series(LineSeries::new([(lo, lo), (hi, hi)], BLACK.mix(0.3)))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            ch.draw_series(pts.iter().map(|&(x, y, same)| {
                Circle::new((x, y), 3, if same { BLUE.filled() } else { RED.filled() })
            }))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
            root.present().map_err(|e| anyhow::anyhow!("{e}"))?;
        }
        return Ok(Some(buf));
    }
    let sorted = |rows: &[Row]| {
        let mut v: Vec<f64> = rows.iter().filter_map(value).collect();
        v.sort_by(f64::total_cmp);
        v
    };
    let (va, vb) = (sorted(a), sorted(b));
    if va.len() < 2 || vb.len() < 2 {
        return Ok(None);
    }
    let lo = va[0].min(vb[0]);
    let hi = va[va.len() - 1].max(vb[vb.len() - 1]);
    let pad = if hi - lo < 1e-9 { 0.5 } else { 0.05 * (hi - lo) };
    let cdf = |v: &[f64]| -> Vec<(f64, f64)> {
        v.iter().enumerate().map(|(i, &x)| (x, (i + 1) as f64 / v.len() as f64)).collect()
    };
    {
        let root = SVGBackend::with_string(&mut buf, (420, 360)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut ch = ChartBuilder::on(&root)
            .caption(format!("{name}: distribution (A blue, B red)"), ("sans-serif", 15))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(40)
            .build_cartesian_2d(lo - pad..hi + pad, 0.0..1.02)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        ch.configure_mesh()
            .x_desc(name)
            .y_desc("fraction of runs")
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        ch.draw_series(LineSeries::new(cdf(&va), BLUE.stroke_width(2)))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        ch.draw_series(LineSeries::new(cdf(&vb), RED.stroke_width(2))).map_err(|e| anyhow::anyhow!("{e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(Some(buf))
}

fn write_html(path: &PathBuf, cmp: &Comparison, a: &[Row], b: &[Row], notes: &[String]) -> Result<()> {
    let mut h = String::from(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>Sweep comparison</title>\
         <style>body{font-family:sans-serif;margin:2em} svg{margin:4px;border:1px solid #ddd} \
         td,th{padding:2px 8px;text-align:right}</style></head><body><h1>Sweep comparison</h1>",
    );
    writeln!(h, "<pre>{}</pre>", esc(&text(cmp)))?;
    for n in notes {
        writeln!(h, "<p><b>Note:</b> {}</p>", esc(n))?;
    }
    writeln!(
        h,
        "<h2>Metrics</h2><table><tr><th>metric</th><th>n</th><th>median A</th><th>median B</th><th>median shift</th><th>largest shift</th></tr>"
    )?;
    for (name, s) in &cmp.metrics {
        writeln!(
            h,
            "<tr><td>{name}</td><td>{}</td><td>{:.4}</td><td>{:.4}</td><td>{:+.4}</td><td>{:.4}</td></tr>",
            s.n, s.median_a, s.median_b, s.median_shift, s.max_abs_shift
        )?;
    }
    writeln!(h, "</table><h2>Plots</h2>")?;
    if cmp.paired {
        writeln!(h, "<p>Red: runs whose success changed.</p>")?;
    }
    for (k, (name, _)) in METRICS.iter().enumerate() {
        if let Some(svg) = plot(name, cmp, a, b, k)? {
            h.push_str(&svg);
        }
    }
    h.push_str("</body></html>\n");
    std::fs::write(path, h)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_tests_match_their_textbook_values() {
        // McNemar: 1 vs 9 discordant pairs: 2 * P(X <= 1 | n = 10) = 2 * 11/1024.
        assert!((mcnemar_exact(1, 9) - 22.0 / 1024.0).abs() < 1e-12);
        assert_eq!(mcnemar_exact(0, 0), 1.0);
        assert_eq!(mcnemar_exact(3, 3), 1.0);
        // Fisher's tea tasting: [[3, 1], [1, 3]] gives two-sided p = 0.4857.
        assert!((fisher_exact(3, 1, 1, 3) - 0.485_714).abs() < 1e-5);
        // [[10, 0], [0, 10]]: 2 / C(20, 10).
        assert!((fisher_exact(10, 0, 0, 10) - 2.0 / 184_756.0).abs() < 1e-12);
        assert!((fisher_exact(5, 5, 5, 5) - 1.0).abs() < 1e-9);
    }

    fn row(index: u64, success: bool, distance: &str) -> Row {
        let mut metrics = vec![String::new(); METRICS.len()];
        metrics[1] = distance.into();
        Row {
            index,
            seed: 100 + index,
            values: vec!["1.0".into()],
            success,
            outcome: if success { "success" } else { "mission_failure" }.into(),
            failed_phase: if success { "" } else { "drive" }.into(),
            failed_criteria: String::new(),
            reason: String::new(),
            metrics,
            reproduce: String::new(),
            wall_time_s: 1.0,
        }
    }

    #[test]
    fn paired_runs_list_fixed_and_broken_and_metric_shifts() {
        let a = vec![row(0, true, "1.0"), row(1, false, "2.0"), row(2, true, "3.0")];
        let b = vec![row(0, false, "1.5"), row(1, true, "2.0"), row(2, true, "3.0")];
        let c = compare_rows(Path::new("a"), &a, Path::new("b"), &b);
        assert!(c.paired && !c.unchanged());
        assert_eq!((c.fixed.clone(), c.broken.clone()), (vec![1], vec![0]));
        assert_eq!(c.changes.len(), 2);
        assert_eq!(c.metrics["distance_m"].max_abs_shift, 0.5);
        assert_eq!(c.p_value, 1.0);
        let same = compare_rows(Path::new("a"), &a, Path::new("a"), &a);
        assert!(same.unchanged() && same.p_value == 1.0 && same.success_rate_difference == 0.0);
        // Other seeds: two samples, not pairs.
        let other: Vec<Row> = b.iter().map(|r| Row { seed: r.seed + 1, ..r.clone() }).collect();
        let u = compare_rows(Path::new("a"), &a, Path::new("c"), &other);
        assert!(!u.paired && u.test == "fisher_exact" && u.changes.is_empty());
    }
}
