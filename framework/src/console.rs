//! The debug console and framework console (seed 000, 4.3): send commands to modules, read their
//! states and statistics, drive the lifecycle, read blackboard slots, from text lines typed by a person
//! or read from a script.
//!
//! ```text
//! send [--queue emergency|debug|nominal] [--via relay1,relay2] <module> <command> [json-args]
//! system <state>        one legal system transition (config, standby, hold, run, safe, shutdown)
//! walk <state>          walk the system through legal transitions to <state>
//! module <name> <state> one module's transition (e.g. `module nav standby` to leave Safe)
//! state [module]        lifecycle, own state, context of every module (or one, from the module)
//! stats                 scheduler statistics per module
//! slots                 blackboard slots with type and sequence number
//! read <slot>           latest value of a slot as JSON
//! events                framework events since the last call
//! acks                  acknowledgements received by the console
//! advance <seconds>     let time pass (simulated under lockstep)
//! help
//! ```

use crate::executor::Executor;
use crate::lifecycle::Lifecycle;
use crate::message::{Command, Queue};
use crate::system::{Endpoint, SystemError};
use crate::time::Duration;
use std::fmt::Write as _;

/// A parsed console line.
#[derive(Clone, Debug, PartialEq)]
pub enum ConsoleCommand {
    /// Send a command to a module.
    Send(Command),
    /// One system transition.
    System(Lifecycle),
    /// Walk the system to a state.
    Walk(Lifecycle),
    /// One module's transition.
    Module(String, Lifecycle),
    /// Show states.
    State(Option<String>),
    /// Show statistics.
    Stats,
    /// List blackboard slots.
    Slots,
    /// Read one slot.
    Read(String),
    /// Show new events.
    Events,
    /// Show acknowledgements received.
    Acks,
    /// Let time pass.
    Advance(Duration),
    /// Show the syntax.
    Help,
}

/// A console error: a malformed line or a failed operation.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct ConsoleError(pub String);

const VERBS: &str = "send, system, walk, module, state, stats, slots, read, events, acks, advance, help";

fn state_arg(word: Option<&str>, verb: &str) -> Result<Lifecycle, ConsoleError> {
    let w = word.ok_or_else(|| ConsoleError(format!("'{verb}' needs a lifecycle state")))?;
    Lifecycle::parse(w).ok_or_else(|| {
        ConsoleError(format!(
            "unknown lifecycle state '{w}' (states: {})",
            Lifecycle::ALL.iter().map(|l| l.name()).collect::<Vec<_>>().join(", ")
        ))
    })
}

