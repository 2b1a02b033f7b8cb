//! ManipulatorControl's parameters (its configuration file's `[params]`) and the arguments of its
//! commands.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// How an object is grasped and held.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspableObject {
    /// The handle's centre in the object's frame (its bar along the frame's x), m.
    pub handle: [f64; 3],
    /// Half the handle bar's width across the fingers, m: where closing fingers stop on it.
    pub handle_half_width_m: f64,
    /// The object's bounding box in its frame: centre and half extents, m (a held object is kept
    /// clear of the body with it).
    pub box_center: [f64; 3],
    /// Half extents of that box, m.
    pub box_half: [f64; 3],
}

/// ManipulatorControl parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ManipulatorParams {
    /// Fastest joint motion, fraction of each joint's velocity limit (the profile's peak).
    pub speed: f64,
    /// Joint acceleration limit, rad/s^2.
    pub acceleration_rad_s2: f64,
    /// Named arm poses, joint values in the arm's order, rad.
    pub poses: BTreeMap<String, Vec<f64>>,
    /// Poses a motion may pass through when its straight path is blocked.
    pub vias: Vec<String>,
    /// Smallest gap between the arm (and what it holds) and the body, m.
    pub margin_m: f64,
    /// Smallest height of the arm above the wheels' ground plane, m.
    pub ground_margin_m: f64,
    /// Joint step between clearance checks along a path, rad.
    pub check_step_rad: f64,
    /// Finger position of an open gripper (each finger), m.
    pub open_m: f64,
    /// The pre-grasp pose is this far above the handle along the approach, m.
    pub pregrasp_height_m: f64,
    /// The descent onto the handle goes in steps of this length, m.
    pub descent_step_m: f64,
    /// After a grasp the object is lifted by this much, m.
    pub lift_m: f64,
    /// Share of the measured error each servo step corrects, (0, 1].
    pub servo_gain: f64,
    /// Longest translation of one servo step, m.
    pub servo_max_step_m: f64,
    /// The servo loop ends within this translation ...
    pub servo_tolerance_m: f64,
    /// ... and this rotation, deg ...
    pub servo_tolerance_deg: f64,
    /// ... leaving the tilt of the approach axis off the handle's normal as it is within this,
    /// deg: the marker's tilt seen face on is its weak part (degrees off, either way, from corner
    /// errors and the believed focal lengths), and the fingers take a handle tilted this much (the
    /// position and the turn about the axis are servoed to the tolerances above).
    pub servo_tilt_dead_band_deg: f64,
    /// Most servo steps of one grasp (0: none, an open-loop grasp from the first view, to measure
    /// what the servoing is worth).
    pub max_servo_steps: u32,
    /// The arm rests this long after a move before an image is taken as its view, s.
    pub settle_s: f64,
    /// A view of the object is the mean of this many images at rest (the marker pose's noise,
    /// millimetres and a degree at the pre-grasp pose, is the servo loop's floor).
    pub view_frames: u32,
    /// Longest wait for the wrist camera to see the object, s.
    pub observe_timeout_s: f64,
    /// An arm move is stopped once it runs this long past twice its planned duration, s ...
    pub move_slack_s: f64,
    /// ... and the motion goes on if the tool is within this of the move's goal by then (the
    /// servos hold a load a few milliradians off their goal), m (and ten times this in rad).
    pub arrive_tolerance_m: f64,
    /// Fingers stopped within this of the handle's half width hold it, m.
    pub grip_tolerance_m: f64,
    /// The held object is lowered into the slot from this far above its resting place, m.
    pub place_height_m: f64,
    /// A place's descent that stops (blocked) more than this above the object's resting place
    /// has not put it into the slot (it sits on a wall): it is tried again to the side
    /// (`seat_search_m`, `seat_tries`), then kept and the place fails, m. Within it, the object
    /// is let go there (the believed kinematics put the slot a little low).
    pub seat_tolerance_m: f64,
    /// A held object stopped on a wall is tried again this far to the side (the believed arm
    /// kinematics put the slot a few centimetres off), m ...
    pub seat_search_m: f64,
    /// ... in this many directions around (0: not tried again).
    pub seat_tries: u32,
    /// The pose the arm goes to after placing an object.
    pub after_place: String,
    /// Objects the manipulator can grasp, by kind (the object database's names).
    pub objects: BTreeMap<String, GraspableObject>,
}

