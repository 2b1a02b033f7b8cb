//! Joint-group control: the actuator module of one position-controlled joint group (the arm, the
//! pan-tilt unit, the gripper).
//!
//! Commands (each motion completes when the move is done, with a deferred acknowledgement):
//! - `move {positions, speed?}`: moves every joint of the group to the given positions;
//! - `move_named {pose, speed?}`: moves to a named pose of the configuration (`stow`, `ready`, ...);
//! - `stop`: stops the group where it is (the move in progress fails);
//! - `recover`: takes the motors out of fault.
//!
//! The joint states are published every cycle as `<module name>/joints`; a failed move (motor
//! fault, blocked joint) fails the command with the device's reason.

use framework::data::JointStates;
use framework::hal::{JointGroup, MoveId, MoveStatus};
use framework::module::Request;
use framework::prelude::*;
use framework::resources::ReservationToken;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Joint-group parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JointGroupParams {
    /// Default speed, fraction of the joints' velocity limits (0..1].
    pub speed: f64,
    /// Named poses: joint positions in the group's joint order, rad or m.
    pub poses: BTreeMap<String, Vec<f64>>,
}

impl Default for JointGroupParams {
    fn default() -> Self {
        JointGroupParams { speed: 0.5, poses: BTreeMap::new() }
    }
}

/// Arguments of `move`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MoveArgs {
    /// Target positions in joint order.
    pub positions: Vec<f64>,
    /// Speed fraction (default: configured).
    #[serde(default)]
    pub speed: Option<f64>,
}

/// Arguments of `move_named`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MoveNamedArgs {
    /// Pose name.
    pub pose: String,
    /// Speed fraction (default: configured).
    #[serde(default)]
    pub speed: Option<f64>,
}

/// The joint-group module.
pub struct JointGroupModule {
    group: Box<dyn JointGroup>,
    token: Option<ReservationToken>,
    out: Option<Writer<JointStates>>,
    params: JointGroupParams,
    current: Option<(MoveId, Request)>,
}

impl JointGroupModule {
    /// A module commanding `group`.
    pub fn new(group: Box<dyn JointGroup>) -> Self {
        JointGroupModule { group, token: None, out: None, params: JointGroupParams::default(), current: None }
    }

    fn start(&mut self, ctx: &mut Ctx<'_>, targets: Vec<f64>, speed: Option<f64>) -> Outcome {
        let Some(token) = &self.token else {
            return Outcome::reject(format!("'{}' does not hold its joint group (not in Run?)", ctx.name()));
        };
        let speed = speed.unwrap_or(self.params.speed);
        match self.group.move_to(token, &targets, speed) {
            Ok(id) => {
                if let Some((_, old)) = self.current.take() {
                    ctx.reply(&old, Outcome::fail("superseded by a new move"));
                }
                match ctx.request() {
                    Some(req) => {
                        self.current = Some((id, req));
                        Outcome::Accepted
                    }
                    None => Outcome::done(),
                }
            }
            Err(e) => Outcome::reject(e.to_string()),
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        // The driver's deadman holds the group if this stops coming (a revoked token: not ours).
        if let Some(token) = &self.token {
            let _ = self.group.keep_alive(token);
        }
        if let Some((id, _)) = &self.current {
            let status = self.group.move_status(*id);
            let outcome = match status {
                MoveStatus::InProgress { .. } => None,
                MoveStatus::Done => {
                    Some(Outcome::Completed(serde_json::json!({ "positions": self.group.positions() })))
                }
                MoveStatus::Stopped => Some(Outcome::fail("move stopped")),
                MoveStatus::Failed(reason) => Some(Outcome::fail(reason)),
                MoveStatus::Unknown => Some(Outcome::fail("the device lost the move")),
            };
            if let Some(o) = outcome {
                let (_, req) = self.current.take().expect("checked");
                ctx.reply(&req, o);
            }
        }
        if let Some(w) = &self.out {
            let states = JointStates { group: self.group.device().to_string(), joints: self.group.states() };
            ctx.write(w, states);
        }
        Ok(())
    }
}

impl Module for JointGroupModule {
    type Params = JointGroupParams;
    const KIND: ModuleKind = ModuleKind::Actuator;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        let slot = format!("{}/joints", d.name());
        self.out = Some(d.writes(&slot));
        // Scenarios switch contexts at runtime (e.g. Mission -> Debug for a fault injection).
        d.context_switchable();
        d.state("active", |m, ctx| m.cycle(ctx));
        d.command("move", |m, ctx, a: MoveArgs| m.start(ctx, a.positions, a.speed));
        d.command("move_named", |m, ctx, a: MoveNamedArgs| {
            let Some(targets) = m.params.poses.get(&a.pose).cloned() else {
                return Outcome::reject(format!(
                    "no pose '{}' (configured: {})",
                    a.pose,
                    m.params.poses.keys().cloned().collect::<Vec<_>>().join(", ")
                ));
            };
            m.start(ctx, targets, a.speed)
        });
        d.command("stop", |m, ctx, _: ()| {
            let Some(token) = &m.token else { return Outcome::reject("not holding the joint group") };
            if let Some((_, req)) = m.current.take() {
                ctx.reply(&req, Outcome::fail("stopped by command"));
            }
            match m.group.stop(token) {
                Ok(()) => Outcome::done(),
                Err(e) => Outcome::fail(e.to_string()),
            }
        });
        d.command("recover", |m, _ctx, _: ()| {
            let Some(token) = &m.token else { return Outcome::reject("not holding the joint group") };
            match m.group.recover(token) {
                Ok(()) => Outcome::done(),
                Err(e) => Outcome::fail(e.to_string()),
            }
        });
    }

    fn configure(&mut self, p: &JointGroupParams) -> Result<(), String> {
        if !(p.speed > 0.0 && p.speed <= 1.0) {
            return Err(format!("speed must be in (0, 1], got {}", p.speed));
        }
        let n = self.group.joint_names().len();
        let limits = self.group.limits();
        for (name, q) in &p.poses {
            if q.len() != n {
                return Err(format!("pose '{name}' has {} positions, the group has {n} joints", q.len()));
            }
            for ((v, l), j) in q.iter().zip(&limits).zip(self.group.joint_names()) {
                if !(*v >= l.lower && *v <= l.upper) {
                    return Err(format!("pose '{name}': {j} = {v} outside [{}, {}]", l.lower, l.upper));
                }
            }
        }
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        match to {
            // A restart after isolation finds its reservation freed: it is taken again.
            Lifecycle::Run if self.token.as_ref().is_none_or(|t| ctx.validate(t).is_err()) => {
                let device = self.group.device().to_string();
                self.token = Some(ctx.acquire(&device).map_err(|e| e.to_string())?);
            }
            Lifecycle::Hold | Lifecycle::Shutdown => {
                if let Some((_, req)) = self.current.take() {
                    ctx.reply(&req, Outcome::fail(format!("'{}' left Run for {to}", ctx.name())));
                }
                if let Some(token) = &self.token {
                    let _ = self.group.stop(token);
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// Safe: the joints hold where they are (the framework fails the move in progress); should this
    /// hook not run (a hang), the group's deadman holds them.
    fn on_safe(&mut self, _ctx: &mut Ctx<'_>) {
        self.current = None;
        if let Some(token) = &self.token {
            let _ = self.group.stop(token);
        }
    }
}
