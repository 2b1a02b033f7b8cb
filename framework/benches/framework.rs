//! `cargo bench -p framework`: costs of the framework's hot paths.
//!
//! - `blackboard_read`, `blackboard_write_read`: one slot read; one write followed by one read.
//! - `message_send_dispatch_ack`: an endpoint sends a command, the lockstep executor dispatches it to
//!   an aperiodic module's typed handler, the acknowledgement travels back and is polled.
//! - `scheduler_tick_per_module`: one lockstep tick over 100 periodic modules with empty state
//!   functions, counted per module (divan's items/s is module ticks per second; time / 100 is the
//!   overhead per module tick).
//!
//! Targets on the 2-core CI machine: read < 100 ns, dispatch < 2 us, scheduler < 1 us per module tick.

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use framework::message::ModuleId;
use framework::prelude::*;
use framework::{BlackBoard, Executor, LockstepExecutor, SystemBuilder};

fn main() {
    divan::main();
}

#[divan::bench]
fn blackboard_read(b: Bencher<'_, '_>) {
    let bb = BlackBoard::new();
    let w = bb.declare_writer::<[f64; 7]>("pose", ModuleId(0)).unwrap();
    let r = bb.declare_reader::<[f64; 7]>("pose", ModuleId(1)).unwrap();
    w.write([1.0; 7], Time::ZERO);
    b.bench_local(|| black_box(r.read()));
}

#[divan::bench]
fn blackboard_write_read(b: Bencher<'_, '_>) {
    let bb = BlackBoard::new();
    let w = bb.declare_writer::<[f64; 7]>("pose", ModuleId(0)).unwrap();
    let r = bb.declare_reader::<[f64; 7]>("pose", ModuleId(1)).unwrap();
    let mut t = 0;
    b.bench_local(|| {
        t += 1;
        w.write([t as f64; 7], Time::from_nanos(t));
        black_box(r.read())
    });
}

#[derive(Default)]
struct Sink {
    total: f64,
}

#[derive(serde::Deserialize)]
struct Speed {
    v: f64,
}

impl Module for Sink {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Actuator;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.command("set_speed", |m, _ctx, a: Speed| {
            m.total += a.v;
            Outcome::done()
        });
    }
}

#[divan::bench]
fn message_send_dispatch_ack(b: Bencher<'_, '_>) {
    let mut sb = SystemBuilder::new();
    sb.add_inline("sink", Sink::default(), "");
    sb.endpoint("ground");
    let mut ex = LockstepExecutor::new(sb, Duration::from_millis(1)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let g = ex.endpoint("ground").unwrap();
    let args = serde_json::json!({ "v": 0.5 });
    b.bench_local(|| {
        g.send(Command::new("sink", "set_speed").json(args.clone())).unwrap();
        ex.tick();
        black_box(g.poll())
    });
}

#[derive(Default)]
struct Idle;
impl Module for Idle {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.state("idle", |_m, _c| Ok(()));
    }
}

#[divan::bench]
fn scheduler_tick_per_module(b: Bencher<'_, '_>) {
    const N: usize = 100;
    let mut sb = SystemBuilder::new();
    for i in 0..N {
        sb.add_inline(&format!("m{i}"), Idle, "[framework]\nperiod_s = 0.001\n");
    }
    let mut ex = LockstepExecutor::new(sb, Duration::from_millis(1)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    b.counter(ItemsCount::new(N)).bench_local(|| black_box(ex.tick()));
}
