//! Remote modules (seed 000, 6.6 and 8.3): a module that runs in another process, possibly on
//! another computer, served through the same APIs as a local one.
//!
//! Making a module remote is a configuration change only: its configuration file names a host
//! (`[framework] host = "tcp/10.0.0.2:7450"`). The system is built as always; the builder wraps
//! that module's cell in a [`RemoteCell`], which the executors step like any other. At each of its
//! steps the proxy sends the host a [`TickRequest`]: the simulated time, the values of the slots
//! the module reads that changed since the last step, and the messages waiting in its inbox (all of
//! them for a cycle; emergencies only otherwise). The host ([`ModuleHost`]) steps the module's own
//! cell at that time and answers with a [`TickReply`]: the slots it wrote, every message it posted
//! (commands, acknowledgements, relays), the framework events it raised and its status. The proxy
//! applies them before the next module of the tick runs, so a lockstep run gives the same results
//! local or remote.
//!
//! Module ids are the same on both sides: the host builds its post office from the participant
//! names the core sends in its [`Hello`], and refuses a module whose declarations (kind, states,
//! slots and their types, configuration) differ from the core's with a clear error. The transport
//! is a [`RemoteLink`]; the `net` crate provides one over Zenoh. A link error or a host that does
//! not answer within the module's hang timeout puts the module in Safe (isolated, with an event);
//! the commands it had accepted are answered Failed, and the rest of the system goes on. Only a
//! `lifecycle` command (the one that takes it out of Safe) reconnects it: a host that is back gets
//! the module rebuilt from its configuration, brought to Config, then handed the command; any
//! other command fails at once, saying why. A host meeting another run of the core (its hello
//! carries a session number) starts afresh, so one host serves run after run.

use crate::blackboard::BlackBoard;
use crate::clock::{ClockDriver, SimClock, WallClock};
use crate::config::{ConfigSource, Schedule};
use crate::events::{Event, EventKind, EventLog, Fault};
use crate::exec_context::ExecContext;
use crate::lifecycle::Lifecycle;
use crate::message::{AckStatus, Body, Message, ModuleId, PostOffice};
use crate::module::{Cell, Declarations, Module, ModuleInfo, OverrunBasis, Runner, StepMode};
use crate::resources::Resources;
use crate::runtime::{Core, ModuleStatus};
use crate::stats::TaskStats;
use crate::time::{Duration, Time};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// What identifies a module's build and configuration: both sides must agree on it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModuleFingerprint {
    /// The module's kind.
    pub kind: String,
    /// The states of its own machine.
    pub states: Vec<String>,
    /// Slots it reads, with their Rust types.
    pub reads: Vec<(String, String)>,
    /// Slots it writes, with their Rust types.
    pub writes: Vec<(String, String)>,
    /// FNV-1a of its configuration file's text.
    pub config_digest: u64,
}

impl ModuleFingerprint {
    /// The fingerprint of a registered module.
    pub fn of(info: &ModuleInfo, config_text: &str, board: &BlackBoard) -> Self {
        let typed = |slots: Vec<String>| -> Vec<(String, String)> {
            slots
                .into_iter()
                .map(|s| {
                    let ty = board.slot(&s).map(|e| e.type_name().to_string()).unwrap_or_default();
                    (s, ty)
                })
                .collect()
        };
        let (reads, writes) = declared_slots(board, info.id);
        let (reads, writes) = (typed(reads), typed(writes));
        ModuleFingerprint {
            kind: format!("{:?}", info.kind),
            states: info.states.clone(),
            reads,
            writes,
            config_digest: fnv1a(config_text.as_bytes()),
        }
    }

    /// How `other` differs from this one, for a refusal; `None` when they agree.
    pub fn difference(&self, other: &ModuleFingerprint) -> Option<String> {
        if self.kind != other.kind {
            return Some(format!("kind {} here, {} there", self.kind, other.kind));
        }
        if self.states != other.states {
            return Some(format!("states {:?} here, {:?} there", self.states, other.states));
        }
        if self.reads != other.reads || self.writes != other.writes {
            return Some(format!(
                "slots read {:?} / written {:?} here, {:?} / {:?} there",
                self.reads, self.writes, other.reads, other.writes
            ));
        }
        if self.config_digest != other.config_digest {
            return Some("its configuration files differ".into());
        }
        None
    }
}

