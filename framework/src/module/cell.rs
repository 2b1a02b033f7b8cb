//! The cell: a module with everything the framework keeps for it, stepped by the executors.

use super::ctx::{FsmView, Ledger};
use super::declare::Fsm;
use super::*;
use crate::config::{ConfigError, ConfigSource, FrameworkKeys, Schedule, Source};
use crate::events::{EventKind, Fault};
use crate::exec_context::ExecContext;
use crate::lifecycle::Lifecycle;
use crate::message::{AckStatus, Body, Message, ModuleId, Outcome, Queue};
use crate::runtime::Core;
use crate::stats::TaskStats;
use crate::time::{Duration, Time};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::panic::{AssertUnwindSafe, catch_unwind};

/// How much of a module's work a step performs.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub(crate) enum StepMode {
    /// Handle every waiting message, then run the state function once (one cycle).
    Cycle,
    /// Handle emergency messages only.
    EmergencyOnly,
}

/// What the deadline is compared with.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub(crate) enum OverrunBasis {
    /// Simulated execution time declared with [`Ctx::charge`] (lockstep: deterministic).
    Charged,
    /// Measured wall-clock execution time (real-time executor).
    Wall,
}

/// The object-safe face of a module cell, driven by the executors.
pub(crate) trait Runner: Send {
    fn info(&self) -> &ModuleInfo;
    fn schedule(&self) -> Schedule;
    fn hang_timeout(&self) -> Duration;
    fn declarations(&self) -> &Declarations;
    fn step(&mut self, core: &Core, now: Time, mode: StepMode, basis: OverrunBasis);
    /// Publishes the initial state, context and lifecycle to the shared status.
    fn publish_status(&self, core: &Core);
    /// Counts cycles skipped because the module was late by whole periods (real-time executor).
    fn add_skipped(&mut self, n: u64);
    /// The text of its configuration as applied (for remote fingerprints).
    fn config_text(&self) -> &str;
    /// The host its configuration says it runs on (`[framework] host`), if remote.
    fn host(&self) -> Option<&str> {
        None
    }
}

/// A module with everything the framework keeps for it.
pub(crate) struct Cell<M: Module> {
    pub(super) info: ModuleInfo,
    pub(super) module: M,
    pub(super) fsm: Fsm<M>,
    pub(super) lifecycle_fns: HashMap<Lifecycle, StateFn<M>>,
    pub(super) commands: BTreeMap<String, Handler<M>>,
    pub(super) on_ack: Option<AckFn<M>>,
    pub(super) context_switchable: bool,
    pub(super) decl: Declarations,
    pub(super) keys: FrameworkKeys,
    pub(super) params_text: String,
    pub(super) source: ConfigSource,
    pub(super) exec: ExecContext,
    pub(super) lifecycle: Lifecycle,
    pub(super) isolated: bool,
    pub(super) ledger: Ledger,
    pub(super) stats: TaskStats,
    pub(super) consecutive_overruns: u32,
    /// A fault injected through the debug queue, raised at the next cycle.
    pub(super) injected: Option<InjectedFault>,
}

/// A fault injected into a module through its debug queue (`inject_fault`), for failure testing.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InjectedFault {
    /// The module's next cycle panics (a crash).
    Panic,
    /// The module's next cycle returns an error.
    Error,
    /// The module's next cycle never returns (a hang): the watchdog must notice.
    Hang,
}

/// The message a panic carried (its payload as text).
pub fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic with a non-string payload".to_string())
}

impl<M: Module> Cell<M> {
    /// Registers a module: loads its configuration, applies its parameters and collects declarations.
    pub(crate) fn new(
        id: ModuleId,
        name: &str,
        mut module: M,
        source: ConfigSource,
        board: &crate::blackboard::BlackBoard,
    ) -> Result<Self, ConfigError> {
        let (cfg, text) = source.load::<M::Params>()?;
        module.configure(&cfg.params).map_err(|e| {
            Source::new(&source.origin(), &text)
                .error_at_key("params", format!("rejected by module '{name}': {e}"))
        })?;
        let mut fsm =
            Fsm { states: Vec::new(), index: HashMap::new(), transitions: HashSet::new(), current: 0 };
        let mut lifecycle_fns = HashMap::new();
        let mut commands = BTreeMap::new();
        let mut on_ack = None;
        let mut context_switchable = false;
        let mut decl = Declarations::default();
        let mut d = Declare {
            id,
            name,
            board,
            fsm: &mut fsm,
            lifecycle_fns: &mut lifecycle_fns,
            commands: &mut commands,
            on_ack: &mut on_ack,
            context_switchable: &mut context_switchable,
            decl: &mut decl,
            pending_transitions: Vec::new(),
            initial: None,
        };
        module.declare(&mut d);
        d.finish();
        if let Some(enabled) = &cfg.framework.commands {
            for c in enabled {
                if !commands.contains_key(c) {
                    let origin = source.origin();
                    let src = Source::new(&origin, &text);
                    return Err(src.error_at_key(
                        "framework.commands",
                        format!(
                            "module '{name}' has no command '{c}' (it binds: {})",
                            commands.keys().cloned().collect::<Vec<_>>().join(", ")
                        ),
                    ));
                }
            }
        }
        Ok(Cell {
            info: ModuleInfo {
                id,
                name: name.to_string(),
                kind: M::KIND,
                states: fsm.states.iter().map(|s| s.name.clone()).collect(),
            },
            module,
            fsm,
            lifecycle_fns,
            commands,
            on_ack,
            context_switchable,
            decl,
            exec: cfg.framework.context,
            keys: cfg.framework,
            params_text: text,
            source,
            lifecycle: Lifecycle::Startup,
            isolated: false,
            ledger: Ledger::default(),
            stats: TaskStats::default(),
            consecutive_overruns: 0,
            injected: None,
        })
    }

