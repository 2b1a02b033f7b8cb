//! # twin: the simulator half of the digital twin
//!
//! Will hold the rapier3d world (terrain heightfield, rocks, the rover with its suspension, 6-DoF arm,
//! gripper, pan-tilt unit and the sample canister), the headless wgpu sensors (stereo cameras,
//! Time-of-Flight cameras), the IMU and encoder models, and the Dry-Run implementations of the
//! framework's HAL device traits. It owns ground truth, which flows only to the logger and the scorer.
//!
//! Status: skeleton. Nothing is simulated yet; the physics and the dry-run HAL arrive with the twin
//! issue, the rendered sensors with their own issue. Depends on `framework` only, never on `gnc`.
