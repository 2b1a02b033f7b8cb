//! Behaviour of the framework core, module by module, on the lockstep executor.

mod common;

use common::*;
use framework::events::{EventKind, Fault};
use framework::prelude::*;
use framework::system::SystemError;
use framework::{AckStatus, Executor, LockstepExecutor, SystemBuilder};

const MS: Duration = Duration::from_millis(1);

fn running(b: SystemBuilder) -> LockstepExecutor {
    let mut ex = LockstepExecutor::new(b, MS).expect("start-up");
    ex.walk_to(Lifecycle::Run).expect("to Run");
    ex
}

#[test]
fn ten_and_fifty_hertz_modules_run_exactly_ten_and_fifty_cycles_per_second() {
    let mut b = SystemBuilder::new();
    b.add_inline("slow", Counter::default(), &periodic(0.1));
    b.add_inline("fast", Counter::default(), &periodic(0.02));
    let mut ex = running(b);
    ex.run_for(Duration::from_secs(1));
    assert_eq!(read::<u64>(ex.core(), "slow/count"), Some(10));
    assert_eq!(read::<u64>(ex.core(), "fast/count"), Some(50));
    let r = ex.reports();
    assert_eq!(r.iter().find(|m| m.name == "slow").unwrap().stats.cycles, 10);
    assert_eq!(r.iter().find(|m| m.name == "fast").unwrap().stats.cycles, 50);
    assert_eq!(ex.now(), Time::from_secs_f64(1.0));
}

#[test]
fn invalid_lifecycle_transitions_are_rejected_with_a_reason() {
    let mut b = SystemBuilder::new();
    b.add_inline("c", Counter::default(), &periodic(0.1));
    let mut ex = LockstepExecutor::new(b, MS).unwrap();
    assert_eq!(ex.system_state(), Lifecycle::Config);
    let e = ex.transition(Lifecycle::Run).unwrap_err();
    assert!(e.to_string().contains("Config -> Run"), "{e}");
    ex.transition(Lifecycle::Standby).unwrap();
    let e = ex.transition(Lifecycle::Run).unwrap_err();
    assert!(e.to_string().contains("illegal transition Standby -> Run"), "{e}");
    ex.walk_to(Lifecycle::Run).unwrap();
    // Safe from anywhere; left only to Standby or Shutdown.
    ex.transition(Lifecycle::Safe).unwrap();
    let e = ex.transition(Lifecycle::Run).unwrap_err();
    assert!(e.to_string().contains("left only by command"), "{e}");
    ex.transition(Lifecycle::Standby).unwrap();
    ex.walk_to(Lifecycle::Shutdown).unwrap();
    assert!(ex.transition(Lifecycle::Config).is_err());
    let states: Vec<_> = ex
        .core()
        .events
        .snapshot()
        .into_iter()
        .filter_map(|e| match e.kind {
            EventKind::SystemState { to, .. } => Some(to),
            _ => None,
        })
        .collect();
    use Lifecycle::*;
    assert_eq!(states, [Config, Standby, Hold, Run, Safe, Standby, Shutdown]);
}

#[test]
fn state_functions_run_only_in_their_lifecycle_state() {
    let mut b = SystemBuilder::new();
    b.add_inline("c", Counter::default(), &periodic(0.01));
    let mut ex = LockstepExecutor::new(b, MS).unwrap();
    ex.walk_to(Lifecycle::Hold).unwrap();
    ex.run_for(Duration::from_millis(100));
    assert_eq!(read::<u64>(ex.core(), "c/count"), None, "Hold does not run the Run state function");
    ex.transition(Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(100));
    assert_eq!(read::<u64>(ex.core(), "c/count"), Some(10));
    ex.transition(Lifecycle::Hold).unwrap();
    ex.run_for(Duration::from_millis(100));
    assert_eq!(read::<u64>(ex.core(), "c/count"), Some(10));
}

/// A module whose "drive" meta-state has two implementations.
#[derive(Default)]
struct Driver {
    out: Option<Writer<f64>>,
    x: f64,
}

