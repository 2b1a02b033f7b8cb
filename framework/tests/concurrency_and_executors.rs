//! Thread-safety of the blackboard, the real-time executor, and equivalence of the two executors.

mod common;

use common::*;
use framework::events::{EventKind, Fault};
use framework::message::ModuleId;
use framework::prelude::*;
use framework::{BlackBoard, Executor, LockstepExecutor, RealtimeExecutor, SystemBuilder};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

#[test]
fn concurrent_blackboard_readers_never_see_torn_or_stale_reordered_values() {
    let bb = BlackBoard::new();
    let w = bb.declare_writer::<Vec<u64>>("big", ModuleId(0)).unwrap();
    let done = Arc::new(AtomicBool::new(false));
    let readers: Vec<_> = (0..4)
        .map(|i| {
            let r = bb.declare_reader::<Vec<u64>>("big", ModuleId(i + 1)).unwrap();
            let done = done.clone();
            std::thread::spawn(move || {
                let mut last_seq = 0;
                let mut reads = 0u64;
                while !done.load(Ordering::Acquire) {
                    if let Some(s) = r.read() {
                        assert!(s.value.iter().all(|v| *v == s.seq), "torn value at seq {}", s.seq);
                        assert_eq!(s.stamp.as_nanos() as u64, s.seq);
                        assert!(s.seq >= last_seq, "sequence went backwards");
                        last_seq = s.seq;
                        reads += 1;
                    }
                }
                reads
            })
        })
        .collect();
    for i in 1..=20_000u64 {
        w.write(vec![i; 64], Time::from_nanos(i as i64));
    }
    done.store(true, Ordering::Release);
    for r in readers {
        assert!(r.join().expect("reader panicked") > 0);
    }
    assert_eq!(bb.slot("big").unwrap().seq(), 20_000);
}

fn producer_consumer() -> SystemBuilder {
    let mut b = SystemBuilder::new();
    b.add_inline(
        "counter",
        Counter::default(),
        "[framework]\nperiod_s = 0.01\n[params]\nsink = \"acc\"\nstop_after = 20\n",
    );
    b.add_inline("acc", Accumulator::default(), "");
    b
}

#[test]
fn the_same_module_set_gives_the_same_outputs_on_both_executors() {
    let mut lock = LockstepExecutor::new(producer_consumer(), Duration::from_millis(1)).unwrap();
    lock.walk_to(Lifecycle::Run).unwrap();
    lock.run_for(Duration::from_secs(1));
    let lock_sum = read::<u64>(lock.core(), "acc/sum");
    let lock_log = read::<Vec<String>>(lock.core(), "acc/log");
    let lock_count = read::<u64>(lock.core(), "counter/count");

    let mut rt = RealtimeExecutor::new(producer_consumer()).unwrap();
    rt.walk_to(Lifecycle::Run).unwrap();
    let core = rt.core().clone();
    for _ in 0..500 {
        if read::<u64>(&core, "acc/sum") == Some(210) {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let rt_sum = read::<u64>(&core, "acc/sum");
    let rt_log = read::<Vec<String>>(&core, "acc/log");
    let rt_count = read::<u64>(&core, "counter/count");
    let reports = rt.stop();

    assert_eq!(lock_sum, Some(210));
    assert_eq!((rt_sum, rt_log, rt_count), (lock_sum, lock_log, lock_count));
    assert!(reports.iter().find(|r| r.name == "counter").unwrap().stats.cycles >= 20);
}

#[test]
fn lockstep_runs_are_deterministic() {
    let run = || {
        let mut ex = LockstepExecutor::new(producer_consumer(), Duration::from_millis(1)).unwrap();
        ex.walk_to(Lifecycle::Run).unwrap();
        ex.run_for(Duration::from_millis(500));
        let events: Vec<_> =
            ex.core().events.snapshot().into_iter().map(|e| serde_json::to_string(&e).unwrap()).collect();
        let slots: Vec<_> =
            ex.core().board.names().iter().map(|n| ex.core().board.slot(n).unwrap().to_json()).collect();
        (events, slots)
    };
    assert_eq!(run(), run());
}

/// Sleeps (really) in its state function: to overrun and to hang on the wall clock.
#[derive(Default)]
struct Sleeper {
    cycles: u64,
    sleep_ms: u64,
    hang_at: Option<u64>,
    hang_ms: u64,
}

#[derive(Default, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct SleeperParams {
    sleep_ms: u64,
    #[serde(default)]
    hang_at: Option<u64>,
    #[serde(default = "default_hang_ms")]
    hang_ms: u64,
}

fn default_hang_ms() -> u64 {
    1500
}

impl Module for Sleeper {
    type Params = SleeperParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.state("work", |m, _ctx| {
            m.cycles += 1;
            let ms = if m.hang_at == Some(m.cycles) { m.hang_ms } else { m.sleep_ms };
            std::thread::sleep(std::time::Duration::from_millis(ms));
            Ok(())
        });
    }
    fn configure(&mut self, p: &SleeperParams) -> Result<(), String> {
        self.sleep_ms = p.sleep_ms;
        self.hang_at = p.hang_at;
        self.hang_ms = p.hang_ms;
        Ok(())
    }
}

