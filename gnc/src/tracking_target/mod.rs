//! `TrackingTarget` (seed 000, 8.1): follows an operator-selected target in the head camera's
//! images and locates it in 3D by stereo.
//!
//! A selection (a `TargetSelection` slot such as the operator's, or the `select` command) names a box in the
//! raw left image of a given capture time; the module keeps the last few rectified pairs, so it
//! starts the [`TemplateTracker`] on the very image the box was drawn in (mapped into the
//! rectified image through the believed calibration) and catches up on the images since. Each new
//! pair is then tracked (around where the target's 3D estimate projects, once it has one, at the
//! size the selected box has at the estimate's range; a lost target of an established estimate is
//! looked for only within that estimate's uncertainty for a while, not over the whole image) and, when
//! the target is found, located by [`locate`] in the rectified pair; the location is placed in `map`
//! through the believed mechanism, the pan-tilt joints and the rover's pose estimate at the image's
//! capture time. For a static target of known size (`known_sizes`), a location farther from where
//! it was selected, or nearer, than the selected box's size allows is a wrong match and is rejected
//! ([`crate::tracking::size`]). The others are fused with the earlier ones ([`TargetEstimate`]: a slowly wandering point; a
//! static target's estimate sharpens as the rover approaches, a moving one is followed). Its
//! covariance is relative to the rover's pose estimate: that estimate's own error moves the rover
//! and the target alike in `map` and does not hinder an approach; only its drift since the target
//! was located does, and `locate` counts it. Published every image: `tracking/target`
//! ([`TargetTrack`]).
//!
//! Commands: `select {bbox, image_stamp_s?}` (a box in a held image, the newest by default),
//! `forget`, `reject` (what the estimate found is not the target, as the wrist camera tells at
//! the end of an approach: its place is excluded and the target looked for again along the line
//! of sight it was selected on: [`reject`]), `stop` (a pending `locate` fails; tracking goes on),
//! and `locate {max_sigma_m?}`,
//! which completes once the target's position (its uncertainty grown by the target's wander since
//! it was last located) is known to `max_sigma_m` (1 sigma, horizontal) and fails if the target
//! is lost for `lost_timeout_s` or nothing is selected.

mod params;
mod placing;
mod prior;
mod reject;

pub use params::{LocateArgs, RejectArgs, SelectArgs, TrackingTargetParams};

use framework::data::ExcludedPlace;
use reject::{beyond, excluded, ray_prior};

use placing::{
    at_expected_depth, box_fits, in_map, inside, map_box, on_the_ground, pose_term, raw_to_rect, rect_to_raw,
    selected_view, sight_through, size_bounds,
};

use crate::localization::rectify::Rectification;
use crate::placement::Placement;
use crate::tracking::estimate::{TargetEstimate, fitted_velocity};
use crate::tracking::locate::{Located, locate};
use crate::tracking::locate_sigma;
use crate::tracking::search::LostSearch;
use crate::tracking::size::{SelectedView, sized_ranges};
use crate::tracking::template::{BBox, TemplateTracker, TrackStatus, Verdict};
use framework::camera::{GreyImage, StereoCalibration};
use framework::data::{LineOfSight, PoseEstimate, StereoImages, TargetSelection, TargetStatus, TargetTrack};
use framework::mechanism::MechanismModel;
use framework::module::Request;
use framework::prelude::*;
use nalgebra::{Matrix3, Point3};
use std::collections::VecDeque;

/// Locations fused since the estimate (re)started after which it is established: one that agrees
/// confirms the box's look, disagreeing ones no longer restart it.
const CONFIRM_AFTER: u32 = 3;

/// Locations must span this long for a velocity to be fitted to them, s.
const MIN_VELOCITY_SPAN_S: f64 = 5.0;

/// Disagreeing locations in a row after which the tracker is taken to be on something else.
const REJECTS_TO_LOSE: u32 = 2;

/// The slot of the target track.
pub const SLOT: &str = "tracking/target";

/// A held rectified pair.
struct Held {
    stamp: Time,
    left: GreyImage,
    right: GreyImage,
}