impl Module for Driver {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Actuator;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("driver/x"));
        d.meta_state(
            "drive",
            &[
                ("slow", |m: &mut Driver, ctx: &mut Ctx<'_>| {
                    m.x += 1.0;
                    ctx.write(m.out.as_ref().unwrap(), m.x);
                    Ok(())
                }),
                ("fast", |m: &mut Driver, ctx: &mut Ctx<'_>| {
                    m.x += 10.0;
                    ctx.write(m.out.as_ref().unwrap(), m.x);
                    Ok(())
                }),
            ],
        );
    }
}

#[test]
fn meta_state_swap_changes_a_running_module_without_restart() {
    let mut b = SystemBuilder::new();
    b.add_inline("driver", Driver::default(), &periodic(0.1));
    b.endpoint("ground");
    let mut ex = running(b);
    let ground = ex.endpoint("ground").unwrap();
    ex.run_for(Duration::from_millis(300));
    assert_eq!(read::<f64>(ex.core(), "driver/x"), Some(3.0));
    let id = ground
        .send(
            Command::new("driver", "set_meta")
                .json(serde_json::json!({"state": "drive", "implementation": "fast"})),
        )
        .unwrap();
    ex.run_for(Duration::from_millis(300));
    assert_eq!(ground.status(id), Some(AckStatus::Completed(serde_json::Value::Null)));
    // Message handled before the cycle's state function: three fast cycles.
    assert_eq!(read::<f64>(ex.core(), "driver/x"), Some(33.0));
    assert_eq!(ex.system_state(), Lifecycle::Run);
    let bad = ground
        .send(
            Command::new("driver", "set_meta")
                .json(serde_json::json!({"state": "drive", "implementation": "warp"})),
        )
        .unwrap();
    ex.run_for(Duration::from_millis(100));
    let Some(AckStatus::Rejected(r)) = ground.status(bad) else { panic!() };
    assert!(r.contains("no implementation 'warp'") && r.contains("slow, fast"), "{r}");
}

#[test]
fn emergency_message_overtakes_earlier_nominal_ones() {
    let mut b = SystemBuilder::new();
    b.add_inline("acc", Accumulator::default(), "");
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    g.send(Command::new("acc", "mark").args("nominal-1")).unwrap();
    g.send(Command::new("acc", "mark").args("nominal-2")).unwrap();
    g.send(Command::new("acc", "mark").args("emergency").on(Queue::Emergency)).unwrap();
    ex.tick();
    assert_eq!(read::<Vec<String>>(ex.core(), "acc/log").unwrap(), ["emergency", "nominal-1", "nominal-2"]);
}

#[test]
fn emergency_messages_reach_periodic_modules_between_their_cycles() {
    let mut b = SystemBuilder::new();
    b.add_inline("c", Counter::default(), &periodic(0.1));
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    ex.run_for(Duration::from_millis(150));
    let n = g.send(Command::new("c", "reset")).unwrap();
    let e = g.send(Command::new("c", "ping").on(Queue::Emergency)).unwrap();
    ex.tick(); // t = 151 ms: not a cycle of c
    assert!(g.status(e).unwrap().is_final(), "emergency handled at the next tick");
    assert_eq!(g.status(n), Some(AckStatus::Pending), "nominal waits for the next cycle");
    ex.run_for(Duration::from_millis(50));
    assert!(g.status(n).unwrap().is_final());
}

