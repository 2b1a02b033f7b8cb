//! CoordinatorManipulation's parameters (its configuration file's `[params]`).

use serde::{Deserialize, Serialize};

/// CoordinatorManipulation parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CoordinatorManipulationParams {
    /// The object kind acquired and stowed (as the marker tracker names it).
    pub object: String,
    /// The wrist camera's frame rate while acquiring, Hz.
    pub camera_hz: f64,
    /// The rover stands with the object this far from `base_link` (horizontally) to look at it, m.
    pub work_distance_m: f64,
    /// ... and moves there first when farther than this from it ...
    pub work_tolerance_m: f64,
    /// ... or when it is more than this off the heading, deg.
    pub max_bearing_deg: f64,
    /// The arm grasps an object whose centre lies within this box of `base_link` (x min, x max,
    /// largest |y|), m; elsewhere the rover moves first.
    pub grasp_region_m: [f64; 3],
    /// Where in that box the rover puts the object when it moves (x), m.
    pub grasp_x_m: f64,
    /// Accuracy the markers must locate the object to (1 sigma), m and deg.
    pub locate_sigma_m: f64,
    /// ... deg.
    pub locate_angle_deg: f64,
    /// The manipulator's poses the wrist camera looks from, tried in turn until one locates the
    /// object (the nearest view first).
    pub look_poses: Vec<String>,
    /// Longest wait for the markers to locate the object from one look pose, s.
    pub locate_timeout_s: f64,
    /// Grasps tried before the command fails.
    pub max_attempts: u32,
    /// Rover moves after looking before the command fails (the back-up search counts as one, and
    /// so does the move after a grasp the arm could not reach).
    pub max_repositions: u32,
    /// When no look pose saw anything of the object (it may lie nearer than the wrist camera's
    /// views reach, or beside them), the rover backs up this far once and looks again, m (0: never).
    pub search_back_m: f64,
    /// Before that, the manipulator's pose the wrist camera looks all round from while the rover
    /// turns a full circle in place, in quarter turns: an object beside or behind the rover (the
    /// head camera's estimate was of a rock beyond it) is glimpsed and gone to ("": no scan).
    pub scan_pose: String,
    /// A locate from a look pose ends early when the wrist camera has seen nothing of the object
    /// in this long since it began, s (0: it runs its `locate_timeout_s`).
    pub glimpse_timeout_s: f64,
    /// The manipulator's pose the arm takes before the rover's moves to the working distance, so
    /// that the wrist camera looks ahead on the way and a glimpse of the object elsewhere than the
    /// head camera's estimate is gone to ("": the arm stays where it is; folded in its stowed
    /// pose, the wrist camera looks at the ground beside a front wheel).
    pub travel_pose: String,
}

impl Default for CoordinatorManipulationParams {
    fn default() -> Self {
        CoordinatorManipulationParams {
            object: "canister".into(),
            camera_hz: 5.0,
            work_distance_m: 1.05,
            work_tolerance_m: 0.15,
            max_bearing_deg: 10.0,
            grasp_region_m: [0.85, 1.2, 0.2],
            grasp_x_m: 1.0,
            locate_sigma_m: 0.01,
            locate_angle_deg: 2.0,
            look_poses: vec!["look_near".into(), "look".into()],
            locate_timeout_s: 8.0,
            max_attempts: 3,
            max_repositions: 3,
            search_back_m: 0.35,
            scan_pose: "look".into(),
            glimpse_timeout_s: 3.0,
            travel_pose: String::new(),
        }
    }
}
