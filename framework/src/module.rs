//! The Module base (seed 000, sections 6 and 7): kinds, the module's own state machine with state
//! functions and meta-states, string-bound commands with typed arguments, blackboard declarations and
//! the context a module sees of the world.
//!
//! A module is a plain Rust type implementing [`Module`]. In [`Module::declare`] it binds, through
//! [`Declare`]:
//! - its states and their *state functions* (run once per cycle while the module is in `Run`), the
//!   allowed transitions between them, and *meta-states*: states whose bound implementation is chosen
//!   at runtime by the framework command `set_meta` without restarting anything;
//! - state functions for the other lifecycle states (`Config`, `Standby`, `Hold`, `Safe`);
//! - commands, by name, with a handler taking a typed argument struct (an unknown command, a disabled
//!   one or malformed arguments are rejected back to the sender with the reason);
//! - the blackboard slots it writes (it becomes their only writer) and reads, and the modules it sends
//!   to, so that the system manager can check the whole graph at start-up.
//!
//! At runtime every state function and handler gets a [`Ctx`]: the framework clock's time, the module's
//! execution context and lifecycle state, blackboard access, message sending with acknowledgement
//! tracking, reservation tokens and events. A module never reads the OS clock.

use crate::blackboard::{BoardData, Reader, Stamped, Writer};
use crate::config::{ConfigError, ConfigSource, FrameworkKeys, ModuleConfigFile, Schedule, Source};
use crate::events::{EventKind, Fault};
use crate::exec_context::ExecContext;
use crate::lifecycle::Lifecycle;
use crate::message::{
    Ack, AckStatus, AckTracker, Body, Command, Message, MessageId, ModuleId, Outcome, Queue, SendError,
};
use crate::resources::{ReservationError, ReservationToken};
use crate::stats::TaskStats;
use crate::system::Core;
use crate::time::{Duration, Time};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Arc;

/// The five module types of the modular robot control software (seed 000, section 7). The lockstep
/// executor runs due modules in this order within a tick.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModuleKind {
    /// Interfaces with robot sensors; publishes their data.
    Sensor,
    /// Implements functions and algorithms on sensor data; feeds actuators.
    Resource,
    /// Coordinates resource modules to carry out complex tasks.
    Coordination,
    /// Interfaces with robot actuators.
    Actuator,
    /// Non-core functions: logging, debugging.
    External,
}

/// An error returned by a state function: the watchdog puts the module in Safe.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct ModuleError(pub String);

impl From<&str> for ModuleError {
    fn from(s: &str) -> Self {
        ModuleError(s.to_string())
    }
}
impl From<String> for ModuleError {
    fn from(s: String) -> Self {
        ModuleError(s)
    }
}

