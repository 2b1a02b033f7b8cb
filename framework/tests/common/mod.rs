//! Small modules used by the framework's integration tests.
#![allow(dead_code, missing_docs)]

use framework::prelude::*;

/// Periodic source: in Run writes its cycle count to `<name>/count` and optionally sends `add` to a
/// sink every cycle.
#[derive(Default)]
pub struct Counter {
    pub out: Option<Writer<u64>>,
    pub n: u64,
    pub sink: Option<String>,
    pub stop_after: Option<u64>,
}

#[derive(Default, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CounterParams {
    #[serde(default)]
    pub sink: Option<String>,
    #[serde(default)]
    pub stop_after: Option<u64>,
}

impl Module for Counter {
    type Params = CounterParams;
    const KIND: ModuleKind = ModuleKind::Sensor;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes(&format!("{}/count", d.name())));
        if let Some(s) = &self.sink {
            d.sends_to(&s.clone());
        }
        d.state("counting", |m, ctx| {
            if m.stop_after.is_some_and(|s| m.n >= s) {
                return Ok(());
            }
            m.n += 1;
            let out = m.out.as_ref().unwrap();
            ctx.write(out, m.n);
            if let Some(s) = &m.sink {
                ctx.send(Command::new(s.clone(), "add").args(serde_json::json!({ "n": m.n })))
                    .map_err(|e| ModuleError(e.to_string()))?;
            }
            Ok(())
        });
        d.command("reset", |m, _ctx, _: ()| {
            m.n = 0;
            Outcome::done()
        });
    }
    fn configure(&mut self, p: &CounterParams) -> Result<(), String> {
        if p.sink.is_some() {
            self.sink = p.sink.clone();
        }
        if p.stop_after.is_some() {
            self.stop_after = p.stop_after;
        }
        Ok(())
    }
}

/// Aperiodic sink: sums what it is sent and publishes the sum; records the order of commands.
#[derive(Default)]
pub struct Accumulator {
    pub sum: u64,
    pub out: Option<Writer<u64>>,
    pub log: Option<Writer<Vec<String>>>,
    pub seen: Vec<String>,
}

#[derive(serde::Deserialize)]
pub struct AddArgs {
    pub n: u64,
}

impl Module for Accumulator {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes(&format!("{}/sum", d.name())));
        self.log = Some(d.writes(&format!("{}/log", d.name())));
        d.command("add", |m, ctx, a: AddArgs| {
            m.sum += a.n;
            m.seen.push(format!("add{}", a.n));
            let (out, log) = (m.out.as_ref().unwrap(), m.log.as_ref().unwrap());
            ctx.write(out, m.sum);
            ctx.write(log, m.seen.clone());
            Outcome::Completed(serde_json::json!(m.sum))
        });
        d.command("mark", |m, ctx, a: String| {
            m.seen.push(a);
            let log = m.log.as_ref().unwrap();
            ctx.write(log, m.seen.clone());
            Outcome::done()
        });
        d.command("debug_note", |_m, ctx, _: ()| {
            ctx.note("debug note");
            Outcome::done()
        });
        d.command("slow_job", |m, ctx, _: ()| {
            // Accepted now, completed at the next cycle.
            m.seen.push("slow_job".into());
            PENDING.with(|p| p.borrow_mut().push(ctx.request().unwrap()));
            Outcome::Accepted
        });
        d.state("idle", |_m, ctx| {
            let pending: Vec<_> = PENDING.with(|p| p.borrow_mut().drain(..).collect());
            for r in pending {
                ctx.reply(&r, Outcome::Completed(serde_json::json!("finished")));
            }
            Ok(())
        });
    }
}

thread_local! {
    static PENDING: std::cell::RefCell<Vec<framework::module::Request>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Module whose state function panics when `boom` says so, or returns an error.
#[derive(Default)]
pub struct Fragile {
    pub cycles: u64,
    pub out: Option<Writer<u64>>,
}

impl Module for Fragile {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("fragile/cycles"));
        d.state("working", |m, ctx| {
            m.cycles += 1;
            let o = m.out.as_ref().unwrap();
            ctx.write(o, m.cycles);
            if m.cycles == 5 {
                panic!("sensor buffer overflow at cycle 5");
            }
            Ok(())
        });
        d.state("failing", |_m, _ctx| Err("cannot read device".into()));
        d.transition("working", "failing");
        d.command("fail", |_m, ctx, _: ()| match ctx.goto("failing") {
            Ok(()) => Outcome::done(),
            Err(e) => Outcome::reject(e.to_string()),
        });
    }
}

/// Module declaring a simulated cost per cycle, to overrun deterministically.
#[derive(Default)]
pub struct Heavy {
    pub cost_ms: i64,
}

#[derive(Default, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeavyParams {
    pub cost_ms: i64,
}

impl Module for Heavy {
    type Params = HeavyParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.state("work", |m, ctx| {
            ctx.charge(Duration::from_millis(m.cost_ms));
            Ok(())
        });
        d.command("set_cost", |m, _ctx, ms: i64| {
            m.cost_ms = ms;
            Outcome::done()
        });
    }
    fn configure(&mut self, p: &HeavyParams) -> Result<(), String> {
        if p.cost_ms < 0 {
            return Err(format!("cost_ms must be >= 0, got {}", p.cost_ms));
        }
        self.cost_ms = p.cost_ms;
        Ok(())
    }
}

pub fn periodic(period_s: f64) -> String {
    format!("[framework]\nperiod_s = {period_s}\n")
}

pub fn debug_periodic(period_s: f64) -> String {
    format!("[framework]\nperiod_s = {period_s}\ncontext = {{ mode = \"dry-run\", purpose = \"debug\" }}\n")
}

pub fn read<T: framework::blackboard::BoardData + Clone>(
    core: &framework::system::Core,
    slot: &str,
) -> Option<T> {
    core.board.reader::<T>(slot).unwrap().and_then(|r| r.read()).map(|s| s.value.clone())
}