/// The core's handshake with a host: which module, the system's participants in id order, and the
/// module as the core built it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    /// The module to run.
    pub module: String,
    /// Every participant's name, in id order.
    pub names: Vec<String>,
    /// The module as the core registered it.
    pub fingerprint: ModuleFingerprint,
    /// The lifecycle state the core believes the module is in (a reconnect rebuilds it to there,
    /// as far as Config: Startup and Config are where a rebuilt module can be).
    pub lifecycle: Lifecycle,
    /// The core's run: a host meeting another run starts afresh (clock, slots, messages).
    pub session: u64,
    /// The sequence number of the module's latest message as the core has seen it (the host
    /// numbers the module's messages on from there, so ids never repeat across a reconnect).
    pub last_seq: u64,
}

/// Which part of a cycle a remote step performs.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum RemoteStep {
    /// Every waiting message, then the state function.
    Cycle,
    /// Emergency messages only.
    EmergencyOnly,
}

/// One slot value in flight: the slot's name and its record as [`crate::blackboard::ErasedSlot::encode`]
/// gives it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SlotRecord {
    /// The slot.
    pub slot: String,
    /// Its stamped value, postcard.
    pub bytes: Vec<u8>,
}

/// One step of a remote module, from the core.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickRequest {
    /// The module.
    pub module: String,
    /// The time of the step, ns.
    pub time_ns: i64,
    /// Which part of a cycle.
    pub step: RemoteStep,
    /// Overruns are judged on the simulated cost (lockstep) or the wall clock.
    pub charged: bool,
    /// The slots it reads whose value changed since its last step.
    pub slots: Vec<SlotRecord>,
    /// The messages handed to it, in the order its inbox gave them, each as JSON.
    pub messages: Vec<String>,
}

/// A remote module's status after a step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RemoteStatus {
    /// Lifecycle state.
    pub lifecycle: Lifecycle,
    /// Isolated in Safe.
    pub isolated: bool,
    /// Its own machine's state.
    pub state: String,
    /// Execution context.
    pub context: ExecContext,
    /// Active implementation of each meta-state.
    pub meta: BTreeMap<String, String>,
    /// Statistics.
    pub stats: TaskStats,
    /// Its period as now configured, ns (none: aperiodic).
    pub period_ns: Option<i64>,
    /// Its hang timeout as now configured, ns.
    pub hang_timeout_ns: i64,
}

/// What a remote step did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TickReply {
    /// The slots it wrote during the step (their latest records).
    pub slots: Vec<SlotRecord>,
    /// Every message it posted, in order, each as JSON.
    pub messages: Vec<String>,
    /// The framework events raised during the step, in order, each as JSON.
    pub events: Vec<String>,
    /// Its status after the step.
    pub status: RemoteStatus,
}

/// Why a remote step did not happen.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RemoteError {
    /// The host could not be reached, or did not answer in time.
    #[error("host unreachable: {0}")]
    Unreachable(String),
    /// The host refused the module (another build or configuration), saying why.
    #[error("refused by the host: {0}")]
    Refused(String),
    /// The answer made no sense (a message or slot that does not decode).
    #[error("bad answer from the host: {0}")]
    Protocol(String),
}

/// A transport between the core and the host of one module.
pub trait RemoteLink: Send {
    /// Introduces the module (at the first step, and to reconnect).
    fn hello(&mut self, hello: &Hello, timeout: std::time::Duration) -> Result<(), RemoteError>;
    /// Runs one step remotely, waiting at most `timeout` for the answer.
    fn tick(&mut self, req: &TickRequest, timeout: std::time::Duration) -> Result<TickReply, RemoteError>;
}

/// Makes the link of a remote module: `(host from its configuration, module name)`.
pub type LinkFactory = Arc<dyn Fn(&str, &str) -> Box<dyn RemoteLink> + Send + Sync>;

