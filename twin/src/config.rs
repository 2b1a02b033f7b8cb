//! Simulation parameters (`assets/rover/twin.toml`): physics, motor models, device noise.

use framework::config::{ConfigError, Source, read_file};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// All twin parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TwinConfig {
    /// Physics engine.
    pub physics: PhysicsConfig,
    /// Wheel motors.
    pub wheels: WheelConfig,
    /// Rocker suspension.
    pub suspension: SuspensionConfig,
    /// Position servos.
    pub servos: ServoConfig,
    /// Gripper.
    pub gripper: GripperConfig,
    /// Locomotor limits for planners.
    pub locomotor: LocomotorLimits,
    /// IMU model.
    pub imu: ImuConfig,
    /// Encoder model.
    pub encoders: EncoderConfig,
    /// How far what the robot's software is told (calibration files, models) is from the truth.
    pub calibration: CalibrationConfig,
    /// How each real camera differs from its nominal design.
    pub camera_build: CameraBuildConfig,
}

/// Physics engine parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsConfig {
    /// Step, s.
    pub dt_s: f64,
    /// Solver substeps.
    pub solver_iterations: usize,
    /// Gravity magnitude, m/s^2 (along -z of the world).
    pub gravity_m_s2: f64,
    /// Projected Gauss-Seidel iterations per substep: more make motors drive heavy loads firmly.
    pub pgs_iterations: usize,
    /// Friction model.
    pub friction_model: FrictionModelName,
    /// Solve friction in the position-correction (biased) pass too. Without it, the correction of
    /// the wheels' resting penetration meets no friction and a parked rover creeps (about 2 degrees
    /// of yaw and 2 cm in 20 s on flat ground).
    pub friction_in_bias_pass: bool,
    /// Cell size of the terrain's collision grid, m (the world's own when smaller).
    pub terrain_cell_m: f64,
    /// Kinematic fidelity: the skid-steer rover turns about a point this far ahead of `base_link`,
    /// m, as it does in full dynamics (its wheels slip about the loaded axle), so both fidelities
    /// move alike for the same wheel rates.
    pub kinematic_turn_center_x_m: f64,
}

/// rapier's friction models.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrictionModelName {
    /// One friction constraint per manifold plus a twist constraint (fast).
    Simplified,
    /// One friction cone per contact point.
    Coulomb,
}

/// Wheel motors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WheelConfig {
    /// Torque limit per wheel, N m.
    pub max_torque_nm: f64,
    /// Velocity-loop gain, N m per rad/s.
    pub velocity_gain: f64,
    /// Position feedback on the integrated rate command, 1/s.
    pub position_gain: f64,
    /// Tread friction coefficient.
    pub friction: f64,
    /// Collision shape of the wheels against the ground.
    pub contact_shape: WheelShape,
    /// Radius of the rounded tread edges of `round_cylinder` wheels, m: more than 0; a radius of
    /// half the wheel's width or more is a fully round tyre profile (just under half is used).
    pub tread_edge_radius_m: f64,
}

/// Collision shape of a wheel.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WheelShape {
    /// The wheel's cylinder with rounded tread edges (`tread_edge_radius_m`).
    RoundCylinder,
    /// A ball of the wheel's radius: a round tyre; contacts cost a fraction of the cylinder's.
    Ball,
}

/// Rocker suspension spring.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuspensionConfig {
    /// Spring, N m/rad.
    pub stiffness: f64,
    /// Damper, N m s/rad.
    pub damping: f64,
}

/// Position servos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServoConfig {
    /// Position error at which a servo gives its full effort, rad (x 0.1 m for prismatic joints):
    /// the stiffness is the joint's effort limit divided by it.
    pub full_effort_error: f64,
    /// Damping as a multiple of the stiffness, s.
    pub damping_time_s: f64,
    /// Done tolerance, rad.
    pub position_tolerance: f64,
    /// Stall time before a fault, s.
    pub stall_time_s: f64,
    /// Recovery time, s.
    pub recover_time_s: f64,
    /// Rate at which the joints' positions and rates are measured, Hz.
    pub state_rate_hz: f64,
    /// Measurement to availability of joint states, s.
    pub state_latency_s: f64,
    /// Deadman: a group whose commanding software has sent nothing (a move, a stop, a recover or a
    /// keep-alive) for this long holds its joints where they are and ends its move, s (0: none).
    #[serde(default = "default_servo_deadman")]
    pub deadman_s: f64,
    /// Where servoed joints stand when the twin starts, by joint name (rad, or m for the
    /// fingers); the others start at 0 (the shipped default: the arm stretched out ahead). The
    /// canister missions start the arm folded in its stowed pose.
    #[serde(default)]
    pub start: std::collections::BTreeMap<String, f64>,
}

fn default_servo_deadman() -> f64 {
    0.5
}

fn default_locomotor_deadman() -> f64 {
    0.25
}

