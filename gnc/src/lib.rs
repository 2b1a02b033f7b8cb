//! # gnc: guidance, navigation and control modules
//!
//! Will hold the mission's module set (seed 000, section 8): perception from ToF elevation maps,
//! traversability, path planning, locomotion, wheel/inertial/visual odometry and their fusion,
//! target and marker tracking, manipulator control with visual servoing, the coordinators and autonomy.
//!
//! Status: skeleton. GNC code sees the world only through the framework's HAL and blackboard; this
//! crate never depends on `twin` and never reads ground truth.