/// A number naming one run of a core to its hosts (a host meeting another one starts afresh).
/// Drawn from the wall clock and the process id: it names the run, it never enters its results.
#[allow(clippy::disallowed_methods)] // an identity, not a time the run uses
pub(crate) fn new_session() -> u64 {
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64);
    fnv1a(format!("{}-{}", t.unwrap_or(0), std::process::id()).as_bytes())
}

/// 64-bit FNV-1a (configuration digests, session numbers; `net` hashes its wire schemas with it).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// The slots module `id` declared it reads and writes, by name.
fn declared_slots(board: &BlackBoard, id: ModuleId) -> (Vec<String>, Vec<String>) {
    let (mut reads, mut writes) = (Vec::new(), Vec::new());
    for (slot, d) in board.declarations() {
        if d.readers.contains(&id) {
            reads.push(slot.clone());
        }
        if d.writers.contains(&id) {
            writes.push(slot);
        }
    }
    (reads, writes)
}

/// The records of `slots` written since `last` saw them (their sequence numbers there), encoded
/// for the other side; `last` is brought up to date.
fn changed_records(
    board: &BlackBoard,
    slots: &[String],
    last: &mut BTreeMap<String, u64>,
) -> Vec<SlotRecord> {
    let mut out = Vec::new();
    for name in slots {
        if let Some(slot) = board.slot(name) {
            let seq = slot.seq();
            if seq > 0
                && last.get(name) != Some(&seq)
                && let Some(bytes) = slot.encode()
            {
                last.insert(name.clone(), seq);
                out.push(SlotRecord { slot: name.clone(), bytes });
            }
        }
    }
    out
}

/// The core's proxy of a remote module: stepped by the executors like a local cell.
pub(crate) struct RemoteCell {
    /// The module's cell as the core built it: its declarations, configuration and initial status.
    /// It never runs here.
    local: Box<dyn Runner>,
    link: Box<dyn RemoteLink>,
    host: String,
    /// Sequence numbers of the read slots as last sent.
    sent: BTreeMap<String, u64>,
    reads: Vec<String>,
    introduced: bool,
    /// The link failed: the module is isolated until a `lifecycle` command reconnects it.
    down: bool,
    schedule: Schedule,
    hang_timeout: Duration,
    /// The core's run, for the host.
    session: u64,
    /// Commands handed to the module and not finally answered yet (answered Failed if its host
    /// is lost).
    forwarded: BTreeMap<crate::message::MessageId, Message>,
    /// The slots the module declared it writes: the only ones its host may fill.
    writes: Vec<String>,
}

impl RemoteCell {
    pub(crate) fn new(
        local: Box<dyn Runner>,
        link: Box<dyn RemoteLink>,
        host: &str,
        board: &BlackBoard,
        session: u64,
    ) -> Self {
        let id = local.info().id;
        let (reads, writes) = declared_slots(board, id);
        let (schedule, hang_timeout) = (local.schedule(), local.hang_timeout());
        RemoteCell {
            local,
            link,
            host: host.to_string(),
            sent: BTreeMap::new(),
            reads,
            introduced: false,
            down: false,
            schedule,
            hang_timeout,
            session,
            forwarded: BTreeMap::new(),
            writes,
        }
    }

    fn hello(&self, core: &Core) -> Hello {
        let info = self.local.info();
        Hello {
            module: info.name.clone(),
            names: core.post.names().to_vec(),
            fingerprint: ModuleFingerprint::of(info, self.local.config_text(), &core.board),
            lifecycle: core.status(info.id).lifecycle(),
            session: self.session,
            last_seq: core.post.inbox(info.id).seq(),
        }
    }

    /// Fails every command among `messages` (a step that never happened) and isolates the module.
    fn lose(&mut self, core: &Core, now: Time, messages: Vec<Message>, why: &RemoteError) {
        let info = self.local.info().clone();
        let forwarded = std::mem::take(&mut self.forwarded).into_values();
        let mut failed = std::collections::BTreeSet::new();
        for m in forwarded.chain(messages) {
            if matches!(m.body, Body::Command { .. }) && failed.insert(m.id) {
                let reason = format!("remote module '{}' on {}: {why}", info.name, self.host);
                if m.recipient == info.id {
                    core.post.acknowledge(&m, info.id, now, AckStatus::Failed(reason));
                } else {
                    // A command it was to relay: refused here, as an isolated relay refuses.
                    core.post.acknowledge(&m, info.id, now, AckStatus::Rejected(reason));
                }
            }
        }
        if !self.down {
            self.down = true;
            let status = core.status(info.id);
            if !status.is_isolated() {
                let fault = Fault::Remote(format!("{} ({})", why, self.host));
                crate::runtime::isolate(core, &info, status.lifecycle(), fault, now);
            }
        }
    }
}

