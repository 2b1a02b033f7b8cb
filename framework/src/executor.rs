//! The scheduler's two executors, running the same module code (seed 000, 6.3; seed 004,
//! "Periodic_Thread").
//!
//! - [`LockstepExecutor`]: simulated time, one thread, deterministic. Each [`LockstepExecutor::tick`]
//!   advances the [`SimClock`] by the base period, then runs the modules that are due in a fixed
//!   order: by kind (sensor, resource, coordination, actuator, external), then registration order.
//!   A periodic module is due when the time is a multiple of its period; an aperiodic module when
//!   messages wait for it. Emergency messages are handled at the next tick by every module, due or
//!   not. Overruns compare the simulated cost a module declares ([`crate::Ctx::charge`]) with its
//!   deadline, so they are deterministic too; wall-clock execution time is measured for statistics.
//! - [`RealtimeExecutor`]: wall-clock time, one thread per module (periodic ones sleep until their
//!   next release, waking early for emergency messages; aperiodic ones wait for messages), skipped
//!   cycles counted when a module is late by whole periods, overruns measured on the wall clock, and a
//!   watchdog thread that isolates a module whose step stays busy past its hang timeout.

use crate::clock::{Clock, ClockDriver, SimClock, WallClock};
use crate::config::Schedule;
use crate::lifecycle::Lifecycle;
use crate::message::{AckStatus, MessageId, ModuleId};
use crate::module::{OverrunBasis, Runner, StepMode};
use crate::system::{Core, Endpoint, ModuleReport, StartupError, SystemBuilder, SystemError, SystemManager};
use crate::time::{Duration, Time};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;

/// What both executors offer to whoever drives a system (runner, console, tests).
pub trait Executor {
    /// The shared core (blackboard, post office, events, status).
    fn core(&self) -> &Arc<Core>;
    /// The system's lifecycle state.
    fn system_state(&self) -> Lifecycle;
    /// Moves the whole system one legal step (e.g. Standby -> Hold).
    fn transition(&mut self, to: Lifecycle) -> Result<(), SystemError>;
    /// Moves one module (e.g. Safe -> Standby after analysis).
    fn module_transition(&mut self, module: &str, to: Lifecycle) -> Result<(), SystemError>;
    /// Lets time pass: simulated time under lockstep, wall time under the real-time executor.
    fn advance(&mut self, d: Duration);

    /// Walks the system through legal steps to `to` (e.g. Config -> Standby -> Hold -> Run).
    fn walk_to(&mut self, to: Lifecycle) -> Result<(), SystemError> {
        let from = self.system_state();
        let path = from.path_to(to).ok_or_else(|| {
            SystemError::Transition(crate::lifecycle::TransitionError {
                from,
                to,
                reason: "no legal path".to_string(),
            })
        })?;
        for s in path {
            self.transition(s)?;
        }
        Ok(())
    }
    /// An endpoint registered on the builder, to send commands from.
    fn endpoint(&self, name: &str) -> Result<Endpoint, SystemError> {
        Endpoint::new(self.core().clone(), name)
    }
    /// Snapshots of every module.
    fn reports(&self) -> Vec<ModuleReport> {
        crate::system::module_reports(self.core())
    }
    /// Current time of the executor's clock.
    fn now(&self) -> Time {
        self.core().now()
    }
}

/// Called by the watchdog thread when a module's step has been busy past its hang timeout: the
/// module's name and how long it had been busy. The real-time executor has isolated it by then.
/// Under lockstep nothing in the system changes (the outcome of a simulated run never depends on
/// wall-clock speed), but a module that never returns blocks the simulation, so a runner uses this
/// to finalize its logs and exit with an error naming the module.
pub type HangHandler = Arc<dyn Fn(&str, Duration) + Send + Sync>;

/// Deterministic executor on simulated time.
pub struct LockstepExecutor {
    core: Arc<Core>,
    driver: ClockDriver,
    base: Duration,
    runners: Vec<Box<dyn Runner>>,
    manager: SystemManager,
    watchdog: Watchdog,
}