/// Parses one console line; `None` for a blank line or a `#` comment.
pub fn parse(line: &str) -> Result<Option<ConsoleCommand>, ConsoleError> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return Ok(None);
    }
    let mut words = line.split_whitespace();
    let verb = words.next().unwrap_or_default();
    let cmd = match verb {
        "send" => {
            let mut queue = Queue::Nominal;
            let mut via: Vec<String> = Vec::new();
            let mut rest: Vec<&str> = words.by_ref().collect();
            while let Some(first) = rest.first().copied() {
                match first {
                    "--queue" => {
                        let q = rest.get(1).ok_or_else(|| ConsoleError("--queue needs a value".into()))?;
                        queue = match *q {
                            "emergency" => Queue::Emergency,
                            "debug" => Queue::Debug,
                            "nominal" => Queue::Nominal,
                            other => {
                                return Err(ConsoleError(format!(
                                    "unknown queue '{other}' (emergency, debug, nominal)"
                                )));
                            }
                        };
                        rest.drain(..2);
                    }
                    "--via" => {
                        let v = rest.get(1).ok_or_else(|| ConsoleError("--via needs module names".into()))?;
                        via = v.split(',').map(str::to_string).collect();
                        rest.drain(..2);
                    }
                    _ => break,
                }
            }
            let (Some(to), Some(name)) = (rest.first(), rest.get(1)) else {
                return Err(ConsoleError(
                    "usage: send [--queue q] [--via a,b] <module> <command> [json-args]".into(),
                ));
            };
            let json = rest[2..].join(" ");
            let args = if json.is_empty() {
                serde_json::Value::Null
            } else {
                serde_json::from_str(&json)
                    .map_err(|e| ConsoleError(format!("arguments are not valid JSON: {e}")))?
            };
            ConsoleCommand::Send(Command::new(*to, *name).json(args).on(queue).via(via))
        }
        "system" => ConsoleCommand::System(state_arg(words.next(), verb)?),
        "walk" => ConsoleCommand::Walk(state_arg(words.next(), verb)?),
        "module" => {
            let m = words.next().ok_or_else(|| ConsoleError("usage: module <name> <state>".into()))?;
            ConsoleCommand::Module(m.to_string(), state_arg(words.next(), verb)?)
        }
        "state" => ConsoleCommand::State(words.next().map(str::to_string)),
        "stats" => ConsoleCommand::Stats,
        "slots" => ConsoleCommand::Slots,
        "read" => ConsoleCommand::Read(
            words.next().ok_or_else(|| ConsoleError("usage: read <slot>".into()))?.to_string(),
        ),
        "events" => ConsoleCommand::Events,
        "acks" => ConsoleCommand::Acks,
        "advance" => {
            let s = words.next().ok_or_else(|| ConsoleError("usage: advance <seconds>".into()))?;
            let secs: f64 =
                s.parse().map_err(|_| ConsoleError(format!("'{s}' is not a number of seconds")))?;
            if !(secs.is_finite() && secs >= 0.0) {
                return Err(ConsoleError(format!("cannot advance by {secs} s")));
            }
            ConsoleCommand::Advance(Duration::from_secs_f64(secs))
        }
        "help" => ConsoleCommand::Help,
        other => {
            return Err(ConsoleError(format!("unknown console command '{other}' (known: {VERBS})")));
        }
    };
    if let Some(extra) = words.next()
        && !matches!(cmd, ConsoleCommand::Send(_))
    {
        return Err(ConsoleError(format!("unexpected '{extra}' after '{verb}'")));
    }
    Ok(Some(cmd))
}

/// A console attached to an endpoint of a running system.
pub struct Console {
    endpoint: Endpoint,
}

impl Console {
    /// A console sending from the endpoint `name` (registered on the builder).
    pub fn new(exec: &dyn Executor, name: &str) -> Result<Self, SystemError> {
        Ok(Console { endpoint: exec.endpoint(name)? })
    }

