//! Framework events: what the system manager, the watchdog and the modules report happened.
//!
//! Events are appended to an [`EventLog`] shared by the whole system; the logger drains it, tests read
//! it. Every event is stamped with the framework clock.

use crate::lifecycle::Lifecycle;
use crate::time::Time;
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Why the watchdog isolated a module.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "fault", content = "detail", rename_all = "snake_case")]
pub enum Fault {
    /// A state function, command handler or hook panicked, with the panic message.
    Panic(String),
    /// A state function returned an error.
    Error(String),
    /// More consecutive deadline overruns than the configured budget.
    Overrun {
        /// Consecutive overruns seen.
        consecutive: u32,
        /// The budget from the module's configuration.
        budget: u32,
    },
    /// The module stopped answering (its step did not return within the hang timeout).
    Hang {
        /// How long it had been busy, in seconds.
        busy_s: f64,
    },
    /// A remote module's host could not be reached, did not answer in time, or refused it.
    Remote(String),
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Fault::Panic(m) => write!(f, "panicked: {m}"),
            Fault::Error(m) => write!(f, "error: {m}"),
            Fault::Overrun { consecutive, budget } => {
                write!(f, "{consecutive} consecutive overruns, budget {budget}")
            }
            Fault::Hang { busy_s } => write!(f, "hung, busy for {busy_s:.3} s"),
            Fault::Remote(why) => write!(f, "remote: {why}"),
        }
    }
}

/// What happened.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum EventKind {
    /// The system as a whole changed lifecycle state.
    SystemState {
        /// Previous state.
        from: Lifecycle,
        /// New state.
        to: Lifecycle,
    },
    /// A module changed lifecycle state.
    ModuleLifecycle {
        /// The module.
        module: String,
        /// Previous state.
        from: Lifecycle,
        /// New state.
        to: Lifecycle,
    },
    /// A module's own state machine changed state.
    ModuleState {
        /// The module.
        module: String,
        /// Previous state.
        from: String,
        /// New state.
        to: String,
    },
    /// A meta-state got another implementation.
    MetaStateSwitched {
        /// The module.
        module: String,
        /// The meta-state.
        state: String,
        /// The implementation now bound.
        implementation: String,
    },
    /// The watchdog put a module in Safe and isolated it.
    ModuleIsolated {
        /// The module.
        module: String,
        /// Why.
        fault: Fault,
    },
    /// A deadline overrun (counted; isolation follows only past the budget).
    Overrun {
        /// The module.
        module: String,
        /// Execution time, seconds.
        exec_s: f64,
        /// Deadline, seconds.
        deadline_s: f64,
    },
    /// A reservation was taken by emergency override.
    ReservationOverridden {
        /// The device.
        device: String,
        /// New holder.
        by: String,
        /// Previous holder, if any.
        previous: Option<String>,
    },
    /// A message was refused by the framework (unknown command, debug queue inactive, ...).
    MessageRejected {
        /// The recipient that refused it.
        module: String,
        /// The command.
        command: String,
        /// The reason sent back.
        reason: String,
    },
    /// Free text from a module.
    Note {
        /// The module.
        module: String,
        /// The text.
        text: String,
    },
}

/// A stamped event.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Clock time.
    pub stamp: Time,
    /// What happened.
    #[serde(flatten)]
    pub kind: EventKind,
}

/// The system's event log.
#[derive(Clone, Debug, Default)]
pub struct EventLog {
    events: Arc<Mutex<Vec<Event>>>,
}

impl EventLog {
    /// Appends an event.
    pub fn raise(&self, stamp: Time, kind: EventKind) {
        tracing::debug!(?kind, %stamp, "framework event");
        self.events.lock().push(Event { stamp, kind });
    }
    /// All events so far, without removing them.
    pub fn snapshot(&self) -> Vec<Event> {
        self.events.lock().clone()
    }
    /// The events from index `from` on (a reader keeps its own position), and the count so far.
    pub fn since(&self, from: usize) -> (Vec<Event>, usize) {
        let e = self.events.lock();
        (e.get(from..).map(<[Event]>::to_vec).unwrap_or_default(), e.len())
    }
    /// Removes and returns the events so far.
    pub fn drain(&self) -> Vec<Event> {
        std::mem::take(&mut *self.events.lock())
    }
}
