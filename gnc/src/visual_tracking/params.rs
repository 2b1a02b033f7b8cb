//! CoordinatorVisualTracking's parameters (its configuration file's `[params]`) and the arguments
//! of its commands.

use serde::{Deserialize, Serialize};

/// CoordinatorVisualTracking parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VisualTrackingParams {
    /// The pan-tilt unit is re-commanded at most this often, s.
    pub command_period_s: f64,
    /// ... and only when the aim moved more than this, rad.
    pub deadband_rad: f64,
    /// Pan-tilt speed of the pursuit, fraction of the joints' limits.
    pub ptu_speed: f64,
    /// Range assumed along the line of sight before stereo ranged the target, m.
    pub sight_range_m: f64,
    /// Default accuracy `locate` is asked for (1 sigma, horizontal), m.
    pub max_sigma_m: f64,
    /// Approach-and-track legs: the accuracy asked before a leg, as a fraction of the distance.
    pub leg_sigma_fraction: f64,
    /// A leg ends at this fraction of the distance to the target ...
    pub leg_fraction: f64,
    /// ... and at most this far from where it starts, m.
    pub max_leg_m: f64,
    /// The approach's goal lies at this fraction of the boundary from the target.
    pub standoff_fraction: f64,
    /// No leg ends nearer the target's estimate than this, m: where the rover, turning in place to
    /// face it, could touch it (the rover's circumscribed radius and the target's half-width) ...
    pub clearance_m: f64,
    /// ... plus this many sigmas of the estimate's uncertainty along the line to it.
    pub clearance_sigmas: f64,
    /// Arrival tolerance of an intermediate leg, m.
    pub leg_tolerance_m: f64,
    /// Most legs of one `point_locate_approach_track`, most times it locates again after facing
    /// the target outside the boundary, and most times an approach sharpens an estimate too
    /// uncertain to come nearer clear of the target.
    pub max_legs: u32,
    /// Longest wait for TrackingTarget to locate the target to the asked accuracy, s.
    pub locate_timeout_s: f64,
    /// A far target (a leg's accuracy asked) still tracked but not located to it after this long
    /// (a few pixels wide, stereo cannot range it well enough) is driven towards along its line of
    /// sight instead: a leg of `leg_fraction` of its assumed range (at most `max_leg_m`), s.
    pub bearing_after_s: f64,
    /// Longest wait for a target to be tracked at all when a command starts, s.
    pub target_wait_s: f64,
    /// An approach whose target, with its estimate this near the rover (m, where it would be in
    /// plain view and stereo locates it sharply; 0: never), is lost or not located to the asked
    /// accuracy within `locate_timeout_s`: the estimate followed a look-alike from afar that is not
    /// the target. TrackingTarget rejects it and looks again along the line of sight the target
    /// was selected on; found there, the approach goes on, once per command.
    pub reject_unseen_within_m: f64,
}

impl Default for VisualTrackingParams {
    fn default() -> Self {
        VisualTrackingParams {
            command_period_s: 0.5,
            deadband_rad: 0.01,
            ptu_speed: 0.5,
            sight_range_m: 20.0,
            max_sigma_m: 0.3,
            leg_sigma_fraction: 0.08,
            leg_fraction: 0.5,
            max_leg_m: 8.0,
            standoff_fraction: 0.8,
            clearance_m: 0.9,
            clearance_sigmas: 2.0,
            leg_tolerance_m: 0.5,
            max_legs: 10,
            locate_timeout_s: 90.0,
            bearing_after_s: 20.0,
            target_wait_s: 10.0,
            reject_unseen_within_m: 0.0,
        }
    }
}

/// Arguments of `point_locate`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointLocateArgs {
    /// Accuracy to locate to, 1 sigma, m (default: configured).
    #[serde(default)]
    pub max_sigma_m: Option<f64>,
}

/// Arguments of `point_locate_approach`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApproachArgs {
    /// The rover stops within this distance of the target, m.
    pub boundary_m: f64,
    /// Accuracy to locate to before approaching, 1 sigma, m (default: configured).
    #[serde(default)]
    pub max_sigma_m: Option<f64>,
}

/// Arguments of `point_locate_approach_track`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApproachTrackArgs {
    /// The loop ends within this distance of the target, m.
    pub max_distance_m: f64,
    /// Accuracy of the last locate, 1 sigma, m (default: configured).
    #[serde(default)]
    pub max_sigma_m: Option<f64>,
}
