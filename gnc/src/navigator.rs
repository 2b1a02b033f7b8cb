//! CoordinatorNavigator (seed 000, 7 and 8.2): takes the rover to a goal over unknown terrain.
//!
//! - `navigate_to {x, y, tolerance_m?}` (`map` frame): completes on arrival within the tolerance,
//!   with the distance left and the plans made; fails with the reason once more consecutive
//!   attempts failed (no path, a failed scan, a failed drive) than `max_failures` (a drive refused
//!   for a fault an earlier navigation left is not one: the fault is cleared, the rover backs off);
//! - `cancel` (or `stop`): stops the rover and fails the navigation in progress.
//!
//! Its `navigating` state is a meta-state, switched at runtime with `set_meta`:
//! - `stop_and_go`: stop, scan with the pan-tilt unit (PerceptionDataFusion `scan`), wait for the
//!   navigation map, plan (PathPlanning `plan`), drive at most `segment_m` of the path (Locomotion
//!   `follow_path`), and again until arrival;
//! - `continuous`: one scan to start with, then map and replan while driving: every new path the
//!   planner publishes (it replans on each new navigation map) replaces the one being followed;
//!   when a replan finds no path the rover stops, scans and plans again.
//!
//! A drive that fails on a stalled wheel clears locomotion's fault and backs off `back_off_m` (not
//! after a stall while reversing) before scanning again; after a front wheel's stall while driving
//! forward (not in a skid turn in place, which stalls on slopes with nothing in the way) the
//! planner is asked to keep the rover out of the spot ahead (`stall_keep_out_m` around the point
//! `stall_ahead_m` ahead: something there the map does not show; the rover's centre where it
//! stalled on the disc's edge, outside once backed off), so the next plan goes round it instead of
//! into it again. So too after any wheel's second stall
//! driving forward at the same spot (within `SAME_STALL_SPOT_M`): a rear wheel that swings into a
//! rock on a turn stalls there each time the same path is driven. After a stall while turning in
//! place, the turns in place near that spot go the other way round (Locomotion's `pivot`): on a
//! slope, the wheel that stalls is the most loaded one rolling uphill, and the same turn tried again
//! stalls again (the main job's return once did, five times over); the other way round it rolls
//! downhill. (The long way round if need be: the paths sent from within `SAME_STALL_SPOT_M` of
//! the spot have their first turn in place, if over Locomotion's `turn_in_place_deg`, made that
//! way; a later one of the same path goes the shorter way.) A stall where the rover has stalled
//! before on this navigation (within `SAME_STALL_SPOT_M`, whatever it was doing), a back-off's
//! own included, is escaped from instead: a straight drive of `escape_m` along the heading, back or
//! forward but not in a direction (on the map, within 60 degrees) that stalled there, clear on the
//! navigation map, to the cheaper ground of the two (`navigator::escape`); with no such way the
//! fault is cleared and the planner asked from where the rover stands. The short back-off had
//! left the rover where the same wheel stalled again, turning either way round on a slope or
//! against a rock the map does not show, until the navigation gave up (four runs of the canister
//! sweep). After a stall driving forward, the rest of the navigation's paths are followed with
//! arcs no tighter than `stall_max_curvature` (Locomotion's `max_curvature`), sharper bends turned
//! in place: on a slope at high friction the skid-steer rover cannot skid round an arc uphill (the
//! loaded outer rear wheel stalls), and the same arc driven again stalls again (a sweep's mission
//! stalled five times over at one bend of its route). Progress is published on `navigation/state`.

use crate::locomotion::{Motion, Sense, guard};
use crate::peer::send;
use escape::Way;
use framework::data::{NavigationMap, NavigationState, Path, PoseEstimate};
use framework::message::{AckStatus, MessageId};
use framework::module::Request;
use framework::prelude::*;
use serde::{Deserialize, Serialize};

