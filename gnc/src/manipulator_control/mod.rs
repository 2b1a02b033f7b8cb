//! ManipulatorControl (seed 000, 8.3): the arm and the gripper as one manipulator, on the believed
//! mechanism model (never the physics), commanding the `arm` and `gripper` joint groups.
//!
//! Every arm motion is planned clear of the rover's own body ([`Clearance`]: the URDF's collision
//! shapes, a held object included) and the ground, through configured via-poses when the straight
//! joint-space path is not clear, each segment timed within the joints' speed and acceleration
//! limits ([`segment_speed`]). A planned move that stalls a servo, or stops short of its goal, is
//! planned again from where the arm stopped, once, after the motors are out of fault (`retry`).
//!
//! Commands (each completes when done, with a deferred acknowledgement):
//! - `move_named {pose}`: a planned motion to a configured pose;
//! - `move_tool {position, rpy_deg}`: the tool centre point to a pose in `base_link` (inverse
//!   kinematics, then a planned motion);
//! - `grasp {object}`: grasps an object's handle from above under visual servoing with the wrist
//!   camera (eye-in-hand): the gripper opens, the arm goes to a pre-grasp pose above the handle
//!   where the wrist camera's marker pose (`tracking/wrist/objects`) puts it, then looks and moves
//!   until the tool is within tolerance of the pre-grasp pose as the camera sees it, descends
//!   onto the handle, closes, checks that the fingers stopped on the handle (not closed on
//!   nothing), and lifts; fails with the reason (the caller may retry);
//! - `place {slot?}`: puts the held object into the stowage slot (a link of the mechanism,
//!   `stow_slot` by default) upright, opens, and lifts the gripper off it; an object whose
//!   descent is blocked on the slot's wall is tried again a little to the side, and kept (the
//!   place fails) when it never goes in;
//! - `open`, `close`: the gripper alone;
//! - `stop`: stops the arm and ends the command in progress.
//!
//! The state (what it does, the servo's last error, whether it holds something) goes out on
//! `manipulation/state`.

use crate::body::joint_values;
use crate::manipulation::clearance::{Clearance, ClearanceParams, Held};
use crate::manipulation::kinematics::ArmKinematics;
use crate::manipulation::servo::mean_pose;
use crate::manipulation::trajectory::{plan_path, segment_speed};
use crate::peer::send;
use framework::data::{JointStates, ManipulationState, ObjectPoses};
use framework::mechanism::{CollisionBox, MechanismModel};
use framework::message::{AckStatus, MessageId};
use framework::module::Request;
use framework::prelude::*;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use std::collections::VecDeque;

mod grasp;
mod params;
mod place;
mod retry;

pub use params::{GraspArgs, GraspableObject, ManipulatorParams, MoveNamedArgs, MoveToolArgs, PlaceArgs};
use place::Seat;

/// The slot of the manipulator's state.
pub const SLOT: &str = "manipulation/state";

/// Names of the modules and slots the manipulator uses.
#[derive(Clone, Debug)]
pub struct ManipulatorPeers {
    /// The arm's joint group.
    pub arm: String,
    /// The gripper's joint group.
    pub gripper: String,
    /// Other joint groups whose links the clearance checks need (the pan-tilt unit).
    pub others: Vec<String>,
    /// The wrist camera's object poses.
    pub objects: String,
}

/// One action of a command.
#[derive(Clone, Debug, PartialEq)]
enum Action {
    /// A planned motion to arm values.
    Plan(Vec<f64>),
    /// A straight joint-space motion, checked (`contact`: a motion at the object itself, setting
    /// it down or leaving it: the held object and the objects set down are not checked).
    Straight { to: Vec<f64>, contact: bool },
    /// The gripper to finger positions.
    Gripper(Vec<f64>),
    /// Find the object's handle and the pre-grasp pose above it.
    Approach,
    /// One look-and-move step of the servo loop.
    Servo,
    /// Down onto the handle.
    Descend,
    /// Did the fingers stop on the handle?
    CheckGrip,
    /// Up by the lift height: a held object along the vertical, the open fingers along the tool's
    /// x axis (a stuck one then straight up to the height it was going to: `retry`).
    Lift,
    /// The object is let go: the manipulator holds nothing.
    Released,
    /// The open fingers towards the slot's centre, where the cradle's clamp centres an object let
    /// go off it (a seat search set it down to the side), before they lift off its handle.
    Recentre,
    /// A joint group's motors out of fault (the arm after a blocked set-down stalled one, the
    /// gripper before a grasp: a close that stalled faults it).
    Recover(Group),
}

