//! The Hardware Abstraction Layer (seed 000, 4.2; seed 004, "multi-level abstractions", "device maps").
//!
//! Device traits at several levels, independent of whether the device is real, simulated (the twin's
//! Dry-Run drivers) or replayed from a log. GNC modules hold devices behind these traits and never know
//! which implementation they got: a [`DeviceMap`] builds the set for an execution context.
//!
//! - [`Locomotor`]: body-level (a twist) and wheel-level (per-wheel rates) commands, and the
//!   [`LocomotorModel`] planners query without a locomotor.
//! - [`JointGroup`]: position-controlled joints (arm, pan-tilt unit, gripper) with the generic motor
//!   state machine of seed 004 (moving / not moving x servoing / not servoing, fault, recovering).
//!   Moves never block: [`JointGroup::move_to`] returns a [`MoveId`] at once, and the caller polls
//!   [`JointGroup::move_status`] for the fraction done (forward processing); waiting "until 45 % done"
//!   is a condition checked each cycle, in the framework clock's time.
//! - [`Imu`] and [`WheelEncoders`]: measurements stamped with the framework clock.
//!
//! Commanding a shared device takes its [`ReservationToken`]; reading does not.

use crate::resources::{ReservationError, ReservationToken};
use crate::time::Time;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Why a device refused or failed a request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeviceError {
    /// The caller does not hold a valid reservation of the device.
    #[error(transparent)]
    Reservation(#[from] ReservationError),
    /// The token is for another device.
    #[error("token for '{token}' cannot command '{device}'")]
    WrongToken {
        /// Device addressed.
        device: String,
        /// Device the token reserves.
        token: String,
    },
    /// The device is in its fault state.
    #[error("device '{device}' is in fault: {reason}")]
    Fault {
        /// Device.
        device: String,
        /// Fault description.
        reason: String,
    },
    /// The command is malformed or out of range.
    #[error("device '{device}': {reason}")]
    InvalidCommand {
        /// Device.
        device: String,
        /// What is wrong.
        reason: String,
    },
}

/// State of a controlled motor (seed 004, Fig. 5): two parallel state pairs, plus fault and
/// recovering states that override them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MotorStatus {
    /// The joint is moving (whatever the cause: command, gravity, contact).
    pub moving: bool,
    /// The servo loop is closed.
    pub servoing: bool,
    /// Set while the motor is in fault, with the reason.
    pub fault: Option<String>,
    /// Set while recovering from a fault.
    pub recovering: bool,
}

impl MotorStatus {
    /// A short name of the state: `FAULT`, `RECOVERING` or `MOVING|NOT_MOVING + SERVOING|NOT_SERVOING`.
    pub fn name(&self) -> String {
        if self.fault.is_some() {
            "FAULT".into()
        } else if self.recovering {
            "RECOVERING".into()
        } else {
            format!(
                "{}+{}",
                if self.moving { "MOVING" } else { "NOT_MOVING" },
                if self.servoing { "SERVOING" } else { "NOT_SERVOING" }
            )
        }
    }
}

/// Measured state of one joint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    /// Joint name (as in the robot description).
    pub name: String,
    /// Position, rad or m (wheels: accumulated angle).
    pub position: f64,
    /// Velocity, rad/s or m/s.
    pub velocity: f64,
    /// Effort, N m or N.
    pub effort: f64,
    /// Motor state.
    pub status: MotorStatus,
}

/// Limits of one joint.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointLimits {
    /// Lower position limit.
    pub lower: f64,
    /// Upper position limit.
    pub upper: f64,
    /// Velocity limit.
    pub velocity: f64,
    /// Effort limit.
    pub effort: f64,
}

/// Identity of a move commanded on a joint group.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct MoveId(pub u64);

/// Progress of a move.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum MoveStatus {
    /// Under way; `fraction` of the planned motion is done (0..1).
    InProgress {
        /// Fraction done.
        fraction: f64,
    },
    /// Reached its target within tolerance.
    Done,
    /// Replaced by a later move or stopped.
    Stopped,
    /// Failed (fault, blocked, timeout), with the reason.
    Failed(String),
    /// No such move.
    Unknown,
}

impl MoveStatus {
    /// Fraction of the move done: 1 when done, 0 when unknown, failed or stopped.
    pub fn fraction(&self) -> f64 {
        match self {
            MoveStatus::InProgress { fraction } => *fraction,
            MoveStatus::Done => 1.0,
            _ => 0.0,
        }
    }
    /// True when the move is done or at least `fraction` of it is (seed 004's wait_until_done(%)).
    pub fn reached(&self, fraction: f64) -> bool {
        matches!(self, MoveStatus::Done) || self.fraction() >= fraction
    }
    /// True for a move that will not progress any more.
    pub fn is_over(&self) -> bool {
        !matches!(self, MoveStatus::InProgress { .. })
    }
}