impl LockstepExecutor {
    /// Checks the system, builds it on a simulated clock with base period `base`, and moves it to
    /// Config. Every module period must be a multiple of `base`.
    pub fn new(builder: SystemBuilder, base: Duration) -> Result<Self, StartupError> {
        if base.is_zero_or_negative() {
            return Err(StartupError { problems: vec![format!("base period must be positive, got {base}")] });
        }
        let (clock, driver) = SimClock::new();
        let a = builder.assemble(Arc::new(clock), Some(base))?;
        let mut runners = a.runners;
        runners.sort_by_key(|r| r.info().kind); // stable: registration order within a kind
        let watchdog = Watchdog::start(a.core.clone(), &runners, WatchdogMode::Report);
        let mut ex = LockstepExecutor { core: a.core, driver, base, runners, manager: a.manager, watchdog };
        ex.transition(Lifecycle::Config).map_err(|e| StartupError { problems: vec![e.to_string()] })?;
        Ok(ex)
    }

    /// Sets the handler called when the watchdog isolates a hung module (see [`HangHandler`]).
    pub fn on_hang(&mut self, handler: HangHandler) {
        *self.watchdog.handler.lock() = Some(handler);
    }

    /// The base period.
    pub fn base_period(&self) -> Duration {
        self.base
    }

    /// Module names in execution order.
    pub fn execution_order(&self) -> Vec<String> {
        self.runners.iter().map(|r| r.info().name.clone()).collect()
    }

    /// Advances one base period and runs every module that is due. Returns the new time.
    pub fn tick(&mut self) -> Time {
        let t = self.driver.advance_by(self.base);
        let core = &*self.core;
        for r in &mut self.runners {
            let inbox = core.post.inbox(r.info().id);
            let due = match r.schedule() {
                Schedule::Periodic(p) => t.as_nanos() % p.as_nanos() == 0,
                Schedule::Aperiodic => !inbox.is_empty(),
            };
            if due {
                r.step(core, t, StepMode::Cycle, OverrunBasis::Charged);
            } else if inbox.emergencies() > 0 {
                r.step(core, t, StepMode::EmergencyOnly, OverrunBasis::Charged);
            }
        }
        t
    }

    /// Runs ticks until at least `d` of simulated time has passed.
    pub fn run_for(&mut self, d: Duration) -> Time {
        let end = self.now() + d;
        self.run_until(end)
    }

    /// Runs ticks until the clock reaches `t`.
    pub fn run_until(&mut self, t: Time) -> Time {
        while self.now() < t {
            self.tick();
        }
        self.now()
    }

    /// Handles waiting emergency messages of every module now, without advancing time.
    pub fn process_emergencies(&mut self) {
        let now = self.now();
        let core = &*self.core;
        for r in &mut self.runners {
            if core.post.inbox(r.info().id).emergencies() > 0 {
                r.step(core, now, StepMode::EmergencyOnly, OverrunBasis::Charged);
            }
        }
    }

    fn module_ack(&mut self, id: MessageId) -> Option<AckStatus> {
        self.process_emergencies();
        self.manager.ack(id)
    }
}

impl Executor for LockstepExecutor {
    fn core(&self) -> &Arc<Core> {
        &self.core
    }
    fn system_state(&self) -> Lifecycle {
        self.manager.state()
    }
    fn transition(&mut self, to: Lifecycle) -> Result<(), SystemError> {
        let sent = self.manager.begin(to)?;
        self.process_emergencies();
        self.manager.finish(to, &sent)
    }
    fn module_transition(&mut self, module: &str, to: Lifecycle) -> Result<(), SystemError> {
        if !self.core.modules().iter().any(|m| m.name == module) {
            return Err(SystemError::UnknownModule(module.to_string()));
        }
        let id = self.manager.send_lifecycle(module, to)?;
        match self.module_ack(id) {
            Some(AckStatus::Completed(_)) => Ok(()),
            Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                Err(SystemError::Refused { to, refusals: vec![r] })
            }
            _ => Err(SystemError::Timeout(module.to_string())),
        }
    }
    fn advance(&mut self, d: Duration) {
        self.run_for(d);
    }
}

/// Executor on the wall clock, one thread per module.
pub struct RealtimeExecutor {
    core: Arc<Core>,
    manager: SystemManager,
    threads: Vec<(ModuleId, JoinHandle<Box<dyn Runner>>)>,
    stop: Arc<AtomicBool>,
    watchdog: Watchdog,
    ack_timeout: std::time::Duration,
}