    pub(super) fn ctx<'c>(
        core: &'c Core,
        info: &'c ModuleInfo,
        fsm: &'c Fsm<M>,
        ledger: &'c mut Ledger,
        now: Time,
        exec: ExecContext,
        lifecycle: Lifecycle,
    ) -> Ctx<'c> {
        Ctx {
            core,
            id: info.id,
            name: &info.name,
            now,
            exec,
            lifecycle,
            fsm: FsmView {
                names: fsm.states.iter().map(|s| s.name.as_str()).collect(),
                index: &fsm.index,
                transitions: &fsm.transitions,
            },
            current: fsm.current,
            goto: None,
            ledger,
            request: None,
            charged: Duration::ZERO,
        }
    }

    /// Puts the module in Safe and isolates it: its safing hook runs first (while it still holds its
    /// devices), the commands it had accepted are answered Failed, then its reservations are freed.
    pub(super) fn isolate(&mut self, core: &Core, now: Time, fault: Fault) {
        let from = std::mem::replace(&mut self.lifecycle, Lifecycle::Safe);
        self.isolated = true;
        let why = fault.to_string();
        self.make_safe(core, now, &why);
        crate::runtime::isolate(core, &self.info, from, fault, now);
    }

    /// Runs the module's safing hook ([`Module::on_safe`]) and answers every command it had accepted
    /// but not finished Failed, naming `why`. A panic in the hook is reported and goes no further.
    pub(super) fn make_safe(&mut self, core: &Core, now: Time, why: &str) {
        let mut ctx =
            Self::ctx(core, &self.info, &self.fsm, &mut self.ledger, now, self.exec, Lifecycle::Safe);
        let module = &mut self.module;
        let r = catch_unwind(AssertUnwindSafe(|| module.on_safe(&mut ctx)));
        drop(ctx);
        if let Err(p) = r {
            let text = format!("safing hook panicked: {}", panic_text(&*p));
            tracing::error!(module = %self.info.name, "{text}");
            core.events.raise(now, EventKind::Note { module: self.info.name.clone(), text });
        }
        for (_, m) in std::mem::take(&mut self.ledger.accepted) {
            let command = match &m.body {
                Body::Command { name, .. } => name.as_str(),
                Body::Ack(_) => "",
            };
            let reason =
                format!("module '{}' went to Safe ({why}) before finishing '{command}'", self.info.name);
            core.post.acknowledge(&m, self.info.id, now, AckStatus::Failed(reason));
        }
    }

    pub(super) fn apply_goto(&mut self, core: &Core, now: Time, goto: Option<usize>) {
        if let Some(to) = goto
            && to != self.fsm.current
        {
            let from = std::mem::replace(&mut self.fsm.current, to);
            let to_name = self.fsm.states[to].name.clone();
            core.status(self.info.id).set_state(&to_name);
            core.events.raise(
                now,
                EventKind::ModuleState {
                    module: self.info.name.clone(),
                    from: self.fsm.states[from].name.clone(),
                    to: to_name,
                },
            );
        }
    }

    pub(super) fn handle(&mut self, core: &Core, now: Time, mut m: Message) {
        self.stats.messages += 1;
        if m.recipient != self.info.id {
            // Relay: pass the message on to its next hop, recording this module in its path.
            if m.route.first() == Some(&self.info.id) {
                m.route.remove(0);
            }
            m.path.push(self.info.id);
            if self.isolated && matches!(m.body, Body::Command { .. }) {
                let reason = format!("relay module '{}' is isolated in Safe", self.info.name);
                m.path.pop();
                core.post.acknowledge(&m, self.info.id, now, AckStatus::Rejected(reason));
            } else {
                core.post.post(m);
            }
            return;
        }
        let (name, args) = match &mut m.body {
            Body::Ack(ack) => {
                self.ledger.sent.update(ack);
                if let Some(f) = self.on_ack
                    && !self.isolated
                {
                    let ack = ack.clone();
                    let mut ctx = Self::ctx(
                        core,
                        &self.info,
                        &self.fsm,
                        &mut self.ledger,
                        now,
                        self.exec,
                        self.lifecycle,
                    );
                    let module = &mut self.module;
                    let r = catch_unwind(AssertUnwindSafe(|| f(module, &mut ctx, &ack)));
                    let goto = ctx.goto;
                    drop(ctx);
                    match r {
                        Ok(()) => self.apply_goto(core, now, goto),
                        Err(p) => self.isolate(core, now, Fault::Panic(panic_text(&*p))),
                    }
                }
                return;
            }
            Body::Command { name, args } => (name.clone(), std::mem::take(args)),
        };
        let outcome = self.dispatch(core, now, &m, &name, args);
        if let Outcome::Rejected(reason) = &outcome {
            core.events.raise(
                now,
                EventKind::MessageRejected {
                    module: self.info.name.clone(),
                    command: name,
                    reason: reason.clone(),
                },
            );
        }
        core.post.acknowledge(&m, self.info.id, now, outcome.into_status());
    }

    pub(super) fn dispatch(
        &mut self,
        core: &Core,
        now: Time,
        m: &Message,
        name: &str,
        args: serde_json::Value,
    ) -> Outcome {
        if m.queue == Queue::Debug && !self.exec.debug_queue_active() {
            return Outcome::reject(format!(
                "debug command '{name}' refused: module '{}' is in {} context; the debug queue is active only in Debug",
                self.info.name, self.exec
            ));
        }
        if name == "inject_fault" && m.queue != Queue::Debug {
            return Outcome::reject(format!(
                "'inject_fault' is accepted only on the debug queue (module '{}')",
                self.info.name
            ));
        }
        if FRAMEWORK_COMMANDS.contains(&name) {
            return self.framework_command(core, now, name, args);
        }
        if self.isolated || self.lifecycle == Lifecycle::Safe {
            return Outcome::reject(format!("module '{}' is in Safe", self.info.name));
        }
        if matches!(self.lifecycle, Lifecycle::Standby | Lifecycle::Shutdown | Lifecycle::Startup) {
            return Outcome::reject(format!(
                "module '{}' is in {}: it takes only framework commands there",
                self.info.name, self.lifecycle
            ));
        }
        if !self.commands.contains_key(name) {
            return Outcome::reject(format!(
                "unknown command '{name}' for module '{}' (it knows: {})",
                self.info.name,
                self.commands.keys().cloned().collect::<Vec<_>>().join(", ")
            ));
        }
        if let Some(enabled) = &self.keys.commands
            && !enabled.iter().any(|c| c == name)
        {
            return Outcome::reject(format!(
                "command '{name}' is disabled by the configuration of module '{}' (framework.commands)",
                self.info.name
            ));
        }
        let handler = &self.commands[name];
        let mut ctx =
            Self::ctx(core, &self.info, &self.fsm, &mut self.ledger, now, self.exec, self.lifecycle);
        ctx.request = Some(Request {
            message: Message {
                body: Body::Command { name: name.into(), args: serde_json::Value::Null },
                ..m.clone()
            },
        });
        // Booked as accepted before the handler runs, so that a reply from inside it clears it.
        let booked =
            Message { body: Body::Command { name: name.into(), args: serde_json::Value::Null }, ..m.clone() };
        ctx.ledger.accepted.insert(m.id, booked);
        let module = &mut self.module;
        let r = catch_unwind(AssertUnwindSafe(|| handler(module, &mut ctx, args)));
        let goto = ctx.goto;
        drop(ctx);
        if !matches!(r, Ok(Outcome::Accepted)) {
            self.ledger.accepted.remove(&m.id);
        }
        match r {
            Ok(outcome) => {
                self.apply_goto(core, now, goto);
                outcome
            }
            Err(p) => {
                let text = panic_text(&*p);
                self.isolate(core, now, Fault::Panic(text.clone()));
                Outcome::fail(format!("handler of '{name}' panicked: {text}"))
            }
        }
    }
}