#[test]
fn debug_commands_are_refused_in_mission_and_accepted_in_debug() {
    let mut b = SystemBuilder::new();
    b.add_inline("mission", Accumulator::default(), "");
    b.add_inline(
        "debug",
        Accumulator::default(),
        "[framework]\ncontext = { mode = \"dry-run\", purpose = \"debug\" }\n",
    );
    b.endpoint("debugger");
    let mut ex = running(b);
    let d = ex.endpoint("debugger").unwrap();
    let a = d.send(Command::new("mission", "debug_note").on(Queue::Debug)).unwrap();
    let c = d.send(Command::new("debug", "debug_note").on(Queue::Debug)).unwrap();
    ex.tick();
    let Some(AckStatus::Rejected(r)) = d.status(a) else { panic!("{:?}", d.status(a)) };
    assert!(r.contains("Mission") && r.contains("debug queue"), "{r}");
    assert_eq!(d.status(c), Some(AckStatus::Completed(serde_json::Value::Null)));
    // The framework's fault injection: debug queue only, then the module crashes at its next cycle
    // and the watchdog isolates it.
    let nominal =
        d.send(Command::new("debug", "inject_fault").json(serde_json::json!({"kind": "panic"}))).unwrap();
    let refused = d
        .send(
            Command::new("mission", "inject_fault")
                .json(serde_json::json!({"kind": "panic"}))
                .on(Queue::Debug),
        )
        .unwrap();
    let crash = d
        .send(
            Command::new("debug", "inject_fault").json(serde_json::json!({"kind": "panic"})).on(Queue::Debug),
        )
        .unwrap();
    ex.tick();
    ex.tick();
    let Some(AckStatus::Rejected(r)) = d.status(nominal) else { panic!("{:?}", d.status(nominal)) };
    assert!(r.contains("only on the debug queue"), "{r}");
    assert!(matches!(d.status(refused), Some(AckStatus::Rejected(_))));
    assert!(matches!(d.status(crash), Some(AckStatus::Completed(_))), "{:?}", d.status(crash));
    let isolated: Vec<_> = ex
        .core()
        .events
        .snapshot()
        .into_iter()
        .filter_map(|e| match e.kind {
            framework::events::EventKind::ModuleIsolated { module, fault } => Some((module, fault)),
            _ => None,
        })
        .collect();
    assert_eq!(isolated.len(), 1, "{isolated:?}");
    assert_eq!(isolated[0].0, "debug");
    assert!(
        matches!(&isolated[0].1, framework::events::Fault::Panic(t) if t.contains("injected")),
        "{isolated:?}"
    );
}

/// A coordinator that sends through a relay and records the acknowledgements it gets.
#[derive(Default)]
struct Coordinator {
    acks: Option<Writer<Vec<String>>>,
    seen: Vec<String>,
    sent: bool,
}

impl Module for Coordinator {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Coordination;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.acks = Some(d.writes("coord/acks"));
        d.sends_to("relay").sends_to("acc");
        d.state("go", |m, ctx| {
            if !m.sent {
                m.sent = true;
                ctx.send(Command::new("acc", "add").args(serde_json::json!({"n": 7})).via(["relay"]))
                    .map_err(|e| ModuleError(e.to_string()))?;
                ctx.send(Command::new("acc", "fly")).map_err(|e| ModuleError(e.to_string()))?;
                ctx.send(Command::new("acc", "add").args(serde_json::json!({"n": "seven"})))
                    .map_err(|e| ModuleError(e.to_string()))?;
                ctx.send(Command::new("acc", "slow_job")).map_err(|e| ModuleError(e.to_string()))?;
            }
            Ok(())
        });
        d.on_ack(|m, ctx, ack| {
            m.seen.push(format!("{}:{}", ack.command, serde_json::to_string(&ack.status).unwrap()));
            ctx.write(m.acks.as_ref().unwrap(), m.seen.clone());
        });
    }
}