impl Runner for RemoteCell {
    fn info(&self) -> &ModuleInfo {
        self.local.info()
    }
    fn schedule(&self) -> Schedule {
        self.schedule
    }
    fn hang_timeout(&self) -> Duration {
        self.hang_timeout
    }
    fn declarations(&self) -> &Declarations {
        self.local.declarations()
    }
    fn config_text(&self) -> &str {
        self.local.config_text()
    }
    fn publish_status(&self, core: &Core) {
        self.local.publish_status(core);
    }
    fn add_skipped(&mut self, n: u64) {
        self.local.add_skipped(n);
    }

    fn step(&mut self, core: &Core, now: Time, mode: StepMode, basis: OverrunBasis) {
        let id = self.local.info().id;
        let inbox = core.post.inbox(id);
        let mut messages = Vec::new();
        match mode {
            StepMode::EmergencyOnly => {
                while let Some(m) = inbox.pop_emergency() {
                    messages.push(m);
                }
            }
            StepMode::Cycle => {
                for _ in 0..inbox.len() {
                    match inbox.pop() {
                        Some(m) => messages.push(m),
                        None => break,
                    }
                }
            }
        }
        if self.down {
            // Only a `lifecycle` command (out of Safe, to Standby or Shutdown) reconnects: other
            // commands fail at once, a module left alone stays in Safe.
            let reconnect = messages.iter().any(|m| {
                m.recipient == id && matches!(&m.body, Body::Command { name, .. } if name == "lifecycle")
            });
            if !reconnect {
                if !messages.is_empty() {
                    let why = RemoteError::Unreachable(
                        "down since its host was lost; take it out of Safe to reconnect".into(),
                    );
                    self.lose(core, now, messages, &why);
                }
                return;
            }
            self.introduced = false;
        }
        let timeout = self.hang_timeout.to_std();
        if !self.introduced {
            let hello = self.hello(core);
            match self.link.hello(&hello, timeout) {
                Ok(()) => {
                    self.introduced = true;
                    self.sent.clear();
                    if self.down {
                        self.down = false;
                        core.events.raise(
                            now,
                            EventKind::Note {
                                module: hello.module.clone(),
                                text: format!("remote module reconnected to {}", self.host),
                            },
                        );
                    }
                }
                Err(e) => return self.lose(core, now, messages, &e),
            }
        }
        let slots = changed_records(&core.board, &self.reads, &mut self.sent);
        let req = TickRequest {
            module: self.local.info().name.clone(),
            time_ns: now.as_nanos(),
            step: match mode {
                StepMode::Cycle => RemoteStep::Cycle,
                StepMode::EmergencyOnly => RemoteStep::EmergencyOnly,
            },
            charged: basis == OverrunBasis::Charged,
            slots,
            messages: messages
                .iter()
                .map(|m| serde_json::to_string(m).expect("messages serialize"))
                .collect(),
        };
        // The link's own timeout bounds the step (the watchdog does not watch it: under lockstep
        // that would end the run instead of putting this module in Safe).
        let reply = self.link.tick(&req, timeout);
        let reply = match reply.and_then(|r| check_status(&r.status).map(|()| r)) {
            Ok(r) => r,
            Err(e) => return self.lose(core, now, messages, &e),
        };
        for m in messages {
            if m.recipient == id && matches!(m.body, Body::Command { .. }) {
                self.forwarded.insert(m.id, m);
            }
        }
        if let Err(e) = apply(core, id, &self.writes, &reply, &mut self.forwarded) {
            return self.lose(core, now, Vec::new(), &e);
        }
        let status = core.status(id);
        let s = &reply.status;
        self.schedule = match s.period_ns {
            Some(p) => Schedule::Periodic(Duration::from_nanos(p)),
            None => Schedule::Aperiodic,
        };
        self.hang_timeout = Duration::from_nanos(s.hang_timeout_ns);
        status.set_lifecycle(s.lifecycle);
        status.set_isolated(s.isolated);
        status.set_state(&s.state);
        status.set_context(s.context);
        for (st, i) in &s.meta {
            status.set_meta(st, i);
        }
        status.set_hang_timeout(self.hang_timeout);
        status.store_stats(&s.stats);
    }
}

