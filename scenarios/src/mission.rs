//! The runner's side of the mission: the ground plan handed to Autonomy (which runs it, seed 004's
//! decision layer), its progress read back from `autonomy/state` as phase results, and the
//! scenario's events sent when their time or their phase comes, debug commands through the
//! Debugger.

use crate::scenario::{QueueName, Scenario, TimedEvent};
use crate::score::{PhaseResult, PhaseStatus};
use framework::data::{ActivityStatus, AutonomyState, MissionEnd};
use framework::events::{EventKind, EventLog};
use framework::{AckStatus, Command, Endpoint, Lifecycle, MessageId, Reader, Time};

/// The module that runs the plan.
pub const AUTONOMY: &str = "autonomy";

/// The plan handed to Autonomy and what it reports.
pub struct Mission {
    names: Vec<String>,
    reader: Option<Reader<AutonomyState>>,
    execute: Option<MessageId>,
    state: AutonomyState,
    /// Why the plan could not be run at all.
    refused: Option<String>,
    /// Set by [`Mission::close`]: the reason the runner ended the mission.
    closed: Option<(Time, String)>,
    /// Autonomy itself failed: nothing supervises the robot any more.
    lost: bool,
}

impl Mission {
    /// A mission of scenario `s`'s phases, progress read from `board`.
    pub fn new(s: &Scenario, board: &framework::BlackBoard) -> Self {
        Mission {
            names: s.phases.iter().map(|p| p.name.clone()).collect(),
            reader: board.reader::<AutonomyState>(gnc::autonomy::SLOT).ok().flatten(),
            execute: None,
            state: AutonomyState::default(),
            refused: None,
            closed: None,
            lost: false,
        }
    }

    /// Hands the plan to Autonomy (once).
    pub fn start(&mut self, s: &Scenario, ground: &Endpoint) {
        if self.execute.is_some() || self.refused.is_some() || s.phases.is_empty() {
            return;
        }
        let args = serde_json::to_value(s.plan()).unwrap_or_default();
        match ground.send(Command::new(AUTONOMY, "execute").json(args)) {
            Ok(id) => self.execute = Some(id),
            Err(e) => self.refused = Some(format!("cannot hand the plan to '{AUTONOMY}': {e}")),
        }
    }

    /// Reads Autonomy's latest state and the plan's acknowledgement; notices an Autonomy that can
    /// no longer run the plan (isolated in Safe, or its command failed without an end).
    pub fn update(&mut self, now: Time, ground: &Endpoint, core: &framework::system::Core) {
        if let Some(st) = self.reader.as_ref().and_then(|r| r.read()) {
            self.state = st.value.clone();
        }
        match self.execute.and_then(|id| ground.status(id)) {
            Some(AckStatus::Rejected(r)) => {
                self.refused = Some(format!("'{AUTONOMY}' refused the plan: {r}"))
            }
            Some(AckStatus::Failed(r)) if self.state.end.is_none() && self.closed.is_none() => {
                self.closed = Some((now, format!("'{AUTONOMY}' failed: {r}")));
                self.lost = true;
            }
            _ => {}
        }
        let isolated = core
            .modules()
            .iter()
            .find(|m| m.name == AUTONOMY)
            .is_some_and(|m| core.status(m.id).is_isolated());
        if isolated && self.state.end.is_none() && self.closed.is_none() {
            self.closed = Some((now, format!("'{AUTONOMY}' is isolated in Safe: the plan stopped")));
            self.lost = true;
        }
    }

    /// True once the plan has ended (every activity run, or the mission ended early), or has no
    /// phases.
    pub fn finished(&self, s: &Scenario) -> bool {
        s.phases.is_empty() || self.refused.is_some() || self.state.end.is_some() || self.closed.is_some()
    }

    /// The phase under way, for progress lines.
    pub fn current_name(&self) -> &str {
        self.state.current.as_deref().unwrap_or("-")
    }

    /// When phase `name` first started, if it has.
    pub fn started(&self, name: &str) -> Option<f64> {
        self.state.activity(name).and_then(|a| a.start_s)
    }

    /// When phase `name` ended (however), if it has.
    pub fn ended(&self, name: &str) -> Option<f64> {
        self.state
            .activity(name)
            .filter(|a| !matches!(a.status, ActivityStatus::Pending | ActivityStatus::Running))
            .and_then(|a| a.end_s)
    }

