//! What TrackingTarget tells its image tracker of the target (the [`Prior`]: where its estimate
//! projects, the box's expected width and the widths its uncertainty allows, how far a lost
//! target may be looked for), the estimate's covariance aged to an image's time, and when the
//! estimate is doubted (the ground seen where it projects; a search there that finds nothing).

use super::placing::pose_drift;
use super::{CONFIRM_AFTER, TrackingTarget};
use crate::tracking::search::search_radius_px;
use crate::tracking::size::along_sight;
use crate::tracking::template::{Prior, TemplateTracker};
use framework::data::PoseEstimate;
use framework::prelude::*;
use nalgebra::{Isometry3, Matrix3, Point3};

/// Of the last [`GROUND_WINDOW`] images with a located box or re-detection candidate, those that
/// found the ground where an established estimate projects, after which the estimate is doubted
/// (`doubt_range_fraction`): most of them (a box slid onto the ground is not always told from the
/// target: a box of a few rows far away cannot be).
const GROUND_TO_DOUBT: u32 = 3;
const GROUND_WINDOW: u32 = 5;

impl TrackingTarget {
    /// The estimate's covariance at `now`: grown by the target's wander since it was last located
    /// and by the drift of the rover's pose estimate (`pose`, when known) since then.
    pub(super) fn aged_covariance(&self, now: Time, pose: Option<&PoseEstimate>) -> Option<Matrix3<f64>> {
        let (c, t, p) = (self.estimate.covariance()?, self.estimate.stamp()?, self.estimate.position()?);
        let age = (now - t).as_secs_f64().max(0.0);
        let drift = pose.map_or_else(Matrix3::zeros, |pose| pose_drift(self.fix_pose_term, pose, &p));
        Some(c + Matrix3::identity() * self.params.target_walk.powi(2) * age + drift)
    }

    /// What the tracker is told of the target in the image of `stamp`, taken from `placed` (the
    /// rectified left camera in `map`, and the rover's pose estimate): where the estimate
    /// projects (else the last line of sight at the last range, or the range the selected box's
    /// size gives, or `sight_range_m`: the camera may have turned), the
    /// box's expected width, and, for an established estimate, how far from its projection a lost
    /// target can be.
    pub(super) fn prior(&self, stamp: Time, placed: Option<&(Isometry3<f64>, PoseEstimate)>) -> Prior {
        let Some((map_from_rect, pose)) = placed else { return Prior::default() };
        let camera = Point3::from(map_from_rect.translation.vector);
        // A moving target is carried by its velocity since it was last located.
        let estimate = self.estimate.position_at(stamp);
        // Before stereo ranges it, the target is where its box's size says (if its size is
        // known: that range is from where it was selected, carried onto the newest line of
        // sight), else at the assumed range.
        let expected = estimate.or_else(|| {
            let sight = self.sight?;
            // The bounds' middle without the box's slack: the extents' geometric mean.
            let [near, far] = self.params.size_tolerance;
            let from_size = self
                .size_bounds()
                .zip(self.selected_view)
                .map(|((lo, hi), view)| along_sight(&sight, &view.camera, (lo * near * hi / far).sqrt()));
            Some(sight.at(self.last_range.or(from_size).unwrap_or(self.params.sight_range_m)))
        });
        let Some(expected) = expected else { return Prior::default() };
        let in_camera = map_from_rect.inverse() * expected;
        let centre = self.rect.model.left.project(&in_camera).map(|uv| (uv.x, uv.y));
        // Only an established estimate (a wrong first location is allowed for) sizes the box and
        // bounds the search.
        let established = self.estimate.count() >= CONFIRM_AFTER;
        // Its covariance now (both uses below need an established estimate).
        let aged = established.then(|| self.aged_covariance(stamp, Some(pose))).flatten();
        // The selected box's width times the ratio of the ranges then and now, both from the one
        // estimate (its range error mostly cancels).
        let width_px = estimate
            .zip(self.selected_view)
            .filter(|_| established)
            .map(|(p, v)| v.width_px * (p - v.camera).norm() / (p - camera).norm())
            .filter(|w| w.is_finite());
        // After a `reject`, the smallest and largest widths the box can have within the prior's
        // uncertainty along the line of sight (to the re-detection gate): a metre or two either way
        // at a few metres. (An estimate that located the target knows its range well enough for
        // the re-detection scales around `width_px`.)
        let width_span_px =
            estimate.zip(self.selected_view).filter(|_| established && self.prior_only).zip(aged).and_then(
                |((p, v), c)| {
                    let range = (p - camera).norm();
                    let along = (p - camera) / range;
                    let sigma = (along.transpose() * c * along)[(0, 0)].max(0.0).sqrt();
                    let reach = self.params.redetect_gate_sigma * sigma;
                    // Nearer than a third of the range or farther than three times it, not looked at.
                    let (near, far) = ((range - reach).max(range / 3.0), (range + reach).min(3.0 * range));
                    let width_at = |r: f64| v.width_px * (camera + along * r - v.camera).norm() / r;
                    // The width shrinks with the range unless the camera moved away from where the
                    // target was selected: its least may then lie between the ends, where the range
                    // from the selecting camera is least relative to this one's.
                    let a = camera - v.camera;
                    let inner = (a.dot(&along) < 0.0).then(|| -a.norm_squared() / a.dot(&along));
                    let widths = [Some(near), Some(far), inner.filter(|r| (near..=far).contains(r))]
                        .into_iter()
                        .flatten()
                        .map(width_at);
                    let (lo, hi) = widths.fold((f64::INFINITY, 0.0f64), |(lo, hi), w| (lo.min(w), hi.max(w)));
                    (lo.is_finite() && hi.is_finite() && lo > 0.0).then_some((lo, hi))
                },
            );
        let radius_px = if established && self.searched_lost.searched_s() < self.params.redetect_whole_after_s
        {
            aged.and_then(|c| {
                let r = map_from_rect.rotation.to_rotation_matrix().into_inner();
                // The box at the size it is looked for.
                let half_box = self.tracker.as_ref().and_then(TemplateTracker::bbox).map_or(0.0, |b| {
                    let (w, h) = (b[2] - b[0], b[3] - b[1]);
                    let k = width_px.map_or(1.0, |e| e / w);
                    0.5 * k * w.hypot(h)
                });
                search_radius_px(
                    &self.rect.model.left.pinhole,
                    &in_camera,
                    &(r.transpose() * c * r),
                    self.params.gate_sigma,
                    self.params.redetect_margin_px,
                    half_box,
                )
            })
        } else {
            None
        };
        Prior { centre, radius_px, width_px, width_span_px }
    }

