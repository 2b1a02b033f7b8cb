//! Registration: the module's own state machine and what [`super::Module::declare`] binds.

use super::*;
use crate::blackboard::{BoardData, Reader, Writer};
use crate::lifecycle::Lifecycle;
use crate::message::{ModuleId, Outcome};
use serde::de::DeserializeOwned;
use std::collections::{BTreeMap, HashMap, HashSet};

pub(super) struct StateEntry<M> {
    pub(super) name: String,
    /// Implementations: one for a plain state, several for a meta-state.
    pub(super) impls: Vec<(String, StateFn<M>)>,
    pub(super) active: usize,
    pub(super) meta: bool,
}

/// The module's own state machine: states, their functions, and the allowed transitions.
pub(super) struct Fsm<M> {
    pub(super) states: Vec<StateEntry<M>>,
    pub(super) index: HashMap<String, usize>,
    pub(super) transitions: HashSet<(usize, usize)>,
    pub(super) current: usize,
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
    pub(super) id: ModuleId,
    pub(super) name: &'a str,
    pub(super) board: &'a crate::blackboard::BlackBoard,
    pub(super) fsm: &'a mut Fsm<M>,
    pub(super) lifecycle_fns: &'a mut HashMap<Lifecycle, StateFn<M>>,
    pub(super) commands: &'a mut BTreeMap<String, Handler<M>>,
    pub(super) on_ack: &'a mut Option<AckFn<M>>,
    pub(super) context_switchable: &'a mut bool,
    pub(super) decl: &'a mut Declarations,
    pub(super) pending_transitions: Vec<(String, String)>,
    pub(super) initial: Option<String>,
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

    pub(super) fn finish(mut self) {
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