/// Result of a state function.
pub type StateResult = Result<(), ModuleError>;
/// A state function: runs once per cycle while its state is current.
pub type StateFn<M> = fn(&mut M, &mut Ctx<'_>) -> StateResult;
type Handler<M> = Box<dyn Fn(&mut M, &mut Ctx<'_>, serde_json::Value) -> Outcome + Send>;
/// A hook called when an acknowledgement of one of the module's commands arrives.
pub type AckFn<M> = fn(&mut M, &mut Ctx<'_>, &Ack);

/// A robot software module.
pub trait Module: Send + Sized + 'static {
    /// The module's own configuration parameters (the `[params]` table of its file).
    type Params: Serialize + DeserializeOwned + Default + Send + 'static;
    /// Its kind.
    const KIND: ModuleKind;
    /// Binds states, commands, blackboard slots and recipients. Called once, at registration.
    fn declare(&mut self, decl: &mut Declare<'_, Self>);
    /// Applies parameters: at start-up and whenever the configuration is changed or reloaded in Config.
    /// An error refuses the new parameters (at start-up: the system does not start).
    fn configure(&mut self, _params: &Self::Params) -> Result<(), String> {
        Ok(())
    }
    /// Called on each lifecycle transition before it takes effect; an error refuses it (except a move
    /// to Safe, which always happens).
    fn on_transition(&mut self, _ctx: &mut Ctx<'_>, _from: Lifecycle, _to: Lifecycle) -> Result<(), String> {
        Ok(())
    }
}

/// Names of the commands the framework handles for every module. Modules cannot bind them.
pub const FRAMEWORK_COMMANDS: &[&str] = &[
    "lifecycle",
    "ping",
    "get_state",
    "get_stats",
    "set_meta",
    "set_context",
    "set_param",
    "reload_config",
    "save_config",
    "inject_fault",
];

struct StateEntry<M> {
    name: String,
    /// Implementations: one for a plain state, several for a meta-state.
    impls: Vec<(String, StateFn<M>)>,
    active: usize,
    meta: bool,
}

/// The module's own state machine: states, their functions, and the allowed transitions.
struct Fsm<M> {
    states: Vec<StateEntry<M>>,
    index: HashMap<String, usize>,
    transitions: HashSet<(usize, usize)>,
    current: usize,
}

/// What a module declared at registration, for the system manager's start-up checks.
#[derive(Clone, Debug, Default)]
pub struct Declarations {
    /// Modules (or endpoints) it sends commands to, including relays.
    pub recipients: Vec<String>,
    /// Problems found while declaring (type mismatches, reserved names, unknown states).
    pub problems: Vec<String>,
}

/// The registration-time binder handed to [`Module::declare`].
pub struct Declare<'a, M> {
    id: ModuleId,
    name: &'a str,
    board: &'a crate::blackboard::BlackBoard,
    fsm: &'a mut Fsm<M>,
    lifecycle_fns: &'a mut HashMap<Lifecycle, StateFn<M>>,
    commands: &'a mut BTreeMap<String, Handler<M>>,
    on_ack: &'a mut Option<AckFn<M>>,
    context_switchable: &'a mut bool,
    decl: &'a mut Declarations,
    pending_transitions: Vec<(String, String)>,
    initial: Option<String>,
}

impl<M: Module> Declare<'_, M> {
    /// The module's name.
    pub fn name(&self) -> &str {
        self.name
    }

    fn add_state(&mut self, name: &str, impls: Vec<(String, StateFn<M>)>, meta: bool) {
        if self.fsm.index.contains_key(name) {
            self.decl.problems.push(format!("state '{name}' declared twice"));
            return;
        }
        self.fsm.index.insert(name.to_string(), self.fsm.states.len());
        self.fsm.states.push(StateEntry { name: name.to_string(), impls, active: 0, meta });
    }

    /// Declares a state of the module's own machine with its state function. The first state declared
    /// is the initial one unless [`Declare::initial`] says otherwise.
    pub fn state(&mut self, name: &str, f: StateFn<M>) -> &mut Self {
        self.add_state(name, vec![(name.to_string(), f)], false);
        self
    }

    /// Declares a meta-state: a state whose function is one of several named implementations, the first
    /// being the default, switchable at runtime by the `set_meta` command.
    pub fn meta_state(&mut self, name: &str, impls: &[(&str, StateFn<M>)]) -> &mut Self {
        if impls.is_empty() {
            self.decl.problems.push(format!("meta-state '{name}' has no implementation"));
            return self;
        }
        let impls = impls.iter().map(|(n, f)| (n.to_string(), *f)).collect();
        self.add_state(name, impls, true);
        self
    }

    /// Sets the initial state.
    pub fn initial(&mut self, name: &str) -> &mut Self {
        self.initial = Some(name.to_string());
        self
    }

    /// Allows a transition between two declared states.
    pub fn transition(&mut self, from: &str, to: &str) -> &mut Self {
        self.pending_transitions.push((from.to_string(), to.to_string()));
        self
    }

    /// Binds a state function to a lifecycle state other than Run (Run runs the module's own states).
    pub fn on(&mut self, state: Lifecycle, f: StateFn<M>) -> &mut Self {
        if matches!(state, Lifecycle::Run | Lifecycle::Startup | Lifecycle::Shutdown) {
            self.decl.problems.push(format!(
                "cannot bind a state function to lifecycle state {state}: Run runs the module's own \
                 states, Startup and Shutdown have none (use Module::on_transition)"
            ));
        } else {
            self.lifecycle_fns.insert(state, f);
        }
        self
    }

    /// Binds a command name to a handler with typed arguments `A` (deserialized from the message's
    /// JSON arguments; a mismatch is rejected back to the sender with serde's message).
    pub fn command<A: DeserializeOwned + 'static>(
        &mut self,
        name: &str,
        handler: fn(&mut M, &mut Ctx<'_>, A) -> Outcome,
    ) -> &mut Self {
        if FRAMEWORK_COMMANDS.contains(&name) {
            self.decl.problems.push(format!("command '{name}' is reserved by the framework"));
            return self;
        }
        if self.commands.contains_key(name) {
            self.decl.problems.push(format!("command '{name}' bound twice"));
            return self;
        }
        let cmd = name.to_string();
        self.commands.insert(
            name.to_string(),
            Box::new(move |m, ctx, args| {
                // A missing argument object is read as an empty one, so `()`-like structs work.
                let args = if args.is_null() { serde_json::Value::Object(Default::default()) } else { args };
                match serde_json::from_value::<A>(args.clone()).or_else(|e| {
                    // Unit and unit-like argument types accept an empty object or null.
                    if args.as_object().is_some_and(|o| o.is_empty()) {
                        serde_json::from_value::<A>(serde_json::Value::Null).map_err(|_| e)
                    } else {
                        Err(e)
                    }
                }) {
                    Ok(a) => handler(m, ctx, a),
                    Err(e) => Outcome::reject(format!("bad arguments for command '{cmd}': {e}")),
                }
            }),
        );
        self
    }

    /// Declares this module the writer of a blackboard slot.
    ///
    /// # Panics
    /// Never for a fresh name; on a type clash the problem is recorded for the start-up check and a
    /// private slot is returned so that declaration can go on.
    pub fn writes<T: BoardData>(&mut self, slot: &str) -> Writer<T> {
        match self.board.declare_writer(slot, self.id) {
            Ok(w) => w,
            Err(e) => {
                self.decl.problems.push(e.to_string());
                crate::blackboard::BlackBoard::new().declare_writer(slot, self.id).expect("fresh board")
            }
        }
    }

    /// Declares a read of a blackboard slot (some module must declare itself its writer).
    pub fn reads<T: BoardData>(&mut self, slot: &str) -> Reader<T> {
        match self.board.declare_reader(slot, self.id) {
            Ok(r) => r,
            Err(e) => {
                self.decl.problems.push(e.to_string());
                crate::blackboard::BlackBoard::new().declare_reader(slot, self.id).expect("fresh board")
            }
        }
    }

    /// Declares that this module sends commands to `module` (checked to exist at start-up).
    pub fn sends_to(&mut self, module: &str) -> &mut Self {
        self.decl.recipients.push(module.to_string());
        self
    }

    /// Sets a hook called with every acknowledgement of this module's commands.
    pub fn on_ack(&mut self, f: AckFn<M>) -> &mut Self {
        *self.on_ack = Some(f);
        self
    }

    /// Allows the execution context to be changed at runtime by the `set_context` command.
    pub fn context_switchable(&mut self) -> &mut Self {
        *self.context_switchable = true;
        self
    }

    fn finish(mut self) {
        for (from, to) in std::mem::take(&mut self.pending_transitions) {
            match (self.fsm.index.get(&from), self.fsm.index.get(&to)) {
                (Some(&a), Some(&b)) => {
                    self.fsm.transitions.insert((a, b));
                }
                _ => self.decl.problems.push(format!("transition {from} -> {to} names an undeclared state")),
            }
        }
        if let Some(init) = self.initial.take() {
            match self.fsm.index.get(&init) {
                Some(&i) => self.fsm.current = i,
                None => self.decl.problems.push(format!("initial state '{init}' is not declared")),
            }
        }
    }
}

/// A command being handled, kept by a module that accepted it to reply later with [`Ctx::reply`].
#[derive(Clone, Debug, PartialEq)]
pub struct Request {
    message: Message,
}

impl Request {
    /// The command's message id.
    pub fn id(&self) -> MessageId {
        self.message.id
    }
    /// The command's name.
    pub fn command(&self) -> &str {
        match &self.message.body {
            Body::Command { name, .. } => name,
            Body::Ack(_) => "",
        }
    }
    /// Who sent it.
    pub fn sender(&self) -> ModuleId {
        self.message.sender
    }
    /// The queue it came on.
    pub fn queue(&self) -> Queue {
        self.message.queue
    }
}

/// Why a state change of the module's own machine was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FsmError {
    /// No such state.
    #[error("module '{module}' has no state '{state}'")]
    UnknownState {
        /// Module.
        module: String,
        /// Requested state.
        state: String,
    },
    /// The transition is not declared.
    #[error("module '{module}': transition {from} -> {to} is not declared")]
    IllegalTransition {
        /// Module.
        module: String,
        /// Current state.
        from: String,
        /// Requested state.
        to: String,
    },
}