/// The joint groups the manipulator commands.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Group {
    Arm,
    Gripper,
}

/// What the command in progress waits for.
#[derive(Clone, Debug)]
enum Wait {
    /// Nothing: take the next action.
    Idle,
    /// A joint-group command, and for an arm move when it should be over and where it goes (an
    /// arm still short of its goal then is stopped: near enough, the motion goes on).
    Command(MessageId, &'static str, Option<(Time, Vec<f64>)>),
    /// An image of the object taken at rest after this time (asked since).
    View { after: Time, since: Time, views: Vec<(Time, Isometry3<f64>)> },
}

/// A command in progress.
struct Job {
    request: Request,
    name: &'static str,
    actions: VecDeque<Action>,
    wait: Wait,
    /// The object being grasped.
    object: Option<String>,
    /// The grasp (tool pose in the handle's frame, at the handle).
    grasp: Option<Isometry3<f64>>,
    servo_steps: u32,
    /// The last servo step's error: translation (m), rotation (rad), and the tilt of the approach
    /// axis off the handle's normal that the dead band left (rad).
    last_error: Option<(f64, f64, f64)>,
    /// Why the command fails once its remaining actions (backing off) are done.
    failed: Option<String>,
    /// Where a `place` puts the object (a link).
    slot: Option<String>,
    /// The arm move in progress sets the held object down (a place's descent).
    setting_down: bool,
    /// A place's seat: where the object goes down into the slot.
    seat: Option<Seat>,
    /// The arm move in progress lifts the open fingers off an object let go.
    lifting_free: bool,
    /// Such a lift got stuck once and went again straight up.
    lift_retried: bool,
    /// The goal of the planned move in progress (while its segments run).
    planned: Option<Vec<f64>>,
    /// The goal of the planned move that stalled once and was planned again from where the arm
    /// stopped (a second stall of that move fails the command; another move may be planned
    /// again once too).
    replanned: Option<Vec<f64>>,
}

/// The ManipulatorControl module.
pub struct ManipulatorControl {
    peers: ManipulatorPeers,
    kinematics: ArmKinematics,
    clearance: Clearance,
    /// The gripper's finger joints (in the gripper group's order).
    fingers: Vec<String>,
    joints: Vec<Option<Reader<JointStates>>>,
    objects: Option<Reader<ObjectPoses>>,
    out: Option<Writer<ManipulationState>>,
    params: ManipulatorParams,
    speed_limits: Vec<f64>,
    job: Option<Job>,
    /// The object held and its pose in the tool frame.
    held: Option<(String, Isometry3<f64>)>,
    last: Option<String>,
}

/// The gap between arm and body below which the clearance check stops a motion, and the other
/// settings, from the parameters and the mechanism (the ground plane: the wheels' lowest point).
fn clearance_params(mechanism: &MechanismModel, p: &ManipulatorParams) -> Result<ClearanceParams, String> {
    let q = vec![0.0; mechanism.dof_count()];
    let poses = mechanism.link_poses(&q).map_err(|e| e.to_string())?;
    let ground = mechanism
        .links()
        .iter()
        .enumerate()
        .filter(|(_, l)| l.name.starts_with("wheel_"))
        .flat_map(|(i, l)| {
            let pose = poses[i];
            l.collision_boxes.iter().map(move |b| crate::manipulation::clearance::Obb::placed(&pose, b))
        })
        .map(|o| o.min_z())
        .fold(f64::INFINITY, f64::min);
    if !ground.is_finite() {
        return Err("the mechanism has no wheels to stand on".into());
    }
    Ok(ClearanceParams {
        margin_m: p.margin_m,
        ground_z_m: ground,
        ground_margin_m: p.ground_margin_m,
        step: p.check_step_rad,
    })
}

/// True for the links on the arm side of the clearance checks.
fn is_arm_link(name: &str) -> bool {
    name.starts_with("arm_link_") || name.starts_with("gripper_")
}

/// The first arm link turns about its own axis on the mount: no motion brings it nearer the body.
const COAXIAL: &[&str] = &["arm_link_1"];

impl ManipulatorControl {
    /// A manipulator of `peers` on the believed `mechanism`, its tool centre point at link `tool`.
    pub fn new(peers: ManipulatorPeers, mechanism: &MechanismModel, tool: &str) -> Result<Self, String> {
        let kinematics = ArmKinematics::new(mechanism, tool)?;
        let params = ManipulatorParams::default();
        let clearance =
            Clearance::new(mechanism, is_arm_link, COAXIAL, clearance_params(mechanism, &params)?);
        let speed_limits = kinematics
            .joint_names()
            .iter()
            .map(|n| mechanism.joint(n).map(|j| j.velocity_limit).map_err(|e| e.to_string()))
            .collect::<Result<_, _>>()?;
        let fingers = mechanism
            .joints()
            .iter()
            .filter(|j| j.name.starts_with("gripper_finger_") && j.dof.is_some())
            .map(|j| j.name.clone())
            .collect();
        Ok(ManipulatorControl {
            peers,
            kinematics,
            clearance,
            fingers,
            joints: Vec::new(),
            objects: None,
            out: None,
            params,
            speed_limits,
            job: None,
            held: None,
            last: None,
        })
    }