/// A module that relays messages and otherwise does nothing.
#[derive(Default)]
struct Relay;
impl Module for Relay {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::External;
    fn declare(&mut self, _d: &mut Declare<'_, Self>) {}
}

#[test]
fn relayed_command_is_acknowledged_back_to_its_sender_and_errors_come_back_too() {
    let mut b = SystemBuilder::new();
    b.add_inline("coord", Coordinator::default(), &periodic(0.01));
    b.add_inline("relay", Relay, &periodic(0.01));
    b.add_inline("acc", Accumulator::default(), &periodic(0.01));
    b.trace_messages(true);
    let mut ex = running(b);
    ex.run_for(Duration::from_millis(100));
    let acks = read::<Vec<String>>(ex.core(), "coord/acks").unwrap();
    assert!(acks.contains(&r#"add:{"status":"completed","detail":7}"#.to_string()), "{acks:?}");
    let unknown = acks.iter().find(|a| a.starts_with("fly:")).unwrap();
    assert!(unknown.contains("rejected") && unknown.contains("unknown command 'fly'"), "{unknown}");
    let bad = acks.iter().find(|a| a.contains("bad arguments")).unwrap();
    assert!(bad.contains("rejected"), "{bad}");
    // Deferred: accepted first, completed later.
    let slow: Vec<_> = acks.iter().filter(|a| a.starts_with("slow_job:")).collect();
    assert_eq!(slow.len(), 2, "{acks:?}");
    assert!(slow[0].contains("accepted") && slow[1].contains("finished"), "{slow:?}");
    // The relayed command and its ack both passed through the relay.
    let trace = ex.core().post.take_trace();
    let relay = ex.core().post.id("relay").unwrap();
    let hops_through_relay = trace.iter().filter(|m| m.path.contains(&relay)).count();
    assert_eq!(hops_through_relay, 2, "command forwarded by relay once, ack forwarded once");
}

#[test]
fn unknown_command_from_an_endpoint_is_rejected_with_the_known_ones() {
    let mut b = SystemBuilder::new();
    b.add_inline("acc", Accumulator::default(), "");
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    let id = g.send(Command::new("acc", "explode")).unwrap();
    ex.tick();
    let Some(AckStatus::Rejected(r)) = g.status(id) else { panic!() };
    assert!(r.contains("unknown command 'explode'") && r.contains("add"), "{r}");
    assert!(g.send(Command::new("nobody", "x")).is_err());
}

#[test]
fn disabled_commands_are_refused() {
    let mut b = SystemBuilder::new();
    b.add_inline("acc", Accumulator::default(), "[framework]\ncommands = [\"add\"]\n");
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    let ok = g.send(Command::new("acc", "add").args(serde_json::json!({"n": 1}))).unwrap();
    let no = g.send(Command::new("acc", "mark").args("x")).unwrap();
    ex.tick();
    assert!(matches!(g.status(ok), Some(AckStatus::Completed(_))));
    let Some(AckStatus::Rejected(r)) = g.status(no) else { panic!() };
    assert!(r.contains("disabled by the configuration"), "{r}");
}

#[test]
fn panicking_module_is_put_in_safe_while_others_continue() {
    let mut b = SystemBuilder::new();
    b.add_inline("fragile", Fragile::default(), &periodic(0.01));
    b.add_inline("c", Counter::default(), &periodic(0.01));
    b.endpoint("ground");
    let mut ex = running(b);
    ex.run_for(Duration::from_secs(1));
    assert_eq!(read::<u64>(ex.core(), "fragile/cycles"), Some(5));
    assert_eq!(read::<u64>(ex.core(), "c/count"), Some(100), "the other module kept running");
    let reports = ex.reports();
    let f = reports.iter().find(|r| r.name == "fragile").unwrap();
    assert_eq!((f.lifecycle, f.isolated), (Lifecycle::Safe, true));
    let events = ex.core().events.snapshot();
    assert!(events.iter().any(|e| matches!(&e.kind,
        EventKind::ModuleIsolated { module, fault: Fault::Panic(m) } if module == "fragile" && m.contains("overflow"))));
    assert_eq!(ex.system_state(), Lifecycle::Run, "the system keeps running");
    // Isolated: its commands are refused, framework commands still answered.
    let g = ex.endpoint("ground").unwrap();
    let cmd = g.send(Command::new("fragile", "fail")).unwrap();
    let ping = g.send(Command::new("fragile", "ping")).unwrap();
    ex.run_for(Duration::from_millis(10));
    assert!(matches!(g.status(cmd), Some(AckStatus::Rejected(r)) if r.contains("Safe")));
    assert!(matches!(g.status(ping), Some(AckStatus::Completed(_))));
    // Leaving Safe only by command, to Standby; then back to Run with the system.
    assert!(ex.module_transition("fragile", Lifecycle::Run).is_err());
    ex.module_transition("fragile", Lifecycle::Standby).unwrap();
    ex.module_transition("fragile", Lifecycle::Hold).unwrap();
    ex.module_transition("fragile", Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(50));
    assert_eq!(read::<u64>(ex.core(), "fragile/cycles"), Some(10));
}

#[test]
fn state_function_error_puts_module_in_safe() {
    let mut b = SystemBuilder::new();
    b.add_inline("fragile", Fragile::default(), &periodic(0.01));
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    ex.run_for(Duration::from_millis(20));
    g.send(Command::new("fragile", "fail")).unwrap();
    ex.run_for(Duration::from_millis(20));
    let events = ex.core().events.snapshot();
    assert!(events.iter().any(|e| matches!(&e.kind, EventKind::ModuleState { to, .. } if to == "failing")));
    assert!(events.iter().any(|e| matches!(&e.kind,
        EventKind::ModuleIsolated { fault: Fault::Error(m), .. } if m == "cannot read device")));
}

#[test]
fn overruns_are_counted_and_isolate_past_the_budget() {
    let mut b = SystemBuilder::new();
    b.add_inline(
        "heavy",
        Heavy::default(),
        "[framework]\nperiod_s = 0.01\noverrun_budget = 3\n[params]\ncost_ms = 15\n",
    );
    b.add_inline("light", Heavy::default(), "[framework]\nperiod_s = 0.01\n[params]\ncost_ms = 5\n");
    b.add_inline(
        "once",
        Heavy::default(),
        "[framework]\nperiod_s = 0.01\noverrun_budget = 3\n[params]\ncost_ms = 0\n",
    );
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    g.send(Command::new("once", "set_cost").args(20)).unwrap();
    ex.run_for(Duration::from_millis(10)); // one overrun for "once"
    g.send(Command::new("once", "set_cost").args(0)).unwrap();
    ex.run_for(Duration::from_millis(190));
    let r = ex.reports();
    let get = |n: &str| r.iter().find(|m| m.name == n).unwrap().clone();
    assert_eq!(get("light").stats.overruns, 0);
    assert_eq!((get("once").stats.overruns, get("once").isolated), (1, false));
    let heavy = get("heavy");
    assert_eq!(heavy.stats.overruns, 4, "isolated at the 4th consecutive overrun with a budget of 3");
    assert!(heavy.isolated && heavy.lifecycle == Lifecycle::Safe);
    assert_eq!(heavy.stats.cycles, 4);
}

#[test]
fn start_up_checks_report_every_declaration_problem() {
    #[derive(Default)]
    struct Reads;
    impl Module for Reads {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Resource;
        fn declare(&mut self, d: &mut Declare<'_, Self>) {
            let _ = d.reads::<f64>("nobody/writes");
            let _ = d.writes::<u64>("shared");
            d.sends_to("ghost");
            d.command("ping", |_m, _c, _: ()| Outcome::done());
        }
    }
    #[derive(Default)]
    struct AlsoWrites;
    impl Module for AlsoWrites {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Resource;
        fn declare(&mut self, d: &mut Declare<'_, Self>) {
            let _ = d.writes::<u64>("shared");
        }
    }
    let mut b = SystemBuilder::new();
    b.add_inline("a", Reads, "");
    b.add_inline("b", AlsoWrites, &periodic(0.0015));
    b.add_inline("a", Relay, "");
    let e = LockstepExecutor::new(b, MS).err().expect("must fail").to_string();
    for needle in [
        "'a' is registered twice",
        "slot 'shared' has several writers: 'a', 'b'",
        "slot 'nobody/writes' is read by 'a' but no module writes it",
        "module 'a' sends to unknown module 'ghost'",
        "command 'ping' is reserved",
        "period 1.500 ms is not a multiple of the base period 1.000 ms",
    ] {
        assert!(e.contains(needle), "missing «{needle}» in:\n{e}");
    }
}

#[test]
fn configuration_errors_name_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("heavy.toml");
    std::fs::write(&path, "[framework]\nperiod_s = 0.01\n\n[params]\ncost_ms = 1\ncots_ms = 2\n").unwrap();
    let mut b = SystemBuilder::new();
    b.add("heavy", Heavy::default(), framework::ConfigSource::file(&path));
    let e = LockstepExecutor::new(b, MS).err().unwrap().to_string();
    assert!(e.contains(&format!("{}:6:1: ", path.display())) && e.contains("cots_ms"), "{e}");

    let mut b = SystemBuilder::new();
    b.add_inline("heavy", Heavy::default(), "[params]\ncost_ms = -4\n");
    let e = LockstepExecutor::new(b, MS).err().unwrap().to_string();
    assert!(e.contains("cost_ms must be >= 0") && e.contains("module 'heavy'"), "{e}");

    let mut b = SystemBuilder::new();
    b.add_inline("acc", Accumulator::default(), "[framework]\ncommands = [\"add\", \"sing\"]\n");
    let e = LockstepExecutor::new(b, MS).err().unwrap().to_string();
    assert!(e.contains(":2:") && e.contains("framework.commands") && e.contains("no command 'sing'"), "{e}");
}

#[test]
fn configuration_changes_reload_and_save_only_in_config() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("heavy.toml");
    std::fs::write(&path, "[framework]\nperiod_s = 0.01\n\n[params]\ncost_ms = 1\n").unwrap();
    let mut b = SystemBuilder::new();
    b.add("heavy", Heavy::default(), framework::ConfigSource::file(&path));
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, MS).unwrap();
    let g = ex.endpoint("ground").unwrap();
    let set = |g: &framework::Endpoint, v: serde_json::Value| {
        g.send(
            Command::new("heavy", "set_param").json(serde_json::json!({"key": "params.cost_ms", "value": v})),
        )
        .unwrap()
    };
    let ok = set(&g, serde_json::json!(12));
    let neg = set(&g, serde_json::json!(-1));
    let typo = g
        .send(
            Command::new("heavy", "set_param").json(serde_json::json!({"key": "params.cots_ms", "value": 1})),
        )
        .unwrap();
    let saved = dir.path().join("saved.toml");
    let save = g.send(Command::new("heavy", "save_config").json(serde_json::json!({"path": saved}))).unwrap();
    ex.run_for(Duration::from_millis(10));
    assert!(matches!(g.status(ok), Some(AckStatus::Completed(_))));
    assert!(matches!(g.status(neg), Some(AckStatus::Rejected(r)) if r.contains("cost_ms must be >= 0")));
    assert!(matches!(g.status(typo), Some(AckStatus::Rejected(r)) if r.contains("cots_ms")));
    assert!(matches!(g.status(save), Some(AckStatus::Completed(_))));
    let text = std::fs::read_to_string(&saved).unwrap();
    assert!(text.contains("cost_ms = 12") && text.contains("period_s = 0.01"), "{text}");
    // Reload from the (edited) file.
    std::fs::write(&path, "[framework]\nperiod_s = 0.02\noverrun_budget = 100\n\n[params]\ncost_ms = 30\n")
        .unwrap();
    let reload = g.send(Command::new("heavy", "reload_config")).unwrap();
    ex.run_for(Duration::from_millis(10));
    assert!(matches!(g.status(reload), Some(AckStatus::Completed(_))), "{:?}", g.status(reload));
    let before = ex.reports().into_iter().find(|r| r.name == "heavy").unwrap().stats;
    ex.walk_to(Lifecycle::Run).unwrap();
    let late = set(&g, serde_json::json!(1));
    ex.run_for(Duration::from_millis(100));
    assert!(matches!(g.status(late), Some(AckStatus::Rejected(r)) if r.contains("only in Config")));
    let heavy = ex.reports().into_iter().find(|r| r.name == "heavy").unwrap();
    assert_eq!(heavy.stats.cycles - before.cycles, 5, "reloaded period of 20 ms");
    assert_eq!(before.overruns, 0);
    assert!(heavy.stats.overruns >= 1, "reloaded cost of 30 ms overruns a 20 ms period");
}