/// The non-generic view of the module's machine that a [`Ctx`] needs.
struct FsmView<'a> {
    names: Vec<&'a str>,
    index: &'a HashMap<String, usize>,
    transitions: &'a HashSet<(usize, usize)>,
}

/// What a module sees of the world while one of its functions runs.
pub struct Ctx<'a> {
    core: &'a Core,
    id: ModuleId,
    name: &'a str,
    now: Time,
    exec: ExecContext,
    lifecycle: Lifecycle,
    fsm: FsmView<'a>,
    current: usize,
    goto: Option<usize>,
    tracker: &'a mut AckTracker,
    request: Option<Request>,
    charged: Duration,
}

impl<'a> Ctx<'a> {
    /// The framework clock's time at the start of this cycle.
    pub fn now(&self) -> Time {
        self.now
    }
    /// This module's name.
    pub fn name(&self) -> &str {
        self.name
    }
    /// This module's id.
    pub fn id(&self) -> ModuleId {
        self.id
    }
    /// The current execution context.
    pub fn context(&self) -> ExecContext {
        self.exec
    }
    /// The module's lifecycle state.
    pub fn lifecycle(&self) -> Lifecycle {
        self.lifecycle
    }
    /// The current state of the module's own machine ("" if it declares none).
    pub fn state(&self) -> &str {
        self.fsm.names.get(self.current).copied().unwrap_or("")
    }
    /// Moves the module's own machine to `state` after the current function returns.
    pub fn goto(&mut self, state: &str) -> Result<(), FsmError> {
        let to = *self.fsm.index.get(state).ok_or_else(|| FsmError::UnknownState {
            module: self.name.to_string(),
            state: state.to_string(),
        })?;
        let from = self.goto.unwrap_or(self.current);
        if from != to && !self.fsm.transitions.contains(&(from, to)) {
            return Err(FsmError::IllegalTransition {
                module: self.name.to_string(),
                from: self.fsm.names[from].to_string(),
                to: state.to_string(),
            });
        }
        self.goto = Some(to);
        Ok(())
    }
    /// The System Manager's status of module `name` (lifecycle state, isolation, statistics), as a
    /// supervisor reads it; `None` when the system has no such module.
    pub fn module_status(&self, name: &str) -> Option<&crate::system::ModuleStatus> {
        self.core.modules().iter().find(|m| m.name == name).map(|m| self.core.status(m.id))
    }
    /// The names of the system's modules, in registration order.
    pub fn module_names(&self) -> Vec<String> {
        self.core.modules().iter().map(|m| m.name.clone()).collect()
    }
    /// The latest value of a slot.
    pub fn read<T: BoardData>(&self, r: &Reader<T>) -> Option<Arc<Stamped<T>>> {
        r.read()
    }
    /// Writes a slot this module declared, stamped with the current time. Dropped if the watchdog has
    /// isolated the module meanwhile. Returns the sequence number written.
    pub fn write<T: BoardData>(&mut self, w: &Writer<T>, value: T) -> Option<u64> {
        self.write_stamped(w, value, self.now)
    }
    /// Writes a slot with an explicit stamp (the acquisition time of a measurement, for instance).
    pub fn write_stamped<T: BoardData>(&mut self, w: &Writer<T>, value: T, stamp: Time) -> Option<u64> {
        if self.core.status(self.id).is_isolated() {
            return None;
        }
        Some(w.write(value, stamp))
    }
    /// Sends a command; its acknowledgements are tracked ([`Ctx::ack_status`]).
    pub fn send(&mut self, cmd: Command) -> Result<MessageId, SendError> {
        if self.core.status(self.id).is_isolated() {
            return Err(SendError::Isolated(self.name.to_string()));
        }
        let name = cmd.name.clone();
        let m = self.core.post.compose(self.id, self.now, cmd)?;
        let id = m.id;
        self.tracker.sent(id, &name);
        self.core.post.post(m);
        Ok(id)
    }
    /// The latest known status of a command this module sent.
    pub fn ack_status(&self, id: MessageId) -> Option<AckStatus> {
        self.tracker.status(id)
    }
    /// Commands sent without a final acknowledgement yet.
    pub fn outstanding_commands(&self) -> usize {
        self.tracker.outstanding()
    }
    /// The command being handled (inside a command handler), to keep and [`Ctx::reply`] to later.
    pub fn request(&self) -> Option<Request> {
        self.request.clone()
    }
    /// Reports the completion or failure of a command accepted earlier.
    pub fn reply(&mut self, request: &Request, outcome: Outcome) {
        self.core.post.acknowledge(&request.message, self.id, self.now, outcome.into_status());
    }
    /// Declares simulated execution time spent in this cycle (the cost on the target computer). The
    /// lockstep executor compares it with the deadline to count overruns deterministically.
    pub fn charge(&mut self, d: Duration) {
        self.charged += d;
    }
    /// Reserves a shared device.
    pub fn acquire(&self, device: &str) -> Result<ReservationToken, ReservationError> {
        self.core.resources.acquire(device, self.id)
    }
    /// Takes a shared device by emergency override, revoking its holder's token; raises an event.
    pub fn override_device(&self, device: &str) -> Result<ReservationToken, ReservationError> {
        let (t, prev) = self.core.resources.override_emergency(device, self.id)?;
        self.core.events.raise(
            self.now,
            EventKind::ReservationOverridden {
                device: device.to_string(),
                by: self.name.to_string(),
                previous: prev.map(|p| self.core.post.name(p).to_string()),
            },
        );
        Ok(t)
    }
    /// Checks that a token still grants command of its device.
    pub fn validate(&self, token: &ReservationToken) -> Result<(), ReservationError> {
        self.core.resources.validate(token)
    }
    /// Gives a device back.
    pub fn release(&self, token: ReservationToken) {
        self.core.resources.release(token)
    }
    /// Raises a free-text event.
    pub fn note(&self, text: impl Into<String>) {
        self.core
            .events
            .raise(self.now, EventKind::Note { module: self.name.to_string(), text: text.into() });
    }
}

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

