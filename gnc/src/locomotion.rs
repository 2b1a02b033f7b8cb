//! Locomotion: the actuator module that owns the rover's locomotor.
//!
//! It turns high-level motion commands into body twists for the HAL locomotor and watches the wheel
//! encoders for stalled drives:
//! - `drive {v, omega, duration_s}`: drives open-loop for a time, then stops and completes;
//! - `goto {x, y, speed?}`: drives to a point of the pose estimate's frame (turning in place first
//!   when the goal is far off the heading) and completes on arrival within tolerance;
//! - `turn_to {yaw_deg}` or `turn_to {facing: [x, y]}`: turns in place to a heading of the
//!   estimate's frame, or to face a point of it from where the estimate puts the rover;
//! - `follow_path {points, clearance_m?, speed?, tolerance_m?, pivot?, max_curvature?}`: follows a
//!   path of the estimate's frame by pure pursuit (a lookahead point on the path, the arc through
//!   it), turning in place when the path is far off the heading or the arc tighter than
//!   `max_curvature` (the command's, else the configured one, the tighter if both; 0: no limit)
//!   (the shorter way round, or for its first such turn only the way `pivot` says: [`Sense`]),
//!   slowing where the path's
//!   clearance to obstacles is small, for heading error and near the end; completes at the last
//!   point with the cross-track errors;
//! - `stop`: stops at once (also fails the manoeuvre in progress);
//! - `recover`: leaves the `fault` state after a stall.
//!
//! With a navigation map to read ([`Locomotion::guarded_by`]) and a footprint configured
//! (`guard_half_extents_m`), `drive`, `goto` and `turn_to`, which no planner checked, are guarded
//! ([`guard`]): refused when the way they would sweep covers an obstacle cell, stopped (failed,
//! not a fault) when the rover's footprint at its estimated pose comes to cover one on the way.
//!
//! Each motion command completes (deferred acknowledgement) when the manoeuvre ends; a new one
//! supersedes the one in progress, which then fails with that reason. A wheel that turns at less
//! than a fraction of its commanded rate for longer than the stall time puts the module in `fault`:
//! the rover stops and the manoeuvre fails naming the wheel and what the rover was commanded to do
//! then (driving forward, reversing, turning in place to the left or right: [`Motion`], [`Sense`]).

use framework::angle::wrap;
use framework::data::{LocomotionState, NavigationMap, PoseEstimate};
use framework::hal::{BodyTwist, Locomotor, WheelEncoders};
use framework::module::Request;
use framework::prelude::*;
use framework::resources::ReservationToken;

mod follow;
pub mod guard;
mod motion;
mod params;
#[cfg(test)]
mod tests;

use follow::Following;
use guard::{CellKey, Footprint, Pose2};
pub use motion::{Motion, Sense, pivot_rate};
pub use params::{DriveArgs, FollowPathArgs, GotoArgs, LocomotionParams, TurnToArgs};
use std::collections::HashSet;

/// A straight move that makes room for a turn in place: to `to` (x, y of the estimate's frame)
/// along `heading` (rad), backwards when `distance` (m) is negative.
#[derive(Clone, Copy, Debug)]
struct Room {
    to: [f64; 2],
    heading: f64,
    distance: f64,
}

#[derive(Clone, Debug)]
enum Manoeuvre {
    Drive {
        twist: BodyTwist,
        until: Time,
    },
    Goto {
        x: f64,
        y: f64,
        speed: f64,
        tolerance: f64,
    },
    /// A turn in place to `yaw`, after a straight move to `room` (x, y) when one makes room for
    /// it (then to face `facing` from where that leaves the rover, when the turn faces a point).
    TurnTo {
        yaw: f64,
        facing: Option<[f64; 2]>,
        room: Option<Room>,
    },
    Follow(Box<Following>),
}

