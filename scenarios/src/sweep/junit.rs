//! `junit.xml`: a campaign as a JUnit test report (the Surefire/Jenkins JUnit XML that CI systems
//! read), one test case per run. A mission failure is a `failure` whose message names the criteria
//! not met and the phase that failed; a run that ended without a verdict (timeout, crash, refused
//! input, abort) is an `error`.

use super::SweepFile;
use super::results::{Row, Summary};
use anyhow::{Context, Result};
use std::fmt::Write as _;
use std::path::Path;

/// Text as XML character data or an attribute value: escaped, and without the characters XML 1.0
/// forbids (a run's stderr may carry terminal escapes).
fn xml(s: &str) -> String {
    let clean: String = s
        .chars()
        .filter(|&c| matches!(c, '\t' | '\n' | '\r') || (c >= ' ' && c != '\u{FFFE}' && c != '\u{FFFF}'))
        .collect();
    quick_xml::escape::escape(clean.as_str()).into_owned()
}

/// The failure message of a run: the criteria not met, then the phase that failed.
fn message(r: &Row) -> String {
    let mut m = Vec::new();
    if !r.failed_criteria.is_empty() {
        m.push(format!("criteria not met: {}", r.failed_criteria.replace(';', ", ")));
    }
    if !r.failed_phase.is_empty() {
        m.push(format!("phase {} failed", r.failed_phase));
    }
    if m.is_empty() {
        m.push(r.reason.clone());
    }
    m.join("; ")
}

/// Writes the report of `rows` to `path`.
pub fn write(path: &Path, name: &str, sweep: &SweepFile, rows: &[Row], summary: &Summary) -> Result<()> {
    let is_error = |r: &Row| !r.success && r.outcome != "mission_failure";
    let failures = rows.iter().filter(|r| !r.success && !is_error(r)).count();
    let errors = rows.iter().filter(|r| is_error(r)).count();
    let time: f64 = rows.iter().map(|r| r.wall_time_s).sum();
    let mut x = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    writeln!(
        x,
        "<testsuites name=\"rover-twin sweep\" tests=\"{}\" failures=\"{failures}\" errors=\"{errors}\" time=\"{time:.3}\">",
        rows.len()
    )?;
    writeln!(
        x,
        "  <testsuite name=\"{}\" tests=\"{}\" failures=\"{failures}\" errors=\"{errors}\" skipped=\"0\" time=\"{time:.3}\">",
        xml(name),
        rows.len()
    )?;
    x.push_str("    <properties>\n");
    let mut props = vec![
        ("scenario".to_string(), sweep.sweep.scenario.clone()),
        ("master_seed".into(), sweep.sweep.master_seed.to_string()),
        ("success_rate".into(), format!("{:.6}", summary.success_rate)),
        (
            "success_rate_ci95".into(),
            format!("{:.6} {:.6}", summary.success_rate_ci95[0], summary.success_rate_ci95[1]),
        ),
    ];
    if let Some(p) = &summary.provenance {
        props.push(("version".into(), p.version.clone()));
        props.push(("git_commit".into(), p.git_commit.clone()));
    }
    for (k, v) in props {
        writeln!(x, "      <property name=\"{}\" value=\"{}\"/>", xml(&k), xml(&v))?;
    }
    x.push_str("    </properties>\n");
    let stem = Path::new(&sweep.sweep.scenario).file_stem().map(|s| s.to_string_lossy().into_owned());
    let classname = format!("rover-twin.{}", stem.unwrap_or_default());
    for r in rows {
        write!(
            x,
            "    <testcase name=\"run {:05} (seed {})\" classname=\"{}\" time=\"{:.3}\"",
            r.index,
            r.seed,
            xml(&classname),
            r.wall_time_s
        )?;
        if r.success {
            x.push_str("/>\n");
            continue;
        }
        x.push_str(">\n");
        let tag = if is_error(r) { "error" } else { "failure" };
        writeln!(
            x,
            "      <{tag} type=\"{}\" message=\"{}\">{}\nreproduce: {}</{tag}>",
            xml(&r.outcome),
            xml(&message(r)),
            xml(&r.reason),
            xml(&r.reproduce)
        )?;
        x.push_str("    </testcase>\n");
    }
    x.push_str("  </testsuite>\n</testsuites>\n");
    std::fs::write(path, x).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_escaped_and_stripped_of_what_xml_forbids() {
        assert_eq!(xml("a<b & \"c\"\u{1b}[31m\n"), "a&lt;b &amp; &quot;c&quot;[31m\n");
    }
}