/// Navigator parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NavigatorParams {
    /// Length of path driven between stops in stop-and-go, m.
    pub segment_m: f64,
    /// Default arrival tolerance, m.
    pub tolerance_m: f64,
    /// Cruise speed, m/s.
    pub speed: f64,
    /// Consecutive failures tolerated before `navigate_to` fails.
    pub max_failures: u32,
    /// After a stall, the rover backs off this far before scanning again, m.
    pub back_off_m: f64,
    /// After a front wheel's stall driving forward (or any wheel's second one at the same spot),
    /// the planner keeps the rover's centre this far from the spot `stall_ahead_m` ahead of where
    /// it stalled (something there the map does not show), m (0: not). At most `stall_ahead_m`, or
    /// the rover would stand in it.
    pub stall_keep_out_m: f64,
    /// See `stall_keep_out_m`, m.
    pub stall_ahead_m: f64,
    /// Longest wait for a fresh navigation map after a scan, s.
    pub map_wait_s: f64,
    /// A stall where the rover stalled before on this navigation is escaped from by a straight
    /// drive this long, back or forward, m (0: backs off `back_off_m` as after a first stall).
    pub escape_m: f64,
    /// After a wheel stalled driving forward on a navigation, the rest of it is driven with arcs
    /// no tighter than this (Locomotion's `max_curvature` for its paths), 1/m: sharper bends are
    /// turned in place (0: arcs as configured in Locomotion). On a slope at high friction, the
    /// skid-steer rover cannot skid round an arc uphill: the loaded outer rear wheel stalls at its
    /// torque limit (a 4 m radius already does not turn it there), while a turn in place does.
    pub stall_max_curvature: f64,
}

impl Default for NavigatorParams {
    fn default() -> Self {
        NavigatorParams {
            segment_m: 2.5,
            tolerance_m: 0.3,
            speed: 0.25,
            max_failures: 4,
            back_off_m: 0.3,
            stall_keep_out_m: 0.5,
            stall_ahead_m: 0.5,
            map_wait_s: 3.0,
            escape_m: 1.0,
            stall_max_curvature: 0.5,
        }
    }
}

/// Arguments of `navigate_to`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavigateArgs {
    /// Goal x, m (`map`).
    pub x: f64,
    /// Goal y, m.
    pub y: f64,
    /// Arrival tolerance, m (default: configured).
    #[serde(default)]
    pub tolerance_m: Option<f64>,
}

/// The tightest tolerance locomotion is asked to stop within at a path's end, m.
const MIN_FOLLOW_TOLERANCE_M: f64 = 0.1;

/// A stall within this of an earlier one on the same navigation is at the same spot again, m.
const SAME_STALL_SPOT_M: f64 = 1.0;

/// A drive that ends less than this nearer the goal than it started made no progress, m.
const MIN_PROGRESS_M: f64 = 0.05;

/// Where a navigation is.
#[derive(Clone, Debug)]
enum Phase {
    Scan(Option<MessageId>),
    /// Waiting since `since` for a navigation map holding what was seen at `after`.
    AwaitMap {
        since: Time,
        after: Time,
    },
    Plan(Option<MessageId>),
    /// Following a path; the distance to the goal when it started.
    Drive {
        id: MessageId,
        path_seq: u64,
        from: f64,
    },
    /// After a stall: clear locomotion's fault, then move away as the retreat says, then scan.
    Recover(Option<MessageId>, Retreat),
    Retreat(MessageId, Retreat),
}

/// How the rover moves away from where a wheel stalled, before it scans again.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Retreat {
    /// Backs off `back_off_m`.
    BackOff,
    /// Drives `escape_m` straight, this way (where it stalled before).
    Escape(Way),
    /// Stays (backing off just stalled, or no way out is clear on the map and not stalled).
    Stay,
}

impl Phase {
    fn name(&self) -> &'static str {
        match self {
            Phase::Scan(_) => "scan",
            Phase::AwaitMap { .. } => "await_map",
            Phase::Plan(_) => "plan",
            Phase::Drive { .. } => "drive",
            Phase::Recover(..) | Phase::Retreat(..) => "recover",
        }
    }
}

/// A navigation in progress.
struct Goal {
    request: Request,
    at: [f64; 2],
    tolerance: f64,
    phase: Phase,
    plans: u32,
    failures: u32,
    /// Where the rover stood (`map`) when a wheel last stalled driving forward on this navigation.
    last_stall: Option<[f64; 2]>,
    /// After a stall turning in place: the way round turns in place go near where it stalled.
    pivot: Option<(Sense, [f64; 2])>,
    /// Where the rover stood (`map`) at each stall of this navigation, and the direction it was
    /// driving in (`map`, rad; None: turning in place).
    stall_spots: Vec<([f64; 2], Option<f64>)>,
    /// A wheel stalled driving forward on this navigation: its paths are followed with arcs no
    /// tighter than `stall_max_curvature`.
    arcs_limited: bool,
}