/// The locomotion module.
pub struct Locomotion {
    locomotor: Box<dyn Locomotor>,
    encoders: Box<dyn WheelEncoders>,
    token: Option<ReservationToken>,
    pose: Option<Reader<PoseEstimate>>,
    /// The navigation map's slot the obstacle guard reads (none: no guard).
    map_slot: Option<String>,
    map: Option<Reader<NavigationMap>>,
    out: Option<Writer<LocomotionState>>,
    params: LocomotionParams,
    manoeuvre: Option<Manoeuvre>,
    pending: Option<Request>,
    command: BodyTwist,
    last_cycle: Option<Time>,
    /// Per wheel: seconds of stall evidence, a leaky integral (grows while the wheel lags its
    /// command, decays at half that rate otherwise), so a jammed wheel that the others drag in
    /// jerks is still caught while brief sticking in skid turns is not.
    stall_evidence: Vec<f64>,
    fault: Option<String>,
    /// While a guarded manoeuvre runs: the obstacle cells under the footprint where it began.
    guard_exempt: Option<HashSet<CellKey>>,
    /// The straight move that made room for the turn in progress, m.
    room_made: Option<f64>,
}

/// The speed of a straight move that makes room for a turn in place, m/s.
const ROOM_SPEED_M_S: f64 = 0.1;
/// A move making room ends where more than this beyond its length is left (the pose estimate
/// jumped, relocalized on a landmark), m.
const ROOM_JUMP_M: f64 = 0.1;

impl Locomotion {
    /// A locomotion module driving `locomotor` and watching `encoders`.
    pub fn new(locomotor: Box<dyn Locomotor>, encoders: Box<dyn WheelEncoders>) -> Self {
        let n = locomotor.model().wheels.len();
        Locomotion {
            locomotor,
            encoders,
            token: None,
            pose: None,
            map_slot: None,
            map: None,
            out: None,
            params: LocomotionParams::default(),
            manoeuvre: None,
            pending: None,
            command: BodyTwist::default(),
            last_cycle: None,
            stall_evidence: vec![0.0; n],
            fault: None,
            guard_exempt: None,
            room_made: None,
        }
    }

    /// Guards `drive`, `goto` and `turn_to` with the navigation map of `slot` (when a footprint
    /// is configured).
    pub fn guarded_by(mut self, slot: &str) -> Self {
        self.map_slot = Some(slot.to_string());
        self
    }

    /// The guard's footprint, when it is on.
    fn footprint(&self) -> Option<Footprint> {
        let [l, w] = self.params.guard_half_extents_m;
        (self.map.is_some() && l > 0.0 && w > 0.0).then_some(Footprint {
            half_length_m: l,
            half_width_m: w,
            margin_m: self.params.guard_margin_m,
        })
    }

    /// The estimated pose on the ground, and the navigation map, for the guard.
    fn guard_view(
        &self,
        ctx: &Ctx<'_>,
    ) -> Option<(Footprint, Pose2, std::sync::Arc<Stamped<NavigationMap>>)> {
        let fp = self.footprint()?;
        let est = self.pose.as_ref().and_then(|r| ctx.read(r))?;
        let map = self.map.as_ref().and_then(|r| ctx.read(r))?;
        let p = est.value.position();
        Some((fp, [p.x, p.y, est.value.yaw()], map))
    }

    /// The guard's check of a manoeuvre about to start (`what`, for the refusal), sweeping the
    /// poses `sweep` gives from the rover's: the obstacle cells exempt for it (those under the
    /// footprint now), None when unguarded (no footprint, map or pose estimate), or the refusal.
    fn guard_plan(
        &self,
        ctx: &Ctx<'_>,
        what: &str,
        sweep: impl FnOnce(Pose2) -> Vec<Pose2>,
    ) -> Result<Option<HashSet<CellKey>>, Outcome> {
        // A command that `start` refuses (in fault, not in Run) is refused for that.
        if self.fault.is_some() || self.token.is_none() {
            return Ok(None);
        }
        let Some((fp, at, map)) = self.guard_view(ctx) else {
            return Ok(None);
        };
        let exempt = fp.keys_under(&map.value, at);
        match fp.first_hit(&map.value, sweep(at), &exempt) {
            Some(c) => Err(Outcome::reject(guard::refusal(what, fp.margin_m, c))),
            None => Ok(Some(exempt)),
        }
    }

