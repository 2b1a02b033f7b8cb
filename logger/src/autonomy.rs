//! Autonomy's state in the logs: the plan's activities as a table and each fault with Autonomy's
//! response as a log line (Rerun); the faults as `foxglove.Log` messages on `/autonomy/faults`
//! (MCAP, where the whole state is also under `/slots/autonomy/state`).

use super::Writer;
use super::mcap_writer::stamp_json;
use anyhow::Result;
use framework::data::AutonomyState;

impl Writer {
    pub(super) fn autonomy(&mut self, stamp: framework::Time, s: &AutonomyState) -> Result<()> {
        let new = s.faults.get(self.autonomy_faults_seen..).unwrap_or_default();
        if let Some(rec) = &self.rrd {
            let mut md = String::from(
                "| activity | status | attempts | start s | end s | reason |\n|---|---|---|---|---|---|\n",
            );
            for a in &s.activities {
                let t = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.1}"));
                md += &format!(
                    "| {} | {:?} | {} | {} | {} | {} |\n",
                    a.name,
                    a.status,
                    a.attempts,
                    t(a.start_s),
                    t(a.end_s),
                    a.reason.as_deref().unwrap_or("").replace('|', "/")
                );
            }
            if let Some(end) = s.end {
                md += &format!("\nMission ended: {end:?}\n");
            }
            rec.log("autonomy/plan", &rerun::TextDocument::from_markdown(md))?;
            for f in new {
                rec.log(
                    "autonomy/faults",
                    &rerun::TextLog::new(format!("{}: {} -> {}", f.activity, f.fault, f.response))
                        .with_level(rerun::TextLogLevel::WARN),
                )?;
            }
        }
        if let Some(m) = &mut self.mcap {
            for f in new {
                let msg = serde_json::json!({
                    "timestamp": stamp_json(stamp), "level": 3, "name": "autonomy",
                    "message": format!("{}: {} -> {}", f.activity, f.fault, f.response), "file": "", "line": 0,
                });
                m.foxglove("/autonomy/faults", "foxglove.Log", stamp, &msg)?;
            }
        }
        self.autonomy_faults_seen = s.faults.len();
        Ok(())
    }
}
