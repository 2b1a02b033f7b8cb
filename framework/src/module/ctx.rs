//! What a module sees of the world while one of its functions runs.

use crate::blackboard::{BoardData, Reader, Stamped, Writer};
use crate::events::EventKind;
use crate::exec_context::ExecContext;
use crate::lifecycle::Lifecycle;
use crate::message::{
    AckStatus, AckTracker, Body, Command, Message, MessageId, ModuleId, Outcome, Queue, SendError,
};
use crate::resources::{ReservationError, ReservationToken};
use crate::runtime::Core;
use crate::time::{Duration, Time};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

/// A module's book of commands: those it sent (with their acknowledgements) and those it accepted
/// and has not yet answered finally (answered Failed if the module goes to Safe first).
#[derive(Default)]
pub(super) struct Ledger {
    pub(super) sent: AckTracker,
    pub(super) accepted: BTreeMap<MessageId, Message>,
}

/// A command being handled, kept by a module that accepted it to reply later with [`Ctx::reply`].
#[derive(Clone, Debug, PartialEq)]
pub struct Request {
    pub(super) message: Message,
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
pub(super) struct FsmView<'a> {
    pub(super) names: Vec<&'a str>,
    pub(super) index: &'a HashMap<String, usize>,
    pub(super) transitions: &'a HashSet<(usize, usize)>,
}

/// What a module sees of the world while one of its functions runs.
pub struct Ctx<'a> {
    pub(super) core: &'a Core,
    pub(super) id: ModuleId,
    pub(super) name: &'a str,
    pub(super) now: Time,
    pub(super) exec: ExecContext,
    pub(super) lifecycle: Lifecycle,
    pub(super) fsm: FsmView<'a>,
    pub(super) current: usize,
    pub(super) goto: Option<usize>,
    pub(super) ledger: &'a mut Ledger,
    pub(super) request: Option<Request>,
    pub(super) charged: Duration,
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
    pub fn module_status(&self, name: &str) -> Option<&crate::runtime::ModuleStatus> {
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
        self.ledger.sent.sent(id, &name);
        self.core.post.post(m);
        Ok(id)
    }
    /// The latest known status of a command this module sent.
    pub fn ack_status(&self, id: MessageId) -> Option<AckStatus> {
        self.ledger.sent.status(id)
    }
    /// Commands sent without a final acknowledgement yet.
    pub fn outstanding_commands(&self) -> usize {
        self.ledger.sent.outstanding()
    }
    /// The command being handled (inside a command handler), to keep and [`Ctx::reply`] to later.
    pub fn request(&self) -> Option<Request> {
        self.request.clone()
    }
    /// Reports the completion or failure of a command accepted earlier.
    ///
    /// A command that was already answered finally (its module went to Safe meanwhile, which
    /// answers what it had accepted Failed) is not answered again: the reply is dropped.
    pub fn reply(&mut self, request: &Request, outcome: Outcome) {
        if !self.ledger.accepted.contains_key(&request.id()) {
            tracing::debug!(
                module = self.name,
                command = request.command(),
                "reply to a command already answered: dropped"
            );
            return;
        }
        if !matches!(outcome, Outcome::Accepted) {
            self.ledger.accepted.remove(&request.id());
        }
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