    /// Counts an image whose box (or a re-detection candidate) found the ground where the
    /// estimate projects (`at_estimate`), or found something else: where the ground shows in most
    /// of the last images, the target is elsewhere (the estimate followed a box that had slid off
    /// it, or stereo put it short from afar), and only locations agreeing with the estimate would
    /// ever be let in. Doubted (`doubt_range_fraction` of its range from the `camera`), it lets
    /// the target's own locations take it over.
    pub(super) fn doubt_on_ground(
        &mut self,
        ctx: &mut Ctx<'_>,
        stamp: Time,
        camera: &Point3<f64>,
        at_estimate: bool,
    ) {
        self.ground_history =
            ((self.ground_history << 1) | u32::from(at_estimate)) & ((1 << GROUND_WINDOW) - 1);
        if self.ground_history.count_ones() < GROUND_TO_DOUBT || self.params.doubt_range_fraction <= 0.0 {
            return;
        }
        self.ground_history = 0;
        let range = self.estimate.position_at(stamp).map_or(0.0, |e| (e - camera).norm());
        let sigma = self.params.doubt_range_fraction * range;
        self.estimate.widen(sigma);
        ctx.note(format!(
            "the {} estimate's place showed the ground in {GROUND_TO_DOUBT} of the last {GROUND_WINDOW} images it was looked at in: doubted by {sigma:.1} m",
            self.target
        ));
    }

    /// Once a search where the established estimate projects has lasted `redetect_whole_after_s`
    /// without finding the target, the estimate is suspect (the whole image is searched): it is
    /// doubted along the line of sight from the `camera`, by `doubt_lost_fraction` of its range,
    /// so that the target's re-detection, metres from a wrong estimate along that line, agrees
    /// with it. (An estimate stuck on look-alikes' locations metres short otherwise rejects the
    /// target's own locations, then every re-detection of it, until `locate` gives up: sweep run
    /// 7.) A prior after a `reject` is not doubted: it spans the ranges the target may be at. The
    /// trade-offs: the line is the current camera's, not those of the views that located the
    /// estimate (near enough once the rover drives at the target); a look-alike on it within the
    /// widened gate is let in as the target would be; the published covariance grows with it.
    pub(super) fn doubt_when_lost(&mut self, ctx: &mut Ctx<'_>, stamp: Time, camera: &Point3<f64>) {
        let fraction = self.params.doubt_lost_fraction;
        let established = self.estimate.count() >= CONFIRM_AFTER && !self.prior_only;
        if fraction <= 0.0 || !established {
            return;
        }
        let Some(at) = self.estimate.position_at(stamp) else { return };
        if !self.searched_lost.doubt_due(self.params.redetect_whole_after_s) {
            return;
        }
        let sight = at - camera;
        let sigma = fraction * sight.norm();
        self.estimate.widen_along(sigma, &sight);
        ctx.note(format!(
            "the {} was searched for {:.0} s where its estimate projects and not found: the estimate is doubted by {sigma:.1} m along the line of sight",
            self.target,
            self.searched_lost.searched_s()
        ));
    }
}