/// The TrackingTarget module.
pub struct TrackingTarget {
    device: String,
    calibration: StereoCalibration,
    rect: Rectification,
    placement: Placement,
    params: TrackingTargetParams,
    images: Option<Reader<StereoImages>>,
    selection_slot: Option<String>,
    selections: Option<Reader<TargetSelection>>,
    out: Option<Writer<TargetTrack>>,
    last_image_seq: u64,
    last_selection_seq: u64,
    held: VecDeque<Held>,
    tracker: Option<TemplateTracker>,
    target: String,
    estimate: TargetEstimate,
    located: u32,
    last_range: Option<f64>,
    lost_since: Option<Time>,
    /// How long the lost target has been searched for where the estimate projects.
    searched_lost: LostSearch,
    /// The last images looked at, newest in bit 0: 1 where one found the ground where the
    /// estimate projects (`doubt_on_ground`).
    ground_history: u32,
    /// A pending `locate` and its accuracy.
    pending: Option<(Request, f64)>,
    /// A failed stereo location was noted since the selection.
    locate_noted: bool,
    /// The line of sight through the box's centre in the last image it was seen in.
    sight: Option<LineOfSight>,
    /// The pose estimate's share of the newest fused location's covariance (see `pose_drift`).
    fix_pose_term: Option<Matrix3<f64>>,
    /// Where the camera was (`map`) in the selection's image, and the selected box there: the
    /// box's expected size at any range follows from them, and for a target of known size, the
    /// ranges it may be at.
    selected_view: Option<SelectedView>,
    /// The selected box touched the raw image's border (so may be smaller than the target).
    selection_clipped: bool,
    /// The fused locations of the last `velocity_window_s` (capture time s, position in `map`).
    recent: Vec<(f64, Point3<f64>)>,
    /// The tracker as the selection started it (its look then), to start again from after a
    /// `reject`.
    selected_tracker: Option<TemplateTracker>,
    /// The line of sight through the selected box's centre, and the rover's pose estimate, in
    /// the selection's image.
    selected_sight: Option<(LineOfSight, PoseEstimate)>,
    /// The places of objects rejected as not the target (`reject`).
    excluded: Vec<ExcludedPlace>,
    /// The estimate is the prior a `reject` restarted it from: nothing located since.
    prior_only: bool,
}

impl TrackingTarget {
    /// The ranges from where it was selected that the selected box allows the target, if its
    /// size is known (`known_sizes`).
    fn size_bounds(&self) -> Option<(f64, f64)> {
        size_bounds(&self.params, &self.target, self.selected_view, self.selection_clipped, &self.rect)
    }

    /// Target tracking on the stereo slot `cameras/<device>` from a pair with the believed
    /// `calibration`, placed on the robot of the believed `mechanism` with the rover's pose from
    /// `pose_slot` and joints from `joints_slots`; selections from `selection_slot` (a
    /// `TargetSelection` slot, when someone publishes selections) and the `select` command.
    pub fn new(
        device: &str,
        calibration: StereoCalibration,
        mechanism: MechanismModel,
        pose_slot: &str,
        joints_slots: &[&str],
        selection_slot: Option<&str>,
    ) -> Self {
        let p = TrackingTargetParams::default();
        TrackingTarget {
            device: device.to_string(),
            rect: Rectification::new(&calibration),
            calibration,
            placement: Placement::new(mechanism, pose_slot, joints_slots, p.history_s),
            params: p,
            images: None,
            selection_slot: selection_slot.map(str::to_string),
            selections: None,
            out: None,
            last_image_seq: 0,
            last_selection_seq: 0,
            held: VecDeque::new(),
            tracker: None,
            target: String::new(),
            estimate: TargetEstimate::default(),
            located: 0,
            last_range: None,
            lost_since: None,
            searched_lost: LostSearch::default(),
            ground_history: 0,
            pending: None,
            locate_noted: false,
            sight: None,
            fix_pose_term: None,
            selected_view: None,
            selection_clipped: false,
            recent: Vec::new(),
            selected_tracker: None,
            selected_sight: None,
            excluded: Vec::new(),
            prior_only: false,
        }
    }