#[test]
fn context_changes_only_where_allowed() {
    #[derive(Default)]
    struct Switchable;
    impl Module for Switchable {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Sensor;
        fn declare(&mut self, d: &mut Declare<'_, Self>) {
            d.context_switchable();
            d.command("probe", |_m, ctx, _: ()| {
                Outcome::Completed(serde_json::json!(ctx.context().to_string()))
            });
        }
    }
    let mut b = SystemBuilder::new();
    b.add_inline("sw", Switchable, "");
    b.add_inline("fixed", Relay, "");
    b.endpoint("ground");
    let mut ex = running(b);
    let g = ex.endpoint("ground").unwrap();
    let ctx = serde_json::json!({"context": {"mode": "operative", "purpose": "debug"}});
    let a = g.send(Command::new("sw", "set_context").json(ctx.clone())).unwrap();
    let b2 = g.send(Command::new("fixed", "set_context").json(ctx)).unwrap();
    let early = g.send(Command::new("sw", "probe").on(Queue::Debug)).unwrap();
    ex.tick();
    // The debug queue is served before the nominal one, so this probe came before the switch.
    assert!(matches!(g.status(early), Some(AckStatus::Rejected(r)) if r.contains("Mission")));
    let dbg = g.send(Command::new("sw", "probe").on(Queue::Debug)).unwrap();
    ex.tick();
    assert!(matches!(g.status(a), Some(AckStatus::Completed(_))));
    assert!(matches!(g.status(b2), Some(AckStatus::Rejected(r)) if r.contains("does not allow")));
    assert_eq!(g.status(dbg), Some(AckStatus::Completed(serde_json::json!("Operative/Debug"))));
}

