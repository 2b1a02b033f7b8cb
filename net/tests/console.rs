//! A console attached over Zenoh on loopback to a lockstep system served between ticks: every
//! request kind, pause and step, hostile frames, and authentication.

use framework::prelude::*;
use framework::{Executor, LockstepExecutor, SystemBuilder};
use net::protocol::{ConsoleReply, ConsoleRequest};
use net::{ConsoleClient, ConsoleServer, NetConfig, NetError};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Counts its cycles into `counter/count`; `add {n}` adds to `counter/total`.
#[derive(Default)]
struct Counter {
    count: u64,
    total: u64,
    out: Option<Writer<u64>>,
    sum: Option<Writer<u64>>,
}

#[derive(serde::Deserialize)]
struct Add {
    n: u64,
}

impl Module for Counter {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("counter/count"));
        self.sum = Some(d.writes("counter/total"));
        d.meta_state("counting", &[("by_one", |m, ctx| m.cycle(ctx)), ("quietly", |m, ctx| m.cycle(ctx))]);
        d.command("add", |m, ctx, a: Add| {
            m.total += a.n;
            if let Some(w) = &m.sum {
                ctx.write(w, m.total);
            }
            Outcome::done()
        });
    }
}

impl Counter {
    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        self.count += 1;
        if let Some(w) = &self.out {
            ctx.write(w, self.count);
        }
        Ok(())
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn config(port: u16) -> NetConfig {
    NetConfig {
        endpoint: format!("tcp/127.0.0.1:{port}"),
        timeout_s: 2.0,
        max_frame_bytes: 64 << 10,
        ..NetConfig::default()
    }
}

/// A system served on its own thread until `stop`, starting paused.
struct Served {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<net::server::ServerStats>>,
}

impl Served {
    fn start(cfg: NetConfig) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let s = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut b = SystemBuilder::new();
            b.add_inline("counter", Counter::default(), "[framework]\nperiod_s = 0.01\n");
            b.endpoint("console");
            let mut ex = LockstepExecutor::new(b, Duration::from_millis(10)).unwrap();
            ex.walk_to(Lifecycle::Run).unwrap();
            let mut server = ConsoleServer::open(&cfg, ex.endpoint("console").unwrap()).unwrap();
            server.pause();
            ready_tx.send(()).unwrap();
            while !s.load(Ordering::SeqCst) {
                server.serve(&mut ex, &s);
                if !s.load(Ordering::SeqCst) {
                    ex.tick();
                }
            }
            server.stats()
        });
        ready_rx.recv_timeout(std::time::Duration::from_secs(20)).expect("server up");
        Served { stop, thread: Some(thread) }
    }
    fn stop(mut self) -> net::server::ServerStats {
        self.stop.store(true, Ordering::SeqCst);
        self.thread.take().unwrap().join().unwrap()
    }
}

fn ask(c: &ConsoleClient, line: &str) -> ConsoleReply {
    let req = ConsoleRequest::parse(line).unwrap().unwrap();
    c.request(&req).unwrap()
}

fn json(r: &ConsoleReply) -> serde_json::Value {
    serde_json::from_str(&r.json).unwrap()
}