#[test]
fn realtime_watchdog_isolates_panicking_and_hung_modules_and_the_rest_keeps_running() {
    let mut b = SystemBuilder::new();
    b.add_inline("fragile", Fragile::default(), "[framework]\nperiod_s = 0.005\n");
    b.add_inline(
        "stuck",
        Sleeper::default(),
        "[framework]\nperiod_s = 0.01\nhang_timeout_s = 0.2\n[params]\nsleep_ms = 0\nhang_at = 3\n",
    );
    b.add_inline(
        "late",
        Sleeper::default(),
        "[framework]\nperiod_s = 0.01\noverrun_budget = 1000\n[params]\nsleep_ms = 25\n",
    );
    b.add_inline("c", Counter::default(), "[framework]\nperiod_s = 0.01\n");
    let mut ex = RealtimeExecutor::new(b).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let core = ex.core().clone();
    let isolated = |name: &str| core.status(core.post.id(name).unwrap()).is_isolated();
    for _ in 0..300 {
        if isolated("fragile") && isolated("stuck") {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let count_then = read::<u64>(&core, "c/count").unwrap_or(0);
    std::thread::sleep(std::time::Duration::from_millis(100));
    let count_later = read::<u64>(&core, "c/count").unwrap_or(0);
    let reports = ex.stop();
    assert!(isolated("fragile") && isolated("stuck"));
    assert!(count_later > count_then, "the counter kept running after the faults");
    let events = core.events.snapshot();
    assert!(events.iter().any(|e| matches!(&e.kind,
        EventKind::ModuleIsolated { module, fault: Fault::Hang { busy_s } } if module == "stuck" && *busy_s >= 0.2)));
    assert!(events.iter().any(|e| matches!(&e.kind,
        EventKind::ModuleIsolated { module, fault: Fault::Panic(_) } if module == "fragile")));
    let late = reports.iter().find(|r| r.name == "late").unwrap();
    assert!(!late.isolated);
    assert!(late.stats.overruns >= 1 && late.stats.skipped >= 1, "{:?}", late.stats);
    assert!(late.stats.exec_max() >= Duration::from_millis(25));
    assert!(
        late.stats.exec_min() <= late.stats.exec_mean() && late.stats.exec_mean() <= late.stats.exec_max()
    );
}

#[test]
fn realtime_lifecycle_and_emergency_commands_reach_module_threads() {
    let mut b = SystemBuilder::new();
    b.add_inline("c", Counter::default(), "[framework]\nperiod_s = 0.5\n");
    b.endpoint("ground");
    let mut ex = RealtimeExecutor::new(b).unwrap();
    ex.walk_to(Lifecycle::Hold).unwrap();
    let g = ex.endpoint("ground").unwrap();
    let id = g.send(Command::new("c", "ping").on(Queue::Emergency)).unwrap();
    // Answered well before the module's next 0.5 s cycle.
    let status = g.wait_final(id, std::time::Duration::from_millis(400));
    assert!(matches!(status, Some(framework::AckStatus::Completed(_))), "{status:?}");
    let e = ex.transition(Lifecycle::Shutdown).unwrap_err();
    assert!(e.to_string().contains("Hold -> Shutdown"), "{e}");
    ex.walk_to(Lifecycle::Shutdown).unwrap();
    let r = ex.stop();
    assert_eq!(r[0].lifecycle, Lifecycle::Shutdown);
}

/// The lockstep run of a `stuck` module whose third cycle takes `hang_ms` of wall time, beside a
/// counter: the hang handler's reports, the stuck module's report, and every slot's value.
fn lockstep_with_a_slow_step(
    hang_ms: u64,
) -> (Vec<(String, Duration)>, framework::system::ModuleReport, Vec<String>) {
    let mut b = SystemBuilder::new();
    b.add_inline(
        "stuck",
        Sleeper::default(),
        &format!("[framework]\nperiod_s = 0.01\nhang_timeout_s = 0.2\n[params]\nsleep_ms = 0\nhang_at = 3\nhang_ms = {hang_ms}\n"),
    );
    b.add_inline("c", Counter::default(), "[framework]\nperiod_s = 0.01\n");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(10)).unwrap();
    let reported = Arc::new(parking_lot::Mutex::new(Vec::new()));
    let r2 = reported.clone();
    ex.on_hang(Arc::new(move |name: &str, busy: Duration| r2.lock().push((name.to_string(), busy))));
    ex.walk_to(Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(100));
    let stuck = ex.reports().into_iter().find(|r| r.name == "stuck").unwrap();
    let slots = ex
        .core()
        .board
        .names()
        .iter()
        .map(|n| format!("{:?}", ex.core().board.slot(n).unwrap().to_json()))
        .collect();
    let r = reported.lock().clone();
    (r, stuck, slots)
}

#[test]
fn lockstep_watchdog_reports_a_step_busy_past_its_hang_timeout_but_wall_speed_never_changes_the_run() {
    let (reports, stuck, slots) = lockstep_with_a_slow_step(1500);
    // Reported once, naming the module, after at least its timeout...
    assert_eq!(reports.len(), 1, "{reports:?}");
    assert_eq!(reports[0].0, "stuck");
    assert!(reports[0].1 >= Duration::from_millis(200));
    // ...but not isolated: once the slow step returned, the run went on as on a fast machine.
    assert!(!stuck.isolated && stuck.lifecycle == Lifecycle::Run, "{stuck:?}");
    assert_eq!(stuck.stats.cycles, 10);
    let (fast_reports, fast_stuck, fast_slots) = lockstep_with_a_slow_step(0);
    assert!(fast_reports.is_empty());
    assert_eq!(fast_stuck.stats.cycles, stuck.stats.cycles);
    assert_eq!(fast_slots, slots, "the simulated outcome does not depend on wall-clock speed");
}
