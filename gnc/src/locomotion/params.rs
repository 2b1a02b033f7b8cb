//! Locomotion's parameters and the arguments of its commands.

use super::Sense;
use serde::{Deserialize, Serialize};

/// Locomotion parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LocomotionParams {
    /// Cruise speed of `goto`, m/s (clamped to the locomotor's limit).
    pub speed: f64,
    /// Largest yaw rate used, rad/s (clamped to the locomotor's limit).
    pub max_yaw_rate: f64,
    /// Speed change limit, m/s^2.
    pub accel: f64,
    /// Heading gain of `goto` and `turn_to`, 1/s.
    pub heading_gain: f64,
    /// `goto` (and `follow_path`) turns in place while the goal (the lookahead point) is more
    /// than this off the heading, degrees.
    pub turn_in_place_deg: f64,
    /// Arrival tolerance of `goto`, m.
    pub goal_tolerance_m: f64,
    /// Heading tolerance of `turn_to`, degrees.
    pub heading_tolerance_deg: f64,
    /// Lookahead distance of `follow_path`, m.
    pub lookahead_m: f64,
    /// Integral gain of `follow_path` on the cross-track error, rad/s per m s.
    pub cross_track_gain_i: f64,
    /// `follow_path` slows down in proportion where the path's clearance is below this, m.
    pub slow_clearance_m: f64,
    /// Slowest cruise speed of `follow_path` (near obstacles), m/s.
    pub min_speed: f64,
    /// A wheel turning at less than this fraction of its commanded rate is stalling.
    pub stall_rate_fraction: f64,
    /// Commanded wheel rates below this are not checked for stalls, rad/s.
    pub stall_min_rate: f64,
    /// How long a wheel may stall before the module stops the rover, s.
    pub stall_time_s: f64,
    /// Tightest arc `follow_path` drives, 1/m (0: no limit): a skid-steer rover cannot skid round
    /// arcs much tighter than its track on slopes (the inner wheels pivot, the outer ones stall).
    /// Where pure pursuit's arc (judged at a lookahead of at least `lookahead_m`) is tighter, it
    /// turns in place until the arc is within half of this; its yaw rate never exceeds this times
    /// its speed otherwise.
    pub max_curvature: f64,
    /// The obstacle guard's footprint: half the rover's length and half its width about
    /// `base_link` (the wheels' outer faces), m; [0, 0] turns the guard off.
    pub guard_half_extents_m: [f64; 2],
    /// The gap the guard keeps between that footprint and an obstacle cell's centre, m.
    pub guard_margin_m: f64,
    /// A turn in place the guard refuses where the rover stands first drives straight, the
    /// shortest way (backwards on a tie), up to this far to where it is clear, m (0: refused).
    pub guard_room_m: f64,
}

impl Default for LocomotionParams {
    fn default() -> Self {
        LocomotionParams {
            speed: 0.3,
            max_yaw_rate: 0.4,
            accel: 0.5,
            heading_gain: 1.5,
            turn_in_place_deg: 35.0,
            goal_tolerance_m: 0.15,
            heading_tolerance_deg: 2.0,
            lookahead_m: 0.6,
            cross_track_gain_i: 0.3,
            slow_clearance_m: 1.0,
            min_speed: 0.08,
            stall_rate_fraction: 0.2,
            stall_min_rate: 0.5,
            stall_time_s: 1.0,
            max_curvature: 0.0,
            guard_half_extents_m: [0.0, 0.0],
            guard_margin_m: 0.05,
            guard_room_m: 0.0,
        }
    }
}

/// Arguments of `drive`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveArgs {
    /// Forward speed, m/s.
    pub v: f64,
    /// Yaw rate, rad/s.
    #[serde(default)]
    pub omega: f64,
    /// How long, s.
    pub duration_s: f64,
}

/// Arguments of `goto`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GotoArgs {
    /// Goal x in the pose estimate's frame, m.
    pub x: f64,
    /// Goal y, m.
    pub y: f64,
    /// Cruise speed, m/s (default: the configured one).
    #[serde(default)]
    pub speed: Option<f64>,
    /// Arrival tolerance, m (default: the configured one).
    #[serde(default)]
    pub tolerance_m: Option<f64>,
}

/// Arguments of `turn_to`: one of the two.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TurnToArgs {
    /// Goal heading in the pose estimate's frame, degrees.
    #[serde(default)]
    pub yaw_deg: Option<f64>,
    /// A point of the pose estimate's frame (x, y, m) to face, from where the estimate puts the
    /// rover when the command arrives (a surveyed landmark to look at).
    #[serde(default)]
    pub facing: Option<[f64; 2]>,
}

/// Arguments of `follow_path`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FollowPathArgs {
    /// Waypoints (x, y) in the pose estimate's frame, m, from (about) the rover to the goal.
    pub points: Vec<[f64; 2]>,
    /// Per waypoint, the clearance to the nearest obstacle, m (default: no slowing).
    #[serde(default)]
    pub clearance_m: Option<Vec<f64>>,
    /// Cruise speed, m/s (default: the configured one).
    #[serde(default)]
    pub speed: Option<f64>,
    /// Arrival tolerance at the last point, m (default: the configured one).
    #[serde(default)]
    pub tolerance_m: Option<f64>,
    /// Its first turn in place goes only this way round (default: the shorter way), the long way
    /// if need be (a turn far off the heading, over `turn_in_place_deg`): after a turn that
    /// stalled a wheel one way there, the way round that loads the wheels differently.
    #[serde(default)]
    pub pivot: Option<Sense>,
    /// Tightest arc driven along this path, 1/m (0: no limit; default: the configured
    /// `max_curvature`; with both set, the tighter): the navigator asks for one after a wheel
    /// stalled driving forward.
    #[serde(default)]
    pub max_curvature: Option<f64>,
}
