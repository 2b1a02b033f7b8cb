//! CoordinatorVisualTracking (seed 000, 8.1): keeps the tracked target in the head camera's view
//! with the pan-tilt unit, and offers the operator's three commands of increasing autonomy:
//!
//! - `point_locate {max_sigma_m?}`: points the head at the target and has TrackingTarget locate it;
//!   completes with its position in `map`, its uncertainty and its distance from the rover;
//! - `point_locate_approach {boundary_m, max_sigma_m?}`: the same, then hands the navigator a goal on
//!   the line from the rover to the target, inside the boundary, and turns the rover to face the
//!   target; completes within `boundary_m` of the target's estimate;
//! - `point_locate_approach_track {max_distance_m, max_sigma_m?}`: repeats point, locate and
//!   approach in legs (each ending at a fraction of the distance left, where stereo ranges the
//!   target better, so the first uncertain estimate is refined on the way; a moving target's
//!   estimate follows it) until the rover is within `max_distance_m`, then faces it (found outside
//!   once faced, as a refined or moving estimate can say, it locates and approaches again);
//! - `stop`: ends the command in progress (the navigation it started is cancelled) and the pursuit.
//!
//! No leg ends nearer the target's estimate than `clearance_m` (where the rover, turning in place
//! to face it, could touch it) plus `clearance_sigmas` of the estimate's uncertainty along the line
//! to it: a leg that would stops there, and where the rover is there already the target is located
//! again to the accuracy at which the final leg ends clear of it (`legs`). A leg's goal where the
//! navigation map leaves the rover no room (the planner would refuse it, attempt after attempt: a
//! rock on the line, or the target itself where its estimate lies beyond it on a look-alike) is
//! moved round the target's estimate at the same distance (`legs::standing_room`).
//!
//! A far target that is tracked but cannot be located to a leg's accuracy (a few pixels wide,
//! stereo ranges it poorly or not at all) is approached along its line of sight: a leg over part
//! of its range (stereo's, however coarse, or for a target of known size the nearest its selected
//! box's size allows), after which it is nearer, larger, and located again.
//! An approach whose target, with its estimate within `reject_unseen_within_m` of the rover (where
//! it would be plainly in view), is lost or not located to the asked accuracy in time followed a
//! look-alike from afar (a rock along the line of sight): TrackingTarget rejects that estimate
//! and looks again along the line of sight the target was selected on; once the head camera finds
//! it again there, the approach goes on (once per command).
//! An approach leg that fails (a wheel stalls short of the goal) with the rover already within the
//! boundary by the target's estimate ends in facing the target as an arrival would.
//! A turn to face the target that stalls a wheel (turning in place on loose ground) is tried once
//! more after locomotion's fault is cleared (`recover`); a second stall fails the command.
//! The target's position is its estimate carried by its velocity to the time it is used.
//!
//! Pursuit: from a command until `stop`, each cycle aims the head camera's optical axis at the
//! target (its fused stereo position once located; before that, its line of sight at the last or an
//! assumed range), through the believed mechanism and the current pose estimate, so the target
//! stays in view while the rover drives and turns. The pan-tilt unit is shared: while the navigator
//! scans the terrain with it (its `scan` phase) the pursuit yields and resumes after.
//! Progress is published on `tracking/visual` ([`VisualTrackingState`]).

use crate::peer::send;
use crate::tracking::locate_sigma;
use crate::tracking::pointing::PanTiltCamera;
use framework::data::{
    JointStates, NavigationMap, NavigationState, PoseEstimate, TargetStatus, TargetTrack, VisualTrackingState,
};
use framework::message::{AckStatus, MessageId};
use framework::module::Request;
use framework::prelude::*;
use nalgebra::Point3;
mod face;
mod legs;
mod params;
mod pursuit;
#[cfg(test)]
mod tests;

pub use legs::{Faced, Leg, bearing_goal, faced, final_leg, final_sigma, next_leg, ranged, sized_middle};
pub use params::{ApproachArgs, ApproachTrackArgs, PointLocateArgs, VisualTrackingParams};

/// A pan-tilt command unchanged is sent again after this many command periods off target.
const RESEND_PERIODS: f64 = 4.0;

/// The slot of the coordinator's state.
pub const SLOT: &str = "tracking/visual";

