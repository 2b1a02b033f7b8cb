//! The console server of a running system: answers console requests between lockstep ticks, so
//! that what a console does happens at a definite simulated time, and holds the run while it is
//! paused (stepping it tick by tick on request).
//!
//! Malformed, oversized or foreign frames are dropped with a logged error (never a panic, never a
//! change to the system); a frame of another protocol version or schema gets a refusal that says so.

use crate::NetError;
use crate::config::NetConfig;
use crate::frame::{self, FrameError};
use crate::protocol::{ConsoleReply, ConsoleRequest};
use framework::executor::Executor;
use framework::lifecycle::Lifecycle;
use framework::message::{Command, MessageId, ModuleId, Queue};
use framework::system::Endpoint;
use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, Ordering};
use zenoh::Wait;
use zenoh::handlers::FifoChannelHandler;
use zenoh::query::{Query, Queryable};

/// Counts of what the server did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServerStats {
    /// Requests answered.
    pub answered: u64,
    /// Frames refused (another version or schema), with a refusal.
    pub refused: u64,
    /// Frames dropped (malformed, oversized, empty).
    pub dropped: u64,
}

/// A system's console server.
pub struct ConsoleServer {
    _session: zenoh::Session,
    queryable: Queryable<FifoChannelHandler<Query>>,
    endpoint: Endpoint,
    max_frame: usize,
    paused: bool,
    steps_left: u64,
    /// A `step` request, answered once its ticks have run: the query, the ticks asked for.
    stepping: Option<(Query, u64)>,
    /// `send` requests that wait for their final acknowledgement: the query, the command, until
    /// when (wall clock).
    waiting: Vec<(Query, MessageId, std::time::Instant)>,
    stats: ServerStats,
}

impl ConsoleServer {
    /// Listens as the configuration says, sending commands from `endpoint` (an endpoint registered on
    /// the system's builder for the console).
    pub fn open(cfg: &NetConfig, endpoint: Endpoint) -> Result<Self, NetError> {
        let session = crate::link::listen(cfg)?;
        let queryable = session
            .declare_queryable(cfg.console_key())
            .wait()
            .map_err(|e| NetError::Link(format!("cannot serve {}: {e}", cfg.console_key())))?;
        Ok(ConsoleServer {
            _session: session,
            queryable,
            endpoint,
            max_frame: cfg.max_frame_bytes,
            paused: false,
            steps_left: 0,
            stepping: None,
            waiting: Vec::new(),
            stats: ServerStats::default(),
        })
    }

    /// Starts paused (the run waits for a console's `step` or `resume`).
    pub fn pause(&mut self) {
        self.paused = true;
    }

    /// Whether the run is paused.
    pub fn paused(&self) -> bool {
        self.paused
    }

    /// What the server did so far.
    pub fn stats(&self) -> ServerStats {
        self.stats
    }

    /// Call before each tick: answers every waiting request; while paused, waits for requests
    /// until a `resume`, a `step` or `interrupt`. Returns once the executor may tick: whether it
    /// waited (a paced run then counts its pace from now).
    pub fn serve(&mut self, exec: &mut dyn Executor, interrupt: &AtomicBool) -> bool {
        let mut waited = false;
        loop {
            if self.steps_left == 0
                && let Some((q, n)) = self.stepping.take()
            {
                let text = format!("stepped {n} ticks; time is {}", exec.now());
                let json = serde_json::json!({ "ticks": n, "time_s": exec.now().as_secs_f64() });
                self.reply(&q, &frame::encode(&ConsoleReply::ok(text, json)));
            }
            while let Ok(Some(q)) = self.queryable.try_recv() {
                self.answer(q, exec);
            }
            self.answer_waiting();
            if !self.paused || self.steps_left > 0 || interrupt.load(Ordering::SeqCst) {
                break;
            }
            waited = true;
            match self.queryable.recv_timeout(std::time::Duration::from_millis(100)) {
                Ok(Some(q)) => self.answer(q, exec),
                Ok(None) => {}
                Err(e) => {
                    // The session is gone: nobody can resume the run from here.
                    tracing::error!("console: the listener closed ({e}); resuming the run");
                    self.paused = false;
                }
            }
        }
        if self.paused && self.steps_left > 0 {
            self.steps_left -= 1;
        }
        waited
    }

