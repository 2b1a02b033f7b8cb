//! The System Manager (seed 000, 4.3): registration, start-up checks, lifecycle, resources.
//!
//! Modules are registered on a [`SystemBuilder`] (the Startup state): each one's configuration file is
//! loaded and its declarations collected. Building checks the whole module graph at once and reports
//! every problem with the module it concerns: duplicate names, two writers of one slot, slots read but
//! written by nobody, commands sent to unknown modules, periods the executor cannot honour. Then the
//! system moves to Config and an executor takes over.
//!
//! Lifecycle transitions are commands like any other: the manager sends a `lifecycle` command on the
//! emergency queue to every module and collects the acknowledgements, so the same mechanism works for
//! modules on other threads or, later, other hosts.

use crate::blackboard::BlackBoard;
use crate::clock::{Clock, WallClock};
use crate::config::ConfigSource;
use crate::events::{EventKind, EventLog};
use crate::lifecycle::{Lifecycle, TransitionError};
use crate::message::{
    Ack, AckStatus, AckTracker, Body, Command, MessageId, ModuleId, PostOffice, Queue, SendError,
};
use crate::module::{Cell, Module, ModuleInfo, Runner};
use crate::resources::Resources;
pub use crate::runtime::{Core, ModuleStatus};
use crate::stats::TaskStats;
use crate::time::Duration;
use parking_lot::Mutex;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// Problems found at start-up; the system does not start while there is any.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("system start-up failed:\n{}", problems.iter().map(|p| format!("  - {p}")).collect::<Vec<_>>().join("\n"))]
pub struct StartupError {
    /// Every problem, each naming its module, slot or file.
    pub problems: Vec<String>,
}