/// Static facts about a registered module.
#[derive(Clone, Debug)]
pub struct ModuleInfo {
    /// Id in the post office.
    pub id: ModuleId,
    /// Name.
    pub name: String,
    /// Kind.
    pub kind: ModuleKind,
    /// The states of its own machine, in the order declared (its lifecycle states are
    /// [`Lifecycle::ALL`]).
    pub states: Vec<String>,
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
}

/// A module with everything the framework keeps for it.
pub(crate) struct Cell<M: Module> {
    info: ModuleInfo,
    module: M,
    fsm: Fsm<M>,
    lifecycle_fns: HashMap<Lifecycle, StateFn<M>>,
    commands: BTreeMap<String, Handler<M>>,
    on_ack: Option<AckFn<M>>,
    context_switchable: bool,
    decl: Declarations,
    keys: FrameworkKeys,
    params_text: String,
    source: ConfigSource,
    exec: ExecContext,
    lifecycle: Lifecycle,
    isolated: bool,
    tracker: AckTracker,
    stats: TaskStats,
    consecutive_overruns: u32,
    /// A fault injected through the debug queue, raised at the next cycle.
    injected: Option<InjectedFault>,
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
            tracker: AckTracker::default(),
            stats: TaskStats::default(),
            consecutive_overruns: 0,
            injected: None,
        })
    }

    fn ctx<'c>(
        core: &'c Core,
        info: &'c ModuleInfo,
        fsm: &'c Fsm<M>,
        tracker: &'c mut AckTracker,
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
            tracker,
            request: None,
            charged: Duration::ZERO,
        }
    }

    /// Puts the module in Safe and isolates it.
    fn isolate(&mut self, core: &Core, now: Time, fault: Fault) {
        let from = std::mem::replace(&mut self.lifecycle, Lifecycle::Safe);
        self.isolated = true;
        crate::system::isolate(core, &self.info, from, fault, now);
    }

    fn apply_goto(&mut self, core: &Core, now: Time, goto: Option<usize>) {
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

    fn handle(&mut self, core: &Core, now: Time, mut m: Message) {
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
                self.tracker.update(ack);
                if let Some(f) = self.on_ack
                    && !self.isolated
                {
                    let ack = ack.clone();
                    let mut ctx = Self::ctx(
                        core,
                        &self.info,
                        &self.fsm,
                        &mut self.tracker,
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

    fn dispatch(
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
            Self::ctx(core, &self.info, &self.fsm, &mut self.tracker, now, self.exec, self.lifecycle);
        ctx.request = Some(Request {
            message: Message {
                body: Body::Command { name: name.into(), args: serde_json::Value::Null },
                ..m.clone()
            },
        });
        let module = &mut self.module;
        let r = catch_unwind(AssertUnwindSafe(|| handler(module, &mut ctx, args)));
        let goto = ctx.goto;
        drop(ctx);
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

    fn state_json(&self) -> serde_json::Value {
        let meta: BTreeMap<_, _> = self
            .fsm
            .states
            .iter()
            .filter(|s| s.meta)
            .map(|s| (s.name.clone(), s.impls[s.active].0.clone()))
            .collect();
        serde_json::json!({
            "module": self.info.name,
            "kind": self.info.kind,
            "lifecycle": self.lifecycle,
            "state": self.fsm.states.get(self.fsm.current).map(|s| s.name.as_str()),
            "context": self.exec.to_string(),
            "isolated": self.isolated,
            "meta_states": meta,
            "commands": self.commands.keys().collect::<Vec<_>>(),
        })
    }

    fn framework_command(&mut self, core: &Core, now: Time, name: &str, args: serde_json::Value) -> Outcome {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct To {
            to: Lifecycle,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Meta {
            state: String,
            implementation: String,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct SetContext {
            context: ExecContext,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct SetParam {
            key: String,
            value: serde_json::Value,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Inject {
            kind: InjectedFault,
        }
        #[derive(Deserialize, Default)]
        #[serde(deny_unknown_fields)]
        struct Save {
            #[serde(default)]
            path: Option<std::path::PathBuf>,
        }
        fn parse<T: DeserializeOwned>(name: &str, args: serde_json::Value) -> Result<T, Outcome> {
            serde_json::from_value(args)
                .map_err(|e| Outcome::reject(format!("bad arguments for '{name}': {e}")))
        }
        let in_config = |this: &Self| {
            if this.lifecycle == Lifecycle::Config {
                Ok(())
            } else {
                Err(Outcome::reject(format!(
                    "'{name}' is allowed only in Config; module '{}' is in {}",
                    this.info.name, this.lifecycle
                )))
            }
        };
        let r: Result<Outcome, Outcome> = (|| match name {
            "ping" => Ok(Outcome::done()),
            "inject_fault" => {
                let Inject { kind } = parse(name, args)?;
                if self.isolated || self.lifecycle != Lifecycle::Run {
                    return Err(Outcome::reject(format!(
                        "module '{}' is not running ({}); nothing to inject into",
                        self.info.name, self.lifecycle
                    )));
                }
                self.injected = Some(kind);
                Ok(Outcome::Completed(serde_json::json!({ "injected": kind })))
            }
            "get_state" => Ok(Outcome::Completed(self.state_json())),
            "get_stats" => Ok(Outcome::Completed(serde_json::to_value(&self.stats).unwrap_or_default())),
            "lifecycle" => {
                let To { to } = parse(name, args)?;
                self.change_lifecycle(core, now, to)
            }
            "set_meta" => {
                let Meta { state, implementation } = parse(name, args)?;
                if self.isolated {
                    return Err(Outcome::reject(format!("module '{}' is isolated in Safe", self.info.name)));
                }
                let i = *self.fsm.index.get(&state).ok_or_else(|| {
                    Outcome::reject(format!("module '{}' has no state '{state}'", self.info.name))
                })?;
                let st = &mut self.fsm.states[i];
                if !st.meta {
                    return Err(Outcome::reject(format!("state '{state}' is not a meta-state")));
                }
                let k = st.impls.iter().position(|(n, _)| *n == implementation).ok_or_else(|| {
                    Outcome::reject(format!(
                        "meta-state '{state}' has no implementation '{implementation}' (it has: {})",
                        st.impls.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>().join(", ")
                    ))
                })?;
                st.active = k;
                core.events.raise(
                    now,
                    EventKind::MetaStateSwitched { module: self.info.name.clone(), state, implementation },
                );
                Ok(Outcome::done())
            }
            "set_context" => {
                let SetContext { context } = parse(name, args)?;
                if !self.context_switchable {
                    return Err(Outcome::reject(format!(
                        "module '{}' does not allow its execution context to change at runtime",
                        self.info.name
                    )));
                }
                self.exec = context;
                core.status(self.info.id).set_context(context);
                Ok(Outcome::done())
            }
            "set_param" => {
                in_config(self)?;
                let SetParam { key, value } = parse(name, args)?;
                let mut doc: toml::Table = toml::from_str(&self.params_text)
                    .map_err(|e| Outcome::fail(format!("current configuration unreadable: {e}")))?;
                let tv: toml::Value = serde_json::from_value(value)
                    .map_err(|e| Outcome::reject(format!("value not representable in TOML: {e}")))?;
                let mut table = &mut doc;
                let parts: Vec<&str> = key.split('.').collect();
                for p in &parts[..parts.len() - 1] {
                    table = table
                        .entry(p.to_string())
                        .or_insert_with(|| toml::Value::Table(Default::default()))
                        .as_table_mut()
                        .ok_or_else(|| Outcome::reject(format!("'{p}' in '{key}' is not a table")))?;
                }
                table.insert(parts[parts.len() - 1].to_string(), tv);
                let text = toml::to_string(&doc).map_err(|e| Outcome::fail(e.to_string()))?;
                self.apply_config_text(&format!("<set_param {key} on module '{}'>", self.info.name), text)
            }
            "reload_config" => {
                in_config(self)?;
                let text = self.source.read().map_err(|e| Outcome::reject(e.to_string()))?;
                self.apply_config_text(&self.source.origin(), text)
            }
            "save_config" => {
                in_config(self)?;
                let Save { path } = if args.is_null() { Save::default() } else { parse(name, args)? };
                let path = match (path, &self.source) {
                    (Some(p), _) => p,
                    (None, ConfigSource::File(p)) => p.clone(),
                    (None, ConfigSource::Inline { .. }) => {
                        return Err(Outcome::reject("configuration is inline; give a path to save to"));
                    }
                };
                std::fs::write(&path, &self.params_text)
                    .map_err(|e| Outcome::fail(format!("cannot write {}: {e}", path.display())))?;
                Ok(Outcome::Completed(serde_json::json!({ "path": path })))
            }
            _ => Err(Outcome::reject(format!("unknown framework command '{name}'"))),
        })();
        r.unwrap_or_else(|o| o)
    }

    /// Parses, validates and applies a new configuration text (Config state only).
    fn apply_config_text(&mut self, origin: &str, text: String) -> Result<Outcome, Outcome> {
        let src = Source::new(origin, &text);
        let cfg: ModuleConfigFile<M::Params> = src.parse().map_err(|e| Outcome::reject(e.to_string()))?;
        cfg.framework.validate(&src).map_err(|e| Outcome::reject(e.to_string()))?;
        self.module.configure(&cfg.params).map_err(|e| {
            Outcome::reject(format!("parameters rejected by module '{}': {e}", self.info.name))
        })?;
        self.exec = cfg.framework.context;
        self.keys = cfg.framework;
        self.params_text = text;
        Ok(Outcome::done())
    }

    fn change_lifecycle(&mut self, core: &Core, now: Time, to: Lifecycle) -> Result<Outcome, Outcome> {
        let from = self.lifecycle;
        from.check_transition(to)
            .map_err(|e| Outcome::reject(format!("module '{}': {e}", self.info.name)))?;
        let mut ctx =
            Self::ctx(core, &self.info, &self.fsm, &mut self.tracker, now, self.exec, self.lifecycle);
        let module = &mut self.module;
        let r = catch_unwind(AssertUnwindSafe(|| module.on_transition(&mut ctx, from, to)));
        drop(ctx);
        match r {
            Ok(Err(reason)) if to != Lifecycle::Safe => {
                return Err(Outcome::reject(format!(
                    "module '{}' refused {from} -> {to}: {reason}",
                    self.info.name
                )));
            }
            Err(p) => {
                let text = panic_text(&*p);
                self.isolate(core, now, Fault::Panic(text.clone()));
                return Err(Outcome::fail(format!("transition hook panicked: {text}")));
            }
            _ => {}
        }
        self.lifecycle = to;
        if from == Lifecycle::Safe {
            self.isolated = false;
            self.consecutive_overruns = 0;
            core.status(self.info.id).set_isolated(false);
        }
        core.status(self.info.id).set_lifecycle(to);
        core.events.raise(now, EventKind::ModuleLifecycle { module: self.info.name.clone(), from, to });
        Ok(Outcome::Completed(serde_json::json!({ "lifecycle": to })))
    }

    fn run_state_function(&mut self, core: &Core, now: Time) -> Duration {
        let f = match self.lifecycle {
            Lifecycle::Run => self.fsm.states.get(self.fsm.current).map(|s| s.impls[s.active].1),
            l => self.lifecycle_fns.get(&l).copied(),
        };
        let Some(f) = f else { return Duration::ZERO };
        // An injected fault takes the state function's place and goes the same way to isolation.
        let injected = self.injected.take();
        let mut ctx =
            Self::ctx(core, &self.info, &self.fsm, &mut self.tracker, now, self.exec, self.lifecycle);
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

    fn add_skipped(&mut self, n: u64) {
        self.stats.skipped += n;
    }

    fn publish_status(&self, core: &Core) {
        let s = core.status(self.info.id);
        s.set_lifecycle(self.lifecycle);
        s.set_context(self.exec);
        s.set_state(self.fsm.states.get(self.fsm.current).map(|s| s.name.as_str()).unwrap_or(""));
    }

    #[allow(clippy::disallowed_methods)] // the executor measures execution time; modules never see it
    fn step(&mut self, core: &Core, now: Time, mode: StepMode, basis: OverrunBasis) {
        let status = core.status(self.info.id);
        if status.is_isolated() && !self.isolated {
            // The watchdog isolated this module from outside (hang): adopt it.
            self.isolated = true;
            self.lifecycle = Lifecycle::Safe;
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
    }
}