    /// Room for a turn in place to `yaw` (rad), or to face `facing`, that the guard refuses where
    /// the rover stands: the straight move (up to `guard_room_m`) after which it is clear, and the
    /// cells exempt for the whole manoeuvre.
    fn room_for_turn(
        &self,
        ctx: &Ctx<'_>,
        yaw: f64,
        facing: Option<[f64; 2]>,
    ) -> Option<(Room, HashSet<CellKey>)> {
        let (fp, at, map) = self.guard_view(ctx)?;
        let exempt = fp.keys_under(&map.value, at);
        let yaw_at = |p: [f64; 2]| facing.map_or(yaw, |[x, y]| (y - p[1]).atan2(x - p[0]));
        let d = guard::room_for_turn(&fp, &map.value, at, yaw_at, self.params.guard_room_m, &exempt)?;
        let to = [at[0] + d * at[2].cos(), at[1] + d * at[2].sin()];
        Some((Room { to, heading: at[2], distance: d }, exempt))
    }

    /// The guard's check of the manoeuvre in progress: the obstacle cell (not exempt) the
    /// footprint at the estimated pose covers.
    fn guard_hit(&self, ctx: &Ctx<'_>) -> Option<[f64; 2]> {
        let exempt = self.guard_exempt.as_ref()?;
        let (fp, at, map) = self.guard_view(ctx)?;
        fp.first_hit(&map.value, [at], exempt)
    }

    fn limits(&self) -> (f64, f64) {
        let m = self.locomotor.model();
        (self.params.speed.min(m.max_speed), self.params.max_yaw_rate.min(m.max_yaw_rate))
    }

    /// Starts a manoeuvre for the command being handled, superseding the one in progress;
    /// `guard`: the obstacle cells exempt from the guard for it (None: unguarded).
    fn start(&mut self, ctx: &mut Ctx<'_>, m: Manoeuvre, guard: Option<HashSet<CellKey>>) -> Outcome {
        if let Some(reason) = &self.fault {
            return Outcome::reject(format!("locomotion is in fault ({reason}); send 'recover' first"));
        }
        if self.token.is_none() {
            return Outcome::reject("locomotion does not hold the locomotor (not in Run?)");
        }
        if let Some(old) = self.pending.take() {
            ctx.reply(
                &old,
                Outcome::fail(format!(
                    "superseded by '{}'",
                    ctx.request().map(|r| r.command().to_string()).unwrap_or_default()
                )),
            );
        }
        self.manoeuvre = Some(m);
        self.guard_exempt = guard;
        self.room_made = None;
        self.pending = ctx.request();
        match ctx.goto("moving") {
            Ok(()) => Outcome::Accepted,
            Err(e) => Outcome::reject(e.to_string()),
        }
    }

    /// Ends the manoeuvre: stops and answers the pending command.
    fn finish(&mut self, ctx: &mut Ctx<'_>, outcome: Outcome, state: &str) -> StateResult {
        self.manoeuvre = None;
        self.guard_exempt = None;
        self.apply(ctx, BodyTwist::default(), true)?;
        if let Some(req) = self.pending.take() {
            ctx.reply(&req, outcome);
        }
        ctx.goto(state).map_err(|e| ModuleError(e.to_string()))
    }

    /// Ends any manoeuvre and stops the wheels.
    fn stop_rover(&mut self) {
        self.manoeuvre = None;
        self.guard_exempt = None;
        if let Some(token) = &self.token {
            let _ = self.locomotor.stop(token);
        }
        self.command = BodyTwist::default();
    }

    /// Fits a twist into the locomotor's limits: yaw rate first (steering wins), then the speed
    /// that leaves every wheel within its rate limit.
    fn saturate(&self, t: BodyTwist) -> BodyTwist {
        let m = self.locomotor.model();
        let omega = t.omega.clamp(-m.max_yaw_rate, m.max_yaw_rate);
        let max_y = m.wheel_positions.iter().map(|p| p.y.abs()).fold(0.0, f64::max);
        let v_room = (m.max_wheel_rate * m.wheel_radius - omega.abs() * max_y).max(0.0) * 0.999;
        let vmax = m.max_speed.min(v_room);
        BodyTwist { v: t.v.clamp(-vmax, vmax), omega }
    }