impl RealtimeExecutor {
    /// Checks the system, moves it to Config, and starts one thread per module and the watchdog.
    pub fn new(builder: SystemBuilder) -> Result<Self, StartupError> {
        let wall = WallClock::new();
        let a = builder.assemble(Arc::new(wall.clone()), None)?;
        let core = a.core;
        let mut manager = a.manager;
        let mut runners = a.runners;
        // Startup -> Config before any thread exists, on this thread.
        let sent =
            manager.begin(Lifecycle::Config).map_err(|e| StartupError { problems: vec![e.to_string()] })?;
        for r in &mut runners {
            r.step(&core, core.now(), StepMode::EmergencyOnly, OverrunBasis::Wall);
        }
        manager
            .finish(Lifecycle::Config, &sent)
            .map_err(|e| StartupError { problems: vec![e.to_string()] })?;

        let stop = Arc::new(AtomicBool::new(false));
        let watchdog = Watchdog::start(core.clone(), &runners, WatchdogMode::Isolate);
        let mut threads = Vec::new();
        for runner in runners {
            let (core, stop, wall) = (core.clone(), stop.clone(), wall.clone());
            let id = runner.info().id;
            let name = runner.info().name.clone();
            let h = std::thread::Builder::new()
                .name(name)
                .spawn(move || module_thread(runner, &core, &stop, &wall))
                .expect("spawn module thread");
            threads.push((id, h));
        }
        Ok(RealtimeExecutor {
            core,
            manager,
            threads,
            stop,
            watchdog,
            ack_timeout: std::time::Duration::from_secs(5),
        })
    }

    /// Stops every thread and returns the final module reports. Threads of hung modules are left
    /// behind (they cannot be joined); everything else is joined.
    pub fn stop(mut self) -> Vec<ModuleReport> {
        self.shutdown_threads();
        crate::system::module_reports(&self.core)
    }

    fn shutdown_threads(&mut self) {
        self.stop.store(true, Ordering::Release);
        for m in self.core.modules() {
            self.core.post.inbox(m.id).wake();
        }
        let hung = self.watchdog.stop();
        for (id, h) in self.threads.drain(..) {
            if !hung.contains(&id) {
                let _ = h.join();
            }
        }
    }
}

impl Drop for RealtimeExecutor {
    fn drop(&mut self) {
        if !self.threads.is_empty() {
            self.shutdown_threads();
        }
    }
}

#[allow(clippy::disallowed_methods)] // the real-time executor sleeps on the OS clock
fn module_thread(
    mut runner: Box<dyn Runner>,
    core: &Core,
    stop: &AtomicBool,
    wall: &WallClock,
) -> Box<dyn Runner> {
    let id = runner.info().id;
    let inbox = core.post.inbox(id);
    // The schedule is read again after every step: a configuration reloaded in Config (period,
    // periodic or not) takes effect from the next release.
    let mut next: Option<Time> = None;
    while !stop.load(Ordering::Acquire) {
        match runner.schedule() {
            Schedule::Periodic(period) => {
                let release = *next.get_or_insert_with(|| wall.now() + period);
                // Sleep until the release, handling emergency messages as they come.
                loop {
                    let now = wall.now();
                    if now >= release || stop.load(Ordering::Acquire) {
                        break;
                    }
                    if inbox.wait_emergency_until(wall.instant_at(release)) {
                        runner.step(core, wall.now(), StepMode::EmergencyOnly, OverrunBasis::Wall);
                    }
                }
                if stop.load(Ordering::Acquire) {
                    break;
                }
                let now = wall.now();
                let mut release = release;
                let late = now - release;
                if late >= period {
                    let skipped = late.as_nanos() / period.as_nanos();
                    runner.add_skipped(skipped as u64);
                    release += period * skipped;
                }
                runner.step(core, now, StepMode::Cycle, OverrunBasis::Wall);
                next = Some(match runner.schedule() {
                    Schedule::Periodic(p) => release + p,
                    Schedule::Aperiodic => release,
                });
            }
            Schedule::Aperiodic => {
                next = None;
                let wake_by = std::time::Instant::now() + std::time::Duration::from_millis(50);
                if inbox.wait_until(wake_by) && !stop.load(Ordering::Acquire) {
                    runner.step(core, wall.now(), StepMode::Cycle, OverrunBasis::Wall);
                }
            }
        }
    }
    runner
}

/// What the watchdog does with a module whose step stays busy past its hang timeout.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
enum WatchdogMode {
    /// Real-time executor: isolates it in Safe (the other threads go on) and calls the handler.
    Isolate,
    /// Lockstep executor: calls the handler (a runner ends the run as an error) and changes nothing
    /// in the system. Wall-clock speed must never decide a simulated outcome: a step that is merely
    /// slow on a loaded machine, once it returns, goes on exactly as on a fast one.
    Report,
}

