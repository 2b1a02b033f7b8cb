//! `cargo bench -p net --bench remote`: what running a module remotely costs a lockstep tick.
//!
//! A two-module system (a producer writing a slot each tick, a consumer reading it and answering
//! a command every tenth tick), with the consumer local, then on a module host over loopback
//! (Zenoh, TCP), with the slot 8 bytes, then 64 KiB (what mirroring a bigger slot adds).
//!
//! - `tick_local`: one tick, both modules local.
//! - `tick_remote_8b`, `tick_remote_64kib`: one tick with the consumer remote: the lockstep
//!   overhead of one remote module per tick, slot mirroring included.

use divan::Bencher;
use framework::config::ConfigSource;
use framework::prelude::*;
use framework::remote::{HostBuilder, ModuleHost};
use framework::{Executor, LockstepExecutor, SystemBuilder};
use net::NetConfig;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

fn main() {
    divan::main();
}

#[derive(Default)]
struct Producer {
    bytes: usize,
    n: u64,
    out: Option<Writer<Vec<u8>>>,
}

impl Module for Producer {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Sensor;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("producer/data"));
        d.sends_to("consumer");
        d.state("producing", |m, ctx| {
            m.n += 1;
            if let Some(w) = &m.out {
                ctx.write(w, vec![m.n as u8; m.bytes]);
            }
            if m.n % 10 == 0 {
                let _ = ctx.send(Command::new("consumer", "ping"));
            }
            Ok(())
        });
    }
}

#[derive(Default)]
struct Consumer {
    seen: u64,
    data: Option<Reader<Vec<u8>>>,
    out: Option<Writer<u64>>,
}

impl Module for Consumer {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.data = Some(d.reads("producer/data"));
        self.out = Some(d.writes("consumer/seen"));
        d.state("consuming", |m, ctx| {
            if let Some(v) = m.data.as_ref().and_then(|r| r.read()) {
                m.seen += v.value.len() as u64;
            }
            if let Some(w) = &m.out {
                ctx.write(w, m.seen);
            }
            Ok(())
        });
    }
}

fn consumer_config(host: Option<&str>) -> String {
    let host = host.map(|h| format!("host = \"{h}\"\n")).unwrap_or_default();
    format!("[framework]\nperiod_s = 0.01\n{host}")
}

struct Served {
    ex: LockstepExecutor,
    stop: Arc<AtomicBool>,
    host: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Served {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.host.take() {
            let _ = h.join();
        }
    }
}

fn system(bytes: usize, remote: bool) -> Served {
    let stop = Arc::new(AtomicBool::new(false));
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let host = remote.then(|| {
        let cfg = NetConfig { endpoint: endpoint.clone(), ..NetConfig::default() };
        let text = consumer_config(Some(&endpoint));
        let host = ModuleHost::new(Box::new(move |name: &str, b: &mut HostBuilder| {
            b.add(name, Consumer::default(), ConfigSource::inline("<consumer>", text.clone()))
        }));
        let s = stop.clone();
        let h = std::thread::spawn(move || {
            net::remote::serve_host(&cfg, host, &s, || ()).unwrap();
        });
        for _ in 0..100 {
            if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        h
    });
    let mut b = SystemBuilder::new();
    b.add_inline("producer", Producer { bytes, ..Default::default() }, "[framework]\nperiod_s = 0.01\n");
    let host_name = remote.then_some(endpoint.as_str());
    b.add("consumer", Consumer::default(), ConfigSource::inline("<consumer>", consumer_config(host_name)));
    b.remote_links(net::remote::link_factory(&NetConfig::default()));
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(10)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    ex.run_for(Duration::from_millis(100));
    Served { ex, stop, host }
}

#[divan::bench(sample_count = 300)]
fn tick_local(b: Bencher<'_, '_>) {
    let mut s = system(8, false);
    b.bench_local(|| s.ex.tick());
}

#[divan::bench(sample_count = 300)]
fn tick_remote_8b(b: Bencher<'_, '_>) {
    let mut s = system(8, true);
    b.bench_local(|| s.ex.tick());
}

#[divan::bench(sample_count = 300)]
fn tick_remote_64kib(b: Bencher<'_, '_>) {
    let mut s = system(64 << 10, true);
    b.bench_local(|| s.ex.tick());
}