    /// The run is over: answers the requests still waiting (a step, commands awaiting their final
    /// acknowledgement) with what happened, so that no console is left without an answer.
    pub fn close(&mut self, exec: &mut dyn Executor) {
        if let Some((q, n)) = self.stepping.take() {
            let ran = n - self.steps_left;
            let r = ConsoleReply::error(format!(
                "the run ended at {} after {ran} of the {n} ticks asked for",
                exec.now()
            ));
            self.reply(&q, &frame::encode(&r));
        }
        for (q, id, _) in std::mem::take(&mut self.waiting) {
            let r = ack_reply(id, self.endpoint.status(id));
            self.reply(&q, &frame::encode(&r));
        }
        while let Ok(Some(q)) = self.queryable.try_recv() {
            let r = ConsoleReply::error(format!("the run ended at {}", exec.now()));
            self.reply(&q, &frame::encode(&r));
        }
    }

    /// Answers the `send` requests whose command has its final acknowledgement, or whose wait is over.
    #[allow(clippy::disallowed_methods)] // a console's wait is wall time; the run's time is not touched
    fn answer_waiting(&mut self) {
        if self.waiting.is_empty() {
            return;
        }
        let now = std::time::Instant::now();
        let waiting = std::mem::take(&mut self.waiting);
        for (q, id, until) in waiting {
            let status = self.endpoint.status(id);
            let done = status.as_ref().is_some_and(|s| s.is_final());
            if done || now >= until {
                let r = ack_reply(id, status);
                self.reply(&q, &frame::encode(&r));
            } else {
                self.waiting.push((q, id, until));
            }
        }
    }

    fn reply(&mut self, q: &Query, bytes: &[u8]) {
        if let Err(e) = q.reply(q.key_expr().clone(), bytes.to_vec()).express(true).wait() {
            tracing::warn!("console: could not answer a request: {e}");
        }
    }

    fn answer(&mut self, q: Query, exec: &mut dyn Executor) {
        let Some(payload) = q.payload() else {
            self.stats.dropped += 1;
            tracing::warn!("console: dropped a request without a payload");
            return;
        };
        let bytes = payload.to_bytes();
        let req = match frame::decode::<ConsoleRequest>(&bytes, self.max_frame) {
            Ok(r) => r,
            Err(e @ (FrameError::Version { .. } | FrameError::Schema { .. })) => {
                self.stats.refused += 1;
                tracing::warn!("console: refused a peer: {e}");
                self.reply(&q, &frame::refusal(&e.to_string()));
                return;
            }
            Err(e) => {
                self.stats.dropped += 1;
                tracing::warn!("console: dropped a malformed frame: {e}");
                return;
            }
        };
        self.stats.answered += 1;
        if let ConsoleRequest::Step { ticks } = req {
            if !self.paused {
                let r = ConsoleReply::error("the run is not paused ('pause' first)");
                self.reply(&q, &frame::encode(&r));
            } else if ticks == 0 {
                let r = ConsoleReply::error("step needs at least one tick");
                self.reply(&q, &frame::encode(&r));
            } else if self.stepping.is_some() {
                let r = ConsoleReply::error("a step is under way: wait for its answer");
                self.reply(&q, &frame::encode(&r));
            } else {
                self.steps_left = ticks;
                self.stepping = Some((q, ticks));
            }
            return;
        }
        let r = match req {
            ConsoleRequest::Send { module, command, args_json, queue, via, wait_s } => {
                match self.send(&module, &command, &args_json, &queue, via) {
                    // Answered once the command has its final acknowledgement, or the wait is over.
                    Ok(id) if wait_s.is_finite() && wait_s > 0.0 => {
                        #[allow(clippy::disallowed_methods)] // a console's wait is wall time
                        let until = std::time::Instant::now()
                            + std::time::Duration::from_secs_f64(wait_s.min(3600.0));
                        self.waiting.push((q, id, until));
                        return;
                    }
                    Ok(id) => ConsoleReply::ok(
                        format!("sent {command} to {module} as {id}"),
                        serde_json::json!({ "id": { "sender": id.sender.0, "seq": id.seq } }),
                    ),
                    Err(why) => ConsoleReply::error(why),
                }
            }
            req => self.handle(req, exec),
        };
        self.reply(&q, &frame::encode(&r));
    }