    /// The system state the mission's end asks for (Hold after an abort, Safe).
    pub fn end_state(&self) -> Option<Lifecycle> {
        if self.lost {
            // Without its decision layer the robot is put in Safe.
            return Some(Lifecycle::Safe);
        }
        match self.state.end? {
            MissionEnd::Completed => None,
            MissionEnd::Aborted => Some(Lifecycle::Hold),
            MissionEnd::Safe => Some(Lifecycle::Safe),
        }
    }

    /// The faults Autonomy detected and its responses.
    pub fn faults(&self) -> &[framework::data::FaultReport] {
        &self.state.faults
    }

    /// Ends the plan at `now` from outside (time limit, abort): the phase under way fails, the
    /// later ones are not run.
    pub fn close(&mut self, now: Time, reason: &str) {
        if self.closed.is_none() {
            self.closed = Some((now, reason.to_string()));
        }
    }

    /// One result per phase, in plan order.
    pub fn results(&self) -> Vec<PhaseResult> {
        self.names
            .iter()
            .map(|name| {
                let a = self.state.activity(name);
                let (mut status, mut reason) = match a.map(|a| a.status) {
                    Some(ActivityStatus::Succeeded) => (PhaseStatus::Succeeded, None),
                    Some(ActivityStatus::Failed) => (PhaseStatus::Failed, a.and_then(|a| a.reason.clone())),
                    Some(ActivityStatus::NotRun) => (PhaseStatus::NotRun, a.and_then(|a| a.reason.clone())),
                    Some(ActivityStatus::Running) => (PhaseStatus::Failed, None),
                    Some(ActivityStatus::Pending) | None => (PhaseStatus::NotRun, None),
                };
                let mut end_s = a.and_then(|a| a.end_s);
                if let Some(r) = &self.refused {
                    (status, reason) = (PhaseStatus::NotRun, Some(r.clone()));
                } else if reason.is_none() && status != PhaseStatus::Succeeded {
                    let closed = self.closed.as_ref().map(|(t, r)| (t.as_secs_f64(), r.as_str()));
                    reason = Some(match (status.clone(), closed) {
                        (PhaseStatus::Failed, Some((t, r))) => {
                            end_s = Some(t);
                            r.to_string()
                        }
                        (_, Some((_, r))) => format!("mission ended first ({r})"),
                        _ => "mission ended first".to_string(),
                    });
                }
                // A success after retries says what the earlier tries met.
                if status == PhaseStatus::Succeeded && a.is_some_and(|a| a.attempts > 1) {
                    let a = a.expect("checked");
                    reason = Some(format!(
                        "succeeded on attempt {} (before: {})",
                        a.attempts,
                        a.reason.as_deref().unwrap_or("a module restarted")
                    ));
                }
                PhaseResult {
                    name: name.clone(),
                    success: status == PhaseStatus::Succeeded,
                    status,
                    start_s: a.and_then(|a| a.start_s),
                    end_s,
                    reason,
                }
            })
            .collect()
    }
}

/// The scenario's events not sent yet.
pub struct Events {
    /// Each with the time its condition first held (near and module-state triggers).
    pending: Vec<(TimedEvent, Option<f64>)>,
    /// The event log read so far, and when each (module, state) was first entered.
    log_seen: usize,
    entered: std::collections::BTreeMap<(String, String), f64>,
}

impl Events {
    /// The events of `s`, once the system runs: states entered before (the start-up walk) do not
    /// trigger them.
    pub fn new(s: &Scenario, log: &EventLog) -> Self {
        Events {
            pending: s.events.iter().cloned().map(|e| (e, None)).collect(),
            log_seen: log.since(usize::MAX).1,
            entered: Default::default(),
        }
    }

    /// The events not sent, as `module.command`.
    pub fn unsent(&self) -> Vec<String> {
        self.pending.iter().map(|(e, _)| format!("{}.{}", e.to, e.command)).collect()
    }

