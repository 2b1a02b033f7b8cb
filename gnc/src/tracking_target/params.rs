//! TrackingTarget's parameters and command arguments.

use crate::tracking::locate::LocateParams;
use crate::tracking::template::TrackerParams;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// TrackingTarget parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackingTargetParams {
    /// The image tracker's.
    pub tracker: TrackerParams,
    /// The stereo locate's.
    pub locate: LocateParams,
    /// Rectified pairs kept to start on a selection's own image.
    pub held_images: usize,
    /// The target's wander between images (random walk), m per sqrt(s): 0 for a static target.
    pub target_walk: f64,
    /// Fastest the target may move, m/s: 0 for a static target. Above 0, its velocity is fitted to
    /// the locations of the last `velocity_window_s` and the search for it in a new image is
    /// where that carries the estimate.
    pub max_target_speed_mps: f64,
    /// Locations fitted for the velocity, s back from the newest.
    pub velocity_window_s: f64,
    /// The velocity carries the estimate at most this long past its newest location, s (a target
    /// unseen longer may have stopped or turned; its wander then says how far it may be).
    pub velocity_horizon_s: f64,
    /// A location further than this many sigmas from the estimate is rejected (a wrong match).
    pub gate_sigma: f64,
    /// The same for a box re-detected after a loss, where a look-alike is likeliest: one such
    /// location must not carry an established estimate off.
    pub redetect_gate_sigma: f64,
    /// Fuse each location with the covariance it has at the depth where the estimate lies, not
    /// at its own (gated at its own): taken at their own depths, the locations that disparity noise
    /// puts nearer count for more and the estimate ends short, 1.9 m at 20 m (see
    /// `Located::at_depth`). Off by default; the mission's configuration turns it on (there, a rock
    /// in front of the canister on its line of sight took visual_approach's estimate over without).
    pub fuse_at_estimate_depth: bool,
    /// A location whose box shows a surface tilted less than this from level is a patch of the
    /// ground, not a target standing on it, and is rejected (a tracker's box slid off the target
    /// onto the ground in front of it finds the ground there, and the estimate follows it),
    /// degrees; -90: never (the default for now: see the mission's configuration). The tilt is
    /// the row profile's (`Located::surface_tilt`), taken `ground_tilt_sigmas` of its uncertainty
    /// towards upright: a profile that cannot tell (a box of a few rows) rejects nothing.
    pub ground_tilt_deg: f64,
    /// See `ground_tilt_deg`.
    pub ground_tilt_sigmas: f64,
    /// Where the estimate's place shows the ground (`ground_tilt_deg`) in most of the last
    /// images, the target may be elsewhere: the estimate's uncertainty grows by this fraction of
    /// its range (1 sigma, each way), and a location where the target is can take it over. Each
    /// time again if the ground keeps showing; a location of the target near the estimate shrinks
    /// it back. 0: never (the default for now: see the mission's configuration).
    pub doubt_range_fraction: f64,
    /// A target searched for where its established estimate projects for `redetect_whole_after_s`
    /// and not found there: the estimate is suspect, and the whole image is searched; its
    /// uncertainty along the line of sight (where stereo from afar errs: metres short or long)
    /// then grows by this fraction of its range (1 sigma), once a search, so that the target's own
    /// re-detection is not rejected by the wrong estimate it is searched with. 0: never.
    pub doubt_lost_fraction: f64,
    /// `locate` fails when the target has been lost this long, s.
    pub lost_timeout_s: f64,
    /// How long the pose and joint histories reach back, s (more than the camera's latency).
    pub history_s: f64,
    /// How far past the newest pose or joint sample an image may be placed, s.
    pub max_extrapolation_s: f64,
    /// Range assumed along the line of sight of a target not located yet (and not of a known
    /// size, whose selected box gives the range), m: where to look for it after the camera moved.
    pub sight_range_m: f64,
    /// A lost target with an established estimate is looked for only within `gate_sigma` of the
    /// estimate's projection, plus this many pixels (the box's own size is added).
    pub redetect_margin_px: f64,
    /// ... until it has been searched for there this long (time with the estimate out of view
    /// not counted), s; then over the whole image (the estimate may be what is wrong).
    pub redetect_whole_after_s: f64,
    /// Targets of known size, by the name a selection gives them: the smallest and the largest
    /// extent (m) the longer side of a box drawn around one spans, over the sides it may be seen
    /// from. The selected box's size then bounds the target's range from where it was selected:
    /// a location outside the bounds is a wrong match and is rejected (see
    /// [`crate::tracking::size::range_bounds`]). Not for a target that may move
    /// (`max_target_speed_mps` above 0) or a selected box cut by the image's border.
    pub known_sizes: BTreeMap<String, [f64; 2]>,
    /// The selected box's slack in those bounds (factors >= 1), towards the near bound and the
    /// far one (a loosely drawn box makes the target look nearer, never farther).
    pub size_tolerance: [f64; 2],
    /// A rejected object's place (`reject`): no location within this of it, horizontally, is
    /// the target, m (a rock's size, and its locations' scatter close by).
    pub reject_radius_m: f64,
    /// After a rejection, a target of unknown size is looked for this far along the selection's
    /// line of sight beyond the rejected object, m (one of known size, as far as its selected
    /// box allows).
    pub reject_search_m: f64,
}

