//! The framework demo: four modules of a rover's heading loop exchanging data and commands.
//!
//! This is a demonstration of the framework, not of the rover: the "gyro" turns the commanded yaw
//! rate into a measured rate with a constant bias and white noise from a seeded generator (no
//! physics yet). What it shows is real framework behaviour:
//! - `gyro` (sensor, 100 Hz) reads the locomotion command from the blackboard and publishes a rate;
//! - `heading` (resource, 50 Hz) integrates it into a heading estimate with growing variance;
//! - `navigator` (coordination, 10 Hz) accepts `turn_to {heading_deg}` from the ground, steers with
//!   a meta-state (`bang_bang` or `proportional`, switchable at runtime) by sending `set_yaw_rate`
//!   commands to `locomotion`, and completes the ground's command when it arrives (deferred ack);
//! - `locomotion` (actuator, aperiodic) applies commanded rates within its limit, refusing out of
//!   range ones, and publishes the command in force.

use framework::estimate::Estimate;
use framework::module::Request;
use framework::prelude::*;
use serde::{Deserialize, Serialize};

/// Publishes the measured yaw rate.
pub struct Gyro {
    cmd: Option<Reader<f64>>,
    out: Option<Writer<f64>>,
    params: GyroParams,
    rng: u64,
}

/// Gyro parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GyroParams {
    /// Constant bias, rad/s.
    pub bias: f64,
    /// White-noise standard deviation, rad/s.
    pub noise: f64,
    /// Seed of the noise generator.
    pub seed: u64,
}

impl Default for GyroParams {
    fn default() -> Self {
        GyroParams { bias: 0.002, noise: 0.001, seed: 1 }
    }
}

impl Default for Gyro {
    fn default() -> Self {
        Gyro { cmd: None, out: None, params: GyroParams::default(), rng: 1 }
    }
}

impl Gyro {
    /// Uniform noise in [-1, 1) from a SplitMix64 stream (seeded, deterministic).
    fn noise(&mut self) -> f64 {
        let z = framework::seed::splitmix64(self.rng);
        self.rng = self.rng.wrapping_add(0x9E37_79B9_7F4A_7C15);
        (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

impl Module for Gyro {
    type Params = GyroParams;
    const KIND: ModuleKind = ModuleKind::Sensor;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.cmd = Some(d.reads("locomotion/yaw_rate"));
        self.out = Some(d.writes("gyro/yaw_rate"));
        d.state("sampling", |m, ctx| {
            let cmd = m.cmd.as_ref().and_then(|r| ctx.read(r)).map(|s| s.value).unwrap_or(0.0);
            // Uniform noise scaled to the configured standard deviation (sqrt(3) sigma half-width).
            let n = m.noise() * m.params.noise * 3f64.sqrt();
            let rate = cmd + m.params.bias + n;
            ctx.write(m.out.as_ref().expect("declared"), rate);
            Ok(())
        });
    }
    fn configure(&mut self, p: &GyroParams) -> Result<(), String> {
        if !(p.noise >= 0.0 && p.noise.is_finite()) {
            return Err(format!("noise must be a non-negative number, got {}", p.noise));
        }
        self.params = p.clone();
        self.rng = p.seed;
        Ok(())
    }
}

/// Integrates the gyro into a heading estimate.
#[derive(Default)]
pub struct Heading {
    rate: Option<Reader<f64>>,
    out: Option<Writer<Estimate<f64, f64>>>,
    estimate: Option<Estimate<f64, f64>>,
    last: Option<Time>,
    params: HeadingParams,
}

/// Heading estimator parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeadingParams {
    /// Rate noise density used to grow the variance, rad/s/sqrt(Hz).
    pub rate_noise: f64,
}

impl Default for HeadingParams {
    fn default() -> Self {
        HeadingParams { rate_noise: 0.002 }
    }
}

impl Module for Heading {
    type Params = HeadingParams;
    const KIND: ModuleKind = ModuleKind::Resource;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.rate = Some(d.reads("gyro/yaw_rate"));
        self.out = Some(d.writes("heading/estimate"));
        d.state("integrating", |m, ctx| {
            let now = ctx.now();
            let dt = m.last.map(|l| (now - l).as_secs_f64()).unwrap_or(0.0);
            m.last = Some(now);
            let rate = m.rate.as_ref().and_then(|r| ctx.read(r)).map(|s| s.value).unwrap_or(0.0);
            let e = m.estimate.get_or_insert(Estimate::new(0.0, 1e-6));
            e.value += rate * dt;
            e.covariance += m.params.rate_noise.powi(2) * dt;
            let e = *e;
            ctx.write(m.out.as_ref().expect("declared"), e);
            Ok(())
        });
    }
    fn configure(&mut self, p: &HeadingParams) -> Result<(), String> {
        self.params = p.clone();
        Ok(())
    }
}

/// Steers to a commanded heading through locomotion.
#[derive(Default)]
pub struct Navigator {
    heading: Option<Reader<Estimate<f64, f64>>>,
    goal: Option<f64>,
    pending: Option<Request>,
    last_cmd: Option<f64>,
    refusals: u32,
    params: NavigatorParams,
}

