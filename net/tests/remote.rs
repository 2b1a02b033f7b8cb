//! Remote modules over Zenoh on loopback: a lockstep system whose `consumer` runs on a module host
//! gives the same results as the all-local one, bit for bit; a host that dies puts the module in
//! Safe while the rest goes on, and a restarted host plus lifecycle commands bring it back.

use framework::config::ConfigSource;
use framework::events::{EventKind, Fault};
use framework::prelude::*;
use framework::remote::{HostBuilder, ModuleHost};
use framework::{AckStatus, Executor, LockstepExecutor, SystemBuilder};
use net::NetConfig;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Counts its cycles into `producer/count`; every third cycle sends `add {n}` to the consumer and
/// counts the completed acknowledgements into `producer/acks`.
#[derive(Default)]
struct Producer {
    cycles: u64,
    sent: Vec<framework::MessageId>,
    acks: u64,
    failed: u64,
    count: Option<Writer<u64>>,
    out: Option<Writer<(u64, u64)>>,
}

impl Module for Producer {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Sensor;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.count = Some(d.writes("producer/count"));
        self.out = Some(d.writes("producer/acks"));
        d.sends_to("consumer");
        d.state("producing", |m, ctx| {
            m.cycles += 1;
            if let Some(w) = &m.count {
                ctx.write(w, m.cycles);
            }
            if m.cycles % 3 == 0
                && let Ok(id) =
                    ctx.send(Command::new("consumer", "add").json(serde_json::json!({ "n": m.cycles })))
            {
                m.sent.push(id);
            }
            let (mut done, mut failed) = (0, 0);
            for id in &m.sent {
                match ctx.ack_status(*id) {
                    Some(AckStatus::Completed(_)) => done += 1,
                    Some(AckStatus::Failed(_) | AckStatus::Rejected(_)) => failed += 1,
                    _ => {}
                }
            }
            (m.acks, m.failed) = (done, failed);
            if let Some(w) = &m.out {
                ctx.write(w, (m.acks, m.failed));
            }
            Ok(())
        });
    }
}

/// Sums what it is told to add (each `add` accepted, finished at its next cycle) and the producer's
/// count at each of its cycles; a meta-state chooses how.
#[derive(Default)]
struct Consumer {
    sum: u64,
    pending: Vec<(framework::module::Request, u64)>,
    log: Vec<String>,
    count: Option<Reader<u64>>,
    out: Option<Writer<u64>>,
    trail: Option<Writer<Vec<String>>>,
}

#[derive(serde::Deserialize)]
struct Add {
    n: u64,
}

impl Consumer {
    fn cycle(&mut self, ctx: &mut Ctx<'_>, weight: u64) -> StateResult {
        for (req, n) in std::mem::take(&mut self.pending) {
            self.sum += n;
            ctx.reply(&req, Outcome::Completed(serde_json::json!({ "sum": self.sum })));
        }
        if let Some(c) = self.count.as_ref().and_then(|r| r.read()) {
            self.sum += weight * c.value;
            self.log.push(format!("{} {} {}", ctx.now(), c.seq, self.sum));
        }
        if let Some(w) = &self.out {
            ctx.write(w, self.sum);
        }
        if let Some(w) = &self.trail {
            ctx.write(w, self.log.clone());
        }
        Ok(())
    }
}