/// Names of the modules the navigator commands.
#[derive(Clone, Debug)]
pub struct NavigatorPeers {
    /// PerceptionDataFusion (scans).
    pub fusion: String,
    /// PathPlanning.
    pub planner: String,
    /// Locomotion.
    pub locomotion: String,
}

/// The CoordinatorNavigator module.
pub struct CoordinatorNavigator {
    peers: NavigatorPeers,
    pose_slot: String,
    pose: Option<Reader<PoseEstimate>>,
    map: Option<Reader<NavigationMap>>,
    path: Option<Reader<Path>>,
    out: Option<Writer<NavigationState>>,
    goal: Option<Goal>,
    mode: &'static str,
    params: NavigatorParams,
}

/// What a step of the navigation asks for.
enum Next {
    Stay,
    To(Phase),
    /// A failed attempt (counted), then this phase instead of a fresh scan.
    FailThen(String, Phase),
    Fail(String),
    Arrived(f64),
}

impl CoordinatorNavigator {
    /// A navigator commanding `peers`, with the rover's pose from `pose_slot`.
    pub fn new(peers: NavigatorPeers, pose_slot: &str) -> Self {
        CoordinatorNavigator {
            peers,
            pose_slot: pose_slot.to_string(),
            pose: None,
            map: None,
            path: None,
            out: None,
            goal: None,
            mode: "stop_and_go",
            params: NavigatorParams::default(),
        }
    }

    fn position(&self, ctx: &Ctx<'_>) -> Option<[f64; 2]> {
        self.pose.as_ref().and_then(|r| ctx.read(r)).map(|p| {
            let c = p.value.position();
            [c.x, c.y]
        })
    }

    /// Asks the planner to keep out of the spot ahead of the rover (where a wheel stalled on
    /// something the map does not show), so that the next plan goes round it.
    fn keep_out_ahead(&self, ctx: &mut Ctx<'_>) {
        let p = &self.params;
        let Some(pose) = self.pose.as_ref().and_then(|r| ctx.read(r)) else { return };
        if p.stall_keep_out_m <= 0.0 {
            return;
        }
        let c = pose.value.position();
        let (_, _, yaw) = pose.value.pose.rotation.euler_angles();
        let (x, y) = (c.x + p.stall_ahead_m * yaw.cos(), c.y + p.stall_ahead_m * yaw.sin());
        let args = serde_json::json!({ "x": x, "y": y, "radius_m": p.stall_keep_out_m });
        if let Err(e) = send(ctx, &self.peers.planner, "avoid", args) {
            ctx.note(format!("the stall's spot is not kept out: {e}"));
        }
    }

    /// How to move away from where a wheel just stalled (`stalled`: the way the rover was driving,
    /// None turning in place), noting the spot: back off, or, where it stalled before on this
    /// navigation, escape along a way clear on the map but those that stalled there (forward, the
    /// stall's keep-out lies ahead too).
    fn retreat_after_stall(&mut self, ctx: &mut Ctx<'_>, stalled: Option<Way>) -> Retreat {
        let fallback = if stalled == Some(Way::Back) { Retreat::Stay } else { Retreat::BackOff };
        let Some(pose) = self.pose.as_ref().and_then(|r| ctx.read(r)) else { return fallback };
        let c = pose.value.position();
        let here = [c.x, c.y];
        let (_, _, yaw) = pose.value.pose.rotation.euler_angles();
        let Some(g) = self.goal.as_mut() else { return fallback };
        g.stall_spots.push((here, stalled.map(|w| w.direction(yaw))));
        let near: Vec<_> = g
            .stall_spots
            .iter()
            .filter(|(s, _)| (here[0] - s[0]).hypot(here[1] - s[1]) <= SAME_STALL_SPOT_M)
            .collect();
        let again = near.len() > 1;
        let stalled_here: Vec<f64> = near.iter().filter_map(|(_, d)| *d).collect();
        let length = self.params.escape_m;
        if !again || length <= 0.0 {
            return fallback;
        }
        let Some(map) = self.map.as_ref().and_then(|r| ctx.read(r)) else { return fallback };
        match escape::ways_out(&map.value, here, yaw, length, &stalled_here).first() {
            Some(&way) => {
                ctx.note(format!("stalled here before: escaping {} {length:.1} m", way.describe()));
                Retreat::Escape(way)
            }
            None => {
                ctx.note(format!(
                    "stalled here before, and no way {length:.1} m back or forward is clear, or not stalled: planning from here"
                ));
                Retreat::Stay
            }
        }
    }

