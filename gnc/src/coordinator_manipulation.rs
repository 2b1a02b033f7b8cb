//! CoordinatorManipulation (seed 000, 8.3 and 8.4): sequences the rover, the wrist camera's marker
//! tracking and the manipulator for the mission's two manipulation commands.
//!
//! - `acquire_canister`: turns the wrist camera on; raises the arm to `travel_pose` (the wrist
//!   camera looking ahead); puts the rover where the arm can reach the object (from the head
//!   camera's target estimate, `tracking/target`: facing it at the working distance), going
//!   instead to where the wrist camera glimpses it on the way, if elsewhere; raises the arm to its
//!   look pose and has the wrist camera's TrackingMarker locate the object by its markers; if the located object is outside the arm's grasp region, moves the
//!   rover by what is missing and looks again. When no look pose saw anything of it, the object
//!   may lie beside or behind the rover (the head camera followed a rock beyond it): the wrist
//!   camera looks all round from `scan_pose` while the rover turns a full circle in place, and a
//!   glimpse is gone to; seen nowhere, it may lie nearer than the views reach: the rover backs up
//!   `search_back_m` once and looks again; seen from none then, where the head camera's estimate
//!   brought the rover, that estimate is of something else and TrackingTarget is told to `reject`
//!   it. Then the manipulator grasps it under visual servoing. A move of the rover that stalls a wheel is recovered from (locomotion's `recover`)
//!   and sent again, what is left of it (a turn to its heading, a drive its remaining distance),
//!   twice at most. A grasp that fails (the fingers closed beside the handle, the servo loop did not
//!   converge) is tried again from the look, up to `max_attempts`; one whose handle the arm cannot
//!   reach from where the rover stands first has the rover face the object and bring it
//!   `grasp_x_m` ahead (a reposition). Completes once the manipulator
//!   reports the object held (its fingers stopped on the handle), with the wrist camera off again.
//! - `stow_canister`: has the manipulator place the held object in the stowage slot.
//! - `stop`: ends the command in progress and stops what it commanded.
//!
//! Progress is published on `manipulation/coordinator` as the generic module state (the command and
//! its step) through the notes; the manipulator's own state is on `manipulation/state`.

use crate::locomotion::guard;
use crate::peer::send;
use framework::data::{ObjectPose, ObjectPoses, PoseEstimate, TargetTrack};
use framework::message::{AckStatus, MessageId};
use framework::module::Request;
use framework::prelude::*;
use nalgebra::{Isometry3, Point3};

mod moves;
mod params;
pub use moves::reposition;
use moves::{Move, REPOSITION_BEARING_DEG};
pub use params::CoordinatorManipulationParams;

/// Names of the modules the coordinator commands and the slots it reads.
#[derive(Clone, Debug)]
pub struct ManipulationPeers {
    /// ManipulatorControl.
    pub manipulator: String,
    /// The wrist camera's TrackingMarker.
    pub markers: String,
    /// The cameras module and the wrist camera's device name.
    pub cameras: (String, String),
    /// Locomotion.
    pub locomotion: String,
    /// The head camera's target track (where the object is, in `map`), if the system has one.
    pub target: Option<String>,
    /// The TrackingTarget module that publishes it: told (`reject`) when the wrist camera saw
    /// nothing of the object where its estimate put it.
    pub tracker: Option<String>,
    /// The pose estimate.
    pub pose: String,
    /// The wrist camera's object poses (a glimpse of the object the markers could not locate to
    /// the accuracy asked still says which way to turn).
    pub objects: String,
}

/// Longest back-up to search for an object no look pose saw, m (it is driven blind, open loop).
const MAX_SEARCH_BACK_M: f64 = 1.0;
/// Most moves towards the head camera's estimate before the look (a turn, a drive, a turn).
const MAX_PREPARE_MOVES: u32 = 3;
/// Moves of one job that may stall a wheel, each recovered from and tried again, before it fails.
const MAX_STALL_RECOVERIES: u32 = 2;
/// The turns of the look all round: quarter turns, a full circle.
const SCAN_TURNS: u32 = 4;