impl Module for Consumer {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.count = Some(d.reads("producer/count"));
        self.out = Some(d.writes("consumer/sum"));
        self.trail = Some(d.writes("consumer/log"));
        d.meta_state("summing", &[("plain", |m, ctx| m.cycle(ctx, 1)), ("double", |m, ctx| m.cycle(ctx, 2))]);
        d.command("add", |m, ctx, a: Add| match ctx.request() {
            Some(r) => {
                m.pending.push((r, a.n));
                Outcome::Accepted
            }
            None => Outcome::reject("no request"),
        });
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn consumer_config(host: Option<&str>) -> String {
    let host = host.map(|h| format!("host = \"{h}\"\n")).unwrap_or_default();
    format!("[framework]\nperiod_s = 0.02\nhang_timeout_s = 1.0\n{host}")
}

fn system(host: Option<&str>) -> LockstepExecutor {
    let mut b = SystemBuilder::new();
    b.add_inline("producer", Producer::default(), "[framework]\nperiod_s = 0.01\n");
    b.add("consumer", Consumer::default(), ConfigSource::inline("<consumer>", consumer_config(host)));
    b.endpoint("ground");
    b.remote_links(net::remote::link_factory(&NetConfig::default()));
    LockstepExecutor::new(b, Duration::from_millis(10)).unwrap()
}

/// A module host serving `consumer` on `endpoint` in a thread, until stopped (as if killed).
struct Host {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<net::remote::HostStats>>,
}

impl Host {
    fn start(endpoint: &str) -> Self {
        let cfg = NetConfig { endpoint: endpoint.to_string(), ..NetConfig::default() };
        let text = consumer_config(Some(endpoint));
        let host = ModuleHost::new(Box::new(move |name: &str, b: &mut HostBuilder| match name {
            "consumer" => {
                b.add("consumer", Consumer::default(), ConfigSource::inline("<consumer>", text.clone()))
            }
            other => Err(format!("this host runs 'consumer' only, not '{other}'")),
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let thread = std::thread::spawn(move || net::remote::serve_host(&cfg, host, &s, || ()).unwrap());
        // The listener is up once a connection succeeds.
        for _ in 0..100 {
            if std::net::TcpStream::connect(endpoint.trim_start_matches("tcp/")).is_ok() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        Host { stop, thread: Some(thread) }
    }
    fn kill(mut self) -> net::remote::HostStats {
        self.stop.store(true, Ordering::SeqCst);
        self.thread.take().unwrap().join().unwrap()
    }
}

/// Every slot's record and every event, as JSON text.
fn outputs(ex: &LockstepExecutor) -> (Vec<String>, Vec<String>) {
    let core = ex.core();
    let slots = core
        .board
        .names()
        .iter()
        .map(|n| format!("{n} {:?}", core.board.slot(n).unwrap().to_json()))
        .collect();
    let events = core.events.snapshot().iter().map(|e| serde_json::to_string(e).unwrap()).collect();
    (slots, events)
}

fn run(ex: &mut LockstepExecutor) {
    ex.walk_to(Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(300));
    let g = ex.endpoint("ground").unwrap();
    g.send(
        Command::new("consumer", "set_meta")
            .json(serde_json::json!({"state": "summing", "implementation": "double"})),
    )
    .unwrap();
    ex.run_for(Duration::from_millis(300));
    ex.walk_to(Lifecycle::Hold).unwrap();
    ex.run_for(Duration::from_millis(50));
}

#[test]
fn a_remote_module_gives_the_all_local_results_bit_for_bit() {
    let mut local = system(None);
    run(&mut local);
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let host = Host::start(&endpoint);
    let mut remote = system(Some(&endpoint));
    run(&mut remote);
    let (ls, le) = outputs(&local);
    let (rs, re) = outputs(&remote);
    assert_eq!(ls, rs, "slots");
    assert_eq!(le, re, "events");
    // The same host serves a second run of the core: it starts afresh, with the same results.
    let mut again = system(Some(&endpoint));
    run(&mut again);
    assert_eq!(outputs(&again), (ls.clone(), le.clone()), "a second run on the same host");
    let sum = &ls.iter().find(|s| s.starts_with("consumer/sum")).unwrap();
    assert!(!sum.contains("None"), "{sum}");
    let consumer = remote.reports().into_iter().find(|r| r.name == "consumer").unwrap();
    assert_eq!(consumer.meta_states["summing"], "double");
    assert_eq!(consumer.lifecycle, Lifecycle::Hold);
    let stats = host.kill();
    assert_eq!(stats.hellos, 2);
    assert!(stats.ticks > 60, "{stats:?}");
}

#[test]
fn a_dead_host_puts_its_module_in_safe_the_rest_goes_on_and_a_restarted_host_brings_it_back() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let host = Host::start(&endpoint);
    let mut ex = system(Some(&endpoint));
    ex.walk_to(Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(200));
    let sum_before = read_u64(&ex, "consumer/sum");
    host.kill();
    ex.run_for(Duration::from_millis(300));
    let consumer = ex.reports().into_iter().find(|r| r.name == "consumer").unwrap();
    assert!(consumer.isolated && consumer.lifecycle == Lifecycle::Safe, "{consumer:?}");
    let isolated: Vec<_> = ex
        .core()
        .events
        .snapshot()
        .into_iter()
        .filter_map(|e| match e.kind {
            EventKind::ModuleIsolated { module, fault: Fault::Remote(why) } => Some((module, why)),
            _ => None,
        })
        .collect();
    assert_eq!(isolated.len(), 1, "{isolated:?}");
    assert!(isolated[0].0 == "consumer" && isolated[0].1.contains(&endpoint), "{isolated:?}");
    // The producer went on; the commands it sent meanwhile failed, naming the host.
    assert_eq!(read_u64(&ex, "producer/count"), 50);
    let acks = ex.core().board.reader::<(u64, u64)>("producer/acks").unwrap().unwrap().read().unwrap().value;
    assert!(acks.1 > 0, "failed commands counted: {acks:?}");
    // The host comes back. A command other than a lifecycle one does not reconnect the module: it
    // fails, naming why, and the module stays in Safe.
    let host = Host::start(&endpoint);
    let g = ex.endpoint("ground").unwrap();
    let add = g.send(Command::new("consumer", "add").json(serde_json::json!({ "n": 1 }))).unwrap();
    ex.run_for(Duration::from_millis(50));
    let Some(AckStatus::Failed(why)) = g.status(add) else { panic!("{:?}", g.status(add)) };
    assert!(why.contains("take it out of Safe"), "{why}");
    assert_eq!(ex.reports().into_iter().find(|r| r.name == "consumer").unwrap().lifecycle, Lifecycle::Safe);
    // The operator takes it out of Safe and back to Run: it reconnects.
    ex.module_transition("consumer", Lifecycle::Standby).unwrap();
    ex.module_transition("consumer", Lifecycle::Hold).unwrap();
    ex.module_transition("consumer", Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(200));
    let consumer = ex.reports().into_iter().find(|r| r.name == "consumer").unwrap();
    assert!(!consumer.isolated && consumer.lifecycle == Lifecycle::Run, "{consumer:?}");
    assert!(read_u64(&ex, "consumer/sum") > 0 && sum_before > 0);
    let stats = host.kill();
    assert_eq!(stats.hellos, 1, "{stats:?}");
}

fn read_u64(ex: &LockstepExecutor, slot: &str) -> u64 {
    ex.core().board.reader::<u64>(slot).unwrap().unwrap().read().map(|s| s.value).unwrap_or(0)
}
