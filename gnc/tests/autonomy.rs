//! Autonomy over a small system of workers: plans run in the order of their preconditions, failed
//! steps retried after recovery commands, timeouts stopped, crashed modules restarted, and missions
//! that cannot go on ended Safe or in Hold, each with its fault report.

use framework::data::{ActivityStatus, AutonomyState, MissionEnd};
use framework::executor::Executor;
use framework::message::AckStatus;
use framework::module::Request;
use framework::prelude::*;
use framework::{ConfigSource, LockstepExecutor, SystemBuilder};
use gnc::autonomy::{Autonomy, SLOT};
use serde::Deserialize;

/// A worker: `work {duration_s, failures}` completes after `duration_s`, failing its first
/// `failures` calls (counted across calls); `stop` ends the work in progress; `recover` counts.
#[derive(Default)]
struct Worker {
    job: Option<(Request, Time)>,
    calls: u32,
    recovered: u32,
    stopped: u32,
}

#[derive(Deserialize)]
struct Work {
    duration_s: f64,
    #[serde(default)]
    failures: u32,
}

impl Module for Worker {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Actuator;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.state("active", |m, ctx| {
            if let Some((req, until)) = m.job.take() {
                if ctx.now() >= until {
                    ctx.reply(&req, Outcome::done());
                } else {
                    m.job = Some((req, until));
                }
            }
            Ok(())
        });
        d.command("work", |m, ctx, a: Work| {
            m.calls += 1;
            if m.calls <= a.failures {
                return Outcome::fail(format!("call {} fails", m.calls));
            }
            m.job = Some((ctx.request().unwrap(), ctx.now() + Duration::from_secs_f64(a.duration_s)));
            Outcome::Accepted
        });
        d.command("recover", |m, _, _: ()| {
            m.recovered += 1;
            Outcome::Completed(serde_json::json!(m.recovered))
        });
        d.command("stop", |m, ctx, _: ()| {
            m.stopped += 1;
            if let Some((req, _)) = m.job.take() {
                ctx.reply(&req, Outcome::fail("stopped"));
            }
            Outcome::done()
        });
        d.command("counts", |m, _, _: ()| {
            Outcome::Completed(serde_json::json!([m.calls, m.recovered, m.stopped]))
        });
    }
}

const CONTEXT: &str = "context = { mode = \"dry-run\", purpose = \"debug\" }";

fn system() -> LockstepExecutor {
    let mut b = SystemBuilder::new();
    for w in ["driver", "arm"] {
        b.add(
            w,
            Worker::default(),
            ConfigSource::inline(w, format!("[framework]\nperiod_s = 0.1\n{CONTEXT}\n")),
        );
    }
    let cfg = format!(
        "[framework]\nperiod_s = 0.1\n{CONTEXT}\n[params]\nmax_restarts = 1\nstop_modules = [\"driver\", \"arm\"]\n"
    );
    b.add("autonomy", Autonomy::new(), ConfigSource::inline("autonomy", cfg));
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    ex
}

/// Runs `plan` (TOML activities) for `seconds`, with `during` called at each tick; the execute
/// command's status and Autonomy's final state.
fn run(
    ex: &mut LockstepExecutor,
    plan: &str,
    seconds: f64,
    mut during: impl FnMut(&mut LockstepExecutor, Time),
) -> (AckStatus, AutonomyState) {
    let plan: toml::Value = toml::from_str(plan).unwrap();
    let ground = ex.endpoint("ground").unwrap();
    let id =
        ground.send(Command::new("autonomy", "execute").json(serde_json::to_value(plan).unwrap())).unwrap();
    let reader = ex.core().board.reader::<AutonomyState>(SLOT).unwrap().unwrap();
    let until = ex.now() + Duration::from_secs_f64(seconds);
    while ex.now() < until {
        let now = ex.tick();
        during(ex, now);
        if reader.read().is_some_and(|s| s.value.end.is_some())
            && ground.status(id).is_some_and(|s| s.is_final())
        {
            break;
        }
    }
    (ground.status(id).unwrap(), reader.read().unwrap().value.clone())
}

fn counts(ex: &mut LockstepExecutor, worker: &str) -> Vec<u32> {
    let ground = ex.endpoint("ground").unwrap();
    let id = ground.send(Command::new(worker, "counts")).unwrap();
    for _ in 0..3 {
        ex.tick();
    }
    match ground.status(id) {
        Some(AckStatus::Completed(v)) => serde_json::from_value(v).unwrap(),
        other => panic!("{other:?}"),
    }
}

