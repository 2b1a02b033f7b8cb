//! Faults make the robot safe: the safing hook, accepted commands answered Failed, commands refused
//! outside the states that take them, and reloaded configurations taking effect in both executors.

mod common;

use common::*;
use framework::prelude::*;
use framework::{AckStatus, Executor, LockstepExecutor, RealtimeExecutor, SystemBuilder};
use parking_lot::Mutex;
use std::sync::Arc;

/// A stand-in for an actuator: the speed last commanded to it.
type Device = Arc<Mutex<f64>>;

/// An actuator module: `go {speed}` is accepted and drives the device every cycle until `arrive`
/// finishes it; its safing hook stops the device.
#[derive(Default)]
struct Driver {
    device: Device,
    speed: f64,
    pending: Option<framework::module::Request>,
    safings: Arc<Mutex<u32>>,
}

#[derive(serde::Deserialize)]
struct Go {
    speed: f64,
}

impl Module for Driver {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Actuator;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.context_switchable();
        d.state("active", |m, _ctx| {
            *m.device.lock() = m.speed;
            Ok(())
        });
        d.command("go", |m, ctx, a: Go| {
            m.speed = a.speed;
            m.pending = ctx.request();
            Outcome::Accepted
        });
        d.command("arrive", |m, ctx, _: ()| {
            m.speed = 0.0;
            match m.pending.take() {
                Some(r) => ctx.reply(&r, Outcome::done()),
                None => return Outcome::reject("nothing under way"),
            }
            Outcome::done()
        });
    }
    fn on_safe(&mut self, _ctx: &mut Ctx<'_>) {
        self.speed = 0.0;
        *self.device.lock() = 0.0;
        *self.safings.lock() += 1;
    }
}

fn system(driver: Driver, context: &str) -> LockstepExecutor {
    let mut b = SystemBuilder::new();
    b.trace_messages(true);
    b.add_inline("driver", driver, &format!("[framework]\nperiod_s = 0.01\n{context}"));
    b.endpoint("ground");
    LockstepExecutor::new(b, Duration::from_millis(10)).unwrap()
}

const DEBUG: &str = "context = { mode = \"dry-run\", purpose = \"debug\" }\n";

#[test]
fn a_module_that_panics_mid_drive_runs_its_safing_hook_and_fails_what_it_had_accepted() {
    let device = Device::default();
    let safings = Arc::new(Mutex::new(0));
    let driver = Driver { device: device.clone(), safings: safings.clone(), ..Default::default() };
    let mut ex = system(driver, DEBUG);
    ex.walk_to(Lifecycle::Run).unwrap();
    let g = ex.endpoint("ground").unwrap();
    let go = g.send(Command::new("driver", "go").json(serde_json::json!({"speed": 0.3}))).unwrap();
    ex.run_for(Duration::from_millis(50));
    assert_eq!(g.status(go), Some(AckStatus::Accepted));
    assert_eq!(*device.lock(), 0.3, "driving");
    let crash = Command::new("driver", "inject_fault").json(serde_json::json!({"kind": "panic"}));
    g.send(crash.on(Queue::Debug)).unwrap();
    ex.run_for(Duration::from_millis(30));
    let r = &ex.reports()[0];
    assert!(r.isolated && r.lifecycle == Lifecycle::Safe, "{r:?}");
    assert_eq!(*device.lock(), 0.0, "the safing hook stopped the device");
    assert_eq!(*safings.lock(), 1);
    let Some(AckStatus::Failed(why)) = g.status(go) else { panic!("{:?}", g.status(go)) };
    assert!(why.contains("went to Safe") && why.contains("panicked") && why.contains("'go'"), "{why}");
    // Its commands are refused from now on; framework commands still answer.
    let again = g.send(Command::new("driver", "go").json(serde_json::json!({"speed": 0.3}))).unwrap();
    let ping = g.send(Command::new("driver", "ping")).unwrap();
    ex.run_for(Duration::from_millis(20));
    assert!(matches!(g.status(again), Some(AckStatus::Rejected(_))));
    assert!(matches!(g.status(ping), Some(AckStatus::Completed(_))));
    // Restored, the module still holds the request it had accepted; its late answer is dropped:
    // the command stays answered once, Failed.
    for to in [Lifecycle::Standby, Lifecycle::Hold, Lifecycle::Run] {
        ex.module_transition("driver", to).unwrap();
    }
    let arrive = g.send(Command::new("driver", "arrive")).unwrap();
    ex.run_for(Duration::from_millis(20));
    assert!(matches!(g.status(arrive), Some(AckStatus::Completed(_))));
    assert!(matches!(g.status(go), Some(AckStatus::Failed(_))), "{:?}", g.status(go));
    let answers = ex
        .core()
        .post
        .take_trace()
        .into_iter()
        .filter(|m| matches!(&m.body, framework::message::Body::Ack(a) if a.of == go && a.status.is_final()))
        .count();
    assert_eq!(answers, 1, "one final answer to 'go'");
}