/// The watchdog thread: watches every module's step against its hang timeout (as currently
/// configured: a reloaded configuration's timeout takes effect).
struct Watchdog {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<Vec<ModuleId>>>,
    handler: Arc<parking_lot::Mutex<Option<HangHandler>>>,
}

impl Watchdog {
    fn start(core: Arc<Core>, runners: &[Box<dyn Runner>], mode: WatchdogMode) -> Self {
        let modules: Vec<_> = runners.iter().map(|r| r.info().clone()).collect();
        let stop = Arc::new(AtomicBool::new(false));
        let handler: Arc<parking_lot::Mutex<Option<HangHandler>>> = Arc::default();
        let thread = {
            let (stop, handler) = (stop.clone(), handler.clone());
            std::thread::Builder::new()
                .name("watchdog".into())
                .spawn(move || watchdog_thread(&core, &stop, &modules, &handler, mode))
                .expect("spawn watchdog thread")
        };
        Watchdog { stop, thread: Some(thread), handler }
    }

    /// Stops the thread; returns the modules it found hung.
    fn stop(&mut self) -> Vec<ModuleId> {
        self.stop.store(true, Ordering::Release);
        self.thread.take().map(|t| t.join().unwrap_or_default()).unwrap_or_default()
    }
}

impl Drop for Watchdog {
    fn drop(&mut self) {
        self.stop();
    }
}

fn watchdog_thread(
    core: &Core,
    stop: &AtomicBool,
    modules: &[crate::module::ModuleInfo],
    handler: &parking_lot::Mutex<Option<HangHandler>>,
    mode: WatchdogMode,
) -> Vec<ModuleId> {
    let mut hung = Vec::new();
    // The busy episode already reported, per module (Report mode reports each episode once).
    let mut reported: std::collections::HashMap<ModuleId, i64> = Default::default();
    while !stop.load(Ordering::Acquire) {
        let poll = modules
            .iter()
            .map(|m| core.status(m.id).hang_timeout() / 4)
            .min()
            .unwrap_or(Duration::from_millis(50))
            .clamp(Duration::from_millis(1), Duration::from_millis(50));
        std::thread::sleep(poll.to_std());
        let now = core.wall_now();
        for info in modules {
            let status = core.status(info.id);
            let (since, timeout) = (status.busy_since_ns(), status.hang_timeout());
            if since < 0 || status.is_isolated() || now - since <= timeout.as_nanos() {
                continue;
            }
            if reported.get(&info.id) == Some(&since) {
                continue;
            }
            reported.insert(info.id, since);
            let busy = Duration::from_nanos(now - since);
            match mode {
                WatchdogMode::Isolate => {
                    let fault = crate::events::Fault::Hang { busy_s: busy.as_secs_f64() };
                    crate::runtime::isolate(core, info, status.lifecycle(), fault, core.now());
                    hung.push(info.id);
                }
                WatchdogMode::Report => {
                    tracing::warn!(module = %info.name, %busy, "module busy past its hang timeout (lockstep: waiting)");
                }
            }
            if let Some(h) = handler.lock().clone() {
                h(&info.name, busy);
            }
        }
    }
    hung
}

impl Executor for RealtimeExecutor {
    fn core(&self) -> &Arc<Core> {
        &self.core
    }
    fn system_state(&self) -> Lifecycle {
        self.manager.state()
    }
    fn transition(&mut self, to: Lifecycle) -> Result<(), SystemError> {
        let sent = self.manager.begin(to)?;
        for (_, id) in &sent {
            self.manager.endpoint().wait_final(*id, self.ack_timeout);
        }
        self.manager.finish(to, &sent)
    }
    fn module_transition(&mut self, module: &str, to: Lifecycle) -> Result<(), SystemError> {
        if !self.core.modules().iter().any(|m| m.name == module) {
            return Err(SystemError::UnknownModule(module.to_string()));
        }
        let id = self.manager.send_lifecycle(module, to)?;
        match self.manager.endpoint().wait_final(id, self.ack_timeout) {
            Some(AckStatus::Completed(_)) => Ok(()),
            Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                Err(SystemError::Refused { to, refusals: vec![r] })
            }
            _ => Err(SystemError::Timeout(module.to_string())),
        }
    }
    fn advance(&mut self, d: Duration) {
        std::thread::sleep(d.to_std());
    }
}
