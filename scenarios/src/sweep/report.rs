//! The sweep report: one self-contained HTML page with SVG plots (plotters) — success rate by
//! dispersed parameter, metric histograms, and the rover tracks over the yard.

use super::{Campaign, METRICS, Row, Summary, SweepFile, metric_values};
use anyhow::Result;
use plotters::prelude::*;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

const W: u32 = 560;
const H: u32 = 340;

fn svg(
    draw: impl FnOnce(&DrawingArea<SVGBackend<'_>, plotters::coord::Shift>) -> Result<()>,
) -> Result<String> {
    let mut buf = String::new();
    {
        let root = SVGBackend::with_string(&mut buf, (W, H)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
        draw(&root)?;
        root.present().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(buf)
}

fn range(v: &[f64]) -> (f64, f64) {
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-9 { (lo - 0.5, hi + 0.5) } else { (lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)) }
}

macro_rules! plot_err {
    ($e:expr) => {
        $e.map_err(|e| anyhow::anyhow!("plot: {e}"))?
    };
}

/// Success (1) or failure (0) of each run against a dispersed parameter, with the success rate of
/// equal-count bins drawn over it.
fn success_by_parameter(key: &str, rows: &[Row], k: usize) -> Result<Option<String>> {
    let pts: Vec<(f64, f64)> = rows
        .iter()
        .filter_map(|r| {
            r.values
                .get(k)?
                .trim_matches('"')
                .parse::<f64>()
                .ok()
                .map(|x| (x, if r.success { 1.0 } else { 0.0 }))
        })
        .collect();
    if pts.is_empty() {
        return Ok(None);
    }
    let (x0, x1) = range(&pts.iter().map(|p| p.0).collect::<Vec<_>>());
    let mut sorted = pts.clone();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
    let bins = (sorted.len() / 5).clamp(1, 8);
    let per = sorted.len().div_ceil(bins);
    let rate: Vec<(f64, f64)> = sorted
        .chunks(per)
        .map(|c| {
            (
                c.iter().map(|p| p.0).sum::<f64>() / c.len() as f64,
                c.iter().map(|p| p.1).sum::<f64>() / c.len() as f64,
            )
        })
        .collect();
    Ok(Some(svg(|root| {
        let mut ch = plot_err!(
            ChartBuilder::on(root)
                .caption(format!("success by {key}"), ("sans-serif", 16))
                .margin(10)
                .x_label_area_size(30)
                .y_label_area_size(40)
                .build_cartesian_2d(x0..x1, -0.05..1.05)
        );
        plot_err!(ch.configure_mesh().x_desc(key).y_desc("success").draw());
        plot_err!(ch.draw_series(pts.iter().map(|&(x, y)| Circle::new(
            (x, y),
            3,
            if y > 0.5 { GREEN.filled() } else { RED.filled() }
        ))));
        plot_err!(ch.draw_series(LineSeries::new(rate.clone(), BLUE.stroke_width(2))));
        Ok(())
    })?))
}

fn histogram(name: &str, values: &[f64]) -> Result<String> {
    let (x0, x1) = range(values);
    let n = 12usize;
    let w = (x1 - x0) / n as f64;
    let mut counts = vec![0u32; n];
    for v in values {
        counts[(((v - x0) / w) as usize).min(n - 1)] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1).max(1);
    svg(|root| {
        let mut ch = plot_err!(
            ChartBuilder::on(root)
                .caption(name, ("sans-serif", 16))
                .margin(10)
                .x_label_area_size(30)
                .y_label_area_size(40)
                .build_cartesian_2d(x0..x1, 0u32..top + 1)
        );
        plot_err!(ch.configure_mesh().x_desc(name).y_desc("runs").draw());
        plot_err!(ch.draw_series(counts.iter().enumerate().map(|(i, &c)| {
            let a = x0 + i as f64 * w;
            Rectangle::new([(a, 0), (a + w, c)], BLUE.mix(0.6).filled())
        })));
        Ok(())
    })
}

/// Reads a run's `track.csv` (t, x, y).
fn track(dir: &Path, index: u64) -> Vec<(f64, f64)> {
    let p = super::run_dir(dir, index).join("track.csv");
    let Ok(mut r) = csv::Reader::from_path(p) else { return Vec::new() };
    r.records()
        .filter_map(|rec| {
            let rec = rec.ok()?;
            Some((rec.get(1)?.parse().ok()?, rec.get(2)?.parse().ok()?))
        })
        .collect()
}

fn tracks(dir: &Path, rows: &[Row]) -> Result<Option<String>> {
    let all: Vec<(bool, Vec<(f64, f64)>)> =
        rows.iter().map(|r| (r.success, track(dir, r.index))).filter(|t| !t.1.is_empty()).collect();
    if all.is_empty() {
        return Ok(None);
    }
    let xs: Vec<f64> = all.iter().flat_map(|t| t.1.iter().map(|p| p.0)).collect();
    let ys: Vec<f64> = all.iter().flat_map(|t| t.1.iter().map(|p| p.1)).collect();
    let ((x0, x1), (y0, y1)) = (range(&xs), range(&ys));
    // Equal scales on both axes.
    let span = (x1 - x0).max(y1 - y0);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    Ok(Some(svg(|root| {
        let mut ch = plot_err!(
            ChartBuilder::on(root)
                .caption("rover tracks (truth; green: success, red: failure)", ("sans-serif", 16))
                .margin(10)
                .x_label_area_size(30)
                .y_label_area_size(40)
                .build_cartesian_2d(cx - span * 0.8..cx + span * 0.8, cy - span / 2.0..cy + span / 2.0)
        );
        plot_err!(ch.configure_mesh().x_desc("east (m)").y_desc("north (m)").draw());
        for (ok, t) in &all {
            let c = if *ok { GREEN.mix(0.7) } else { RED.mix(0.7) };
            plot_err!(ch.draw_series(LineSeries::new(t.clone(), c.stroke_width(1))));
        }
        Ok(())
    })?))
}

/// Text escaped for HTML.
pub(crate) fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// Writes `report.html` into `out`.
pub fn write(
    out: &Path,
    sweep: &SweepFile,
    rows: &[Row],
    summary: &Summary,
    campaign: Option<&Campaign>,
) -> Result<()> {
    let mut h = String::new();
    let title = campaign.map(|c| c.sweep_file.clone()).unwrap_or_else(|| sweep.sweep.scenario.clone());
    writeln!(
        h,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>Sweep report: {}</title>",
        esc(&title)
    )?;
    writeln!(
        h,
        "<style>body{{font-family:sans-serif;margin:2em}} svg{{margin:4px;border:1px solid #ddd}} td,th{{padding:2px 8px;text-align:right}}</style></head><body>"
    )?;
    writeln!(
        h,
        "<h1>Sweep report</h1><p>Sweep {} over scenario <code>{}</code>, master seed {}.</p>",
        esc(&title),
        esc(&sweep.sweep.scenario),
        sweep.sweep.master_seed
    )?;
    let [lo, hi] = summary.success_rate_ci95;
    writeln!(
        h,
        "<p><b>{} / {} runs succeeded</b>: success rate {:.1}% (95% CI {:.1}% - {:.1}%){}.</p>",
        summary.successes,
        summary.runs,
        summary.success_rate * 100.0,
        lo * 100.0,
        hi * 100.0,
        if summary.partial { " — partial: not every planned run finished" } else { "" }
    )?;
    writeln!(
        h,
        "<h2>Metrics</h2><table><tr><th>metric</th><th>n</th><th>mean</th><th>min</th><th>p5</th><th>p50</th><th>p95</th><th>max</th></tr>"
    )?;
    for (name, m) in &summary.metrics {
        writeln!(
            h,
            "<tr><td>{name}</td><td>{}</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            m.n, m.mean, m.min, m.p5, m.p50, m.p95, m.max
        )?;
    }
    writeln!(h, "</table>")?;
    if let Some(t) = grid_table(out, sweep, rows)? {
        writeln!(h, "<h2>Outcome by case (grid)</h2><p>Also in <code>grid.csv</code>.</p>")?;
        h.push_str(&t);
    }
    writeln!(h, "<h2>Success by parameter</h2>")?;
    for (k, d) in sweep.dispersions.iter().enumerate() {
        if let Some(s) = success_by_parameter(&d.key, rows, k)? {
            h.push_str(&s);
        }
    }
    writeln!(h, "<h2>Metric histograms</h2>")?;
    for (k, (name, _)) in METRICS.iter().enumerate() {
        let v = metric_values(rows, k);
        if v.len() >= 2 {
            h.push_str(&histogram(name, &v)?);
        }
    }
    if let Some(t) = tracks(out, rows)? {
        writeln!(h, "<h2>Tracks</h2>")?;
        h.push_str(&t);
    }
    if !summary.failures_by_cause.is_empty() {
        writeln!(h, "<h2>Failures by cause</h2><table><tr><th>cause</th><th>runs</th><th>indices</th></tr>")?;
        let mut causes: Vec<_> = summary.failures_by_cause.iter().collect();
        causes.sort_by_key(|(c, runs)| (std::cmp::Reverse(runs.len()), c.as_str()));
        for (cause, runs) in causes {
            let list: Vec<String> = runs.iter().map(u64::to_string).collect();
            writeln!(
                h,
                "<tr><td style=\"text-align:left\">{}</td><td>{}</td><td style=\"text-align:left\">{}</td></tr>",
                esc(cause),
                runs.len(),
                list.join(", ")
            )?;
        }
        writeln!(h, "</table>")?;
    }
    writeln!(h, "<h2>Failed runs</h2><ul>")?;
    for r in rows.iter().filter(|r| !r.success) {
        writeln!(
            h,
            "<li>run {} ({}): {}<br><code>{}</code></li>",
            r.index,
            esc(&r.outcome),
            esc(&r.reason),
            esc(&r.reproduce)
        )?;
    }
    writeln!(h, "</ul></body></html>")?;
    std::fs::write(out.join("report.html"), h)?;
    Ok(())
}

/// A grid value as a short label: a command table (`{to, command, args}`) as `to.command(args)`,
/// anything else as its text.
fn grid_label(text: &str) -> String {
    let v = crate::scenario::parse_value(text);
    let Some(t) = v.as_table() else { return text.trim_matches('"').to_string() };
    match (t.get("to").and_then(|v| v.as_str()), t.get("command").and_then(|v| v.as_str())) {
        (Some(to), Some(c)) => {
            let args = t.get("args").map(|a| a.to_string()).unwrap_or_default();
            format!("{to}.{c}{}", if args.is_empty() { String::new() } else { format!(" {args}") })
        }
        _ => text.to_string(),
    }
}

/// One run of a grid, as a table cell: its outcome, the phase that failed and why, the system's
/// final state and what Autonomy did about faults (from the run's `score.json`).
pub fn grid_cell(dir: &Path, row: &Row) -> String {
    let p = super::run_dir(dir, row.index).join("score.json");
    let Ok(score) = std::fs::read_to_string(&p)
        .map_err(anyhow::Error::from)
        .and_then(|t| serde_json::from_str::<crate::score::Score>(&t).map_err(anyhow::Error::from))
    else {
        return row.outcome.clone();
    };
    let mut cell = if score.success { "success".to_string() } else { score.outcome.clone() };
    if let Some(f) = score.phases.iter().find(|p| !p.success && p.status == crate::score::PhaseStatus::Failed)
    {
        cell += &format!("; {} failed: {}", f.name, f.reason.as_deref().unwrap_or("?"));
    }
    cell += &format!("; final state {}", score.metrics.final_state);
    let responses: Vec<String> =
        score.faults.iter().map(|f| format!("{} ({})", f.response, f.activity)).collect();
    if !responses.is_empty() {
        cell += &format!("; autonomy: {}", responses.join(", "));
    }
    cell
}

/// The runs of a sweep with grid dispersions as a matrix: the first grid's values down, the
/// second's across (one column when there is one grid); `grid.csv` holds the same, one run a line.
pub fn grid_table(out: &Path, sweep: &SweepFile, rows: &[Row]) -> Result<Option<String>> {
    let grids: Vec<usize> =
        sweep.dispersions.iter().enumerate().filter(|(_, d)| d.grid.is_some()).map(|(k, _)| k).collect();
    let Some(&down) = grids.first() else { return Ok(None) };
    let across = grids.get(1).copied();
    let mut csv = csv::Writer::from_path(out.join("grid.csv"))?;
    let mut head: Vec<String> = grids.iter().map(|&k| sweep.dispersions[k].key.clone()).collect();
    head.extend(["index", "success", "outcome"].map(String::from));
    csv.write_record(&head)?;
    let mut cells: BTreeMap<(String, String), Vec<(bool, String)>> = BTreeMap::new();
    let (mut downs, mut acrosses) = (Vec::new(), Vec::new());
    for r in rows {
        let d = grid_label(&r.values[down]);
        let a = across.map(|k| grid_label(&r.values[k])).unwrap_or_default();
        if !downs.contains(&d) {
            downs.push(d.clone());
        }
        if !acrosses.contains(&a) {
            acrosses.push(a.clone());
        }
        let cell = grid_cell(out, r);
        let mut rec: Vec<String> = grids.iter().map(|&k| grid_label(&r.values[k])).collect();
        rec.extend([r.index.to_string(), r.success.to_string(), cell.clone()]);
        csv.write_record(&rec)?;
        cells.entry((d, a)).or_default().push((r.success, cell));
    }
    csv.flush()?;
    let mut h = String::from("<table border=\"1\" style=\"border-collapse:collapse\"><tr><th></th>");
    for a in &acrosses {
        write!(h, "<th>{}</th>", esc(a))?;
    }
    h.push_str("</tr>");
    for d in &downs {
        write!(h, "<tr><th style=\"text-align:left\">{}</th>", esc(d))?;
        for a in &acrosses {
            let list = cells.get(&(d.clone(), a.clone())).cloned().unwrap_or_default();
            let ok = !list.is_empty() && list.iter().all(|c| c.0);
            let text: Vec<String> = list.iter().map(|c| esc(&c.1)).collect();
            write!(
                h,
                "<td style=\"text-align:left;background:{}\">{}</td>",
                if ok { "#dfd" } else { "#fdd" },
                text.join("<br>")
            )?;
        }
        h.push_str("</tr>");
    }
    h.push_str("</table>");
    Ok(Some(h))
}
