//! The twin's fault injector: a simulation-side module that takes fault-injection commands on its
//! debug queue and applies them to the twin (seed 000, 6.5: failure injection in the Debug context).
//!
//! - `stall_wheel {wheel, stalled = true, duration_s}`: jams (or frees) a wheel drive, for good or
//!   for `duration_s` (a stone caught in it);
//! - `dropout {device, duration_s}`: a sensor (`imu`, `encoders`, a camera) delivers no new data;
//! - `slip_grasp {count = 1}`: the next `count` closings of the gripper on the handle do not hold it;
//! - `joint_fault {group, reason}`: a joint group's motors go to FAULT (a servo trip), until the
//!   group's `recover`.
//!
//! Module crashes are injected with the framework's own `inject_fault` command, sent to the module.
//! The scenario's debug events reach both through the Debugger.

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
    #[serde(default)]
    duration_s: Option<f64>,
}

/// Arguments of `slip_grasp`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Slip {
    #[serde(default = "one")]
    count: u32,
}

fn one() -> u32 {
    1
}

/// Arguments of `joint_fault`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JointFault {
    group: String,
    #[serde(default = "trip")]
    reason: String,
}

fn trip() -> String {
    "injected servo trip".into()
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
            let r = match a.duration_s {
                Some(d) if !(d.is_finite() && d > 0.0) => {
                    return Outcome::reject(format!("duration_s must be positive, got {d}"));
                }
                Some(d) if a.stalled => {
                    m.twin.lock().set_wheel_stalled_until(&a.wheel, ctx.now() + Duration::from_secs_f64(d))
                }
                _ => m.twin.lock().set_wheel_stalled(&a.wheel, a.stalled),
            };
            match r {
                Ok(()) => {
                    let what = match (a.stalled, a.duration_s) {
                        (false, _) => "freed".to_string(),
                        (true, None) => "jammed".to_string(),
                        (true, Some(d)) => format!("jammed for {d} s"),
                    };
                    ctx.note(format!("injected: wheel '{}' {what}", a.wheel));
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
        d.command("slip_grasp", |m, ctx, a: Slip| {
            if let Err(o) = on_debug_queue(ctx) {
                return o;
            }
            m.twin.lock().slip_next_grasps(a.count);
            ctx.note(format!("injected: the next {} grasp(s) slip", a.count));
            Outcome::done()
        });
        d.command("joint_fault", |m, ctx, a: JointFault| {
            if let Err(o) = on_debug_queue(ctx) {
                return o;
            }
            match m.twin.lock().fault_group(&a.group, &a.reason) {
                Ok(()) => {
                    ctx.note(format!("injected: '{}' in FAULT ({})", a.group, a.reason));
                    Outcome::done()
                }
                Err(e) => Outcome::reject(e),
            }
        });
    }
}