/// Errors of system-level operations.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SystemError {
    /// The system cannot make that transition.
    #[error(transparent)]
    Transition(#[from] TransitionError),
    /// Some modules refused or failed the transition.
    #[error("transition to {to} incomplete: {}", refusals.join("; "))]
    Refused {
        /// The requested state.
        to: Lifecycle,
        /// One line per refusing module.
        refusals: Vec<String>,
    },
    /// No module of that name.
    #[error("no module named '{0}'")]
    UnknownModule(String),
    /// A message could not be sent.
    #[error(transparent)]
    Send(#[from] SendError),
    /// Acknowledgements did not arrive in time (real-time executor).
    #[error("no acknowledgement from {0} within the timeout")]
    Timeout(String),
}

enum Entry {
    Module(Box<dyn Runner>),
    Endpoint,
}

/// Registers modules and endpoints, then builds an executor (the Startup state).
pub struct SystemBuilder {
    board: BlackBoard,
    resources: Resources,
    entries: Vec<Entry>,
    names: Vec<String>,
    problems: Vec<String>,
    trace_messages: bool,
    remote_links: Option<crate::remote::LinkFactory>,
    hosts_ignored: bool,
}

/// Name of the system manager's own endpoint.
pub const SYSTEM: &str = "system";

impl Default for SystemBuilder {
    fn default() -> Self {
        Self::new()
    }
}

impl SystemBuilder {
    /// A builder with the system manager's endpoint registered.
    pub fn new() -> Self {
        let mut b = SystemBuilder {
            board: BlackBoard::new(),
            resources: Resources::new(),
            entries: Vec::new(),
            names: Vec::new(),
            problems: Vec::new(),
            trace_messages: false,
            remote_links: None,
            hosts_ignored: false,
        };
        b.endpoint(SYSTEM);
        b
    }

    fn next_id(&mut self, name: &str) -> Option<ModuleId> {
        if self.names.iter().any(|n| n == name) {
            self.problems.push(format!("'{name}' is registered twice"));
            return None;
        }
        if name.is_empty() || name.contains(char::is_whitespace) {
            self.problems.push(format!("'{name}' is not a valid module name (empty or with spaces)"));
            return None;
        }
        self.names.push(name.to_string());
        Some(ModuleId(self.names.len() as u32 - 1))
    }

    /// Registers a module with its configuration. Problems are reported by the build.
    pub fn add<M: Module>(&mut self, name: &str, module: M, config: ConfigSource) -> &mut Self {
        let Some(id) = self.next_id(name) else { return self };
        let source = config.clone();
        match Cell::new(id, name, module, config, &self.board) {
            Ok(cell) => {
                for p in &cell_problems(&cell) {
                    self.problems.push(format!("module '{name}': {p}"));
                }
                self.entries.push(Entry::Module(Box::new(cell)));
            }
            Err(e) => {
                self.problems.push(source.relocate(e).to_string());
                // Keep ids aligned with names: the slot stays, as an endpoint nobody uses.
                self.entries.push(Entry::Endpoint);
            }
        }
        self
    }

    /// Registers a module whose configuration is given as TOML text (tests, demos, generated setups).
    pub fn add_inline<M: Module>(&mut self, name: &str, module: M, toml: &str) -> &mut Self {
        self.add(name, module, ConfigSource::inline(format!("<inline config of module '{name}'>"), toml))
    }

    /// Registers an external endpoint: a participant without a module (an operator console, a script,
    /// a ground station) that sends commands and receives their acknowledgements.
    pub fn endpoint(&mut self, name: &str) -> &mut Self {
        if self.next_id(name).is_some() {
            self.entries.push(Entry::Endpoint);
        }
        self
    }

    /// Registers a shared device managed by reservation tokens.
    pub fn device(&mut self, name: &str) -> &mut Self {
        self.resources.register(name);
        self
    }

    /// How to reach the hosts of remote modules (those whose configuration names a
    /// `[framework] host`): a network layer's link factory. Without one, a remote module is a
    /// start-up problem.
    pub fn remote_links(&mut self, factory: crate::remote::LinkFactory) -> &mut Self {
        self.remote_links = Some(factory);
        self
    }

    /// Runs every module here, whatever host its configuration names (a configuration check that
    /// needs no network).
    pub fn ignore_hosts(&mut self) -> &mut Self {
        self.hosts_ignored = true;
        self
    }

    /// Records every posted message for inspection (off by default).
    pub fn trace_messages(&mut self, on: bool) -> &mut Self {
        self.trace_messages = on;
        self
    }

    /// Problems found so far while registering (configuration errors, duplicate names); the
    /// system will not start while there is any.
    pub fn problems(&self) -> &[String] {
        &self.problems
    }

    /// The shared devices and their reservations (device maps register their devices here).
    pub fn resources(&self) -> &Resources {
        &self.resources
    }
    /// The blackboard being declared.
    pub fn board(&self) -> &BlackBoard {
        &self.board
    }

    /// Runs the start-up checks and moves every module to Config.
    pub(crate) fn assemble(
        self,
        clock: Arc<dyn Clock>,
        base_period: Option<Duration>,
    ) -> Result<Assembled, StartupError> {
        let mut problems = self.problems;
        let mut runners = Vec::new();
        let session = crate::remote::new_session();
        for e in self.entries {
            if let Entry::Module(r) = e {
                let Some(host) = r.host().map(str::to_string).filter(|_| !self.hosts_ignored) else {
                    runners.push(r);
                    continue;
                };
                let name = r.info().name.clone();
                match &self.remote_links {
                    Some(f) => {
                        let link = f(&host, &name);
                        let cell = crate::remote::RemoteCell::new(r, link, &host, &self.board, session);
                        runners.push(Box::new(cell));
                    }
                    None => problems.push(format!(
                        "module '{name}' is configured to run on host {host}, but this program has no network layer"
                    )),
                }
            }
        }
        // Recipients must exist.
        for r in &runners {
            for to in &r.declarations().recipients {
                if !self.names.iter().any(|n| n == to) {
                    problems.push(format!("module '{}' sends to unknown module '{to}'", r.info().name));
                }
            }
        }
        // Slots: exactly one writer; every read slot written by someone.
        let name_of = |id: ModuleId| self.names.get(id.0 as usize).cloned().unwrap_or_default();
        for (slot, d) in self.board.declarations() {
            if d.writers.len() > 1 {
                let w: Vec<_> = d.writers.iter().map(|w| format!("'{}'", name_of(*w))).collect();
                problems.push(format!("slot '{slot}' has several writers: {}", w.join(", ")));
            }
            if d.writers.is_empty() {
                let r: Vec<_> = d.readers.iter().map(|w| format!("'{}'", name_of(*w))).collect();
                problems.push(format!("slot '{slot}' is read by {} but no module writes it", r.join(", ")));
            }
        }
        // Periods must be whole multiples of the lockstep base period.
        if let Some(base) = base_period {
            for r in &runners {
                if let crate::config::Schedule::Periodic(p) = r.schedule()
                    && p.as_nanos() % base.as_nanos() != 0
                {
                    problems.push(format!(
                        "module '{}': period {p} is not a multiple of the base period {base}",
                        r.info().name
                    ));
                }
            }
        }
        if !problems.is_empty() {
            return Err(StartupError { problems });
        }
        let modules: Vec<ModuleInfo> = runners.iter().map(|r| r.info().clone()).collect();
        let core = Arc::new(Core {
            clock,
            post: PostOffice::new(self.names.clone(), self.trace_messages),
            board: self.board,
            resources: self.resources,
            events: EventLog::default(),
            status: self.names.iter().map(|_| ModuleStatus::new()).collect(),
            wall: WallClock::new(),
            modules,
        });
        for r in &runners {
            r.publish_status(&core);
        }
        let manager = SystemManager::new(core.clone());
        Ok(Assembled { core, runners, manager })
    }
}

fn cell_problems(r: &dyn Runner) -> Vec<String> {
    r.declarations().problems.clone()
}

pub(crate) struct Assembled {
    pub core: Arc<Core>,
    pub runners: Vec<Box<dyn Runner>>,
    pub manager: SystemManager,
}

/// An external participant: sends commands and collects their acknowledgements. Thread-safe.
#[derive(Clone)]
pub struct Endpoint {
    core: Arc<Core>,
    id: ModuleId,
    tracker: Arc<Mutex<AckTracker>>,
}

impl Endpoint {
    pub(crate) fn new(core: Arc<Core>, name: &str) -> Result<Self, SystemError> {
        let id = core.post.id(name).ok_or_else(|| SystemError::UnknownModule(name.to_string()))?;
        Ok(Endpoint { core, id, tracker: Arc::default() })
    }
    /// This endpoint's id.
    pub fn id(&self) -> ModuleId {
        self.id
    }
    /// Sends a command stamped with the current clock time.
    pub fn send(&self, cmd: Command) -> Result<MessageId, SendError> {
        let name = cmd.name.clone();
        let m = self.core.post.compose(self.id, self.core.now(), cmd)?;
        let id = m.id;
        self.tracker.lock().sent(id, &name);
        self.core.post.post(m);
        Ok(id)
    }
    /// Takes the acknowledgements that arrived, updating the tracker.
    pub fn poll(&self) -> Vec<Ack> {
        let mut acks = Vec::new();
        let inbox = self.core.post.inbox(self.id);
        while let Some(m) = inbox.pop() {
            if let Body::Ack(a) = m.body {
                self.tracker.lock().update(&a);
                acks.push(a);
            }
        }
        acks
    }
    /// Latest known status of a command sent from here (polls first).
    pub fn status(&self, id: MessageId) -> Option<AckStatus> {
        self.poll();
        self.tracker.lock().status(id)
    }
    /// Blocks (real time) until `id` has a final status or the timeout passes.
    #[allow(clippy::disallowed_methods)] // waiting for other threads is measured on the OS clock
    pub fn wait_final(&self, id: MessageId, timeout: std::time::Duration) -> Option<AckStatus> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if let Some(s) = self.status(id)
                && s.is_final()
            {
                return Some(s);
            }
            if !self.core.post.inbox(self.id).wait_until(deadline) {
                return self.status(id);
            }
        }
    }
}