#[test]
fn modules_run_in_kind_order_within_a_tick() {
    let mut b = SystemBuilder::new();
    b.add_inline("ext", Relay, &periodic(0.001));
    b.add_inline("coord", Coordinator::default(), &periodic(0.001));
    b.add_inline("sensor", Counter::default(), &periodic(0.001));
    b.add_inline("relay", Relay, "");
    b.add_inline("acc", Accumulator::default(), "");
    let ex = LockstepExecutor::new(b, MS).unwrap();
    assert_eq!(ex.execution_order(), ["sensor", "acc", "coord", "ext", "relay"]);
}

#[test]
fn own_state_machine_rejects_undeclared_transitions() {
    #[derive(Default)]
    struct Walker {
        result: Option<Writer<String>>,
    }
    impl Module for Walker {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Coordination;
        fn declare(&mut self, d: &mut Declare<'_, Self>) {
            self.result = Some(d.writes("walker/result"));
            d.state("idle", |_m, _c| Ok(()));
            d.state("moving", |_m, _c| Ok(()));
            d.state("arrived", |_m, _c| Ok(()));
            d.transition("idle", "moving").transition("moving", "arrived");
            d.command("go", |m, ctx, to: String| {
                let r = match ctx.goto(&to) {
                    Ok(()) => "ok".to_string(),
                    Err(e) => e.to_string(),
                };
                ctx.write(m.result.as_ref().unwrap(), r);
                Outcome::done()
            });
        }
    }
    let mut b = SystemBuilder::new();
    b.add_inline("w", Walker::default(), "");
    b.endpoint("g");
    let mut ex = running(b);
    let g = ex.endpoint("g").unwrap();
    g.send(Command::new("w", "go").args("arrived")).unwrap();
    ex.tick();
    let r = read::<String>(ex.core(), "walker/result").unwrap();
    assert!(r.contains("transition idle -> arrived is not declared"), "{r}");
    g.send(Command::new("w", "go").args("moving")).unwrap();
    ex.tick();
    assert_eq!(read::<String>(ex.core(), "walker/result").unwrap(), "ok");
    assert_eq!(ex.reports()[0].state, "moving");
    g.send(Command::new("w", "go").args("teleport")).unwrap();
    ex.tick();
    assert!(read::<String>(ex.core(), "walker/result").unwrap().contains("no state 'teleport'"));
}

