//! Infractions: what the rover did that it should not have, each with when and where (as CARLA's
//! leaderboard lists them). From ground truth and the system's event log, for the score and the
//! logs only: nothing here feeds back into the run.
//!
//! Kinds: `collision` (a rover part against a rock or an object), `self_collision` (the arm, the
//! gripper or a held canister against the rover's body), `tilt` (the body tilted past the
//! scenario's `max_tilt_deg`, or [`DEFAULT_TILT_LIMIT_DEG`]: once per excursion), `safe` (the
//! system entered Safe), `isolated` (the watchdog isolated a module), `timeout` (a phase's step or
//! the run's time limit ran out).

use crate::score::{PhaseResult, PhaseStatus};
use framework::Time;
use framework::events::{Event, EventKind};

/// The tilt limit when the scenario sets none, degrees (the rover's static stability margin).
pub const DEFAULT_TILT_LIMIT_DEG: f64 = 30.0;
/// How far below the limit the tilt must come back before another excursion counts, degrees.
const TILT_REARM_DEG: f64 = 1.0;

pub use logger::Infraction;

/// Collects infractions as the run goes.
pub struct Infractions {
    tilt_limit_deg: f64,
    tilted: bool,
    contacts_seen: usize,
    events_seen: usize,
    /// Where the base was at the latest sample.
    last_xy: [f64; 3],
    /// Where it was each second, for what is known only by its time at the end.
    track: Vec<(f64, [f64; 3])>,
    list: Vec<Infraction>,
    logged: usize,
}

impl Infractions {
    /// A collector for a scenario whose tilt limit is `max_tilt_deg` (if it sets one).
    pub fn new(max_tilt_deg: Option<f64>) -> Self {
        Infractions {
            tilt_limit_deg: max_tilt_deg.unwrap_or(DEFAULT_TILT_LIMIT_DEG),
            tilted: false,
            contacts_seen: 0,
            events_seen: 0,
            last_xy: [0.0; 3],
            track: Vec::new(),
            list: Vec::new(),
            logged: 0,
        }
    }

    fn add(&mut self, kind: &str, t_s: f64, detail: String) {
        self.list.push(Infraction { kind: kind.into(), t_s, position_m: self.last_xy, detail });
    }

    /// Looks at the twin's truth and the event log at `now`.
    pub fn sample(&mut self, now: Time, twin: &twin::Twin, log: &framework::events::EventLog) {
        let base = twin.base_pose();
        self.last_xy = base.translation.vector.into();
        let t = now.as_secs_f64();
        if self.track.last().is_none_or(|l| t - l.0 >= 1.0 - 1e-9) {
            self.track.push((t, self.last_xy));
        }
        let tilt = framework::angle::tilt_deg(&base);
        if tilt > self.tilt_limit_deg && !self.tilted {
            self.add("tilt", t, format!("body tilted {tilt:.1} deg (limit {:.1} deg)", self.tilt_limit_deg));
            self.tilted = true;
        } else if tilt < self.tilt_limit_deg - TILT_REARM_DEG {
            // One excursion ends when the body is well back below the limit, not at every
            // crossing of a body shaking at it.
            self.tilted = false;
        }
        let contacts = twin.contact_events();
        for c in contacts.get(self.contacts_seen..).unwrap_or_default().to_vec() {
            let kind = if c.self_collision { "self_collision" } else { "collision" };
            self.add(kind, c.t_s, format!("{} against {}", c.parts[0], c.parts[1]));
        }
        self.contacts_seen = contacts.len();
        let (events, count) = log.since(self.events_seen);
        self.events_seen = count;
        self.read_events(&events);
    }

    fn read_events(&mut self, events: &[Event]) {
        for e in events {
            let t = e.stamp.as_secs_f64();
            match &e.kind {
                EventKind::SystemState { to: framework::Lifecycle::Safe, from } => {
                    self.add("safe", t, format!("the system went from {from} to Safe"));
                }
                EventKind::ModuleIsolated { module, fault } => {
                    let why = serde_json::to_string(fault).unwrap_or_default();
                    self.add("isolated", t, format!("module '{module}' isolated: {why}"));
                }
                _ => {}
            }
        }
    }

    /// Where the base was at time `t` (the nearest sample of a second's track before it).
    fn position_at(&self, t: f64) -> [f64; 3] {
        let k = self.track.partition_point(|s| s.0 <= t);
        self.track.get(k.saturating_sub(1)).map(|s| s.1).unwrap_or(self.last_xy)
    }

    /// The infractions found since the last call (for the logs, as they happen).
    pub fn new_since_last(&mut self) -> Vec<Infraction> {
        let new = self.list[self.logged..].to_vec();
        self.logged = self.list.len();
        new
    }

    /// At the end of the run: the last of the event log (the Safe or Hold the plan's end asked
    /// for), the contacts beyond those the twin lists, and the phases' timeouts. What this adds
    /// comes out of [`Infractions::new_since_last`] like the rest, for the logs.
    pub fn close(&mut self, phases: &[PhaseResult], log: &framework::events::EventLog, twin: &twin::Twin) {
        let (events, count) = log.since(self.events_seen);
        self.events_seen = count;
        self.read_events(&events);
        let counted = (twin.collisions() + twin.self_collisions()) as usize;
        let listed = twin.contact_events().len();
        if counted > listed {
            let t = twin.time().as_secs_f64();
            self.add(
                "collision",
                t,
                format!(
                    "{} more contacts than the twin lists (it keeps the first {listed})",
                    counted - listed
                ),
            );
        }
        for p in phases {
            let Some(reason) = p.reason.as_deref() else { continue };
            // Autonomy's words for a step out of time, and the runner's for the run's limit.
            if p.status == PhaseStatus::Failed
                && (reason.contains("did not complete within") || reason.contains("time limit"))
            {
                let t = p.end_s.unwrap_or_default();
                let at = self.position_at(t);
                self.list.push(Infraction {
                    kind: "timeout".into(),
                    t_s: t,
                    position_m: at,
                    detail: format!("phase {}: {reason}", p.name),
                });
            }
        }
    }

    /// Every infraction, in time order.
    pub fn into_list(mut self) -> Vec<Infraction> {
        self.list.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
        self.list
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn safe_entries_and_isolations_come_from_the_event_log_once_each() {
        let mut f = Infractions::new(None);
        let log = framework::events::EventLog::default();
        log.raise(
            Time::from_secs_f64(2.0),
            EventKind::SystemState { from: framework::Lifecycle::Run, to: framework::Lifecycle::Safe },
        );
        log.raise(
            Time::from_secs_f64(3.0),
            EventKind::SystemState { from: framework::Lifecycle::Safe, to: framework::Lifecycle::Hold },
        );
        let (events, n) = log.since(0);
        f.read_events(&events);
        f.events_seen = n;
        let (events, _) = log.since(f.events_seen);
        f.read_events(&events);
        let all = f.into_list();
        assert_eq!(all.len(), 1);
        assert_eq!((all[0].kind.as_str(), all[0].t_s), ("safe", 2.0));
    }
}
