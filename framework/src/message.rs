//! Message passing (seed 000, 5.2): commands and acknowledgements between modules.
//!
//! Every [`Message`] is stamped with the sender's clock time when posted, names its sender and final
//! recipient, and may travel through relay modules (`route`), recording the hops it took (`path`) so
//! that its acknowledgement goes back the same way. Each participant has an [`Inbox`] with three queues:
//! [`Queue::Emergency`] is drained before anything else, [`Queue::Debug`] is served only in the Debug
//! context (refused back to the sender in Mission), and [`Queue::Nominal`] is the normal channel.
//! Acknowledgements ([`AckStatus`]: accepted, rejected with reason, completed, failed) are tracked per
//! message by the sender's [`AckTracker`].

use crate::time::Time;
use parking_lot::{Condvar, Mutex};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use std::fmt;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Index of a participant (module or external endpoint) in the post office.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct ModuleId(pub u32);

/// Unique identity of a message: its original sender and that sender's sequence number.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct MessageId {
    /// The participant that created the message.
    pub sender: ModuleId,
    /// The sender's message counter, starting at 1.
    pub seq: u64,
}

impl fmt::Display for MessageId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "#{}.{}", self.sender.0, self.seq)
    }
}

/// The three queues of an inbox, in processing priority.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Queue {
    /// High priority: processed before everything else, at the next base tick even by periodic modules.
    Emergency,
    /// Debug commands: executed only in the Debug context.
    Debug,
    /// The nominal channel.
    Nominal,
}

/// What a message carries.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Body {
    /// A command, bound by name to a handler of the recipient, with its arguments.
    Command {
        /// The command name.
        name: String,
        /// The arguments (deserialized into the handler's typed argument struct).
        args: serde_json::Value,
    },
    /// An acknowledgement of an earlier command.
    Ack(Ack),
}

/// A message between participants.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Message {
    /// Its identity.
    pub id: MessageId,
    /// Clock time at which it was posted.
    pub stamp: Time,
    /// The original sender.
    pub sender: ModuleId,
    /// The final recipient.
    pub recipient: ModuleId,
    /// Relay hops still to pass before the recipient, next first.
    pub route: Vec<ModuleId>,
    /// Relay hops already passed, in order.
    pub path: Vec<ModuleId>,
    /// The queue it travels on.
    pub queue: Queue,
    /// What it carries.
    pub body: Body,
}

impl Message {
    /// The participant this message must be delivered to next.
    pub fn next_hop(&self) -> ModuleId {
        self.route.first().copied().unwrap_or(self.recipient)
    }
}

/// The state of a command as its sender sees it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", content = "detail", rename_all = "lowercase")]
pub enum AckStatus {
    /// Sent; no acknowledgement yet.
    Pending,
    /// Accepted by the recipient; completion will follow.
    Accepted,
    /// Refused, with the reason.
    Rejected(String),
    /// Carried out, with an optional result.
    Completed(serde_json::Value),
    /// Accepted but failed while being carried out, with the reason.
    Failed(String),
}

impl AckStatus {
    /// True for the statuses that end a command's life (rejected, completed, failed).
    pub fn is_final(&self) -> bool {
        matches!(self, AckStatus::Rejected(_) | AckStatus::Completed(_) | AckStatus::Failed(_))
    }
}

/// An acknowledgement of a command.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ack {
    /// The command acknowledged.
    pub of: MessageId,
    /// Its name (for logs and messages).
    pub command: String,
    /// The participant that acknowledges (the recipient, or a relay that could not forward).
    pub by: ModuleId,
    /// The status.
    pub status: AckStatus,
}

/// What a command handler returns.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// Done, with a result (use [`Outcome::done`] for none).
    Completed(serde_json::Value),
    /// Accepted; the module will report completion or failure later with `Ctx::reply`.
    Accepted,
    /// Refused, with the reason.
    Rejected(String),
    /// Tried and failed, with the reason.
    Failed(String),
}

impl Outcome {
    /// Completed with no result.
    pub fn done() -> Self {
        Outcome::Completed(serde_json::Value::Null)
    }
    /// Refused with a reason.
    pub fn reject(reason: impl Into<String>) -> Self {
        Outcome::Rejected(reason.into())
    }
    /// Failed with a reason.
    pub fn fail(reason: impl Into<String>) -> Self {
        Outcome::Failed(reason.into())
    }
    pub(crate) fn into_status(self) -> AckStatus {
        match self {
            Outcome::Completed(v) => AckStatus::Completed(v),
            Outcome::Accepted => AckStatus::Accepted,
            Outcome::Rejected(r) => AckStatus::Rejected(r),
            Outcome::Failed(r) => AckStatus::Failed(r),
        }
    }
}