/// The system manager: the system's lifecycle state and the transitions of its modules.
pub struct SystemManager {
    core: Arc<Core>,
    state: Lifecycle,
    endpoint: Endpoint,
}

impl SystemManager {
    fn new(core: Arc<Core>) -> Self {
        let endpoint = Endpoint::new(core.clone(), SYSTEM).expect("system endpoint is registered first");
        SystemManager { core, state: Lifecycle::Startup, endpoint }
    }
    /// The system's lifecycle state.
    pub fn state(&self) -> Lifecycle {
        self.state
    }
    /// The shared core.
    pub fn core(&self) -> &Arc<Core> {
        &self.core
    }

    /// Sends the lifecycle command for a system transition to every module that takes part (all but
    /// those in Safe, unless the target is Safe itself or Shutdown). Returns the commands sent.
    pub(crate) fn begin(&mut self, to: Lifecycle) -> Result<Vec<(String, MessageId)>, SystemError> {
        self.state.check_transition(to)?;
        let mut sent = Vec::new();
        for m in self.core.modules() {
            let l = self.core.status(m.id).lifecycle();
            let takes_part = match to {
                Lifecycle::Safe => l != Lifecycle::Safe,
                Lifecycle::Shutdown => l != Lifecycle::Shutdown,
                Lifecycle::Standby if self.state == Lifecycle::Safe => true,
                _ => l != Lifecycle::Safe,
            };
            if takes_part {
                sent.push((m.name.clone(), self.send_lifecycle(&m.name, to)?));
            }
        }
        Ok(sent)
    }