/// Position-controlled joints moved together: an arm, a pan-tilt unit, a gripper.
///
/// Drivers may have a deadman: a group whose software has sent nothing (a command or a
/// [`JointGroup::keep_alive`]) for the driver's deadman time holds its joints where they are and
/// ends its move as stopped, so that a module that dies mid-move does not leave the arm moving.
pub trait JointGroup: Send {
    /// Device name (also its reservation name).
    fn device(&self) -> &str;
    /// Joint names, in the order of every vector this trait takes and returns.
    fn joint_names(&self) -> Vec<String>;
    /// Joint limits.
    fn limits(&self) -> Vec<JointLimits>;
    /// Measured states.
    fn states(&self) -> Vec<JointState>;
    /// Starts a move to `targets`, at `speed` (a fraction of each joint's velocity limit, (0, 1]).
    /// Returns at once; a new move replaces the one under way.
    fn move_to(
        &mut self,
        token: &ReservationToken,
        targets: &[f64],
        speed: f64,
    ) -> Result<MoveId, DeviceError>;
    /// Progress of a move.
    fn move_status(&self, id: MoveId) -> MoveStatus;
    /// Stops where it is (holding position).
    fn stop(&mut self, token: &ReservationToken) -> Result<(), DeviceError>;
    /// Leaves the fault state (through RECOVERING) and servos at the present position.
    fn recover(&mut self, token: &ReservationToken) -> Result<(), DeviceError>;
    /// Tells the driver that the software commanding the group is alive (call it every cycle while
    /// holding the group; a driver without a deadman ignores it).
    fn keep_alive(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        let _ = token;
        Ok(())
    }
    /// Measured joint positions.
    fn positions(&self) -> Vec<f64> {
        self.states().iter().map(|s| s.position).collect()
    }
}

/// A body-frame velocity command for a rover (frame `base_link`: x forward, z up).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BodyTwist {
    /// Forward speed, m/s.
    pub v: f64,
    /// Yaw rate, rad/s (counter-clockwise seen from above).
    pub omega: f64,
}

/// What the rover's locomotion can do, for planners (seed 004, "separate models from control").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocomotorModel {
    /// Wheel joint names, in wheel-vector order.
    pub wheels: Vec<String>,
    /// Wheel centres in `base_link`, m.
    pub wheel_positions: Vec<Point3<f64>>,
    /// Wheel radius, m.
    pub wheel_radius: f64,
    /// Distance between left and right wheel centres, m.
    pub track: f64,
    /// Distance between front and rear axles, m.
    pub wheelbase: f64,
    /// Largest wheel rate, rad/s.
    pub max_wheel_rate: f64,
    /// Largest wheel torque, N m.
    pub max_wheel_torque: f64,
    /// Largest forward speed, m/s.
    pub max_speed: f64,
    /// Largest yaw rate, rad/s.
    pub max_yaw_rate: f64,
    /// Steepest slope the rover may be commanded onto, rad.
    pub max_slope: f64,
    /// Highest step (rock) it may drive over, m.
    pub max_step: f64,
    /// Belly clearance, m.
    pub ground_clearance: f64,
    /// Total mass, kg.
    pub mass: f64,
}

impl LocomotorModel {
    /// Wheel rates (rad/s, wheel order) that realize a body twist with skid steering; `None` when the
    /// twist is beyond the rover's limits.
    pub fn wheel_rates(&self, cmd: BodyTwist) -> Option<Vec<f64>> {
        if cmd.v.abs() > self.max_speed + 1e-12 || cmd.omega.abs() > self.max_yaw_rate + 1e-12 {
            return None;
        }
        let rates: Vec<f64> =
            self.wheel_positions.iter().map(|p| (cmd.v - cmd.omega * p.y) / self.wheel_radius).collect();
        rates.iter().all(|r| r.abs() <= self.max_wheel_rate + 1e-9).then_some(rates)
    }
    /// The body twist that wheel rates would give on firm ground without slip (least squares).
    pub fn body_twist(&self, rates: &[f64]) -> BodyTwist {
        let n = rates.len().min(self.wheel_positions.len()) as f64;
        let speed = |r: &f64| r * self.wheel_radius;
        let mean_v = rates.iter().map(speed).sum::<f64>() / n;
        let mean_y = self.wheel_positions.iter().map(|p| p.y).sum::<f64>() / n;
        let (mut sxy, mut syy) = (0.0, 0.0);
        for (r, p) in rates.iter().zip(&self.wheel_positions) {
            sxy += (p.y - mean_y) * (speed(r) - mean_v);
            syy += (p.y - mean_y).powi(2);
        }
        let omega = if syy > 0.0 { -sxy / syy } else { 0.0 };
        BodyTwist { v: mean_v + omega * mean_y, omega }
    }
    /// True when a slope (rad) is within the rover's limit.
    pub fn can_climb(&self, slope: f64) -> bool {
        slope <= self.max_slope
    }
}