impl Default for TrackingTargetParams {
    fn default() -> Self {
        TrackingTargetParams {
            tracker: TrackerParams::default(),
            locate: LocateParams::default(),
            held_images: 8,
            target_walk: 0.01,
            max_target_speed_mps: 0.0,
            velocity_window_s: 20.0,
            velocity_horizon_s: 10.0,
            gate_sigma: 3.5,
            redetect_gate_sigma: 2.5,
            fuse_at_estimate_depth: false,
            ground_tilt_deg: -90.0,
            ground_tilt_sigmas: 2.0,
            doubt_range_fraction: 0.0,
            doubt_lost_fraction: 0.0,
            lost_timeout_s: 20.0,
            history_s: 4.0,
            max_extrapolation_s: 0.15,
            sight_range_m: 20.0,
            redetect_margin_px: 16.0,
            redetect_whole_after_s: 10.0,
            known_sizes: BTreeMap::new(),
            size_tolerance: [1.25, 1.5],
            reject_radius_m: 1.0,
            reject_search_m: 10.0,
        }
    }
}

/// Arguments of `select`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SelectArgs {
    /// The box in the raw left image, pixels: [u_min, v_min, u_max, v_max].
    pub bbox: [f64; 4],
    /// Capture time of the image it was drawn in, s (default: the newest held image).
    #[serde(default)]
    pub image_stamp_s: Option<f64>,
    /// What the target is.
    #[serde(default)]
    pub target: Option<String>,
}

/// Arguments of `reject`.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RejectArgs {
    /// Where (`map`, m) the object found not to be the target was (the estimate someone acted
    /// on); default: the estimate now.
    #[serde(default)]
    pub position: Option<[f64; 3]>,
}

/// Arguments of `locate`.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocateArgs {
    /// Horizontal 1-sigma the position must reach, m (default 0.5).
    #[serde(default)]
    pub max_sigma_m: Option<f64>,
}

