//! The runtime core shared by the modules of one system, whichever executor runs them and wherever
//! they run: clock, post office, blackboard, resources, events, and each participant's status
//! (lifecycle, isolation, busy time, statistics). Modules and executors see each other only through
//! it, so that a remote proxy can stand in for a module.

use crate::blackboard::BlackBoard;
use crate::clock::{Clock, WallClock};
use crate::events::{EventKind, EventLog};
use crate::exec_context::ExecContext;
use crate::lifecycle::Lifecycle;
use crate::message::{ModuleId, PostOffice};
use crate::module::ModuleInfo;
use crate::resources::Resources;
use crate::stats::TaskStats;
use crate::time::Time;
use parking_lot::Mutex;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU8, Ordering};

/// Shared, thread-safe status of one participant, readable from any thread.
#[derive(Debug, Default)]
pub struct ModuleStatus {
    lifecycle: AtomicU8,
    isolated: AtomicBool,
    busy_since_ns: AtomicI64,
    hang_timeout_ns: AtomicI64,
    stats: Mutex<TaskStats>,
    state: Mutex<String>,
    context: Mutex<ExecContext>,
    meta: Mutex<std::collections::BTreeMap<String, String>>,
}

impl ModuleStatus {
    pub(crate) fn new() -> Self {
        let s = ModuleStatus::default();
        s.busy_since_ns.store(-1, Ordering::Relaxed);
        s
    }
    /// Lifecycle state.
    pub fn lifecycle(&self) -> Lifecycle {
        Lifecycle::ALL[self.lifecycle.load(Ordering::Acquire) as usize]
    }
    pub(crate) fn set_lifecycle(&self, l: Lifecycle) {
        let i = Lifecycle::ALL.iter().position(|x| *x == l).unwrap_or(0);
        self.lifecycle.store(i as u8, Ordering::Release);
    }
    /// True when the watchdog isolated the module.
    pub fn is_isolated(&self) -> bool {
        self.isolated.load(Ordering::Acquire)
    }
    pub(crate) fn set_isolated(&self, v: bool) {
        self.isolated.store(v, Ordering::Release);
    }
    /// Wall time (ns on the system's wall clock) at which the current step began, or -1 when idle.
    pub fn busy_since_ns(&self) -> i64 {
        self.busy_since_ns.load(Ordering::Acquire)
    }
    pub(crate) fn set_busy_since(&self, ns: i64) {
        self.busy_since_ns.store(ns, Ordering::Release);
    }
    /// The hang timeout of the module's current configuration (a reloaded one takes effect).
    pub fn hang_timeout(&self) -> crate::time::Duration {
        crate::time::Duration::from_nanos(self.hang_timeout_ns.load(Ordering::Acquire))
    }
    pub(crate) fn set_hang_timeout(&self, d: crate::time::Duration) {
        self.hang_timeout_ns.store(d.as_nanos(), Ordering::Release);
    }
    /// Statistics so far.
    pub fn stats(&self) -> TaskStats {
        self.stats.lock().clone()
    }
    pub(crate) fn store_stats(&self, s: &TaskStats) {
        self.stats.lock().clone_from(s);
    }
    /// Current state of the module's own machine.
    pub fn state(&self) -> String {
        self.state.lock().clone()
    }
    pub(crate) fn set_state(&self, s: &str) {
        let mut g = self.state.lock();
        g.clear();
        g.push_str(s);
    }
    /// The active implementation of each meta-state.
    pub fn meta_states(&self) -> std::collections::BTreeMap<String, String> {
        self.meta.lock().clone()
    }
    pub(crate) fn set_meta(&self, state: &str, implementation: &str) {
        self.meta.lock().insert(state.to_string(), implementation.to_string());
    }
    /// Current execution context.
    pub fn context(&self) -> ExecContext {
        *self.context.lock()
    }
    pub(crate) fn set_context(&self, c: ExecContext) {
        *self.context.lock() = c;
    }
}

/// Everything shared by the modules of one system, whichever executor runs them.
pub struct Core {
    /// The executor's clock.
    pub clock: Arc<dyn Clock>,
    /// The post office (inboxes of every participant).
    pub post: PostOffice,
    /// The blackboard.
    pub board: BlackBoard,
    /// Shared devices and their reservations.
    pub resources: Resources,
    /// The event log.
    pub events: EventLog,
    pub(crate) status: Vec<ModuleStatus>,
    pub(crate) wall: WallClock,
    pub(crate) modules: Vec<ModuleInfo>,
}

impl Core {
    /// Status of a participant.
    pub fn status(&self, id: ModuleId) -> &ModuleStatus {
        &self.status[id.0 as usize]
    }
    /// Registered modules (not endpoints), in registration order.
    pub fn modules(&self) -> &[ModuleInfo] {
        &self.modules
    }
    /// Nanoseconds on the system's wall clock (for hang detection only).
    pub(crate) fn wall_now(&self) -> i64 {
        self.wall.now().as_nanos()
    }
    /// Current time of the executor's clock.
    pub fn now(&self) -> Time {
        self.clock.now()
    }
}

/// Puts a module in Safe and isolates it: its state functions stop, its messages are refused, its
/// reservations are freed, and an event says why. Used by the module's own cell (panic, error,
/// overrun) and by the watchdog thread (hang).
pub(crate) fn isolate(
    core: &Core,
    info: &ModuleInfo,
    from: Lifecycle,
    fault: crate::events::Fault,
    now: Time,
) {
    let status = core.status(info.id);
    status.set_isolated(true);
    status.set_lifecycle(Lifecycle::Safe);
    core.resources.release_all_of(info.id);
    tracing::warn!(module = %info.name, ?fault, "watchdog isolated module");
    core.events.raise(now, EventKind::ModuleIsolated { module: info.name.clone(), fault });
    if from != Lifecycle::Safe {
        core.events
            .raise(now, EventKind::ModuleLifecycle { module: info.name.clone(), from, to: Lifecycle::Safe });
    }
}