/// A command to send: recipient, name, arguments, queue and relays.
#[derive(Clone, Debug, PartialEq)]
pub struct Command {
    /// Name of the final recipient.
    pub to: String,
    /// The command name.
    pub name: String,
    /// Its arguments.
    pub args: serde_json::Value,
    /// The queue.
    pub queue: Queue,
    /// Names of the relay modules to pass through, in order.
    pub via: Vec<String>,
}

impl Command {
    /// A nominal command without arguments.
    pub fn new(to: impl Into<String>, name: impl Into<String>) -> Self {
        Command {
            to: to.into(),
            name: name.into(),
            args: serde_json::Value::Null,
            queue: Queue::Nominal,
            via: Vec::new(),
        }
    }
    /// Sets the arguments from any serializable value.
    ///
    /// # Panics
    /// If `args` cannot be represented as JSON (a map with non-string keys, say): a programming error.
    pub fn args(mut self, args: impl Serialize) -> Self {
        self.args = serde_json::to_value(args).expect("command arguments must serialize to JSON");
        self
    }
    /// Sets raw JSON arguments.
    pub fn json(mut self, args: serde_json::Value) -> Self {
        self.args = args;
        self
    }
    /// Sends on the given queue.
    pub fn on(mut self, queue: Queue) -> Self {
        self.queue = queue;
        self
    }
    /// Relays through these modules, in order.
    pub fn via<S: Into<String>>(mut self, relays: impl IntoIterator<Item = S>) -> Self {
        self.via = relays.into_iter().map(Into::into).collect();
        self
    }
}

/// Why a message could not be posted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SendError {
    /// No participant of that name exists.
    #[error("unknown recipient '{0}'")]
    UnknownRecipient(String),
    /// The sending module is isolated by the watchdog.
    #[error("module '{0}' is isolated and cannot send")]
    Isolated(String),
}

#[derive(Default)]
struct Queues {
    emergency: VecDeque<Message>,
    debug: VecDeque<Message>,
    nominal: VecDeque<Message>,
}

/// One participant's three queues.
#[derive(Default)]
pub struct Inbox {
    queues: Mutex<Queues>,
    signal: Condvar,
    len: AtomicUsize,
    emergencies: AtomicUsize,
    next_seq: AtomicU64,
}

impl Inbox {
    fn push(&self, m: Message) {
        let mut q = self.queues.lock();
        match m.queue {
            Queue::Emergency => {
                q.emergency.push_back(m);
                self.emergencies.fetch_add(1, Ordering::Release);
            }
            Queue::Debug => q.debug.push_back(m),
            Queue::Nominal => q.nominal.push_back(m),
        }
        self.len.fetch_add(1, Ordering::Release);
        drop(q);
        self.signal.notify_all();
    }

    /// Takes the next message in priority order (emergency, debug, nominal).
    pub fn pop(&self) -> Option<Message> {
        if self.len.load(Ordering::Acquire) == 0 {
            return None;
        }
        let mut q = self.queues.lock();
        let m = if let Some(m) = q.emergency.pop_front() {
            self.emergencies.fetch_sub(1, Ordering::Release);
            Some(m)
        } else {
            q.debug.pop_front().or_else(|| q.nominal.pop_front())
        };
        if m.is_some() {
            self.len.fetch_sub(1, Ordering::Release);
        }
        m
    }

    /// Takes the next emergency message only.
    pub fn pop_emergency(&self) -> Option<Message> {
        if self.emergencies.load(Ordering::Acquire) == 0 {
            return None;
        }
        let m = self.queues.lock().emergency.pop_front();
        if m.is_some() {
            self.emergencies.fetch_sub(1, Ordering::Release);
            self.len.fetch_sub(1, Ordering::Release);
        }
        m
    }

    /// Number of waiting messages.
    pub fn len(&self) -> usize {
        self.len.load(Ordering::Acquire)
    }
    /// True when no message waits.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Number of waiting emergency messages.
    pub fn emergencies(&self) -> usize {
        self.emergencies.load(Ordering::Acquire)
    }

    /// Blocks until a message is waiting or `deadline` passes; true if a message is waiting.
    pub fn wait_until(&self, deadline: std::time::Instant) -> bool {
        let mut q = self.queues.lock();
        while self.len.load(Ordering::Acquire) == 0 {
            if self.signal.wait_until(&mut q, deadline).timed_out() {
                break;
            }
        }
        self.len.load(Ordering::Acquire) > 0
    }