/// Rover locomotion.
///
/// Drivers may have a deadman: wheels commanded to turn stop when no fresh command (`drive`,
/// `set_wheel_rates`, `stop`) comes within the driver's deadman time, so the commanding module
/// sends one every cycle.
pub trait Locomotor: Send {
    /// Device name (also its reservation name).
    fn device(&self) -> &str;
    /// The locomotor model.
    fn model(&self) -> &LocomotorModel;
    /// Body-level command.
    fn drive(&mut self, token: &ReservationToken, cmd: BodyTwist) -> Result<(), DeviceError>;
    /// Wheel-level command, rad/s per wheel.
    fn set_wheel_rates(&mut self, token: &ReservationToken, rates: &[f64]) -> Result<(), DeviceError>;
    /// Stops the wheels (holding).
    fn stop(&mut self, token: &ReservationToken) -> Result<(), DeviceError>;
}

/// A wheel encoder reading: what the motors turned, slip included.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EncoderReading {
    /// Capture time: when the counts were latched (the reading arrives later, after the
    /// device's latency).
    pub stamp: Time,
    /// Wheel joint names.
    pub wheels: Vec<String>,
    /// Accumulated wheel angles, rad: whole encoder counts times the angle of one count.
    pub angles: Vec<f64>,
    /// Wheel rates, rad/s: the count difference over the last sample period (so they step in
    /// counts too, and lag the true rate by half a period).
    pub rates: Vec<f64>,
}

/// Wheel encoders.
pub trait WheelEncoders: Send {
    /// The newest reading available now; None before the first one has arrived.
    fn read(&mut self) -> Option<EncoderReading>;
}

/// An inertial measurement in the IMU frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImuSample {
    /// Capture time: the end of the interval the sample averages over.
    pub stamp: Time,
    /// Specific force (acceleration minus gravity), m/s^2, frame `imu_link`. At rest it points up.
    pub specific_force: Vector3<f64>,
    /// Angular rate, rad/s, frame `imu_link`.
    pub angular_rate: Vector3<f64>,
}

/// An inertial measurement unit. Each handle is a reader of its own: every reader gets every
/// sample, and two readers get the same samples.
pub trait Imu: Send {
    /// Every sample that has arrived since this reader's last call, oldest first (empty when none
    /// has). A reader that falls far behind loses the oldest samples (the device's buffer is
    /// bounded); their absence shows as a gap in the stamps.
    fn read(&mut self) -> Vec<ImuSample>;
    /// Sample period, s.
    fn period(&self) -> f64;
}

/// Builds the devices of a robot for an execution context (seed 004's abstract-factory device map):
/// the Dry-Run map binds them to the twin, an Operative map would bind real drivers.
pub trait DeviceMap {
    /// Which context the devices belong to.
    fn mode(&self) -> crate::exec_context::Mode;
    /// The locomotion.
    fn locomotor(&self) -> Result<Box<dyn Locomotor>, DeviceError>;
    /// The wheel encoders.
    fn encoders(&self) -> Result<Box<dyn WheelEncoders>, DeviceError>;
    /// The IMU.
    fn imu(&self) -> Result<Box<dyn Imu>, DeviceError>;
    /// A joint group by name (`arm`, `ptu`, `gripper`).
    fn joint_group(&self, name: &str) -> Result<Box<dyn JointGroup>, DeviceError>;
    /// A stereo camera by name (`head_stereo`, `loc_stereo`).
    fn stereo_camera(&self, name: &str) -> Result<Box<dyn StereoCamera>, DeviceError>;
    /// A Time-of-Flight camera by name (`tof_left`, `tof_right`).
    fn tof_camera(&self, name: &str) -> Result<Box<dyn TofCamera>, DeviceError>;
    /// A single camera by name (`wrist_camera`).
    fn mono_camera(&self, name: &str) -> Result<Box<dyn MonoCamera>, DeviceError>;
    /// The robot's mechanism model as its calibration gives it (joint zero offsets and link lengths
    /// as measured, which differ from the hardware's by the calibration error).
    fn mechanism(&self) -> Result<crate::mechanism::MechanismModel, DeviceError>;
}