    /// Forgets everything known of the target; `tracker` (a new selection's, or none) follows it
    /// from now on.
    fn start_over(&mut self, tracker: Option<TemplateTracker>) {
        self.selected_tracker = tracker.clone();
        self.selected_sight = None;
        self.excluded.clear();
        self.prior_only = false;
        self.tracker = tracker;
        self.estimate = TargetEstimate::default();
        self.located = 0;
        self.lost_since = None;
        self.searched_lost = LostSearch::default();
        self.ground_history = 0;
        self.locate_noted = false;
        self.last_range = None;
        self.sight = None;
        self.fix_pose_term = None;
        self.selected_view = None;
        self.recent.clear();
    }

    /// Starts tracking the box `bbox` (raw left pixels) of the held image of `stamp` (None: the
    /// newest), then catches up on the images since.
    fn select(
        &mut self,
        ctx: &mut Ctx<'_>,
        target: &str,
        bbox: [f64; 4],
        stamp: Option<Time>,
    ) -> Result<(), String> {
        let k = match stamp {
            Some(t) => {
                self.held.iter().position(|h| (h.stamp - t).as_secs_f64().abs() < 1e-3).ok_or_else(|| {
                    format!("the image of {t} is no longer held (the {} newest are)", self.held.len())
                })?
            }
            None => self.held.len().checked_sub(1).ok_or("no image yet")?,
        };
        let rect_box = map_box(&bbox, |p| raw_to_rect(&self.rect, &self.calibration, p))
            .ok_or_else(|| format!("the box {bbox:?} does not map into the rectified image"))?;
        let mut tracker = TemplateTracker::new(self.params.tracker.clone());
        tracker.init(&self.held[k].left, rect_box)?;
        self.start_over(Some(tracker));
        self.target = target.to_string();
        let raw = &self.calibration.left.model.pinhole;
        let (w, h) = (f64::from(raw.width), f64::from(raw.height));
        self.selection_clipped = bbox[0] <= 1.0 || bbox[1] <= 1.0 || bbox[2] >= w - 1.0 || bbox[3] >= h - 1.0;
        ctx.note(format!(
            "tracking the {target} selected at {bbox:?} in the image of {}",
            self.held[k].stamp
        ));
        let first = self.held[k].stamp;
        self.process(ctx, first, false);
        for j in k + 1..self.held.len() {
            let stamp = self.held[j].stamp;
            self.process(ctx, stamp, true);
        }
        Ok(())
    }

