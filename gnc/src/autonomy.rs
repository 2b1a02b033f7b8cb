//! Autonomy (seed 000, 8; seed 004: the decision layer over the functional layer): receives the
//! ground plan as activities with their preconditions, runs them as command sequences for the
//! coordinators, monitors acknowledgements and timeouts, and is the top level of fault detection,
//! isolation and recovery.
//!
//! - `execute {activities}` (a [`Plan`]): accepted once its preconditions check out (names known,
//!   no cycle); runs one activity at a time, the first in plan order whose preconditions have
//!   succeeded; completes when every activity has run, fails when one failed for good (with the
//!   reason naming the activity and its command).
//! - `cancel`: ends the plan, stopping what the activity under way commanded.
//!
//! Fault handling, in order:
//! - a module isolated in Safe (a crash, an error, an overrun, a hang), whichever it is: what the
//!   activity under way commanded is stopped, the module restarted (Safe -> Standby -> Hold -> Run, up
//!   to `max_restarts` per module), and the activity tried again from its first step; past the
//!   limit, or when the restart is refused, the mission ends Safe;
//! - a step refused, failed or timed out: the module told to `stop`, the activity's `recovery`
//!   commands run, and the activity tried again from its first step, `retries` times;
//! - an activity failed for good: its `on_failure` decides: `continue` (what needs it is not run),
//!   `abort` (motion stopped, the system to Hold) or `safe` (motion stopped, the system to Safe).
//!
//! Every fault and response goes into `autonomy/state` ([`AutonomyState`]) with the activities'
//! progress; the runner (the system manager) carries out the Hold or Safe it asks for.

use framework::data::{
    ActivityReport, ActivityStatus, AutonomyState, FailurePolicy, FaultReport, MissionEnd, Plan, PlanStep,
};
use framework::message::{AckStatus, MessageId};
use framework::module::Request;
use framework::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The slot Autonomy publishes its state on.
pub const SLOT: &str = "autonomy/state";

/// Autonomy parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AutonomyParams {
    /// Restart modules found isolated in Safe.
    pub restart_modules: bool,
    /// Restarts of one module before the mission ends Safe.
    pub max_restarts: u32,
    /// Longest wait for each lifecycle step of a restart, s.
    pub restart_timeout_s: f64,
    /// Modules told to `stop` when the mission ends in Hold or Safe, or before a restart (those the
    /// system has; the actuators last).
    pub stop_modules: Vec<String>,
}

impl Default for AutonomyParams {
    fn default() -> Self {
        AutonomyParams {
            restart_modules: true,
            max_restarts: 2,
            restart_timeout_s: 5.0,
            stop_modules: [
                "manipulation",
                "visual_tracking",
                "navigator",
                "manipulator_control",
                "locomotion",
                "arm",
                "gripper",
                "ptu",
            ]
            .map(String::from)
            .to_vec(),
        }
    }
}

/// What the activity under way waits for.
#[derive(Clone, Debug, PartialEq)]
enum Stage {
    /// Its step `k`.
    Step(usize),
    /// Waiting until the time given before the next try's recovery.
    Wait(Time),
    /// Its recovery command `k`, before the next try.
    Recovery(usize),
    /// A restart of `module`: its lifecycle command towards `to`.
    Restart { module: String, to: Lifecycle },
}

struct Running {
    activity: usize,
    stage: Stage,
    /// The command awaited, its recipient and its deadline.
    awaited: Option<(MessageId, String, Time)>,
}

struct Execution {
    request: Request,
    plan: Plan,
    deps: Vec<Vec<usize>>,
    running: Option<Running>,
    /// Retries spent per activity (restarts after a module crash do not count).
    retries_used: Vec<u32>,
}

/// The Autonomy module.
pub struct Autonomy {
    params: AutonomyParams,
    state: AutonomyState,
    execution: Option<Execution>,
    restarts: BTreeMap<String, u32>,
    writer: Option<Writer<AutonomyState>>,
}

impl Default for Autonomy {
    fn default() -> Self {
        Self::new()
    }
}

impl Autonomy {
    /// Autonomy with no plan yet.
    pub fn new() -> Self {
        Autonomy {
            params: AutonomyParams::default(),
            state: AutonomyState::default(),
            execution: None,
            restarts: BTreeMap::new(),
            writer: None,
        }
    }

