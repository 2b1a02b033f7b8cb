//! The names of the modules a scenario can configure, in the order the system registers them
//! (the system builds them; the scenario loader checks a scenario's tables against them).

/// Modules of the system a scenario runs, in registration order.
/// `cameras` is registered only when the scenario has a `[modules.cameras]` table (it renders); the
/// navigation chain (the ToF modules to the navigator) only with the cameras and a ToF rate; visual
/// odometry only with the cameras and a localization stereo rate; the head camera's trackers only
/// with the cameras and a head stereo rate; the wrist camera's marker tracker with the cameras (it
/// sees images once a plan or the scenario gives the wrist camera a rate; it is off by default), and
/// the manipulator and its coordinator with it (they grasp under the wrist camera's view).
pub const MODULES: &[&str] = &[
    "localization_mechanical",
    "localization_inertial",
    "locomotion",
    "arm",
    "ptu",
    "gripper",
    "cameras",
    "localization_visual",
    "localization_fusion",
    "tracking_marker",
    "tracking_marker_wrist",
    "tracking_target",
    "perception_tof",
    "perception_fusion",
    "traversability",
    "path_planning",
    "navigator",
    "visual_tracking",
    "manipulator_control",
    "manipulation",
    "autonomy",
    framework::debugger::NAME,
    crate::faults::NAME,
];