    /// The object followed is not the target (`reject`): its place is excluded, the estimate
    /// restarts from the selection's line of sight (where the selected box's size allows a target
    /// of known size, else beyond the rejected object), and the tracker from the selection's look,
    /// lost, so that the next images re-detect the target there (see [`reject`]).
    fn reject(&mut self, ctx: &mut Ctx<'_>, at: Option<Point3<f64>>) -> Result<(), String> {
        let mut tracker = self.selected_tracker.clone().ok_or("no target selected")?;
        let now = ctx.now();
        if self.prior_only {
            return Err(format!(
                "no {} has been located since the last rejection: there is nothing to reject",
                self.target
            ));
        }
        let object = at
            .or_else(|| self.estimate.position_at(now))
            .filter(|p| p.coords.iter().all(|v| v.is_finite()))
            .ok_or_else(|| format!("the {} is not located: there is nothing to reject", self.target))?;
        let place = ExcludedPlace { position: object, radius_m: self.params.reject_radius_m };
        self.excluded.push(place);
        let prior = self.selected_sight.clone().and_then(|(sight, pose)| {
            // A target of known size: where its selected box's size puts it, between the ranges
            // at which its smallest and its largest extent fill the box exactly (the box's slack
            // left out: with it the prior spans 7 m at 25 m, and the first rock on the line is
            // let in), centred at their geometric mean (as `prior`); the rejected object, which
            // may lie in front of the target or behind it, is excluded. Else beyond the rejected
            // object. The operator's box is exact here; a box drawn loose would put the target
            // beyond this stretch.
            let [near_slack, far_slack] = self.params.size_tolerance;
            let stretch = match self.size_bounds() {
                Some((lo, hi)) => {
                    let (near, far) = (lo * near_slack, hi / far_slack);
                    (near, Some((near * far).sqrt()), far)
                }
                None => {
                    let near = beyond(&sight, &place);
                    (near, None, near + self.params.reject_search_m)
                }
            };
            // Across the line: the head's pointing and the selected box's half width.
            let half_box =
                self.selected_view.map_or(0.0, |v| 0.5 * v.width_px / self.rect.model.left.pinhole.fx);
            let pointing = self.params.locate.pointing_sigma_deg.to_radians();
            let lateral = |r: f64| r * pointing.hypot(half_box);
            let prior = ray_prior(&sight, stretch, lateral, self.params.redetect_gate_sigma)?;
            Some((prior, pose))
        });
        match prior {
            Some((prior, pose)) if self.estimate.start_from(&prior, now, CONFIRM_AFTER) => {
                self.prior_only = true;
                // Relative to the pose estimate of the selection's image: its drift since counts.
                self.fix_pose_term = Some(pose_term(&pose, &prior.position));
                let sigmas = prior.covariance.symmetric_eigenvalues().map(f64::sqrt);
                ctx.note(format!(
                    "the object followed at {object:?} is not the {}: excluded; looked for again along the line of sight it was selected on, around {:?} ({:.1} m along, {:.2} m across, 1 sigma)",
                    self.target,
                    prior.position,
                    sigmas.max(),
                    sigmas.min(),
                ));
            }
            _ => {
                self.estimate = TargetEstimate::default();
                self.fix_pose_term = None;
                ctx.note(format!(
                    "the object followed at {object:?} is not the {}: excluded; nothing is left of the line of sight it was selected on: looked for anywhere",
                    self.target
                ));
            }
        }
        tracker.reject();
        self.tracker = Some(tracker);
        self.lost_since = None;
        self.searched_lost = LostSearch::default();
        self.ground_history = 0;
        self.locate_noted = false;
        self.last_range = None;
        self.sight = self.selected_sight.as_ref().map(|(s, _)| *s);
        self.recent.clear();
        Ok(())
    }