    fn execute(&mut self, ctx: &mut Ctx<'_>, plan: Plan) -> Outcome {
        let Some(request) = ctx.request() else {
            return Outcome::reject("execute must come as a command");
        };
        if self.execution.is_some() {
            return Outcome::reject("a plan is under way; cancel it first");
        }
        let deps = match plan.dependencies() {
            Ok(d) => d,
            Err(e) => return Outcome::reject(format!("bad plan: {e}")),
        };
        self.state = AutonomyState {
            activities: plan
                .activities
                .iter()
                .map(|a| ActivityReport { name: a.name.clone(), ..Default::default() })
                .collect(),
            current: None,
            faults: Vec::new(),
            end: None,
        };
        ctx.note(format!("plan of {} activities accepted", plan.activities.len()));
        let retries_used = vec![0; plan.activities.len()];
        self.restarts.clear();
        self.execution = Some(Execution { request, plan, deps, running: None, retries_used });
        Outcome::Accepted
    }

    fn fault(&mut self, ctx: &Ctx<'_>, activity: &str, fault: String, response: String) {
        ctx.note(format!("fault in '{activity}': {fault} -> {response}"));
        self.state.faults.push(FaultReport {
            at_s: ctx.now().as_secs_f64(),
            activity: activity.to_string(),
            fault,
            response,
        });
    }

    /// Sends `stop` to every configured module the system has and that is not in Safe.
    fn stop_all(&self, ctx: &mut Ctx<'_>) {
        for m in &self.params.stop_modules {
            if ctx.module_status(m).is_some_and(|s| !s.is_isolated()) {
                let _ = ctx.send(Command::new(m.clone(), "stop").on(Queue::Emergency));
            }
        }
    }

    fn send_step(ctx: &mut Ctx<'_>, s: &PlanStep) -> Result<(MessageId, String, Time), String> {
        let queue = if s.emergency { Queue::Emergency } else { Queue::Nominal };
        let cmd = Command::new(s.to.clone(), s.command.clone()).json(s.args.clone()).on(queue);
        let id = ctx.send(cmd).map_err(|e| format!("cannot send {}.{}: {e}", s.to, s.command))?;
        Ok((id, s.to.clone(), ctx.now() + Duration::from_secs_f64(s.timeout_s)))
    }

    /// Ends the mission: the plan's request answered, motion stopped unless it completed.
    fn finish(&mut self, ctx: &mut Ctx<'_>, end: MissionEnd, reason: Option<String>) {
        let Some(ex) = self.execution.take() else { return };
        let now = ctx.now().as_secs_f64();
        for r in &mut self.state.activities {
            match r.status {
                ActivityStatus::Running => {
                    r.status = ActivityStatus::Failed;
                    r.end_s = Some(now);
                    r.reason = Some(reason.clone().unwrap_or_else(|| "the mission ended".into()));
                }
                ActivityStatus::Pending => {
                    r.status = ActivityStatus::NotRun;
                    r.reason = Some(format!(
                        "mission ended first ({})",
                        reason.as_deref().unwrap_or("an earlier activity failed")
                    ));
                }
                _ => {}
            }
        }
        if end != MissionEnd::Completed {
            self.stop_all(ctx);
        }
        self.state.current = None;
        self.state.end = Some(end);
        let failed: Vec<String> = self
            .state
            .activities
            .iter()
            .filter(|a| a.status == ActivityStatus::Failed)
            .map(|a| format!("'{}': {}", a.name, a.reason.as_deref().unwrap_or("failed")))
            .collect();
        let outcome = match (&reason, failed.is_empty()) {
            (None, true) => {
                Outcome::Completed(serde_json::to_value(&self.state.activities).unwrap_or_default())
            }
            (Some(r), _) => Outcome::fail(r.clone()),
            (None, false) => Outcome::fail(format!("activities failed: {}", failed.join("; "))),
        };
        ctx.note(format!("mission ended: {end:?}"));
        ctx.reply(&ex.request, outcome);
    }

    /// The next activity to start, marking those that can never run; `None` when none is left.
    fn next_activity(&mut self, ctx: &Ctx<'_>) -> Option<usize> {
        // Marking one activity NotRun can block one listed before it: scan until nothing changes.
        loop {
            let not_run = self.count(ActivityStatus::NotRun);
            if let Some(i) = self.scan(ctx) {
                return Some(i);
            }
            if self.count(ActivityStatus::NotRun) == not_run {
                return None;
            }
        }
    }

    fn count(&self, status: ActivityStatus) -> usize {
        self.state.activities.iter().filter(|a| a.status == status).count()
    }

