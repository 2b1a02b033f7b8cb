//! The console protocol: what a console asks of a running system, and what it answers.
//!
//! A request is one query on the system's console key; the answer is one reply. Command arguments
//! travel as JSON text: the receiving module types them (a mismatch is rejected back with serde's
//! message), as they do in-process.

use serde::{Deserialize, Serialize};

/// A console's request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ConsoleRequest {
    /// The run: time, system state, paused or not.
    Status,
    /// Every module: kind, lifecycle state, own state, context, meta-states, isolation, statistics.
    Modules,
    /// Sends a command to a module (debug commands are taken only by modules in a Debug context).
    Send {
        /// The recipient.
        module: String,
        /// The command.
        command: String,
        /// Its arguments as JSON text ("null" for none).
        args_json: String,
        /// `nominal`, `emergency` or `debug`.
        queue: String,
        /// Relays, in order.
        via: Vec<String>,
        /// Answer once the command has its final acknowledgement, or after this many seconds of
        /// wall time with its latest one (0: at once, with its id).
        wait_s: f64,
    },
    /// The latest status of a command this console sent.
    Ack {
        /// The id's sender part.
        sender: u32,
        /// The id's sequence number.
        seq: u64,
    },
    /// The blackboard's slots.
    Slots,
    /// The latest value of one slot.
    Read {
        /// The slot.
        slot: String,
    },
    /// One legal system transition (`walk`: through legal steps) to a lifecycle state.
    System {
        /// The state's name.
        to: String,
        /// Walk there through legal steps.
        walk: bool,
    },
    /// One module's lifecycle transition.
    Module {
        /// The module.
        module: String,
        /// The state's name.
        to: String,
    },
    /// Pauses a lockstep run before its next tick.
    Pause,
    /// Runs `ticks` base periods of a paused run, answered once they have run.
    Step {
        /// How many.
        ticks: u64,
    },
    /// Resumes a paused run.
    Resume,
}

/// The answer to a request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConsoleReply {
    /// The request was carried out.
    pub ok: bool,
    /// For a person.
    pub text: String,
    /// For a script: JSON text.
    pub json: String,
}

impl ConsoleReply {
    /// A success with its text and JSON.
    pub fn ok(text: impl Into<String>, json: serde_json::Value) -> Self {
        ConsoleReply { ok: true, text: text.into(), json: json.to_string() }
    }
    /// A failure, saying why.
    pub fn error(reason: impl Into<String>) -> Self {
        let reason = reason.into();
        ConsoleReply { ok: false, json: serde_json::json!({ "error": reason }).to_string(), text: reason }
    }
}

/// The console's command lines, as `rover-twin console` takes them.
pub const HELP: &str = "\
status                      time, system state, paused or not
modules                     every module: kind, lifecycle, state, context, statistics, meta-states
send [--queue nominal|emergency|debug] [--via a,b] <module> <command> [json-args]
                            send a command and wait for its acknowledgement
ack <sender>.<seq>          the latest acknowledgement of a command sent from this console
slots | read <slot>         the blackboard's slots; the latest value of one
system <state>              one legal system transition (walk <state>: through legal steps)
module <name> <state>       one module's transition (e.g. module navigator standby to leave Safe)
pause | step [ticks] | resume
help";

impl ConsoleRequest {
    /// Parses one console line; `None` for a blank line, a `#` comment or `help`.
    pub fn parse(line: &str) -> Result<Option<ConsoleRequest>, String> {
        use framework::console::ConsoleCommand as C;
        let words: Vec<&str> = line.split_whitespace().collect();
        let no_more = |n: usize| match words.get(n) {
            Some(w) => Err(format!("unexpected '{w}' after '{}'", words[0])),
            None => Ok(()),
        };
        match words.first().copied() {
            None => return Ok(None),
            Some(w) if w.starts_with('#') => return Ok(None),
            Some("help") => return Ok(None),
            Some("status") => return no_more(1).map(|()| Some(ConsoleRequest::Status)),
            Some("modules") => return no_more(1).map(|()| Some(ConsoleRequest::Modules)),
            Some("pause") => return no_more(1).map(|()| Some(ConsoleRequest::Pause)),
            Some("resume") => return no_more(1).map(|()| Some(ConsoleRequest::Resume)),
            Some("step") => {
                no_more(2)?;
                let ticks = match words.get(1) {
                    Some(n) => n.parse::<u64>().map_err(|_| format!("step: '{n}' is not a tick count"))?,
                    None => 1,
                };
                return Ok(Some(ConsoleRequest::Step { ticks }));
            }
            Some("ack") => {
                no_more(2)?;
                let id = words.get(1).ok_or("ack needs an id: <sender>.<seq>, as send printed it")?;
                let (s, q) = id
                    .trim_start_matches('#')
                    .split_once('.')
                    .and_then(|(s, q)| Some((s.parse().ok()?, q.parse().ok()?)))
                    .ok_or_else(|| format!("ack: '{id}' is not an id like 7.3"))?;
                return Ok(Some(ConsoleRequest::Ack { sender: s, seq: q }));
            }
            _ => {}
        }
        let cmd = framework::console::parse(line).map_err(|e| e.0)?;
        Ok(match cmd {
            None => None,
            Some(C::Send(c)) => Some(ConsoleRequest::Send {
                module: c.to,
                command: c.name,
                args_json: c.args.to_string(),
                queue: match c.queue {
                    framework::Queue::Nominal => "nominal",
                    framework::Queue::Emergency => "emergency",
                    framework::Queue::Debug => "debug",
                }
                .into(),
                via: c.via,
                wait_s: 0.0,
            }),
            Some(C::System(to)) => Some(ConsoleRequest::System { to: to.name().into(), walk: false }),
            Some(C::Walk(to)) => Some(ConsoleRequest::System { to: to.name().into(), walk: true }),
            Some(C::Module(m, to)) => Some(ConsoleRequest::Module { module: m, to: to.name().into() }),
            Some(C::Slots) => Some(ConsoleRequest::Slots),
            Some(C::Read(slot)) => Some(ConsoleRequest::Read { slot }),
            Some(C::State(None)) | Some(C::Stats) => Some(ConsoleRequest::Modules),
            Some(other) => {
                return Err(format!(
                    "'{}' is a local console command only",
                    format!("{other:?}").to_lowercase()
                ));
            }
        })
    }
}

crate::wire!(ConsoleRequest, 1);
crate::wire!(ConsoleReply, 2);