/// Which command a job carries out.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    Acquire,
    Stow,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Acquire => "acquire_canister",
            Kind::Stow => "stow_canister",
        }
    }
}

/// Where a job is: the command awaited and what it was for.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Step {
    CameraOn,
    /// The arm to the travel pose, before the rover's moves to the working distance.
    TravelPose,
    /// Turning or driving to the working distance from the target estimate.
    Prepare,
    Look,
    Locate,
    /// Driving to put the located object in the grasp region.
    Reposition,
    /// The arm to the scan pose, for the look all round.
    ScanPose,
    /// A quarter turn of the look all round.
    Scan,
    /// Clearing locomotion's fault after a wheel stalled in a move (the step it was made in):
    /// then what is left of the move is sent again.
    Recover {
        then: Moving,
    },
    Grasp,
    Place,
    CameraOff,
}

/// The step a move of the rover is made in, to go on with after a stall.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Moving {
    Prepare,
    Reposition,
    Scan,
}

impl Moving {
    fn step(self) -> Step {
        match self {
            Moving::Prepare => Step::Prepare,
            Moving::Reposition => Step::Reposition,
            Moving::Scan => Step::Scan,
        }
    }
}

/// A glimpse this far from the place the rover is driving to the working distance from is of
/// the object elsewhere: the rover goes there instead, m.
const GLIMPSE_ELSEWHERE_M: f64 = 0.5;

/// A glimpse while a look pose's locate runs, farther than this from `base_link`, lies beyond
/// every look pose's view (the farthest, `look`, sees 1.05-1.7 m ahead): the rover goes to it at
/// once rather than trying the other poses first, m.
const FAR_GLIMPSE_M: f64 = 2.0;

struct Job {
    request: Request,
    kind: Kind,
    step: Step,
    id: MessageId,
    attempts: u32,
    repositions: u32,
    /// A reposition (for a grasp out of reach, or towards a glimpse) is under way and has one more
    /// move to send when its first completes (a turn to face the object is followed by the drive
    /// to the grasp distance).
    reach_move_left: bool,
    /// Moves towards the head camera's estimate so far.
    prepares: u32,
    /// The look pose in use (index into `look_poses`).
    look: usize,
    /// The object's position in `map` from the last locate, for the turn after a reposition.
    object_map: Option<Point3<f64>>,
    /// Whether the rover has backed up to search for an object no look pose saw.
    searched_back: bool,
    /// Whether the wrist camera has looked all round (or is looking), and the rover's heading
    /// (`map`, rad) it began from.
    scan_from: Option<f64>,
    /// Quarter turns of the look all round sent.
    scan_turns: u32,
    /// The head camera's estimate (`map`) the rover was brought to the object by, if it was:
    /// where the wrist camera looked for the object.
    head_estimate: Option<Point3<f64>>,
    /// Whether the wrist camera has seen the object (located or glimpsed) in this job.
    seen: bool,
    /// The wrist camera's latest glimpse of the object in this job not yet moved towards (its
    /// pose not located to the accuracy asked), looked for every cycle: any image counts, of
    /// any look pose, and of the drives between them (from the travel pose, the wrist camera
    /// looks ahead).
    glimpse: Option<ObjectPose>,
    /// The capture time of the image the last glimpse was taken from (none: none yet): an image
    /// glimpses once.
    glimpse_stamp: Option<Time>,
    /// When the job began: images from before it are not of its object's search.
    started: Time,
    /// Locates that ran (and failed) in this round of look poses: none, and the arm never
    /// reached a look pose.
    round_locates: u32,
    /// Moves that stalled a wheel, each recovered from and tried again.
    stalls: u32,
    /// The last move of the rover, to send again (what is left of it) after a stall.
    last_move: Option<Move>,
    result: serde_json::Value,
    /// When the step awaited began.
    since: Time,
}

/// The CoordinatorManipulation module.
pub struct CoordinatorManipulation {
    peers: ManipulationPeers,
    target: Option<Reader<TargetTrack>>,
    pose: Option<Reader<PoseEstimate>>,
    objects: Option<Reader<ObjectPoses>>,
    params: CoordinatorManipulationParams,
    job: Option<Job>,
}