    /// One pass of [`Autonomy::next_activity`] in plan order.
    fn scan(&mut self, ctx: &Ctx<'_>) -> Option<usize> {
        let ex = self.execution.as_ref()?;
        for i in 0..ex.plan.activities.len() {
            if self.state.activities[i].status != ActivityStatus::Pending {
                continue;
            }
            let blocked = ex.deps[i].iter().find(|&&d| {
                matches!(self.state.activities[d].status, ActivityStatus::Failed | ActivityStatus::NotRun)
            });
            if let Some(&d) = blocked {
                let r = &mut self.state.activities[i];
                r.status = ActivityStatus::NotRun;
                r.reason = Some(format!("needs '{}', which did not succeed", ex.plan.activities[d].name));
                continue;
            }
            if !ex.deps[i].iter().all(|&d| self.state.activities[d].status == ActivityStatus::Succeeded) {
                continue;
            }
            let a = &ex.plan.activities[i];
            if let Some(s) = a.steps.iter().find(|s| ctx.module_status(&s.to).is_none()) {
                let r = &mut self.state.activities[i];
                r.status = ActivityStatus::NotRun;
                r.reason = Some(format!("needs module '{}', which this system does not have yet", s.to));
                continue;
            }
            return Some(i);
        }
        None
    }

    /// Starts stage `stage` of the activity under way (or moves past it when it has no command).
    fn begin(&mut self, ctx: &mut Ctx<'_>, mut run: Running) -> Result<Running, String> {
        let ex = self.execution.as_ref().expect("running without a plan");
        let a = &ex.plan.activities[run.activity];
        loop {
            match run.stage.clone() {
                Stage::Step(k) if k < a.steps.len() => {
                    run.awaited = Some(Self::send_step(ctx, &a.steps[k])?);
                    return Ok(run);
                }
                Stage::Recovery(k) if k < a.recovery.len() => match Self::send_step(ctx, &a.recovery[k]) {
                    Ok(awaited) => {
                        run.awaited = Some(awaited);
                        return Ok(run);
                    }
                    Err(e) => {
                        // A recovery command that cannot be sent (no such module) is skipped.
                        ctx.note(format!("'{}': {e} (recovery goes on)", a.name));
                        run.stage = Stage::Recovery(k + 1);
                    }
                },
                Stage::Recovery(_) => run.stage = Stage::Step(0),
                Stage::Wait(_) => {
                    run.awaited = None;
                    return Ok(run);
                }
                Stage::Restart { module, to } => {
                    let cmd = Command::new(module.clone(), "lifecycle")
                        .json(serde_json::json!({ "to": to }))
                        .on(Queue::Emergency);
                    let id = ctx.send(cmd).map_err(|e| format!("cannot restart '{module}': {e}"))?;
                    let deadline = ctx.now() + Duration::from_secs_f64(self.params.restart_timeout_s);
                    run.awaited = Some((id, module, deadline));
                    return Ok(run);
                }
                Stage::Step(_) => {
                    run.awaited = None;
                    return Ok(run);
                }
            }
        }
    }

    /// A module of the system (a crash anywhere is a fault) found isolated in Safe, other than this
    /// one, in registration order.
    fn isolated_module(&self, ctx: &Ctx<'_>) -> Option<String> {
        ctx.module_names()
            .into_iter()
            .find(|n| n != ctx.name() && ctx.module_status(n).is_some_and(|s| s.is_isolated()))
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        if self.execution.is_some() {
            self.advance(ctx);
        }
        if let Some(w) = &self.writer {
            let s = self.state.clone();
            ctx.write(w, s);
        }
        Ok(())
    }