#[test]
fn reservation_tokens_through_the_context() {
    #[derive(Default)]
    struct User {
        token: Option<framework::resources::ReservationToken>,
        log: Option<Writer<String>>,
    }
    impl Module for User {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Coordination;
        fn declare(&mut self, d: &mut Declare<'_, Self>) {
            self.log = Some(d.writes(&format!("{}/log", d.name())));
            d.command("take", |m, ctx, emergency: bool| {
                let r = if emergency { ctx.override_device("ptu") } else { ctx.acquire("ptu") };
                match r {
                    Ok(t) => {
                        m.token = Some(t);
                        Outcome::done()
                    }
                    Err(e) => Outcome::reject(e.to_string()),
                }
            });
            d.command("check", |m, ctx, _: ()| match &m.token {
                Some(t) => match ctx.validate(t) {
                    Ok(()) => Outcome::Completed(serde_json::json!("valid")),
                    Err(e) => Outcome::Completed(serde_json::json!(e.to_string())),
                },
                None => Outcome::reject("no token"),
            });
        }
    }
    let mut b = SystemBuilder::new();
    b.add_inline("nav", User::default(), "");
    b.add_inline("fdir", User::default(), "");
    b.device("ptu");
    b.endpoint("g");
    let mut ex = running(b);
    let g = ex.endpoint("g").unwrap();
    let a = g.send(Command::new("nav", "take").args(false)).unwrap();
    let b1 = g.send(Command::new("fdir", "take").args(false)).unwrap();
    ex.tick();
    assert!(matches!(g.status(a), Some(AckStatus::Completed(_))));
    assert!(matches!(g.status(b1), Some(AckStatus::Rejected(r)) if r.contains("reserved")));
    g.send(Command::new("fdir", "take").args(true)).unwrap();
    ex.tick();
    let c = g.send(Command::new("nav", "check")).unwrap();
    ex.tick();
    assert!(
        matches!(g.status(c), Some(AckStatus::Completed(v)) if v.as_str().unwrap().contains("no longer valid"))
    );
    assert!(ex.core().events.snapshot().iter().any(|e| matches!(&e.kind,
        EventKind::ReservationOverridden { by, previous: Some(p), .. } if by == "fdir" && p == "nav")));
}