impl CoordinatorManipulation {
    /// A coordinator of `peers`.
    pub fn new(peers: ManipulationPeers) -> Self {
        CoordinatorManipulation {
            peers,
            target: None,
            pose: None,
            objects: None,
            params: Default::default(),
            job: None,
        }
    }

    fn pose(&self, ctx: &Ctx<'_>) -> Result<Isometry3<f64>, String> {
        self.pose
            .as_ref()
            .and_then(|r| ctx.read(r))
            .map(|p| p.value.pose)
            .ok_or_else(|| "no pose estimate".into())
    }

    fn camera(&self, ctx: &mut Ctx<'_>, hz: f64) -> Result<MessageId, String> {
        let (cameras, device) = &self.peers.cameras;
        send(ctx, cameras, "set_rate", serde_json::json!({ "device": device, "hz": hz }))
    }

    /// The arm to the look pose `job.look` (from the first after a move or a failed grasp).
    fn look(&self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<(), String> {
        let pose = self.params.look_poses.get(job.look).ok_or("no look pose left")?;
        job.id = send(ctx, &self.peers.manipulator, "move_named", serde_json::json!({ "pose": pose }))?;
        job.step = Step::Look;
        // A look ends a reposition for a grasp out of reach (also one cut short by a stall).
        job.reach_move_left = false;
        Ok(())
    }

    /// The rover to the working distance from the head camera's estimate of the object (when
    /// there is one), then the look.
    fn prepare(&self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<(), String> {
        let Some(object) = self.object_estimate(ctx, job) else { return self.look(ctx, job) };
        let p = &self.params;
        let (want, tol, bearing) = (p.work_distance_m, p.work_tolerance_m, p.max_bearing_deg.to_radians());
        if job.prepares < MAX_PREPARE_MOVES && self.move_towards(ctx, job, &object, want, tol, bearing)? {
            job.prepares += 1;
            job.step = Step::Prepare;
            return Ok(());
        }
        self.look(ctx, job)
    }

    /// The object's position the rover goes to look at it from: where the wrist camera saw it,
    /// else the head camera's estimate (read once per job, and kept in `head_estimate` as the
    /// estimate the rover came by).
    fn object_estimate(&self, ctx: &Ctx<'_>, job: &mut Job) -> Option<Point3<f64>> {
        if job.object_map.is_none() {
            let track = self.target.as_ref().and_then(|r| ctx.read(r)).map(|t| t.value.clone());
            job.object_map = track.and_then(|t| t.position_at(ctx.now()));
            job.head_estimate = job.object_map;
        }
        job.object_map
    }

    /// No look pose saw anything of the object: the wrist camera looks all round from the scan
    /// pose while the rover turns a full circle in place (once; a glimpse is gone to); seen
    /// nowhere, the rover backs up `search_back_m` (once) so that the views reach nearer, and
    /// looks again from the first pose; after that, the locate fails with `reason`. If the rover came by the head camera's estimate and the wrist camera
    /// never saw the object, what the head camera follows is not the object: its tracker is told
    /// (`reject`, with the estimate the rover came by), so that a retry after a new approach goes
    /// to where it looks for it again. A round in which the arm reached no look pose looked for
    /// nothing: the look fails, and nothing is rejected.
    fn search_back(&self, ctx: &mut Ctx<'_>, job: &mut Job, reason: &str) -> Result<(), String> {
        if job.round_locates == 0 {
            // The arm reached no look pose: nothing was looked for.
            return Err(format!("Look failed: {reason}"));
        }
        if job.scan_from.is_none() && !self.params.scan_pose.is_empty() {
            ctx.note(format!(
                "{}: not located and not seen from any look pose ({reason}): looking all round from '{}'",
                job.kind.name(),
                self.params.scan_pose
            ));
            job.scan_from = Some(self.pose(ctx)?.rotation.euler_angles().2);
            job.scan_turns = 0;
            job.glimpse = None;
            let args = serde_json::json!({ "pose": self.params.scan_pose });
            job.id = send(ctx, &self.peers.manipulator, "move_named", args)?;
            job.step = Step::ScanPose;
            return Ok(());
        }
        let back = self.params.search_back_m;
        if job.searched_back || back <= 0.0 {
            if let (Some(tracker), false, Some(place)) = (&self.peers.tracker, job.seen, job.head_estimate) {
                let position = [place.x, place.y, place.z];
                send(ctx, tracker, "reject", serde_json::json!({ "position": position }))?;
                return Err(format!(
                    "Locate failed: {reason}; nothing of the {} where the head camera's estimate put it: its tracker is told to reject that estimate",
                    self.params.object
                ));
            }
            return Err(format!("Locate failed: {reason}"));
        }
        job.searched_back = true;
        job.repositions += 1;
        ctx.note(format!(
            "{}: not located and not seen from any look pose ({reason}): backing up {back} m to look again",
            job.kind.name()
        ));
        self.drive_straight(ctx, job, -back)?;
        job.look = 0;
        job.step = Step::Reposition;
        Ok(())
    }

    /// The look all round goes on: after a quarter turn in which the wrist camera glimpsed the
    /// object, the rover goes to the working distance from where it was seen and looks from the
    /// look poses; else the next quarter turn; after a full circle seeing nothing, on with the
    /// search (`search_back`).
    fn scan(&self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<(), String> {
        if let Some(seen) = job.glimpse.take() {
            job.prepares = 0;
            job.look = 0;
            let at = Point3::from(seen.map_from_object.translation.vector);
            return self.go_to_glimpse(ctx, job, at, "looking all round");
        }
        let from = job.scan_from.ok_or("no scan under way")?;
        if job.scan_turns >= SCAN_TURNS {
            return self.search_back(ctx, job, "not seen all round either");
        }
        job.scan_turns += 1;
        let yaw = from + f64::from(job.scan_turns) * std::f64::consts::FRAC_PI_2;
        self.move_rover(ctx, job, Move::Turn { yaw })?;
        job.step = Step::Scan;
        Ok(())
    }

    /// The rover to the working distance from `at` (`map`), where the wrist camera glimpsed the
    /// object `when` (said in the note), and the look from there.
    fn go_to_glimpse(
        &self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        at: Point3<f64>,
        when: &str,
    ) -> Result<(), String> {
        ctx.note(format!(
            "{}: {when}, the wrist camera glimpsed the {} at ({:.2}, {:.2}): going there",
            job.kind.name(),
            self.params.object,
            at.x,
            at.y
        ));
        job.object_map = Some(at);
        job.glimpse = None;
        self.prepare(ctx, job)
    }

    fn advance(&mut self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<Option<serde_json::Value>, String> {
        // A glimpse in any image since the job began: of any look pose (the newest image alone,
        // at a round's end, may be of another pose that sees nothing), or of a drive (the object
        // passing through the wrist camera's view from the travel pose; sweep run 8 saw its
        // markers for 20 s driving to the working distance, then from no look pose).
        if let Some(o) = self.objects.as_ref().and_then(|o| ctx.read(o))
            && o.value.stamp >= job.started
            && job.glimpse_stamp != Some(o.value.stamp)
            && let Some(seen) = o.value.objects.iter().find(|x| x.object == self.params.object)
        {
            job.seen = true;
            job.glimpse = Some(seen.clone());
            job.glimpse_stamp = Some(o.value.stamp);
            // On the way to the working distance from the head camera's estimate (a prior metres
            // long after a reject: run 8 drove over the canister on its way), the object where the
            // wrist camera sees it is the one to go to.
            let at = Point3::from(seen.map_from_object.translation.vector);
            let elsewhere = job.object_map.is_none_or(|o| (o - at).xy().norm() > GLIMPSE_ELSEWHERE_M);
            if job.step == Step::Prepare && elsewhere {
                self.go_to_glimpse(ctx, job, at, "on the way to the working distance")?;
                return Ok(None);
            }
            // From a look pose, beyond where any look pose sees (sweep draw 69: 2.8 m ahead from
            // the first pose, gone to only after all six, 40 s later).
            if job.step == Step::Locate
                && seen.base_from_object.translation.vector.xy().norm() > FAR_GLIMPSE_M
            {
                let _ = ctx.send(Command::new(&self.peers.markers, "stop"));
                job.prepares = 0;
                job.look = 0;
                self.go_to_glimpse(ctx, job, at, "from a look pose, beyond every look pose's view")?;
                return Ok(None);
            }
        }
        let status = match ctx.ack_status(job.id) {
            Some(AckStatus::Completed(v)) => Ok(v),
            Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => Err(r),
            _ if job.step == Step::Locate
                && (ctx.now() - job.since).as_secs_f64() > self.params.locate_timeout_s =>
            {
                let _ = ctx.send(Command::new(&self.peers.markers, "stop"));
                Err(format!(
                    "not located to {} m within {} s",
                    self.params.locate_sigma_m, self.params.locate_timeout_s
                ))
            }
            _ if job.step == Step::Locate
                && self.params.glimpse_timeout_s > 0.0
                && (ctx.now() - job.since).as_secs_f64() > self.params.glimpse_timeout_s
                && job.glimpse_stamp.is_none_or(|s| s < job.since) =>
            {
                let _ = ctx.send(Command::new(&self.peers.markers, "stop"));
                Err(format!("nothing of it in view for {} s", self.params.glimpse_timeout_s))
            }
            _ => return Ok(None),
        };
        if job.step == Step::Locate && status.is_err() {
            job.round_locates += 1;
        }
        match (job.step, status) {
            // A head camera's estimate to drive to: the arm to its travel pose first.
            (Step::CameraOn, Ok(_))
                if !self.params.travel_pose.is_empty() && self.object_estimate(ctx, job).is_some() =>
            {
                let args = serde_json::json!({ "pose": self.params.travel_pose });
                job.id = send(ctx, &self.peers.manipulator, "move_named", args)?;
                job.step = Step::TravelPose;
            }
            (Step::TravelPose, Err(r)) => {
                ctx.note(format!(
                    "{}: the arm did not take the travel pose '{}' ({r}): moving with it where it is",
                    job.kind.name(),
                    self.params.travel_pose
                ));
                self.prepare(ctx, job)?;
            }
            (Step::CameraOn | Step::TravelPose | Step::Prepare, Ok(_)) => self.prepare(ctx, job)?,
            (Step::ScanPose | Step::Scan, Ok(_)) => self.scan(ctx, job)?,
            (Step::Look, Ok(_)) => {
                let args = serde_json::json!({
                    "object": self.params.object,
                    "max_sigma_m": self.params.locate_sigma_m,
                    "max_angle_deg": self.params.locate_angle_deg,
                });
                job.id = send(ctx, &self.peers.markers, "locate", args)?;
                job.step = Step::Locate;
                job.since = ctx.now();
                if job.look == 0 {
                    // A new round of look poses.
                    job.round_locates = 0;
                }
            }
            (Step::Locate, Ok(v)) => {
                job.seen = true;
                let xyz: [f64; 3] = serde_json::from_value(v["base_from_object"]["xyz"].clone())
                    .map_err(|e| format!("locate's result has no base_from_object: {e}"))?;
                let object = Point3::from(xyz);
                let pose = self.pose(ctx)?;
                job.object_map = Some(pose * object);
                match reposition(&object, &self.params) {
                    None => {
                        job.attempts += 1;
                        job.id = send(
                            ctx,
                            &self.peers.manipulator,
                            "grasp",
                            serde_json::json!({ "object": self.params.object }),
                        )?;
                        job.step = Step::Grasp;
                    }
                    Some(_) if job.repositions >= self.params.max_repositions => {
                        return Err(format!(
                            "the {} is still out of the arm's reach at ({:.2}, {:.2}) after {} moves",
                            self.params.object, object.x, object.y, job.repositions
                        ));
                    }
                    Some(_) => {
                        job.repositions += 1;
                        ctx.note(format!(
                            "{}: the {} at ({:.2}, {:.2}) in base_link is out of the grasp region: moving the rover",
                            job.kind.name(),
                            self.params.object,
                            object.x,
                            object.y,
                        ));
                        let target = job.object_map.ok_or("no object position")?;
                        let x = self.params.grasp_x_m;
                        // Facing it within a few degrees, then to the grasp distance.
                        self.move_towards(ctx, job, &target, x, 0.0, REPOSITION_BEARING_DEG.to_radians())?;
                        job.step = Step::Reposition;
                    }
                }
            }
            (Step::Reposition, Ok(_)) => {
                if let (true, Some(target)) = (job.reach_move_left, job.object_map) {
                    job.reach_move_left = false;
                    if self.move_within_reach(ctx, job, &target)? {
                        return Ok(None);
                    }
                }
                job.look = 0;
                self.look(ctx, job)?;
            }
            // A move locomotion's obstacle guard refused or stopped (the rover's corners would
            // sweep the object, or a rock beside it): on with the look from where the rover is.
            (Step::Prepare | Step::Reposition, Err(r)) if guard::is_guard_reason(&r) => {
                ctx.note(format!(
                    "{}: the rover's move was not made ({r}): looking from here",
                    job.kind.name()
                ));
                job.reach_move_left = false;
                job.look = 0;
                self.look(ctx, job)?;
            }
            // A move that stalled a wheel (a skid turn on a slope, a rock beside a wheel) leaves
            // locomotion in fault: cleared, the rover's move is tried again from where it is.
            (step @ (Step::Prepare | Step::Reposition | Step::Scan), Err(r))
                if r.contains("stalled") && job.stalls < MAX_STALL_RECOVERIES =>
            {
                job.stalls += 1;
                ctx.note(format!("{}: the move stalled ({r}): recovering and trying again", job.kind.name()));
                job.id = send(ctx, &self.peers.locomotion, "recover", serde_json::Value::Null)?;
                let then = match step {
                    Step::Prepare => Moving::Prepare,
                    Step::Scan => Moving::Scan,
                    _ => Moving::Reposition,
                };
                job.step = Step::Recover { then };
            }
            // Locomotion out of fault (`recover` completes when it was not in fault too): what is
            // left of the move, from where the rover is (a drive is open loop, its way made good
            // taken from the pose estimate), or on as if it had completed when nothing is.
            (Step::Recover { then }, Ok(_)) => {
                let pose = self.pose(ctx)?;
                let rest = job.last_move.and_then(|m| m.rest([pose.translation.x, pose.translation.y]));
                match (rest, then) {
                    (Some(m), _) => {
                        self.move_rover(ctx, job, m)?;
                        job.step = then.step();
                    }
                    (None, Moving::Prepare) => self.prepare(ctx, job)?,
                    (None, Moving::Scan) => self.scan(ctx, job)?,
                    (None, Moving::Reposition) => {
                        job.look = 0;
                        self.look(ctx, job)?;
                    }
                }
            }
            (Step::Recover { .. }, Err(r)) => return Err(format!("cannot clear locomotion's fault: {r}")),
            // The look all round cut short (the arm refused the scan pose, a turn refused or
            // stalled past the recoveries): the search goes on without it (the back-up, then
            // the reject), rather than the job failing with the head camera's estimate kept.
            (Step::ScanPose | Step::Scan, Err(r)) => {
                ctx.note(format!(
                    "{}: the look all round failed ({r}): searching on without it",
                    job.kind.name()
                ));
                job.glimpse = None;
                self.search_back(ctx, job, &r)?;
            }
            (Step::Grasp, Ok(v)) => {
                if v["holding"].as_str() != Some(self.params.object.as_str()) {
                    return Err(format!("the grasp completed without holding the {}", self.params.object));
                }
                job.result = v;
                job.id = self.camera(ctx, 0.0)?;
                job.step = Step::CameraOff;
            }
            (Step::Look | Step::Locate, Err(r)) if job.look + 1 < self.params.look_poses.len() => {
                job.look += 1;
                ctx.note(format!(
                    "{}: not located from the look pose ({r}): from '{}'",
                    job.kind.name(),
                    self.params.look_poses[job.look]
                ));
                self.look(ctx, job)?;
            }
            (Step::Look | Step::Locate, Err(r)) if job.repositions < self.params.max_repositions => {
                // Not located from any look pose (the last one perhaps not reached: a motion the
                // arm refuses): if the wrist camera glimpsed the object since the locate began,
                // turn and drive towards it and look again. Both moves: a glimpse off the heading
                // is turned to and then driven to (a turn alone left a glimpse 3 m away as far out
                // of the look poses' view as before: sweep draws 61 and 69, session 48).
                let Some(seen) = job.glimpse.take() else {
                    return self.search_back(ctx, job, &r).map(|()| None);
                };
                job.repositions += 1;
                let target = Point3::from(seen.map_from_object.translation.vector);
                job.object_map = Some(target);
                ctx.note(format!(
                    "{}: not located ({r}), but glimpsed at ({:.2}, {:.2}) in base_link: moving towards it",
                    job.kind.name(),
                    seen.base_from_object.translation.x,
                    seen.base_from_object.translation.y
                ));
                let x = self.params.grasp_x_m;
                job.look = 0;
                if self.move_towards(ctx, job, &target, x, 0.1, REPOSITION_BEARING_DEG.to_radians())? {
                    job.reach_move_left = matches!(job.last_move, Some(Move::Turn { .. }));
                    job.step = Step::Reposition;
                } else {
                    self.look(ctx, job)?;
                }
            }
            (Step::Grasp, Err(r)) if job.attempts < self.params.max_attempts => {
                job.look = 0;
                // A handle the arm cannot reach from where the rover stands (inside the grasp
                // region by the locate, yet no grasp of it is reachable: its turn, the ground)
                // stays so however often it is looked at: the rover first turns to face the
                // object and drives to have it `grasp_x_m` straight ahead (the moves that are
                // needed; one reposition). Only the approach's failure, before the arm left the
                // look pose (ManipulatorControl's "no grasp of ..."): a later step that cannot
                // reach (a servo step, the descent, the lift) leaves the arm low or holding.
                if let (true, true, Some(target)) = (
                    r.starts_with("no grasp of") && r.contains("cannot reach"),
                    job.repositions < self.params.max_repositions,
                    job.object_map,
                ) && self.move_within_reach(ctx, job, &target)?
                {
                    job.repositions += 1;
                    job.reach_move_left = true;
                    ctx.note(format!(
                        "{}: grasp {} failed ({r}): moving the rover to have the {} {:.2} m straight ahead",
                        job.kind.name(),
                        job.attempts,
                        self.params.object,
                        self.params.grasp_x_m
                    ));
                    job.step = Step::Reposition;
                    return Ok(None);
                }
                ctx.note(format!("{}: grasp {} failed ({r}): looking again", job.kind.name(), job.attempts));
                self.look(ctx, job)?;
            }
            (Step::CameraOff, Ok(_)) | (Step::Place, Ok(_)) => {
                if job.kind == Kind::Stow {
                    return Ok(Some(serde_json::json!({ "stowed": self.params.object })));
                }
                let mut result = job.result.clone();
                result["attempts"] = job.attempts.into();
                result["repositions"] = job.repositions.into();
                return Ok(Some(result));
            }
            (step, Err(r)) => return Err(format!("{step:?} failed: {r}")),
        }
        Ok(None)
    }

    fn start(&mut self, ctx: &mut Ctx<'_>, kind: Kind) -> Outcome {
        let Some(request) = ctx.request() else {
            return Outcome::reject(format!("{} must come as a command", kind.name()));
        };
        self.cancel(ctx, &format!("superseded by {}", kind.name()));
        let first = match kind {
            Kind::Acquire => self.camera(ctx, self.params.camera_hz).map(|id| (id, Step::CameraOn)),
            Kind::Stow => {
                send(ctx, &self.peers.manipulator, "place", serde_json::json!({})).map(|id| (id, Step::Place))
            }
        };
        match first {
            Ok((id, step)) => {
                self.job = Some(Job {
                    request,
                    kind,
                    step,
                    id,
                    attempts: 0,
                    repositions: 0,
                    reach_move_left: false,
                    prepares: 0,
                    look: 0,
                    object_map: None,
                    searched_back: false,
                    scan_from: None,
                    scan_turns: 0,
                    head_estimate: None,
                    seen: false,
                    glimpse: None,
                    glimpse_stamp: None,
                    started: ctx.now(),
                    round_locates: 0,
                    stalls: 0,
                    last_move: None,
                    result: serde_json::Value::Null,
                    since: ctx.now(),
                });
                Outcome::Accepted
            }
            Err(e) => Outcome::reject(e),
        }
    }

    fn cancel(&mut self, ctx: &mut Ctx<'_>, reason: &str) {
        let Some(job) = self.job.take() else { return };
        if job.kind == Kind::Acquire {
            let _ = self.camera(ctx, 0.0);
        }
        let to = match job.step {
            Step::Prepare | Step::Reposition | Step::Scan | Step::Recover { .. } => {
                Some(&self.peers.locomotion)
            }
            Step::TravelPose | Step::Look | Step::ScanPose | Step::Grasp | Step::Place => {
                Some(&self.peers.manipulator)
            }
            Step::Locate => Some(&self.peers.markers),
            Step::CameraOn | Step::CameraOff => None,
        };
        if let Some(to) = to {
            let _ = ctx.send(Command::new(to, "stop"));
        }
        ctx.reply(&job.request, Outcome::fail(reason));
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        if let Some(mut job) = self.job.take() {
            match self.advance(ctx, &mut job) {
                Ok(None) => self.job = Some(job),
                Ok(Some(result)) => {
                    ctx.note(format!("{} completed: {result}", job.kind.name()));
                    ctx.reply(&job.request, Outcome::Completed(result));
                }
                Err(reason) => {
                    ctx.note(format!("{} failed: {reason}", job.kind.name()));
                    if job.kind == Kind::Acquire {
                        let _ = self.camera(ctx, 0.0);
                    }
                    ctx.reply(&job.request, Outcome::fail(reason));
                }
            }
        }
        Ok(())
    }
}

impl Module for CoordinatorManipulation {
    type Params = CoordinatorManipulationParams;
    const KIND: ModuleKind = ModuleKind::Coordination;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        if let Some(t) = &self.peers.target {
            self.target = Some(d.reads(t));
        }
        self.pose = Some(d.reads(&self.peers.pose));
        self.objects = Some(d.reads(&self.peers.objects));
        d.sends_to(&self.peers.manipulator)
            .sends_to(&self.peers.markers)
            .sends_to(&self.peers.cameras.0)
            .sends_to(&self.peers.locomotion);
        if let Some(tracker) = &self.peers.tracker {
            d.sends_to(tracker);
        }
        d.context_switchable();
        d.state("active", |m, ctx| m.cycle(ctx));
        d.command("acquire_canister", |m, ctx, _: ()| m.start(ctx, Kind::Acquire));
        d.command("stow_canister", |m, ctx, _: ()| m.start(ctx, Kind::Stow));
        d.command("stop", |m, ctx, _: ()| {
            m.cancel(ctx, "stopped by command");
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &CoordinatorManipulationParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("camera_hz", p.camera_hz),
            ("work_distance_m", p.work_distance_m),
            ("work_tolerance_m", p.work_tolerance_m),
            ("max_bearing_deg", p.max_bearing_deg),
            ("grasp_x_m", p.grasp_x_m),
            ("locate_sigma_m", p.locate_sigma_m),
            ("locate_angle_deg", p.locate_angle_deg),
            ("locate_timeout_s", p.locate_timeout_s),
            ("max_attempts", p.max_attempts as f64),
        ])?;
        if p.glimpse_timeout_s.is_nan() || p.glimpse_timeout_s < 0.0 {
            return Err(format!("glimpse_timeout_s {} must be 0 or more", p.glimpse_timeout_s));
        }
        if !(0.0..=MAX_SEARCH_BACK_M).contains(&p.search_back_m) {
            return Err(format!(
                "search_back_m {} must be between 0 and {MAX_SEARCH_BACK_M} m (the back-up is driven blind)",
                p.search_back_m
            ));
        }
        if p.look_poses.is_empty() {
            return Err("look_poses must name at least one pose".into());
        }
        let [lo, hi, y] = p.grasp_region_m;
        if !(lo < p.grasp_x_m && p.grasp_x_m < hi && y > 0.0) {
            return Err(format!(
                "grasp_x_m {} must lie inside grasp_region_m {:?}",
                p.grasp_x_m, p.grasp_region_m
            ));
        }
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

#[cfg(test)]
mod tests;