    /// Blocks until an emergency message is waiting or `deadline` passes; true if one is waiting.
    pub fn wait_emergency_until(&self, deadline: std::time::Instant) -> bool {
        let mut q = self.queues.lock();
        while self.emergencies.load(Ordering::Acquire) == 0 {
            if self.signal.wait_until(&mut q, deadline).timed_out() {
                break;
            }
        }
        self.emergencies.load(Ordering::Acquire) > 0
    }

    /// Wakes any thread waiting on this inbox (used to stop executors).
    pub fn wake(&self) {
        let _q = self.queues.lock();
        self.signal.notify_all();
    }

    /// The sequence number of the participant's latest message (0 before its first).
    pub(crate) fn seq(&self) -> u64 {
        self.next_seq.load(Ordering::Acquire)
    }
    /// Makes the participant's next message number follow `seq` (messages it sent elsewhere: a
    /// remote module's, numbered by its host).
    pub(crate) fn advance_seq_to(&self, seq: u64) {
        self.next_seq.fetch_max(seq, Ordering::AcqRel);
    }

    fn next_id(&self, sender: ModuleId) -> MessageId {
        MessageId { sender, seq: self.next_seq.fetch_add(1, Ordering::Relaxed) + 1 }
    }
}

/// Routes messages between participants by name or id; owns every participant's inbox.
pub struct PostOffice {
    names: Vec<String>,
    index: HashMap<String, ModuleId>,
    inboxes: Vec<Inbox>,
    trace: Option<Mutex<Vec<Message>>>,
}

impl PostOffice {
    pub(crate) fn new(names: Vec<String>, trace: bool) -> Self {
        let index = names.iter().enumerate().map(|(i, n)| (n.clone(), ModuleId(i as u32))).collect();
        let inboxes = names.iter().map(|_| Inbox::default()).collect();
        PostOffice { names, index, inboxes, trace: trace.then(|| Mutex::new(Vec::new())) }
    }

    /// The id of a participant.
    pub fn id(&self, name: &str) -> Option<ModuleId> {
        self.index.get(name).copied()
    }
    /// The name of a participant.
    pub fn name(&self, id: ModuleId) -> &str {
        self.names.get(id.0 as usize).map(String::as_str).unwrap_or("<unknown>")
    }
    /// All participant names, indexed by id.
    pub fn names(&self) -> &[String] {
        &self.names
    }
    /// A participant's inbox.
    pub fn inbox(&self, id: ModuleId) -> &Inbox {
        &self.inboxes[id.0 as usize]
    }

    /// Builds a message from `sender` for `cmd`, stamped `now`, without posting it.
    pub fn compose(&self, sender: ModuleId, now: Time, cmd: Command) -> Result<Message, SendError> {
        let recipient = self.id(&cmd.to).ok_or_else(|| SendError::UnknownRecipient(cmd.to.clone()))?;
        let route = cmd
            .via
            .iter()
            .map(|r| self.id(r).ok_or_else(|| SendError::UnknownRecipient(r.clone())))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Message {
            id: self.inbox(sender).next_id(sender),
            stamp: now,
            sender,
            recipient,
            route,
            path: Vec::new(),
            queue: cmd.queue,
            body: Body::Command { name: cmd.name, args: cmd.args },
        })
    }

    /// Whether every participant a message names (sender, recipient, route, path) exists here.
    pub fn knows_all(&self, m: &Message) -> bool {
        let n = self.names.len();
        let ok = |id: &ModuleId| (id.0 as usize) < n;
        let ack_ok = match &m.body {
            Body::Ack(a) => ok(&a.by) && ok(&a.of.sender),
            Body::Command { .. } => true,
        };
        ok(&m.sender) && ok(&m.recipient) && m.route.iter().all(ok) && m.path.iter().all(ok) && ack_ok
    }

    /// Delivers a message to its next hop.
    pub fn post(&self, m: Message) {
        if let Some(t) = &self.trace {
            t.lock().push(m.clone());
        }
        let hop = m.next_hop();
        self.inbox(hop).push(m);
    }

    /// Posts an acknowledgement of `original` back to its sender, along the reverse of its path.
    pub fn acknowledge(&self, original: &Message, by: ModuleId, now: Time, status: AckStatus) {
        let Body::Command { name, .. } = &original.body else {
            return;
        };
        let ack = Message {
            id: self.inbox(by).next_id(by),
            stamp: now,
            sender: by,
            recipient: original.sender,
            route: original.path.iter().rev().copied().collect(),
            path: Vec::new(),
            queue: if original.queue == Queue::Emergency { Queue::Emergency } else { Queue::Nominal },
            body: Body::Ack(Ack { of: original.id, command: name.clone(), by, status }),
        };
        self.post(ack);
    }

    /// Takes the messages traced so far (when tracing is on).
    pub fn take_trace(&self) -> Vec<Message> {
        self.trace.as_ref().map(|t| std::mem::take(&mut *t.lock())).unwrap_or_default()
    }
}