/// Which command a job carries out.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    PointLocate,
    Approach { boundary: f64 },
    Track { max_distance: f64 },
}

impl Kind {
    /// The distance the command must end within, for those that approach.
    fn boundary(&self) -> Option<f64> {
        match *self {
            Kind::PointLocate => None,
            Kind::Approach { boundary } => Some(boundary),
            Kind::Track { max_distance } => Some(max_distance),
        }
    }

    fn name(&self) -> &'static str {
        match self {
            Kind::PointLocate => "point_locate",
            Kind::Approach { .. } => "point_locate_approach",
            Kind::Track { .. } => "point_locate_approach_track",
        }
    }
}

/// Where a job is.
#[derive(Clone, Debug)]
enum Step {
    /// Waiting for the target to be tracked, since.
    AwaitTarget(Time),
    /// Asked TrackingTarget to locate (message, since, accuracy, whether a far target not
    /// located in time may be approached along its line of sight instead).
    Locate(MessageId, Time, f64, bool),
    /// Driving to a goal.
    Approach(MessageId, [f64; 2]),
    /// Turning to face the target.
    Face(MessageId),
    /// Clearing locomotion's fault (a wheel stalled in the turn, or in a failed leg that ended
    /// within the boundary) before turning to face the target.
    Recover(MessageId),
    /// TrackingTarget told to reject the target's estimate (message, since, the failure that
    /// led to it): waiting for the rejection and for the target to be found again where
    /// TrackingTarget then looks for it (the head turning there), before locating it.
    Reacquire(MessageId, Time, String),
}

/// Turns that stalled a wheel and are tried again (after locomotion's fault is cleared) before the
/// job fails: turning in place on loose ground can bog a wheel down once.
const FACE_RETRIES: u32 = 1;

impl Step {
    fn name(&self) -> &'static str {
        match self {
            Step::AwaitTarget(_) => "await_target",
            Step::Locate(..) => "locate",
            Step::Approach(..) => "approach",
            Step::Face(_) => "face",
            Step::Recover(_) => "recover",
            Step::Reacquire(..) => "reacquire",
        }
    }
}

/// A command in progress.
struct Job {
    request: Request,
    kind: Kind,
    step: Step,
    max_sigma: f64,
    legs: u32,
    /// Stalled turns tried again so far.
    face_retries: u32,
    /// Times the target was found outside the boundary once faced.
    refaced: u32,
    /// Times the estimate was too uncertain to come nearer and was located again sharper.
    sharpened: u32,
    /// The estimate was rejected, the target unseen near the rover (`reject_unseen_within_m`).
    rejected: bool,
}

/// Names of the modules the coordinator commands.
#[derive(Clone, Debug)]
pub struct VisualTrackingPeers {
    /// TrackingTarget.
    pub tracker: String,
    /// The pan-tilt unit's joint group.
    pub ptu: String,
    /// Locomotion (turning to face the target).
    pub locomotion: String,
    /// CoordinatorNavigator, when the system navigates (approaches need it).
    pub navigator: Option<String>,
}

/// The CoordinatorVisualTracking module.
pub struct CoordinatorVisualTracking {
    peers: VisualTrackingPeers,
    camera: PanTiltCamera,
    pose_slot: String,
    track: Option<Reader<TargetTrack>>,
    pose: Option<Reader<PoseEstimate>>,
    joints: Option<Reader<JointStates>>,
    navigation: Option<Reader<NavigationState>>,
    /// The navigation map: where a leg's goal leaves the rover room to stand.
    map: Option<Reader<NavigationMap>>,
    out: Option<Writer<VisualTrackingState>>,
    params: VisualTrackingParams,
    job: Option<Job>,
    pursuing: bool,
    /// The last pan and tilt commanded and when.
    commanded: Option<([f64; 2], Time)>,
    /// Where the head was last aimed (`map`).
    aim: Option<Point3<f64>>,
    yielding: bool,
    /// The last job's outcome, for the state.
    last: Option<String>,
}

