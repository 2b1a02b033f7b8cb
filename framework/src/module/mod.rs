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

mod cell;
mod ctx;
mod declare;
mod framework_commands;

pub(crate) use cell::{Cell, OverrunBasis, Runner, StepMode};
pub use cell::{InjectedFault, panic_text};
pub use ctx::{Ctx, FsmError, Request};
pub use declare::{Declarations, Declare};

use crate::lifecycle::Lifecycle;
use crate::message::{Ack, ModuleId, Outcome};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

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
    /// The safing hook: called whenever the module enters Safe, commanded or isolated by the watchdog
    /// (a panic, an error, overruns; after a hang, once its step returns), before its reservations
    /// are freed. An actuator module stops what it drives here. Commands it had accepted are
    /// answered Failed by the framework afterwards.
    fn on_safe(&mut self, _ctx: &mut Ctx<'_>) {}
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