    /// Sends those whose time has come by `now` (in file order): commands on the debug queue as the
    /// Debugger's `inject`, the others directly. A send that fails is noted in the event log.
    /// `near(object, within_m)` says from ground truth whether the rover is that near the object.
    pub fn send_due(
        &mut self,
        now: Time,
        mission: &Mission,
        ep: &Endpoint,
        log: &EventLog,
        near: &dyn Fn(&str, f64) -> bool,
    ) {
        if self.pending.iter().any(|(e, _)| e.module_state.is_some()) {
            let (events, count) = log.since(self.log_seen);
            self.log_seen = count;
            for ev in events {
                let t = ev.stamp.as_secs_f64();
                let entered = match ev.kind {
                    EventKind::ModuleLifecycle { module, to, .. } => Some((module, to.to_string())),
                    EventKind::ModuleState { module, to, .. } => Some((module, to)),
                    EventKind::SystemState { to, .. } => Some(("system".to_string(), to.to_string())),
                    _ => None,
                };
                if let Some(k) = entered {
                    self.entered.entry(k).or_insert(t);
                }
            }
        }
        let t_now = now.as_secs_f64();
        let mut i = 0;
        while i < self.pending.len() {
            let (e, armed) = &mut self.pending[i];
            let start = if let Some(t) = e.at_s {
                Some(t)
            } else if let Some(p) = &e.phase {
                mission.started(p)
            } else if let Some(p) = &e.phase_end {
                mission.ended(p)
            } else if let Some(n) = &e.near {
                if armed.is_none() && near(&n.object, n.within_m) {
                    *armed = Some(t_now);
                }
                *armed
            } else if let Some(m) = &e.module_state {
                self.entered.get(&(m.module.clone(), m.state.clone())).copied()
            } else {
                None
            };
            let Some(t) = start.map(|s| s + if e.at_s.is_some() { 0.0 } else { e.after_s }) else {
                i += 1;
                continue;
            };
            if Time::from_secs_f64(t) > now {
                i += 1;
                continue;
            }
            let (e, _) = self.pending.remove(i);
            let args = e.args.as_ref().and_then(|a| serde_json::to_value(a).ok()).unwrap_or_default();
            let cmd = match e.queue {
                QueueName::Debug => Command::new(framework::debugger::NAME, "inject")
                    .json(serde_json::json!({ "to": e.to, "command": e.command, "args": args })),
                q => Command::new(e.to.clone(), e.command.clone()).json(args).on(q.into()),
            };
            if let Err(err) = ep.send(cmd) {
                log.raise(
                    now,
                    EventKind::Note {
                        module: "events".into(),
                        text: format!("event {}.{} due at {t} s not sent: {err}", e.to, e.command),
                    },
                );
            }
        }
    }
}

/// Checks every `module_state` trigger of the scenario against the system built for it (`core`):
/// the module is in this configuration, and the state is one of its lifecycle states or one its
/// own machine declares (a trigger on any other would never fire). Errors name the file and line.
pub fn check_triggers(
    loaded: &crate::scenario::Loaded,
    core: &framework::system::Core,
) -> anyhow::Result<()> {
    let lifecycle = |state: &str| framework::Lifecycle::ALL.iter().any(|l| l.name() == state);
    for (i, e) in loaded.scenario.events.iter().enumerate() {
        let Some(m) = &e.module_state else { continue };
        let fail = |key: &str, msg: String| -> anyhow::Result<()> {
            let parts: Vec<String> =
                ["event".to_string(), i.to_string(), "module_state".into(), key.into()].into();
            Err(crate::scenario::locate(&parts, &loaded.files, &loaded.overrides, msg).into())
        };
        if m.module == "system" {
            if !lifecycle(&m.state) {
                let states: Vec<&str> = framework::Lifecycle::ALL.iter().map(|l| l.name()).collect();
                fail(
                    "state",
                    format!("the system has no state '{}' (it has: {})", m.state, states.join(", ")),
                )?;
            }
            continue;
        }
        let Some(info) = core.modules().iter().find(|x| x.name == m.module) else {
            let names: Vec<&str> = core.modules().iter().map(|x| x.name.as_str()).collect();
            fail(
                "module",
                format!(
                    "module '{}' is not in this scenario's system (it has: system, {})",
                    m.module,
                    names.join(", ")
                ),
            )?;
            continue;
        };
        if !lifecycle(&m.state) && !info.states.contains(&m.state) {
            fail(
                "state",
                format!(
                    "module '{}' has no state '{}' (its own: {}; lifecycle: {})",
                    m.module,
                    m.state,
                    info.states.join(", "),
                    framework::Lifecycle::ALL.iter().map(|l| l.name()).collect::<Vec<_>>().join(", ")
                ),
            )?;
        }
    }
    Ok(())
}