/// A status from a host that makes sense (a period or timeout of zero would stall the executors).
fn check_status(s: &RemoteStatus) -> Result<(), RemoteError> {
    if s.period_ns.is_some_and(|p| p <= 0) || s.hang_timeout_ns <= 0 {
        return Err(RemoteError::Protocol(format!(
            "status with period {:?} ns and hang timeout {} ns",
            s.period_ns, s.hang_timeout_ns
        )));
    }
    Ok(())
}

/// Applies a step's results to the core: slots, events, then messages (as a local module's step
/// leaves them). Only the module's declared slots are written, and only messages naming known
/// participants are posted; the module's final answers clear `forwarded`.
fn apply(
    core: &Core,
    id: ModuleId,
    writes: &[String],
    reply: &TickReply,
    forwarded: &mut BTreeMap<crate::message::MessageId, Message>,
) -> Result<(), RemoteError> {
    let mut messages = Vec::with_capacity(reply.messages.len());
    for m in &reply.messages {
        let m: Message =
            serde_json::from_str(m).map_err(|e| RemoteError::Protocol(format!("message: {e}")))?;
        if !core.post.knows_all(&m) {
            return Err(RemoteError::Protocol(format!("message {} names an unknown participant", m.id)));
        }
        messages.push(m);
    }
    let mut events = Vec::with_capacity(reply.events.len());
    for e in &reply.events {
        events.push(
            serde_json::from_str::<Event>(e).map_err(|e| RemoteError::Protocol(format!("event: {e}")))?,
        );
    }
    for r in &reply.slots {
        if !writes.contains(&r.slot) {
            return Err(RemoteError::Protocol(format!(
                "the host wrote slot '{}', which the module does not write",
                r.slot
            )));
        }
        let slot = core
            .board
            .slot(&r.slot)
            .ok_or_else(|| RemoteError::Protocol(format!("the host wrote unknown slot '{}'", r.slot)))?;
        slot.import(&r.bytes).map_err(|e| RemoteError::Protocol(e.to_string()))?;
    }
    for e in events {
        core.events.raise(e.stamp, e.kind);
    }
    for m in messages {
        if m.sender == id {
            core.post.inbox(id).advance_seq_to(m.id.seq);
        }
        if let Body::Ack(a) = &m.body
            && a.by == id
            && a.status.is_final()
        {
            forwarded.remove(&a.of);
        }
        core.post.post(m);
    }
    Ok(())
}

/// Builds a module for a host: called with the module's name, to register it on the host
/// ([`HostBuilder::add`]).
pub type ModuleFactory = Box<dyn Fn(&str, &mut HostBuilder) -> Result<(), String> + Send>;

/// Registers the modules of a host, with the core's participant names.
pub struct HostBuilder {
    names: Vec<String>,
    board: BlackBoard,
    runners: BTreeMap<String, Box<dyn Runner>>,
}

impl HostBuilder {
    /// Registers `module` under `name` (one of the core's participants) with its configuration.
    pub fn add<M: Module>(&mut self, name: &str, module: M, config: ConfigSource) -> Result<(), String> {
        let Some(i) = self.names.iter().position(|n| n == name) else {
            return Err(format!("the core has no participant named '{name}'"));
        };
        let cell =
            Cell::new(ModuleId(i as u32), name, module, config, &self.board).map_err(|e| e.to_string())?;
        self.runners.insert(name.to_string(), Box::new(cell));
        Ok(())
    }
}