    fn advance(&mut self, ctx: &mut Ctx<'_>) {
        let Some(mut run) = self.execution.as_mut().and_then(|e| e.running.take()) else {
            match self.next_activity(ctx) {
                Some(i) => {
                    let ex = self.execution.as_ref().expect("checked");
                    let name = ex.plan.activities[i].name.clone();
                    let r = &mut self.state.activities[i];
                    r.status = ActivityStatus::Running;
                    r.attempts = 1;
                    r.start_s = Some(ctx.now().as_secs_f64());
                    self.state.current = Some(name.clone());
                    ctx.note(format!("activity '{name}' started"));
                    let run = Running { activity: i, stage: Stage::Step(0), awaited: None };
                    self.resume(ctx, run);
                }
                None => self.finish(ctx, MissionEnd::Completed, None),
            }
            return;
        };
        let name = self.state.activities[run.activity].name.clone();
        if let Stage::Wait(until) = run.stage {
            if ctx.now() >= until {
                run.stage = Stage::Recovery(0);
                self.resume(ctx, run);
            } else {
                self.put_back(run);
            }
            return;
        }
        let Some((id, _, deadline)) = run.awaited.clone() else {
            self.activity_done(ctx, run);
            return;
        };
        // Fault detection: a module isolated in Safe (unless it is being restarted).
        let restarting = match &run.stage {
            Stage::Restart { module, .. } => Some(module.clone()),
            _ => None,
        };
        if restarting.is_none()
            && let Some(m) = self.isolated_module(ctx)
        {
            self.on_isolated(ctx, run, &name, m);
            return;
        }
        let what = self.describe(&run);
        let failure = match ctx.ack_status(id) {
            Some(AckStatus::Completed(_)) => {
                run.stage = match run.stage {
                    Stage::Step(k) => Stage::Step(k + 1),
                    Stage::Recovery(k) => Stage::Recovery(k + 1),
                    Stage::Wait(_) => Stage::Recovery(0),
                    Stage::Restart { module, to: Lifecycle::Standby } => {
                        Stage::Restart { module, to: Lifecycle::Hold }
                    }
                    Stage::Restart { module, to: Lifecycle::Hold } => {
                        Stage::Restart { module, to: Lifecycle::Run }
                    }
                    Stage::Restart { module, .. } => {
                        ctx.note(format!("module '{module}' restarted"));
                        Stage::Step(0)
                    }
                };
                self.resume(ctx, run);
                return;
            }
            Some(AckStatus::Rejected(r)) => format!("{what} refused: {r}"),
            Some(AckStatus::Failed(r)) => format!("{what} failed: {r}"),
            _ if ctx.now() >= deadline => {
                format!("{what} did not complete within {} s", self.timeout_of(&run))
            }
            _ => {
                self.put_back(run);
                return;
            }
        };
        if let Stage::Recovery(k) = run.stage {
            // Recovery is best effort (a `recover` refused because nothing is in fault): noted,
            // the next recovery command runs; the activity's reason stays the step's failure.
            Self::stop_awaited(ctx, &run);
            ctx.note(format!("'{name}': {failure} (recovery goes on)"));
            let run = Running { activity: run.activity, stage: Stage::Recovery(k + 1), awaited: None };
            self.resume(ctx, run);
            return;
        }
        if restarting.is_some() {
            self.fault(ctx, &name, failure.clone(), "safe".into());
            self.fail_activity(ctx, run.activity, failure.clone());
            self.finish(ctx, MissionEnd::Safe, Some(format!("'{name}': {failure}")));
            return;
        }
        self.on_failure(ctx, run, &name, failure);
    }

    fn put_back(&mut self, run: Running) {
        if let Some(ex) = self.execution.as_mut() {
            ex.running = Some(run);
        }
    }

    /// Sends what the stage needs and keeps the activity running, or fails it.
    fn resume(&mut self, ctx: &mut Ctx<'_>, run: Running) {
        let activity = run.activity;
        match self.begin(ctx, run) {
            Ok(run) => self.put_back(run),
            Err(e) => {
                let name = self.state.activities[activity].name.clone();
                let run = Running { activity, stage: Stage::Step(0), awaited: None };
                self.on_failure(ctx, run, &name, e);
            }
        }
    }

    fn describe(&self, run: &Running) -> String {
        let ex = self.execution.as_ref().expect("running without a plan");
        let a = &ex.plan.activities[run.activity];
        match &run.stage {
            Stage::Step(k) => a
                .steps
                .get(*k)
                .map_or_else(String::new, |s| format!("step {} ({}.{})", k + 1, s.to, s.command)),
            Stage::Recovery(k) => a
                .recovery
                .get(*k)
                .map_or_else(String::new, |s| format!("recovery {} ({}.{})", k + 1, s.to, s.command)),
            Stage::Restart { module, to } => format!("restart of '{module}' ({to})"),
            Stage::Wait(_) => "the wait before a retry".into(),
        }
    }

    fn timeout_of(&self, run: &Running) -> f64 {
        let ex = self.execution.as_ref().expect("running without a plan");
        let a = &ex.plan.activities[run.activity];
        match &run.stage {
            Stage::Step(k) => a.steps.get(*k).map_or(0.0, |s| s.timeout_s),
            Stage::Recovery(k) => a.recovery.get(*k).map_or(0.0, |s| s.timeout_s),
            Stage::Restart { .. } => self.params.restart_timeout_s,
            Stage::Wait(_) => 0.0,
        }
    }

    /// Stops what the activity's awaited command was doing.
    fn stop_awaited(ctx: &mut Ctx<'_>, run: &Running) {
        if let Some((_, to, _)) = &run.awaited
            && ctx.module_status(to).is_some_and(|s| !s.is_isolated())
        {
            let _ = ctx.send(Command::new(to.clone(), "stop").on(Queue::Emergency));
        }
    }

