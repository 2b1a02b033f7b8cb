//! The Debugger (seed 000, 6.5): an external module that injects debug commands, failures above all,
//! into the other modules through their debug queues. It works only in the Debug context: in a
//! Mission context it refuses every injection, and the targets' debug queues are closed anyway.
//!
//! - `inject {to, command, args}`: sends `command` with `args` to module `to` on its debug queue and
//!   completes with the target's own acknowledgement (its result, or its refusal or failure naming
//!   the target);
//! - `injections`: what was injected so far, in order (time, target, command, outcome).

use crate::NoParams;
use crate::message::{Ack, AckStatus, Command, MessageId, Outcome, Queue};
use crate::module::{Ctx, Declare, Module, ModuleKind, Request};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The name systems give the debugger.
pub const NAME: &str = "debugger";

/// Arguments of `inject`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Inject {
    to: String,
    command: String,
    #[serde(default)]
    args: serde_json::Value,
}

/// One injection and how the target took it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Injection {
    /// When it was sent, simulated s.
    pub at_s: f64,
    /// The target module.
    pub to: String,
    /// The debug command.
    pub command: String,
    /// `pending`, `completed`, `rejected: ...` or `failed: ...`.
    pub outcome: String,
}

/// The Debugger module.
#[derive(Default)]
pub struct Debugger {
    /// Injections awaiting the target's acknowledgement: the request to answer and the log index.
    pending: BTreeMap<MessageId, (Request, usize)>,
    log: Vec<Injection>,
}

impl Debugger {
    /// A debugger with nothing injected yet.
    pub fn new() -> Self {
        Debugger::default()
    }

    fn inject(&mut self, ctx: &mut Ctx<'_>, a: Inject) -> Outcome {
        let Some(request) = ctx.request() else {
            return Outcome::reject("inject must come as a command");
        };
        if !ctx.context().debug_queue_active() {
            return Outcome::reject(format!(
                "the debugger injects only in a Debug context; it is in {} (set the run's purpose to debug)",
                ctx.context()
            ));
        }
        let cmd = Command::new(a.to.clone(), a.command.clone()).json(a.args).on(Queue::Debug);
        match ctx.send(cmd) {
            Ok(id) => {
                ctx.note(format!("injecting {}.{}", a.to, a.command));
                self.log.push(Injection {
                    at_s: ctx.now().as_secs_f64(),
                    to: a.to,
                    command: a.command,
                    outcome: "pending".into(),
                });
                self.pending.insert(id, (request, self.log.len() - 1));
                Outcome::Accepted
            }
            Err(e) => Outcome::reject(format!("cannot inject into '{}': {e}", a.to)),
        }
    }

    fn on_ack(&mut self, ctx: &mut Ctx<'_>, ack: &Ack) {
        if !ack.status.is_final() {
            return;
        }
        let Some((request, i)) = self.pending.remove(&ack.of) else { return };
        let entry = &mut self.log[i];
        let (outcome, text) = match &ack.status {
            AckStatus::Completed(v) => (Outcome::Completed(v.clone()), "completed".to_string()),
            AckStatus::Rejected(r) => (
                Outcome::reject(format!("'{}' refused {}: {r}", entry.to, entry.command)),
                format!("rejected: {r}"),
            ),
            AckStatus::Failed(r) => (
                Outcome::fail(format!("'{}' failed {}: {r}", entry.to, entry.command)),
                format!("failed: {r}"),
            ),
            AckStatus::Pending | AckStatus::Accepted => return,
        };
        ctx.note(format!("injection {}.{}: {text}", entry.to, entry.command));
        entry.outcome = text;
        ctx.reply(&request, outcome);
    }
}

impl Module for Debugger {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::External;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.context_switchable();
        d.command("inject", |m, ctx, a: Inject| m.inject(ctx, a));
        d.command("injections", |m, _ctx, _: ()| {
            Outcome::Completed(serde_json::to_value(&m.log).unwrap_or_default())
        });
        d.on_ack(|m, ctx, ack| m.on_ack(ctx, ack));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ConfigSource;
    use crate::executor::Executor;
    use crate::time::Duration;
    use crate::{Lifecycle, LockstepExecutor, SystemBuilder};

    /// A module with one debug-only effect: `poke` counts.
    #[derive(Default)]
    struct Target;
    impl Module for Target {
        type Params = NoParams;
        const KIND: ModuleKind = ModuleKind::Resource;
        fn declare(&mut self, d: &mut Declare<'_, Self>) {
            d.command("poke", |_, ctx, _: ()| {
                if ctx.request().is_some_and(|r| r.queue() == Queue::Debug) {
                    Outcome::Completed(serde_json::json!("poked"))
                } else {
                    Outcome::reject("poke only on the debug queue")
                }
            });
        }
    }

    fn system(purpose: &str) -> LockstepExecutor {
        let cfg = format!(
            "[framework]\nperiod_s = 0.1\ncontext = {{ mode = \"dry-run\", purpose = \"{purpose}\" }}\n"
        );
        let dbg = format!("[framework]\ncontext = {{ mode = \"dry-run\", purpose = \"{purpose}\" }}\n");
        let mut b = SystemBuilder::new();
        b.add("target", Target, ConfigSource::inline("target", cfg));
        b.add(NAME, Debugger::new(), ConfigSource::inline(NAME, dbg));
        b.endpoint("ground");
        let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
        ex.walk_to(Lifecycle::Run).unwrap();
        ex
    }

    fn inject(ex: &mut LockstepExecutor, command: &str) -> AckStatus {
        let ground = ex.endpoint("ground").unwrap();
        let args = serde_json::json!({ "to": "target", "command": command });
        let id = ground.send(Command::new(NAME, "inject").json(args)).unwrap();
        for _ in 0..10 {
            ex.tick();
        }
        ground.status(id).unwrap()
    }

    #[test]
    fn in_debug_the_injection_reaches_the_target_on_its_debug_queue_and_its_answer_comes_back() {
        let mut ex = system("debug");
        assert_eq!(inject(&mut ex, "poke"), AckStatus::Completed(serde_json::json!("poked")));
        match inject(&mut ex, "nonsense") {
            AckStatus::Rejected(r) => assert!(r.contains("'target' refused nonsense"), "{r}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn in_mission_the_debugger_refuses_to_inject() {
        let mut ex = system("mission");
        match inject(&mut ex, "poke") {
            AckStatus::Rejected(r) => assert!(r.contains("only in a Debug context"), "{r}"),
            other => panic!("{other:?}"),
        }
    }
}