/// A host of remote modules: their cells, on a core of their own whose participants (and so ids)
/// are the core's.
pub struct ModuleHost {
    core: Arc<Core>,
    driver: ClockDriver,
    runners: BTreeMap<String, Box<dyn Runner>>,
    /// Sequence numbers of each hosted module's written slots as last returned.
    returned: BTreeMap<String, u64>,
    /// The slots each hosted module reads and writes (declared once, at its hello).
    slots: BTreeMap<String, (Vec<String>, Vec<String>)>,
    factory: ModuleFactory,
    /// The core run being served.
    session: Option<u64>,
}

impl ModuleHost {
    /// A host that builds its modules with `factory` once the core says hello.
    pub fn new(factory: ModuleFactory) -> Self {
        let (clock, driver) = SimClock::new();
        let core = Arc::new(Core {
            clock: Arc::new(clock),
            post: PostOffice::new(Vec::new(), false),
            board: BlackBoard::new(),
            resources: Resources::new(),
            events: EventLog::default(),
            status: Vec::new(),
            wall: WallClock::new(),
            modules: Vec::new(),
        });
        ModuleHost {
            core,
            driver,
            runners: BTreeMap::new(),
            returned: BTreeMap::new(),
            slots: BTreeMap::new(),
            factory,
            session: None,
        }
    }

    /// The names of the modules it runs now.
    pub fn modules(&self) -> Vec<String> {
        self.runners.keys().cloned().collect()
    }

    /// Takes a core's hello: builds the module (again, after a reconnect: a fresh module from its
    /// configuration, brought to Config when the core has it past Startup) and checks that it is
    /// the core's. Other modules already hosted are kept when the core's participants are the same.
    pub fn hello(&mut self, hello: &Hello) -> Result<(), RemoteError> {
        if self.session != Some(hello.session) || self.core.post.names() != hello.names.as_slice() {
            // Another run (or system): start afresh with its participants, its clock at zero.
            self.session = Some(hello.session);
            let (clock, driver) = SimClock::new();
            self.core = Arc::new(Core {
                clock: Arc::new(clock),
                // Traced: a step's messages go back in the order they were posted.
                post: PostOffice::new(hello.names.clone(), true),
                board: BlackBoard::new(),
                resources: Resources::new(),
                events: EventLog::default(),
                status: hello.names.iter().map(|_| ModuleStatus::new()).collect(),
                wall: WallClock::new(),
                modules: Vec::new(),
            });
            self.driver = driver;
            self.runners.clear();
            self.returned.clear();
            self.slots.clear();
        }
        // Always a fresh cell: the core reconnects after the host lost the module's state.
        let mut b = HostBuilder {
            names: hello.names.clone(),
            board: self.core.board.clone(),
            runners: BTreeMap::new(),
        };
        (self.factory)(&hello.module, &mut b).map_err(RemoteError::Refused)?;
        let runner = b.runners.remove(&hello.module).ok_or_else(|| {
            RemoteError::Refused(format!("this host does not run module '{}'", hello.module))
        })?;
        if let Some(p) = runner.declarations().problems.first() {
            return Err(RemoteError::Refused(format!("module '{}': {p}", hello.module)));
        }
        let mine = ModuleFingerprint::of(runner.info(), runner.config_text(), &self.core.board);
        if let Some(d) = mine.difference(&hello.fingerprint) {
            return Err(RemoteError::Refused(format!(
                "module '{}' is not the core's: {d} (both sides must run the same build and configuration)",
                hello.module
            )));
        }
        // A rebuilt module starts clean: not isolated, in Startup, numbering its messages on from
        // the last one the core saw.
        let id = runner.info().id;
        let status = self.core.status(id);
        status.set_isolated(false);
        status.set_lifecycle(Lifecycle::Startup);
        self.core.post.inbox(id).advance_seq_to(hello.last_seq);
        self.slots.insert(hello.module.clone(), declared_slots(&self.core.board, id));
        runner.publish_status(&self.core);
        self.runners.insert(hello.module.clone(), runner);
        // A rebuilt module starts in Startup; the core's `lifecycle` commands take it on from
        // Config (the state every module reaches at start-up).
        if hello.lifecycle != Lifecycle::Startup {
            self.bring_to_config(&hello.module)?;
        }
        Ok(())
    }