impl<M: Module> Cell<M> {
    pub(super) fn run_state_function(&mut self, core: &Core, now: Time) -> Duration {
        let f = match self.lifecycle {
            Lifecycle::Run => self.fsm.states.get(self.fsm.current).map(|s| s.impls[s.active].1),
            l => self.lifecycle_fns.get(&l).copied(),
        };
        let Some(f) = f else { return Duration::ZERO };
        // An injected fault takes the state function's place and goes the same way to isolation.
        let injected = self.injected.take();
        let mut ctx =
            Self::ctx(core, &self.info, &self.fsm, &mut self.ledger, now, self.exec, self.lifecycle);
        let module = &mut self.module;
        let r = catch_unwind(AssertUnwindSafe(|| {
            let Some(kind) = injected else { return f(module, &mut ctx) };
            let text = format!("fault injected through the debug queue ({kind:?})");
            match kind {
                InjectedFault::Panic => panic!("{text}"),
                InjectedFault::Error => Err(ModuleError(text)),
                InjectedFault::Hang => loop {
                    // Never returns: the watchdog isolates the module after its hang timeout (and,
                    // under lockstep, calls the executor's hang handler).
                    std::thread::park();
                },
            }
        }));
        let (goto, charged) = (ctx.goto, ctx.charged);
        drop(ctx);
        match r {
            Ok(Ok(())) => self.apply_goto(core, now, goto),
            Ok(Err(e)) => self.isolate(core, now, Fault::Error(e.0)),
            Err(p) => self.isolate(core, now, Fault::Panic(panic_text(&*p))),
        }
        charged
    }
}

