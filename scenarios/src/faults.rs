//! The twin's fault injector: a simulation-side module that takes fault-injection commands on its
//! debug queue and applies them to the twin (seed 000, 6.5: failure injection in the Debug context).
//!
//! - `stall_wheel {wheel, stalled = true}`: jams (or frees) a wheel drive;
//! - `dropout {device, duration_s}`: a sensor (`imu`, `encoders`, a camera) delivers no new data.
//!
//! Module crashes are injected with the framework's own `inject_fault` command, sent to the module.

use framework::prelude::*;
use serde::Deserialize;
use twin::devices::SharedTwin;

/// Module name the scenarios use.
pub const NAME: &str = "twin_faults";

/// Arguments of `stall_wheel`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Stall {
    wheel: String,
    #[serde(default = "yes")]
    stalled: bool,
}

fn yes() -> bool {
    true
}

/// Arguments of `dropout`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Dropout {
    device: String,
    duration_s: f64,
}

/// The fault injector.
pub struct TwinFaults {
    twin: SharedTwin,
}

impl TwinFaults {
    /// An injector acting on `twin`.
    pub fn new(twin: SharedTwin) -> Self {
        TwinFaults { twin }
    }
}

fn on_debug_queue(ctx: &Ctx<'_>) -> Result<(), Outcome> {
    match ctx.request() {
        Some(r) if r.queue() == Queue::Debug => Ok(()),
        _ => Err(Outcome::reject("fault injections are accepted only on the debug queue")),
    }
}

impl Module for TwinFaults {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::External;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        d.command("stall_wheel", |m, ctx, a: Stall| {
            if let Err(o) = on_debug_queue(ctx) {
                return o;
            }
            match m.twin.lock().set_wheel_stalled(&a.wheel, a.stalled) {
                Ok(()) => {
                    ctx.note(format!(
                        "injected: wheel '{}' {}",
                        a.wheel,
                        if a.stalled { "jammed" } else { "freed" }
                    ));
                    Outcome::done()
                }
                Err(e) => Outcome::reject(e),
            }
        });
        d.command("dropout", |m, ctx, a: Dropout| {
            if let Err(o) = on_debug_queue(ctx) {
                return o;
            }
            if !(a.duration_s.is_finite() && a.duration_s > 0.0) {
                return Outcome::reject(format!("duration_s must be positive, got {}", a.duration_s));
            }
            let until = ctx.now() + Duration::from_secs_f64(a.duration_s);
            m.twin.lock().set_dropout(&a.device, until);
            ctx.note(format!("injected: '{}' silent for {} s", a.device, a.duration_s));
            Outcome::done()
        });
    }
}