impl CoordinatorVisualTracking {
    /// A coordinator of `peers` pointing `camera` (the tracking camera on the pan-tilt unit), with
    /// the rover's pose estimate from `pose_slot`.
    pub fn new(peers: VisualTrackingPeers, camera: PanTiltCamera, pose_slot: &str) -> Self {
        CoordinatorVisualTracking {
            peers,
            camera,
            pose_slot: pose_slot.to_string(),
            track: None,
            pose: None,
            joints: None,
            navigation: None,
            map: None,
            out: None,
            params: VisualTrackingParams::default(),
            job: None,
            pursuing: false,
            commanded: None,
            aim: None,
            yielding: false,
            last: None,
        }
    }

    /// The target's track, once a target is being tracked.
    fn track(&self, ctx: &Ctx<'_>) -> Option<TargetTrack> {
        self.track
            .as_ref()
            .and_then(|r| ctx.read(r))
            .map(|t| t.value.clone())
            .filter(|t| !t.target.is_empty())
    }

    fn pose(&self, ctx: &Ctx<'_>) -> Option<PoseEstimate> {
        self.pose.as_ref().and_then(|r| ctx.read(r)).map(|p| p.value.clone())
    }

    /// Asks TrackingTarget to locate to the accuracy the job's next step needs.
    fn locate(&self, ctx: &mut Ctx<'_>, job: &Job) -> Result<Step, String> {
        let sigma = match job.kind {
            Kind::Track { max_distance } => {
                // A far target first to the accuracy its leg needs, the last leg's to the asked one
                // and to the one that lets it end clear of the target.
                let range = self
                    .distance(ctx)
                    .or_else(|| self.track(ctx).and_then(|t| t.range_m.or(sized_middle(&t))))
                    .unwrap_or(self.params.sight_range_m);
                if range > max_distance / self.params.leg_fraction {
                    job.max_sigma.max(self.params.leg_sigma_fraction * range)
                } else {
                    job.max_sigma.min(final_sigma(max_distance, &self.params))
                }
            }
            _ => job.max_sigma,
        };
        self.locate_to(ctx, sigma, true)
    }

    /// Asks TrackingTarget to locate to `sigma` (1 sigma, m); `bearing`: a far target not located
    /// in time may be approached along its line of sight instead.
    fn locate_to(&self, ctx: &mut Ctx<'_>, sigma: f64, bearing: bool) -> Result<Step, String> {
        let id = send(ctx, &self.peers.tracker, "locate", serde_json::json!({ "max_sigma_m": sigma }))?;
        Ok(Step::Locate(id, ctx.now(), sigma, bearing))
    }

    /// A leg along the target's line of sight, for a far target still tracked (seen within the
    /// last second) and ranged at least roughly (by stereo, or by its known size) that stereo
    /// cannot locate to a leg's accuracy:
    /// None when it is not tracked, has no range, or the job has no legs left (the locate then
    /// goes on until its timeout).
    fn bearing_leg(&self, ctx: &mut Ctx<'_>, job: &mut Job) -> Option<Step> {
        let track = self.track(ctx)?;
        let now = ctx.now();
        let seen = track.status != TargetStatus::Lost && (now - track.stamp).as_secs_f64() <= 1.0;
        let sight = track.line_of_sight.filter(|_| seen)?;
        let pose = self.pose(ctx)?;
        let r = pose.pose.translation.vector;
        // A range from stereo, however coarse, or the nearest a target of known size may be
        // (never the assumed one: legs on no evidence could drive past a target that is near but
        // too small to range).
        let range = self.distance(ctx).or_else(|| ranged(&track))?;
        let goal = bearing_goal([r.x, r.y], &sight.direction, range, &self.params)?;
        let nav = self.peers.navigator.clone()?;
        if job.legs >= self.params.max_legs {
            return None;
        }
        let args =
            serde_json::json!({ "x": goal[0], "y": goal[1], "tolerance_m": self.params.leg_tolerance_m });
        let id = match send(ctx, &nav, "navigate_to", args) {
            Ok(id) => id,
            Err(e) => {
                ctx.note(format!("cannot send a leg along the line of sight: {e}"));
                return None;
            }
        };
        job.legs += 1;
        ctx.note(format!(
            "{} leg {}: not located to a leg's accuracy within {} s: {:.2} m along the line of sight (bearing {:.1} deg), to ({:.2}, {:.2})",
            job.kind.name(),
            job.legs,
            self.params.bearing_after_s,
            (goal[0] - r.x).hypot(goal[1] - r.y),
            sight.direction.y.atan2(sight.direction.x).to_degrees(),
            goal[0],
            goal[1]
        ));
        Some(Step::Approach(id, goal))
    }