/// Gripper.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GripperConfig {
    /// Latch distance, m.
    pub latch_distance_m: f64,
    /// The fingers hold the handle only when their closing axis is within this of the handle's
    /// narrow axis, degrees.
    pub grasp_tolerance_deg: f64,
    /// A canister released within this horizontal distance of the stowage slot rests in the
    /// cradle, m (kinematic fidelity; in full dynamics the cradle's walls hold it).
    pub cradle_capture_m: f64,
}

/// Locomotor limits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocomotorLimits {
    /// m/s.
    pub max_speed_m_s: f64,
    /// rad/s.
    pub max_yaw_rate_rad_s: f64,
    /// Degrees.
    pub max_slope_deg: f64,
    /// m.
    pub max_step_m: f64,
    /// Deadman: wheels commanded to turn with no fresh command for this long stop, s (0: none).
    #[serde(default = "default_locomotor_deadman")]
    pub deadman_s: f64,
}

/// IMU noise model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuConfig {
    /// Output rate, Hz.
    pub rate_hz: f64,
    /// Accelerometer white noise density.
    pub accel_noise_density: f64,
    /// Gyro white noise density.
    pub gyro_noise_density: f64,
    /// Accelerometer bias random walk.
    pub accel_bias_walk: f64,
    /// Gyro bias random walk.
    pub gyro_bias_walk: f64,
    /// Accelerometer turn-on bias sigma.
    pub accel_bias_initial: f64,
    /// Gyro turn-on bias sigma.
    pub gyro_bias_initial: f64,
    /// Capture to availability, s.
    pub latency_s: f64,
    /// Extra delay, uniform in [0, jitter_s], per sample, s.
    pub jitter_s: f64,
}

/// Encoder model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderConfig {
    /// Counts per wheel revolution.
    pub counts_per_rev: u32,
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Capture to availability, s.
    pub latency_s: f64,
    /// Extra delay, uniform in [0, jitter_s], per reading, s.
    pub jitter_s: f64,
}

/// Errors of the models and calibrations the robot's software is given, relative to the simulated
/// truth: standard deviations of the errors drawn for each run from its seed (0: the software is
/// told the truth). Seed 004: the software believes a model, the hardware does what it does.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationConfig {
    /// Believed wheel radius, as a fraction of the true one.
    pub wheel_radius_fraction: f64,
    /// Believed track (wheel spacing across), as a fraction of the true one.
    pub track_fraction: f64,
    /// Believed zero of each arm joint, degrees.
    pub arm_joint_zero_deg: f64,
    /// Believed length of each arm link (the offset between consecutive joints), m.
    pub arm_link_length_m: f64,
    /// Believed focal lengths of each camera, as a fraction of the true ones.
    pub camera_focal_fraction: f64,
    /// Believed principal point of each camera, pixels.
    pub camera_principal_point_px: f64,
    /// Believed radial distortion k1 of each camera.
    pub camera_k1: f64,
    /// Believed rotation between the two cameras of a pair, degrees (about each axis).
    pub stereo_rotation_deg: f64,
    /// Believed translation between the two cameras of a pair, m (along each axis).
    pub stereo_translation_m: f64,
    /// Believed rotation of a camera (pair) on its mount link, degrees (about each axis).
    pub camera_mount_rotation_deg: f64,
    /// Believed position of a camera (pair) on its mount link, m (along each axis).
    pub camera_mount_translation_m: f64,
}

/// How each real camera differs from its nominal design (`sensors.toml` and the URDF): standard
/// deviations of the differences drawn for each run from its seed. The twin renders with the
/// drawn cameras; the calibration the software gets is close to them, not to the design.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraBuildConfig {
    /// Focal lengths, as a fraction of the nominal.
    pub focal_fraction: f64,
    /// Principal point, pixels.
    pub principal_point_px: f64,
    /// Radial distortion k1 (added to the nominal).
    pub k1: f64,
    /// Rotation of the optical frame relative to the URDF's, degrees (about each axis).
    pub rotation_deg: f64,
}

impl TwinConfig {
    /// The shipped configuration, `assets/rover/twin.toml`.
    pub fn default_path() -> std::path::PathBuf {
        crate::assets_dir().join("rover/twin.toml")
    }

