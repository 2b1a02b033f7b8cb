//! Infractions in the logs, at the time they happen: a warning in Rerun's `logs/infractions` (and
//! a point where the rover was, in the 3D view) and a `foxglove.Log` on MCAP's `/infractions`.

use super::Writer;
use super::mcap_writer::stamp_json;
use crate::Infraction;
use anyhow::Result;
use framework::Time;

impl Writer {
    pub(super) fn infractions(&mut self, now: Time, list: Vec<Infraction>) -> Result<()> {
        for i in list {
            let text = format!(
                "{} at {:.2} s, ({:.2}, {:.2}, {:.2}) m: {}",
                i.kind, i.t_s, i.position_m[0], i.position_m[1], i.position_m[2], i.detail
            );
            if let Some(rec) = &self.rrd {
                rec.log(
                    "logs/infractions",
                    &rerun::TextLog::new(text.clone()).with_level(rerun::TextLogLevel::WARN),
                )?;
                // One entity each, so that a later infraction does not replace an earlier one.
                self.infractions_logged += 1;
                rec.log(
                    format!("world/infractions/{}/{}", i.kind, self.infractions_logged),
                    &rerun::Points3D::new([i.position_m.map(|v| v as f32)])
                        .with_radii([0.15])
                        .with_colors([rerun::Color::from_rgb(230, 60, 30)]),
                )?;
            }
            if let Some(m) = &mut self.mcap {
                m.foxglove(
                    "/infractions",
                    "foxglove.Log",
                    now,
                    &serde_json::json!({
                        "timestamp": stamp_json(Time::from_secs_f64(i.t_s)), "level": 3, "message": text,
                        "name": i.kind, "file": "", "line": 0,
                    }),
                )?;
            }
        }
        Ok(())
    }
}