    /// After a locate (sent at `since`) that failed or timed out, with `reason`: where an
    /// approach's static target has its estimate within `reject_unseen_within_m` of the rover
    /// (in plain view there, and located sharply by stereo) and is lost, or has had no location
    /// fused since the locate began, the estimate followed something that is not the target:
    /// TrackingTarget is told to reject it (looking again along the line of sight the target was
    /// selected on) and the job waits for the target to be found there, once per command. None
    /// otherwise (the job fails with the locate).
    fn reject_unseen(&self, ctx: &mut Ctx<'_>, job: &mut Job, since: Time, reason: String) -> Option<Step> {
        let within = self.params.reject_unseen_within_m;
        if job.rejected || within <= 0.0 || job.kind.boundary().is_none() {
            return None;
        }
        let (target, rover, track) = self.positions(ctx).ok()?;
        let d = dist(rover, &target);
        // A moving target may simply have left: its line of sight of old says nothing of it
        // (a static one's velocity is zero, whatever horizon it is published with).
        let moving = track.velocity.norm() > 0.0;
        let lost = track.status == TargetStatus::Lost;
        let unseen = lost || track.position_stamp.is_none_or(|s| s <= since);
        if d > within || moving || !unseen {
            return None;
        }
        let args = serde_json::json!({ "position": [target.x, target.y, target.z] });
        let id = match send(ctx, &self.peers.tracker, "reject", args) {
            Ok(id) => id,
            Err(e) => {
                ctx.note(format!("cannot reject the unseen target's estimate: {e}"));
                return None;
            }
        };
        job.rejected = true;
        let what = if lost { "lost" } else { "not located" };
        ctx.note(format!(
            "{}: the target is {what} with its estimate {d:.2} m away, where it would be in plain view: the estimate followed something else; rejecting it, looking again along the line of sight it was selected on",
            job.kind.name()
        ));
        Some(Step::Reacquire(id, ctx.now(), reason))
    }

    /// The target's located position (carried by its velocity to now) and the rover's, in `map`.
    fn positions(&self, ctx: &Ctx<'_>) -> Result<(Point3<f64>, [f64; 2], TargetTrack), String> {
        let track = self.track(ctx).ok_or("no target tracked")?;
        let target = track.position_at(ctx.now()).ok_or("the target is not located")?;
        let pose = self.pose(ctx).ok_or_else(|| format!("no pose estimate on '{}'", self.pose_slot))?;
        let r = pose.pose.translation.vector;
        Ok((target, [r.x, r.y], track))
    }

    /// Horizontal distance from the rover to the located target, m.
    fn distance(&self, ctx: &Ctx<'_>) -> Option<f64> {
        self.positions(ctx).ok().map(|(target, rover, _)| dist(rover, &target))
    }