/// Checks that `token` reserves `device` and is still valid.
pub fn check_token(
    resources: &crate::resources::Resources,
    device: &str,
    token: &ReservationToken,
) -> Result<(), DeviceError> {
    if token.device() != device {
        return Err(DeviceError::WrongToken { device: device.into(), token: token.device().into() });
    }
    resources.validate(token)?;
    Ok(())
}

/// A stereo camera pair. Its images are raw (distorted, unrectified); its calibration is what a
/// calibration file says of it, which is close to, but not, the truth.
pub trait StereoCamera: Send {
    /// Device name.
    fn device(&self) -> &str;
    /// The pair's calibration: each camera's intrinsics and distortion, the pair's extrinsics, the
    /// mounting.
    fn calibration(&self) -> &crate::camera::StereoCalibration;
    /// Sets the frame rate, Hz: at most the camera's own; 0 stops capturing.
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError>;
    /// The newest pair that has arrived since the last call, if any. Images carry their capture
    /// time; they arrive after the camera's latency.
    fn capture(
        &mut self,
    ) -> Result<Option<(crate::camera::GreyImage, crate::camera::GreyImage)>, DeviceError>;
}

/// A single camera (the wrist camera). Its images are raw (distorted); its calibration is what a
/// calibration file says of it (intrinsics, distortion, its mounting on its link).
pub trait MonoCamera: Send {
    /// Device name.
    fn device(&self) -> &str;
    /// The camera's calibration.
    fn calibration(&self) -> &crate::camera::CameraCalibration;
    /// Sets the frame rate, Hz: at most the camera's own; 0 stops capturing.
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError>;
    /// The newest image that has arrived since the last call, if any (stamped with its capture
    /// time; it arrives after the camera's latency).
    fn capture(&mut self) -> Result<Option<crate::camera::GreyImage>, DeviceError>;
}

/// A Time-of-Flight depth camera.
pub trait TofCamera: Send {
    /// Device name.
    fn device(&self) -> &str;
    /// The camera's calibration (intrinsics, mounting).
    fn calibration(&self) -> &crate::camera::CameraCalibration;
    /// Range limits, m.
    fn range_limits(&self) -> (f64, f64);
    /// Sets the frame rate, Hz: at most the camera's own; 0 stops capturing.
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError>;
    /// The newest frame that has arrived since the last call, if any (stamped with its capture
    /// time; it arrives after the camera's latency).
    fn capture(&mut self) -> Result<Option<crate::camera::TofFrame>, DeviceError>;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> LocomotorModel {
        LocomotorModel {
            wheels: vec!["fl".into(), "fr".into(), "rl".into(), "rr".into()],
            wheel_positions: vec![
                Point3::new(0.4, 0.5, -0.2),
                Point3::new(0.4, -0.5, -0.2),
                Point3::new(-0.4, 0.5, -0.2),
                Point3::new(-0.4, -0.5, -0.2),
            ],
            wheel_radius: 0.16,
            track: 1.0,
            wheelbase: 0.8,
            max_wheel_rate: 3.0,
            max_wheel_torque: 40.0,
            max_speed: 0.4,
            max_yaw_rate: 0.6,
            max_slope: 0.4,
            max_step: 0.2,
            ground_clearance: 0.25,
            mass: 160.0,
        }
    }

    #[test]
    fn skid_steer_kinematics_round_trip() {
        let m = model();
        let cmd = BodyTwist { v: 0.2, omega: 0.3 };
        let r = m.wheel_rates(cmd).unwrap();
        assert!((r[0] - (0.2 - 0.15) / 0.16).abs() < 1e-12 && (r[1] - (0.2 + 0.15) / 0.16).abs() < 1e-12);
        let back = m.body_twist(&r);
        assert!((back.v - 0.2).abs() < 1e-12 && (back.omega - 0.3).abs() < 1e-12);
        assert!(m.wheel_rates(BodyTwist { v: 1.0, omega: 0.0 }).is_none());
    }

    #[test]
    fn motor_state_names_and_move_fractions() {
        let mut s = MotorStatus { moving: true, servoing: true, ..Default::default() };
        assert_eq!(s.name(), "MOVING+SERVOING");
        s.fault = Some("overcurrent".into());
        assert_eq!(s.name(), "FAULT");
        assert!(MoveStatus::InProgress { fraction: 0.5 }.reached(0.45));
        assert!(!MoveStatus::InProgress { fraction: 0.4 }.reached(0.45));
        assert!(MoveStatus::Done.reached(1.0) && MoveStatus::Failed("x".into()).is_over());
    }
}