    /// After a wheel stalled driving forward: the rest of this navigation turns in place where
    /// its paths bend more sharply than `stall_max_curvature` (if set).
    fn limit_arcs(&mut self, ctx: &mut Ctx<'_>) {
        let k = self.params.stall_max_curvature;
        let Some(g) = self.goal.as_mut() else { return };
        if k <= 0.0 || g.arcs_limited {
            return;
        }
        g.arcs_limited = true;
        ctx.note(format!(
            "a wheel stalled driving forward: the rest of this navigation turns in place rather than drive arcs under {:.1} m radius",
            1.0 / k
        ));
    }

    fn distance_to_goal(&self, ctx: &Ctx<'_>) -> Option<f64> {
        let g = self.goal.as_ref()?;
        self.position(ctx).map(|p| (g.at[0] - p[0]).hypot(g.at[1] - p[1]))
    }

    /// The way round the rover turns in place where it is: the other way than a turn that stalled
    /// near here (none: the shorter way).
    fn pivot_here(&self, ctx: &Ctx<'_>) -> Option<Sense> {
        let (sense, spot) = self.goal.as_ref()?.pivot?;
        let here = self.position(ctx)?;
        ((here[0] - spot[0]).hypot(here[1] - spot[1]) <= SAME_STALL_SPOT_M).then_some(sense)
    }

