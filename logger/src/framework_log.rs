//! The framework's own records in the logs: events (lifecycle, state changes, notes, isolations),
//! every message and acknowledgement, and the scheduler's statistics per module.

use super::Writer;
use super::json_schema;
use super::mcap_writer::stamp_json;
use anyhow::Result;
use framework::Time;

impl Writer {
    pub(super) fn events(
        &mut self,
        now: Time,
        events: Vec<framework::events::Event>,
        messages: Vec<(String, String, framework::message::Message)>,
    ) -> Result<()> {
        use framework::events::EventKind as K;
        for e in events {
            let (level, rr_level, module) = match &e.kind {
                K::ModuleIsolated { module, .. } => (4, rerun::TextLogLevel::ERROR, Some(module.clone())),
                K::MessageRejected { module, .. } | K::Overrun { module, .. } => {
                    (3, rerun::TextLogLevel::WARN, Some(module.clone()))
                }
                K::ModuleLifecycle { module, .. }
                | K::ModuleState { module, .. }
                | K::MetaStateSwitched { module, .. }
                | K::Note { module, .. } => (2, rerun::TextLogLevel::INFO, Some(module.clone())),
                K::ReservationOverridden { .. } => (3, rerun::TextLogLevel::WARN, None),
                K::SystemState { .. } => (2, rerun::TextLogLevel::INFO, None),
            };
            let text = serde_json::to_string(&e.kind)?;
            if let Some(rec) = &self.rrd {
                rec.log("logs/events", &rerun::TextLog::new(text.clone()).with_level(rr_level))?;
                if let Some(m) = &module {
                    rec.log(format!("modules/{m}"), &rerun::TextLog::new(text.clone()).with_level(rr_level))?;
                }
            }
            if let Some(m) = &mut self.mcap {
                m.foxglove(
                    "/events",
                    "foxglove.Log",
                    now,
                    &serde_json::json!({ "timestamp": stamp_json(e.stamp), "level": level, "message": text, "name": module.unwrap_or_else(|| "system".into()), "file": "", "line": 0 }),
                )?;
            }
        }
        for (from, to, msg) in messages {
            let (kind, what) = match &msg.body {
                framework::message::Body::Command { name, args } => {
                    ("command", format!("{from} -> {to}: {name} {args}"))
                }
                framework::message::Body::Ack(a) => (
                    "ack",
                    format!("{from} -> {to}: ack of {}: {}", a.command, serde_json::to_string(&a.status)?),
                ),
            };
            if let Some(rec) = &self.rrd {
                rec.log(
                    "logs/messages",
                    &rerun::TextLog::new(what.clone()).with_level(rerun::TextLogLevel::DEBUG),
                )?;
            }
            if let Some(m) = &mut self.mcap {
                m.write(
                    "/messages",
                    "rover_twin.Message",
                    || {
                        let properties = serde_json::json!({
                            "id": { "type": "object", "properties": {
                                "sender": { "type": "integer" }, "seq": { "type": "integer" } } },
                            "stamp": { "type": "integer" },
                            "from": { "type": "string" },
                            "to": { "type": "string" },
                            "queue": { "type": "string" },
                            "kind": { "type": "string", "enum": ["command", "ack"] },
                            // A command's name and arguments, or an acknowledgement's status: the
                            // shape varies with the command.
                            "body": json_schema::open_object(),
                        });
                        json_schema::object(
                            "rover_twin.Message",
                            "A message of the message-passing system (command or acknowledgement)",
                            properties,
                        )
                    },
                    now,
                    &serde_json::json!({ "id": serde_json::to_value(msg.id)?, "stamp": msg.stamp.as_nanos(), "from": from, "to": to, "queue": format!("{:?}", msg.queue).to_lowercase(), "kind": kind, "body": msg.body }),
                )?;
            }
        }
        Ok(())
    }

    pub(super) fn stats(&mut self, now: Time, reports: Vec<framework::system::ModuleReport>) -> Result<()> {
        if let Some(rec) = &self.rrd {
            for r in &reports {
                let (c0, e0) = self.last_stats.get(&r.name).copied().unwrap_or((0, 0));
                let cycles = r.stats.cycles - c0;
                if cycles > 0 {
                    let mean_us = (r.stats.exec_total_ns - e0) as f64 / cycles as f64 / 1e3;
                    rec.log(
                        format!("plots/scheduler/{}/exec_mean_us", r.name),
                        &rerun::Scalars::single(mean_us),
                    )?;
                }
                rec.log(
                    format!("plots/scheduler/{}/overruns", r.name),
                    &rerun::Scalars::single(r.stats.overruns as f64),
                )?;
                self.last_stats.insert(r.name.clone(), (r.stats.cycles, r.stats.exec_total_ns));
            }
        }
        if let Some(m) = &mut self.mcap {
            let reports = serde_json::json!({ "modules": reports });
            m.write(
                "/scheduler/stats",
                "rover_twin.ModuleReports",
                || {
                    json_schema::inferred(
                        "rover_twin.ModuleReports",
                        "Per-module lifecycle, FSM state, context and task statistics",
                        &reports,
                    )
                },
                now,
                &reports,
            )?;
        }
        Ok(())
    }
}