    /// Sends one module a lifecycle command.
    pub(crate) fn send_lifecycle(&self, module: &str, to: Lifecycle) -> Result<MessageId, SystemError> {
        Ok(self.endpoint.send(
            Command::new(module, "lifecycle").on(Queue::Emergency).json(serde_json::json!({ "to": to })),
        )?)
    }

    /// Collects the acknowledgements of a transition and updates the system state.
    pub(crate) fn finish(&mut self, to: Lifecycle, sent: &[(String, MessageId)]) -> Result<(), SystemError> {
        let mut refusals = Vec::new();
        for (name, id) in sent {
            match self.endpoint.status(*id) {
                Some(AckStatus::Completed(_)) => {}
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => refusals.push(r),
                other => refusals.push(format!("module '{name}' did not complete ({other:?})")),
            }
        }
        // A move to Safe or Shutdown happens whatever individual modules say.
        if refusals.is_empty() || matches!(to, Lifecycle::Safe | Lifecycle::Shutdown) {
            let from = std::mem::replace(&mut self.state, to);
            self.core.events.raise(self.core.now(), EventKind::SystemState { from, to });
        }
        if refusals.is_empty() { Ok(()) } else { Err(SystemError::Refused { to, refusals }) }
    }

    /// Status of the last command sent by the manager with this id.
    pub(crate) fn ack(&self, id: MessageId) -> Option<AckStatus> {
        self.endpoint.status(id)
    }

    /// The endpoint the manager sends from.
    pub fn endpoint(&self) -> &Endpoint {
        &self.endpoint
    }
}

/// A snapshot of one module for consoles and reports.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ModuleReport {
    /// Name.
    pub name: String,
    /// Kind.
    pub kind: crate::module::ModuleKind,
    /// Lifecycle state.
    pub lifecycle: Lifecycle,
    /// Own state-machine state.
    pub state: String,
    /// Execution context.
    pub context: String,
    /// Isolated by the watchdog.
    pub isolated: bool,
    /// The active implementation of each meta-state.
    pub meta_states: BTreeMap<String, String>,
    /// Statistics.
    pub stats: TaskStats,
}

/// Snapshots of every module.
pub fn module_reports(core: &Core) -> Vec<ModuleReport> {
    core.modules()
        .iter()
        .map(|m| {
            let s = core.status(m.id);
            ModuleReport {
                name: m.name.clone(),
                kind: m.kind,
                lifecycle: s.lifecycle(),
                state: s.state(),
                context: s.context().to_string(),
                isolated: s.is_isolated(),
                meta_states: s.meta_states(),
                stats: s.stats(),
            }
        })
        .collect()
}

/// Statistics of every module by name.
pub fn stats_by_module(core: &Core) -> BTreeMap<String, TaskStats> {
    core.modules().iter().map(|m| (m.name.clone(), core.status(m.id).stats())).collect()
}

/// Map of module names to ids.
pub fn module_ids(core: &Core) -> HashMap<String, ModuleId> {
    core.modules().iter().map(|m| (m.name.clone(), m.id)).collect()
}