    /// The path to send to locomotion: the whole path, or (stop-and-go) its first `segment_m`;
    /// turns in place only the way `pivot` says, if it says.
    fn path_args(&self, path: &Path, whole: bool, pivot: Option<Sense>) -> serde_json::Value {
        let mut points = vec![path.points[0]];
        let mut clearance = vec![path.clearance_m[0]];
        let mut left = if whole { f64::INFINITY } else { self.params.segment_m };
        for k in 1..path.points.len() {
            let (a, b) = (path.points[k - 1], path.points[k]);
            let d = (b[0] - a[0]).hypot(b[1] - a[1]);
            if d >= left {
                let f = left / d;
                points.push([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])]);
                let (ca, cb) = (path.clearance_m[k - 1], path.clearance_m[k]);
                clearance.push(ca + f * (cb - ca));
                break;
            }
            left -= d;
            points.push(b);
            clearance.push(path.clearance_m[k]);
        }
        // Stop near enough the path's end that the goal's tolerance holds: the path may end short
        // of the goal (when the goal lies in an obstacle) by up to that tolerance. (Asking for
        // more than the goal's tolerance only has the rover creep and circle round the end.)
        let (tol, at) =
            self.goal.as_ref().map(|g| (g.tolerance, g.at)).unwrap_or((self.params.tolerance_m, [0.0; 2]));
        let path_end = *path.points.last().expect("a path has points");
        let follow_tol = if points.last() == Some(&path_end) {
            let short = (path_end[0] - at[0]).hypot(path_end[1] - at[1]);
            (tol - short).max(MIN_FOLLOW_TOLERANCE_M)
        } else {
            // A stop-and-go segment ends anywhere on the path.
            self.params.tolerance_m
        };
        let mut args = serde_json::json!({
            "points": points, "clearance_m": clearance, "speed": self.params.speed,
            "tolerance_m": follow_tol,
        });
        if let Some(sense) = pivot {
            args["pivot"] = serde_json::json!(sense);
        }
        if self.goal.as_ref().is_some_and(|g| g.arcs_limited) {
            args["max_curvature"] = serde_json::json!(self.params.stall_max_curvature);
        }
        args
    }

    /// One step of the navigation in progress, in mode `continuous` or stop-and-go.
    fn step(&mut self, ctx: &mut Ctx<'_>, continuous: bool) -> Next {
        let now = ctx.now();
        let peers = self.peers.clone();
        let map_stamp = self.map.as_ref().and_then(|r| ctx.read(r)).map(|m| m.stamp);
        let Some(g) = self.goal.as_ref() else { return Next::Stay };
        let (at, tol) = (g.at, g.tolerance);
        match g.phase.clone() {
            Phase::Scan(None) => match send(ctx, &peers.fusion, "scan", serde_json::json!({})) {
                Ok(id) => Next::To(Phase::Scan(Some(id))),
                Err(e) => Next::Fail(e),
            },
            Phase::Scan(Some(id)) => match ctx.ack_status(id) {
                Some(AckStatus::Completed(detail)) => {
                    // The navigation map to plan on holds the scan's last local map.
                    let after = detail
                        .get("last_map_stamp_ns")
                        .and_then(|v| v.as_i64())
                        .map(|ns| Time::from_secs_f64(ns as f64 * 1e-9))
                        .unwrap_or(now);
                    Next::To(Phase::AwaitMap { since: now, after })
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    Next::Fail(format!("scan failed: {r}"))
                }
                _ => Next::Stay,
            },
            Phase::AwaitMap { since, after } => {
                let fresh = map_stamp.is_some_and(|t| t >= after);
                if fresh || (map_stamp.is_some() && (now - since).as_secs_f64() >= self.params.map_wait_s) {
                    Next::To(Phase::Plan(None))
                } else if (now - since).as_secs_f64() >= 3.0 * self.params.map_wait_s {
                    Next::Fail("no navigation map after the scan".into())
                } else {
                    Next::Stay
                }
            }
            Phase::Plan(None) => {
                let args = serde_json::json!({ "x": at[0], "y": at[1], "tolerance_m": tol });
                match send(ctx, &peers.planner, "plan", args) {
                    Ok(id) => Next::To(Phase::Plan(Some(id))),
                    Err(e) => Next::Fail(e),
                }
            }
            Phase::Plan(Some(id)) => match ctx.ack_status(id) {
                Some(AckStatus::Completed(_)) => {
                    let Some(path) = self.path.as_ref().and_then(|r| ctx.read(r)) else {
                        return Next::Fail("the planner published no path".into());
                    };
                    if path.value.points.is_empty() {
                        return Next::Fail("the planner published an empty path".into());
                    }
                    if let Some(g) = self.goal.as_mut() {
                        g.plans += 1;
                    }
                    let args = self.path_args(&path.value, continuous, self.pivot_here(ctx));
                    let from = self.distance_to_goal(ctx).unwrap_or(f64::INFINITY);
                    match send(ctx, &peers.locomotion, "follow_path", args) {
                        Ok(id) => Next::To(Phase::Drive { id, path_seq: path.seq, from }),
                        Err(e) => Next::Fail(e),
                    }
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => Next::Fail(format!("no path: {r}")),
                _ => Next::Stay,
            },
            Phase::Recover(None, retreat) => {
                match send(ctx, &peers.locomotion, "recover", serde_json::Value::Null) {
                    Ok(id) => Next::To(Phase::Recover(Some(id), retreat)),
                    Err(e) => Next::Fail(e),
                }
            }
            Phase::Recover(Some(id), retreat) => match ctx.ack_status(id) {
                // Rejected: not in fault any more; either way, move away.
                Some(AckStatus::Completed(_) | AckStatus::Rejected(_)) => {
                    const SPEED: f64 = 0.1;
                    let (v, length) = match retreat {
                        Retreat::BackOff => (-SPEED, self.params.back_off_m),
                        Retreat::Escape(way) => (way.sign() * SPEED, self.params.escape_m),
                        Retreat::Stay => return Next::To(Phase::Scan(None)),
                    };
                    let args = serde_json::json!({ "v": v, "omega": 0.0, "duration_s": length / SPEED });
                    match send(ctx, &peers.locomotion, "drive", args) {
                        Ok(id) => Next::To(Phase::Retreat(id, retreat)),
                        Err(e) => Next::Fail(e),
                    }
                }
                Some(AckStatus::Failed(r)) => Next::Fail(format!("cannot clear locomotion's fault: {r}")),
                _ => Next::Stay,
            },
            Phase::Retreat(id, retreat) => {
                let status = ctx.ack_status(id);
                let stalled = matches!(&status, Some(AckStatus::Failed(r)) if r.contains("stalled"));
                let doing = match retreat {
                    Retreat::Escape(way) => format!("escaping {}", way.describe()),
                    _ => "backing off".to_string(),
                };
                match status {
                    Some(AckStatus::Completed(_)) => Next::To(Phase::Scan(None)),
                    // A wheel stalled on the way out: clear the fault, and out another way.
                    Some(AckStatus::Failed(r)) if stalled => {
                        let way = match retreat {
                            Retreat::Escape(way) => way,
                            _ => Way::Back,
                        };
                        let next = self.retreat_after_stall(ctx, Some(way));
                        Next::FailThen(format!("{doing} failed: {r}"), Phase::Recover(None, next))
                    }
                    // Locomotion's obstacle guard refused the way out (a corner would sweep an
                    // obstacle cell the centre line keeps clear of) or stopped it: planned from
                    // where the rover stands.
                    Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) if guard::is_guard_reason(&r) => {
                        Next::FailThen(format!("{doing} failed: {r}"), Phase::Scan(None))
                    }
                    Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                        Next::Fail(format!("{doing} failed: {r}"))
                    }
                    _ => Next::Stay,
                }
            }
            Phase::Drive { id, path_seq, from } => {
                let status = ctx.ack_status(id);
                // Failed (not rejected): the drive ran and ended on a stall of its own.
                let failed = matches!(status, Some(AckStatus::Failed(_)));
                match status {
                    Some(AckStatus::Completed(_)) => {
                        let left = self.distance_to_goal(ctx).unwrap_or(f64::INFINITY);
                        if left <= tol {
                            return Next::Arrived(left);
                        }
                        if left > from - MIN_PROGRESS_M {
                            return Next::Fail(format!(
                                "no progress: the path ended {left:.2} m from the goal, {from:.2} m before it"
                            ));
                        }
                        if let Some(g) = self.goal.as_mut() {
                            g.failures = 0;
                        }
                        Next::To(if continuous { Phase::Plan(None) } else { Phase::Scan(None) })
                    }
                    Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                        if r.contains("stalled") || r.contains("fault") {
                            // A front wheel stalled driving forward: something ahead the map
                            // does not show. (A rear wheel's obstacle is behind or beside; a skid
                            // turn in place that stalled on a slope, or a stall while reversing,
                            // says nothing of the way ahead: keeping out there would only block
                            // the way on, as it once did the return to the start.)
                            // Driving forward into the same spot again, whichever wheel
                            // stalled, the way on from here is blocked for this rover (a rear
                            // wheel swinging into a rock the map does not show on a turn): the
                            // plan must go round it.
                            // Only this navigation's own stalls driving forward count (not a
                            // rejection naming a fault left from before, nor a turn in place).
                            let forward = failed && r.contains(Motion::Forward.describe());
                            if let (true, Some(here)) = (forward, self.position(ctx)) {
                                let last = self.goal.as_ref().and_then(|g| g.last_stall);
                                let again = last.is_some_and(|b| {
                                    (here[0] - b[0]).hypot(here[1] - b[1]) <= SAME_STALL_SPOT_M
                                });
                                if let Some(g) = self.goal.as_mut() {
                                    g.last_stall = Some(here);
                                }
                                if r.contains("wheel_front") || again {
                                    self.keep_out_ahead(ctx);
                                }
                                self.limit_arcs(ctx);
                            }
                            // A turn in place that stalled: the next ones near here go the other
                            // way round (and, should that stall too, back the first way).
                            let turning = failed && r.contains(Motion::TurningInPlace.describe());
                            if let (true, Some(here)) = (turning, self.position(ctx)) {
                                let stalled = if r.contains(Sense::Right.describe()) {
                                    Sense::Right
                                } else {
                                    Sense::Left
                                };
                                let other = stalled.opposite();
                                if let Some(g) = self.goal.as_mut() {
                                    g.pivot = Some((other, here));
                                }
                                ctx.note(format!(
                                    "a turn in place stalled{}: the next ones here turn{}",
                                    stalled.describe(),
                                    other.describe()
                                ));
                            }
                            // Out of the spot: back off, or escape where it stalled before.
                            let retreat = if failed {
                                let way = if r.contains(Motion::Forward.describe()) {
                                    Some(Way::Forward)
                                } else if r.contains(Motion::Reversing.describe()) {
                                    Some(Way::Back)
                                } else {
                                    None
                                };
                                self.retreat_after_stall(ctx, way)
                            } else {
                                // A fault left from before (a navigation that gave up on a
                                // stall leaves it for its caller): not this navigation's failed
                                // attempt. Cleared, and backed off from where it stalled. (No
                                // loop: once cleared, only a new stall of its own fails a drive.)
                                ctx.note(format!(
                                    "locomotion is in a fault left from before ({r}): clearing it"
                                ));
                                return Next::To(Phase::Recover(None, Retreat::BackOff));
                            };
                            Next::FailThen(format!("drive failed: {r}"), Phase::Recover(None, retreat))
                        } else {
                            Next::Fail(format!("drive failed: {r}"))
                        }
                    }
                    _ if continuous => {
                        // A replanned path replaces the one being followed.
                        let Some(path) = self.path.as_ref().and_then(|r| ctx.read(r)) else {
                            return Next::Stay;
                        };
                        if path.seq == path_seq {
                            return Next::Stay;
                        }
                        if path.value.points.is_empty() {
                            let _ = send(ctx, &peers.locomotion, "stop", serde_json::Value::Null);
                            return Next::Fail("replanning found no path".into());
                        }
                        if let Some(g) = self.goal.as_mut() {
                            g.plans += 1;
                        }
                        let args = self.path_args(&path.value, true, self.pivot_here(ctx));
                        match send(ctx, &peers.locomotion, "follow_path", args) {
                            Ok(id) => Next::To(Phase::Drive { id, path_seq: path.seq, from }),
                            Err(e) => Next::Fail(e),
                        }
                    }
                    _ => Next::Stay,
                }
            }
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>, continuous: bool) -> StateResult {
        self.mode = if continuous { "continuous" } else { "stop_and_go" };
        if self.goal.is_none() {
            // The goal went with a lifecycle change (Hold): back to idle.
            self.publish(ctx);
            return ctx.goto("idle").map_err(|e| ModuleError(e.to_string()));
        }
        match self.step(ctx, continuous) {
            Next::Stay => {}
            Next::To(phase) => {
                if let Some(g) = self.goal.as_mut() {
                    g.phase = phase;
                }
            }
            Next::Arrived(left) => {
                if let Some(g) = self.goal.take() {
                    let _ = ctx.send(Command::new(&self.peers.planner, "clear"));
                    ctx.reply(
                        &g.request,
                        Outcome::Completed(serde_json::json!({
                            "distance_to_goal_m": left, "plans": g.plans,
                        })),
                    );
                }
                ctx.goto("idle").map_err(|e| ModuleError(e.to_string()))?;
            }
            Next::Fail(reason) => self.failed(ctx, reason, Phase::Scan(None))?,
            Next::FailThen(reason, then) => self.failed(ctx, reason, then)?,
        }
        self.publish(ctx);
        Ok(())
    }

    /// Counts a failure: tries again from `then` (a scan, or a recovery), or gives up past the limit.
    fn failed(&mut self, ctx: &mut Ctx<'_>, reason: String, then: Phase) -> StateResult {
        let max = self.params.max_failures;
        let Some(g) = self.goal.as_mut() else { return Ok(()) };
        g.failures += 1;
        ctx.note(format!("navigation attempt failed ({} of {}): {reason}", g.failures, max + 1));
        if g.failures <= max {
            g.phase = then;
            return Ok(());
        }
        let g = self.goal.take().expect("checked");
        let _ = ctx.send(Command::new(&self.peers.locomotion, "stop"));
        let _ = ctx.send(Command::new(&self.peers.planner, "clear"));
        ctx.reply(
            &g.request,
            Outcome::fail(format!("gave up after {} failed attempts: {reason}", g.failures)),
        );
        ctx.goto("idle").map_err(|e| ModuleError(e.to_string()))
    }

    /// Stops the rover and fails the navigation in progress, if any, with `reason`.
    fn halt(&mut self, ctx: &mut Ctx<'_>, reason: &str) {
        if let Some(g) = self.goal.take() {
            let _ = ctx.send(Command::new(&self.peers.locomotion, "stop"));
            let _ = ctx.send(Command::new(&self.peers.planner, "clear"));
            ctx.reply(&g.request, Outcome::fail(reason));
        }
        if ctx.state() != "idle" {
            let _ = ctx.goto("idle");
        }
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let state = NavigationState {
            phase: self.goal.as_ref().map(|g| g.phase.name()).unwrap_or("idle").to_string(),
            mode: self.mode.to_string(),
            goal: self.goal.as_ref().map(|g| g.at),
            distance_to_goal_m: self.distance_to_goal(ctx),
            plans: self.goal.as_ref().map(|g| g.plans).unwrap_or(0),
            failures: self.goal.as_ref().map(|g| g.failures).unwrap_or(0),
        };
        if let Some(w) = &self.out {
            ctx.write(w, state);
        }
    }
}

