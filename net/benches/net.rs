//! `cargo bench -p net`: the network layer's costs and its decoder's robustness.
//!
//! - `frame_decoder_fuzz_1m`: one million hostile frames (random bytes, valid headers on random
//!   bodies, valid frames with flipped bits, truncations, lengths that lie) through the decoder;
//!   every case must return (an error or a valid message), none may panic. Time is per million.
//! - `frame_encode_decode`: one console request encoded and decoded.
//! - `console_query_round_trip`: a console's `status` query answered by a system's server over
//!   loopback TCP (Zenoh), one request and one reply.
//! - `console_command_ack_round_trip`: a command sent through the console to a module, answered
//!   with its final acknowledgement, the lockstep system ticking as fast as it can meanwhile.
//! - `zenoh_query_floor`, `zenoh_put_ping_pong_floor`: Zenoh's own round trips on the same
//!   loopback sessions, answered in a callback with nothing of ours in between: the floor the two
//!   console figures stand on. Compare the console figures with these, measured in the same run.
//!
//! Target: command and acknowledgement round trip under 200 us on loopback.

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use framework::prelude::*;
use framework::{Executor, LockstepExecutor, SystemBuilder};
use net::frame::{self, DEFAULT_MAX_FRAME_BYTES};
use net::protocol::{ConsoleReply, ConsoleRequest};
use net::{ConsoleClient, ConsoleServer, NetConfig};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

fn main() {
    divan::main();
}

/// xorshift64*: a bench-local generator (the workspace's seeded RNGs are for the simulation).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn sample() -> ConsoleRequest {
    ConsoleRequest::Send {
        module: "locomotion".into(),
        command: "goto".into(),
        args_json: r#"{"x": 4.0, "y": -2.5, "tolerance_m": 0.3}"#.into(),
        queue: "nominal".into(),
        via: vec!["autonomy".into()],
        wait_s: 0.0,
    }
}

/// The `i`th hostile case.
fn hostile(rng: &mut Rng, valid: &[u8], out: &mut Vec<u8>) {
    out.clear();
    match rng.below(5) {
        0 => (0..rng.below(96)).for_each(|_| out.push(rng.next() as u8)),
        1 => {
            out.extend_from_slice(&valid[..frame::HEADER_BYTES]);
            let n = rng.below(96);
            out[16..20].copy_from_slice(&(n as u32).to_le_bytes());
            (0..n).for_each(|_| out.push(rng.next() as u8));
        }
        2 => {
            out.extend_from_slice(valid);
            for _ in 0..1 + rng.below(3) {
                let i = rng.below(out.len());
                out[i] ^= 1 << rng.below(8);
            }
        }
        3 => out.extend_from_slice(&valid[..rng.below(valid.len())]),
        _ => {
            out.extend_from_slice(valid);
            let lie = rng.next() as u32;
            out[16..20].copy_from_slice(&lie.to_le_bytes());
        }
    }
}

#[divan::bench(sample_count = 1, sample_size = 1)]
fn frame_decoder_fuzz_1m(b: Bencher<'_, '_>) {
    const CASES: u64 = 1_000_000;
    let valid = frame::encode(&sample());
    b.counter(ItemsCount::new(CASES)).bench_local(|| {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let mut buf = Vec::with_capacity(256);
        let (mut ok, mut err) = (0u64, 0u64);
        for _ in 0..CASES {
            hostile(&mut rng, &valid, &mut buf);
            let r = std::panic::catch_unwind(|| {
                frame::decode::<ConsoleRequest>(&buf, DEFAULT_MAX_FRAME_BYTES).is_ok()
            });
            match r {
                Ok(true) => ok += 1,
                Ok(false) => err += 1,
                Err(_) => panic!("the decoder panicked on {buf:02x?}"),
            }
        }
        assert_eq!(ok + err, CASES);
        println!(
            "frame_decoder_fuzz_1m: {CASES} cases, {err} refused, {ok} decoded to a valid message, 0 panics"
        );
    });
}

#[divan::bench]
fn frame_encode_decode(b: Bencher<'_, '_>) {
    let req = sample();
    b.bench_local(|| {
        let f = frame::encode(black_box(&req));
        frame::decode::<ConsoleRequest>(&f, DEFAULT_MAX_FRAME_BYTES).unwrap()
    });
}