#[test]
fn a_console_lists_sends_reads_steps_pauses_resumes_and_drives_the_lifecycle() {
    let cfg = config(free_port());
    let served = Served::start(cfg.clone());
    let c = ConsoleClient::connect(&cfg).unwrap();

    let s = ask(&c, "status");
    assert!(s.ok && json(&s)["paused"] == true && json(&s)["system"] == "Run", "{s:?}");
    let t0 = json(&s)["time_s"].as_f64().unwrap();

    let m = ask(&c, "modules");
    assert!(m.text.contains("counter") && m.text.contains("counting=by_one"), "{}", m.text);
    assert_eq!(json(&m)[0]["lifecycle"], "Run");
    assert_eq!(json(&m)[0]["meta_states"]["counting"], "by_one");

    // A command sent while paused is acknowledged once time runs.
    let sent = ask(&c, "send counter add {\"n\": 5}");
    assert!(sent.ok, "{sent:?}");
    let id = &json(&sent)["id"];
    let ack_line = format!("ack {}.{}", id["sender"], id["seq"]);
    assert_eq!(json(&ask(&c, &ack_line))["final"], false);
    let stepped = ask(&c, "step 3");
    assert!(stepped.ok, "{stepped:?}");
    assert!((json(&stepped)["time_s"].as_f64().unwrap() - (t0 + 0.03)).abs() < 1e-9, "{stepped:?}");
    let ack = ask(&c, &ack_line);
    assert_eq!(json(&ack)["final"], true, "{ack:?}");
    assert!(ack.text.contains("completed"), "{}", ack.text);
    assert_eq!(json(&ask(&c, "read counter/total"))["value"], 5);
    assert_eq!(json(&ask(&c, "read counter/count"))["value"], 3, "three ticks, three cycles");
    assert!(ask(&c, "slots").text.contains("counter/total"));

    // A command that waits for its final acknowledgement: answered once time has run.
    let waiter = {
        let cfg = cfg.clone();
        std::thread::spawn(move || {
            let c2 = ConsoleClient::connect(&cfg).unwrap();
            let req = ConsoleRequest::Send {
                module: "counter".into(),
                command: "add".into(),
                args_json: r#"{"n": 2}"#.into(),
                queue: "nominal".into(),
                via: vec![],
                wait_s: 1.5,
            };
            c2.request(&req).unwrap()
        })
    };
    std::thread::sleep(std::time::Duration::from_millis(300));
    ask(&c, "step 2");
    let done = waiter.join().unwrap();
    assert_eq!(json(&done)["final"], true, "{done:?}");
    assert_eq!(json(&done)["status"]["status"], "completed");
    assert_eq!(json(&ask(&c, "read counter/total"))["value"], 7);

    // Meta-state switch through a framework command, seen in the listing.
    ask(&c, "send counter set_meta {\"state\": \"counting\", \"implementation\": \"quietly\"}");
    ask(&c, "step 1");
    assert_eq!(json(&ask(&c, "modules"))[0]["meta_states"]["counting"], "quietly");

    // Lifecycle: the system to Hold and back, one module to Standby and back.
    assert_eq!(json(&ask(&c, "system hold"))["system"], "Hold");
    assert!(!ask(&c, "system shutdown").ok, "Hold -> Shutdown is not a legal step");
    assert_eq!(json(&ask(&c, "walk run"))["system"], "Run");
    assert!(ask(&c, "module counter hold").ok);
    assert_eq!(json(&ask(&c, "modules"))[0]["lifecycle"], "Hold");
    assert!(ask(&c, "module counter run").ok);

    // Errors come back as answers, never as a broken link.
    assert!(!ask(&c, "read no/such/slot").ok);
    assert!(ask(&c, "send nobody ping").text.contains("nobody"));
    let bad = c
        .request(&ConsoleRequest::Send {
            module: "counter".into(),
            command: "add".into(),
            args_json: "{bad".into(),
            queue: "nominal".into(),
            via: vec![],
            wait_s: 0.0,
        })
        .unwrap();
    assert!(!bad.ok && bad.text.contains("not valid JSON"), "{bad:?}");

    // Resume: time runs without being stepped.
    let before = json(&ask(&c, "status"))["time_s"].as_f64().unwrap();
    assert!(ask(&c, "resume").ok);
    std::thread::sleep(std::time::Duration::from_millis(100));
    let after = json(&ask(&c, "pause"))["time_s"].as_f64().unwrap();
    assert!(after > before, "{before} -> {after}");
    assert!(!ask(&c, "step 0").ok);
    let stats = served.stop();
    assert_eq!((stats.refused, stats.dropped), (0, 0));
}

#[test]
fn garbage_oversized_and_incompatible_frames_are_dropped_or_refused_and_the_server_goes_on() {
    let cfg = config(free_port());
    let served = Served::start(cfg.clone());
    let c = ConsoleClient::connect(&cfg).unwrap();
    // Garbage and an oversized frame: dropped, the client times out.
    assert!(matches!(c.request_raw(b"hello, rover".to_vec()), Err(NetError::Timeout(..))));
    let mut huge = net::frame::encode(&ConsoleRequest::Read { slot: "x".repeat(100 << 10) });
    assert!(matches!(c.request_raw(huge.clone()), Err(NetError::Timeout(..))));
    // A frame whose schema differs (another build of the message types): refused, saying why.
    huge.truncate(0);
    let mut other = net::frame::encode(&ConsoleRequest::Status);
    other[8] ^= 0xff;
    let refused = net::frame::decode::<ConsoleReply>(&c.request_raw(other).unwrap(), 1 << 20).unwrap_err();
    assert!(refused.to_string().contains("incompatible peer"), "{refused}");
    // The server answers well-formed requests as before.
    assert!(ask(&c, "status").ok);
    let stats = served.stop();
    assert_eq!((stats.dropped, stats.refused), (2, 1), "{stats:?}");
}

#[test]
fn with_auth_only_peers_with_accepted_credentials_connect() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("users.txt"), "operator:s3cret\n").unwrap();
    let port = free_port();
    let file = |user: &str, password: &str, users: bool| {
        let p = dir.path().join(format!("{user}-{password}-{users}.toml"));
        let users = if users { "users_file = \"users.txt\"\n" } else { "" };
        std::fs::write(
            &p,
            format!(
                "endpoint = \"tcp/127.0.0.1:{port}\"\ntimeout_s = 2.0\n[auth]\nuser = \"{user}\"\npassword = \"{password}\"\n{users}"
            ),
        )
        .unwrap();
        NetConfig::load(&p).unwrap()
    };
    let served = Served::start(file("rover", "rover-pw", true));
    let wrong = ConsoleClient::connect(&file("operator", "guess", false));
    assert!(wrong.is_err(), "a wrong password is refused");
    let none = ConsoleClient::connect(&config(port));
    assert!(none.is_err(), "no credentials at all are refused");
    let right = ConsoleClient::connect(&file("operator", "s3cret", false)).unwrap();
    assert!(ask(&right, "status").ok);
    served.stop();
}

#[test]
fn a_configuration_that_listens_beyond_loopback_without_auth_is_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("net.toml");
    std::fs::write(&p, "endpoint = \"tcp/0.0.0.0:7447\"\n").unwrap();
    let e = NetConfig::load(&p).unwrap_err().to_string();
    assert!(e.contains("net.toml") && e.contains("endpoint") && e.contains("[auth]"), "{e}");
    std::fs::write(&p, "endpoint = \"tcp/127.0.0.1:7447\"\nmax_frame_bytes = 3\n").unwrap();
    assert!(NetConfig::load(&p).unwrap_err().to_string().contains("max_frame_bytes"));
}