#[test]
fn console_script_drives_a_system() {
    let mut b = SystemBuilder::new();
    b.add_inline("c", Counter::default(), &periodic(0.1));
    b.add_inline("acc", Accumulator::default(), "");
    b.endpoint("console");
    let mut ex = LockstepExecutor::new(b, MS).unwrap();
    let mut console = framework::console::Console::new(&ex, "console").unwrap();
    let out = console
        .run_script(
            &mut ex,
            "demo.script",
            "# bring up\nwalk run\nadvance 0.5\nsend acc add {\"n\": 4}\nadvance 0.01\nacks\nread c/count\nstats\nstate\n",
        )
        .unwrap();
    assert_eq!(out[0], "system is Run");
    assert_eq!(out[1], "time is 0.500000 s");
    assert!(out[2].starts_with("sent add to acc"), "{}", out[2]);
    assert!(out[4].contains("add by") && out[4].contains("completed"), "{}", out[4]);
    assert!(out[5].contains("\"value\":5"), "{}", out[5]);
    assert!(out[6].contains("cycles"), "{}", out[6]);
    assert!(out[7].contains("system: Run") && out[7].contains("acc"), "{}", out[7]);
    let e = console.run_script(&mut ex, "demo.script", "stats\nsystem levitate\n").unwrap_err();
    assert!(e.0.starts_with("demo.script:2: unknown lifecycle state 'levitate'"), "{e}");
    let e = console.run_script(&mut ex, "x", "system standby\n").unwrap_err();
    assert!(e.0.contains("illegal transition Run -> Standby"), "{e}");
}

#[test]
fn lifecycle_hook_can_refuse_a_transition() {
    #[derive(Default)]
    struct Picky;
    impl Module for Picky {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Actuator;
        fn declare(&mut self, _d: &mut Declare<'_, Self>) {}
        fn on_transition(&mut self, _c: &mut Ctx<'_>, _f: Lifecycle, to: Lifecycle) -> Result<(), String> {
            if to == Lifecycle::Hold { Err("motors not powered".into()) } else { Ok(()) }
        }
    }
    let mut b = SystemBuilder::new();
    b.add_inline("p", Picky, "");
    let mut ex = LockstepExecutor::new(b, MS).unwrap();
    ex.transition(Lifecycle::Standby).unwrap();
    let e = ex.transition(Lifecycle::Hold).unwrap_err();
    assert!(
        matches!(&e, SystemError::Refused { refusals, .. } if refusals[0].contains("motors not powered")),
        "{e}"
    );
    assert_eq!(ex.system_state(), Lifecycle::Standby);
}