#[derive(Default)]
struct Echo;

impl Module for Echo {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.state("idle", |_, _| Ok(()));
    }
}

/// A lockstep system ticking as fast as it can, served between ticks, until dropped.
struct Served {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
    cfg: NetConfig,
}

impl Served {
    fn start() -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let cfg = NetConfig { endpoint: format!("tcp/127.0.0.1:{port}"), ..NetConfig::default() };
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, rx) = std::sync::mpsc::channel();
        let (s, c) = (stop.clone(), cfg.clone());
        let thread = std::thread::spawn(move || {
            let mut b = SystemBuilder::new();
            b.add_inline("echo", Echo, "[framework]\nperiod_s = 0.001\n");
            b.endpoint("console");
            let mut ex = LockstepExecutor::new(b, Duration::from_millis(1)).unwrap();
            ex.walk_to(Lifecycle::Run).unwrap();
            let mut server = ConsoleServer::open(&c, ex.endpoint("console").unwrap()).unwrap();
            tx.send(()).unwrap();
            while !s.load(Ordering::SeqCst) {
                server.serve(&mut ex, &s);
                ex.tick();
            }
        });
        rx.recv().unwrap();
        Served { stop, thread: Some(thread), cfg }
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[divan::bench(sample_count = 200)]
fn console_query_round_trip(b: Bencher<'_, '_>) {
    let served = Served::start();
    let c = ConsoleClient::connect(&served.cfg).unwrap();
    b.bench_local(|| assert!(c.request(&ConsoleRequest::Status).unwrap().ok));
}

#[divan::bench(sample_count = 200)]
fn console_command_ack_round_trip(b: Bencher<'_, '_>) {
    let served = Served::start();
    let c = ConsoleClient::connect(&served.cfg).unwrap();
    let ping = ConsoleRequest::Send {
        module: "echo".into(),
        command: "ping".into(),
        args_json: "null".into(),
        queue: "nominal".into(),
        via: vec![],
        wait_s: 5.0,
    };
    b.bench_local(|| {
        let r: ConsoleReply = c.request(&ping).unwrap();
        assert!(r.json.contains("\"final\":true"), "{r:?}");
    });
}

/// Zenoh's own floor under the console: a query over loopback answered in the queryable's callback
/// (no system, no frame decoding), with the same sessions as the console's.
#[divan::bench(sample_count = 200)]
fn zenoh_query_floor(b: Bencher<'_, '_>) {
    use zenoh::Wait;
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let cfg = NetConfig { endpoint: format!("tcp/127.0.0.1:{port}"), ..NetConfig::default() };
    let server = net::link::listen(&cfg).unwrap();
    let key = cfg.console_key();
    let _q = server
        .declare_queryable(&key)
        .callback(|q| {
            let _ = q.reply(q.key_expr().clone(), vec![0u8; 32]).wait();
        })
        .wait()
        .unwrap();
    let client = net::link::connect(&cfg).unwrap();
    b.bench_local(|| {
        let r = client.get(&key).payload(vec![0u8; 32]).wait().unwrap();
        r.recv().unwrap()
    });
}

/// Zenoh's floor for a put answered by a put: the request published to a subscriber whose callback
/// publishes the answer to the requester's subscriber.
#[divan::bench(sample_count = 200)]
fn zenoh_put_ping_pong_floor(b: Bencher<'_, '_>) {
    use zenoh::Wait;
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let cfg = NetConfig { endpoint: format!("tcp/127.0.0.1:{port}"), ..NetConfig::default() };
    let server = net::link::listen(&cfg).unwrap();
    let answer = server.declare_publisher("bench/answer").express(true).wait().unwrap();
    let _s = server
        .declare_subscriber("bench/request")
        .callback(move |s| {
            let _ = answer.put(s.payload().to_bytes().into_owned()).wait();
        })
        .wait()
        .unwrap();
    let client = net::link::connect(&cfg).unwrap();
    let answers = client.declare_subscriber("bench/answer").wait().unwrap();
    let request = client.declare_publisher("bench/request").express(true).wait().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(300));
    b.bench_local(|| {
        request.put(vec![0u8; 32]).wait().unwrap();
        answers.recv().unwrap()
    });
}