    /// Sends a twist to the locomotor, with the acceleration limit unless `hard`.
    fn apply(&mut self, ctx: &mut Ctx<'_>, want: BodyTwist, hard: bool) -> StateResult {
        let dt = self.last_cycle.map(|t| (ctx.now() - t).as_secs_f64()).unwrap_or(0.0);
        let v = if hard {
            want.v
        } else {
            let dv = self.params.accel * dt;
            want.v.clamp(self.command.v - dv, self.command.v + dv)
        };
        let cmd = self.saturate(BodyTwist { v, omega: want.omega });
        if let Some(token) = &self.token {
            let r = if cmd == BodyTwist::default() {
                self.locomotor.stop(token)
            } else {
                self.locomotor.drive(token, cmd)
            };
            r.map_err(|e| ModuleError(format!("locomotor refused {cmd:?}: {e}")))?;
        }
        self.command = cmd;
        Ok(())
    }

    /// The twist a manoeuvre asks for now, or the outcome that ends it.
    fn control(&mut self, ctx: &Ctx<'_>) -> Result<BodyTwist, Outcome> {
        let (vmax, wmax) = self.limits();
        let p = &self.params;
        let pose = self.pose.as_ref().and_then(|r| ctx.read(r));
        match self.manoeuvre.clone() {
            None => Ok(BodyTwist::default()),
            Some(Manoeuvre::Drive { twist, until }) => {
                if ctx.now() >= until {
                    Err(Outcome::done())
                } else {
                    Ok(twist)
                }
            }
            Some(Manoeuvre::Goto { x, y, speed, tolerance }) => {
                let Some(est) = pose else {
                    return Err(Outcome::fail("no pose estimate to steer with"));
                };
                let pos = est.value.position();
                let (dx, dy) = (x - pos.x, y - pos.y);
                let dist = dx.hypot(dy);
                if dist <= tolerance {
                    return Err(Outcome::Completed(serde_json::json!({
                        "x": pos.x, "y": pos.y, "distance_to_goal_m": dist
                    })));
                }
                let herr = wrap(dy.atan2(dx) - est.value.yaw());
                let omega = (p.heading_gain * herr).clamp(-wmax, wmax);
                let v = if herr.abs() > p.turn_in_place_deg.to_radians() {
                    0.0
                } else {
                    // Slow down near the goal and while the heading is still off.
                    speed.min(vmax).min(0.6 * dist + 0.05) * herr.cos()
                };
                Ok(BodyTwist { v, omega })
            }
            Some(Manoeuvre::Follow(mut f)) => {
                let dt = self.last_cycle.map(|t| (ctx.now() - t).as_secs_f64()).unwrap_or(0.0);
                let Some(est) = pose else {
                    return Err(Outcome::fail("no pose estimate to steer with"));
                };
                let pos = est.value.position();
                let here = [pos.x, pos.y];
                let end = *f.points.last().expect("a path has points");
                let to_end = (end[0] - here[0]).hypot(end[1] - here[1]);
                let (k, t, cross) = f.closest(here);
                f.segment = k;
                f.worst_cross_track = f.worst_cross_track.max(cross);
                f.sum_sq += cross * cross;
                f.samples += 1;
                let at_last_segment = k + 2 >= f.points.len();
                if to_end <= f.tolerance && at_last_segment {
                    return Err(Outcome::Completed(serde_json::json!({
                        "x": pos.x, "y": pos.y, "distance_to_goal_m": to_end,
                        "max_cross_track_m": f.worst_cross_track,
                        "rms_cross_track_m": (f.sum_sq / f.samples as f64).sqrt(),
                    })));
                }
                let target = f.along(k, t, p.lookahead_m);
                let (dx, dy) = (target[0] - pos.x, target[1] - pos.y);
                let alpha = wrap(dy.atan2(dx) - est.value.yaw());
                let clearance = f.clearance_at(k, t);
                let left = f.remaining(k, t);
                let signed = f.signed_cross_track(k, here, cross);
                // Pure pursuit's arc through the lookahead point has curvature 2 sin(alpha) / L.
                // Far off the heading, or on an arc too tight to skid round, the rover turns in
                // place until the arc is within half the limit (hysteresis: no chatter between the
                // two at the limit). Near the path's end the lookahead point comes close and any
                // offset makes a tight arc: the limit is judged at the full lookahead there.
                let lookahead = dx.hypot(dy).max(1e-3);
                let curvature = 2.0 * alpha.sin() / lookahead;
                let judged = 2.0 * alpha.sin() / lookahead.max(p.lookahead_m);
                let limited = f.max_curvature > 0.0;
                let limit = if f.pivoting { 0.5 } else { 1.0 } * f.max_curvature;
                let too_tight = limited && judged.abs() > limit;
                let was_pivoting = f.pivoting;
                f.pivoting = alpha.abs() > p.turn_in_place_deg.to_radians() || too_tight;
                if was_pivoting && !f.pivoting {
                    // The sense imposed was for the first turn in place (where one stalled the
                    // other way): the path's later turns go the shorter way.
                    f.pivot = None;
                }
                // The cross-track integral corrects the arcs; the long turns in place to within half
                // the arc limit would wind it up. (Without the limit, the follower is as it was.)
                if !(f.pivoting && limited) {
                    f.cross_integral = (f.cross_integral + signed * dt).clamp(-0.5, 0.5);
                }
                let result = if f.pivoting {
                    // The long way round (a sense imposed) only for turns far off the heading, not
                    // for an arc just too tight.
                    let only = f.pivot.filter(|_| alpha.abs() > p.turn_in_place_deg.to_radians());
                    let mut omega = pivot_rate(alpha, p.heading_gain, wmax, only);
                    if limited {
                        // A useful rate to the end of those turns (wheels stick at very low rates).
                        omega = omega.signum() * omega.abs().max(0.05_f64.min(wmax));
                    }
                    BodyTwist { v: 0.0, omega }
                } else {
                    let slow = (clearance / p.slow_clearance_m).min(1.0);
                    let cruise = (f.speed.min(vmax) * slow).max(p.min_speed.min(f.speed));
                    let v =
                        cruise.min(0.6 * left.min(to_end.max(left.min(p.lookahead_m))) + 0.05) * alpha.cos();
                    // Pure pursuit: the arc through the lookahead point, with an integral on the
                    // cross-track error.
                    let omega = v * curvature - p.cross_track_gain_i * f.cross_integral;
                    // The arc the rover drives is its yaw rate over the speed it will have this
                    // cycle (speeding up from a turn in place, less than `v`): within the limit.
                    let omega = if limited {
                        let v_now = v.min(self.command.v.max(0.0) + p.accel * dt);
                        let most = (v_now * f.max_curvature).max(0.0);
                        omega.clamp(-most, most)
                    } else {
                        omega
                    };
                    BodyTwist { v, omega: omega.clamp(-wmax, wmax) }
                };
                self.manoeuvre = Some(Manoeuvre::Follow(f));
                Ok(result)
            }
            Some(Manoeuvre::TurnTo { mut yaw, facing, room }) => {
                let Some(est) = pose else {
                    return Err(Outcome::fail("no pose estimate to steer with"));
                };
                if let Some(r) = room {
                    // Making room first: straight along the heading the move started on, until
                    // what is left of it along that heading is under a centimetre (or, the
                    // estimate having jumped, more than the whole move: it ends there too).
                    let pos = est.value.position();
                    let (s, c) = r.heading.sin_cos();
                    let left = ((r.to[0] - pos.x) * c + (r.to[1] - pos.y) * s) * r.distance.signum();
                    if left > 0.01 && left <= r.distance.abs() + ROOM_JUMP_M {
                        let v = r.distance.signum() * ROOM_SPEED_M_S.min(vmax).min(0.6 * left + 0.03);
                        return Ok(BodyTwist { v, omega: 0.0 });
                    }
                    if let Some([x, y]) = facing {
                        yaw = (y - pos.y).atan2(x - pos.x);
                    }
                    self.manoeuvre = Some(Manoeuvre::TurnTo { yaw, facing, room: None });
                    self.room_made = Some(r.distance);
                }
                let herr = wrap(yaw - est.value.yaw());
                if herr.abs() <= p.heading_tolerance_deg.to_radians() {
                    let mut done = serde_json::json!({ "yaw_deg": est.value.yaw().to_degrees() });
                    if let Some(d) = self.room_made.take() {
                        done["room_m"] = d.into();
                    }
                    return Err(Outcome::Completed(done));
                }
                let omega = (p.heading_gain * herr).clamp(-wmax, wmax);
                // Keep turning at a useful rate near the goal (wheels stick at very low rates).
                let omega = omega.signum() * omega.abs().max(0.05_f64.min(wmax));
                Ok(BodyTwist { v: 0.0, omega })
            }
        }
    }