    /// The whole mechanism's joint values now (the joint groups' latest states).
    fn all_joints(&self, ctx: &Ctx<'_>) -> Option<Vec<f64>> {
        let mut states = Vec::new();
        for r in &self.joints {
            let s = ctx.read(r.as_ref()?)?;
            states.extend(s.value.joints.iter().map(|j| (j.name.clone(), j.position)));
        }
        Some(joint_values(self.kinematics.mechanism(), states.iter().map(|(n, v)| (n.as_str(), *v))))
    }

    /// The arm's joint values now.
    fn arm_now(&self, ctx: &Ctx<'_>) -> Result<(Vec<f64>, Vec<f64>), String> {
        let all = self.all_joints(ctx).ok_or("no joint states yet")?;
        Ok((self.kinematics.arm_values(&all), all))
    }

    /// The held object as the clearance checks see it.
    fn held_shape(&self) -> Option<Held> {
        let (kind, tool_from_object) = self.held.as_ref()?;
        let o = self.params.objects.get(kind)?;
        let link = self.kinematics.mechanism().link(self.kinematics.tip()).ok()?;
        let c = Vector3::from(o.box_center);
        Some(Held {
            link,
            shape: CollisionBox {
                origin: tool_from_object * Isometry3::translation(c.x, c.y, c.z),
                half_extents: Vector3::from(o.box_half),
            },
        })
    }

    /// IK seeds besides the present joints: the named poses.
    fn seeds(&self) -> Vec<Vec<f64>> {
        self.params.poses.values().cloned().collect()
    }

    fn vias(&self) -> Vec<Vec<f64>> {
        self.params.vias.iter().filter_map(|v| self.params.poses.get(v).cloned()).collect()
    }

    /// Sends the arm along the first segment of a planned path, queueing the rest.
    fn start_plan(&mut self, ctx: &mut Ctx<'_>, job: &mut Job, to: &[f64]) -> Result<(), String> {
        let (q, all) = self.arm_now(ctx)?;
        let held = self.held_shape();
        let full = |a: &[f64]| self.kinematics.full(a, &all);
        let path = plan_path(&self.clearance, &full, &q, to, &self.vias(), held.as_ref())
            .map_err(|e| e.to_string())?;
        if path.len() > 1 {
            ctx.note(format!(
                "{}: the straight path is blocked, going through {} via-poses",
                job.name,
                path.len() - 1
            ));
        }
        // Each segment is checked already: the first goes now, the others after it.
        for p in path.iter().skip(1).rev() {
            job.actions.push_front(Action::Straight { to: p.clone(), contact: false });
        }
        self.move_arm(ctx, job, &q, &path[0])
    }