    /// Loads and validates a configuration file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = read_file(path)?;
        Self::from_str(&text, &path.display().to_string())
    }

    /// Parses and validates TOML text.
    pub fn from_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        /// Shortest physics step, s.
        const MIN_DT_S: f64 = 1e-5;
        /// Most solver iterations per step.
        const MAX_ITERATIONS: usize = 1000;
        /// Fastest sensor rate, Hz.
        const MAX_RATE_HZ: f64 = 10_000.0;
        let src = Source::new(origin, text);
        let c: TwinConfig = src.parse()?;
        let pos = |k: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(src.error_at_key(k, format!("must be positive, got {v}")))
            }
        };
        pos("physics.dt_s", c.physics.dt_s)?;
        if !(MIN_DT_S..=0.05).contains(&c.physics.dt_s) {
            return Err(src.error_at_key(
                "physics.dt_s",
                format!("must be in [{MIN_DT_S}, 0.05] s (stable contacts), got {}", c.physics.dt_s),
            ));
        }
        for (k, n) in [
            ("physics.solver_iterations", c.physics.solver_iterations),
            ("physics.pgs_iterations", c.physics.pgs_iterations),
        ] {
            if !(1..=MAX_ITERATIONS).contains(&n) {
                return Err(src.error_at_key(k, format!("must be 1..={MAX_ITERATIONS}, got {n}")));
            }
        }
        pos("physics.gravity_m_s2", c.physics.gravity_m_s2)?;
        pos("physics.terrain_cell_m", c.physics.terrain_cell_m)?;
        // A sensor faster than the physics step would report the same state many times, and a
        // period that rounds to 0 ns would never advance.
        for (k, hz) in [
            ("servos.state_rate_hz", c.servos.state_rate_hz),
            ("imu.rate_hz", c.imu.rate_hz),
            ("encoders.rate_hz", c.encoders.rate_hz),
        ] {
            if hz.is_finite() && hz > MAX_RATE_HZ {
                let got = framework::config::num(hz);
                return Err(src.error_at_key(k, format!("must be at most {MAX_RATE_HZ} Hz, got {got}")));
            }
        }
        pos("wheels.max_torque_nm", c.wheels.max_torque_nm)?;
        pos("wheels.velocity_gain", c.wheels.velocity_gain)?;
        pos("wheels.tread_edge_radius_m", c.wheels.tread_edge_radius_m)?;
        pos("servos.full_effort_error", c.servos.full_effort_error)?;
        pos("servos.damping_time_s", c.servos.damping_time_s)?;
        pos("servos.position_tolerance", c.servos.position_tolerance)?;
        pos("servos.state_rate_hz", c.servos.state_rate_hz)?;
        pos("imu.rate_hz", c.imu.rate_hz)?;
        pos("gripper.latch_distance_m", c.gripper.latch_distance_m)?;
        pos("gripper.cradle_capture_m", c.gripper.cradle_capture_m)?;
        if !(c.gripper.grasp_tolerance_deg > 0.0 && c.gripper.grasp_tolerance_deg <= 90.0) {
            return Err(src.error_at_key("gripper.grasp_tolerance_deg", "must be in (0, 90] degrees"));
        }
        pos("locomotor.max_speed_m_s", c.locomotor.max_speed_m_s)?;
        pos("locomotor.max_slope_deg", c.locomotor.max_slope_deg)?;
        if c.encoders.counts_per_rev == 0 {
            return Err(src.error_at_key("encoders.counts_per_rev", "must be at least 1"));
        }
        pos("encoders.rate_hz", c.encoders.rate_hz)?;
        let non_negative = |k: &str, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(src.error_at_key(k, format!("must be >= 0, got {v}")))
            }
        };
        for (k, v) in [
            ("imu.latency_s", c.imu.latency_s),
            ("imu.jitter_s", c.imu.jitter_s),
            ("encoders.latency_s", c.encoders.latency_s),
            ("encoders.jitter_s", c.encoders.jitter_s),
            ("servos.state_latency_s", c.servos.state_latency_s),
            ("servos.deadman_s", c.servos.deadman_s),
            ("locomotor.deadman_s", c.locomotor.deadman_s),
        ] {
            non_negative(k, v)?;
        }
        let k = &c.calibration;
        for (key, v) in [
            ("calibration.wheel_radius_fraction", k.wheel_radius_fraction),
            ("calibration.track_fraction", k.track_fraction),
            ("calibration.arm_joint_zero_deg", k.arm_joint_zero_deg),
            ("calibration.arm_link_length_m", k.arm_link_length_m),
            ("calibration.camera_focal_fraction", k.camera_focal_fraction),
            ("calibration.camera_principal_point_px", k.camera_principal_point_px),
            ("calibration.camera_k1", k.camera_k1),
            ("calibration.stereo_rotation_deg", k.stereo_rotation_deg),
            ("calibration.stereo_translation_m", k.stereo_translation_m),
            ("calibration.camera_mount_rotation_deg", k.camera_mount_rotation_deg),
            ("calibration.camera_mount_translation_m", k.camera_mount_translation_m),
            ("camera_build.focal_fraction", c.camera_build.focal_fraction),
            ("camera_build.principal_point_px", c.camera_build.principal_point_px),
            ("camera_build.k1", c.camera_build.k1),
            ("camera_build.rotation_deg", c.camera_build.rotation_deg),
        ] {
            non_negative(key, v)?;
        }
        if k.wheel_radius_fraction > 0.2 || k.track_fraction > 0.2 || c.camera_build.focal_fraction > 0.2 {
            return Err(src.error_at_key("calibration", "fractional errors above 0.2 are no calibration"));
        }
        Ok(c)
    }
}