    /// Tracks and locates in the held image of `stamp` (`track`: false for the selection's own
    /// image, which is only located) and publishes the track.
    fn process(&mut self, ctx: &mut Ctx<'_>, stamp: Time, track: bool) {
        let Some(h) = self.held.iter().find(|h| h.stamp == stamp) else { return };
        // Where the camera was: for the prediction and the location (the 2D track goes on without).
        let placed =
            self.placement.camera_at(&self.calibration.left, stamp).map(|(pose, base_from_optical)| {
                (pose.pose * base_from_optical * self.rect.left_from_rect, pose)
            });
        let prior = self.prior(stamp, placed.as_ref().ok());
        let Some(tracker) = &mut self.tracker else { return };
        // The re-detection candidates located (and their locations), not to locate one twice.
        let mut checked: Vec<(BBox, Result<Located, String>)> = Vec::new();
        // A re-detection candidate found the ground where the estimate projects.
        let mut ground_candidate_at_estimate = false;
        // This image's box found the ground where the estimate projects (None: no box located).
        let mut ground_at_estimate = None;
        let mut searched = false;
        let result = if track {
            // Where the estimate says the target is out of the image (the head looks elsewhere:
            // a scan), there is nothing to track, and a search would only find look-alikes: the
            // tracker waits for it to come back into view where the estimate projects.
            let (w, ht) = (h.left.width as f64, h.left.height as f64);
            let out_of_view = self.estimate.position().is_some()
                && placed.is_ok()
                && prior.centre.is_none_or(|(u, v)| !(0.0..w).contains(&u) || !(0.0..ht).contains(&v));
            if out_of_view {
                crate::tracking::template::TrackResult {
                    bbox: tracker.bbox().unwrap_or([0.0; 4]),
                    confidence: 0.0,
                    status: TrackStatus::Lost,
                }
            } else {
                searched = true;
                // An established estimate checks each re-detection candidate: one whose stereo
                // location disagrees with it is a look-alike (the ground beside a small target,
                // a rock), and the next best is tried; one stereo cannot locate (a few pixels far
                // away) says nothing either way. Except after a `reject` (`prior_only`): the
                // target is then looked for near the rover, where stereo locates it, and one it
                // cannot locate (at the image's edge, in a shadow) is not taken on its look alone.
                let established = self.estimate.count() >= CONFIRM_AFTER;
                let prior_only = self.prior_only;
                let unlocated = if prior_only { Verdict::Disagrees } else { Verdict::Unknown };
                let (estimate, params, rect, fix, rejected) =
                    (&self.estimate, &self.params, &self.rect, self.fix_pose_term, &self.excluded);
                let view = self.selected_view;
                let (target, clipped) = (&self.target, self.selection_clipped);
                let bounds = size_bounds(params, target, view, clipped, rect);
                let mut check = |b: &BBox| {
                    let Some((map_from_rect, pose)) = placed.as_ref().ok() else { return Verdict::Unknown };
                    let loc = locate(&h.left, &h.right, &rect.model, *b, &params.locate);
                    let verdict = match &loc {
                        Err(_) => unlocated,
                        Ok(loc) => {
                            let here = in_map(loc, map_from_rect, pose, fix);
                            let gate = params.redetect_gate_sigma;
                            let sized = view.is_none_or(|v| v.allows(&here.position, bounds));
                            // After a `reject`, the candidate's own box must be as large as
                            // the target at its range too (see [`reject`]). Not before: an
                            // approach that followed a rock would lose it for good, where it
                            // should reach it and have the wrist camera tell (canister_sweep
                            // run 8 then ended in the approach, lost at 2.3 m).
                            let fits = !prior_only
                                || box_fits(params, target, clipped, rect, map_from_rect, b, &here.position);
                            let ground = on_the_ground(loc, map_from_rect, &rect.model, params).is_some();
                            ground_candidate_at_estimate |= ground && inside(b, prior.centre);
                            let elsewhere = !excluded(rejected, &here.position);
                            if sized
                                && fits
                                && !ground
                                && elsewhere
                                && estimate.agrees(&here, stamp, params.target_walk, gate)
                            {
                                Verdict::Agrees
                            } else {
                                Verdict::Disagrees
                            }
                        }
                    };
                    checked.push((*b, loc));
                    verdict
                };
                let check =
                    (established && placed.is_ok()).then_some(&mut check as &mut dyn FnMut(&BBox) -> Verdict);
                let r = tracker.update_checked(&h.left, &prior, check);
                // The selection's own image could not be placed: the first placed image where the
                // target is found stands for it.
                if self.selected_view.is_none()
                    && r.status != TrackStatus::Lost
                    && let Ok((map_from_rect, pose)) = &placed
                {
                    self.selected_view = Some(selected_view(map_from_rect, &r.bbox));
                    self.selected_sight =
                        Some((sight_through(&self.rect, map_from_rect, &r.bbox), pose.clone()));
                }
                r
            }
        } else {
            if let (Ok((map_from_rect, pose)), Some(b)) = (&placed, tracker.bbox()) {
                self.selected_view = Some(selected_view(map_from_rect, &b));
                self.selected_sight = Some((sight_through(&self.rect, map_from_rect, &b), pose.clone()));
            }
            crate::tracking::template::TrackResult {
                bbox: tracker.bbox().unwrap_or([0.0; 4]),
                confidence: 1.0,
                status: TrackStatus::Tracking,
            }
        };
        let mut measured = None;
        let found = result.status != TrackStatus::Lost;
        self.searched_lost.frame(stamp, found, searched);
        if found {
            self.lost_since = None;
        } else {
            self.lost_since.get_or_insert(stamp);
        }
        let located = match (&placed, result.status) {
            (_, TrackStatus::Lost) => None,
            (Err(e), _) => Some(Err(format!("not placed: {e}"))),
            (Ok(_), _) => match checked.into_iter().find(|(b, _)| *b == result.bbox) {
                Some((_, loc)) => Some(loc),
                None => Some(locate(&h.left, &h.right, &self.rect.model, result.bbox, &self.params.locate)),
            },
        };
        match (located, &placed) {
            (Some(Ok(loc)), Ok((map_from_rect, pose))) => {
                // Once established (confirmed locations), the estimate is not restarted by
                // disagreeing locations: they mean the tracker is on something else. Before, a
                // wrong first location must not lock out the right ones.
                let established = self.estimate.count() >= CONFIRM_AFTER;
                // A prior (after a `reject`) gates like an established estimate, but no location
                // has confirmed it: none is weighed at its depth, no look is learnt by it.
                let confirmed = established && !self.prior_only;
                // Fused at the estimate's depth if so configured, but gated at its own: what lies in
                // front of the target (the likeliest look-alike) is held to its own smaller
                // uncertainty, what lies behind to its wider one (gated at both, the visual
                // approach on 4 cm treads ended 2.1 m from the canister, beside it). The pair
                // calibration's disparity error, the largest share of either far away, is the
                // estimate's as much as the location's and counts once (`tracking::estimate`):
                // a look-alike behind the target differs by its real disparity.
                let own = in_map(&loc, map_from_rect, pose, self.fix_pose_term);
                let p = own.position;
                let there = if self.params.fuse_at_estimate_depth {
                    let there = at_expected_depth(
                        &loc,
                        map_from_rect,
                        self.estimate.position_at(stamp),
                        confirmed,
                        &self.rect.model,
                        &self.params.locate,
                    );
                    // At the measured position (at_depth keeps it), with the errors of the
                    // estimate's depth.
                    in_map(&there, map_from_rect, pose, self.fix_pose_term)
                } else {
                    own.clone()
                };
                let gate = if result.status == TrackStatus::Redetected {
                    self.params.redetect_gate_sigma
                } else {
                    self.params.gate_sigma
                };
                let walk = self.params.target_walk;
                let bounds = size_bounds(
                    &self.params,
                    &self.target,
                    self.selected_view,
                    self.selection_clipped,
                    &self.rect,
                );
                let ground = on_the_ground(&loc, map_from_rect, &self.rect.model, &self.params);
                ground_at_estimate =
                    Some(ground.is_some() && established && inside(&result.bbox, prior.centre));
                let sized = self.selected_view.is_none_or(|v| v.allows(&p, bounds));
                let rejected = excluded(&self.excluded, &p);
                if rejected {
                    // Where an object rejected as not the target stands: the box is on it again,
                    // and the target is looked for elsewhere (with an estimate or without).
                    self.estimate.count_rejection();
                    tracker.reject();
                    ctx.note(format!(
                        "a {} location at {p:?} is where an object rejected as not the {} stands: rejected",
                        self.target, self.target
                    ));
                } else if let Some(tilt) = ground {
                    // A patch of the ground counts as a disagreeing location (never as one that
                    // restarts the estimate): the box slid off the target.
                    self.estimate.count_rejection();
                    ctx.note(format!(
                        "a {} location at {p:?} is the ground (its box shows a surface tilted {tilt:.0} deg at most): rejected",
                        self.target
                    ));
                } else if !sized {
                    // A location the box's size rules out counts as a disagreeing one (never as
                    // one that restarts the estimate): the box is on something else, or stereo
                    // matched the wrong thing.
                    self.estimate.count_rejection();
                    if let (Some(v), Some((lo, hi))) = (self.selected_view, bounds) {
                        ctx.note(format!(
                            "a {} location at {p:?} is {:.1} m from where it was selected, where its box's size puts it {lo:.1}-{hi:.1} m away: rejected",
                            self.target,
                            (p - v.camera).norm()
                        ));
                    }
                }
                let fused = sized
                    && ground.is_none()
                    && !rejected
                    && if self.params.fuse_at_estimate_depth && self.estimate.agrees(&own, stamp, walk, gate)
                    {
                        self.estimate.fuse(&there, stamp, walk, f64::INFINITY, false)
                    } else {
                        self.estimate.fuse(&own, stamp, walk, gate, !established)
                    };
                if fused {
                    // Where an established estimate holds it, the box is the target: its look is
                    // learnt.
                    if confirmed {
                        tracker.confirm(&h.left);
                    }
                    measured = Some(p);
                    let t = stamp.as_secs_f64();
                    let window = self.params.velocity_window_s;
                    if self.estimate.count() == 1 {
                        // (Re)started: the locations before were of something else.
                        self.recent.clear();
                        self.ground_history = 0;
                    }
                    self.recent.retain(|r| r.0 >= t - window);
                    self.recent.push((t, p));
                    let speed = self.params.max_target_speed_mps;
                    let v = fitted_velocity(&self.recent, speed, MIN_VELOCITY_SPAN_S);
                    self.estimate.set_velocity(v, self.params.velocity_horizon_s);
                    self.fix_pose_term = Some(pose_term(pose, &p));
                    self.located += 1;
                    self.prior_only = false;
                    self.last_range = Some(loc.position.coords.norm());
                } else {
                    if sized && ground.is_none() && !rejected {
                        ctx.note(format!(
                            "a {} location at {p:?} disagrees with the estimate: rejected",
                            self.target
                        ));
                    }
                    if established && self.estimate.rejected() >= REJECTS_TO_LOSE {
                        // The box is on something else: look for the target where it is.
                        tracker.reject();
                        if self.estimate.rejected() == REJECTS_TO_LOSE {
                            ctx.note(format!(
                                "the tracker's box disagreed with the {} estimate {REJECTS_TO_LOSE} times: re-detecting",
                                self.target
                            ));
                        }
                    }
                }
            }
            (Some(Err(e)), _) if !self.locate_noted => {
                ctx.note(format!("the {} is tracked but not located: {e}", self.target));
                self.locate_noted = true;
            }
            _ => {}
        }
        if let (Some(at_estimate), Ok((map_from_rect, _))) =
            (ground_at_estimate.or(ground_candidate_at_estimate.then_some(true)), &placed)
        {
            self.doubt_on_ground(ctx, stamp, &Point3::from(map_from_rect.translation.vector), at_estimate);
        }
        if let Ok((map_from_rect, _)) = &placed {
            self.doubt_when_lost(ctx, stamp, &Point3::from(map_from_rect.translation.vector));
        }
        if result.status != TrackStatus::Lost
            && let Ok((map_from_rect, _)) = &placed
        {
            self.sight = Some(sight_through(&self.rect, map_from_rect, &result.bbox));
        }
        let status = match result.status {
            TrackStatus::Tracking => TargetStatus::Tracking,
            TrackStatus::Redetected => TargetStatus::Redetected,
            TrackStatus::Lost => TargetStatus::Lost,
        };
        let bbox =
            map_box(&result.bbox, |p| rect_to_raw(&self.rect, &self.calibration, p)).unwrap_or(result.bbox);
        // Where along the line of sight the selected box's size puts a target of known size.
        let sized_range_m = self
            .sight
            .zip(self.selected_view)
            .zip(self.size_bounds())
            .map(|((sight, view), bounds)| sized_ranges(&sight, &view.camera, bounds));
        let out = TargetTrack {
            target: self.target.clone(),
            camera: self.device.clone(),
            stamp,
            status,
            confidence: result.confidence,
            bbox,
            position: self.estimate.position(),
            position_stamp: self.estimate.stamp(),
            velocity: self.estimate.velocity(),
            velocity_horizon_s: self.estimate.velocity_horizon_s(),
            covariance: self.estimate.covariance().unwrap_or_else(Matrix3::zeros),
            range_m: self.last_range,
            sized_range_m,
            measured,
            located: self.located,
            line_of_sight: self.sight,
            excluded: self.excluded.clone(),
        };
        if let Some(w) = &self.out {
            ctx.write_stamped(w, out, stamp);
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        self.placement.update(ctx);
        let mut fresh = None;
        if let Some(frame) = self.images.as_ref().and_then(|r| ctx.read(r))
            && frame.seq != self.last_image_seq
        {
            self.last_image_seq = frame.seq;
            let stamp = frame.value.left.stamp;
            self.held.push_back(Held {
                stamp,
                left: self.rect.left(&frame.value.left),
                right: self.rect.right(&frame.value.right),
            });
            while self.held.len() > self.params.held_images.max(1) {
                self.held.pop_front();
            }
            fresh = Some(stamp);
        }
        if let Some(sel) = self.selections.as_ref().and_then(|r| ctx.read(r))
            && sel.seq != self.last_selection_seq
        {
            self.last_selection_seq = sel.seq;
            let s = sel.value.clone();
            if s.camera != self.device {
                ctx.note(format!(
                    "a selection in '{}' ignored: this module tracks in '{}'",
                    s.camera, self.device
                ));
            } else if let Err(e) = self.select(ctx, &s.target, s.bbox, Some(s.image_stamp)) {
                ctx.note(format!("the {} selection cannot be tracked: {e}", s.target));
            }
            return self.settle(ctx);
        }
        if let Some(stamp) = fresh {
            self.process(ctx, stamp, true);
        }
        self.settle(ctx)
    }

    /// Answers a pending `locate` when it can.
    fn settle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let Some((_, max_sigma)) = &self.pending else { return Ok(()) };
        // The estimate ages: a target that may wander is known less well the longer ago it was
        // last located, and the rover's pose estimate has drifted since.
        let aged = self.aged_covariance(ctx.now(), self.placement.newest_pose());
        let outcome = if let (Some(p), Some(c)) = (self.estimate.position_at(ctx.now()), aged)
            && locate_sigma(&c) <= *max_sigma
        {
            Some(Outcome::Completed(serde_json::json!({
                "target": self.target,
                "position": [p.x, p.y, p.z],
                "sigma_m": [c[(0, 0)].sqrt(), c[(1, 1)].sqrt(), c[(2, 2)].sqrt()],
                "located": self.located,
            })))
        } else if self.tracker.is_none() {
            Some(Outcome::fail("no target selected"))
        } else if let Some(since) = self.lost_since
            && (ctx.now() - since).as_secs_f64() > self.params.lost_timeout_s
        {
            Some(Outcome::fail(format!("the {} has been lost since {since}", self.target)))
        } else {
            None
        };
        if let Some(o) = outcome {
            let (req, _) = self.pending.take().expect("checked");
            ctx.reply(&req, o);
        }
        Ok(())
    }
}