    /// Commands one straight segment of the arm.
    fn move_arm(&mut self, ctx: &mut Ctx<'_>, job: &mut Job, from: &[f64], to: &[f64]) -> Result<(), String> {
        let accel = vec![self.params.acceleration_rad_s2; to.len()];
        let speed = segment_speed(from, to, &self.speed_limits, &accel, self.params.speed);
        let id = send(ctx, &self.peers.arm, "move", serde_json::json!({ "positions": to, "speed": speed }))?;
        // The device's duration for that speed; a move still under way long after it is blocked.
        let duration = from
            .iter()
            .zip(to)
            .zip(&self.speed_limits)
            .map(|((a, b), v)| (b - a).abs() / (v * speed).max(1e-9))
            .fold(0.0, f64::max);
        let deadline = ctx.now() + Duration::from_secs_f64(2.0 * duration + self.params.move_slack_s);
        job.wait = Wait::Command(id, "arm move", Some((deadline, to.to_vec())));
        Ok(())
    }

    /// A straight segment, checked first.
    fn straight(
        &mut self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        to: &[f64],
        contact: bool,
    ) -> Result<(), String> {
        let (q, all) = self.arm_now(ctx)?;
        let held = if contact { None } else { self.held_shape() };
        let (from, to_all) = (self.kinematics.full(&q, &all), self.kinematics.full(to, &all));
        let c = self.clearance.segment_contact(&from, &to_all, held.as_ref(), !contact)?;
        if let Some((s, c)) = c {
            return Err(format!(
                "{}: the motion is stopped before it starts: at {:.0} % of it {c}",
                job.name,
                s * 100.0
            ));
        }
        self.move_arm(ctx, job, &q, to)
    }

    /// The tool's path down (or up) along its own x axis by `length`, as joint values every
    /// descent step, from the arm's values `q`.
    fn line(&self, q: &[f64], length: f64) -> Result<Vec<Vec<f64>>, String> {
        self.stepped(q, length, |start, d| start * Isometry3::translation(d, 0.0, 0.0))
    }

    /// The arm's values from `q` moving the tool by `dz` along the base's vertical (its
    /// orientation kept), every descent step.
    fn vertical(&self, q: &[f64], dz: f64) -> Result<Vec<Vec<f64>>, String> {
        self.along_base(q, &Vector3::z(), dz)
    }

    /// The arm's values from `q` moving the tool by `length` along the unit direction `dir` of the
    /// base frame (its orientation kept), every descent step.
    fn along_base(&self, q: &[f64], dir: &Vector3<f64>, length: f64) -> Result<Vec<Vec<f64>>, String> {
        self.stepped(q, length, |start, d| Isometry3::from(dir * d) * start)
    }

    /// The arm's values every descent step as the tool moves `length` from where it is at `q`,
    /// `moved` giving its pose (from the start pose) a signed distance along the way.
    fn stepped(
        &self,
        q: &[f64],
        length: f64,
        moved: impl Fn(&Isometry3<f64>, f64) -> Isometry3<f64>,
    ) -> Result<Vec<Vec<f64>>, String> {
        let start = self.kinematics.forward(q)?;
        let n = (length.abs() / self.params.descent_step_m).ceil().max(1.0) as usize;
        let mut seed = q.to_vec();
        let mut out = Vec::with_capacity(n);
        for k in 1..=n {
            seed = self.kinematics.inverse(&moved(&start, length * k as f64 / n as f64), &seed, &[])?;
            out.push(seed.clone());
        }
        Ok(out)
    }

    /// The object's newest pose seen at rest after `after`, in the tool frame (the arm at `q`).
    fn view(&self, ctx: &Ctx<'_>, object: &str, after: Time, q: &[f64]) -> Option<(Time, Isometry3<f64>)> {
        let poses = ctx.read(self.objects.as_ref()?)?;
        if poses.value.stamp < after {
            return None;
        }
        let o = poses.value.objects.iter().find(|o| o.object == object)?;
        // The arm rests: the believed kinematics that placed the camera at the stamp place the tool
        // now, so their errors cancel between the two.
        let base_from_tool = self.kinematics.forward(q).ok()?;
        Some((poses.value.stamp, base_from_tool.inverse() * o.base_from_object))
    }