    /// What a job does after a locate or an arrival: the next leg, facing, or the result.
    fn after_locate(&self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<Option<Outcome>, String> {
        let (target, rover, t) = self.positions(ctx)?;
        let Some(boundary) = job.kind.boundary() else {
            return Ok(Some(Outcome::Completed(self.result(ctx, job)?)));
        };
        let track = matches!(job.kind, Kind::Track { .. });
        let sigma = sigma_along(rover, &target, &t);
        match next_leg(rover, [target.x, target.y], sigma, boundary, track, &self.params) {
            Leg::Arrived => job.step = self.face(ctx)?,
            Leg::Sharpen(want) => {
                if job.sharpened >= self.params.max_legs {
                    return Err(format!(
                        "the target's estimate, {sigma:.2} m uncertain (1 sigma) {:.2} m away, was sharpened {} times and is still too uncertain to come nearer clear of it",
                        dist(rover, &target),
                        job.sharpened
                    ));
                }
                job.sharpened += 1;
                // TrackingTarget's locate bounds the larger of the x and y sigmas, not the one
                // along the line: asked in proportion, for an ellipse the same shape.
                let ask = want * locate_sigma(&t.covariance) / sigma.max(1e-9);
                ctx.note(format!(
                    "{}: the target's estimate, {sigma:.2} m uncertain (1 sigma) along the line to it {:.2} m away, is too uncertain to come nearer clear of it: locating it to {want:.3} m along that line first ({ask:.3} m in x and y)",
                    job.kind.name(),
                    dist(rover, &target)
                ));
                // No leg along the line of sight meanwhile: it would keep no margin for the
                // estimate's error.
                job.step = self.locate_to(ctx, ask, false)?;
            }
            Leg::Drive { goal, tolerance } => {
                if job.legs >= self.params.max_legs {
                    return Err(format!(
                        "still {:.2} m from the target after {} legs",
                        dist(rover, &target),
                        job.legs
                    ));
                }
                let nav =
                    self.peers.navigator.clone().ok_or("no navigator in this system: cannot approach")?;
                // A goal the map leaves the rover no room at (in an obstacle's inflation: a rock
                // on the line, or the target itself where the estimate lies beyond it on a
                // look-alike) is moved round the target, at the same distance from it.
                let map = self.map.as_ref().and_then(|r| ctx.read(r));
                let moved =
                    map.and_then(|m| legs::standing_room(&m.value, [target.x, target.y], goal, tolerance));
                let goal = if let Some((at, turn)) = moved {
                    ctx.note(format!(
                        "{}: the leg's goal ({:.2}, {:.2}) leaves the rover no room on the navigation map: moved {turn:.0} deg round the target's estimate, to ({:.2}, {:.2})",
                        job.kind.name(),
                        goal[0],
                        goal[1],
                        at[0],
                        at[1]
                    ));
                    at
                } else {
                    goal
                };
                let args = serde_json::json!({ "x": goal[0], "y": goal[1], "tolerance_m": tolerance });
                let id = send(ctx, &nav, "navigate_to", args)?;
                job.legs += 1;
                ctx.note(format!(
                    "{} leg {}: to ({:.2}, {:.2}), {:.2} m from the target's estimate",
                    job.kind.name(),
                    job.legs,
                    goal[0],
                    goal[1],
                    (goal[0] - target.x).hypot(goal[1] - target.y)
                ));
                job.step = Step::Approach(id, goal);
            }
        }
        Ok(None)
    }

    /// Clears locomotion's fault (the step after it turns to face the target).
    fn recover(&self, ctx: &mut Ctx<'_>) -> Result<Step, String> {
        Ok(Step::Recover(send(ctx, &self.peers.locomotion, "recover", serde_json::Value::Null)?))
    }

    /// A completed job's result.
    fn result(&self, ctx: &Ctx<'_>, job: &Job) -> Result<serde_json::Value, String> {
        let (target, rover, track) = self.positions(ctx)?;
        let pose = self.pose(ctx).ok_or("no pose estimate")?;
        let c = track.covariance;
        let bearing = (target.y - rover[1]).atan2(target.x - rover[0]);
        let (_, _, yaw) = pose.pose.rotation.euler_angles();
        Ok(serde_json::json!({
            "target": track.target,
            "position": [target.x, target.y, target.z],
            "sigma_m": [c[(0, 0)].sqrt(), c[(1, 1)].sqrt(), c[(2, 2)].sqrt()],
            "distance_m": dist(rover, &target),
            "bearing_off_heading_deg": framework::angle::wrap(bearing - yaw).to_degrees(),
            "legs": job.legs,
        }))
    }

    /// Advances the job in progress; its outcome once it ends.
    fn advance(&mut self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<Option<Outcome>, String> {
        let now = ctx.now();
        match job.step.clone() {
            Step::AwaitTarget(since) => {
                if self.track(ctx).is_some() {
                    job.step = self.locate(ctx, job)?;
                } else if (now - since).as_secs_f64() > self.params.target_wait_s {
                    return Err(format!(
                        "no target tracked after {} s: the operator must select one",
                        self.params.target_wait_s
                    ));
                }
            }
            Step::Locate(id, since, sigma, bearing) => match ctx.ack_status(id) {
                Some(AckStatus::Completed(_)) => return self.after_locate(ctx, job),
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    let reason = format!("locate failed: {r}");
                    job.step = self.reject_unseen(ctx, job, since, reason.clone()).ok_or(reason)?;
                }
                // A far leg's accuracy (above the job's own) not reached in a while: along the
                // line of sight, if the target is tracked.
                _ if matches!(job.kind, Kind::Track { .. })
                    && bearing
                    && sigma > job.max_sigma
                    && (now - since).as_secs_f64() > self.params.bearing_after_s
                    && let Some(step) = self.bearing_leg(ctx, job) =>
                {
                    let _ = ctx.send(Command::new(&self.peers.tracker, "stop"));
                    job.step = step;
                }
                _ if (now - since).as_secs_f64() > self.params.locate_timeout_s => {
                    let _ = ctx.send(Command::new(&self.peers.tracker, "stop"));
                    let reason = format!(
                        "the target was not located to {sigma:.2} m within {} s",
                        self.params.locate_timeout_s
                    );
                    job.step = self.reject_unseen(ctx, job, since, reason.clone()).ok_or(reason)?;
                }
                _ => {}
            },
            Step::Approach(id, _) => match ctx.ack_status(id) {
                Some(AckStatus::Completed(_)) => {
                    // Locate again from here: nearer, the estimate sharpens (or follows a moving
                    // target) before the next leg or the final check.
                    job.step = self.locate(ctx, job)?;
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    // The leg aimed inside the boundary with room to spare: a leg that fails
                    // (a wheel bogged down short of its goal) may still have brought the rover
                    // within it, which is what the command asks.
                    let within = job.kind.boundary().zip(self.distance(ctx)).filter(|(b, d)| d <= b);
                    let Some((b, d)) = within else {
                        return Err(format!("approach failed: {r}"));
                    };
                    ctx.note(format!(
                        "the approach leg failed ({r}), but the target is {d:.2} m away, within the {b:.2} m boundary: clearing locomotion's fault, facing it"
                    ));
                    job.step = self.recover(ctx)?;
                }
                _ => {}
            },
            Step::Face(id) => match ctx.ack_status(id) {
                // A turn that locomotion's obstacle guard refused or stopped (the rover's corners
                // would sweep the target, or a rock beside it): on from the heading it has.
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r))
                    if crate::locomotion::guard::is_guard_reason(&r) =>
                {
                    ctx.note(format!("turning to face the target: {r}; going on from this heading"));
                    return self.faced_here(ctx, job);
                }
                Some(AckStatus::Completed(_)) => return self.faced_here(ctx, job),
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    if r.contains("stalled") && job.face_retries < FACE_RETRIES {
                        job.face_retries += 1;
                        ctx.note(format!(
                            "turning to face the target failed ({r}): clearing the fault, turning again"
                        ));
                        job.step = self.recover(ctx)?;
                    } else {
                        return Err(format!("turning to face the target failed: {r}"));
                    }
                }
                _ => {}
            },
            Step::Reacquire(id, since, reason) => match ctx.ack_status(id) {
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    return Err(format!("{reason}; its estimate could not be rejected: {r}"));
                }
                // Rejected, and found again (tracked or re-detected in an image since): located.
                Some(AckStatus::Completed(_))
                    if self.track(ctx).is_some_and(|t| t.status != TargetStatus::Lost && t.stamp > since) =>
                {
                    job.step = self.locate(ctx, job)?;
                }
                _ if (now - since).as_secs_f64() > self.params.locate_timeout_s => {
                    return Err(format!(
                        "{reason}; not found again within {} s of its estimate's rejection",
                        self.params.locate_timeout_s
                    ));
                }
                _ => {}
            },
            Step::Recover(id) => match ctx.ack_status(id) {
                // Rejected: not in fault any more; either way, turn again.
                Some(AckStatus::Completed(_) | AckStatus::Rejected(_)) => job.step = self.face(ctx)?,
                Some(AckStatus::Failed(r)) => return Err(format!("cannot clear locomotion's fault: {r}")),
                _ => {}
            },
        }
        Ok(None)
    }

    /// Whether an approach may be asked to end within `boundary` (the argument `name`): the final
    /// leg must end clear of the target (`clearance_m`) with room for the estimate's error.
    fn approachable(&self, name: &str, boundary: f64) -> Result<(), String> {
        if !(boundary.is_finite() && boundary > 0.0) {
            return Err(format!("{name} must be positive, got {boundary}"));
        }
        if final_sigma(boundary, &self.params) <= 0.0 {
            let (standoff, tolerance) = final_leg(boundary, &self.params);
            return Err(format!(
                "{name} {boundary} m is too tight: the final leg may end {:.2} m from the target, within the {} m the rover keeps clear of it (clearance_m)",
                standoff - tolerance,
                self.params.clearance_m
            ));
        }
        Ok(())
    }

    fn start(&mut self, ctx: &mut Ctx<'_>, kind: Kind, max_sigma: Option<f64>) -> Outcome {
        let max_sigma = max_sigma.unwrap_or(self.params.max_sigma_m);
        if !(max_sigma.is_finite() && max_sigma > 0.0) {
            return Outcome::reject(format!("max_sigma_m must be positive, got {max_sigma}"));
        }
        if !matches!(kind, Kind::PointLocate) && self.peers.navigator.is_none() {
            return Outcome::reject("no navigator in this system: cannot approach");
        }
        let Some(request) = ctx.request() else {
            return Outcome::reject(format!("{} must come as a command", kind.name()));
        };
        self.cancel(ctx, &format!("superseded by {}", kind.name()));
        self.pursuing = true;
        self.job = Some(Job {
            request,
            kind,
            step: Step::AwaitTarget(ctx.now()),
            max_sigma,
            legs: 0,
            face_retries: 0,
            refaced: 0,
            sharpened: 0,
            rejected: false,
        });
        Outcome::Accepted
    }

    /// Ends the job in progress, if any, with `reason`, stopping what it commanded.
    fn cancel(&mut self, ctx: &mut Ctx<'_>, reason: &str) {
        let Some(job) = self.job.take() else { return };
        match job.step {
            Step::Locate(..) => {
                let _ = ctx.send(Command::new(&self.peers.tracker, "stop"));
            }
            Step::Approach(..) => {
                if let Some(nav) = &self.peers.navigator {
                    let _ = ctx.send(Command::new(nav, "cancel"));
                }
            }
            Step::Face(_) | Step::Recover(_) => {
                let _ = ctx.send(Command::new(&self.peers.locomotion, "stop"));
            }
            Step::AwaitTarget(_) | Step::Reacquire(..) => {}
        }
        self.last = Some(format!("{}: {reason}", job.kind.name()));
        ctx.reply(&job.request, Outcome::fail(reason));
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        if self.pursuing {
            self.pursue(ctx);
        }
        if let Some(mut job) = self.job.take() {
            match self.advance(ctx, &mut job) {
                Ok(None) => self.job = Some(job),
                Ok(Some(outcome)) => {
                    self.last = Some(format!("{}: completed", job.kind.name()));
                    ctx.note(format!("{} completed after {} legs", job.kind.name(), job.legs));
                    ctx.reply(&job.request, outcome);
                }
                Err(reason) => {
                    self.last = Some(format!("{}: {reason}", job.kind.name()));
                    ctx.note(format!("{} failed: {reason}", job.kind.name()));
                    ctx.reply(&job.request, Outcome::fail(reason));
                }
            }
        }
        self.publish(ctx);
        Ok(())
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let distance = self.distance(ctx);
        let state = VisualTrackingState {
            command: self.job.as_ref().map(|j| j.kind.name().to_string()),
            step: self.job.as_ref().map_or("idle", |j| j.step.name()).to_string(),
            pursuing: self.pursuing,
            yielding: self.yielding,
            pan_tilt: self.commanded.map(|(q, _)| q),
            aim: self.aim,
            goal: self.job.as_ref().and_then(|j| match j.step {
                Step::Approach(_, g) => Some(g),
                _ => None,
            }),
            distance_m: distance,
            legs: self.job.as_ref().map_or(0, |j| j.legs),
            last_outcome: self.last.clone(),
        };
        if let Some(w) = &self.out {
            ctx.write(w, state);
        }
    }
}