    /// Checks every wheel against its commanded rate; the name of a stalled one.
    fn stalled_wheel(&mut self, now: Time) -> Option<String> {
        // No reading yet (the first is on its way): no evidence either way.
        let reading = self.encoders.read()?;
        let model = self.locomotor.model();
        let want = model.wheel_rates(self.command)?;
        let dt = self.last_cycle.map(|t| (now - t).as_secs_f64()).unwrap_or(0.0);
        for (k, (&w, &got)) in want.iter().zip(&reading.rates).enumerate() {
            let stalling = w.abs() >= self.params.stall_min_rate
                && (got * w.signum()) < self.params.stall_rate_fraction * w.abs();
            let e = &mut self.stall_evidence[k];
            *e = if stalling { *e + dt } else { (*e - 0.5 * dt).max(0.0) };
            if *e >= self.params.stall_time_s {
                return Some(model.wheels[k].clone());
            }
        }
        None
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let (mode, goal) = match (&self.fault, &self.manoeuvre) {
            (Some(_), _) => ("fault", None),
            (None, None) => ("idle", None),
            (None, Some(Manoeuvre::Drive { .. })) => ("drive", None),
            (None, Some(Manoeuvre::Goto { x, y, .. })) => ("goto", Some([*x, *y])),
            (None, Some(Manoeuvre::TurnTo { .. })) => ("turn", None),
            (None, Some(Manoeuvre::Follow(f))) => ("follow", f.points.last().copied()),
        };
        if let Some(w) = &self.out {
            ctx.write(w, LocomotionState { command: self.command, mode: mode.into(), goal });
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let now = ctx.now();
        if let Some(wheel) = self.stalled_wheel(now) {
            let motion = Motion::of(self.command);
            let sense = match motion {
                Motion::TurningInPlace => Sense::of(self.command.omega).describe(),
                _ => "",
            };
            let reason = format!(
                "wheel '{wheel}' stalled {}{sense}: it turned at under {:.0}% of its commanded rate for {} s",
                motion.describe(),
                self.params.stall_rate_fraction * 100.0,
                self.params.stall_time_s
            );
            ctx.note(format!("stopping the rover: {reason}"));
            self.fault = Some(reason.clone());
            self.stall_evidence.iter_mut().for_each(|s| *s = 0.0);
            self.finish(ctx, Outcome::fail(reason), "fault")?;
        } else if let Some(c) = self.guard_hit(ctx) {
            let reason = guard::stop_reason(self.params.guard_margin_m, c);
            ctx.note(format!("stopping the rover: {reason}"));
            self.finish(ctx, Outcome::fail(reason), "idle")?;
        } else {
            match self.control(ctx) {
                Ok(twist) => self.apply(ctx, twist, false)?,
                Err(outcome) => self.finish(ctx, outcome, "idle")?,
            }
        }
        self.last_cycle = Some(now);
        self.publish(ctx);
        Ok(())
    }
}

impl Module for Locomotion {
    type Params = LocomotionParams;
    const KIND: ModuleKind = ModuleKind::Actuator;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.pose = Some(d.reads(crate::localization_fusion::SLOT));
        if let Some(slot) = self.map_slot.clone() {
            self.map = Some(d.reads(&slot));
        }
        self.out = Some(d.writes("locomotion/state"));
        // Scenarios switch contexts at runtime (e.g. Mission -> Debug for a fault injection).
        d.context_switchable();
        d.state("idle", |m, ctx| m.cycle(ctx));
        d.state("moving", |m, ctx| m.cycle(ctx));
        d.state("fault", |m, ctx| {
            m.last_cycle = Some(ctx.now());
            m.publish(ctx);
            Ok(())
        });
        d.transition("idle", "moving")
            .transition("moving", "idle")
            .transition("moving", "moving")
            .transition("moving", "fault")
            .transition("idle", "fault")
            .transition("fault", "idle");
        d.command("drive", |m, ctx, a: DriveArgs| {
            let (vmax, wmax) = m.limits();
            if !(a.v.abs() <= vmax && a.omega.abs() <= wmax && a.duration_s >= 0.0 && a.duration_s.is_finite()) {
                return Outcome::reject(format!(
                    "drive v={} m/s omega={} rad/s for {} s is outside |v|<={vmax}, |omega|<={wmax}, duration>=0",
                    a.v, a.omega, a.duration_s
                ));
            }
            let until = ctx.now() + Duration::from_secs_f64(a.duration_s);
            let guard = match m.guard_plan(ctx, "the drive", |at| guard::drive_poses(at, a.v, a.omega, a.duration_s)) {
                Ok(g) => g,
                Err(refused) => return refused,
            };
            m.start(ctx, Manoeuvre::Drive { twist: BodyTwist { v: a.v, omega: a.omega }, until }, guard)
        });
        d.command("goto", |m, ctx, a: GotoArgs| {
            let speed = a.speed.unwrap_or(m.params.speed);
            let tolerance = a.tolerance_m.unwrap_or(m.params.goal_tolerance_m);
            if !(a.x.is_finite() && a.y.is_finite() && speed > 0.0 && tolerance > 0.0) {
                return Outcome::reject(
                    "goto needs a finite goal, a positive speed and a positive tolerance",
                );
            }
            let turn = m.params.turn_in_place_deg.to_radians();
            let guard =
                match m.guard_plan(ctx, "the goto", |at| guard::goto_poses(at, a.x, a.y, turn, tolerance)) {
                    Ok(g) => g,
                    Err(refused) => return refused,
                };
            m.start(ctx, Manoeuvre::Goto { x: a.x, y: a.y, speed, tolerance }, guard)
        });
        d.command("follow_path", |m, ctx, a: FollowPathArgs| {
            let speed = a.speed.unwrap_or(m.params.speed);
            let tolerance = a.tolerance_m.unwrap_or(m.params.goal_tolerance_m);
            // No clearance given: nothing to slow down for (finite, so interpolation stays exact).
            let clearance = a.clearance_m.unwrap_or_else(|| vec![f64::MAX; a.points.len()]);
            if a.points.is_empty() || a.points.iter().flatten().any(|v| !v.is_finite()) {
                return Outcome::reject("follow_path needs at least one finite point");
            }
            if clearance.len() != a.points.len()
                || clearance.iter().any(|c| c.is_nan() || *c < 0.0)
                || !(speed > 0.0 && tolerance > 0.0)
            {
                return Outcome::reject(
                    "follow_path needs one clearance per point, a positive speed and a positive tolerance",
                );
            }
            let configured = m.params.max_curvature;
            let max_curvature = match a.max_curvature {
                None => configured,
                Some(k) if !(k >= 0.0 && k.is_finite()) => {
                    return Outcome::reject(format!(
                        "follow_path's max_curvature must be 0 (no limit) or positive, got {k}"
                    ));
                }
                // The tighter of the command's and a configured limit; 0 asks for none.
                Some(k) if k > 0.0 && configured > 0.0 => k.min(configured),
                Some(k) => k,
            };
            let mut points = a.points;
            let mut clearance = clearance;
            if points.len() == 1 {
                // A single point: a segment of no length, steered to like a goto (no cross-track).
                points.insert(0, points[0]);
                clearance.insert(0, clearance[0]);
            }
            m.start(
                ctx,
                Manoeuvre::Follow(Box::new(Following {
                    points,
                    clearance,
                    speed,
                    tolerance,
                    segment: 0,
                    cross_integral: 0.0,
                    worst_cross_track: 0.0,
                    sum_sq: 0.0,
                    samples: 0,
                    pivoting: false,
                    pivot: a.pivot,
                    max_curvature,
                })),
                None,
            )
        });
        d.command("turn_to", |m, ctx, a: TurnToArgs| {
            let facing = a.facing;
            let yaw = match (a.yaw_deg, a.facing) {
                (Some(yaw), None) if yaw.is_finite() => yaw.to_radians(),
                (None, Some([x, y])) if x.is_finite() && y.is_finite() => {
                    let Some(pose) = m.pose.as_ref().and_then(|r| ctx.read(r)) else {
                        return Outcome::reject("turn_to facing a point needs a pose estimate: none yet");
                    };
                    let at = pose.value.pose.translation.vector;
                    if (x - at.x).hypot(y - at.y) < 1e-3 {
                        return Outcome::reject(format!("the rover stands on ({x}, {y}): no way to face it"));
                    }
                    (y - at.y).atan2(x - at.x)
                }
                _ => return Outcome::reject("turn_to needs yaw_deg or facing = [x, y], one of them, finite"),
            };
            let yaw = wrap(yaw);
            match m.guard_plan(ctx, "the turn", |at| guard::turn_poses(at, yaw)) {
                Ok(guard) => m.start(ctx, Manoeuvre::TurnTo { yaw, facing, room: None }, guard),
                Err(refused) => match m.room_for_turn(ctx, yaw, facing) {
                    Some((room, exempt)) => {
                        ctx.note(format!(
                            "turn_to {:.0} deg: no room to turn here; {} {:.2} m first",
                            yaw.to_degrees(),
                            if room.distance < 0.0 { "backing" } else { "driving ahead" },
                            room.distance.abs()
                        ));
                        m.start(ctx, Manoeuvre::TurnTo { yaw, facing, room: Some(room) }, Some(exempt))
                    }
                    None => refused,
                },
            }
        });
        d.command("stop", |m, ctx, _: ()| {
            if let Some(old) = m.pending.take() {
                ctx.reply(&old, Outcome::fail("stopped by command"));
            }
            m.manoeuvre = None;
            m.guard_exempt = None;
            if let Err(e) = m.apply(ctx, BodyTwist::default(), true) {
                return Outcome::fail(e.0);
            }
            if ctx.state() == "moving" {
                let _ = ctx.goto("idle");
            }
            Outcome::done()
        });
        d.command("recover", |m, ctx, _: ()| {
            if m.fault.take().is_none() {
                // Nothing to recover from: done (as a joint group's `recover` is).
                return Outcome::Completed(serde_json::json!("not in fault"));
            }
            match ctx.goto("idle") {
                Ok(()) => Outcome::done(),
                Err(e) => Outcome::fail(e.to_string()),
            }
        });
    }