impl Default for ManipulatorParams {
    fn default() -> Self {
        ManipulatorParams {
            speed: 0.6,
            acceleration_rad_s2: 2.0,
            poses: BTreeMap::new(),
            vias: Vec::new(),
            margin_m: 0.015,
            ground_margin_m: 0.05,
            check_step_rad: 0.02,
            open_m: 0.04,
            pregrasp_height_m: 0.12,
            descent_step_m: 0.02,
            lift_m: 0.12,
            servo_gain: 0.8,
            servo_max_step_m: 0.06,
            servo_tolerance_m: 0.003,
            servo_tolerance_deg: 1.5,
            servo_tilt_dead_band_deg: 6.0,
            max_servo_steps: 10,
            settle_s: 0.3,
            view_frames: 3,
            observe_timeout_s: 4.0,
            move_slack_s: 3.0,
            arrive_tolerance_m: 0.005,
            grip_tolerance_m: 0.004,
            place_height_m: 0.1,
            seat_tolerance_m: 0.02,
            seat_search_m: 0.03,
            seat_tries: 6,
            after_place: "stowed".into(),
            objects: BTreeMap::new(),
        }
    }
}

impl ManipulatorParams {
    /// Checks the values against each other and the arm (`limits` and `joint_names` in the arm's
    /// joint order).
    pub fn validate(&self, limits: &[(f64, f64)], joint_names: &[String]) -> Result<(), String> {
        crate::params::require_positive(&[
            ("speed", self.speed),
            ("acceleration_rad_s2", self.acceleration_rad_s2),
            ("margin_m", self.margin_m),
            ("check_step_rad", self.check_step_rad),
            ("open_m", self.open_m),
            ("pregrasp_height_m", self.pregrasp_height_m),
            ("descent_step_m", self.descent_step_m),
            ("lift_m", self.lift_m),
            ("servo_gain", self.servo_gain),
            ("servo_max_step_m", self.servo_max_step_m),
            ("servo_tolerance_m", self.servo_tolerance_m),
            ("servo_tolerance_deg", self.servo_tolerance_deg),
            ("settle_s", self.settle_s),
            ("observe_timeout_s", self.observe_timeout_s),
            ("move_slack_s", self.move_slack_s),
            ("arrive_tolerance_m", self.arrive_tolerance_m),
            ("grip_tolerance_m", self.grip_tolerance_m),
            ("place_height_m", self.place_height_m),
            ("view_frames", f64::from(self.view_frames)),
        ])?;
        if !(0.0..45.0).contains(&self.servo_tilt_dead_band_deg) {
            return Err(format!(
                "servo_tilt_dead_band_deg must be in [0, 45), got {}",
                self.servo_tilt_dead_band_deg
            ));
        }
        if self.speed > 1.0 || self.servo_gain > 1.0 {
            return Err(format!(
                "speed and servo_gain must be in (0, 1], got {} and {}",
                self.speed, self.servo_gain
            ));
        }
        for (name, q) in &self.poses {
            if q.len() != limits.len() {
                return Err(format!(
                    "pose '{name}' has {} values, the arm has {} joints",
                    q.len(),
                    limits.len()
                ));
            }
            if let Some((j, v)) =
                q.iter().enumerate().find(|(j, v)| !(limits[*j].0..=limits[*j].1).contains(*v))
            {
                return Err(format!("pose '{name}': {} = {v} outside its limits", joint_names[j]));
            }
        }
        if let Some(v) = self.vias.iter().find(|v| !self.poses.contains_key(*v)) {
            return Err(format!("via-pose '{v}' is not a configured pose"));
        }
        if !self.poses.contains_key(&self.after_place) {
            return Err(format!("after_place pose '{}' is not a configured pose", self.after_place));
        }
        Ok(())
    }
}

/// Arguments of `move_named`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MoveNamedArgs {
    /// The pose's name.
    pub pose: String,
}

/// Arguments of `move_tool`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MoveToolArgs {
    /// The tool centre point in `base_link`, m.
    pub position: [f64; 3],
    /// Its orientation, roll, pitch and yaw, deg.
    pub rpy_deg: [f64; 3],
}

/// Arguments of `grasp`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspArgs {
    /// The object kind (as the marker tracker names it).
    pub object: String,
}

/// Arguments of `place`.
#[derive(Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaceArgs {
    /// The link the object is placed on (default `stow_slot`).
    #[serde(default)]
    pub slot: Option<String>,
}