#[test]
fn activities_run_in_plan_order_and_the_plan_completes() {
    let mut ex = system();
    let plan = r#"
        [[activities]]
        name = "drive"
        steps = [{ to = "driver", command = "work", args = { duration_s = 1.0 }, timeout_s = 5.0 }]
        [[activities]]
        name = "grasp"
        steps = [{ to = "arm", command = "work", args = { duration_s = 0.5 }, timeout_s = 5.0 }]
    "#;
    let (ack, st) = run(&mut ex, plan, 10.0, |_, _| {});
    assert!(matches!(ack, AckStatus::Completed(_)), "{ack:?}");
    assert_eq!(st.end, Some(MissionEnd::Completed));
    let (d, g) = (st.activity("drive").unwrap(), st.activity("grasp").unwrap());
    assert_eq!((d.status, g.status), (ActivityStatus::Succeeded, ActivityStatus::Succeeded));
    assert!(d.end_s.unwrap() <= g.start_s.unwrap(), "{st:?}");
    assert!(st.faults.is_empty());
}

#[test]
fn a_failed_step_is_recovered_and_retried_and_a_failure_for_good_follows_its_policy() {
    let mut ex = system();
    // The arm fails twice: with one retry (after `recover`; a refused recovery command is passed
    // over, best effort, and costs no retry) the first activity still fails, so
    // its dependant is not run; the free one still runs; the mission fails without Hold or Safe.
    let plan = r#"
        [[activities]]
        name = "grasp"
        retries = 1
        recovery = [
            { to = "arm", command = "nonsense", timeout_s = 2.0 },
            { to = "arm", command = "recover", timeout_s = 2.0 },
        ]
        on_failure = "continue"
        steps = [{ to = "arm", command = "work", args = { duration_s = 0.5, failures = 2 }, timeout_s = 5.0 }]
        [[activities]]
        name = "stow"
        steps = [{ to = "arm", command = "work", args = { duration_s = 0.5 }, timeout_s = 5.0 }]
        [[activities]]
        name = "return"
        after = []
        steps = [{ to = "driver", command = "work", args = { duration_s = 0.5 }, timeout_s = 5.0 }]
    "#;
    let (ack, st) = run(&mut ex, plan, 10.0, |_, _| {});
    assert!(matches!(&ack, AckStatus::Failed(r) if r.contains("'grasp'")), "{ack:?}");
    assert_eq!(st.end, Some(MissionEnd::Completed));
    let g = st.activity("grasp").unwrap();
    assert_eq!((g.status, g.attempts), (ActivityStatus::Failed, 2));
    assert!(g.reason.as_deref().unwrap().contains("call 2 fails"), "{g:?}");
    assert_eq!(st.activity("stow").unwrap().status, ActivityStatus::NotRun);
    assert!(st.activity("stow").unwrap().reason.as_deref().unwrap().contains("'grasp'"));
    assert_eq!(st.activity("return").unwrap().status, ActivityStatus::Succeeded);
    let responses: Vec<&str> = st.faults.iter().map(|f| f.response.as_str()).collect();
    assert_eq!(responses, ["retry (1 of 1)", "continue"]);
    assert_eq!(counts(&mut ex, "arm")[1], 1, "recovered once");

    // The same failing once, retried after a wait: the retry succeeds.
    let mut ex = system();
    let plan = plan
        .replace("failures = 2", "failures = 1")
        .replace("retries = 1", "retries = 1\nretry_delay_s = 1.5");
    let (ack, st) = run(&mut ex, &plan, 10.0, |_, _| {});
    assert!(matches!(ack, AckStatus::Completed(_)), "{ack:?}");
    let g = st.activity("grasp").unwrap();
    assert_eq!((g.status, g.attempts), (ActivityStatus::Succeeded, 2));
    // The wait, then the work's 0.5 s.
    let waited = g.end_s.unwrap() - st.faults[0].at_s;
    assert!((2.0..2.5).contains(&waited), "{waited} s from the failure to the end");
}

