//! Manipulation data (seed 000, 8.3): what the manipulator is doing.

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// The manipulator's state: its command, where the command is, the tool's pose and what it holds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ManipulationState {
    /// The command in progress (`move_named`, `move_tool`, `grasp`, `place`, `open`, `close`).
    pub command: Option<String>,
    /// What it waits for: `idle`, `arm move`, `gripper move`, `recover` (a joint group's motors
    /// out of fault), `view` (an image of the object at rest).
    pub step: String,
    /// The tool centre point in `base_link` by the believed kinematics, m.
    pub tool_in_base: Option<Isometry3<f64>>,
    /// The object kind the gripper holds.
    pub holding: Option<String>,
    /// Visual-servoing steps of the grasp in progress.
    pub servo_steps: u32,
    /// The servo's last measured distance from the pre-grasp pose, m.
    pub servo_error_m: Option<f64>,
    /// How the last command ended.
    pub last_outcome: Option<String>,
}
