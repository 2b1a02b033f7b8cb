//! The manipulation algorithms (seed 000, 8.3), apart from the module that runs them
//! ([`crate::manipulator_control::ManipulatorControl`]) so each is tested alone:
//! [`kinematics`] (the arm on the believed mechanism: forward and inverse kinematics, grasps from
//! above), [`clearance`] (the arm and what it holds kept clear of the rover's body and the ground),
//! [`trajectory`] (paths through via-poses, segment timing within speed and acceleration limits)
//! and [`servo`] (position-based visual servoing, eye-in-hand).

pub mod clearance;
pub mod kinematics;
pub mod servo;
pub mod trajectory;