impl<M: Module> Runner for Cell<M> {
    fn info(&self) -> &ModuleInfo {
        &self.info
    }
    fn schedule(&self) -> Schedule {
        self.keys.schedule()
    }
    fn hang_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.keys.hang_timeout_s)
    }
    fn declarations(&self) -> &Declarations {
        &self.decl
    }

    fn config_text(&self) -> &str {
        &self.params_text
    }
    fn host(&self) -> Option<&str> {
        self.keys.host.as_deref()
    }

    fn add_skipped(&mut self, n: u64) {
        self.stats.skipped += n;
    }

    fn publish_status(&self, core: &Core) {
        let s = core.status(self.info.id);
        s.set_lifecycle(self.lifecycle);
        s.set_context(self.exec);
        s.set_hang_timeout(self.hang_timeout());
        s.set_state(self.fsm.states.get(self.fsm.current).map(|s| s.name.as_str()).unwrap_or(""));
        for st in self.fsm.states.iter().filter(|st| st.meta) {
            s.set_meta(&st.name, &st.impls[st.active].0);
        }
    }

    #[allow(clippy::disallowed_methods)] // the executor measures execution time; modules never see it
    fn step(&mut self, core: &Core, now: Time, mode: StepMode, basis: OverrunBasis) {
        let status = core.status(self.info.id);
        if status.is_isolated() && !self.isolated {
            // The watchdog isolated this module from outside (a hang, real-time executor) while its
            // step was stuck: adopt it, and make it safe now that the step has returned (its
            // devices' deadmen have stopped them meanwhile).
            self.isolated = true;
            self.lifecycle = Lifecycle::Safe;
            self.make_safe(core, now, "hung past its hang timeout");
        }
        let started = std::time::Instant::now();
        status.set_busy_since(core.wall_now());
        let inbox = core.post.inbox(self.info.id);
        match mode {
            StepMode::EmergencyOnly => {
                while let Some(m) = inbox.pop_emergency() {
                    self.handle(core, now, m);
                }
            }
            StepMode::Cycle => {
                // Only the messages waiting now: a module messaging itself cannot starve the cycle.
                for _ in 0..inbox.len() {
                    match inbox.pop() {
                        Some(m) => self.handle(core, now, m),
                        None => break,
                    }
                }
                if !self.isolated
                    && self.lifecycle != Lifecycle::Shutdown
                    && self.lifecycle != Lifecycle::Startup
                {
                    let charged = self.run_state_function(core, now);
                    let exec = Duration::from_std(started.elapsed());
                    self.stats.record_cycle(exec);
                    self.stats.charged_total_ns += charged.as_nanos();
                    if let Some(deadline) = self.keys.deadline() {
                        let spent = match basis {
                            OverrunBasis::Charged => charged,
                            OverrunBasis::Wall => exec,
                        };
                        if spent > deadline {
                            self.stats.overruns += 1;
                            self.consecutive_overruns += 1;
                            core.events.raise(
                                now,
                                EventKind::Overrun {
                                    module: self.info.name.clone(),
                                    exec_s: spent.as_secs_f64(),
                                    deadline_s: deadline.as_secs_f64(),
                                },
                            );
                            if self.consecutive_overruns > self.keys.overrun_budget && !self.isolated {
                                let fault = Fault::Overrun {
                                    consecutive: self.consecutive_overruns,
                                    budget: self.keys.overrun_budget,
                                };
                                self.isolate(core, now, fault);
                            }
                        } else {
                            self.consecutive_overruns = 0;
                        }
                    }
                }
            }
        }
        status.set_busy_since(-1);
        status.store_stats(&self.stats);
        // A configuration reloaded during this step brings its own hang timeout to the watchdog.
        status.set_hang_timeout(self.hang_timeout());
    }
}