    fn configure(&mut self, p: &LocomotionParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("speed", p.speed),
            ("max_yaw_rate", p.max_yaw_rate),
            ("accel", p.accel),
            ("heading_gain", p.heading_gain),
            ("goal_tolerance_m", p.goal_tolerance_m),
            ("heading_tolerance_deg", p.heading_tolerance_deg),
            ("stall_time_s", p.stall_time_s),
            ("lookahead_m", p.lookahead_m),
            ("cross_track_gain_i", p.cross_track_gain_i),
            ("slow_clearance_m", p.slow_clearance_m),
            ("min_speed", p.min_speed),
        ])?;
        if !(0.0..1.0).contains(&p.stall_rate_fraction) {
            return Err(format!("stall_rate_fraction must be in [0, 1), got {}", p.stall_rate_fraction));
        }
        if !(p.max_curvature >= 0.0 && p.max_curvature.is_finite()) {
            return Err(format!("max_curvature must be 0 (no limit) or positive, got {}", p.max_curvature));
        }
        crate::params::require_non_negative(&[
            ("guard_half_extents_m[0]", p.guard_half_extents_m[0]),
            ("guard_half_extents_m[1]", p.guard_half_extents_m[1]),
            ("guard_margin_m", p.guard_margin_m),
            ("guard_room_m", p.guard_room_m),
        ])?;
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        match to {
            // A restart after isolation finds its reservation freed: it is taken again.
            Lifecycle::Run if self.token.as_ref().is_none_or(|t| ctx.validate(t).is_err()) => {
                let device = self.locomotor.device().to_string();
                self.token = Some(ctx.acquire(&device).map_err(|e| e.to_string())?);
            }
            Lifecycle::Hold | Lifecycle::Shutdown => {
                // Leaving Run stops the rover; the manoeuvre in progress fails.
                if let Some(req) = self.pending.take() {
                    ctx.reply(&req, Outcome::fail(format!("locomotion left Run for {to}")));
                }
                self.stop_rover();
            }
            _ => {}
        }
        Ok(())
    }

    /// Safe (commanded, or isolated after a panic or an error): the rover stops now; the framework
    /// answers the manoeuvre in progress Failed. Should this hook not run (a hang), the locomotor's
    /// deadman stops the wheels.
    fn on_safe(&mut self, _ctx: &mut Ctx<'_>) {
        self.pending = None;
        self.stop_rover();
    }
}