    fn on_isolated(&mut self, ctx: &mut Ctx<'_>, run: Running, name: &str, module: String) {
        let fault = format!("module '{module}' is isolated in Safe");
        let restarts = self.restarts.entry(module.clone()).or_default();
        if self.params.restart_modules && *restarts < self.params.max_restarts {
            *restarts += 1;
            let n = *restarts;
            Self::stop_awaited(ctx, &run);
            self.fault(
                ctx,
                name,
                fault,
                format!("restart '{module}' ({n} of {}), retry", self.params.max_restarts),
            );
            let r = &mut self.state.activities[run.activity];
            r.attempts += 1;
            let run = Running {
                activity: run.activity,
                stage: Stage::Restart { module, to: Lifecycle::Standby },
                awaited: None,
            };
            self.resume(ctx, run);
        } else {
            self.fault(ctx, name, fault.clone(), "safe".into());
            self.fail_activity(ctx, run.activity, fault.clone());
            self.finish(ctx, MissionEnd::Safe, Some(format!("'{name}': {fault}, no restart left")));
        }
    }

    fn on_failure(&mut self, ctx: &mut Ctx<'_>, run: Running, name: &str, failure: String) {
        Self::stop_awaited(ctx, &run);
        let ex = self.execution.as_mut().expect("running without a plan");
        let a = &ex.plan.activities[run.activity];
        let (retries, policy, delay) = (a.retries, a.on_failure, a.retry_delay_s);
        let used = &mut ex.retries_used[run.activity];
        if *used < retries {
            *used += 1;
            let n = *used;
            self.fault(ctx, name, failure.clone(), format!("retry ({n} of {retries})"));
            let r = &mut self.state.activities[run.activity];
            r.attempts += 1;
            r.reason = Some(failure);
            let until = ctx.now() + Duration::from_secs_f64(delay);
            let run = Running { activity: run.activity, stage: Stage::Wait(until), awaited: None };
            self.resume(ctx, run);
            return;
        }
        let response = match policy {
            FailurePolicy::Continue => "continue",
            FailurePolicy::Abort => "abort",
            FailurePolicy::Safe => "safe",
        };
        self.fault(ctx, name, failure.clone(), response.into());
        self.fail_activity(ctx, run.activity, failure.clone());
        match policy {
            FailurePolicy::Continue => {}
            FailurePolicy::Abort => {
                self.finish(ctx, MissionEnd::Aborted, Some(format!("'{name}': {failure}")))
            }
            FailurePolicy::Safe => self.finish(ctx, MissionEnd::Safe, Some(format!("'{name}': {failure}"))),
        }
    }

    fn fail_activity(&mut self, ctx: &Ctx<'_>, i: usize, reason: String) {
        let r = &mut self.state.activities[i];
        r.status = ActivityStatus::Failed;
        r.end_s = Some(ctx.now().as_secs_f64());
        r.reason = Some(reason);
        self.state.current = None;
    }

    fn activity_done(&mut self, ctx: &Ctx<'_>, run: Running) {
        let r = &mut self.state.activities[run.activity];
        r.status = ActivityStatus::Succeeded;
        r.end_s = Some(ctx.now().as_secs_f64());
        ctx.note(format!("activity '{}' succeeded (attempt {})", r.name, r.attempts));
        self.state.current = None;
    }

    fn cancel(&mut self, ctx: &mut Ctx<'_>, reason: &str) {
        if let Some(run) = self.execution.as_mut().and_then(|e| e.running.take()) {
            Self::stop_awaited(ctx, &run);
        }
        if self.execution.is_some() {
            self.finish(ctx, MissionEnd::Aborted, Some(reason.to_string()));
        }
    }
}

impl Module for Autonomy {
    type Params = AutonomyParams;
    const KIND: ModuleKind = ModuleKind::Coordination;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.writer = Some(d.writes(SLOT));
        d.context_switchable();
        d.state("active", |m, ctx| m.cycle(ctx));
        d.command("execute", |m, ctx, plan: Plan| m.execute(ctx, plan));
        d.command("cancel", |m, ctx, _: ()| {
            m.cancel(ctx, "cancelled by command");
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &AutonomyParams) -> Result<(), String> {
        crate::params::require_positive(&[("restart_timeout_s", p.restart_timeout_s)])?;
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        if matches!(to, Lifecycle::Hold | Lifecycle::Safe | Lifecycle::Shutdown) && self.execution.is_some() {
            self.cancel(ctx, &format!("'{}' left Run for {to}", ctx.name()));
            // The state functions do not run outside Run: the final state is written here.
            if let Some(w) = &self.writer {
                let s = self.state.clone();
                ctx.write(w, s);
            }
        }
        Ok(())
    }
}