#[test]
fn a_commanded_move_to_safe_runs_the_hook_once_and_a_finished_command_is_not_failed_later() {
    let device = Device::default();
    let safings = Arc::new(Mutex::new(0));
    let driver = Driver { device: device.clone(), safings: safings.clone(), ..Default::default() };
    let mut ex = system(driver, "");
    ex.walk_to(Lifecycle::Run).unwrap();
    let g = ex.endpoint("ground").unwrap();
    let first = g.send(Command::new("driver", "go").json(serde_json::json!({"speed": 0.1}))).unwrap();
    ex.run_for(Duration::from_millis(20));
    g.send(Command::new("driver", "arrive")).unwrap();
    ex.run_for(Duration::from_millis(20));
    assert!(matches!(g.status(first), Some(AckStatus::Completed(_))));
    let second = g.send(Command::new("driver", "go").json(serde_json::json!({"speed": 0.2}))).unwrap();
    ex.run_for(Duration::from_millis(20));
    assert_eq!(*device.lock(), 0.2);
    ex.module_transition("driver", Lifecycle::Safe).unwrap();
    assert_eq!(*device.lock(), 0.0);
    assert_eq!(*safings.lock(), 1);
    assert!(matches!(g.status(first), Some(AckStatus::Completed(_))), "finished commands stay finished");
    let Some(AckStatus::Failed(why)) = g.status(second) else { panic!("{:?}", g.status(second)) };
    assert!(why.contains("commanded"), "{why}");
}

#[test]
fn module_commands_are_refused_in_standby_and_shutdown_and_framework_commands_are_not() {
    let mut ex = system(Driver::default(), "");
    let g = ex.endpoint("ground").unwrap();
    for state in [Lifecycle::Standby, Lifecycle::Shutdown] {
        ex.walk_to(state).unwrap();
        let go = g.send(Command::new("driver", "go").json(serde_json::json!({"speed": 0.1}))).unwrap();
        let ping = g.send(Command::new("driver", "ping")).unwrap();
        ex.run_for(Duration::from_millis(20));
        let Some(AckStatus::Rejected(why)) = g.status(go) else { panic!("{state}: {:?}", g.status(go)) };
        assert!(why.contains(&state.to_string()), "{why}");
        assert!(matches!(g.status(ping), Some(AckStatus::Completed(_))), "{state}");
    }
}

fn count(core: &framework::system::Core) -> u64 {
    read::<u64>(core, "c/count").unwrap_or(0)
}

#[test]
fn a_period_reloaded_in_config_takes_effect_in_the_realtime_executor() {
    let mut b = SystemBuilder::new();
    b.add_inline("c", Counter::default(), &periodic(0.1));
    b.endpoint("ground");
    let mut ex = RealtimeExecutor::new(b).unwrap();
    let g = ex.endpoint("ground").unwrap();
    let set = g
        .send(
            Command::new("c", "set_param")
                .json(serde_json::json!({"key": "framework.period_s", "value": 0.01})),
        )
        .unwrap();
    assert!(
        matches!(g.wait_final(set, std::time::Duration::from_secs(5)), Some(AckStatus::Completed(_))),
        "{:?}",
        g.status(set)
    );
    ex.walk_to(Lifecycle::Run).unwrap();
    let core = ex.core().clone();
    let start = count(&core);
    std::thread::sleep(std::time::Duration::from_millis(1000));
    let cycles = count(&core) - start;
    ex.stop();
    // At the configured 0.1 s it would count about 10; at the reloaded 0.01 s about 100.
    assert!(cycles > 30, "{cycles} cycles in 1 s");
}

/// A module whose `slow` command makes its next cycle take 300 ms of wall time.
#[derive(Default)]
struct Slow {
    slow: bool,
}

impl Module for Slow {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.state("work", |m, _ctx| {
            if std::mem::take(&mut m.slow) {
                std::thread::sleep(std::time::Duration::from_millis(300));
            }
            Ok(())
        });
        d.command("slow", |m, _ctx, _: ()| {
            m.slow = true;
            Outcome::done()
        });
    }
}

#[test]
fn a_hang_timeout_reloaded_in_config_takes_effect_in_the_watchdog() {
    let mut b = SystemBuilder::new();
    b.add_inline("s", Slow::default(), "[framework]\nperiod_s = 0.01\nhang_timeout_s = 30.0\n");
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(10)).unwrap();
    let reported = Arc::new(Mutex::new(Vec::new()));
    let r2 = reported.clone();
    ex.on_hang(Arc::new(move |name: &str, _busy: Duration| r2.lock().push(name.to_string())));
    let g = ex.endpoint("ground").unwrap();
    let slow_run = |ex: &mut LockstepExecutor| {
        ex.walk_to(Lifecycle::Run).unwrap();
        g.send(Command::new("s", "slow")).unwrap();
        ex.run_for(Duration::from_millis(30));
    };
    slow_run(&mut ex);
    assert!(reported.lock().is_empty(), "300 ms is well inside 30 s");
    ex.walk_to(Lifecycle::Config).unwrap();
    let set = g
        .send(
            Command::new("s", "set_param")
                .json(serde_json::json!({"key": "framework.hang_timeout_s", "value": 0.05})),
        )
        .unwrap();
    ex.run_for(Duration::from_millis(10));
    assert!(matches!(g.status(set), Some(AckStatus::Completed(_))), "{:?}", g.status(set));
    slow_run(&mut ex);
    assert_eq!(*reported.lock(), vec!["s".to_string()], "reported against the reloaded 0.05 s");
}