    /// Sends a console's command from its endpoint; the command's id.
    fn send(
        &mut self,
        module: &str,
        command: &str,
        args_json: &str,
        queue: &str,
        via: Vec<String>,
    ) -> Result<MessageId, String> {
        let queue = match queue {
            "nominal" => Queue::Nominal,
            "emergency" => Queue::Emergency,
            "debug" => Queue::Debug,
            q => return Err(format!("unknown queue '{q}' (nominal, emergency, debug)")),
        };
        let args: serde_json::Value =
            serde_json::from_str(args_json).map_err(|e| format!("arguments are not valid JSON: {e}"))?;
        let cmd = Command::new(module, command).json(args).on(queue).via(via);
        self.endpoint.send(cmd).map_err(|e| e.to_string())
    }

    fn handle(&mut self, req: ConsoleRequest, exec: &mut dyn Executor) -> ConsoleReply {
        let lifecycle = |name: &str| {
            Lifecycle::parse(name).ok_or_else(|| {
                let all: Vec<_> = Lifecycle::ALL.iter().map(|l| l.name()).collect();
                ConsoleReply::error(format!("unknown lifecycle state '{name}' (states: {})", all.join(", ")))
            })
        };
        match req {
            ConsoleRequest::Status => {
                let json = serde_json::json!({
                    "time_s": exec.now().as_secs_f64(),
                    "system": exec.system_state().name(),
                    "paused": self.paused,
                });
                let paused = if self.paused { ", paused" } else { "" };
                ConsoleReply::ok(format!("time {}; system {}{paused}", exec.now(), exec.system_state()), json)
            }
            ConsoleRequest::Modules => {
                let reports = exec.reports();
                let mut text = format!(
                    "{:<24} {:<12} {:<9} {:<14} {:<18} {:>8} {:>8} {:>10}  meta-states\n",
                    "module", "kind", "lifecycle", "state", "context", "cycles", "overruns", "exec mean"
                );
                for r in &reports {
                    let meta: Vec<_> = r.meta_states.iter().map(|(s, i)| format!("{s}={i}")).collect();
                    let _ = writeln!(
                        text,
                        "{:<24} {:<12} {:<9} {:<14} {:<18} {:>8} {:>8} {:>10}  {}{}",
                        r.name,
                        format!("{:?}", r.kind).to_lowercase(),
                        r.lifecycle.name(),
                        r.state,
                        r.context,
                        r.stats.cycles,
                        r.stats.overruns,
                        r.stats.exec_mean().to_string(),
                        meta.join(" "),
                        if r.isolated { " ISOLATED" } else { "" }
                    );
                }
                ConsoleReply::ok(text.trim_end(), serde_json::to_value(&reports).unwrap_or_default())
            }
            // Sent in `answer`, which may hold the answer until the acknowledgement.
            ConsoleRequest::Send { .. } => {
                ConsoleReply::error("send is answered by the server's answer path")
            }
            ConsoleRequest::Ack { sender, seq } => {
                let id = MessageId { sender: ModuleId(sender), seq };
                ack_reply(id, self.endpoint.status(id))
            }
            ConsoleRequest::Slots => {
                let core = exec.core();
                let mut text = String::new();
                let mut json = Vec::new();
                for name in core.board.names() {
                    if let Some(s) = core.board.slot(&name) {
                        let _ = writeln!(text, "{name:<36} seq={:<8} {}", s.seq(), s.type_name());
                        json.push(serde_json::json!({ "slot": name, "seq": s.seq(), "type": s.type_name() }));
                    }
                }
                ConsoleReply::ok(text.trim_end(), serde_json::Value::Array(json))
            }
            ConsoleRequest::Read { slot } => match exec.core().board.slot(&slot) {
                Some(s) => {
                    // The stamped record: its value, stamp (ns) and sequence number.
                    let r = s.to_json().unwrap_or(serde_json::Value::Null);
                    let json = serde_json::json!({
                        "slot": slot, "seq": r["seq"], "stamp_ns": r["stamp"], "value": r["value"],
                    });
                    ConsoleReply::ok(r["value"].to_string(), json)
                }
                None => ConsoleReply::error(format!("no slot named '{slot}'")),
            },
            ConsoleRequest::System { to, walk } => {
                let to = match lifecycle(&to) {
                    Ok(l) => l,
                    Err(r) => return r,
                };
                let r = if walk { exec.walk_to(to) } else { exec.transition(to) };
                match r {
                    Ok(()) => ConsoleReply::ok(
                        format!("system is {}", exec.system_state()),
                        serde_json::json!({ "system": exec.system_state().name() }),
                    ),
                    Err(e) => ConsoleReply::error(e.to_string()),
                }
            }
            ConsoleRequest::Module { module, to } => {
                let to = match lifecycle(&to) {
                    Ok(l) => l,
                    Err(r) => return r,
                };
                match exec.module_transition(&module, to) {
                    Ok(()) => ConsoleReply::ok(
                        format!("module {module} is {to}"),
                        serde_json::json!({ "module": module, "lifecycle": to.name() }),
                    ),
                    Err(e) => ConsoleReply::error(e.to_string()),
                }
            }
            ConsoleRequest::Pause => {
                self.paused = true;
                ConsoleReply::ok(
                    format!("paused at {}", exec.now()),
                    serde_json::json!({ "paused": true, "time_s": exec.now().as_secs_f64() }),
                )
            }
            ConsoleRequest::Resume => {
                self.paused = false;
                if let Some((q, n)) = self.stepping.take() {
                    let ran = n - self.steps_left;
                    let r = ConsoleReply::ok(
                        format!("stepped {ran} of {n} ticks, then resumed; time is {}", exec.now()),
                        serde_json::json!({ "ticks": ran, "time_s": exec.now().as_secs_f64() }),
                    );
                    self.reply(&q, &frame::encode(&r));
                }
                self.steps_left = 0;
                ConsoleReply::ok(
                    format!("resumed at {}", exec.now()),
                    serde_json::json!({ "paused": false, "time_s": exec.now().as_secs_f64() }),
                )
            }
            // Answered in `answer`, once its ticks have run.
            ConsoleRequest::Step { .. } => ConsoleReply::error("step is answered once its ticks have run"),
        }
    }
}

/// The answer naming a command's latest acknowledgement.
fn ack_reply(id: MessageId, status: Option<framework::AckStatus>) -> ConsoleReply {
    let json_id = serde_json::json!({ "sender": id.sender.0, "seq": id.seq });
    match status {
        Some(s) => ConsoleReply::ok(
            format!("{id}: {}", serde_json::to_string(&s).unwrap_or_default()),
            serde_json::json!({ "id": json_id, "final": s.is_final(), "status": s }),
        ),
        None => ConsoleReply::ok(
            format!("{id}: no acknowledgement yet"),
            serde_json::json!({ "id": json_id, "final": false, "status": null }),
        ),
    }
}