    fn bring_to_config(&mut self, module: &str) -> Result<(), RemoteError> {
        let id =
            self.core.post.id(module).ok_or_else(|| RemoteError::Refused(format!("no module '{module}'")))?;
        let cmd = crate::message::Command::new(module, "lifecycle")
            .on(crate::message::Queue::Emergency)
            .json(serde_json::json!({ "to": Lifecycle::Config }));
        let m = self
            .core
            .post
            .compose(id, self.core.now(), cmd)
            .map_err(|e| RemoteError::Refused(e.to_string()))?;
        self.core.post.post(m);
        let now = self.core.now();
        if let Some(r) = self.runners.get_mut(module) {
            r.step(&self.core, now, StepMode::EmergencyOnly, OverrunBasis::Charged);
        }
        // The module acknowledged itself: nobody waits for it.
        let _ = self.core.post.inbox(id).pop();
        self.core.events.drain();
        Ok(())
    }

    /// Runs one step of a hosted module.
    pub fn tick(&mut self, req: &TickRequest) -> Result<TickReply, RemoteError> {
        let core = self.core.clone();
        let runner = self.runners.get_mut(&req.module).ok_or_else(|| {
            RemoteError::Refused(format!("module '{}' was not introduced (hello first)", req.module))
        })?;
        let t = Time::from_nanos(req.time_ns);
        if t < core.now() {
            return Err(RemoteError::Protocol(format!("time went back from {} to {t}", core.now())));
        }
        self.driver.advance_to(t);
        let id = runner.info().id;
        let Some((reads, writes)) = self.slots.get(&req.module) else {
            return Err(RemoteError::Refused(format!(
                "module '{}' was not introduced (hello first)",
                req.module
            )));
        };
        for r in &req.slots {
            let slot = core.board.slot(&r.slot).filter(|_| reads.contains(&r.slot)).ok_or_else(|| {
                RemoteError::Protocol(format!("module '{}' reads no slot '{}'", req.module, r.slot))
            })?;
            slot.import(&r.bytes).map_err(|e| RemoteError::Protocol(e.to_string()))?;
        }
        let mut incoming = Vec::with_capacity(req.messages.len());
        for m in &req.messages {
            let m: Message =
                serde_json::from_str(m).map_err(|e| RemoteError::Protocol(format!("message: {e}")))?;
            if !core.post.knows_all(&m) {
                return Err(RemoteError::Protocol(format!("message {} names an unknown participant", m.id)));
            }
            incoming.push(m);
        }
        for m in incoming {
            core.post.post(m);
        }
        // What was posted before the step is not the step's.
        core.post.take_trace();
        let mode = match req.step {
            RemoteStep::Cycle => StepMode::Cycle,
            RemoteStep::EmergencyOnly => StepMode::EmergencyOnly,
        };
        let basis = if req.charged { OverrunBasis::Charged } else { OverrunBasis::Wall };
        runner.step(&core, t, mode, basis);
        let slots = changed_records(&core.board, writes, &mut self.returned);
        // Every message the step posted, in posting order; the host's inboxes are emptied (the
        // core delivers them, to its modules or back here at the recipient's next step).
        let messages = core
            .post
            .take_trace()
            .iter()
            .map(|m| serde_json::to_string(m).expect("messages serialize"))
            .collect();
        for i in 0..core.post.names().len() {
            let inbox = core.post.inbox(ModuleId(i as u32));
            while inbox.pop().is_some() {}
        }
        let events =
            core.events.drain().iter().map(|e| serde_json::to_string(e).expect("events serialize")).collect();
        let st = core.status(id);
        let status = RemoteStatus {
            lifecycle: st.lifecycle(),
            isolated: st.is_isolated(),
            state: st.state(),
            context: st.context(),
            meta: st.meta_states(),
            stats: st.stats(),
            period_ns: match runner.schedule() {
                Schedule::Periodic(p) => Some(p.as_nanos()),
                Schedule::Aperiodic => None,
            },
            hang_timeout_ns: runner.hang_timeout().as_nanos(),
        };
        Ok(TickReply { slots, messages, events, status })
    }
}