impl Module for TrackingTarget {
    type Params = TrackingTargetParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.images = Some(d.reads(&format!("cameras/{}", self.device)));
        if let Some(slot) = &self.selection_slot {
            self.selections = Some(d.reads(slot));
        }
        self.placement.declare(d);
        self.out = Some(d.writes(SLOT));
        d.context_switchable();
        d.state("tracking", |m, ctx| m.cycle(ctx));
        d.command("select", |m, ctx, a: SelectArgs| {
            let target = a.target.unwrap_or_else(|| "target".into());
            match m.select(ctx, &target, a.bbox, a.image_stamp_s.map(Time::from_secs_f64)) {
                Ok(()) => Outcome::done(),
                Err(e) => Outcome::reject(e),
            }
        });
        d.command("stop", |m, ctx, _: ()| {
            if let Some((req, _)) = m.pending.take() {
                ctx.reply(&req, Outcome::fail("stopped"));
            }
            Outcome::done()
        });
        d.command("reject", |m, ctx, a: RejectArgs| match m.reject(ctx, a.position.map(Point3::from)) {
            Ok(()) => Outcome::done(),
            Err(e) => Outcome::reject(e),
        });
        d.command("forget", |m, _ctx, _: ()| {
            m.start_over(None);
            Outcome::done()
        });
        d.command("locate", |m, ctx, a: LocateArgs| {
            let sigma = a.max_sigma_m.unwrap_or(0.5);
            if !(sigma.is_finite() && sigma > 0.0) {
                return Outcome::reject(format!("max_sigma_m must be positive, got {sigma}"));
            }
            if m.tracker.is_none() {
                return Outcome::reject("no target selected (by the operator or 'select')");
            }
            let Some(req) = ctx.request() else { return Outcome::reject("locate needs a request to answer") };
            if let Some((old, _)) = m.pending.replace((req, sigma)) {
                ctx.reply(&old, Outcome::fail("superseded by a new locate"));
            }
            Outcome::Accepted
        });
    }

    fn configure(&mut self, p: &TrackingTargetParams) -> Result<(), String> {
        p.validate()?;
        self.placement.configure(p.history_s, p.max_extrapolation_s);
        self.params = p.clone();
        Ok(())
    }
}