impl Module for CoordinatorNavigator {
    type Params = NavigatorParams;
    const KIND: ModuleKind = ModuleKind::Coordination;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.pose = Some(d.reads(&self.pose_slot));
        self.map = Some(d.reads("navigation/map"));
        self.path = Some(d.reads("navigation/path"));
        self.out = Some(d.writes("navigation/state"));
        d.sends_to(&self.peers.fusion).sends_to(&self.peers.planner).sends_to(&self.peers.locomotion);
        d.context_switchable();
        d.state("idle", |m, ctx| {
            m.publish(ctx);
            Ok(())
        });
        d.meta_state(
            "navigating",
            &[("stop_and_go", |m, ctx| m.cycle(ctx, false)), ("continuous", |m, ctx| m.cycle(ctx, true))],
        );
        d.transition("idle", "navigating")
            .transition("navigating", "idle")
            .transition("navigating", "navigating");
        d.command("navigate_to", |m, ctx, a: NavigateArgs| {
            let tolerance = a.tolerance_m.unwrap_or(m.params.tolerance_m);
            if !(a.x.is_finite() && a.y.is_finite() && tolerance > 0.0) {
                return Outcome::reject("navigate_to needs a finite goal and a positive tolerance_m");
            }
            let Some(request) = ctx.request() else {
                return Outcome::reject("navigate_to must come as a command");
            };
            if let Some(old) = m.goal.take() {
                // The rover stops following the old goal's path before the new goal's scan.
                let _ = ctx.send(Command::new(&m.peers.locomotion, "stop"));
                ctx.reply(&old.request, Outcome::fail("superseded by a new navigate_to"));
            }
            m.goal = Some(Goal {
                request,
                at: [a.x, a.y],
                tolerance,
                phase: Phase::Scan(None),
                plans: 0,
                failures: 0,
                last_stall: None,
                pivot: None,
                stall_spots: Vec::new(),
                arcs_limited: false,
            });
            match ctx.goto("navigating") {
                Ok(()) => Outcome::Accepted,
                Err(e) => Outcome::reject(e.to_string()),
            }
        });
        d.command("cancel", |m, ctx, _: ()| {
            if m.goal.is_none() {
                return Outcome::reject("not navigating");
            }
            m.halt(ctx, "cancelled");
            Outcome::done()
        });
        // What the ground sends a module whose step it aborts: stop whatever is under way.
        d.command("stop", |m, ctx, _: ()| {
            m.halt(ctx, "stopped by command");
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &NavigatorParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("segment_m", p.segment_m),
            ("tolerance_m", p.tolerance_m),
            ("speed", p.speed),
            ("map_wait_s", p.map_wait_s),
            ("back_off_m", p.back_off_m),
        ])?;
        crate::params::require_non_negative(&[
            ("stall_keep_out_m", p.stall_keep_out_m),
            ("stall_ahead_m", p.stall_ahead_m),
            ("escape_m", p.escape_m),
            ("stall_max_curvature", p.stall_max_curvature),
        ])?;
        if p.stall_keep_out_m > p.stall_ahead_m {
            return Err(format!(
                "stall_keep_out_m ({}) must be at most stall_ahead_m ({}): the rover would stand in its own keep-out",
                p.stall_keep_out_m, p.stall_ahead_m
            ));
        }
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        if matches!(to, Lifecycle::Hold | Lifecycle::Safe | Lifecycle::Shutdown)
            && let Some(g) = self.goal.take()
        {
            // The planner keeps no goal of ours (it would replan forever).
            let _ = ctx.send(Command::new(&self.peers.planner, "clear"));
            ctx.reply(&g.request, Outcome::fail(format!("the navigator left Run for {to}")));
        }
        Ok(())
    }
}

mod escape;
#[cfg(test)]
mod tests;