    /// Executes one command and returns its text output.
    pub fn execute(&mut self, exec: &mut dyn Executor, cmd: ConsoleCommand) -> Result<String, ConsoleError> {
        let err = |e: SystemError| ConsoleError(e.to_string());
        let core = exec.core().clone();
        let mut out = String::new();
        match cmd {
            ConsoleCommand::Send(c) => {
                let to = c.to.clone();
                let name = c.name.clone();
                let id = self.endpoint.send(c).map_err(|e| ConsoleError(e.to_string()))?;
                let _ = write!(out, "sent {name} to {to} as {id}");
            }
            ConsoleCommand::System(to) => {
                exec.transition(to).map_err(err)?;
                let _ = write!(out, "system is {}", exec.system_state());
            }
            ConsoleCommand::Walk(to) => {
                exec.walk_to(to).map_err(err)?;
                let _ = write!(out, "system is {}", exec.system_state());
            }
            ConsoleCommand::Module(m, to) => {
                exec.module_transition(&m, to).map_err(err)?;
                let _ = write!(out, "module {m} is {to}");
            }
            ConsoleCommand::State(None) => {
                let _ = writeln!(out, "system: {} at {}", exec.system_state(), exec.now());
                for r in exec.reports() {
                    let _ = writeln!(
                        out,
                        "{:<20} {:<12} {:<8} state={:<12} {}{}",
                        r.name,
                        format!("{:?}", r.kind),
                        r.lifecycle.name(),
                        r.state,
                        r.context,
                        if r.isolated { " ISOLATED" } else { "" }
                    );
                }
            }
            ConsoleCommand::State(Some(m)) => {
                let id = self
                    .endpoint
                    .send(Command::new(m, "get_state"))
                    .map_err(|e| ConsoleError(e.to_string()))?;
                let _ = write!(out, "asked for state as {id}; see 'acks' after time passes");
            }
            ConsoleCommand::Stats => {
                let _ = writeln!(
                    out,
                    "{:<20} {:>8} {:>8} {:>8} {:>8} {:>11} {:>11} {:>11}",
                    "module", "cycles", "overrun", "skipped", "msgs", "exec min", "exec mean", "exec max"
                );
                for r in exec.reports() {
                    let s = &r.stats;
                    let _ = writeln!(
                        out,
                        "{:<20} {:>8} {:>8} {:>8} {:>8} {:>11} {:>11} {:>11}",
                        r.name,
                        s.cycles,
                        s.overruns,
                        s.skipped,
                        s.messages,
                        s.exec_min().to_string(),
                        s.exec_mean().to_string(),
                        s.exec_max().to_string()
                    );
                }
            }
            ConsoleCommand::Slots => {
                for name in core.board.names() {
                    if let Some(s) = core.board.slot(&name) {
                        let _ = writeln!(out, "{name:<32} seq={:<8} {}", s.seq(), s.type_name());
                    }
                }
            }
            ConsoleCommand::Read(slot) => {
                let s =
                    core.board.slot(&slot).ok_or_else(|| ConsoleError(format!("no slot named '{slot}'")))?;
                let v = s.to_json().unwrap_or(serde_json::Value::Null);
                let _ = write!(out, "{v}");
            }
            ConsoleCommand::Events => {
                for e in core.events.drain() {
                    let _ = writeln!(out, "{}", serde_json::to_string(&e).unwrap_or_default());
                }
            }
            ConsoleCommand::Acks => {
                for a in self.endpoint.poll() {
                    let _ = writeln!(
                        out,
                        "{} {} by #{}: {}",
                        a.of,
                        a.command,
                        a.by.0,
                        serde_json::to_string(&a.status).unwrap_or_default()
                    );
                }
            }
            ConsoleCommand::Advance(d) => {
                exec.advance(d);
                let _ = write!(out, "time is {}", exec.now());
            }
            ConsoleCommand::Help => out.push_str(HELP),
        }
        Ok(out.trim_end().to_string())
    }

    /// Runs a script line by line; an error names the script and line.
    pub fn run_script(
        &mut self,
        exec: &mut dyn Executor,
        origin: &str,
        text: &str,
    ) -> Result<Vec<String>, ConsoleError> {
        let mut outputs = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let at = |e: ConsoleError| ConsoleError(format!("{origin}:{}: {}", i + 1, e.0));
            if let Some(cmd) = parse(line).map_err(at)? {
                outputs.push(self.execute(exec, cmd).map_err(at)?);
            }
        }
        Ok(outputs)
    }
}

const HELP: &str = "send [--queue emergency|debug|nominal] [--via a,b] <module> <command> [json-args]
system <state> | walk <state> | module <name> <state>
state [module] | stats | slots | read <slot> | events | acks
advance <seconds> | help";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_send_with_options_and_json() {
        let c = parse("send --queue emergency --via relay gripper open {\"width\": 0.05}").unwrap().unwrap();
        let ConsoleCommand::Send(c) = c else { panic!() };
        assert_eq!((c.to.as_str(), c.name.as_str(), c.queue), ("gripper", "open", Queue::Emergency));
        assert_eq!(c.via, vec!["relay".to_string()]);
        assert_eq!(c.args["width"], 0.05);
    }

    #[test]
    fn clear_errors() {
        assert!(parse("  # comment").unwrap().is_none());
        assert!(parse("fly away").unwrap_err().0.contains("unknown console command 'fly'"));
        assert!(parse("system flying").unwrap_err().0.contains("unknown lifecycle state 'flying'"));
        assert!(parse("send a b {bad").unwrap_err().0.contains("not valid JSON"));
        assert!(parse("send --queue loud a b").unwrap_err().0.contains("unknown queue"));
        assert!(parse("stats now").unwrap_err().0.contains("unexpected 'now'"));
        assert_eq!(parse("advance 0.5").unwrap(), Some(ConsoleCommand::Advance(Duration::from_millis(500))));
    }
}