fn dist(rover: [f64; 2], target: &Point3<f64>) -> f64 {
    (target.x - rover[0]).hypot(target.y - rover[1])
}

/// The target's uncertainty along the horizontal line from the rover to it (1 sigma, m).
fn sigma_along(rover: [f64; 2], target: &Point3<f64>, track: &TargetTrack) -> f64 {
    let u = nalgebra::Vector2::new(target.x - rover[0], target.y - rover[1]);
    let c = track.covariance.fixed_view::<2, 2>(0, 0);
    match u.try_normalize(1e-9) {
        Some(u) => (u.transpose() * c * u)[(0, 0)].max(0.0).sqrt(),
        // On top of it: the larger horizontal sigma.
        None => c.symmetric_eigenvalues().max().max(0.0).sqrt(),
    }
}

impl Module for CoordinatorVisualTracking {
    type Params = VisualTrackingParams;
    const KIND: ModuleKind = ModuleKind::Coordination;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.track = Some(d.reads(crate::tracking_target::SLOT));
        self.pose = Some(d.reads(&self.pose_slot));
        self.joints = Some(d.reads(&format!("{}/joints", self.peers.ptu)));
        if self.peers.navigator.is_some() {
            self.navigation = Some(d.reads("navigation/state"));
            self.map = Some(d.reads("navigation/map"));
        }
        self.out = Some(d.writes(SLOT));
        d.sends_to(&self.peers.tracker).sends_to(&self.peers.ptu).sends_to(&self.peers.locomotion);
        if let Some(nav) = &self.peers.navigator {
            d.sends_to(nav);
        }
        d.context_switchable();
        d.state("active", |m, ctx| m.cycle(ctx));
        d.command("point_locate", |m, ctx, a: PointLocateArgs| {
            m.start(ctx, Kind::PointLocate, a.max_sigma_m)
        });
        d.command("point_locate_approach", |m, ctx, a: ApproachArgs| {
            if let Err(e) = m.approachable("boundary_m", a.boundary_m) {
                return Outcome::reject(e);
            }
            m.start(ctx, Kind::Approach { boundary: a.boundary_m }, a.max_sigma_m)
        });
        d.command("point_locate_approach_track", |m, ctx, a: ApproachTrackArgs| {
            if let Err(e) = m.approachable("max_distance_m", a.max_distance_m) {
                return Outcome::reject(e);
            }
            m.start(ctx, Kind::Track { max_distance: a.max_distance_m }, a.max_sigma_m)
        });
        d.command("stop", |m, ctx, _: ()| {
            m.cancel(ctx, "stopped by command");
            m.pursuing = false;
            m.commanded = None;
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &VisualTrackingParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("command_period_s", p.command_period_s),
            ("deadband_rad", p.deadband_rad),
            ("ptu_speed", p.ptu_speed),
            ("sight_range_m", p.sight_range_m),
            ("max_sigma_m", p.max_sigma_m),
            ("leg_sigma_fraction", p.leg_sigma_fraction),
            ("max_leg_m", p.max_leg_m),
            ("leg_tolerance_m", p.leg_tolerance_m),
            ("max_legs", p.max_legs as f64),
            ("locate_timeout_s", p.locate_timeout_s),
            ("bearing_after_s", p.bearing_after_s),
            ("target_wait_s", p.target_wait_s),
        ])?;
        crate::params::require_non_negative(&[("reject_unseen_within_m", p.reject_unseen_within_m)])?;
        if p.ptu_speed > 1.0 {
            return Err(format!("ptu_speed must be in (0, 1], got {}", p.ptu_speed));
        }
        if p.bearing_after_s >= p.locate_timeout_s {
            return Err(format!(
                "bearing_after_s ({}) must be below locate_timeout_s ({}): legs along the line of sight would never start",
                p.bearing_after_s, p.locate_timeout_s
            ));
        }
        if !(p.leg_fraction > 0.0 && p.leg_fraction < 1.0) {
            return Err(format!("leg_fraction must be in (0, 1), got {}", p.leg_fraction));
        }
        // The final tolerance, 0.5 (1 - f) of the boundary, must not reach past the target (and
        // the stand-off keeps the rover clear of it).
        if !(p.standoff_fraction >= 0.5 && p.standoff_fraction < 1.0) {
            return Err(format!("standoff_fraction must be in [0.5, 1), got {}", p.standoff_fraction));
        }
        crate::params::require_positive(&[
            ("clearance_m", p.clearance_m),
            ("clearance_sigmas", p.clearance_sigmas),
        ])?;
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        if matches!(to, Lifecycle::Hold | Lifecycle::Safe | Lifecycle::Shutdown) {
            self.cancel(ctx, &format!("'{}' left Run for {to}", ctx.name()));
            self.pursuing = false;
            self.commanded = None;
        }
        Ok(())
    }
}