/// A sender's view of the commands it sent: the latest status of each, with a short history of
/// finished ones.
#[derive(Debug, Default)]
pub struct AckTracker {
    pending: HashMap<MessageId, (String, AckStatus)>,
    finished: VecDeque<(MessageId, String, AckStatus)>,
}

const FINISHED_KEPT: usize = 256;

impl AckTracker {
    /// Records a command just sent.
    pub fn sent(&mut self, id: MessageId, command: &str) {
        self.pending.insert(id, (command.to_string(), AckStatus::Pending));
    }
    /// Records an acknowledgement.
    pub fn update(&mut self, ack: &Ack) {
        if ack.status.is_final() {
            self.pending.remove(&ack.of);
            if self.finished.len() == FINISHED_KEPT {
                self.finished.pop_front();
            }
            self.finished.push_back((ack.of, ack.command.clone(), ack.status.clone()));
        } else if let Some(e) = self.pending.get_mut(&ack.of) {
            e.1 = ack.status.clone();
        }
    }
    /// The latest known status of a command (None if unknown or long forgotten).
    pub fn status(&self, id: MessageId) -> Option<AckStatus> {
        if let Some((_, s)) = self.pending.get(&id) {
            return Some(s.clone());
        }
        self.finished.iter().rev().find(|(i, _, _)| *i == id).map(|(_, _, s)| s.clone())
    }
    /// Number of commands without a final acknowledgement.
    pub fn outstanding(&self) -> usize {
        self.pending.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn office() -> PostOffice {
        PostOffice::new(vec!["a".into(), "b".into(), "c".into()], false)
    }

    #[test]
    fn emergency_overtakes_nominal_and_debug() {
        let po = office();
        let a = po.id("a").unwrap();
        for (i, q) in [Queue::Nominal, Queue::Debug, Queue::Emergency].into_iter().enumerate() {
            let m = po.compose(a, Time::from_nanos(i as i64), Command::new("b", format!("c{i}")).on(q));
            po.post(m.unwrap());
        }
        let b = po.inbox(po.id("b").unwrap());
        let order: Vec<_> = std::iter::from_fn(|| b.pop())
            .map(|m| match m.body {
                Body::Command { name, .. } => name,
                Body::Ack(_) => unreachable!(),
            })
            .collect();
        assert_eq!(order, ["c2", "c1", "c0"]);
    }

    #[test]
    fn unknown_recipients_and_relays_are_refused() {
        let po = office();
        let a = po.id("a").unwrap();
        assert_eq!(
            po.compose(a, Time::ZERO, Command::new("zz", "x")).unwrap_err(),
            SendError::UnknownRecipient("zz".into())
        );
        assert!(po.compose(a, Time::ZERO, Command::new("c", "x").via(["nope"])).is_err());
    }

    #[test]
    fn ack_goes_back_along_the_reverse_path() {
        let po = office();
        let (a, b, c) = (po.id("a").unwrap(), po.id("b").unwrap(), po.id("c").unwrap());
        let mut m = po.compose(a, Time::ZERO, Command::new("c", "x").via(["b"])).unwrap();
        assert_eq!(m.next_hop(), b);
        m.route.remove(0);
        m.path.push(b);
        assert_eq!(m.next_hop(), c);
        po.acknowledge(&m, c, Time::ZERO, AckStatus::Completed(serde_json::Value::Null));
        let ack = po.inbox(b).pop().unwrap();
        assert_eq!(ack.recipient, a);
        assert_eq!(ack.next_hop(), b);
    }

    #[test]
    fn tracker_keeps_latest_status() {
        let mut t = AckTracker::default();
        let id = MessageId { sender: ModuleId(0), seq: 1 };
        t.sent(id, "go");
        assert_eq!(t.status(id), Some(AckStatus::Pending));
        let mut ack = Ack { of: id, command: "go".into(), by: ModuleId(1), status: AckStatus::Accepted };
        t.update(&ack);
        assert_eq!(t.status(id), Some(AckStatus::Accepted));
        ack.status = AckStatus::Failed("stalled".into());
        t.update(&ack);
        assert_eq!(t.status(id), Some(AckStatus::Failed("stalled".into())));
        assert_eq!(t.outstanding(), 0);
    }
}