    fn object_params(&self, object: &str) -> Result<&GraspableObject, String> {
        self.params.objects.get(object).ok_or_else(|| {
            format!(
                "no grasp configured for '{object}' (configured: {})",
                self.params.objects.keys().cloned().collect::<Vec<_>>().join(", ")
            )
        })
    }

    /// Takes the next action of a job whose wait is over; `Ok(true)` when none is left.
    fn next_action(&mut self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<bool, String> {
        let Some(action) = job.actions.pop_front() else { return Ok(true) };
        // Only a place's descent sets the object down (a failure there lets go early).
        job.setting_down = false;
        // A lift's steps go on lifting.
        job.lifting_free &= matches!(action, Action::Straight { contact: true, .. });
        // A planned move's segments go on with its goal.
        if !matches!(action, Action::Straight { contact: false, .. }) {
            job.planned = None;
        }
        match action {
            Action::Plan(to) => {
                if job.replanned.as_ref() != Some(&to) {
                    job.replanned = None;
                }
                job.planned = Some(to.clone());
                self.start_plan(ctx, job, &to)?
            }
            Action::Straight { to, contact } => {
                // A place's descent (not the lift of a place that failed, holding the object).
                job.setting_down =
                    contact && self.held.is_some() && job.slot.is_some() && job.failed.is_none();
                self.straight(ctx, job, &to, contact)?
            }
            Action::Recover(group) => {
                let to = match group {
                    Group::Arm => &self.peers.arm,
                    Group::Gripper => &self.peers.gripper,
                };
                let id = send(ctx, to, "recover", serde_json::Value::Null)?;
                job.wait = Wait::Command(id, "recover", None);
            }
            Action::Gripper(to) => {
                let id = send(ctx, &self.peers.gripper, "move", serde_json::json!({ "positions": to }))?;
                job.wait = Wait::Command(id, "gripper move", None);
            }
            Action::Approach | Action::Servo => {
                // Both need a view of the object at rest; the action goes back in front of the
                // queue and runs when the view comes (see `viewed`).
                job.actions.push_front(action);
                let now = ctx.now();
                let after = now + Duration::from_secs_f64(self.params.settle_s);
                job.wait = Wait::View { after, since: now, views: Vec::new() };
            }
            Action::Descend => {
                let (q, _) = self.arm_now(ctx)?;
                let path = self.line(&q, self.params.pregrasp_height_m)?;
                for p in path.into_iter().rev() {
                    job.actions.push_front(Action::Straight { to: p, contact: false });
                }
                return self.next_action(ctx, job);
            }
            Action::Lift => {
                let (q, _) = self.arm_now(ctx)?;
                // Up: an object still held out of a slot along the vertical, the way it went down
                // (a descent that stopped short may leave the tool tilted); else, and the open
                // fingers off an object let go, against the tool's x axis (the way the fingers
                // point: a tilted tool going up vertically drags a finger along the handle).
                let path = if job.slot.is_some() && self.held.is_some() {
                    self.vertical(&q, self.params.lift_m)?
                } else {
                    self.line(&q, -self.params.lift_m)?
                };
                job.lifting_free = self.held.is_none();
                for p in path.into_iter().rev() {
                    job.actions.push_front(Action::Straight { to: p, contact: true });
                }
                return self.next_action(ctx, job);
            }
            Action::CheckGrip => self.check_grip(ctx, job)?,
            Action::Recentre => {
                let (q, _) = self.arm_now(ctx)?;
                let path =
                    job.seat.as_ref().map(|seat| self.recentre(&q, seat)).transpose()?.unwrap_or_default();
                for p in path.into_iter().rev() {
                    job.actions.push_front(Action::Straight { to: p, contact: true });
                }
                return self.next_action(ctx, job);
            }
            Action::Released => {
                // Let go in the slot, the object stays there: the arm keeps clear of it.
                if let (Some(shape), Some(slot)) = (self.held_shape(), job.slot.clone()) {
                    let (_, all) = self.arm_now(ctx)?;
                    let m = self.kinematics.mechanism();
                    let base_from_tool =
                        m.transform(m.root(), self.kinematics.tip(), &all).map_err(|e| e.to_string())?;
                    let base_from_slot = m.transform(m.root(), &slot, &all).map_err(|e| e.to_string())?;
                    let link = m.link(&slot).map_err(|e| e.to_string())?;
                    let origin = base_from_slot.inverse() * base_from_tool * shape.shape.origin;
                    self.clearance.add_placed(Held { link, shape: CollisionBox { origin, ..shape.shape } });
                }
                self.held = None;
                return self.next_action(ctx, job);
            }
        }
        Ok(false)
    }

    /// Advances the job; its result once it ends.
    fn advance(&mut self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<Option<serde_json::Value>, String> {
        match job.wait.clone() {
            Wait::Idle => {}
            Wait::Command(id, what, deadline) => match ctx.ack_status(id) {
                Some(AckStatus::Completed(_)) => job.wait = Wait::Idle,
                // Not in fault: nothing to recover.
                Some(AckStatus::Rejected(_) | AckStatus::Failed(_)) if what == "recover" => {
                    job.wait = Wait::Idle
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) if job.setting_down => {
                    self.set_down_early(ctx, job, &format!("{what} failed: {r}"));
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r))
                    if job.lifting_free && !job.lift_retried =>
                {
                    // A finger caught firmly stalls a servo: the move fails rather than stops short.
                    self.lift_again(ctx, job, deadline.map(|(_, q)| q), &format!("failed: {r}"))?;
                }
                Some(AckStatus::Failed(r))
                    if r.contains("stalled") && job.planned.is_some() && job.replanned.is_none() =>
                {
                    self.plan_again(ctx, job, &format!("{what} failed: {r}"));
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    return Err(format!("{what} failed: {r}"));
                }
                _ if deadline.as_ref().is_some_and(|(d, _)| ctx.now() > *d) => {
                    let _ = ctx.send(Command::new(&self.peers.arm, "stop"));
                    let goal = deadline.map(|(_, q)| q).unwrap_or_default();
                    let (q, _) = self.arm_now(ctx)?;
                    let (at, want) = (self.kinematics.forward(&q)?, self.kinematics.forward(&goal)?);
                    let off = (at.translation.vector - want.translation.vector).norm();
                    let angle = (at.rotation.inverse() * want.rotation).angle();
                    let far =
                        off > self.params.arrive_tolerance_m || angle > self.params.arrive_tolerance_m / 0.1;
                    if far && job.setting_down {
                        let why = format!("the arm stopped {:.1} mm from its goal", off * 1e3);
                        self.set_down_early(ctx, job, &why);
                        return Ok(None);
                    }
                    if far && job.lifting_free && !job.lift_retried {
                        let why = format!("stopped {:.1} mm from its goal", off * 1e3);
                        self.lift_again(ctx, job, Some(goal), &why)?;
                        return Ok(None);
                    }
                    if far && job.planned.is_some() && job.replanned.is_none() {
                        let why = format!("the arm stopped {:.1} mm from its goal", off * 1e3);
                        self.plan_again(ctx, job, &why);
                        return Ok(None);
                    }
                    if far {
                        return Err(format!(
                            "{what}: the arm stopped {:.1} mm from its goal (blocked on its way?)",
                            off * 1e3
                        ));
                    }
                    // The servos hold a load a few milliradians off: near enough goes on.
                    job.wait = Wait::Idle;
                }
                _ => return Ok(None),
            },
            Wait::View { after, since, mut views } => {
                let object = job.object.clone().ok_or("no object")?;
                let (q, _) = self.arm_now(ctx)?;
                if let Some((stamp, t)) = self.view(ctx, &object, after, &q)
                    && views.last().is_none_or(|(last, _)| stamp > *last)
                {
                    views.push((stamp, t));
                }
                let timed_out = (ctx.now() - since).as_secs_f64() > self.params.observe_timeout_s;
                if views.len() >= self.params.view_frames as usize || (timed_out && !views.is_empty()) {
                    job.wait = Wait::Idle;
                    let poses: Vec<Isometry3<f64>> = views.into_iter().map(|(_, t)| t).collect();
                    self.viewed(ctx, job, mean_pose(&poses))?;
                    return Ok(None);
                }
                if timed_out {
                    return Err(format!(
                        "the wrist camera did not see the {object} within {} s",
                        self.params.observe_timeout_s
                    ));
                }
                job.wait = Wait::View { after, since, views };
                return Ok(None);
            }
        }
        if self.next_action(ctx, job)? {
            return Ok(Some(self.result(ctx, job)));
        }
        Ok(None)
    }

    fn result(&self, ctx: &Ctx<'_>, job: &Job) -> serde_json::Value {
        let tool = self.arm_now(ctx).ok().and_then(|(q, _)| self.kinematics.forward(&q).ok());
        serde_json::json!({
            "holding": self.held.as_ref().map(|(k, _)| k.clone()),
            "servo_steps": job.servo_steps,
            "servo_error_mm": job.last_error.map(|(p, ..)| p * 1e3),
            "servo_error_deg": job.last_error.map(|(_, a, _)| a.to_degrees()),
            "servo_tilt_deg": job.last_error.map(|(.., tilt)| tilt.to_degrees()),
            "tool": tool.map(|t| [t.translation.x, t.translation.y, t.translation.z]),
        })
    }

    fn start(
        &mut self,
        ctx: &mut Ctx<'_>,
        name: &'static str,
        actions: Vec<Action>,
        object: Option<String>,
        slot: Option<String>,
    ) -> Outcome {
        let Some(request) = ctx.request() else {
            return Outcome::reject(format!("{name} must come as a command"));
        };
        self.cancel(ctx, &format!("superseded by {name}"));
        let mut job = Job {
            request,
            name,
            actions: actions.into(),
            wait: Wait::Idle,
            object,
            grasp: None,
            servo_steps: 0,
            last_error: None,
            failed: None,
            slot,
            setting_down: false,
            seat: None,
            lifting_free: false,
            lift_retried: false,
            planned: None,
            replanned: None,
        };
        match self.next_action(ctx, &mut job) {
            Ok(true) => Outcome::Completed(self.result(ctx, &job)),
            Ok(false) => {
                self.job = Some(job);
                Outcome::Accepted
            }
            Err(e) => Outcome::reject(e),
        }
    }

    /// Ends the job in progress, if any, with `reason`, stopping the arm.
    fn cancel(&mut self, ctx: &mut Ctx<'_>, reason: &str) {
        let Some(job) = self.job.take() else { return };
        if matches!(job.wait, Wait::Command(..)) {
            let _ = ctx.send(Command::new(&self.peers.arm, "stop"));
        }
        self.last = Some(format!("{}: {reason}", job.name));
        ctx.reply(&job.request, Outcome::fail(reason));
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        if let Some(mut job) = self.job.take() {
            match self.advance(ctx, &mut job) {
                Ok(None) => self.job = Some(job),
                Ok(Some(_)) if job.failed.is_some() => {
                    let why = job.failed.take().unwrap_or_default();
                    self.last = Some(format!("{}: {why}", job.name));
                    ctx.note(format!("{} failed: {why}", job.name));
                    ctx.reply(&job.request, Outcome::fail(why));
                }
                Ok(Some(result)) => {
                    self.last = Some(format!("{}: completed", job.name));
                    ctx.note(format!("{} completed: {result}", job.name));
                    ctx.reply(&job.request, Outcome::Completed(result));
                }
                Err(reason) => {
                    self.last = Some(format!("{}: {reason}", job.name));
                    ctx.note(format!("{} failed: {reason}", job.name));
                    ctx.reply(&job.request, Outcome::fail(reason));
                }
            }
        }
        self.publish(ctx);
        Ok(())
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let Some(w) = &self.out else { return };
        let tool = self.arm_now(ctx).ok().and_then(|(q, _)| self.kinematics.forward(&q).ok());
        let state = ManipulationState {
            command: self.job.as_ref().map(|j| j.name.to_string()),
            step: self.job.as_ref().map_or("idle".into(), |j| match &j.wait {
                Wait::Idle => "idle".into(),
                Wait::Command(_, what, _) => (*what).to_string(),
                Wait::View { .. } => "view".into(),
            }),
            tool_in_base: tool,
            holding: self.held.as_ref().map(|(k, _)| k.clone()),
            servo_steps: self.job.as_ref().map_or(0, |j| j.servo_steps),
            servo_error_m: self.job.as_ref().and_then(|j| j.last_error.map(|e| e.0)),
            last_outcome: self.last.clone(),
        };
        ctx.write(w, state);
    }
}

impl Module for ManipulatorControl {
    type Params = ManipulatorParams;
    const KIND: ModuleKind = ModuleKind::Coordination;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        let groups: Vec<String> = [self.peers.arm.clone(), self.peers.gripper.clone()]
            .into_iter()
            .chain(self.peers.others.clone())
            .collect();
        self.joints = groups.iter().map(|g| Some(d.reads(&format!("{g}/joints")))).collect();
        self.objects = Some(d.reads(&self.peers.objects));
        self.out = Some(d.writes(SLOT));
        d.sends_to(&self.peers.arm).sends_to(&self.peers.gripper);
        d.context_switchable();
        d.state("active", |m, ctx| m.cycle(ctx));
        d.command("move_named", |m, ctx, a: MoveNamedArgs| {
            let Some(q) = m.params.poses.get(&a.pose).cloned() else {
                return Outcome::reject(format!(
                    "no pose '{}' (configured: {})",
                    a.pose,
                    m.params.poses.keys().cloned().collect::<Vec<_>>().join(", ")
                ));
            };
            m.start(ctx, "move_named", vec![Action::Plan(q)], None, None)
        });
        d.command("move_tool", |m, ctx, a: MoveToolArgs| {
            let [r, p, y] = a.rpy_deg.map(f64::to_radians);
            let goal = Isometry3::from_parts(
                Translation3::from(Vector3::from(a.position)),
                UnitQuaternion::from_euler_angles(r, p, y),
            );
            let q = match m.arm_now(ctx).and_then(|(q, _)| m.kinematics.inverse(&goal, &q, &m.seeds())) {
                Ok(q) => q,
                Err(e) => return Outcome::reject(e),
            };
            m.start(ctx, "move_tool", vec![Action::Plan(q)], None, None)
        });
        d.command("grasp", |m, ctx, a: GraspArgs| {
            if let Err(e) = m.object_params(&a.object) {
                return Outcome::reject(e);
            }
            if let Some((k, _)) = &m.held {
                return Outcome::reject(format!("the gripper already holds the {k}"));
            }
            let open = vec![m.params.open_m; m.fingers.len()];
            let close = vec![0.0; m.fingers.len()];
            let actions = vec![
                Action::Recover(Group::Gripper),
                Action::Gripper(open),
                Action::Approach,
                Action::Gripper(close),
                Action::CheckGrip,
                Action::Lift,
            ];
            m.start(ctx, "grasp", actions, Some(a.object), None)
        });
        d.command("place", |m, ctx, a: PlaceArgs| {
            let slot = a.slot.unwrap_or_else(|| "stow_slot".into());
            match m.place_actions(ctx, &slot) {
                Ok((actions, seat)) => {
                    let outcome = m.start(ctx, "place", actions, None, Some(slot));
                    if let Some(job) = &mut m.job {
                        job.seat = Some(seat);
                    }
                    outcome
                }
                Err(e) => Outcome::reject(e),
            }
        });
        d.command("open", |m, ctx, _: ()| {
            let open = vec![m.params.open_m; m.fingers.len()];
            m.start(ctx, "open", vec![Action::Gripper(open), Action::Released], None, None)
        });
        d.command("close", |m, ctx, _: ()| {
            let close = vec![0.0; m.fingers.len()];
            m.start(ctx, "close", vec![Action::Gripper(close)], None, None)
        });
        d.command("stop", |m, ctx, _: ()| {
            m.cancel(ctx, "stopped by command");
            let _ = ctx.send(Command::new(&m.peers.arm, "stop"));
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &ManipulatorParams) -> Result<(), String> {
        p.validate(&self.kinematics.limits(), self.kinematics.joint_names())?;
        self.clearance = Clearance::new(
            self.kinematics.mechanism(),
            is_arm_link,
            COAXIAL,
            clearance_params(self.kinematics.mechanism(), p)?,
        );
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        if matches!(to, Lifecycle::Hold | Lifecycle::Safe | Lifecycle::Shutdown) {
            self.cancel(ctx, &format!("'{}' left Run for {to}", ctx.name()));
        }
        Ok(())
    }
}