/// Navigator parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavigatorParams {
    /// Turn rate used by bang-bang steering, rad/s.
    pub turn_rate: f64,
    /// Proportional gain, 1/s.
    pub gain: f64,
    /// Arrival tolerance, degrees.
    pub tolerance_deg: f64,
}

impl Default for NavigatorParams {
    fn default() -> Self {
        NavigatorParams { turn_rate: 0.3, gain: 1.5, tolerance_deg: 1.0 }
    }
}

/// Arguments of `turn_to`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TurnTo {
    /// Goal heading, degrees.
    pub heading_deg: f64,
}

impl Navigator {
    fn steer(&mut self, ctx: &mut Ctx<'_>, law: fn(&NavigatorParams, f64) -> f64) -> StateResult {
        let (Some(goal), Some(stamped)) = (self.goal, self.heading.as_ref().and_then(|r| ctx.read(r))) else {
            return Ok(());
        };
        let h = stamped.value;
        let err = wrap(goal - h.value);
        let rate =
            if err.abs() < self.params.tolerance_deg.to_radians() { 0.0 } else { law(&self.params, err) };
        if self.last_cmd != Some(rate) {
            ctx.send(Command::new("locomotion", "set_yaw_rate").args(rate))
                .map_err(|e| ModuleError(e.to_string()))?;
            self.last_cmd = Some(rate);
        }
        if rate == 0.0 {
            self.goal = None;
            if let Some(req) = self.pending.take() {
                let out = serde_json::json!({ "heading_deg": h.value.to_degrees(), "sigma_deg": h.std_dev().to_degrees() });
                ctx.reply(&req, Outcome::Completed(out));
            }
            ctx.goto("idle").map_err(|e| ModuleError(e.to_string()))?;
        }
        Ok(())
    }
}

impl Module for Navigator {
    type Params = NavigatorParams;
    const KIND: ModuleKind = ModuleKind::Coordination;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.heading = Some(d.reads("heading/estimate"));
        d.sends_to("locomotion");
        d.state("idle", |_m, _ctx| Ok(()));
        d.meta_state(
            "turning",
            &[
                ("bang_bang", |m: &mut Navigator, ctx: &mut Ctx<'_>| {
                    m.steer(ctx, |p, err| p.turn_rate.copysign(err))
                }),
                ("proportional", |m: &mut Navigator, ctx: &mut Ctx<'_>| {
                    m.steer(ctx, |p, err| (p.gain * err).clamp(-p.turn_rate, p.turn_rate))
                }),
            ],
        );
        d.transition("idle", "turning").transition("turning", "idle");
        d.command("turn_to", |m, ctx, a: TurnTo| {
            if !a.heading_deg.is_finite() {
                return Outcome::reject("heading_deg must be finite");
            }
            if let Some(old) = m.pending.take() {
                ctx.reply(&old, Outcome::fail("superseded by a new turn_to"));
            }
            m.goal = Some(wrap(a.heading_deg.to_radians()));
            m.pending = ctx.request();
            match ctx.goto("turning") {
                Ok(()) => Outcome::Accepted,
                Err(e) => Outcome::reject(e.to_string()),
            }
        });
        d.on_ack(|m, ctx, ack| {
            if let AckStatus::Rejected(reason) = &ack.status {
                m.refusals += 1;
                ctx.note(format!("locomotion refused {}: {reason}", ack.command));
            }
        });
    }
    fn configure(&mut self, p: &NavigatorParams) -> Result<(), String> {
        if p.turn_rate <= 0.0 || p.gain <= 0.0 || p.tolerance_deg <= 0.0 {
            return Err("turn_rate, gain and tolerance_deg must be positive".into());
        }
        self.params = p.clone();
        Ok(())
    }
}

use framework::AckStatus;
use framework::angle::wrap;

/// Applies yaw-rate commands within its limit.
#[derive(Default)]
pub struct Locomotion {
    out: Option<Writer<f64>>,
    params: LocomotionParams,
}

/// Locomotion parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocomotionParams {
    /// Largest yaw rate the rover can turn at, rad/s.
    pub max_yaw_rate: f64,
}

impl Default for LocomotionParams {
    fn default() -> Self {
        LocomotionParams { max_yaw_rate: 0.5 }
    }
}

impl Module for Locomotion {
    type Params = LocomotionParams;
    const KIND: ModuleKind = ModuleKind::Actuator;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("locomotion/yaw_rate"));
        d.command("set_yaw_rate", |m, ctx, rate: f64| {
            if !rate.is_finite() || rate.abs() > m.params.max_yaw_rate {
                return Outcome::reject(format!(
                    "yaw rate {rate} rad/s outside +-{} rad/s",
                    m.params.max_yaw_rate
                ));
            }
            ctx.write(m.out.as_ref().expect("declared"), rate);
            Outcome::done()
        });
        d.command("stop", |m, ctx, _: ()| {
            ctx.write(m.out.as_ref().expect("declared"), 0.0);
            Outcome::done()
        });
    }
    fn configure(&mut self, p: &LocomotionParams) -> Result<(), String> {
        self.params = p.clone();
        Ok(())
    }
    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        // Entering Hold or Safe stops the rover.
        if matches!(to, Lifecycle::Hold | Lifecycle::Safe) {
            ctx.write(self.out.as_ref().expect("declared"), 0.0);
        }
        Ok(())
    }
}