impl TrackingTargetParams {
    /// Checks the parameters: a clear error naming the first one out of range.
    pub fn validate(&self) -> Result<(), String> {
        let p = self;
        crate::params::require_positive(&[
            ("held_images", p.held_images as f64),
            ("gate_sigma", p.gate_sigma),
            ("redetect_gate_sigma", p.redetect_gate_sigma),
            ("lost_timeout_s", p.lost_timeout_s),
            ("history_s", p.history_s),
            ("sight_range_m", p.sight_range_m),
            ("redetect_margin_px", p.redetect_margin_px),
            ("redetect_whole_after_s", p.redetect_whole_after_s),
            ("reject_radius_m", p.reject_radius_m),
            ("reject_search_m", p.reject_search_m),
            ("velocity_window_s", p.velocity_window_s),
            ("velocity_horizon_s", p.velocity_horizon_s),
            ("tracker.track_threshold", p.tracker.track_threshold),
            ("tracker.redetect_threshold", p.tracker.redetect_threshold),
            ("locate.disparity_sigma_px", p.locate.disparity_sigma_px),
        ])?;
        if p.redetect_gate_sigma > p.gate_sigma {
            return Err(format!(
                "redetect_gate_sigma ({}) must not exceed gate_sigma ({})",
                p.redetect_gate_sigma, p.gate_sigma
            ));
        }
        if p.tracker.scales.is_empty() || p.tracker.redetect_scales.is_empty() {
            return Err("tracker.scales and tracker.redetect_scales must not be empty".into());
        }
        if p.tracker.template_cells < 8 || p.tracker.max_templates < 2 {
            return Err("tracker.template_cells must be >= 8 and tracker.max_templates >= 2".into());
        }
        if p.locate.min_points == 0 || p.locate.max_samples == 0 || p.locate.half_window > 15 {
            return Err(
                "locate.min_points and locate.max_samples must be >= 1, locate.half_window <= 15".into()
            );
        }
        if !(p.tracker.context_weight > 0.0 && p.tracker.context_weight <= 1.0) {
            return Err(format!(
                "tracker.context_weight must be in (0, 1], got {}",
                p.tracker.context_weight
            ));
        }
        if !(p.tracker.anchor_rescale.is_finite() && p.tracker.anchor_rescale > 1.0) {
            return Err(format!(
                "tracker.anchor_rescale must be a factor above 1, got {} (at 1 the anchor would be retaken every frame)",
                p.tracker.anchor_rescale
            ));
        }
        if !(p.tracker.model_rate > 0.0 && p.tracker.model_rate <= 1.0) {
            return Err(format!("tracker.model_rate must be in (0, 1], got {}", p.tracker.model_rate));
        }
        if !(p.ground_tilt_deg.is_finite() && (-90.0..90.0).contains(&p.ground_tilt_deg)) {
            return Err(format!("ground_tilt_deg must be in [-90, 90) degrees, got {}", p.ground_tilt_deg));
        }
        if !(p.ground_tilt_sigmas.is_finite() && p.ground_tilt_sigmas >= 0.0) {
            return Err(format!("ground_tilt_sigmas must be >= 0, got {}", p.ground_tilt_sigmas));
        }
        for (k, v) in
            [("doubt_range_fraction", p.doubt_range_fraction), ("doubt_lost_fraction", p.doubt_lost_fraction)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{k} must be >= 0, got {v}"));
            }
        }
        if !(p.max_target_speed_mps.is_finite() && p.max_target_speed_mps >= 0.0) {
            return Err(format!("max_target_speed_mps must be >= 0, got {}", p.max_target_speed_mps));
        }
        if !(p.target_walk.is_finite() && p.target_walk >= 0.0) {
            return Err(format!("target_walk must be >= 0, got {}", p.target_walk));
        }
        if !(p.max_extrapolation_s.is_finite() && p.max_extrapolation_s >= 0.0) {
            return Err(format!("max_extrapolation_s must be >= 0, got {}", p.max_extrapolation_s));
        }
        if !p.size_tolerance.iter().all(|k| k.is_finite() && *k >= 1.0) {
            return Err(format!("size_tolerance must be two factors >= 1, got {:?}", p.size_tolerance));
        }
        for (name, e) in &p.known_sizes {
            if !e.iter().all(|v| v.is_finite() && *v > 0.0) {
                return Err(format!("known_sizes.{name} must be two positive extents in m, got {e:?}"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_defaults_pass_and_a_tracker_out_of_range_is_named() {
        assert_eq!(TrackingTargetParams::default().validate(), Ok(()));
        let with = |f: fn(&mut TrackerParams)| {
            let mut p = TrackingTargetParams::default();
            f(&mut p.tracker);
            p.validate().unwrap_err()
        };
        assert!(with(|t| t.anchor_rescale = 1.0).contains("tracker.anchor_rescale"));
        assert!(with(|t| t.anchor_rescale = f64::NAN).contains("tracker.anchor_rescale"));
        assert!(with(|t| t.context_weight = 0.0).contains("tracker.context_weight"));
        assert!(with(|t| t.model_rate = 1.5).contains("tracker.model_rate"));
    }
}