#[test]
fn a_step_past_its_timeout_is_stopped_and_the_safe_policy_stops_all_motion() {
    let mut ex = system();
    let plan = r#"
        [[activities]]
        name = "drive"
        on_failure = "safe"
        steps = [{ to = "driver", command = "work", args = { duration_s = 30.0 }, timeout_s = 2.0 }]
        [[activities]]
        name = "grasp"
        steps = [{ to = "arm", command = "work", args = { duration_s = 0.5 }, timeout_s = 5.0 }]
    "#;
    let (ack, st) = run(&mut ex, plan, 10.0, |_, _| {});
    assert!(matches!(&ack, AckStatus::Failed(r) if r.contains("within 2 s")), "{ack:?}");
    assert_eq!(st.end, Some(MissionEnd::Safe));
    let d = st.activity("drive").unwrap();
    assert_eq!(d.status, ActivityStatus::Failed);
    assert!((d.end_s.unwrap() - d.start_s.unwrap() - 2.0).abs() < 0.25, "{d:?}");
    assert_eq!(st.activity("grasp").unwrap().status, ActivityStatus::NotRun);
    // The timed-out step and then every motion module told to stop.
    assert!(counts(&mut ex, "driver")[2] >= 2);
    assert!(counts(&mut ex, "arm")[2] >= 1);
}

#[test]
fn a_crashed_module_is_restarted_and_the_activity_tried_again_until_the_restarts_run_out() {
    let mut ex = system();
    let plan = r#"
        [[activities]]
        name = "drive"
        steps = [{ to = "driver", command = "work", args = { duration_s = 3.0 }, timeout_s = 10.0 }]
    "#;
    let crash = |ex: &mut LockstepExecutor| {
        let ground = ex.endpoint("ground").unwrap();
        ground
            .send(
                Command::new("driver", "inject_fault")
                    .json(serde_json::json!({ "kind": "panic" }))
                    .on(Queue::Debug),
            )
            .unwrap();
    };
    // One crash: restarted, driven again from the start, done.
    let mut crashed = false;
    let (ack, st) = run(&mut ex, plan, 20.0, |ex, now| {
        if !crashed && now >= Time::from_secs_f64(1.0) {
            crashed = true;
            crash(ex);
        }
    });
    assert!(matches!(ack, AckStatus::Completed(_)), "{ack:?} {st:?}");
    let d = st.activity("drive").unwrap();
    assert_eq!((d.status, d.attempts), (ActivityStatus::Succeeded, 2), "{st:?}");
    assert_eq!(st.faults.len(), 1);
    assert!(st.faults[0].fault.contains("'driver' is isolated"), "{:?}", st.faults);
    assert!(st.faults[0].response.starts_with("restart 'driver' (1 of 1)"), "{:?}", st.faults);
    assert_eq!(counts(&mut ex, "driver")[0], 2, "worked twice");

    // A new plan gets its own restart budget (max_restarts = 1): restarted after the first crash,
    // the second ends the mission Safe.
    let mut crashes = 0;
    let start = ex.now();
    let (ack, st) = run(&mut ex, plan, 20.0, |ex, now| {
        if crashes < 2 && now >= start + Duration::from_secs_f64(1.0 + 1.5 * crashes as f64) {
            crashes += 1;
            crash(ex);
        }
    });
    assert_eq!(st.faults[0].response, "restart 'driver' (1 of 1), retry", "{:?}", st.faults);
    assert!(matches!(&ack, AckStatus::Failed(r) if r.contains("no restart left")), "{ack:?}");
    assert_eq!(st.end, Some(MissionEnd::Safe));
    assert_eq!(st.faults.last().unwrap().response, "safe");
}

#[test]
fn bad_plans_are_refused_and_missing_modules_named() {
    let mut ex = system();
    let plan = r#"
        [[activities]]
        name = "a"
        after = ["b"]
        [[activities]]
        name = "b"
        after = ["a"]
    "#;
    let (ack, _) = run(&mut ex, plan, 1.0, |_, _| {});
    assert!(matches!(&ack, AckStatus::Rejected(r) if r.contains("cycle")), "{ack:?}");
    let plan = r#"
        [[activities]]
        name = "mapping"
        on_failure = "continue"
        steps = [{ to = "perception", command = "scan", timeout_s = 5.0 }]
    "#;
    let (ack, st) = run(&mut ex, plan, 2.0, |_, _| {});
    assert!(matches!(ack, AckStatus::Completed(_)), "{ack:?}");
    let m = st.activity("mapping").unwrap();
    assert_eq!(m.status, ActivityStatus::NotRun);
    assert!(m.reason.as_deref().unwrap().contains("needs module 'perception'"), "{m:?}");
}
